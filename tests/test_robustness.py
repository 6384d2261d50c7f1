"""Bad input gets a clear error, and a failed snap loses nothing.

Every bad input below asserts the error TYPE and a message substring that
names the problem.  This module covers 53 distinct bad inputs; with the 25
bad IGES files of ``tests/test_iges.py`` (``BAD``) that makes 78.  Seventeen
of them, and a normals callable that fails on one process only, also run
under ``mpiexec -n 2`` and ``-n 3`` (``tests/mpi/bad_input.py``: every process
must raise the same class, within a timeout).

Mesh and tags (DOLFINx meshes)
   1. tag that does not exist (``NagataGeometry``)             ValueError      (MPI)
   2. tag that does not exist (``Snapper``)                    ValueError
   3. snapped tag on interior facets                           ValueError      (MPI)
   4. cell tags passed as facet tags (geometry and Snapper)    ValueError
   5. facet tags of another mesh                               ValueError
   6. 2D: two triangles touching only at a vertex              NonManifoldError
   7. 3D: two tetrahedra touching only at an edge              NonManifoldError
   8. 2D: zero-length boundary facet                           NormalsError
   9. 3D: zero-area boundary facet                             NormalsError
  10. coincident vertices (duplicate nodes, slit mesh)         ValueError
  11. NaN coordinates at a boundary node                       ValueError
  12. infinite coordinates at an interior node (Snapper)       ValueError      (MPI: one rank)
  12b. a zero-area cell (Snapper)                              ValueError      (MPI: one rank)
  13. quadrilateral cells                                      ValueError
  14. hexahedral cells                                         ValueError
  15. interval cells (1D)                                      ValueError
  16. degree-2 (curved) coordinate element                     ValueError
  17. triangles embedded in 3D (manifold mesh)                 ValueError
Normals (``NagataGeometry(normals=...)``)
  18-21. array: zeros, NaN, wrong shape, ~160 deg apart on neighbouring vertices
  22-25. callable: the same four                       NormalsError / ValueError
CAD geometry
  26. IGES circle shifted by 10 cm against the DFG mesh        CadError
  27. IGES circle in millimetres, mesh in metres               CadError
  28. NURBS curves for a 3D mesh (needs surfaces)              CadError
  29-31. projection of NaN / infinite / 1e300 points           ValueError
         (``global_search`` crashed with an IndexError on 1e300)
Lineage / Snapper
  32. ``Snapper.refine`` given a foreign mesh                  LineageError    (MPI)
  33. ``Snapper.refine`` given a stale (older) mesh            LineageError
  34. Snapper built on another mesh than its geometry          ValueError      (MPI)
  35. mesh moved after the geometry was built                  ValueError
  36. unknown smoothing method                                 ValueError
  37. ``min_fraction`` outside [0, 1]                          ValueError
Surfaces (``NagataGeometry.from_surface``, ``SURFACES``)
  38. open polygon, 39. open triangulated surface              NonManifoldError
  40. vertex index out of range, 41. negative index, 42. non-integer indices,
  43. facets with 4 columns, 44. NaN points, 45. polygon with one reversed
  segment, 46. surface with one inverted triangle, 47./48. polygon/surface
  with a duplicated (coincident) vertex, 49. facet_tags of the wrong length,
  50. normals array of the wrong length, 51. no facets        ValueError
  52. zero-area triangle                                       NormalsError

Not a bad input: two tetrahedra touching at one vertex (a pinch) have a
manifold set of boundary edges; each side keeps its own normals and snaps
on its own (``test_3d_vertex_pinch_is_supported``).

Failure atomicity: when snapping fails (``InvertedCellsError`` from a coarse
mesh with a prescribed wild normal field, with and without smoothing;
``CadError`` at construction or during ``refine``; ``LineageError``), the
mesh passed in and its facet tags are bitwise unchanged and the Snapper is
still usable: its next ``refine`` gives bitwise the result of a fresh
Snapper.

"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import warnings

import basix.ufl
import numpy as np
import pytest
from mpi4py import MPI

import dolfinx.mesh
import generate
import make_iges
from robustness_inputs import exterior_tags, flatten_one_cell, wall_tags, wavy
from surfaces import circle_polygon, sphere_octahedron

from nagata_snap import (
    InvertedCellsError,
    LineageError,
    NagataGeometry,
    NonManifoldError,
    NormalsError,
    Snapper,
)
from nagata_snap.cad import CadError, CadGeometry
from nagata_snap.cad.iges import write_iges
from nagata_snap.cad.nurbs import circle

HERE = os.path.dirname(os.path.abspath(__file__))
COMM = MPI.COMM_WORLD


# ----------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------
def simplex_mesh(cells, x, cell: str | None = None, degree: int = 1):
    """DOLFINx mesh from explicit cells and coordinates (rank 0 holds the data)."""
    x = np.asarray(x, dtype=float)
    cells = np.asarray(cells, dtype=np.int64)
    if cell is None:
        cell = {3: "triangle", 4: "tetrahedron"}[cells.shape[1]]
    el = basix.ufl.element("Lagrange", cell, degree, shape=(x.shape[1],))
    if COMM.rank != 0:
        x, cells = x[:0], cells[:0]
    return dolfinx.mesh.create_mesh(COMM, cells, el, x)


def snapshot(mesh, ft):
    """Bitwise copies of everything of the user's mesh and tags that snapping could touch."""
    return (
        mesh.geometry.x.copy(),
        mesh.geometry.dofmaps[0].copy(),
        np.asarray(mesh.geometry.input_global_indices).copy(),
        ft.indices.copy(),
        ft.values.copy(),
    )


