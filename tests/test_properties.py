"""Property tests (hypothesis) of the Nagata kernels and the NURBS projection.

Nagata kernels (:mod:`nagata_snap.nagata.patch`), for random valid input: unit
normals within 80 degrees of each other, finite points:

* ``curve_coefficient``, ``curve_coefficient_multi`` and ``evaluate`` never
  give NaN or infinity;
* a patch reproduces its vertices exactly (bitwise);
* a plane is reproduced exactly: all normals equal to the plane normal give
  coefficients that are exactly zero, so the patch is the flat facet (and a
  facet in ``z = 0`` evaluates to ``z = 0`` exactly);
* the curve is symmetric under edge reversal: ``c(-d, n1, n0) = c(d, n0, n1)``
  (bitwise for the multi-normal coefficient, to rounding for eq. 15);
* ``NagataGeometry.from_surface`` on random star-shaped polygons: finite
  coefficients, vertices reproduced exactly.

NURBS projection (:mod:`nagata_snap.cad.projection`), for random valid curves
and surfaces (clamped knot vectors with distinct interior knots, positive
weights; graph-like control polygons/nets, i.e. monotone in x (and y), so
that the entity does not fold back onto itself closer than its sampling):

* a point on the entity projects to itself (global search, and Newton
  seeded nearby);
* evaluating the entity at the returned parameters gives the returned point;
* projection of finite points (near or far) never returns NaN.

Runtime: derandomized, 100-200 examples per property, deadlines set (about 40 s).
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from nagata_snap import NagataGeometry
from nagata_snap.nagata import patch as N
from nagata_snap.cad.nurbs import NurbsCurve, NurbsSurface
from nagata_snap.cad.projection import GlobalSearcher, global_search, project_newton

SETTINGS = {"derandomize": True, "database": None, "deadline": 2000,
            "suppress_health_check": [HealthCheck.too_slow]}

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
point = st.tuples(finite, finite, finite).map(np.array)
scale = st.floats(1e-3, 1e3)


def rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of ``v`` about the unit ``axis``."""
    return (v * np.cos(angle) + np.cross(axis, v) * np.sin(angle)
            + axis * np.dot(axis, v) * (1.0 - np.cos(angle)))


@st.composite
def unit(draw):
    z = draw(st.floats(-1.0, 1.0))
    phi = draw(st.floats(0.0, 2 * np.pi))
    r = np.sqrt(max(0.0, 1.0 - z * z))
    v = np.array([r * np.cos(phi), r * np.sin(phi), z])
    return v / np.linalg.norm(v)


