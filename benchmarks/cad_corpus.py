"""CAD mode on the corpus of real files (``meshes/corpus``): one row per file, as a user meets them.

The files were written by other CAD systems (``meshes/corpus/MANIFEST.md``
names each file's source, licence and originating system).  For every file
the script measures, against OpenCASCADE's own results:

* **faces by kind**: OpenCASCADE's surface type of every face (a
  ``Geom_RectangularTrimmedSurface`` counted as ``trimmed(<basis>)``);
* **read**: ``CadGeometry.from_file`` (the reader process, the default; its
  one-off start is measured once and printed separately) and in this
  process (``isolate=False``), against OpenCASCADE's import
  (``ReadFile`` + ``TransferRoots`` + ``OneShape``), best of 3 interleaved,
  wall clock; the target is read <= 2x the import where the import takes
  >= 0.1 s, else <= the import + 0.3 s;
* **verify**: what ``CadModel.summary()`` says of the conversion check, and its time within
  the read (OpenCASCADE's samples in the reader plus our comparison; target <= the import);
* **closest points**: ``CadGeometry.closest_point`` of 1000 points pushed
  1e-3 of the model size off random points of the trimmed faces (random
  directions; faces drawn by area; the random generator seeded by the file's
  name, so ``--files`` gives each file the points of a full run) against
  OpenCASCADE's (``occ_reference.closest_agreement``: ``BRepExtrema_DistShapeShape``
  on a compound of all the faces, and, where the faces have C0 lines inside
  (creases of a B-spline face at its knots), on the faces split there by
  ``ShapeUpgrade_ShapeDivideContinuity``, the nearer of the two): agreed
  where the distances differ by at most 1e-6 of the size (0.1 % of the push)
  and our foot point lies on the face we name (its OpenCASCADE distance
  from that trimmed face <= 1e-9 of the size); "wrong" counts points found
  on a face at a distance that OpenCASCADE's point beats, or with a foot off
  that face (the silent error); "nearer than OCC" counts points whose foot
  is on the face by OpenCASCADE's own evaluation and classifier and nearer
  than its closest point (OpenCASCADE's point is then not the closest; such a
  point counts neither as agreeing nor as wrong); "split" how many reference
  points came from the split faces;
* **snapping** (each in a child process, through the CLI's path:
  ``mesh_cad`` with the CLI's defaults, ``Snapper``, uniform
  ``Snapper.refine``): 2 levels serial and 1 under ``mpiexec -n 2``: the
  boundary vertices left short, the largest distance of a snapped vertex
  from OpenCASCADE's trimmed face it is recorded on over the model size
  (max, not a percentile; where it exceeds 1e-9 of the size, whether the vertex
  lies on a CAD edge or vertex of that face whose OpenCASCADE tolerance covers
  it, :func:`nagata_snap.cad.tolerance.count_far`, as the CLI's summary: the faces of a file written
  with a tolerance meet only within it; and, counted apart, whether it lies on the
  surfaces of both faces of an edge of its face, within ``t / sin(theta / 2)`` of the edge,
  ``t`` its tolerance and ``theta`` the faces' angle: two surfaces each within ``t`` of
  the edge meet that far from it, :func:`nagata_snap.cad.tolerance.meeting_gaps`),
  ``(lineage + place + smooth+check + tags) /
  refine`` per level, and the largest distance between the serial and the
  parallel level-1 boundary vertices (matched one to one), after smoothing and
  repair and as placement put them, and of the vertices apart how many the repair
  moved in either run (:func:`mpi_split`).

A file passes when its closest points agree on >= 99.9 % with none wrong,
its read time and its verification time meet their targets, and it either snaps (2 levels, 0 short,
every vertex within 1e-9 of the size, MPI = serial to 1e-12 of the size) or
is refused with an error that names the problem (meshing, reading); a vertex
farther than 1e-9 of the size from its face counts only beyond the file's own
tolerance of the edge it lies on.  Last
line: ``cad_corpus_ok <passed>/<files>``.

    python benchmarks/cad_corpus.py [--files a.step,b.igs] [--points 1000] [--no-snap] [--timeout 1200]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import mpi4py.MPI as MPI
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")
CORPUS = os.path.join(ROOT, "meshes", "corpus")
sys.path[:0] = [os.path.join(ROOT, "meshes"), CORPUS, ROOT]
from inventory import plain_file  # noqa: E402
from occ_reference import OccShape  # noqa: E402
from occ_reference import closest_agreement as occ_agreement  # noqa: E402

from nagata_snap.cad import CadGeometry  # noqa: E402
from nagata_snap.cad.read import _quiet  # noqa: E402
from nagata_snap.cad.tolerance import count_far  # noqa: E402

#: stages of Snapper.refine beyond the refinement itself
OVERHEAD = ("lineage", "place", "smooth+check", "tags")


def manifest(folder: str = CORPUS) -> list[dict]:
    """The corpus manifest's rows (``<folder>/manifest.json``)."""
    with open(os.path.join(folder, "manifest.json")) as f:
        return json.load(f)


