"""Owner/ghost exchanges over a few nodes, and reductions every process computes alike.

The repair's nonlinear problems (:mod:`nagata_snap.smoothing.untangle` on a
:class:`~nagata_snap.smoothing.neighbourhood.Neighbourhood`) are distributed
like the mesh: each process evaluates the cells it owns, and a node shared
by processes has one owner (the mesh's geometry index map) and ghost copies.
A problem touches a few thousand nodes of a mesh of millions, so its
exchanges must not cost O(mesh) per iteration as a ``dolfinx.la`` scatter of
the whole node array would (:class:`~nagata_snap.smoothing.band.NodeSync`).
A :class:`Halo` is set up once for the ghost nodes a process needs (each
owner is told, by one all-to-all, which of its nodes to send where), then

* :meth:`Halo.exchange` sends the owners' values to the ghost copies
  (coordinates, Newton variables, flags), and
* :meth:`Halo.exchange_back` the ghost copies' values to the owners, which
  combine them with their own (:meth:`Halo.reverse`: a sum for gradients and
  Hessian diagonals, a minimum for edge lengths), in rank order.

The optimiser's decisions (line-search acceptance, damping, convergence,
the repair's stages) must be the same on every process, so they are taken
from reductions whose result is the same bits everywhere by construction:
:func:`total` gathers the processes' partial sums and adds them in rank
order on every process (an ``MPI_Allreduce`` sum may combine the partial
sums in another order on another rank); maxima, minima and logical
reductions are exact.
"""

from __future__ import annotations

import dataclasses

import dolfinx.common
import numpy as np
from mpi4py import MPI

__all__ = ["Layout", "Halo", "total", "gathered", "in_rank_order", "maximum", "minimum", "every", "anywhere",
           "first_index"]


@dataclasses.dataclass(frozen=True)
class Layout:
    """Which local nodes a process owns, and which process owns the others.

    Attributes:
        comm: the communicator.
        n_owned: owned nodes: local ``0..n_owned-1``, global ``offset + local``.
        offset: global number of local node 0.
        ghost_gid: ``(g,)`` global numbers of the ghost nodes (local ``n_owned + k``).
        ghost_owner: ``(g,)`` their owners' ranks.
    """

    comm: MPI.Comm
    n_owned: int
    offset: int
    ghost_gid: np.ndarray
    ghost_owner: np.ndarray

    @classmethod
    def of(cls, imap: dolfinx.common.IndexMap) -> Layout:
        """The layout of an index map (``mesh.geometry.index_map()``)."""
        return cls(imap.comm, int(imap.size_local), int(imap.local_range[0]),
                   np.asarray(imap.ghosts, dtype=np.int64), np.asarray(imap.owners, dtype=np.int64))

    @classmethod
    def serial(cls, n: int) -> Layout:
        """``n`` nodes on one process (``MPI.COMM_SELF``), no ghosts."""
        return cls(MPI.COMM_SELF, int(n), 0, np.zeros(0, np.int64), np.zeros(0, np.int64))

    @property
    def n(self) -> int:
        """Local nodes (owned and ghost)."""
        return self.n_owned + len(self.ghost_gid)

    def to_global(self, local: np.ndarray) -> np.ndarray:
        """Global numbers of local nodes ``local (...)``."""
        local = np.asarray(local, dtype=np.int64)
        ghost = self.ghost_gid[np.clip(local - self.n_owned, 0, max(len(self.ghost_gid) - 1, 0))] \
            if len(self.ghost_gid) else np.zeros_like(local)
        return np.where(local < self.n_owned, self.offset + local, ghost)

    def to_local(self, gid: np.ndarray) -> np.ndarray:
        """Local numbers of global nodes ``gid (...)``; -1 where this process does not have the node."""
        g = np.asarray(gid, dtype=np.int64)
        out = np.where((g >= self.offset) & (g < self.offset + self.n_owned), g - self.offset, -1)
        if len(self.ghost_gid):
            order = np.argsort(self.ghost_gid)
            pos = np.minimum(np.searchsorted(self.ghost_gid, g, sorter=order), order.size - 1)
            hit = (out < 0) & (self.ghost_gid[order[pos]] == g)
            out = np.where(hit, self.n_owned + order[pos], out)
        return out


