"""Lineage on meshes with slivers under MPI, driven by tests/test_lineage.py.

Usage: mpiexec -n 2 python lineage_slivers.py

For 2D and 3D, uniform and marked refinement, builds the sliver mesh of
``test_lineage.sliver_mesh`` (distributed by DOLFINx), refines it, runs
``child_facets`` and checks the result against the truth on every process
(``test_lineage.check_against_truth``).  Rank 0 prints one line per case:
``slivers DIM MODE CHILD_FACETS PARENT_FACETS RANKS_WITH_CELLS`` (totals).
"""

import os
import sys

import mpi4py.MPI as MPI

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))  # generate
from test_lineage import check_against_truth, refine_sliver_mesh, sliver_mesh

from nagata_snap.mesh.lineage import child_facets

comm = MPI.COMM_WORLD
for dim in (2, 3):
    for mode in ("uniform", "marked"):
        mesh0 = sliver_mesh(comm, dim)
        prev, mesh1, pc = refine_sliver_mesh(mesh0, mode == "marked")
        ch = child_facets(mesh0, prev, mesh1, pc)
        check_against_truth(mesh0, prev, mesh1, pc, ch)
        n_child = comm.allreduce(len(ch.parent))
        n_parent = comm.allreduce(len(prev.cells))
        busy = comm.allreduce(int(mesh0.topology.index_map(dim).size_local > 0))
        if comm.rank == 0:
            print("slivers", dim, mode, n_child, n_parent, busy, flush=True)
