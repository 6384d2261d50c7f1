"""Tests of the IGES reader/writer (nagata_snap.cad.iges) and meshes/make_iges.py.

Expected values come from the source documents (Kadir 2010, App. C: centre
and radius printed in the Start section of the example files) or from
closed-form geometry (circle, sphere, torus, rotations) evaluated with numpy,
or from OpenCASCADE through gmsh -- never from the code under test.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import make_iges  # meshes/ is on sys.path (conftest.py)
from nagata_snap.cad import iges as I
from nagata_snap.cad.iges import (
    IgesError,
    IgesModel,
    IgesWarning,
    format_iges,
    points_in_polygon,
    read_iges,
    write_iges,
)
from nagata_snap.cad.nurbs import NurbsCurve, NurbsSurface

import gmsh  # noqa: E402  (a dependency: a missing gmsh must fail, not skip)


# ----------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------
def quiet_read(src) -> IgesModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IgesWarning)
        return read_iges(src)


def F(x: float) -> str:
    return I._fmt_real(x)


def E(etype: int, params, form: int = 0, trans: int = 0, status: str = "00000000"):
    """Entity tuple for format_iges; ints are written as integers, floats as reals."""
    toks = [str(etype)]
    for p in params:
        toks.append(p if isinstance(p, str) else str(p) if isinstance(p, (int, np.integer)) else F(p))
    return (etype, form, toks, trans, status)


def text_of(*ents) -> str:
    return format_iges(list(ents))


def sample_curve(c: NurbsCurve, n: int = 401) -> np.ndarray:
    return c.evaluate(np.linspace(*c.domain, n))[0]


def sample_surface(s: NurbsSurface, n: int = 41, m: int = 43):
    u = np.linspace(*s.domain_u, n)
    v = np.linspace(*s.domain_v, m)
    U, V = np.meshgrid(u, v, indexing="ij")
    return U.ravel(), V.ravel(), s.evaluate(U.ravel(), V.ravel())[0]


def rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def e124(R: np.ndarray, t, trans: int = 0):
    M = np.column_stack([R, np.asarray(t, float)])
    return E(124, [float(x) for x in M.ravel()], trans=trans)


def project(s: NurbsSurface, P: np.ndarray, n: int = 48, iters: int = 30):
    """Closest (u, v) on ``s`` to the points ``P`` (k,3): grid start + clamped Newton."""
    (u0, u1), (v0, v1) = s.domain_u, s.domain_v
    U, V = np.meshgrid(np.linspace(u0, u1, n), np.linspace(v0, v1, n), indexing="ij")
    G = s.evaluate(U.ravel(), V.ravel())[0]
    best = np.argmin(((P[:, None, :] - G[None]) ** 2).sum(-1), axis=1)
    uu, vv = U.ravel()[best].copy(), V.ravel()[best].copy()
    for _ in range(iters):
        S, Su, Sv, Suu, Suv, Svv = s.evaluate(uu, vv, nderiv=2)
        r = S - P
        f, g = (r * Su).sum(1), (r * Sv).sum(1)
        a = (Su * Su).sum(1) + (r * Suu).sum(1)
        b = (Su * Sv).sum(1) + (r * Suv).sum(1)
        c = (Sv * Sv).sum(1) + (r * Svv).sum(1)
        det = a * c - b * b
        det = np.where(np.abs(det) < 1e-300, 1e-300, det)
        uu = np.clip(uu - (c * f - b * g) / det, u0, u1)
        vv = np.clip(vv - (a * g - b * f) / det, v0, v1)
    return uu, vv, np.linalg.norm(s.evaluate(uu, vv)[0] - P, axis=1)


def inside_face(model: IgesModel, k: int, uv: np.ndarray) -> np.ndarray:
    loop = model.trim_loops[k]
    ins = np.ones(len(uv), bool) if loop is None else points_in_polygon(loop, uv)
    for h in model.trim_holes[k]:
        ins &= ~points_in_polygon(h, uv)
    return ins


# ----------------------------------------------------------------------
# fixtures
# ----------------------------------------------------------------------
@pytest.fixture(scope="module")
def occ():
    was = gmsh.isInitialized()
    if not was:
        gmsh.initialize(interruptible=False)
    terminal = gmsh.option.getNumber("General.Terminal")
    gmsh.option.setNumber("General.Terminal", 0)
    yield gmsh
    if was:
        gmsh.option.setNumber("General.Terminal", terminal)
    else:
        gmsh.finalize()


@pytest.fixture(scope="module")
def files(tmp_path_factory, occ):
    d = tmp_path_factory.mktemp("iges")
    make_iges.write_all(d)
    return d


def occ_import(path):
    """Import an IGES file into a fresh gmsh model; returns the model name."""
    name = f"imp{occ_import.n}"
    occ_import.n += 1
    gmsh.model.add(name)
    gmsh.model.occ.importShapes(str(path), highestDimOnly=False)
    gmsh.model.occ.synchronize()
    return name


occ_import.n = 0


def occ_distance(dim: int, P: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest entity of dimension ``dim`` (OCC closest point)."""
    d = np.full(len(P), np.inf)
    for _, tag in gmsh.model.getEntities(dim):
        c, _ = gmsh.model.getClosestPoint(dim, tag, P.ravel().tolist())
        d = np.minimum(d, np.linalg.norm(np.reshape(c, (-1, 3)) - P, axis=1))
    return d


# ======================================================================
# Kadir (2010) App. C example files
# ======================================================================
# Start section of "IGES File 1": "Center = (0.2, 0.2, 0.0), Radius = 0.05"
KC, KR = np.array([0.2, 0.2, 0.0]), 0.05
# Start section of "IGES File 2": "Center(x,y)=(0.55, 0.5), zmin=0, zmax=0.4, Radius=0.05"
YC, YR, YZ = np.array([0.55, 0.5]), 0.05, (0.0, 0.4)
W_PRINTED = make_iges.KADIR_WEIGHT
weight_rounding_error = make_iges.weight_rounding_error


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


