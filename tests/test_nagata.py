"""Nagata curve and patch kernels against published numbers and exact geometry."""

import numpy as np
import pytest
from surfaces import barycentric_grid, closed_cylinder, sphere_octahedron

from nagata_snap import NagataGeometry
from nagata_snap.nagata import patch as nagata


def quarter_circle(ne):
    th = np.linspace(0, np.pi / 2, ne + 1)
    x = np.c_[np.cos(th), np.sin(th), 0 * th]
    return x[:-1], x[1:]


@pytest.mark.parametrize("ne, radial, normal_deg", [(2, 0.314, 0.703), (3, 0.060, 0.202), (1, None, 6.6)])
def test_quarter_circle_matches_neto_table1(ne, radial, normal_deg):
    """Seed 000, Table 1: quarter unit circle with exact normals."""
    x0, x1 = quarter_circle(ne)
    c = nagata.curve_coefficient(x1 - x0, x0, x1)
    xi = np.linspace(0, 1, 4001)
    p = nagata.curve(x0, x1, c, xi)
    r = np.linalg.norm(p, axis=-1)
    tangent = (x1 - x0)[:, None] + (2 * xi[None, :, None] - 1) * c[:, None]  # eq. (4)
    tangent /= np.linalg.norm(tangent, axis=-1, keepdims=True)
    ang = np.degrees(np.arcsin(np.clip(np.abs(np.einsum("eki,eki->ek", tangent, p / r[..., None])), 0, 1)))
    if radial is not None:
        assert 100 * (r.max() - 1) == pytest.approx(radial, abs=5e-4)
        # the curve lies outside the circle, maximum at mid-edge
        assert r.min() >= 1 - 1e-15
        assert np.all(np.argmax(r, axis=1) == 2000)
    assert ang.max() == pytest.approx(normal_deg, abs=5e-3 if ne > 1 else 0.05)


def test_circle_error_formula_and_order():
    """Max radial error ~ R (2 pi / N)^4 / 128, order 4 (seeds/README)."""
    errs = []
    for n in (16, 32, 64):
        th = 2 * np.pi * np.arange(n + 1) / n
        x = np.c_[np.cos(th), np.sin(th), 0 * th]
        c = nagata.curve_coefficient(x[1:] - x[:-1], x[:-1], x[1:])
        r = np.linalg.norm(nagata.curve(x[:-1], x[1:], c, [0.5]), axis=-1)
        errs.append(r.max() - 1)
        assert errs[-1] == pytest.approx((2 * np.pi / n) ** 4 / 128, rel=0.02)
    assert np.log2(errs[0] / errs[1]) == pytest.approx(4, abs=0.05)


def test_coefficient_symmetry_and_flat_edges():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(50, 3))
    n0 = rng.normal(size=(50, 3))
    n1 = n0 + 0.3 * rng.normal(size=(50, 3))
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    c = nagata.curve_coefficient(d, n0, n1)
    np.testing.assert_allclose(nagata.curve_coefficient(-d, n1, n0), c, atol=1e-12)
    # both normals flipped: same curve
    np.testing.assert_allclose(nagata.curve_coefficient(d, -n0, -n1), c, atol=1e-12)
    # parallel normals: exactly straight
    assert np.all(nagata.curve_coefficient(d, n0, n0) == 0)
    # eq. (6), n0.(d - c) = 0 and n1.(d + c) = 0, on chords of an ellipsoid with exact normals
    # (the bound B_MAX does not act on a smooth surface)
    a2 = np.array([1.0, 0.49, 0.25])
    u = rng.normal(size=(200, 3))
    x0 = u / np.sqrt((u**2 / a2).sum(axis=1, keepdims=True))
    u = x0 + 0.3 * rng.normal(size=(200, 3))
    x1 = u / np.sqrt((u**2 / a2).sum(axis=1, keepdims=True))
    g0, g1 = x0 / a2, x1 / a2
    m0, m1 = g0 / np.linalg.norm(g0, axis=1, keepdims=True), g1 / np.linalg.norm(g1, axis=1, keepdims=True)
    keep = np.einsum("ei,ei->e", m0, m1) > 0.3
    c = nagata.curve_coefficient(x1 - x0, m0, m1)[keep]
    e = (x1 - x0)[keep]
    np.testing.assert_allclose(np.einsum("ei,ei->e", m0[keep], e - c), 0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("ei,ei->e", m1[keep], e + c), 0, atol=1e-12)


