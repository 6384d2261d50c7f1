"""The IGES writer (nagata_snap.cad.iges) and the files of meshes/make_iges.py, read by OpenCASCADE.

Reading is OpenCASCADE's (:func:`nagata_snap.cad.read.read_shape`); the
expected values come from the source documents (Kadir 2010, App. C: centre
and radius printed in the Start section of the example files), from
closed-form geometry, or from OpenCASCADE through gmsh.

(The hand-written IGES reader these tests used to cover was removed: the
OpenCASCADE reader reads every entity it read, and many it skipped, with the
file's topology; its tests of malformed input are replaced by
``tests/test_cad_read.py``.)
"""

from __future__ import annotations

import math

import gmsh
import numpy as np

import make_iges  # meshes/ is on sys.path (conftest.py)
from nagata_snap.cad.iges import write_iges
from nagata_snap.cad.nurbs import NurbsCurve, NurbsSurface, cylinder, torus
from nagata_snap.cad.read import read_shape
from nagata_snap.cad.topology import nurbs_curve, nurbs_surface

import pytest

# Start section of "IGES File 1": "Center = (0.2, 0.2, 0.0), Radius = 0.05"
KC, KR = np.array([0.2, 0.2, 0.0]), 0.05
# Start section of "IGES File 2": "Center(x,y)=(0.55, 0.5), zmin=0, zmax=0.4, Radius=0.05"
YC, YR, YZ = np.array([0.55, 0.5]), 0.05, (0.0, 0.4)
W_PRINTED = make_iges.KADIR_WEIGHT


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("iges")
    make_iges.write_all(d)
    return d


def sample_curve(c: NurbsCurve, n: int = 401) -> np.ndarray:
    return c.evaluate(np.linspace(*c.domain, n))[0]


def sample_surface(s: NurbsSurface, n: int = 41, m: int = 43):
    u = np.linspace(*s.domain_u, n)
    v = np.linspace(*s.domain_v, m)
    U, V = np.meshgrid(u, v, indexing="ij")
    return U.ravel(), V.ravel(), s.evaluate(U.ravel(), V.ravel())[0]


def test_kadir_circle_file_layout(files):
    text = (files / "kadir_circle.igs").read_text()
    assert text == make_iges.kadir_circle_text()
    # the copies kept in the repository are the ones the script writes
    for name, make in (("kadir_circle.igs", make_iges.kadir_circle_text),
                       ("kadir_cylinder.igs", make_iges.kadir_cylinder_text)):
        repo = make_iges.HERE / name
        if repo.exists():
            assert repo.read_text() == make()
    assert all(len(line) == 80 for line in text.splitlines())
    assert text.splitlines()[-1].startswith("S      2G      1D      2P     16")


def test_kadir_files_read_by_occ(files):
    """Kadir's printed circle and cylinder (inches, kept in the file's unit)."""
    d = read_shape(files / "kadir_circle.igs", unit="FILE")
    assert d["file_units"] == ["INCH"] and d["unit"] == "INCH" and not d["faces"]
    (edge,) = d["edges"]
    c = nurbs_curve(edge["curve"])
    np.testing.assert_array_equal(c.weights / c.weights[0], [1, W_PRINTED] * 4 + [1])
    P = sample_curve(c, 2001)
    rel = np.abs(np.linalg.norm(P - KC, axis=1) - KR) / KR
    bound = make_iges.weight_rounding_error(W_PRINTED)
    assert 1e-9 < bound < 1e-7
    assert rel.max() <= bound * (1 + 1e-6) + 1e-14
    assert rel.max() >= 0.99 * bound  # the error really is the rounded weight
    d = read_shape(files / "kadir_cylinder.igs", unit="FILE")
    (face,) = d["faces"]
    s = nurbs_surface(face["surface"])
    _, _, P = sample_surface(s, 801, 11)
    rel = np.abs(np.linalg.norm(P[:, :2] - YC, axis=1) - YR) / YR
    assert rel.max() <= bound * (1 + 1e-6) + 1e-14
    assert abs(P[:, 2].min() - YZ[0]) < 1e-15 and abs(P[:, 2].max() - YZ[1]) < 1e-15


def test_units_are_converted_as_gmsh_does(files):
    """The DFG circle is written in metres: OCC (and gmsh) give millimetres by default."""
    mm = read_shape(files / "dfg_circle.igs")
    m = read_shape(files / "dfg_circle.igs", unit="M")
    assert mm["file_units"] == ["M"] and mm["unit"] == "MM"
    P_mm = sample_curve(nurbs_curve(mm["edges"][0]["curve"]))
    P_m = sample_curve(nurbs_curve(m["edges"][0]["curve"]))
    np.testing.assert_allclose(P_mm, 1000 * P_m, rtol=1e-13, atol=1e-12)
    rel = np.abs(np.linalg.norm(P_m - KC, axis=1) - KR) / KR
    assert rel.max() < 1e-12
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.importShapes(str(files / "dfg_circle.igs"))
        gmsh.model.occ.synchronize()
        box = np.reshape(gmsh.model.getBoundingBox(-1, -1), (2, 3))
    finally:
        gmsh.finalize()
    np.testing.assert_allclose(box.mean(axis=0)[:2], 1000 * KC[:2], atol=1e-3)