def test_kadir_circle(files):
    m = read_iges(files / "kadir_circle.igs")
    assert m.units == "INCH" and m.source == "kadir_circle.igs"
    assert len(m.curves) == 1 and not m.surfaces and m.skipped == {}
    c = m.curves[0]
    # data as printed in the thesis
    assert c.degree == 2
    np.testing.assert_array_equal(c.knots, [0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1, 1])
    np.testing.assert_array_equal(c.weights, [1, W_PRINTED] * 4 + [1])
    # points at the knots (weight-1 control points) lie exactly on the circle, at 0/90/180/270 deg
    P = c.evaluate(np.array([0.0, 0.25, 0.5, 0.75, 1.0]))[0]
    ang = np.deg2rad([0, 90, 180, 270, 360])
    expect = KC + KR * np.column_stack([np.cos(ang), np.sin(ang), 0 * ang])
    np.testing.assert_allclose(P, expect, rtol=0, atol=1e-12 * KR)
    # everywhere else the printed weight 0.707107 (not 1/sqrt 2) limits the accuracy
    P = sample_curve(c, 2001)
    rel = np.abs(np.linalg.norm(P - KC, axis=1) - KR) / KR
    bound = weight_rounding_error(W_PRINTED)
    assert 1e-9 < bound < 1e-7
    assert rel.max() <= bound * (1 + 1e-6) + 1e-14
    assert rel.max() >= 0.99 * bound  # the error really is the rounded weight
    np.testing.assert_array_equal(P[:, 2], 0.0)


def test_dfg_circle_exact(files):
    m = read_iges(files / "dfg_circle.igs")
    assert m.units == "M" and len(m.curves) == 1
    c = m.curves[0]
    P = sample_curve(c, 4001)
    rel = np.abs(np.linalg.norm(P - KC, axis=1) - KR) / KR
    assert rel.max() < 1e-12
    # the whole circle is traced: angles cover [0, 2 pi)
    a = np.unwrap(np.arctan2(P[:, 1] - KC[1], P[:, 0] - KC[0]))
    assert abs(a[-1] - a[0] - 2 * math.pi) < 1e-12
    assert c.is_closed


def test_kadir_cylinder(files):
    with pytest.warns(IgesWarning, match=r"parameter range .* knot domain"):
        m = read_iges(files / "kadir_cylinder.igs")
    assert len(m.surfaces) == 1 and m.trim_loops == [None]
    s = m.surfaces[0]
    assert (s.degree_u, s.degree_v) == (2, 1)
    assert s.control_points.shape == (9, 2, 3)
    # the printed net: first row z = 0, second z = 0.4, u runs around the circle
    np.testing.assert_array_equal(s.control_points[:, 0, 2], 0.0)
    np.testing.assert_array_equal(s.control_points[:, 1, 2], 0.4)
    np.testing.assert_array_equal(s.control_points[0, 0], [0.6, 0.5, 0.0])
    np.testing.assert_array_equal(s.control_points[2, 1], [0.55, 0.55, 0.4])
    U, V, P = sample_surface(s, 801, 11)
    rel = np.abs(np.linalg.norm(P[:, :2] - YC, axis=1) - YR) / YR
    assert rel.max() <= weight_rounding_error(W_PRINTED) * (1 + 1e-6) + 1e-14
    np.testing.assert_allclose(P[:, 2], YZ[0] + V * (YZ[1] - YZ[0]), atol=1e-15)
    at_knots = np.isin(U, [0.0, 0.25, 0.5, 0.75, 1.0])
    assert rel[at_knots].max() < 1e-12


# ======================================================================
# files written by OpenCASCADE (gmsh)
# ======================================================================
def test_occ_sphere_torus(files):
    m = read_iges(files / "occ_sphere.igs")
    assert len(m.surfaces) == 1 and not m.curves and m.units == "MM"
    _, _, P = sample_surface(m.surfaces[0], 61, 67)
    assert np.abs(np.linalg.norm(P, axis=1) - 1.0).max() < 1e-9
    assert m.trim_loops[0] is not None
    m = read_iges(files / "occ_torus.igs")
    assert len(m.surfaces) == 1
    _, _, P = sample_surface(m.surfaces[0], 61, 67)
    R, r = 1.0, 0.3
    dist = np.hypot(np.hypot(P[:, 0], P[:, 1]) - R, P[:, 2])  # distance to the core circle
    assert np.abs(dist - r).max() < 1e-9 * (R + r)
    # the face covers the whole torus: the trim loop encloses (almost) the whole domain
    s, loop = m.surfaces[0], m.trim_loops[0]
    area = 0.5 * abs(np.sum(loop[:, 0] * np.roll(loop[:, 1], -1) - np.roll(loop[:, 0], -1) * loop[:, 1]))
    dom = np.ptp(s.domain_u) * np.ptp(s.domain_v)
    assert abs(area / dom - 1) < 1e-6


