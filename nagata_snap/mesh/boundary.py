"""Boundary facets of a DOLFINx mesh as plain arrays, and MPI-consistent node updates.

The snapping pipeline works on arrays over boundary facets; this module is the
only place that reads DOLFINx topology for them.  Each exterior facet is
handled by exactly one process: the one that owns its (single) cell, so a
facet is never processed twice and ghost cells need no parent information.
"""

from __future__ import annotations

from dataclasses import dataclass

import dolfinx.common
import dolfinx.la
import dolfinx.mesh
import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from nagata_snap.mesh.simplex import facet_normal_vectors, local_facet_vertices

__all__ = [
    "BoundaryFacets",
    "boundary_facets",
    "cell_facet_nodes",
    "cell_facets_of",
    "facets_of_cells",
    "facet_normal_vectors",
    "tag_values",
    "update_nodes",
    "check_p1_simplex",
    "check_snap_input",
    "present_tags",
]


def check_p1_simplex(mesh: dolfinx.mesh.Mesh) -> None:
    """Raise ``ValueError`` unless ``mesh`` is an affine triangle or tetrahedron mesh
    with finite coordinates (collective on ``mesh.comm``)."""
    ct = mesh.topology.cell_type
    if ct not in (dolfinx.mesh.CellType.triangle, dolfinx.mesh.CellType.tetrahedron):
        raise ValueError(
            f"nagata_snap supports triangle and tetrahedron meshes, got {ct.name} cells"
        )
    if mesh.geometry.cmaps[0].degree != 1:
        raise ValueError(
            f"nagata_snap refines affine meshes (coordinate degree 1), got degree "
            f"{mesh.geometry.cmaps[0].degree}"
        )
    if mesh.geometry.dim != mesh.topology.dim:
        raise ValueError(
            f"geometric dimension {mesh.geometry.dim} differs from topological dimension "
            f"{mesh.topology.dim}: manifold meshes are not supported"
        )
    # collective, so that every process raises (NaN on one process only)
    x = mesh.geometry.x
    bad = ~np.isfinite(x).all(axis=1)
    n_bad = mesh.comm.allreduce(int(np.count_nonzero(bad[: mesh.geometry.index_map().size_local])))
    if n_bad:
        first = np.round(x[np.flatnonzero(bad)[0]], 6).tolist() if bad.any() else "another process"
        raise ValueError(f"the mesh has {n_bad} nodes with NaN or infinite coordinates (first: {first})")


def present_tags(facet_tags: dolfinx.mesh.MeshTags, comm: MPI.Comm) -> list[int]:
    """Sorted tag values of ``facet_tags`` over all processes of ``comm`` (collective)."""
    values = np.concatenate(comm.allgather(np.asarray(facet_tags.values, dtype=np.int64)))
    return [int(t) for t in np.unique(values)]


def check_snap_input(
    mesh: dolfinx.mesh.Mesh, facet_tags: dolfinx.mesh.MeshTags, tags: npt.ArrayLike | None = None
) -> list[int]:
    """Validate a mesh, its facet tags and the tags to snap; the tags to snap (collective).

    The one check of every entry point (:class:`~nagata_snap.snapper.Snapper`,
    :class:`~nagata_snap.nagata.geometry.NagataGeometry`, the command line):
    ``mesh`` is an affine simplex mesh with finite coordinates
    (:func:`check_p1_simplex`), ``facet_tags`` are facet tags of ``mesh``, the
    ``tags`` exist and none of them is on an interior facet.  Every process
    raises the same error.

    Args:
        mesh: the coarse mesh.
        facet_tags: its facet tags.
        tags: tag values to snap; ``None``: every tag present.

    Returns:
        The tags to snap as a list of ints.

    Raises:
        ValueError: naming the problem (unsupported mesh, tags of another mesh
            or of cells, missing tags, snapped tags on interior facets).
    """
    check_p1_simplex(mesh)
    if facet_tags.topology is not mesh.topology._cpp_object:
        raise ValueError(
            "facet_tags belong to another mesh (MeshTags are bound to the mesh they were "
            "created on); create them on this mesh"
        )
    _check_facet_dim(facet_tags)
    present = present_tags(facet_tags, mesh.comm)
    snap = present if tags is None else [int(t) for t in np.atleast_1d(np.asarray(tags))]
    missing = sorted(set(snap) - set(present))
    if missing:
        raise ValueError(
            f"facet tags {missing} do not exist in the mesh's facet tags; available facet tags: "
            f"{', '.join(map(str, present)) or 'none'}"
        )
    # owned tagged facets that are not exterior (DOLFINx's exterior set is parallel-aware)
    fmap = mesh.topology.index_map(mesh.topology.dim - 1)
    tagged = np.asarray(facet_tags.indices)[np.isin(facet_tags.values, snap)]
    interior = np.setdiff1d(tagged[tagged < fmap.size_local],
                            dolfinx.mesh.exterior_facet_indices(mesh.topology))
    n_interior = mesh.comm.allreduce(len(interior))
    if n_interior:
        raise ValueError(
            f"{n_interior} facets with snapped tags {snap} are interior facets; only exterior "
            "boundary facets can be snapped"
        )
    return snap


