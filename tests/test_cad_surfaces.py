"""Analytic surfaces and curves (nagata_snap.cad.surfaces / .curves) against OpenCASCADE.

The same placements are built as OCC ``Geom_*`` surfaces and curves; points
(near and far, on the axis, at the poles, at the apex, across the seam) are
projected by our closed form and by ``GeomAPI_ProjectPointOnSurf`` /
``GeomAPI_ProjectPointOnCurve``; evaluation and normals are compared with
``Geom_Surface.D1`` / ``GeomLProp_SLProps``.
"""

from __future__ import annotations

import numpy as np
import pytest

from nagata_snap.cad.curves import Circle, Line
from nagata_snap.cad.projection import project_newton
from nagata_snap.cad.surfaces import Cone, Cylinder, Plane, Sphere, Torus

from OCP.Geom import (
    Geom_Circle,
    Geom_ConicalSurface,
    Geom_CylindricalSurface,
    Geom_Line,
    Geom_Plane,
    Geom_SphericalSurface,
    Geom_ToroidalSurface,
    Geom_TrimmedCurve,
)
from OCP.GeomAPI import GeomAPI_ProjectPointOnCurve, GeomAPI_ProjectPointOnSurf
from OCP.GeomLProp import GeomLProp_SLProps
from OCP.gp import gp_Ax2, gp_Ax3, gp_Circ, gp_Dir, gp_Lin, gp_Pnt

RNG = np.random.default_rng(7)
O = np.array([0.3, -0.2, 0.5])
Z = np.array([1.0, 2.0, 2.0]) / 3.0
X = np.cross(Z, [0.0, 0.0, 1.0])
X /= np.linalg.norm(X)
Y = np.cross(Z, X)
BOX = [[0.0, 2 * np.pi], [-1.0, 1.0]]


def ax3(left: bool = False) -> gp_Ax3:
    a = gp_Ax3(gp_Pnt(*O), gp_Dir(*Z), gp_Dir(*X))
    if left:
        a.YReverse()
    return a


def frame(left: bool = False):
    return (O, X, -Y if left else Y, Z)


CASES = {
    "plane": (lambda lf: Plane(*frame(lf), [[-1, 1], [-1, 1]]), lambda lf: Geom_Plane(ax3(lf))),
    "cylinder": (lambda lf: Cylinder(*frame(lf), 0.7, BOX), lambda lf: Geom_CylindricalSurface(ax3(lf), 0.7)),
    "cone": (lambda lf: Cone(*frame(lf), 0.4, 0.5, [[0, 2 * np.pi], [-0.5, 1.0]]),
             lambda lf: Geom_ConicalSurface(ax3(lf), 0.5, 0.4)),
    # the other nappe (v below the apex): the generator at negative radius, u + pi
    "cone_lower": (lambda lf: Cone(*frame(lf), 0.4, 0.5, [[0, 2 * np.pi], [-2.5, -1.0]]),
                   lambda lf: Geom_ConicalSurface(ax3(lf), 0.5, 0.4)),
    "sphere": (lambda lf: Sphere(*frame(lf), 0.9, [[0, 2 * np.pi], [-np.pi / 2, np.pi / 2]]),
               lambda lf: Geom_SphericalSurface(ax3(lf), 0.9)),
    "torus": (lambda lf: Torus(*frame(lf), 1.0, 0.3, [[0, 2 * np.pi], [0, 2 * np.pi]]),
              lambda lf: Geom_ToroidalSurface(ax3(lf), 1.0, 0.3)),
}


def occ_project(s, X):
    out = np.empty((len(X), 2))
    dist = np.empty(len(X))
    for i, x in enumerate(X):
        pr = GeomAPI_ProjectPointOnSurf(gp_Pnt(*x), s)
        out[i] = pr.LowerDistanceParameters()
        dist[i] = pr.LowerDistance()
    return out, dist


def near_points(surf, n, spread):
    u = RNG.uniform(*surf.bounds[0], n)
    v = RNG.uniform(*surf.bounds[1], n)
    S = surf._points(u, v)
    return S + RNG.normal(scale=spread, size=S.shape)


