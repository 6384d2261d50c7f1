"""Cells of a refinement under MPI, driven by tests/test_bisect.py.

Usage: [mpiexec -n P] python bisect_cells.py {plain,bisect} OUT.npy

Meshes a cylinder with gmsh (unstructured: faces with equally long edges are
frequent after one refinement), refines it twice uniformly with
``dolfinx.mesh.refine`` (plain) or :func:`nagata_snap.mesh.bisect.refine`, and
saves on rank 0 every cell as its four vertex positions, sorted, ``(cells, 12)``
rows in lexicographic order, so runs on any number of processes compare directly.
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

import dolfinx.mesh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from test_bisect import cylinder_mesh, sorted_cells

from nagata_snap.mesh import bisect

how, out = sys.argv[1], sys.argv[2]
comm = MPI.COMM_WORLD
mesh = cylinder_mesh(comm)
for _ in range(2):
    mesh.topology.create_entities(1)
    if how == "plain":
        mesh = dolfinx.mesh.refine(mesh, None, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)[0]
    else:
        mesh = bisect.refine(mesh, None)[0]
rows = comm.gather(sorted_cells(mesh), root=0)
if comm.rank == 0:
    rows = np.concatenate(rows)
    np.save(out, rows[np.lexsort(rows.T[::-1])])
