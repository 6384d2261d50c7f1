"""Tests of nagata_snap.mesh.simplex against independent truth (closed forms, numpy.linalg)."""

import math

import numpy as np
import pytest

from nagata_snap.mesh.simplex import (
    TET_EDGE_FACETS,
    TET_EDGES,
    barycentric,
    cell_columns,
    cells_touching,
    compact_nodes,
    edge_length_range,
    edge_lengths,
    facet_measures,
    facet_normal_vectors,
    inverse_small,
    local_edges,
    local_facet_vertices,
    p1_gradients,
    signed_volumes,
)

RNG = np.random.default_rng(7)


def random_cells(n: int, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random simplices as separate nodes: ``x (n (dim + 1), 3)``, ``cells (n, dim + 1)``."""
    x = np.zeros((n * (dim + 1), 3))
    x[:, :dim] = RNG.standard_normal((n * (dim + 1), dim))
    return x, np.arange(n * (dim + 1)).reshape(n, dim + 1)


@pytest.mark.parametrize("dim", [2, 3])
def test_signed_volumes_are_determinants(dim):
    x, cells = random_cells(200, dim)
    X = x[cells][:, :, :dim]
    det = np.linalg.det(np.swapaxes(X[:, 1:] - X[:, :1], 1, 2))
    np.testing.assert_allclose(signed_volumes(x, cells, dim), det / math.factorial(dim),
                               rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("dim", [2, 3])
def test_edge_lengths_are_all_vertex_pair_distances(dim):
    x, cells = random_cells(50, dim)
    X = x[cells]
    L = edge_lengths(X)
    pairs = [(a, b) for a in range(dim + 1) for b in range(a + 1, dim + 1)]
    want = np.stack([np.linalg.norm(X[:, a] - X[:, b], axis=1) for a, b in pairs], axis=1)
    np.testing.assert_allclose(np.sort(L, axis=1), np.sort(want, axis=1), rtol=1e-14)
    lo, hi = edge_length_range(x, cells, dim)
    np.testing.assert_allclose(lo, want.min(axis=1), rtol=1e-14)
    np.testing.assert_allclose(hi, want.max(axis=1), rtol=1e-14)


def test_local_tables():
    for nv in (2, 3, 4):
        e = local_edges(nv)
        assert len(e) == nv * (nv - 1) // 2
        assert len({tuple(p) for p in e}) == len(e) and np.all(e[:, 0] < e[:, 1])
        assert np.all(e[: nv - 1, 0] == 0)  # the edges from vertex 0 first
    with pytest.raises(ValueError, match="2, 3 or 4 vertices"):
        local_edges(5)
    fv = local_facet_vertices(3)
    for (a, b), (f, g) in zip(TET_EDGES, TET_EDGE_FACETS, strict=True):
        # both facets contain the edge, and facet j does not contain vertex j
        assert {a, b} <= set(fv[f]) and {a, b} <= set(fv[g])
        assert f not in fv[f] and g not in fv[g]


def test_facet_normals_and_measures():
    seg = np.array([[[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]]])
    assert facet_measures(seg)[0] == pytest.approx(5.0)
    assert facet_normal_vectors(seg)[0] @ (seg[0, 1] - seg[0, 0]) == 0.0
    tri = RNG.standard_normal((100, 3, 3))
    a, b, c = (np.linalg.norm(tri[:, i] - tri[:, j], axis=1) for i, j in ((0, 1), (0, 2), (1, 2)))
    s = 0.5 * (a + b + c)
    heron = np.sqrt(s * (s - a) * (s - b) * (s - c))
    np.testing.assert_allclose(facet_measures(tri), heron, rtol=1e-8)


@pytest.mark.parametrize("dim", [2, 3])
def test_p1_gradients_reproduce_linear_functions(dim):
    x, cells = random_cells(100, dim)
    G, meas = p1_gradients(x, cells, dim)
    X = x[cells][:, :, :dim]
    # sum_a grad lambda_a = 0 and sum_a x_a (x) grad lambda_a = I (a linear function's gradient)
    np.testing.assert_allclose(G.sum(axis=1), 0.0, atol=1e-8)
    eye = np.einsum("cai,caj->cij", X, G)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(dim), eye.shape), atol=1e-8)
    np.testing.assert_allclose(meas, np.abs(signed_volumes(x, cells, dim)), rtol=1e-10)


@pytest.mark.parametrize("m", [2, 3, 4])
def test_barycentric_recovers_points_and_distance(m):
    X = RNG.standard_normal((60, m, 3))
    lam = RNG.dirichlet(np.ones(m), size=(60, 5))
    y = np.einsum("nkm,nmi->nki", lam, X)
    got, dist = barycentric(y, X)
    np.testing.assert_allclose(got, lam, atol=1e-8)
    assert np.all(dist < 1e-8)
    if m < 4:  # a point off the affine hull: its distance, relative to the longest edge from vertex 0
        n = facet_normal_vectors(X)  # perpendicular to the segment / triangle
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        _, d = barycentric(y + 0.5 * n[:, None, :], X)
        h = np.linalg.norm(X[:, 1:] - X[:, :1], axis=2).max(axis=1)
        np.testing.assert_allclose(d, np.broadcast_to(0.5 / h[:, None], d.shape), rtol=1e-8)


def test_inverse_small_matches_numpy():
    for k in (1, 2, 3):
        M = RNG.standard_normal((40, k, k)) + 3 * np.eye(k)
        inv, det = inverse_small(M)
        np.testing.assert_allclose(inv, np.linalg.inv(M), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(det, np.linalg.det(M), rtol=1e-10)


def test_cells_touching():
    cells = np.array([[0, 1, 2], [2, 3, 4], [5, 6, 7]])
    mask = np.zeros(8, dtype=bool)
    mask[2] = True
    assert cells_touching(mask, cell_columns(cells)).tolist() == [True, True, False]
    mask[:] = False
    assert not cells_touching(mask, cell_columns(cells)).any()


def test_compact_nodes_equal_unique_inverse() -> None:
    # a few cells over a sparse set of node ids (some unused, repeated, the largest id last)
    rng = np.random.default_rng(3)
    cells = rng.choice(np.arange(0, 200, 7), size=(30, 4))
    nodes, local = compact_nodes(cells, 200)
    ref_nodes, ref_inv = np.unique(cells, return_inverse=True)
    assert np.array_equal(nodes, ref_nodes)
    assert np.array_equal(local, ref_inv.reshape(cells.shape))
    assert np.array_equal(nodes[local], cells)
