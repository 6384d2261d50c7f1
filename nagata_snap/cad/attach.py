"""Attach: the records of the coarse mesh's boundary facets on the CAD entities (Kadir 2.3.1).

Each boundary facet gets ONE entity (face in 3D, edge curve in 2D) on which
all its vertices lie (Kadir 2.3.4) and the parameters of its vertices there,
stored per facet in :class:`nagata_snap.mesh.records.Records`:

* the entity is known when the mesh came from the CAD (``faces``, or the
  mesher's classification recorded as :class:`MeshHints`): one projection
  per vertex (:func:`on_faces`), none where the mesher's parameters give
  the vertex itself (:func:`seed_is_point`);
* otherwise a global search finds it (:func:`search_faces`): every entity
  whose bounding box holds the vertex (within the tolerance) is a candidate,
  analytic faces project in closed form, NURBS faces by Newton from their
  own search samples, trimmed faces only count within their loops, and each
  facet takes the entity nearest to all its vertices.

With topology (3D models) :func:`attach` then adds the CAD-edge channels
(:func:`edge_channels`, over all MPI processes): a facet edge is on a CAD
edge if a facet sharing it lies on another face (see
:mod:`nagata_snap.cad.geometry`).

A mesh made from the CAD is attached by a fixed number of array operations
beside the projections, so that a small mesh costs little per vertex: the
hinted facets are found by a binary search of their node-set keys (sorted
once when the hints are recorded), the vertex ids given serve as they are
(only the global search numbers the vertices without gaps), the (vertex,
entity) pairs and, on one process, the facet edges are each sorted once.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from nagata_snap.cad.errors import CadError
from nagata_snap.cad.params import contiguous
from nagata_snap.cad.slots import MERGE_RTOL, box_pairs, facet_array, longest_edge, vertex_groups
from nagata_snap.cad.stage import StageGeometry
from nagata_snap.mesh.arrays import best_per_group, norms, pack_rows, ramp, row_index, unique_rows
from nagata_snap.mesh.records import Records

__all__ = ["MeshHints", "AttachGeometry", "attach", "attach_local", "search_faces", "on_faces", "edge_channels"]

@dataclass(frozen=True)
class MeshHints:
    """Where the mesh generator put the coarse boundary facets.

    Attributes:
        nodes: ``(nf, nfv)`` global node ids of each facet, sorted per facet.
        faces: ``(nf,)`` entity of each facet.
        params: ``(nf, nfv, d)`` parameters of the vertices (in the order of
            :attr:`nodes`; NaN where unknown).
        keys: ``(nf,)`` sorted int64 keys of the facets' node sets (the sorted ids
            side by side, :func:`~nagata_snap.mesh.arrays.pack_rows`, ``bits`` bits
            each), or None where the ids are too wide for 63 bits.
        at: ``(nf,)`` facet of each key.
        bits: bits of one node id in a key.
    """

    nodes: np.ndarray
    faces: np.ndarray
    params: np.ndarray
    keys: np.ndarray | None = None
    at: np.ndarray | None = None
    bits: int = 0

    @classmethod
    def from_facets(cls, facet_nodes: npt.ArrayLike, faces: npt.ArrayLike, params: npt.ArrayLike | None,
                    d: int) -> MeshHints:
        """Hints from ``facet_nodes (nf, nfv)``, ``faces (nf,)`` and ``params (nf, nfv, d)`` (or None)."""
        fn = np.asarray(facet_nodes, dtype=np.int64)
        nf = len(fn)
        faces = np.asarray(faces, dtype=np.int64).reshape(nf)
        par = np.full((nf, fn.shape[1], d), np.nan) if params is None else \
            np.asarray(params, dtype=float).reshape(nf, fn.shape[1], d)
        order = np.argsort(fn, axis=1)
        nodes = np.take_along_axis(fn, order, axis=1)
        keys = at = None
        bits = int(nodes.max()).bit_length() if nf else 0
        if nf and nodes.min() >= 0 and bits * nodes.shape[1] <= 63:
            packed = pack_rows(nodes, bits)
            at = packed.argsort(kind="stable")
            keys = packed[at]
        return cls(nodes, faces, np.take_along_axis(par, order[:, :, None], axis=1), keys, at, bits)

    def lookup(self, gid: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(faces (nf,), seeds (nf, nfv, d))`` of facets ``gid (nf, nfv)`` (global node ids),
        or None if some facet is not among the hints.

        A facet is found by its node set: its sorted ids' key in :attr:`keys` (binary
        search); where a node set is in the hints twice, the later facet counts.
        """
        nf, nfv = gid.shape
        order = gid.argsort(axis=1)
        if self.keys is None or self.at is None:
            hit = self._hits_by_rows(np.take_along_axis(gid, order, axis=1))
        else:
            srt = gid.copy()
            srt.sort(axis=1)
            if nf and (srt[:, 0].min() < 0 or int(srt[:, -1].max()).bit_length() > self.bits):
                return None  # an id no hinted facet has
            key = pack_rows(srt, self.bits)
            pos = self.keys.searchsorted(key, side="right") - 1  # -1 (wraps): below every key
            hit = self.at[pos] if len(self.keys) and (self.keys[pos] == key).all() else None
        if hit is None:
            return None
        rank = order.argsort(axis=1)  # position of each facet vertex among its sorted ids
        seeds = self.params.reshape(len(self.nodes) * nfv, -1)[hit[:, None] * nfv + rank]
        return self.faces[hit], seeds

    def _hits_by_rows(self, srt: np.ndarray) -> np.ndarray | None:
        """``(nf,)`` hinted facet of each of the sorted node-id rows ``srt (nf, nfv)`` (the later
        one of equal hinted rows), or None if one is not hinted: the rows numbered together."""
        row = row_index(np.concatenate([self.nodes, srt]))
        where = np.full(int(row.max()) + 1, -1, dtype=np.int64)
        where[row[: len(self.nodes)]] = np.arange(len(self.nodes))
        hit = where[row[len(self.nodes):]]
        return None if (hit < 0).any() else hit


