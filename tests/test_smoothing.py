"""Tests of nagata_snap.smoothing.smooth: interior smoothing, guard and repair."""

import json
import os
import pathlib
import subprocess
import sys

import mpi4py.MPI as MPI
import numpy as np
import pytest

import dolfinx
import dolfinx.mesh

from nagata_snap.smoothing.quality import inverted_cells, mean_ratio
from nagata_snap.smoothing.repair import FIRST_SWEEPS, InvertedCellsError, RepairResult, repair
from nagata_snap.smoothing.smooth import smooth

COMM = MPI.COMM_SELF
REPO = pathlib.Path(__file__).resolve().parents[1]
N = 16
H = 1.0 / N
TOL = 1e-12


def n_inverted(msh, x, x_ref):
    cells = msh.geometry.dofmaps[0]
    return inverted_cells(x, x_ref, cells, msh.geometry.dim).size


def square_push(amp, n=N, comm=COMM):
    """Unit square; interior nodes of the left side pushed in by amp*sin(pi y)."""
    msh = dolfinx.mesh.create_unit_square(comm, n, n)
    x_ref = msh.geometry.x.copy()
    x = x_ref
    left = np.flatnonzero((x[:, 0] < TOL) & (x[:, 1] > TOL) & (x[:, 1] < 1 - TOL))
    bnd = np.flatnonzero((x[:, 0] < TOL) | (x[:, 0] > 1 - TOL)
                         | (x[:, 1] < TOL) | (x[:, 1] > 1 - TOL))
    fixed = np.setdiff1d(bnd, left).astype(np.int32)
    left = left.astype(np.int32)
    msh.geometry.x[left, 0] += amp * np.sin(np.pi * x_ref[left, 1])
    return msh, x_ref, left, fixed


@pytest.fixture(scope="module")
def pushed():
    # 1.5 x the cell size at mid-side: the first columns of cells invert
    return square_push(1.5 * H)


@pytest.mark.parametrize("method", ["elastic", "laplace"])
def test_smoothing_removes_inversions(pushed, method):
    msh, x_ref, left, fixed = pushed
    x_cur = msh.geometry.x.copy()
    ref_copy, left_copy, fixed_copy = x_ref.copy(), left.copy(), fixed.copy()
    assert n_inverted(msh, x_cur, x_ref) > 0  # the test is meaningful
    x_none = smooth(msh, x_ref, left, fixed, method="none")
    np.testing.assert_array_equal(x_none, x_cur)
    info = {}
    x_new = smooth(msh, x_ref, left, fixed, method=method, info=info)
    assert n_inverted(msh, x_new, x_ref) == 0
    assert mean_ratio(x_new, msh.geometry.dofmaps[0], 2).min() > 0.2
    # prescribed and fixed nodes exactly where they were put
    np.testing.assert_array_equal(x_new[left], x_cur[left])
    np.testing.assert_array_equal(x_new[fixed], x_ref[fixed])
    # interior actually moved, and only inside the band
    assert np.abs(x_new - x_cur).max() > 0.5 * H
    band_width = SMOOTH_LAYERS * H
    far = x_ref[:, 0] > band_width + 1e-9
    np.testing.assert_array_equal(x_new[far], x_ref[far])
    assert info["band_free_nodes"] > 0 and info["band_cells"] < 2 * N * N
    # inputs untouched
    np.testing.assert_array_equal(msh.geometry.x, x_cur)
    np.testing.assert_array_equal(x_ref, ref_copy)
    np.testing.assert_array_equal(left, left_copy)
    np.testing.assert_array_equal(fixed, fixed_copy)


SMOOTH_LAYERS = 4


def test_straight_mesh_is_fixed_point(pushed):
    _, x_ref, left, fixed = pushed
    msh2 = dolfinx.mesh.create_unit_square(COMM, N, N)
    for method in ("elastic", "laplace"):
        x_new = smooth(msh2, x_ref, left, fixed, method=method)
        np.testing.assert_allclose(x_new, x_ref, atol=1e-14)


@pytest.mark.parametrize("sweeps", [1, 8, 50])
def test_laplace_sweeps_equal_petsc_richardson(pushed, sweeps):
    # the matrix-free sweeps against PETSc's Richardson + Jacobi on the assembled graph
    # Laplacian of the band (the path taken when PETSc options are given)
    msh, x_ref, left, fixed = pushed
    free = smooth(msh, x_ref, left, fixed, method="laplace", sweeps=sweeps)
    petsc = smooth(msh, x_ref, left, fixed, method="laplace", sweeps=sweeps,
                   petsc_options={"ksp_richardson_scale": 1.0})
    assert np.abs(free - x_ref).max() > 0.1 * H  # the interior moved
    np.testing.assert_allclose(free, petsc, rtol=0, atol=1e-14)


