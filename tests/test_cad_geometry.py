"""CadGeometry.attach/place (Kadir 2010, ch. 2) on synthetic boundary meshes.

Refinement is emulated with numpy: every facet is split at its edge
midpoints, a new vertex gets the straight midpoint as position and the
parametric midpoint of the edge's end parameters (from the parent facet's
unwrapped records) as seed, as the lead's generic refine step does.
"""

from __future__ import annotations

import numpy as np
import pytest

from nagata_snap.cad import CadError, CadGeometry
from nagata_snap.cad.nurbs import NurbsCurve, circle, cylinder, sphere
from nagata_snap.mesh.records import Records

S2 = np.sqrt(0.5)


# ----------------------------------------------------------------------
# refinement emulation
# ----------------------------------------------------------------------
def split_segments(x: np.ndarray, rec: Records) -> tuple[np.ndarray, Records]:
    """Each segment (a, b) -> (a, m), (m, b); m straight, params midpoint."""
    m = x.mean(axis=1)
    pm = rec.params.mean(axis=1)
    st = np.concatenate([np.stack([x[:, 0], m], 1), np.stack([m, x[:, 1]], 1)])
    pr = np.concatenate([np.stack([rec.params[:, 0], pm], 1), np.stack([pm, rec.params[:, 1]], 1)])
    return st, Records(np.concatenate([rec.root, rec.root]), pr)


def split_triangles(x: np.ndarray, rec: Records) -> tuple[np.ndarray, Records]:
    """Each triangle (a, b, c) -> 4 children through its edge midpoints."""
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    pa, pb, pc = rec.params[:, 0], rec.params[:, 1], rec.params[:, 2]
    mab, mbc, mca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    qab, qbc, qca = (pa + pb) / 2, (pb + pc) / 2, (pc + pa) / 2
    kids = [(a, mab, mca), (mab, b, mbc), (mca, mbc, c), (mab, mbc, mca)]
    pk = [(pa, qab, qca), (qab, pb, qbc), (qca, qbc, pc), (qab, qbc, qca)]
    st = np.concatenate([np.stack(k, 1) for k in kids])
    pr = np.concatenate([np.stack(k, 1) for k in pk])
    return st, Records(np.tile(rec.root, 4), pr)


