"""Closest points on trimmed faces whose nearest point lies on the face's boundary.

The closest point of ``x`` on a trimmed face is either a stationary point of
the distance to its surface inside the trimming loops (what Newton finds,
:class:`~nagata_snap.cad.projection.GlobalSearcher`) or a point of the
face's boundary.  Where a surface's foot point is outside its face, or
inside but within the band of a loop (the polygon's test cannot tell there,
:mod:`~nagata_snap.cad.trimming`), :func:`with_boundary` adds the face's
boundary candidate:

1. the closest point ``E`` of ``x`` on the face's CAD edges (their 3D curves,
   :class:`~nagata_snap.cad.stage.CadTopology`: closed form or Newton, as
   OpenCASCADE measures a point's distance to a face's edges);
2. ``E`` on the face: its projection onto the face's surface, whose
   parameters are on the loop where the edge lies on the surface (within
   :data:`EDGE_GAP` of the model size; a file whose edges are only within a
   looser tolerance of their faces gets no boundary candidate there);
3. a foot point within a loop's band is kept only if it lies inside the
   true trimming curve through ``E``
   (:meth:`~nagata_snap.cad.trimming.TrimLoops.outside_by`).

Every candidate then competes by distance, for all points at once.
"""

from __future__ import annotations

import numpy as np

from nagata_snap.cad.stage import StageGeometry
from nagata_snap.mesh.arrays import best_per_group, norms

__all__ = ["with_boundary"]

#: an edge curve's point counts as on its face's boundary if within this fraction of the
#: model size of the face's surface
EDGE_GAP = 1e-9


def _pairs(pt: np.ndarray, ent: np.ndarray, mask: np.ndarray, n_ent: int) -> tuple[np.ndarray, np.ndarray]:
    """``(pt (p,), ent (p,))``: the distinct (point, entity) pairs of the rows in ``mask``."""
    key = np.unique(pt[mask] * n_ent + ent[mask])
    return key // n_ent, key % n_ent


