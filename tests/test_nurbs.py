"""NURBS evaluation kernel against exact geometry, finite differences and OpenCASCADE.

References (project seeds): Kadir (2010) App. A (eq. A.3) and App. C.3 (the
circle/cylinder nets); Herrero Adan & Cardoso (2020) eqs. (5)-(6) and
Appendix D (test surfaces); Neto (2010) App. C eqs. (42)-(46).
"""

from __future__ import annotations

import numpy as np
import pytest
from nurbs_reference import herrero_71, occ_bspline

from nagata_snap.cad.nurbs import (
    NurbsCurve,
    NurbsError,
    NurbsSurface,
    basis_functions,
    circle,
    find_span,
    cylinder,
    sphere,
    torus,
)

S2 = np.sqrt(0.5)
CIRCLE_KNOTS = [0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1, 1]


def explicit_circle(c=(0.2, 0.2, 0.0), R=0.05) -> NurbsCurve:
    """Kadir (2010) App. C.3 / IGES File 1 net, with the exact weights sqrt(2)/2."""
    c = np.asarray(c, dtype=float)
    net = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1], [1, 0]], float)
    P = c + R * np.c_[net, np.zeros(9)]
    return NurbsCurve(2, CIRCLE_KNOTS, P, [1, S2, 1, S2, 1, S2, 1, S2, 1])


def herrero_72_mid() -> NurbsSurface:
    """Herrero Adan & Cardoso (2020), Appendix D, Example 7.2, mid surface (Tables D.7, D.8)."""
    table = [
        [(0, 40, 150, 1), (20, 40, 150, 1)],
        [(0, 0, 150, 0.707), (20, 20, 150, 0.707)],
        [(40, 0, 150, 1), (40, 20, 150, 1)],
        [(80, 0, 150, 0.707), (60, 20, 150, 0.707)],
        [(80, 40, 150, 1), (60, 40, 150, 1)],
    ]
    a = np.array(table, dtype=float)
    return NurbsSurface(2, 1, [0, 0, 0, 0.5, 0.5, 1, 1, 1], [0, 0, 1, 1], a[..., :3], a[..., 3])


def herrero_71_equal_weights() -> NurbsSurface:
    """The net of Herrero Adan's Example 7.1 with every weight 0.6: a polynomial B-spline,
    evaluated without the weight channel (the weights cancel)."""
    s = herrero_71()
    surf = NurbsSurface(2, 2, s.knots_u, s.knots_v, s.control_points, np.full(s.weights.shape, 0.6))
    assert not surf._rational and s._rational  # the two evaluation paths
    return surf


# ----------------------------------------------------------------------
# independent scalar reference: Herrero Adan eqs. (5)-(6), Neto eq. (46)
# ----------------------------------------------------------------------
def naive_N(i, p, U, u, k=0):
    """Recursive B-spline basis (eq. 5-6) and its k-th derivative (eq. 46), scalar."""
    if k == 0:
        if p == 0:
            return 1.0 if U[i] <= u < U[i + 1] else 0.0
        a = 0.0 if U[i + p] == U[i] else (u - U[i]) / (U[i + p] - U[i]) * naive_N(i, p - 1, U, u)
        b = 0.0 if U[i + p + 1] == U[i + 1] else (U[i + p + 1] - u) / (U[i + p + 1] - U[i + 1]) * naive_N(
            i + 1, p - 1, U, u
        )
        return a + b
    if p == 0:
        return 0.0
    a = 0.0 if U[i + p] == U[i] else naive_N(i, p - 1, U, u, k - 1) / (U[i + p] - U[i])
    b = 0.0 if U[i + p + 1] == U[i + 1] else naive_N(i + 1, p - 1, U, u, k - 1) / (U[i + p + 1] - U[i + 1])
    return p * (a - b)


