"""Snapping loops on the DFG 2D-1 channel and a sphere in a box, against exact geometry."""

import os
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI
from scipy.spatial import cKDTree

import dolfinx.mesh
import generate
from surfaces import nagata_surface_error

from nagata_snap import CadGeometry, LineageError, NagataGeometry, Snapper
from nagata_snap.cad.nurbs import circle
from nagata_snap.geometry import SnapGeometry

HERE = os.path.dirname(__file__)
CENTRE = np.array([0.2, 0.2, 0.0])
R = generate.DFG_RADIUS


def facet_vertices(mesh, ft, tag):
    nodes = dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(tag))
    return mesh.geometry.x[np.unique(nodes)]


def measure(mesh):
    tdim = mesh.topology.dim
    x = mesh.geometry.x
    cells = mesh.geometry.dofmaps[0][: mesh.topology.index_map(tdim).size_local]
    e = x[cells][:, 1:, :tdim] - x[cells][:, :1, :tdim]
    return mesh.comm.allreduce(np.abs(np.linalg.det(e)).sum() / (2 if tdim == 2 else 6))


@pytest.fixture(scope="module")
def dfg():
    md = generate.dfg_channel(MPI.COMM_WORLD, n_circle=16, h_far=0.1)
    return md.mesh, md.facet_tags


def circle_dist(x):
    return np.abs(np.linalg.norm(x[..., :2] - CENTRE[:2], axis=-1) - R)


@pytest.mark.parametrize("mode", ["uniform", "adaptive"])
def test_dfg_cylinder_converges_to_circle(dfg, mode):
    mesh, ft = dfg
    geo = NagataGeometry(mesh, ft)  # all tags snapped: walls must stay exactly straight
    e_nagata = nagata_surface_error(geo, circle_dist, generate.CYLINDER)
    n = 16
    # exact normals on a circle of N equal segments: R (2 pi / N)^4 / 128 (seeds/README)
    assert e_nagata == pytest.approx(R * (2 * np.pi / n) ** 4 / 128, rel=0.05)
    snapper = Snapper(mesh, ft, geo)
    plain = mesh
    exact_area = generate.DFG_LENGTH * generate.DFG_HEIGHT - np.pi * R**2
    area_err = []
    for _ in range(5 if mode == "uniform" else 4):
        edges = None
        if mode == "adaptive":
            mid = dolfinx.mesh.compute_midpoints(
                mesh, 2, np.arange(mesh.topology.index_map(2).size_local, dtype=np.int32)
            )
            cells = np.flatnonzero(np.linalg.norm(mid - CENTRE, axis=1) < 0.1).astype(np.int32)
            mesh.topology.create_connectivity(2, 1)
            edges = dolfinx.mesh.compute_incident_entities(mesh.topology, cells, 2, 1)
        mesh, ft, _, _, rep = snapper.refine(mesh, edges)
        assert rep.inverted_after_smoothing == 0 and rep.partially_moved == 0
        cyl = facet_vertices(mesh, ft, generate.CYLINDER)
        assert circle_dist(cyl).max() <= e_nagata * (1 + 1e-9)
        walls = facet_vertices(mesh, ft, generate.WALLS)
        assert np.min(np.abs(walls[:, 1:2] - [0.0, generate.DFG_HEIGHT]), axis=1).max() <= 1e-14
        for t, xv in ((generate.INLET, 0.0), (generate.OUTLET, generate.DFG_LENGTH)):
            assert np.abs(facet_vertices(mesh, ft, t)[:, 0] - xv).max() <= 1e-14
        area_err.append(abs(measure(mesh) - exact_area))
        if mode == "uniform":
            plain.topology.create_entities(1)
            plain = dolfinx.mesh.refine(plain)[0]
    if mode == "uniform":
        # plain refinement keeps the 16-gon: its new circle vertices sit at the polygon's error
        poly = 0.5 * n * R**2 * np.sin(2 * np.pi / n)
        assert measure(plain) == pytest.approx(generate.DFG_LENGTH * generate.DFG_HEIGHT - poly, rel=1e-12)
        plain.topology.create_connectivity(1, 2)
        ext = dolfinx.mesh.exterior_facet_indices(plain.topology)
        xb = plain.geometry.x[np.unique(dolfinx.mesh.entities_to_geometry(plain, 1, ext))]
        xb = xb[circle_dist(xb) < 0.1 * R]  # boundary vertices of the 16-gon
        assert circle_dist(xb).max() == pytest.approx(R * (1 - np.cos(np.pi / n)), rel=1e-6)
        # the snapped area converges to within the Nagata curve's deviation from the
        # circle (perimeter x max error), far below the stalled polygon's area error
        plain_err = abs(measure(plain) - exact_area)
        assert area_err[0] > area_err[1] > area_err[2]
        assert area_err[-1] <= 2 * np.pi * R * e_nagata
        assert area_err[-1] < plain_err / 50


