"""Closest-point projection (Kadir 2010 App. B, eqs. B.1/B.2) against independent truth.

Truth: analytic closest points of circles, cylinders, spheres and tori; and
OpenCASCADE's projection (``gmsh.model.getClosestPoint``) on the same
geometry built with ``gmsh.model.occ`` (primitives, and a B-spline surface
with the control net of Herrero Adan & Cardoso 2020, App. D, Example 7.1).
"""

from __future__ import annotations

import numpy as np
import pytest
from nurbs_reference import herrero_71, occ_bspline

from nagata_snap.cad.nurbs import NurbsCurve, NurbsSurface, circle, cylinder, sphere, torus
from nagata_snap.cad.projection import (
    GlobalSearcher,
    ProjectionResult,
    global_search,
    project_newton,
)

S2 = np.sqrt(0.5)


# ----------------------------------------------------------------------
# analytic closest points
# ----------------------------------------------------------------------
def closest_on_circle(P, c, R):
    """Circle in the plane z = c_z, centre c: closest point of P (off the axis)."""
    d = P - c
    d[:, 2] = 0.0
    return c + R * d / np.linalg.norm(d, axis=1)[:, None]


def closest_on_sphere(P, c, R):
    d = P - c
    return c + R * d / np.linalg.norm(d, axis=1)[:, None]


def closest_on_cylinder(P, c, R):
    """Infinite cylinder of axis z through c (the finite one when z is inside)."""
    d = P - c
    d[:, 2] = 0.0
    out = c + R * d / np.linalg.norm(d, axis=1)[:, None]
    out[:, 2] = P[:, 2]
    return out


def closest_on_torus(P, c, Rmaj, rmin):
    d = P - c
    xy = d.copy()
    xy[:, 2] = 0.0
    tube = c + Rmaj * xy / np.linalg.norm(xy, axis=1)[:, None]
    e = P - tube
    return tube + rmin * e / np.linalg.norm(e, axis=1)[:, None]


def normals(surf: NurbsSurface, u, v):
    _, Su, Sv = surf.evaluate(u, v, 1)
    n = np.cross(Su, Sv)
    return n / np.linalg.norm(n, axis=1)[:, None]


def chord_midpoints(surf: NurbsSurface, n, dparam, rng, umargin=0.0):
    """Refinement-like data: random short edges on the surface, their straight
    midpoints and the parametric midpoints of their end parameters (the seeds
    of Kadir 2.3.3)."""
    (u0, u1), _ = surf.domain_u, surf.domain_v
    u = rng.uniform(u0 + umargin, u1 - umargin, n)
    v = rng.random(n)
    ang = rng.uniform(0, 2 * np.pi, n)
    du, dv = dparam * np.cos(ang), dparam * np.sin(ang)
    a = surf.evaluate(u, v)[0]
    b = surf.evaluate(u + du, v + dv)[0]
    return 0.5 * (a + b), np.c_[u + du / 2, v + dv / 2], np.linalg.norm(a - b, axis=1)


# ----------------------------------------------------------------------
# curves
# ----------------------------------------------------------------------
def test_circle_midpoint_seeds_exact():
    c, R = np.array([0.2, 0.2, 0.0]), 0.05
    cur = circle(c, R)
    rng = np.random.default_rng(0)
    n = 5000
    t = rng.random(n)
    dt = rng.uniform(-0.04, 0.04, n)  # chords up to ~0.25 R
    a, b = cur.evaluate(t)[0], cur.evaluate(t + dt)[0]
    P = 0.5 * (a + b)
    res = project_newton(cur, P, t + dt / 2)  # unwrapped parametric midpoints
    assert isinstance(res, ProjectionResult)
    assert res.params.shape == (n,) and res.points.shape == (n, 3)
    assert res.converged.all()
    np.testing.assert_allclose(res.points, closest_on_circle(P, c, R), rtol=0, atol=1e-12 * R)
    np.testing.assert_allclose(res.distance, np.linalg.norm(res.points - P, axis=1), rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(cur.evaluate(res.params)[0], res.points, rtol=0, atol=4e-16)  # a few ulp
    assert res.iterations.max() <= 7
    assert np.all((res.params >= 0) & (res.params <= 1))  # wrapped into the domain


def test_circle_far_points_global_search_exact():
    c, R = np.array([0.2, 0.2, 0.0]), 0.05
    cur = circle(c, R)
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, 2 * np.pi, 3000)
    rad = R * rng.uniform(0.3, 2.5, 3000)  # inside and outside, several edge lengths away
    P = c + np.c_[rad * np.cos(ang), rad * np.sin(ang), rng.uniform(-0.02, 0.02, 3000)]
    ent, par, dist = global_search([cur], P)
    assert ent.shape == (3000,) and par.shape == (3000, 1)
    X = cur.evaluate(par[:, 0])[0]
    truth = closest_on_circle(P, c, R)
    np.testing.assert_allclose(X, truth, rtol=0, atol=1e-12 * R)
    np.testing.assert_allclose(dist, np.linalg.norm(truth - P, axis=1), rtol=1e-12, atol=1e-17)
    # 2D input (z = 0) is accepted
    P2 = np.c_[P[:, :2], 0 * ang]
    _, p2, d2 = global_search(cur, P[:, :2])
    truth2 = closest_on_circle(P2, c, R)
    np.testing.assert_allclose(cur.evaluate(p2[:, 0])[0], truth2, rtol=0, atol=1e-12 * R)
    np.testing.assert_allclose(d2, np.linalg.norm(truth2 - P2, axis=1), rtol=0, atol=1e-12 * R)


