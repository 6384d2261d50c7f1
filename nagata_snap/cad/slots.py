"""Facet-vertex slots of the CAD stages: facet arrays, vertex identity, box queries.

Everything works on all facets (or facet vertices, "slots") at once: a
*slot* is one vertex of one facet, so a mesh vertex shared by ``k`` facets
has ``k`` slots, and :func:`vertex_groups` tells which slots are one vertex.

Generic idioms (distinct rows, ramps, ragged lists) are in
:mod:`nagata_snap.mesh.arrays`.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from nagata_snap.mesh.arrays import norms, unique_rows

__all__ = ["MERGE_RTOL", "facet_array", "longest_edge", "vertex_groups", "box_pairs"]

#: two facet vertices closer than this (relative to the model size) are one vertex
MERGE_RTOL = 1e-10


def facet_array(a: npt.ArrayLike, what: str) -> np.ndarray:
    """Validated facet coordinates ``(nf, nfv, 3)`` (2D input ``(nf, nfv, 2)`` gets ``z = 0``).

    Raises:
        ValueError: wrong shape, or NaN / infinite coordinates (``what`` names the argument).
    """
    x = np.asarray(a, dtype=float)
    if x.ndim != 3 or x.shape[2] not in (2, 3) or x.shape[1] < 1:
        raise ValueError(f"{what} must have shape (nf, nfv, 3), got {x.shape}")
    if x.shape[2] == 2:
        x = np.concatenate([x, np.zeros((*x.shape[:2], 1))], axis=2)
    if not np.isfinite(x).all():
        raise ValueError(f"{what} contains NaN or infinite coordinates")
    return x


def longest_edge(x: np.ndarray) -> np.ndarray:
    """Largest vertex-pair distance of each facet ``(nf, nfv, 3)`` -> ``(nf,)`` (0 for single points).

    Any ``nfv``: the points of a facet of a higher-degree mesh (``curved_mesh``)
    are placed as one facet too.
    """
    if x.shape[1] < 2:
        return np.zeros(x.shape[0])
    i, j = _pairs(x.shape[1])
    return norms(x.take(i, axis=1) - x.take(j, axis=1)).max(axis=1)


@lru_cache(maxsize=8)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(i, j)`` of the vertex pairs ``i < j`` of ``n`` vertices."""
    return np.triu_indices(n, 1)


def vertex_groups(points: np.ndarray, radius: float, nodes: np.ndarray | None = None) -> np.ndarray:
    """``(n,)`` vertex id ``0..m-1`` (no gaps) of each of ``points (n, 3)``.

    Slots with equal ``nodes`` ids are one vertex; without ``nodes``, points closer than ``radius``.
    """
    if nodes is not None:
        return np.unique(np.asarray(nodes).reshape(-1), return_inverse=True)[1].reshape(-1)
    n = len(points)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    _, inv, uniq = unique_rows(points)
    pairs = cKDTree(uniq).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        m = len(uniq)
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _, lab = connected_components(g, directed=False)
        return np.asarray(lab[inv])
    return inv


def box_pairs(points: np.ndarray, tol: np.ndarray, lo: np.ndarray, hi: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """``(point, box)`` pairs with the point inside the box inflated by the point's ``tol``.

    ``points (n, 3)``, ``tol (n,)``, boxes ``lo``, ``hi (m, 3)``.  A KD-tree
    of the points answers one ball query per box (its circumsphere plus the
    largest tolerance), then the boxes are tested exactly.
    """
    if len(points) == 0 or len(lo) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    tree = cKDTree(points)
    centre, radius = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo, axis=1) + tol.max()
    hits = tree.query_ball_point(centre, radius)
    box = np.repeat(np.arange(len(lo)), [len(h) for h in hits])
    pt = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits]) if len(box) else \
        np.zeros(0, dtype=np.int64)
    t = tol[pt][:, None]
    ok = np.all((points[pt] >= lo[box] - t) & (points[pt] <= hi[box] + t), axis=1)
    return pt[ok], box[ok]