def test_nearly_parallel_normals_do_not_bend_a_straight_edge():
    """A cylinder generator with estimated normals 1e-4 off: eq. (15) as printed bends it by
    a tenth of its length or more; the bound keeps the bend O(|d| normal error)."""
    rng = np.random.default_rng(4)
    d = np.tile([0.0, 0.0, 0.1], (100, 1))
    n = np.tile([1.0, 0.0, 0.0], (100, 1))
    n0 = n + 1e-4 * rng.normal(size=(100, 3))
    n1 = n + 1e-4 * rng.normal(size=(100, 3))
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    v, dv = (n0 + n1) / 2, (n0 - n1) / 2
    dc = np.einsum("ei,ei->e", n0, dv)
    unbounded = (np.einsum("ei,ei->e", d, v) / dc)[:, None] * dv  # second term of eq. (15)
    assert np.linalg.norm(unbounded, axis=1).max() > 0.01
    err = np.maximum(np.linalg.norm(n0 - n, axis=1), np.linalg.norm(n1 - n, axis=1))  # about 2e-4
    c = nagata.curve_coefficient(d, n0, n1)
    assert np.all(np.linalg.norm(c, axis=1) <= 2 * 0.1 * err)  # O(|d| error), as for curved edges
    cm = nagata.curve_coefficient_multi(d, n0[:, None], n1[:, None])
    np.testing.assert_allclose(cm, c, atol=1e-15)
    # a straight crease whose side normals differ by rounding: the multi-normal curve stays straight
    m = np.tile([0.0, 1.0, 0.0], (100, 1))
    cm = nagata.curve_coefficient_multi(d, np.stack([n0, m], 1), np.stack([n1, m], 1))
    assert np.all(np.linalg.norm(cm, axis=1) <= 2 * 0.1 * err)


def test_multi_normal_reduces_to_two_normal_and_keeps_planes():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(20, 3))
    n0 = rng.normal(size=(20, 3))
    n1 = n0 + 0.2 * rng.normal(size=(20, 3))
    n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    c2 = nagata.curve_coefficient(d, n0, n1)
    cm = nagata.curve_coefficient_multi(d, n0[:, None], n1[:, None])
    np.testing.assert_allclose(cm, c2, atol=1e-10)
    # zero-padding rows change nothing
    pad = np.zeros((20, 1, 3))
    cmp = nagata.curve_coefficient_multi(d, np.concatenate([n0[:, None], pad], 1), n1[:, None])
    np.testing.assert_allclose(cmp, c2, atol=1e-10)
    # edge of a box (two planes meeting at 90 deg): straight, exactly
    d = np.array([[0.0, 0.0, 1.0]])
    ex, ey = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    c = nagata.curve_coefficient_multi(d, np.array([[ex, ey]]), np.array([[ex, ey]]))
    assert np.all(np.abs(c) < 1e-15)
    # rim of a cylinder: plane normal e_z plus two radial normals -> curve stays in the plane
    a, b = np.array([1.0, 0, 0]), np.array([np.cos(0.5), np.sin(0.5), 0])
    ez = np.array([0, 0, 1.0])
    c = nagata.curve_coefficient_multi((b - a)[None], np.array([[a, ez]]), np.array([[b, ez]]))
    assert abs(c[0, 2]) < 1e-15
    np.testing.assert_allclose(c, nagata.curve_coefficient((b - a)[None], a[None], b[None]), atol=1e-14)



def test_multi_normal_nearly_coplanar_crease_stays_straight():
    """A straight crease with estimated normals a little off at each end
    (the four normals then span 3D with a tiny third eigenvalue): the
    coefficient stays of the order of the perturbation, not of the edge."""
    rng = np.random.default_rng(5)
    d = np.array([[0.222, 0.0, 0.0]])
    na, nb = np.array([0.0, 1.0, 0.0]), np.array([0.0, -0.733, 0.68]) / np.hypot(0.733, 0.68)
    for _ in range(20):
        n0 = np.array([na, nb]) + 1e-3 * rng.normal(size=(2, 3))
        n1 = np.array([na, nb]) + 1e-3 * rng.normal(size=(2, 3))
        n0 /= np.linalg.norm(n0, axis=1, keepdims=True)
        n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
        c = nagata.curve_coefficient_multi(d, n0[None], n1[None])
        assert np.linalg.norm(c) < 0.01 * 0.222



