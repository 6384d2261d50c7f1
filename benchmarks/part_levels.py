"""A machined part through refinement levels: where each level's time goes.

The 275-face block of :func:`cad_parts.bracket` (a STEP file written by gmsh's
OpenCASCADE: filleted edges, 60 counterbored and chamfered holes, a slot swept
along a B-spline, three bosses) is meshed by :func:`nagata_snap.cad.mesh_cad`
(``--size``, ``--curvature``) and refined uniformly ``--levels`` times by
:meth:`nagata_snap.Snapper.refine` with its defaults.  Printed per level:

* cells, boundary vertices moved, cells inverted before smoothing and the
  repair stage that ended the level;
* the seconds of each stage of ``report.times`` (the largest over the ranks);
* every smoothing and repair attempt (``report.smoothing_attempts``: stage,
  cells and free nodes it moved, seconds);
* ``over_refine``: ``(lineage + place + smooth+check) / refine``, the measure of
  ``benchmarks/snap_overhead.py``, against the ``dolfinx.mesh.refine`` of the
  same call;
* the largest distance of a snapped vertex from its CAD face, relative to the
  model size, and the vertices left short of the geometry.

Last line: ``part_over_refine <largest over_refine of the levels>``.

    python benchmarks/part_levels.py [--size 30] [--curvature 6] [--levels 1]
    mpiexec -n 2 python benchmarks/part_levels.py --levels 2
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import mpi4py.MPI as MPI
import numpy as np

sys.path[:0] = [os.path.dirname(os.path.abspath(__file__))]

import cad_parts  # noqa: E402

from nagata_snap import Snapper  # noqa: E402
from nagata_snap.cad import mesh_cad  # noqa: E402
from nagata_snap.cli import boundary_distance  # noqa: E402

STAGES = ("refine", "lineage", "place", "smooth+check", "tags")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=float, default=30.0, help="largest element size [mm] (default 30)")
    ap.add_argument("--curvature", type=int, default=6, help="gmsh elements per 2 pi of curvature (default 6)")
    ap.add_argument("--levels", type=int, default=1)
    args = ap.parse_args()
    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)

    path = os.path.join(tempfile.mkdtemp(prefix="part_levels_"), "bracket.step") if comm.rank == 0 else None
    path = comm.bcast(path)
    if comm.rank == 0:
        cad_parts.bracket(path)
    comm.barrier()
    t0 = time.perf_counter()
    cm, geo = mesh_cad(path, comm, size=args.size, curvature=args.curvature)
    assert geo.model is not None
    say(f"{geo.model.summary()}; meshed (size {args.size}, curvature {args.curvature}): "
        f"{cm.mesh.topology.index_map(3).size_global} cells, {comm.size} processes "
        f"({time.perf_counter() - t0:.1f} s)", flush=True)

    snapper, mesh, worst = Snapper(cm.mesh, cm.facet_tags, geo), cm.mesh, 0.0
    for level in range(1, args.levels + 1):
        mesh, _, _, _, rep = snapper.refine(mesh)
        times = {k: comm.allreduce(rep.times.get(k, 0.0), op=MPI.MAX) for k in STAGES}
        over = (times["lineage"] + times["place"] + times["smooth+check"]) / times["refine"]
        worst = max(worst, over)
        d = np.concatenate(comm.allgather(boundary_distance(snapper)))
        say(f"level {level}: {rep.num_cells} cells, {rep.boundary_vertices_moved} boundary vertices moved "
            f"(max {rep.max_displacement:.3g}), {rep.inverted_before_smoothing} inverted before smoothing, "
            f"stage {rep.repair_stage}; " + ", ".join(f"{k} {v:.2f} s" for k, v in times.items())
            + f"; over_refine {over:.2f}")
        for a in rep.smoothing_attempts:
            say(f"    {a['stage']:9s} cells {a.get('cells', 0):8d} nodes {a.get('nodes', 0):7d} "
                f"{a['seconds']:8.2f} s  bad after {a.get('n_bad', 0)}")
        say(f"    distance from the CAD face: max {d.max(initial=0.0) / geo.size:.1e} of the model size; "
            f"{rep.partially_moved} vertices left short", flush=True)
    say(f"part_over_refine {worst:.2f}")


if __name__ == "__main__":
    main()
