"""A boundary vertex pushed past its neighbour along the curve: only sliding repairs it.

Unit disk (8 coarse segments), two snapped levels, in Nagata mode (exact
normals, so the Nagata curves are close to the circle) and in CAD mode (an
exact rational NURBS circle).  The level-2 boundary vertex at 22.5
degrees (the middle of a coarse segment) is prescribed a new position on its
Nagata curve at 36 degrees, beyond its neighbour at 33.75 degrees: the
boundary edge between them turns over, and no interior motion can repair
the cell on it.  ``repair`` is called on the level-2 mesh with and without a
:class:`~nagata_snap.smoothing.slide.SlidingBoundary`.

Run serially (by the tests) or under ``mpiexec -n N [mode] [split]``: rank 0
prints one JSON line, the result of the distributed run and, for comparison,
of the same problem solved on rank 0 alone (``COMM_SELF``).  ``split``
partitions the coarse disk along the ray at 45 degrees (see :func:`problem`),
so that sliding vertices lie on a process boundary.
"""

from __future__ import annotations

import json
import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import generate
import make_iges
from surfaces import nagata_surface_error

from nagata_snap import NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.smoothing.quality import inverted_cells
from nagata_snap.mesh.records import Records
from nagata_snap.smoothing.repair import repair
from nagata_snap.smoothing.slide import SlideFacets, SlidingBoundary

ANGLE_FROM, ANGLE_TO = np.radians(22.5), np.radians(36.0)


def sector_partitioner(start_deg, stop_deg):
    """A cell partitioner for the gmsh disk: cells whose centroid angle lies in
    ``[start_deg, stop_deg)`` to rank 1, the others to rank 0 (no ghost cells).

    The cells arrive in gmsh's node numbering (tag - 1) on the rank that meshed;
    their coordinates are read from gmsh, which still holds the model then.
    """
    import gmsh

    import dolfinx.graph

    def partition(comm, nparts, cell_types, cells):
        c = np.asarray(cells[0], dtype=np.int64).reshape(-1, 3)
        dest = np.zeros(len(c), dtype=np.int32)
        if len(c):
            tags, pts, _ = gmsh.model.mesh.getNodes()
            xyz = np.zeros((int(tags.max()), 3))
            xyz[tags.astype(np.int64) - 1] = pts.reshape(-1, 3)
            mid = xyz[c].mean(axis=1)
            ang = np.degrees(np.arctan2(mid[:, 1], mid[:, 0])) % 360.0
            dest[(ang >= start_deg) & (ang < stop_deg)] = min(1, nparts - 1)
        return dolfinx.graph.adjacencylist(dest, np.arange(len(c) + 1, dtype=np.int32))._cpp_object

    return partition


def problem(comm, mode, split=False):
    """(mesh, geometry, snapped facet nodes, records, x, x_target, moved, boundary nodes).

    ``split``: the coarse disk partitioned along the ray at 45 degrees (the cells in
    the half turn from 45 to 225 degrees on rank 1), so that the coarse vertex at 45
    degrees, two level-2 boundary edges from the pushed vertex, is on a process
    boundary: its facets are on two processes and only both say that it is a corner.
    """
    md = generate.unit_disk(comm, n=8, partitioner=sector_partitioner(45.0, 225.0) if split else None)
    if mode == "cad":
        geo = CadGeometry([make_iges.circle_curve((0.0, 0.0, 0.0), 1.0)])
    else:
        geo = NagataGeometry(md.mesh, md.facet_tags, normals=lambda x: x)
    snapper = Snapper(md.mesh, md.facet_tags, geo)
    m, *_ = snapper.refine(md.mesh)
    m, *_ = snapper.refine(m)
    lv = snapper._level
    nodes, records = lv.boundary.nodes[lv.snapped], lv.records
    x = m.geometry.x.copy()
    # the slots of the vertex at 22.5 degrees, and its new place on its own curve
    ang = np.arctan2(x[nodes, 1], x[nodes, 0])
    hit = np.abs(ang - ANGLE_FROM) < 1e-3  # (the Nagata curve is 1e-9 rad off the circle here)
    f, v = np.nonzero(hit)
    moved = np.unique(nodes[hit]).astype(np.int32)
    x_t = x.copy()
    target = np.array([np.cos(ANGLE_TO), np.sin(ANGLE_TO), 0.0])
    if f.size and mode == "cad":
        x_t[moved] = target  # on the circle
    elif f.size:  # on its Nagata curve
        seed = records.take(f[:1])
        pts = np.repeat(target[None, None], nodes.shape[1], 1)
        q, _ = geo.project(Records(seed.root, seed.params), pts)
        x_t[moved] = q[0, v[0]]
    return m, geo, nodes, records, x, x_t, moved, np.unique(lv.boundary.nodes).astype(np.int32)


