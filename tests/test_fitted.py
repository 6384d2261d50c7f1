"""FittedGeometry: local least-squares fits blended over the coarse facets (issue 30)."""

import itertools
import os
import subprocess
import sys

import numpy as np
import pytest
from mpi4py import MPI
from scipy.spatial import cKDTree

import generate
from surfaces import (
    barycentric_grid,
    ellipse_polygon,
    gmsh_occ_surface,
    gmsh_surface,
    nagata_surface_error,
    sphere_octahedron,
)

from nagata_snap import FittedGeometry, NagataGeometry, Snapper
from nagata_snap.fitted.fit import fit_surfaces, surface_height
from nagata_snap.geometry import SnapGeometry

HERE = os.path.dirname(__file__)


def fitted_error(geo, dist, per_edge=12):
    return nagata_surface_error(geo, dist, per_edge=per_edge)


def orders(errors):
    return [float(np.log2(a / b)) for a, b in itertools.pairwise(errors)]


@pytest.mark.parametrize("degree", [0, 1, 7, 2.5, True, "4"])
def test_bad_degree_is_named(degree):
    p, t, _ = sphere_octahedron(1)
    with pytest.raises(ValueError, match="degree must be an integer from 2 to 6"):
        FittedGeometry.from_surface(p, t, degree=degree)


@pytest.mark.parametrize("degree", [2, 3, 4, 5, 6])
@pytest.mark.parametrize("planar", [False, True])
def test_fit_reproduces_height_polynomial(degree, planar):
    """A degree-p fit through points of a degree-p height polynomial is that polynomial."""
    rng = np.random.default_rng(degree)
    S, m = 5, 40
    uv = rng.uniform(-1, 1, (S, m, 2)) * 0.3
    if planar:
        uv[..., 1] = 0.0
    coef = rng.normal(size=(S, degree + 1, degree + 1))

    def poly(u, v):
        out = np.zeros_like(u)
        for i in range(degree + 1):
            for j in range(degree + 1 - i):
                if i + j >= 1 and not (planar and j):
                    out += coef[:, i, j, None] * u**i * v**j
        return out

    w = poly(uv[..., 0], uv[..., 1])
    pts = np.concatenate([uv, w[..., None]], axis=2)
    frame = np.broadcast_to(np.eye(3), (S, 3, 3))
    if planar:
        frame = np.broadcast_to(np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 1]]), (S, 3, 3))
    h = np.full(S, 0.1)
    c = fit_surfaces(np.zeros((S, 3)), frame, pts, np.ones((S, m), dtype=bool), h, degree, planar)
    test = rng.uniform(-1, 1, (S, 7, 2)) * 0.2
    if planar:
        test[..., 1] = 0.0
    got = surface_height(c, degree, planar, test[..., 0] / 0.1, test[..., 1] / 0.1) * 0.1
    assert np.abs(got - poly(test[..., 0], test[..., 1])).max() < 1e-10


def test_slope_rows_determine_a_sphere():
    """Six points of a unit sphere around the pole (too few for the 8 terms of a degree-2 fit) with the
    exact normals there and at the pole (:func:`slope_rows`): the fit is the sphere to rounding."""
    t = np.linspace(0, 2 * np.pi, 7)[:-1] + 0.1
    a = 0.3
    pts = np.stack([np.sin(a) * np.cos(t), np.sin(a) * np.sin(t), np.cos(a) - 1.0 + 0 * t], axis=1)[None]
    centre = np.array([[0.0, 0.0, -1.0]])
    normals = np.concatenate([np.array([[[0.0, 0.0, 1.0]]]), pts - centre[:, None]], axis=1)
    x0, frame, h, mask = np.zeros((1, 3)), np.eye(3)[None], np.array([0.3]), np.ones((1, 6), dtype=bool)
    alone = fit_surfaces(x0, frame, pts, mask, h, 2, False)
    c = fit_surfaces(x0, frame, pts, mask, h, 2, False, normals=normals)
    uv = np.array([[0.05, 0.1, -0.2, 0.15], [0.12, -0.2, 0.0, 0.25]])[None]
    w = surface_height(c, 2, False, uv[:, 0] / 0.3, uv[:, 1] / 0.3) * 0.3
    exact = np.sqrt(1.0 - uv[:, 0] ** 2 - uv[:, 1] ** 2) - 1.0
    assert np.abs(w - exact).max() < 1e-12
    w0 = surface_height(alone, 2, False, uv[:, 0] / 0.3, uv[:, 1] / 0.3) * 0.3
    assert not np.abs(w0 - exact).max() < 1e-9  # positions alone do not determine it