class AttachGeometry(StageGeometry, Protocol):
    """What attaching reads of :class:`~nagata_snap.cad.geometry.CadGeometry` beyond
    :class:`~nagata_snap.cad.stage.StageGeometry`."""

    @property
    def _hints(self) -> MeshHints | None: ...
    @property
    def _analytic(self) -> np.ndarray: ...
    @property
    def _sizes(self) -> np.ndarray: ...


def attach(geo: AttachGeometry, facet_points: npt.ArrayLike, nodes: npt.ArrayLike | None,
           faces: npt.ArrayLike | None, seeds: npt.ArrayLike | None, comm: Any = None) -> Records:
    """Records of the coarse mesh's boundary facets (collective with topology and ``comm``).

    See :meth:`nagata_snap.cad.geometry.CadGeometry.attach`.  An error on one
    process is raised on every process (after the exchange of facet-edge keys).
    """
    err: Exception | None = None
    out = None
    try:
        if nodes is None and geo.topology is not None and comm is not None and comm.size > 1:
            # without them vertex ids are process-local, and facet edges of different
            # processes would be matched by coincidence
            raise ValueError("attach over several processes needs nodes (input-global vertex indices "
                             "of the facets, mesh.geometry.input_global_indices)")
        out = attach_local(geo, facet_points, nodes, faces, seeds)
    except Exception as e:  # raised after the collective exchange below
        err = e
    if geo.topology is None:
        if err is not None:
            raise err
        assert out is not None
        return out[0]
    keys = None if out is None else out[1]
    allkeys: np.ndarray | None
    if comm is not None and comm.size > 1:
        every = comm.allgather(keys)
        if err is not None:
            raise err
        if any(k is None for k in every):
            raise CadError("attach failed on another process")
        allkeys = np.concatenate(list(every))
    else:
        if err is not None:
            raise err
        allkeys = keys
    assert out is not None and keys is not None and allkeys is not None
    records = out[0]
    channels = edge_channels(keys, allkeys, records.params.shape[1])
    records.params = np.concatenate([records.params, channels], axis=2)
    return records


