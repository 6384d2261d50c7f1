"""P3 Poisson on a solid torus without CAD: the fitted surface, Nagata patches and straight cells.

Problem: ``-Lap u = f`` in the solid torus ``T`` (axis z, major radius
``R = 1``, minor radius ``r = 0.5``), ``u = 0`` on its surface, with the
manufactured solution

    u(x) = (r^2 - rho^2) (1 + x / 2),     rho^2 = (sqrt(x^2 + y^2) - R)^2 + z^2

(``--solution quadratic``, the default: smooth in and around the torus, zero
on its surface ``rho = r``, its gradient there of size 1) or ``u(x) =
cos(pi rho^2 / (2 r^2)) (1 + x / 2)`` (``--solution cosine``: the same zero
set, steeper, so its P3 discretisation error hides the geometry's); ``f =
-Lap u`` formed by UFL.  As a user who knows the boundary data only on the
true surface would, ``u_h = 0`` is imposed on the boundary of the discrete
domain ``T_h``, so the domain's error enters the solution
(``--boundary-data exact`` imposes ``u``'s own values on ``T_h``'s boundary
instead: then the geometry hardly matters and even straight cells converge at
the P3 order).  The L2 error ``||u - u_h||`` is computed on ``T_h`` with the
exact ``u`` (a UFL expression).

One coarse gmsh mesh of the solid torus per mesh size ``h``
(``meshes/generate.py``, ``MeshSizeMin = MeshSizeMax = h``), as without CAD a
finer surface only comes from a finer coarse mesh; on each, the geometry is
rebuilt from the mesh alone (normals estimated) and the P3 problem solved on

* ``straight``: the gmsh mesh's own affine cells;
* ``Nagata``: ``Snapper.curved_mesh(degree=3)`` with ``NagataGeometry``;
* ``fitted``: the same with ``FittedGeometry(degree=4)``;
* ``CAD``: the same on the exact torus (a NURBS ``CadGeometry``), the
  reference: what is left there is the discretisation's own error.

Also printed: the largest distance of each CAD-free surface from the exact
torus (sampled patches).  Orders are ``log(e_{i-1} / e_i) / log(h_{i-1} /
h_i)`` over the nominal sizes.

Last line: ``poisson_p3_torus_fitted_order <finest-pair order, fitted>``.

Examples::

    python benchmarks/torus_poisson.py
    python benchmarks/torus_poisson.py --h 0.2 0.1 --solution cosine
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import mpi4py.MPI as MPI  # before dolfinx/petsc4py

import numpy as np
import ufl

import dolfinx.fem.petsc
import dolfinx.mesh
from dolfinx import fem

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))
import generate
from surfaces import nagata_surface_error, torus_exact

from nagata_snap import FittedGeometry, NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.nurbs import torus

#: the torus' major and minor radius
R, r = 1.0, 0.5

#: the discretisations compared, in the printed order
KINDS = ("straight", "Nagata", "fitted", "CAD")


def exact(x, solution: str = "quadratic"):
    """The manufactured solution (UFL) at the SpatialCoordinate ``x``: zero on the torus surface."""
    rho2 = (ufl.sqrt(x[0] ** 2 + x[1] ** 2) - R) ** 2 + x[2] ** 2
    if solution == "quadratic":
        return (r**2 - rho2) * (1 + x[0] / 2)
    return ufl.cos(ufl.pi * rho2 / (2 * r**2)) * (1 + x[0] / 2)


def solve_l2_error(mesh: dolfinx.mesh.Mesh, degree: int = 3, prefix: str = "torus_", solution: str = "quadratic",
                   boundary_data: str = "zero") -> tuple[float, int]:
    """``(||u - u_h||_L2(mesh), dofs)``: the P``degree`` solution, ``u_h = 0`` on the exterior boundary
    (``boundary_data="exact"``: ``u_h`` = the interpolant of ``u`` there)."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    V = fem.functionspace(mesh, ("Lagrange", degree))
    dofs = fem.locate_dofs_topological(V, tdim - 1, dolfinx.mesh.exterior_facet_indices(mesh.topology))
    u_ex = exact(ufl.SpatialCoordinate(mesh), solution)
    if boundary_data == "exact":
        g = fem.Function(V)
        g.interpolate(fem.Expression(u_ex, V.element.interpolation_points))
        bc = fem.dirichletbc(g, dofs)
    else:
        bc = fem.dirichletbc(0.0, dofs, V)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    dx = ufl.dx(metadata={"quadrature_degree": 2 * degree + 2})
    problem = dolfinx.fem.petsc.LinearProblem(
        ufl.inner(ufl.grad(u), ufl.grad(v)) * dx, -ufl.div(ufl.grad(u_ex)) * v * dx,
        bcs=[bc], petsc_options_prefix=prefix,
        petsc_options={"ksp_type": "cg", "pc_type": "gamg", "ksp_rtol": 1e-12,
                       "ksp_error_if_not_converged": True})
    uh = problem.solve()
    uh = uh[0] if isinstance(uh, tuple) else uh
    e = fem.assemble_scalar(fem.form((uh - u_ex) ** 2 * dx))
    return float(np.sqrt(mesh.comm.allreduce(e))), V.dofmap.index_map.size_global