def same_vertex_agreement(straight: np.ndarray, pts: np.ndarray) -> float:
    """Largest disagreement between slots holding the same straight vertex."""
    flat_s, flat_p = straight.reshape(-1, 3), pts.reshape(-1, 3)
    _, inv = np.unique(flat_s, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    ref = np.zeros((inv.max() + 1, 3))
    ref[inv] = flat_p
    return float(np.abs(flat_p - ref[inv]).max())


def check_records(geo: CadGeometry, pts: np.ndarray, rec: Records, atol: float) -> None:
    assert rec.root.dtype == np.int64 and rec.params.dtype == np.float64
    np.testing.assert_allclose(geo.evaluate(rec.root, rec.params), pts, rtol=0, atol=atol)
    # closed directions: the parameters of one facet never jump by a period
    for e, ent in enumerate(geo.entities):
        sel = rec.root == e
        for a, closed in enumerate(ent.closed):
            if closed and sel.any():
                p = rec.params[sel][:, :, a]
                period = np.diff(ent.bounds[a])[0]
                assert np.ptp(p, axis=1).max() < 0.5 * period


# ----------------------------------------------------------------------
# 2D: polygon of a circle
# ----------------------------------------------------------------------
def circle_polygon(c, R, n, offset):
    t = offset + np.linspace(0, 2 * np.pi, n + 1)[:-1]
    x = c + R * np.c_[np.cos(t), np.sin(t), 0 * t]
    return np.stack([x, np.roll(x, -1, axis=0)], axis=1)


@pytest.mark.parametrize("offset", [0.3, 0.0])  # 0.0: a vertex exactly on the seam u = 0 = 1
def test_circle_polygon_refinement(offset):
    c, R = np.array([0.2, 0.2, 0.0]), 0.05  # the DFG / Kadir IGES File 1 cylinder
    geo = CadGeometry([circle(c, R)])
    facets = circle_polygon(c, R, 7, offset)
    rec = geo.attach(facets)
    assert rec.root.shape == (7,) and rec.params.shape == (7, 2, 1)
    np.testing.assert_array_equal(rec.root, 0)
    check_records(geo, facets, rec, 1e-15)
    x = facets
    for _ in range(4):
        st, rec = split_segments(x, rec)
        pts, rec, report = geo.place(rec, st)
        rad = np.linalg.norm(pts - c, axis=2)
        np.testing.assert_allclose(rad, R, rtol=1e-12, atol=0)
        # the new vertex is the radial projection of the straight midpoint
        d = st - c
        d[..., 2] = 0
        np.testing.assert_allclose(pts, c + R * d / np.linalg.norm(d, axis=2)[..., None], rtol=0, atol=1e-12 * R)
        assert same_vertex_agreement(st, pts) <= 1e-12 * R
        check_records(geo, pts, rec, 1e-15)
        assert report.n_points == st.shape[0] * 2 and report.n_fallback == 0
        assert report.n_vertices == st.shape[0]
        h = report.iterations_histogram
        # one seeded projection per distinct (vertex, seed), not per facet slot:
        # only the vertex on the seam has two seeds (u = 0 and u = 1)
        assert report.n_vertices <= h.sum() <= report.n_vertices + 1 and len(h) - 1 <= 7
        # the old vertices (half of them) are exact already: 0 iterations
        assert h[0] >= st.shape[0] // 2
        np.testing.assert_allclose(report.max_residual, np.max(np.linalg.norm(pts - st, axis=2)), rtol=1e-12)
        x = pts


def test_multiple_curves_and_shared_vertices():
    """The unit circle as four quarter arcs; coarse vertices every 30 degrees,
    so the patch junctions (0, 90, 180, 270 degrees) are mesh vertices."""
    arcs = []
    for k in range(4):
        a0, a1 = k * np.pi / 2, (k + 1) * np.pi / 2
        P = [[np.cos(a0), np.sin(a0), 0], [np.cos(a0) + np.cos(a1), np.sin(a0) + np.sin(a1), 0],
             [np.cos(a1), np.sin(a1), 0]]
        arcs.append(NurbsCurve(2, [0, 0, 0, 1, 1, 1], P, [1, S2, 1]))
    geo = CadGeometry(arcs)
    facets = circle_polygon(np.zeros(3), 1.0, 12, 0.0)
    rec = geo.attach(facets)
    ang = np.arctan2(facets.mean(axis=1)[:, 1], facets.mean(axis=1)[:, 0]) % (2 * np.pi)
    np.testing.assert_array_equal(rec.root, (ang // (np.pi / 2)).astype(int))
    check_records(geo, facets, rec, 1e-15)
    x = facets
    for _ in range(3):
        st, rec = split_segments(x, rec)
        pts, rec, report = geo.place(rec, st)
        np.testing.assert_allclose(np.linalg.norm(pts, axis=2), 1.0, rtol=1e-12, atol=0)
        assert same_vertex_agreement(st, pts) == 0.0
        assert report.n_fallback == 0 and report.n_off_root == 0
        check_records(geo, pts, rec, 1e-15)
        x = pts


def test_attach_rejects_facets_off_the_geometry():
    c, R = np.zeros(3), 1.0
    geo = CadGeometry([circle(c, R)])
    facets = circle_polygon(c, R, 8, 0.1)
    facets[3, 1] *= 1.05  # 5 % of the radius off the circle (facet 3 and 4 share it)
    facets[4, 0] = facets[3, 1]
    with pytest.raises(CadError, match=r"facet (3|4).*from the nearest entity") as info:
        geo.attach(facets)
    assert "2 of 8" in str(info.value)
    # a generous tolerance accepts it
    CadGeometry([circle(c, R)], tol_factor=0.2).attach(facets)


def test_place_fallback_from_bad_seeds():
    c, R = np.zeros(3), 1.0
    geo = CadGeometry([circle(c, R)])
    facets = circle_polygon(c, R, 10, 0.2)
    rec = geo.attach(facets)
    st, rec = split_segments(facets, rec)
    d = st.copy()
    d[..., 2] = 0
    truth = R * d / np.linalg.norm(d, axis=2)[..., None]
    # seeds half a period off: the safeguarded Newton still finds the right point
    bad = rec.params.copy()
    bad[:3, 1, 0] += 0.5
    pts, rec2, report = geo.place(Records(rec.root, bad), st)
    np.testing.assert_allclose(pts, truth, rtol=0, atol=1e-12)
    # seeds exactly at the antipodes: a stationary point (the farthest point),
    # where Kadir's zero-cosine criterion stops Newton; the result jumps by
    # ~2R > edge length, so the fallbacks must take over
    anti = geo.searcher.search(-st[:3, 1])[1]
    bad = rec.params.copy()
    bad[:3, 1] = anti
    pts, rec2, report = geo.place(Records(rec.root, bad), st)
    assert report.n_fallback == 3 and report.n_unresolved == 0
    np.testing.assert_allclose(pts, truth, rtol=0, atol=1e-12)
    check_records(geo, pts, rec2, 1e-15)


def test_place_input_checks():
    geo = CadGeometry([circle()])
    facets = circle_polygon(np.zeros(3), 1.0, 6, 0.1)
    rec = geo.attach(facets)
    with pytest.raises(ValueError, match="do not match"):
        geo.place(Records(rec.root[:-1], rec.params[:-1]), facets)
    with pytest.raises(ValueError, match="entities"):
        geo.place(Records(rec.root + 3, rec.params), facets)
    with pytest.raises(ValueError, match="all curves or all surfaces"):
        CadGeometry([circle(), sphere()])
    empty = geo.attach(np.zeros((0, 2, 3)))
    assert empty.root.shape == (0,) and empty.params.shape == (0, 2, 1)


# ----------------------------------------------------------------------
# 3D: triangulated cylinder and sphere
# ----------------------------------------------------------------------
def cylinder_triangles(c, R, H, nt, nz, offset):
    t = offset + 2 * np.pi * np.arange(nt) / nt
    z = np.linspace(0, H, nz + 1)
    X = c + np.stack(np.broadcast_arrays(R * np.cos(t)[:, None], R * np.sin(t)[:, None], z[None, :]), -1)
    tri = []
    for i in range(nt):
        i1 = (i + 1) % nt
        for j in range(nz):
            tri.append([X[i, j], X[i1, j], X[i1, j + 1]])
            tri.append([X[i, j], X[i1, j + 1], X[i, j + 1]])
    return np.array(tri)


@pytest.mark.parametrize("offset", [0.1, 0.0])
def test_cylinder_triangulation_refinement(offset):
    c, R, H = np.array([0.55, 0.5, 0.0]), 0.05, 0.4  # Kadir IGES File 2 cylinder
    geo = CadGeometry([cylinder(c, R, H)])
    facets = cylinder_triangles(c, R, H, 10, 4, offset)
    rec = geo.attach(facets)
    assert rec.params.shape == (80, 3, 2)
    check_records(geo, facets, rec, 1e-15)
    x = facets
    for _ in range(2):
        st, rec = split_triangles(x, rec)
        pts, rec, report = geo.place(rec, st)
        rad = np.hypot(pts[..., 0] - c[0], pts[..., 1] - c[1])
        np.testing.assert_allclose(rad, R, rtol=1e-12, atol=0)
        np.testing.assert_allclose(pts[..., 2], st[..., 2], rtol=0, atol=1e-12 * H)  # radial projection
        assert same_vertex_agreement(st, pts) <= 1e-12 * R
        check_records(geo, pts, rec, 1e-15)
        assert report.n_fallback == 0
        assert len(report.iterations_histogram) - 1 <= 7
        x = pts


def octahedron_sphere(level):
    """Octahedron (vertices include both poles) split ``level`` times, on the unit sphere."""
    V = np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    F = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [1, 0, 5], [2, 1, 5], [3, 2, 5], [0, 3, 5]]
    T = V[np.array(F)]
    for _ in range(level):
        a, b, c = T[:, 0], T[:, 1], T[:, 2]
        ab, bc, ca = [(p + q) / np.linalg.norm(p + q, axis=1)[:, None] for p, q in ((a, b), (b, c), (c, a))]
        T = np.concatenate([np.stack(k, 1) for k in [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]])
    return T


def test_sphere_with_poles_refinement():
    geo = CadGeometry([sphere()])
    facets = octahedron_sphere(1)  # Neto's mesh 1 (32 triangles, 18 nodes)
    rec = geo.attach(facets)
    check_records(geo, facets, rec, 1e-15)
    x = facets
    for _ in range(3):
        st, rec = split_triangles(x, rec)
        pts, rec, report = geo.place(rec, st)
        np.testing.assert_allclose(np.linalg.norm(pts, axis=2), 1.0, rtol=1e-12, atol=0)
        d = st / np.linalg.norm(st, axis=2)[..., None]
        np.testing.assert_allclose(pts, d, rtol=0, atol=1e-12)
        assert same_vertex_agreement(st, pts) <= 1e-12
        check_records(geo, pts, rec, 1e-14)
        assert report.n_unresolved == 0
        assert len(report.iterations_histogram) - 1 <= 7
        x = pts


def test_attach_with_node_ids_and_2d_input():
    geo = CadGeometry([circle()])
    facets = circle_polygon(np.zeros(3), 1.0, 6, 0.1)
    nodes = np.stack([np.arange(6), (np.arange(6) + 1) % 6], axis=1)
    r1 = geo.attach(facets, nodes)
    r2 = geo.attach(facets[..., :2])
    np.testing.assert_array_equal(r1.root, r2.root)
    np.testing.assert_allclose(r1.params, r2.params, atol=1e-15)


# ----------------------------------------------------------------------
# IGES input (written by nagata_snap.cad.iges, read by OpenCASCADE)
# ----------------------------------------------------------------------
def test_from_iges_round_trip(tmp_path):
    from nagata_snap.cad import iges
    c, R = np.array([0.2, 0.2, 0.0]), 0.05
    path = tmp_path / "model.igs"
    iges.write_iges(path, curves=[circle(c, R)], surfaces=[cylinder(np.array([0.55, 0.5, 0.0]), R, 0.4)])
    g2 = CadGeometry.from_iges(path, dim=2)
    g3 = CadGeometry.from_iges(path)  # surfaces preferred
    assert g2.param_dim == 1 and g3.param_dim == 2
    facets = circle_polygon(c, R, 8, 0.3)
    st, rec = split_segments(facets, g2.attach(facets))
    pts, _, _ = g2.place(rec, st)
    np.testing.assert_allclose(np.linalg.norm(pts - c, axis=2), R, rtol=1e-12, atol=0)
    only_curves = tmp_path / "c.igs"
    iges.write_iges(only_curves, curves=[circle(c, R)])
    with pytest.raises(CadError, match="no faces to snap a 3D mesh onto"):
        CadGeometry.from_iges(only_curves, dim=3)


def test_place_fallback_from_nan_seeds():
    # a facet whose records are all NaN: the other-vertex seeds fail too, the
    # KD-tree seeds on the facet's entity must find the points
    c, R = np.zeros(3), 1.0
    geo = CadGeometry([circle(c, R)])
    facets = circle_polygon(c, R, 10, 0.2)
    st, rec = split_segments(facets, geo.attach(facets))
    params = rec.params.copy()
    params[4] = np.nan
    pts, rec2, report = geo.place(Records(rec.root, params), st)
    d = st.copy()
    d[..., 2] = 0
    np.testing.assert_allclose(pts, R * d / np.linalg.norm(d, axis=2)[..., None], rtol=0, atol=1e-12)
    assert report.n_fallback == 2 and report.n_unresolved == 0
    assert np.all(np.isfinite(rec2.params))
    check_records(geo, pts, rec2, 1e-15)


def half_cylinder(c, R, H, start):
    """Half of a cylinder side: angles [start, start + pi] (5-point half circle)."""
    ang = start + np.arange(5) * np.pi / 4
    rad = np.where(np.arange(5) % 2 == 1, R / np.cos(np.pi / 4), R)
    ring = np.c_[rad * np.cos(ang), rad * np.sin(ang), np.zeros(5)]
    P = np.stack([c + ring, c + ring + [0, 0, H]], axis=1)
    w = np.array([1, S2, 1, S2, 1])
    from nagata_snap.cad.nurbs import NurbsSurface

    return NurbsSurface(2, 1, [0, 0, 0, 0.5, 0.5, 1, 1, 1], [0, 0, 1, 1], P, np.stack([w, w], 1))


def test_two_surface_patches():
    c, R, H = np.zeros(3), 1.0, 2.0
    geo = CadGeometry([half_cylinder(c, R, H, 0.0), half_cylinder(c, R, H, np.pi)])
    assert not any(geo.entities[0].closed)
    facets = cylinder_triangles(c, R, H, 8, 3, 0.0)  # vertices on both junction lines
    rec = geo.attach(facets)
    centroid = facets.mean(axis=1)
    np.testing.assert_array_equal(rec.root, (centroid[:, 1] < 0).astype(int))
    check_records(geo, facets, rec, 1e-15)
    x = facets
    for _ in range(2):
        st, rec = split_triangles(x, rec)
        pts, rec, report = geo.place(rec, st)
        np.testing.assert_allclose(np.hypot(pts[..., 0], pts[..., 1]), R, rtol=1e-12, atol=0)
        assert same_vertex_agreement(st, pts) == 0.0
        assert report.n_fallback == 0
        check_records(geo, pts, rec, 1e-15)
        x = pts


# ----------------------------------------------------------------------
# trimmed faces (IGES 144/142 outer loops and holes)
# ----------------------------------------------------------------------
def plane_patch(origin, e1, e2, u, v):
    """Bilinear NURBS plane ``origin + u e1 + v e2`` over ``u, v`` ranges (parameters = lengths)."""
    from nagata_snap.cad.nurbs import NurbsSurface

    o, e1, e2 = (np.asarray(a, dtype=float) for a in (origin, e1, e2))
    P = np.array([[o + a * e1 + b * e2 for b in v] for a in u])
    return NurbsSurface(1, 1, [u[0], u[0], u[1], u[1]], [v[0], v[0], v[1], v[1]], P, np.ones((2, 2)))


def rectangle(u, v, n=4):
    """Closed polygon around ``[u0, u1] x [v0, v1]`` with ``n`` points per side."""
    t = np.linspace(0, 1, n, endpoint=False)
    a, b = np.array([u[0], v[0]]), np.array([u[1], v[1]])
    c = [a, np.array([b[0], a[1]]), b, np.array([a[0], b[1]])]
    return np.concatenate([c[k] + t[:, None] * (c[(k + 1) % 4] - c[k]) for k in range(4)])


def test_point_near_face_extension_goes_to_the_face_containing_its_closest_point():
    # face A: the floor z = 0, a surface over x in [0, 2] trimmed to x in [0, 1];
    # face B: the wall x = 1 standing on A's trimming edge, z in [0, 1]
    A = plane_patch([0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 2], [0, 1])
    B = plane_patch([1, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1], [0, 1])
    loops = [rectangle([0, 1], [0, 1]), None]
    P = np.array([[1.5, 0.5, 0.3], [1.2, 0.3, 0.05], [0.6, 0.5, 0.2], [0.95, 0.5, 0.3]])
    # B (the wall) really holds the closest points of the first two; A of the last two
    untrimmed = CadGeometry([A, B])
    ent0, _, d0 = untrimmed.closest_point(P)
    np.testing.assert_array_equal(ent0, [0, 0, 0, 1])  # A's extension wins without trims
    np.testing.assert_allclose(d0, [0.3, 0.05, 0.2, 0.05], rtol=0, atol=1e-14)
    geo = CadGeometry([A, B], loops)
    ent, par, dist = geo.closest_point(P)
    np.testing.assert_array_equal(ent, [1, 1, 0, 1])
    np.testing.assert_allclose(dist, [0.5, 0.2, 0.2, 0.05], rtol=0, atol=1e-14)
    assert geo.inside(ent, par).all()
    # a point exactly on the shared edge (A's trim, B's boundary) is on either face
    edge = np.array([[1.0, 0.4, 0.0]])
    for e, uv in ((0, [[1.0, 0.4]]), (1, [[0.0, 0.4]])):
        assert geo.inside([e], uv).all()
    assert not geo.inside([0], [[1.0 + 1e-4, 0.4]]).any()  # beyond the trim by 1e-4 (length units)
    assert geo.closest_point(edge)[2][0] <= 1e-15
    # attach: a wall triangle whose vertices all project onto A's extension closer
    # than... they lie on B, so B; a floor triangle next to the edge: A
    wall = np.array([[[1, 0.2, 0.0], [1, 0.4, 0.0], [1, 0.3, 0.1]]])
    floor = np.array([[[1, 0.2, 0.0], [1, 0.4, 0.0], [0.9, 0.3, 0.0]]])
    np.testing.assert_array_equal(geo.attach(np.concatenate([wall, floor])).root, [1, 0])


def test_trim_rejects_projection_outside_face_and_inside_holes():
    A = plane_patch([0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 1], [-1, 1])
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    hole = 0.5 * np.c_[np.cos(t), np.sin(t)]
    geo = CadGeometry([A], [rectangle([-0.9, 0.9], [-0.9, 0.9])], [[hole]])
    # inside the hole; on its circle (between polygon vertices too); on the face;
    # on the outer loop; beyond it by 1e-3 and 1e-5; outside the surface (clamped
    # onto its boundary, outside the loop)
    uv = np.array([[0.0, 0.0], [0.49, 0.0], [0.5, 0.0], [0.5 * np.cos(0.05), 0.5 * np.sin(0.05)],
                   [0.7, 0.7], [0.9, 0.2], [0.9 + 1e-3, 0.2], [0.2, -0.9 - 1e-5], [1.5, 0.0]])
    np.testing.assert_array_equal(geo.inside(np.zeros(len(uv)), uv),
                                  [False, False, True, True, True, True, False, False, False])
    # the search grid keeps only samples on the face
    assert np.all(np.hypot(*geo.searcher.sample_params.T) >= 0.5 - 1e-3)
    with pytest.raises(ValueError, match="surfaces only"):
        CadGeometry([circle()], [hole])
    with pytest.raises(ValueError, match="entries for 1"):
        CadGeometry([A], [None, None])


def plate_with_hole(n=8, R=0.5, r_out=0.9, depth=0.4):
    """Triangles of a plate z = 0 around a hole of radius R and of the hole's wall.

    Ring vertices on the circle (z = 0) are shared by the plate (outer ring at
    ``r_out``) and the wall (lower ring at ``z = -depth``)."""
    t = 2 * np.pi * (np.arange(n) + 0.25) / n
    rim = np.c_[R * np.cos(t), R * np.sin(t), 0 * t]
    out = np.c_[r_out * np.cos(t), r_out * np.sin(t), 0 * t]
    low = rim - [0, 0, depth]
    tri = []
    for i in range(n):
        j = (i + 1) % n
        tri += [[rim[i], out[i], out[j]], [rim[i], out[j], rim[j]]]
    plate = len(tri)
    for i in range(n):
        j = (i + 1) % n
        tri += [[rim[i], rim[j], low[j]], [rim[i], low[j], low[i]]]
    return np.array(tri), plate


def test_edge_vertices_of_plate_and_hole_land_on_the_trimming_curve():
    """The rim of a hole: a new vertex between two rim vertices is the midpoint of
    a chord, inside the hole; projected onto the plate's surface it stays there
    (distance 0, on the plane's extension).  With the hole as a trimming loop
    that result is rejected (the wall's is taken); in any case the vertex is on
    facets of both entities, so it is put onto their common edge, the circle."""
    R = 0.5
    plate = plane_patch([0, 0, 0], [1, 0, 0], [0, 1, 0], [-1, 1], [-1, 1])
    wall = cylinder(np.array([0, 0, -1.0]), R, 1.0)
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    hole = R * np.c_[np.cos(t), np.sin(t)]
    facets, nplate = plate_with_hole(R=R)
    for trimmed in (True, False):
        geo = CadGeometry([plate, wall], *(([rectangle([-1, 1], [-1, 1]), None], [[hole], []]) if trimmed else ()))
        rec = geo.attach(facets)
        np.testing.assert_array_equal(rec.root, np.r_[np.zeros(nplate), np.ones(len(facets) - nplate)])
        x = facets
        for level in range(3):
            st, rec = split_triangles(x, rec)
            pts, rec, report = geo.place(rec, st)
            flat = pts.reshape(-1, 3)
            on_rim = np.isclose(st.reshape(-1, 3)[:, 2], 0.0, atol=1e-15) & (
                np.hypot(*st.reshape(-1, 3)[:, :2].T) < R + 1e-12)
            rad = np.hypot(flat[:, 0], flat[:, 1])
            np.testing.assert_allclose(rad[on_rim], R, rtol=0, atol=1e-13)
            np.testing.assert_allclose(flat[on_rim, 2], 0.0, rtol=0, atol=1e-15)
            np.testing.assert_allclose(pts[rec.root == 0][..., 2], 0.0, rtol=0, atol=1e-15)  # plate stays flat
            w = pts[rec.root == 1]
            np.testing.assert_allclose(np.hypot(w[..., 0], w[..., 1]), R, rtol=0, atol=1e-14)
            assert same_vertex_agreement(st, pts) == 0.0
            assert report.n_unresolved == 0
            assert (report.n_left_face > 0) == trimmed
            assert report.n_edge_vertices == 8 * 2 ** (level + 1)
            assert report.max_edge_gap <= 1e-14
            # records: every slot's parameters evaluate to its vertex on its own entity
            np.testing.assert_allclose(geo.evaluate(rec.root, rec.params), pts, rtol=0, atol=1e-14)
            assert geo.inside(np.repeat(rec.root, 3), rec.params.reshape(-1, 2)).all()
            x = pts


def test_row_ids_by_lexsort_match_numpy_unique():
    """``_row_index`` (facet-edge and hint keys) numbers rows as ``np.unique(axis=0)`` does."""
    from nagata_snap.mesh.arrays import row_index as _row_index

    rng = np.random.default_rng(3)
    for shape in ((0, 2), (1, 3), (500, 2), (2000, 3)):
        rows = rng.integers(0, 40, size=shape) * 10**9  # large global ids too
        np.testing.assert_array_equal(
            _row_index(rows), np.unique(rows, axis=0, return_inverse=True)[1].reshape(-1))


def test_three_distinct_points_check_of_trimming_wires():
    from nagata_snap.cad.topology import _three_distinct

    a, b, c = [0.0, 0.0], [1.0, 0.0], [0.0, 1.0]
    assert _three_distinct(np.array([a, b, c]))
    assert _three_distinct(np.array([a, a, b, b, a, c]))
    assert not _three_distinct(np.array([a, b, a, b, b]))
    assert not _three_distinct(np.array([a, a, a]))
    assert not _three_distinct(np.array([a, b]))


def test_wire_check_names_the_first_wire_without_three_distinct_finite_points():
    """``topology._check_wires`` (a quick test of three points per wire, the full one where that
    fails) against ``np.unique`` of every wire's rows rounded to 1e-12 of its extent."""
    from nagata_snap.cad.topology import _check_wires, _FaceError

    rng = np.random.default_rng(5)

    def wire(kind: int) -> np.ndarray:
        n = int(rng.integers(1, 40))
        P = rng.uniform(-3.0, 5.0, (n, 2))
        if kind == 1:  # two values, alternating
            P[:] = P[0]
            P[1::2] = P[min(1, n - 1)] + 1.0
        elif kind == 2:  # one point off the rest, by less than the rounding
            P[:] = P[0]
            P[n // 2] += 1e-14
        elif kind == 3:
            P[rng.integers(n)] = np.nan
        elif kind == 4:  # the quick test's three rows equal, another row off
            P[:] = P[0]
            P[-1] += 1.0
            P[n // 2 + 1:n - 1] -= 0.5
        return P

    for _ in range(300):
        wires = [wire(int(rng.choice(5, p=[0.8, 0.05, 0.05, 0.05, 0.05]))) for _ in range(int(rng.integers(1, 6)))]
        ends = np.r_[0, np.cumsum([len(w) for w in wires])]
        P = np.concatenate(wires)
        good = []
        for w in wires:
            if not np.isfinite(w).all():
                good.append(False)
                continue
            R = np.round(w / max(w.max() - w.min(), 1e-300), 12)
            good.append(len(np.unique(R, axis=0)) >= 3)
        face = list(range(10, 10 + len(wires)))
        if all(good):
            _check_wires(P, ends, face)
        else:
            with pytest.raises(_FaceError) as info:
                _check_wires(P, ends, face)
            assert info.value.face == face[good.index(False)]


def test_trim_loops_checked_together_as_loop_by_loop(monkeypatch):
    """``TrimLoops`` of loops with bands (a model's) checks and prepares them all at once: the
    same polygons, segments, bands and slabs as loop by loop, and the same error for a loop
    that is not a finite polygon of 2 vertices (or a band of the wrong length)."""
    from nagata_snap.cad.trimming import TrimLoops

    rng = np.random.default_rng(8)
    ents = [cylinder(1.0 + i, 2.0) for i in range(4)]

    def loops_and_bands():
        loops, bands = [], []
        for _ in ents:  # the loops of each entity
            lp, bd = [], []
            for _ in range(int(rng.integers(0, 3))):
                P = rng.uniform(0.0, 1.0, (int(rng.integers(2, 30)), 2))
                if rng.random() < 0.3:  # closed on its first vertex
                    P = np.r_[P, P[:1]]
                lp.append(P)
                bd.append(rng.uniform(0.0, 1e-3, len(P) - (len(P) > 2 and (P[0] == P[-1]).all())))
            loops.append(lp)
            bands.append(bd)
        return loops, bands

    def state(t):
        return [[(P.tobytes(), seg.tobytes(), band.tobytes(), sl.y0, sl.n, sl.dy, sl.seg.tobytes(), sl.ptr.tobytes())
                 for P, seg, band, sl in lp] for lp in t._loops]

    for _ in range(30):
        loops, bands = loops_and_bands()
        with monkeypatch.context() as m:  # all at once: not loop by loop
            m.setattr(TrimLoops, "_checked", lambda self, lp, b: pytest.fail("checked loop by loop"))
            together = TrimLoops(ents, loops, bands)
        with monkeypatch.context() as m:
            m.setattr(TrimLoops, "_checked_together", lambda self, lp, b: None)
            alone = TrimLoops(ents, loops, bands)
        assert state(together) == state(alone)
        assert np.array_equal(together.trimmed, [bool(lp) for lp in loops])
    loops, bands = [[np.zeros((3, 2))], [], [], []], [[np.zeros(3)], [], [], []]
    for bad, match in ((np.array([[0.0, 0.0], [np.nan, 1.0], [1.0, 1.0]]), "loop 0 must be a finite"),
                       (np.array([[0.0, 0.0], [0.0, 0.0]]), "fewer than 2 vertices"),
                       (np.arange(8.0).reshape(4, 2), "cannot reshape")):
        loops[0][0] = bad
        with pytest.raises(ValueError, match=match):
            TrimLoops(ents, loops, bands)


def test_corner_rule_counts_distinct_faces_and_edges():
    """``corner_vertices``: three faces, or two distinct CAD edges, make a corner; repeats do not."""
    from nagata_snap.mesh.corners import corner_vertices

    vertex = np.array([0, 0, 0, 1, 1, 1, 2, 2, 3, 3])
    face = np.array([0, 1, 2, 0, 1, 1, 0, 1, 4, 4])
    edge = np.array([-1, -1, -1, 5, 5, 5, 5, 6, -1, -1])  # vertex 2 on edges 5 and 6
    np.testing.assert_array_equal(corner_vertices(vertex, face, 5, 3), [True, False, False, False, False])
    np.testing.assert_array_equal(corner_vertices(vertex, face, 5, 3, edge=edge),
                                  [True, False, True, False, False])
    np.testing.assert_array_equal(corner_vertices(vertex, face, 5, 2), [True, True, True, False, False])
    assert not corner_vertices(np.zeros(0, int), np.zeros(0, int), 2, 3).any()


@pytest.mark.parametrize("offset", [0, 2**40])
def test_mesh_hints_find_facets_by_their_node_sets(offset):
    """``MeshHints.lookup``: a facet is found whatever the order of its nodes, and its seeds follow
    that order; a facet the mesher did not make gives None (also with ids beyond or below every
    hinted one); a node set hinted twice gives the later facet.  With ``offset`` 2**40 the ids
    are too wide for one packed key per facet (the rows are numbered together instead)."""
    from nagata_snap.cad.attach import MeshHints

    nodes = np.array([[10, 20, 30], [30, 20, 40], [50, 60, 70], [60, 70, 50]]) + offset
    params = np.arange(24.0).reshape(4, 3, 2)
    hints = MeshHints.from_facets(nodes, [7, 8, 5, 6], params, 2)
    assert (hints.keys is None) == (offset > 0)
    faces, seeds = hints.lookup(np.array([[20, 40, 30], [30, 10, 20], [70, 50, 60]]) + offset)
    np.testing.assert_array_equal(faces, [8, 7, 6])
    np.testing.assert_array_equal(seeds, np.stack([params[1][[1, 2, 0]], params[0][[2, 0, 1]],
                                                   params[3][[1, 2, 0]]]))
    for missing in ([10, 20, 40], [10, 20, 2**41], [-1, 10, 20], [0, 10, 20]):
        assert hints.lookup(np.array([[10, 20, 30], missing]) + offset) is None


def test_place_stages_recover_from_a_bad_seed_on_the_root_entity():
    """``place.on_root``: a seed that sends Newton to the far side of the sphere (farther than the
    facet's edge) is retried from the facet's other vertices; every slot ends at ``x / |x|``."""
    from nagata_snap.cad.place import merge, on_root, slots_of

    geo = CadGeometry([sphere()])
    facets = octahedron_sphere(2)
    rec = geo.attach(facets)
    x = facets[:, :, :] * 1.01  # off the sphere, radially
    i = np.flatnonzero(np.abs(facets[:, 0, 2]) < 0.9)[0]  # a first vertex away from the poles
    anti = geo.attach(-facets[i:i + 1]).params[0, 0]
    rec.params[i, 0] = anti  # its seed: the antipode
    s = slots_of(geo, rec, x, "x")
    p = on_root(geo, s)
    assert p.n_fallback >= 1 and p.valid.all()
    truth = (x / np.linalg.norm(x, axis=2)[..., None]).reshape(-1, 3)
    np.testing.assert_allclose(p.proj, truth, rtol=0, atol=1e-12)
    m = merge(geo, s, p)  # one position per vertex: the same here
    np.testing.assert_allclose(p.proj, truth, rtol=0, atol=1e-12)
    assert m.n_edge == 0 and len(m.rep_of_group) == len(np.unique(facets.reshape(-1, 3).round(12), axis=0))


def test_attach_keeps_exact_seeds_and_projects_inexact_ones():
    """Seeds that are their vertex (a mesher's node parameters) are the vertex's parameters;
    seeds a little off are projected by Newton to the same parameters; vertices moved off
    the face (beyond its end) still fail the attach check, whatever their seeds."""
    R, H = 0.7, 1.3
    geo = CadGeometry([cylinder(np.zeros(3), R, H)])
    rng = np.random.default_rng(5)
    P = np.stack([rng.uniform(0.05, 0.45, (40, 3)), rng.uniform(0.1, 0.9, (40, 3))], axis=2)  # (nf, 3, 2)
    facets = geo.evaluate(np.zeros(40, dtype=np.int64), P)
    faces = np.zeros(40, dtype=np.int64)
    exact = geo.attach(facets, faces=faces, seeds=P)
    np.testing.assert_array_equal(exact.params[:, :, :2], P)
    near = geo.attach(facets, faces=faces, seeds=P + rng.uniform(-1e-3, 1e-3, P.shape))
    np.testing.assert_allclose(near.params[:, :, :2], P, rtol=0, atol=1e-12)
    assert np.allclose(np.hypot(facets[..., 0], facets[..., 1]), R, rtol=1e-14)
    with pytest.raises(CadError, match="do not lie on the CAD geometry"):
        geo.attach(facets + np.array([0.0, 0.0, 0.3 * H]), faces=faces, seeds=P)


def test_collapsed_rows_of_a_net_mark_surfaces_that_can_degenerate():
    """A sphere's net collapses at the poles; a cylinder's and a torus' never do."""
    from nagata_snap.cad.nurbs import torus
    from nagata_snap.cad.params import degenerate

    assert sphere().can_degenerate
    assert not cylinder().can_degenerate and not torus().can_degenerate
    s = sphere()
    (u0, u1), (_, v1) = s.domain_u, s.domain_v
    at = np.array([[u0, 0.3 * v1], [0.5 * (u0 + u1), 0.3 * v1], [u1, 0.7 * v1]])
    np.testing.assert_array_equal(degenerate([s], np.zeros(3, dtype=np.int64), at),
                                  [[False, True], [False, False], [False, True]])


def test_outside_by_on_loops_along_the_ends_of_open_directions():
    """A loop that runs along the end of an open parameter direction (a B-spline face trimmed
    by its own knot domain, as CATIA writes them): the test points beyond such a segment are
    clamped onto it, yet ``outside_by`` still knows the face's side there (the polygon's own
    even-odd test): negative for a point inside, positive beyond, on all four sides."""
    from nagata_snap.cad.nurbs import NurbsSurface
    from nagata_snap.cad.trimming import TrimLoops

    P = np.array([[[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]], [[3.0, 0.0, 0.0], [3.0, 2.0, 0.1]]])
    s = NurbsSurface(1, 1, [0, 0, 1, 1], [0, 0, 1, 1], P, np.ones((2, 2)))
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    t = TrimLoops([s], [[square]], [[np.full(4, 1e-3)]])
    ref = np.array([[0.5, 0.0], [1.0, 0.5], [0.5, 1.0], [0.0, 0.5]])  # on each side
    inward = np.array([[0.0, 1.0], [-1.0, 0.0], [0.0, -1.0], [1.0, 0.0]])
    ent = np.zeros(4, dtype=np.int64)
    assert (t.outside_by(ent, ref, ref + 0.1 * inward) < 0).all()
    assert (t.outside_by(ent, ref, ref - 0.1 * inward) > 0).all()
