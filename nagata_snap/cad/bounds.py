"""Boxes that bound pieces of the geometry, for the global closest-point search.

The seeded search (:class:`~nagata_snap.cad.projection.GlobalSearcher`) starts
Newton from the nearest grid samples of a point; it finds the closest point
only where one of those samples lies in that point's basin of the distance.
Where the samples of one sheet are much denser than those of another (a
narrow band of a face beside a wide one at a concave corner, the apex of a
spindle torus where a whole row of samples is about equally near), all the
nearest samples can lie in the basin of a farther minimum.  A bound decides
instead: a box that holds a piece of surface and whose distance from the point
exceeds a distance already reached cannot hold the point's closest point;
every piece whose box is nearer gets a Newton run of its own.

* :class:`BoxClasses`: boxes grouped by size (half-diagonals within a factor
  2), a KD-tree of the centres per group; :meth:`BoxClasses.near` gives every
  ``(point, box)`` pair whose box is within a given distance of the point, for
  all points at once (one ball query per group).
* :func:`cell_boxes`: the boxes of the cells of a surface's search grid (the
  pieces between adjacent grid samples), from the surface evaluated at the
  grid refined once in each direction: a cell's box holds its 3 x 3 points,
  widened by the largest sagitta among them (the distance of each mid point
  from the midpoint of the two points either side of it, and of the centre
  from the mean of the corners).  Between the 3 x 3 points the surface bulges
  about a quarter of that (a quadratic's sagitta over half the step), so the
  widening covers surfaces that are smooth at the grid's scale; it is an
  estimate, not a proof (a patch that oscillates between the samples is not
  bounded by it).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from nagata_snap.mesh.arrays import Groups

__all__ = ["BoxClasses", "cell_boxes", "box_gap"]


def box_gap(lo: np.ndarray, hi: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``(n,)`` distance of points ``X (n, 3)`` from boxes ``[lo, hi]`` (each ``(n, 3)``), 0 inside."""
    return np.linalg.norm(np.maximum(np.maximum(lo - X, X - hi), 0.0), axis=1)


class BoxClasses:
    """Boxes grouped by size for ball queries of many points at once.

    Args:
        lo, hi: ``(m, 3)`` the boxes' corners.
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        self.lo, self.hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        half = 0.5 * np.linalg.norm(self.hi - self.lo, axis=1)
        cls = np.floor(np.log2(np.maximum(half, 1e-300))).astype(np.int64)
        centre = 0.5 * (self.hi + self.lo)
        g = Groups(cls)
        #: per class: its boxes, their largest half-diagonal, the KD-tree of their centres
        self.classes = [(g.order[sl], float(half[g.order[sl]].max()), cKDTree(centre[g.order[sl]]))
                        for _, sl in g]

    def near(self, X: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(point (p,), box (p,))``: every pair of a point of ``X (n, 3)`` and a box whose
        distance from it is at most ``r (n,)`` (length units)."""
        n = len(X)
        pts, boxes = [], []
        for members, half, tree in self.classes:  # loop over size classes (a few dozen at most)
            hits = tree.query_ball_point(X, r + half)
            cnt = np.fromiter(map(len, hits), dtype=np.int64, count=n)
            if not cnt.any():
                continue
            p = np.repeat(np.arange(n), cnt)
            b = members[np.concatenate([np.asarray(h, dtype=np.int64) for h in hits if h])]
            keep = box_gap(self.lo[b], self.hi[b], X[p]) <= r[p]
            pts.append(p[keep])
            boxes.append(b[keep])
        if not pts:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.concatenate(pts), np.concatenate(boxes)


def cell_boxes(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes of the cells of a surface's grid.

    Args:
        G: ``(2 nu - 1, 2 nv - 1, 3)`` the surface at a grid of ``nu x nv`` parameters
            refined once (every other row and column the grid's own points, between them
            the midpoints of the parameters).

    Returns:
        ``(lo, hi)``, each ``((nu - 1) (nv - 1), 3)``, cell ``(i, j)`` (between grid
        parameters ``i, i + 1`` and ``j, j + 1``) at row ``i (nv - 1) + j``: the box of its
        3 x 3 points widened by their largest sagitta (see the module docstring).
    """
    nu, nv = (G.shape[0] + 1) // 2, (G.shape[1] + 1) // 2
    blocks = np.lib.stride_tricks.sliding_window_view(G, (3, 3), axis=(0, 1))[::2, ::2]  # (nu-1, nv-1, 3, 3, 3)
    B = np.moveaxis(blocks, 2, -1)  # (nu-1, nv-1, 3, 3) + (3,) as (..., a, b, xyz)
    B = B.reshape(nu - 1, nv - 1, 3, 3, 3)
    lo = B.min(axis=(2, 3)).reshape(-1, 3)
    hi = B.max(axis=(2, 3)).reshape(-1, 3)
    sag = np.zeros((nu - 1, nv - 1))
    for mid, ends in (((1, 0), ((0, 0), (2, 0))), ((1, 2), ((0, 2), (2, 2))),  # mids of the u sides
                      ((0, 1), ((0, 0), (0, 2))), ((2, 1), ((2, 0), (2, 2))),  # of the v sides
                      ((1, 1), ((0, 1), (2, 1))), ((1, 1), ((1, 0), (1, 2))),  # the centre, both ways
                      ((1, 1), ((0, 0), (2, 2))), ((1, 1), ((0, 2), (2, 0)))):  # and along the diagonals
        a, b = ends
        d = B[:, :, mid[0], mid[1]] - 0.5 * (B[:, :, a[0], a[1]] + B[:, :, b[0], b[1]])
        np.maximum(sag, np.linalg.norm(d, axis=2), out=sag)
    pad = sag.reshape(-1, 1)
    return lo - pad, hi + pad
