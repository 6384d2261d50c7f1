"""Lineage of boundary facets through ``dolfinx.mesh.refine``.

For every exterior facet of the refined mesh we find the facet of the
previous level it lies in, and the barycentric coordinates of its vertices in
that parent facet.  The parent cell comes from the ``parent_cell`` map of
``dolfinx.mesh.refine``; the parent facet is the boundary facet of that parent
cell that contains the child's vertices, checked geometrically.  Because
refinement only bisects edges, every barycentric coordinate is 0, 1/2 or 1;
they are rounded to these values (so lineage never drifts) after checking
that the unrounded ones are within round-off of them.

In DOLFINx 0.11 ``parent_cell`` is indexed by the refined cells' order before
DOLFINx reorders them (``topology.original_cell_index`` relates the two); we
detect which indexing holds by checking that every child cell lies in its
parent cell, so the code keeps working if DOLFINx changes the convention and
fails loudly if neither holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

import dolfinx.mesh

from .boundary import BoundaryFacets, boundary_facets, facet_nodes

__all__ = ["LineageError", "ChildFacets", "parent_cells", "child_facets", "child_interior_facets", "barycentric"]

#: Tolerance on barycentric coordinates (dimensionless) when recognising
#: children: bisection gives exactly 0, 1/2, 1 up to round-off.
TOL = 1e-7


class LineageError(RuntimeError):
    """The refined mesh is not a refinement of the previous level's mesh."""


@dataclass
class ChildFacets:
    """Exterior facets of a refined mesh and where they come from.

    Attributes:
        boundary: exterior facets of owned cells of the refined mesh.
        parent: ``(nf,)`` index of each facet's parent into the previous
            level's boundary facets.
        weights: ``(nf, nfv, nfv)`` barycentric coordinates of each vertex
            in the parent facet (0, 1/2 or 1).
        parent_cells: ``(num_owned_cells,)`` parent cell of every owned cell.
    """

    boundary: BoundaryFacets
    parent: npt.NDArray[np.int64]
    weights: npt.NDArray[np.float64]
    parent_cells: npt.NDArray[np.int32]


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
    E = X[:, 1:] - X[:, :1]  # (n, m-1, 3)
    G = np.einsum("nai,nbi->nab", E, E)
    r = np.einsum("nai,nki->nka", E, y - X[:, :1])
    mu = np.linalg.solve(G[:, None], r[..., None])[..., 0] if G.shape[1] > 1 else r / G[:, None, :, 0]
    lam = np.concatenate([1.0 - mu.sum(axis=2, keepdims=True), mu], axis=2)
    back = np.einsum("nkm,nmi->nki", lam, X)
    h = np.sqrt(np.max(np.einsum("nai,nai->na", E, E), axis=1))
    return lam, np.linalg.norm(back - y, axis=2) / h[:, None]


def parent_cells(
    mesh1: dolfinx.mesh.Mesh,
    mesh0: dolfinx.mesh.Mesh,
    parent_cell: npt.NDArray[np.int32],
    check: npt.NDArray[np.int32] | None = None,
) -> np.ndarray:
    """Parent cell (local index in ``mesh0``) of every owned cell of ``mesh1``.

    Args:
        check: owned cells of ``mesh1`` on which the indexing is verified
            geometrically (default: all owned cells).

    Raises:
        LineageError: if no indexing of ``parent_cell`` puts every checked child in its parent.
    """
    n_owned = mesh1.topology.index_map(mesh1.topology.dim).size_local
    if len(parent_cell) != n_owned:
        raise LineageError(
            f"parent_cell has {len(parent_cell)} entries for {n_owned} owned cells: the mesh was "
            "redistributed after refinement; refine without a partitioner"
        )
    pc = np.asarray(parent_cell)
    candidates = []
    oci = np.asarray(mesh1.topology.original_cell_index, dtype=np.int64)[:n_owned]
    if n_owned:
        lo = oci.min()
        if oci.max() - lo + 1 == n_owned:
            candidates.append(pc[oci - lo])
    candidates.append(pc)
    check = np.arange(n_owned) if check is None else np.asarray(check)
    x1, x0 = mesh1.geometry.x, mesh0.geometry.x
    g1, g0 = mesh1.geometry.dofmaps[0], mesh0.geometry.dofmaps[0]
    cen = x1[g1[check]].mean(axis=1)[:, None, :]
    for P in candidates:
        lam, dist = barycentric(cen, x0[g0[P[check]]])
        if np.all(lam > -TOL) and np.all(dist < TOL):
            return P
    raise LineageError(
        "the refined mesh's parent_cell map does not put child cells inside their parents: "
        "the mesh is not a refinement of the previous level"
    )


