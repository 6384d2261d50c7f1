"""Lineage of boundary facets through ``dolfinx.mesh.refine``.

For every exterior facet of the refined mesh we find the facet of the
previous level it lies in, and the barycentric coordinates of its vertices in
that parent facet.  The parent cell comes from the ``parent_cell`` map of
``dolfinx.mesh.refine``; the parent facet is the boundary facet of that parent
cell that contains the child's vertices.

The matching is combinatorial: refinement only bisects edges, so every
vertex of a child cell is a vertex of its parent cell or the midpoint of one
of its edges, and every vertex of a child facet a vertex or an edge midpoint
of its parent facet.  Each child vertex is matched to the nearest of these
points, and accepted when it is within :data:`TOL` of the parent's longest
edge (plus a few ulps of the coordinates).  The test needs no inverse of the
parent's shape: a sliver (a flat tetrahedron, a flat triangle) has a tiny
volume but not tiny edges, so its points stay far apart on the scale of its
edges, while barycentric coordinates of a sliver (a Gram-matrix inverse,
conditioning squared) are wrong by far more than round-off.  The barycentric
coordinates follow from the match (1 at a vertex, 1/2 and 1/2 at an edge
midpoint), so they are exact and lineage never drifts.

Facets are handled as (owned cell, local facet index) pairs: an exterior
facet of the refined mesh lies in an exterior facet of the previous level, so
only the local facets of the children of boundary cells are examined, and no
facet entities of the refined mesh are created (that would cost a good part
of the refinement itself).  Completeness is checked instead of
assumed: the children of every parent facet must tile it (their areas or
lengths add up to its own).

In DOLFINx 0.11 ``parent_cell`` is indexed by the refined cells' order before
DOLFINx reorders them (``topology.original_cell_index`` relates the two); we
detect which indexing holds by checking that every vertex of a child cell is
a vertex or an edge midpoint of its parent cell, so the code keeps working if
DOLFINx changes the convention and fails loudly if neither holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx.mesh
import numpy as np
import numpy.typing as npt

from nagata_snap.errors import LineageError
from nagata_snap.mesh.arrays import ramp
from nagata_snap.mesh.boundary import BoundaryFacets, cell_facet_nodes
from nagata_snap.mesh.simplex import edge_lengths, facet_measures, local_edges, local_facet_vertices

__all__ = [
    "LineageError",
    "ChildFacets",
    "parent_cells",
    "match_points",
    "point_weights",
    "child_facets",
    "child_interior_facets",
]

#: Tolerance (dimensionless) on the distance of a child vertex from the parent
#: vertex or edge midpoint it is, relative to the parent's longest edge.
#: Refinement computes midpoints in floating point, so the true distance is
#: round-off of the coordinates, far below this.
TOL = 1e-9

#: Round-off allowance added to the tolerance, relative to the largest
#: coordinate of the parent (cells far from the origin).
ULPS = 64 * np.finfo(float).eps

#: Children checked by :func:`parent_cells` with ``select`` to pick the indexing.
SAMPLE = 4096


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


def point_weights(m: int) -> np.ndarray:
    """``(m + ne, m)`` barycentric coordinates of the points a child vertex can be in a
    simplex of ``m`` vertices: its vertices, then the midpoints of its ``ne`` edges in
    :func:`~nagata_snap.mesh.simplex.local_edges` order (1 at a vertex; 1/2 and 1/2 at an
    edge midpoint).  The codes of :func:`match_points` index its rows."""
    e = local_edges(m)
    W = np.zeros((m + len(e), m))
    W[np.arange(m), np.arange(m)] = 1.0
    W[m + np.arange(len(e))[:, None], e] = 0.5
    return W


def match_points(y: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which vertex or edge midpoint of simplex ``X[i]`` each point ``y[i, j]`` is.

    Each point is matched to the nearest of the simplex's vertices and edge
    midpoints (the rows of :func:`point_weights`); the match is accepted within :data:`TOL` of the
    simplex's longest edge (plus round-off of its coordinates).  Nothing is
    inverted, so flat simplices (slivers) are matched as reliably as round ones.

    Args:
        y: ``(n, k, 3)`` points.
        X: ``(n, m, 3)`` simplex vertices, ``m = 2, 3`` or ``4``.

    Returns:
        ``(code (n, k), off (n, k))``: index of the point matched (a row of
        :func:`point_weights`), -1 where the nearest one is farther than the
        tolerance; the distance to the nearest, relative to the longest edge.
    """
    n, k, m = len(y), y.shape[1], X.shape[1]
    e = local_edges(m)
    Y = np.ascontiguousarray(np.moveaxis(y, 2, 0))  # (3, n, k): arithmetic on (n, k) arrays
    Xc = np.moveaxis(X, 2, 0)  # (3, n, m)
    best = np.full((n, k), np.inf)
    code = np.zeros((n, k), dtype=np.int64)
    d2, r, closer = np.empty((n, k)), np.empty((n, k)), np.empty((n, k), dtype=bool)
    for q in range(m + len(e)):  # vectorised over all points; m + ne <= 10 candidates
        Q = Xc[:, :, q] if q < m else 0.5 * (Xc[:, :, e[q - m, 0]] + Xc[:, :, e[q - m, 1]])
        np.subtract(Y[0], Q[0][:, None], out=r)
        np.multiply(r, r, out=d2)
        for i in (1, 2):
            np.subtract(Y[i], Q[i][:, None], out=r)
            r *= r
            d2 += r
        np.less(d2, best, out=closer)
        np.copyto(best, d2, where=closer)
        np.copyto(code, q, where=closer)
    dist = np.sqrt(best)
    h = np.max(edge_lengths(X), axis=1)[:, None]
    tol = TOL * h + ULPS * np.max(np.abs(X), axis=(1, 2))[:, None]
    code[~(dist <= tol)] = -1
    with np.errstate(invalid="ignore", divide="ignore"):
        return code, dist / h


