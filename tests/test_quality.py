"""Tests of nagata_snap.smoothing.quality against closed-form / independently computed truth."""

import json
import math

import mpi4py.MPI as MPI
import numpy as np
import pytest

import dolfinx
import dolfinx.mesh

from nagata_snap.mesh.simplex import signed_volumes
from nagata_snap.smoothing.quality import QualityReport, inverted_cells, mean_ratio, quality_stats

TRI = np.array([[0, 1, 2]])
TET = np.array([[0, 1, 2, 3]])


def pad3(p):
    p = np.asarray(p, dtype=np.float64)
    out = np.zeros((p.shape[0], 3))
    out[:, : p.shape[1]] = p
    return out


def regular_tet():
    # alternate vertices of the unit cube: regular tetrahedron, edge sqrt(2)
    return np.array([[0.0, 0, 0], [1, 1, 0], [1, 0, 1], [0, 1, 1]])


def test_equilateral_triangle():
    x = pad3([[0, 0], [1, 0], [0.5, math.sqrt(3) / 2]])
    q = quality_stats(x, TRI, 2)
    assert q["volume"][0] == pytest.approx(math.sqrt(3) / 4, rel=1e-14)
    assert q["min_angle"][0] == pytest.approx(60.0, abs=1e-10)
    assert q["max_angle"][0] == pytest.approx(60.0, abs=1e-10)
    assert q["radius_ratio"][0] == pytest.approx(1.0, abs=1e-12)
    assert q["mean_ratio"][0] == pytest.approx(1.0, abs=1e-12)
    # invariance under scaling, rotation and translation
    th = 0.7
    rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    x2 = pad3(3.7 * x[:, :2] @ rot.T + [5.0, -2.0])
    q2 = quality_stats(x2, TRI, 2)
    for k in ("min_angle", "max_angle", "radius_ratio", "mean_ratio"):
        assert q2[k][0] == pytest.approx(q[k][0], abs=1e-10)


def test_regular_tetrahedron():
    x = regular_tet()
    q = quality_stats(x, TET, 3)
    dihedral = math.degrees(math.acos(1.0 / 3.0))  # 70.528779...
    assert abs(q["volume"][0]) == pytest.approx(1.0 / 3.0, rel=1e-14)  # (sqrt 2)^3 / (6 sqrt 2)
    assert q["min_angle"][0] == pytest.approx(dihedral, abs=1e-10)
    assert q["max_angle"][0] == pytest.approx(dihedral, abs=1e-10)
    assert q["radius_ratio"][0] == pytest.approx(1.0, abs=1e-12)
    assert q["mean_ratio"][0] == pytest.approx(1.0, abs=1e-12)


def test_right_isosceles_triangle():
    x = pad3([[0, 0], [1, 0], [0, 1]])
    q = quality_stats(x, TRI, 2)
    assert q["min_angle"][0] == pytest.approx(45.0, abs=1e-10)
    assert q["max_angle"][0] == pytest.approx(90.0, abs=1e-10)
    # right triangle: r = (a + b - c) / 2, R = c / 2  ->  2 r / R = 2 (sqrt2 - 1)
    assert q["radius_ratio"][0] == pytest.approx(2 * (math.sqrt(2) - 1), rel=1e-12)
    # 4 sqrt3 A / (a^2 + b^2 + c^2) = 4 sqrt3 * 0.5 / 4
    assert q["mean_ratio"][0] == pytest.approx(math.sqrt(3) / 2, rel=1e-12)


def test_signed_volumes_orientation():
    x = pad3([[0, 0], [1, 0], [0, 1]])
    assert signed_volumes(x, TRI, 2)[0] == pytest.approx(0.5)
    assert signed_volumes(x, TRI[:, [0, 2, 1]], 2)[0] == pytest.approx(-0.5)
    # the third coordinate is ignored in 2D
    x[:, 2] = [1.0, -3.0, 7.0]
    assert signed_volumes(x, TRI, 2)[0] == pytest.approx(0.5)
    t = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    assert signed_volumes(t, TET, 3)[0] == pytest.approx(1.0 / 6.0)
    assert signed_volumes(t, TET[:, [1, 0, 2, 3]], 3)[0] == pytest.approx(-1.0 / 6.0)


def test_flipped_cell_detected():
    # two triangles sharing an edge; push the apex of one through the edge
    x_ref = pad3([[0, 0], [1, 0], [0.5, 1], [0.5, -1]])
    cells = np.array([[0, 1, 2], [1, 0, 3]])
    assert inverted_cells(x_ref, x_ref, cells, 2).size == 0
    x_new = x_ref.copy()
    x_new[2, 1] = -0.2  # apex of cell 0 below the shared edge
    np.testing.assert_array_equal(inverted_cells(x_new, x_ref, cells, 2), [0])
    # same in 3D: reflect one vertex through the opposite face
    t = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    t2 = t.copy()
    t2[3, 2] = -0.5
    np.testing.assert_array_equal(inverted_cells(t2, t, TET, 3), [0])
    # orientation-aware ratios of an inverted cell are negative
    q = quality_stats(t2, TET, 3, orientation=signed_volumes(t, TET, 3))
    assert q["mean_ratio"][0] < 0 and q["radius_ratio"][0] < 0
    # the reference orientation decides, not the sign convention of the cell
    cells_cw = TET[:, [1, 0, 2, 3]]
    assert inverted_cells(t, t, cells_cw, 3).size == 0
    np.testing.assert_array_equal(inverted_cells(t2, t, cells_cw, 3), [0])


