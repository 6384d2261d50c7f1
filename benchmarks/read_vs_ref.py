"""Read + convert of this checkout against a git revision of it, side by side in one process.

The revision's ``nagata_snap`` is exported (``git archive``) into a temporary directory and
renamed ``nagata_snap_ref``, so that both versions are imported together; for every part and
format of ``meshes/parts.py`` asked for, OpenCASCADE's own import of the file (``ReadFile`` +
``TransferRoots`` + ``OneShape``), the revision's ``CadGeometry.from_file(isolate=False)`` and
this checkout's are timed interleaved, ``--rounds`` rounds, and the best time of each is kept
(CPU time, ``time.process_time``; ``--wall``: wall time).  Interleaving in one process makes
the ratios comparable on a shared machine, where one run of each at different moments is not.

    python benchmarks/read_vs_ref.py [--ref main] [--parts a,b] [--formats step,iges] [--rounds 15] [--wall]
                                     [--stages] [--isolate]

Printed per part and format: the three times [ms] and the ratios of the revision and of this
checkout to OpenCASCADE's import, and this checkout's verification of the faces against
OpenCASCADE (:mod:`nagata_snap.cad.verify`, part of its time; the best of each side over the
rounds, timed with the same clock unless ``--isolate``): OpenCASCADE's samples (``times["check"]``,
in the reader), our side of the checks (``times["verify"]``) and their sum over OpenCASCADE's
import, and the revision's sum over the import.  ``--files``: CAD files
(e.g. of meshes/corpus) instead of the parts.  ``--stages``: also ``read_shape`` of the revision and of this
checkout, interleaved likewise, and the best time of each of its stages (``times``: ``read``,
``heal``, ``convert``; measured with the same clock) and of the whole call.  ``--isolate``: both
read through their reader process (``isolate=True``, each revision's own server, started before
the timing), as the CLI reads; then time it with ``--wall`` (the CPU clock sees this process only).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from types import SimpleNamespace

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def export_ref(ref: str) -> str:
    """Directory holding the revision's package as ``nagata_snap_ref``."""
    out = tempfile.mkdtemp(prefix="read_vs_ref_")
    tar = subprocess.run(["git", "-C", ROOT, "archive", ref, "nagata_snap"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", out], input=tar, check=True)
    pkg = os.path.join(out, "nagata_snap_ref")
    os.rename(os.path.join(out, "nagata_snap"), pkg)
    for d, _, files in os.walk(pkg):  # its imports of itself
        for f in files:
            if f.endswith(".py"):
                p = os.path.join(d, f)
                with open(p) as fh:
                    text = fh.read()
                with open(p, "w") as fh:
                    fh.write(text.replace("nagata_snap.", "nagata_snap_ref.").replace("import nagata_snap\n",
                                                                                     "import nagata_snap_ref\n"))
    return out


def add_part_options(ap: argparse.ArgumentParser) -> None:
    """``--parts`` (the parts of benchmarks/cad_parts.py) and ``--formats``, shared with attach_vs_ref."""
    ap.add_argument("--parts", default="box_fillet_chamfer,plate,revolved,extruded_bspline,lofted_blade,"
                                       "crossing_cylinders,seamed,assembly,profile_2d,plate_holes_2d")
    ap.add_argument("--formats", default="step,iges", help="step, iges (faces-only or B-rep, as the part is written)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--ref", default="main", help="git revision to compare with (default main)")
    add_part_options(ap)
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--wall", action="store_true", help="wall time instead of CPU time")
    ap.add_argument("--files", default="", help="comma-separated CAD files instead of --parts")
    ap.add_argument("--stages", action="store_true",
                    help="also read_shape's stage times, the revision's and this checkout's")
    ap.add_argument("--isolate", action="store_true",
                    help="read through the reader process (isolate=True), as the CLI does; use with --wall")
    args = ap.parse_args()
    sys.path[:0] = [export_ref(args.ref), ROOT, os.path.join(ROOT, "meshes")]
    out = os.fdopen(os.dup(1), "w")
    os.dup2(os.open(os.devnull, os.O_WRONLY), 1)  # OpenCASCADE's messages on reading IGES
    import mpi4py.MPI  # noqa: F401  (before DOLFINx, which the packages import)
    import nagata_snap_ref.cad as ref
    import parts
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    import nagata_snap.cad as new
    import nagata_snap.cad.read as new_read
    import nagata_snap_ref.cad.read as ref_read

    def occ(path: str) -> None:
        r = STEPControl_Reader() if path.lower().endswith((".step", ".stp")) else IGESControl_Reader()
        r.ReadFile(path)
        r.TransferRoots()
        r.OneShape()

    import nagata_snap.cad.verify as new_verify
    import nagata_snap_ref.cad.verify as ref_verify

    clock = time.perf_counter if args.wall else time.process_time
    if args.stages or not args.isolate:  # read_shape times its stages and the verification its
        # side with time.perf_counter: the clock chosen instead (in this process only)
        for mod in (ref_read, new_read, ref_verify, new_verify):
            mod.time = SimpleNamespace(perf_counter=clock)
    stages = ("read", "heal", "convert", "total")
    tmp = tempfile.mkdtemp(prefix="read_vs_ref_parts_")
    print(f"{'part':20s} {'format':9s} {'OCC':>7s} {args.ref:>7s} {'this':>7s}   ratio {args.ref:>5s} {'this':>5s}"
          f"   verify: {'OCC':>7s} {'ours':>7s} {'/OCC':>5s} {args.ref + '/OCC':>9s}   "
          f"({'wall' if args.wall else 'CPU'} ms, best of {args.rounds}; verification: "
          f"{'wall' if args.isolate or args.wall else 'CPU'}; then the medians of OCC, {args.ref}, this)",
          file=out, flush=True)
    if args.files:
        cases = [(os.path.basename(p), os.path.splitext(p)[1][1:], p) for p in args.files.split(",")]
    else:
        cases = []
        for name in args.parts.split(","):
            for fmt in args.formats.split(","):
                f = fmt if fmt == "step" else ("iges" if parts.PARTS[name].iges_faces_solid else "iges_brep")
                cases.append((name, f, str(parts.write_part(name, tmp, (f,))[f])))
    for name, f, path in cases:
        checks = {"check": float("inf"), "verify": float("inf")}
        checks_ref = dict(checks)

        def read(mod, checks, p=path):
            t = mod.CadGeometry.from_file(p, isolate=args.isolate).model.times
            for k in checks:
                checks[k] = min(checks[k], t.get(k, float("nan")))

        runs = {"occ": lambda p=path: occ(p),
                "ref": lambda c=checks_ref: read(ref, c),
                "this": lambda c=checks: read(new, c)}
        best = dict.fromkeys(runs, float("inf"))
        every: dict[str, list[float]] = {k: [] for k in runs}
        for g in runs.values():
            g()  # first calls (imports, caches) are not timed
        for _ in range(args.rounds):
            for k, g in runs.items():
                t0 = clock()
                g()
                every[k].append(clock() - t0)
                best[k] = min(best[k], every[k][-1])
        o = best["occ"]
        ver = checks["check"] + checks["verify"]
        print(f"{name:20s} {f:9s} {1e3 * o:7.2f} {1e3 * best['ref']:7.2f} {1e3 * best['this']:7.2f}   "
              f"      {best['ref'] / o:5.2f} {best['this'] / o:5.2f}           {1e3 * checks['check']:7.2f} "
              f"{1e3 * checks['verify']:7.2f} {ver / o:5.2f} {sum(checks_ref.values()) / o:9.2f}   median "
              + " ".join(f"{1e3 * sorted(every[k])[len(every[k]) // 2]:.1f}" for k in runs), file=out, flush=True)
        if args.stages:
            reads = {"ref": lambda p=path: ref_read.read_shape(p), "this": lambda p=path: new_read.read_shape(p)}
            st = {k: dict.fromkeys(stages, float("inf")) for k in reads}
            for _ in range(args.rounds):
                for k, g in reads.items():
                    t0 = clock()
                    times = {**g()["times"], "total": -t0}
                    times["total"] += clock()
                    for s in stages:
                        st[k][s] = min(st[k][s], times[s])
            print(f"{'':20s} {'read_shape':9s} " + "  ".join(
                f"{s} {1e3 * st['ref'][s]:.2f} -> {1e3 * st['this'][s]:.2f}" for s in stages), file=out, flush=True)


if __name__ == "__main__":
    main()