def test_sphere_in_box_converges_and_box_stays_flat():
    md = generate.sphere_in_box(MPI.COMM_WORLD, h_sphere=0.3, h_box=0.6)
    mesh, ft = md.mesh, md.facet_tags
    geo = NagataGeometry(mesh, ft)  # box faces snapped too: must stay flat, edges sharp

    def dist(x):
        return np.abs(np.linalg.norm(x, axis=-1) - 0.5)

    e_nagata = nagata_surface_error(geo, dist, generate.SPHERE)
    snapper = Snapper(mesh, ft, geo)
    exact = 8.0 - 4 / 3 * np.pi * 0.5**3
    errs = []
    for _ in range(2):
        mesh, ft, _, _, rep = snapper.refine(mesh)
        assert rep.inverted_after_smoothing == 0 and rep.partially_moved == 0
        assert dist(facet_vertices(mesh, ft, generate.SPHERE)).max() <= e_nagata * (1 + 1e-9)
        box = facet_vertices(mesh, ft, generate.BOX)
        assert np.abs(np.abs(box).max(axis=1) - 1.0).max() <= 1e-14
        errs.append(abs(measure(mesh) - exact))
    assert errs[1] < errs[0] / 3.5


def test_refine_rejects_foreign_mesh(dfg):
    mesh, ft = dfg
    snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[generate.CYLINDER]))
    other = generate.dfg_channel(MPI.COMM_WORLD, n_circle=16, h_far=0.1).mesh
    with pytest.raises(LineageError, match="expects the mesh it returned last"):
        snapper.refine(other)
    m1 = snapper.refine(mesh).mesh
    with pytest.raises(LineageError):
        snapper.refine(mesh)  # the coarse mesh is no longer the current level
    snapper.refine(m1)


def test_stage_names_the_running_stage(dfg):
    """Snapper.stage is the stage refine is in while it runs (the CLI's heartbeat reads it)."""
    mesh, ft = dfg
    geo = NagataGeometry(mesh, ft, tags=[generate.CYLINDER])
    snapper = Snapper(mesh, ft, geo)
    seen, place = [], geo.place

    def spy(*args):
        seen.append(snapper.stage)
        return place(*args)

    geo.place = spy
    assert snapper.stage is None
    report = snapper.refine(mesh).report
    assert seen == ["place"] and snapper.stage is None
    assert {"refine", "lineage", "place", "smooth+check", "tags"} <= set(report.times)


def test_unknown_and_interior_tags(dfg):
    mesh, ft = dfg
    with pytest.raises(ValueError, match=r"facet tags \[99\] do not exist"):
        NagataGeometry(mesh, ft, tags=[99])
    # tag an interior facet with the snapped tag
    mesh.topology.create_connectivity(1, 2)
    f2c = mesh.topology.connectivity(1, 2)
    interior = np.flatnonzero(np.diff(f2c.offsets) == 2)[:3].astype(np.int32)
    idx = np.concatenate([ft.indices, interior])
    val = np.concatenate([ft.values, np.full(3, generate.CYLINDER, np.int32)])
    o = np.argsort(idx)
    bad = dolfinx.mesh.meshtags(mesh, 1, idx[o], val[o])
    with pytest.raises(ValueError, match="interior facets"):
        NagataGeometry(mesh, bad, tags=[generate.CYLINDER])
    # the Snapper runs the same check (one check_snap_input for every entry point)
    geo = NagataGeometry(mesh, ft, tags=[generate.CYLINDER])
    with pytest.raises(ValueError, match=r"3 facets with snapped tags .* are interior facets"):
        Snapper(mesh, bad, geo)
    # tags on interior facets that are not snapped are fine (interfaces, kept by refine)
    assert Snapper(mesh, bad, geo, tags=[generate.WALLS]).tags == [generate.WALLS]