def random_curve(rng) -> NurbsCurve:
    p = int(rng.integers(1, 5))
    n = int(rng.integers(p + 1, p + 8))
    inner = np.sort(rng.uniform(0.1, 3.0, n - p - 1))
    U = np.concatenate([[0.0] * (p + 1), inner, [3.3] * (p + 1)])
    return NurbsCurve(degree=p, knots=U, control_points=rng.normal(size=(n, 3)) * 10 ** rng.uniform(-3, 3),
                      weights=rng.uniform(0.2, 3.0, n))


def random_surface(rng) -> NurbsSurface:
    p, q = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    nu, nv = int(rng.integers(p + 1, p + 5)), int(rng.integers(q + 1, q + 5))
    U = np.concatenate([[0.0] * (p + 1), np.sort(rng.uniform(0.1, 0.9, nu - p - 1)), [1.0] * (p + 1)])
    V = np.concatenate([[-2.0] * (q + 1), np.sort(rng.uniform(-1.9, 4.9, nv - q - 1)), [5.0] * (q + 1)])
    gu, gv = np.meshgrid(np.linspace(0, 1, nu), np.linspace(0, 1, nv), indexing="ij")
    P = np.stack([gu, gv, 0.2 * np.sin(3 * gu + gv)], axis=-1) + 0.05 * rng.normal(size=(nu, nv, 3))
    return NurbsSurface(degree_u=p, degree_v=q, knots_u=U, knots_v=V, control_points=P,
                        weights=rng.uniform(0.3, 2.5, (nu, nv)))


def test_round_trip_through_occ_is_exact(tmp_path):
    """Written curves and surfaces come back from OpenCASCADE with the same geometry."""
    rng = np.random.default_rng(1)
    curves = [random_curve(rng) for _ in range(6)]
    surfaces = [random_surface(rng) for _ in range(5)]
    path = tmp_path / "rt.igs"
    write_iges(path, curves, surfaces, units="M", author="me")
    lines = path.read_text().splitlines()
    assert all(len(s) == 80 for s in lines)
    counts = {c: sum(1 for s in lines if s[72] == c) for c in "SGDPT"}
    assert [int(lines[-1][8 * k + 1:8 * k + 8]) for k in range(4)] == [counts[c] for c in "SGDP"]
    d = read_shape(path, unit="FILE")
    assert d["file_units"] == ["M"] and len(d["faces"]) == len(surfaces)
    for a, f in zip(surfaces, d["faces"], strict=True):
        b = nurbs_surface(f["surface"])
        U, V, P = sample_surface(a, 13, 15)
        np.testing.assert_allclose(b.evaluate(U, V)[0], P, rtol=0, atol=1e-13 * a.bbox_size)
    got = [nurbs_curve(e["curve"]) for e in d["edges"] if e["curve"]["type"] == "bspline"]
    for a in curves:  # each written curve is one of the edges read
        P = sample_curve(a, 51)
        assert any(b.domain == a.domain and np.abs(sample_curve(b, 51) - P).max() <= 1e-13 * a.bbox_size
                   for b in got)


def test_written_files_imported_by_gmsh(tmp_path):
    """gmsh's own OpenCASCADE import: same points at the same parameters."""
    rng = np.random.default_rng(7)
    curves = [make_iges.circle_curve((0.2, 0.2, 0.0), 0.05)] + [random_curve(rng) for _ in range(2)]
    surfaces = [torus((0, 0, 0), 1.0, 0.3), cylinder((0.55, 0.5, 0.0), 0.05, 0.4)] + \
        [random_surface(rng) for _ in range(3)]
    path = tmp_path / "ours.igs"
    write_iges(path, curves, surfaces)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("Geometry.OCCImportLabels", 0)
        gmsh.model.occ.importShapes(str(path), highestDimOnly=False)
        gmsh.model.occ.synchronize()
        faces = [t for _, t in gmsh.model.getEntities(2)]
        assert len(faces) == len(surfaces)
        for s, f in zip(surfaces, faces, strict=True):
            lo, hi = gmsh.model.getParametrizationBounds(2, f)
            np.testing.assert_allclose(lo, [s.domain_u[0], s.domain_v[0]], atol=1e-15)
            np.testing.assert_allclose(hi, [s.domain_u[1], s.domain_v[1]], atol=1e-15)
            U, V, P = sample_surface(s, 17, 19)
            val = np.reshape(gmsh.model.getValue(2, f, np.column_stack([U, V]).ravel().tolist()), (-1, 3))
            assert np.abs(val - P).max() < 1e-12 * s.bbox_size
        lens = sum(gmsh.model.occ.getMass(1, t) for _, t in gmsh.model.getEntities(1)
                   if gmsh.model.getType(1, t) == "BSpline")
        assert lens > 2 * math.pi * 0.05
    finally:
        gmsh.finalize()


def test_make_iges_deterministic(tmp_path, files):
    make_iges.write_all(tmp_path)
    for name in ("kadir_circle.igs", "kadir_cylinder.igs", "dfg_circle.igs",
                 "occ_sphere.igs", "occ_torus.igs", "occ_part.igs"):
        assert (tmp_path / name).read_bytes() == (files / name).read_bytes(), name


def test_writer_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError, match="nothing to write"):
        write_iges(tmp_path / "x.igs")