def _check_kind(geo: AttachGeometry, nfv: int) -> None:
    """Facets of ``nfv`` vertices need entities of dimension ``nfv - 1``."""
    d = geo.param_dim
    if nfv - 1 != d:
        have = "curves" if d == 1 else "surfaces"
        need = "curves (2D mesh, segment facets)" if nfv == 2 else "surfaces (3D mesh, triangle facets)"
        raise CadError(
            f"facets with {nfv} vertices need {need}; this CadGeometry has {have} "
            "(CadGeometry.from_file(path, dim=...) picks the kind)"
        )


#: facet edge ``m`` of a triangle: its vertices ``_EDGE_A[m]``, ``_EDGE_B[m]`` (the two other than ``m``)
_EDGE_A, _EDGE_B = np.array([1, 2, 0]), np.array([2, 0, 1])


def facet_edge_keys(ids: np.ndarray, root: np.ndarray) -> np.ndarray:
    """``(3 nf, 3)`` ``(node a, node b, face)`` of the edges of triangles ``ids (nf, 3)`` on faces ``root (nf,)``.

    Facet edge ``m`` is the one opposite vertex ``m`` (row ``3 f + m``); ``a < b``.
    """
    a, b = ids.take(_EDGE_A, axis=1), ids.take(_EDGE_B, axis=1)
    out = np.empty((len(ids), 3, 3), dtype=np.int64)
    np.minimum(a, b, out=out[:, :, 0])
    np.maximum(a, b, out=out[:, :, 1])
    out[:, :, 2] = root[:, None]
    return out.reshape(-1, 3)


def attach_local(geo: AttachGeometry, facet_points: npt.ArrayLike, nodes: npt.ArrayLike | None,
                 faces: npt.ArrayLike | None, seeds: npt.ArrayLike | None
                 ) -> tuple[Records, np.ndarray | None]:
    """Records without CAD-edge channels, and (with topology) the facet-edge keys ``(3 nf, 3)``."""
    fp = facet_array(facet_points, "facet_points")
    nf, nfv, _ = fp.shape
    _check_kind(geo, nfv)
    gid_input = None if nodes is None else np.asarray(nodes, dtype=np.int64).reshape(nf, nfv)
    # vertex identity: the given ids (equal ids, one vertex), else the points' grouping
    radius = MERGE_RTOL * geo.size
    gid = gid_input if gid_input is not None else vertex_groups(fp.reshape(-1, 3), radius).reshape(nf, nfv)
    h = longest_edge(fp)
    tol = geo.tol_factor * h
    if nf == 0:
        root, params = np.zeros(0, dtype=np.int64), np.zeros((0, nfv, geo.param_dim))
    else:
        if faces is None and geo._hints is not None and gid_input is not None:
            hinted = geo._hints.lookup(gid_input)
            if hinted is not None:
                faces, seeds = hinted
        if faces is None:  # the global search numbers the vertices 0..m-1
            if gid_input is not None:
                gid = vertex_groups(fp.reshape(-1, 3), radius, gid_input).reshape(nf, nfv)
            root, params, score = search_faces(geo, fp, gid, tol)
        else:
            root, params, score = on_faces(geo, fp, gid, faces, seeds, tol)
        check_attached(geo, fp, root, score, tol, h, given=faces is not None)
        params = contiguous(geo.entities, geo._period, root, params)
    keys = None
    if geo.topology is not None:
        keys = facet_edge_keys(gid_input if gid_input is not None else gid, root)
    return Records(root, params), keys


