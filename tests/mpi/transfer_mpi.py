"""Solution transfer under MPI, driven by tests/test_transfer.py.

Usage: python transfer_mpi.py DIM OUT.npz

Snaps a coarse disk (DIM 2) or ball (DIM 3) twice (DOLFINx's default refine
keeps children on their parent's process and gives the refined mesh ghost
cells, so level 2 has a ghosted parent) and transfers fields at each level.
Rank 0 writes to OUT.npz:

* ``ghost_cells_<level>``: ghost cells of the refined mesh per process;
* ``exact_err_<space>_<level>``: max error of a transferred polynomial of the
  space's degree against DOLFINx's interpolant on the refined mesh;
* ``ghost_err_<level>``: change of the transferred array by one more
  ``scatter_forward`` (0: ghosts already equal their owners);
* ``dofs_<which>_<level>``: gathered owned dofs of a transferred smooth P2
  vector field as rows ``x, y, z, values``, for all dofs (``all``) and the
  dofs on the boundary (``boundary``).
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import generate  # noqa: E402
from test_transfer import polynomial, space  # noqa: E402

import dolfinx.fem as fem  # noqa: E402

from nagata_snap import NagataGeometry, Snapper  # noqa: E402

comm = MPI.COMM_WORLD
dim, out = int(sys.argv[1]), sys.argv[2]
if dim == 2:
    md, tag = generate.unit_disk(comm, n=8), generate.DISK_BOUNDARY
else:
    md, tag = generate.ball(comm, radius=1.0, h=0.6), generate.BALL_SPHERE
mesh, ft = md.mesh, md.facet_tags
snapper = Snapper(mesh, ft, NagataGeometry(mesh, ft, tags=[tag]))
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
        V0, deg = space(mesh0, key)
        V1, _ = space(mesh1, key)
        f = polynomial(dim, deg, tuple(V0.element.value_shape))
        u0, exact = fem.Function(V0), fem.Function(V1)
        u0.interpolate(f)
        exact.interpolate(f)
        w = snapper.transfer(u0, V1)
        err = float(np.abs(w.x.array - exact.x.array).max(initial=0.0))
        scale = comm.allreduce(float(np.abs(exact.x.array).max(initial=0.0)), op=MPI.MAX)
        result[f"exact_err_{key}_{level}"] = comm.allreduce(err, op=MPI.MAX) / scale

    el = ("Lagrange", 2, (dim,))
    V0, V1 = fem.functionspace(mesh0, el), fem.functionspace(mesh1, el)
    u0 = fem.Function(V0)
    u0.interpolate(lambda x: np.stack([np.sin(2 * x[0]) * np.exp(x[1]) + 2 + k * x[dim - 1] ** 3
                                       for k in range(dim)]))
    w = snapper.transfer(u0, V1)
    before = w.x.array.copy()
    w.x.scatter_forward()
    result[f"ghost_err_{level}"] = comm.allreduce(float(np.abs(w.x.array - before).max(initial=0.0)),
                                                  op=MPI.MAX)
    n_own = V1.dofmap.index_map.size_local
    X = V1.tabulate_dof_coordinates()[:n_own]
    rows = np.column_stack([X, w.x.array.reshape(-1, dim)[:n_own]])
    bdofs = fem.locate_dofs_topological(V1, dim - 1, ft.find(tag))
    bdofs = bdofs[bdofs < n_own]
    for which, r in (("all", rows), ("boundary", rows[bdofs])):
        gathered = comm.gather(r, root=0)
        if comm.rank == 0:
            result[f"dofs_{which}_{level}"] = np.concatenate(gathered)

if comm.rank == 0:
    np.savez(out, **result)