def _check_facet_dim(facet_tags: dolfinx.mesh.MeshTags) -> None:
    """``ValueError`` unless ``facet_tags`` tag entities of dimension ``tdim - 1``."""
    if facet_tags.dim != facet_tags.topology.dim - 1:
        raise ValueError(
            f"facet_tags tag entities of dimension {facet_tags.dim}, but facets of this "
            f"{facet_tags.topology.dim}D mesh have dimension {facet_tags.topology.dim - 1} "
            "(cell tags passed as facet tags?)"
        )


def cell_facet_nodes(mesh: dolfinx.mesh.Mesh, cells: np.ndarray, local: np.ndarray) -> np.ndarray:
    """``(n, nfv)`` geometry nodes of local facet ``local[i]`` of cell ``cells[i]`` (P1 geometry).

    Needs no facet entities, only the cells' geometry dofmap.
    """
    tdim = mesh.topology.dim
    g = mesh.geometry.dofmaps[0]
    return np.take_along_axis(g[cells], local_facet_vertices(tdim)[local], axis=1).astype(np.int32)


def facets_of_cells(mesh: dolfinx.mesh.Mesh, cells: np.ndarray, local: np.ndarray) -> np.ndarray:
    """``(n,)`` local facet index of local facet ``local[i]`` of cell ``cells[i]``.

    Creates the mesh's facets if it has none (O(mesh)).
    """
    tdim = mesh.topology.dim
    mesh.topology.create_entities(tdim - 1)
    c2f = mesh.topology.connectivity(tdim, tdim - 1).array.reshape(-1, tdim + 1)
    return c2f[cells, local].astype(np.int32)


@dataclass
class BoundaryFacets:
    """Exterior facets whose cell is owned by this process.

    A facet is identified by its cell and its local index in that cell, so
    refined levels need no facet entities (creating them is O(mesh) work on
    the order of the refinement itself); the facet indices are computed on
    demand by :meth:`facet_indices`.

    Attributes:
        cells: ``(nf,)`` local index of the owned cell of each facet.
        local: ``(nf,)`` local facet index in that cell (opposite vertex ``local``).
        nodes: ``(nf, nfv)`` local geometry-node indices of the facet vertices.
        opposite: ``(nf,)`` geometry node of the cell vertex not on the facet.
        facets: ``(nf,)`` local facet indices, or None until :meth:`facet_indices`.
    """

    cells: npt.NDArray[np.int32]
    local: npt.NDArray[np.int32]
    nodes: npt.NDArray[np.int32]
    opposite: npt.NDArray[np.int32]
    facets: npt.NDArray[np.int32] | None = None

    def facet_indices(self, mesh: dolfinx.mesh.Mesh) -> npt.NDArray[np.int32]:
        """``(nf,)`` local facet indices in ``mesh`` (creates the facets if needed)."""
        if self.facets is None:
            self.facets = facets_of_cells(mesh, self.cells, self.local)
        return self.facets

    @classmethod
    def from_cells(cls, mesh: dolfinx.mesh.Mesh, cells: np.ndarray, local: np.ndarray,
                   facets: np.ndarray | None = None) -> BoundaryFacets:
        """The facets ``local`` of the owned ``cells`` (nodes and opposite vertices looked up)."""
        cells = np.asarray(cells, dtype=np.int32)
        local = np.asarray(local, dtype=np.int32)
        opposite = mesh.geometry.dofmaps[0][cells, local].astype(np.int32)
        return cls(cells, local, cell_facet_nodes(mesh, cells, local), opposite, facets)

    def outward_normals(self, x: np.ndarray) -> np.ndarray:
        """``(nf, 3)`` unit outward normals of the straight facets for coordinates ``x``."""
        p = x[self.nodes]
        n = facet_normal_vectors(p)
        flip = np.einsum("ij,ij->i", n, x[self.opposite] - p[:, 0]) > 0
        n[flip] *= -1
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def boundary_facets(mesh: dolfinx.mesh.Mesh) -> BoundaryFacets:
    """Exterior facets of ``mesh`` that belong to cells owned by this process."""
    tdim = mesh.topology.dim
    fdim = tdim - 1
    top = mesh.topology
    top.create_entities(fdim)
    top.create_connectivity(fdim, tdim)
    top.create_connectivity(tdim, fdim)
    f2c = top.connectivity(fdim, tdim)
    num_facets = top.index_map(fdim).size_local + top.index_map(fdim).num_ghosts
    ncell_f = np.diff(f2c.offsets)[:num_facets]
    cand = np.flatnonzero(ncell_f == 1).astype(np.int32)
    # A facet with one local cell may still be interior across a process
    # boundary.  DOLFINx's parallel-aware exterior set lists owned facets
    # only; ghost facets get their owner's flag through a scatter.
    ext_owned = dolfinx.mesh.exterior_facet_indices(top)
    is_ext = np.zeros(num_facets, dtype=bool)
    is_ext[ext_owned] = True
    fmap = top.index_map(fdim)
    if mesh.comm.size > 1:
        vec = dolfinx.la.vector(fmap, 1)
        vec.array[:] = 0.0
        vec.array[: fmap.size_local] = is_ext[: fmap.size_local]
        vec.scatter_forward()
        is_ext = vec.array > 0.5
    cand = cand[is_ext[cand]]
    cells, local, index = cell_facets_of(mesh, cand)  # drops facets of ghost cells
    return BoundaryFacets.from_cells(mesh, cells, local, facets=cand[index])