def assert_unchanged(before, mesh, ft):
    after = snapshot(mesh, ft)
    for a, b in zip(before, after, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()


def raises(exc, match, fn, *args, **kwargs):
    """Assert ``fn`` raises exactly the class ``exc`` (or a subclass) with ``match`` in the message."""
    with pytest.raises(exc) as info, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fn(*args, **kwargs)
    assert match in str(info.value), f"{match!r} not in {str(info.value)!r}"
    return info.value


@pytest.fixture(scope="module")
def dfg():
    md = generate.dfg_channel(COMM, n_circle=16, h_far=0.1)
    return md.mesh, md.facet_tags


@pytest.fixture(scope="module")
def square():
    m = dolfinx.mesh.create_unit_square(COMM, 4, 4)
    return m, exterior_tags(m)


# ======================================================================
# mesh and tags
# ======================================================================
def test_unknown_tag(dfg):
    mesh, ft = dfg
    raises(ValueError, "facet tags [99] do not exist", NagataGeometry, mesh, ft, tags=[99])
    geo = NagataGeometry(mesh, ft, tags=[generate.CYLINDER])
    raises(ValueError, "facet tags [99] do not exist", Snapper, mesh, ft, geo, tags=[99])


def test_tags_on_interior_facets(dfg):
    mesh, ft = dfg
    mesh.topology.create_connectivity(1, 2)
    f2c = mesh.topology.connectivity(1, 2)
    nloc = mesh.topology.index_map(1).size_local
    interior = np.flatnonzero(np.diff(f2c.offsets)[:nloc] == 2)[:3].astype(np.int32)
    idx = np.concatenate([ft.indices, interior])
    val = np.concatenate([ft.values, np.full(len(interior), generate.CYLINDER, np.int32)])
    o = np.argsort(idx)
    bad = dolfinx.mesh.meshtags(mesh, 1, idx[o], val[o])
    raises(ValueError, "interior facets", NagataGeometry, mesh, bad, tags=[generate.CYLINDER])


def test_cell_tags_passed_as_facet_tags(square):
    mesh, ft = square
    ncell = mesh.topology.index_map(2).size_local
    ct = dolfinx.mesh.meshtags(mesh, 2, np.arange(ncell, dtype=np.int32), np.ones(ncell, np.int32))
    raises(ValueError, "cell tags passed as facet tags", NagataGeometry, mesh, ct)
    geo = NagataGeometry(mesh, ft)
    raises(ValueError, "cell tags passed as facet tags", Snapper, mesh, ct, geo, tags=[1])


def test_facet_tags_of_another_mesh(square):
    _, ft = square
    other = dolfinx.mesh.create_unit_square(COMM, 4, 4)
    raises(ValueError, "belong to another mesh", NagataGeometry, other, ft)


def test_non_manifold_2d_vertex():
    # two triangles touching only at the origin: 4 boundary facets meet there
    mesh = simplex_mesh([[0, 1, 2], [0, 3, 4]], [[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]])
    e = raises(NonManifoldError, "shared by [4] boundary facets", NagataGeometry, mesh, exterior_tags(mesh))
    assert "touching only at a vertex" in str(e) and "[0.0, 0.0, 0.0]" in str(e)


def test_non_manifold_3d_edge():
    # two tetrahedra sharing only the edge (0, 0, 0)-(1, 0, 0)
    x = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1]]
    mesh = simplex_mesh([[0, 1, 2, 3], [0, 1, 4, 5]], x)
    e = raises(NonManifoldError, "edges are shared by [4] boundary facets", NagataGeometry, mesh,
               exterior_tags(mesh))
    assert "touching only at an edge" in str(e)