def test_bound_keeps_tilted_chord_against_nearly_parallel_normals_straight():
    """Eq. (15) with normals 0.35 deg apart and a chord tilted 0.3 deg against
    them (estimated normals on a straight edge of a cylinder): |c| = 1.7 |d|
    as published, of the order of the normals' difference with the bound
    (B_MAX); a circle (no tilt) is unchanged."""
    d = np.array([[0.0, 0.0, 0.12]])
    n0 = np.array([[-1.0, 0.0, 0.002]])
    n1 = np.array([[-1.0, 0.0, 0.008]])
    n0 /= np.linalg.norm(n0)
    n1 /= np.linalg.norm(n1)
    v, dv = (n0 + n1) / 2, (n0 - n1) / 2
    dc = np.einsum("ei,ei->e", n0, dv)
    published = (np.einsum("ei,ei->e", d, dv) / (1 - dc))[:, None] * v \
        + (np.einsum("ei,ei->e", d, v) / dc)[:, None] * dv  # eq. (15) as printed
    assert np.linalg.norm(published) > 1.5 * 0.12
    c = nagata.curve_coefficient(d, n0, n1)
    assert np.linalg.norm(c) < 0.01 * 0.12
    # the unit circle in 6 segments: eq. (15) has b = 0 there, the bound does not act
    th = np.linspace(0, np.pi / 2, 7)
    x = np.c_[np.cos(th), np.sin(th), 0 * th]
    e = x[1:] - x[:-1]
    v, dv = (x[:-1] + x[1:]) / 2, (x[:-1] - x[1:]) / 2
    dc = np.einsum("ei,ei->e", x[:-1], dv)
    np.testing.assert_allclose(nagata.curve_coefficient(e, x[:-1], x[1:]),
                               (np.einsum("ei,ei->e", e, dv) / (1 - dc))[:, None] * v, atol=1e-15)


def test_patch_reproduces_vertices_and_planes():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(10, 3, 3))
    c = rng.normal(size=(10, 3, 3))
    lam = np.broadcast_to(np.eye(3), (10, 3, 3))
    assert np.array_equal(nagata.evaluate(x, c, lam), x)  # exact in floating point (Nagata, after eq. 44)
    # a planar patch with its plane normal at every vertex is the flat triangle
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    edges = nagata.LOCAL_EDGES[3]
    cc = nagata.curve_coefficient(x[:, edges[:, 1]] - x[:, edges[:, 0]], n[:, None], n[:, None])
    g = np.broadcast_to(barycentric_grid(3, 6), (10, 28, 3))
    np.testing.assert_array_equal(cc, 0)
    np.testing.assert_allclose(nagata.evaluate(x, cc, g), np.einsum("pkv,pvi->pki", g, x), atol=1e-15)