def sliver(eps):
    # four nearly coplanar points at the corners of a square: all edges of
    # comparable length, volume -> 0, dihedral angles -> 0 and 180 degrees
    return np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, eps], [0, -1, eps]])


def test_sliver_below_floor():
    x = sliver(1e-4)
    q = quality_stats(x, TET, 3)
    le = np.linalg.norm(x[[0, 0, 0, 1, 1, 2]] - x[[1, 2, 3, 2, 3, 3]], axis=1)
    assert le.min() / le.max() > 0.7  # not a needle: edge-based checks miss it
    assert q["min_angle"][0] < 1.0
    assert q["max_angle"][0] > 179.0
    assert q["mean_ratio"][0] < 0.01  # below the repair quality floor
    assert q["radius_ratio"][0] < 0.01
    assert mean_ratio(x, TET, 3)[0] == pytest.approx(q["mean_ratio"][0], rel=1e-12)
    # relative volume floor: sliver of a healthy reference tet
    x_ref = sliver(1.0)
    assert inverted_cells(x, x_ref, TET, 3, rel_floor=1e-2).size == 1
    assert inverted_cells(x, x_ref, TET, 3, rel_floor=1e-5).size == 0
    # a fully flat cell is always below the floor
    assert inverted_cells(sliver(0.0), x_ref, TET, 3).size == 1
    assert quality_stats(sliver(0.0), TET, 3)["mean_ratio"][0] == 0.0


def _circumradius(P):
    """Independent circumradius: solve 2 (p_i - p_0) . c = |p_i|^2 - |p_0|^2."""
    A = 2.0 * (P[:, 1:, :] - P[:, :1, :])
    b = (P[:, 1:, :] ** 2).sum(-1) - (P[:, :1, :] ** 2).sum(-1)
    c = np.linalg.solve(A, b[..., None])[..., 0]
    return np.linalg.norm(P[:, 0, :] - c, axis=1)


def test_random_triangles_against_independent_formulas():
    rng = np.random.default_rng(1)
    n = 200
    P = rng.uniform(-1, 1, size=(n, 3, 2))
    x = pad3(P.reshape(-1, 2))
    cells = np.arange(3 * n).reshape(n, 3)
    q = quality_stats(x, cells, 2)
    a = np.linalg.norm(P[:, 1] - P[:, 2], axis=1)
    b = np.linalg.norm(P[:, 0] - P[:, 2], axis=1)
    c = np.linalg.norm(P[:, 0] - P[:, 1], axis=1)
    # law of cosines
    A0 = np.degrees(np.arccos((b**2 + c**2 - a**2) / (2 * b * c)))
    A1 = np.degrees(np.arccos((a**2 + c**2 - b**2) / (2 * a * c)))
    A2 = 180.0 - A0 - A1
    ang = np.stack([A0, A1, A2], 1)
    np.testing.assert_allclose(q["min_angle"], ang.min(1), atol=1e-7)
    np.testing.assert_allclose(q["max_angle"], ang.max(1), atol=1e-7)
    s = 0.5 * (a + b + c)
    area = np.sqrt(s * (s - a) * (s - b) * (s - c))  # Heron
    np.testing.assert_allclose(np.abs(q["volume"]), area, rtol=1e-8)
    r_in = area / s
    np.testing.assert_allclose(q["radius_ratio"], 2 * r_in / _circumradius(P), rtol=1e-7)