@st.composite
def near(draw, centre: np.ndarray, max_deg: float, min_deg: float = 0.0):
    """A unit vector at an angle in [min_deg, max_deg] from ``centre``."""
    other = draw(unit())
    axis = np.cross(centre, other)
    if np.linalg.norm(axis) < 1e-6:
        axis = np.cross(centre, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(centre, [0.0, 1.0, 0.0])
    axis /= np.linalg.norm(axis)
    ang = np.radians(draw(st.floats(min_deg, max_deg)))
    v = rotate(centre, axis, ang)
    return v / np.linalg.norm(v)


@st.composite
def normal_pair(draw, max_deg=80.0):
    n0 = draw(unit())
    return n0, draw(near(n0, max_deg))


# ----------------------------------------------------------------------
# Nagata kernels
# ----------------------------------------------------------------------
@settings(max_examples=200, **SETTINGS)
@given(x0=point, x1=point, n=normal_pair())
def test_curve_coefficient_finite(x0, x1, n):
    c = N.curve_coefficient(x1 - x0, n[0], n[1])
    assert np.all(np.isfinite(c))
    pts = N.curve(x0[None], x1[None], c[None], np.linspace(0, 1, 7))
    assert np.all(np.isfinite(pts))


@st.composite
def multi_normals(draw):
    """Edge with 1-2 normals per end (zero padding allowed), all within 80 deg of each other."""
    m = draw(unit())
    ends = []
    for _ in range(2):
        k = draw(st.integers(1, 2))
        ns = [draw(near(m, 40.0)) for _ in range(k)]
        ns += [np.zeros(3)] * (2 - k)
        ends.append(np.array(ns))
    return ends


@settings(max_examples=200, **SETTINGS)
@given(x0=point, x1=point, n=multi_normals())
def test_curve_coefficient_multi_finite_and_symmetric(x0, x1, n):
    d = (x1 - x0)[None]
    c = N.curve_coefficient_multi(d, n[0][None], n[1][None])
    assert np.all(np.isfinite(c))
    # reversing the edge swaps the ends: the same coefficient, bitwise
    cr = N.curve_coefficient_multi(-d, n[1][None], n[0][None])
    np.testing.assert_array_equal(c, cr)


@st.composite
def triangle(draw):
    """Finite triangle and three normals within 80 deg of each other."""
    x = np.array([draw(point) for _ in range(3)])
    m = draw(unit())
    n = np.array([draw(near(m, 40.0)) for _ in range(3)])
    return x, n


def patch_coefficients_of(x, n):
    e = N.LOCAL_EDGES[3]
    return N.curve_coefficient(x[e[:, 1]] - x[e[:, 0]], n[e[:, 0]], n[e[:, 1]])


@st.composite
def barycentric(draw, k=6, nfv=3):
    w = np.array([[draw(st.floats(0.0, 1.0)) for _ in range(nfv)] for _ in range(k)])
    w[:, 0] += 1e-3
    return w / w.sum(axis=1, keepdims=True)


@settings(max_examples=200, **SETTINGS)
@given(tri=triangle(), lam=barycentric())
def test_patch_finite_and_reproduces_vertices(tri, lam):
    x, n = tri
    c = patch_coefficients_of(x, n)
    assert np.all(np.isfinite(c))
    assert np.all(np.isfinite(N.evaluate(x[None], c[None], lam[None])))
    v = N.evaluate(x[None], c[None], np.eye(3)[None])[0]
    np.testing.assert_array_equal(v, x)  # exactly, not to rounding
    # the curve form too
    cc = N.curve_coefficient(x[1] - x[0], n[0], n[1])
    v2 = N.evaluate(x[None, :2], cc[None, None], np.eye(2)[None])[0]
    np.testing.assert_array_equal(v2, x[:2])


@settings(max_examples=150, **SETTINGS)
@given(nrm=unit(), origin=point, uv=st.lists(st.tuples(finite, finite), min_size=3, max_size=3),
       lam=barycentric(), flat_z=st.booleans())
def test_plane_is_reproduced_exactly(nrm, origin, uv, lam, flat_z):
    if flat_z:  # a facet in the plane z = 0 with normal e_z
        nrm, origin = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    a = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(nrm, a)
    x = np.array([origin + s * a + t * b for s, t in uv])
    if flat_z:
        x[:, 2] = 0.0
    n = np.repeat(nrm[None], 3, axis=0)
    c = patch_coefficients_of(x, n)
    assert np.all(c == 0.0)  # exactly flat: the patch is the straight facet
    cm = N.curve_coefficient_multi((x[1] - x[0])[None], n[None, :2], n[None, 1:])
    assert np.all(cm == 0.0)
    p = N.evaluate(x[None], c[None], lam[None])[0]
    size = np.abs(x).max() + np.abs(origin).max() + 1.0
    assert np.abs((p - origin) @ nrm).max() <= 16 * np.finfo(float).eps * size
    if flat_z:
        assert np.all(p[:, 2] == 0.0)


@st.composite
def valid_edge(draw):
    """Edge and end normals like those of a smooth curve: normals 0 or 2..80 deg apart,
    each roughly perpendicular to the edge (as on a circular arc, within 1.5x its angle)."""
    L = draw(scale)
    n0 = draw(unit())
    parallel = draw(st.booleans())
    n1 = n0.copy() if parallel else draw(near(n0, 80.0, 2.0))
    theta = np.arccos(np.clip(n0 @ n1, -1, 1))
    # chord direction: perpendicular to the bisector, in the plane of the normals (arc),
    # tilted out of that plane by a random amount
    v = n0 + n1
    v /= np.linalg.norm(v)
    t = n1 - n0 if not parallel else np.cross(n0, draw(unit()))
    t = t - (t @ v) * v
    assume(np.linalg.norm(t) > 1e-6)
    t /= np.linalg.norm(t)
    w = np.cross(v, t)
    tilt = np.radians(draw(st.floats(-60.0, 60.0)))
    lift = draw(st.floats(-1.5, 1.5)) * np.sin(theta / 2)
    d = L * (np.cos(tilt) * t + np.sin(tilt) * w + lift * v)
    return d, n0, n1


@settings(max_examples=200, **SETTINGS)
@given(e=valid_edge(), xi=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=5))
def test_curve_symmetric_under_reversal(e, xi):
    d, n0, n1 = e
    c = N.curve_coefficient(d, n0, n1)
    cr = N.curve_coefficient(-d, n1, n0)
    L = np.linalg.norm(d)
    # the same coefficient up to rounding (exactly unit normals would give it exactly)
    assert np.linalg.norm(c - cr) <= 1e-11 * (L + np.linalg.norm(c))
    x0, x1 = np.zeros(3), d
    xi = np.asarray(xi)
    fwd = N.curve(x0[None], x1[None], c[None], xi)[0]
    bwd = N.curve(x1[None], x0[None], cr[None], 1.0 - xi)[0]
    assert np.abs(fwd - bwd).max() <= 1e-11 * (L + np.linalg.norm(c))