@pytest.mark.parametrize("left", [False, True])
@pytest.mark.parametrize("kind", sorted(CASES))
def test_evaluation_and_normals_match_occ(kind, left):
    ours, theirs = CASES[kind][0](left), CASES[kind][1](left)
    u = RNG.uniform(*ours.bounds[0], 40)
    v = RNG.uniform(*ours.bounds[1], 40)
    S, Su, Sv = ours.evaluate(u, v, 1)
    N = ours.normals(np.c_[u, v])
    for i in range(40):
        p = theirs.Value(u[i], v[i])
        assert np.allclose(S[i], [p.X(), p.Y(), p.Z()], atol=1e-15, rtol=0)
        props = GeomLProp_SLProps(theirs, u[i], v[i], 1, 1e-12)
        d1u, d1v = props.D1U(), props.D1V()
        assert np.allclose(Su[i], [d1u.X(), d1u.Y(), d1u.Z()], atol=1e-14)
        assert np.allclose(Sv[i], [d1v.X(), d1v.Y(), d1v.Z()], atol=1e-14)
        n = props.Normal()
        assert np.allclose(N[i], [n.X(), n.Y(), n.Z()], atol=1e-13)


@pytest.mark.parametrize("left", [False, True])
@pytest.mark.parametrize("kind", sorted(CASES))
def test_closest_point_matches_occ(kind, left):
    ours, theirs = CASES[kind][0](left), CASES[kind][1](left)
    X = np.concatenate([near_points(ours, 200, 0.05), near_points(ours, 50, 0.3)])
    P, S, d = ours.closest(X)
    uv, dref = occ_project(theirs, X)
    if kind.startswith("cone"):  # OCC's cone has both nappes; ours the face's
        keep = ours.nappe * (uv[:, 1] - ours.v_apex) >= 0
        X, P, S, d, uv, dref = X[keep], P[keep], S[keep], d[keep], uv[keep], dref[keep]
        assert keep.sum() > 200
    size = ours.bbox_size
    np.testing.assert_allclose(d, dref, rtol=0, atol=1e-14 * size)
    np.testing.assert_allclose(ours._points(P[:, 0], P[:, 1]), S, rtol=0, atol=1e-15 * size)
    # the same parameters (u modulo the period)
    for a, per in enumerate(ours.periods):
        du = P[:, a] - uv[:, a]
        if np.isfinite(per):
            du = (du + per / 2) % per - per / 2
        np.testing.assert_allclose(du, 0, atol=1e-9)


@pytest.mark.parametrize("left", [False, True])
def test_tangents_of_surfaces_of_revolution_are_the_kernels(left):
    """_tangents_soa is _eval_soa's first derivatives (equal but for the signs of zeros), and
    the offset lengths of the refinement from them are the same to the last bit."""
    from nagata_snap.cad.topology import _lengths

    for kind in ("cylinder", "cone", "cone_lower", "sphere", "torus"):
        surf = CASES[kind][0](left)
        u = np.r_[RNG.uniform(*surf.bounds[0], 200), 0.0, np.pi / 2, np.pi, 1.5 * np.pi]
        v = np.r_[RNG.uniform(*surf.bounds[1], 200), surf.bounds[1], surf.bounds[1]]
        P = np.ascontiguousarray(np.stack([u, v]))
        D = surf._eval_soa(P, 1)
        Su, Sv = surf._tangents_soa(P)
        assert np.array_equal(Su, D[1]) and np.array_equal(np.broadcast_to(Sv, D[2].shape), D[2])
        a, b = RNG.normal(size=(2, len(u))) * RNG.choice([0.0, 1e-9, 1.0], size=(2, len(u)))
        assert _lengths(a, b, Su, Sv).tobytes() == _lengths(a, b, D[1], D[2]).tobytes()