@pytest.mark.parametrize("p", [1, 2, 3, 4])
def test_basis_matches_naive_recursion(p):
    rng = np.random.default_rng(p)
    inner = np.sort(np.r_[rng.random(6), 0.4, 0.4])  # includes a double knot
    U = np.r_[[0.0] * (p + 1), inner, [1.0] * (p + 1)]
    u = np.r_[rng.random(60), 0.4, U[p + 2]]  # at knots too (right-continuous side)
    span, N = basis_functions(U, p, u, nderiv=3)
    for k in range(4):
        ref = np.array(
            [[naive_N(s - p + a, p, U, uj, k) for a in range(p + 1)] for s, uj in zip(span, u, strict=True)]
        )
        scale = max(1.0, np.abs(ref).max())
        np.testing.assert_allclose(N[k], ref, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("p", [1, 2, 3])
def test_find_span_is_the_knot_interval_of_each_parameter(p):
    """``find_span``: ``u_s <= u < u_{s+1}`` with a non-empty span inside the domain (at a repeated
    knot the span after it), the last non-empty span at ``u = u_max``, and beyond the domain the
    first or last non-empty span (the span a clamp to the domain would give)."""
    U = np.r_[[0.0] * (p + 1), 0.2, 0.5, 0.5, 0.8, [1.0] * (p + 1)]
    n = len(U) - p - 1
    nonempty = [s for s in range(p, n) if U[s] < U[s + 1]]
    u = np.r_[np.linspace(0.0, 1.0, 41), 0.5, 0.8, -0.3, 1.7]
    want = [max((s for s in nonempty if U[s] <= min(max(x, 0.0), 1.0)), default=nonempty[0]) for x in u]
    np.testing.assert_array_equal(find_span(U, p, n, u), want)
    inside = (u >= 0.0) & (u < 1.0)
    s = find_span(U, p, n, u[inside])
    assert np.all(U[s] <= u[inside]) and np.all(u[inside] < U[s + 1])


def test_basis_partition_of_unity_and_end_of_range():
    U = [0, 0, 0, 0, 0.3, 0.3, 0.7, 1, 1, 1, 1]
    u = np.r_[np.linspace(0, 1, 101), 1.0]
    _, N = basis_functions(U, 3, u, nderiv=2)
    np.testing.assert_allclose(N[0].sum(axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(N[1].sum(axis=1), 0.0, atol=1e-12)
    np.testing.assert_allclose(N[2].sum(axis=1), 0.0, atol=1e-10)
    # at u = u_max the last (one-sided) span is used: N_{n-1} = 1
    span, N = basis_functions(U, 3, [1.0])
    assert span[0] == 6 and N[0, 0, -1] == 1.0


# ----------------------------------------------------------------------
# circle (Kadir App. C.3 net)
# ----------------------------------------------------------------------
def test_circle_radius_exact():
    c, R = np.array([0.2, 0.2, 0.0]), 0.05
    cur = explicit_circle(c, R)
    u = np.r_[np.linspace(0, 1, 4001), CIRCLE_KNOTS]
    C = cur.evaluate(u)[0]
    np.testing.assert_allclose(np.linalg.norm(C - c, axis=1), R, rtol=1e-14, atol=0)
    assert np.all(C[:, 2] == 0.0)
    # the constructor helper builds the same curve
    np.testing.assert_array_equal(circle(c, R).control_points, cur.control_points)
    # the points at the arc ends (knots) are the on-circle control points
    k = np.array([0, 0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(cur.evaluate(k)[0], cur.control_points[::2], rtol=0, atol=1e-17)


def test_circle_derivatives_exact_tangent_and_fd():
    c, R = np.array([0.2, 0.2, 0.0]), 0.05
    cur = explicit_circle(c, R)
    u = np.linspace(0, 1, 1001)
    C0, C1, C2 = cur.evaluate(u, 2)
    r = C0 - c
    theta = np.arctan2(r[:, 1], r[:, 0])
    t = np.c_[-np.sin(theta), np.cos(theta), 0 * theta]  # exact unit tangent, counter-clockwise
    speed = np.linalg.norm(C1, axis=1)
    # C' is parallel to the exact tangent and points the same way
    np.testing.assert_allclose(C1 / speed[:, None], t, rtol=0, atol=1e-13)
    # |C - c| = R implies C'.(C-c) = 0 and C''.(C-c) = -|C'|^2
    np.testing.assert_allclose(np.einsum("ki,ki->k", C1, r), 0.0, atol=1e-14 * R * speed.max())
    np.testing.assert_allclose(np.einsum("ki,ki->k", C2, r), -(speed**2), rtol=1e-12, atol=0)
    # speed = R d(theta)/du: compare with the angle's finite difference
    h = 1e-6
    uu = u[(np.abs((u * 4) % 1) > 1e-3) & (u > h) & (u < 1 - h)]  # away from knots
    Cp, Cm = cur.evaluate(uu + h)[0], cur.evaluate(uu - h)[0]
    C0, C1, C2 = cur.evaluate(uu, 2)
    np.testing.assert_allclose(C1, (Cp - Cm) / (2 * h), rtol=0, atol=1e-8 * np.abs(C1).max())
    np.testing.assert_allclose(C2, (Cp - 2 * C0 + Cm) / h**2, rtol=0, atol=2e-4 * np.abs(C2).max())
    D1p, D1m = cur.evaluate(uu + h, 1)[1], cur.evaluate(uu - h, 1)[1]
    np.testing.assert_allclose(C2, (D1p - D1m) / (2 * h), rtol=0, atol=1e-8 * np.abs(C2).max())


def test_curve_end_of_knot_range_exact():
    # an open, non-uniform, non-symmetric rational cubic
    rng = np.random.default_rng(3)
    P = rng.random((7, 3))
    w = rng.uniform(0.5, 2.0, 7)
    U = [0, 0, 0, 0, 0.2, 0.5, 0.6, 1.5, 1.5, 1.5, 1.5]
    cur = NurbsCurve(3, U, P, w)
    assert cur.domain == (0.0, 1.5) and not cur.is_closed
    C = cur.evaluate([0.0, 1.5], 2)
    np.testing.assert_allclose(C[0], P[[0, -1]], rtol=0, atol=1e-15)
    # end derivative: the left limit (one-sided span), continuous with u -> 1.5-
    e = 1e-7
    left = cur.evaluate([1.5 - e, 1.5 - 2 * e], 2)
    d2 = np.abs(C[2, 1]).max()
    np.testing.assert_allclose(C[1, 1], left[1, 0], rtol=0, atol=2 * e * d2)
    fd = (3 * C[0, 1] - 4 * left[0, 0] + left[0, 1]) / (2 * e)  # one-sided, 2nd order
    np.testing.assert_allclose(C[1, 1], fd, rtol=0, atol=1e-6 * np.abs(C[1, 1]).max())
    fd2 = (3 * C[1, 1] - 4 * left[1, 0] + left[1, 1]) / (2 * e)
    np.testing.assert_allclose(C[2, 1], fd2, rtol=0, atol=1e-5 * d2)


def test_wrap_closed_clamp_open():
    cur = explicit_circle()
    # 1.3 wraps to 0.30000000000000004: equal up to that rounding of the parameter
    np.testing.assert_allclose(cur.evaluate([1.3, -0.2], 2), cur.evaluate([0.3, 0.8], 2), rtol=1e-13, atol=1e-14)
    np.testing.assert_array_equal(cur.evaluate([2.25]), cur.evaluate([0.25]))
    arc = NurbsCurve(2, [0, 0, 0, 1, 1, 1], [[1, 0, 0], [1, 1, 0], [0, 1, 0]], [1, S2, 1])
    assert not arc.is_closed
    np.testing.assert_array_equal(arc.evaluate([-3.0, 7.0]), arc.evaluate([0.0, 1.0]))


def test_closed_detection_and_domain():
    assert explicit_circle().is_closed
    # unclamped (uniform) knots: domain is [knots[p], knots[-p-1]]
    P = np.c_[np.cos(np.arange(6)), np.sin(np.arange(6)), np.zeros(6)]
    cur = NurbsCurve(3, np.arange(10.0), P, np.ones(6))
    assert cur.domain == (3.0, 6.0)
    c0, c1 = cur.evaluate([3.0, 6.0])[0]
    assert not cur.is_closed and np.linalg.norm(c1 - c0) > 0.1


@pytest.mark.parametrize(
    "kwargs, msg",
    [
        ({"knots": [0, 0, 0, 1, 1]}, "knots given"),
        ({"knots": [0, 0, 0, 0.7, 0.5, 1, 1, 1]}, "non-decreasing"),
        ({"weights": [1, 1, 0, 1, 1]}, "positive"),
        ({"weights": [1, 1, np.nan, 1, 1]}, "positive"),
        ({"control_points": np.r_[np.zeros((4, 3)), [[np.inf, 0, 0]]]}, "NaN or infinite"),
        ({"control_points": np.zeros((5, 4))}, "shape"),
        ({"knots": [0, 0, 0, 0.5, 0.5, 0.5, 0.5, 1]}, "multiplicity"),
        ({"degree": 0}, "degree"),
        ({"knots": [0, 0, 0, np.nan, 1, 1, 1, 1]}, "NaN"),
    ],
)
def test_curve_validation(kwargs, msg):
    args = {"degree": 2, "knots": [0, 0, 0, 0.3, 0.6, 1, 1, 1],
            "control_points": np.random.default_rng(0).random((5, 3)), "weights": np.ones(5)}
    args.update(kwargs)
    with pytest.raises(NurbsError, match=msg):
        NurbsCurve(**args)
    assert issubclass(NurbsError, ValueError)


def _curve_args(rng, dim: int, closed: bool) -> tuple:
    p = int(rng.integers(1, 5))
    inner = np.sort(rng.uniform(0.0, 1.0, int(rng.integers(0, 9))))
    if inner.size and p > 1:
        inner = np.sort(np.r_[inner, inner[:1]])  # a double knot
    ends = ([0.0] * (p + 1), [1.0] * (p + 1)) if closed or rng.random() < 0.7 else (  # clamped, or not
        np.linspace(-0.2, 0.0, p + 1), np.linspace(1.0, 1.2, p + 1))
    knots = np.r_[ends[0], inner, ends[1]] * rng.uniform(0.5, 3.0) - rng.uniform(0, 2)
    n = len(knots) - p - 1
    P = rng.normal(size=(n, dim))
    if closed:
        P[-1] = P[0]
    return p, knots, P, (None if rng.random() < 0.4 else rng.uniform(0.3, 2.0, n))


def test_many_curves_built_together_as_one_by_one():
    """``NurbsCurve.many`` gives each curve exactly as its constructor does (every field and
    derived array to the last bit: closedness, span table, homogeneous points, box size), for 2D
    and 3D control points; an invalid curve raises the constructor's error of the first one."""
    rng = np.random.default_rng(21)
    for dim in (2, 3):
        args = [_curve_args(rng, dim, closed=i % 3 == 0) for i in range(30)]
        many = NurbsCurve.many(*zip(*args, strict=True))
        assert sum(c.is_closed for c in many) >= 10
        for c, (p, k, P, w) in zip(many, args, strict=True):
            want = NurbsCurve(p, k, P, np.ones(len(P)) if w is None else w)
            for name in ("degree", "knots", "control_points", "weights", "_pwT", "_spans", "_size", "is_closed"):
                a, b = getattr(c, name), getattr(want, name)
                assert type(a) is type(b) and np.asarray(a).tobytes() == np.asarray(b).tobytes(), name
                assert not isinstance(a, np.ndarray) or (a.dtype == b.dtype and not a.flags.writeable)
            u = np.linspace(*want.domain, 7)
            assert c.evaluate(u, 2).tobytes() == want.evaluate(u, 2).tobytes()
    args = [_curve_args(rng, 3, closed=False) for _ in range(5)]
    bad = list(args[3])
    bad[1] = bad[1][::-1]
    with pytest.raises(NurbsError, match="non-decreasing"):
        NurbsCurve.many(*zip(*args[:3], bad, args[4], strict=True))


def _clamped_knots(rng, p: int, clamped: bool = True) -> np.ndarray:
    inner = np.sort(rng.uniform(0.1, 0.9, int(rng.integers(0, 4))))
    ends = (([0.0] * (p + 1), [1.0] * (p + 1)) if clamped
            else (np.linspace(-0.3, 0.0, p + 1), np.linspace(1.0, 1.3, p + 1)))
    return np.r_[ends[0], inner, ends[1]]


def test_closedness_from_the_net_is_the_sampling_tests():
    """Where the control net decides a surface's closedness (clamped ends: rows within the
    tolerance, or corners beyond it, by more than the rounding bound) it is the sampling
    test's outcome; rows near the tolerance, unclamped ends, unequal weights or a net far
    from the origin are left to the sampling test.  Curves: their evaluated ends decide."""
    rng = np.random.default_rng(5)
    decided = {0.0: 0, 1e6: 0}
    for trial in range(300):
        p, q = int(rng.integers(1, 5)), int(rng.integers(1, 5))
        clamped = trial % 7 != 0
        ku, kv = _clamped_knots(rng, p, clamped), _clamped_knots(rng, q, True)
        nu, nv = len(ku) - p - 1, len(kv) - q - 1
        shift = [0.0, 0.0, 1e2, 1e7][(trial // 8) % 4]
        P = rng.normal(size=(nu, nv, 3)) + shift
        W = [np.ones((nu, nv)), rng.uniform(0.5, 2.0, (nu, nv))][trial % 2]
        a = trial % 2 if trial % 3 else 0  # the direction made (nearly) closed
        lo, hi = (np.s_[0], np.s_[-1]) if a == 0 else (np.s_[:, 0], np.s_[:, -1])
        W[hi] = W[lo] if trial % 5 else W[hi]
        P[hi] = P[lo]
        tol = 1e-9 * NurbsSurface(p, q, ku, kv, P, W).bbox_size
        rel = [0.0, 0.3, 1 - 1e-3, 1 - 1e-9, 1 + 1e-9, 1.01, 3.0, 1e6][trial % 8]
        d = rng.normal(size=P[hi].shape)
        d *= rel * tol / np.linalg.norm(d, axis=-1).max()
        P[hi] += d
        s = NurbsSurface(p, q, ku, kv, P, W)
        net = s._closed_by_net()
        sampled = [s._boundaries_coincide(0), s._boundaries_coincide(1)]
        assert [s.closed_u, s.closed_v] == sampled
        for b in range(2):
            assert net[b] in (-1, int(sampled[b])), (trial, b, net, sampled)
        if clamped and shift == 0.0 and rel in decided and net[a] >= 0 and (rel > 0 or trial % 5):
            decided[rel] += 1
    assert min(decided.values()) >= 5  # the clear cases are decided from the net
    for trial in range(200):
        p = int(rng.integers(1, 5))
        k = _clamped_knots(rng, p, trial % 6 != 0)
        P = rng.normal(size=(len(k) - p - 1, 2 + trial % 2)) + [0.0, 0.0, 1e2, 1e7][(trial // 6) % 4]
        rel = [0.0, 0.3, 1 - 1e-9, 1 + 1e-9, 1.01, 1e6][trial % 6]
        c = NurbsCurve(p, k, P, np.ones(len(P)))
        d = rng.normal(size=P.shape[1])
        P[-1] = P[0] + d * rel * 1e-9 * c.bbox_size / np.linalg.norm(d)
        c = NurbsCurve(p, k, P, rng.uniform(0.5, 2.0, len(P)))
        ends = c.evaluate(list(c.domain))[0]
        assert c.is_closed == bool(np.linalg.norm(ends[0] - ends[1]) <= 1e-9 * c.bbox_size), trial


def test_surface_validation_and_immutability():
    s = sphere()
    with pytest.raises(NurbsError, match="weights"):
        NurbsSurface(2, 2, s.knots_u, s.knots_v, s.control_points, s.weights[:, :-1])
    with pytest.raises(NurbsError, match="v direction"):
        NurbsSurface(2, 2, s.knots_u, s.knots_v[:-1], s.control_points, s.weights)
    with pytest.raises(ValueError):
        s.control_points[0, 0, 0] = 5.0  # read-only
    with pytest.raises(NurbsError, match="nderiv"):
        s.evaluate([0.5], [0.5], 3)


# ----------------------------------------------------------------------
# surfaces against exact geometry
# ----------------------------------------------------------------------
def _fd_check(surf: NurbsSurface, u, v, h=1e-5, rtol=1e-6):
    D = surf.evaluate(u, v, 2)
    d1 = lambda a, b: surf.evaluate(a, b, 1)  # noqa: E731
    Su_fd = (surf.evaluate(u + h, v)[0] - surf.evaluate(u - h, v)[0]) / (2 * h)
    Sv_fd = (surf.evaluate(u, v + h)[0] - surf.evaluate(u, v - h)[0]) / (2 * h)
    Suu_fd = (d1(u + h, v)[1] - d1(u - h, v)[1]) / (2 * h)
    Suv_fd = (d1(u, v + h)[1] - d1(u, v - h)[1]) / (2 * h)
    Svu_fd = (d1(u + h, v)[2] - d1(u - h, v)[2]) / (2 * h)
    Svv_fd = (d1(u, v + h)[2] - d1(u, v - h)[2]) / (2 * h)
    for got, ref in [(D[1], Su_fd), (D[2], Sv_fd), (D[3], Suu_fd), (D[4], Suv_fd), (D[4], Svu_fd), (D[5], Svv_fd)]:
        np.testing.assert_allclose(got, ref, rtol=0, atol=rtol * max(np.abs(ref).max(), surf.bbox_size))


def _away_from_knots(x, knots, margin):
    k = np.unique(knots)
    return np.min(np.abs(x[:, None] - k[None, :]), axis=1) > margin


def test_sphere_exact_and_derivatives():
    c, R = np.array([1.0, -2.0, 0.5]), 2.5
    s = sphere(c, R)
    assert (s.closed_u, s.closed_v) == (False, True)
    rng = np.random.default_rng(0)
    u, v = rng.random(2000), rng.random(2000)
    u = np.r_[u, 0, 1, 0.5, 1.0]
    v = np.r_[v, 0, 1, 1.0, 0.25]
    S, Su, Sv, Suu, Suv, Svv = s.evaluate(u, v, 2)
    r = S - c
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), R, rtol=1e-14, atol=0)
    # |S - c| = R  =>  r.S_a = 0 and r.S_ab = -S_a.S_b
    dot = lambda a, b: np.einsum("ki,ki->k", a, b)  # noqa: E731
    scale = R * np.max(np.linalg.norm(np.c_[Su, Sv], axis=1))
    np.testing.assert_allclose(dot(r, Su), 0, atol=1e-14 * scale)
    np.testing.assert_allclose(dot(r, Sv), 0, atol=1e-14 * scale)
    for H, a, b in [(Suu, Su, Su), (Suv, Su, Sv), (Svv, Sv, Sv)]:
        np.testing.assert_allclose(dot(r, H), -dot(a, b), rtol=0, atol=1e-12 * scale**2 / R**2)
    # poles: u = 0 and 1 are the south/north poles, S_v vanishes there
    np.testing.assert_allclose(s.evaluate([0, 0], [0.1, 0.7])[0], [c - [0, 0, R]] * 2, atol=1e-15)
    np.testing.assert_allclose(s.evaluate([1], [0.3], 1)[2], [[0, 0, 0]], atol=1e-14)
    uu = rng.uniform(0.02, 0.98, 300)
    vv = rng.random(300)
    keep = _away_from_knots(uu, s.knots_u, 1e-3) & _away_from_knots(vv, s.knots_v, 1e-3)
    _fd_check(s, uu[keep], vv[keep])


def test_cylinder_and_torus_exact():
    rng = np.random.default_rng(1)
    u, v = rng.random(3000), rng.random(3000)
    cyl = cylinder((0.55, 0.5, 0.0), 0.05, 0.4)  # Kadir App. C, IGES File 2 (exact weights)
    assert (cyl.closed_u, cyl.closed_v) == (True, False)
    S = cyl.evaluate(u, v)[0]
    np.testing.assert_allclose(np.hypot(S[:, 0] - 0.55, S[:, 1] - 0.5), 0.05, rtol=1e-14, atol=0)
    np.testing.assert_allclose(S[:, 2], 0.4 * v, rtol=0, atol=4e-16)
    tor = torus((0.0, 0.0, 1.0), 2.0, 0.5)
    assert (tor.closed_u, tor.closed_v) == (True, True)
    S = tor.evaluate(u, v)[0]
    rho = np.hypot(S[:, 0], S[:, 1])
    np.testing.assert_allclose(np.hypot(rho - 2.0, S[:, 2] - 1.0), 0.5, rtol=1e-14, atol=0)
    keep = _away_from_knots(u, tor.knots_u, 1e-3) & _away_from_knots(v, tor.knots_v, 1e-3)
    _fd_check(tor, u[keep][:300], v[keep][:300])


def test_surface_corners_and_wrap():
    s = herrero_71()
    cp = s.control_points
    corners = s.evaluate([0, 1, 0, 1], [0, 0, 1, 1])[0]
    np.testing.assert_allclose(corners, cp[[0, -1, 0, -1], [0, 0, -1, -1]], rtol=0, atol=1e-13)
    assert (s.closed_u, s.closed_v) == (False, False)
    np.testing.assert_array_equal(s.evaluate([-1.0, 2.0], [0.3, 9.0]), s.evaluate([0.0, 1.0], [0.3, 1.0]))
    t = torus()
    np.testing.assert_array_equal(t.evaluate([1.25, -0.5], [0.1, 3.75], 2), t.evaluate([0.25, 0.5], [0.1, 0.75], 2))


# ----------------------------------------------------------------------
# Herrero Adan App. D surfaces against OpenCASCADE (gmsh) and finite differences
# ----------------------------------------------------------------------
@pytest.mark.parametrize("make", [herrero_71, herrero_72_mid, herrero_71_equal_weights])
def test_herrero_surfaces_vs_occ_and_fd(make):
    import gmsh
    surf = make()
    rng = np.random.default_rng(7)
    u, v = rng.random(400), rng.random(400)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("herrero")
        tag = occ_bspline(gmsh, surf)
        uv = np.c_[u, v].ravel().tolist()
        X = np.array(gmsh.model.getValue(2, tag, uv)).reshape(-1, 3)
        D1 = np.array(gmsh.model.getDerivative(2, tag, uv)).reshape(-1, 2, 3)
        D2 = np.array(gmsh.model.getSecondDerivative(2, tag, uv)).reshape(-1, 3, 3)  # uu, vv, uv
    finally:
        gmsh.finalize()
    S = surf.evaluate(u, v, 2)
    size = surf.bbox_size
    np.testing.assert_allclose(S[0], X, rtol=0, atol=1e-12 * size)
    np.testing.assert_allclose(S[1], D1[:, 0], rtol=0, atol=1e-11 * size)
    np.testing.assert_allclose(S[2], D1[:, 1], rtol=0, atol=1e-11 * size)
    np.testing.assert_allclose(S[3], D2[:, 0], rtol=0, atol=1e-10 * size)
    np.testing.assert_allclose(S[5], D2[:, 1], rtol=0, atol=1e-10 * size)
    np.testing.assert_allclose(S[4], D2[:, 2], rtol=0, atol=1e-10 * size)
    keep = _away_from_knots(u, surf.knots_u, 1e-3) & _away_from_knots(v, surf.knots_v, 1e-3)
    keep &= (u > 1e-3) & (u < 1 - 1e-3) & (v > 1e-3) & (v < 1 - 1e-3)
    _fd_check(surf, u[keep], v[keep])


def test_curve_vs_occ_bspline_curve():
    import gmsh
    rng = np.random.default_rng(11)
    P = rng.random((8, 3))
    w = rng.uniform(0.3, 3.0, 8)
    U = [0, 0, 0, 0, 0.1, 0.45, 0.45, 0.8, 1, 1, 1, 1]
    cur = NurbsCurve(3, U, P, w)
    u = np.r_[rng.random(200), 0.0, 0.45, 1.0]
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("curve")
        tags = [gmsh.model.occ.addPoint(*p) for p in P]
        k, m = np.unique(U, return_counts=True)
        tag = gmsh.model.occ.addBSpline(tags, degree=3, weights=w.tolist(), knots=k.tolist(), multiplicities=m.tolist())
        gmsh.model.occ.synchronize()
        X = np.array(gmsh.model.getValue(1, tag, u.tolist())).reshape(-1, 3)
        D1 = np.array(gmsh.model.getDerivative(1, tag, u.tolist())).reshape(-1, 3)
        # gmsh's getSecondDerivative on curves was observed to be accurate to
        # only ~1e-5 here (its surface second derivatives match to 1e-10), so
        # the curve's C'' is compared with central differences of OCC's C'
        h = 1e-6
        uu = u[(u > 2 * h) & (u < 1 - 2 * h) & (np.abs(u - 0.45) > 2 * h) & (np.abs(u - 0.1) > 2 * h)]
        D1p = np.array(gmsh.model.getDerivative(1, tag, (uu + h).tolist())).reshape(-1, 3)
        D1m = np.array(gmsh.model.getDerivative(1, tag, (uu - h).tolist())).reshape(-1, 3)
    finally:
        gmsh.finalize()
    C = cur.evaluate(u, 2)
    np.testing.assert_allclose(C[0], X, rtol=0, atol=1e-13)
    np.testing.assert_allclose(C[1], D1, rtol=0, atol=1e-11 * np.abs(D1).max())
    D2 = (D1p - D1m) / (2 * h)
    np.testing.assert_allclose(cur.evaluate(uu, 2)[2], D2, rtol=0, atol=1e-7 * np.abs(D2).max())