@settings(max_examples=100, **SETTINGS)
@given(n=st.integers(5, 24), radii=st.lists(st.floats(0.7, 1.3), min_size=24, max_size=24),
       jitter=st.floats(0.0, 0.8), scale_=st.floats(1e-3, 1e3), seed=st.integers(0, 2**16))
def test_star_polygon_geometry(n, radii, jitter, scale_, seed):
    rng = np.random.default_rng(seed)
    th = 2 * np.pi * (np.arange(n) + jitter * (rng.random(n) - 0.5)) / n
    r = np.asarray(radii[:n]) * scale_
    p = np.c_[r * np.cos(th), r * np.sin(th)]
    s = np.c_[np.arange(n), (np.arange(n) + 1) % n]
    geo = NagataGeometry.from_surface(p, s)
    assert np.all(np.isfinite(geo.coef))
    verts = geo.evaluate(np.arange(n), np.broadcast_to(np.eye(2), (n, 2, 2)))
    np.testing.assert_array_equal(verts, geo.x)
    mid = geo.evaluate(np.arange(n), np.full((n, 3, 2), [[0.25, 0.75]]))
    assert np.all(np.isfinite(mid))


# ----------------------------------------------------------------------
# NURBS projection
# ----------------------------------------------------------------------
@st.composite
def knot_vector(draw, degree: int, n_ctrl: int):
    """Clamped knot vector on [0, 1] with distinct interior knots (spans >= 1/20 of the mean)."""
    n_int = n_ctrl - degree - 1
    gaps = np.array([draw(st.floats(0.05, 1.0)) for _ in range(n_int + 1)])
    interior = np.cumsum(gaps)[:-1] / gaps.sum()
    return np.r_[np.zeros(degree + 1), interior, np.ones(degree + 1)]


@st.composite
def nurbs_curve(draw):
    p = draw(st.integers(1, 3))
    n = draw(st.integers(p + 1, p + 5))
    U = draw(knot_vector(p, n))
    steps = np.array([draw(st.floats(0.1, 1.0)) for _ in range(n)])
    x = np.cumsum(steps)  # graph-like: monotone in x
    yz = np.array([[draw(st.floats(-1.0, 1.0)) for _ in range(2)] for _ in range(n)])
    planar = draw(st.booleans())
    if planar:
        yz[:, 1] = 0.0
    P = np.c_[x, yz]
    w = np.array([draw(st.floats(0.3, 3.0)) for _ in range(n)])
    return NurbsCurve(p, U, P, w)


@st.composite
def nurbs_surface(draw):
    p, q = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    nu, nv = draw(st.integers(p + 1, p + 3)), draw(st.integers(q + 1, q + 3))
    U, V = draw(knot_vector(p, nu)), draw(knot_vector(q, nv))
    x = np.cumsum([draw(st.floats(0.2, 1.0)) for _ in range(nu)])
    y = np.cumsum([draw(st.floats(0.2, 1.0)) for _ in range(nv)])
    z = np.array([[draw(st.floats(-0.5, 0.5)) for _ in range(nv)] for _ in range(nu)])
    P = np.stack([np.broadcast_to(x[:, None], (nu, nv)), np.broadcast_to(y[None], (nu, nv)), z], axis=2)
    w = np.array([[draw(st.floats(0.3, 3.0)) for _ in range(nv)] for _ in range(nu)])
    return NurbsSurface(p, q, U, V, P, w)


