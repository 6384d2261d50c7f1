"""What the guard's smoothing buys: quality of the changed cells with sweeps only, elastic, or none.

A CAD part (``--file``, default the 275-face block of :func:`cad_parts.bracket`)
is meshed by :func:`nagata_snap.cad.mesh_cad` and refined ``--levels`` times
by :meth:`nagata_snap.Snapper.refine`, once per variant of the guard's first
stage (``--variants``):

* ``sweeps``: the default, ``FIRST_SWEEPS`` Jacobi sweeps of graph-Laplacian
  averaging over the band, the elastic solve only near bad or poor cells;
* ``elastic``: the stiffened elastic extension over the whole band
  (``first_sweeps=0``, the guard before the sweeps);
* ``none``: no interior smoothing (``smoothing='none'``) for reference.

Per level and variant: the seconds of ``smooth+check``, the repair stage,
and the quality of the cells near the snapped vertices (within
``AUTO_LAYERS_MAX`` vertex layers, the widest band: the same cells for
every variant, on each process its own, without ghost layers): the 5th
percentile and minimum of the minimum dihedral angle (degrees) and of the
mean ratio, and the histogram of the mean ratio (``RATIO_BINS``).

    python benchmarks/guard_quality.py [--size 60] [--levels 1] [--variants sweeps,elastic,none]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

import mpi4py.MPI as MPI
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.dirname(HERE)]

import cad_parts  # noqa: E402

import nagata_snap.snapper as snapper_mod  # noqa: E402
from nagata_snap import Snapper  # noqa: E402
from nagata_snap.cad import mesh_cad  # noqa: E402
from nagata_snap.mesh.simplex import cell_columns, cells_touching  # noqa: E402
from nagata_snap.smoothing.band import AUTO_LAYERS_MAX  # noqa: E402
from nagata_snap.smoothing.quality import RATIO_BINS, quality_stats  # noqa: E402

VARIANTS = {"sweeps": ("elastic", {}), "elastic": ("elastic", {"first_sweeps": 0}),
            "none": ("none", {})}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--file", default="")
    ap.add_argument("--size", type=float, default=60.0)
    ap.add_argument("--curvature", type=int, default=6)
    ap.add_argument("--levels", type=int, default=1)
    ap.add_argument("--variants", default="sweeps,elastic,none")
    args = ap.parse_args()
    comm = MPI.COMM_WORLD
    path = args.file
    if not path:
        path = comm.bcast(os.path.join(tempfile.mkdtemp(prefix="guard_quality_"), "bracket.step")
                          if comm.rank == 0 else None)
        if comm.rank == 0:
            cad_parts.bracket(path)
        comm.barrier()
    cm, geo = mesh_cad(path, comm, size=args.size, curvature=args.curvature)
    seen: dict = {}
    real_repair = snapper_mod.repair

    def spy(mesh, x_ref, x_target, *a, **kw):  # keeps the reference and target coordinates
        seen["x_ref"], seen["x_tgt"] = np.array(x_ref), np.array(x_target)
        return real_repair(mesh, x_ref, x_target, *a, **kw)

    snapper_mod.repair = spy
    say = print if comm.rank == 0 else (lambda *a, **k: None)
    say(f"{'variant':8s} {'lvl':>3s} {'cells':>9s} {'changed':>8s} {'s':>6s} {'stage':>9s} "
        f"{'angle p5':>8s} {'min':>6s} {'ratio p5':>8s} {'min':>6s}  mean-ratio histogram "
        f"{RATIO_BINS.tolist()}")
    for name in args.variants.split(","):
        method, opts = VARIANTS[name]
        sn = Snapper(cm.mesh, cm.facet_tags, geo, smoothing=method, smoothing_options=opts)
        mesh = cm.mesh
        for level in range(1, args.levels + 1):
            mesh, _, _, _, rep = sn.refine(mesh)
            x = mesh.geometry.x
            nown = mesh.topology.index_map(3).size_local
            cells = mesh.geometry.dofmaps[0][:nown]
            # the same cells for every variant: within AUTO_LAYERS_MAX layers of the snapped nodes
            mark = np.any(seen["x_tgt"] != seen["x_ref"], axis=1)
            cols = cell_columns(cells)
            for _ in range(AUTO_LAYERS_MAX - 1):
                mark[cells[cells_touching(mark, cols)].reshape(-1)] = True
            ch = cells[cells_touching(mark, cols)]
            q = quality_stats(x, ch, 3)
            ang = np.concatenate(comm.allgather(q["min_angle"]))
            rat = np.concatenate(comm.allgather(q["mean_ratio"]))
            hist = np.histogram(np.clip(rat, 0, 1), RATIO_BINS)[0]
            t = comm.allreduce(rep.times["smooth+check"], op=MPI.MAX)
            say(f"{name:8s} {level:3d} {rep.num_cells:9d} {ang.size:8d} {t:6.2f} {rep.repair_stage:>9s} "
                f"{np.percentile(ang, 5):8.3f} {ang.min():6.2f} {np.percentile(rat, 5):8.4f} "
                f"{rat.min():6.3f}  {hist.tolist()}", flush=True)


if __name__ == "__main__":
    main()