def cell_facets_of(
    mesh: dolfinx.mesh.Mesh, facets: npt.NDArray[np.int32]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each facet in ``facets`` as (owned cell, local facet) pairs, once per owned adjacent cell.

    Returns:
        ``(cells, local, index)``: ``index`` into ``facets``.
    """
    tdim = mesh.topology.dim
    fdim = tdim - 1
    if len(facets) == 0:
        z = np.zeros(0, dtype=np.int32)
        return z, z, np.zeros(0, dtype=np.int64)
    mesh.topology.create_connectivity(fdim, tdim)
    mesh.topology.create_connectivity(tdim, fdim)
    f2c = mesh.topology.connectivity(fdim, tdim)
    c2f = mesh.topology.connectivity(tdim, fdim).array.reshape(-1, tdim + 1)
    facets = np.asarray(facets, dtype=np.int32)
    cnt = np.diff(f2c.offsets)[facets]
    index = np.repeat(np.arange(len(facets)), cnt)
    pos = np.repeat(f2c.offsets[facets], cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
    cells = f2c.array[pos]
    own = cells < mesh.topology.index_map(tdim).size_local
    index, cells = index[own], cells[own].astype(np.int32)
    local = np.argmax(c2f[cells] == facets[index][:, None], axis=1).astype(np.int32)
    return cells, local, index


def tag_values(
    facet_tags: dolfinx.mesh.MeshTags | None, facets: npt.NDArray[np.int32], default: int = -1
) -> np.ndarray:
    """Tag value of each facet in ``facets`` (``default`` where untagged)."""
    out = np.full(len(facets), default, dtype=np.int64)
    if facet_tags is None:
        return out
    _check_facet_dim(facet_tags)
    if len(facet_tags.indices) == 0:
        return out
    pos = np.searchsorted(facet_tags.indices, facets)
    pos = np.minimum(pos, len(facet_tags.indices) - 1)
    hit = facet_tags.indices[pos] == facets
    out[hit] = facet_tags.values[pos[hit]]
    return out


def update_nodes(
    mesh: dolfinx.mesh.Mesh,
    x: np.ndarray,
    nodes: np.ndarray,
    values: np.ndarray,
    index_map: dolfinx.common.IndexMap | None = None,
) -> np.ndarray:
    """Write new positions of geometry nodes consistently across processes.

    Every process passes the nodes it computed (owned or ghost, repeats
    allowed; equal repeats up to round-off).  Owners receive the mean of all
    contributions (one per contributing process), then ghosts receive the
    owner's value, so all copies of a node agree exactly.

    Args:
        mesh: the mesh (its communicator; its geometry index map numbers the
            nodes unless ``index_map`` is given).
        x: ``(n, 3)`` coordinates, modified in place.
        nodes: ``(k,)`` local geometry nodes.
        values: ``(k, 3)`` new coordinates.
        index_map: index map of the nodes (e.g. a degree-2 geometry's).

    Returns:
        ``(moved,)`` bool array over local nodes: True where a node received a value.
    """
    imap = mesh.geometry.index_map() if index_map is None else index_map
    n_local = imap.size_local + imap.num_ghosts
    uniq, first = np.unique(nodes, return_index=True)
    if mesh.comm.size == 1:
        x[uniq] = values[first]
        moved = np.zeros(n_local, dtype=bool)
        moved[uniq] = True
        return moved
    vec = dolfinx.la.vector(imap, 4)
    a = vec.array.reshape(-1, 4)
    a[:] = 0.0
    a[uniq, :3] = values[first]
    a[uniq, 3] = 1.0
    vec.scatter_reverse(dolfinx.la.InsertMode.add)
    own = a[: imap.size_local]
    hit = own[:, 3] > 0
    own[hit, :3] /= own[hit, 3:4]
    own[hit, 3] = 1.0
    own[~hit] = 0.0
    vec.scatter_forward()
    moved = a[:, 3] > 0
    x[moved] = a[moved, :3]
    return moved