def check_attached(geo: AttachGeometry, fp: np.ndarray, root: np.ndarray, score: np.ndarray, tol: np.ndarray,
                   h: np.ndarray, given: bool) -> None:
    """Raise :class:`CadError` naming the worst facet if a facet's ``score`` exceeds its ``tol``.

    ``fp (nf, nfv, 3)`` facets, ``root (nf,)`` their entities, ``score (nf,)``
    the largest vertex distance to it, ``tol``, ``h (nf,)`` tolerance and
    longest edge; ``given``: the entities were given (not searched).
    """
    bad = (~(score <= tol)).nonzero()[0]
    if not bad.size:
        return
    nf = len(fp)
    flat = fp.reshape(-1, 3)
    worst = bad[np.argmax(np.where(np.isfinite(score[bad]), score[bad], np.inf) / np.maximum(h[bad], 1e-300))]
    what = (
        f"is {score[worst]:.3e} from {'its' if given else 'the nearest'} entity "
        f"({root[worst]}), more than the tolerance {tol[worst]:.3e} = tol_factor "
        f"{geo.tol_factor:g} x facet size {h[worst]:.3e}"
        if np.isfinite(score[worst])
        else "has no projection inside the trimming loops of any single face"
    )
    raise CadError(
        f"{bad.size} of {nf} boundary facets do not lie on the CAD geometry; e.g. "
        f"facet {worst} (vertices {fp[worst].round(6).tolist()}) {what}"
        + (
            f"; no facet lies on it: mesh boundary box {flat.min(axis=0).round(6).tolist()}"
            f" .. {flat.max(axis=0).round(6).tolist()}, CAD box "
            f"{geo.searcher.bbox_lo.min(axis=0).round(6).tolist()} .. "
            f"{geo.searcher.bbox_hi.max(axis=0).round(6).tolist()} (wrong file, units "
            "or placement?)"
            if bad.size == nf
            else ""
        )
    )


