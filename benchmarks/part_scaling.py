"""Real parts through refinement levels, serial and under MPI: the snapper against a plain loop.

For each CAD file (``--files``; default the 275-face block of
:func:`cad_parts.bracket`, written to a temporary STEP file) the part is
meshed by :func:`nagata_snap.cad.mesh_cad` (``--size``, ``--curvature``) and
refined uniformly ``--levels`` times, in separate processes (so that each
peak RSS is its own), for every process count of ``--procs``:

* ``snap``: :meth:`nagata_snap.Snapper.refine` with its defaults; every stage
  of ``report.times`` (the largest over the processes), the guard's own
  breakdown (``report.quality.timings``: band, setup, solve, check,
  optimise, untangle, ...), the repair stage and the cells inverted before
  smoothing;
* ``plain``: what a loop without snapping that keeps its facet tags does:
  ``dolfinx.mesh.refine`` with parent maps, the facets of the refined mesh,
  then ``transfer_meshtag`` (serial only: DOLFINx 0.11's ``transfer_meshtag``
  aborts on a distributed mesh, so under MPI the plain loop is refine + facets).

Per level and process count it prints ``(Snapper.refine - refine) / refine``
(``refine`` is the ``dolfinx.mesh.refine`` inside ``Snapper.refine``), the
peak RSS of the largest process of both runs (``ru_maxrss`` after the level,
so a level's peak includes the levels before it, as in a real loop), and the
repair's seconds (``repair``: untangle + slide + optimise, the largest over
the processes).  With ``--cpu`` a second line per level gives CPU seconds
(``time.process_time``, the largest over the processes and their sum) of the
repair stages (:mod:`nagata_snap.smoothing.repair`'s ``_untangle``,
``_slide``, ``_optimise`` and ``_partial``, timed by wrapping them) and of
the whole ``Snapper.refine``: on a machine whose cores are shared with other
jobs the wall clocks of a parallel run measure the load more than the code.

Last line: ``part_overhead_max <largest ratio over the levels whose refine
takes >= 1 s>`` (``nan`` if no level took that long).

    python benchmarks/part_scaling.py [--files a.step,b.step] [--size 30] [--levels 2]
                                      [--procs 1,2] [--cpu]

Internally it calls itself with ``--run snap|plain --file F`` (under
``mpiexec -n P`` for P > 1), which prints one JSON line per level.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.dirname(HERE)]

STAGES = ("refine", "lineage", "place", "smooth+check", "tags")
#: the repair stages of the guard (keys of its timings; with --cpu, functions of smoothing.repair)
REPAIR = ("untangle", "slide", "optimise", "partial")


def _rss_mb() -> float:
    """Peak resident set size of this process so far (MB; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _cpu_timers() -> dict[str, float]:
    """Wrap the repair stages of ``nagata_snap.smoothing.repair`` to add up their CPU seconds."""
    repair = sys.modules["nagata_snap.smoothing.repair"]
    seconds: dict[str, float] = {}
    for name in REPAIR:
        fn = getattr(repair, "_" + name)

        def timed(*a, _fn=fn, _name=name, **k):
            t0 = time.process_time()
            try:
                return _fn(*a, **k)
            finally:
                seconds[_name] = seconds.get(_name, 0.0) + time.process_time() - t0

        setattr(repair, "_" + name, timed)
    return seconds


def run_one(mode: str, path: str, size: float, curvature: int, levels: int, cpu: bool = False) -> None:
    """One process group: mesh ``path``, refine ``levels`` times (``mode`` snap / plain), JSON per level."""
    import mpi4py.MPI as MPI

    import dolfinx.mesh

    import nagata_snap.smoothing.repair  # noqa: F401  (the module, for _cpu_timers)
    from nagata_snap import Snapper
    from nagata_snap.cad import mesh_cad

    comm = MPI.COMM_WORLD
    cpu_s = _cpu_timers() if cpu and mode == "snap" else None
    cm, geo = mesh_cad(path, comm, size=size, curvature=curvature)
    mesh, tags = cm.mesh, cm.facet_tags
    snapper = Snapper(mesh, tags, geo) if mode == "snap" else None
    for level in range(1, levels + 1):
        comm.barrier()
        t0 = time.perf_counter()
        out: dict = {"mode": mode, "file": os.path.basename(path), "level": level, "procs": comm.size}
        if snapper is not None:
            if cpu_s is not None:
                cpu_s.clear()
            c0 = time.process_time()
            mesh, tags, _, _, rep = snapper.refine(mesh)
            wall = time.perf_counter() - t0
            out["times"] = {k: comm.allreduce(rep.times.get(k, 0.0), op=MPI.MAX) for k in STAGES}
            q = rep.quality
            guard = dict(q.timings) if q is not None else {}
            out["guard"] = {k: comm.allreduce(guard[k], op=MPI.MAX) for k in sorted(guard)}
            out["repair"] = sum(out["guard"].get(k, 0.0) for k in REPAIR)
            if cpu_s is not None:
                mine = {**{k: cpu_s.get(k, 0.0) for k in REPAIR}, "Snapper.refine": time.process_time() - c0}
                out["cpu"] = {k: (comm.allreduce(v, op=MPI.MAX), comm.allreduce(v)) for k, v in mine.items()}
            out["stage"] = rep.repair_stage
            out["inverted_before"] = rep.inverted_before_smoothing
            out["moved"] = rep.boundary_vertices_moved
            out["cells"] = rep.num_cells
        else:
            tdim = mesh.topology.dim
            t_r = time.perf_counter()
            mesh.topology.create_entities(1)  # (refine needs the edges; Snapper.refine creates them too)
            new, parent_cell, parent_facet = dolfinx.mesh.refine(
                mesh, option=dolfinx.mesh.RefinementOption.parent_cell_and_facet)
            t_ref = time.perf_counter() - t_r
            new.topology.create_entities(tdim - 1)
            new.topology.create_connectivity(tdim - 1, tdim)
            if comm.size == 1:  # (DOLFINx 0.11's transfer_meshtag aborts on a distributed mesh)
                mesh.topology.create_connectivity(tdim - 1, tdim)
                tags = dolfinx.mesh.transfer_meshtag(tags, new, parent_cell, parent_facet)
            mesh = new
            wall = time.perf_counter() - t0
            out["times"] = {"refine": comm.allreduce(t_ref, op=MPI.MAX)}
            out["cells"] = mesh.topology.index_map(tdim).size_global
        out["wall"] = comm.allreduce(wall, op=MPI.MAX)
        out["rss_mb"] = comm.allreduce(_rss_mb(), op=MPI.MAX)
        if comm.rank == 0:
            print("RESULT " + json.dumps(out), flush=True)


def _launch(mode: str, path: str, procs: int, args: argparse.Namespace) -> list[dict]:
    cmd = [sys.executable, os.path.abspath(__file__), "--run", mode, "--file", path,
           "--size", str(args.size), "--curvature", str(args.curvature), "--levels", str(args.levels)]
    if args.cpu:
        cmd.append("--cpu")
    if procs > 1:
        cmd = ["mpiexec", "-n", str(procs), *cmd]
    res = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if res.returncode:
        sys.stderr.write(res.stdout + res.stderr)
        raise SystemExit(f"{' '.join(cmd)} failed ({res.returncode})")
    return [json.loads(line[7:]) for line in res.stdout.splitlines() if line.startswith("RESULT ")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--files", default="", help="comma-separated CAD files (default: the 275-face block)")
    ap.add_argument("--size", type=float, default=30.0, help="largest element size [mm] (default 30)")
    ap.add_argument("--curvature", type=int, default=6, help="gmsh elements per 2 pi of curvature")
    ap.add_argument("--levels", type=int, default=2)
    ap.add_argument("--procs", default="1,2", help="process counts (default 1,2)")
    ap.add_argument("--cpu", action="store_true",
                    help="also CPU seconds per process of the repair stages and of Snapper.refine")
    ap.add_argument("--run", choices=("snap", "plain"), help=argparse.SUPPRESS)
    ap.add_argument("--file", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.run:
        run_one(args.run, args.file, args.size, args.curvature, args.levels, args.cpu)
        return
    files = [f for f in args.files.split(",") if f]
    if not files:
        import cad_parts

        files = [os.path.join(tempfile.mkdtemp(prefix="part_scaling_"), "bracket.step")]
        cad_parts.bracket(files[0])
    worst = -math.inf
    print(f"{'file':14s} {'P':>2s} {'lvl':>3s} {'cells':>9s} {'refine':>7s} " +
          " ".join(f"{k:>12s}" for k in STAGES[1:]) + f" {'ratio':>6s} {'RSS snap':>9s} "
          f"{'RSS plain':>9s} {'RSS x':>6s} {'stage':>9s} {'inv':>5s} {'repair':>7s}  guard breakdown [s]",
          flush=True)
    for path in files:
        for procs in (int(p) for p in args.procs.split(",")):
            snap = _launch("snap", path, procs, args)
            plain = _launch("plain", path, procs, args)
            for s, p in zip(snap, plain, strict=True):
                t = s["times"]
                ratio = (s["wall"] - t["refine"]) / t["refine"]
                if t["refine"] >= 1.0:
                    worst = max(worst, ratio)
                guard = ", ".join(f"{k} {v:.2f}" for k, v in s["guard"].items()
                                  if k not in ("total",) and v >= 0.005)
                print(f"{s['file'][:14]:14s} {procs:2d} {s['level']:3d} {s['cells']:9d} "
                      f"{t['refine']:7.2f} " + " ".join(f"{t[k]:12.2f}" for k in STAGES[1:]) +
                      f" {ratio:6.2f} {s['rss_mb']:8.0f}M {p['rss_mb']:8.0f}M "
                      f"{s['rss_mb'] / p['rss_mb']:6.2f} {s['stage']:>9s} {s['inverted_before']:5d} "
                      f"{s['repair']:7.2f}  {guard}", flush=True)
                if "cpu" in s:
                    print("    cpu [s], largest process / all processes: " + ", ".join(
                        f"{k} {mx:.2f} / {tot:.2f}" for k, (mx, tot) in s["cpu"].items() if tot >= 0.005),
                        flush=True)
    print(f"part_overhead_max {worst if worst > -math.inf else math.nan:.2f}")


if __name__ == "__main__":
    main()
