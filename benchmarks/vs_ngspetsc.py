"""nagata_snap against ngsPETSc's geometry-aware refinement (Netgen) on the same mesh.

ngsPETSc (``ngsPETSc.utils.fenicsx.GeometricModel``) refines a DOLFINx mesh by
refining the Netgen mesh it came from, whose new boundary points Netgen puts
on the OpenCASCADE geometry, and then rebuilds a new DOLFINx mesh from it (no
``parent_cell``/``parent_facet``, tags rebuilt).  nagata_snap refines the
DOLFINx mesh with ``dolfinx.mesh.refine`` and snaps the new boundary vertices
(parent maps kept).

Geometry (``--dim 2``): the DFG 2D-1 channel 2.2 x 0.41 minus the disk of
radius 0.05 at (0.2, 0.2); (``--dim 3``): the box [-1, 1]^3 minus the ball of
radius 0.5; built with ``netgen.occ`` and meshed by ngsPETSc (``model_to_mesh``,
``--hmax``).  Both tools start from that DOLFINx mesh and refine every cell
``--levels`` times.  nagata_snap snaps the circle / sphere to an exact NURBS
(CAD mode, ``nagata_snap.cad.nurbs.circle`` / ``sphere``) with its default
smoothing and checks.  Printed per level: cells, wall time of each tool's
refinement step (ngsPETSc: ``refineMarkedElements``; nagata_snap:
``Snapper.refine``; for scale, plain ``create_entities(1)`` + ``dolfinx.mesh.refine``,
and ``over`` = (``Snapper.refine`` - plain) / plain), their ratio,
and the largest distance of the circle's boundary vertices from the exact
circle.

Curved part (``--degrees``, default 2 3 4): on every level, ngsPETSc's
``GeometricModel.curveField(k)`` (Netgen curves its elements on the
OpenCASCADE geometry and DOLFINx nodes are sampled from them) against
``Snapper.curved_mesh(degree=k)``: wall time, the largest distance of all
boundary nodes (vertices, edge and face nodes) from the exact circle /
sphere, and the area / volume error of the domain.

Last lines: ``snap_over_refine <over on the finest level>`` and
``speedup_vs_ngspetsc <time ratio of the refinement on the finest level>``.

Needs ngsPETSc, which is not a dependency of nagata_snap (its petsc4py
requirement would build PETSc from source; the DOLFINx wheel brings its own)::

    python3.12 -m venv /work/venvs/ngs     # a venv of its own: netgen brings its own OpenCASCADE
    /work/venvs/ngs/bin/pip install dolfinx-solver-real scipy numba meshio netgen-mesher packaging
    /work/venvs/ngs/bin/pip install --no-deps ngsPETSc
    PYTHONPATH=$PWD /work/venvs/ngs/bin/python benchmarks/vs_ngspetsc.py [--dim 3]
    python docs/results.py --only vs_ngspetsc --python vs_ngspetsc=/work/venvs/ngs/bin/python

Serial only (the comparison is of the refinement step itself).
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time

import mpi4py.MPI as MPI
import numpy as np

import dolfinx.mesh

from nagata_snap import Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.nurbs import circle, sphere

CURVED, FLAT = 4, 3
#: dim -> (centre, radius) of the curved boundary
CASES = {2: (np.array([0.2, 0.2]), 0.05), 3: (np.zeros(3), 0.5)}


def curved_distance(mesh) -> float:
    """Max | |x - c| - R | over the exterior facets' nodes within 0.2 R of the circle / sphere
    (all geometry nodes of the facets: vertices, and edge / face nodes of curved meshes)."""
    tdim = mesh.topology.dim
    c, r = CASES[tdim]
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ext = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    x = mesh.geometry.x[np.unique(dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, ext))]
    d = np.abs(np.linalg.norm(x[:, :tdim] - c, axis=1) - r)
    return float(d[d < 0.2 * r].max())


def domain_error(mesh) -> float:
    """|area / volume - exact| of the channel minus the disk / box minus the ball."""
    import ufl

    import dolfinx.fem as fem

    tdim = mesh.topology.dim
    _, r = CASES[tdim]
    exact = 2.2 * 0.41 - np.pi * r**2 if tdim == 2 else 8.0 - 4.0 / 3.0 * np.pi * r**3
    k = mesh.geometry.cmaps[0].degree
    dx = ufl.dx(domain=mesh, metadata={"quadrature_degree": 2 * k})
    return abs(fem.assemble_scalar(fem.form(fem.Constant(mesh, 1.0) * dx)) - exact)


def curved_tags(mesh) -> dolfinx.mesh.MeshTags:
    """Facet tags: CURVED on the exterior facets near the circle / sphere, FLAT on the others."""
    tdim = mesh.topology.dim
    c, r = CASES[tdim]
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ext = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim - 1, ext)
    near = np.linalg.norm(mid[:, :tdim] - c, axis=1) < 1.5 * r
    return dolfinx.mesh.meshtags(mesh, tdim - 1, ext, np.where(near, CURVED, FLAT).astype(np.int32))


def curve_both(model, snapper, degrees, level: int) -> list[str]:
    """Table lines: ngsPETSc ``curveField(k)`` and ``Snapper.curved_mesh(degree=k)`` side by side."""
    lines = []
    for deg in degrees:
        t0 = time.perf_counter()
        c_ng = model.curveField(deg)
        t_ng = time.perf_counter() - t0
        t0 = time.perf_counter()
        c_ours, info = snapper.curved_mesh(degree=deg)
        t_ours = time.perf_counter() - t0
        lines.append(f"{level:>5} {deg:>2} {t_ng:>13.3f} {t_ours:>9.3f} {t_ng / t_ours:>8.1f} "
                     f"{curved_distance(c_ng):>9.1e} {curved_distance(c_ours):>9.1e} "
                     f"{domain_error(c_ng):>9.1e} {domain_error(c_ours):>9.1e}"
                     + (f"  ({info.reduced_nodes} nodes pulled back)" if info.reduced_nodes else ""))
    return lines


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dim", type=int, choices=(2, 3), default=2)
    p.add_argument("--hmax", type=float, help="Netgen mesh size of the coarse mesh "
                   "(default 0.02 in 2D, 0.15 in 3D)")
    p.add_argument("--levels", type=int, help="uniform refinements (default 4 in 2D, 2 in 3D)")
    p.add_argument("--degrees", type=int, nargs="*", default=[2, 3, 4],
                   help="geometry degrees of the curved comparison (none: skip it)")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    if comm.size > 1:
        sys.exit("vs_ngspetsc.py runs serially")
    try:
        import netgen.occ as occ
        from ngsPETSc.utils.fenicsx import GeometricModel
    except ImportError as exc:
        sys.exit(f"ngsPETSc / netgen not installed ({exc}); see the docstring of this script")

    d = args.dim
    hmax = args.hmax or (0.02 if d == 2 else 0.15)
    levels = args.levels if args.levels is not None else (4 if d == 2 else 2)
    c, r = CASES[d]
    if d == 2:
        shape = occ.Rectangle(2.2, 0.41).Face() - occ.Circle(occ.Pnt(c[0], c[1]), r).Face()
        nurbs = circle((c[0], c[1], 0.0), r)
    else:
        shape = occ.Box(occ.Pnt(-1, -1, -1), occ.Pnt(1, 1, 1)) - occ.Sphere(occ.Pnt(0, 0, 0), r)
        nurbs = sphere((0.0, 0.0, 0.0), r)
    model = GeometricModel(occ.OCCGeometry(shape, dim=d), comm)
    t0 = time.perf_counter()
    ng_mesh, _, _ = model.model_to_mesh(hmax=hmax, gdim=d)
    print(f"coarse Netgen mesh (hmax {hmax}): {ng_mesh.topology.index_map(d).size_global} "
          f"cells, {time.perf_counter() - t0:.2f} s")
    # the same coarse mesh for nagata_snap (a copy: ngsPETSc keeps its own)
    ours = dolfinx.mesh.create_mesh(
        comm, ng_mesh.geometry.dofmaps[0].astype(np.int64),
        ng_mesh.ufl_domain().ufl_coordinate_element(), ng_mesh.geometry.x[:, :d].copy())
    snapper = Snapper(ours, curved_tags(ours), CadGeometry([nurbs]), tags=[CURVED])
    plain = ours

    print(f"{'level':>5} {'cells ng':>9} {'cells ours':>10} {'ngsPETSc [s]':>13} {'ours [s]':>9} "
          f"{'plain [s]':>9} {'over':>6} {'ng/ours':>8} {'dist ng':>9} {'dist ours':>9}")
    ratio = over = float("nan")
    curved_rows = [curve_both(model, snapper, args.degrees, 0)]
    for k in range(1, levels + 1):
        cells = np.arange(ng_mesh.topology.index_map(d).size_local, dtype=np.int32)
        t0 = time.perf_counter()
        ng_mesh, _ = model.refineMarkedElements(d, cells)
        t_ng = time.perf_counter() - t0

        t0 = time.perf_counter()
        ours, _, _, _, report = snapper.refine(ours)
        t_ours = time.perf_counter() - t0

        t0 = time.perf_counter()  # a plain loop needs the edges too (Snapper.refine makes them)
        plain.topology.create_entities(1)
        plain = dolfinx.mesh.refine(plain)[0]
        t_plain = time.perf_counter() - t0

        ratio, over = t_ng / t_ours, (t_ours - t_plain) / t_plain
        print(f"{k:>5} {ng_mesh.topology.index_map(d).size_global:>9} "
              f"{ours.topology.index_map(d).size_global:>10} {t_ng:>13.3f} {t_ours:>9.3f} "
              f"{t_plain:>9.3f} {over:>6.2f} {ratio:>8.1f} {curved_distance(ng_mesh):>9.1e} "
              f"{curved_distance(ours):>9.1e}", flush=True)
        curved_rows.append(curve_both(model, snapper, args.degrees, k))
    print("(ngsPETSc rebuilds the mesh: no parent_cell / parent_facet; nagata_snap returns "
          "DOLFINx's own)")
    if levels:
        print("Snapper.refine on the finest level, seconds per stage: "
              + ", ".join(f"{k} {v:.3f}" for k, v in report.times.items()))
    if args.degrees:
        print("\ncurved geometry: ngsPETSc curveField(k) vs Snapper.curved_mesh(degree=k) on "
              "the same meshes; dist = max distance of the boundary nodes from the exact "
              f"{'circle' if d == 2 else 'sphere'}, err = {'area' if d == 2 else 'volume'} error")
        print(f"{'level':>5} {'k':>2} {'ngsPETSc [s]':>13} {'ours [s]':>9} {'ng/ours':>8} "
              f"{'dist ng':>9} {'dist ours':>9} {'err ng':>9} {'err ours':>9}")
        for line in itertools.chain(*curved_rows):
            print(line)
    print(f"snap_over_refine {over:.3f}")
    print(f"speedup_vs_ngspetsc {ratio:.1f}")


if __name__ == "__main__":
    main()