def parent_cells(
    mesh1: dolfinx.mesh.Mesh,
    mesh0: dolfinx.mesh.Mesh,
    parent_cell: npt.NDArray[np.int32],
    select: npt.NDArray[np.bool_],
) -> np.ndarray:
    """Parent cell (local index in ``mesh0``) of every owned cell of ``mesh1``.

    Args:
        select: ``(num_cells0,)`` bool over the cells of ``mesh0``: the
            indexing is verified on (an evenly spaced sample of at most
            ``SAMPLE``) children of the selected parents, as each candidate
            indexing names them: every vertex of a child must be a vertex or
            an edge midpoint of its parent (:func:`match_points`).
            This only chooses between the indexings; :func:`child_facets`
            then verifies every child facet it uses.

    Raises:
        LineageError: if no indexing of ``parent_cell`` makes every checked
            child out of its parent's vertices and edge midpoints.
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
    worst: tuple[int, int, int, float] | None = None  # (bad, checked, first bad child, its offset)
    for P in candidates:
        chk = np.flatnonzero(select[P])
        chk = chk[:: max(1, len(chk) // SAMPLE)]
        code, off = match_points(x1[g1[chk]], x0[g0[P[chk]]])
        bad = np.flatnonzero(np.any(code < 0, axis=1))
        if bad.size == 0:
            return P
        if worst is None or bad.size < worst[0]:
            worst = (bad.size, len(chk), int(chk[bad[0]]), float(np.nanmax(off[bad[0]])))
    assert worst is not None
    nbad, nchk, c, d = worst
    raise LineageError(
        f"the refined mesh's parent_cell map does not make child cells of their parents' vertices "
        f"and edge midpoints: in {nbad} of {nchk} checked cells a vertex is neither (first: the "
        f"cell at {x1[g1[c]].round(6).tolist()}, {d:.2e} of its parent's longest edge off); the "
        "mesh is not a refinement of the previous level: pass the mesh that dolfinx.mesh.refine "
        "returned for the previous level's mesh, with its parent_cell, before moving its vertices"
    )


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
    k = ramp(ncand)
    return child, order[start + k]


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
        ``cells0`` of the parent facet, barycentric coordinates
        ``(n, nfv, nfv)`` of the child's vertices in the parent (0, 1/2, 1).

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
    # A local facet of a child lies in a parent facet exactly when its nv - 1
    # vertices are vertices or edge midpoints of the parent facet (the
    # remaining vertex, off the facet, is the one opposite it).
    X = x0[nodes0]  # (m, nfv, 3)
    code, _ = match_points(x1[mesh1.geometry.dofmaps[0][kids[pair_kid]]], X[cand])
    on = code >= 0
    one_off = np.count_nonzero(on, axis=1) == nv - 1
    kc = kids[pair_kid[one_off]].astype(np.int32)
    kl = np.argmin(on[one_off], axis=1).astype(np.int32)  # the vertex off the facet
    cand = cand[one_off]
    fcode = np.take_along_axis(code[one_off], local_facet_vertices(tdim)[kl], axis=1)
    weights = point_weights(nv - 1)[fcode]  # (n, nfv, nfv)
    fn = cell_facet_nodes(mesh1, kc, kl)
    key = np.sort(kc.astype(np.int64) * nv + kl)
    twice = key[1:][key[1:] == key[:-1]]
    if twice.size:
        c, j = divmod(int(twice[0]), nv)
        raise LineageError(
            f"{twice.size} facets of the refined mesh lie in more than one parent facet; first at "
            f"{x1[cell_facet_nodes(mesh1, np.array([c]), np.array([j]))[0]].round(6).tolist()}"
        )
    # every parent facet must be tiled by its children (area / length sum); the
    # round-off allowance is on the scale of the longest edge, so flat facets pass
    covered = np.bincount(cand, weights=facet_measures(x1[fn]), minlength=len(cells0))
    whole = facet_measures(X)
    h = np.max(edge_lengths(X), axis=1)
    gap = np.abs(covered - whole) > 1e-8 * whole + 1e-12 * h ** (tdim - 1)
    if np.any(gap):
        first = np.flatnonzero(gap)[0]
        raise LineageError(
            f"{int(gap.sum())} facets of the previous level are not covered by facets of the "
            f"refined mesh (the mesh is not a refinement of the previous level); first at "
            f"{x0[nodes0[first]].round(6).tolist()}"
        )
    return kc, kl, cand, weights


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