def test_planes_and_straight_edges_stay_exact():
    """A box (irregular gmsh mesh, estimated normals): faces stay planar, edges straight, to rounding."""
    import gmsh

    p, t, tags = gmsh_occ_surface(lambda: gmsh.model.occ.addBox(-1, -1, -1, 2, 2, 2), 0.6)
    geo = FittedGeometry.from_surface(p, t, tags)
    g = barycentric_grid(3, 8)
    x = geo.evaluate(np.arange(geo.num_patches), np.broadcast_to(g, (geo.num_patches, *g.shape)))
    assert np.abs(np.abs(x).max(axis=2) - 1.0).max() < 1e-13
    assert (geo.fit_degree >= 2).all()


def test_evaluate_nothing():
    """No points (a process whose refinement placed none on this surface): empty results, no error."""
    p, t, _ = sphere_octahedron(1)
    geo = FittedGeometry.from_surface(p, t)
    assert geo.evaluate(np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3))).shape == (0, 3, 3)
    assert geo.evaluate(np.arange(2), np.zeros((2, 0, 3))).shape == (2, 0, 3)


def test_sphere_converges_fast():
    """Estimated normals on octahedron subdivisions of the unit sphere: order >= 5 (quadrics are in the model)."""
    errs = []
    for level in (1, 2, 3):
        p, t, _ = sphere_octahedron(level)
        geo = FittedGeometry.from_surface(p, t)
        errs.append(fitted_error(geo, lambda x: np.abs(np.linalg.norm(x, axis=-1) - 1.0)))
    assert min(orders(errs)) >= 5.0, errs


def test_torus_converges_at_order_five_and_beats_nagata():
    """Irregular gmsh torus meshes, estimated normals, degree 4 against the exact torus."""
    errs, nagata = [], []
    for h in (0.2, 0.1, 0.05):
        p, t, exact, _ = gmsh_surface("torus", h)
        errs.append(fitted_error(FittedGeometry.from_surface(p, t, crease_angle=80), exact.distance))
        nagata.append(fitted_error(NagataGeometry.from_surface(p, t, crease_angle=80), exact.distance))
    assert orders(errs)[-1] >= 4.5, errs
    assert errs[-1] <= 0.15 * nagata[-1], (errs, nagata)


def test_degree_three():
    """Degree 3: far below Nagata on the ellipsoid (a quadric is in the model); on the torus, where the
    cubic fits are about as accurate as the patches at these sizes, the guard keeps the fits that
    improve on the patches and no worse than Nagata's (measured 0.65; 1.31 before the guard compared
    the fits' disagreement with their correction of the patch)."""
    for kind, bound in (("ellipsoid", 0.1), ("torus", 1.0)):
        p, t, exact, _ = gmsh_surface(kind, 0.05)
        fit = fitted_error(FittedGeometry.from_surface(p, t, degree=3, crease_angle=80), exact.distance)
        nagata = fitted_error(NagataGeometry.from_surface(p, t, crease_angle=80), exact.distance)
        assert fit <= bound * nagata, (kind, fit, nagata)


def _edge_samples(geo, tt):
    """For every coarse edge shared by two patches: points from both sides at the same positions."""
    vid = geo.corners.vertex
    rf, rv = geo.corners.ridge_facets, geo.corners.ridge_vertices
    sides = []
    for s in (0, 1):
        f = rf[:, s]
        lam = np.zeros((len(f), len(tt), 3))
        for k, w in ((0, 1.0 - tt), (1, tt)):
            pos = np.argmax(vid[f] == rv[:, k, None], axis=1)
            lam[np.arange(len(f)), :, pos] = w
        sides.append(geo.evaluate(f, lam))
    return sides