# ----------------------------------------------------------------------------------------------
# OpenCASCADE's side
# ----------------------------------------------------------------------------------------------
def occ_import(path: str):
    """OpenCASCADE's own import of ``path``: its shape."""
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    with _quiet():  # the IGES reader's entity counts on stdout
        r = STEPControl_Reader() if path.lower().endswith((".step", ".stp")) else IGESControl_Reader()
        r.ReadFile(path)
        r.TransferRoots()
        return r.OneShape()


def face_kinds(shape) -> dict[str, int]:
    """Faces of ``shape`` by OpenCASCADE surface type (``trimmed(<basis>)`` for a trimmed surface)."""
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    kinds: dict[str, int] = {}
    ex = TopExp_Explorer(shape, TopAbs_FACE)
    while ex.More():
        s = BRep_Tool.Surface_s(TopoDS.Face(ex.Current()))
        name = s.DynamicType().Name().removeprefix("Geom_")
        if name == "RectangularTrimmedSurface":
            name = f"trimmed({s.BasisSurface().DynamicType().Name().removeprefix('Geom_')})"
        kinds[name] = kinds.get(name, 0) + 1
        ex.Next()
    return dict(sorted(kinds.items(), key=lambda kv: -kv[1]))


def read_times(path: str, rounds: int = 3) -> dict[str, float]:
    """Wall seconds, least of ``rounds`` interleaved calls: OCC's import (``occ``), our read in the
    reader process (already started, ``ours``) and in this process (``ours_inproc``), and the
    verification of the converted faces within our read (``verify``: OpenCASCADE's samples in
    the reader, ``times["check"]``, plus our side, ``times["verify"]``)."""
    calls = {"occ": lambda: occ_import(path),
              "ours": lambda: CadGeometry.from_file(path),
              "ours_inproc": lambda: CadGeometry.from_file(path, isolate=False)}
    best = dict.fromkeys([*calls, "verify"], np.inf)
    for _ in range(rounds):
        for k, f in calls.items():
            t0 = time.perf_counter()
            out = f()
            best[k] = min(best[k], time.perf_counter() - t0)
            if k == "ours":  # OpenCASCADE's samples (reader) + our side of the checks
                best["verify"] = min(best["verify"], out.model.times.get("check", 0.0)
                                     + out.model.times.get("verify", 0.0))
    return best


def surface_points(faces: list, n: int, rng) -> np.ndarray:
    """``(n, 3)`` random points on OpenCASCADE's trimmed ``faces``: faces drawn by area, then
    (u, v) uniform in the face's parameter box, kept where the face classifier says IN."""
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepClass import BRepClass_FaceClassifier
    from OCP.BRepGProp import BRepGProp
    from OCP.BRepTools import BRepTools
    from OCP.GProp import GProp_GProps
    from OCP.TopAbs import TopAbs_State
    from OCP.gp import gp_Pnt2d

    area = np.empty(len(faces))
    for k, f in enumerate(faces):
        props = GProp_GProps()
        BRepGProp.SurfaceProperties_s(f, props)
        area[k] = max(props.Mass(), 0.0)
    pick = rng.choice(len(faces), size=n, p=area / area.sum())
    out = []
    for k in pick:
        f, a = faces[k], BRepAdaptor_Surface(faces[k])
        u0, u1, v0, v1 = BRepTools.UVBounds_s(f)
        for _ in range(200):  # rejection sampling in the face's box
            u, v = u0 + (u1 - u0) * rng.random(), v0 + (v1 - v0) * rng.random()
            if BRepClass_FaceClassifier(f, gp_Pnt2d(u, v), 1e-9).State() == TopAbs_State.TopAbs_IN:
                q = a.Value(u, v)
                out.append((q.X(), q.Y(), q.Z()))
                break
    return np.array(out)


def closest_agreement(path: str, geo: CadGeometry, n: int, rng) -> dict:
    """Our global closest points of ``n`` pushed-off points against OpenCASCADE's
    (:func:`occ_reference.closest_agreement`), as fractions of the points and counts."""
    occ = OccShape(path, "MM")
    X = surface_points(occ.faces, n, rng)
    d = rng.normal(size=X.shape)
    X = X + 1e-3 * geo.size * d / np.linalg.norm(d, axis=1, keepdims=True)
    r = occ_agreement(geo, occ, X)
    m = max(r["n"], 1)
    return {"points": r["n"], "found": r["found"] / m, "agree": r["agree"] / m, "wrong": r["wrong"],
            "nearer": r["nearer"], "split": r["split"]}


