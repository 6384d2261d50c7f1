"""CAD edges and corners: the topology arrays and the moves of feature vertices onto them.

A 3D model's edges and vertices (:class:`~nagata_snap.cad.stage.CadTopology`) are gathered as
arrays over the geometry's faces, so that the feature vertices of all
facets are found at once (:class:`~nagata_snap.mesh.arrays.Ragged` lists:
the edge curves and CAD vertices of each face, the faces of each feature).
Placement (:mod:`nagata_snap.cad.place`) then moves them:

* :func:`nearest_features`: an edge slot to the nearest edge curve of its
  face, a corner slot to the nearest CAD vertex of its face, if that feature
  lies on every face of the vertex (:func:`feature_holds_faces`: one of its
  own faces, or :func:`on_faces`, where touching solids each have their copy
  of a shared edge);
* :func:`onto_feature`: from there onto the intersection of the faces of
  that edge (vertex): the edge curves of a file are only within their
  tolerance of the faces;
* :func:`shared_entity_vertices`: geometries without topology put a vertex
  shared by facets of several entities onto all of them.

Both of the last use :func:`intersect`, Gauss-Newton steps onto the
intersection of several entities: project ``x`` onto every entity, move it
to the nearest point of the intersection of the tangent planes there
(``n_i . (y - p_i) = 0``, minimum-norm least squares), repeat.
"""

from __future__ import annotations

import numpy as np

from nagata_snap.cad.params import unit_normals, unwrap
from nagata_snap.cad.stage import StageGeometry
from nagata_snap.mesh.arrays import best_per_group, ramp

__all__ = ["nearest_features", "feature_holds_faces", "alongside", "on_faces", "onto_feature", "intersect",
           "shared_entity_vertices"]

#: an edge vertex (on facets of several entities) counts as on all of them within
#: this fraction of the model size
EDGE_RTOL = 1e-14
#: Gauss-Newton steps that bring an edge vertex onto all its entities
EDGE_SWEEPS = 8
#: a feature's point lies on a face that is not one of its own within the file's tolerance
#: of the feature, at least this fraction of the model size
ON_FACE_RTOL = 1e-9
#: a foot on an edge curve is at its end within this fraction of the curve's parameter range
ALONG_RTOL = 1e-9
#: singular values of the stacked face normals below this fraction of the largest are
#: dropped in the intersection steps (faces meeting at less than ~1 degree)
TANGENT_RCOND = 2e-2


