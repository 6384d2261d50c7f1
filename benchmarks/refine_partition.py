"""Does the refinement split a mesh the same way serially and under MPI?

A corpus file is meshed as ``benchmarks/cad_corpus.py`` meshes it (``mesh_cad``, curvature
12 per 2 pi, gmsh on rank 0), refined once uniformly (no snapping) by plain
``dolfinx.mesh.refine`` and by the snapper's :func:`nagata_snap.mesh.bisect.refine`, serially
and under ``mpiexec -n P``; every refined cell is compared as the set of its four vertex
positions.  The vertices are the same in all runs (edge midpoints); plain DOLFINx splits
cells otherwise where it chose between tied longest edges by partition-dependent vertex
numbers, the snapper's refinement breaks those ties by position.

    python benchmarks/refine_partition.py [--file meshes/corpus/m6_countersunk_screw_build123d.step] [--procs 2]

Last line: ``refine_cells_differing <cells of the serial mesh not in the parallel one, the
snapper's refinement> of <cells>`` (the line before it: the same for plain DOLFINx).
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


def dump_cells(path: str, how: str, out: str) -> None:
    """Mesh, refine once (``how``: plain or bisect), save the refined cells' sorted vertex positions (rank 0)."""
    from mpi4py import MPI

    import dolfinx
    from nagata_snap.cad import mesh_cad
    from nagata_snap.mesh import bisect

    comm = MPI.COMM_WORLD
    cm, geo = mesh_cad(path, comm, unit="MM", curvature=12)
    cm.mesh.topology.create_entities(1)
    if how == "plain":
        m1, _, _ = dolfinx.mesh.refine(cm.mesh, None, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)
    else:
        m1, _, _ = bisect.refine(cm.mesh, None)
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
    parser.add_argument("--dump", nargs=2, help=argparse.SUPPRESS)  # internal: HOW OUT of a child run
    args = parser.parse_args()
    if args.dump:
        dump_cells(args.file, *args.dump)
        return
    me = [sys.executable, os.path.abspath(__file__), "--file", args.file]
    mpiexec = shutil.which("mpiexec") or os.path.join(os.path.dirname(sys.executable), "mpiexec")
    differing = {}
    with tempfile.TemporaryDirectory() as tmp:
        for how in ("plain", "bisect"):
            runs = {}
            for p in (1, args.procs):
                out = os.path.join(tmp, f"cells_{how}_{p}.npy")
                cmd = [*me, "--dump", how, out]
                subprocess.run(cmd if p == 1 else [mpiexec, "-n", str(p), *cmd], check=True)
                runs[p] = {row.tobytes() for row in np.load(out).reshape(-1, 12)}
            serial, par = runs[1], runs[args.procs]
            differing[how] = len(serial - par)
            what = "dolfinx.mesh.refine" if how == "plain" else "nagata_snap.mesh.bisect.refine"
            print(f"{os.path.basename(args.file)}, {what}: level 1 {len(serial)} cells serially, "
                  f"{len(par)} under -n {args.procs}; {len(serial - par)} serial cells not in the "
                  f"parallel mesh, {len(par - serial)} parallel cells not in the serial mesh")
    print(f"refine_cells_differing_plain {differing['plain']} of {len(serial)}")
    print(f"refine_cells_differing {differing['bisect']} of {len(serial)}")


if __name__ == "__main__":
    main()
