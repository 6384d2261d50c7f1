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
   :data:`EDGE_GAP` of the model size).  A file whose edges are only within a
   looser tolerance of their faces (a CATIA V4 IGES file: up to 5e-3 of the
   size) has faces whose boundary no 3D edge curve traces: there the boundary
   candidate is the closest point of the curves the face's p-curves trace on
   its surface, ``S(c(t))`` (:class:`CurveOnSurface`), the face being the
   surface within its p-curves (as OpenCASCADE's classifier has it);
3. a foot point within a loop's band is kept only if it lies inside the
   true trimming curve through ``E``
   (:meth:`~nagata_snap.cad.trimming.TrimLoops.outside_by`).

Every candidate then competes by distance, for all points at once.
"""

from __future__ import annotations

import numpy as np

from nagata_snap.cad.nurbs import NurbsCurve
from nagata_snap.cad.projection import GlobalSearcher, normalize_params
from nagata_snap.cad.stage import StageGeometry
from nagata_snap.mesh.arrays import Ragged, best_per_group, norms

__all__ = ["with_boundary", "CurveOnSurface"]

#: an edge curve's point counts as on its face's boundary if within this fraction of the
#: model size of the face's surface (and of the curve its p-curve traces there)
EDGE_GAP = 1e-9
#: samples per p-curve at which a face's boundary is compared with its edges' 3D curves
GAP_SAMPLES = 9


class CurveOnSurface:
    """The curve ``C(t) = S(c(t))`` a p-curve ``c`` traces on its face's surface ``S``: a curve
    entity of :mod:`~nagata_snap.cad.projection` (``param_dim`` 1, over the p-curve's range).

    ``C' = S_u c_u' + S_v c_v'`` and ``C'' = S_uu c_u'^2 + 2 S_uv c_u' c_v' + S_vv c_v'^2 +
    S_u c_u'' + S_v c_v''`` (the chain rule), ``c`` mapped by the face's ``uv_map``
    (affine: its derivatives by its linear part) and wrapped into the surface's domain.

    Args:
        desc: the p-curve's description (``read_shape``'s ``"pcurve"``: line, circle or
            B-spline, with its ``range``).
        surface: the face's surface.
        uv_map: the face's ``(3, 2)`` map of the file's parameters to the surface's, or None.
    """

    param_dim = 1
    closed = (False,)

    def __init__(self, desc: dict, surface, uv_map: np.ndarray | None):
        self.surface = surface
        self.kind = desc["type"]
        t0, t1 = (float(t) for t in desc["range"])
        self.bounds = np.array([[min(t0, t1), max(t0, t1)]])
        self.M = np.r_[np.eye(2), np.zeros((1, 2))] if uv_map is None else np.asarray(uv_map, dtype=float)
        lo, hi = self.bounds[0]
        if self.kind == "line":
            self.a, self.b = (np.asarray(desc[k], dtype=float)[:2] for k in ("origin", "direction"))
            knots = np.array([lo, hi])
        elif self.kind == "circle":
            self.a, self.x, self.y = (np.asarray(desc[k], dtype=float)[:2] for k in ("center", "x", "y"))
            self.r = float(desc["radius"])
            knots = np.linspace(lo, hi, max(2, int(np.ceil((hi - lo) / (np.pi / 8))) + 1))
        else:
            poles = np.asarray(desc["poles"], dtype=float)
            w = desc.get("weights")
            self.nurbs = NurbsCurve(int(desc["degree"]), np.asarray(desc["knots"], dtype=float), poles,
                                    np.ones(len(poles)) if w is None else np.asarray(w, dtype=float))
            k = self.nurbs.distinct_knots
            knots = np.unique(np.r_[lo, k[(k > lo) & (k < hi)], hi])
        self.distinct_knots = knots
        X = self._eval_soa(np.linspace(lo, hi, 65)[None, :], 0)[0].T
        self.bbox = (X.min(axis=0), X.max(axis=0))
        self.bbox_size = float(np.linalg.norm(self.bbox[1] - self.bbox[0]))

    def _pcurve(self, t: np.ndarray, nderiv: int) -> np.ndarray:
        """``(nderiv + 1, 2, k)``: the p-curve and its derivatives at ``t (k,)`` (file parameters)."""
        out = np.zeros((nderiv + 1, 2, len(t)))
        if self.kind == "line":
            out[0] = self.a[:, None] + self.b[:, None] * t
            if nderiv:
                out[1] = self.b[:, None]
        elif self.kind == "circle":
            c, s = np.cos(t), np.sin(t)
            out[0] = self.a[:, None] + self.r * (self.x[:, None] * c + self.y[:, None] * s)
            for d in range(1, nderiv + 1):  # d/dt (cos, sin) = (-sin, cos)
                c, s = -s, c
                out[d] = self.r * (self.x[:, None] * c + self.y[:, None] * s)
        else:
            out[:] = self.nurbs._eval_soa(np.clip(t, *self.nurbs.domain)[None, :], nderiv)[:, :2]
        return out

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        """``params (1, k)`` -> ``(nderiv + 1, 3, k)``: ``C, C', C''`` (see the class docstring)."""
        c = np.einsum("dak,ab->dbk", self._pcurve(params[0], nderiv), self.M[:2])
        c[0] += self.M[2][:, None]
        q = normalize_params(self.surface, c[0].T).T
        E = self.surface._eval_soa(np.ascontiguousarray(q), nderiv)
        out = np.empty((nderiv + 1, 3, params.shape[1]))
        out[0] = E[0]
        if nderiv >= 1:
            du, dv = c[1]
            out[1] = E[1] * du + E[2] * dv
        if nderiv >= 2:
            ddu, ddv = c[2]
            out[2] = E[3] * du * du + 2.0 * E[4] * du * dv + E[5] * dv * dv + E[1] * ddu + E[2] * ddv
        return out

    def params_on_surface(self, t: np.ndarray) -> np.ndarray:
        """``(k, 2)`` the surface's parameters of ``C(t)``, ``t (k,)``."""
        c = self._pcurve(np.asarray(t, dtype=float), 0)[0].T @ self.M[:2] + self.M[2]
        return normalize_params(self.surface, c)


class _FacePCurves:
    """The curves on their surfaces (:class:`CurveOnSurface`) of the p-curves of a topology's
    faces, built face by face where first needed (:meth:`ensure`), and which faces are
    *loose*: a point of such a curve (at :data:`GAP_SAMPLES` parameters of each) farther than
    :data:`EDGE_GAP` of the size from its edge's 3D curve (measured, not the file's
    tolerance: a file may claim less than its curves keep).  ``face_curves``: per face its
    curves' indices (:class:`Ragged`), ``loose (n_faces,)`` bool, ``searcher`` over the curves
    (None without any).  The topology's ``pcurves``."""

    def __init__(self, top, size: float):
        self._top, self._tol = top, EDGE_GAP * size
        self.curves: list[CurveOnSurface] = []
        self._per_face: list[list[int]] = [[] for _ in top.faces]
        self.built = np.zeros(len(top.faces), dtype=bool)
        self.loose = np.zeros(len(top.faces), dtype=bool)
        self.face_curves = Ragged(self._per_face)
        self.searcher: GlobalSearcher | None = None

    def ensure(self, faces: np.ndarray) -> None:
        """Build the curves of ``faces (k,)`` not built yet, and their ``loose`` flags."""
        top = self._top
        todo = np.unique(faces[~self.built[faces]]).tolist()
        if not todo:
            return
        for i in todo:  # loop over the new faces and their p-curves (set-up, once per face)
            f = top.faces[i]
            for lp in f.loops:
                for e, d in zip(lp.uses, lp.pcurves or (), strict=False):
                    curve = CurveOnSurface(d, f.surface, f.uv_map)
                    self._per_face[i].append(len(self.curves))
                    self.curves.append(curve)
                    c = top.curve_of_edge[e]
                    if c >= 0 and top.searcher is not None and not self.loose[i]:
                        lo, hi = curve.bounds[0]
                        P = curve._eval_soa(np.linspace(lo, hi, GAP_SAMPLES)[None, :], 0)[0].T
                        self.loose[i] = top.searcher.search_on(P, np.full(len(P), c))[2].max() > self._tol
            self.built[i] = True
        self.face_curves = Ragged(self._per_face)
        self.searcher = GlobalSearcher(self.curves) if self.curves else None


def _face_pcurves(geo: StageGeometry) -> _FacePCurves:
    """The topology's :class:`_FacePCurves`, built on first need."""
    top = geo.topology
    assert top is not None
    if top.pcurves is None:
        top.pcurves = _FacePCurves(top, geo.size)
    return top.pcurves


def _on_pcurves(geo: StageGeometry, X: np.ndarray, pt: np.ndarray, face: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points of ``X[pt] (p, 3)`` on the curves the p-curves of faces ``face (p,)``
    trace on their surfaces: ``(params (p, 2) on the surface, distance (p,), found (p,))``
    (``found`` False for a face without p-curves)."""
    fp = _face_pcurves(geo)
    fp.ensure(face)
    q, dist = np.zeros((len(pt), 2)), np.full(len(pt), np.inf)
    if fp.searcher is None:
        return q, dist, np.zeros(len(pt), dtype=bool)
    cnt, crv = fp.face_curves.take(face)
    pair = np.repeat(np.arange(len(pt)), cnt)
    if pair.size == 0:
        return q, dist, np.zeros(len(pt), dtype=bool)
    t, _, d = fp.searcher.search_on(X[pt[pair]], crv)[:3]
    best = best_per_group(pair, d, len(pt))
    hit = best >= 0
    for c in np.unique(crv[best[hit]]):  # loop over the curves of the results (their maps)
        rows = np.flatnonzero(hit)[crv[best[hit]] == c]
        q[rows] = fp.curves[c].params_on_surface(t[best[rows]].reshape(-1))
    dist[hit] = d[best[hit]]
    return q, dist, hit


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
    # an edge curve farther from its face than EDGE_GAP of the size, or from the curve its p-curve
    # traces on it (a file's loose tolerance): the face's boundary is the curve its p-curves trace
    fp = _face_pcurves(geo)
    fp.ensure(bf)
    loose = (gap > EDGE_GAP * geo.size) | fp.loose[bf]
    if loose.any():
        rows = np.flatnonzero(loose)
        qL, dL, okL = _on_pcurves(geo, X, bp[rows], bf[rows])
        rows = rows[okL]
        qE[rows], dE[rows], loose[rows] = qL[okL], dL[okL], False
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
    # a loose edge of a face without p-curves gives no boundary point: its surface point is not
    # the edge's, nor its side the loop's; nothing farther than such an edge point counts for
    # its point (``unsure``)
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