def _alltoallv(comm: MPI.Comm, data: np.ndarray, counts: np.ndarray, rcounts: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``data`` (grouped by destination, ``counts (P,)`` rows each) to every process.

    ``rcounts (P,)``: the rows each process sends here, if known (else one more all-to-all).
    Returns ``(received rows grouped by source rank, rows received from each rank (P,))``.
    """
    data = np.ascontiguousarray(data)
    width = int(np.prod(data.shape[1:], dtype=np.int64))
    counts = np.asarray(counts, dtype=np.int64)
    if rcounts is None:
        rcounts = np.empty_like(counts)
        comm.Alltoall(counts, rcounts)
    out = np.empty((int(rcounts.sum()), *data.shape[1:]), dtype=data.dtype)
    sc, rc = counts * width, rcounts * width
    sd = np.r_[0, np.cumsum(sc)[:-1]]
    rd = np.r_[0, np.cumsum(rc)[:-1]]
    comm.Alltoallv([data.reshape(-1), (sc, sd)], [out.reshape(-1), (rc, rd)])
    return out, rcounts


class Halo:
    """Exchanges between owners and the ghost copies of the local nodes ``ghosts`` (collective set-up).

    Args:
        layout: the node layout.
        ghosts: ``(k,)`` local ghost nodes (``>= layout.n_owned``) whose owners'
            values this process needs.

    Attributes:
        recv_nodes: ``(k,)`` those ghost nodes, grouped by owner (the order of
            :meth:`exchange`'s result).
        send_nodes: ``(s,)`` owned nodes other processes need, grouped by the
            process that needs them (a node may appear once per such process).
    """

    def __init__(self, layout: Layout, ghosts: np.ndarray):
        self.comm = layout.comm
        ghosts = np.asarray(ghosts, dtype=np.int64).reshape(-1)
        self.parallel = self.comm.size > 1
        if not self.parallel:
            if ghosts.size:
                raise ValueError("a process alone has no ghost nodes")
            self.recv_nodes = self.send_nodes = np.zeros(0, np.int64)
            return
        owner = layout.ghost_owner[ghosts - layout.n_owned]
        order = np.argsort(owner, kind="stable")
        self.recv_nodes = ghosts[order]
        self._rcount = np.bincount(owner, minlength=self.comm.size).astype(np.int64)
        asked, self._scount = _alltoallv(self.comm, layout.ghost_gid[self.recv_nodes - layout.n_owned],
                                         self._rcount)
        self.send_nodes = asked - layout.offset
        if self.send_nodes.size and (self.send_nodes.min() < 0 or self.send_nodes.max() >= layout.n_owned):
            raise ValueError("a process asked for a node its owner does not own")

    def exchange(self, values: np.ndarray) -> np.ndarray:
        """Owners' ``values`` (rows of :attr:`send_nodes`) -> rows of :attr:`recv_nodes` (collective)."""
        if not self.parallel:
            return np.zeros((0, *np.shape(values)[1:]), dtype=np.asarray(values).dtype)
        return _alltoallv(self.comm, values, self._scount, self._rcount)[0]

    def exchange_back(self, values: np.ndarray) -> np.ndarray:
        """Ghost copies' ``values`` (rows of :attr:`recv_nodes`) -> rows of :attr:`send_nodes` (collective)."""
        if not self.parallel:
            return np.zeros((0, *np.shape(values)[1:]), dtype=np.asarray(values).dtype)
        return _alltoallv(self.comm, values, self._rcount, self._scount)[0]

    def forward(self, a: np.ndarray) -> None:
        """``a (n, ...)`` over local nodes: ghost rows of :attr:`recv_nodes` set to the owners' (in place)."""
        if self.parallel:
            a[self.recv_nodes] = self.exchange(a[self.send_nodes])

    def reverse(self, a: np.ndarray, ufunc: np.ufunc = np.add) -> None:
        """Owners' rows of ``a (n, ...)`` combined (``ufunc.at``) with their ghost copies' rows (in place).

        The ghost rows are left as they are (:meth:`forward` sends the result back).
        """
        if self.parallel:
            ufunc.at(a, self.send_nodes, self.exchange_back(a[self.recv_nodes]))


def gathered(comm: MPI.Comm, values: np.ndarray) -> np.ndarray:
    """``(P, k)``: every process's ``values (k,)`` (float64), in rank order (collective)."""
    v = np.ascontiguousarray(values, dtype=np.float64).reshape(-1)
    if comm.size == 1:
        return v[None]
    parts = np.empty((comm.size, v.size))
    comm.Allgather(v, parts)
    return parts


def in_rank_order(parts: np.ndarray) -> np.ndarray:
    """Sum of the rows of ``parts (P, ...)``, added in rank order (the same bits on every process)."""
    out = parts[0].copy()
    for k in range(1, len(parts)):
        out += parts[k]
    return out


def total(comm: MPI.Comm, value: float) -> float:
    """Sum over processes, added in rank order: the same bits on every process (collective)."""
    if comm.size == 1:
        return float(value)
    return float(in_rank_order(gathered(comm, np.array([value])))[0])


def maximum(comm: MPI.Comm, value: float) -> float:
    """Largest ``value`` over processes (exact; collective)."""
    return float(value) if comm.size == 1 else float(comm.allreduce(float(value), op=MPI.MAX))


def minimum(comm: MPI.Comm, value: float) -> float:
    """Smallest ``value`` over processes (exact; collective)."""
    return float(value) if comm.size == 1 else float(comm.allreduce(float(value), op=MPI.MIN))


def every(comm: MPI.Comm, flag: bool) -> bool:
    """True if ``flag`` on every process (collective)."""
    return bool(flag) if comm.size == 1 else bool(comm.allreduce(bool(flag), op=MPI.LAND))


def anywhere(comm: MPI.Comm, flag: bool) -> bool:
    """True if ``flag`` on any process (collective)."""
    return bool(flag) if comm.size == 1 else bool(comm.allreduce(bool(flag), op=MPI.LOR))


def first_index(comm: MPI.Comm, n: int) -> int:
    """Number of items on the processes of lower rank (``n`` items here; collective): this process's
    first index in a numbering of all processes' items in rank order."""
    if comm.size == 1:
        return 0
    return int(sum(comm.allgather(int(n))[: comm.rank]))