def test_3d_vertex_pinch_is_supported():
    """Not a bad input: two tetrahedra touching at a vertex have a manifold set of
    boundary edges; each side of the pinch gets its own normals and snaps on its own."""
    x = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]]
    mesh = simplex_mesh([[0, 1, 2, 3], [0, 4, 5, 6]], x)
    ft = exterior_tags(mesh)
    r = Snapper(mesh, ft, NagataGeometry(mesh, ft), smoothing="none").refine(mesh)
    assert np.all(np.isfinite(r.mesh.geometry.x))


def test_zero_length_facet_2d():
    mesh = simplex_mesh([[0, 1, 2]], [[0, 0], [1, 0], [1, 0]])
    e = raises(NormalsError, "zero area", NagataGeometry, mesh, exterior_tags(mesh))
    assert "[1.0, 0.0, 0.0]" in str(e)


def test_zero_area_facet_3d():
    # the facet (0, 1, 2) is a straight line
    mesh = simplex_mesh([[0, 1, 2, 3], [1, 2, 3, 4]], [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 1]])
    raises(NormalsError, "boundary facets have zero area", NagataGeometry, mesh, exterior_tags(mesh))


def test_coincident_vertices():
    # unit square as two triangles whose diagonal vertices are duplicated: a slit
    # (or an unmerged mesh) whose two sides would be snapped independently
    mesh = simplex_mesh([[0, 1, 2], [3, 4, 5]], [[0, 0], [1, 0], [1, 1], [0, 0], [1, 1], [0, 1]])
    e = raises(ValueError, "coincident vertices", NagataGeometry, mesh, exterior_tags(mesh))
    assert "merge duplicate nodes" in str(e)


def test_degenerate_cell():
    # an interior vertex moved onto the opposite edge of one of its triangles
    mesh = dolfinx.mesh.create_unit_square(COMM, 4, 4)
    ft = exterior_tags(mesh)
    geo = NagataGeometry(mesh, ft)
    flatten_one_cell(mesh)
    raises(ValueError, "degenerate cells", Snapper, mesh, ft, geo)


def test_nan_boundary_coordinates():
    mesh = dolfinx.mesh.create_unit_square(COMM, 3, 3)
    ft = exterior_tags(mesh)
    x = mesh.geometry.x
    x[np.flatnonzero(np.abs(x[:, 1]) < 1e-12)[:1], 0] = np.nan
    raises(ValueError, "NaN or infinite coordinates", NagataGeometry, mesh, ft)


def test_inf_interior_coordinates():
    mesh = dolfinx.mesh.create_unit_square(COMM, 3, 3)
    ft = exterior_tags(mesh)
    geo = NagataGeometry(mesh, ft)
    x = mesh.geometry.x
    inner = np.flatnonzero((np.abs(x[:, :2] - 0.5) < 0.4).all(axis=1))
    x[inner[:1], 1] = np.inf
    # an interior node is not seen by the geometry, but the Snapper refuses the mesh
    # (before this check, refine failed much later with a misleading LineageError)
    raises(ValueError, "NaN or infinite coordinates", Snapper, mesh, ft, geo)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: dolfinx.mesh.create_unit_square(COMM, 2, 2, dolfinx.mesh.CellType.quadrilateral),
         "got quadrilateral cells"),
        (lambda: dolfinx.mesh.create_unit_cube(COMM, 1, 1, 1, dolfinx.mesh.CellType.hexahedron),
         "got hexahedron cells"),
        (lambda: dolfinx.mesh.create_unit_interval(COMM, 4), "got interval cells"),
        (lambda: simplex_mesh([[0, 1, 2, 3, 4, 5]], [[0, 0], [1, 0], [0, 1], [0.5, 0.5], [0, 0.5], [0.5, 0]],
                              "triangle", degree=2),
         "coordinate degree 1"),
        (lambda: simplex_mesh([[0, 1, 2], [1, 3, 2]], [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1]]),
         "manifold meshes are not supported"),
    ],
    ids=["quadrilateral", "hexahedron", "interval", "degree2", "manifold"],
)
def test_unsupported_meshes(make, match):
    mesh = make()
    ft = exterior_tags(mesh)
    raises(ValueError, match, NagataGeometry, mesh, ft)
    cad = CadGeometry([circle((0.5, 0.5, 0.0), 0.5)])
    raises(ValueError, match, Snapper, mesh, ft, cad)


