"""The distributed untangler against the serial one, and the halo's exchanges (run under mpiexec).

A unit square (2D) / cube (3D), its boundary bent by a smooth map (so the
optimum is not the straight mesh) and its interior nodes scrambled by a
deterministic function of their position, by up to ``AMP`` cell widths (some
cells invert), is untangled by :func:`nagata_snap.smoothing.untangle.optimise`:

* distributed: every process passes its local nodes and the cells it owns,
  with the :class:`~nagata_snap.smoothing.halo.Layout` of the geometry's
  index map (ghost mode ``none`` and ``shared_facet``);
* serially on rank 0: the same cells and nodes (``COMM_SELF`` mesh of the same
  size, matched by the nodes' original input indices).

The ``blocks`` cases move (and scramble) only the interior nodes that no
other process has a copy of: no cell then couples two processes' variables,
and the untangler factorises each process's block of the Hessian alone
(block Jacobi, exact).

Rank 0 prints one JSON line per (dimension, ghost mode): the largest
difference of the owned nodes from the serial result, both runs' smallest
volume ratio, rounds and convergence, whether every ghost copy holds its
owner's value, and the halo checks (forward: every ghost row gets its
owner's global number; reverse: each owner counts its copies, the number
of processes that have the node).
"""

import json
import os
import sys

import mpi4py.MPI as MPI
import numpy as np

import dolfinx.mesh

import nagata_snap.smoothing.untangle as untangle
from nagata_snap.smoothing.halo import Halo, Layout, total
from nagata_snap.smoothing.untangle import optimise, targets, volume_ratio_min

#: problems whose Hessian was factorised block by block (untangle._Problem._block_solver calls)
BLOCK_SETUPS = [0]
_block_solver = untangle._Problem._block_solver


def _counted(self):
    BLOCK_SETUPS[0] += 1
    _block_solver(self)


untangle._Problem._block_solver = _counted

N = {2: 10, 3: 5}
AMP = 0.45


def build(comm, d, ghost_mode):
    if d == 2:
        return dolfinx.mesh.create_unit_square(comm, N[2], N[2], ghost_mode=ghost_mode)
    return dolfinx.mesh.create_unit_cube(comm, N[3], N[3], N[3], ghost_mode=ghost_mode)


def problem(mesh, d, free=None):
    """(x scrambled (n, d), x_ref (n, d), owned cells, free nodes, scale) of a mesh.

    ``free``: the nodes that move and are scrambled (default: the interior ones).
    """
    x_ref = mesh.geometry.x[:, :d].copy()
    if free is None:
        free = ~np.any((x_ref < 1e-12) | (x_ref > 1 - 1e-12), axis=1)
    a = np.array([[12.9898, 7.1, 3.3], [78.233, 1.7, 9.2], [4.1, 37.7, 2.9]])[:d, :d]
    # the whole mesh bent (so the optimum is not the straight mesh), the free nodes scrambled
    bent = x_ref + 0.1 * np.sin(2 * np.pi * np.roll(x_ref, 1, axis=1))
    x = bent + np.where(free[:, None], AMP / N[d] * np.sin(x_ref @ a * N[d]), 0.0)
    n_own = mesh.topology.index_map(d).size_local
    cells = np.asarray(mesh.geometry.dofmaps[0][:n_own], dtype=np.int64)
    return x, x_ref, cells, free, np.full(len(x), 1.0 / N[d])


def halo_checks(mesh):
    """(forward gives owners' global numbers, reverse counts the copies of each node)."""
    imap = mesh.geometry.index_map()
    lay = Layout.of(imap)
    n = lay.n
    halo = Halo(lay, np.arange(lay.n_owned, n))
    gid = np.where(np.arange(n) < lay.n_owned, lay.offset + np.arange(n), -1).astype(np.float64)
    halo.forward(gid)
    fwd = bool(np.array_equal(gid, lay.to_global(np.arange(n)).astype(np.float64)))
    ones = np.ones(n)
    halo.reverse(ones, np.add)
    holders = ones[: lay.n_owned]  # processes that have each owned node
    expected = np.ones(lay.n_owned)
    np.add.at(expected, halo.send_nodes, 1.0)
    back = np.array_equal(holders, expected) and np.array_equal(lay.to_local(lay.to_global(np.arange(n))),
                                                                np.arange(n))
    return fwd, bool(back)


