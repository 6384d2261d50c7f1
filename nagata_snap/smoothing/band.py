"""The band of cells around the moved nodes, and ghost-consistent node masks.

The smoothers (:mod:`nagata_snap.smoothing.smooth`) and the repair
(:mod:`nagata_snap.smoothing.repair`) work on a *band*: the cells within
``layers`` vertex-neighbour layers of the moved nodes (layer 1 = cells
touching a moved node, layer ``j+1`` = cells touching a node of layer
``j``).  No mesh is built for it: node masks over the geometry nodes are
grown layer by layer (:func:`expand`) and kept consistent over the
processes by ``dolfinx.la.vector`` scatters on ``mesh.geometry.index_map()``
(:class:`NodeSync`, the owner's value of a node is authoritative), so the
cost follows the number of moved nodes, not the mesh.

Constrained (Dirichlet) nodes of a band problem: the moved nodes, the
``fixed`` nodes, the outer layer of the band and, with
``fix_boundary=True``, every exterior-boundary node that is not listed as
moved (:func:`prepare`).
"""

from __future__ import annotations

from typing import Any

import dolfinx
import dolfinx.common
import dolfinx.la
import dolfinx.mesh
import numpy as np
import numpy.typing as npt
from mpi4py import MPI

from nagata_snap.mesh.boundary import check_p1_simplex
from nagata_snap.mesh.simplex import edge_length_range
from nagata_snap.smoothing.kernels import grow_layer

__all__ = ["NodeSync", "node_mask", "AUTO_LAYERS", "AUTO_LAYERS_MAX", "auto_layers", "expand",
           "max_layers", "exterior_nodes", "prepare", "Band"]

#: Band width: one number of layers, or ``(n,)`` layers per node.
Layers = int | np.ndarray


class NodeSync:
    """Ghost-consistency helpers for arrays over the nodes of an index map.

    Args:
        imap: ``dolfinx.common.IndexMap`` of the nodes (``mesh.geometry.index_map()``).

    Attributes:
        comm: its communicator; n_owned, n: owned and local (owned + ghost)
            node counts; parallel: more than one process.
    """

    def __init__(self, imap: dolfinx.common.IndexMap):
        self.imap = imap
        self.comm = imap.comm
        self.n_owned = imap.size_local
        self.n = imap.size_local + imap.num_ghosts
        self.parallel = imap.comm.size > 1
        self._vec: dict[int, Any] = {}

    def _v(self, bs: int) -> Any:
        if bs not in self._vec:
            self._vec[bs] = dolfinx.la.vector(self.imap, bs)
        return self._vec[bs]

    def any(self, mask: np.ndarray) -> np.ndarray:
        """Collective OR: a node is True everywhere if True on any rank."""
        if not self.parallel:
            return np.asarray(mask, dtype=bool).copy()
        v = self._v(1)
        v.array[:] = np.asarray(mask, dtype=np.float64)
        v.scatter_reverse(dolfinx.la.InsertMode.add)
        v.scatter_forward()
        return v.array > 0.5

    def total(self, a: np.ndarray) -> np.ndarray:
        """Collective sum: ``a`` (n,) / (n, bs) summed over every process's copy of each node.

        Each process contributes its values at its own rows (owned and
        ghost); every copy of a node gets the sum.  Serial: a copy of ``a``.
        """
        return self._exchange(a, add=True)

    def forward(self, a: np.ndarray) -> np.ndarray:
        """Copy of ``a`` (n, bs) / (n,) with ghost rows replaced by the owner's."""
        return self._exchange(a, add=False)

    def _exchange(self, a: np.ndarray, add: bool) -> np.ndarray:
        """A copy of ``a`` through the ghost exchange: the copies summed onto the owner
        first (``add``), then the owner's rows sent to the ghosts."""
        a = np.array(a, dtype=np.float64, copy=True)
        if not self.parallel:
            return a
        bs = 1 if a.ndim == 1 else a.shape[1]
        v = self._v(bs)
        v.array[:] = a.reshape(-1)
        if add:
            v.scatter_reverse(dolfinx.la.InsertMode.add)
        v.scatter_forward()
        return v.array.reshape(a.shape).copy()


