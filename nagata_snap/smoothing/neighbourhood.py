"""The neighbourhood of a few bad cells, distributed like the mesh.

The repair (:mod:`nagata_snap.smoothing.repair`) fixes the cells that a linear
smoother left inverted or degenerate by a nonlinear optimisation
(:mod:`nagata_snap.smoothing.untangle`) over the nodes near them.  That
neighbourhood is small (the cost of a repair follows the trouble, not the
mesh), and it is distributed like the mesh: nothing is gathered.

* The cells within ``layers`` vertex layers of the seed cells are marked
  with ghost-consistent node masks (:func:`~nagata_snap.smoothing.band.expand`,
  collective); each process keeps the marked cells it has (owned and ghost)
  and, for the optimiser, the ones it owns: every cell of the
  neighbourhood is evaluated by exactly one process.
* A :class:`~nagata_snap.smoothing.halo.Halo` connects the ghost nodes of
  the neighbourhood to their owners; per-node data the repair needs from
  all cells of a node (its shortest edge, the layer distance from the bad
  cells, marks) are combined there, so every copy of a node holds the
  same value, the one a serial run computes.
* The optimiser then works on each process's local nodes and owned cells
  (:func:`~nagata_snap.smoothing.untangle.optimise` with this
  neighbourhood's :class:`~nagata_snap.smoothing.halo.Layout`): each
  process evaluates its cells, gradient and Hessian are summed onto the
  nodes' owners (a distributed PETSc matrix, factorised by MUMPS), and the
  ghost copies of the moving nodes get their owners' values every
  iteration.

So a parallel run makes the serial run's decisions and iterations up to the
order of floating-point sums (the gradient and Hessian entries of a node
shared by processes, the energy's partial sums, MUMPS's distributed
factorisation): its nodes agree with the serial ones to round-off times the
conditioning of the Newton solves wherever no decision (a line-search
acceptance, a stopping test, a bisection's validity) lies within that
round-off of its threshold.
"""

from __future__ import annotations

import dolfinx.mesh
import numpy as np
from mpi4py import MPI

from nagata_snap.mesh.simplex import edge_length_range
from nagata_snap.smoothing.band import NodeSync, expand
from nagata_snap.smoothing.halo import Halo, Layout, anywhere
from nagata_snap.smoothing.kernels import grow_layer

__all__ = ["Neighbourhood"]


class Neighbourhood:
    """Cells within ``layers`` vertex layers of the seed cells, distributed (collective).

    Args:
        mesh: the mesh (topology and parallel layout).
        sync: :class:`~nagata_snap.smoothing.band.NodeSync` of its geometry nodes.
        seeds: ``(nc,)`` bool over local cells (owned and ghost).
        layers: vertex layers around the seeds (>= 1).
        x_ref: ``(n, 3)`` reference coordinates of the local nodes.

    Attributes:
        local_cells: ``(m,)`` local cells (owned and ghost) of the neighbourhood.
        cells: ``(k, d + 1)`` local nodes of the owned ones (the optimiser's cells).
        nodes: ``(n,)`` bool, local nodes of the neighbourhood's cells.
        complete: ``(n,)`` bool, nodes all of whose cells are in the
            neighbourhood (only these may move).
        scale: ``(n,)`` shortest reference edge at each node over all its
            neighbourhood cells, on every process (length unit; 0 outside).
        layout: the geometry nodes' :class:`~nagata_snap.smoothing.halo.Layout`.
        halo: :class:`~nagata_snap.smoothing.halo.Halo` of the neighbourhood's ghost nodes.
        n_cells, n_nodes: sizes (global, equal on all processes).
    """

    def __init__(self, mesh: dolfinx.mesh.Mesh, sync: NodeSync, seeds: np.ndarray, layers: int,
                 x_ref: np.ndarray):
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
        self.nodes, self.complete, cin = expand(dofmap, mark, layers, sync)
        self.layers = layers
        self.local_cells = np.flatnonzero(cin).astype(np.int32)
        self._dofs = dofmap[self.local_cells]
        self.cells = np.ascontiguousarray(self._dofs[self.local_cells < n_own_cells], dtype=np.int64)
        self.layout = Layout.of(mesh.geometry.index_map())
        self.halo = Halo(self.layout, sync.n_owned + np.flatnonzero(self.nodes[sync.n_owned:]))
        self.n_cells = int(comm.allreduce(self.cells.shape[0]))
        self.n_nodes = int(comm.allreduce(int(np.count_nonzero(self.nodes[: sync.n_owned]))))
        hmin, _ = edge_length_range(x_ref, self.cells, d)
        scale = np.full(sync.n, np.inf)
        for k in range(d + 1):
            np.minimum.at(scale, self.cells[:, k], hmin)
        self.halo.reverse(scale, np.minimum)
        self.halo.forward(scale)
        self.scale = np.where(np.isfinite(scale), scale, 0.0)

    def any(self, mask: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: the neighbourhood's nodes marked on any process's copy (collective).

        ``mask (n,)`` is a local mark (e.g. the nodes of this process's bad
        cells); nodes outside the neighbourhood are False in the result.
        """
        m = (np.asarray(mask, dtype=bool) & self.nodes).astype(np.int8)
        self.halo.reverse(m, np.maximum)
        self.halo.forward(m)
        return m > 0

    def distance(self, seeds: np.ndarray) -> np.ndarray:
        """Vertex-layer distance ``(n,)`` of the nodes from the seed nodes (collective).

        ``seeds (n,)`` bool, ghost-consistent on the neighbourhood's nodes
        (:meth:`any`).  0 on the seeds, ``k`` on nodes of neighbourhood cells
        touching a node at distance ``k - 1``; ``layers + 1`` beyond (and
        outside the neighbourhood).
        """
        mark = np.asarray(seeds, dtype=bool) & self.nodes
        dist = np.where(mark, 0, self.layers + 1)
        for k in range(1, self.layers + 1):
            new = self.any(grow_layer(self._dofs, mark)[0])  # mark and the next layer
            dist[new & ~mark] = k
            mark |= new
        return dist

    def cells_moving(self, moving: np.ndarray) -> int:
        """Global number of neighbourhood cells with a node of ``moving (n,)`` (collective)."""
        return int(self.comm.allreduce(int(np.count_nonzero(moving[self.cells].any(axis=1)))))

    def reach(self, bad_nodes: np.ndarray, dist: np.ndarray) -> int:
        """Largest ``dist`` on the nodes ``bad_nodes (n,)`` (local marks) (collective).

        ``layers + 1`` if one of them is outside the neighbourhood.
        """
        if anywhere(self.comm, bool(np.any(bad_nodes & ~self.nodes))):
            return self.layers + 1
        return int(self.comm.allreduce(int(dist[bad_nodes].max(initial=0)), op=MPI.MAX))
