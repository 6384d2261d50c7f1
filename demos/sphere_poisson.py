"""Poisson in the unit ball: uniform refinement with and without snapping.

Problem: -Lap u = f in the unit ball B, u = 0 on the sphere, with the exact
solution

    u(x) = cos(pi r^2 / 2),   r = |x|,
    f(x) = 3 pi sin(pi r^2 / 2) + pi^2 r^2 cos(pi r^2 / 2),

(non-polynomial, so P1 and P2 discretisation errors are both visible).  The
boundary condition u_h = 0 is imposed on the boundary of the discrete domain
B_h, as a user who only knows the data on the true sphere would do.  The
errors ||u - u_h|| in L2(B_h) and the H1 seminorm are computed on B_h with the
exact u (a UFL expression, high-degree quadrature).

Three runs from the same coarse gmsh ball (``meshes/generate.py``):

* ``plain``:  ``dolfinx.mesh.refine`` (uniform): the boundary stays the
  coarse polyhedron, whose distance from the sphere (and so the error of the
  boundary condition) never decreases: the errors stall;
* ``snapped``: ``nagata_snap.Snapper`` with a ``NagataGeometry`` on the
  sphere (estimated vertex normals, or the exact ones with
  ``--exact-normals``; on a sphere Max's estimate is exact, so both give the
  same patches up to round-off): new boundary vertices are placed on the Nagata
  patches of the coarse facets, so the domain converges to (very nearly) the
  ball and the errors keep falling (for P1: L2 order 2, H1 order 1);
* ``curved``: the same snapped levels, solved on ``Snapper.curved_mesh(degree=k)``
  with k = max(2, P) (isoparametric geometry: every node of the boundary
  facets on the geometry).  With P2 or P3 the straight snapped cells limit
  the L2 error to order 2 (the domain error); the curved cells give order
  P + 1.  The Nagata patches are fixed by the coarse
  mesh, so their own (small) distance from the sphere is an error floor; with
  ``--geometry cad`` the sphere is an exact NURBS (``nagata_snap.cad.nurbs.sphere``)
  and there is no floor.

Examples::

    python demos/sphere_poisson.py
    python demos/sphere_poisson.py --degree 2 --levels 3 --json sphere.json
    python demos/sphere_poisson.py --degree 2 --geometry cad
    python demos/sphere_poisson.py --degree 3 --geometry cad --levels 3   # last line: curved_p3_l2_order
    mpiexec -n 2 python demos/sphere_poisson.py
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import mpi4py.MPI as MPI  # must precede dolfinx/petsc4py

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import dolfinx  # noqa: E402
import dolfinx.fem.petsc  # noqa: E402
import dolfinx.mesh  # noqa: E402
import ufl  # noqa: E402
from dolfinx import fem  # noqa: E402

import nagata_snap  # noqa: E402
from meshes import generate  # noqa: E402

RUNS = ("plain", "snapped", "curved")


def exact(x):
    """UFL exact solution and right-hand side at the SpatialCoordinate ``x``."""
    r2 = ufl.inner(x, x)
    s = ufl.pi * r2 / 2
    u = ufl.cos(s)
    f = 3 * ufl.pi * ufl.sin(s) + ufl.pi**2 * r2 * ufl.cos(s)
    return u, f


def solve_poisson(mesh, degree: int, prefix: str) -> tuple[fem.Function, int, float]:
    """P``degree`` solution with u = 0 on the whole exterior boundary."""
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    V = fem.functionspace(mesh, ("Lagrange", degree))
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    bc = fem.dirichletbc(0.0, fem.locate_dofs_topological(V, tdim - 1, facets), V)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    _, f = exact(ufl.SpatialCoordinate(mesh))
    dx = ufl.dx(metadata={"quadrature_degree": degree + 3})
    a = ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
    L = f * v * dx
    problem = dolfinx.fem.petsc.LinearProblem(
        a, L, bcs=[bc], petsc_options_prefix=prefix,
        petsc_options={"ksp_type": "cg", "pc_type": "gamg", "ksp_rtol": 1e-12,
                       "ksp_error_if_not_converged": True},
    )
    t0 = time.perf_counter()
    uh = problem.solve()
    if isinstance(uh, tuple):
        uh = uh[0]
    t = time.perf_counter() - t0
    dofs = V.dofmap.index_map.size_global
    return uh, dofs, t


def errors(uh: fem.Function, degree: int) -> tuple[float, float]:
    """L2 and H1-seminorm errors against the exact solution on the discrete domain."""
    mesh = uh.function_space.mesh
    u, _ = exact(ufl.SpatialCoordinate(mesh))
    dx = ufl.dx(metadata={"quadrature_degree": degree + 4})
    e = u - uh
    l2 = fem.assemble_scalar(fem.form(e * e * dx))
    h1 = fem.assemble_scalar(fem.form(ufl.inner(ufl.grad(e), ufl.grad(e)) * dx))
    comm = mesh.comm
    return float(np.sqrt(comm.allreduce(l2))), float(np.sqrt(comm.allreduce(h1)))


def sphere_distance(mesh) -> float:
    """Largest | |x| - 1 | over the exterior boundary vertices (global)."""
    fdim = mesh.topology.dim - 1
    mesh.topology.create_connectivity(fdim, fdim + 1)
    facets = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    d = 0.0
    if len(facets):
        nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, fdim, facets))
        d = float(np.abs(np.linalg.norm(mesh.geometry.x[nodes], axis=1) - 1.0).max())
    return mesh.comm.allreduce(d, op=MPI.MAX)


def _row(uh, dofs, mesh, level, t_refine, t_solve, degree, prev) -> dict:
    l2, h1 = errors(uh, degree)
    row = {"level": level, "dofs": dofs,
           "cells": mesh.topology.index_map(mesh.topology.dim).size_global,
           "L2": l2, "H1": h1, "sphere_distance": sphere_distance(mesh),
           "time_refine": t_refine, "time_solve": t_solve}
    if prev:
        row["order_L2"] = float(np.log2(prev[-1]["L2"] / l2))
        row["order_H1"] = float(np.log2(prev[-1]["H1"] / h1))
    return row


def _say(kind: str, row: dict, comm, quiet: bool) -> None:
    if comm.rank == 0 and not quiet:
        o = (f"  orders L2 {row['order_L2']:5.2f}  H1 {row['order_H1']:5.2f}"
             if row["level"] else "")
        print(f"[{kind}] level {row['level']}: {row['dofs']:8d} dofs  L2 {row['L2']:.3e}  "
              f"H1 {row['H1']:.3e}{o}  | sphere dist {row['sphere_distance']:.1e} | refine "
              f"{row['time_refine']:.2f}s solve {row['time_solve']:.2f}s", flush=True)


def run(kind: str, args, comm) -> dict[str, list[dict]]:
    """Run ``plain`` or ``snapped`` (the latter also gives the ``curved`` rows)."""
    data = generate.ball(comm, h=args.h)
    mesh, ft = data.mesh, data.facet_tags
    snapper = None
    if kind == "snapped":
        if args.geometry == "cad":
            from nagata_snap.cad import CadGeometry
            from nagata_snap.cad.nurbs import sphere

            geometry = CadGeometry([sphere((0.0, 0.0, 0.0), 1.0)])
            snapper = nagata_snap.Snapper(mesh, ft, geometry, tags=[generate.BALL_SPHERE])
        else:
            normals = (lambda x: x) if args.exact_normals else None
            geometry = nagata_snap.NagataGeometry(mesh, ft, tags=[generate.BALL_SPHERE],
                                                  normals=normals)
            snapper = nagata_snap.Snapper(mesh, ft, geometry)
    rows: dict[str, list[dict]] = {kind: []} if snapper is None else {kind: [], "curved": []}
    for level in range(args.levels + 1):
        t_refine = 0.0
        if level > 0:
            t0 = time.perf_counter()
            if snapper is None:
                mesh.topology.create_entities(1)
                mesh, _, _ = dolfinx.mesh.refine(mesh)
            else:
                mesh, ft, _, _, _ = snapper.refine(mesh)
            t_refine = time.perf_counter() - t0
        uh, dofs, t_solve = solve_poisson(mesh, args.degree, f"ball_{kind}_{level}_")
        row = _row(uh, dofs, mesh, level, t_refine, t_solve, args.degree, rows[kind])
        rows[kind].append(row)
        _say(kind, row, comm, args.quiet)
        if snapper is not None:
            t0 = time.perf_counter()
            curved, _ = snapper.curved_mesh(degree=max(2, args.degree))
            t_curve = time.perf_counter() - t0
            uh, dofs, t_solve = solve_poisson(curved, args.degree, f"ball_curved_{level}_")
            row = _row(uh, dofs, curved, level, t_refine + t_curve, t_solve, args.degree,
                       rows["curved"])
            rows["curved"].append(row)
            _say("curved", row, comm, args.quiet)
    return rows


def table(results: dict) -> str:
    head = f"{'level':>5}"
    for k in RUNS:
        head += f" | {k + ' dofs':>13} {'L2':>9} {'ord':>5} {'H1':>9} {'ord':>5}"
    lines = [head, "-" * len(head)]
    for i in range(len(results[RUNS[0]])):
        s = f"{i:5d}"
        for k in RUNS:
            r = results[k][i]
            o2 = f"{r['order_L2']:5.2f}" if "order_L2" in r else f"{'-':>5}"
            o1 = f"{r['order_H1']:5.2f}" if "order_H1" in r else f"{'-':>5}"
            s += f" | {r['dofs']:13d} {r['L2']:9.2e} {o2} {r['H1']:9.2e} {o1}"
        lines.append(s)
    return "\n".join(lines)


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        prog="sphere_poisson.py",
        description=(
            "Poisson in the unit ball (u = cos(pi r^2/2), u = 0 on the sphere), uniform "
            "refinement with plain dolfinx.mesh.refine, with snapping of the sphere (straight "
            "cells) and on the curved mesh of the snapped levels (geometry of degree max(2, P)); "
            "prints L2 and H1 "
            "errors and observed orders per level for the three runs."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--degree", type=int, choices=(1, 2, 3), default=1,
                   help="Lagrange degree of the solution (the curved run uses geometry of the "
                        "same degree, at least 2)")
    p.add_argument("--levels", type=int, default=3,
                   help="number of uniform refinements (levels+1 solves per run)")
    p.add_argument("--h", type=float, default=0.4, help="mesh size of the coarse gmsh ball")
    p.add_argument("--geometry", choices=("nagata", "cad"), default="nagata",
                   help="snap to Nagata patches of the coarse sphere (no CAD) or to an exact "
                        "NURBS sphere (CAD mode)")
    p.add_argument("--exact-normals", action="store_true",
                   help="build the Nagata patches with the exact sphere normals n(x) = x "
                        "(a callable) instead of estimating them from the coarse mesh; Max's "
                        "weights are exact for vertices on a sphere, so the results agree to "
                        "round-off: this shows the API (Nagata geometry only)")
    p.add_argument("--json", metavar="FILE", help="write the three runs, every level, as JSON")
    p.add_argument("--quiet", action="store_true", help="print only the final table")
    args = p.parse_args(argv)
    if args.levels < 0:
        p.error("--levels must be >= 0")
    if args.h <= 0:
        p.error("--h must be > 0")
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    comm = MPI.COMM_WORLD
    t0 = time.perf_counter()
    if comm.rank == 0 and not args.quiet:
        normals = ("" if args.geometry == "cad"
                   else f", {'exact' if args.exact_normals else 'estimated'} normals")
        print(f"Poisson in the unit ball, P{args.degree}, coarse h = {args.h}, {args.levels} "
              f"uniform refinements, geometry {args.geometry}{normals}, "
              f"{comm.size} MPI process(es)", flush=True)
    results = {**run("plain", args, comm), **run("snapped", args, comm)}
    total = time.perf_counter() - t0
    out = {"config": {"degree": args.degree, "levels": args.levels, "h": args.h,
                      "exact_normals": args.exact_normals,
                      "geometry": args.geometry, "mpi_size": comm.size},
           "runs": results, "total_time": total}
    if comm.rank == 0:
        print("\n" + table(results))
        print(f"total wall time {total:.1f} s on {comm.size} process(es)", flush=True)
        curved = results["curved"]
        if len(curved) > 1:
            print(f"curved_p{args.degree}_l2_order {curved[-1]['order_L2']:.3f}", flush=True)
        if args.json:
            with open(args.json, "w") as fh:
                json.dump(out, fh, indent=1)
    return out


if __name__ == "__main__":
    main()