# ======================================================================
# normals
# ======================================================================
@pytest.fixture(scope="module")
def disk():
    md = generate.unit_disk(COMM, n=12)
    return md.mesh, md.facet_tags


def radial(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def wild_normals(x, deg=75.0, n=12):
    """Radial normals tilted by +deg / -deg on alternate vertices of the n-gon:
    neighbouring vertices' normals are 2 deg + 360/n apart."""
    t = np.arctan2(x[:, 1], x[:, 0])
    s = np.where(np.round(t / (2 * np.pi / n)) % 2 == 0, 1.0, -1.0)
    a = t + s * np.radians(deg)
    return np.c_[np.cos(a), np.sin(a), 0 * a]


@pytest.mark.parametrize(
    "normals, exc, match",
    [
        ("zeros", NormalsError, "zero, NaN or infinite"),
        ("nan", NormalsError, "zero, NaN or infinite"),
        ("shape", ValueError, "normals array must have shape"),
        ("opposite", NormalsError, "degrees apart"),
    ],
)
def test_bad_normal_arrays(disk, normals, exc, match):
    mesh, ft = disk
    x = mesh.geometry.x
    arr = {
        "zeros": lambda: np.zeros((len(x), 2)),
        "nan": lambda: np.where(np.arange(len(x))[:, None] == 3, np.nan, radial(x[:, :2])),
        "shape": lambda: radial(x[:, :2])[:5],
        "opposite": lambda: wild_normals(x)[:, :2],
    }[normals]()
    raises(exc, match, NagataGeometry, mesh, ft, normals=arr, crease_angle=89.0)


@pytest.mark.parametrize(
    "fn, exc, match",
    [
        (lambda x: np.zeros_like(x), NormalsError, "zero, NaN or infinite"),
        (lambda x: np.full_like(x, np.nan), NormalsError, "zero, NaN or infinite"),
        (lambda x: x[:, :1], ValueError, "normals callable returned shape"),
        (wild_normals, NormalsError, "degrees apart (opposite normals on neighbouring vertices)"),
    ],
    ids=["zeros", "nan", "shape", "opposite"],
)
def test_bad_normal_callables(disk, fn, exc, match):
    mesh, ft = disk
    raises(exc, match, NagataGeometry, mesh, ft, normals=fn, crease_angle=89.0)


def test_flipped_normals_are_not_an_error(disk):
    """Orientation is free (README): a sign flip on some vertices gives the same patches."""
    mesh, ft = disk
    x = mesh.geometry.x
    n = radial(x[:, :2])
    flip = np.where(np.arange(len(x)) % 2, -1.0, 1.0)[:, None]
    a = NagataGeometry(mesh, ft, normals=n * flip)
    b = NagataGeometry(mesh, ft, normals=n)
    np.testing.assert_array_equal(a.coef, b.coef)


# ======================================================================
# CAD geometry
# ======================================================================
def write_circle(path, centre, radius, units):
    if COMM.rank == 0:
        write_iges(path, curves=[make_iges.circle_curve(centre, radius)], units=units)
    COMM.barrier()
    return CadGeometry.from_iges(path)


def test_cad_far_from_mesh(dfg, tmp_path_factory):
    mesh, ft = dfg
    before = snapshot(mesh, ft)
    path = str(tmp_path_factory.mktemp("iges") / "shifted.igs")
    cad = write_circle(path, (0.3, 0.2, 0.0), 0.05, "M")  # 10 cm off the DFG cylinder
    e = raises(CadError, "do not lie on the CAD geometry", Snapper, mesh, ft, cad, tags=[generate.CYLINDER])
    assert "no facet lies on it" in str(e) and "placement" in str(e)
    assert_unchanged(before, mesh, ft)


def test_cad_wrong_units(dfg, tmp_path_factory):
    mesh, ft = dfg
    path = str(tmp_path_factory.mktemp("iges") / "mm.igs")
    cad = write_circle(path, (200.0, 200.0, 0.0), 50.0, "MM")
    e = raises(CadError, "wrong file, units or placement", Snapper, mesh, ft, cad, tags=[generate.CYLINDER])
    assert "CAD box [150.0, 150.0, 0.0]" in str(e)


def test_cad_curves_for_a_3d_mesh():
    mesh = dolfinx.mesh.create_unit_cube(COMM, 2, 2, 2)
    ft = exterior_tags(mesh)
    cad = CadGeometry([circle((0.5, 0.5, 0.0), 0.5)])
    raises(CadError, "need surfaces", Snapper, mesh, ft, cad)


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1e300], ids=["nan", "inf", "1e300"])
@pytest.mark.parametrize("how", ["global_search", "project_newton"])
def test_projection_of_non_finite_points(bad, how):
    # 1e300 used to crash global_search with an IndexError deep inside (the KD-tree
    # query overflows and returns "no neighbour")
    from nagata_snap.cad.projection import global_search, project_newton

    ent = circle((0.0, 0.0, 0.0), 1.0)
    X = np.array([[1.0, 0.0, 0.0], [bad, 0.0, 0.0]])
    fn = (lambda: global_search(ent, X)) if how == "global_search" else (lambda: project_newton(ent, X, [0.1, 0.2]))
    raises(ValueError, "points must be finite and at most 1e+100 in magnitude", fn)