def test_cylinder_rims_stay_sharp_and_converge():
    """Closed cylinder with sharp rims: both sides of a rim edge give one point, on the circle (a planar
    circle is a conic of the curve fits' model: exact to rounding), the surface at order >= 4.5."""
    tt = np.linspace(0.0, 1.0, 9)
    rim, surf = [], []
    for h in (0.2, 0.1, 0.05):
        p, t, exact, tags = gmsh_surface("cylinder", h)
        geo = FittedGeometry.from_surface(p, t, tags, crease_angle=80)
        a, b = _edge_samples(geo, tt)
        assert np.abs(a - b).max() <= 1e-14  # C0 across every coarse edge, creases included
        cr = geo.crease
        assert cr.sum() > 0
        x = a[cr]
        rim.append(np.hypot(np.hypot(x[..., 0], x[..., 1]) - 1.0, np.abs(x[..., 2]) - 0.5).max())
        surf.append(fitted_error(geo, exact.distance))
    assert max(rim) <= 1e-13, rim
    assert orders(surf)[-1] >= 4.5, surf


@pytest.mark.parametrize("curvature, bound", [(12, 0.6), (16, 0.5), (20, 0.5)])
def test_filleted_plate_beats_nagata(tmp_path, curvature, bound):
    """The filleted plate's coarse mesh against the CAD (OpenCASCADE's closest point on each facet's face):
    quarter-arc rims of 3 segments between corners are fitted (Hermite data: both faces' normals); the
    pocket-corner tori (3-5 segments per 90 degrees, tangent to planes and cylinders on every side) are
    refitted with the neighbours' normals on their rims (``FittedGeometry._hermite_refit``).  The largest
    distance is at most 0.5x Nagata's at curvature 16 and 20 (measured 0.22, 0.20; 1.00 before the
    refits) and 0.6x at 12 (0.55; 0.86 before); nothing bounded."""
    import parts
    from occ_reference import gmsh_face_distance

    from nagata_snap.meshing import gmsh_session, import_cad, mesh_cad_file

    path = parts.write_part("plate_filleted", tmp_path, formats=("step",))["step"]
    g = barycentric_grid(3, 4)
    with gmsh_session("plate"):
        import_cad(path)
        cm = mesh_cad_file(path, MPI.COMM_SELF, curvature=curvature)
        errs = []
        for geo in (FittedGeometry(cm.mesh, cm.facet_tags), NagataGeometry(cm.mesh, cm.facet_tags)):
            x = geo.evaluate(np.arange(geo.num_patches), np.broadcast_to(g, (geo.num_patches, *g.shape)))
            errs.append(max(gmsh_face_distance(int(t), x[geo.tag == t].reshape(-1, 3)).max()
                            for t in np.unique(geo.tag)))
            if isinstance(geo, FittedGeometry):
                assert geo.n_clipped == 0
    assert errs[0] <= bound * errs[1], errs


def test_p3_poisson_on_the_fitted_torus():
    """P3 Poisson in a solid torus meshed at h = 0.14, u = 0 imposed on the discrete boundary
    (``benchmarks/torus_poisson.py``): on ``curved_mesh(degree=3)`` of the fitted surface the L2 error
    against the exact solution is below 0.8x Nagata's (measured 0.69; 0.36 at h = 0.07) and 1% of the
    straight cells' (the domain's error, order 2)."""
    sys.path.insert(0, os.path.join(HERE, "..", "benchmarks"))
    import torus_poisson as tp

    md = generate.solid_torus(MPI.COMM_WORLD, major_radius=tp.R, minor_radius=tp.r, h=0.14)
    err = {"straight": tp.solve_l2_error(md.mesh)[0]}
    for label, geo in tp.geometries(md.mesh, md.facet_tags).items():
        if label != "CAD":
            cm, _ = Snapper(md.mesh, md.facet_tags, geo).curved_mesh(degree=3)
            err[label] = tp.solve_l2_error(cm)[0]
    assert err["fitted"] < 0.8 * err["Nagata"], err
    assert err["fitted"] < 0.01 * err["straight"], err


def test_ellipse_polygon_converges():
    """2D: polygons inscribed in an ellipse (unequal segments): order >= 4.5, 10x below Nagata's."""
    errs = []
    for n in (48, 96, 192):
        p, s, exact = ellipse_polygon(n)
        errs.append(nagata_surface_error(FittedGeometry.from_surface(p, s), exact.distance))
    assert orders(errs)[-1] >= 4.5, errs
    assert errs[-1] <= 0.1 * nagata_surface_error(NagataGeometry.from_surface(p, s), exact.distance)