def vertex_candidates(geo: AttachGeometry, V: np.ndarray, tv: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Projections of distinct vertices ``V (nv, 3)`` onto their candidate entities.

    Candidates: every entity whose bounding box holds the vertex within its
    tolerance ``tv (nv,)``; a vertex off every candidate also gets the
    nearest entity anywhere (for the error message).  Results outside a
    trimmed face count as infinitely far.

    Returns:
        ``(vertex (k,), entity (k,), params (k, d), dist (k,))``, one row per
        (vertex, entity) pair.
    """
    ne = geo.num_entities
    pv, pe = box_pairs(V, tv + 1e-12 * geo.size, geo.searcher.bbox_lo, geo.searcher.bbox_hi)
    res = geo.searcher.search_on(V[pv], pe, accept=geo._accept)
    par, dist = res[0], res[2]
    if geo._accept is not None:
        dist = np.where(res[3], dist, np.inf)
    near = np.zeros(len(V), dtype=bool)
    near[pv[dist <= tv[pv]]] = True
    lost = np.flatnonzero(~near)
    if lost.size:  # off every candidate: the nearest entity anywhere (for the message)
        g = geo.searcher.search(V[lost], accept=geo._accept)
        gd = g[2] if geo._accept is None else np.where(g[3], g[2], np.inf)
        pv, pe = np.concatenate([pv, lost]), np.concatenate([pe, g[0]])
        par, dist = np.concatenate([par, g[1]]), np.concatenate([dist, gd])
        k = pv * ne + pe
        o = np.lexsort((dist, k))  # the nearest result per (vertex, entity)
        o = o[np.concatenate([[True], k[o][1:] != k[o][:-1]])]
        pv, pe, par, dist = pv[o], pe[o], par[o], dist[o]
    return pv, pe, par, dist


def search_faces(geo: AttachGeometry, fp: np.ndarray, gid: np.ndarray, tol: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Global search: per facet the entity nearest to all its vertices.

    ``fp (nf, nfv, 3)`` facets, ``gid (nf, nfv)`` vertex ids, ``tol (nf,)``.
    The candidate entities of a facet are those within tolerance of one of
    its vertices, and each vertex's nearest entity (:func:`vertex_candidates`).

    Returns:
        ``(root (nf,), params (nf, nfv, d), score (nf,))``, ``score`` the
        largest vertex distance to the chosen entity.
    """
    nf, nfv, _ = fp.shape
    d, ne = geo.param_dim, geo.num_entities
    vid = gid.reshape(-1)
    nv = int(vid.max()) + 1
    V = fp.reshape(-1, 3)[np.unique(vid, return_index=True)[1]]
    tv = np.zeros(nv)
    np.maximum.at(tv, vid, np.repeat(tol, nfv))
    pv, pe, par, dist = vertex_candidates(geo, V, tv)
    key = pv * ne + pe
    order = np.argsort(key)
    key, par, dist, pv, pe = key[order], par[order], dist[order], pv[order], pe[order]
    # candidate (facet, entity): entities within tolerance of a facet vertex
    cnt_v = np.bincount(pv, minlength=nv)
    start_v = np.concatenate([[0], np.cumsum(cnt_v)])[:-1]
    cnt = cnt_v[vid]
    rows = np.repeat(start_v[vid], cnt) + ramp(cnt)
    fac = np.repeat(np.repeat(np.arange(nf), nfv), cnt)
    near = dist[rows] <= tol[fac]
    # ... and each vertex's nearest entity (the facet's distance for the error message)
    best = best_per_group(pv, dist, nv)[vid]
    bf = np.repeat(np.arange(nf), nfv)[best >= 0]
    pair = np.unique(np.concatenate([fac[near] * ne + key[rows[near]] % ne,
                                     bf * ne + pe[best[best >= 0]]]))
    cf, ce = pair // ne, pair % ne  # every facet has one (its vertices' nearest entities)
    need = gid[cf].reshape(-1) * ne + np.repeat(ce, nfv)
    pos = np.minimum(np.searchsorted(key, need), len(key) - 1)
    dmax = np.where(key[pos] == need, dist[pos], np.inf).reshape(-1, nfv).max(axis=1)
    # choose per facet: smallest largest distance, ties to the lowest entity index
    order = np.lexsort((ce, dmax, cf))
    choice = order[np.searchsorted(cf[order], np.arange(nf))]
    params = par[pos].reshape(-1, nfv, d)[choice]
    return ce[choice].astype(np.int64), params, dmax[choice]


def on_faces(geo: AttachGeometry, fp: np.ndarray, gid: np.ndarray, faces: npt.ArrayLike,
             seeds: npt.ArrayLike | None, tol: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parameters of every facet vertex on a given entity (known faces, optional seeds).

    ``fp (nf, nfv, 3)`` facets, ``gid (nf, nfv)`` vertex ids (equal ids: one vertex;
    any integers), ``faces (nf,)``,
    ``seeds (nf, nfv, d)`` (NaN: unknown), ``tol (nf,)`` per facet.  Newton from the seeds (closed
    form on analytic faces), else from the entity's own search samples.

    Returns:
        ``(root (nf,), params (nf, nfv, d), score (nf,))`` as :func:`search_faces`.
    """
    nf, nfv, _ = fp.shape
    d = geo.param_dim
    root = np.asarray(faces, dtype=np.int64).reshape(-1)
    if root.shape != (nf,):
        raise ValueError(f"faces must have shape ({nf},), got {root.shape}")
    if nf and (root.min() < 0 or root.max() >= geo.num_entities):
        raise ValueError(f"faces refer to entities outside 0..{geo.num_entities - 1}")
    X = fp.reshape(-1, 3)
    ent = root.repeat(nfv)
    tol = tol.repeat(nfv)
    sd = np.full((nf * nfv, d), np.nan) if seeds is None else \
        np.asarray(seeds, dtype=float).reshape(nf * nfv, d)
    # one projection per (vertex, entity): the slots of a vertex on one face share it
    pairs = np.empty((nf * nfv, 2), dtype=np.int64)
    pairs[:, 0], pairs[:, 1] = gid.reshape(-1), ent
    first, inv, _ = unique_rows(pairs)
    t = np.zeros(len(first))
    np.maximum.at(t, inv, tol)
    par = np.zeros((len(first), d))
    dist = np.full(len(first), np.inf)
    finite = np.isfinite(sd[first]).all(axis=1)
    analytic = geo._analytic[ent[first]]
    on = (finite & ~analytic).nonzero()[0]
    if on.size:  # NURBS seeds that are the vertex itself (a mesh made from the CAD) need no Newton
        s = first[on]
        ok, dd = seed_is_point(geo, X[s], ent[s], sd[s])
        par[on[ok]], dist[on[ok]] = sd[s[ok]], dd[ok]
    seeded = ((finite | analytic) & ~(dist <= t)).nonzero()[0]
    if seeded.size:  # Newton from the given seeds (closed form on analytic faces)
        s = first[seeded]
        S = sd[s] if finite[seeded].all() else np.nan_to_num(sd[s])
        p, _, dd, _, conv = geo.searcher.refine(s, ent[s], S, X, geo.max_iter)
        par[seeded], dist[seeded] = p, np.where(conv, dd, np.inf)
    todo = (~(dist <= t)).nonzero()[0]
    if todo.size:  # the entity's own search samples
        s = first[todo]
        res = geo.searcher.search_on(X[s], ent[s])
        better = res[2] < dist[todo]
        par[todo[better]], dist[todo[better]] = res[0][better], res[2][better]
    params = par[inv].reshape(nf, nfv, d)
    return root, params, dist[inv].reshape(nf, nfv).max(axis=1)


#: a seed is its vertex if they are this close (relative to the entity's size)
SEED_RTOL = 1e-13


def seed_is_point(geo: AttachGeometry, X: np.ndarray, ent: np.ndarray, seeds: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``(ok (n,) bool, dist (n,))``: entity ``ent`` at ``seeds (n, d)`` is the point ``X (n, 3)``
    (within :data:`SEED_RTOL` of the entity's size), so the seed is the vertex's closest
    point; ``dist`` how far they are apart.

    One evaluation per point instead of a Newton projection: the parameters a
    mesher gives with its nodes are exact (gmsh evaluates the CAD at them).
    """
    S = geo.evaluate(ent, seeds[:, None, :])[:, 0]
    dist = norms(S - X)
    return dist <= SEED_RTOL * geo._sizes[ent], dist


def edge_channels(keys: np.ndarray, allkeys: np.ndarray, nfv: int) -> np.ndarray:
    """CAD-edge channels ``(nf, nfv, 3)`` from the facet-edge keys of all processes.

    ``keys (3 nf, 3)``: ``(node a, node b, face)`` of this process's facet
    edges (:func:`facet_edge_keys`); ``allkeys`` those of every process (on one
    process ``keys`` itself: then they are numbered once).  A facet edge is on a
    CAD edge if a facet sharing it (on any process) lies on another face.
    Channel ``m`` of facet vertex ``i`` is ``f_m (1 - delta_im)``.
    """
    nf = len(keys) // 3
    if nf == 0:
        return np.zeros((0, nfv, 3))
    mine = allkeys is keys
    row = row_index(keys[:, :2] if mine else np.concatenate([keys[:, :2], allkeys[:, :2]]))
    n = int(row.max()) + 1
    lo, hi = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    lo.fill(np.iinfo(np.int64).max)
    hi.fill(np.iinfo(np.int64).min)
    every = row if mine else row[len(keys):]
    np.minimum.at(lo, every, allkeys[:, 2])
    np.maximum.at(hi, every, allkeys[:, 2])
    row = row[: len(keys)]
    flag = (lo[row] != hi[row]).reshape(nf, 1, 3)  # (nf, 1, m)
    return flag * _off_diagonal(nfv)  # (nf, i, m)


@lru_cache(maxsize=4)
def _off_diagonal(nfv: int) -> np.ndarray:
    """``(nfv, 3)`` float: 1 where vertex ``i`` is not the one opposite facet edge ``m``."""
    return 1.0 - np.eye(nfv, 3)