def check_against_occ(path, mesh_size: float = 0.08):
    """Our trimmed faces vs the OCC import of the same file.

    1. points sampled inside our trimming loops lie on OCC faces (closest-point distance);
    2. every interior node of a gmsh mesh of the OCC faces lies on one of our surfaces,
       inside its loops (this checks the loops and the sense of rotation of 120);
    3. the trimmed areas agree (midpoint rule, 1e-3).
    """
    m = quiet_read(path)
    occ_import(path)
    try:
        lo, hi = gmsh.model.getBoundingBox(-1, -1)[:3], gmsh.model.getBoundingBox(-1, -1)[3:]
        size = float(np.linalg.norm(np.subtract(hi, lo)))
        for k, s in enumerate(m.surfaces):
            U, V, P = sample_surface(s, 31, 33)
            ins = inside_face(m, k, np.column_stack([U, V]))
            assert ins.sum() > 50
            assert occ_distance(2, P[ins]).max() < 1e-9 * size
        old = gmsh.option.getNumber("Mesh.MeshSizeMax")
        gmsh.option.setNumber("Mesh.MeshSizeMax", mesh_size)
        try:
            gmsh.model.mesh.generate(2)
        finally:
            gmsh.option.setNumber("Mesh.MeshSizeMax", old)
        total = 0
        for _, f in gmsh.model.getEntities(2):
            _, x, _ = gmsh.model.mesh.getNodes(2, f, includeBoundary=False)
            X = np.reshape(x, (-1, 3))
            ok = np.zeros(len(X), bool)
            for k, s in enumerate(m.surfaces):
                uu, vv, dist = project(s, X)
                ok |= (dist < 1e-9 * size) & inside_face(m, k, np.column_stack([uu, vv]))
            assert ok.all(), f"{(~ok).sum()} OCC mesh nodes of face {f} are not on our trimmed faces"
            total += len(X)
        assert total > 100
        area_occ = sum(gmsh.model.occ.getMass(2, t) for _, t in gmsh.model.getEntities(2))
        area = 0.0
        for k, s in enumerate(m.surfaces):
            N = 300
            (u0, u1), (v0, v1) = s.domain_u, s.domain_v
            u = u0 + (np.arange(N) + 0.5) * (u1 - u0) / N
            v = v0 + (np.arange(N) + 0.5) * (v1 - v0) / N
            UU, VV = np.meshgrid(u, v, indexing="ij")
            uv = np.column_stack([UU.ravel(), VV.ravel()])
            ins = inside_face(m, k, uv)
            D = s.evaluate(uv[ins, 0], uv[ins, 1], nderiv=1)
            area += np.linalg.norm(np.cross(D[1], D[2]), axis=1).sum() * (u1 - u0) * (v1 - v0) / N**2
        assert abs(area - area_occ) < 1e-3 * area_occ
    finally:
        gmsh.model.remove()
    return m


def test_occ_part_multiface(files):
    with pytest.warns(IgesWarning, match=r"type 402"):
        m = read_iges(files / "occ_part.igs")
    assert m.skipped == {402: 1}
    assert len(m.surfaces) == 7  # 6 planes + the cylindrical hole (120)
    assert sum(len(h) for h in m.trim_holes) == 2  # top and bottom faces have the hole
    check_against_occ(files / "occ_part.igs")


@pytest.mark.parametrize(
    "name,build",
    [
        ("wedge_sphere", lambda: gmsh.model.occ.addSphere(0.3, 0, 0, 1, -1, -0.5, 1.2, 4.0)),
        ("part_torus", lambda: gmsh.model.occ.addTorus(0.1, 0.2, 0.3, 1, 0.3, -1, 2.5)),
        ("cone", lambda: gmsh.model.occ.addCone(0, 0, 0, 0.3, 0.2, 1, 0.5, 0.2, -1, 4.0)),
    ],
)
def test_occ_partial_revolutions(tmp_path, occ, name, build):
    """Partial revolutions: the sense of rotation of entity 120 and the trimming loops matter."""
    gmsh.model.add(name)
    try:
        build()
        gmsh.model.occ.synchronize()
        gmsh.write(str(tmp_path / f"{name}.igs"))
    finally:
        gmsh.model.remove()
    check_against_occ(tmp_path / f"{name}.igs")


# ======================================================================
# writer
# ======================================================================
def random_curve(rng, closed_knots=True) -> NurbsCurve:
    p = int(rng.integers(1, 5))
    n = int(rng.integers(p + 1, p + 8))
    if closed_knots:
        inner = np.sort(rng.uniform(0.1, 3.0, n - p - 1))
        if len(inner) > 1:
            inner[1] = inner[0]  # a double knot
        U = np.concatenate([[0.0] * (p + 1), inner, [3.3] * (p + 1)])
    else:
        U = np.sort(rng.uniform(-1, 2, n + p + 1))
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


def test_round_trip_exact(tmp_path):
    rng = np.random.default_rng(1)
    curves = [random_curve(rng, k % 2 == 0) for k in range(8)]
    surfaces = [random_surface(rng) for _ in range(6)]
    path = tmp_path / "rt.igs"
    write_iges(path, curves, surfaces, units="M", author="me")
    text = path.read_text()
    lines = text.splitlines()
    assert all(len(s) == 80 for s in lines)
    counts = {c: sum(1 for s in lines if s[72] == c) for c in "SGDPT"}
    t = lines[-1]
    assert [int(t[8 * k + 1:8 * k + 8]) for k in range(4)] == [counts[c] for c in "SGDP"]
    m = read_iges(path)
    assert m.units == "M" and m.unit_flag == 6
    assert len(m.curves) == 8 and len(m.surfaces) == 6
    for a, b in zip(curves, m.curves):
        assert a.degree == b.degree
        for attr in ("knots", "control_points", "weights"):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
    for a, b in zip(surfaces, m.surfaces):
        assert (a.degree_u, a.degree_v) == (b.degree_u, b.degree_v)
        for attr in ("knots_u", "knots_v", "control_points", "weights"):
            np.testing.assert_array_equal(getattr(a, attr), getattr(b, attr))
    # writing what was read gives the same file
    (tmp_path / "again").mkdir()
    write_iges(tmp_path / "again" / "rt.igs", m.curves, m.surfaces, units="M", author="me")
    assert (tmp_path / "again" / "rt.igs").read_text() == text


