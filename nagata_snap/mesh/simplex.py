"""Kernels on simplices (segments, triangles, tetrahedra), vectorised over all of them at once.

Every geometric formula on a single simplex that the pipeline needs is
written here once: local vertex tables, edge vectors and lengths, signed
measures, facet normals and measures, P1 hat-function gradients,
barycentric coordinates, and batched inverses of tiny matrices.  There is
no Python loop over simplices; loops run over the (at most 6) local edges
or the (at most 3) coordinates.

Two layouts of the same data are used, and the kernels say which they take:

* *gathered*: ``X (n, m, dim)``, the ``m`` vertices of each of ``n``
  simplices (``x[cells]``);
* *components*: ``P[k][j]``, coordinate ``j`` of vertex ``k`` of every cell,
  a list of lists of ``(n,)`` float64 arrays (:func:`vertex_components`).
  Column-wise ``np.take`` on contiguous coordinate arrays is several times
  faster than the ``x[cells]`` gather on large meshes, and the formulas then
  work on flat arrays; :mod:`nagata_snap.smoothing.quality` uses it.

Local numbering follows DOLFINx (Basix): local facet ``j`` of a triangle or
tetrahedron is the one opposite local vertex ``j``; edges are listed in
:data:`TRI_EDGES` / :data:`TET_EDGES` order (the edges from vertex 0 first).

Cell arrays are ``(nc, tdim + 1)`` integer indices into ``x (n, 3)`` (as
``mesh.geometry.dofmaps[0]`` of a P1 mesh; in 2D the third coordinate is
ignored); lengths are in the unit of the mesh.

>>> import numpy as np
>>> x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
>>> signed_volumes(x, np.array([[0, 1, 2, 3], [1, 0, 2, 3]]), 3) * 6
array([ 1., -1.])
>>> edge_lengths(x[None, :3]) ** 2
array([[1., 1., 2.]])
>>> barycentric(np.array([[[0.25, 0.25, 0.0]]]), x[None, :3])[0]
array([[[0.5 , 0.25, 0.25]]])
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from nagata_snap.mesh.arrays import dot

__all__ = [
    "SEGMENT_EDGES",
    "TRI_EDGES",
    "TET_EDGES",
    "TET_EDGE_FACETS",
    "local_edges",
    "local_facet_vertices",
    "cell_dim",
    "cell_columns",
    "cells_touching",
    "compact_nodes",
    "vertex_components",
    "gathered_components",
    "edge_components",
    "sub",
    "cross",
    "signed_volumes",
    "signed_volumes_of",
    "edge_lengths",
    "edge_length_range",
    "edge_matrices",
    "p1_gradients",
    "facet_normal_vectors",
    "facet_measures",
    "barycentric",
    "inverse_small",
]

#: Type of the component layout: ``P[k][j]`` is an ``(n,)`` array.
Components = Sequence[Sequence[np.ndarray]]

# ---------------------------------------------------------------------------
# Local tables
# ---------------------------------------------------------------------------

#: ``(1, 2)`` local vertices of the edge of a segment.
SEGMENT_EDGES = np.array([[0, 1]])
#: ``(3, 2)`` local vertices of the three edges of a triangle.
TRI_EDGES = np.array([[0, 1], [0, 2], [1, 2]])
#: ``(6, 2)`` local vertices of the six edges of a tetrahedron.
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
#: ``(6, 2)`` for each edge of :data:`TET_EDGES` the two local facets that meet
#: there (facet ``j`` is opposite vertex ``j``, so these are the two vertices
#: not on the edge).
TET_EDGE_FACETS = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])
_EDGES = {2: SEGMENT_EDGES, 3: TRI_EDGES, 4: TET_EDGES}


def local_edges(nv: int) -> np.ndarray:
    """``(ne, 2)`` local vertex pairs of the edges of a simplex with ``nv`` (2, 3 or 4) vertices."""
    if nv not in _EDGES:
        raise ValueError(f"simplices have 2, 3 or 4 vertices here, got {nv}")
    return _EDGES[nv]


def local_facet_vertices(tdim: int) -> np.ndarray:
    """``(tdim + 1, tdim)`` local vertices of each local facet of a simplex.

    DOLFINx (Basix) numbers the facets of triangles and tetrahedra so that
    local facet ``j`` is the one opposite local vertex ``j``; its vertices are
    the others in increasing order.
    """
    nv = tdim + 1
    return np.array([[v for v in range(nv) if v != j] for j in range(nv)], dtype=np.int32)


def cell_dim(cells: np.ndarray, gdim: int) -> int:
    """Topological dimension of ``cells (nc, tdim + 1)``, checked to be a triangle / tetrahedron mesh of ``gdim``.

    Raises:
        ValueError: ``cells`` is not 2D, or its cells are not triangles in
            2D / tetrahedra in 3D.
    """
    cells = np.asarray(cells)
    if cells.ndim != 2:
        raise ValueError(f"cells must be 2D (nc, tdim+1), got shape {cells.shape}")
    tdim = cells.shape[1] - 1
    if gdim not in (2, 3) or tdim != gdim:
        raise ValueError(
            f"only triangles in 2D and tetrahedra in 3D are supported "
            f"(gdim={gdim}, cells with {cells.shape[1]} vertices)")
    return tdim


# ---------------------------------------------------------------------------
# Cell-node incidence
# ---------------------------------------------------------------------------


def cell_columns(cells: np.ndarray) -> list[np.ndarray]:
    """Contiguous copies of the ``nv`` columns of a ``(nc, nv)`` cell array (for :func:`cells_touching`)."""
    return [np.ascontiguousarray(cells[:, k]) for k in range(cells.shape[1])]


def compact_nodes(cells: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``(nodes (k,), local (nc, nv))``: the distinct nodes of ``cells`` (ids below ``n``), sorted,
    and the cells in their positions, as ``np.unique(cells, return_inverse=True)`` without a sort
    (a mask over the ``n`` nodes and its running count)."""
    on = np.zeros(n, dtype=bool)
    on[np.asarray(cells).reshape(-1)] = True
    num = np.cumsum(on) - 1
    return np.flatnonzero(on), num[cells]