def test_degenerate_points_take_the_seed():
    """On the axis, at the poles, at the apex and on a torus' tube centre the free
    parameter is the seed's; the foot point is still the exact one."""
    O0, e = np.zeros(3), np.eye(3)
    cyl = Cylinder(O0, e[0], e[1], e[2], 1.0, BOX)
    P, S, d = cyl.closest([[0, 0, 0.3]], [[1.25, 0.0]])
    assert P[0, 0] == 1.25 and P[0, 1] == 0.3 and abs(d[0] - 1.0) < 1e-15
    sph = Sphere(O0, e[0], e[1], e[2], 2.0, [[0, 2 * np.pi], [-np.pi / 2, np.pi / 2]])
    P, S, d = sph.closest([[0, 0, 3.0], [0, 0, -0.5]], [[0.7, 0.0], [2.0, 0.0]])
    np.testing.assert_allclose(P, [[0.7, np.pi / 2], [2.0, -np.pi / 2]], atol=1e-15)
    np.testing.assert_allclose(S, [[0, 0, 2.0], [0, 0, -2.0]], atol=1e-15)
    np.testing.assert_allclose(sph.normals(P), [[0, 0, 1.0], [0, 0, -1.0]], atol=1e-15)
    tor = Torus(O0, e[0], e[1], e[2], 1.0, 0.25, [[0, 2 * np.pi], [0, 2 * np.pi]])
    P, S, d = tor.closest([[0.0, 1.0, 0.0]], [[0.0, 2.5]])
    assert abs(P[0, 0] - np.pi / 2) < 1e-15 and P[0, 1] == 2.5 and abs(d[0] - 0.25) < 1e-15
    # cone with its apex at z = -0.8: points beyond the apex go to the apex or to the
    # opposite generator, whichever is nearer (checked by brute force on the nappe)
    cone = Cone(O0, e[0], e[1], e[2], 0.4, 0.5, [[0, 2 * np.pi], [-0.8 / np.cos(0.5), 1.0]])
    assert abs(cone.v_apex - (-0.4 / np.sin(0.5))) < 1e-15
    Xq = np.array([[0, 0, -2.0], [0.05, 0, -1.5], [0.3, 0.1, -0.9], [0.0, 0.0, 0.2]])
    P, S, d = cone.closest(Xq, np.full((4, 2), 0.3))
    uu, vv = np.meshgrid(np.linspace(0, 2 * np.pi, 721), cone.v_apex + np.linspace(0, 3, 3001) ** 2 / 3)
    grid = cone._points(uu.ravel(), vv.ravel())
    brute = np.linalg.norm(grid[None] - Xq[:, None], axis=2).min(axis=1)
    assert np.all(d <= brute + 1e-12) and np.all(d >= brute - 2e-3)
    assert np.all(P[:, 1] >= cone.v_apex)
    apex = cone._points(np.zeros(1), np.array([cone.v_apex]))[0]
    np.testing.assert_allclose(S[0], apex, atol=1e-15)
    assert P[0, 0] == 0.3  # u is free at the apex: the seed


def test_seam_wrapping_follows_the_face_bounds():
    e = np.eye(3)
    cyl = Cylinder(np.zeros(3), e[0], e[1], e[2], 1.0, [[np.pi, 3 * np.pi], [0, 1]])
    P, _, _ = cyl.closest([[1.0, -1e-9, 0.5], [1.0, 1e-9, 0.5], [-1.0, 0.0, 0.5]])
    assert np.all((P[:, 0] >= np.pi) & (P[:, 0] < 3 * np.pi))
    np.testing.assert_allclose(P[:, 0], [2 * np.pi - 1e-9, 2 * np.pi + 1e-9, np.pi], atol=1e-15)


def test_newton_on_analytic_surfaces_agrees_with_the_closed_form():
    """The generic Newton (used by nothing but this check) converges to the closed form."""
    for kind in ("cylinder", "sphere", "torus"):
        s = CASES[kind][0](False)
        X = near_points(s, 100, 0.03)
        P, S, d = s.closest(X)
        res = project_newton(s, X, P + RNG.normal(scale=0.05, size=P.shape))
        np.testing.assert_allclose(res.distance, d, rtol=0, atol=1e-13)
        np.testing.assert_allclose(res.points, S, rtol=0, atol=1e-13)


# ----------------------------------------------------------------------
# curves
# ----------------------------------------------------------------------
def occ_curve_project(c, t0, t1, X):
    tc = Geom_TrimmedCurve(c, t0, t1)
    out = np.empty(len(X))
    for i, x in enumerate(X):
        pr = GeomAPI_ProjectPointOnCurve(gp_Pnt(*x), tc)
        if pr.NbPoints() == 0:  # no orthogonal foot on the trimmed curve: the nearer end
            a, b = tc.Value(t0), tc.Value(t1)
            out[i] = min(a.Distance(gp_Pnt(*x)), b.Distance(gp_Pnt(*x)))
        else:
            a, b = tc.Value(t0), tc.Value(t1)
            out[i] = min(pr.LowerDistance(), a.Distance(gp_Pnt(*x)), b.Distance(gp_Pnt(*x)))
    return out


