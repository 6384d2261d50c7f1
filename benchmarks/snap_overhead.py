"""Overhead of interior smoothing + quality check relative to ``dolfinx.mesh.refine``.

Skeleton benchmark (the snapping itself is a stand-in until the refinement
hook exists): a square channel [-L, L]^2 with a circular hole of radius R,
meshed by gmsh with the hole as an inscribed ``--segments``-gon and about
``--cells`` triangles. The mesh is refined (uniformly by default, or only the
cells within ``--near`` of the hole), then the refined hole-boundary nodes
are snapped radially onto the true circle (the boundary displacement), and
the interior is smoothed with 'elastic' and with 'laplace', followed by the
validity / quality check.

Timed stages (max over ranks, best of ``--repeat``):
  refine     dolfinx.mesh.refine
  smooth     nagata_snap.smoothing.smooth(method)   (band + setup + solve)
  check      inverted_cells on all owned cells (+ allreduce)
  report     QualityReport.from_mesh (angles, ratios, histograms, reductions)
  repair     nagata_snap.smoothing.repair(method)   (smooth + guard + report)

Output: a table, then the last line ``snap_over_refine <worst ratio>`` with
ratio = (smooth + check + report) / refine, worst over the two methods.

Usage:
  python benchmarks/snap_overhead.py [--cells 100000] [--segments 16]
  mpiexec -n 2 python benchmarks/snap_overhead.py
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time

import mpi4py.MPI as MPI
import numpy as np

import dolfinx
import dolfinx.mesh

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
from nagata_snap.quality import QualityReport, inverted_cells  # noqa: E402
from nagata_snap.smoothing import repair, smooth  # noqa: E402


def build_mesh(comm, cells: int, segments: int, R: float, L: float):
    import gmsh

    import dolfinx.io.gmsh

    # uniform size h: about 2 area / (sqrt(3)/2 h^2) ... use area / (0.45 h^2)
    area = (2 * L) ** 2 - 0.5 * segments * R**2 * np.sin(2 * np.pi / segments)
    h = float(np.sqrt(area / (0.45 * cells)))
    if comm.rank == 0:
        gmsh.initialize()
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("channel_hole")
        geo = gmsh.model.geo
        outer = [geo.addPoint(x, y, 0, h) for x, y in [(-L, -L), (L, -L), (L, L), (-L, L)]]
        ol = [geo.addLine(outer[i], outer[(i + 1) % 4]) for i in range(4)]
        t = 2 * np.pi * np.arange(segments) / segments
        hp = [geo.addPoint(R * np.cos(a), R * np.sin(a), 0, h) for a in t]
        hl = [geo.addLine(hp[i], hp[(i + 1) % segments]) for i in range(segments)]
        s = geo.addPlaneSurface([geo.addCurveLoop(ol), geo.addCurveLoop(hl)])
        geo.synchronize()
        gmsh.model.addPhysicalGroup(2, [s], 1)
        gmsh.model.addPhysicalGroup(1, ol, 1)
        gmsh.model.addPhysicalGroup(1, hl, 2)
        gmsh.model.mesh.generate(2)
    msh = dolfinx.io.gmsh.model_to_mesh(gmsh.model if comm.rank == 0 else None, comm, 0,
                                        gdim=2).mesh
    if comm.rank == 0:
        gmsh.finalize()
    return msh


def boundary_nodes(msh, R):
    """(hole nodes, other boundary nodes) as local geometry indices."""
    msh.topology.create_connectivity(1, 2)
    bf = dolfinx.mesh.exterior_facet_indices(msh.topology)
    bnodes = np.unique(dolfinx.mesh.entities_to_geometry(msh, 1, bf))
    # ghost boundary nodes of owned facets on other ranks: use geometry too
    x = msh.geometry.x
    r = np.linalg.norm(x[bnodes, :2], axis=1)
    hole = bnodes[r < R * (1 + 1e-9)].astype(np.int32)
    other = bnodes[r >= R * (1 + 1e-9)].astype(np.int32)
    return hole, other


def timed(comm, fn, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        comm.Barrier()
        t0 = time.perf_counter()
        out = fn()
        dt = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
        best = min(best, dt)
    return best, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, default=100_000, help="target cells before refine")
    ap.add_argument("--segments", type=int, default=16, help="hole polygon segments")
    ap.add_argument("--near", type=float, default=None,
                    help="refine only cells within this distance of the hole (default: uniform)")
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    comm = MPI.COMM_WORLD
    R, L = 0.5, 2.0

    msh0 = build_mesh(comm, args.cells, args.segments, R, L)
    msh0.topology.create_entities(1)
    edges = None
    if args.near is not None:
        edges = dolfinx.mesh.locate_entities(
            msh0, 1, lambda x: np.linalg.norm(x[:2], axis=0) < R + args.near)
    # best of --repeat refinements of the same coarse mesh
    t_refine, (msh, _, _) = timed(comm, lambda: dolfinx.mesh.refine(msh0, edges), args.repeat)
    n0 = msh0.topology.index_map(2).size_global
    n1 = msh.topology.index_map(2).size_global

    hole, other = boundary_nodes(msh, R)
    x_ref = msh.geometry.x.copy()
    rh = np.linalg.norm(x_ref[hole, :2], axis=1)
    msh.geometry.x[hole, :2] *= (R / rh)[:, None]
    x_tgt = msh.geometry.x.copy()
    n_moved = comm.allreduce(int(np.count_nonzero(
        np.abs(rh[hole < msh.geometry.index_map().size_local] - R) > 0)))
    tdim = 2
    n_own = msh.topology.index_map(tdim).size_local
    cells_own = msh.geometry.dofmaps[0][:n_own]
    h_min = comm.allreduce(float(msh.h(tdim, np.arange(n_own, dtype=np.int32)).min()),
                           op=MPI.MIN)
    max_disp = comm.allreduce(float(np.abs(rh - R).max()) if rh.size else 0.0, op=MPI.MAX)

    smooth(msh, x_ref, hole, other, method="elastic")  # JIT warm-up, not timed

    rows = []
    ratios = {}
    for method in ("elastic", "laplace"):
        info: dict = {}
        t_s, x_new = timed(comm, lambda: smooth(msh, x_ref, hole, other, method=method,
                                                layers=args.layers, info=info), args.repeat)
        t_c, n_inv = timed(comm, lambda: comm.allreduce(
            int(inverted_cells(x_new, x_ref, cells_own, 2).size)), args.repeat)
        t_r, rep = timed(comm, lambda: QualityReport.from_mesh(
            msh, x_new, x_ref=x_ref, x_before=x_tgt), args.repeat)
        t_rep, res = timed(comm, lambda: repair(msh, x_ref, x_tgt, hole, other, method=method,
                                                layers=args.layers), args.repeat)
        ratio = (t_s + t_c + t_r) / t_refine
        ratios[method] = ratio
        rows.append((method, t_s, t_c, t_r, t_rep, ratio, n_inv, rep.n_inverted_before,
                     res.stage, info.get("band_cells", 0), info.get("timings", {})))

    if comm.rank == 0:
        print(f"mesh: {n0} cells -> refine -> {n1} cells on {comm.size} rank(s); "
              f"hole {args.segments}-gon, R={R}; moved nodes {n_moved}, "
              f"max snap displacement {max_disp:.3g} (h_min {h_min:.3g})")
        print(f"{'stage':<28}{'seconds':>10}{'/refine':>10}")
        print(f"{'refine':<28}{t_refine:>10.4f}{1.0:>10.3f}")
        for (method, t_s, t_c, t_r, t_rep, ratio, n_inv, n_inv0, stage, nb, tim) in rows:
            print(f"{'smooth ' + method:<28}{t_s:>10.4f}{t_s / t_refine:>10.3f}")
            for k, v in tim.items():
                print(f"{'  ' + k:<28}{v:>10.4f}{v / t_refine:>10.3f}")
            print(f"{'check (inverted_cells)':<28}{t_c:>10.4f}{t_c / t_refine:>10.3f}")
            print(f"{'report (QualityReport)':<28}{t_r:>10.4f}{t_r / t_refine:>10.3f}")
            print(f"{'repair ' + method + ' (all-in)':<28}{t_rep:>10.4f}"
                  f"{t_rep / t_refine:>10.3f}")
            print(f"{'  -> inverted before/after':<28}{n_inv0:>10d}{n_inv:>10d}"
                  f"   band cells {nb}, repair stage '{stage}'")
        worst = max(ratios.values())
        print(f"snap_over_refine {worst:.4f}")


if __name__ == "__main__":
    main()
