"""Lineage of boundary facets through ``dolfinx.mesh.refine``.

For every exterior facet of the refined mesh we find the facet of the
previous level it lies in, and the barycentric coordinates of its vertices in
that parent facet.  The parent cell comes from the ``parent_cell`` map of
``dolfinx.mesh.refine``; the parent facet is the boundary facet of that parent
cell that contains the child's vertices, checked geometrically.  Because
refinement only bisects edges, every barycentric coordinate is 0, 1/2 or 1;
they are rounded to these values (so lineage never drifts) after checking
that the unrounded ones are within round-off of them.

Facets are handled as (owned cell, local facet index) pairs: an exterior
facet of the refined mesh lies in an exterior facet of the previous level, so
only the local facets of the children of boundary cells are examined, and no
facet entities of the refined mesh are created (that would cost a good part
of the refinement itself).  Completeness is checked instead of
assumed: the children of every parent facet must tile it (their areas or
lengths add up to its own).

In DOLFINx 0.11 ``parent_cell`` is indexed by the refined cells' order before
DOLFINx reorders them (``topology.original_cell_index`` relates the two); we
detect which indexing holds by checking that every child cell lies in its
parent cell, so the code keeps working if DOLFINx changes the convention and
fails loudly if neither holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx.mesh
import numpy as np
import numpy.typing as npt

from nagata_snap.mesh.boundary import BoundaryFacets, cell_facet_nodes
from nagata_snap.mesh.simplex import barycentric, edge_lengths, facet_measures, facet_normal_vectors

__all__ = [
    "LineageError",
    "ChildFacets",
    "parent_cells",
    "child_facets",
    "child_interior_facets",
]

#: Tolerance on barycentric coordinates (dimensionless) when recognising
#: children: bisection gives exactly 0, 1/2, 1 up to round-off.
TOL = 1e-7


#: Children checked by :func:`parent_cells` with ``select`` to pick the indexing.
SAMPLE = 4096


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


def parent_cells(
    mesh1: dolfinx.mesh.Mesh,
    mesh0: dolfinx.mesh.Mesh,
    parent_cell: npt.NDArray[np.int32],
    select: npt.NDArray[np.bool_],
) -> np.ndarray:
    """Parent cell (local index in ``mesh0``) of every owned cell of ``mesh1``.

    Args:
        select: ``(num_cells0,)`` bool over the cells of ``mesh0``: the
            indexing is verified geometrically on (an evenly spaced sample of
            at most ``SAMPLE``) children of the selected parents, as each
            candidate indexing names them.
            This only chooses between the indexings; :func:`child_facets`
            then verifies every child facet it uses.

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
    x1, x0 = mesh1.geometry.x, mesh0.geometry.x
    g1, g0 = mesh1.geometry.dofmaps[0], mesh0.geometry.dofmaps[0]
    for P in candidates:
        chk = np.flatnonzero(select[P])
        chk = chk[:: max(1, len(chk) // SAMPLE)]
        cen = x1[g1[chk]].mean(axis=1)[:, None, :]
        lam, dist = barycentric(cen, x0[g0[P[chk]]])
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


def _hyperplanes(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``(m, 3)`` and sizes ``(m,)`` of segments / triangles ``X (m, nfv, 3)``.

    The size is the longest edge from vertex 0 (the scale of
    :func:`~nagata_snap.mesh.simplex.barycentric`; edges from vertex 0 come first).
    """
    n = facet_normal_vectors(X)
    h = np.max(edge_lengths(X)[:, : X.shape[1] - 1], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / np.linalg.norm(n, axis=1, keepdims=True), h


def _children(
    mesh0: dolfinx.mesh.Mesh,
    cells0: np.ndarray,
    nodes0: np.ndarray,
    mesh1: dolfinx.mesh.Mesh,
    P: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Local facets of the children of ``cells0`` that lie in the parent facets ``nodes0``.

    Args:
        cells0: ``(m,)`` owned cell of ``mesh0`` of each parent facet.
        nodes0: ``(m, nfv)`` geometry nodes of each parent facet.
        P: parent cell of every owned cell of ``mesh1``.

    Returns:
        ``(cells1, local1, parent, weights)`` over the child facets found:
        owned cell of ``mesh1`` and local facet index, index into
        ``cells0`` of the parent facet, rounded barycentric
        coordinates ``(n, nfv, nfv)`` of the child's vertices in the parent.

    Raises:
        LineageError: a child facet in two parent facets, or a parent facet
            not covered by its children (the mesh is not a refinement).
    """
    tdim = mesh1.topology.dim
    nv = tdim + 1
    ncell0 = mesh0.topology.index_map(tdim).size_local
    has = np.zeros(ncell0, dtype=bool)
    has[cells0] = True
    kids = np.flatnonzero(has[P])  # owned fine cells whose parent has such a facet
    pair_kid, cand = _pairs(P[kids], cells0, ncell0)
    x1, x0 = mesh1.geometry.x, mesh0.geometry.x
    # Cheap filter first: a local facet of a child lies in a parent facet only
    # if exactly its nv - 1 vertices lie in the parent facet's hyperplane (the
    # remaining vertex is then the one opposite it).
    X = x0[nodes0]  # (m, nfv, 3)
    nrm, h = _hyperplanes(X)
    V = x1[mesh1.geometry.dofmaps[0][kids[pair_kid]]]  # (np, nv, 3)
    dist = np.einsum("pvi,pi->pv", V - X[cand, :1], nrm[cand])
    on = np.abs(dist) < TOL * h[cand, None]
    one_off = np.count_nonzero(on, axis=1) == nv - 1
    kc = kids[pair_kid[one_off]].astype(np.int32)
    kl = np.argmin(on[one_off], axis=1).astype(np.int32)  # the vertex off the plane
    cand = cand[one_off]
    fn = cell_facet_nodes(mesh1, kc, kl)
    ok, lr = _match(x1[fn], X[cand])
    sel = np.flatnonzero(ok)
    key = np.sort(kc[sel].astype(np.int64) * nv + kl[sel])
    twice = key[1:][key[1:] == key[:-1]]
    if twice.size:
        c, j = divmod(int(twice[0]), nv)
        raise LineageError(
            f"{twice.size} facets of the refined mesh lie in more than one parent facet; first at "
            f"{x1[cell_facet_nodes(mesh1, np.array([c]), np.array([j]))[0]].round(6).tolist()}"
        )
    cand = cand[sel]
    # every parent facet must be tiled by its children (area / length sum)
    covered = np.bincount(cand, weights=facet_measures(x1[fn[sel]]), minlength=len(cells0))
    whole = facet_measures(x0[nodes0])
    gap = np.abs(covered - whole) > 1e-8 * np.maximum(whole, np.finfo(float).tiny)
    if np.any(gap):
        first = np.flatnonzero(gap)[0]
        raise LineageError(
            f"{int(gap.sum())} facets of the previous level are not covered by facets of the "
            f"refined mesh (the mesh is not a refinement of the previous level); first at "
            f"{x0[nodes0[first]].round(6).tolist()}"
        )
    return kc[sel], kl[sel], cand, lr[sel]


def child_interior_facets(
    mesh0: dolfinx.mesh.Mesh,
    cells0: np.ndarray,
    local0: np.ndarray,
    mesh1: dolfinx.mesh.Mesh,
    P: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Children of (interior, e.g. interface) facets given as owned-cell / local-facet pairs.

    Args:
        cells0, local0: ``(m,)`` the parent facets, as owned cells of
            ``mesh0`` and local facet indices (a facet between two owned
            cells appears once per side).
        P: parent cell of every owned cell of ``mesh1`` (:func:`parent_cells`).

    Returns:
        ``(cells1, local1, index)``: the child facets in the same form (once
        per owned adjacent child cell) and the index into ``cells0`` of the
        parent of each.
    """
    if len(cells0) == 0:
        z = np.zeros(0, dtype=np.int32)
        return z, z, np.zeros(0, dtype=np.int64)
    c1, l1, parent, _ = _children(mesh0, cells0, cell_facet_nodes(mesh0, cells0, local0), mesh1, P)
    return c1, l1, parent


def child_facets(
    mesh0: dolfinx.mesh.Mesh,
    prev: BoundaryFacets,
    mesh1: dolfinx.mesh.Mesh,
    parent_cell: npt.NDArray[np.int32],
) -> ChildFacets:
    """Match the exterior facets of ``mesh1`` to the exterior facets ``prev`` of ``mesh0``.

    A facet of ``mesh1`` is exterior exactly when it lies in an exterior
    facet of ``mesh0``, so only the local facets of the children of cells
    with an exterior facet are examined, without creating facet entities.

    Args:
        mesh0: mesh that was refined (with its final, snapped coordinates).
        prev: its exterior facets (as used at the previous level).
        mesh1: the refined mesh, coordinates as returned by ``dolfinx.mesh.refine``.
        parent_cell: the ``parent_cell`` array returned by ``dolfinx.mesh.refine``.

    Raises:
        LineageError: a child facet in two parent facets, or a parent
            boundary facet that its children do not cover.
    """
    select = np.zeros(mesh0.topology.index_map(mesh0.topology.dim).size_local, dtype=bool)
    select[prev.cells] = True
    P = parent_cells(mesh1, mesh0, parent_cell, select)
    cells, local, parent, weights = _children(mesh0, prev.cells, prev.nodes, mesh1, P)
    return ChildFacets(BoundaryFacets.from_cells(mesh1, cells, local), parent.astype(np.int64),
                       weights, P)
