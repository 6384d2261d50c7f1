"""Degree-2 (isoparametric) mesh geometry on the true boundary.

Snapping vertices leaves straight cells, so the geometry error of the mesh is
second order.  For P2 and higher elements this dominates; a degree-2
coordinate element removes it.  :func:`curved_mesh` builds, on the topology of
a snapped straight mesh, a degree-2 geometry whose nodes are

* the vertices, as they are;
* the mid-node of every snapped boundary edge, on the geometry at the
  parametric midpoint of the edge's lineage record (Nagata: the coarse patch
  at the barycentric midpoint; CAD: Newton closest point seeded there);
* every other mid-node at the straight edge midpoint.

The Jacobian of every cell with a moved mid-node is checked at quadrature
points and vertices (not only at vertices); where it changes sign or drops
below a fraction of the straight cell's, the offending mid-nodes are moved
back toward the straight midpoint by bisection, and their number is reported.

The curved mesh shares the straight mesh's topology object, so facet tags,
``parent_cell`` maps and cell numbering apply to both.  Refinement loops keep
refining the straight mesh (``dolfinx.mesh.refine`` needs affine cells) and
rebuild the curved geometry from the lineage at each level.
"""

from __future__ import annotations

from dataclasses import dataclass

import basix
import basix.ufl
import numpy as np
import ufl

import dolfinx.cpp
import dolfinx.fem
import dolfinx.mesh

from .boundary import BoundaryFacets, update_nodes
from .records import Records

__all__ = ["CurvedInfo", "curved_mesh", "jacobian_determinants"]


@dataclass
class CurvedInfo:
    """What :func:`curved_mesh` did (global numbers).

    Attributes:
        boundary_midnodes: mid-nodes placed on the geometry.
        reduced_midnodes: mid-nodes moved back toward the straight midpoint to
            keep Jacobians positive.
        min_jacobian_ratio: smallest ``det J / det J_straight`` over checked points.
    """

    boundary_midnodes: int
    reduced_midnodes: int
    min_jacobian_ratio: float


def _check_points(cell: basix.CellType) -> np.ndarray:
    """Quadrature points of degree 4 plus the reference vertices."""
    q, _ = basix.make_quadrature(cell, 4)
    return np.concatenate([q, basix.geometry(cell)])


def jacobian_determinants(x: np.ndarray, cells: np.ndarray, tdim: int) -> np.ndarray:
    """``det J`` of degree-2 simplices at check points (quadrature of degree 4 and vertices).

    Args:
        x: ``(n, 3)`` node coordinates.
        cells: ``(nc, ndofs)`` nodes of each cell in basix P2 order.
        tdim: 2 or 3.

    Returns:
        ``(nc, npts)`` determinants.
    """
    ct = basix.CellType.triangle if tdim == 2 else basix.CellType.tetrahedron
    el = basix.create_element(basix.ElementFamily.P, ct, 2, basix.LagrangeVariant.equispaced)
    dphi = el.tabulate(1, _check_points(ct))[1 : tdim + 1, :, :, 0]  # (tdim, npts, ndofs)
    X = x[cells][:, :, :tdim]  # (nc, ndofs, gdim)
    J = np.einsum("cki,dqk->cqid", X, dphi)
    return np.linalg.det(J)