def nearest_features(geo: StageGeometry, ent: np.ndarray, X: np.ndarray, hs: np.ndarray,
                     cls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of edge and corner slots: nearest edge curve / CAD vertex of their face.

    Args:
        geo: the geometry (with topology).
        ent: ``(k,)`` face of each slot.
        X: ``(k, 3)`` positions.
        hs: ``(k,)`` longest edge of the slot's facet (search radius).
        cls: ``(k,)`` 1 for an edge slot, 2 or more for a corner slot.

    Returns:
        ``(points (k, 3), feature (k,))``: ``c + 1`` for edge curve ``c``,
        ``-(v + 1)`` for CAD vertex ``v``, 0 where none was found.
    """
    top = geo.topology
    assert top is not None
    k = len(ent)
    out = np.zeros((k, 3))
    fid = np.zeros(k, dtype=np.int64)
    # corners: the nearest CAD vertex of the face within the facet's tolerance
    corner = np.flatnonzero(cls >= 2)
    if corner.size:
        cnt, vert = top.face_vertices.take(ent[corner])
        slot = np.repeat(corner, cnt)
        dv = np.linalg.norm(top.points[vert] - X[slot], axis=1)
        best = best_per_group(np.repeat(np.arange(corner.size), cnt), dv, corner.size,
                              dv <= geo.tol_factor * hs[slot])
        hit = best >= 0
        out[corner[hit]] = top.points[vert[best[hit]]]
        fid[corner[hit]] = -(vert[best[hit]] + 1)
    # edges (and corners without a vertex nearby): the nearest edge curve of the face
    todo = np.flatnonzero(fid == 0)
    if todo.size and top.searcher is not None:
        cnt, crv = top.face_curves.take(ent[todo])
        slot = np.repeat(todo, cnt)
        t = hs[slot][:, None]
        inbox = np.all((X[slot] >= top.lo[crv] - t) & (X[slot] <= top.hi[crv] + t), axis=1)
        slot, crv = slot[inbox], crv[inbox]
        grp = np.searchsorted(todo, slot)
        res = top.searcher.search_on(X[slot], crv)
        best = best_per_group(grp, res[2], todo.size, res[2] <= hs[slot])
        hit = best >= 0
        out[todo[hit]] = res[1][best[hit]]
        fid[todo[hit]] = crv[best[hit]] + 1
    return out, fid


def feature_holds_faces(geo: StageGeometry, fid: np.ndarray, gid: np.ndarray, ent: np.ndarray,
                        idx: np.ndarray, points: np.ndarray, par: np.ndarray) -> np.ndarray:
    """``(k,)`` bool: the feature of slot ``idx (k,)`` lies on every face its vertex is on.

    Per slot: ``fid (ns,)`` feature (``c + 1`` edge curve ``c``, ``-(v + 1)``
    CAD vertex ``v``), ``gid (ns,)`` vertex, ``ent (ns,)`` face, ``par (ns, d)``
    parameters on it; ``points (k, 3)`` the feature's point found for slot
    ``idx``.  A vertex on facets of faces ``A`` and ``B`` belongs on a CAD
    edge (vertex) of both; the nearest edge curve of ``A`` need not be one:
    where two solids of an assembly touch, the mesher's fragments meet along
    a line that is no edge of either file face.  A face of the vertex counts as held if it is one of the feature's
    faces, or if the feature's point lies on it (:func:`on_faces`): two
    touching solids each have their own copy of a shared rim (a pin's end
    flush in a plate's hole: the pin's end disk and the plate's face are
    coplanar and meet only along the rim, an edge of each).
    """
    top = geo.topology
    assert top is not None
    ne = geo.num_entities
    # (vertex, face), sorted by vertex, and a slot of each
    pairs, pslot = np.unique(gid.astype(np.int64) * ne + ent, return_index=True)
    pv, pf = pairs // ne, pairs % ne
    lo = np.searchsorted(pv, gid[idx], side="left")
    cnt = np.searchsorted(pv, gid[idx], side="right") - lo
    pi = np.repeat(lo, cnt) + ramp(cnt)
    faces = pf[pi]  # the faces of each slot's vertex
    rows = np.repeat(top.feature_rows(fid[idx]), cnt)
    ff = top.feature_faces
    fkeys = np.sort(np.repeat(np.arange(len(ff.counts)), ff.counts) * ne + ff.flat)
    key = rows * ne + faces
    at = np.minimum(np.searchsorted(fkeys, key), len(fkeys) - 1)
    miss = fkeys[at] != key if len(fkeys) else np.ones(len(key), dtype=bool)
    slot = np.repeat(np.arange(len(idx)), cnt)
    m = np.flatnonzero(miss)
    if m.size:  # not one of the feature's faces: does the feature's point lie on it?
        points = np.asarray(points, dtype=float)
        m = m[alongside(geo, fid[idx][slot[m]], points[slot[m]])]
        miss[m] = ~on_faces(geo, points[slot[m]], faces[m], top.feature_tolerance[rows[m]], par[pslot[pi[m]]])
    return np.bincount(slot, weights=miss, minlength=len(idx)) == 0


def alongside(geo: StageGeometry, fid: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``(k,)`` bool: the point ``q (k, 3)`` of feature ``fid (k,)`` found as a vertex's nearest
    is a foot on its edge curve, not its end: within the curve's range (or on a closed
    curve), or the feature is a CAD vertex (found within the corners' small radius).

    The nearest point of an edge curve clamped at the curve's end says only that the
    vertex is beyond that end: a vertex on the fragments of two touching solids, on a
    line that is no edge of either face, can have a CAD corner of one face as nearest
    point of its edges and that corner on the other face, and belongs elsewhere.
    """
    top = geo.topology
    assert top is not None and top.searcher is not None
    out = fid < 0
    e = np.flatnonzero(fid > 0)
    if e.size:
        crv = fid[e] - 1
        u = top.searcher.search_on(q[e], crv)[0][:, 0]
        lo, hi = top.curve_range[crv].T
        eps = ALONG_RTOL * (hi - lo)
        out[e] = top.curve_closed[crv] | ((u > lo + eps) & (u < hi - eps))
    return out


def on_faces(geo: StageGeometry, X: np.ndarray, faces: np.ndarray, tol: np.ndarray,
             seeds: np.ndarray | None = None) -> np.ndarray:
    """``(n,)`` bool: point ``X[i] (n, 3)`` lies on (the closure of) face ``faces[i]``.

    Within ``t = max(tol[i], ON_FACE_RTOL * size)`` (``tol (n,)``, length units: the
    file's tolerance of the feature the point is on) of the face's surface (Newton from
    ``seeds (n, d)`` where given and finite, else from the face's search samples), and either
    on the trimmed face (inside its loops' polygons or bands) or within ``t`` of one of its
    edge curves.  The edge curves, not only the loops: the loops are the p-curves, which
    OpenCASCADE computes where a STEP file has none, and which can stray from the
    edges' 3D curves by more than the edges' recorded tolerance (the I-DEAS assembly
    of ``docs/pages/results/corpus.md``).
    """
    t = np.maximum(tol, ON_FACE_RTOL * geo.size)
    n = len(faces)
    par, dist = np.zeros((n, geo.param_dim)), np.full(n, np.inf)
    known = np.flatnonzero(np.all(np.isfinite(seeds), axis=1)) if seeds is not None else np.zeros(0, np.int64)
    if known.size:
        assert seeds is not None
        pp, _, dd, _, conv = geo.searcher.refine(known, faces[known], seeds[known], X, geo.max_iter)
        par[known], dist[known] = pp, np.where(conv, dd, np.inf)
    rest = np.flatnonzero(~(dist <= t))
    if rest.size:  # unseeded, or Newton went astray: from the face's samples
        par[rest], _, dist[rest] = geo.searcher.search_on(X[rest], faces[rest])[:3]
    ok = dist <= t
    if geo.trims is None or geo.topology is None:
        return ok
    near = np.flatnonzero(ok)
    if near.size == 0:
        return ok
    out = near[~geo.trims.inside(faces[near], par[near], band=False)]  # outside the polygons:
    rim = out[geo.trims.loop_distance(faces[out], par[out]) > 0.0] if out.size else out  # and their bands
    if rim.size:  # on the surface, beyond the loops: on an edge curve of the face?
        q, fid = nearest_features(geo, faces[rim], X[rim], t[rim], np.ones(rim.size, dtype=np.int64))
        ok[rim] = (fid != 0) & (np.linalg.norm(q - X[rim], axis=1) <= t[rim])
    return ok


def onto_feature(geo: StageGeometry, reps: np.ndarray, ent: np.ndarray, proj: np.ndarray, par: np.ndarray,
                 fid: np.ndarray, hs: np.ndarray) -> float:
    """Move feature vertices onto the intersection of their edge's (vertex's) faces.

    ``reps (g,)``: one representative slot per vertex; per slot ``ent (ns,)``
    face, ``proj (ns, 3)`` position, ``par (ns, d)`` parameters, ``fid (ns,)``
    feature (``c + 1`` for edge curve ``c``, ``-(v + 1)`` for CAD vertex
    ``v``, 0: none), ``hs (ns,)`` step cap.  Updates ``proj`` of the
    representative slots in place; returns the largest remaining distance to
    one of the faces.
    """
    top = geo.topology
    assert top is not None
    reps = reps[fid[reps] != 0]
    rows = top.feature_rows(fid[reps])
    multi = top.feature_faces.counts[rows] > 1  # on the intersection of several faces
    reps, rows = reps[multi], rows[multi]
    if reps.size == 0:
        return 0.0
    cnt, pe = top.feature_faces.take(rows)
    gpos = np.repeat(np.arange(reps.size), cnt)
    # seeds: the representative's own parameters on its own face
    seeds = np.full((len(pe), geo.param_dim), np.nan)
    own = pe == ent[reps][gpos]
    seeds[own] = par[reps][gpos[own]]
    x, _, g = intersect(geo, proj[reps], gpos, pe, seeds, hs[reps], proj[reps])
    proj[reps] = x
    return float(g.max(initial=0.0))


def truncated_lstsq(N: np.ndarray, res: np.ndarray, rcond: float = TANGENT_RCOND) -> np.ndarray:
    """Minimum-norm ``y (G, 3)`` with ``N y ~ res`` per group, small singular values dropped.

    ``N (G, m, 3)`` stacked unit normals (zero rows ignored), ``res (G, m)``.
    """
    U, sv, Vt = np.linalg.svd(N, full_matrices=False)  # (G, m, k), (G, k), (G, k, 3)
    keep = sv > rcond * sv[:, :1]
    inv = np.where(keep, 1.0 / np.where(keep, sv, 1.0), 0.0)
    coef = np.einsum("gmk,gm->gk", U, res) * inv
    return np.einsum("gk,gkj->gj", coef, Vt)


def _on_entities(geo: StageGeometry, x: np.ndarray, gpos: np.ndarray, pe: np.ndarray, seeds: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projections of points ``x (G, 3)`` onto their entities (pairs ``(gpos, pe)``, ``(m,)``).

    Newton from ``seeds (m, d)`` (NaN: from the entity's search samples).
    Returns ``(params (m, d), points (m, 3), score (G,))``, ``score`` the
    largest distance of each point to one of its entities.
    """
    m = len(gpos)
    pp, px, pd = np.zeros((m, geo.param_dim)), np.zeros((m, 3)), np.zeros(m)
    known = np.all(np.isfinite(seeds), axis=1)
    if known.any():
        k = np.flatnonzero(known)
        pp[k], px[k], pd[k], _, _ = geo.searcher.refine(gpos[k], pe[k], seeds[k], x, geo.max_iter)
    if not known.all():
        k = np.flatnonzero(~known)
        pp[k], px[k], pd[k] = geo.searcher.search_on(x[gpos[k]], pe[k])
    score = np.zeros(len(x))
    np.maximum.at(score, gpos, pd)
    return pp, px, score


def intersect(geo: StageGeometry, x0: np.ndarray, gpos: np.ndarray, pe: np.ndarray, seeds: np.ndarray,
              hg: np.ndarray, anchor: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton onto the intersection of several entities per point.

    Points ``x0 (G, 3)``; pairs ``(gpos (m,), pe (m,))`` (point, entity),
    sorted by point, with Newton seeds ``(m, d)`` (NaN: from the entity's
    search samples).  Each step projects ``x`` onto every entity of the
    point and moves it to the nearest point of the intersection of the
    tangent planes there (``n_i . (y - p_i) = 0``, minimum-norm least
    squares, step capped to ``hg (G,)``).  Directions in which the normals
    are (nearly) dependent -- faces meeting tangentially, as a fillet or a
    chamfer cone meets its plane -- get no step (:func:`truncated_lstsq`):
    along a tangent contact the intersection is ill-posed and the start (the
    edge curve's point) is kept there.  The best point over
    :data:`EDGE_SWEEPS` steps is kept if it is nearer all the entities than
    the start and within ``hg`` of ``anchor (G, 3)``.

    Returns ``(x (G, 3), params (m, d), gap (G,))``: ``gap`` the largest
    distance of the final point to one of its entities.
    """
    G, m = len(x0), len(gpos)
    start = np.searchsorted(gpos, np.arange(G))
    rank = np.arange(m) - start[gpos]
    etol = EDGE_RTOL * geo.size
    x = x0.copy()
    pp, px, score = _on_entities(geo, x, gpos, pe, seeds)
    pp0, score0 = pp.copy(), score.copy()
    best_x, best_pp, best = x.copy(), pp.copy(), score.copy()
    todo = best > etol
    mr = int(rank.max()) + 1
    for _sweep in range(EDGE_SWEEPS):
        if not todo.any():
            break
        nrm = unit_normals(geo.entities, pe, pp)  # (m, 3), zero where degenerate (pole)
        N = np.zeros((G, mr, 3))
        N[gpos, rank] = nrm
        res = np.zeros((G, mr))
        res[gpos, rank] = np.einsum("ij,ij->i", nrm, x[gpos] - px)
        step = truncated_lstsq(N, res)
        sl_ = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, hg / np.maximum(sl_, 1e-300))[:, None]
        x = np.where(todo[:, None], x - step, x)
        pp, px, score = _on_entities(geo, x, gpos, pe, pp)
        better = todo & (score < best)
        best_x[better], best[better] = x[better], score[better]
        best_pp[better[gpos]] = pp[better[gpos]]
        todo &= best > etol
    keep = (best < score0) & (np.linalg.norm(best_x - anchor, axis=1) <= hg)
    x_fin = np.where(keep[:, None], best_x, x0)
    pp_fin = np.where(keep[gpos][:, None], best_pp, pp0)
    return x_fin, pp_fin, np.where(keep, best, score0)


def shared_entity_vertices(
    geo: StageGeometry, gid: np.ndarray, ent: np.ndarray, proj: np.ndarray, par: np.ndarray,
    X: np.ndarray, hs: np.ndarray,
) -> tuple[int, float]:
    """Geometries without topology: put vertices shared by facets of several entities onto all of them.

    A mesh vertex on facets of entities ``A`` and ``B`` lies on the CAD edge
    the two faces share: :func:`intersect` moves it there (step capped to
    the local edge length, within it of the straight vertex ``X``).  Every
    slot then takes the parameters of that point on its own entity.  Only
    the facets on this process are seen: geometries with topology use the
    CAD edges instead.

    Per slot: ``gid (ns,)`` vertex, ``ent (ns,)`` entity, ``X (ns, 3)``
    straight position, ``hs (ns,)`` longest edge of its facet.  Updates
    ``proj (ns, 3)`` (one position per vertex already) and ``par (ns, d)``
    in place; returns ``(number of edge vertices, largest distance of an
    edge vertex to one of its entities)``.
    """
    ne = geo.num_entities
    if len(gid) == 0:
        return 0, 0.0
    key = gid * ne + ent
    ukey, first_slot, inv = np.unique(key, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    ug = ukey // ne
    cnt = np.bincount(ug)
    pidx = np.flatnonzero(cnt[ug] > 1)  # (group, entity) pairs of edge vertices
    if pidx.size == 0:
        return 0, 0.0
    m = pidx.size
    pe = ukey[pidx] % ne
    groups, gpos = np.unique(ug[pidx], return_inverse=True)
    gpos = gpos.reshape(-1)
    G = groups.size
    start = np.searchsorted(gpos, np.arange(G))  # pairs are sorted by group
    gslot = first_slot[pidx][start]  # one slot per edge vertex
    x = proj[gslot].copy()
    hg = np.zeros(G)
    sl = np.flatnonzero(np.isin(gid, groups))
    np.maximum.at(hg, np.searchsorted(groups, gid[sl]), hs[sl])
    x_fin, pp_fin, gap = intersect(geo, x, gpos, pe, par[first_slot[pidx]], hg, X[gslot])
    pos = np.full(len(ukey), -1, dtype=np.int64)
    pos[pidx] = np.arange(m)
    ps = pos[inv]
    s = np.flatnonzero(ps >= 0)
    proj[s] = x_fin[gpos[ps[s]]]
    par[s] = unwrap(geo._period, ent[s], pp_fin[ps[s]], par[s])
    return int(G), float(gap.max())
