"""Snapping cases that invert cells: what the guard does, what it costs, what it leaves short.

Cases (Nagata mode, normals estimated from the coarse mesh):

* ``8gon-bl``: DFG channel, cylinder meshed as an 8-gon with a graded
  boundary layer (first layer 4e-4, much thinner than the 8-gon's sagitta
  3.8e-3), 3 uniform levels;
* ``sphere-squeezed``: sphere R = 0.5 in a box with its first cell layer
  squeezed to 0.15 of its thickness (``generate.squeeze_wall_layer``), 2
  uniform levels;
* machined-part features (``tests/hard_parts.py``: coarse gmsh/OCC meshes
  with curvature sizing, every face snapped; Nagata mode, and with
  ``--cad`` also CAD mode: the part written as IGES by gmsh/OCC, meshed from
  that file and snapped onto its NURBS by ``CadGeometry``): ``plate`` (through-holes,
  counterbore, fillets, pocket), ``thin_wall``, ``concave_cylinder``,
  ``reentrant_fillet``; 2 uniform levels, then 2 levels refining the cells
  in the quarter of the part of smallest ``x`` (``--no-marked``: without them).

For each level: cells, cells inverted by the snapped boundary before
smoothing, the repair stage, vertices left short of the geometry
(``partial``, and as a fraction of the snapped vertices), the largest
shortfall over the model size (bounding-box diagonal), vertices that slid
on the geometry, the smallest angle (2D) / dihedral angle (3D) of the
changed cells next to the coarse mesh's own smallest, ``smooth+check`` and
``refine`` seconds.  With ``--compare`` every level is also repaired by the
previous ladder (band-wide stiffened elastic re-solves, then partial moves;
no untangler, no sliding) on the same refined mesh, side by side.

Last lines: ``inverted_after <total>`` (must be 0),
``hard_cases_short_fraction <max over levels>`` and
``hard_cases_smooth_over_refine <max over levels with >= 1e5 cells>``.

Usage: ``python benchmarks/hard_cases.py [--cases a,b] [--cad | --cad-only] [--compare] [--no-marked]``
(also under ``mpiexec -n 2``).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import mpi4py.MPI as MPI
import numpy as np

import dolfinx.mesh

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "meshes"))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
import generate  # noqa: E402
import hard_parts  # noqa: E402

from nagata_snap import NagataGeometry, Snapper  # noqa: E402
from nagata_snap.smoothing.quality import quality_stats  # noqa: E402
from nagata_snap.smoothing.repair import repair  # noqa: E402

OPTS: dict = {}
#: the ladder before the untangler (Snapper's schedule then): for --compare
OLD_LADDER = {"untangle": False, "stiffen": ((0.0, 3), (1.0, 3), (1.0, 6))}
BIG = 100_000  # the cost target applies from this many cells


def coarse_min_angle(mesh) -> float:
    tdim = mesh.topology.dim
    n = mesh.topology.index_map(tdim).size_local
    q = quality_stats(mesh.geometry.x, mesh.geometry.dofmaps[0][:n], mesh.geometry.dim)
    return mesh.comm.allreduce(float(q["min_angle"].min(initial=180.0)), op=MPI.MIN)


def snapped_vertices(mesh, ft, tags) -> int:
    nodes = np.unique(dolfinx.mesh.entities_to_geometry(
        mesh, mesh.topology.dim - 1, ft.indices[np.isin(ft.values, tags)]))
    n_own = mesh.geometry.index_map().size_local
    return mesh.comm.allreduce(int(np.count_nonzero(nodes < n_own)))


def model_size(mesh) -> float:
    x = mesh.geometry.x[: mesh.geometry.index_map().size_local]
    lo = np.min(mesh.comm.allgather(x.min(axis=0)), axis=0)
    hi = np.max(mesh.comm.allgather(x.max(axis=0)), axis=0)
    return float(np.linalg.norm(hi - lo))


def marked_edges(mesh) -> np.ndarray:
    """Edges of the cells in the quarter ``x < x_min + (x_max - x_min) / 4`` of the bounding box."""
    tdim = mesh.topology.dim
    x = mesh.geometry.x
    lo = mesh.comm.allreduce(float(x[:, 0].min()), op=MPI.MIN)
    hi = mesh.comm.allreduce(float(x[:, 0].max()), op=MPI.MAX)
    cells = np.arange(mesh.topology.index_map(tdim).size_local, dtype=np.int32)
    mid = dolfinx.mesh.compute_midpoints(mesh, tdim, cells)
    mesh.topology.create_connectivity(tdim, 1)
    return dolfinx.mesh.compute_incident_entities(mesh.topology,
                                                  cells[mid[:, 0] < lo + 0.25 * (hi - lo)], tdim, 1)


def old_ladder(snapper, mesh_in, edges):
    """The same level repaired by the previous ladder: (stage, partial, seconds)."""
    import time

    from nagata_snap import snapper as hook

    calls = {}
    orig = hook.repair

    def spy(*a, **k):
        calls["args"], calls["kw"] = a, k
        raise _Stop

    hook.repair = spy
    try:
        snapper.refine(mesh_in, edges)
    except _Stop:
        pass
    finally:
        hook.repair = orig
    a, k = calls["args"], dict(calls["kw"])
    k.pop("slide", None)
    k.update(OLD_LADDER)
    t0 = time.perf_counter()
    res = repair(*a, **k)
    dt = mesh_in.comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    n_short = mesh_in.comm.allreduce(int(np.count_nonzero(res.shortfall > 0)))
    return res.stage, n_short, dt


class _Stop(Exception):
    pass


def run(name, comm, mesh, ft, tags, levels, say, compare, rows, geo=None):
    mode = "cad" if geo is not None else "nagata"
    geo = NagataGeometry(mesh, ft, tags=tags) if geo is None else geo
    size = model_size(mesh)
    amin0 = coarse_min_angle(mesh)
    fold = f", {hard_parts.folded_patches(geo)} of {geo.num_patches} coarse Nagata patches folded" \
        if mode == "nagata" else ""
    say(f"\n{name} ({mode}): {mesh.topology.index_map(mesh.topology.dim).size_global} coarse "
        f"cells, model size {size:.3g}, coarse min angle {amin0:.2f} deg{fold}")
    head = (f"{'level':>6} {'cells':>9} {'inv.':>5} {'stage':>9} {'partial':>8} {'short %':>8} "
            f"{'short/size':>10} {'slid':>5} {'min angle':>9} {'s+c s':>7} {'refine s':>8}")
    if compare:
        head += f" | {'old stage':>9} {'partial':>8} {'s+c s':>7}"
    say(head)
    snapper = Snapper(mesh, ft, geo, smoothing_options=OPTS)
    for k, kind in enumerate(levels, start=1):
        edges = None if kind == "u" else marked_edges(mesh)
        old = old_ladder(snapper, mesh, edges) if compare else None
        mesh, ft, *_, rep = snapper.refine(mesh, edges)
        n_snap = snapped_vertices(mesh, ft, tags)
        frac = rep.partially_moved / max(n_snap, 1)
        sc, rf = rep.times["smooth+check"], rep.times["refine"]
        sc = comm.allreduce(sc, op=MPI.MAX)
        rf = comm.allreduce(rf, op=MPI.MAX)
        amin = rep.quality.min_angle.min
        row = {"case": f"{name} {mode}", "level": f"{k}{kind}", "cells": rep.num_cells,
               "inverted": rep.quality.n_inverted_after, "frac": frac,
               "short": rep.max_shortfall / size, "angle_ratio": amin / amin0, "sc": sc, "refine": rf}
        rows.append(row)
        line = (f"{k:>5}{kind} {rep.num_cells:>9} {rep.inverted_before_smoothing:>5} "
                f"{rep.repair_stage:>9} {rep.partially_moved:>8} {100 * frac:>8.3f} "
                f"{rep.max_shortfall / size:>10.2e} {rep.slid_vertices:>5} {amin:>9.2f} "
                f"{sc:>7.3f} {rf:>8.3f}")
        if old is not None:
            line += f" | {old[0]:>9} {old[1]:>8} {old[2]:>7.3f}"
        say(line)


def cases(comm, names, marked, cad, nagata=True):
    lv2 = ("u", "u", "m", "m") if marked else ("u", "u")
    if "8gon-bl" in names:
        md = generate.dfg_channel(comm, n_circle=8, boundary_layer=True)
        yield "8gon-bl", md.mesh, md.facet_tags, [generate.CYLINDER], ("u", "u", "u"), None
    if "sphere-squeezed" in names:
        md = generate.sphere_in_box(comm, h_sphere=0.25, h_box=0.5)
        generate.squeeze_wall_layer(md.mesh)
        yield "sphere-squeezed", md.mesh, md.facet_tags, [generate.SPHERE], ("u", "u"), None
    for part in hard_parts.PARTS:
        if part in names:
            md = hard_parts.part(comm, part)
            tags = np.unique(np.concatenate(comm.allgather(md.facet_tags.values))).tolist()
            if nagata:
                yield part, md.mesh, md.facet_tags, tags, lv2, None
            if cad:
                import tempfile

                from nagata_snap.cad import CadGeometry

                with tempfile.TemporaryDirectory() as tmp:
                    path = comm.bcast(os.path.join(tmp, f"{part}.igs") if comm.rank == 0 else None)
                    if comm.rank == 0:
                        hard_parts.write_iges(part, path)
                    comm.barrier()
                    md = hard_parts.from_iges(comm, path)
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # OCC's group entities (type 402)
                        geo = CadGeometry.from_iges(path)
                    comm.barrier()  # every process has read the file
                tags = np.unique(np.concatenate(comm.allgather(md.facet_tags.values))).tolist()
                yield part, md.mesh, md.facet_tags, tags, lv2, geo


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default="8gon-bl,sphere-squeezed," + ",".join(hard_parts.PARTS))
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--cad", action="store_true", help="also CAD mode of the parts")
    ap.add_argument("--cad-only", action="store_true", help="the parts in CAD mode only")
    ap.add_argument("--no-marked", action="store_true")
    args = ap.parse_args()
    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)
    rows: list[dict] = []
    for name, mesh, ft, tags, levels, geo in cases(comm, args.cases.split(","), not args.no_marked,
                                                   args.cad or args.cad_only, not args.cad_only):
        run(name, comm, mesh, ft, tags, levels, say, args.compare, rows, geo)
    big = [r["sc"] / r["refine"] for r in rows if r["cells"] >= BIG]
    say(f"\nmin angle of changed cells / coarse min angle, smallest: "
        f"{min(r['angle_ratio'] for r in rows):.3f}; max shortfall / model size, largest: "
        f"{max(r['short'] for r in rows):.2e}")
    say(f"inverted_after {sum(r['inverted'] for r in rows)}")
    say(f"hard_cases_short_fraction {max(r['frac'] for r in rows):.5f}")
    say(f"hard_cases_smooth_over_refine {max(big) if big else float('nan'):.3f}")


if __name__ == "__main__":
    main()