def cells_touching(mask: np.ndarray, cols: Sequence[np.ndarray]) -> np.ndarray:
    """``(nc,)`` bool: the cells with at least one node in ``mask (n,)`` (bool over the nodes).

    ``cols`` is :func:`cell_columns` of the cells.  Column-wise ``take`` on a
    uint8 view: several times faster than ``mask[cells].any(1)``.
    """
    m8 = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    out = m8.take(cols[0])
    for c in cols[1:]:
        out |= m8.take(c)
    return out.view(bool)


# ---------------------------------------------------------------------------
# Component layout
# ---------------------------------------------------------------------------


def vertex_components(x: np.ndarray, cells: np.ndarray, gdim: int) -> list[list[np.ndarray]]:
    """Coordinates of the cells' vertices in the component layout.

    Args:
        x: ``(n, 3)`` node coordinates; cells: ``(nc, nv)`` node indices.
        gdim: number of coordinates taken (the first ``gdim`` columns of ``x``).

    Returns:
        ``P`` with ``P[k][j]`` the ``(nc,)`` float64 coordinate ``j`` of
        vertex ``k`` of every cell.
    """
    x = np.asarray(x, dtype=np.float64)
    cells = np.asarray(cells)
    comps = [np.ascontiguousarray(x[:, j]) for j in range(gdim)]
    out = []
    for k in range(cells.shape[1]):
        ck = np.ascontiguousarray(cells[:, k])
        out.append([c.take(ck) for c in comps])
    return out


def gathered_components(X: np.ndarray) -> list[list[np.ndarray]]:
    """The component layout ``P[k][j] = X[:, k, j]`` of gathered vertices ``X (n, m, dim)``."""
    return [[X[:, k, j] for j in range(X.shape[2])] for k in range(X.shape[1])]