def test_snapper_refinement_loop():
    """A SnapGeometry: two refinements of a sphere in a box, the box flat, the sphere on the fitted surface."""
    md = generate.sphere_in_box(MPI.COMM_WORLD, h_sphere=0.3, h_box=0.6)
    mesh, ft = md.mesh, md.facet_tags
    geo = FittedGeometry(mesh, ft)
    assert isinstance(geo, SnapGeometry)

    def dist(x):
        return np.abs(np.linalg.norm(x, axis=-1) - 0.5)

    e_fit = nagata_surface_error(geo, dist, generate.SPHERE)
    e_nagata = nagata_surface_error(NagataGeometry(mesh, ft), dist, generate.SPHERE)
    assert e_fit < e_nagata
    snapper = Snapper(mesh, ft, geo)
    for _ in range(2):
        mesh, ft, _, _, rep = snapper.refine(mesh)
        assert rep.inverted_after_smoothing == 0 and rep.partially_moved == 0
        sph = np.unique(mesh.geometry.x[
            __import__("dolfinx").mesh.entities_to_geometry(mesh, 2, ft.find(generate.SPHERE)).ravel()], axis=0)
        assert dist(sph).max() <= e_fit * (1 + 1e-9)
        box = np.unique(mesh.geometry.x[
            __import__("dolfinx").mesh.entities_to_geometry(mesh, 2, ft.find(generate.BOX)).ravel()], axis=0)
        assert np.abs(np.abs(box).max(axis=1) - 1.0).max() <= 1e-13


def _run(n, args, tmp_path):
    out = tmp_path / f"np{n}.npz"
    exe = [os.path.join(os.path.dirname(sys.executable), "mpiexec"), "-n", str(n)] if n > 1 else []
    r = subprocess.run([*exe, sys.executable, os.path.join(HERE, "mpi", "snap_loop.py"), *args, str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    return np.load(out)


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["sphere_fitted", "dfg_fitted"])
def test_mpi_matches_serial(case, tmp_path):
    """Snapped boundary vertices are the same under mpiexec -n 2 as in serial (1e-12)."""
    serial, par = _run(1, [case, "2", "uniform"], tmp_path), _run(2, [case, "2", "uniform"], tmp_path)
    for k in (1, 2):
        a, b = serial[f"boundary{k}"], par[f"boundary{k}"]
        assert a.shape == b.shape
        d, i = cKDTree(a).query(b)
        assert d.max() <= 1e-12 and len(np.unique(i)) == len(a)


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "nagata_snap.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def test_cli_surface_fitted(tmp_path):
    """``--surface fitted --degree 4`` on the DFG channel's 16-gon: the cylinder vertices on the circle."""
    import dolfinx.io

    msh = tmp_path / "dfg.msh"
    generate.dfg_channel(MPI.COMM_SELF, n_circle=16, h_far=0.1, msh_file=str(msh))
    out = tmp_path / "fine.xdmf"
    r = _cli(msh, "--tags", generate.CYLINDER, "--levels", 2, "--surface", "fitted", "--degree", 4, "--output", out)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "fitted surface of degree 4" in r.stdout
    with dolfinx.io.XDMFFile(MPI.COMM_SELF, str(out), "r") as f:
        mesh = f.read_mesh(name="mesh")
        mesh.topology.create_connectivity(1, 2)
        ft = f.read_meshtags(mesh, name="facet_tags")
    x = mesh.geometry.x[dolfinx.mesh.entities_to_geometry(mesh, 1, ft.find(generate.CYLINDER)).ravel()]
    d = np.abs(np.linalg.norm(x[:, :2] - np.array(generate.DFG_CENTER)[:2], axis=1) - generate.DFG_RADIUS)
    assert len(np.unique(x, axis=0)) == 16 * 4
    # a circle is a conic of the fits' model, exact; what is left is the blend of two exact
    # points (3.6e-7), far below the Nagata curve's 9.3e-6 (test_cli)
    assert d.max() < 1e-6
    for bad in (["--surface", "fitted", "--degree", 7], ["--surface", "spline"]):
        r = _cli(msh, "--tags", generate.CYLINDER, *bad)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    r = _cli(msh, "--tags", generate.CYLINDER, "--surface", "fitted", "--degree", 7)
    assert "--degree must be from 2 to 6" in r.stderr