#: facets of other processes that SlideFacets took in (at sliding vertices they share)
RECEIVED = [0]
_with_shared = SlideFacets._with_shared


def _counting(self, fn, *args):
    out = _with_shared(self, fn, *args)
    RECEIVED[0] += len(out[0]) - len(fn)
    return out


SlideFacets._with_shared = _counting


def run(comm, with_slide: bool, mode: str = "nagata", split: bool = False) -> dict:
    m, geo, nodes, records, x, x_t, moved, bnd = problem(comm, mode, split)
    slide = SlidingBoundary(nodes, records, geo, np.zeros(0, np.int32)) if with_slide else None
    RECEIVED[0] = 0
    res = repair(m, x, x_t, moved, bnd, slide=slide)
    n_own = m.geometry.index_map().size_local
    cells = m.geometry.dofmaps[0][: m.topology.index_map(2).size_local]
    out = {"stage": res.stage, "slid": res.slid, "received_facets": comm.allreduce(RECEIVED[0]),
           "n_short": comm.allreduce(int(np.count_nonzero(res.shortfall > 0))),
           "n_inverted": comm.allreduce(int(inverted_cells(res.x, x, cells, 2).size))}
    if with_slide:
        # every snapped vertex is where its (updated) records put it
        rec = slide.records
        pts = geo.evaluate(rec.root, rec.params)
        out["records_gap"] = comm.allreduce(float(np.abs(pts - res.x[nodes]).max(initial=0.0)),
                                            op=MPI.MAX)
        out["on_circle"] = comm.allreduce(
            float(np.abs(np.hypot(res.x[nodes, 0], res.x[nodes, 1]) - 1.0).max(initial=0.0)),
            op=MPI.MAX)
        out["geometry_error"] = 1e-12 if mode == "cad" else nagata_surface_error(
            geo, lambda p: np.abs(np.hypot(p[..., 0], p[..., 1]) - 1))
        # Nagata: coarse vertices never move (records with a zero barycentric coordinate)
        zero = (rec.params == 0).any(axis=2) if mode == "nagata" else np.zeros(nodes.shape, bool)
        out["coarse_moved"] = comm.allreduce(
            float(np.abs(res.x[nodes][zero] - x[nodes][zero]).max(initial=0.0)), op=MPI.MAX)
        own = np.flatnonzero(np.isin(np.arange(n_own), nodes))
        ang = np.arctan2(res.x[own, 1], res.x[own, 0])
        out["angles"] = sorted(np.round(np.degrees(np.concatenate(comm.allgather(ang))), 9).tolist())
        out["target_kept"] = bool(comm.allreduce(
            int(np.all(res.x[moved] == x_t[moved])), op=MPI.MIN))
    return out


def main():
    comm = MPI.COMM_WORLD
    mode = sys.argv[1] if len(sys.argv) > 1 else "nagata"
    split = "split" in sys.argv[2:]
    par = {"slide": run(comm, True, mode, split), "no_slide": run(comm, False, mode, split)}
    ser = None
    if comm.rank == 0 and comm.size > 1:
        ser = {"slide": run(MPI.COMM_SELF, True, mode), "no_slide": run(MPI.COMM_SELF, False, mode)}
    if comm.rank == 0:
        print(json.dumps({"size": comm.size, "par": par, "ser": ser}), flush=True)


if __name__ == "__main__":
    main()