def test_random_tets_against_independent_formulas():
    rng = np.random.default_rng(2)
    n = 200
    P = rng.uniform(-1, 1, size=(n, 4, 3))
    cells = np.arange(4 * n).reshape(n, 4)
    q = quality_stats(P.reshape(-1, 3), cells, 3)
    vol = np.abs(np.linalg.det(P[:, 1:] - P[:, :1])) / 6.0
    np.testing.assert_allclose(np.abs(q["volume"]), vol, rtol=1e-9)
    # faces opposite each vertex, outward unit normals from explicit orientation
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]
    normals, areas = [], []
    for k, (i, j, l) in enumerate(faces):
        nrm = np.cross(P[:, j] - P[:, i], P[:, l] - P[:, i])
        side = np.einsum("ij,ij->i", nrm, P[:, k] - P[:, i])
        nrm = -nrm * np.sign(side)[:, None]  # point away from vertex k
        areas.append(0.5 * np.linalg.norm(nrm, axis=1))
        normals.append(nrm / np.linalg.norm(nrm, axis=1)[:, None])
    dih = []
    for k in range(4):
        for m in range(k + 1, 4):
            cosang = np.einsum("ij,ij->i", normals[k], normals[m])
            dih.append(180.0 - np.degrees(np.arccos(np.clip(cosang, -1, 1))))
    dih = np.stack(dih, 1)
    np.testing.assert_allclose(q["min_angle"], dih.min(1), atol=1e-6)
    np.testing.assert_allclose(q["max_angle"], dih.max(1), atol=1e-6)
    r_in = 3 * vol / np.sum(areas, axis=0)
    np.testing.assert_allclose(q["radius_ratio"], 3 * r_in / _circumradius(P), rtol=1e-6)
    e2 = sum(np.sum((P[:, i] - P[:, j]) ** 2, 1) for i in range(4) for j in range(i + 1, 4))
    np.testing.assert_allclose(q["mean_ratio"], 12 * (3 * vol) ** (2 / 3) / e2, rtol=1e-9)


def test_report_on_structured_mesh():
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 5)
    x_ref = msh.geometry.x.copy()
    rep = QualityReport.from_mesh(msh, x_ref=x_ref, x_before=x_ref,
                                  timings={"smooth": 0.5, "check": 0.25},
                                  shortfall=np.array([0.0, 0.1, 0.3]))
    assert rep.n_cells == 60
    # all cells are right triangles with legs 1/6, 1/5: independent truth
    ang = math.degrees(math.atan2(1 / 5, 1 / 6))
    assert rep.min_angle.min == pytest.approx(min(ang, 90 - ang), abs=1e-10)
    assert rep.max_angle.max == pytest.approx(90.0, abs=1e-10)
    assert int(rep.mean_ratio.hist.sum()) == 60
    assert int(rep.min_angle.hist.sum()) == 60
    assert rep.n_inverted_before == 0 and rep.n_inverted_after == 0
    assert rep.n_moved == 0 and rep.max_displacement == 0.0
    assert rep.n_shortfall == 2 * MPI.COMM_WORLD.size
    assert rep.max_shortfall == pytest.approx(0.3)
    d = rep.as_dict()
    json.dumps(d)  # plain types only
    assert d["timings"] == {"smooth": 0.5, "check": 0.25}
    s = str(rep)
    for key in ("radius ratio", "mean ratio", "inverted after smooth", "max shortfall",
                "smooth", "check"):
        assert key in s
    # aligned table: the four summary rows have the same length
    rows = [ln for ln in s.splitlines() if ln.strip().startswith(("min angle", "max angle",
                                                                  "radius ratio", "mean ratio"))]
    assert len({len(r) for r in rows[:4]}) == 1


def test_changed_scope_covers_exactly_the_cells_with_moved_nodes():
    """scope='changed': metrics of the cells touching a moved node, same inversion counts."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_SELF, 8, 8)
    x_ref = msh.geometry.x.copy()
    x = x_ref.copy()
    x_before = x_ref.copy()
    cells = msh.geometry.dofmaps[0]
    # push the node nearest (0.5, 0.5) past its neighbours (inverts cells), and
    # before smoothing also a second node
    i = int(np.argmin(np.linalg.norm(x_ref[:, :2] - 0.5, axis=1)))
    j = int(np.argmin(np.linalg.norm(x_ref[:, :2] - 0.25, axis=1)))
    x[i, 0] += 0.2
    x_before[[i, j], 0] += 0.2
    full = QualityReport.from_arrays(MPI.COMM_SELF, x, cells, 2, x_ref=x_ref, x_before=x_before)
    part = QualityReport.from_arrays(MPI.COMM_SELF, x, cells, 2, x_ref=x_ref, x_before=x_before,
                                     scope="changed")
    touched = np.flatnonzero(np.isin(cells, [i, j]).any(axis=1))
    assert part.scope == "changed" and part.n_cells == touched.size == 12
    assert part.n_cells_mesh == full.n_cells == 128
    q = quality_stats(x, cells[touched], 2)
    assert part.min_angle.min == pytest.approx(float(q["min_angle"].min()), abs=1e-12)
    assert part.max_angle.max == pytest.approx(float(q["max_angle"].max()), abs=1e-12)
    assert int(part.mean_ratio.hist.sum()) == 12
    assert part.n_inverted_after == full.n_inverted_after > 0
    assert part.n_inverted_before == full.n_inverted_before > 0
    assert (part.n_moved, part.max_displacement) == (full.n_moved, full.max_displacement)
    assert "12 changed cells of 128" in str(part)
    with pytest.raises(ValueError, match="scope"):
        QualityReport.from_arrays(MPI.COMM_SELF, x, cells, 2, scope="band")
    with pytest.raises(ValueError, match="needs x_ref"):
        QualityReport.from_arrays(MPI.COMM_SELF, x, cells, 2, scope="changed")