def sub(a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Component-wise difference ``a - b`` of two vectors in the component layout."""
    return [ai - bi for ai, bi in zip(a, b, strict=True)]


def cross(a: Sequence[np.ndarray], b: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Cross product of two 3-vectors in the component layout (three ``(n,)`` arrays each)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def edge_components(P: Components) -> list[list[np.ndarray]]:
    """Edge vectors ``x_b - x_a`` of every simplex, one per edge of :func:`local_edges` ``(len(P))``."""
    return [sub(P[b], P[a]) for a, b in local_edges(len(P))]


def signed_volumes_of(P: Components) -> np.ndarray:
    """Signed measures ``(n,)`` of triangles (2 coordinates) or tetrahedra (3) in the component layout.

    Triangles: ``0.5 det[x1 - x0, x2 - x0]`` (L^2); tetrahedra:
    ``det[x1 - x0, x2 - x0, x3 - x0] / 6`` (L^3).  Positive for
    counter-clockwise / right-handed vertex order.
    """
    e1, e2 = sub(P[1], P[0]), sub(P[2], P[0])
    if len(P) == 3:
        return 0.5 * (e1[0] * e2[1] - e1[1] * e2[0])
    return dot(e1, cross(e2, sub(P[3], P[0]))) / 6.0


# ---------------------------------------------------------------------------
# Measures and lengths
# ---------------------------------------------------------------------------


def signed_volumes(x: np.ndarray, cells: np.ndarray, gdim: int) -> np.ndarray:
    """Signed measure ``(nc,)`` of every cell (float64; :func:`signed_volumes_of`).

    Args:
        x: ``(n, 3)`` node coordinates (length unit L).
        cells: ``(nc, gdim + 1)`` node indices per cell.
        gdim: 2 (triangles: signed area from the first two coordinates, L^2)
            or 3 (tetrahedra: signed volume, L^3).
    """
    cell_dim(cells, gdim)
    return signed_volumes_of(vertex_components(x, cells, gdim))


def edge_lengths(X: np.ndarray) -> np.ndarray:
    """``(n, ne)`` edge lengths of simplices ``X (n, m, dim)``, edges in :func:`local_edges` ``(m)`` order."""
    l2 = [dot(e, e) for e in edge_components(gathered_components(X))]
    return np.sqrt(np.stack(l2, axis=1)) if l2 else np.zeros((X.shape[0], 0))


def edge_length_range(x: np.ndarray, cells: np.ndarray, gdim: int) -> tuple[np.ndarray, np.ndarray]:
    """``(shortest, longest)`` edge length of every cell, two ``(nc,)`` arrays (length unit).

    Args: as :func:`signed_volumes`.
    """
    cell_dim(cells, gdim)
    l2 = [dot(e, e) for e in edge_components(vertex_components(x, cells, gdim))]
    return np.sqrt(np.minimum.reduce(l2)), np.sqrt(np.maximum.reduce(l2))


def edge_matrices(x: np.ndarray, cells: np.ndarray, gdim: int) -> np.ndarray:
    """``(nc, gdim, gdim)`` edge vectors from vertex 0: row ``j`` is ``x_{j+1} - x_0`` (first ``gdim`` coordinates).

    The transpose is the Jacobian of the affine map from the reference cell.
    """
    X = x[cells][:, :, :gdim]
    return X[:, 1:] - X[:, :1]


def p1_gradients(x: np.ndarray, cells: np.ndarray, gdim: int) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the P1 hat functions and cell measures of affine simplices.

    Args:
        x: ``(n, 3)`` node coordinates; cells: ``(nc, gdim + 1)`` nodes of each cell.

    Returns:
        ``(G (nc, gdim + 1, gdim), measure (nc,))``: ``G[c, a]`` is the
        gradient of the hat function of local vertex ``a`` in cell ``c``
        (1 / length unit); ``measure`` is the (unsigned) area / volume.
        Degenerate cells give inf / nan entries (no exception); callers
        reject those rows.
    """
    Jinv, det = inverse_small(edge_matrices(x, cells, gdim))
    G = np.empty((len(cells), gdim + 1, gdim))
    G[:, 1:] = Jinv.transpose(0, 2, 1)  # grad lambda_a = column a - 1 of J^-1
    with np.errstate(invalid="ignore"):
        G[:, 0] = -G[:, 1:].sum(axis=1)
    return G, np.abs(det) / (2.0 if gdim == 2 else 6.0)


def facet_normal_vectors(p: np.ndarray) -> np.ndarray:
    """``(n, 3)`` unnormalised normals of segments / triangles ``p (n, nfv, 3)``.

    In 2D ``(t_y, -t_x, 0)`` for the edge ``t``, in 3D the cross product of
    two edges: the length is the segment's length or twice the triangle's
    area. The orientation follows the vertex order.
    """
    t = p[:, 1] - p[:, 0]
    if p.shape[1] == 2:
        return np.stack([t[:, 1], -t[:, 0], np.zeros(len(t))], axis=1)
    return np.cross(t, p[:, 2] - p[:, 0])


def facet_measures(p: np.ndarray) -> np.ndarray:
    """``(n,)`` length (2 vertices) or area (3 vertices) of segments / triangles ``p (n, nfv, 3)``."""
    return np.linalg.norm(facet_normal_vectors(p), axis=1) / (p.shape[1] - 1)


# ---------------------------------------------------------------------------
# Barycentric coordinates and tiny inverses
# ---------------------------------------------------------------------------


def barycentric(y: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric coordinates of points in segments/triangles/tetrahedra.

    Args:
        y: ``(n, k, 3)`` points.
        X: ``(n, m, 3)`` simplex vertices, ``m = 2, 3`` or ``4``.

    Returns:
        ``(lam (n, k, m), dist (n, k))``: least-squares barycentric
        coordinates and the distance of each point from the simplex's affine hull,
        relative to the simplex's longest edge from vertex 0.
    """
    # Component-wise arithmetic on (n,) columns: for these tiny matrices it is
    # several times faster than einsum / matmul / linalg.solve over the batch.
    m, k = X.shape[1], y.shape[1]
    E = [[X[:, a + 1, i] - X[:, 0, i] for i in range(3)] for a in range(m - 1)]
    G = np.empty((len(X), m - 1, m - 1))
    for a in range(m - 1):
        for b in range(a, m - 1):
            G[:, a, b] = G[:, b, a] = E[a][0] * E[b][0] + E[a][1] * E[b][1] + E[a][2] * E[b][2]
    Gi, _ = inverse_small(G)
    lam = np.empty((len(X), k, m))
    dist2 = np.zeros((len(X), k))
    for p in range(k):
        d = [y[:, p, i] - X[:, 0, i] for i in range(3)]
        r = [E[a][0] * d[0] + E[a][1] * d[1] + E[a][2] * d[2] for a in range(m - 1)]
        mu = [sum(Gi[:, a, b] * r[b] for b in range(m - 1)) for a in range(m - 1)]
        lam[:, p, 0] = 1.0 - sum(mu)
        for a in range(m - 1):
            lam[:, p, a + 1] = mu[a]
        for i in range(3):  # residual of the projection onto the affine hull
            res = d[i] - sum(mu[a] * E[a][i] for a in range(m - 1))
            dist2[:, p] += res * res
    h = np.sqrt(np.max(np.diagonal(G, axis1=1, axis2=2), axis=1))
    return lam, np.sqrt(dist2) / h[:, None]


def inverse_small(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverses and determinants of ``(n, k, k)`` matrices, ``k <= 3``, by the adjugate.

    Much faster than batched ``np.linalg.inv`` / ``solve`` for such tiny
    matrices. Singular matrices give inf/nan entries (no exception); callers
    reject those rows.

    Returns:
        ``(inv (n, k, k), det (n,))``.
    """
    k = M.shape[1]
    if k == 1:
        det = M[:, 0, 0].copy()
        adj = np.ones_like(M)
    elif k == 2:
        a, b, c, d = M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1]
        det = a * d - b * c
        adj = np.stack([np.stack([d, -b], axis=1), np.stack([-c, a], axis=1)], axis=1)
    elif k == 3:
        m0, m1, m2 = M[:, 0], M[:, 1], M[:, 2]
        c12 = np.cross(m1, m2)
        det = np.einsum("ni,ni->n", m0, c12)
        adj = np.stack([c12, np.cross(m2, m0), np.cross(m0, m1)], axis=2)
    else:
        raise ValueError(f"inverse_small handles k <= 3, got k = {k}")
    with np.errstate(divide="ignore", invalid="ignore"):
        return adj / det[:, None, None], det
