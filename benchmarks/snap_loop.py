"""Nagata snapping loop vs plain ``dolfinx.mesh.refine``: distances and measures per level.

Two cases, uniform refinement, Nagata mode with the normals estimated from the
coarse mesh (every tag snapped, so the straight walls / box faces are snapped
too and must stay flat):

* DFG 2D-1 channel, cylinder R = 0.05 at (0.2, 0.2) meshed as a 16-gon;
* sphere R = 0.5 in the box [-1, 1]^3 (coarse gmsh mesh, h = 0.3 on the sphere).

Per level it prints the max distance of the curved boundary's vertices from
the exact circle / sphere (snapped and plain), the enclosed area / volume
error (snapped and plain) and the max deviation of the flat boundary's
vertices from their planes.  Reference line: the coarse Nagata surface error
(max over densely sampled patch points), and in 2D the closed form
``R (2 pi / N)^4 / 128`` for a circle of N equal segments.

Usage: ``python benchmarks/snap_loop.py [--levels-2d 5] [--levels-3d 3]``
(also under ``mpiexec -n 2``).  Last line: ``snapped_dist_over_nagata <max ratio>``
(at most 1: the vertices never leave the coarse Nagata surface's error band).
"""

from __future__ import annotations

import argparse
import os
import sys

import mpi4py.MPI as MPI
import numpy as np

import dolfinx.mesh

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))
import generate
from surfaces import nagata_surface_error

from nagata_snap import NagataGeometry, Snapper


def tagged_vertices(mesh, ft, tag) -> np.ndarray:
    nodes = dolfinx.mesh.entities_to_geometry(mesh, mesh.topology.dim - 1, ft.find(tag))
    return mesh.geometry.x[np.unique(nodes)]


def measure(mesh) -> float:
    tdim = mesh.topology.dim
    x = mesh.geometry.x
    cells = mesh.geometry.dofmaps[0][: mesh.topology.index_map(tdim).size_local]
    e = x[cells][:, 1:, :tdim] - x[cells][:, :1, :tdim]
    return mesh.comm.allreduce(np.abs(np.linalg.det(e)).sum() / (2 if tdim == 2 else 6))


def gmax(comm, a: np.ndarray) -> float:
    return comm.allreduce(float(a.max()) if a.size else 0.0, op=MPI.MAX)


def plain_curved_vertices(mesh, dist, tol) -> np.ndarray:
    """Exterior vertices of a plain refined mesh within ``tol`` of the curved surface.

    (The other boundaries of both cases are much farther than ``tol`` from it.)
    """
    tdim = mesh.topology.dim
    mesh.topology.create_connectivity(tdim - 1, tdim)
    ext = dolfinx.mesh.exterior_facet_indices(mesh.topology)
    xb = mesh.geometry.x[np.unique(dolfinx.mesh.entities_to_geometry(mesh, tdim - 1, ext))]
    return xb[dist(xb) < tol]


def study(name, comm, mesh, ft, curved_tag, flat, dist, near, exact, levels, say, reference=None):
    geo = NagataGeometry(mesh, ft)
    e_nag = nagata_surface_error(geo, dist, curved_tag)
    say(f"\n{name}: coarse Nagata surface error {e_nag:.4e}"
        + (f"  (closed form {reference:.4e})" if reference is not None else ""))
    say(f"{'level':>5} {'vertices':>10} {'dist snapped':>13} {'dist plain':>11} "
        f"{'measure err snapped':>20} {'plain':>10} {'flat dev':>9}")
    snapper = Snapper(mesh, ft, geo, quality_report=False)
    plain = mesh
    worst = 0.0
    for k in range(1, levels + 1):
        mesh, ft, *_ = snapper.refine(mesh)
        plain.topology.create_entities(1)
        plain = dolfinx.mesh.refine(plain)[0]
        d_s = gmax(comm, dist(tagged_vertices(mesh, ft, curved_tag)))
        d_p = gmax(comm, dist(plain_curved_vertices(plain, dist, near)))
        dev = max(gmax(comm, f(tagged_vertices(mesh, ft, t))) for t, f in flat)
        worst = max(worst, d_s / e_nag)
        say(f"{k:>5} {mesh.geometry.index_map().size_global:>10} {d_s:>13.4e} {d_p:>11.4e} "
            f"{abs(measure(mesh) - exact):>20.4e} {abs(measure(plain) - exact):>10.3e} {dev:>9.1e}")
    return worst


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--levels-2d", type=int, default=5)
    p.add_argument("--levels-3d", type=int, default=3)
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)

    R, c = generate.DFG_RADIUS, np.array([0.2, 0.2])
    md = generate.dfg_channel(comm, n_circle=16, h_far=0.1)
    L, H = generate.DFG_LENGTH, generate.DFG_HEIGHT
    w2 = study(
        "DFG channel, 16-gon cylinder", comm, md.mesh, md.facet_tags, generate.CYLINDER,
        [(generate.WALLS, lambda x: np.min(np.abs(x[:, 1:2] - [0.0, H]), axis=1)),
         (generate.INLET, lambda x: np.abs(x[:, 0])), (generate.OUTLET, lambda x: np.abs(x[:, 0] - L))],
        lambda x: np.abs(np.linalg.norm(x[..., :2] - c, axis=-1) - R), 0.1 * R,
        L * H - np.pi * R**2, args.levels_2d, say, reference=R * (2 * np.pi / 16) ** 4 / 128)

    md = generate.sphere_in_box(comm, h_sphere=0.3, h_box=0.6)
    w3 = study(
        "sphere R = 0.5 in the box [-1, 1]^3", comm, md.mesh, md.facet_tags, generate.SPHERE,
        [(generate.BOX, lambda x: np.abs(np.abs(x).max(axis=1) - 1.0))],
        lambda x: np.abs(np.linalg.norm(x, axis=-1) - 0.5), 0.05,
        8.0 - 4.0 / 3.0 * np.pi * 0.5**3, args.levels_3d, say)
    say(f"snapped_dist_over_nagata {max(w2, w3):.4f}")


if __name__ == "__main__":
    main()
