"""Placement of a level's new boundary vertices: ``mpiexec -n N`` against serial on rank 0.

Usage: mpiexec -n N python place_split.py FILE OUT.json

The corpus file is meshed as the CLI does (:func:`nagata_snap.cad.mesh_cad`) on all
processes, refined once and its new boundary vertices placed
(``Snapper._bisect``, ``_lineage``, ``_place``: no smoothing, whose band DOLFINx's
partition-dependent interior refinement changes); rank 0 does the same on
``COMM_SELF``.  The boundary facets of a uniform refinement do not depend on the
partition, so every placed vertex must be the serial one: a vertex on a process
boundary is placed from all its facets, not from the ones its process holds.
Rank 0 writes the largest distance over the model size and the vertex counts to OUT.json.
"""

import json
import sys

import mpi4py.MPI as MPI
import numpy as np
from scipy.spatial import cKDTree

from nagata_snap import Snapper
from nagata_snap.cad import mesh_cad


def placed(comm: MPI.Comm, path: str) -> tuple[np.ndarray, np.ndarray, float]:
    """``(straight (n, 3), placed (n, 3), model size)`` of this process's new boundary vertices."""
    cm, geo = mesh_cad(path, comm, unit="MM", curvature=12)
    snapper = Snapper(cm.mesh, cm.facet_tags, geo)
    mesh1, parent_cell, _ = snapper._bisect(cm.mesh, None)
    level, _ = snapper._lineage(snapper._level, mesh1, parent_cell)
    x_ref, *_ = snapper._place(level)
    nodes = np.unique(level.boundary.nodes[level.snapped])
    nodes = nodes[nodes < mesh1.geometry.index_map().size_local]  # owned: each vertex once
    return x_ref[nodes], mesh1.geometry.x[nodes], geo.size


comm = MPI.COMM_WORLD
path, out = sys.argv[1], sys.argv[2]
X, P, size = placed(comm, path)
allX, allP = comm.gather(X, root=0), comm.gather(P, root=0)
if comm.rank == 0:
    Xs, Ps, _ = placed(MPI.COMM_SELF, path)
    Xp, Pp = np.concatenate(allX), np.concatenate(allP)
    d, i = cKDTree(Xs).query(Xp)
    diff = np.linalg.norm(Ps[i] - Pp, axis=1) / size
    with open(out, "w") as f:
        json.dump({"serial": len(Xs), "parallel": len(Xp), "unmatched": int(np.sum(d > 1e-12 * size)),
                   "one_to_one": bool(np.unique(i).size == len(i)), "max": float(diff.max()),
                   "moved": int(np.sum(np.linalg.norm(Ps - Xs, axis=1) > 0))}, f)
