"""Solution transfer to a snapped refined mesh: parent maps against a point search.

For each case a coarse gmsh mesh of the unit disk (2D) or ball (3D) is
refined uniformly once by :class:`nagata_snap.Snapper` (Nagata patches of the
coarse boundary: new boundary vertices move outside their parent cells), and
a P2 vector field ``f`` is interpolated on the coarse mesh and carried to the
refined one, side by side in one run, by

* ``ours``:  :meth:`nagata_snap.Snapper.transfer` (parent-cell map, batched
  pull-back, no search);
* ``nonmatching``: ``dolfinx.fem.create_interpolation_data(V1, V0, cells,
  padding)`` + ``Function.interpolate_nonmatching`` over all cells, which
  searches a bounding-box tree for every interpolation point (``padding``
  1e-8 as in ``demos/dfg.py``; points that lie in no cell get zero).

Each timing is the best of ``--repeat`` runs (max over MPI ranks); an
untimed first call of the transfer warms up (basix elements).  Columns: dofs of the refined P2 vector space,
seconds of both, their ratio, dofs that the point search left at zero (f >= 1
everywhere, so a zero is padding, not a value) and the maximum error against
``f`` at the refined mesh's dof points for both (the parent interpolant's
error, and 1 where a dof was zero-filled), and the number of dofs whose point
lies outside its parent cell.

Cases (refined-mesh P2 vector dofs):  2d-1e5, 2d-1e6, 3d-1e5, 3d-1e6.

Output: one row per case, then the last line
``transfer_speedup_vs_nonmatching <min ratio>``.

Usage:
  python benchmarks/transfer.py [--cases 2d-1e5,3d-1e5] [--repeat 3]
  mpiexec -n 2 python benchmarks/transfer.py
"""

from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

import mpi4py.MPI as MPI

import numpy as np

import dolfinx.fem as fem

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "meshes"))
import generate  # noqa: E402

from nagata_snap import NagataGeometry, Snapper  # noqa: E402

#: case -> (dimension, coarse mesh size h); the refined P2 vector space has about
#: the dofs in the name.
CASES = {
    "2d-1e5": (2, 0.035),
    "2d-1e6": (2, 0.011),
    "3d-1e5": (3, 0.19),
    "3d-1e6": (3, 0.087),
}
PADDING = 1e-8


def field(x: np.ndarray, dim: int) -> np.ndarray:
    """A smooth vector field >= 1 (a zero-filled dof is visible as an error of 1 or more)."""
    base = 2.0 + np.sin(3.0 * x[0]) * np.cos(2.0 * x[1]) + 0.5 * x[dim - 1] ** 2
    return np.stack([base + 0.25 * k for k in range(dim)])


def best_time(comm, fn, repeat: int):
    """Best wall time over ``repeat`` calls (max over ranks) and the last result."""
    out, best = None, math.inf
    for _ in range(repeat):
        comm.barrier()
        t0 = time.perf_counter()
        out = fn()
        best = min(best, comm.allreduce(time.perf_counter() - t0, op=MPI.MAX))
    return best, out


def run_case(comm, name: str, repeat: int) -> dict:
    dim, h = CASES[name]
    if dim == 2:
        md = generate.unit_disk(comm, n=round(2 * math.pi / h), h=h)
        tag = generate.DISK_BOUNDARY
    else:
        md = generate.ball(comm, radius=1.0, h=h)
        tag = generate.BALL_SPHERE
    mesh0, ft0 = md.mesh, md.facet_tags
    snapper = Snapper(mesh0, ft0, NagataGeometry(mesh0, ft0, tags=[tag]), quality_report=False)
    mesh1, *_ = snapper.refine(mesh0)
    el = ("Lagrange", 2, (dim,))
    V0, V1 = fem.functionspace(mesh0, el), fem.functionspace(mesh1, el)
    u0 = fem.Function(V0)
    u0.interpolate(lambda x: field(x, dim))
    exact = fem.Function(V1)
    exact.interpolate(lambda x: field(x, dim))
    cells = np.arange(mesh1.topology.index_map(dim).size_local, dtype=np.int32)

    def nonmatching():
        data = fem.create_interpolation_data(V1, V0, cells, PADDING)
        w = fem.Function(V1)
        w.interpolate_nonmatching(u0, cells, data)
        return w

    snapper.transfer(u0, V1)  # warm-up (basix elements); the point search needs none
    t_ours, (ours, info) = best_time(comm, lambda: snapper.transfer(u0, V1, return_info=True), repeat)
    t_nm, nm = best_time(comm, nonmatching, repeat)
    n_own = V1.dofmap.index_map.size_local * dim

    def stats(w):
        a, e = w.x.array[:n_own], exact.x.array[:n_own]
        return (comm.allreduce(int(np.count_nonzero(a == 0.0))),
                comm.allreduce(float(np.abs(a - e).max(initial=0.0)), op=MPI.MAX))

    (z_ours, e_ours), (z_nm, e_nm) = stats(ours), stats(nm)
    return {"case": name, "dofs": V1.dofmap.index_map.size_global * dim, "ours": t_ours, "nm": t_nm,
            "ratio": t_nm / t_ours, "zeros_ours": z_ours, "zeros_nm": z_nm, "err_ours": e_ours,
            "err_nm": e_nm, "outside": info.outside}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    comm = MPI.COMM_WORLD
    names = [c for c in args.cases.split(",") if c]
    unknown = sorted(set(names) - set(CASES))
    if unknown:
        parser.error(f"unknown cases {unknown}; choose from {list(CASES)}")
    head = (f"{'case':>7} {'dofs':>9} {'ours [s]':>9} {'nonmatch [s]':>12} {'ratio':>6} "
            f"{'zeros ours/nm':>13} {'max err ours':>12} {'max err nm':>10} {'outside':>8}")
    if comm.rank == 0:
        print(f"P2 vector transfer to a snapped refined mesh, {comm.size} process(es), "
              f"best of {args.repeat}", flush=True)
        print(head, flush=True)
    rows = []
    for name in names:
        r = run_case(comm, name, args.repeat)
        rows.append(r)
        if comm.rank == 0:
            print(f"{r['case']:>7} {r['dofs']:9d} {r['ours']:9.3f} {r['nm']:12.3f} "
                  f"{r['ratio']:6.1f} {r['zeros_ours']:>6d}/{r['zeros_nm']:<6d} "
                  f"{r['err_ours']:12.2e} {r['err_nm']:10.2e} {r['outside']:8d}", flush=True)
    if comm.rank == 0:
        print(f"transfer_speedup_vs_nonmatching {min(r['ratio'] for r in rows):.1f}", flush=True)


if __name__ == "__main__":
    main()
