"""Does ``dolfinx.mesh.refine`` split a mesh the same way serially and under MPI?

A corpus file is meshed as ``benchmarks/cad_corpus.py`` meshes it (``mesh_cad``, curvature
12 per 2 pi, gmsh on rank 0), refined once uniformly by plain ``dolfinx.mesh.refine`` (no
snapping), serially and under ``mpiexec -n P``; every refined cell is compared as the set of
its four vertex positions.  The vertices are the same in both runs (edge midpoints); the cells
differ where the refinement chose between tied longest edges by partition-dependent vertex
numbers, so the snapper's repair, which works on cells, can see other cells under MPI.

    python benchmarks/refine_partition.py [--file meshes/corpus/m6_countersunk_screw_build123d.step] [--procs 2]

Last line: ``refine_cells_differing <cells of the serial mesh not in the parallel one> of <cells>``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.dirname(HERE)]


def dump_cells(path: str, out: str) -> None:
    """Mesh, refine once, and save the refined cells' sorted vertex positions (rank 0)."""
    from mpi4py import MPI

    import dolfinx
    from nagata_snap.cad import mesh_cad

    comm = MPI.COMM_WORLD
    cm, geo = mesh_cad(path, comm, unit="MM", curvature=12)
    cm.mesh.topology.create_entities(1)
    m1, _, _ = dolfinx.mesh.refine(cm.mesh, None, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)
    n = m1.topology.index_map(m1.topology.dim).size_local
    X = np.round(m1.geometry.x[m1.geometry.dofmaps[0][:n]] / geo.size, 9)
    allX = comm.gather(X, root=0)
    if comm.rank == 0:
        X = np.concatenate(allX)
        points, pid = np.unique(X.reshape(-1, 3), axis=0, return_inverse=True)
        np.save(out, points[np.sort(pid.reshape(X.shape[:2]), axis=1)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--file", default=os.path.join(os.path.dirname(HERE), "meshes", "corpus",
                                                       "m6_countersunk_screw_build123d.step"))
    parser.add_argument("--procs", type=int, default=2)
    parser.add_argument("--dump", help=argparse.SUPPRESS)  # internal: the child run's output file
    args = parser.parse_args()
    if args.dump:
        dump_cells(args.file, args.dump)
        return
    me = [sys.executable, os.path.abspath(__file__), "--file", args.file]
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for p in (1, args.procs):
            out = os.path.join(tmp, f"cells_{p}.npy")
            cmd = [*me, "--dump", out]
            mpiexec = shutil.which("mpiexec") or os.path.join(os.path.dirname(sys.executable), "mpiexec")
            subprocess.run(cmd if p == 1 else [mpiexec, "-n", str(p), *cmd], check=True)
            runs[p] = {row.tobytes() for row in np.load(out).reshape(-1, 12)}
    serial, par = runs[1], runs[args.procs]
    print(f"{os.path.basename(args.file)}: level 1 {len(serial)} cells serially, {len(par)} under "
          f"-n {args.procs}; {len(serial - par)} serial cells not in the parallel mesh, "
          f"{len(par - serial)} parallel cells not in the serial mesh")
    print(f"refine_cells_differing {len(serial - par)} of {len(serial)}")


if __name__ == "__main__":
    main()