@pytest.mark.parametrize("t0, t1", [(0.0, 2 * np.pi), (0.3, 2.0), (-1.0, 4.5), (1.0, 7.0)])
def test_circle_arc_closest_point_matches_occ(t0, t1):
    c = Circle(O, X, Y, 0.6, t0, t1)
    occ = Geom_Circle(gp_Circ(gp_Ax2(gp_Pnt(*O), gp_Dir(*Z), gp_Dir(*X)), 0.6))
    t = RNG.uniform(-np.pi, 3 * np.pi, 300)
    Xq = c._points(t) + RNG.normal(scale=0.2, size=(300, 3))
    T, _, d = c.closest(Xq)
    np.testing.assert_allclose(d, occ_curve_project(occ, t0, t1, Xq), rtol=0, atol=1e-14)
    assert np.all((T[:, 0] >= t0) & (T[:, 0] <= t1))
    p = occ.Value(1.1)
    np.testing.assert_allclose(c._points(np.array([1.1]))[0], [p.X(), p.Y(), p.Z()], atol=1e-15)


def test_line_segment_closest_point_matches_occ():
    ln = Line(O, Z, -0.5, 1.5)
    occ = Geom_Line(gp_Lin(gp_Pnt(*O), gp_Dir(*Z)))
    Xq = O + RNG.normal(scale=1.5, size=(300, 3))
    T, _, d = ln.closest(Xq)
    np.testing.assert_allclose(d, occ_curve_project(occ, -0.5, 1.5, Xq), rtol=0, atol=1e-14)
    assert np.all((T >= -0.5) & (T <= 1.5))


def test_closest_wraps_angles_into_the_face_box_and_matches_evaluation():
    """Closed-form parameters lie in ``[u0, u0 + 2 pi)`` for any ``u0`` (also next to
    multiples of 2 pi, where the floor-based wrap rounds), and the foot points computed
    without trigonometry are the surface's points at those parameters."""
    for u0 in (-7.0, -np.pi, 0.0, 2 * np.pi, 11.0):
        box = [[u0, u0 + 2 * np.pi], [0.0, 2 * np.pi]]
        for s in (Cylinder(O, X, Y, Z, 0.7, box), Torus(O, X, Y, Z, 1.0, 0.3, box),
                  Cone(O, X, Y, Z, 0.5, 0.4, [box[0], [-0.5, 1.0]]),
                  Cone(O, X, Y, Z, 0.5, 0.4, [box[0], [-4.0, -2.0]])):
            ang = np.concatenate([RNG.uniform(-20, 20, 300), 2 * np.pi * np.arange(-3, 4) + 1e-17,
                                  2 * np.pi * np.arange(-3, 4) - 1e-17])
            q = np.c_[np.cos(ang), np.sin(ang), RNG.uniform(-0.2, 0.2, len(ang))] * [1.2, 1.2, 1.0]
            Xq = O + q @ np.stack([X, Y, Z])
            P, S, d = s.closest(Xq)
            assert np.all((P[:, 0] >= u0) & (P[:, 0] < u0 + 2 * np.pi + 1e-15))
            np.testing.assert_allclose(s._points(P[:, 0], P[:, 1]), S, rtol=0, atol=1e-14)
            np.testing.assert_allclose(np.linalg.norm(S - Xq, axis=1), d, rtol=0, atol=1e-14)


def test_planes_and_segments_project_at_once_as_each_alone():
    """``AffineBatch`` (all planes, or all segments, of a part in one call) gives OCC's
    distances and the single-entity closed forms, with segment ends clamped."""
    from nagata_snap.cad.projection import AffineBatch

    rng = np.random.default_rng(4)
    for kind, make, occ in (
        ("plane", lambda o, e: Plane(o, e[0], e[1], e[2], [[-1, 1], [-1, 1]]),
         lambda o, e: Geom_Plane(gp_Ax3(gp_Pnt(*o), gp_Dir(*e[2]), gp_Dir(*e[0])))),
        ("line", lambda o, e: Line(o, e[2], -0.5, 1.5), None),
    ):
        frames = [np.linalg.qr(rng.normal(size=(3, 3)))[0].T for _ in range(4)]
        origins = rng.normal(size=(4, 3))
        ents = [make(o, f) for o, f in zip(origins, frames, strict=True)]
        batch = AffineBatch(ents)
        which = rng.integers(0, 4, 400)
        Xq = origins[which] + rng.normal(scale=2.0, size=(400, 3))
        P, S, d = batch.closest(which, Xq)
        for i, e in enumerate(ents):
            sel = which == i
            Pi, Si, di = e.closest(Xq[sel])
            np.testing.assert_allclose(P[sel], Pi.reshape(P[sel].shape), rtol=0, atol=1e-14)
            np.testing.assert_allclose(S[sel], Si, rtol=0, atol=1e-14)
            np.testing.assert_allclose(d[sel], di, rtol=0, atol=1e-14)
            if occ is not None:
                np.testing.assert_allclose(d[sel], occ_project(occ(origins[i], frames[i]), Xq[sel])[1],
                                           rtol=0, atol=1e-13)
            else:
                np.testing.assert_allclose(d[sel], occ_curve_project(
                    Geom_Line(gp_Lin(gp_Pnt(*origins[i]), gp_Dir(*frames[i][2]))), -0.5, 1.5, Xq[sel]),
                    rtol=0, atol=1e-13)
        if kind == "line":
            assert np.all((P >= -0.5) & (P <= 1.5)) and np.any(P == 1.5) and np.any(P == -0.5)