def test_written_files_imported_by_occ(tmp_path, files, occ):
    rng = np.random.default_rng(7)
    dfg = read_iges(files / "dfg_circle.igs").curves
    torus = read_iges(files / "occ_torus.igs").surfaces
    cyl = quiet_read(files / "kadir_cylinder.igs").surfaces
    curves = dfg + [random_curve(rng) for _ in range(2)]
    surfaces = torus + cyl + [random_surface(rng) for _ in range(3)]
    path = tmp_path / "ours.igs"
    write_iges(path, curves, surfaces)
    occ_import(path)
    try:
        faces = [t for _, t in gmsh.model.getEntities(2)]
        assert len(faces) == len(surfaces)
        for s, f in zip(surfaces, faces):
            # closest points (OCC's projection is unreliable exactly at the domain corners,
            # so the samples stay inside the parameter domain)
            u = np.linspace(*s.domain_u, 19)[1:-1]
            v = np.linspace(*s.domain_v, 21)[1:-1]
            U, V = np.meshgrid(u, v, indexing="ij")
            P = s.evaluate(U.ravel(), V.ravel())[0]
            assert occ_distance(2, P).max() < 1e-9 * s.bbox_size
            # and the imported surface has our parametrisation: same points at the same (u, v)
            lo, hi = gmsh.model.getParametrizationBounds(2, f)
            np.testing.assert_allclose(lo, [s.domain_u[0], s.domain_v[0]], atol=1e-15)
            np.testing.assert_allclose(hi, [s.domain_u[1], s.domain_v[1]], atol=1e-15)
            Uf, Vf, P = sample_surface(s, 17, 19)
            val = np.reshape(gmsh.model.getValue(2, f, np.column_stack([Uf, Vf]).ravel().tolist()), (-1, 3))
            assert np.abs(val - P).max() < 1e-12 * s.bbox_size
        edges = [t for _, t in gmsh.model.getEntities(1)]
        for c in curves:
            # OCC splits curves at C1 breaks (double knots) into edges, and its projection
            # onto an edge is inaccurate (~1e-9) right at the edge ends: sample between knots
            u = np.linspace(*c.domain, 201)
            k = c.distinct_knots
            u = u[np.min(np.abs(u[:, None] - k[None, :]), axis=1) > 1e-3 * np.ptp(c.domain)]
            P = c.evaluate(u)[0]
            assert occ_distance(1, P).max() < 1e-9 * c.bbox_size
            # the edges carry our parametrisation: same points at the same parameters
            covered = 0.0
            for t in edges:
                (a,), (b,) = gmsh.model.getParametrizationBounds(1, t)
                if not (c.domain[0] <= a < b <= c.domain[1]):
                    continue
                ut = np.linspace(a, b, 11)
                val = np.reshape(gmsh.model.getValue(1, t, ut.tolist()), (-1, 3))
                if np.abs(val - c.evaluate(ut)[0]).max() < 1e-12 * c.bbox_size:
                    covered += b - a
            assert abs(covered - np.ptp(c.domain)) < 1e-12 * np.ptp(c.domain)
    finally:
        gmsh.model.remove()


# ======================================================================
# format variants
# ======================================================================
def variant_texts():
    """(name, text) of the same circle with different number spellings / line ends."""
    c = make_iges.circle_curve((0.2, 0.2, 0.0), 0.05)
    toks = I._curve_params(c)
    base = format_iges([(126, 0, toks)])

    def respell(fmt):
        out = toks[:7]  # type, K, M, PROP1-4 stay integers
        out += [fmt(float(x)) for x in toks[7:]]
        return format_iges([(126, 0, out)])

    yield "base", base
    yield "D exponent", respell(lambda x: f"{x:.17E}".replace("E", "D"))
    yield "d exponent", respell(lambda x: f"{x:.17e}".replace("e", "d"))
    yield "e exponent", respell(lambda x: f"{x:.17e}")
    yield "spaces", respell(lambda x: f" {x!r} ")
    yield "trailing blanks stripped", "\n".join(s.rstrip() for s in base.splitlines()) + "\n"
    yield "CRLF", base.replace("\n", "\r\n")
    yield "CR", base.replace("\n", "\r")
    yield "no newline", base.replace("\n", "")
    yield "missing normal", format_iges([(126, 0, toks[:-3])])
    yield "missing range and normal", format_iges([(126, 0, toks[:-5])])
    yield "bytes", base.encode("ascii")


def test_variants_parse_identically():
    ref = read_iges(dict(variant_texts())["base"]).curves[0]
    seen = 0
    for name, text in variant_texts():
        m = read_iges(text)
        assert len(m.curves) == 1, name
        c = m.curves[0]
        for attr in ("knots", "control_points", "weights"):
            np.testing.assert_array_equal(getattr(c, attr), getattr(ref, attr), err_msg=name)
        seen += 1
    assert seen == 12


def test_occ_file_crlf_and_stripped(files):
    text = (files / "occ_part.igs").read_text()
    ref = quiet_read(text)
    for t in (text.replace("\n", "\r\n"), "\n".join(s.rstrip() for s in text.splitlines())):
        m = quiet_read(t)
        assert len(m.surfaces) == len(ref.surfaces)
        for a, b in zip(ref.surfaces, m.surfaces):
            np.testing.assert_array_equal(a.control_points, b.control_points)


# ======================================================================
# bad inputs
# ======================================================================
def kadir_lines() -> list[str]:
    return make_iges.kadir_circle_text().splitlines()


def set_p(lines, k, data):
    """Replace the data columns of P line k (1-based) keeping the layout."""
    i = next(j for j, s in enumerate(lines) if s[72] == "P" and int(s[73:]) == k)
    assert len(data) <= 64
    lines[i] = f"{data:<64s}" + lines[i][64:]
    return lines


def join(lines):
    return "\n".join(lines) + "\n"


def bad_truncated():
    return join(kadir_lines()[:-3])


def bad_t_count():
    ls = kadir_lines()
    ls[-1] = ls[-1].replace("P     16", "P     17")
    return join(ls)


def bad_missing_p_line():
    ls = kadir_lines()
    del ls[10]
    return join(ls)


def bad_layout():  # whitespace collapsed, as in the thesis' text or the GiD file of seed 000
    return join([" ".join(s.split()) for s in kadir_lines()])


def bad_long_line():
    ls = kadir_lines()
    ls[3] = ls[3] + "XYZ"
    return join(ls)


def bad_non_numeric():
    return join(set_p(kadir_lines(), 4, "0.0,0.0,0.0,0.2x,0.25,0.5,0.5,0.75,0.75,1.0,1.0,1.0,"))


def bad_nan():
    return join(set_p(kadir_lines(), 5, "1.0,NaN,1.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,"))


def bad_inf():
    return join(set_p(kadir_lines(), 6, "0.25,1.0D999,0.0,"))


def bad_decreasing():
    return join(set_p(kadir_lines(), 4, "0.0,0.0,0.0,0.25,0.25,0.75,0.5,0.75,0.75,1.0,1.0,1.0,"))


def bad_knot_count():  # one knot missing for K=8, M=2
    return join(set_p(kadir_lines(), 4, "0.0,0.0,0.0,0.25,0.25,0.5,0.5,0.75,1.0,1.0,1.0,"))