# ======================================================================
# lineage and Snapper arguments
# ======================================================================
def test_refine_foreign_and_stale_mesh(square):
    mesh, ft = square
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft))
    other = dolfinx.mesh.create_unit_square(COMM, 4, 4)
    raises(LineageError, "expects the mesh it returned last", snapper.refine, other)
    m1 = snapper.refine(mesh).mesh
    raises(LineageError, "expects the mesh it returned last", snapper.refine, mesh)  # stale
    snapper.refine(m1)


def test_snapper_on_another_mesh_than_its_geometry(square):
    mesh, ft = square
    geo = NagataGeometry(mesh, ft)
    other = dolfinx.mesh.create_unit_square(COMM, 5, 5)
    raises(ValueError, "mesh this NagataGeometry was built on", Snapper, other, exterior_tags(other), geo)


def test_mesh_moved_after_geometry_was_built():
    mesh = dolfinx.mesh.create_unit_square(COMM, 3, 3)
    ft = exterior_tags(mesh)
    geo = NagataGeometry(mesh, ft)
    mesh.geometry.x[:, :2] *= 2.0
    raises(ValueError, "differ from the mesh this NagataGeometry was built on", Snapper, mesh, ft, geo)


def test_bad_snapper_options(square):
    mesh, ft = square
    geo = NagataGeometry(mesh, ft)
    raises(ValueError, "smoothing must be", Snapper, mesh, ft, geo, smoothing="spring")
    raises(ValueError, "min_fraction must be in [0, 1]", Snapper, mesh, ft, geo, min_fraction=2.0)


def _run_script(code: str, timeout=120):
    r = subprocess.run([sys.executable, "-c", code], cwd=os.path.dirname(HERE), capture_output=True,
                       text=True, timeout=timeout)
    return r.returncode, r.stdout + r.stderr


@pytest.mark.parametrize("edges", ["[-1]", "[10**6]"])
def test_refine_edges_out_of_range(edges):
    code = (
        "import mpi4py.MPI as MPI, numpy as np, dolfinx.mesh as dm\n"
        "from nagata_snap import NagataGeometry, Snapper\n"
        "m = dm.create_unit_square(MPI.COMM_WORLD, 3, 3)\n"
        "m.topology.create_connectivity(1, 2)\n"
        "f = dm.exterior_facet_indices(m.topology)\n"
        "ft = dm.meshtags(m, 1, f, np.ones(len(f), np.int32))\n"
        "s = Snapper(m, ft, NagataGeometry(m, ft))\n"
        "try:\n"
        f"    s.refine(m, np.array({edges}, dtype=np.int32))\n"
        "except ValueError as e:\n"
        "    print('ValueError:', e)\n"
    )
    rc, out = _run_script(code)
    assert rc == 0 and "ValueError:" in out and "edge" in out, out[-2000:]


