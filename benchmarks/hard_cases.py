"""Snapping cases that invert cells without smoothing: what the guard reports.

* 2D: DFG channel, cylinder meshed as an 8-gon with a graded boundary layer
  (first layer 4e-4, much thinner than the 8-gon's sagitta 3.8e-3), 3
  uniform levels;
* 3D: sphere R = 0.5 in a box with its first cell layer squeezed to 0.15 of
  its thickness (``generate.squeeze_wall_layer``), 2 uniform levels.

For each level: cells inverted by the snapped boundary before smoothing,
after smoothing, the repair stage, vertices only partially moved, the band
width, the minimum angle of the cells that snapping changed and the largest
distance of the snapped vertices from the exact circle / sphere next to the
coarse Nagata surface's own distance.  Last line: ``inverted_after <total>``
(must be 0).

Usage: ``python benchmarks/hard_cases.py`` (also under ``mpiexec -n 2``).
"""

from __future__ import annotations

import os
import sys

import mpi4py.MPI as MPI
import numpy as np

import dolfinx.mesh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))
import generate  # noqa: E402
from surfaces import nagata_surface_error  # noqa: E402

from nagata_snap import NagataGeometry, Snapper  # noqa: E402


OPTS: dict = {}


def run(name, comm, mesh, ft, tag, dist, levels, say) -> int:
    geo = NagataGeometry(mesh, ft, tags=[tag])
    e_nag = nagata_surface_error(geo, dist)
    say(f"\n{name} (coarse Nagata surface error {e_nag:.3e})")
    say(f"{'level':>5} {'cells':>9} {'inv. before':>12} {'inv. after':>11} {'stage':>8} "
        f"{'partial':>8} {'layers':>7} {'min angle':>10} {'max dist':>10}")
    snapper = Snapper(mesh, ft, geo, smoothing_options=OPTS)
    total = 0
    for k in range(1, levels + 1):
        mesh, ft, *_, rep = snapper.refine(mesh)
        nodes = np.unique(dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(tag)))
        d = dist(mesh.geometry.x[nodes])
        dmax = comm.allreduce(float(d.max()) if d.size else 0.0, op=MPI.MAX)
        layers = max((int(a.get("layers", 0)) for a in rep.smoothing_attempts), default=0)
        total += rep.inverted_after_smoothing
        say(f"{k:>5} {mesh.topology.index_map(mesh.topology.dim).size_global:>9} "
            f"{rep.inverted_before_smoothing:>12} {rep.inverted_after_smoothing:>11} "
            f"{rep.repair_stage:>8} {rep.partially_moved:>8} {layers!s:>7} "
            f"{rep.quality.min_angle.min:>10.2f} {dmax:>10.3e}")
    return total


def main() -> None:
    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)
    md = generate.dfg_channel(comm, n_circle=8, boundary_layer=True)
    c, R = np.array([0.2, 0.2]), generate.DFG_RADIUS
    total = run("DFG channel, 8-gon cylinder with a graded boundary layer", comm, md.mesh,
                md.facet_tags, generate.CYLINDER,
                lambda x: np.abs(np.linalg.norm(x[..., :2] - c, axis=-1) - R), 3, say)
    md = generate.sphere_in_box(comm, h_sphere=0.25, h_box=0.5)
    generate.squeeze_wall_layer(md.mesh)
    total += run("sphere in a box, first cell layer squeezed to 0.15", comm, md.mesh,
                 md.facet_tags, generate.SPHERE,
                 lambda x: np.abs(np.linalg.norm(x, axis=-1) - 0.5), 2, say)
    say(f"inverted_after {total}")


if __name__ == "__main__":
    main()