@pytest.mark.parametrize("model", ["elastic", "harmonic"])
def test_translation_is_reproduced(model):
    msh = dolfinx.mesh.create_unit_square(COMM, 12, 12)
    x_ref = msh.geometry.x.copy()
    x = x_ref
    bnd = np.flatnonzero((x[:, 0] < TOL) | (x[:, 0] > 1 - TOL)
                         | (x[:, 1] < TOL) | (x[:, 1] > 1 - TOL)).astype(np.int32)
    t = np.array([0.0137, -0.0071, 0.0])
    msh.geometry.x[bnd] += t
    # band wide enough to contain the whole mesh
    x_new = smooth(msh, x_ref, bnd, np.zeros(0, np.int32), method="elastic",
                   model=model, layers=20)
    np.testing.assert_allclose(x_new - x_ref, np.broadcast_to(t, x_ref.shape), atol=1e-10)
    # with the default band, nodes beyond it stay (outer band boundary fixed)
    x_b = smooth(msh, x_ref, bnd, np.zeros(0, np.int32), method="elastic", layers=2)
    centre = np.flatnonzero(np.abs(x_ref[:, :2] - 0.5).max(axis=1) < 0.5 - 3.5 / 12)
    assert centre.size > 0
    np.testing.assert_array_equal(x_b[centre], x_ref[centre])


@pytest.mark.parametrize("dim, model, exponent", [(2, "elastic", 1.0), (3, "elastic", 2.0),
                                                  (3, "harmonic", 1.0)])
def test_band_system_equals_ufl_assembly(dim, model, exponent):
    """The band system, assembled by hand from hat-function gradients, gives
    the same displacement as the same problem written in UFL and assembled
    and solved (LU) by DOLFINx on the whole mesh, with Dirichlet data on
    every node that is not an unknown of the band."""
    import ufl
    import dolfinx.fem.petsc

    if dim == 2:
        msh = dolfinx.mesh.create_unit_square(COMM, 10, 10, dolfinx.mesh.CellType.triangle)
    else:
        msh = dolfinx.mesh.create_unit_cube(COMM, 5, 5, 5)
    x_ref = msh.geometry.x.copy()
    x = x_ref
    on_bnd = np.any((x[:, :dim] < TOL) | (x[:, :dim] > 1 - TOL), axis=1)
    left = np.flatnonzero((x[:, 0] < TOL) & on_bnd)
    inner_left = left[np.all((x[left, 1:dim] > TOL) & (x[left, 1:dim] < 1 - TOL), axis=1)]
    disp = np.zeros_like(x_ref)
    disp[inner_left, 0] = 0.06 * np.prod(np.sin(np.pi * x[inner_left, 1:dim]), axis=1)
    disp[inner_left, 1] = 0.02 * np.sin(2 * np.pi * x[inner_left, 1])
    msh.geometry.x[:] = x_ref + disp
    x_new = smooth(msh, x_ref, inner_left.astype(np.int32), np.zeros(0, np.int32),
                   method="elastic", model=model, exponent=exponent, layers=2, rtol=1e-14)
    msh.geometry.x[:] = x_ref

    # unknowns of a 2-layer band, worked out here from the cells directly:
    # nodes of cells touching a moved node, minus moved and boundary nodes
    cells = msh.geometry.dofmaps[0]
    moved = np.zeros(len(x), bool)
    moved[inner_left] = True
    layer1 = np.zeros(len(x), bool)
    layer1[cells[moved[cells].any(axis=1)].ravel()] = True
    free = layer1 & ~moved & ~on_bnd

    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1, (dim,)))
    node_to_dof = np.empty(len(x), np.int32)
    node_to_dof[cells.ravel()] = V.dofmap.list.ravel()
    Q = dolfinx.fem.functionspace(msh, ("DG", 0))
    E = dolfinx.fem.Function(Q)
    E.interpolate(dolfinx.fem.Expression(1.0 / ufl.CellVolume(msh) ** exponent,
                                         Q.element.interpolation_points))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    nu = 0.3
    mu, lmbda = 1 / (2 * (1 + nu)), nu / ((1 + nu) * (1 - 2 * nu))
    if model == "elastic":
        eps = lambda w: ufl.sym(ufl.grad(w))  # noqa: E731
        a = E * (2 * mu * ufl.inner(eps(u), eps(v)) + lmbda * ufl.div(u) * ufl.div(v)) * ufl.dx
    else:
        a = E * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
    ubc = dolfinx.fem.Function(V)
    ubc.x.array.reshape(-1, dim)[node_to_dof] = disp[:, :dim]
    bc = dolfinx.fem.dirichletbc(ubc, node_to_dof[~free].astype(np.int32))
    L = ufl.inner(dolfinx.fem.Constant(msh, np.zeros(dim)), v) * ufl.dx
    problem = dolfinx.fem.petsc.LinearProblem(
        a, L, bcs=[bc], petsc_options_prefix="test_band_ufl_",
        petsc_options={"ksp_type": "preonly", "pc_type": "lu"})
    uh = problem.solve()
    ref = uh.x.array.reshape(-1, dim)[node_to_dof]
    assert free.sum() >= 9  # a column (2D) or a layer (3D) of unknowns
    np.testing.assert_allclose(x_new[:, :dim] - x_ref[:, :dim], ref, rtol=0, atol=1e-12)