def test_open_curve_clamps_at_end():
    arc = NurbsCurve(2, [0, 0, 0, 1, 1, 1], [[1, 0, 0], [1, 1, 0], [0, 1, 0]], [1, S2, 1])  # quarter circle
    P = np.array([[1.2, -0.5, 0.0], [-0.5, 1.3, 0.0], [0.8, 0.1, 0.0]])
    res = project_newton(arc, P, [0.3, 0.7, 0.5])
    assert res.converged.all()
    np.testing.assert_allclose(res.points[0], [1, 0, 0], atol=1e-15)  # off the start: the end point
    np.testing.assert_allclose(res.points[1], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(res.params[:2], [0.0, 1.0], atol=0)
    np.testing.assert_allclose(res.points[2], P[2] / np.linalg.norm(P[2]), atol=1e-14)


def test_multiple_curve_patches():
    # the unit circle as four quarter arcs (four entities)
    arcs = []
    for k in range(4):
        a0, a1 = k * np.pi / 2, (k + 1) * np.pi / 2
        P = [[np.cos(a0), np.sin(a0), 0], [np.cos(a0) + np.cos(a1), np.sin(a0) + np.sin(a1), 0],
             [np.cos(a1), np.sin(a1), 0]]
        arcs.append(NurbsCurve(2, [0, 0, 0, 1, 1, 1], P, [1, S2, 1]))
    rng = np.random.default_rng(2)
    ang = rng.uniform(0, 2 * np.pi, 2000)
    ang = ang[np.min(np.abs(ang[:, None] - np.arange(5) * np.pi / 2), axis=1) > 1e-3]  # not at the joints
    rad = rng.uniform(0.5, 1.6, ang.size)
    P = np.c_[rad * np.cos(ang), rad * np.sin(ang), 0 * ang]
    ent, _, dist = global_search(arcs, P)
    np.testing.assert_array_equal(ent, (ang // (np.pi / 2)).astype(int))
    np.testing.assert_allclose(dist, np.abs(rad - 1), rtol=0, atol=1e-13)


# ----------------------------------------------------------------------
# surfaces: analytic truth
# ----------------------------------------------------------------------
@pytest.mark.parametrize("which", ["sphere", "cylinder", "torus"])
def test_surface_midpoint_seeds_exact_and_iterations(which):
    rng = np.random.default_rng(3)
    if which == "sphere":
        c, R = np.array([0.3, -0.2, 0.1]), 1.3
        surf, truth, scale, margin = sphere(c, R), lambda P: closest_on_sphere(P, c, R), R, 0.05
    elif which == "cylinder":
        c, R = np.array([0.55, 0.5, 0.0]), 0.05
        surf, truth, scale, margin = cylinder(c, R, 0.4), lambda P: closest_on_cylinder(P, c, R), R, 0.0
    else:
        c = np.array([0.0, 0.0, 1.0])
        surf, truth, scale, margin = torus(c, 2.0, 1.0), lambda P: closest_on_torus(P, c, 2.0, 1.0), 1.0, 0.0
    n = 20000
    P, seeds, _ = chord_midpoints(surf, n, 0.02, rng, margin)
    if which == "cylinder":
        keep = (P[:, 2] > 0) & (P[:, 2] < 0.4)
        P, seeds = P[keep], seeds[keep]
    res = project_newton(surf, P, seeds)
    assert res.converged.all()
    np.testing.assert_allclose(res.points, truth(P), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(res.distance, np.linalg.norm(truth(P) - P, axis=1), rtol=0, atol=1e-12 * scale)
    # Kadir Table 4.2: neighbour-seeded Newton needs at most 7 iterations, mostly 2
    assert res.iterations.max() <= 7
    assert res.iterations.mean() <= 3.0
    assert np.median(res.iterations) <= 3


def test_surface_far_points_global_search_exact():
    c = np.array([0.0, 0.0, 1.0])
    tor = torus(c, 2.0, 1.0)
    rng = np.random.default_rng(4)
    P = rng.uniform([-3.5, -3.5, -0.8], [3.5, 3.5, 2.8], (4000, 3))
    xy = np.hypot(P[:, 0], P[:, 1])
    ridge = np.hypot(xy - 2.0, P[:, 2] - 1.0)  # distance to the tube's centre circle
    P = P[(ridge > 0.1) & (xy > 0.1)]  # the closest point is unique off these sets
    _, par, dist = global_search([tor], P)
    X = tor.evaluate(par[:, 0], par[:, 1])[0]
    np.testing.assert_allclose(X, closest_on_torus(P, c, 2.0, 1.0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(dist, np.abs(ridge[(ridge > 0.1) & (xy > 0.1)] - 1.0), rtol=0, atol=1e-12)


def test_sphere_near_poles():
    c, R = np.zeros(3), 1.0
    sph = sphere(c, R)
    rng = np.random.default_rng(5)
    n = 500
    theta = rng.uniform(0, 0.2, n)  # colatitude: near the north pole, incl. almost on it
    phi = rng.uniform(0, 2 * np.pi, n)
    rad = rng.uniform(0.8, 1.2, n)
    P = rad[:, None] * np.c_[np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)]
    P[0] = [0, 0, 1.1]  # exactly above the pole
    seeds = np.c_[np.full(n, 0.95), rng.random(n)]  # arbitrary longitude
    res = project_newton(sph, P, seeds)
    # Next to the pole S_v = (A_v - B_v S)/B is a small difference of O(1)
    # terms (|S_v| ~ 1e-6 at 3e-7 from the axis), so r.S_v carries roundoff
    # ~1e-16 |r| and the longitude of points within ~1e-6 of the axis is only
    # resolved to ~1e-12 in position (observed 2.5e-12 at 2.7e-7 from the axis
    # and 0.12 below the surface).  Elsewhere the 1e-12 target holds.
    truth = closest_on_sphere(P, c, R)
    axis = np.hypot(P[:, 0], P[:, 1]) < 1e-5
    np.testing.assert_allclose(res.points[~axis], truth[~axis], rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.points[axis], truth[axis], rtol=0, atol=1e-11)
    assert res.converged.all()
    # seeded on the wrong side of the pole, Newton is clamped onto it; the
    # collapsed-edge restart must not be needed for good seeds:
    good = project_newton(sph, P, np.c_[np.full(n, 0.95), (phi / (2 * np.pi)) % 1.0])
    np.testing.assert_allclose(good.points[~axis], truth[~axis], rtol=0, atol=1e-12)


def test_project_newton_input_checks():
    sph = sphere()
    with pytest.raises(ValueError, match="shape"):
        project_newton(sph, np.zeros((3, 3)), np.zeros(3))  # surfaces need (k, 2) seeds
    with pytest.raises(ValueError, match="rows"):
        project_newton(sph, np.zeros((3, 3)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="all curves or all surfaces"):
        GlobalSearcher([sph, circle()])
    res = project_newton(sph, np.zeros((0, 3)), np.zeros((0, 2)))
    assert res.points.shape == (0, 3) and res.params.shape == (0, 2)


def test_frozen_points_keep_their_result():
    # a point whose seed is exact needs 0 iterations; others in the batch iterate
    sph = sphere()
    uv = np.array([[0.3, 0.2], [0.6, 0.7]])
    P = sph.evaluate(uv[:, 0], uv[:, 1])[0]
    P[1] *= 1.1
    res = project_newton(sph, P, np.array([[0.3, 0.2], [0.62, 0.69]]))
    assert res.iterations[0] == 0 and res.iterations[1] >= 1
    np.testing.assert_array_equal(res.params[0], [0.3, 0.2])
    assert res.converged.all()


# ----------------------------------------------------------------------
# against OpenCASCADE (gmsh.model.getClosestPoint)
# ----------------------------------------------------------------------
@pytest.fixture()
def gmsh_session():
    import gmsh

    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("projection")
    yield gmsh
    gmsh.finalize()


def _face_of_type(gmsh, kind: str) -> int:
    tags = [t for d, t in gmsh.model.getEntities(2) if gmsh.model.getType(2, t) == kind]
    assert len(tags) == 1, (kind, [(t, gmsh.model.getType(2, t)) for _, t in gmsh.model.getEntities(2)])
    return tags[0]


def _occ_closest(gmsh, tag: int, P: np.ndarray) -> np.ndarray:
    return np.array(gmsh.model.getClosestPoint(2, tag, P.ravel().tolist())[0]).reshape(-1, 3)


def _near_points(surf, n, tmax, rng, umargin=0.05, vmargin=0.0):
    (u0, u1), (v0, v1) = surf.domain_u, surf.domain_v
    u = rng.uniform(u0 + umargin, u1 - umargin, n)
    v = rng.uniform(v0 + vmargin, v1 - vmargin, n)
    t = rng.uniform(-tmax, tmax, n)
    return surf.evaluate(u, v)[0] + t[:, None] * normals(surf, u, v)


@pytest.mark.parametrize("which", ["sphere", "cylinder", "torus"])
def test_against_occ_primitives(gmsh_session, which):
    gmsh = gmsh_session
    rng = np.random.default_rng(6)
    if which == "sphere":
        c, R = np.array([0.3, -0.2, 0.1]), 1.3
        surf = sphere(c, R)
        gmsh.model.occ.addSphere(*c, R)
        kind, h, size = "Sphere", 0.1 * R, 2 * R
    elif which == "cylinder":
        c, R, H = np.array([0.55, 0.5, 0.0]), 0.05, 0.4
        surf = cylinder(c, R, H)
        gmsh.model.occ.addCylinder(*c, 0, 0, H, R)
        kind, h, size = "Cylinder", 0.1 * R, H
    else:
        c = np.array([0.0, 0.0, 1.0])
        surf = torus(c, 2.0, 1.0)
        gmsh.model.occ.addTorus(*c, 2.0, 1.0)
        kind, h, size = "Torus", 0.1, 6.0
    gmsh.model.occ.synchronize()
    tag = _face_of_type(gmsh, kind)
    # points up to three edge lengths h from the surface
    P = _near_points(surf, 1500, 3 * h, rng, umargin=0.05 if which == "sphere" else 0.0,
                     vmargin=0.05 if which == "cylinder" else 0.0)
    occ = _occ_closest(gmsh, tag, P)
    _, par, dist = global_search([surf], P)
    ours = surf.evaluate(par[:, 0], par[:, 1])[0]
    np.testing.assert_allclose(ours, occ, rtol=0, atol=1e-9 * size)
    np.testing.assert_allclose(dist, np.linalg.norm(occ - P, axis=1), rtol=0, atol=1e-9 * size)


def test_against_occ_bspline_herrero(gmsh_session):
    """Herrero Adan & Cardoso (2020) App. D, Example 7.1 net, as an OCC B-spline surface."""
    gmsh = gmsh_session
    surf = herrero_71()
    tag = occ_bspline(gmsh, surf)
    size = surf.bbox_size
    rng = np.random.default_rng(8)
    P = _near_points(surf, 1000, 4.0, rng, umargin=0.05, vmargin=0.05)  # edge length ~ a few units
    occ = _occ_closest(gmsh, tag, P)
    _, par, dist = global_search([surf], P)
    ours = surf.evaluate(par[:, 0], par[:, 1])[0]
    np.testing.assert_allclose(ours, occ, rtol=0, atol=1e-9 * size)
    np.testing.assert_allclose(dist, np.linalg.norm(occ - P, axis=1), rtol=0, atol=1e-9 * size)
    # seeded Newton from the parameter of a nearby point converges to the same point
    res = project_newton(surf, P, par + rng.uniform(-0.01, 0.01, par.shape))
    assert res.converged.all()
    np.testing.assert_allclose(res.points, occ, rtol=0, atol=1e-9 * size)


def test_maximum_is_not_reported_converged():
    # seeded exactly at the farthest point of a circle, the gradient (B.1
    # numerator) vanishes: Kadir's zero-cosine test holds at this maximum, but
    # J < 0 there, so it must not be reported as a converged closest point
    cur = circle()
    P = np.array([[0.5, 0.0, 0.0], [0.0, -1.3, 0.0]])
    far = global_search([cur], -P / np.linalg.norm(P, axis=1)[:, None])[1][:, 0]  # the antipodes
    res = project_newton(cur, P, far)
    assert not res.converged.any()
    # from a slightly perturbed seed the safeguarded iteration reaches the minimum
    res = project_newton(cur, P, far + 1e-3)
    assert res.converged.all()
    np.testing.assert_allclose(res.points, P / np.linalg.norm(P, axis=1)[:, None], rtol=0, atol=1e-14)


def test_search_grids_are_built_on_first_use_and_agree_with_the_eager_ones():
    """A searcher samples an entity only when a search needs seeds on it (a search on
    given entities: those; a global search: all), with the same samples and results."""
    c = np.zeros(3)
    ents = [sphere(c, 1.0), torus(c, 3.0, 0.5)]
    gs = GlobalSearcher(ents)
    assert gs._samples == {} and gs._all is None  # construction samples nothing
    X = closest_on_torus(np.array([[3.4, 0.2, 0.1], [-2.9, 0.3, 0.2]]), c, 3.0, 0.5) * 1.01
    _, _, dist = gs.search_on(X, [1, 1])
    assert set(gs._samples) == {1} and gs._all is None
    np.testing.assert_allclose(dist, np.linalg.norm(closest_on_torus(X, c, 3.0, 0.5) - X, axis=1), atol=1e-12)
    e, _, d = gs.search(X)
    assert set(gs._samples) == {0, 1} and np.all(e == 1)
    np.testing.assert_allclose(d, dist, atol=1e-12)
    P1, X1 = gs.entity_samples(1)
    n0 = len(gs.entity_samples(0)[0])
    np.testing.assert_array_equal(gs.sample_params[n0:], P1)
    np.testing.assert_array_equal(gs.sample_points[n0:], X1)
    np.testing.assert_array_equal(gs.sample_entity, np.repeat([0, 1], [n0, len(P1)]))


class _Vectorised(NurbsSurface):
    """A NURBS surface that :func:`project_newton` iterates with its vectorised numpy loop
    (the compiled kernel serves :class:`NurbsSurface` itself only)."""


@pytest.mark.parametrize("which", ["sphere", "cylinder", "torus", "bspline"])
@pytest.mark.parametrize("max_iter", [3, 20])
def test_compiled_surface_newton_follows_the_vectorised_iteration(which, max_iter):
    # the compiled per-point Newton must give the vectorised loop's iterates to the bit:
    # near and far points, random seeds (Gauss-Newton steps, halvings, clamping at the open
    # directions' bounds, poles, wrapping), and points stopped by the iteration limit
    rng = np.random.default_rng(11)
    if which == "sphere":
        surf = sphere(np.array([0.3, -0.2, 0.1]), 1.3)
    elif which == "cylinder":
        surf = cylinder(np.array([0.5, 0.5, 0.0]), 0.3, 0.4)
    elif which == "torus":
        surf = torus(np.array([0.0, 0.0, 1.0]), 2.0, 1.0)
    else:  # a wavy open patch of degree (3, 2)
        u, v = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 5), indexing="ij")
        net = np.stack([u, v, 0.2 * rng.standard_normal(u.shape)], axis=-1)
        surf = NurbsSurface(3, 2, [0, 0, 0, 0, 0.4, 0.7, 1, 1, 1, 1], [0, 0, 0, 0.3, 0.6, 1, 1, 1], net,
                            np.ones(u.shape))
    vec = _Vectorised(surf.degree_u, surf.degree_v, surf.knots_u, surf.knots_v, surf.control_points,
                      surf.weights)
    lo, hi = surf.bbox
    P = rng.uniform(lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo), (600, 3))
    b = surf.bounds
    seeds = rng.uniform(b[:, 0], b[:, 1], (600, 2))
    seeds[:50, 1] = b[1, 0]  # on a bound of the second direction (a pole of the sphere)
    fast, ref = project_newton(surf, P, seeds, max_iter), project_newton(vec, P, seeds, max_iter)
    assert (~ref.converged).any() or max_iter == 20  # the limit is reached with 3 iterations
    for name in ("params", "points", "distance", "iterations", "converged"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(ref, name), err_msg=name)