def test_arcs_project_at_once_as_each_alone():
    """``ArcBatch`` (all circles of a part in one call) gives each arc's own closest points to
    the bit (full circles and partial arcs, points beyond an arc's ends, on an axis: the
    seed) and OCC's distances."""
    from nagata_snap.cad.curves import ArcBatch

    rng = np.random.default_rng(5)
    frames = [np.eye(3)] + [np.linalg.qr(rng.normal(size=(3, 3)))[0].T for _ in range(4)]
    centers = rng.normal(size=(5, 3))
    ranges = [(0.0, 2 * np.pi), (0.3, 2.0), (-1.0, 4.5), (1.0, 7.0), (2.0, 2.5)]
    arcs = [Circle(c, f[0], f[1], 0.4 + 0.2 * i, *r)
            for i, (c, f, r) in enumerate(zip(centers, frames, ranges, strict=True))]
    ents = [Line(O, Z, 0.0, 1.0), *arcs]  # a line among them: not the batch's
    batch = ArcBatch(ents)
    assert batch.has.tolist() == [False] + [True] * 5
    which = rng.integers(1, 6, 600)
    Xq = centers[which - 1] + rng.normal(scale=0.8, size=(600, 3))
    Xq[:5] = centers + 2.0 * np.stack([f[2] for f in frames])  # on the axes (the first exactly)
    which[:5] = np.arange(1, 6)
    seeds = rng.uniform(-1.0, 7.0, 600)
    seeds[5:300] = np.nan
    P, S, d = batch.closest(which, Xq, seeds)
    assert np.isfinite(P).all()
    for i, e in enumerate(arcs, start=1):
        sel = which == i
        Pi, Si, di = e.closest(Xq[sel], seeds[sel])
        np.testing.assert_array_equal(P[sel], Pi)
        np.testing.assert_array_equal(S[sel], Si)
        np.testing.assert_array_equal(d[sel], di)
        occ = Geom_Circle(gp_Circ(gp_Ax2(gp_Pnt(*centers[i - 1]), gp_Dir(*frames[i - 1][2]),
                                         gp_Dir(*frames[i - 1][0])), 0.4 + 0.2 * (i - 1)))
        off = sel & (np.arange(600) >= 5)
        np.testing.assert_allclose(d[off], occ_curve_project(occ, *ranges[i - 1], Xq[off]), rtol=0, atol=1e-13)
    assert P[0, 0] == seeds[0]  # on the full circle's axis: the seed


# ----------------------------------------------------------------------
# curves and surfaces built together (a file's edges and faces)
# ----------------------------------------------------------------------
def _arc_box(c: Circle) -> tuple[np.ndarray, np.ndarray]:
    """Exact bounding box of a circular arc: its ends and the axis extremes inside its range."""
    t0, t1 = c.bounds[0]
    # extremes of coordinate i: d/dt (cos t X_i + sin t Y_i) = 0 at t = atan2(Y_i, X_i) (+ pi)
    cand = [t0, t1]
    for i in range(3):
        for t in np.arctan2(c.Y[i], c.X[i]) + np.pi * np.arange(-4, 5):
            if t0 <= t <= t1:
                cand.append(t)
    P = c._points(np.array(cand))
    return P.min(axis=0), P.max(axis=0)


