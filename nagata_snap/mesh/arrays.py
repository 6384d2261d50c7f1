"""Small vectorised array idioms used across the pipeline, each written once.

>>> import numpy as np
>>> best_per_group(np.array([0, 0, 1, 2]), np.array([3.0, 1.0, 2.0, 5.0]), 4)
array([ 1,  2,  3, -1])
>>> dot(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([[1.0, 1.0], [1.0, 0.0]]))
array([4., 2.])
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["best_per_group", "dot", "dot_last"]


def best_per_group(
    group: np.ndarray,
    score: np.ndarray | tuple[np.ndarray, ...],
    n: int,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Row of the lowest ``score`` in each group ``0..n-1``.

    Args:
        group: ``(m,)`` group index of each row, in ``0..n-1``.
        score: ``(m,)`` score of each row, or a tuple of ``(m,)`` keys, the
            most significant first (e.g. ``(~accepted, distance)``).
        n: number of groups.
        mask: ``(m,)`` bool, only these rows compete (default: all).

    Returns:
        ``(n,)`` int64 row index per group, ``-1`` for a group without rows.
        Ties go to the first row.  For the highest score pass ``-score``.
    """
    out = np.full(n, -1, dtype=np.int64)
    rows = np.arange(len(group)) if mask is None else np.flatnonzero(mask)
    if rows.size:
        keys = score if isinstance(score, tuple) else (score,)
        order = rows[np.lexsort((*(np.asarray(k)[rows] for k in reversed(keys)), group[rows]))]
        g, first = np.unique(group[order], return_index=True)
        out[g] = order[first]
    return out


def dot(a: Sequence[np.ndarray] | np.ndarray, b: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Dot product over the first axis: ``a``, ``b`` are ``d`` component arrays (a list or ``(d, ...)``)."""
    out = a[0] * b[0]
    for ai, bi in zip(a[1:], b[1:], strict=True):
        out = out + ai * bi
    return out


def dot_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis of ``(..., d)`` arrays."""
    return np.einsum("...i,...i->...", a, b)
