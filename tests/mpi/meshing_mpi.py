"""mesh_cad_file under MPI against the serial run (driver for tests/test_meshing.py).

Usage: mpiexec -n 2 python meshing_mpi.py OUTDIR

For each part, rank 0 writes the STEP file; the part is meshed on COMM_WORLD
(gmsh on rank 0, the mesh distributed) and on COMM_SELF by rank 0 (serial).
The per-facet data of every process (owned exterior facets) are gathered and
keyed by the facets' sorted vertex input global indices; the two runs must
give the same facets, entities, vertex classification and (u, v) (exactly:
the same gmsh run).  Then a missing file must raise on every process.
Prints ``meshing_mpi <name> ok`` per case.
"""

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "meshes"))
import parts

from nagata_snap.meshing import mesh_cad_file

comm = MPI.COMM_WORLD
out = sys.argv[1]


def table(cm):
    """Per facet, by sorted input global index: key, entity, vertex dims/tags/params in that order."""
    igi = np.asarray(cm.mesh.geometry.input_global_indices, dtype=np.int64)[cm.facets.nodes]
    order = np.argsort(igi, axis=1)
    key = np.take_along_axis(igi, order, axis=1)
    dims = np.take_along_axis(cm.node_entity_dim, order, axis=1)
    tags = np.take_along_axis(cm.node_entity_tag, order, axis=1)
    params = np.take_along_axis(cm.node_params, order[:, :, None], axis=1)
    rows = np.lexsort(key.T[::-1])
    return key[rows], cm.facet_entity[rows], dims[rows], tags[rows], params[rows]


def gathered(cm):
    parts_ = cm.mesh.comm.gather(table(cm), root=0)
    if cm.mesh.comm.rank != 0:
        return None
    key, ent, dims, tags, params = (np.concatenate([p[i] for p in parts_]) for i in range(5))
    rows = np.lexsort(key.T[::-1])
    return key[rows], ent[rows], dims[rows], tags[rows], params[rows]


for name in ("plate_holes_2d", "plate_filleted", "seamed", "assembly"):
    path = os.path.join(out, f"{name}.step")
    if comm.rank == 0:
        parts.write_part(name, out, ("step",))
    comm.barrier()
    par = gathered(mesh_cad_file(path, comm))
    assert par is not None or comm.rank != 0
    ok = True
    if comm.rank == 0:
        ser = table(mesh_cad_file(path, MPI.COMM_SELF))
        for a, b, what in zip(par, ser, ("facets", "entities", "vertex dims", "vertex tags", "params"), strict=True):
            if a.shape != b.shape or not np.array_equal(a, b):
                print(f"{name}: {what} differ between mpiexec -n {comm.size} and serial", flush=True)
                ok = False
        assert len(np.unique(par[0], axis=0)) == len(par[0])  # each facet once over the processes
    ok = comm.bcast(ok, root=0)
    if comm.rank == 0 and ok:
        print(f"meshing_mpi {name} ok", flush=True)

try:
    mesh_cad_file(os.path.join(out, "missing.step"), comm)
    raised = False
except FileNotFoundError as exc:
    raised = "missing.step" in str(exc)
if all(comm.allgather(raised)) and comm.rank == 0:
    print("meshing_mpi missing ok", flush=True)
