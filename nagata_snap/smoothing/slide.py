"""Snapped boundary vertices that slide on the geometry during the repair.

A cell whose vertices are all on the boundary (common in coarse meshes of
thin walls, fillets and holes) cannot be helped by moving interior nodes.
The repair (:mod:`nagata_snap.smoothing.repair`) may then move nearby snapped
boundary vertices *along* the geometry: each sliding vertex moves in its
tangent space (optimised together with the interior, :mod:`nagata_snap.smoothing.untangle`)
and is projected back onto its facets' geometric entity, so it stays exactly
on the geometry and its lineage record follows it (no drift at later levels).
Corners (vertices whose facets lie on ``nfv`` or more distinct entities:
three faces in 3D, two curves in 2D) never slide, whatever the geometry's
projection does with them.

The geometry is asked through one call, ``project(records, points) ->
(points (nf, nfv, 3), records)``: the closest point of each facet vertex on
its facet's own entity, seeded by the record, with sharp edges and corners
kept on their feature (:meth:`nagata_snap.nagata.geometry.NagataGeometry.project`:
a vertex on a coarse edge moves along it, a coarse vertex not at all;
:meth:`nagata_snap.cad.CadGeometry.project`: a vertex on a CAD edge moves
along that edge, a CAD vertex not at all).  The tangent space of a vertex is that of the projection: the
span of the projection's finite-difference Jacobian ``(P(p + h e_j) - P(p)) / h``
(rank 2 on a face, 1 on an edge, 0 at a corner), so the feature rules live
in the geometry only.

Under MPI each process projects the sliding vertices it has, from all their
facets (those of other processes at a shared vertex are exchanged once), in
an order that does not depend on the partition, and the owner's result is
the one every copy keeps (:class:`SlideFacets`); every process updates the
records of its own facets.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from nagata_snap.mesh.corners import corner_vertices
from nagata_snap.mesh.records import Records
from nagata_snap.smoothing.band import NodeSync
from nagata_snap.smoothing.neighbourhood import Neighbourhood

__all__ = ["SlidingBoundary", "SlideFacets"]

#: Finite-difference step of the tangent spaces, relative to the vertex's shortest edge.
TANGENT_STEP = 1e-4


def _projector(geometry: object) -> Callable[[Records, np.ndarray], tuple[np.ndarray, Records]]:
    """``project(records, points) -> (points, records)`` of a snapping geometry (checked at run time)."""
    project = getattr(geometry, "project", None)
    if project is None:
        raise TypeError(f"{type(geometry).__name__} has no project(records, points): its "
                        "boundary vertices cannot slide (pass repair options without sliding)")
    return lambda rec, pts: _first_two(project(rec, pts))


def _first_two(result: tuple) -> tuple[np.ndarray, Records]:
    """``(points, records)``: the first two items of a geometry's ``project`` result."""
    return result[0], result[1]


class SlidingBoundary:
    """The snapped facets of one process, their records and the geometry that projects onto them.

    Args:
        nodes: ``(nf, nfv)`` local geometry nodes of this process's snapped facets.
        records: their :class:`~nagata_snap.mesh.records.Records` (copied).
        geometry: the snapping geometry (its ``project``, see the module docstring).
        blocked: ``(m,)`` local nodes that never slide (e.g. on boundary facets
            that are not snapped).

    Attributes:
        records: the records, updated where vertices slid (read them after
            :func:`~nagata_snap.smoothing.repair.repair` succeeded).
        n_slid: global number of vertices that slid.
    """

    def __init__(self, nodes: np.ndarray, records: Records, geometry: object, blocked: np.ndarray):
        self.nodes = np.asarray(nodes, dtype=np.int64)
        self.records = Records(np.array(records.root), np.array(records.params, dtype=float))
        self.project = _projector(geometry)
        self.blocked = np.asarray(blocked, dtype=np.int64).reshape(-1)
        self.n_slid = 0

    def eligible(self, sync: NodeSync) -> np.ndarray:
        """``(n,)`` bool: nodes of snapped facets not blocked (ghost-consistent; collective)."""
        snap = np.zeros(sync.n, dtype=bool)
        snap[self.nodes.reshape(-1)] = True
        block = np.zeros(sync.n, dtype=bool)
        block[self.blocked] = True
        return sync.any(snap) & ~sync.any(block)