def node_mask(n: int, idx: npt.ArrayLike) -> np.ndarray:
    """``(n,)`` bool, True at the local node indices ``idx``.

    Raises:
        IndexError: an index is outside ``0..n-1``.
    """
    m = np.zeros(n, dtype=bool)
    idx = np.asarray(idx, dtype=np.int64).reshape(-1)
    if idx.size:
        if idx.min() < 0 or idx.max() >= n:
            raise IndexError("node index out of range of the local geometry nodes")
        m[idx] = True
    return m


#: ``layers='auto'``: (largest relative displacement, band layers); above the
#: last threshold the band has AUTO_LAYERS_MAX layers.
AUTO_LAYERS = ((0.1, 2), (0.3, 3))
AUTO_LAYERS_MAX = 4


def auto_layers(x_ref: np.ndarray, disp: np.ndarray, cells: np.ndarray,
                touched: np.ndarray, sync: NodeSync) -> np.ndarray:
    """Band width of every node for the prescribed displacement ``disp`` (n, 3) (collective).

    ``touched`` (nc,) bool: the cells with a displaced node (a superset does
    no harm: cells without one have relative displacement 0).

    The relative displacement of a cell is the largest prescribed
    displacement of its nodes over its shortest reference edge; a displaced
    node takes the largest over its cells: below 0.1 (the usual case after
    refinement, where the snapping distance is O(h^2)) two layers around it
    are enough to spread the move, below 0.3 three, otherwise four (as for
    the first levels of a very coarse polygon).  So one far-moving vertex
    widens the band only around itself.  The repair goes further where
    cells still invert.

    Returns:
        (n,) int: layers around each displaced node (0 elsewhere), ghost-consistent.
    """
    n = x_ref.shape[0]
    dn = np.linalg.norm(disp, axis=1)
    node_rel = np.zeros(n)
    sel = np.flatnonzero(touched)
    if sel.size:
        sub = cells[sel]
        hmin, _ = edge_length_range(x_ref, sub, sub.shape[1] - 1)
        dmax = dn[sub].max(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(hmin > 0, dmax / hmin, np.inf)
        for k in range(sub.shape[1]):
            np.maximum.at(node_rel, sub[:, k], rel)
    # (a process sees only some cells of a node: a threshold passed on any widens)
    moving = sync.any(dn > 0)
    out = np.where(moving, AUTO_LAYERS[0][1], 0)
    wider = [layers for _, layers in AUTO_LAYERS[1:]] + [AUTO_LAYERS_MAX]
    for (limit, _), layers in zip(AUTO_LAYERS, wider, strict=True):
        out = np.where(moving & sync.any(node_rel > limit), layers, out)
    return out


def expand(cells: np.ndarray, mark: np.ndarray, layers: Layers, sync: NodeSync
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grow a node mask by ``layers`` cell layers (collective).

    Args:
        cells: ``(nc, nv)`` local cells (owned and ghost); mark: ``(n,)`` bool
            start nodes (ghost-consistent).
        layers: an int, or ``(n,)`` ints per node of ``mark`` (each such
            node grows by its own number of layers: the widest start first,
            the others join when as many steps remain as they need).

    Returns:
        ``(mark_k (n,), mark_{k-1} (n,), cells_in (nc,))`` bool, with
        ``cells_in`` the cells touching a node of ``mark_{k-1}``.
    """
    per_node = np.ndim(layers) > 0
    total = max_layers(layers, sync.comm)
    if per_node:
        need = np.where(mark, layers, 0)
        mark = need >= total
    prev = mark
    cin = np.zeros(cells.shape[0], dtype=bool)
    for step in range(total):
        if per_node:
            mark = mark | (need >= total - step)
        new, cin = grow_layer(cells, mark)  # (one compiled pass over the cells)
        new = sync.any(new)
        prev, mark = mark, new
    return mark, prev, cin


def max_layers(layers: Layers, comm: MPI.Comm) -> int:
    """Band width of an int or per-node ``layers`` (the largest over all processes)."""
    if np.ndim(layers) == 0:
        return int(layers)
    return int(comm.allreduce(int(np.max(layers, initial=0)), op=MPI.MAX))


def exterior_nodes(mesh: dolfinx.mesh.Mesh, sync: NodeSync) -> np.ndarray:
    """(n,) bool: nodes on the exterior boundary of ``mesh`` (collective).

    Creates the facets and the facet-to-cell connectivity if the mesh has
    none (O(mesh)); :class:`~nagata_snap.snapper.Snapper` lists its boundary
    nodes as ``fixed`` instead, which costs nothing.
    """
    tdim = mesh.topology.dim
    mesh.topology.create_entities(tdim - 1)
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ext = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    nodes = dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, ext)
    return sync.any(node_mask(sync.n, nodes))


def prepare(mesh: dolfinx.mesh.Mesh, x_ref: npt.ArrayLike, moved: npt.ArrayLike,
            fixed: npt.ArrayLike, fix_boundary: bool
            ) -> tuple[NodeSync, np.ndarray, np.ndarray, np.ndarray]:
    """Validate the inputs of a smoother and build its ghost-consistent node masks (collective).

    Args:
        mesh: P1 triangle / tetrahedron mesh; x_ref: ``(n, 3)`` reference
            coordinates of its local nodes; moved, fixed: local node indices.
        fix_boundary: also fix every exterior-boundary node that is not moved.

    Returns:
        ``(sync, x_ref (n, 3) float64, moved (n,) bool, fixed (n,) bool)``;
        a node both moved and fixed counts as moved.

    Raises:
        ValueError: not a P1 simplex mesh with finite coordinates
            (:func:`~nagata_snap.mesh.boundary.check_p1_simplex`, the check of
            every entry point), or ``x_ref`` of the wrong shape.
    """
    check_p1_simplex(mesh)
    sync = NodeSync(mesh.geometry.index_map())
    n = sync.n
    x_ref = np.asarray(x_ref, dtype=np.float64)
    if x_ref.shape != (n, 3):
        raise ValueError(f"x_ref must have shape {(n, 3)}, got {x_ref.shape}")
    moved_mask = sync.any(node_mask(n, moved))
    fixed_mask = sync.any(node_mask(n, fixed))
    if fix_boundary:
        fixed_mask |= exterior_nodes(mesh, sync)
    return sync, x_ref, moved_mask, fixed_mask & ~moved_mask


class Band:
    """Cells within ``layers`` of the moved nodes and the unknowns on them (collective).

    No mesh is built for the band: its system is assembled from the parent
    mesh's cells straight into a PETSc matrix whose unknowns are the band's
    free nodes, numbered contiguously by their owners. So the work follows
    the band, not the mesh, and there is no per-band mesh, function space or
    form set-up (building the band with ``dolfinx.mesh.create_mesh`` and
    assembling UFL forms on it cost more than everything else).

    Attributes:
        cells: (m,) int32 local parent cells of the band (owned and ghost);
            every node the smoother can move is only in cells of this list.
        own_cells: the owned ones (each cell is assembled once, by its owner).
        own_free: (k,) local indices of the owned free nodes (in a band cell,
            not constrained: neither moved, fixed nor in the band's outer
            layer), in global order.
        gid: (n,) int64 global number of each free node (-1 elsewhere).
        n_cells_global, n_nodes_global, n_free_global: band size.
    """

    def __init__(self, mesh: dolfinx.mesh.Mesh, moved_mask: np.ndarray, fixed_mask: np.ndarray,
                 sync: NodeSync, layers: Layers):
        if np.ndim(layers) == 0 and layers < 1:
            raise ValueError("layers must be >= 1")
        comm = mesh.comm
        cells = mesh.geometry.dofmaps[0]
        mark, prev, cin = expand(cells, moved_mask, layers, sync)
        self.cells = np.flatnonzero(cin).astype(np.int32)
        n_own_cells = mesh.topology.index_map(mesh.topology.dim).size_local
        self.own_cells = self.cells[self.cells < n_own_cells]
        in_band = np.zeros(sync.n, dtype=bool)
        in_band[cells[self.cells].reshape(-1)] = True
        in_band = sync.any(in_band)
        free = in_band & ~(moved_mask | fixed_mask | (mark & ~prev))
        self.own_free = np.flatnonzero(free[: sync.n_owned])
        offset = comm.exscan(self.own_free.size) if comm.size > 1 else 0
        gid = np.full(sync.n, -1.0)
        gid[self.own_free] = (offset or 0) + np.arange(self.own_free.size)
        self.gid = sync.forward(gid).astype(np.int64)
        self.n_cells_global = comm.allreduce(int(self.own_cells.size))
        self.n_nodes_global = comm.allreduce(int(np.count_nonzero(in_band[: sync.n_owned])))
        self.n_free_global = comm.allreduce(int(self.own_free.size))


