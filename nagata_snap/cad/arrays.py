"""Array idioms of the CAD stages: facet arrays, vertex identity, row ids, ragged lists, box queries.

Everything works on all facets (or facet vertices, "slots") at once: a
*slot* is one vertex of one facet, so a mesh vertex shared by ``k`` facets
has ``k`` slots, and :func:`vertex_groups` tells which slots are one vertex.

>>> import numpy as np
>>> row_index(np.array([[2, 1], [0, 5], [2, 1]]))
array([1, 0, 1])
>>> Ragged([[4, 5], [], [6]]).take(np.array([2, 0]))
(array([1, 2]), array([6, 4, 5]))
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from nagata_snap.mesh.simplex import edge_lengths

__all__ = ["MERGE_RTOL", "facet_array", "longest_edge", "unique_rows", "row_index", "vertex_groups", "ramp",
           "box_pairs", "Ragged"]

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
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{what} contains NaN or infinite coordinates")
    return x


def longest_edge(x: np.ndarray) -> np.ndarray:
    """Largest edge (vertex-pair distance) of each facet ``(nf, nfv, 3)`` -> ``(nf,)`` (0 for single points)."""
    if x.shape[1] < 2:
        return np.zeros(x.shape[0])
    return edge_lengths(x).max(axis=1)


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct rows of ``a (n, k)`` (float or int): ``(first (m,), inverse (n,), rows (m, k))``.

    As ``np.unique(a, axis=0, return_index=True, return_inverse=True)`` (rows
    compared by value: ``-0.0 == 0.0``; a row with NaN is its own group), but
    with one ``np.lexsort`` of the columns instead of a sort of the rows as
    opaque byte strings.
    """
    a = np.ascontiguousarray(a)
    n = a.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp), a[:0]
    order = np.lexsort(a.T[::-1])  # stable: equal rows keep their input order
    srt = a[order]
    new = np.ones(n, dtype=bool)
    new[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    inverse = np.empty(n, dtype=np.intp)
    inverse[order] = np.cumsum(new) - 1
    return order[new], inverse, srt[new]


def row_index(rows: np.ndarray) -> np.ndarray:
    """``(n,)`` id of each row of ``rows (n, k)`` (equal rows, equal ids; ids ``0..m-1``)."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    return unique_rows(rows)[1].astype(np.int64, copy=False)


def vertex_groups(points: np.ndarray, radius: float, nodes: np.ndarray | None = None) -> np.ndarray:
    """``(n,)`` vertex id of each of ``points (n, 3)``: equal ``nodes`` ids, else points closer than ``radius``."""
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


def ramp(counts: np.ndarray) -> np.ndarray:
    """``[0..c0-1, 0..c1-1, ...]`` for counts ``c`` (vectorised)."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(starts, counts)


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


class Ragged:
    """Integer lists of different lengths as one flat array with offsets (CSR).

    ``take(rows)`` gathers many rows at once without a Python loop over them.
    """

    def __init__(self, lists: Sequence[Sequence[int] | np.ndarray]):
        self.counts = np.array([len(a) for a in lists], dtype=np.int64)
        self.ptr = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        self.flat = np.concatenate([np.asarray(a, dtype=np.int64) for a in lists] + [np.zeros(0, np.int64)])

    def take(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(counts (k,), values (counts.sum(),))``: the rows ``rows (k,)``, concatenated in order."""
        cnt = self.counts[rows]
        return cnt, self.flat[np.repeat(self.ptr[rows], cnt) + ramp(cnt)]