def test_interior_facet_tags_survive_refine(dfg):
    """Nothing is lost: a tag on interior facets (not snapped) is kept by refine,
    as by dolfinx.mesh.transfer_meshtag."""
    mesh, ft = dfg
    mesh.topology.create_connectivity(1, 2)
    f2c = mesh.topology.connectivity(1, 2)
    nloc = mesh.topology.index_map(1).size_local
    interior = np.flatnonzero(np.diff(f2c.offsets)[:nloc] == 2)[:5].astype(np.int32)
    idx = np.concatenate([ft.indices, interior])
    val = np.concatenate([ft.values, np.full(len(interior), 7, np.int32)])
    o = np.argsort(idx)
    ft7 = dolfinx.mesh.meshtags(mesh, 1, idx[o], val[o])
    r = Snapper(mesh, ft7, NagataGeometry(mesh, ft7, tags=[generate.CYLINDER])).refine(mesh)
    n7 = COMM.allreduce(int(np.count_nonzero(r.facet_tags.values == 7)))
    assert n7 == 2 * COMM.allreduce(len(interior))  # every tagged interior edge is bisected


# ======================================================================
# surfaces (NagataGeometry.from_surface)
# ======================================================================
POLY, SEG, _ = circle_polygon(8)
SPH, TRI, _ = sphere_octahedron(1)


def _flip_one(t):
    t = t.copy()
    t[0] = t[0, ::-1]
    return t


def _duplicate_vertex(p, t):
    """Give one corner of the first facet its own copy of its vertex."""
    t = t.copy()
    p = np.concatenate([p, p[t[0, 0]][None]])
    t[0, 0] = len(p) - 1
    return p, t


def _zero_area(p, t):
    p = p.copy()
    p[t[0, 2]] = 0.5 * (p[t[0, 0]] + p[t[0, 1]])
    return p, t


SURFACES = [
    ("open_polygon", lambda: (POLY, SEG[:-1]), {}, NonManifoldError, "or an open surface"),
    ("open_surface", lambda: (SPH, TRI[:-1]), {}, NonManifoldError, "or an open surface"),
    ("index_out_of_range", lambda: (POLY, np.where(SEG == 7, 8, SEG)), {}, ValueError,
     "indices are outside 0..7"),
    ("negative_index", lambda: (POLY, np.where(SEG == 7, -1, SEG)), {}, ValueError, "indices are outside"),
    ("float_indices", lambda: (SPH, TRI + 0.5), {}, ValueError, "integer vertex indices"),
    ("four_columns", lambda: (SPH, np.c_[TRI, TRI[:, 0]]), {}, ValueError, "facets must have shape"),
    ("nan_points", lambda: (np.where(np.arange(8)[:, None] == 3, np.nan, POLY), SEG), {}, ValueError,
     "NaN or infinite coordinates"),
    ("reversed_segment", lambda: (POLY, _flip_one(SEG)), {}, ValueError, "not consistently oriented"),
    ("inverted_triangle", lambda: (SPH, _flip_one(TRI)), {}, ValueError, "not consistently oriented"),
    ("duplicate_vertex_polygon", lambda: _duplicate_vertex(POLY, SEG), {}, ValueError, "coincident vertices"),
    ("duplicate_vertex_surface", lambda: _duplicate_vertex(SPH, TRI), {}, ValueError, "coincident vertices"),
    ("zero_area_triangle", lambda: _zero_area(SPH, TRI), {}, NormalsError, "zero area"),
    ("tags_length", lambda: (POLY, SEG), {"facet_tags": [1, 2]}, ValueError, "facet_tags must have shape (8,)"),
    ("normals_rows", lambda: (POLY, SEG), {"normals": np.ones((3, 2))}, ValueError,
     "normals array must have shape"),
    ("empty", lambda: (np.zeros((0, 2)), np.zeros((0, 2), int)), {}, ValueError, "F >= 1"),
]


@pytest.mark.parametrize("make, kw, exc, match", [s[1:] for s in SURFACES], ids=[s[0] for s in SURFACES])
def test_bad_surfaces(make, kw, exc, match):
    p, t = make()
    raises(exc, match, NagataGeometry.from_surface, p, t, **kw)