def test_unlisted_boundary_nodes_are_held(pushed):
    msh, x_ref, left, _ = pushed
    # no fixed list at all: fix_boundary holds the other boundary nodes
    x = x_ref
    bnd = np.flatnonzero((x[:, 0] < TOL) | (x[:, 0] > 1 - TOL)
                         | (x[:, 1] < TOL) | (x[:, 1] > 1 - TOL))
    others = np.setdiff1d(bnd, left)
    x_new = smooth(msh, x_ref, left, np.zeros(0, np.int32))
    np.testing.assert_array_equal(x_new[others], x_ref[others])
    x_free = smooth(msh, x_ref, left, np.zeros(0, np.int32), fix_boundary=False)
    assert np.abs(x_free[others] - x_ref[others]).max() > 0  # slides if not held


def circle_hole_mesh(n_refine=4, R=0.5, L=2.0):
    """Square minus a hole meshed as an inscribed 8-gon, uniformly refined."""
    import gmsh

    import dolfinx.io.gmsh

    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("hole8")
        geo = gmsh.model.geo
        lc_in = 2 * R * np.sin(np.pi / 8)
        outer = [geo.addPoint(x, y, 0, 0.6) for x, y in [(-L, -L), (L, -L), (L, L), (-L, L)]]
        ol = [geo.addLine(outer[i], outer[(i + 1) % 4]) for i in range(4)]
        hp = [geo.addPoint(R * np.cos(t), R * np.sin(t), 0, lc_in)
              for t in np.arange(8) * np.pi / 4]
        hl = [geo.addLine(hp[i], hp[(i + 1) % 8]) for i in range(8)]
        s = geo.addPlaneSurface([geo.addCurveLoop(ol), geo.addCurveLoop(hl)])
        geo.synchronize()
        gmsh.model.addPhysicalGroup(2, [s], 1)
        gmsh.model.addPhysicalGroup(1, ol, 1)
        gmsh.model.addPhysicalGroup(1, hl, 2)
        gmsh.model.mesh.generate(2)
        msh = dolfinx.io.gmsh.model_to_mesh(gmsh.model, COMM, 0, gdim=2).mesh
    finally:
        gmsh.finalize()
    for _ in range(n_refine):
        msh.topology.create_entities(1)
        msh, _, _ = dolfinx.mesh.refine(msh)
    x_ref = msh.geometry.x.copy()
    msh.topology.create_connectivity(1, 2)
    bf = dolfinx.mesh.exterior_facet_indices(msh.topology)
    bnodes = np.unique(dolfinx.mesh.entities_to_geometry(msh, 1, bf))
    r = np.linalg.norm(x_ref[bnodes, :2], axis=1)
    hole = bnodes[r < R + 1e-9].astype(np.int32)
    outer_nodes = bnodes[r >= R + 1e-9].astype(np.int32)
    # snap the refined polygon nodes radially onto the true circle
    rh = np.linalg.norm(x_ref[hole, :2], axis=1)
    msh.geometry.x[hole, :2] *= (R / rh)[:, None]
    return msh, x_ref, hole, outer_nodes


@pytest.fixture(scope="module")
def hole():
    return circle_hole_mesh()