def _distinct(pt: np.ndarray, ent: np.ndarray, params: np.ndarray, dist: np.ndarray, tol: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rows ``(pt, ent, params, dist)`` without repeats: one of the rows of a point and
    entity whose distances agree to ``tol`` (length units; the seeds of one minimum)."""
    key = np.round(dist / tol) if tol > 0 else dist
    order = np.lexsort((key, ent, pt))
    first = np.ones(len(order), dtype=bool)
    first[1:] = (np.diff(pt[order]) != 0) | (np.diff(ent[order]) != 0) | (np.diff(key[order]) != 0)
    keep = order[first]
    return pt[keep], ent[keep], params[keep], dist[keep]


def _sure(trims, pt: np.ndarray, ent: np.ndarray, params: np.ndarray, dist: np.ndarray, ok: np.ndarray,
          n: int, ne: int) -> np.ndarray:
    """``(m,)`` bool: the rows on their face beyond the band of its loops (where the polygon's
    test is exact), tested for the rows that compete only (the nearest on its face of each
    point and face, tying with the point's nearest): the others count as sure."""
    best_ok = np.full(n, np.inf)
    np.minimum.at(best_ok, pt[ok], dist[ok])
    _, pair = np.unique(pt * ne + ent, return_inverse=True)
    lead = best_per_group(pair.reshape(-1), dist, int(pair.max()) + 1, ok)
    lead = lead[lead >= 0]
    lead = lead[dist[lead] <= best_ok[pt[lead]] * (1.0 + 1e-6)]
    sure = ok.copy()
    sure[lead] = trims.loop_distance(ent[lead], params[lead], enough=0.0) > 0.0
    return sure


def _on_edges(geo: StageGeometry, X: np.ndarray, pt: np.ndarray, face: np.ndarray, bound: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of ``X[pt] (p, 3)`` on the edge curves of faces ``face (p,)``: ``(points
    (p, 3), distance (p,))`` (``inf`` where no curve of the face is within ``bound (p,)``, by
    its bounding box)."""
    top = geo.topology
    assert top is not None and top.searcher is not None
    out, dist = np.zeros((len(pt), 3)), np.full(len(pt), np.inf)
    cnt, crv = top.face_curves.take(face)
    pair = np.repeat(np.arange(len(pt)), cnt)
    Y = X[pt[pair]]
    gap = norms(np.maximum(np.maximum(top.lo[crv] - Y, Y - top.hi[crv]), 0.0))
    keep = gap <= bound[pair]
    pair, crv, Y = pair[keep], crv[keep], Y[keep]
    if pair.size == 0:
        return out, dist
    _, C, d = top.searcher.search_on(Y, crv)[:3]
    best = best_per_group(pair, d, len(pt))
    hit = best >= 0
    out[hit], dist[hit] = C[best[hit]], d[best[hit]]
    return out, dist


def with_boundary(geo: StageGeometry, X: np.ndarray, pt: np.ndarray, ent: np.ndarray, params: np.ndarray,
                  dist: np.ndarray) -> tuple[np.ndarray, ...]:
    """The Newton results of a global search with the faces' boundary candidates.

    Args:
        geo: a 3D geometry with trimming loops and topology.
        X: ``(n, 3)`` the points.
        pt, ent, params, dist: ``(m,)``, ``(m,)``, ``(m, 2)``, ``(m,)`` the search's rows
            (:meth:`~nagata_snap.cad.projection.GlobalSearcher.search_rows`).

    Returns:
        ``(pt, ent, params, dist, ok)`` over the rows and the added boundary candidates,
        ``ok`` the rows on their face (a foot within a loop's band that the trimming curve
        through the boundary candidate puts outside is not) and not farther than a boundary
        point that could not be put on its face (its point is then not found).
    """
    trims = geo.trims
    assert trims is not None
    n, ne = len(X), geo.num_entities
    pt, ent, params, dist = _distinct(pt, ent, params, dist, 1e-12 * geo.size)
    ok = trims.inside(ent, params)
    sure = _sure(trims, pt, ent, params, dist, ok, n, ne)
    best_sure = np.full(n, np.inf)
    np.minimum.at(best_sure, pt[sure], dist[sure])
    # every (point, trimmed face) pair of the rows: where an edge of the face is nearer than the
    # point's best sure result, the face's closest point is near that edge
    bp, bf = _pairs(pt, ent, trims.trimmed[ent], ne)
    if bp.size == 0:
        return pt, ent, params, dist, ok
    bound = np.where(np.isfinite(best_sure), best_sure, geo.size)[bp] * (1.0 + 1e-9) + 1e-12 * geo.size
    E, dE = _on_edges(geo, X, bp, bf, bound)
    hit = np.isfinite(dE)
    bp, bf, E, dE = bp[hit], bf[hit], E[hit], dE[hit]
    if bp.size == 0:
        return pt, ent, params, dist, ok
    qE, _, gap = geo.searcher.search_on(E, bf)[:3]  # the edge point's parameters on the face
    # Newton on the face from the edge point: the face's minimum near its edge (the search's
    # seeds may all lie in the basin of a farther one)
    qN, _, dN, _, _ = geo.searcher.refine(bp, bf, qE, X)
    pt, ent, params, dist = (np.concatenate([pt, bp]), np.concatenate([ent, bf]), np.concatenate([params, qN]),
                             np.concatenate([dist, dN]))
    okN = trims.inside(bf, qN)
    sureN = okN.copy()
    win = np.flatnonzero(okN & (dN <= best_sure[bp] * (1.0 + 1e-6)))  # those that may compete
    sureN[win] = trims.loop_distance(bf[win], qN[win], enough=0.0) > 0.0
    ok, sure = np.concatenate([ok, okN]), np.concatenate([sure, sureN])
    # an edge curve farther from its face than EDGE_GAP of the size (a file's loose tolerance)
    # gives no boundary point: its surface point is not the edge's, nor its side the loop's;
    # nothing farther than such an edge point counts for its point (``unsure``)
    loose = gap > EDGE_GAP * geo.size
    unsure = np.full(n, np.inf)
    np.minimum.at(unsure, bp[loose], dE[loose])
    on = ~loose & trims.inside(bf, qE)
    bp, bf, qE = bp[on], bf[on], qE[on]
    if bp.size == 0:
        return pt, ent, params, dist, ok & (dist <= unsure[pt])
    # feet within a band: inside the trimming curve through their face's boundary point?
    band = np.flatnonzero(ok & ~sure)
    at = np.searchsorted(bp * ne + bf, pt[band] * ne + ent[band])
    found = at < len(bp)
    found[found] &= (bp * ne + bf)[at[found]] == (pt * ne + ent)[band[found]]
    band, at = band[found], at[found]
    beyond = trims.outside_by(ent[band], qE[at], params[band]) > 0.0
    ok[band[beyond]] = False
    S = geo.evaluate(bf, qE[:, None, :])[:, 0]
    pt, ent, params = np.concatenate([pt, bp]), np.concatenate([ent, bf]), np.concatenate([params, qE])
    dist, ok = np.concatenate([dist, norms(S - X[bp])]), np.concatenate([ok, np.ones(len(bp), dtype=bool)])
    return pt, ent, params, dist, ok & (dist <= unsure[pt])
