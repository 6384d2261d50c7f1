"""Bad inputs under MPI: every process must raise the same error class (no hang).

Usage: python bad_input.py CASE [CASE ...]   (under mpiexec -n N or serially)

Each case runs collectively; every process catches its exception, and the
class names and messages of all processes are gathered.  Rank 0 prints one
line ``RESULT {json}`` mapping each case to ``[[class, message], ...]`` (one
entry per rank; ``"OK"`` where a process raised nothing).  A process that
does not raise while another does would wait in a collective call: the
caller's timeout turns that into a failure.

Cases:
  unknown_tag               NagataGeometry(tags=[99])              ValueError
  foreign_mesh              Snapper.refine(another mesh)           LineageError
  interior_tag              snapped tag on interior facets of rank 0 only   ValueError
  nan_on_one_rank           NaN at an interior node of the last rank only   ValueError
  geometry_of_another_mesh  Snapper on a mesh the geometry was not built on ValueError
  cad_far                   IGES circle 10 cm off the DFG cylinder CadError
  cad_mm                    IGES circle in millimetres, mesh in metres      CadError
  cad_curves_for_3d         NURBS curves for a tetrahedral mesh    CadError
  cell_tags                 cell tags passed as facet tags         ValueError
  tags_of_another_mesh      facet tags created on another mesh     ValueError
  stale_mesh                Snapper.refine(the mesh before the last one)    LineageError
  zero_normals              normals array of zeros                 NormalsError
  nan_normals_one_rank      normals callable giving NaN on the last rank only NormalsError
  mesh_moved                mesh moved on rank 0 after the geometry was built ValueError
  quadrilaterals            quadrilateral mesh                     ValueError
  bad_option                Snapper(smoothing="spring")            ValueError
  inverted                  wall normals tilted +-50 deg, no smoothing, no repair InvertedCellsError
  degenerate_cell_one_rank  a zero-area cell on the last rank only  ValueError
  cad_attach_without_nodes  CadGeometry.attach(comm=...) of a solid without nodes ValueError (n > 1 only)
"""

import json
import os
import sys
import tempfile

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
import generate
import make_iges
from robustness_inputs import exterior_tags, flatten_one_cell, wall_tags, wavy

import dolfinx.mesh

from nagata_snap import NagataGeometry, Snapper
from nagata_snap.cad import CadGeometry
from nagata_snap.cad.iges import write_iges
from nagata_snap.cad.nurbs import circle

comm = MPI.COMM_WORLD


_dfg = None


def dfg():
    global _dfg
    if _dfg is None:
        md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
        _dfg = md.mesh, md.facet_tags
    return _dfg


def unknown_tag():
    mesh, ft = dfg()
    NagataGeometry(mesh, ft, tags=[99])


def foreign_mesh():
    mesh, ft = dfg()
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[generate.CYLINDER]))
    snapper.refine(dolfinx.mesh.create_unit_square(comm, 4, 4))


def interior_tag():
    mesh, ft = dfg()
    mesh.topology.create_connectivity(1, 2)
    f2c = mesh.topology.connectivity(1, 2)
    nloc = mesh.topology.index_map(1).size_local
    interior = np.flatnonzero(np.diff(f2c.offsets)[:nloc] == 2)[:3].astype(np.int32)
    if comm.rank != 0:
        interior = interior[:0]
    idx = np.concatenate([ft.indices, interior])
    val = np.concatenate([ft.values, np.full(len(interior), generate.CYLINDER, np.int32)])
    o = np.argsort(idx)
    bad = dolfinx.mesh.meshtags(mesh, 1, idx[o], val[o])
    NagataGeometry(mesh, bad, tags=[generate.CYLINDER])


def nan_on_one_rank():
    mesh = dolfinx.mesh.create_unit_square(comm, 8, 8)
    ft = exterior_tags(mesh)
    geo = NagataGeometry(mesh, ft)
    if comm.rank == comm.size - 1:
        x = mesh.geometry.x
        n = mesh.geometry.index_map().size_local
        inner = np.flatnonzero((np.abs(x[:n, :2] - 0.5) < 0.4).all(axis=1))
        x[inner[:1], 0] = np.nan
    Snapper(mesh, ft, geo)


def geometry_of_another_mesh():
    a = dolfinx.mesh.create_unit_square(comm, 4, 4)
    geo = NagataGeometry(a, exterior_tags(a))
    b = dolfinx.mesh.create_unit_square(comm, 6, 6)
    Snapper(b, exterior_tags(b), geo)


def cad_far():
    mesh, ft = dfg()
    d = comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None)
    path = os.path.join(d, "shifted.igs")
    if comm.rank == 0:
        write_iges(path, curves=[make_iges.circle_curve((0.3, 0.2, 0.0), 0.05)], units="M")
    comm.barrier()
    Snapper(mesh, ft, CadGeometry.from_iges(path), tags=[generate.CYLINDER])