class SlideFacets:
    """The snapped facets around the sliding vertices this process holds (collective set-up).

    Every process projects the sliding vertices it has (owned and ghost)
    from all their facets: its own and, at a vertex that other processes'
    facets share, theirs (exchanged once, with their records and
    coordinates: ``O(processes x facets at shared sliding vertices)``),
    in a canonical order (by the reference coordinates of the facets'
    vertices), so a vertex's projection is computed from the same slots in
    the same order as in a serial run.  The owners' results are then sent
    to the ghost copies, so all copies agree bitwise.

    Args:
        boundary: this process's :class:`SlidingBoundary`.
        nbh: the :class:`~nagata_snap.smoothing.neighbourhood.Neighbourhood`
            the vertices slide in (its halo connects their copies).
        slide: ``(n,)`` bool over local nodes, the sliding vertices (the same
            on every copy of a node).
        x_ref: ``(n, 3)`` reference coordinates; x: ``(n, 3)`` current coordinates
            (the fixed facet vertices' positions).

    Attributes:
        slide: ``(k,)`` local indices of the sliding vertices.
        facets: ``(F, nfv)`` local node of every slot of the facets around them
            (canonical order; -1: a node of another process's facet that this
            process does not have).
        records: their records.
        corner: ``(k,)`` bool, the sliding vertices at a corner (their facets
            on ``nfv`` or more distinct entities): they must not slide.
    """

    def __init__(self, boundary: SlidingBoundary, nbh: Neighbourhood, slide: np.ndarray,
                 x_ref: np.ndarray, x: np.ndarray):
        self.boundary, self.nbh = boundary, nbh
        self.slide = np.flatnonzero(slide)
        fn = boundary.nodes
        rows = np.flatnonzero(slide[fn].any(axis=1)) if fn.size else np.zeros(0, np.int64)
        self._rows = rows
        recs = boundary.records
        fac, xr, pts0, root, params = self._with_shared(fn[rows], recs.root[rows], recs.params[rows],
                                                        slide, x_ref, x)
        # canonical order: each facet's vertices by (x, y, z) reference coordinates, then the facets
        by_xyz = np.lexsort((xr[..., 2], xr[..., 1], xr[..., 0]), axis=-1)
        key = np.take_along_axis(xr, by_xyz[..., None], axis=1).reshape(len(fac), 3 * fac.shape[1])
        order = np.lexsort(key.T[::-1])
        inv = np.empty_like(order)
        inv[order] = np.arange(order.size)
        self._pos = inv[: rows.size]  # canonical rows of this process's own facets
        self.facets, self._pts0 = fac[order], pts0[order]
        self.records = Records(root[order], params[order])
        # each sliding vertex takes its point from its first slot in canonical order
        f, v = np.nonzero(np.isin(self.facets, self.slide))
        node = self.facets[f, v]
        first = np.unique(node, return_index=True)[1]
        where = np.full(len(slide), -1, dtype=np.int64)
        where[node[first]] = first
        sel = where[self.slide]
        self.first = np.stack([f[sel], v[sel]], axis=1)
        self._params = self.records.params
        # corners never slide (the rule of nagata_snap.mesh.corners)
        on = self.facets >= 0
        fo = np.nonzero(on)[0]
        self.corner = corner_vertices(self.facets[on], self.records.root[fo], len(slide),
                                      self.facets.shape[1])[self.slide]

    def _with_shared(self, fn: np.ndarray, root: np.ndarray, params: np.ndarray, slide: np.ndarray,
                     x_ref: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """This process's facets ``fn (f, nfv)`` at sliding vertices and the other processes'
        facets at the sliding vertices it shares with them (collective).

        Returns ``(local nodes (F, nfv), x_ref (F, nfv, 3), x (F, nfv, 3), root (F,),
        params (F, ...))``, this process's facets first.
        """
        nbh = self.nbh
        comm, lay = nbh.comm, nbh.layout
        xr, xx = x_ref[fn], x[fn]
        if comm.size == 1:
            return fn, xr, xx, root, params
        # processes with facets at each sliding vertex (owners count all copies)
        has = np.zeros(len(slide), dtype=np.int64)
        has[fn[slide[fn]]] = 1
        nbh.halo.reverse(has, np.add)
        nbh.halo.forward(has)
        shared = ((has[fn] > 1) & slide[fn]).any(axis=1)
        parts = comm.allgather((lay.to_global(fn[shared]), xr[shared], xx[shared], root[shared],
                                params[shared]))
        other = [q for r, q in enumerate(parts) if r != comm.rank and len(q[3])]
        out = [fn, xr, xx, root, params]
        for gid, oxr, oxx, oroot, opar in other:
            loc = lay.to_local(gid)
            keep = ((loc >= 0) & slide[np.maximum(loc, 0)]).any(axis=1)
            for k, a in enumerate((loc, oxr, oxx, oroot, opar)):
                out[k] = np.concatenate([out[k], a[keep]])
        return tuple(out)

    def _points(self, x: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``(F, nfv, 3)`` slot positions: ``x`` (local nodes), the sliding vertices at ``points``."""
        d = x.shape[1]
        pts = self._pts0.copy()
        on = self.facets >= 0
        pts[on, :d] = x[self.facets[on]]
        row = np.full(x.shape[0], -1, dtype=np.int64)
        row[self.slide] = np.arange(self.slide.size)
        s = np.zeros(self.facets.shape, dtype=bool)
        s[on] = row[self.facets[on]] >= 0
        pts[s, :d] = points[row[self.facets[s]]]
        return pts

    def _owners(self, a: np.ndarray) -> np.ndarray:
        """``a (k, ...)`` over the sliding vertices with every ghost copy set to its owner's (collective)."""
        full = np.zeros((len(self.nbh.nodes), *a.shape[1:]))
        full[self.slide] = a
        self.nbh.halo.forward(full)
        return full[self.slide]

    def project(self, x: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Closest points ``(k, d)`` on the geometry of the sliding vertices moved to ``points`` (collective).

        ``x``: ``(n, d)`` local coordinates (the other facet vertices).
        Remembers the new parameters of every slot for :meth:`commit`.
        """
        d = x.shape[1]
        out, rec = self.boundary.project(self.records, self._points(x, points))
        self._params = np.asarray(rec.params, dtype=float)
        return self._owners(np.asarray(out)[self.first[:, 0], self.first[:, 1], :d])

    def tangents(self, x: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """On-geometry points ``(k, d)`` and orthonormal tangent bases ``(k, d, d - 1)`` (collective).

        Columns are zero where the tangent space has fewer dimensions (a
        vertex on a CAD edge or crease has one, a corner none).
        """
        d = x.shape[1]
        p = self.project(x, x[self.slide])
        params = self._params  # (the parameters of p, for commit)
        h = TANGENT_STEP * scale[self.slide]
        J = np.empty((self.slide.size, d, d))
        for j in range(d):  # d projections of all sliding vertices at once
            q = p.copy()
            q[:, j] += h
            J[:, :, j] = (self.project(x, q) - p) / h[:, None]
        U, s, _ = np.linalg.svd(J)
        basis = U[:, :, : d - 1] * (s[:, None, : d - 1] > 0.5)
        self._params = params
        return p, self._owners(basis)

    def commit(self, slid: np.ndarray) -> None:
        """Write the parameters of the last :meth:`project` of the vertices ``slid (k,)`` into the
        records of this process's facets."""
        moved = np.zeros(len(self.nbh.nodes) + 1, dtype=bool)  # [-1]: nodes of other processes
        moved[self.slide[np.asarray(slid, dtype=bool)]] = True
        mask = moved[self.facets]
        self.records.params[mask] = self._params[mask]
        mine = mask[self._pos]
        own = self.boundary.records.params[self._rows]
        own[mine] = self._params[self._pos][mine]
        self.boundary.records.params[self._rows] = own