@pytest.mark.parametrize("method", ["elastic", "laplace"])
def test_circle_hole_snap(hole, method):
    msh, x_ref, hole_nodes, outer_nodes = hole
    x_cur = msh.geometry.x.copy()
    assert n_inverted(msh, x_cur, x_ref) > 0
    x_new = smooth(msh, x_ref, hole_nodes, outer_nodes, method=method)
    assert n_inverted(msh, x_new, x_ref) == 0
    np.testing.assert_array_equal(x_new[hole_nodes], x_cur[hole_nodes])
    np.testing.assert_array_equal(x_new[outer_nodes], x_ref[outer_nodes])
    r = np.linalg.norm(x_new[hole_nodes, :2], axis=1)
    np.testing.assert_allclose(r, 0.5, rtol=1e-14)


def test_box_3d_elastic():
    n = 6
    msh = dolfinx.mesh.create_unit_cube(COMM, n, n, n)
    x_ref = msh.geometry.x.copy()
    x = x_ref
    bnd = np.flatnonzero(np.any((x < TOL) | (x > 1 - TOL), axis=1))
    face = np.flatnonzero((x[:, 0] < TOL) & np.all((x[:, 1:] > TOL) & (x[:, 1:] < 1 - TOL),
                                                   axis=1)).astype(np.int32)
    fixed = np.setdiff1d(bnd, face).astype(np.int32)
    bump = np.sin(np.pi * x_ref[face, 1]) * np.sin(np.pi * x_ref[face, 2])
    msh.geometry.x[face, 0] += 1.6 / n * bump
    assert n_inverted(msh, msh.geometry.x, x_ref) > 0
    for method in ("elastic", "laplace"):
        x_new = smooth(msh, x_ref, face, fixed, method=method)
        assert n_inverted(msh, x_new, x_ref) == 0
        np.testing.assert_array_equal(x_new[face], msh.geometry.x[face])


def test_repair_accepts_valid_smoothing(pushed):
    msh, x_ref, left, fixed = pushed
    # the elastic band everywhere (first_sweeps=0): exactly the smoother's result
    r = repair(msh, x_ref, msh.geometry.x, left, fixed, first_sweeps=0)
    assert isinstance(r, RepairResult)
    assert r.stage == "smooth"
    assert r.n_inverted_unsmoothed > 0 and r.n_inverted_smoothed == 0
    np.testing.assert_array_equal(r.fraction, 1.0)
    np.testing.assert_array_equal(r.shortfall, 0.0)
    np.testing.assert_array_equal(r.x, smooth(msh, x_ref, left, fixed))
    assert r.report.n_inverted_after == 0 and r.report.n_inverted_before > 0
    assert r.report.n_shortfall == 0
    # the default: sweeps over the band first, the elastic solve only near cells left bad or poor
    r = repair(msh, x_ref, msh.geometry.x, left, fixed)
    assert r.stage in ("smooth", "optimise") and r.report.n_inverted_after == 0
    first = r.attempts[0]
    assert first["stage"] == "smooth" and first["method"] == "laplace"
    assert first["sweeps"] == FIRST_SWEEPS
    swept = smooth(msh, x_ref, left, fixed, method="laplace", sweeps=FIRST_SWEEPS)
    if len(r.attempts) == 1:  # nothing bad or poor after the sweeps: their result as it is
        np.testing.assert_array_equal(r.x, swept)
    else:  # the elastic solve near the trouble: only nodes of its band differ from the sweeps
        assert r.attempts[1]["method"] == "elastic"
        assert r.attempts[1]["cells"] <= r.attempts[0]["cells"]


def test_repair_untangles_when_band_too_narrow():
    msh, x_ref, left, fixed = square_push(0.4)  # 6.4 h, beyond a 4-layer band
    x_t = msh.geometry.x.copy()
    assert n_inverted(msh, smooth(msh, x_ref, left, fixed), x_ref) > 0
    r = repair(msh, x_ref, x_t, left, fixed)
    assert r.stage == "untangle"
    assert n_inverted(msh, r.x, x_ref) == 0
    np.testing.assert_array_equal(r.x[left], x_t[left])  # every node at its target
    np.testing.assert_array_equal(r.x[fixed], x_ref[fixed])
    ut = [a for a in r.attempts if a["stage"] == "untangle"]
    assert ut and all(a["cells"] > 0 and a["nodes"] > 0 and a["seconds"] >= 0 for a in ut)
    assert ut[-1]["n_bad"] == 0
    # the old ladder (band-wide stiffened re-solves, no untangler) also gets there
    r2 = repair(msh, x_ref, x_t, left, fixed, untangle=False, stiffen=((1.0, 2), (2.0, 3)))
    assert r2.stage == "stiffen" and n_inverted(msh, r2.x, x_ref) == 0