# ----------------------------------------------------------------------------------------------
# snapping, in a child process (serial or under mpiexec)
# ----------------------------------------------------------------------------------------------
def _recording():
    """:class:`nagata_snap.Snapper` that keeps the snapped boundary positions each level's
    placement gave (``placed``, before smoothing and repair), to tell them from the repair's."""
    from nagata_snap import Snapper

    class Recording(Snapper):
        placed = np.zeros((0, 3))

        def _place(self, level):
            out = super()._place(level)
            self.placed = level.mesh.geometry.x[level.boundary.nodes[level.snapped]].reshape(-1, 3).copy()
            return out

    return Recording


def snap_case(path: str, levels: int, out: str) -> None:
    """Mesh ``path`` as the CLI does, refine and snap ``levels`` times; JSON into ``out`` (rank 0)."""
    from nagata_snap.cad import mesh_cad

    comm = MPI.COMM_WORLD
    _Recording = _recording()
    res: dict = {"levels": []}
    try:
        t0 = time.perf_counter()
        cm, geo = mesh_cad(path, comm, unit="MM", curvature=12)
        res["mesh_seconds"] = time.perf_counter() - t0
        res["cells0"] = cm.mesh.topology.index_map(cm.mesh.topology.dim).size_global
        res["summary"] = geo.model.summary() if geo.model is not None else ""
        res["meshed_with"] = getattr(cm, "meshed_with", "")  # the mesher's retry that worked, if any
    except Exception as e:  # the refusal is the result: its message is what the user reads
        res["error"] = f"meshing/reading: {type(e).__name__}: {e}"
        if comm.rank == 0:
            with open(out, "w") as f:
                json.dump(res, f)
        return
    occ = OccShape(path, cm.unit or "MM") if comm.rank == 0 else None
    mesh = cm.mesh
    try:
        snapper = _Recording(mesh, cm.facet_tags, geo)
        for _ in range(levels):
            mesh, *_, rep = snapper.refine(mesh)
            res["levels"].append(_level_row(snapper, rep, occ, geo.size, comm))
    except Exception as e:
        res["error"] = f"level {len(res['levels']) + 1}: {type(e).__name__}: {e}"
    if comm.rank == 0:
        with open(out, "w") as f:
            json.dump(res, f)


def _level_row(snapper, rep, occ, size: float, comm) -> dict:
    """One level: cells, stage times, vertices short, OCC distance of the snapped vertices."""
    lv = snapper._level
    sel = np.flatnonzero(lv.snapped)
    nodes, rec = lv.boundary.nodes[sel], lv.records  # one record per snapped facet
    P = lv.mesh.geometry.x[nodes].reshape(-1, 3)
    F = np.repeat(rec.root, nodes.shape[1])
    U = rec.params[..., :2].reshape(-1, 2)  # the faces' (u, v): a first guess for OCC's distance
    allP = comm.gather(P, root=0)
    allF = comm.gather(F, root=0)
    allU = comm.gather(U, root=0)
    # the repair's moves: vertices whose final position is not the one placement gave them
    allX = comm.gather(snapper.placed, root=0)
    row = {"cells": rep.num_cells, "short": int(rep.partially_moved),
           "times": {k: float(comm.allreduce(v, op=MPI.MAX)) for k, v in rep.times.items()}}
    if comm.rank == 0:
        P, F = np.concatenate(allP), np.concatenate(allF)
        U = np.concatenate(allU)
        _, first = np.unique(np.c_[np.round(P / size, 13), F], axis=0, return_index=True)
        d = occ.face_distance(F[first], P[first], accept=1e-10 * size,
                              params=U[first])
        row["dist"] = float(d.max(initial=0.0)) / size
        model = snapper.geometry.model
        far, within = count_far(model, F[first], P[first], d, size)
        _, meeting = count_far(model, F[first], P[first], d, size, meet=True)
        row["beyond_tolerance"] = far - meeting
        row["in_gaps"] = within
        row["where_faces_meet"] = meeting - within
        row["boundary"] = np.unique(np.round(P, 12), axis=0).tolist()
        X = np.concatenate(allX)
        moved = np.any(P != X, axis=1)
        row["placed"] = np.unique(np.round(X, 12), axis=0).tolist()
        row["repaired"] = np.unique(np.round(P[moved], 12), axis=0).tolist()
    return row


