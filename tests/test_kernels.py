"""The compiled kernels of the guard against the numpy formulations they replace.

Each kernel (:mod:`nagata_snap.smoothing.kernels`) must give the numpy
reference's results to rounding, on meshes with valid, flat and inverted
cells, in 2D and 3D: the untangling energy with its gradient and cell
Hessians (:func:`~nagata_snap.smoothing.untangle.energy_numpy`), the signed
volumes and mean ratios of the check, and the band matrix blocks
(``smooth._summed_blocks``).
"""

from __future__ import annotations

import mpi4py.MPI as MPI
import numpy as np
import pytest

import dolfinx.mesh

from nagata_snap.mesh.simplex import p1_gradients, signed_volumes
from nagata_snap.smoothing import kernels
from nagata_snap.smoothing.quality import mean_ratio
from nagata_snap.smoothing.smooth import _lame, _summed_blocks
from nagata_snap.smoothing.untangle import energy, energy_numpy, targets


def _mesh(d: int) -> tuple[np.ndarray, np.ndarray]:
    if d == 2:
        m = dolfinx.mesh.create_unit_square(MPI.COMM_SELF, 6, 5)
    else:
        m = dolfinx.mesh.create_unit_cube(MPI.COMM_SELF, 4, 3, 3)
    return np.array(m.geometry.x), np.array(m.geometry.dofmaps[0], dtype=np.int64)


def _close(a: np.ndarray, b: np.ndarray, rtol: float = 1e-12) -> None:
    scale = max(float(np.abs(b).max()), 1e-300)
    assert np.abs(np.asarray(a) - np.asarray(b)).max() <= rtol * scale


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("amp", [0.02, 0.8])
def test_energy_matches_numpy(d: int, amp: float) -> None:
    x, cells = _mesh(d)
    winv = targets(x[:, :d], cells)
    h = 1.0 / 6.0
    rng = np.random.default_rng(3)
    xp = x[:, :d] + amp * h * rng.standard_normal((x.shape[0], d))
    delta = 1e-3
    got = energy(xp, cells, winv, delta, hessian=True)
    ref = energy_numpy(xp, cells, winv, delta, hessian=True)
    if amp > 0.1:  # the large perturbation inverts cells: the regularised branch is exercised
        assert np.count_nonzero(ref[2] < 0) > 0
    assert got[0] == pytest.approx(ref[0], rel=1e-13)
    for a, b in zip(got[1:], ref[1:], strict=True):
        assert a.shape == b.shape
        _close(a, b)
    F, g, s = energy(xp, cells, winv, delta, grad=False)
    assert g is None and pytest.approx(ref[0], rel=1e-13) == F
    _close(s, ref[2])