def _circle_file(name, centre, radius, units):
    d = comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None)
    path = os.path.join(d, name)
    if comm.rank == 0:
        write_iges(path, curves=[make_iges.circle_curve(centre, radius)], units=units)
    comm.barrier()
    return path


def cad_mm():
    mesh, ft = dfg()
    path = _circle_file("mm.igs", (200.0, 200.0, 0.0), 50.0, "MM")
    Snapper(mesh, ft, CadGeometry.from_iges(path), tags=[generate.CYLINDER])


def cad_curves_for_3d():
    mesh = dolfinx.mesh.create_unit_cube(comm, 2, 2, 2)
    Snapper(mesh, exterior_tags(mesh), CadGeometry([circle((0.5, 0.5, 0.0), 0.5)]))


def cell_tags():
    mesh = dolfinx.mesh.create_unit_square(comm, 4, 4)
    n = mesh.topology.index_map(2).size_local
    ct = dolfinx.mesh.meshtags(mesh, 2, np.arange(n, dtype=np.int32), np.ones(n, np.int32))
    NagataGeometry(mesh, ct)


def tags_of_another_mesh():
    a = dolfinx.mesh.create_unit_square(comm, 4, 4)
    b = dolfinx.mesh.create_unit_square(comm, 4, 4)
    NagataGeometry(a, exterior_tags(b))


def stale_mesh():
    mesh = dolfinx.mesh.create_unit_square(comm, 4, 4)
    ft = exterior_tags(mesh)
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft))
    snapper.refine(mesh)
    snapper.refine(mesh)  # the coarse mesh again, not the one returned


def zero_normals():
    mesh, ft = dfg()
    NagataGeometry(mesh, ft, tags=[generate.CYLINDER], normals=np.zeros((len(mesh.geometry.x), 2)))


def nan_normals_one_rank():
    mesh, ft = dfg()

    def normals(x):
        n = np.c_[x[:, 0] - 0.2, x[:, 1] - 0.2, 0 * x[:, 0]]
        if comm.rank == comm.size - 1:
            n[:1] = np.nan
        return n

    NagataGeometry(mesh, ft, tags=[generate.CYLINDER], normals=normals)


def mesh_moved():
    mesh = dolfinx.mesh.create_unit_square(comm, 4, 4)
    ft = exterior_tags(mesh)
    geo = NagataGeometry(mesh, ft)
    if comm.rank == 0:
        mesh.geometry.x[:, :2] *= 2.0
    Snapper(mesh, ft, geo)


def quadrilaterals():
    mesh = dolfinx.mesh.create_unit_square(comm, 4, 4, dolfinx.mesh.CellType.quadrilateral)
    NagataGeometry(mesh, exterior_tags(mesh))


def bad_option():
    mesh = dolfinx.mesh.create_unit_square(comm, 4, 4)
    ft = exterior_tags(mesh)
    Snapper(mesh, ft, NagataGeometry(mesh, ft), smoothing="spring")


def inverted():
    mesh = dolfinx.mesh.create_rectangle(comm, [[0.0, 0.0], [1.0, 0.1]], [4, 2])
    ft = wall_tags(mesh)
    geo = NagataGeometry(mesh, ft, tags=[1], normals=wavy(50.0), crease_angle=60.0)
    Snapper(mesh, ft, geo, smoothing="none", repair=False).refine(mesh)


def degenerate_cell_one_rank():
    mesh = dolfinx.mesh.create_unit_square(comm, 8, 8)
    ft = exterior_tags(mesh)
    geo = NagataGeometry(mesh, ft)
    if comm.rank == comm.size - 1:
        flatten_one_cell(mesh)  # an owned cell of zero area, on this process only
    Snapper(mesh, ft, geo)


def cad_attach_without_nodes():
    import parts

    d = comm.bcast(tempfile.mkdtemp() if comm.rank == 0 else None)
    if comm.rank == 0:
        parts.write_part("box_fillet_chamfer", d, ("step",))
    comm.barrier()
    geo = CadGeometry.from_file(os.path.join(d, "box_fillet_chamfer.step"))
    lo, hi = np.array([0.0, 0.0, 30.0]), np.array([60.0, 40.0, 30.0])  # the top face (z = 30)
    facets = (lo + (hi - lo) * np.array([[[0.4, 0.4, 0], [0.6, 0.4, 0], [0.5, 0.6, 0]]]))
    geo.attach(facets, comm=comm)


result = {}
for case in sys.argv[1:]:
    try:
        globals()[case]()
        out = ("OK", "")
    except Exception as e:  # the class is the result
        out = (type(e).__name__, str(e)[:300])
    result[case] = comm.allgather(out)
if comm.rank == 0:
    print("RESULT " + json.dumps(result), flush=True)