def test_repair_partial_move():
    amp = 1.3  # would push the left side through the right one (x = 1)
    msh, x_ref, left, fixed = square_push(amp)
    x_t = msh.geometry.x.copy()
    inputs = [a.copy() for a in (x_ref, x_t, left, fixed)]
    r = repair(msh, x_ref, x_t, left, fixed)
    assert r.stage == "partial"
    cells = msh.geometry.dofmaps[0]
    assert inverted_cells(r.x, x_ref, cells, 2).size == 0
    assert mean_ratio(r.x, cells, 2).min() >= 0.01 - 1e-12  # quality floor honoured
    assert np.all((r.fraction >= 0) & (r.fraction <= 1)) and r.fraction.min() < 1
    assert r.fraction.min() > 0.2  # not a trivial "do nothing"
    # moved nodes lie on the segment x_ref -> target at the reported fraction
    d = x_t[left] - x_ref[left]
    np.testing.assert_allclose(r.x[left], x_ref[left] + r.fraction[:, None] * d, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(x_t[left] - r.x[left], axis=1), r.shortfall,
                               atol=1e-14)
    # the fraction varies smoothly along the side (no jagged pattern)
    order = np.argsort(x_ref[left, 1])
    assert np.abs(np.diff(r.fraction[order])).max() < 0.15
    assert r.report.n_shortfall == np.count_nonzero(r.shortfall > 0) > 0
    assert r.report.max_shortfall == pytest.approx(r.shortfall.max())
    assert r.report.n_inverted_after == 0
    assert "not fully moved" in str(r.report)
    np.testing.assert_array_equal(r.x[fixed], x_ref[fixed])
    for a, b in zip(inputs, (x_ref, x_t, left, fixed), strict=True):
        np.testing.assert_array_equal(a, b)