@pytest.mark.parametrize("d", [2, 3])
def test_volume_mean_ratio_matches_numpy(d: int) -> None:
    x, cells = _mesh(d)
    rng = np.random.default_rng(5)
    x[:, :d] += 0.2 * rng.standard_normal((x.shape[0], d))
    cells[0, 1] = cells[0, 0]  # a collapsed cell: volume 0, ratio 0
    vol, q = kernels.volume_mean_ratio(x, cells, d)
    _close(vol, signed_volumes(x, cells, d))
    _close(q, mean_ratio(x, cells, d))
    assert vol[0] == 0.0 and q[0] == 0.0
    assert np.count_nonzero(vol < 0) > 0  # inverted cells keep their sign


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("model", ["elastic", "harmonic", "graph"])
def test_band_blocks_match_numpy(d: int, model: str) -> None:
    x, cells = _mesh(d)
    G, meas = p1_gradients(x, cells, d)
    w = meas * (meas.max() / meas) ** 1.0
    free_node = np.ones(x.shape[0], dtype=bool)
    free_node[::3] = False  # constrained nodes
    gid_node = np.where(free_node, np.cumsum(free_node) - 1, -1)
    gid = gid_node[cells]
    free = gid >= 0
    nf = int(free_node.sum())
    # the numpy reference: pairs sorted by key, summed per node pair
    c, a, b = np.nonzero(free[:, :, None] & free[:, None, :])
    key = gid[c, a] * nf + gid[c, b]
    order = np.argsort(key, kind="stable")
    key = key[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ref = _summed_blocks(G, w, model, 0.3, c[order], a[order], b[order], start)
    mu, lmbda = _lame(0.3)
    kind = {"elastic": 0, "harmonic": 1, "graph": 2}[model]
    indptr, cols, blocks = kernels.band_blocks(G, w, gid, gid, kind, mu, lmbda, nf, nf)
    rows = np.repeat(np.arange(nf), np.diff(indptr))
    assert np.array_equal(rows * nf + cols, key[start])
    _close(blocks, ref)


@pytest.mark.parametrize("d", [2, 3])
def test_hessian_blocks_sum_to_dense_assembly(d: int) -> None:
    # some vertices move (variable blocks >= 0), the others not (-1); random cell Hessians
    _, cells = _mesh(d)
    rng = np.random.default_rng(5)
    n = int(cells.max()) + 1
    moves = rng.random(n) < 0.5
    var_node = np.where(moves, np.cumsum(moves) - 1, -1)
    nb = int(moves.sum())
    cv = np.ascontiguousarray(var_node[cells])
    m, nv = cv.shape
    H = rng.standard_normal((m, nv, d, nv, d))
    slot, brow, bcol = kernels.hessian_blocks(cv, nb)
    vals = kernels.sum_hessians(H, slot, brow.size)
    # the dense matrix of the moving variables, one cell entry at a time
    ref = np.zeros((nb * d, nb * d))
    for k in range(m):
        for v in range(nv):
            for w in range(nv):
                if cv[k, v] >= 0 and cv[k, w] >= 0:
                    ref[cv[k, v] * d:(cv[k, v] + 1) * d, cv[k, w] * d:(cv[k, w] + 1) * d] += H[k, v, :, w, :]
    got = np.zeros_like(ref)
    for b in range(brow.size):
        got[brow[b] * d:(brow[b] + 1) * d, bcol[b] * d:(bcol[b] + 1) * d] += vals[b]
    _close(got, ref)
    # each block once; a pair of moving vertices of a cell has a block, a pair with a fixed one none
    assert np.unique(brow * nb + bcol).size == brow.size
    both = (cv[:, :, None] >= 0) & (cv[:, None, :] >= 0)
    assert np.array_equal(slot >= 0, both) and both.any() and not both.all()
    assert np.all(np.diff(brow) >= 0)


@pytest.mark.parametrize("d", [2, 3])
def test_graph_sums_match_dense_laplacian(d: int) -> None:
    # the off-diagonal part of the graph Laplacian (edge weight = cells sharing it), built densely
    x, cells = _mesh(d)
    n = x.shape[0]
    W = np.zeros((n, n))
    for cell in cells:
        for a in cell:
            for b in cell:
                if a != b:
                    W[a, b] += 1.0
    u = np.random.default_rng(7).standard_normal((n, d))
    _close(kernels.graph_sums(cells, u), W @ u)


@pytest.mark.parametrize("amp", [0.0, 0.3, 0.9])
def test_tet_shapes_match_numpy(amp: float) -> None:
    # valid, strongly distorted and inverted tetrahedra, and one flat cell
    from nagata_snap.mesh.simplex import edge_components, signed_volumes_of, vertex_components
    from nagata_snap.smoothing.quality import _tetrahedron_shapes

    x, cells = _mesh(3)
    rng = np.random.default_rng(11)
    xp = x + amp * 0.25 * rng.standard_normal(x.shape)
    xp[cells[0, 3]] = 0.5 * (xp[cells[0, 1]] + xp[cells[0, 2]])  # cell 0 flat
    vol, amin, amax, rr, l2s = kernels.tet_shapes(xp, cells)
    P = vertex_components(xp, cells, 3)
    ref_vol = signed_volumes_of(P)
    ev = edge_components(P)
    l2 = [np.einsum("i...,i...->...", np.array(e), np.array(e)) for e in ev]
    ref = _tetrahedron_shapes(ev, l2, ref_vol)
    if amp > 0.5:
        assert np.count_nonzero(ref_vol < 0) > 0
    _close(vol, ref_vol)
    for a, b in zip((amin, amax, rr), ref, strict=True):
        _close(a, b)
    _close(l2s, sum(l2))
    assert rr[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_rotate_blocks_match_einsum(d: int) -> None:
    # R_i^T H_b R_j on some blocks (row i, column j), the others untouched
    rng = np.random.default_rng(13)
    q, nb = 40, 9
    Hb = rng.standard_normal((q, d, d))
    brow, bcol = rng.integers(0, nb, q), rng.integers(0, nb, q)
    sel = np.arange(1, q, 3, dtype=np.int64)
    R = rng.standard_normal((nb, d, d))
    ref = Hb.copy()
    ref[sel] = np.einsum("qca,qce,qef->qaf", R[brow[sel]], Hb[sel], R[bcol[sel]])
    got = Hb.copy()
    kernels.rotate_blocks(got, R, brow, bcol, sel)
    _close(got, ref)
    assert np.array_equal(got[0], Hb[0])


@pytest.mark.parametrize("d", [2, 3])
def test_grow_layer_matches_cell_columns(d: int) -> None:
    # one layer grown from a few nodes, against the column-wise numpy formulation
    _, cells = _mesh(d)
    cells = np.ascontiguousarray(cells, dtype=np.int32)
    n = int(cells.max()) + 1
    mark = np.zeros(n, dtype=bool)
    mark[[0, n // 2]] = True
    new, touch = kernels.grow_layer(cells, mark)
    ref_touch = mark[cells].any(axis=1)
    ref_new = mark.copy()
    ref_new[cells[ref_touch].reshape(-1)] = True
    assert np.array_equal(touch, ref_touch) and np.array_equal(new, ref_new)
    assert mark.sum() < new.sum() < n


@pytest.mark.parametrize("d", [2, 3])
def test_energy_blocks_equal_cell_hessians_summed(d: int) -> None:
    # the fused pass gives the bits of the cell Hessians (energy_terms) summed by sum_hessians,
    # on a perturbed mesh with inverted cells, half the nodes moving, random node scales
    x, cells = _mesh(d)
    winv = targets(x[:, :d], cells)
    B = np.ascontiguousarray(np.concatenate([-winv.sum(axis=1, keepdims=True), winv], axis=1))
    rng = np.random.default_rng(11)
    xp = np.ascontiguousarray(x[:, :d] + 0.5 / 6.0 * rng.standard_normal((x.shape[0], d)))
    moves = rng.random(x.shape[0]) < 0.5
    var = np.ascontiguousarray(np.where(moves, np.cumsum(moves) - 1, -1)[cells])
    sv = np.ascontiguousarray(rng.uniform(0.5, 2.0, x.shape[0])[cells])
    slot, brow, _ = kernels.hessian_blocks(var, int(moves.sum()))
    F, g, sig, H = kernels.energy_terms(xp, cells, B, 1e-3, True, sv)
    assert np.count_nonzero(sig < 0) > 0
    F2, g2, Hb = kernels.energy_blocks(xp, cells, B, 1e-3, sv, slot, brow.size)
    assert F2 == F and np.array_equal(g2, g)
    assert np.array_equal(Hb, kernels.sum_hessians(H, slot, brow.size))
