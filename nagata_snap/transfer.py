"""Solution transfer between refinement levels through the parent-cell map.

An adaptive loop carries the previous level's solution to the refined mesh
(Newton initial guess, time stepping, comparing levels).  After snapping the
levels are no longer nested: new boundary vertices left their parent cells, so
a point search (``dolfinx.fem.create_interpolation_data`` +
``Function.interpolate_nonmatching``) finds no cell for some interpolation
points and leaves their dofs at zero.  The refinement's parent-cell map makes
the search unnecessary.  :func:`transfer` works in four batched stages (numpy
over all cells at once, basix for the tabulations):

1. *push forward*: the target element's interpolation points (reference
   coordinates) are mapped through every owned child cell's geometry (any
   Lagrange coordinate element, straight or curved of any degree);
2. *pull back*: each physical point is mapped into the reference cell of the
   child's parent: one batched inverse Jacobian for affine parents, a
   vectorised Newton iteration on the parent's coordinate element for curved
   ones (started from the affine pull-back of the parent's vertices).
   A point that the moved boundary put slightly outside its parent gets
   reference coordinates slightly outside the reference cell, and the parent's
   polynomial is extended there: no clipping, no search, no zero;
3. *select*: where child cells share a dof (continuous spaces), the candidate
   lying deepest inside its parent (largest smallest barycentric coordinate)
   is used, across processes too (ghost candidates go to the dof's owner), so
   the result does not depend on the partition;
4. *evaluate*: the parent element is tabulated at the pulled-back points and
   contracted with the parent cell's coefficients.  For Lagrange elements
   the point values are the dofs (one point per scalar dof, blocked by
   component); elements whose dofs are not point values (the Legendre variant
   of discontinuous Lagrange) apply the element's interpolation matrix per
   cell.

Polynomials that the parent space reproduces are transferred exactly, also
at points outside the parent (the extension is the same polynomial).  The
parent-cell map must be the one in the refined mesh's final cell order
(:func:`nagata_snap.mesh.lineage.parent_cells` gives it from DOLFINx's
``parent_cell``; :class:`~nagata_snap.snapper.Snapper` keeps it).  It may map
to any ancestor level (compose the maps of several refinements): the
pull-back does not assume that the child lies in the cell it is mapped to.

MPI: ``dolfinx.mesh.refine`` keeps children on their parent's process (its
default partitioner and ``partitioner=None``), so the parent cell of every
owned child is a local cell; owned dofs are computed where their cells are,
ghosts are filled by ``scatter_forward``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, overload

import basix
import dolfinx.common
import dolfinx.fem
import dolfinx.mesh
import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from nagata_snap.mesh.arrays import best_per_group
from nagata_snap.mesh.parallel import collective
from nagata_snap.mesh.simplex import inverse_small

__all__ = ["TransferInfo", "transfer", "pull_back"]

#: Points processed per basix tabulation (bounds the temporary memory).
CHUNK = 1 << 17

#: Newton steps below this many units in the last place of the coordinates, over the
#: cell size, are round-off: the pull-back has converged as far as it can.
ROUNDOFF = 16 * np.finfo(float).eps

#: Smallest barycentric coordinate below which a point counts as outside its parent.
OUTSIDE = 1e-10

_SIMPLICES = {dolfinx.mesh.CellType.triangle: basix.CellType.triangle,
              dolfinx.mesh.CellType.tetrahedron: basix.CellType.tetrahedron}


@dataclass
class TransferInfo:
    """What :func:`transfer` did (global numbers).

    Attributes:
        points: points evaluated in parent cells (one per scalar dof of a
            Lagrange space, per cell and point otherwise).
        outside: of them, points outside their parent cell (the moved
            boundary; the parent's polynomial was extended there).
        max_outside: largest distance outside, as minus the smallest
            barycentric coordinate in the parent's reference cell (0 if none).
        newton_points: points pulled back by Newton (curved parents).
        newton_iterations: most Newton iterations any of them needed.
    """

    points: int
    outside: int
    max_outside: float
    newton_points: int
    newton_iterations: int


class _Space:
    """A Lagrange function space as arrays: basix element, block size, dofmap."""

    def __init__(self, V: dolfinx.fem.FunctionSpace, what: str) -> None:
        if len(V.component()):
            raise ValueError(
                f"{what} is a sub-space of a mixed space: collapse it first "
                "(V_sub, dofs = W.sub(i).collapse()) and transfer into V_sub"
            )
        try:
            e = V.element.basix_element
        except RuntimeError:
            raise ValueError(
                f"{what} has a mixed or quadrature element: transfer each collapsed sub-space "
                "(W.sub(i).collapse()) on its own; quadrature spaces have no polynomial to extend"
            ) from None
        if e.family != basix.ElementFamily.P or e.map_type != basix.MapType.identity:
            raise ValueError(
                f"transfer supports Lagrange and discontinuous Lagrange spaces; {what} has a "
                f"{e.family.name} element: interpolate into a (vector) Lagrange space, transfer "
                "that, and interpolate back, or use dolfinx.fem.create_interpolation_data with "
                "Function.interpolate_nonmatching (a point search)"
            )
        if V.ufl_element().is_symmetric:
            raise ValueError(f"{what} is a symmetric tensor space: transfer its full tensor "
                             "counterpart (shape=(d, d), symmetry=None)")
        if V.element.needs_dof_transformations:
            raise ValueError(f"{what}'s element needs dof transformations, which transfer "
                             "does not apply")
        mesh = V.mesh
        if mesh.topology.cell_type not in _SIMPLICES:
            raise ValueError(f"transfer supports triangle and tetrahedron meshes, got "
                             f"{mesh.topology.cell_type.name} cells")
        if mesh.geometry.dim != mesh.topology.dim:
            raise ValueError("transfer needs gdim == tdim (no manifold meshes)")
        self.element = e
        self.bs = V.dofmap.bs
        self.value_shape = tuple(int(s) for s in V.element.value_shape)
        self.dofs = V.dofmap.list
        self.imap = V.dofmap.index_map
        self.mesh = mesh


def _tabulate(element: basix.finite_element.FiniteElement, n: int, X: np.ndarray) -> np.ndarray:
    """``(1 + derivatives, k, ndofs)`` basis values (and derivatives up to order ``n``) of a
    scalar ``element`` at reference points ``X (k, tdim)``.

    basix annotates ``tabulate`` as ``ArrayLike``; it returns an ndarray of shape
    ``(derivatives, k, ndofs, value size)``, whose last axis (1 here) is dropped.
    """
    return np.asarray(element.tabulate(n, X))[:, :, :, 0]


def _coordinate_element(mesh: dolfinx.mesh.Mesh) -> basix.finite_element.FiniteElement:
    """The basix element of ``mesh``'s (Lagrange) coordinate map."""
    cmap = mesh.geometry.cmaps[0]
    return basix.create_element(basix.ElementFamily.P, _SIMPLICES[mesh.topology.cell_type],
                                cmap.degree, basix.LagrangeVariant(cmap.variant))


def _cell_nodes(mesh: dolfinx.mesh.Mesh, cells: np.ndarray) -> np.ndarray:
    """``(n, ndofs_geometry, gdim)`` node coordinates of ``cells``."""
    gdim = mesh.geometry.dim
    # np.take: several times faster than fancy indexing with a 2D index (numpy 2.x)
    nodes = np.take(mesh.geometry.dofmaps[0], cells, axis=0)
    return np.take(mesh.geometry.x[:, :gdim], nodes, axis=0)


def _push_forward(mesh: dolfinx.mesh.Mesh, n_cells: int, X: np.ndarray) -> np.ndarray:
    """Physical points ``(gdim, n_cells, q)`` of reference points ``X (q, tdim)`` in the
    first ``n_cells`` cells (component-major: one BLAS product per coordinate)."""
    phi = _tabulate(_coordinate_element(mesh), 0, X)[0]  # (q, m)
    nodes = _cell_nodes(mesh, np.arange(n_cells))  # (n, m, gdim)
    return np.stack([nodes[:, :, d] @ phi.T for d in range(mesh.geometry.dim)])


def _vertex_maps(nodes: np.ndarray, tdim: int) -> tuple[np.ndarray, np.ndarray]:
    """Origins ``(n, gdim)`` and Jacobians ``(n, gdim, tdim)`` of the affine maps through
    the vertices ``nodes[:, :tdim + 1]`` (a Lagrange simplex's first nodes)."""
    v0 = nodes[:, 0]
    return v0, np.stack([nodes[:, k + 1] - v0 for k in range(tdim)], axis=2)


def _affine_pull_back(nodes: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Reference coordinates ``(tdim, n, q)`` of points ``y (gdim, n, q)`` under the
    vertices' affine maps of the cells with geometry ``nodes (n, m, gdim)``."""
    tdim = y.shape[0]
    v0, J = _vertex_maps(nodes, tdim)
    Jinv, det = inverse_small(J)
    if not np.all(np.isfinite(det) & (det != 0)):
        raise ValueError("parent cells with zero area / volume: cannot pull points back into them")
    d = [y[i] - v0[:, i, None] for i in range(tdim)]
    return np.stack([sum(Jinv[:, t, i, None] * d[i] for i in range(tdim)) for t in range(tdim)])


def _curved(nodes: np.ndarray, element: basix.finite_element.FiniteElement) -> np.ndarray:
    """``(n,)`` bool: cells whose higher-order nodes leave the affine map of their vertices."""
    if element.degree == 1:
        return np.zeros(len(nodes), dtype=bool)
    points = np.asarray(element.points)  # (m, tdim) reference nodes
    v0, J = _vertex_maps(nodes, points.shape[1])
    affine = v0[:, None, :] + np.einsum("ndt,mt->nmd", J, points)
    h = np.max(np.linalg.norm(J, axis=1), axis=1)
    return np.max(np.linalg.norm(nodes - affine, axis=2), axis=1) > 1e-12 * h


def pull_back(
    nodes: np.ndarray,
    y: np.ndarray,
    element: basix.finite_element.FiniteElement,
    X: np.ndarray,
    tol: float = 1e-13,
    max_iterations: int = 30,
) -> tuple[np.ndarray, int]:
    """Reference coordinates of points in curved cells by a vectorised Newton iteration.

    Solves ``sum_k phi_k(X) nodes_k = y`` for every point at once (basix
    tabulation of the coordinate element), also for points outside the cell
    (the polynomial map is extended).

    Args:
        nodes: ``(n, m, gdim)`` geometry nodes of the cell of each point.
        y: ``(n, gdim)`` physical points.
        element: the coordinate element (basix, ``m`` basis functions).
        X: ``(n, tdim)`` initial reference coordinates (e.g. the affine pull-back).
        tol: Newton step size (reference units) at which a point has
            converged, raised to the round-off level ``ROUNDOFF`` x (largest
            node coordinate) / (cell size) for cells much smaller than their
            distance from the origin.
        max_iterations: iterations before giving up.

    Returns:
        ``(X (n, tdim), iterations)``: the most iterations any point needed.

    Raises:
        RuntimeError: Newton did not converge for some points.
    """
    X = np.array(X, dtype=float, copy=True)
    tdim = X.shape[1]
    size = np.abs(nodes).max(axis=(1, 2))  # coordinate magnitude: round-off scale of F
    active = np.arange(len(X))
    for it in range(1, max_iterations + 1):
        tab = _tabulate(element, 1, X[active])  # (1 + tdim, na, m)
        xn = nodes[active]
        F = np.einsum("nm,nmd->nd", tab[0], xn) - y[active]
        J = np.einsum("tnm,nmd->ndt", tab[1:], xn)
        Jinv, det = inverse_small(J)
        dX = np.einsum("ntd,nd->nt", Jinv, F)
        X[active] -= dX
        step = np.linalg.norm(dX, axis=1)
        # reference-unit size of the round-off in F (cells small against their coordinates)
        floor = ROUNDOFF * size[active] / np.abs(det) ** (1.0 / tdim)
        active = active[~(step < np.maximum(tol, floor))]  # NaN steps stay active
        if not active.size:
            return X, it
    raise RuntimeError(
        f"Newton pull-back did not converge for {active.size} points in curved parent cells "
        f"(first at {np.round(y[active[0]], 6).tolist()}); the child is too far from its parent"
    )


def _pull_back_into(mesh0: dolfinx.mesh.Mesh, cells: np.ndarray, y: np.ndarray
                    ) -> tuple[np.ndarray, int, int]:
    """Reference coordinates ``(tdim, n, q)`` of points ``y (gdim, n, q)`` in ``cells (n,)``.

    Returns ``(X, newton points, newton iterations)``.
    """
    tdim = mesh0.topology.dim
    nodes = _cell_nodes(mesh0, cells)  # (n, m, gdim)
    X = _affine_pull_back(nodes, y)
    cmap = _coordinate_element(mesh0)
    curved = np.flatnonzero(_curved(nodes, cmap))
    its = 0
    if curved.size:
        q = y.shape[2]
        Xc, its = pull_back(np.repeat(nodes[curved], q, axis=0),
                            y[:, curved].reshape(tdim, -1).T, cmap,
                            X[:, curved].reshape(tdim, -1).T)
        X[:, curved] = Xc.T.reshape(tdim, len(curved), q)
    return X, curved.size * y.shape[2], its


def _insideness(X: np.ndarray) -> np.ndarray:
    """Smallest barycentric coordinate of reference points ``X (tdim, ...)`` (< 0: outside)."""
    return np.minimum(np.minimum.reduce(X), 1.0 - np.add.reduce(X))


def _evaluate(u: dolfinx.fem.Function, space: _Space, cells: np.ndarray, X: np.ndarray
              ) -> np.ndarray:
    """``(n, bs)`` values of ``u`` at reference points ``X (n, tdim)`` of ``cells (n,)``."""
    coeffs = u.x.array.reshape(-1, space.bs)
    out = np.empty((len(cells), space.bs), dtype=u.x.array.dtype)
    for s in range(0, len(cells), CHUNK):
        sl = slice(s, s + CHUNK)
        phi = _tabulate(space.element, 0, X[sl])[0]  # (k, ndofs)
        c = np.take(coeffs, np.take(space.dofs, cells[sl], axis=0), axis=0)  # (k, ndofs, bs)
        for b in range(space.bs):
            out[sl, b] = np.einsum("kd,kd->k", phi, c[:, :, b])
    return out


def _owner_best(imap: dolfinx.common.IndexMap, score: np.ndarray, values: np.ndarray,
                comm: MPI.Comm) -> tuple[np.ndarray, np.ndarray]:
    """Give each owned dof the best candidate over all processes.

    Args:
        score: ``(n_local + n_ghost,)`` score of this process's candidate
            (``-inf``: none).
        values: ``(n_local + n_ghost, bs)`` its values.

    Returns:
        ``(score, values)`` over the owned dofs.
    """
    n_own = imap.size_local
    if comm.size == 1:
        return score[:n_own], values[:n_own]
    has = np.flatnonzero(np.isfinite(score[n_own:]))
    owners = np.asarray(imap.owners)[has]
    order = np.argsort(owners, kind="stable")
    has, owners = has[order], owners[order]
    counts = np.bincount(owners, minlength=comm.size)
    gidx = np.asarray(imap.ghosts, dtype=np.int64)[has]
    send = np.concatenate([gidx[:, None].astype(float), score[n_own + has][:, None],
                           values[n_own + has]], axis=1)
    rcounts = np.array(comm.alltoall(counts.tolist()))
    width = send.shape[1]
    recv = np.empty((rcounts.sum(), width))
    comm.Alltoallv([send, counts * width], [recv, rcounts * width])
    local = recv[:, 0].astype(np.int64) - imap.local_range[0]
    idx = np.concatenate([np.arange(n_own), local])
    sc = np.concatenate([score[:n_own], recv[:, 1]])
    val = np.concatenate([values[:n_own], recv[:, 2:]])
    pick = best_per_group(idx, -np.where(np.isfinite(sc), sc, -np.inf), n_own)
    ok = pick >= 0
    out_s = np.full(n_own, -np.inf)
    out_v = np.zeros((n_own, values.shape[1]))
    out_s[ok], out_v[ok] = sc[pick[ok]], val[pick[ok]]
    return out_s, out_v


def _point_dofs(u: dolfinx.fem.Function, src: _Space, tgt: _Space, P: np.ndarray, X: np.ndarray,
                score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lagrange target: one point value per scalar dof, the best candidate across cells.

    Args:
        P: ``(n1,)`` parent cell of each owned child cell.
        X: ``(tdim, n1, q)`` reference coordinates of the interpolation points in the parents.
        score: ``(n1, q)`` their smallest barycentric coordinates.

    Returns:
        ``(values (n_owned, bs), score (n_owned,))`` of the owned target dofs.
    """
    n1, q = score.shape
    tdim = X.shape[0]
    comm = tgt.mesh.comm
    n_loc = tgt.imap.size_local + tgt.imap.num_ghosts
    dof = tgt.dofs[:n1].reshape(-1)
    pick = best_per_group(dof, -score.reshape(-1), n_loc)
    have = np.flatnonzero(pick >= 0)
    pairs = pick[have]
    vals = np.zeros((n_loc, src.bs), dtype=u.x.array.dtype)
    vals[have] = _evaluate(u, src, P[pairs // q], X.reshape(tdim, -1)[:, pairs].T)
    sc = np.full(n_loc, -np.inf)
    sc[have] = score.reshape(-1)[pairs]
    sc, vals = _owner_best(tgt.imap, sc, vals, comm)
    missing = comm.allreduce(int(np.count_nonzero(~np.isfinite(sc))))
    if missing:
        raise RuntimeError(f"{missing} owned dofs lie in no owned child cell of any process")
    return vals, sc


def _check_parent_map(parent_cells: npt.ArrayLike, mesh0: dolfinx.mesh.Mesh,
                      mesh1: dolfinx.mesh.Mesh) -> np.ndarray:
    """``parent_cells`` as int64 after checking it maps every owned cell of ``mesh1`` to a
    local cell of ``mesh0``."""
    tdim = mesh1.topology.dim
    n1 = mesh1.topology.index_map(tdim).size_local
    n0 = mesh0.topology.index_map(tdim).size_local + mesh0.topology.index_map(tdim).num_ghosts
    P = np.asarray(parent_cells, dtype=np.int64)
    if P.shape != (n1,) or (n1 and (P.min() < 0 or P.max() >= n0)):
        raise ValueError(
            f"parent_cells must map the {n1} owned cells of V's mesh to local cells "
            f"0..{n0 - 1} of u's mesh; got shape {P.shape}"
            + (f", values {P.min()}..{P.max()}" if P.size else "")
        )
    return P


@overload
def transfer(u: dolfinx.fem.Function, V: dolfinx.fem.FunctionSpace,
             parent_cells: npt.NDArray[np.integer], *,
             return_info: Literal[False] = ...) -> dolfinx.fem.Function: ...


@overload
def transfer(u: dolfinx.fem.Function, V: dolfinx.fem.FunctionSpace,
             parent_cells: npt.NDArray[np.integer], *,
             return_info: Literal[True]) -> tuple[dolfinx.fem.Function, TransferInfo]: ...


@overload
def transfer(u: dolfinx.fem.Function, V: dolfinx.fem.FunctionSpace,
             parent_cells: npt.NDArray[np.integer], *,
             return_info: bool) -> dolfinx.fem.Function | tuple[dolfinx.fem.Function, TransferInfo]: ...


def transfer(
    u: dolfinx.fem.Function,
    V: dolfinx.fem.FunctionSpace,
    parent_cells: npt.NDArray[np.integer],
    *,
    return_info: bool = False,
) -> dolfinx.fem.Function | tuple[dolfinx.fem.Function, TransferInfo]:
    """Transfer ``u`` onto ``V`` through the parent cell of every child cell (no search).

    Args:
        u: function on the parent mesh (straight or curved, any Lagrange
            coordinate degree); its ghost values must be up to date
            (``u.x.scatter_forward()``, as after a solve).  A sub-function
            (``w.sub(i)``) is collapsed first.
        V: Lagrange or discontinuous Lagrange space (any degree and variant;
            scalar, vector or tensor valued; a collapsed sub-space of a mixed
            space) on the child mesh (straight or curved), of the same value
            shape as ``u``.
        parent_cells: ``(num_owned_cells,)`` local cell of ``u``'s mesh for
            every owned cell of ``V``'s mesh, in the child mesh's final cell
            order (:func:`nagata_snap.mesh.lineage.parent_cells`; ``Snapper`` keeps
            it), or the composition of such maps over several levels.
        return_info: also return a :class:`TransferInfo`.

    Returns:
        The transferred function on ``V`` (owned and ghost dofs set), and
        with ``return_info`` its :class:`TransferInfo`.

    Raises:
        ValueError: unsupported element family, mixed or sub-space ``V``,
            different value shapes, or a parent map of the wrong size.
        RuntimeError: Newton pull-back failed in a curved parent.
    """
    if len(u.function_space.component()):
        u = u.collapse()
    src, tgt = _Space(u.function_space, "u's space"), _Space(V, "V")
    if src.value_shape != tgt.value_shape:
        raise ValueError(f"u has value shape {src.value_shape}, V has {tgt.value_shape}")
    mesh0, mesh1 = src.mesh, tgt.mesh
    tdim = mesh1.topology.dim
    if mesh0.topology.dim != tdim:
        raise ValueError(f"u lives on a {mesh0.topology.dim}D mesh, V on a {tdim}D mesh")
    Xref = V.element.interpolation_points

    def local() -> tuple[np.ndarray, np.ndarray, int, int]:  # no MPI inside: raised on all
        P = _check_parent_map(parent_cells, mesh0, mesh1)
        y = _push_forward(mesh1, len(P), Xref)  # (gdim, n1, q)
        return (P, *_pull_back_into(mesh0, P, y))  # X: (tdim, n1, q)

    P, X, n_newton, its = collective(mesh1.comm, local)
    n1 = len(P)
    score = _insideness(X)  # (n1, q)

    w = dolfinx.fem.Function(V)
    arr = w.x.array.reshape(-1, tgt.bs)
    if V.element.interpolation_ident:
        vals, sc = _point_dofs(u, src, tgt, P, X, score)
        arr[: tgt.imap.size_local] = vals
    else:  # dofs are not point values: the element's interpolation matrix, cell by cell
        vals = _evaluate(u, src, np.repeat(P, len(Xref)), X.reshape(tdim, -1).T)
        M = np.asarray(tgt.element.interpolation_matrix)  # (ndofs, q) of the scalar element
        arr[tgt.dofs[:n1]] = np.einsum("dq,cqb->cdb", M, vals.reshape(n1, len(Xref), tgt.bs))
        sc = score.reshape(-1)
    w.x.scatter_forward()
    if not return_info:
        return w
    comm = mesh1.comm
    out = sc[sc < -OUTSIDE]
    info = TransferInfo(
        points=comm.allreduce(int(sc.size)),
        outside=comm.allreduce(int(out.size)),
        max_outside=comm.allreduce(float(-out.min(initial=0.0)), op=MPI.MAX),
        newton_points=comm.allreduce(n_newton),
        newton_iterations=comm.allreduce(its, op=MPI.MAX),
    )
    return w, info
