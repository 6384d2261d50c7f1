"""Mesh every part of meshes/parts.py from its STEP file with nagata_snap.meshing.mesh_cad_file.

Prints, per part: CAD faces (2D: curves), cells, owned boundary facets, the
vertices' largest distance from their facet's CAD face (gmsh/OCC closest
point, relative to the model size) and the times of the stages (import,
mesh, table on the gmsh process; distribute and match on every process).
Last line: ``mesh_parts_ok <parts whose facets all lie on their face to 1e-9>/<parts>``.

    python benchmarks/mesh_parts.py [--size-factor 0.1] [--curvature 12] [--parts a,b]
    mpiexec -n 2 python benchmarks/mesh_parts.py
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import mpi4py.MPI as MPI
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "meshes"))
sys.path.insert(0, os.path.join(HERE, ".."))
import gmsh  # noqa: E402
import parts  # noqa: E402

from nagata_snap.meshing import gmsh_session, import_cad, mesh_cad_file  # noqa: E402


def max_distance(cm, path) -> float:
    """Largest distance of the owned facets' vertices from their facet's face (OCC), / model size."""
    fdim = cm.mesh.topology.dim - 1
    X = cm.mesh.geometry.x[cm.facets.nodes]
    worst = 0.0
    with gmsh_session("truth"):
        import_cad(path)
        for e in np.unique(cm.facet_entity):
            P = X[cm.facet_entity == e].reshape(-1, 3)
            cp, _ = gmsh.model.getClosestPoint(fdim, int(e), P.ravel())
            worst = max(worst, float(np.abs(np.reshape(cp, (-1, 3)) - P).max()))
    return cm.mesh.comm.allreduce(worst, op=MPI.MAX) / cm.model_size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-factor", type=float, default=0.1)
    ap.add_argument("--curvature", type=float, default=12)
    ap.add_argument("--parts", default=",".join(parts.PARTS))
    args = ap.parse_args()
    comm = MPI.COMM_WORLD
    names = args.parts.split(",")
    tmp = tempfile.mkdtemp() if comm.rank == 0 else None
    tmp = comm.bcast(tmp, root=0)
    if comm.rank == 0:
        print(f"{'part':20s} {'faces':>5s} {'cells':>7s} {'bfacets':>7s} {'dist/size':>9s} "
              f"{'import':>6s} {'mesh':>6s} {'table':>6s} {'distr':>6s} {'match':>6s} {'total':>6s}  [s]")
    ok = 0
    for name in names:
        path = os.path.join(tmp, f"{name}.step")
        if comm.rank == 0:
            parts.write_part(name, tmp, ("step",))
        comm.barrier()
        t0 = time.perf_counter()
        cm = mesh_cad_file(path, comm, size_factor=args.size_factor, curvature=args.curvature)
        total = time.perf_counter() - t0
        tdim = cm.mesh.topology.dim
        cells = cm.mesh.topology.index_map(tdim).size_global
        nbf = comm.allreduce(len(cm.facet_entity))
        faces = len(set().union(*comm.allgather(set(cm.facet_entity.tolist()))))
        dist = max_distance(cm, path)
        ok += dist <= 1e-9
        t = cm.times
        if comm.rank == 0:
            print(f"{name:20s} {faces:5d} {cells:7d} {nbf:7d} {dist:9.1e} {t['import']:6.2f} {t['mesh']:6.2f} "
                  f"{t['table']:6.2f} {t['distribute']:6.2f} {t['match']:6.3f} {total:6.2f}", flush=True)
    if comm.rank == 0:
        print(f"mesh_parts_ok {ok}/{len(names)}")


if __name__ == "__main__":
    main()