def bad_degree_count():  # M=3 with the same 12 knots
    return join(set_p(kadir_lines(), 2, "8,3,"))


def bad_zero_weight():
    return join(set_p(kadir_lines(), 5, "1.0,0.707107,0.0,0.707107,1.0,0.707107,1.0,0.707107,1.0,"))


def bad_negative_weight():
    return join(set_p(kadir_lines(), 5, "1.0,0.707107,1.0,-0.707107,1.0,0.707107,1.0,0.707107,1.0,"))


def bad_k_less_than_m():
    return join(set_p(kadir_lines(), 2, "1,2,"))


def bad_no_supported():
    return text_of(E(212, [1, 5, 0.1, 0.1, 0, 0.0, 0.0, 0, 0, 0.0, 0.0, 0.0, "5HHELLO"]),
                   E(406, [1, "4Hname"], form=15))


def bad_de_field():
    ls = kadir_lines()
    i = next(j for j, s in enumerate(ls) if s[72] == "D")
    ls[i] = ls[i][:32] + "     abc" + ls[i][40:]
    return join(ls)


def bad_no_record_delimiter():
    return join(set_p(kadir_lines(), 16, "0.0,0.0,1.0,"))


def bad_entity_mismatch():
    return join(set_p(kadir_lines(), 1, "128,"))


def bad_section_order():
    ls = kadir_lines()
    ls[1], ls[2] = ls[2], ls[1]
    return join(ls)


def bad_odd_d():
    ls = kadir_lines()
    i = next(j for j, s in enumerate(ls) if s[72] == "D")
    del ls[i + 1]
    ls[-1] = ls[-1].replace("D      2", "D      1")
    return join(ls)


def bad_dangling_pointer():
    return text_of(E(102, [2, 3, 99]), E(110, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0], status="00010000"))


def bad_circular():  # DE 3 contains itself
    return text_of(E(102, [1, 3]), E(102, [2, 5, 3], status="00010000"),
                   E(110, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0], status="00010000"))


def bad_overflow():  # finite numbers whose homogeneous form (w P) overflows
    c = make_iges.circle_curve()
    t = I._curve_params(c)
    t[7 + 12:7 + 12 + 9] = ["1.0E300"] * 9
    t[7 + 21:7 + 21 + 27] = ["1.0E300"] * 27
    return format_iges([(126, 0, t)])


def bad_empty():
    return "\n\n"


def bad_zero_radius():
    return text_of(E(100, [0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]))


BAD = [
    (bad_truncated, "truncated file"),
    (bad_t_count, "Terminate record says section P has 17"),
    (bad_missing_p_line, "Terminate record says section P has 16"),
    (bad_layout, "wrong column layout"),
    (bad_long_line, "80 columns"),
    (bad_non_numeric, "non-numeric value '0.2x'"),
    (bad_nan, "non-numeric value 'NaN'"),
    (bad_inf, "not finite"),
    (bad_decreasing, "knot vector T is decreasing"),
    (bad_knot_count, "wrong knot vector length"),
    (bad_degree_count, "wrong knot vector length"),
    (bad_zero_weight, "weights must be positive"),
    (bad_negative_weight, "weights must be positive"),
    (bad_k_less_than_m, "fewer than degree+1"),
    (bad_no_supported, "no supported curve or surface"),
    (bad_de_field, "not an integer"),
    (bad_no_record_delimiter, "record delimiter"),
    (bad_entity_mismatch, "not the entity type 126"),
    (bad_section_order, "sections must come in the order"),
    (bad_odd_d, "odd number of Directory Entry lines"),
    (bad_dangling_pointer, "does not point to a directory entry"),
    (bad_circular, "circular reference"),
    (bad_overflow, "overflow"),
    (bad_empty, "empty file"),
    (bad_zero_radius, "zero radius"),
]


@pytest.mark.parametrize("make,msg", BAD, ids=[f.__name__ for f, _ in BAD])
def test_bad_input(make, msg):
    text = make()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IgesWarning)
        with pytest.raises(IgesError, match=None) as info:
            read_iges(text)
    assert msg in str(info.value), str(info.value)


def test_bad_input_messages_locate_the_problem():
    with pytest.raises(IgesError) as info:
        read_iges(bad_decreasing())
    assert "DE 1" in str(info.value) and "entity 126" in str(info.value) and "file line" in str(info.value)
    with pytest.raises(IgesError) as info:
        read_iges(bad_layout())
    assert "line 1" in str(info.value)
    with pytest.raises(IgesError, match="cannot read IGES file"):
        read_iges("/nonexistent/file.igs")


def test_nurbs_error_is_wrapped(monkeypatch):
    def refuse(**kw):
        raise I.NurbsError("refused by the NURBS class")

    monkeypatch.setattr(I, "NurbsCurve", refuse)
    with pytest.raises(IgesError, match=r"DE 1 \(126\): invalid NURBS: refused by the NURBS class"):
        read_iges(make_iges.kadir_circle_text())


def test_bad_input_count():
    assert len(BAD) >= 12


# ======================================================================
# fuzzing
# ======================================================================
def _fuzz_sources() -> list[str]:
    arc = text_of(
        E(144, [3, 1, 0, 11]),
        E(120, [5, 9, 0.0, 2 * math.pi], status="00010000"),
        E(110, [0.0, 0.0, 0.0, 0.0, 0.0, 1.0], status="00010000"),
        E(124, [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 1.0, 0.0, 0.0]),
        E(100, [0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0], trans=7, status="00010000"),
        E(142, [0, 3, 13, 0, 1], status="00010500"),
        E(102, [2, 15, 17], status="00010500"),
        E(110, [1.5, 6.0, 0.0, -1.5, 6.0, 0.0], status="00010500"),
        E(110, [-1.5, 0.1, 0.0, 1.5, 0.1, 0.0], status="00010500"),
    )
    return [make_iges.kadir_circle_text(), make_iges.kadir_cylinder_text(), arc]


FUZZ_SOURCES = _fuzz_sources()
FUZZ_CHARS = list(",;0123456789.-+EDHe PGDST\n")


