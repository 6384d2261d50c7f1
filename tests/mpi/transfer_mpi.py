"""Solution transfer under MPI, driven by tests/test_transfer.py.

Usage: python transfer_mpi.py DIM OUT.npz

Snaps a coarse disk (DIM 2) or ball (DIM 3) twice (DOLFINx's default refine
keeps children on their parent's process and gives the refined mesh ghost
cells, so level 2 has a ghosted parent) and transfers fields at each level.
Rank 0 writes to OUT.npz:

* ``ghost_cells_<level>``: ghost cells of the refined mesh per process;
* ``exact_err_<space>_<level>``: max error of a transferred polynomial of the
  space's degree against DOLFINx's interpolant on the refined mesh;
* ``dofs_<which>_<level>``: gathered dofs of a transferred smooth P2 vector
  field as rows ``x, y, z, values``: every owned dof (``all``), every ghost
  dof of every process (``ghost``), the owned dofs on the boundary
  (``boundary``).
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))  # generate
from test_transfer import coarse_snapper, exactness_error

import dolfinx.fem as fem


comm = MPI.COMM_WORLD
dim, out = int(sys.argv[1]), sys.argv[2]
snapper, mesh, ft, tag = coarse_snapper(comm, dim)
result = {}
for level in (1, 2):  # level 1: unghosted parent (gmsh); level 2: parent with ghost cells
    mesh0 = mesh
    mesh, ft, *_ = snapper.refine(mesh0)
    mesh1 = mesh
    P = snapper.parent_cells
    n1 = mesh1.topology.index_map(dim).size_local
    n0 = mesh0.topology.index_map(dim).size_local
    # every owned child has an owned parent on this process
    assert len(P) == n1 and (n1 == 0 or P.max() < n0), "children left their parent's process"
    result[f"ghost_cells_{level}"] = np.array(
        comm.allgather(mesh1.topology.index_map(dim).num_ghosts))
    for key in ("P1", "P2", "P3", "P2-vector", "DG1"):
        result[f"exact_err_{key}_{level}"], _ = exactness_error(snapper, mesh0, mesh1, key)

    el = ("Lagrange", 2, (dim,))
    V0, V1 = fem.functionspace(mesh0, el), fem.functionspace(mesh1, el)
    u0 = fem.Function(V0)
    u0.interpolate(lambda x: np.stack([np.sin(2 * x[0]) * np.exp(x[1]) + 2 + k * x[dim - 1] ** 3
                                       for k in range(dim)]))
    w = snapper.transfer(u0, V1)
    n_own = V1.dofmap.index_map.size_local
    rows = np.column_stack([V1.tabulate_dof_coordinates(), w.x.array.reshape(-1, dim)])
    bdofs = fem.locate_dofs_topological(V1, dim - 1, ft.find(tag))
    bdofs = bdofs[bdofs < n_own]
    for which, r in (("all", rows[:n_own]), ("ghost", rows[n_own:]), ("boundary", rows[bdofs])):
        gathered = comm.gather(r, root=0)
        if comm.rank == 0:
            result[f"dofs_{which}_{level}"] = np.concatenate(gathered)

if comm.rank == 0:
    np.savez(out, **result)
