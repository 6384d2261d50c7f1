"""The neighbourhood of a few bad cells, gathered on every process in a canonical order.

The repair (:mod:`nagata_snap.smoothing.repair`) fixes the cells that a linear
smoother left inverted or degenerate by a nonlinear optimisation
(:mod:`nagata_snap.smoothing.untangle`) over the nodes near them.  That neighbourhood
is small (the cost of a repair follows the trouble, not the mesh), so
instead of a distributed nonlinear solve it is gathered whole on every
process and solved there serially, identically:

* the cells within ``layers`` vertex layers of the seed cells are marked
  with ghost-consistent node masks (collective);
* each process contributes its owned cells (as global node numbers) and its
  owned nodes (global number, reference coordinates, values);
* nodes are ordered by their reference coordinates (lexicographically),
  cells by their sorted canonical vertices, and each cell's vertices
  ascending (the shape measure ``S = A W^-1`` does not depend on the vertex
  order).  The local problem is therefore the same arrays in the same order
  whatever the partition, so every process gets bitwise the same result
  from the same input, and a parallel run the serial one up to the
  round-off of its input (the linear band solve before it).

Results are written back into every local copy (owned and ghost) of the
neighbourhood's nodes, so no scatter is needed.
"""

from __future__ import annotations

import dolfinx.mesh
import numpy as np
from mpi4py import MPI

from nagata_snap.mesh.simplex import cell_columns, cells_touching, edge_length_range
from nagata_snap.smoothing.band import NodeSync, expand

__all__ = ["Neighbourhood", "layer_distance"]


def _allgather(comm: MPI.Comm, a: np.ndarray) -> np.ndarray:
    """Concatenation of ``a`` of every process, in rank order (collective)."""
    if comm.size == 1:
        return np.asarray(a)
    return np.concatenate(comm.allgather(np.asarray(a)))


class Neighbourhood:
    """Cells within ``layers`` vertex layers of the seed cells, on every process (collective).

    Args:
        mesh: the mesh (topology and parallel layout).
        sync: :class:`~nagata_snap.smoothing.band.NodeSync` of its geometry nodes.
        cols: :func:`~nagata_snap.mesh.simplex.cell_columns` of the geometry dofmap.
        seeds: ``(nc,)`` bool over local cells (owned and ghost).
        layers: vertex layers around the seeds (>= 1).
        x_ref: ``(n, 3)`` reference coordinates of the local nodes.

    Attributes:
        local_cells: ``(m,)`` local cells (owned and ghost) of the neighbourhood.
        local_nodes: ``(k,)`` local nodes of those cells; ``local_pos`` their
            canonical positions.
        x_ref: ``(N, d)`` canonical reference coordinates.
        cells: ``(M, d + 1)`` canonical cells.
        gid: ``(N,)`` global node numbers (of this partition).
        complete: ``(N,)`` bool, nodes all of whose cells are in the
            neighbourhood (only these may move).
        scale: ``(N,)`` shortest reference edge at each node (length unit).
        n_cells, n_nodes: sizes (global, equal on all processes).
    """

    def __init__(self, mesh: dolfinx.mesh.Mesh, sync: NodeSync, cols: list[np.ndarray],
                 seeds: np.ndarray, layers: int, x_ref: np.ndarray):
        comm = mesh.comm
        self.comm = comm
        d = mesh.geometry.dim
        dofmap = mesh.geometry.dofmaps[0]
        n_own_cells = mesh.topology.index_map(mesh.topology.dim).size_local
        mark = np.zeros(sync.n, dtype=bool)
        mark[dofmap[seeds].reshape(-1)] = True
        mark = sync.any(mark)
        if layers < 1:
            raise ValueError(f"a neighbourhood has at least one layer, got {layers}")
        # the last layer's nodes are the nodes of the cells touching the layer before
        in_nodes, inner, cin = expand(dofmap, mark, layers, sync, cols)
        self.local_cells = np.flatnonzero(cin).astype(np.int32)
        l2g = mesh.geometry.index_map().local_to_global(np.arange(sync.n, dtype=np.int32))
        l2g = np.asarray(l2g, dtype=np.int64)
        own = np.flatnonzero(in_nodes[: sync.n_owned])
        self._own = own
        gid = _allgather(comm, l2g[own])
        xr = _allgather(comm, x_ref[own, :d])
        order = np.lexsort(xr.T[::-1])  # canonical: by reference coordinates
        self._to_canon = np.empty(order.size, dtype=np.int64)
        self._to_canon[order] = np.arange(order.size)
        self.gid = gid[order]
        self.x_ref = xr[order]
        self._by_gid = np.argsort(self.gid)
        self.n_nodes = int(self.gid.size)
        self.complete = self.gather(inner.astype(np.float64)) > 0.5
        oc = self.local_cells[self.local_cells < n_own_cells]
        cells = self.canonical(l2g[dofmap[oc]])
        cells = np.sort(_allgather(comm, cells).reshape(-1, d + 1), axis=1)
        self.cells = cells[np.lexsort(cells.T[::-1])]
        self.local_nodes = np.flatnonzero(in_nodes)
        self.local_pos = self.canonical(l2g[self.local_nodes])
        self.n_cells = int(self.cells.shape[0])
        hmin, _ = edge_length_range(np.c_[self.x_ref, np.zeros((self.n_nodes, 3 - d))],
                                    self.cells, d)
        scale = np.full(self.n_nodes, np.inf)
        for k in range(d + 1):
            np.minimum.at(scale, self.cells[:, k], hmin)
        self.scale = np.where(np.isfinite(scale), scale, 0.0)

    def canonical(self, gids: np.ndarray) -> np.ndarray:
        """Canonical positions of global node numbers (all must be in the neighbourhood)."""
        g = np.asarray(gids, dtype=np.int64)
        return self._by_gid[np.searchsorted(self.gid, g, sorter=self._by_gid)]

    def gather(self, a: np.ndarray) -> np.ndarray:
        """Canonical ``(N, ...)`` copy of a local node array ``(n, ...)`` (owners' values; collective)."""
        a = np.asarray(a)
        vals = _allgather(self.comm, a[self._own])
        out = np.empty((self.n_nodes, *a.shape[1:]), dtype=a.dtype)
        out[self._to_canon] = vals
        return out

    def scatter(self, x: np.ndarray, values: np.ndarray) -> None:
        """Write canonical ``values (N, d)`` into the local coordinates ``x (n, 3)`` in place."""
        d = values.shape[1]
        x[self.local_nodes, :d] = values[self.local_pos]


def layer_distance(cells: np.ndarray, seeds: np.ndarray, layers: int) -> np.ndarray:
    """Vertex-layer distance ``(n,)`` from the seed nodes (``layers + 1`` beyond).

    Args:
        cells: ``(M, d + 1)`` cells; seeds: ``(n,)`` bool over the nodes.
        layers: largest distance to compute.

    Returns:
        ``(n,)`` int: 0 on the seeds, ``k`` on nodes of cells touching a node
        at distance ``k - 1``; ``layers + 1`` for nodes farther away.
    """
    mark = np.asarray(seeds, dtype=bool).copy()
    dist = np.where(mark, 0, layers + 1)
    cols = cell_columns(cells)
    for k in range(1, layers + 1):
        new = np.zeros_like(mark)
        new[cells[cells_touching(mark, cols)].reshape(-1)] = True
        dist[new & ~mark] = k
        mark |= new
    return dist