def run_case(path: str, levels: int, nproc: int, timeout: float) -> dict:
    """:func:`snap_case` in a child process (``mpiexec -n nproc`` if ``nproc > 1``)."""
    out = tempfile.mktemp(suffix=".json", prefix="corpus_")
    cmd = [sys.executable, os.path.abspath(__file__), "--case", path, "--levels", str(levels), "--json", out]
    if nproc > 1:
        cmd = ["mpiexec", "-n", str(nproc), *cmd]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s", "levels": []}
    if not os.path.exists(out):
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        return {"error": f"exit {proc.returncode}: {' | '.join(tail)}", "levels": []}
    with open(out) as f:
        res = json.load(f)
    os.unlink(out)
    return res


def mpi_match(a: list, b: list, size: float) -> float:
    """Largest distance between matched points of two boundary vertex sets over ``size``; inf if
    the sets are not in one-to-one correspondence."""
    from scipy.spatial import cKDTree

    A, B = np.asarray(a), np.asarray(b)
    if A.shape != B.shape or len(A) == 0:
        return np.inf
    d, i = cKDTree(A).query(B)
    return float(d.max()) / size if np.unique(i).size == len(i) else np.inf


def mpi_split(serial: dict, par: dict, size: float, rtol: float = 1e-12) -> dict:
    """Level 1 of a serial and a parallel run compared, as :func:`mpi_match`: ``placed``, the
    boundary vertices as placement put them (they depend on the coarse level's records only),
    and ``final``, after smoothing and repair; of the final vertices farther than ``rtol`` of the
    size apart, ``repaired``: those the repair moved (slid on the geometry or pulled back) in
    either run, and ``unrepaired``: the others.  The repair works on cells, which
    ``dolfinx.mesh.refine`` may split otherwise under MPI (among tied longest edges its choice
    depends on the partition), so a vertex it moves can end elsewhere in either run."""
    from scipy.spatial import cKDTree

    out = {"placed": mpi_match(serial.get("placed", []), par.get("placed", []), size),
           "final": np.inf, "repaired": 0, "unrepaired": 0}
    S, B = np.asarray(serial["boundary"]), np.asarray(par["boundary"])
    if S.shape != B.shape or len(S) == 0:
        return out
    d, i = cKDTree(S).query(B)
    if np.unique(i).size != len(i):
        return out
    out["final"] = float(d.max()) / size
    off = d > rtol * size
    rep = np.zeros(int(off.sum()), dtype=bool)
    for run, pts in ((serial, S[i[off]]), (par, B[off])):  # each run at its own position
        R = np.asarray(run.get("repaired", [])).reshape(-1, 3)
        if len(R) and len(pts):
            rep |= cKDTree(R).query(pts)[0] <= rtol * size
    out["repaired"], out["unrepaired"] = int(rep.sum()), int((~rep).sum())
    return out