def test_both_geometries_are_snap_geometries(dfg):
    """NagataGeometry and CadGeometry offer what the snapper uses (mypy checks the
    signatures, in nagata_snap.cli); an object without ``project`` is not one."""
    mesh, ft = dfg
    cad = CadGeometry([circle((0.2, 0.2, 0.0), R)])
    for geo in (NagataGeometry(mesh, ft, tags=[generate.CYLINDER]), cad):
        assert isinstance(geo, SnapGeometry)

    class NoProject:
        tags = None

        def attach(self, points, nodes=None, *, comm=None): ...
        def place(self, records, straight): ...
        def evaluate(self, root, params): ...

    assert not isinstance(NoProject(), SnapGeometry)


def _run_mpi(n, args, tmp_path):
    out = tmp_path / f"np{n}.npz"
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    cmd = [mpiexec, "-n", str(n), sys.executable, os.path.join(HERE, "mpi", "snap_loop.py"), *args, str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return np.load(out)


@pytest.mark.mpi
@pytest.mark.parametrize(
    "case, levels, mode, nprocs",
    [("dfg", 3, "uniform", (2, 3)), ("dfg", 3, "adaptive", (2,)), ("sphere", 2, "uniform", (2,))],
)
def test_mpi_matches_serial(case, levels, mode, nprocs, tmp_path):
    """Vertices get the same coordinates under mpiexec -n 2/3 as in serial (1e-12).

    In 3D, DOLFINx's own tetrahedron refinement picks each cell's interior
    diagonal by a tie-break on global vertex indices, which depend on the
    partition (plain ``refine`` shows the same, without any snapping), so the
    interior vertices and the smoothing that follows differ between partitions;
    in 3D only the boundary vertices, which snapping places, are compared.
    """
    serial = _run_mpi(1, [case, str(levels), mode], tmp_path)
    for n in nprocs:
        par = _run_mpi(n, [case, str(levels), mode], tmp_path)
        for k in range(1, levels + 1):
            keys = [f"boundary{k}"] + ([f"level{k}"] if case == "dfg" else [])
            for key in keys:
                a, b = serial[key], par[key]
                assert a.shape == b.shape, key
                d, i = cKDTree(a).query(b)
                assert d.max() <= 1e-12, key
                assert len(np.unique(i)) == len(a)  # a bijection
            # facet tags: the same measure per tag value; in 2D the same tagged facets
            a, b = serial[f"tagarea{k}"], par[f"tagarea{k}"]
            assert np.array_equal(a[:, 0], b[:, 0])
            assert np.allclose(a[:, 1], b[:, 1], rtol=1e-12, atol=0)
            if case == "dfg":
                a, b = serial[f"tagmid{k}"], par[f"tagmid{k}"]
                assert a.shape == b.shape
                d, i = cKDTree(a[:, :3]).query(b[:, :3])
                assert d.max() <= 1e-12 and np.array_equal(a[i, 3], b[:, 3])


def test_quality_report_scopes(dfg):
    mesh, ft = dfg
    geo = NagataGeometry(mesh, ft, tags=[generate.CYLINDER])
    runs = {q: Snapper(mesh, ft, geo, quality_report=q).refine(mesh) for q in (True, "all", False)}
    a, b = runs[True].report.quality, runs["all"].report.quality
    assert runs[False].report.quality is None
    assert np.array_equal(runs[True].mesh.geometry.x, runs["all"].mesh.geometry.x)
    assert (a.scope, b.scope) == ("changed", "all")
    assert a.n_cells_mesh == b.n_cells == b.n_cells_mesh
    assert 0 < a.n_cells < b.n_cells / 4  # only the cells around the cylinder (coarse mesh)
    assert (a.n_moved, a.max_displacement, a.n_inverted_before, a.n_inverted_after) == (
        b.n_moved, b.max_displacement, b.n_inverted_before, b.n_inverted_after)
    assert a.min_angle.min >= b.min_angle.min
    with pytest.raises(ValueError, match="quality_report"):
        Snapper(mesh, ft, geo, quality_report="some")
