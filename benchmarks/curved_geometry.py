"""Area/volume error of snapped straight cells vs curved geometry of degree k = 2, 3, 4.

DFG channel minus the cylinder (IGES circle, exact), the unit ball (NURBS
sphere written to IGES) and a solid torus (NURBS torus: a surface with two
different principal curvatures), uniform refinement; CAD mode so that the
exact geometry is the reference.  Columns: the straight snapped cells, then
``Snapper.curved_mesh(degree=k)`` with its default nodes (equispaced for
k = 2, ``gll_warped`` above) and, to show what the node distribution does,
k = 3 with equispaced nodes.  Prints errors and observed orders.

Without CAD (``--cad-free H ...``): solid tori meshed at each size H, the
surface rebuilt from each coarse mesh (Nagata patches,
:class:`~nagata_snap.FittedGeometry` of degree 3 and 4, estimated normals,
the surfaces a user without a CAD file gets) and ``curved_mesh(degree=k)``
of that coarse mesh measured against the exact torus volume.

The channel's area error is computed where it arises: the area the curving
adds to each cell (curved minus straight, summed with ``math.fsum`` over the
cells it changes) minus the circular segments the straight polygon cuts off,
``R^2 / 2 (theta - sin theta)`` per chord.  Assembling the whole area
(0.894) and subtracting the exact value would stop at a round-off floor of
about 1e-13; this way the orders stay visible to about 1e-17.

Last lines: ``curved_order_ball <k=3 volume order on the finest pair>`` and
``curved_order_torus_fitted <k=4 volume order on the finest pair, fitted p = 4>``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time

import mpi4py.MPI as MPI
import numpy as np
import ufl

import dolfinx.fem as fem
import dolfinx.mesh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))
import generate
import make_iges

from nagata_snap import FittedGeometry, NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.iges import write_iges
from nagata_snap.cad.nurbs import sphere, torus

#: (label, degree, variant) of the curved columns
RUNS = [("k=2", 2, None), ("k=3 equisp.", 3, "equispaced"), ("k=3", 3, None), ("k=4", 4, None)]


def measure(m, degree: int = 1) -> float:
    dx = ufl.dx(domain=m, metadata={"quadrature_degree": 2 * degree})
    return m.comm.allreduce(fem.assemble_scalar(fem.form(fem.Constant(m, 1.0) * dx)))


def cell_measures(m, degree: int) -> np.ndarray:
    """Area / volume of each owned cell (DG0 assembly)."""
    Q = fem.functionspace(m, ("DG", 0))
    dx = ufl.dx(domain=m, metadata={"quadrature_degree": 2 * degree})
    v = fem.assemble_vector(fem.form(ufl.TestFunction(Q) * dx))
    return v.array[: m.topology.index_map(m.topology.dim).size_local].copy()


def segment_area(straight, ft, tag: int, radius: float) -> float:
    """Sum of the circular segments cut off by the straight chords of the facets ``tag``."""
    ent = ft.find(tag)
    ent = ent[ent < straight.topology.index_map(1).size_local]  # owned facets: each once
    g = dolfinx.mesh.entities_to_geometry(straight, 1, ent)
    x = straight.geometry.x
    chord = np.linalg.norm(x[g[:, 1]] - x[g[:, 0]], axis=1)
    theta = 2.0 * np.arcsin(np.minimum(chord / (2.0 * radius), 1.0))
    return straight.comm.allreduce(math.fsum(0.5 * radius**2 * (theta - np.sin(theta))))


def area_error_dfg(straight, curved, ft, degree: int) -> float:
    """|area(curved) - exact| of the DFG channel from per-cell changes (see the docstring)."""
    added = math.fsum(cell_measures(curved, degree) - cell_measures(straight, 1))
    added = curved.comm.allreduce(added)
    return abs(added + segment_area(straight, ft, generate.CYLINDER, generate.DFG_RADIUS))


def study(name, mesh, ft, geo, tag, error, levels, comm):
    """Rows ``(cells, straight error, curved errors...)`` per level, printed as a table."""
    snapper = Snapper(mesh, ft, geo, tags=[tag])
    rows, times = [], np.zeros(len(RUNS))
    for level in range(levels):
        if level:
            mesh, ft, *_ = snapper.refine(mesh)
        row = [mesh.topology.index_map(mesh.topology.dim).size_global, error(mesh, mesh, ft, 1)]
        for j, (_, k, variant) in enumerate(RUNS):
            t0 = time.perf_counter()
            cm, info = snapper.curved_mesh(degree=k, variant=variant)
            times[j] = time.perf_counter() - t0
            if info.reduced_nodes:
                print(f"  ({RUNS[j][0]}: {info.reduced_nodes} nodes pulled back)")
            row.append(error(mesh, cm, ft, k))
        rows.append(row)
    rows = np.array(rows)
    if comm.rank == 0:
        print(f"\n{name}")
        head = f"{'cells':>9} {'straight':>10} {'ord':>5}"
        for label, _, _ in RUNS:
            head += f" | {label:>11} {'ord':>5}"
        print(head)
        for i, r in enumerate(rows):
            line = f"{int(r[0]):9d}"
            for j in range(1, rows.shape[1]):
                o = f"{np.log2(rows[i - 1][j] / r[j]):5.2f}" if i else " " * 5
                line += (" | " if j > 1 else " ") + f"{r[j]:{11 if j > 1 else 10}.3e} {o}"
            print(line)
        print("curve_mesh time on the finest level [s]: " + ", ".join(
            f"{label} {t:.2f}" for (label, _, _), t in zip(RUNS, times, strict=True)))
    return rows


def cad_free_torus(hs: list[float], comm) -> float:
    """The solid torus without CAD, one coarse mesh per ``h``: the geometry is rebuilt from each.

    Refining one coarse mesh converges to the coarse mesh's own surface, so a
    CAD-free surface is measured over coarse meshes of decreasing size:
    volume error of ``curved_mesh(degree=k)`` (k = 2, 3, 4) on the
    coarse mesh itself and the largest distance of the surface (sampled
    patches) from the exact torus, for Nagata patches and the fitted surface
    of degree 3 and 4.  Returns the k = 4 volume order on the finest pair
    with the fitted surface of degree 4.
    """
    from surfaces import nagata_surface_error, torus_exact

    exact = 2 * np.pi**2 * 1.0 * 0.5**2
    dist = torus_exact(1.0, 0.5).distance
    kinds = {"Nagata": lambda m, ft: NagataGeometry(m, ft, tags=[generate.TORUS_SURFACE])}
    for d in (3, 4):
        kinds[f"fitted p={d}"] = lambda m, ft, d=d: FittedGeometry(m, ft, tags=[generate.TORUS_SURFACE], degree=d)
    res: dict[str, list] = {k: [] for k in kinds}
    cells = []
    for h in hs:
        md = generate.solid_torus(comm, major_radius=1.0, minor_radius=0.5, h=h)
        cells.append(md.mesh.topology.index_map(3).size_global)
        for label, make in kinds.items():
            geo = make(md.mesh, md.facet_tags)
            snapper = Snapper(md.mesh, md.facet_tags, geo, tags=[generate.TORUS_SURFACE])
            row = [comm.allreduce(nagata_surface_error(geo, dist, generate.TORUS_SURFACE, per_edge=8), op=MPI.MAX)]
            for k in (2, 3, 4):
                cm, _ = snapper.curved_mesh(degree=k)
                row.append(abs(measure(cm, k) - exact))
            res[label].append(row)
    if comm.rank == 0:
        print("\nsolid torus R = 1, r = 0.5 without CAD: one coarse mesh per h, the surface rebuilt from it; "
              "largest distance of the surface and volume error of curved_mesh(degree=k) on the coarse mesh")
        print(f"{'h':>6} {'cells':>7} {'surface':>14} | {'dist':>9} {'ord':>5} | {'vol k=2':>9} {'ord':>5} | "
              f"{'vol k=3':>9} {'ord':>5} | {'vol k=4':>9} {'ord':>5}")
        for label, rows in res.items():
            for i, r in enumerate(rows):
                line = f"{hs[i]:6.3f} {cells[i]:7d} {label:>14}"
                for j, v in enumerate(r):
                    o = f"{np.log2(rows[i - 1][j] / v):5.2f}" if i else " " * 5
                    line += f" | {v:9.3e} {o}"
                print(line)
    r = res["fitted p=4"]
    return float(np.log2(r[-2][3] / r[-1][3]))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--levels-2d", type=int, default=6, help="levels of the DFG channel")
    p.add_argument("--levels-3d", type=int, default=4, help="levels of the ball")
    p.add_argument("--levels-torus", type=int, default=4, help="levels of the solid torus (0: skip)")
    p.add_argument("--cad-free", type=float, nargs="*", default=[0.4, 0.2, 0.1], metavar="H",
                   help="coarse mesh sizes of the solid torus without CAD (none: skip)")
    p.add_argument("--cad-free-only", action="store_true", help="only the solid torus without CAD")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    if args.cad_free_only:
        order = cad_free_torus(args.cad_free, comm)
        if comm.rank == 0:
            print(f"\ncurved_order_torus_fitted {order:.3f}")
        return
    tmp = tempfile.mkdtemp() if comm.rank == 0 else None
    tmp = comm.bcast(tmp)
    if comm.rank == 0:
        make_iges.write_dfg_circle(tmp)
        write_iges(os.path.join(tmp, "sphere.igs"), surfaces=[sphere((0.0, 0.0, 0.0), 1.0)])
    comm.barrier()
    md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
    study("DFG channel minus cylinder (area error)", md.mesh, md.facet_tags,
          CadGeometry.from_iges(os.path.join(tmp, "dfg_circle.igs")), generate.CYLINDER,
          lambda s, c, ft, k: area_error_dfg(s, c, ft, k), args.levels_2d, comm)
    md = generate.ball(comm, radius=1.0, h=0.5)
    rows = study("unit ball (volume error)", md.mesh, md.facet_tags,
                 CadGeometry.from_iges(os.path.join(tmp, "sphere.igs")), generate.BALL_SPHERE,
                 lambda s, c, ft, k: abs(measure(c, k) - 4 / 3 * np.pi), args.levels_3d, comm)
    if args.levels_torus:
        md = generate.solid_torus(comm, major_radius=1.0, minor_radius=0.5, h=0.3)
        study("solid torus R = 1, r = 0.5 (volume error)", md.mesh, md.facet_tags,
              CadGeometry([torus((0.0, 0.0, 0.0), 1.0, 0.5)]), generate.TORUS_SURFACE,
              lambda s, c, ft, k: abs(measure(c, k) - 2 * np.pi**2 * 1.0 * 0.5**2),
              args.levels_torus, comm)
    order = cad_free_torus(args.cad_free, comm) if len(args.cad_free) > 1 else float("nan")
    if comm.rank == 0:
        print(f"\ncurved_order_ball {np.log2(rows[-2][4] / rows[-1][4]):.3f}")
        print(f"curved_order_torus_fitted {order:.3f}")


if __name__ == "__main__":
    main()
