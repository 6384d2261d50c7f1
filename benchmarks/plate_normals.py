"""Nagata mode on a machined plate: estimated normals against the CAD's exact normals.

The part ``plate_filleted`` of ``meshes/parts.py`` (100 x 60 x 12 mm plate,
4 through-holes r 4, 2 counterbores r 8, a pocket; filleted corners r 8,
pocket corners r 4, pocket floor r 2) is written as STEP and meshed coarsely
by :func:`nagata_snap.meshing.mesh_cad_file` (curvature sizing, 12 elements
per 2 pi; one facet tag per CAD face).  The whole boundary is snapped in
Nagata mode through ``levels`` uniform refinements, with

* ``jet``: the default estimate (:mod:`nagata_snap.nagata.jets`),
* ``mwselr``: Max's weighting (the previous default),
* ``fitted``: :class:`~nagata_snap.FittedGeometry` (degree 4, estimated
  normals) instead of Nagata patches,
* ``cad``: the CAD's exact normals, each facet's on its own face
  (``--cad occ``, the default: the ``CadGeometry`` of
  :func:`nagata_snap.cad.mesh_cad`, the file read by OCP, faces and (u, v)
  from gmsh's mesh; ``--cad gmsh``: OpenCASCADE through gmsh,
  ``gmsh.model.getNormal`` at the vertices' (u, v)),

and plain ``dolfinx.mesh.refine``.  Every boundary vertex of the last level on
a curved face (cylinders, tori, fillets) is measured against that face with
gmsh's ``getClosestPoint`` (OpenCASCADE), as a fraction of the model size.

Last line: ``plate_jet_over_cad <max distance, jet / CAD normals>``.

Usage: ``python benchmarks/plate_normals.py [--levels 2] [--cad occ|gmsh]``
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))

import gmsh
import parts
from occ_reference import GmshFaceNormals, gmsh_curved_faces, gmsh_face_distance

import dolfinx.mesh

from nagata_snap import FittedGeometry, NagataGeometry, Snapper
from nagata_snap.mesh.boundary import boundary_facets
from nagata_snap.cad import mesh_cad
from nagata_snap.meshing import gmsh_session, import_cad, mesh_cad_file


def face_distances(mesh, ft, faces, jump: float | None = None) -> np.ndarray:
    """Distance from its CAD face (gmsh closest point; ``jump``: see ``occ_reference.gmsh_face_distance``)
    of every vertex of the facets tagged with ``faces``."""
    x = mesh.geometry.x
    mesh.topology.create_connectivity(mesh.topology.dim - 1, mesh.topology.dim)
    out = []
    for f in faces:
        nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(f)))
        if len(nodes):
            out.append(gmsh_face_distance(f, x[nodes], jump))
    return np.concatenate(out)


def run(label, cm, normals, levels, faces, size, cls=NagataGeometry):
    t0 = time.perf_counter()
    geo = cls(cm.mesh, cm.facet_tags, normals=normals)
    t_geo = time.perf_counter() - t0
    snapper = Snapper(cm.mesh, cm.facet_tags, geo)
    mesh, ft = cm.mesh, cm.facet_tags
    partial = 0
    for _ in range(levels):
        mesh, ft, _, _, report = snapper.refine(mesh)
        partial += int(report.partially_moved)
    d = face_distances(mesh, ft, faces)
    print(f"{label:>8} {d.max() / size:12.3e} {np.sqrt(np.mean(d**2)) / size:12.3e} {partial:8d} "
          f"{mesh.topology.index_map(3).size_global:10d} {t_geo:8.2f}s", flush=True)
    return d.max()


def plain(cm, levels, faces, size):
    mesh, ft = cm.mesh, cm.facet_tags
    for _ in range(levels):
        mesh.topology.create_entities(1)
        mesh.topology.create_entities(mesh.topology.dim - 1)
        new, pc, pf = dolfinx.mesh.refine(mesh, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)
        new.topology.create_entities(new.topology.dim - 1)
        ft = dolfinx.mesh.transfer_meshtag(ft, new, pc, pf)
        mesh = new
    d = face_distances(mesh, ft, faces)
    print(f"{'plain':>8} {d.max() / size:12.3e} {np.sqrt(np.mean(d**2)) / size:12.3e} {'':>8} "
          f"{mesh.topology.index_map(3).size_global:10d}", flush=True)
    return d.max()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--levels", type=int, default=2)
    ap.add_argument("--cad", choices=("occ", "gmsh"), default="occ")
    ap.add_argument("--curvature", type=float, default=12.0, help="elements per 2 pi of curvature")
    args = ap.parse_args()
    comm = MPI.COMM_WORLD
    if comm.size > 1:
        raise SystemExit("serial benchmark (gmsh evaluates the CAD on one process)")
    with tempfile.TemporaryDirectory() as tmp:
        path = parts.write_part("plate_filleted", tmp, formats=("step",))["step"]
        with gmsh_session("plate"):
            import_cad(path)
            if args.cad == "occ":  # the CAD read by OCP, each facet's face and (u, v) from gmsh's mesh
                cm, cad = mesh_cad(path, comm, curvature=args.curvature)
            else:
                cm = mesh_cad_file(path, comm, curvature=args.curvature)
                cad = GmshFaceNormals(cm)
            faces = gmsh_curved_faces()
            size = cm.model_size
            nb = len(boundary_facets(cm.mesh).facets)
            print(f"plate_filleted: {len(gmsh.model.getEntities(2))} faces ({len(faces)} curved), coarse mesh "
                  f"{cm.mesh.topology.index_map(3).size_global} tetrahedra, {nb} boundary facets, size "
                  f"{cm.size:.2f} mm, model size {size:.1f} mm; {args.levels} uniform levels")
            print(f"{'normals':>8} {'max dist':>12} {'rms dist':>12} {'partial':>8} {'cells':>10} {'geometry':>9}")
            print(f"{'':>8} {'/ size':>12} {'/ size':>12}")
            d = {name: run(name, cm, src, args.levels, faces, size)
                 for name, src in (("jet", None), ("mwselr", "mwselr"), ("cad", cad))}
            d["fitted"] = run("fitted", cm, None, args.levels, faces, size, FittedGeometry)
            d["plain"] = plain(cm, args.levels, faces, size)
    print(f"\njet / cad {d['jet'] / d['cad']:.2f}, mwselr / cad {d['mwselr'] / d['cad']:.2f}, "
          f"plain / jet {d['plain'] / d['jet']:.1f}")
    print(f"fitted (degree 4, estimated normals) / jet {d['fitted'] / d['jet']:.3f}")
    print(f"plate_jet_over_cad {d['jet'] / d['cad']:.3f}")


if __name__ == "__main__":
    main()