def mutate(text: str, ops) -> str:
    for op, pos, ch in ops:
        if not text:
            break
        i = pos % len(text)
        if op == "flip":
            text = text[:i] + ch + text[i + 1:]
        elif op == "delete":
            text = text[:i] + text[i + 1:]
        elif op == "insert":
            text = text[:i] + ch + text[i:]
        else:  # truncate one line
            lines = text.split("\n")
            k = pos % len(lines)
            lines[k] = lines[k][: (pos // 7) % 81]
            text = "\n".join(lines)
    return text


@settings(max_examples=3000, deadline=2000, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(
    src=st.integers(0, len(FUZZ_SOURCES) - 1),
    ops=st.lists(
        st.tuples(st.sampled_from(["flip", "delete", "insert", "truncate"]),
                  st.integers(0, 10**6), st.sampled_from(FUZZ_CHARS)),
        min_size=1, max_size=6,
    ),
)
def test_fuzz_reader_only_raises_iges_error(src, ops):
    text = mutate(FUZZ_SOURCES[src], ops)
    old = I._WRAP_INTERNAL_ERRORS
    I._WRAP_INTERNAL_ERRORS = False  # let reader bugs surface as themselves
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                out = read_iges(text)
            except IgesError:
                return
        assert isinstance(out, IgesModel)
        assert out.curves or out.surfaces
    finally:
        I._WRAP_INTERNAL_ERRORS = old


def test_fuzz_sources_are_valid():
    for t in FUZZ_SOURCES:
        m = quiet_read(t)
        assert m.curves or m.surfaces


# ======================================================================
# analytic entities (hand-built files)
# ======================================================================
def test_arc_100():
    c, r, zt = np.array([1.0, 2.0]), 0.5, 0.3
    a0, a1 = math.radians(30), math.radians(250)
    s = c + r * np.array([math.cos(a0), math.sin(a0)])
    e = c + r * np.array([math.cos(a1), math.sin(a1)])
    m = read_iges(text_of(E(100, [zt, *c, *s, *e])))
    (crv,) = m.curves
    assert crv.degree == 2
    P = sample_curve(crv, 1001)
    np.testing.assert_allclose(np.linalg.norm(P[:, :2] - c, axis=1), r, rtol=1e-13)
    np.testing.assert_allclose(P[:, 2], zt, rtol=0, atol=1e-15)
    np.testing.assert_allclose(P[0, :2], s, atol=1e-14)
    np.testing.assert_allclose(P[-1, :2], e, atol=1e-14)
    ang = np.unwrap(np.arctan2(P[:, 1] - c[1], P[:, 0] - c[0]))
    assert np.all(np.diff(ang) > 0)  # counterclockwise
    assert abs(ang[-1] - ang[0] - (a1 - a0)) < 1e-12
    # full circle: start == terminate point
    m = read_iges(text_of(E(100, [zt, *c, *s, *s])))
    P = sample_curve(m.curves[0], 1001)
    ang = np.unwrap(np.arctan2(P[:, 1] - c[1], P[:, 0] - c[0]))
    assert abs(ang[-1] - ang[0] - 2 * math.pi) < 1e-12
    np.testing.assert_allclose(np.linalg.norm(P[:, :2] - c, axis=1), r, rtol=1e-13)


def test_arc_with_chained_124():
    RA, tA = rot("x", math.pi / 2), np.array([1.0, 0.0, 0.0])
    RB, tB = rot("z", 0.4), np.array([0.0, 0.0, 2.0])
    c, r, zt = np.array([0.5, -0.25]), 0.75, -0.1
    s = c + [r, 0.0]
    e = c + [0.0, r]
    m = read_iges(text_of(
        E(100, [zt, *c, *s, *e], trans=3),  # DE 1 -> 124 at DE 3
        e124(RA, tA, trans=5),  # DE 3 -> DE 5 (chained)
        e124(RB, tB),  # DE 5
    ))
    assert len(m.curves) == 1 and not m.surfaces and m.skipped == {}
    P = sample_curve(m.curves[0], 501)
    # undo x_model = RB (RA x + tA) + tB
    X = ((P - tB) @ RB - tA) @ RA
    np.testing.assert_allclose(X[:, 2], zt, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(X[:, :2] - c, axis=1), r, rtol=1e-13)
    np.testing.assert_allclose(X[0, :2], s, atol=1e-14)
    np.testing.assert_allclose(X[-1, :2], e, atol=1e-14)


def test_line_110():
    p1, p2 = np.array([1.0, -2.0, 0.5]), np.array([-3.0, 4.0, 2.0])
    m = read_iges(text_of(E(110, [*p1, *p2])))
    (c,) = m.curves
    assert c.degree == 1
    t = np.linspace(*c.domain, 11)
    s = (t - t[0]) / (t[-1] - t[0])
    np.testing.assert_allclose(c.evaluate(t)[0], p1 + s[:, None] * (p2 - p1), atol=1e-15)


def test_composite_102():
    # stadium half: line (0,0)-(1,0), arc centre (1,0.5) r 0.5 from -90 to 90 deg, line (1,1)-(0,1)
    m = read_iges(text_of(
        E(102, [3, 3, 5, 7]),
        E(110, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0], status="00010000"),
        E(100, [0.0, 1.0, 0.5, 1.0, 0.0, 1.0, 1.0], status="00010000"),
        E(110, [1.0, 1.0, 0.0, 0.0, 1.0, 0.0], status="00010000"),
    ))
    assert len(m.curves) == 1 and m.skipped == {}
    c = m.curves[0]
    assert c.degree == 2
    P = sample_curve(c, 3001)
    on_l1 = (np.abs(P[:, 1]) < 1e-14) & (P[:, 0] >= -1e-14) & (P[:, 0] <= 1 + 1e-14)
    on_l2 = (np.abs(P[:, 1] - 1) < 1e-14) & (P[:, 0] >= -1e-14) & (P[:, 0] <= 1 + 1e-14)
    on_arc = (np.abs(np.hypot(P[:, 0] - 1, P[:, 1] - 0.5) - 0.5) < 1e-13) & (P[:, 0] >= 1 - 1e-14)
    assert np.all(on_l1 | on_l2 | on_arc)
    assert on_l1.sum() > 100 and on_l2.sum() > 100 and on_arc.sum() > 100
    np.testing.assert_allclose(P[0], [0, 0, 0], atol=1e-15)
    np.testing.assert_allclose(P[-1], [0, 1, 0], atol=1e-15)
    assert np.min(np.linalg.norm(P - [1.5, 0.5, 0], axis=1)) < 2e-3  # passes the apex
    assert np.max(np.linalg.norm(np.diff(P, axis=0), axis=1)) < 5e-3  # continuous


def test_composite_with_gap_is_split():
    with pytest.warns(IgesWarning, match="do not meet"):
        m = read_iges(text_of(
            E(102, [2, 3, 5]),
            E(110, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0], status="00010000"),
            E(110, [2.0, 0.0, 0.0, 3.0, 0.0, 0.0], status="00010000"),
        ))
    assert len(m.curves) == 2


def revolved_line_file(axis_from, axis_to, sa, ta):
    return text_of(
        E(120, [3, 5, sa, ta]),
        E(110, [*axis_from, *axis_to], status="00010000"),
        E(110, [1.0, 0.0, 0.0, 1.0, 0.0, 2.0], status="00010000"),
    )


def test_revolution_120_sense_of_rotation():
    sa, ta = 0.5, 2.0
    for to, sign in (((0.0, 0.0, 1.0), 1.0), ((0.0, 0.0, -1.0), -1.0)):
        m = read_iges(revolved_line_file((0.0, 0.0, 0.0), to, sa, ta))
        (s,) = m.surfaces
        U, V, P = sample_surface(s, 21, 41)
        np.testing.assert_allclose(np.hypot(P[:, 0], P[:, 1]), 1.0, rtol=1e-13)
        ang = sign * np.arctan2(P[:, 1], P[:, 0])  # right-handed about the axis direction
        assert ang.min() > sa - 1e-12 and ang.max() < ta + 1e-12
        assert abs(ang.min() - sa) < 1e-12 and abs(ang.max() - ta) < 1e-12
        assert P[:, 2].min() > -1e-15 and P[:, 2].max() < 2 + 1e-15
        # NURBS parameter = angle at the knots (segment ends)
        corner = s.evaluate(np.array([s.domain_u[0]]), np.array([s.domain_v[0]]))[0][0]
        np.testing.assert_allclose(corner, [math.cos(sa), sign * math.sin(sa), 0.0], atol=1e-15)


def sphere_file(loop_t=(-0.5, 0.5), loop_th=(1.0, 2.0)):
    t0, t1 = loop_t
    a0, a1 = loop_th
    return text_of(
        E(144, [3, 1, 0, 11]),  # DE 1
        E(120, [5, 7, 0.0, 2 * math.pi], status="00010000"),  # DE 3
        E(110, [0.0, 0.0, 0.0, 0.0, 0.0, 1.0], status="00010000"),  # DE 5 axis +z
        E(100, [0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0], trans=9, status="00010000"),  # DE 7
        e124(np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]), [0, 0, 0]),  # DE 9: xy -> xz
        E(142, [0, 3, 13, 0, 1], status="00010500"),  # DE 11
        E(102, [4, 15, 17, 19, 21], status="00010500"),  # DE 13
        E(110, [t0, a0, 0.0, t1, a0, 0.0], status="00010500"),
        E(110, [t1, a0, 0.0, t1, a1, 0.0], status="00010500"),
        E(110, [t1, a1, 0.0, t0, a1, 0.0], status="00010500"),
        E(110, [t0, a1, 0.0, t0, a0, 0.0], status="00010500"),
    )