# ----------------------------------------------------------------------------------------------
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--corpus", default=CORPUS, help="the corpus folder (with its manifest.json)")
    ap.add_argument("--files", help="comma-separated corpus file names (default: all in the manifest)")
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--no-snap", action="store_true", help="read, verify and closest points only")
    ap.add_argument("--timeout", type=float, default=1200.0, help="seconds per snapping run")
    ap.add_argument("--case", help=argparse.SUPPRESS)
    ap.add_argument("--levels", type=int, default=2, help=argparse.SUPPRESS)
    ap.add_argument("--json", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        snap_case(args.case, args.levels, args.json)
        return
    rows = manifest(args.corpus)
    if args.files:
        wanted = set(args.files.split(","))
        rows = [r for r in rows if r["file"] in wanted]
    t0 = time.perf_counter()
    first_file = next(r["file"] for r in rows if not r["file"].endswith(".gz"))
    CadGeometry.from_file(os.path.join(args.corpus, first_file))  # starts the reader process
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    CadGeometry.from_file(os.path.join(args.corpus, first_file))
    start = first - (time.perf_counter() - t0)
    print(f"reader process start (once per process): {start:.2f} s")
    passed = 0
    for r in rows:
        with plain_file(Path(args.corpus) / r["file"]) as path:  # a .gz file through a plain copy
            rng = np.random.default_rng(zlib.crc32(r["file"].encode()))  # the file's own points
            ok, notes = _file_row(str(path), r, args, rng)
        passed += ok
        print(f"  -> {'ok' if ok else 'FAIL'}: {notes}", flush=True)
    print(f"cad_corpus_ok {passed}/{len(rows)}")


def _file_row(path: str, r: dict, args, rng) -> tuple[bool, str]:
    """Print one file's figures; whether it passes and why not."""
    name = r["file"]
    kinds = face_kinds(occ_import(path))
    print(f"\n{name} ({r.get('system', '?')}, {r.get('format', '?')}): {sum(kinds.values())} faces "
          + ", ".join(f"{k} {n}" for k, n in kinds.items()), flush=True)
    try:
        geo = CadGeometry.from_file(path)
    except Exception as e:
        print(f"  read: refused: {type(e).__name__}: {e}")
        return "face" in str(e) or "surface" in str(e), "refused at read (the error must name the face)"
    t = read_times(path)
    limit = 2 * t["occ"] if t["occ"] >= 0.1 else t["occ"] + 0.3
    read_ok = t["ours"] <= limit
    verify_ok = t["verify"] <= t["occ"]
    print(f"  read {t['ours']:.3f} s (in process {t['ours_inproc']:.3f} s), OCC import {t['occ']:.3f} s: "
          f"ratio {t['ours'] / t['occ']:.2f} ({'met' if read_ok else 'NOT met'}: limit {limit:.3f} s); "
          f"verify {t['verify']:.3f} s of it: {t['verify'] / t['occ']:.2f} x the import "
          f"({'met' if verify_ok else 'NOT met'}: limit 1x)")
    print(f"  model: {geo.model.summary() if geo.model is not None else '-'}")
    cp = closest_agreement(path, geo, args.points, rng)
    cp_ok = cp["agree"] >= 0.999 and cp["wrong"] == 0
    print(f"  closest points: {cp['points']} points, found {100 * cp['found']:.1f} %, agree with OCC "
          f"{100 * cp['agree']:.2f} %, wrong {cp['wrong']}, nearer than OCC {cp['nearer']} "
          f"(OCC's reference from the faces split at C0 lines: {cp['split']})")
    notes = [] if read_ok else ["read time"]
    notes += [] if verify_ok else ["verify time"]
    read_ok &= verify_ok
    notes += [] if cp_ok else ["closest points"]
    if args.no_snap:
        return read_ok and cp_ok, ", ".join(notes) or "read and closest points"
    snap_ok, why = _snap_rows(path, geo.size, args.timeout)
    return read_ok and cp_ok and snap_ok, ", ".join([*notes, why])


def _snap_rows(path: str, size: float, timeout: float) -> tuple[bool, str]:
    serial = run_case(path, 2, 1, timeout)
    if serial["levels"] == [] and "error" in serial:
        print(f"  snapping: refused: {serial['error']}")
        return "try" in serial["error"], "refused (the error must say what to try)"
    par = run_case(path, 1, 2, timeout)
    retry = f", gmsh retry: {serial['meshed_with']}" if serial.get("meshed_with") else ""
    print(f"  coarse mesh {serial.get('cells0', 0)} cells ({serial.get('mesh_seconds', 0):.1f} s{retry})")
    ok = "error" not in serial and "error" not in par and len(serial["levels"]) == 2
    for k, lv in enumerate(serial["levels"], 1):
        tm = lv["times"]
        ratio = sum(tm.get(s, 0.0) for s in OVERHEAD) / max(tm["refine"], 1e-12)
        print(f"  level {k}: {lv['cells']} cells, short {lv['short']}, max dist/size {lv['dist']:.1e} "
              f"({lv['in_gaps']} vertices farther than 1e-9 of it but on a CAD edge within its tolerance, "
              f"{lv.get('where_faces_meet', 0)} where the faces' surfaces meet within an edge's tolerance, "
              f"{lv['beyond_tolerance']} beyond), refine {tm['refine']:.2f} s, overhead/refine {ratio:.2f}")
        ok &= lv["short"] == 0 and lv["beyond_tolerance"] == 0
    for res, what in ((serial, "serial"), (par, "mpiexec -n 2")):
        if "error" in res:
            print(f"  {what}: {res['error']}")
    m = mpi_split(serial["levels"][0], par["levels"][0], size) if serial["levels"] and par["levels"] else \
        {"placed": np.inf, "final": np.inf, "repaired": 0, "unrepaired": 0}
    print(f"  mpiexec -n 2, level 1: boundary vertices match serial to {m['final']:.1e} of the size; as placed "
          f"(before smoothing and repair) to {m['placed']:.1e}; {m['repaired'] + m['unrepaired']} farther than "
          f"1e-12 of it apart, {m['repaired']} of them moved by the repair in either run, {m['unrepaired']} not")
    ok &= m["final"] <= 1e-12
    return ok, "snapped" if ok else "snapping"


if __name__ == "__main__":
    main()
