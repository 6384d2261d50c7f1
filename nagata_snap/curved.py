"""Isoparametric mesh geometry of degree k on the true boundary.

Snapping vertices leaves straight cells, so the geometry error of the mesh is
second order.  For P2 and higher elements this dominates; a coordinate
element of degree ``k`` removes it.  :func:`curved_mesh` builds, on the
topology of a snapped straight mesh, a degree-``k`` geometry
(``dolfinx.fem.interpolate_geometry`` of the straight mesh, then moved) whose
nodes are

* the vertices, as they are;
* every other node of a snapped boundary facet (edge nodes and, in 3D,
  face-interior nodes), on the geometry at the parametric position of the
  node in the facet's lineage record: the record's parameters combined with
  the node's barycentric coordinates in the facet (Nagata: the coarse patch
  there; CAD: Newton seeded there, on the CAD edge for nodes of facets of
  several CAD faces);
* every node of an edge that is not on a snapped facet, at its straight
  position;
* the remaining nodes (cell-interior nodes, and in 3D the interior nodes of
  faces that are not snapped), blended from the displacement of the nodes on
  the cell's edges and snapped faces: the displacement field of each cell is
  the hierarchic polynomial extension ``sum_e l_a l_b q_e(l_b - l_a) +
  sum_f l_a l_b l_c p_f(l_a, l_b, l_c)`` (``l`` barycentric coordinates,
  ``q_e`` fitted to the edge's nodes, ``p_f`` homogeneous of degree ``k - 3``
  fitted to a snapped face's residual), which reproduces the given nodes and
  is intrinsic to each edge and face, so cells sharing a face agree on it.

Node distribution: the coordinate element is a basix Lagrange variant
DOLFINx accepts for mesh geometry (``equispaced`` or one of the ``gll_*``
variants; the Chebyshev, GL and Legendre variants exist only for
discontinuous elements).  The default is ``equispaced`` for ``k <= 2`` (the
same nodes) and ``gll_warped`` above: its edge nodes are the Gauss-Lobatto
points, so the integral of a curved edge's interpolant is Gauss-Lobatto
quadrature (exact to degree ``2k - 1``) and each edge's area error
integrates to zero at leading order (see the README for the measured orders).

Validity: ``det J`` of every cell with a moved node is checked at the points
of a degree-``2k`` quadrature, the vertices and the Lagrange nodes; where it
changes sign or drops below ``min_ratio`` of the straight cell's, the
displacements of the cell's boundary nodes are halved (bisection), the
blended nodes recomputed, and the count reported in :class:`CurvedInfo`.

The curved mesh shares the straight mesh's topology object, so facet tags,
``parent_cell`` maps and cell numbering apply to both.  Refinement loops keep
refining the straight mesh (``dolfinx.mesh.refine`` needs affine cells) and
rebuild the curved geometry from the lineage at each level.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import basix
import dolfinx.fem
import dolfinx.la
import dolfinx.mesh
import numpy as np
from mpi4py import MPI

from nagata_snap.geometry import SnapGeometry
from nagata_snap.mesh.boundary import BoundaryFacets, local_facet_vertices, update_nodes
from nagata_snap.mesh.parallel import collective_place
from nagata_snap.mesh.records import Records

__all__ = ["CurvedInfo", "curved_mesh", "jacobian_determinants", "VARIANTS"]

#: Lagrange variants DOLFINx accepts for a continuous coordinate element.
VARIANTS = ("equispaced", "gll_warped", "gll_isaac", "gll_centroid")

#: cells per block of the vectorised Jacobian evaluation (bounds memory)
_BLOCK = 20000


@dataclass
class CurvedInfo:
    """What :func:`curved_mesh` did (global numbers).

    Attributes:
        degree: degree of the coordinate element.
        variant: its basix Lagrange variant.
        boundary_nodes: non-vertex nodes of snapped facets placed on the geometry.
        blended_nodes: interior nodes (cell interiors, unsnapped faces) set
            from the boundary displacement of their cells.
        reduced_nodes: boundary nodes moved back toward their straight
            position to keep Jacobians positive.
        max_shortfall: largest distance of a reduced node from its place on
            the geometry (0 if none was reduced; length unit).
        min_jacobian_ratio: smallest ``det J / det J_straight`` over checked points.
    """

    degree: int
    variant: str
    boundary_nodes: int
    blended_nodes: int
    reduced_nodes: int
    max_shortfall: float
    min_jacobian_ratio: float


def default_variant(degree: int) -> str:
    """``'equispaced'`` for ``degree <= 2`` (the same nodes), else ``'gll_warped'``."""
    return "equispaced" if degree <= 2 else "gll_warped"


@dataclass(frozen=True)
class _Reference:
    """Reference-cell data of a degree-``k`` Lagrange coordinate element."""

    element: basix.finite_element.FiniteElement
    lam: np.ndarray  # (ndofs, nv) barycentric coordinates of the nodes
    facet_closure: np.ndarray  # (nfacets, ncl) closure dofs of each local facet
    facet_weights: np.ndarray  # (nfacets, ncl, nfv) node barycentrics in the facet vertices
    edge_dofs: np.ndarray  # (n_edge_dofs,) interior dofs of all edges
    edge_extension: np.ndarray  # (ndofs, n_edge_dofs) edge displacements -> all nodes
    face_dofs: list[np.ndarray]  # 3D: interior dofs of each face
    face_extension: list[np.ndarray]  # 3D: (ndofs, n_face_dofs) face residual -> all nodes
    interior_dofs: np.ndarray  # cell-interior dofs
    dphi: np.ndarray  # (tdim, npts, ndofs) basis derivatives at the check points


def _fit_extension(lam: np.ndarray, own: np.ndarray, basis) -> np.ndarray:
    """``(ndofs, len(own))`` matrix: values at the nodes ``own`` -> the extension at all nodes.

    ``basis(lam) -> (n, len(own))`` evaluates the extension functions at
    barycentric points; they are fitted to the values at ``own``.
    """
    return basis(lam) @ np.linalg.inv(basis(lam[own]))


@functools.cache
def _reference(tdim: int, degree: int, variant: str) -> _Reference:
    ct = basix.CellType.triangle if tdim == 2 else basix.CellType.tetrahedron
    el = basix.create_element(basix.ElementFamily.P, ct, degree, basix.LagrangeVariant[variant])
    pts = np.asarray(el.points)
    lam = np.column_stack([1.0 - pts.sum(axis=1), pts])
    fdim = tdim - 1
    fv = local_facet_vertices(tdim)
    closure = np.array([el.entity_closure_dofs[fdim][f] for f in range(tdim + 1)])
    weights = np.stack([lam[closure[f]][:, fv[f]] for f in range(tdim + 1)])

    edges = basix.topology(ct)[1]
    ext, cols = [], []
    for e, (a, b) in enumerate(edges):  # loop over the 3 or 6 reference edges
        own = np.asarray(el.entity_dofs[1][e])
        def edge_basis(l, a=a, b=b):
            s = l[:, b] - l[:, a]
            return (l[:, a] * l[:, b])[:, None] * s[:, None] ** np.arange(degree - 1)
        ext.append(_fit_extension(lam, own, edge_basis))
        cols.append(own)
    face_dofs, face_ext = [], []
    if tdim == 3:
        powers = [p for p in itertools.product(range(degree - 2), repeat=3) if sum(p) == degree - 3]
        for f, verts in enumerate(basix.topology(ct)[2]):
            own = np.asarray(el.entity_dofs[2][f], dtype=np.int64)
            face_dofs.append(own)
            if len(own) == 0:
                face_ext.append(np.zeros((len(lam), 0)))
                continue
            def face_basis(l, v=tuple(verts)):
                lf = l[:, list(v)]
                bubble = lf.prod(axis=1)
                return bubble[:, None] * np.stack([np.prod(lf ** np.array(p), axis=1)
                                                   for p in powers], axis=1)
            face_ext.append(_fit_extension(lam, own, face_basis))
    q, _ = basix.make_quadrature(ct, 2 * degree)
    check = np.concatenate([q, basix.geometry(ct), pts])
    dphi = np.asarray(el.tabulate(1, check))[1 : tdim + 1, :, :, 0]
    return _Reference(
        element=el, lam=lam, facet_closure=closure, facet_weights=weights,
        edge_dofs=np.concatenate(cols).astype(np.int64),
        edge_extension=np.concatenate(ext, axis=1),
        face_dofs=face_dofs, face_extension=face_ext,
        interior_dofs=np.asarray(el.entity_dofs[tdim][0], dtype=np.int64), dphi=dphi,
    )


def _degree_of(ndofs: int, tdim: int) -> int:
    for k in range(1, 16):
        if ndofs == (np.prod([k + i for i in range(1, tdim + 1)]) // np.prod(range(1, tdim + 1))):
            return k
    raise ValueError(f"{ndofs} nodes per cell is no Lagrange simplex of dimension {tdim}")


def jacobian_determinants(x: np.ndarray, cells: np.ndarray | None, tdim: int,
                          variant: str | None = None) -> np.ndarray:
    """``det J`` of degree-k simplices at the check points.

    The check points are a degree-``2k`` quadrature, the reference vertices and
    the Lagrange nodes.

    Args:
        x: ``(n, 3)`` node coordinates, or ``(nc, ndofs, 3)`` the nodes of each
            cell if ``cells`` is None.
        cells: ``(nc, ndofs)`` nodes of each cell in basix order (the degree
            follows from ``ndofs``), or None.
        tdim: 2 or 3.
        variant: the coordinate element's Lagrange variant (default
            :func:`default_variant` of the degree).

    Returns:
        ``(nc, npts)`` determinants.
    """
    nc, ndofs = (x.shape[0], x.shape[1]) if cells is None else cells.shape
    k = _degree_of(ndofs, tdim)
    dphi = _reference(tdim, k, variant or default_variant(k)).dphi
    out = np.empty((nc, dphi.shape[1]))
    for s in range(0, nc, _BLOCK):  # blocks of cells (memory)
        X = (x[s : s + _BLOCK] if cells is None else x[cells[s : s + _BLOCK]])[:, :, :tdim]
        out[s : s + _BLOCK] = np.linalg.det(np.einsum("cki,dqk->cqid", X, dphi))
    return out


def blend(disp: np.ndarray, snapped_faces: np.ndarray | None, ref: _Reference) -> np.ndarray:
    """Displacement of all nodes of cells from that of their edges and snapped faces.

    Args:
        disp: ``(nc, ndofs, 3)`` node displacements of the cells (edge nodes
            and the interior nodes of snapped faces are read, the rest ignored).
        snapped_faces: 3D: ``(nc, 4)`` bool, which local faces are snapped.
        ref: the reference data.

    Returns:
        ``(nc, ndofs, 3)`` the hierarchic polynomial extension at all nodes.
    """
    out = np.einsum("ne,ced->cnd", ref.edge_extension, disp[:, ref.edge_dofs])
    for f, own in enumerate(ref.face_dofs):  # loop over the 4 faces (3D)
        if len(own) == 0:
            continue
        assert snapped_faces is not None  # faces (with nodes) exist in 3D, where they are given
        res = (disp[:, own] - out[:, own]) * snapped_faces[:, f, None, None]
        out += np.einsum("nm,cmd->cnd", ref.face_extension[f], res)
    return out


def _blended_dofs(ref: _Reference, snapped_faces: np.ndarray | None, nc: int) -> np.ndarray:
    """``(nc, ndofs)`` bool: the nodes of each cell that blending sets."""
    ndofs = len(ref.lam)
    out = np.zeros((nc, ndofs), dtype=bool)
    out[:, ref.interior_dofs] = True
    for f, own in enumerate(ref.face_dofs):
        assert snapped_faces is not None  # faces exist in 3D, where they are given
        out[:, own] = ~snapped_faces[:, f, None]
    return out


def curved_mesh(
    mesh: dolfinx.mesh.Mesh,
    boundary: BoundaryFacets,
    snapped: np.ndarray,
    records: Records,
    geometry: SnapGeometry,
    degree: int = 2,
    variant: str | None = None,
    min_ratio: float = 0.05,
    max_bisections: int = 10,
) -> tuple[dolfinx.mesh.Mesh, CurvedInfo]:
    """Degree-``degree`` mesh on the topology of ``mesh`` with boundary nodes on the geometry.

    Args:
        mesh: snapped affine mesh.
        boundary: its exterior facets of owned cells.
        snapped: ``(nf,)`` bool, which of ``boundary`` are snapped.
        records: lineage records of the snapped facets (in order).
        geometry: the snapping geometry (its ``place`` method is used).
        degree: degree ``k >= 2`` of the coordinate element (tested: 2, 3, 4).
        variant: basix Lagrange variant of the nodes, one of :data:`VARIANTS`
            (default :func:`default_variant`).
        min_ratio: smallest allowed ``det J / det J_straight`` at check points.
        max_bisections: halvings of a boundary node's displacement before
            giving up and leaving it at its straight position.

    Returns:
        ``(curved mesh, CurvedInfo)``.

    Raises:
        ValueError: bad ``degree``, ``variant`` or ``min_ratio``.
        CadError: CAD projection failed for some nodes.
    """
    if isinstance(degree, bool) or not isinstance(degree, (int, np.integer)) or not 2 <= degree <= 6:
        raise ValueError(f"degree must be an integer from 2 to 6, got {degree!r}")
    variant = default_variant(degree) if variant is None else variant
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if not 0.0 <= min_ratio < 1.0:
        raise ValueError(f"min_ratio must be in [0, 1), got {min_ratio}")
    comm = mesh.comm
    tdim = mesh.topology.dim
    ref = _reference(tdim, int(degree), variant)
    ce = dolfinx.fem.coordinate_element(mesh.topology.cell_type, int(degree),
                                        int(basix.LagrangeVariant[variant]))
    curved = dolfinx.fem.interpolate_geometry(mesh, ce)
    x = curved.geometry.x  # straight positions until the end
    # the vertices exactly where snapping put them (interpolate_geometry evaluates the affine map)
    x[curved.geometry.dofmaps[0][:, : tdim + 1]] = mesh.geometry.x[mesh.geometry.dofmaps[0]]

    mv, disp = _place_boundary_nodes(curved, boundary, snapped, records, geometry, ref)
    cells = _CurvedCells(curved, boundary, snapped, ref, mv, disp)
    alpha, ratio = _bisect(cells, min_ratio, max_bisections)
    x[mv] += alpha[:, None] * disp
    if cells.scratch is not None:
        bn = np.flatnonzero(cells.blended)
        x[bn] += cells.scratch[bn]

    imap = curved.geometry.index_map()
    own_mv = mv < imap.size_local
    short = np.linalg.norm((1.0 - alpha[own_mv])[:, None] * disp[own_mv], axis=1)
    info = CurvedInfo(
        degree=int(degree),
        variant=variant,
        boundary_nodes=comm.allreduce(int(np.count_nonzero(own_mv))),
        blended_nodes=comm.allreduce(int(np.count_nonzero(cells.blended[: imap.size_local]))),
        reduced_nodes=comm.allreduce(int(np.count_nonzero(own_mv & (alpha < 1.0)))),
        max_shortfall=comm.allreduce(float(short.max(initial=0.0)), op=MPI.MAX),
        min_jacobian_ratio=comm.allreduce(float(ratio.min(initial=np.inf)), op=MPI.MIN),
    )
    return curved, info


class _CurvedCells:
    """The owned cells with a placed node: their nodes, snapped faces and displacements.

    Args:
        curved: the degree-k mesh (straight node positions).
        boundary, snapped: the exterior facets and which are snapped.
        ref: reference data of the coordinate element.
        mv: ``(m,)`` placed nodes; disp: ``(m, 3)`` their full displacements.
    """

    def __init__(self, curved, boundary: BoundaryFacets, snapped: np.ndarray, ref: _Reference,
                 mv: np.ndarray, disp: np.ndarray):
        tdim = curved.topology.dim
        self.curved, self.ref, self.mv, self.disp = curved, ref, mv, disp
        self.imap = curved.geometry.index_map()
        n_nodes = self.imap.size_local + self.imap.num_ghosts
        dofs = curved.geometry.dofmaps[0]
        moved = np.zeros(n_nodes, dtype=bool)
        moved[mv] = True
        n_own = curved.topology.index_map(tdim).size_local
        cand = np.flatnonzero(moved[dofs[:n_own]].any(axis=1))
        self.faces = None  # 3D: (nc, 4) which local faces are snapped
        if tdim == 3:
            self.faces = np.zeros((len(cand), tdim + 1), dtype=bool)
            sel = np.flatnonzero(snapped)
            self.faces[np.searchsorted(cand, boundary.cells[sel]), boundary.local[sel]] = True
        self.dofs = dofs[cand]  # (nc, ndofs)
        self.x0 = curved.geometry.x[self.dofs]  # (nc, ndofs, 3) straight
        where = np.full(n_nodes, -1)
        where[mv] = np.arange(len(mv))
        self.row = where[self.dofs]  # (nc, ndofs) row of each cell node in mv, or -1
        self.bmask = _blended_dofs(ref, self.faces, len(cand))
        has_blend = curved.comm.allreduce(bool(self.bmask.any()), op=MPI.LOR)
        self.scratch = np.zeros((n_nodes, 3)) if has_blend else None
        self.blended = np.zeros(n_nodes, dtype=bool)

    def displacements(self, alpha: np.ndarray) -> np.ndarray:
        """``(nc, ndofs, 3)`` node displacements with the boundary ones scaled by ``alpha (m,)``.

        Collective.  Blended values go through one node array (``scratch``),
        so that every cell and process sees the same value for a node.
        """
        on = self.row >= 0
        D = np.zeros((*self.dofs.shape, 3))
        D[on] = alpha[self.row[on], None] * self.disp[self.row[on]]
        if self.scratch is not None:
            b = blend(D, self.faces, self.ref)
            nodes = self.dofs[self.bmask]
            self.blended = update_nodes(self.curved, self.scratch, nodes, b[self.bmask],
                                        index_map=self.imap)
            D[self.bmask] = self.scratch[nodes]
        return D

    def placed_in(self, bad: np.ndarray) -> np.ndarray:
        """``(m,)`` bool: placed nodes of the cells ``bad`` on any process (collective)."""
        flag = np.zeros(self.imap.size_local + self.imap.num_ghosts)
        flag[np.unique(self.dofs[bad])] = 1.0
        return _sync_max(self.curved, self.imap, flag)[self.mv] > 0


def _bisect(cells: _CurvedCells, min_ratio: float, max_bisections: int):
    """Jacobian guard: halve the boundary displacements of cells below ``min_ratio``.

    ``det J / det J_straight`` at the check points; after ``max_bisections``
    halvings the offending nodes go back to their straight position.

    Returns:
        ``(alpha (m,), ratio (nc, npts))``: the scale of each placed node's
        displacement, and the ratios of the final positions.  Collective.
    """
    tdim = cells.curved.topology.dim
    variant = basix.LagrangeVariant(cells.curved.geometry.cmaps[0].variant).name
    det0 = jacobian_determinants(cells.x0, None, tdim, variant)[:, :1]  # straight: constant
    alpha = np.ones(len(cells.mv))
    own = cells.mv < cells.imap.size_local
    comm = cells.curved.comm
    for it in itertools.count():
        D = cells.displacements(alpha)
        ratio = jacobian_determinants(cells.x0 + D, None, tdim, variant) / det0
        hit = cells.placed_in(ratio.min(axis=1, initial=np.inf) < min_ratio)
        if it > max_bisections or comm.allreduce(int(np.count_nonzero(hit & own))) == 0:
            return alpha, ratio
        alpha[hit] = 0.0 if it == max_bisections else 0.5 * alpha[hit]


def _place_boundary_nodes(
    curved: dolfinx.mesh.Mesh, boundary: BoundaryFacets, snapped: np.ndarray, records: Records,
    geometry: SnapGeometry, ref: _Reference,
) -> tuple[np.ndarray, np.ndarray]:
    """Place the non-vertex nodes of snapped facets on the geometry (collective).

    Each facet's closure nodes get the record's parameters combined with the
    node's barycentric coordinates in the facet, and are placed by
    ``geometry.place`` (the straight positions ``curved.geometry.x`` are the
    CAD projection's starting points).

    Returns:
        ``(nodes (m,), displacement (m, 3))``: the placed nodes (owned and
        ghost, the same values on every process) and their moves.
    """
    sel = np.flatnonzero(snapped)
    c, lf = boundary.cells[sel], boundary.local[sel]
    x = curved.geometry.x
    fdofs = np.take_along_axis(curved.geometry.dofmaps[0][c], ref.facet_closure[lf], axis=1)
    W = ref.facet_weights[lf]  # (nf, ncl, nfv)
    rec = Records(records.root, np.einsum("fpv,fvk->fpk", W, records.params))
    pts, _, _ = collective_place(curved.comm, geometry, rec, x[fdofs],
                                 f"boundary nodes of the degree-{ref.element.degree} geometry")
    # vertices (basix numbers them first) stay where snapping put them
    nonvertex = ref.facet_closure[lf] >= ref.lam.shape[1]
    target = x.copy()
    moved = update_nodes(curved, target, fdofs[nonvertex], pts[nonvertex],
                         index_map=curved.geometry.index_map())
    mv = np.flatnonzero(moved)
    return mv, target[mv] - x[mv]


def _sync_max(mesh, imap, flag: np.ndarray) -> np.ndarray:
    """Owner-and-ghost consistent logical OR of a per-node flag."""
    if mesh.comm.size == 1:
        return flag
    v = dolfinx.la.vector(imap, 1)
    v.array[:] = flag
    v.scatter_reverse(dolfinx.la.InsertMode.add)
    v.array[: imap.size_local] = v.array[: imap.size_local] > 0
    v.scatter_forward()
    return (v.array > 0).astype(float)
