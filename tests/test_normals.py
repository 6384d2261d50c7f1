"""Estimated vertex normals and crease handling against exact geometry."""

import numpy as np
import pytest
from surfaces import barycentric_grid, circle_polygon, sphere_octahedron

from nagata_snap import NagataGeometry, NonManifoldError, NormalsError


def cube_surface(n=2):
    """Closed cube [0,1]^3, each face an n x n grid of quads split in two, outward winding."""
    g = np.linspace(0, 1, n + 1)
    pts, tris = [], []
    for axis in range(3):
        for side in (0.0, 1.0):
            u, v = np.meshgrid(g, g, indexing="ij")
            p = np.zeros((n + 1, n + 1, 3))
            a, b = [k for k in range(3) if k != axis]
            p[..., axis] = side
            p[..., a], p[..., b] = u, v
            base = sum(len(q) for q in pts)
            pts.append(p.reshape(-1, 3))
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            i, j = i.ravel(), j.ravel()
            v00, v10 = base + i * (n + 1) + j, base + (i + 1) * (n + 1) + j
            v01, v11 = v00 + 1, v10 + 1
            t = np.concatenate([np.c_[v00, v10, v11], np.c_[v00, v11, v01]])
            nrm = np.cross(p.reshape(-1, 3)[t[:, 1] - base] - p.reshape(-1, 3)[t[:, 0] - base],
                           p.reshape(-1, 3)[t[:, 2] - base] - p.reshape(-1, 3)[t[:, 0] - base])
            out = np.zeros(3)
            out[axis] = 1 if side else -1
            flip = nrm @ out < 0
            t[flip] = t[flip][:, [0, 2, 1]]
            tris.append(t)
    pts = np.concatenate(pts)
    tris = np.concatenate(tris)
    key = np.round(pts * 1e9).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return pts[first], inv.reshape(-1)[tris]


def test_mwselr_exact_on_sphere():
    """Max's weighting is exact for vertices on a sphere (Neto 2010: zero error)."""
    p, t, exact = sphere_octahedron(2)
    geo = NagataGeometry.from_surface(p, t)
    n = geo.corner_normal.reshape(-1, 3)
    x = geo.x.reshape(-1, 3)
    np.testing.assert_allclose(n, exact.normal(x), atol=1e-13)


def test_edge_reciprocal_weights_exact_on_circle_with_unequal_segments():
    p, s, exact = circle_polygon(17, radius=0.7, centre=(0.3, -0.2), jitter=0.6, seed=3)
    geo = NagataGeometry.from_surface(p, s)
    n = geo.corner_normal.reshape(-1, 3)[:, :2]
    np.testing.assert_allclose(n, exact.normal(geo.x.reshape(-1, 3)), atol=1e-13)


def test_cube_creases_keep_faces_flat_and_corners_sharp():
    p, t = cube_surface(3)
    geo = NagataGeometry.from_surface(p, t)
    # every corner normal is a coordinate axis: one normal per face at edges and corners
    n = geo.corner_normal.reshape(-1, 3)
    assert np.allclose(np.sort(np.abs(n), axis=1), [0, 0, 1], atol=1e-14)
    assert np.all(np.abs(geo.coef) == 0)
    g = barycentric_grid(3, 5)
    pts = geo.evaluate(np.arange(geo.num_patches), np.broadcast_to(g, (geo.num_patches, *g.shape)))
    flat = np.einsum("pkv,pvi->pki", np.broadcast_to(g, pts.shape[:2] + (3,)), geo.x)
    assert np.abs(pts - flat).max() == 0.0


def test_crease_angle_controls_sharpness():
    """A coarse octagon (45 deg turns) is smooth at the default 60 deg, sharp at 30 deg."""
    p, s, exact = circle_polygon(8)
    smooth = NagataGeometry.from_surface(p, s)
    sharp = NagataGeometry.from_surface(p, s, crease_angle=30.0)
    assert np.abs(smooth.coef).max() > 0.05
    assert np.abs(sharp.coef).max() == 0.0


def test_non_manifold_and_degenerate_inputs_raise():
    p, t = cube_surface(1)
    # a triangle glued onto an existing edge: that edge has three facets
    extra = np.concatenate([p, [[0.5, 0.5, 2.0]]])
    e = t[0, :2]
    with pytest.raises(NonManifoldError, match="shared by"):
        NagataGeometry.from_surface(extra, np.concatenate([t, [[e[0], e[1], len(p)]]]))
    # open surface: boundary edges have one facet
    with pytest.raises(NonManifoldError):
        NagataGeometry.from_surface(p, t[:-1])
    # zero-area facet
    bad = p.copy()
    tri = t[0]
    bad[tri[2]] = 0.5 * (bad[tri[0]] + bad[tri[1]])
    with pytest.raises(NormalsError, match="zero"):
        NagataGeometry.from_surface(bad, t)


def test_supplied_normals_checked():
    p, s, exact = circle_polygon(12)
    with pytest.raises(NormalsError, match="zero, NaN"):
        NagataGeometry.from_surface(p, s, normals=lambda x: np.zeros_like(x))
    with pytest.raises(NormalsError, match="zero, NaN"):
        NagataGeometry.from_surface(p, s, normals=lambda x: np.full_like(x, np.nan))
    # alternating sign is accepted (orientation is free), and gives the exact-normal curve
    def alt(x):
        n = exact.normal(x)
        return n * np.where(np.arange(len(n)) % 2, -1, 1)[:, None]
    a = NagataGeometry.from_surface(p, s, normals=alt)
    b = NagataGeometry.from_surface(p, s, normals=exact.normal)
    np.testing.assert_allclose(a.coef, b.coef, atol=1e-15)
    # normals that point along the boundary are rejected by the crease rule with a warning
    with pytest.warns(UserWarning, match="supplied normals differ"):
        NagataGeometry.from_surface(p, s, normals=lambda x: np.c_[-x[:, 1], x[:, 0], 0 * x[:, 0]])