def entity_points(ent, params):
    if ent.param_dim == 1:
        return ent.evaluate(params[:, 0])[0]
    return ent.evaluate(params[:, 0], params[:, 1])[0]


@st.composite
def entity_and_params(draw):
    ent = draw(st.one_of(nurbs_curve(), nurbs_surface()))
    k = draw(st.integers(1, 6))
    params = np.array([[draw(st.floats(0.0, 1.0)) for _ in range(ent.param_dim)] for _ in range(k)])
    return ent, params


@settings(max_examples=150, **SETTINGS)
@given(ep=entity_and_params(), delta=st.floats(-0.02, 0.02))
def test_point_on_entity_projects_to_itself(ep, delta):
    ent, params = ep
    X = entity_points(ent, params)
    size = ent.bbox_size
    # global search (KD-tree seeds + Newton)
    _, par, dist = global_search(ent, X)
    assert np.all(dist <= 1e-9 * size), dist
    np.testing.assert_allclose(entity_points(ent, par), X, rtol=0, atol=1e-9 * size)
    # Newton seeded near the true parameters (as in refinement: the parametric midpoint)
    res = project_newton(ent, X, np.clip(params + delta, 0.0, 1.0).reshape(len(X), -1).squeeze(-1)
                         if ent.param_dim == 1 else np.clip(params + delta, 0.0, 1.0))
    assert np.all(res.distance <= 1e-9 * size), res.distance
    assert np.all(res.converged)


@st.composite
def entity_points_seeds(draw):
    ent = draw(st.one_of(nurbs_curve(), nurbs_surface()))
    k = draw(st.integers(1, 8))
    far = draw(st.sampled_from([1.0, 10.0, 1e3, 1e6]))
    X = np.array([[draw(st.floats(-far, far)) for _ in range(3)] for _ in range(k)])
    seeds = np.array([[draw(st.floats(-0.5, 1.5)) for _ in range(ent.param_dim)] for _ in range(k)])
    return ent, X, seeds


@settings(max_examples=100, **SETTINGS)
@given(eps=entity_points_seeds())
def test_projection_finite_and_consistent(eps):
    ent, X, seeds = eps
    size = ent.bbox_size
    seeds_in = seeds[:, 0] if ent.param_dim == 1 else seeds
    res = project_newton(ent, X, seeds_in)
    par = np.asarray(res.params).reshape(len(X), -1)
    for a in (par, res.points, res.distance):
        assert np.all(np.isfinite(a))
    # parameters inside the domain, and the returned point is S(params) (the last,
    # tiny Newton step is applied to first order: O(step^2) from S(params))
    assert np.all((par >= 0.0) & (par <= 1.0))
    scale_ = size + np.abs(X).max()
    np.testing.assert_allclose(entity_points(ent, par), res.points, rtol=0, atol=1e-10 * scale_)
    np.testing.assert_allclose(np.linalg.norm(res.points - X, axis=1), res.distance, rtol=0,
                               atol=1e-12 * scale_)
    # global search: finite, and S(params) is at the reported distance
    _, gp, gd = GlobalSearcher([ent]).search(X)
    assert np.all(np.isfinite(gp)) and np.all(np.isfinite(gd))
    np.testing.assert_allclose(np.linalg.norm(entity_points(ent, gp) - X, axis=1), gd, rtol=0,
                               atol=1e-10 * scale_)


def test_projection_of_extreme_but_accepted_points_is_finite():
    """Coordinates up to projection.MAX_COORD (1e100) still give finite results."""
    from nagata_snap.cad.nurbs import circle, sphere

    X = np.array([[1e100, 0.0, 0.0], [-3e99, 2e99, 1e99], [0.0, 0.0, 1e-300]])
    for ent, seeds in ((circle((0, 0, 0), 1.0), np.full(3, 0.3)), (sphere((0, 0, 0), 1.0), np.full((3, 2), 0.3))):
        res = project_newton(ent, X, seeds)
        for a in (res.params, res.points, res.distance):
            assert np.all(np.isfinite(a))
        _, p, d = global_search(ent, X)
        assert np.all(np.isfinite(p)) and np.all(np.isfinite(d))