def test_revolution_sphere_with_param_space_loop():
    m = read_iges(sphere_file())
    assert len(m.surfaces) == 1 and not m.curves  # param-space curves are not reported
    s, loop = m.surfaces[0], m.trim_loops[0]
    _, _, P = sample_surface(s, 51, 53)
    np.testing.assert_allclose(np.linalg.norm(P, axis=1), 1.0, rtol=1e-13)
    # IGES parameters of entity 120: (t, theta) = (generatrix arc angle, rotation angle);
    # S(t, theta) = (cos t cos theta, cos t sin theta, sin t).  The loop vertices, mapped to our
    # NURBS parameters, must land on the image of the rectangle boundary.
    Q = s.evaluate(loop[:, 0], loop[:, 1])[0]
    t = np.arcsin(np.clip(Q[:, 2], -1, 1))
    th = np.arctan2(Q[:, 1], Q[:, 0])
    on_t = np.minimum(np.abs(t + 0.5), np.abs(t - 0.5)) < 1e-12
    on_th = np.minimum(np.abs(th - 1.0), np.abs(th - 2.0)) < 1e-12
    assert np.all(on_t | on_th)
    assert t.min() > -0.5 - 1e-12 and t.max() < 0.5 + 1e-12
    assert th.min() > 1.0 - 1e-12 and th.max() < 2.0 + 1e-12
    for tc, thc in ((-0.5, 1.0), (0.5, 1.0), (0.5, 2.0), (-0.5, 2.0)):
        expect = [math.cos(tc) * math.cos(thc), math.cos(tc) * math.sin(thc), math.sin(tc)]
        assert np.min(np.linalg.norm(Q - expect, axis=1)) < 1e-13
    # a point inside the loop maps to the inside of the rectangle
    uv_in = loop.mean(axis=0)
    assert points_in_polygon(loop, uv_in[None])[0]


def test_tabulated_cylinder_122():
    r, h = 2.0, 3.0
    m = read_iges(text_of(
        E(122, [3, r, 0.0, h]),  # L = C(t0) + (0, 0, h)
        E(100, [0.0, 0.0, 0.0, r, 0.0, 0.0, r], status="00010000"),  # quarter circle
    ))
    (s,) = m.surfaces
    assert (s.degree_u, s.degree_v) == (2, 1)
    U, V, P = sample_surface(s, 31, 11)
    np.testing.assert_allclose(np.hypot(P[:, 0], P[:, 1]), r, rtol=1e-13)
    v01 = (V - V.min()) / np.ptp(V)
    np.testing.assert_allclose(P[:, 2], h * v01, atol=1e-14)
    ang = np.arctan2(P[:, 1], P[:, 0])
    assert ang.min() > -1e-14 and ang.max() < math.pi / 2 + 1e-14


