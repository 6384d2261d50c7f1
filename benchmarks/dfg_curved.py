"""DFG 2D-1 drag on curved geometry: P2/P1 on degree-2 cells next to P3/P2 on degree-3 cells.

The adaptive loop of ``demos/flow_past_cylinder.py``'s ``iges`` run (coarse
16-gon cylinder, IGES circle, Taylor-Hood P2/P1 on the straight snapped cells
warm-started from the previous level, residual indicator, Doerfler marking
with theta = 0.5) makes the meshes, so they are those of the demo's ``iges``
and ``iges-p2`` columns.  On every level the flow is also solved on
``Snapper.curved_mesh(degree=2)`` with P2/P1 (the demo's ``iges-p2``) and on
``Snapper.curved_mesh(degree=3)`` with P3/P2 (both Newton from zero: the first
step is the Stokes solve).  Printed per level: dofs and relative c_D error
(volume form) of the three solves, and the time of the P3/P2 solve.  Last
line: ``dfg_p3_cd_error <relative c_D error of P3/P2 on degree-3 cells, finest level>``.

Examples::

    python benchmarks/dfg_curved.py
    python benchmarks/dfg_curved.py --levels 6
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import mpi4py.MPI as MPI

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

from demos.dfg import CYLINDER, dorfler_mark, ns_residual_indicator, solve_dfg  # noqa: E402
from meshes import generate, make_iges  # noqa: E402
from nagata_snap import Snapper  # noqa: E402
from nagata_snap.cad import CadGeometry  # noqa: E402


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--levels", type=int, default=10, help="adaptive refinements")
    p.add_argument("--theta", type=float, default=0.5, help="Doerfler fraction")
    p.add_argument("--n-circle", type=int, default=16, help="segments of the coarse cylinder")
    p.add_argument("--h-far", type=float, default=0.04, help="coarse mesh size away from the cylinder")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    tmp = comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None)
    if comm.rank == 0:
        make_iges.write_dfg_circle(tmp)
    comm.barrier()
    data = generate.dfg_channel(comm, n_circle=args.n_circle, h_far=args.h_far)
    mesh, ft = data.mesh, data.facet_tags
    snapper = Snapper(mesh, ft, CadGeometry.from_iges(os.path.join(tmp, "dfg_circle.igs"), dim=2),
                      tags=[CYLINDER])
    if comm.rank == 0:
        print(f"{'level':>5} | {'straight P2/P1':^19} | {'degree-2 cells, P2/P1':^21} | "
              f"{'degree-3 cells, P3/P2':^30}")
        print(f"{'':>5} | {'dofs':>8} {'err c_D':>10} | {'dofs':>8} {'err c_D':>12} | "
              f"{'dofs':>8} {'err c_D':>12} {'time [s]':>8}", flush=True)
    rows, u_prev = [], None
    for level in range(args.levels + 1):
        straight = solve_dfg(mesh, ft, initial_guess=u_prev)
        c2, _ = snapper.curved_mesh(degree=2)
        p2 = solve_dfg(c2, ft)
        t0 = time.perf_counter()
        c3, info = snapper.curved_mesh(degree=3)
        p3 = solve_dfg(c3, ft, degree=(3, 2))
        t3 = time.perf_counter() - t0
        row = {"level": level, "straight": (straight.dofs, straight.err_c_D),
               "p2": (p2.dofs, p2.err_c_D), "p3": (p3.dofs, p3.err_c_D, t3),
               "reduced_nodes": info.reduced_nodes}
        rows.append(row)
        if comm.rank == 0:
            print(f"{level:5d} | {straight.dofs:8d} {straight.err_c_D:10.2e} | {p2.dofs:8d} "
                  f"{p2.err_c_D:12.3e} | {p3.dofs:8d} {p3.err_c_D:12.3e} {t3:8.1f}", flush=True)
        if level < args.levels:
            eta = ns_residual_indicator(straight.u, straight.p, ft)
            edges = dorfler_mark(mesh, eta, args.theta)
            u_prev = straight.u
            mesh, ft, *_ = snapper.refine(mesh, edges)
    if comm.rank == 0:
        print(f"dfg_p3_cd_error {rows[-1]['p3'][1]:.3e}")
    return rows


if __name__ == "__main__":
    main()