def _match(y: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which candidate parent facets ``X (n, nfv, 3)`` contain child facets ``y (n, nfv, 3)``.

    Returns ``(ok (n,), rounded barycentric weights (n, nfv, nfv))``.
    """
    lam, dist = barycentric(y, X)
    lr = np.round(2.0 * lam) / 2.0
    ok = (
        np.all(np.abs(lam - lr) < TOL, axis=(1, 2))
        & np.all(dist < TOL, axis=1)
        & np.all(lr >= 0.0, axis=(1, 2))
    )
    return ok, lr


def _pairs(P: np.ndarray, cells0: np.ndarray, ncell0: int) -> tuple[np.ndarray, np.ndarray]:
    """All (child index, parent-facet index) pairs with the same parent cell.

    ``P (n,)`` parent cell of each child; ``cells0 (m,)`` cell of each parent facet.
    """
    order = np.argsort(cells0, kind="stable")
    counts = np.bincount(cells0, minlength=ncell0)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    ncand = counts[P]
    child = np.repeat(np.arange(len(P)), ncand)
    start = np.repeat(offsets[P], ncand)
    k = np.arange(len(child)) - np.repeat(np.cumsum(ncand) - ncand, ncand)
    return child, order[start + k]


def child_interior_facets(
    mesh0: dolfinx.mesh.Mesh,
    facets0: npt.NDArray[np.int32],
    mesh1: dolfinx.mesh.Mesh,
    P: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Facets of ``mesh1`` lying in the (interior) facets ``facets0`` of ``mesh0``.

    Args:
        facets0: local facet indices of ``mesh0`` (e.g. tagged interfaces).
        P: parent cell of every owned cell of ``mesh1`` (:func:`parent_cells`).

    Returns:
        ``(facets1, index)``: local facets of ``mesh1`` (from owned cells, each
        once) and the index into ``facets0`` of the facet each lies in.
    """
    tdim = mesh0.topology.dim
    fdim = tdim - 1
    if len(facets0) == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int64)
    mesh0.topology.create_connectivity(fdim, tdim)
    f2c = mesh0.topology.connectivity(fdim, tdim)
    ncell0 = mesh0.topology.index_map(tdim).size_local
    cnt = np.diff(f2c.offsets)[facets0]
    which = np.repeat(np.arange(len(facets0)), cnt)
    cells0 = f2c.array[np.repeat(f2c.offsets[facets0], cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))]
    own = cells0 < ncell0
    which, cells0 = which[own], cells0[own]
    mesh1.topology.create_connectivity(tdim, fdim)
    c2f1 = mesh1.topology.connectivity(tdim, fdim).array.reshape(-1, tdim + 1)
    has = np.zeros(ncell0, dtype=bool)
    has[cells0] = True
    kids = np.flatnonzero(has[P])  # owned fine cells whose parent has such a facet
    if len(kids) == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int64)
    child, cand = _pairs(P[kids], cells0, ncell0)
    fine = c2f1[kids[child]]  # (npair, tdim+1) candidate child facets
    fine = fine.ravel()
    cand = np.repeat(cand, tdim + 1)
    y = mesh1.geometry.x[facet_nodes(mesh1, fine.astype(np.int32))]
    X = mesh0.geometry.x[facet_nodes(mesh0, facets0[which[cand]].astype(np.int32))]
    ok, _ = _match(y, X)
    f1, first = np.unique(fine[ok], return_index=True)
    return f1.astype(np.int32), which[cand[ok][first]]


def child_facets(
    mesh0: dolfinx.mesh.Mesh,
    prev: BoundaryFacets,
    mesh1: dolfinx.mesh.Mesh,
    parent_cell: npt.NDArray[np.int32],
    P: np.ndarray | None = None,
) -> ChildFacets:
    """Match the exterior facets of ``mesh1`` to the exterior facets ``prev`` of ``mesh0``.

    Args:
        mesh0: mesh that was refined (with its final, snapped coordinates).
        prev: its exterior facets (as used at the previous level).
        mesh1: the refined mesh, coordinates as returned by ``dolfinx.mesh.refine``.
        parent_cell: the ``parent_cell`` array returned by ``dolfinx.mesh.refine``.
        P: parent cell of every owned cell of ``mesh1`` if already known.

    Raises:
        LineageError: a child facet that lies in no parent boundary facet.
    """
    bf = boundary_facets(mesh1)
    nf = len(bf.facets)
    nfv = bf.nodes.shape[1]
    P = parent_cells(mesh1, mesh0, parent_cell, bf.cells) if P is None else P
    ncell0 = mesh0.topology.index_map(mesh0.topology.dim).size_local
    child, cand = _pairs(P[bf.cells], prev.cells, ncell0)
    ok, lr = _match(mesh1.geometry.x[bf.nodes[child]], mesh0.geometry.x[prev.nodes[cand]])
    hits = np.bincount(child[ok], minlength=nf)
    if np.any(hits != 1):
        lost = np.flatnonzero(hits != 1)
        raise LineageError(
            f"{len(lost)} boundary facets of the refined mesh lie in "
            f"{sorted(set(hits[lost].tolist()))} parent boundary facets instead of one; first at "
            f"{mesh1.geometry.x[bf.nodes[lost[0]]].round(6).tolist()}"
        )
    sel = np.flatnonzero(ok)
    parent = np.empty(nf, dtype=np.int64)
    weights = np.empty((nf, nfv, nfv))
    parent[child[sel]] = cand[sel]
    weights[child[sel]] = lr[sel]
    return ChildFacets(bf, parent, weights, P)
