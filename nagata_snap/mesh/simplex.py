"""Batched tiny dense linear algebra (vectorised over the first axis)."""

from __future__ import annotations

import numpy as np

__all__ = ["inverse_small"]


def inverse_small(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses and determinants of ``(n, k, k)`` matrices, ``k <= 3``, by the adjugate.

    Much faster than batched ``np.linalg.inv`` / ``solve`` for such tiny
    matrices. Singular matrices give inf/nan entries (no exception); callers
    reject those rows.

    Returns:
        ``(inv (n, k, k), det (n,))``.
    """
    k = M.shape[1]
    if k == 1:
        det = M[:, 0, 0].copy()
        adj = np.ones_like(M)
    elif k == 2:
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        det = a * d - b * c
        adj = np.stack([np.stack([d, -b], axis=1), np.stack([-c, a], axis=1)], axis=1)
    elif k == 3:
        m0, m1, m2 = M[:, 0], M[:, 1], M[:, 2]
        c12 = np.cross(m1, m2)
        det = np.einsum("ni,ni->n", m0, c12)
        adj = np.stack([c12, np.cross(m2, m0), np.cross(m0, m1)], axis=2)
    else:
        raise ValueError(f"inverse_small handles k <= 3, got k = {k}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return adj / det[:, None, None], det