def test_repair_impossible_raises():
    msh, x_ref, left, fixed = square_push(0.0)
    mid = left[np.argmin(np.abs(x_ref[left, 1] - 0.5))]
    x_t = x_ref.copy()
    x_t[mid, 0] = 1.5  # through the opposite (fixed) side x = 1
    inputs = [a.copy() for a in (x_ref, x_t, left, fixed)]
    geom = msh.geometry.x.copy()
    with pytest.raises(InvertedCellsError) as err:
        repair(msh, x_ref, x_t, np.array([mid], np.int32), fixed, min_fraction=0.9)
    e = err.value
    assert isinstance(e, RuntimeError)
    assert e.count > 0 and e.cells.size == min(e.count, 100)
    msg = str(e)
    assert f"{e.count} cell(s)" in msg and str(int(e.cells[0])) in msg
    # independent re-check: the named cells are bad when the node is moved
    # min_fraction of the way and the first smoother (by default the sweeps
    # over the band) is re-solved, the repair's final round
    msh_c, _, _, _ = square_push(0.0)
    msh_c.geometry.x[mid] = x_ref[mid] + 0.9 * (x_t[mid] - x_ref[mid])
    x_c = smooth(msh_c, x_ref, np.array([mid], np.int32), fixed, method="laplace",
                 sweeps=FIRST_SWEEPS)
    cells = msh.geometry.dofmaps[0]
    q_ref = mean_ratio(x_ref, cells, 2)
    bad = set(inverted_cells(x_c, x_ref, cells, 2).tolist())
    bad |= set(np.flatnonzero(mean_ratio(x_c, cells, 2) < np.minimum(0.01, 0.5 * q_ref)).tolist())
    assert sorted(bad) == e.cells.tolist()  # serial: global == local cell index
    for a, b in zip(inputs, (x_ref, x_t, left, fixed), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(msh.geometry.x, geom)
    # no partial moves allowed -> also an error
    with pytest.raises(InvertedCellsError):
        repair(msh, x_ref, x_t, np.array([mid], np.int32), fixed, allow_partial=False)
    # default (min_fraction = 0): a valid, reported partial move
    r = repair(msh, x_ref, x_t, np.array([mid], np.int32), fixed)
    assert r.stage == "partial" and r.fraction[0] < 2 / 3  # cannot pass x = 1
    assert inverted_cells(r.x, x_ref, msh.geometry.dofmaps[0], 2).size == 0


def test_nothing_moved():
    msh, x_ref, _, fixed = square_push(0.0)
    empty = np.zeros(0, np.int32)
    for method in ("elastic", "laplace", "none"):
        np.testing.assert_array_equal(smooth(msh, x_ref, empty, fixed, method=method), x_ref)
    r = repair(msh, x_ref, x_ref, empty, fixed)
    assert r.stage == "smooth" and r.fraction.size == 0
    np.testing.assert_array_equal(r.x, x_ref)


def test_bad_inputs():
    msh, x_ref, left, fixed = square_push(0.0)
    with pytest.raises(ValueError):
        smooth(msh, x_ref[:-1], left, fixed)
    with pytest.raises(ValueError):
        smooth(msh, x_ref, left, fixed, method="bogus")
    with pytest.raises(TypeError):
        smooth(msh, x_ref, left, fixed, layer=3)
    with pytest.raises(IndexError):
        smooth(msh, x_ref, np.array([x_ref.shape[0]], np.int32), fixed)
    # a zero-area reference cell next to the moved nodes: no stiffness for it
    msh, x_ref, left, fixed = square_push(0.05 * H)  # (the moved nodes must move)
    flat = x_ref.copy()
    cells = msh.geometry.dofmaps[0]
    one_left = (np.isin(cells, left).sum(axis=1) == 1) & ~np.isin(cells, fixed).any(axis=1)
    tri = cells[np.flatnonzero(one_left)[0]]
    w, v0, v1 = tri[np.argsort(~np.isin(tri, left))]  # the moved node first
    flat[v0] = 0.5 * (flat[w] + flat[v1])
    with pytest.raises(ValueError, match="zero area / volume"):
        smooth(msh, flat, left, fixed)
    # NaN in the prescribed positions: the check of every entry point names it
    msh, x_ref, left, fixed = square_push(0.05 * H)
    msh.geometry.x[left[0], 0] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite"):
        smooth(msh, x_ref, left, fixed)
    with pytest.raises(ValueError, match="NaN or infinite"):
        repair(msh, x_ref, msh.geometry.x.copy(), left, fixed)


#: How close to a threshold of the check (relative to the straight cell) a cell must be for a
#: serial and a parallel repair to be allowed to decide differently.  Their coordinates differ
#: by the order of floating-point sums (the band solve's parallel reductions; the optimiser's
#: gradient and Hessian entries at nodes shared by processes, its energy's partial sums,
#: MUMPS's distributed factorisation): round-off times the conditioning of the solves.  The
#: optimiser stops at a relative decrease of its energy of 1e-9 (untangle.FTOL_FINAL), so a
#: stopping test that the round-off tips can leave the nodes up to about sqrt(1e-9) x (scale)
#: apart; a check's count, and every decision taken from it, can then change only where a
#: checked cell is that close to the floor of the volume, the mean ratio or the poor ratio.
MARGIN = 1e-4
#: Coordinates of a serial and a parallel repair that took the same decisions (size 1 meshes):
#: round-off times the conditioning of the optimiser's Newton systems (the mean-ratio energy
#: can be nearly flat along some directions: its converged minimum is then fixed only to
#: round-off / curvature; tests/mpi/untangle_mpi.py measures 1e-9 on a 10 x 10 square).
SAME = 1e-8


def _kept(a: dict) -> bool:
    """Whether an attempt's result could be taken (a partial trial: if valid)."""
    return a["n_bad"] == 0 if a["stage"] == "partial" else a.get("kept") is not False


def _decisions(attempts: list[dict]) -> list[tuple[tuple, int]]:
    """``(decision, index)`` of every attempt whose outcome steers the repair: what it is
    (stage, round, t, layers) and what it decided (its bad cells if taken, a partial trial's
    validity).  A discarded attempt changes nothing, and its own count is no decision."""
    out = []
    for i, a in enumerate(attempts):
        if a["stage"] != "partial" and not _kept(a):
            continue
        outcome = a["n_bad"] == 0 if a["stage"] == "partial" else a["n_bad"]
        out.append(((a["stage"], a["round"], a["t"], a["layers"], outcome), i))
    return out


def _excused(attempts: list[dict], i: int) -> bool:
    """Whether round-off may decide attempt ``i``: its check is marginal (``MARGIN``), or a
    result it depends on did not converge (its own, a taken one before it, or, for the
    untangle and slide stages, whose loop reads every untangle attempt, a discarded untangle
    attempt): an optimisation stopped by its iteration limit depends on the round-off of
    every iteration, not only on its input's."""
    a = attempts[i]
    if a["margin"] < MARGIN:
        return True
    for j, b in enumerate(attempts[: i + 1]):
        if b.get("converged") is not False:
            continue
        if j == i or _kept(b) or (b["stage"] == "untangle" and a["stage"] in ("untangle", "slide")):
            return True
    return False


def steered_by_unconverged(attempts: list[dict]) -> bool:
    """Whether the repair's result depends on an optimisation stopped by its iteration limit:
    a taken attempt that did not converge, or an untangle attempt that did not (taken or not:
    the untangle loop reads every attempt, and the partial stage blames the vertices around the
    cells the untangle stage left bad, so which vertices it pulls back, and how far, follows
    those cells).  Round-off of every iteration of such an optimisation reaches the nodes even
    when the recorded decisions agree."""
    return any(a.get("converged") is False and (_kept(a) or a["stage"] == "untangle")
               for a in attempts if a["stage"] != "partial")


def first_divergence(ser: list[dict], par: list[dict]) -> int | None:
    """Index (among the steering decisions) of the first one a serial and a parallel repair
    took differently, None if they took the same throughout; asserts that round-off could
    decide it (:func:`_excused`)."""
    ds, dp = _decisions(ser), _decisions(par)
    for k, ((a, i), (b, j)) in enumerate(zip(ds, dp, strict=False)):
        if a != b:
            assert _excused(ser, i) or _excused(par, j), (k, ser[i], par[j])
            return k
    assert len(ds) == len(dp), (ser, par)
    return None


@pytest.mark.mpi
def test_mpi_matches_serial():
    """``smooth`` and ``repair`` under ``mpiexec -n 2`` against serial runs (``tests/mpi/smooth_mpi.py``).

    The smoothers (one linear solve) agree with serial to round-off.  The repair
    (``repair_partial``: the left side pushed through the right one, ending in
    the partial stage's bisections, after untangle attempts that cannot succeed
    and are discarded) is compared by its decisions: the serial and the
    parallel run must take the same decisions (:func:`first_divergence`), and
    then their nodes agree to round-off; they may part only where round-off can
    decide (a check within ``MARGIN`` of a threshold, or an optimisation that did
    not converge, :func:`steered_by_unconverged`: then the runs continue differently
    and only the robust facts are compared: the stage, valid results, the cells and
    moved vertices, and vertices left short on both).  In this case the untangle
    attempts stop at their iteration limit (the left side cannot be untangled) and
    the partial stage's blame follows the cells they leave bad (184-186 in one run,
    186 in the other), so its nodes part by up to 0.12 in some runs with the same
    recorded decisions; the nodes are compared where every optimisation converged.
    """
    script = REPO / "tests" / "mpi" / "smooth_mpi.py"
    bindir = pathlib.Path(sys.executable).parent
    mpiexec = bindir / "mpiexec"
    assert mpiexec.exists(), f"mpiexec not found next to {sys.executable} (the MPI test cannot run)"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([str(mpiexec), "-n", "2", sys.executable, str(script)],
                          capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = [json.loads(ln) for ln in proc.stdout.splitlines() if ln.startswith("{")]
    assert "DONE" in proc.stdout
    assert len(lines) == 10
    for out in lines:
        if out["case"].startswith("refined_"):
            assert out["n"] == 33 ** 2 and out["n_inverted_unsmoothed"] > 0
        else:
            assert out["n"] == (N + 1) ** 2
        assert out["ghost_ok"], out
        assert out["n_inverted"] == 0, out
        if "report_par" in out:
            par, ser = dict(out["report_par"]), dict(out["report_ser"])
            assert out["stage"] == ["partial", "partial"]
            assert par.pop("n_shortfall") > 0 and ser.pop("n_shortfall") > 0
            assert par == ser
            same = first_divergence(out["attempts_ser"], out["attempts_par"]) is None
            if same and not (steered_by_unconverged(out["attempts_ser"])
                             or steered_by_unconverged(out["attempts_par"])):
                assert out["maxdiff"] < SAME, out
        else:
            assert out["maxdiff"] < SAME, out


SNAPPER_CASES = {  # case -> number of JSON lines per smoother (levels)
    "sphere": 2, "sphere_tiefree": 2, "dfg": 3, "direct3d": 1, "direct3d_hard": 1, "direct2d": 1,
}


@pytest.mark.mpi
@pytest.mark.parametrize("nprocs, cases", [
    (2, tuple(SNAPPER_CASES)),
    (3, ("sphere_tiefree", "dfg", "direct3d_hard", "direct2d")),
])
def test_mpi_snapper_unghosted_gmsh(nprocs, cases):
    """Smoothing inside ``Snapper.refine`` on unghosted gmsh meshes, 2D and 3D.

    See tests/mpi/snapper_smooth_mpi.py. For every level and smoother:
    * the parallel result equals a serial ``repair`` on the very same
      (gathered) mesh to round-off, unless a marginal check let the two
      decide differently (:func:`first_divergence`);
    * when the serial and the parallel pipeline produced the same refined
      mesh (2D; 3D without tied face edges), the coordinates agree too.
    3D meshes with equally long face edges (``sphere``) are refined by
    DOLFINx into partition-dependent interior diagonals, so there only the
    first point applies.
    """
    script = REPO / "tests" / "mpi" / "snapper_smooth_mpi.py"
    mpiexec = pathlib.Path(sys.executable).parent / "mpiexec"
    assert mpiexec.exists(), f"mpiexec not found next to {sys.executable} (the MPI test cannot run)"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([str(mpiexec), "-n", str(nprocs), sys.executable, str(script), *cases],
                          capture_output=True, text=True, timeout=900, env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "DONE" in proc.stdout
    lines = [json.loads(ln) for ln in proc.stdout.splitlines() if ln.startswith("{")]
    assert len(lines) == 2 * sum(SNAPPER_CASES[c] for c in cases)
    assert {(o["case"], o["method"]) for o in lines} == {
        (c, m) for c in cases for m in ("elastic", "laplace")}
    for out in lines:
        assert out["size"] == nprocs
        assert out["ghosts_coarse"] == [0] * nprocs, out  # unghosted gmsh distribution
        assert out["ghost_ok"] and out["n_inverted"] == 0, out
        assert out["stage_serial_rerun"] == out["stage"], out
        if first_divergence(out["attempts_serial_rerun"], out["attempts"]) is None:
            assert out["same_mesh_maxdiff"] < SAME, out
        if out["case"].startswith("direct"):
            assert out["n_smoothed"] > 0, out
            if out["case"] == "direct3d_hard":
                assert out["stage"] == "partial", out
            continue
        assert out["n_inverted_serial"] == 0, out
        if out["cells_differ"] == 0:
            assert out["serial_maxdiff"] < 1e-12, out
            # the same snapped vertices moved (by more than 1e-12 of the size)
            assert out["moved"] == out["moved_serial"], out
        if out["case"] in ("sphere_tiefree", "dfg"):
            assert out["ref_matched"] and out["cells_differ"] == 0, out
            assert out["serial_maxdiff"] < 1e-12 and out["pointset_maxdiff"] < 1e-12, out


def test_cg_falls_back_to_lu_when_it_does_not_converge(hole):
    """The default CG + GAMG solve, stopped after one iteration, is redone by MUMPS LU."""
    msh, x_ref, hole_nodes, outer_nodes = hole
    info: dict = {}
    x_lu = smooth(msh, x_ref, hole_nodes, outer_nodes, solver="mumps")
    x_cg = smooth(msh, x_ref, hole_nodes, outer_nodes)  # default: cg
    x_fb = smooth(msh, x_ref, hole_nodes, outer_nodes, solver="cg",
                  petsc_options={"ksp_max_it": 1}, info=info)
    scale = np.abs(x_lu - x_ref).max()
    assert scale > 0
    # the one-iteration CG would be far off; the fallback is the LU solution
    np.testing.assert_allclose(x_fb, x_lu, rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(x_cg, x_lu, rtol=0, atol=1e-8 * scale)
    assert info["solver_fallbacks"] == 1


@pytest.mark.parametrize("rel, layers", [(0.05, 2), (0.2, 3), (0.5, 4)])
def test_auto_band_width_follows_the_relative_displacement(rel, layers):
    """layers='auto': 2, 3 or 4 layers for a push of 5 %, 20 %, 50 % of the cell size."""
    msh, x_ref, left, fixed = square_push(rel * H)  # shortest edge of the cells: H
    info: dict = {}
    x_new = smooth(msh, x_ref, left, fixed, info=info)
    assert info["layers"] == layers
    assert n_inverted(msh, x_new, x_ref) == 0
    # only nodes within that many layers of the pushed side moved (grid columns)
    moved = np.flatnonzero(np.any(x_new != x_ref, axis=1))
    assert x_ref[moved, 0].max() < (layers + 0.5) * H