def geometries(mesh, ft) -> dict:
    """The two CAD-free surfaces of the torus rebuilt from ``mesh`` (estimated normals), and the exact one."""
    tags = [generate.TORUS_SURFACE]
    return {"Nagata": NagataGeometry(mesh, ft, tags=tags), "fitted": FittedGeometry(mesh, ft, tags=tags, degree=4),
            "CAD": CadGeometry([torus((0.0, 0.0, 0.0), R, r)])}


def run_h(h: float, comm, degree: int = 3, **problem) -> dict:
    """Errors of the discretisations (:data:`KINDS`) on one coarse mesh of size ``h``
    (``problem``: ``solution``, ``boundary_data`` of :func:`solve_l2_error`)."""
    md = generate.solid_torus(comm, major_radius=R, minor_radius=r, h=h)
    mesh, ft = md.mesh, md.facet_tags
    row: dict = {"h": h, "cells": mesh.topology.index_map(3).size_global}
    t0 = time.perf_counter()
    row["straight"], row["dofs"] = solve_l2_error(mesh, degree, "torus_straight_", **problem)
    dist = torus_exact(R, r).distance
    for label, geo in geometries(mesh, ft).items():
        cm, _ = Snapper(mesh, ft, geo, tags=[generate.TORUS_SURFACE]).curved_mesh(degree=degree)
        row[label], _ = solve_l2_error(cm, degree, f"torus_{label}_", **problem)
        if label != "CAD":
            row[f"dist {label}"] = comm.allreduce(
                nagata_surface_error(geo, dist, generate.TORUS_SURFACE, per_edge=8), op=MPI.MAX)
    row["time"] = time.perf_counter() - t0
    return row


def order(rows: list[dict], i: int, key: str) -> float:
    """Observed order of ``key`` between rows ``i - 1`` and ``i``."""
    return float(np.log(rows[i - 1][key] / rows[i][key]) / np.log(rows[i - 1]["h"] / rows[i]["h"]))


def print_table(rows: list[dict], solution: str, boundary_data: str) -> None:
    data = "u = 0" if boundary_data == "zero" else "u's own values"
    print(f"P3 Poisson in the solid torus R = {R}, r = {r}, {solution} solution, {data} on the discrete boundary; "
          "L2 error (order: over the nominal h)")
    head = f"{'h':>6} {'cells':>7} {'dofs':>8}"
    for k in KINDS:
        head += f" | {k:>9} {'ord':>5}"
    print(head + " | fitted/Nagata | dist Nagata  dist fitted | time [s]")
    for i, row in enumerate(rows):
        line = f"{row['h']:6.3f} {row['cells']:7d} {row['dofs']:8d}"
        for k in KINDS:
            line += f" | {row[k]:9.3e} " + (f"{order(rows, i, k):5.2f}" if i else " " * 5)
        line += f" | {row['fitted'] / row['Nagata']:13.3f} | {row['dist Nagata']:11.3e} {row['dist fitted']:12.3e}"
        print(line + f" | {row['time']:8.1f}", flush=True)


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--h", type=float, nargs="+", default=[0.28, 0.2, 0.14, 0.1, 0.07],
                   help="coarse mesh sizes (one gmsh mesh each)")
    p.add_argument("--solution", choices=("quadratic", "cosine"), default="quadratic",
                   help="the manufactured solution (see above)")
    p.add_argument("--boundary-data", choices=("zero", "exact"), default="zero",
                   help="u_h on the discrete boundary: 0 (u's value on the true surface) or u's own values")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    rows = [run_h(h, comm, solution=args.solution, boundary_data=args.boundary_data) for h in args.h]
    if comm.rank == 0:
        print_table(rows, args.solution, args.boundary_data)
        if len(rows) > 1:
            print(f"\npoisson_p3_torus_fitted_order {order(rows, len(rows) - 1, 'fitted'):.3f}")
    return rows


if __name__ == "__main__":
    main()