def test_patch_tangents_match_finite_differences():
    """The monomial tangents (eq. 37) that closest_on_patch's Newton uses are the patch's."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(5, 3, 3))
    c = 0.3 * rng.normal(size=(5, 3, 3))
    eta = np.full((5, 1), 0.6)
    zeta = np.full((5, 1), 0.25)

    def pt(e, z):
        lam = np.stack([1 - e, e - z, z], axis=-1)
        return nagata.evaluate(x, c, lam)

    h = 1e-6
    xe, xz = nagata.patch_tangents(nagata.patch_coefficients(x, c), eta, zeta)
    np.testing.assert_allclose(xe, (pt(eta + h, zeta) - pt(eta - h, zeta)) / (2 * h), atol=1e-8)
    np.testing.assert_allclose(xz, (pt(eta, zeta + h) - pt(eta, zeta - h)) / (2 * h), atol=1e-8)


def test_closest_on_patch_matches_dense_sampling():
    """closest_on_patch on patches of a sphere (exact normals): the point it finds is as close
    as the best of a dense barycentric grid, and its residual is normal to the patch."""
    p, t, exact = sphere_octahedron(1)
    geo = NagataGeometry.from_surface(p, t, normals=exact.normal)
    P = geo.num_patches
    rng = np.random.default_rng(7)
    lam0 = rng.dirichlet(np.full(3, 4.0), size=P)  # well inside each triangle
    on = geo.evaluate(np.arange(P), lam0[:, None])[:, 0]
    target = on * (1.0 + 0.05 * rng.uniform(-1.0, 1.0, size=(P, 1)))  # off the surface radially
    seed = np.full((P, 3), 1.0 / 3.0)
    lam = nagata.closest_on_patch(geo.x, geo.coef, seed, target)
    np.testing.assert_allclose(lam.sum(axis=1), 1.0, atol=1e-14)
    found = geo.evaluate(np.arange(P), lam[:, None])[:, 0]
    g = barycentric_grid(3, 200)
    dense = geo.evaluate(np.arange(P), np.broadcast_to(g, (P, *g.shape)))
    best = np.linalg.norm(dense - target[:, None], axis=2).min(axis=1)
    dist = np.linalg.norm(found - target, axis=1)
    assert np.all(dist <= best + 1e-12)
    # a grid point within h (spacing) of the foot is at most sqrt(dist^2 + h^2) - dist away
    h = np.linalg.norm(geo.x[:, 1] - geo.x[:, 0], axis=1).max() / 200
    assert np.all(best - dist < h * h / (2 * dist))
    xe, xz = nagata.patch_tangents(nagata.patch_coefficients(geo.x, geo.coef),
                                   1.0 - lam[:, :1], lam[:, 2:])
    r = found - target
    for tangent in (xe[:, 0], xz[:, 0]):
        cos = np.einsum("pi,pi->p", r, tangent) / (np.linalg.norm(r, axis=1) * np.linalg.norm(tangent, axis=1))
        assert np.abs(cos).max() < 1e-8


def test_sphere_mesh1_matches_neto_table2_and_appendix_d():
    """Seed 000: sphere mesh 1 (32 triangles, 18 nodes); Table 2 radial error, App. D coefficients."""
    p, t, exact = sphere_octahedron(1)
    assert (len(t), len(p)) == (32, 18)
    geo = NagataGeometry.from_surface(p, t, normals=exact.normal)
    g = barycentric_grid(3, 40)
    pts = geo.evaluate(np.arange(geo.num_patches), np.broadcast_to(g, (32, *g.shape)))
    r = np.linalg.norm(pts, axis=-1)
    assert 100 * (r.max() - 1) == pytest.approx(1.03, abs=0.01)
    assert 100 * (r.min() - 1) == pytest.approx(-0.21, abs=0.01)
    # Appendix D, patch 1: vertices x00 = (-1,0,0), x10 = (-.707,-.707,0), x11 = (-.707,0,.707)
    s2 = np.sqrt(0.5)
    xv = np.array([[[-1.0, 0, 0], [-s2, -s2, 0], [-s2, 0, s2]]])
    edges = nagata.LOCAL_EDGES[3]
    c = nagata.curve_coefficient(xv[:, edges[:, 1]] - xv[:, edges[:, 0]], xv[:, edges[:, 0]], xv[:, edges[:, 1]])
    co = nagata.patch_coefficients(xv, c)
    printed = {  # columns of App. D, patch 1 (x, y, z rows), printed to 3 digits
        "c00": [-1.0, -0.612e-16, 0.0],
        "c10": [-0.117e-7, -0.828, 0.250e-8],
        "c01": [0.234e-7, 0.828, 0.828],
        "c11": [-0.471, -0.357, 0.114],
        "c20": [0.293, 0.121, -0.250e-8],
        "c02": [0.471, 0.236, -0.236],
    }
    for k, v in printed.items():
        np.testing.assert_allclose(co[k][0], v, atol=6e-4, err_msg=k)


def test_convergence_orders_sphere_and_cylinder():
    """Nagata 2005, Fig. 9: order ~4 for Nagata patches, 2 for flat facets."""
    def errs(p, t, ex, tags=None, snap=None):
        geo = NagataGeometry.from_surface(p, t, tags, snap, normals=ex.normal)
        g = barycentric_grid(3, 12)
        lam = np.broadcast_to(g, (geo.num_patches, *g.shape))
        return ex.distance(geo.evaluate(np.arange(geo.num_patches), lam)).max(), ex.distance(
            np.einsum("pkv,pvi->pki", lam, geo.x)
        ).max()

    s = [errs(*sphere_octahedron(k)) for k in (3, 4)]
    assert np.log2(s[0][0] / s[1][0]) == pytest.approx(4, abs=0.2)
    assert np.log2(s[0][1] / s[1][1]) == pytest.approx(2, abs=0.1)
    cyl = []
    for n in (16, 32):
        p, t, ex, tg = closed_cylinder(n)
        cyl.append(errs(p, t, ex, tg, [1]))
    assert np.log2(cyl[0][0] / cyl[1][0]) == pytest.approx(4, abs=0.2)
    assert np.log2(cyl[0][1] / cyl[1][1]) == pytest.approx(2, abs=0.1)
