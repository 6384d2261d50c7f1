"""Place: snap facet vertices onto their facets' entities after a refinement (Kadir 2.2, 2.3.3).

The stages, each a function over all facet vertices ("slots") at once:

1. :func:`slots_of`: the records and positions, validated and flattened
   (:class:`Slots`);
2. :func:`on_root`: seeded projection of every slot onto its facet's entity
   (closed form on analytic entities), with fallbacks on that entity: the
   facet's other vertices' parameters and their mean as seeds
   (:func:`retry_facet_seeds`), then the entity's own search samples
   (:func:`retry_samples`);
3. geometries without topology only: results outside the face's trimming
   loops are rejected (:func:`reject_left_face`), and slots still without a
   projection try the entities nearby (:func:`nearby_entities`), then all
   (:func:`any_entity`);
4. :func:`unwrap_to_seeds`: parameters unwrapped across seams relative to
   the seeds;
5. :func:`merge`: one position per mesh vertex: CAD edges and corners
   (:func:`feature_slots`), the best slot of each vertex
   (:func:`representatives`), feature vertices onto the intersection of
   their faces, and the parameters of that position on every slot's own
   entity (:func:`reparametrise`).

:func:`place` runs them all and reports (:class:`~nagata_snap.geometry.PlaceReport`);
:func:`project` (the sliding boundary's projection) runs 1, 2, 4 and 5
without the jump test and the fallbacks onto other entities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from nagata_snap.cad.features import (
    feature_holds_faces,
    nearest_features,
    onto_feature,
    shared_entity_vertices,
)
from nagata_snap.cad.params import unwrap
from nagata_snap.cad.slots import MERGE_RTOL, box_pairs, facet_array, longest_edge, vertex_groups
from nagata_snap.cad.stage import StageGeometry
from nagata_snap.geometry import PlaceReport
from nagata_snap.mesh.arrays import best_per_group, unique_rows
from nagata_snap.mesh.corners import corner_vertices
from nagata_snap.mesh.records import Records

__all__ = ["Slots", "Projection", "place", "project", "slots_of", "seeded_projection", "on_root",
           "retry_facet_seeds", "retry_samples", "reject_left_face", "nearby_entities", "any_entity",
           "unwrap_to_seeds", "merge", "feature_slots", "representatives", "reparametrise"]

#: a slot is at its vertex's representative position within this fraction of the model size
SAME_RTOL = 1e-9


@dataclass
class Slots:
    """The facet vertices ("slots") of one call, ``ns = nf * nfv`` of them.

    Attributes:
        root: ``(nf,)`` entity of each facet.
        params: ``(nf, nfv, d)`` the records' parameters (the seeds).
        chan: ``(nf, nfv, c)`` the records' CAD-edge channels (``c = 0`` without topology).
        X: ``(ns, 3)`` positions (straight, or targets).
        ent: ``(ns,)`` entity of each slot (its facet's).
        seed: ``(ns, d)`` Newton seed of each slot.
        hs: ``(ns,)`` longest edge of the slot's facet.
    """

    root: np.ndarray
    params: np.ndarray
    chan: np.ndarray
    X: np.ndarray
    ent: np.ndarray
    seed: np.ndarray
    hs: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(nf, nfv)``."""
        return self.params.shape[0], self.params.shape[1]

    def records(self, par: np.ndarray) -> Records:
        """Records of the facets with the slots' parameters ``par (ns, d)`` and the channels."""
        nf, nfv = self.shape
        out = par.reshape(nf, nfv, -1)
        if self.chan.shape[2]:
            out = np.concatenate([out, self.chan], axis=2)
        return Records(self.root.copy(), out)


@dataclass
class Projection:
    """Per slot: the current projection (updated in place by the stages).

    Attributes:
        par: ``(ns, d)`` parameters on the slot's own entity.
        proj: ``(ns, 3)`` position.
        dist: ``(ns,)`` distance from the slot's ``X``.
        valid: ``(ns,)`` an acceptable projection was found.
        its: Newton iterations of the seeded projections (one per distinct
            (entity, point, seed)).
        n_fallback: slots whose seeded projection failed (or jumped).
        on_root: ``(ns,)`` the position is on the slot's own entity.
    """

    par: np.ndarray
    proj: np.ndarray
    dist: np.ndarray
    valid: np.ndarray
    its: np.ndarray
    n_fallback: int
    on_root: np.ndarray


@dataclass
class Merged:
    """Result of :func:`merge`: one position per vertex.

    Attributes:
        gid: ``(ns,)`` vertex of each slot.
        rep_of_group: ``(n_vertices,)`` representative slot of each vertex.
        n_edge: vertices put on CAD edges or corners.
        gap: largest distance of such a vertex from one of its faces.
        n_left: face slots found outside their face's trimming loops.
    """

    gid: np.ndarray
    rep_of_group: np.ndarray
    n_edge: int = 0
    gap: float = 0.0
    n_left: int = 0


def slots_of(geo: StageGeometry, records: Records, points: npt.ArrayLike, what: str) -> Slots:
    """Validated and flattened slots of ``records`` at ``points (nf, nfv, 3)`` (``what`` names them).

    Raises:
        ValueError: the records do not match the points or refer to unknown entities.
    """
    st = facet_array(points, what)
    root = np.asarray(records.root, dtype=np.int64).reshape(-1)
    params = np.asarray(records.params, dtype=float)
    nf, nfv, _ = st.shape
    d, w = geo.param_dim, geo.record_width
    if root.shape != (nf,) or params.ndim != 3 or params.shape[:2] != (nf, nfv) or \
            params.shape[2] not in (d, w):
        raise ValueError(
            f"records (root {root.shape}, params {params.shape}) do not match {what} "
            f"{st.shape} (expected root ({nf},), params ({nf}, {nfv}, {w}))"
        )
    if nf and (root.min() < 0 or root.max() >= geo.num_entities):
        raise ValueError(f"records.root refers to entities outside 0..{geo.num_entities - 1}")
    chan = params[:, :, d:] if params.shape[2] == w and w > d else np.zeros((nf, nfv, w - d))
    params = params[:, :, :d]
    return Slots(root, params, chan, st.reshape(-1, 3), np.repeat(root, nfv), params.reshape(-1, d),
                 np.repeat(longest_edge(st), nfv))


def seeded_projection(geo: StageGeometry, ent: np.ndarray, X: np.ndarray, seeds: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Seeded projection of ``X (n, 3)`` onto entities ``ent (n,)`` from ``seeds (n, d)``.

    One Newton run per distinct (entity, point, seed).  Returns ``(params
    (n, d), points (n, 3), dist (n,), iterations (runs,), converged (n,))``.
    """
    if len(ent) == 0:
        z = np.zeros(0)
        return np.zeros((0, geo.param_dim)), np.zeros((0, 3)), z, z.astype(np.int64), z.astype(bool)
    uniq, inv, _ = unique_rows(np.column_stack([ent.astype(float), X, seeds]))
    par, proj, dist, its, conv = geo.searcher.refine(uniq, ent[uniq], seeds[uniq], X, geo.max_iter)
    return par[inv], proj[inv], dist[inv], its, conv[inv]


def on_root(geo: StageGeometry, s: Slots, jump: bool = True) -> Projection:
    """Projection of every slot onto its facet's entity, with fallbacks on that entity.

    Seeded Newton (closed form on analytic entities); where it fails (or,
    with ``jump``, lands farther than the facet's longest edge):
    :func:`retry_facet_seeds`, then :func:`retry_samples`.
    """
    par, proj, dist, its, conv = seeded_projection(geo, s.ent, s.X, s.seed)
    ok = conv & np.all(np.isfinite(proj), axis=1)
    if jump:
        ok &= dist <= s.hs
    dist = np.where(np.isfinite(dist), dist, np.finfo(float).max)
    p = Projection(par, proj, dist, ok, its, int(np.sum(~ok)), np.ones(len(ok), dtype=bool))
    retry_facet_seeds(geo, s, p, jump)
    retry_samples(geo, s, p, jump)
    return p


def retry_facet_seeds(geo: StageGeometry, s: Slots, p: Projection, jump: bool) -> None:
    """Invalid slots: Newton from the facet's other vertices' parameters and their mean (in place)."""
    bad = np.flatnonzero(~p.valid)
    if not bad.size:
        return
    nfv, d = s.params.shape[1:]
    f = bad // nfv
    cand = np.concatenate([s.params[f], s.params[f].mean(axis=1, keepdims=True)], axis=1)
    m = nfv + 1
    pt = np.repeat(bad, m)
    cp, cx, cd, _, cc = geo.searcher.refine(pt, s.ent[pt], cand.reshape(-1, d), s.X, geo.max_iter)
    good = cc & (cd <= s.hs[pt] if jump else np.isfinite(cd))
    rows = best_per_group(np.repeat(np.arange(bad.size), m), cd, bad.size, good)
    hit = rows >= 0
    i, r = bad[hit], rows[hit]
    p.par[i], p.proj[i], p.dist[i], p.valid[i] = cp[r], cx[r], cd[r], True


def retry_samples(geo: StageGeometry, s: Slots, p: Projection, jump: bool) -> None:
    """Invalid slots: Newton from the entity's own search samples (in place; a closer
    result is kept even if not acceptable)."""
    bad = np.flatnonzero(~p.valid)
    if not bad.size:
        return
    res = geo.searcher.search_on(s.X[bad], s.ent[bad])
    good = (res[2] <= s.hs[bad]) if jump else np.isfinite(res[2])
    closer = good | (res[2] < p.dist[bad])
    i = bad[closer]
    p.par[i], p.proj[i], p.dist[i] = res[0][closer], res[1][closer], res[2][closer]
    p.valid[bad[good]] = True


def reject_left_face(geo: StageGeometry, s: Slots, p: Projection) -> int:
    """Geometries without topology: a result beyond its face's trimming loops becomes invalid
    (it falls back to other entities); returns how many."""
    if geo._accept is None:
        return 0
    left = p.valid & ~geo._accept(s.ent, p.par)
    p.valid &= ~left
    return int(left.sum())


def nearby_entities(geo: StageGeometry, s: Slots, p: Projection) -> None:
    """Geometries without topology: invalid slots try their own entity and the entities whose
    bounding box is within an edge length, from their search samples (in place).

    An acceptable result on the root wins, then one on another entity (which
    clears ``on_root``; the slot keeps its best parameters on its own entity).
    """
    bad = np.flatnonzero(~p.valid)
    if not bad.size:
        return
    ne = geo.num_entities
    pb, be = box_pairs(s.X[bad], s.hs[bad], geo.searcher.bbox_lo, geo.searcher.bbox_hi)
    u = np.unique(np.concatenate([pb, np.arange(bad.size)]) * ne + np.concatenate([be, s.ent[bad]]))
    bi, be = u // ne, u % ne
    res = geo.searcher.search_on(s.X[bad][bi], be, accept=geo._accept)
    qp, qx, qd = res[:3]
    qroot = be == s.ent[bad][bi]
    qok = qd <= s.hs[bad][bi]
    if geo._accept is not None:  # only results on the faces (neighbours sharing the edge)
        qok &= res[3]
    r_root = best_per_group(bi, qd, bad.size, qroot)  # best attempt on the root
    r_ok = best_per_group(bi, qd, bad.size, qok & qroot)  # acceptable on the root
    r_any = best_per_group(bi, qd, bad.size, qok)  # acceptable anywhere
    use_root = r_ok >= 0
    use_other = ~use_root & (r_any >= 0)
    i, r = bad[use_root], r_ok[use_root]
    p.par[i], p.proj[i], p.dist[i], p.valid[i] = qp[r], qx[r], qd[r], True
    i, r = bad[use_other], r_any[use_other]
    p.proj[i], p.dist[i], p.valid[i], p.on_root[i] = qx[r], qd[r], True, False
    upd = ~use_root & (r_root >= 0)
    i, r = bad[upd], r_root[upd]
    closer = ~p.valid[i] & (qd[r] < p.dist[i])
    p.par[i] = np.where((~p.valid[i] | ~p.on_root[i])[:, None], qp[r], p.par[i])
    p.proj[i[closer]], p.dist[i[closer]] = qx[r[closer]], qd[r[closer]]


def any_entity(geo: StageGeometry, s: Slots, p: Projection) -> None:
    """Geometries without topology: invalid slots take the global search over all entities (in place)."""
    bad = np.flatnonzero(~p.valid)
    if not bad.size:
        return
    acc = geo._accept
    res = geo.searcher.search(s.X[bad], accept=acc)
    ge, gp, gd = res[:3]
    gin = res[3] if acc is not None else np.ones(bad.size, dtype=bool)
    gx = geo.evaluate(ge, gp[:, None]).reshape(-1, 3)
    groot = ge == s.ent[bad]
    gok = gin & (gd <= s.hs[bad])
    take = gok | (gd < p.dist[bad])
    i = bad[take]
    p.proj[i], p.dist[i], p.on_root[i] = gx[take], gd[take], groot[take]
    p.valid[i] = gok[take]
    sr = take & groot
    p.par[bad[sr]] = gp[sr]


def unwrap_to_seeds(geo: StageGeometry, s: Slots, par: np.ndarray) -> np.ndarray:
    """``par (ns, d)`` unwrapped relative to the seeds (contiguous within the facet); facets
    with non-finite seeds relative to their first vertex."""
    nf, nfv = s.shape
    d = par.shape[1]
    par = unwrap(geo._period, s.ent, par, s.seed)
    nanf = ~np.all(np.isfinite(s.seed).reshape(nf, -1), axis=1)
    if nanf.any():
        pf = par.reshape(nf, nfv, d)
        sub = pf[nanf]
        ref = np.repeat(sub[:, :1], nfv, axis=1).reshape(-1, d)
        pf[nanf] = unwrap(geo._period, np.repeat(s.root[nanf], nfv), sub.reshape(-1, d), ref).reshape(-1, nfv, d)
        par = pf.reshape(-1, d)
    return par


def feature_slots(geo: StageGeometry, s: Slots, p: Projection, gid: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """Edge and corner slots (with topology) and their positions on the features.

    A slot is on an edge (corner) if its record's CAD-edge channels put it on
    one (two) flagged coarse edges, or if it is a face slot of a trimmed face
    whose projection left the face's loops (the parametric midpoints of a
    facet's vertices can leave a face where its boundary is concave, and the
    nearest point of the face is then on its boundary).  Such slots move to
    the nearest edge curve (CAD vertex) of their face
    (:func:`~nagata_snap.cad.features.nearest_features`; ``p.proj`` in
    place).  Then the corners (decided from all slots of the vertex by
    :func:`~nagata_snap.mesh.corners.corner_vertices`; ``X`` may be a target
    off the vertex) and the edge slots whose record is at a CAD vertex (a
    seam's end on a closed edge) go to the CAD vertex where the record is.

    A feature counts only if it lies on every face the slot's vertex is on
    (:func:`~nagata_snap.cad.features.feature_holds_faces`); the slots whose
    nearest feature does not are ``loose``: their vertex goes onto the
    intersection of its own faces (as without topology).

    Returns:
        ``(cls (ns,), fid (ns,), n_left, loose (ns,))``: 0 face, 1 edge, 2
        corner; the feature (``c + 1`` edge curve ``c``, ``-(v + 1)`` CAD
        vertex ``v``, 0 none); the face slots found outside their loops; the
        loose slots.
    """
    ns = len(s.ent)
    fid = np.zeros(ns, dtype=np.int64)
    chan = s.chan.reshape(ns, -1)
    if geo.topology is None or not chan.shape[1]:
        return np.zeros(ns, dtype=np.int64), fid, 0, np.zeros(ns, dtype=bool)
    cls = np.count_nonzero(chan == 1.0, axis=1)  # 0 face, 1 edge, >= 2 corner
    n_left = 0
    if geo.trims is not None:
        fs = np.flatnonzero((cls == 0) & geo.trims.trimmed[s.ent])
        off = fs[~geo.trims.inside(s.ent[fs], p.par[fs])]
        cls[off] = 1
        n_left = int(off.size)
    feat = np.flatnonzero(cls > 0)
    loose = np.zeros(ns, dtype=bool)
    if feat.size:
        fx, ff = nearest_features(geo, s.ent[feat], s.X[feat], s.hs[feat], cls[feat])
        ok = ff != 0
        fid[feat] = ff
        found = feat[ok]
        holds = feature_holds_faces(geo, fid, gid, s.ent, found, fx[ok], p.par)
        loose[found[~holds]] = True  # on faces that share no CAD edge there: intersect them
        fid[found[~holds]] = 0
        ok[ok] = holds
        p.proj[feat[ok]] = fx[ok]
        p.dist[feat[ok]] = np.linalg.norm(fx[ok] - s.X[feat[ok]], axis=1)  # the nearest feature wins
        cls[feat[~ok]] = 0
    is_corner = corner_vertices(gid, s.ent, int(gid.max()) + 1, geo.param_dim + 1,
                                edge=np.where(fid > 0, fid - 1, -1))
    corner = np.flatnonzero((is_corner[gid] | (cls >= 1)) & (fid >= 0) & np.all(np.isfinite(s.seed), axis=1))
    if corner.size:
        at = geo.evaluate(s.ent[corner], s.seed[corner][:, None]).reshape(-1, 3)
        fx, ff = nearest_features(geo, s.ent[corner], at, s.hs[corner], np.full(corner.size, 2))
        hit = np.flatnonzero(ff < 0)
        fid_c = np.zeros(ns, dtype=np.int64)
        fid_c[corner[hit]] = ff[hit]
        hit = hit[feature_holds_faces(geo, fid_c, gid, s.ent, corner[hit], fx[hit], p.par)]
        c = corner[hit]
        p.proj[c], fid[c], cls[c] = fx[hit], ff[hit], 2
        p.dist[c] = np.linalg.norm(fx[hit] - s.X[c], axis=1)
        loose[c] = False
    return cls, fid, n_left, loose


def representatives(gid: np.ndarray, cls: np.ndarray, p: Projection) -> np.ndarray:
    """``(n_vertices,)`` the best slot of each vertex ``gid (ns,)``: an edge or corner slot
    (``cls``) first, then valid, on its own entity, nearest (an edge or corner slot: its
    feature's point nearest the vertex, :func:`feature_slots`)."""
    return best_per_group(gid, (-np.minimum(cls, 2), ~p.valid, ~p.on_root, p.dist), int(gid.max()) + 1)


def reparametrise(geo: StageGeometry, s: Slots, par: np.ndarray, proj: np.ndarray, idx: np.ndarray
                  ) -> np.ndarray:
    """Parameters of the slots ``idx (k,)`` at their new position ``proj`` on their own entity.

    Seeded by their ``par (ns, d)``; where the seed leads Newton astray (e.g.
    across a seam) the face's own search samples.  Updates ``par`` in place
    (unwrapped to the seeds); returns ``(k,)`` the distances of ``proj`` from
    the entities.
    """
    pr, _, dd, _, _ = seeded_projection(geo, s.ent[idx], proj[idx], par[idx])
    far = np.flatnonzero(~(dd <= SAME_RTOL * geo.size))
    if far.size:
        res = geo.searcher.search_on(proj[idx[far]], s.ent[idx[far]])
        better = res[2] < dd[far]
        pr[far[better]], dd[far[better]] = res[0][better], res[2][better]
    par[idx] = unwrap(geo._period, s.ent[idx], pr, s.seed[idx])
    return dd


def merge(geo: StageGeometry, s: Slots, p: Projection) -> Merged:
    """One position per mesh vertex; CAD edges and corners; parameters of every slot.

    Every slot of a vertex gets the position of its representative
    (:func:`representatives`).  With topology, feature vertices
    (:func:`feature_slots`) then move onto the intersection of the faces of
    their edge (vertex) (:func:`~nagata_snap.cad.features.onto_feature`);
    without, vertices on facets of several entities onto all of them
    (:func:`~nagata_snap.cad.features.shared_entity_vertices`).  Every slot
    takes the parameters of the final position on its own entity.  Updates
    ``p.proj``, ``p.par`` and ``p.dist`` (from ``s.X``).
    """
    gid = vertex_groups(s.X, MERGE_RTOL * geo.size)
    cls, fid, n_left, loose = feature_slots(geo, s, p, gid)
    m = Merged(gid, representatives(gid, cls, p), n_left=n_left)
    rep = m.rep_of_group[gid]
    feat_slot = cls[rep] > 0
    if feat_slot.any():  # onto the intersection of the feature's faces
        m.gap = onto_feature(geo, m.rep_of_group, s.ent, p.proj, p.par, fid, s.hs)
        m.n_edge = int(np.unique(gid[feat_slot]).size)
    moved = np.linalg.norm(p.proj - p.proj[rep], axis=1) > SAME_RTOL * geo.size
    redo = feat_slot | moved
    if geo.topology is None:
        redo &= s.ent == s.ent[rep]
    p.proj = p.proj[rep]
    if redo.any():  # the slot's parameters of the representative position, on its own entity
        dd = reparametrise(geo, s, p.par, p.proj, np.flatnonzero(redo))
        if feat_slot.any():
            m.gap = max(m.gap, float(dd[feat_slot[redo]].max(initial=0.0)))
    if geo.topology is None:
        m.n_edge, m.gap = shared_entity_vertices(geo, gid, s.ent, p.proj, p.par, s.X, s.hs)
    elif loose.any():  # feature vertices whose faces share no CAD edge nearby
        sel = np.flatnonzero(np.isin(gid, gid[loose]))
        proj, par = p.proj[sel], p.par[sel]
        n, gap = shared_entity_vertices(geo, gid[sel], s.ent[sel], proj, par, s.X[sel], s.hs[sel])
        p.proj[sel], p.par[sel] = proj, par
        m.n_edge, m.gap = m.n_edge + n, max(m.gap, gap)
    p.dist = np.linalg.norm(p.proj - s.X, axis=1)
    return m


def place(geo: StageGeometry, records: Records, straight: npt.ArrayLike
          ) -> tuple[np.ndarray, Records, PlaceReport]:
    """Snapped positions, records and report: see :meth:`nagata_snap.cad.geometry.CadGeometry.place`."""
    s = slots_of(geo, records, straight, "straight")
    nf, nfv = s.shape
    if nf * nfv == 0:
        return np.zeros((nf, nfv, 3)), Records(s.root.copy(), np.asarray(records.params).copy()), PlaceReport()
    p = on_root(geo, s)
    n_left = 0
    if geo.topology is None:
        n_left = reject_left_face(geo, s, p)
        nearby_entities(geo, s, p)
        any_entity(geo, s, p)
    n_unresolved = int(np.sum(~p.valid))
    p.par = unwrap_to_seeds(geo, s, p.par)
    m = merge(geo, s, p)
    if geo.topology is not None:
        n_left = m.n_left
    vd = p.dist[m.rep_of_group]  # one value per distinct vertex
    report = PlaceReport(
        max_residual=float(vd.max()) if vd.size else 0.0,
        mean_residual=float(vd.mean()) if vd.size else 0.0,
        iterations_histogram=np.bincount(p.its, minlength=1),
        n_points=nf * nfv,
        n_vertices=int(vd.size),
        n_fallback=p.n_fallback,
        n_off_root=int(np.sum(~p.on_root)),
        n_unresolved=n_unresolved,
        n_left_face=n_left,
        n_edge_vertices=m.n_edge,
        max_edge_gap=float(m.gap),
    )
    return p.proj.reshape(nf, nfv, 3), s.records(p.par), report


def project(geo: StageGeometry, records: Records, points: npt.ArrayLike) -> tuple[np.ndarray, Records]:
    """Closest points on each facet's own entity: see :meth:`nagata_snap.cad.geometry.CadGeometry.project`."""
    s = slots_of(geo, records, points, "points")
    nf, nfv = s.shape
    if nf * nfv == 0:
        return np.zeros((nf, nfv, 3)), Records(s.root.copy(), np.asarray(records.params).copy())
    p = on_root(geo, s, jump=False)
    p.par = unwrap_to_seeds(geo, s, p.par)
    merge(geo, s, p)
    return p.proj.reshape(nf, nfv, 3), s.records(p.par)
