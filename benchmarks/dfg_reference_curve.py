"""DFG 2D-1 reference curve on meshes regenerated on the true circle.

For each level l the gmsh mesh is rebuilt from the geometry (all circle
vertices on the true circle), and the steady Navier-Stokes problem is solved
with Taylor-Hood P2/P1 (``demos/dfg.py``).  Two families:

* ``uniform``: ``dfg_channel_regenerated(l, n_circle=16, h_far=0.04)``, the
  sizes of l uniform refinements of the default coarse mesh (16-gon), but
  with the circle regenerated: n_circle = 16 * 2^l, h_far = 0.04 / 2^l m;
* ``circle32``: ``dfg_channel_regenerated(l, n_circle=32, h_far=0.04)``, one
  extra circle halving at the same far-field size (the family behind the
  numbers quoted in DESIGN.md: 3.8e-3 at ~10k dofs, 1.0e-3 at ~39k, 2.3e-4 at
  ~150k).

Prints dofs, c_D, c_L, dp, relative errors (volume and surface drag/lift),
Newton iterations and times.  Usage::

    python benchmarks/dfg_reference_curve.py [--family uniform|circle32|both]
        [--max-level 3] [--csv out.csv]
    mpiexec -n 2 python benchmarks/dfg_reference_curve.py
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import mpi4py.MPI as MPI

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from demos.dfg import C_D_REF, C_L_REF, DP_REF, solve_dfg
from meshes.generate import dfg_channel_regenerated

FAMILIES = {"uniform": 16, "circle32": 32}


def run(family: str, max_level: int, comm=MPI.COMM_WORLD) -> list[dict]:
    """Solve levels 0..max_level of ``family``; return one dict per level."""
    rows = []
    n0 = FAMILIES[family]
    for level in range(max_level + 1):
        t0 = time.perf_counter()
        data = dfg_channel_regenerated(comm, level, n_circle=n0, h_far=0.04)
        t_mesh = time.perf_counter() - t0
        res = solve_dfg(data.mesh, data.facet_tags)
        row = {"family": family, "level": level, "n_circle": n0 * 2**level,
               "h_far": 0.04 / 2**level, "mesh_time": t_mesh}
        row.update(res.row())
        rows.append(row)
        if comm.rank == 0:
            print(
                f"{family:>8} {level:3d} {row['n_circle']:5d} {res.dofs:8d} {res.c_D:12.8f} "
                f"{res.c_L:12.9f} {res.dp:12.9f} {res.err_c_D:9.2e} {res.err_c_L:9.2e} "
                f"{res.err_dp:9.2e} {res.err_c_D_surface:9.2e} {res.err_c_L_surface:9.2e} "
                f"{res.newton_iterations:3d} {t_mesh:7.2f} {res.solve_time:7.2f} "
                f"{res.total_time:7.2f}",
                flush=True,
            )
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", choices=[*FAMILIES, "both"], default="both")
    parser.add_argument("--max-level", type=int, default=3)
    parser.add_argument("--csv", default=None, help="write the table as CSV (rank 0)")
    args = parser.parse_args(argv)
    comm = MPI.COMM_WORLD
    if comm.rank == 0:
        print(f"reference: c_D = {C_D_REF}, c_L = {C_L_REF}, dp = {DP_REF}; "
              f"{comm.size} MPI rank(s)")
        print(
            f"{'family':>8} {'lvl':>3} {'n_cyl':>5} {'dofs':>8} {'c_D':>12} {'c_L':>12} "
            f"{'dp':>12} {'err c_D':>9} {'err c_L':>9} {'err dp':>9} {'c_D srf':>9} "
            f"{'c_L srf':>9} {'its':>3} {'t_mesh':>7} {'t_solve':>7} {'t_total':>7}"
        )
    families = list(FAMILIES) if args.family == "both" else [args.family]
    rows = []
    for fam in families:
        rows += run(fam, args.max_level, comm)
    if args.csv and comm.rank == 0:
        with open(args.csv, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


if __name__ == "__main__":
    main()