def test_valid_surfaces_still_accepted():
    NagataGeometry.from_surface(POLY, SEG)
    NagataGeometry.from_surface(SPH, TRI)
    NagataGeometry.from_surface(SPH, TRI, normals=SPH)


# ======================================================================
# failure atomicity
# ======================================================================
@pytest.fixture
def channel():
    """[0, 1] x [0, 0.04], 4 x 2 cells: the wall y = 0 (tag 1) is 0.25 per edge, cells 0.02 high."""
    mesh = dolfinx.mesh.create_rectangle(COMM, [[0.0, 0.0], [1.0, 0.04]], [4, 2])
    return mesh, wall_tags(mesh)


# wall normals 100 and 110 deg apart: the bulge (about 0.09, 4 cell heights) inverts cells
# even after smoothing; normals more than 111 deg apart no longer bulge more (nagata.B_MAX)
INVERTING = [
    ("no_smoothing", 50.0, 60.0, {"repair": False, "smoothing": "none"}),
    ("smoothing_and_repair", 55.0, 80.0, {"min_fraction": 1.0}),
]


def top_edges(mesh):
    """Edges in the top half of the channel (refining them does not touch the wall)."""
    mesh.topology.create_entities(1)
    nloc = mesh.topology.index_map(1).size_local
    mid = dolfinx.mesh.compute_midpoints(mesh, 1, np.arange(nloc, dtype=np.int32))
    return np.flatnonzero(mid[:, 1] > 0.024).astype(np.int32)


@pytest.mark.parametrize("deg, crease, kw", [c[1:] for c in INVERTING], ids=[c[0] for c in INVERTING])
def test_inverted_cells_leave_everything_unchanged(channel, deg, crease, kw):
    mesh, ft = channel
    before = snapshot(mesh, ft)
    geo = NagataGeometry(mesh, ft, tags=[1], normals=wavy(deg), crease_angle=crease)
    snapper = Snapper(mesh, ft, geo, **kw)
    assert_unchanged(before, mesh, ft)
    e1 = raises(InvertedCellsError, "inverted", snapper.refine, mesh)
    assert e1.count > 0 and len(e1.cells) > 0
    assert_unchanged(before, mesh, ft)
    assert snapper.level == 0 and snapper.mesh is mesh
    # the state did not advance: the same call fails the same way ...
    e2 = raises(InvertedCellsError, "inverted", snapper.refine, mesh)
    assert str(e2) == str(e1)
    assert_unchanged(before, mesh, ft)
    # ... and a refinement away from the wall gives exactly what a fresh Snapper gives
    edges = top_edges(mesh)
    r = snapper.refine(mesh, edges)
    fresh = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[1], normals=wavy(deg), crease_angle=crease), **kw)
    r0 = fresh.refine(mesh, edges)
    assert snapper.level == 1 and snapper.mesh is r.mesh
    assert r.mesh.geometry.x.tobytes() == r0.mesh.geometry.x.tobytes()
    assert r.facet_tags.values.tobytes() == r0.facet_tags.values.tobytes()
    assert_unchanged(before, mesh, ft)


class FailingOnce:
    """A CAD geometry (a ``SnapGeometry``) whose first ``place`` reports every point unresolved."""

    def __init__(self, geo):
        self.geo = geo
        self.tags = geo.tags
        self.calls = 0

    def attach(self, *args, **kwargs):
        return self.geo.attach(*args, **kwargs)

    def project(self, records, points):
        return self.geo.project(records, points)

    def evaluate(self, root, params):
        return self.geo.evaluate(root, params)

    def place(self, records, straight):
        pts, rec, rep = self.geo.place(records, straight)
        self.calls += 1
        if self.calls == 1:
            rep = dataclasses.replace(rep, n_unresolved=int(pts.shape[0] * pts.shape[1]))
        return pts, rec, rep


def test_cad_error_during_refine_leaves_everything_unchanged(dfg, tmp_path):
    mesh, ft = dfg
    before = snapshot(mesh, ft)
    path = make_iges.write_dfg_circle(tmp_path)
    geo = FailingOnce(CadGeometry.from_iges(path))
    snapper = Snapper(mesh, ft, geo, tags=[generate.CYLINDER])
    raises(CadError, "no acceptable projection", snapper.refine, mesh)
    assert_unchanged(before, mesh, ft)
    assert snapper.level == 0 and snapper.mesh is mesh
    r = snapper.refine(mesh)
    r0 = Snapper(mesh, ft, CadGeometry.from_iges(path), tags=[generate.CYLINDER]).refine(mesh)
    assert r.mesh.geometry.x.tobytes() == r0.mesh.geometry.x.tobytes()
    assert snapper.level == 1
    assert_unchanged(before, mesh, ft)