def test_many_curves_are_the_curves_built_one_by_one():
    """``Line.many`` / ``Circle.many`` give each curve exactly (to the last bit) what its own
    constructor gives; the circles' boxes hold the exact arc box, widened by at most the
    sagitta of the 64 sample steps; a line's box is its end points'."""
    k = 7
    O_, D = RNG.normal(size=(k, 3)), RNG.normal(size=(k, 3))
    t0 = RNG.uniform(-3.0, 0.0, k)
    t1 = t0 + RNG.uniform(0.1, 2 * np.pi, k)
    R = RNG.uniform(0.5, 3.0, k)
    Xs = RNG.normal(size=(k, 3))
    Ys = np.cross(D, Xs)
    lines = Line.many(O_, D, t0, t1)
    circles = Circle.many(O_, Xs, Ys, R, t0, t1)
    for i in range(k):
        one = [Line(O_[i], D[i], t0[i], t1[i]), Circle(O_[i], Xs[i], Ys[i], R[i], t0[i], t1[i])]
        for a, b in zip((lines[i], circles[i]), one, strict=True):
            assert a.closed == b.closed and a.bbox_size == b.bbox_size
            for name in ("bounds", "limits"):
                assert np.array_equal(getattr(a, name), getattr(b, name))
            assert all(np.array_equal(p, q) for p, q in zip(a.bbox, b.bbox, strict=True))
            assert all(np.array_equal(p, q) for p, q in zip(a._eval_soa(np.array([[0.1, 0.7]]), 2),
                                                            b._eval_soa(np.array([[0.1, 0.7]]), 2), strict=True))
        lo, hi = _arc_box(circles[i])
        pad = R[i] * (1 - np.cos((t1[i] - t0[i]) / 128))
        assert np.all(circles[i].bbox[0] <= lo + 1e-14) and np.all(circles[i].bbox[1] >= hi - 1e-14)
        assert np.all(circles[i].bbox[0] >= lo - pad - 1e-14) and np.all(circles[i].bbox[1] <= hi + pad + 1e-14)
        ends = lines[i]._points(np.array([t0[i], t1[i]]))
        assert np.array_equal(lines[i].bbox[0], ends.min(axis=0))
    with pytest.raises(ValueError, match="circle radius must be positive, got -1"):
        Circle.many(O_[:2], Xs[:2], Ys[:2], [1.0, -1.0], t0[:2], t1[:2])
    with pytest.raises(ValueError, match="finite with t0 < t1"):
        Line.many(O_[:2], D[:2], [0.0, 1.0], [1.0, 1.0])


def test_surface_boxes_filled_together_are_each_surfaces_own():
    """``fill_boxes`` on many analytic faces gives each the box it computes alone (to the last
    bit), and every box holds a dense sample of its face (a plane's: its 4 corners exactly).

    Except on the sphere: its pad, the sagitta ``R (1 - cos(max(du, dv) / 2))`` of the larger
    grid step, is short of a cell's diagonal there, and a sphere's box can miss its face by up
    to about another such pad (as before batching: the boxes are unchanged)."""
    from nagata_snap.cad.surfaces import fill_boxes

    def make():
        out = []
        for i in range(3):
            b = [[0.1 * i, 1.5 + i], [-0.5, 0.4 + 0.2 * i]]
            out += [Plane(O + i, X, Y, Z, b), Cylinder(O - i, X, Y, Z, 0.7 + i, b),
                    Cone(O, X, Y, Z, 0.4 + i, 0.3, b), Sphere(O, X, Y, Z, 1.0 + i, [[0, 2], [-1.2, 0.5]]),
                    Torus(O, X, Y, Z, 2.0 + i, 0.5, b)]
        return out

    together, alone = make(), make()
    fill_boxes(together)
    for a, b in zip(together, alone, strict=True):
        box = b.bbox  # computed alone, on first use
        assert all(np.array_equal(p, q) for p, q in zip(a.bbox, box, strict=True)) and a.bbox_size == b.bbox_size
        (u0, u1), (v0, v1) = a.bounds
        uu, vv = np.meshgrid(np.linspace(u0, u1, 101), np.linspace(v0, v1, 101))
        pts = a.evaluate(uu.ravel(), vv.ravel())[0]
        slack = 1e-12
        if isinstance(a, Sphere):
            slack += a._sagitta((u1 - u0) / 16, (v1 - v0) / 16)
        assert np.all(pts >= a.bbox[0] - slack) and np.all(pts <= a.bbox[1] + slack)
        if isinstance(a, Plane):
            C = a.evaluate([u0, u0, u1, u1], [v0, v1, v0, v1])[0]
            assert np.allclose(a.bbox[0], C.min(axis=0), rtol=0, atol=1e-15)
            assert np.allclose(a.bbox[1], C.max(axis=0), rtol=0, atol=1e-15)