def curved_mesh(
    mesh: dolfinx.mesh.Mesh,
    boundary: BoundaryFacets,
    snapped: np.ndarray,
    records: Records,
    geometry,
    min_ratio: float = 0.05,
    max_bisections: int = 10,
) -> tuple[dolfinx.mesh.Mesh, CurvedInfo]:
    """Degree-2 mesh on the topology of ``mesh`` with boundary mid-nodes on the geometry.

    Args:
        mesh: snapped affine mesh.
        boundary: its exterior facets of owned cells.
        snapped: ``(nf,)`` bool, which of ``boundary`` are snapped.
        records: lineage records of the snapped facets (in order).
        geometry: the snapping geometry (its ``place`` method is used).
        min_ratio: smallest allowed ``det J / det J_straight`` at check points.
        max_bisections: halvings of a mid-node's displacement before giving up
            and leaving it at the straight midpoint.

    Returns:
        ``(curved mesh, CurvedInfo)``.
    """
    comm = mesh.comm
    tdim = mesh.topology.dim
    gdim = mesh.geometry.dim
    fdim = tdim - 1
    Q = dolfinx.fem.functionspace(mesh, ("Lagrange", 2))
    X = Q.tabulate_dof_coordinates().copy()  # straight: vertices and edge midpoints
    imap = Q.dofmap.index_map
    dofs = Q.dofmap.list
    n_nodes = imap.size_local + imap.num_ghosts
    X_straight = X.copy()

    # closure dofs of each snapped facet, matched to its vertex pairs
    sel = np.flatnonzero(snapped)
    c, lf = boundary.cells[sel], boundary.local[sel]
    layout = Q.dofmap.dof_layout
    closure = np.array([layout.entity_closure_dofs(fdim, i) for i in range(tdim + 1)])
    fdofs = np.take_along_axis(dofs[c], closure[lf], axis=1)  # (nf, nclosure)
    nfv = tdim
    pairs = np.array([[0, 1]]) if nfv == 2 else np.array([[0, 1], [1, 2], [0, 2]])
    fx = mesh.geometry.x[boundary.nodes[sel]]  # (nf, nfv, 3)
    mids = 0.5 * (fx[:, pairs[:, 0]] + fx[:, pairs[:, 1]])  # (nf, ne, 3)
    dx = np.linalg.norm(X[fdofs][:, None, :, :] - mids[:, :, None, :], axis=3)  # (nf, ne, ncl)
    mid_dof = np.take_along_axis(fdofs, np.argmin(dx, axis=2), axis=1)  # (nf, ne)
    h = np.linalg.norm(fx[:, pairs[:, 1]] - fx[:, pairs[:, 0]], axis=2)
    if len(sel) and np.min(dx, axis=2).max(initial=0.0) > 1e-9 * h.max(initial=1.0):
        raise RuntimeError("could not match the degree-2 edge nodes of boundary facets to their edges")

    # place vertices and mid-nodes of each facet together (edge lengths for CAD fallbacks)
    W = np.zeros((nfv + len(pairs), nfv))
    W[np.arange(nfv), np.arange(nfv)] = 1.0
    W[nfv + np.arange(len(pairs)), pairs[:, 0]] = 0.5
    W[nfv + np.arange(len(pairs)), pairs[:, 1]] = 0.5
    rec = Records(records.root, np.einsum("pv,fvk->fpk", W, records.params))
    straight = np.concatenate([fx, mids], axis=1)
    pts, _, _ = geometry.place(rec, straight)
    target = X.copy()
    moved = update_nodes(mesh, target, mid_dof.ravel(), pts[:, nfv:].reshape(-1, 3), index_map=imap)

    # Jacobian guard on cells with a moved mid-node, bisection on the displacement
    n_own_cells = mesh.topology.index_map(tdim).size_local
    cells = dofs[:n_own_cells]
    check = np.flatnonzero(moved[cells].any(axis=1))
    det0 = jacobian_determinants(X_straight, cells[check], tdim)[:, :1]  # affine: constant
    alpha = np.ones(n_nodes)
    reduced = np.zeros(n_nodes, dtype=bool)
    for _ in range(max_bisections + 1):
        Xc = X_straight + alpha[:, None] * (target - X_straight)
        ratio = jacobian_determinants(Xc, cells[check], tdim) / det0
        bad = check[ratio.min(axis=1) < min_ratio]
        flag = np.zeros(n_nodes)
        flag[np.unique(cells[bad])] = 1.0
        flag = _sync_max(mesh, imap, flag) * moved
        if comm.allreduce(int(flag[: imap.size_local].sum())) == 0:
            break
        hit = flag > 0
        reduced |= hit
        alpha[hit] *= 0.5
    else:
        alpha[reduced] = 0.0
        Xc = X_straight + alpha[:, None] * (target - X_straight)
        ratio = jacobian_determinants(Xc, cells[check], tdim) / det0
    X = Xc

    ce = dolfinx.fem.coordinate_element(mesh.topology.cell_type, 2)
    igi = imap.local_to_global(np.arange(n_nodes, dtype=np.int32)).astype(np.int64)
    geom = dolfinx.mesh.create_geometry(imap, dofs, ce, np.ascontiguousarray(X[:, :gdim]), igi)
    cpp_mesh = dolfinx.cpp.mesh.Mesh_float64(comm, mesh.topology._cpp_object, geom._cpp_object)
    cell_name = "triangle" if tdim == 2 else "tetrahedron"
    domain = ufl.Mesh(basix.ufl.element("Lagrange", cell_name, 2, shape=(gdim,)))
    curved = dolfinx.mesh.Mesh(cpp_mesh, domain)
    own = np.zeros(n_nodes, dtype=bool)
    own[: imap.size_local] = True
    info = CurvedInfo(
        boundary_midnodes=comm.allreduce(int(np.count_nonzero(moved & own))),
        reduced_midnodes=comm.allreduce(int(np.count_nonzero(reduced & own))),
        min_jacobian_ratio=comm.allreduce(float(ratio.min(initial=np.inf)), op=_mpi_min()),
    )
    return curved, info


def _sync_max(mesh, imap, flag: np.ndarray) -> np.ndarray:
    """Owner-and-ghost consistent logical OR of a per-node flag."""
    if mesh.comm.size == 1:
        return flag
    import dolfinx.la

    v = dolfinx.la.vector(imap, 1)
    v.array[:] = flag
    v.scatter_reverse(dolfinx.la.InsertMode.add)
    v.array[: imap.size_local] = v.array[: imap.size_local] > 0
    v.scatter_forward()
    return (v.array > 0).astype(float)


def _mpi_min():
    from mpi4py import MPI

    return MPI.MIN