def test_lineage_error_leaves_snapper_usable(square):
    mesh, ft = square
    before = snapshot(mesh, ft)
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft))
    raises(LineageError, "expects the mesh it returned last", snapper.refine,
           dolfinx.mesh.create_unit_square(COMM, 4, 4))
    assert snapper.level == 0 and snapper.mesh is mesh
    r = snapper.refine(mesh)
    r0 = Snapper(mesh, ft, NagataGeometry(mesh, ft)).refine(mesh)
    assert r.mesh.geometry.x.tobytes() == r0.mesh.geometry.x.tobytes()
    assert_unchanged(before, mesh, ft)


def test_failed_construction_leaves_mesh_unchanged(disk):
    mesh, ft = disk
    before = snapshot(mesh, ft)
    raises(NormalsError, "degrees apart", NagataGeometry, mesh, ft, normals=wild_normals, crease_angle=89.0)
    raises(ValueError, "do not exist", NagataGeometry, mesh, ft, tags=[42])
    assert_unchanged(before, mesh, ft)


# ======================================================================
# MPI: every process raises the same error class, no hang
# ======================================================================
MPI_CASES = {
    "unknown_tag": "ValueError",
    "foreign_mesh": "LineageError",
    "interior_tag": "ValueError",
    "nan_on_one_rank": "ValueError",
    "geometry_of_another_mesh": "ValueError",
    "cad_far": "CadError",
    "cad_mm": "CadError",
    "cad_curves_for_3d": "CadError",
    "cell_tags": "ValueError",
    "tags_of_another_mesh": "ValueError",
    "stale_mesh": "LineageError",
    "zero_normals": "NormalsError",
    "nan_normals_one_rank": "NormalsError",
    "mesh_moved": "ValueError",
    "quadrilaterals": "ValueError",
    "bad_option": "ValueError",
    "inverted": "InvertedCellsError",
    "degenerate_cell_one_rank": "ValueError",
}


def run_bad_input(n: int, cases: dict) -> dict:
    exe = [os.path.join(os.path.dirname(sys.executable), "mpiexec"), "-n", str(n)] if n > 1 else []
    cmd = [*exe, sys.executable, os.path.join(HERE, "mpi", "bad_input.py"), *cases]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    except subprocess.TimeoutExpired as e:  # a process waiting for the others: a hang
        pytest.fail(f"mpiexec -n {n} bad_input.py hung (timeout): {e.stdout!r} {e.stderr!r}")
    assert r.returncode == 0, r.stdout + r.stderr
    line = [s for s in r.stdout.splitlines() if s.startswith("RESULT ")]
    assert line, r.stdout + r.stderr
    return json.loads(line[-1][len("RESULT "):])


def check_bad_input_result(res: dict, cases: dict, n: int):
    for case, expected in cases.items():
        names = [c for c, _ in res[case]]
        assert names == [expected] * n, (case, res[case])
        assert all(m for _, m in res[case]), (case, res[case])


@pytest.mark.mpi
def test_cad_attach_over_processes_needs_input_global_ids():
    """Without ``nodes`` the vertex ids of different processes would be compared as if global."""
    res = run_bad_input(2, {"cad_attach_without_nodes": "ValueError"})["cad_attach_without_nodes"]
    assert [c for c, _ in res] == ["ValueError"] * 2, res
    assert all("needs nodes" in m for _, m in res), res
    serial = run_bad_input(1, {"cad_attach_without_nodes": "OK"})["cad_attach_without_nodes"]
    assert serial == [["OK", ""]], serial  # one process: local ids are the ids


def test_bad_input_script_serial():
    check_bad_input_result(run_bad_input(1, MPI_CASES), MPI_CASES, 1)


@pytest.mark.mpi
@pytest.mark.parametrize("n", [2, 3])
def test_bad_input_mpi_all_ranks_raise_the_same_error(n):
    check_bad_input_result(run_bad_input(n, MPI_CASES), MPI_CASES, n)
