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

Everything here works on the gathered :class:`~nagata_snap.smoothing.neighbourhood.Neighbourhood`
(identical on every process); the facets around the sliding vertices are
gathered too, and every process updates the records of its own facets.
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
    """The snapped facets around the sliding vertices of a neighbourhood (collective set-up).

    Args:
        boundary: this process's :class:`SlidingBoundary`.
        nbh: the gathered neighbourhood.
        slide: ``(k,)`` canonical indices of the sliding vertices.

    Attributes:
        facets: ``(F, nfv)`` canonical vertices of the gathered facets (canonical order).
        records: their records.
        first: ``(k, 2)`` (facet, slot) that gives each sliding vertex its point.
        corner: ``(k,)`` bool, the sliding vertices at a corner (their facets
            on ``nfv`` or more distinct entities): they must not slide.
    """

    def __init__(self, boundary: SlidingBoundary, nbh: Neighbourhood, slide: np.ndarray):
        comm = nbh.comm
        self.boundary = boundary
        self.slide = np.asarray(slide, dtype=np.int64)
        fn = boundary.nodes
        canon = np.full(max(int(fn.max(initial=-1)), int(nbh.local_nodes.max(initial=-1))) + 1,
                        -1, dtype=np.int64)
        canon[nbh.local_nodes] = nbh.local_pos
        cf = canon[fn]  # -1: not in the neighbourhood
        is_slide = np.zeros(nbh.n_nodes + 1, dtype=bool)  # [-1] stays False
        is_slide[self.slide] = True
        rows = np.flatnonzero(is_slide[cf].any(axis=1)) if cf.size else np.zeros(0, np.int64)
        self._rows = rows
        recs = boundary.records
        parts = comm.allgather((cf[rows], recs.root[rows], recs.params[rows]))
        fac = np.concatenate([p[0] for p in parts]).reshape(-1, fn.shape[1])
        root = np.concatenate([p[1] for p in parts])
        params = np.concatenate([p[2] for p in parts]).reshape((len(root), *recs.params.shape[1:]))
        key = np.sort(fac, axis=1)
        order = np.lexsort(key.T[::-1])
        inv = np.empty_like(order)
        inv[order] = np.arange(order.size)
        offset = sum(len(p[1]) for p in parts[: comm.rank])
        self._pos = inv[offset + np.arange(rows.size)]  # canonical rows of this process's facets
        self.facets = fac[order]
        self.records = Records(root[order], params[order])
        # each sliding vertex takes its point from its first slot in canonical order
        f, v = np.nonzero(is_slide[self.facets])
        node = self.facets[f, v]
        first = np.unique(node, return_index=True)[1]
        where = np.full(nbh.n_nodes, -1, dtype=np.int64)
        where[node[first]] = first
        sel = where[self.slide]
        self.first = np.stack([f[sel], v[sel]], axis=1)
        self._params = self.records.params
        # corners never slide (the rule of nagata_snap.mesh.corners)
        self.corner = corner_vertices(node, self.records.root[f], nbh.n_nodes, self.facets.shape[1])[self.slide]

    def project(self, x: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Closest points ``(k, d)`` on the geometry of the sliding vertices moved to ``points``.

        ``x``: ``(N, d)`` canonical coordinates of the neighbourhood (the
        other facet vertices).  Remembers the new parameters of every slot
        for :meth:`commit`.
        """
        d = x.shape[1]
        pts = np.zeros((*self.facets.shape, 3))
        pts[..., :d] = x[self.facets]
        mask = np.isin(self.facets, self.slide)
        pos = np.full(x.shape[0], -1, dtype=np.int64)
        pos[self.slide] = np.arange(self.slide.size)
        pts[mask, :d] = points[pos[self.facets[mask]]]
        out, rec = self.boundary.project(self.records, pts)
        self._params = np.asarray(rec.params, dtype=float)
        return np.asarray(out)[self.first[:, 0], self.first[:, 1], :d]

    def tangents(self, x: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """On-geometry points ``(k, d)`` and orthonormal tangent bases ``(k, d, d - 1)``.

        Columns are zero where the tangent space has fewer dimensions (a
        vertex on a CAD edge or crease has one, a corner none).
        """
        d = x.shape[1]
        p = self.project(x, x[self.slide])
        h = TANGENT_STEP * scale[self.slide]
        J = np.empty((self.slide.size, d, d))
        for j in range(d):  # d projections of all sliding vertices at once
            q = p.copy()
            q[:, j] += h
            J[:, :, j] = (self.project(x, q) - p) / h[:, None]
        U, s, _ = np.linalg.svd(J)
        basis = U[:, :, : d - 1] * (s[:, None, : d - 1] > 0.5)
        self.project(x, p)  # leave the parameters of p for commit
        return p, basis

    def commit(self, slid: np.ndarray) -> None:
        """Write the parameters of the last :meth:`project` of the vertices ``slid (k,)`` into the records."""
        moved = np.zeros(int(self.facets.max(initial=-1)) + 1, dtype=bool)
        moved[self.slide[np.asarray(slid, dtype=bool)]] = True
        mask = moved[self.facets]
        self.records.params[mask] = self._params[mask]
        mine = mask[self._pos]
        own = self.boundary.records.params[self._rows]
        own[mine] = self._params[self._pos][mine]
        self.boundary.records.params[self._rows] = own