def unshared(lay, inner):
    """``inner`` without the nodes that have a copy on another process (then no cell couples
    two processes' variables: the block-diagonal solve)."""
    halo = Halo(lay, np.arange(lay.n_owned, lay.n))
    mark = np.zeros(lay.n, dtype=np.int8)
    mark[lay.n_owned:] = 1
    halo.reverse(mark, np.maximum)
    halo.forward(mark)
    return inner & (mark == 0)


def run_case(comm, d, gm, blocks, shrink=False):
    """One case: distributed and serial untangling compared (JSON line on rank 0)."""
    mesh = build(comm, d, gm)
    x, x_ref, cells, inner, scale = problem(mesh, d)
    lay = Layout.of(mesh.geometry.index_map())
    if blocks:
        x, x_ref, cells, inner, scale = problem(mesh, d, unshared(lay, inner))
    winv = targets(x_ref, cells)
    smin0 = comm.allreduce(volume_ratio_min(x, cells, winv), op=MPI.MIN)
    BLOCK_SETUPS[0] = 0
    res = optimise(x, cells, winv, inner, scale, layout=lay, shrink=shrink)
    block_setups = comm.allreduce(BLOCK_SETUPS[0], op=MPI.MIN)
    fwd, back = halo_checks(mesh)
    # every copy of a node holds its owner's coordinates
    xc = res.x.copy()
    Halo(lay, np.arange(lay.n_owned, lay.n)).forward(xc)
    ghosts_ok = comm.allreduce(bool(np.array_equal(xc, res.x)), op=MPI.LAND)
    f_loc = float(np.sum(res.x[: lay.n_owned]))
    sums = comm.allgather(total(comm, f_loc))
    n = lay.n_owned
    gi = comm.gather(np.asarray(mesh.geometry.input_global_indices[:n]), root=0)
    gx = comm.gather(res.x[:n], root=0)
    gf = comm.gather(inner[:n], root=0)
    if comm.rank != 0:
        return
    smesh = build(MPI.COMM_SELF, d, gm)
    order = np.argsort(smesh.geometry.input_global_indices)
    gi_all, gx_all = np.concatenate(gi), np.concatenate(gx)
    sfree = np.zeros(len(order), dtype=bool)
    sfree[order[gi_all]] = np.concatenate(gf)  # (the same moving nodes)
    sx, sx_ref, scells, sinner, sscale = problem(smesh, d, sfree)
    sres = optimise(sx, scells, targets(sx_ref, scells), sinner, sscale, shrink=shrink)
    diff = float(np.abs(gx_all - sres.x[order][gi_all]).max())
    print(json.dumps({"d": d, "ghost_mode": str(gm), "blocks": blocks, "block_setups": block_setups,
                      "shrink": shrink, "shrinks": [res.shrinks, sres.shrinks],
                      "moving": int(sinner.sum()),
                      "size": comm.size, "maxdiff": diff,
                      "sigma_min_start": smin0, "sigma_min": [res.sigma_min, sres.sigma_min],
                      "converged": [res.converged, sres.converged],
                      "rounds": [res.rounds, sres.rounds], "ghosts_ok": ghosts_ok,
                      "halo_forward": fwd, "halo_reverse": back,
                      "total_same_everywhere": len(set(sums)) == 1}), flush=True)


def main():
    comm = MPI.COMM_WORLD
    none, shared = dolfinx.mesh.GhostMode.none, dolfinx.mesh.GhostMode.shared_facet
    for d, gm, blocks in [(2, none, False), (2, shared, False), (3, none, False), (3, shared, False),
                          (2, none, True), (3, none, True)]:
        run_case(comm, d, gm, blocks)
    for d in (2, 3):  # the final round's active set shrinking
        run_case(comm, d, shared, False, shrink=True)


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import _abort

    _abort.run(main)