def test_bounded_plane_108_and_unbounded_skipped():
    tri = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 2.0], [0.0, 4.0, 2.0]])
    ents = [
        E(108, [0.0, 0.0, 1.0, 2.0, 3, 0.0, 0.0, 0.0, 0.0], form=1),  # DE 1, bounded by DE 3
        E(102, [3, 5, 7, 9], status="00010000"),
        E(110, [*tri[0], *tri[1]], status="00010000"),
        E(110, [*tri[1], *tri[2]], status="00010000"),
        E(110, [*tri[2], *tri[0]], status="00010000"),
        E(108, [1.0, 0.0, 0.0, 5.0, 0, 0.0, 0.0, 0.0, 0.0], form=0),  # unbounded: skipped
    ]
    with pytest.warns(IgesWarning, match=r"1 entity of IGES type 108 \(.*unbounded plane"):
        m = read_iges(text_of(*ents))
    assert m.skipped == {108: 1}
    assert len(m.surfaces) == 1 and not m.curves
    s, loop = m.surfaces[0], m.trim_loops[0]
    _, _, P = sample_surface(s, 11, 11)
    np.testing.assert_allclose(P[:, 2], 2.0, atol=1e-15)
    area = 0.5 * abs(np.sum(loop[:, 0] * np.roll(loop[:, 1], -1) - np.roll(loop[:, 0], -1) * loop[:, 1]))
    assert abs(area - 6.0) < 1e-12
    Q = s.evaluate(loop[:, 0], loop[:, 1])[0]
    for corner in tri:
        assert np.min(np.linalg.norm(Q - corner, axis=1)) < 1e-14
    # a model point inside the triangle is inside the loop, one outside is not
    def uv_of(x):
        uu, vv, d = project(s, np.array([x]))
        assert d[0] < 1e-12
        return np.array([[uu[0], vv[0]]])
    assert points_in_polygon(loop, uv_of([0.5, 0.5, 2.0]))[0]
    assert not points_in_polygon(loop, uv_of([2.5, 3.0, 2.0]))[0]


def test_trimmed_144_on_128_with_hole():
    P = np.array([[[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]], [[2.0, 0.0, 0.0], [2.0, 2.0, 0.0]]])
    sq = [(0.1, 0.1), (0.9, 0.1), (0.9, 0.9), (0.1, 0.9)]
    hole = [(0.4, 0.4), (0.6, 0.4), (0.6, 0.6), (0.4, 0.6)]

    def lines(pts):
        return [E(110, [*pts[k], 0.0, *pts[(k + 1) % 4], 0.0], status="00010500") for k in range(4)]

    params128 = [1, 1, 1, 1, 0, 0, 1, 0, 0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0, 1.0,
                 1.0, 1.0, 1.0, 1.0, *P.transpose(1, 0, 2).ravel().tolist(), 0.0, 1.0, 0.0, 1.0]
    ents = [
        E(144, [3, 1, 1, 5, 17]),  # DE 1: PTS=3, PTO=5, PTI=17
        E(128, params128, status="00010000"),  # DE 3
        E(142, [0, 3, 7, 0, 1], status="00010000"),  # DE 5 outer, BPTR=7
        E(102, [4, 9, 11, 13, 15], status="00010500"),  # DE 7
        *lines(sq),  # DE 9..15
        E(142, [0, 3, 19, 0, 1], status="00010000"),  # DE 17 inner, BPTR=19
        E(102, [4, 21, 23, 25, 27], status="00010500"),  # DE 19
        *lines(hole),  # DE 21..27
    ]
    m = read_iges(text_of(*ents))
    assert not m.curves and len(m.surfaces) == 1 and m.surface_de == [1]
    loop = m.trim_loops[0]
    for c in sq:
        assert np.min(np.linalg.norm(loop - c, axis=1)) < 1e-15
    assert len(m.trim_holes[0]) == 1
    inside = inside_face(m, 0, np.array([[0.2, 0.2], [0.5, 0.5], [0.95, 0.5]]))
    assert inside.tolist() == [True, False, False]


def test_unsupported_entities_warn_once_per_type():
    ents = [
        E(110, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0]),
        E(104, [1.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 1.0]),
        E(104, [1.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 1.0]),
        E(212, [1, 5, 0.1, 0.1, 0, 0.0, 0.0, 0, 0, 0.0, 0.0, 0.0, "5HA,B;C"]),
    ]
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        m = read_iges(text_of(*ents))
    msgs = [str(w.message) for w in rec if issubclass(w.category, IgesWarning)]
    assert len(msgs) == 2
    assert any("2 entities of IGES type 104" in s for s in msgs)
    assert any("1 entity of IGES type 212" in s for s in msgs)
    assert m.skipped == {104: 2, 212: 1}
    assert len(m.curves) == 1


def test_126_subrange_trims_exactly():
    c = make_iges.circle_curve((0.0, 0.0, 0.0), 1.0)
    toks = I._curve_params(c)
    toks[-5:-3] = [F(0.1), F(0.6)]  # V(0), V(1): a proper sub-range of [0, 1]
    m = read_iges(format_iges([(126, 0, toks)]))
    d = m.curves[0]
    assert d.domain == (0.1, 0.6)
    t = np.linspace(0.1, 0.6, 101)
    np.testing.assert_allclose(d.evaluate(t)[0], c.evaluate(t)[0], atol=1e-14)


def test_make_iges_deterministic(tmp_path, files):
    make_iges.write_all(tmp_path)
    for name in ("kadir_circle.igs", "kadir_cylinder.igs", "dfg_circle.igs",
                 "occ_sphere.igs", "occ_torus.igs", "occ_part.igs"):
        assert (tmp_path / name).read_bytes() == (files / name).read_bytes(), name
