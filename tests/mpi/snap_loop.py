"""Snapping loop driver used by the MPI tests.

Usage: python snap_loop.py CASE LEVELS {uniform|adaptive} OUT.npz,
CASE one of dfg, sphere, dfg_iges, cylinder_iges, dfg_fitted, sphere_fitted.
Rank 0 writes, for every level, the gathered coordinates of all geometry
nodes (owned nodes only, so each node once) and of the boundary vertices to OUT.npz.
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import generate
import make_iges

import dolfinx.mesh

from nagata_snap import FittedGeometry, NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.iges import write_iges
from nagata_snap.cad.nurbs import cylinder

comm = MPI.COMM_WORLD
case, levels, mode, out = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
outdir = os.path.dirname(os.path.abspath(out))
if case.startswith("dfg"):
    md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
    centre, tag = np.array([0.2, 0.2, 0.0]), generate.CYLINDER
elif case.startswith("sphere"):
    md = generate.sphere_in_box(comm, h_sphere=0.35, h_box=0.6)
    centre, tag = np.zeros(3), generate.SPHERE
else:
    md = generate.cylinder_in_box(comm, h_cylinder=0.03, h_box=0.15)
    centre, tag = np.array([*generate.KADIR_CYL_CENTER, 0.2]), generate.CIB_CYLINDER
mesh, ft = md.mesh, md.facet_tags
if case == "dfg":
    geometry = NagataGeometry(mesh, ft)
elif case == "sphere":
    geometry = NagataGeometry(mesh, ft, tags=[tag])
elif case == "dfg_fitted":
    geometry = FittedGeometry(mesh, ft)
elif case == "sphere_fitted":
    geometry = FittedGeometry(mesh, ft, tags=[tag])
elif case == "dfg_iges":
    path = os.path.join(outdir, "dfg_circle.igs")
    if comm.rank == 0:
        make_iges.write_dfg_circle(outdir)
    comm.barrier()
    geometry = CadGeometry.from_iges(path)
else:  # exact NURBS cylinder of Kadir's geometry, written by our IGES writer
    path = os.path.join(outdir, "cylinder.igs")
    if comm.rank == 0:
        write_iges(path, surfaces=[cylinder((*generate.KADIR_CYL_CENTER, 0.0), generate.KADIR_CYL_RADIUS, 0.4)])
    comm.barrier()
    geometry = CadGeometry.from_iges(path)
snapper = Snapper(mesh, ft, geometry, tags=[tag])
result = {}
for k in range(levels):
    edges = None
    if mode == "adaptive":
        tdim = mesh.topology.dim
        mid = dolfinx.mesh.compute_midpoints(
            mesh, tdim, np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
        )
        cells = np.flatnonzero(np.linalg.norm(mid - centre, axis=1) < (0.8 if case.startswith("sphere") else 0.15))
        mesh.topology.create_connectivity(tdim, 1)
        edges = dolfinx.mesh.compute_incident_entities(mesh.topology, cells.astype(np.int32), tdim, 1)
    mesh0, ft0 = mesh, ft
    mesh, ft, pc, pf, rep = snapper.refine(mesh, edges)
    if comm.size == 1:  # transfer_meshtag aborts (double free) under mpiexec in DOLFINx 0.11
        # the tags found without facet entities are DOLFINx's own transfer
        ref = dolfinx.mesh.transfer_meshtag(ft0, mesh, pc, pf)
        pairs = [set(zip(t.indices.tolist(), t.values.tolist(), strict=True)) for t in (ft, ref)]
        if pairs[0] != pairs[1]:
            raise AssertionError(f"facet tags differ from transfer_meshtag at level {k + 1}")
    # tagged facets (owned ones, so each once): midpoint and tag, and measure per tag
    fdim = mesh.topology.dim - 1
    own = ft.indices < mesh.topology.index_map(fdim).size_local
    fx = mesh.geometry.x[dolfinx.mesh.entities_to_geometry(mesh, fdim, ft.indices[own])]
    meas = (np.linalg.norm(fx[:, 1] - fx[:, 0], axis=1) if fdim == 1 else
            0.5 * np.linalg.norm(np.cross(fx[:, 1] - fx[:, 0], fx[:, 2] - fx[:, 0]), axis=1))
    vals = np.unique(np.concatenate(comm.allgather(ft.values)))
    area = np.array([comm.allreduce(float(meas[ft.values[own] == v].sum())) for v in vals])
    tm = comm.gather(np.column_stack([fx.mean(axis=1), ft.values[own]]), root=0)
    snapped = np.unique(dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(tag)))
    ss = comm.gather(mesh.geometry.x[snapped], root=0)
    n = mesh.geometry.index_map().size_local
    xs = comm.gather(mesh.geometry.x[:n], root=0)
    ext = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    bnodes = dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ext).ravel()
    bs = comm.gather(mesh.geometry.x[bnodes], root=0)
    if comm.rank == 0:
        result[f"level{k + 1}"] = np.concatenate(xs)
        result[f"boundary{k + 1}"] = np.unique(np.concatenate(bs), axis=0)
        result[f"snapped{k + 1}"] = np.unique(np.concatenate(ss), axis=0)
        result[f"tagmid{k + 1}"] = np.concatenate(tm)
        result[f"tagarea{k + 1}"] = np.column_stack([vals, area])
        result[f"iterations{k + 1}"] = np.asarray(rep.geometry.iterations_histogram)
if comm.rank == 0:
    np.savez(out, **result)
    print("done", comm.size, flush=True)
