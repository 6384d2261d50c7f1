"""CAD mode on the machined parts of meshes/parts.py: reading, attach, place, projection, snapping.

For every part (STEP, and IGES: faces-only where gmsh re-solidifies it, else
B-rep IGES) the script measures, side by side in one process:

* read: ``CadGeometry.from_file`` in this process (OpenCASCADE read, B-rep
  conversion, trimming loops) against OpenCASCADE's own import of the same
  file (``STEPControl_Reader`` / ``IGESControl_Reader``: ``ReadFile`` +
  ``TransferRoots`` + ``OneShape``), called in turn for 7 rounds, the least
  time of each side: the ratio of the CPU times (``time.process_time``: the
  work done, what the target <= 2 is judged on; on a shared machine the wall
  clock also counts the time other processes hold the cores) and of the wall
  times;
* attach: ``CadGeometry.attach`` of the coarse gmsh mesh's boundary facets, per
  distinct boundary vertex, with gmsh's classification (``mesh_cad``: known
  faces and (u, v) seeds; target < 20 us; best of 50 calls: a call on the
  smallest parts takes ~0.3 ms, which a busy spell of a shared machine
  doubles for several calls in a row (best of 10 gave 11-22 us/vertex on the
  same 25-vertex part in consecutive runs), and the first calls in a process
  also warm numpy's and the CPU's caches) and without (global search; one call,
  which includes building the search grid and its KD-tree);
* place: the ``place`` stage of ``Snapper.refine`` per snapped point, two
  uniform levels;
* snapping: after the two levels, every snapped vertex's distance from OCC's
  closest point on its own face (relative to the model size; must be
  <= 1e-9) and the inverted cells (must be 0).

Then projection against OpenCASCADE (gmsh's ``getClosestPoint``, batched, on
the same surface of the same file): 1e5 points near each analytic face type
(plane, cylinder, cone, sphere, torus; target >= 10x faster) and near a
B-spline face (the lofted blade; seeded Newton as in a refinement; target
>= 100x).

Last line: ``cad_parts_ok <passed>/<total>``: one check per part and format
(snapped vertices on their faces, none left short, 0 inverted cells) and one per target above.

A second table gives the same read and attach figures on files with many
faces (a plate with 10 x 10 through-holes; a 275-face machined block with
fillets, counterbored and chamfered holes, a B-spline slot and bosses; both
built here) and on a fine mesh of ``plate``, where per-vertex costs are not
dominated by fixed ones.

What the projection comparison measures: both sides compute the closest point
on the face's underlying surface, without the trimming test (ours: the
closed form of :mod:`nagata_snap.cad.surfaces`, or seeded Newton on NURBS;
gmsh's ``getClosestPoint`` on a CAD face: OpenCASCADE's
``GeomAPI_ProjectPointOnSurf`` on the surface restricted to the face's
parameter box), for the same 1e5 points (best of 5 calls on both sides,
interleaved; on the NURBS face OCC gets the first tenth of the points: its
time per point does not depend on n).

    python benchmarks/cad_parts.py [--parts a,b] [--points 100000] [--no-large]
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
sys.path[:0] = [os.path.join(HERE, "..", "meshes"), os.path.join(HERE, "..")]
import gmsh  # noqa: E402
import parts  # noqa: E402
from occ_reference import OccShape  # noqa: E402

from nagata_snap import Snapper  # noqa: E402
from nagata_snap.cad import CadGeometry, mesh_cad  # noqa: E402
from nagata_snap.cad.projection import project_points  # noqa: E402
from nagata_snap.mesh import bisect  # noqa: E402
from nagata_snap.meshing import gmsh_session, import_cad  # noqa: E402
from nagata_snap.smoothing.quality import inverted_cells  # noqa: E402
from nagata_snap.mesh.records import Records  # noqa: E402


#: part -> (gmsh size factor, curvature): the sizes of tests/test_cad_parts.py (coarse, but fine
#: enough that the current smoother needs no partial moves: coarser, the thin blade and the torus
#: groove leave vertices short of the CAD, issue 12)
MESH = {"box_fillet_chamfer": (0.4, 4), "plate": (0.3, 8), "revolved": (0.6, 10),
        "extruded_bspline": (0.4, 4), "lofted_blade": (0.5, 4), "crossing_cylinders": (0.4, 4),
        "seamed": (0.4, 4), "assembly": (0.3, 6), "profile_2d": (0.1, 12), "plate_holes_2d": (0.1, 12)}


def read_seconds(path: str, rounds: int = 7) -> tuple[tuple[float, float], tuple[float, float]]:
    """OpenCASCADE's own import of ``path`` (ReadFile + TransferRoots + OneShape) and
    ``CadGeometry.from_file(path, isolate=False)`` in this process, called in turn for
    ``rounds`` rounds: ``((occ wall, occ cpu), (ours wall, ours cpu))``, each the least of its
    rounds (CPU: ``time.process_time``).  Interleaved, so that both sides see the same load."""
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    def occ() -> None:
        r = STEPControl_Reader() if path.endswith((".step", ".stp")) else IGESControl_Reader()
        r.ReadFile(path)
        r.TransferRoots()
        r.OneShape()

    best = np.full((2, 2), np.inf)
    for _ in range(rounds):
        for k, f in enumerate((occ, lambda: CadGeometry.from_file(path, isolate=False))):
            t0, c0 = time.perf_counter(), time.process_time()
            f()
            best[k] = np.minimum(best[k], (time.perf_counter() - t0, time.process_time() - c0))
    return (float(best[0, 0]), float(best[0, 1])), (float(best[1, 0]), float(best[1, 1]))


def attach_timing(cm, geo) -> tuple[float, float, int]:
    """us per distinct boundary vertex: attach with the mesh hints (best of 50), and by global
    search (the first call)."""
    gids = np.asarray(cm.mesh.geometry.input_global_indices, dtype=np.int64)[cm.facets.nodes]
    x = cm.mesh.geometry.x[cm.facets.nodes]
    nv = len(np.unique(gids))

    def seconds(calls: int) -> float:
        best = np.inf
        for _ in range(calls):
            t0 = time.perf_counter()
            geo.attach(x, nodes=gids)
            best = min(best, time.perf_counter() - t0)
        return best

    hinted = seconds(50)
    hints, geo._hints = geo._hints, None
    search = seconds(1)
    geo._hints = hints
    return 1e6 * hinted / nv, 1e6 * search / nv, nv


def snap_part(name: str, fmt: str, path: str) -> dict:
    sf, cu = MESH[name]
    cm, geo = mesh_cad(path, MPI.COMM_SELF, size_factor=sf, curvature=cu)
    t_hint, t_search, nv = attach_timing(cm, geo)
    snapper = Snapper(cm.mesh, cm.facet_tags, geo)
    mesh, occ = cm.mesh, OccShape(path, cm.unit or "MM")
    tdim = mesh.topology.dim
    place_us, worst, inverted = [], 0.0, 0
    for _ in range(2):
        prev = mesh
        mesh, *_, rep = snapper.refine(mesh)
        place_us.append(1e6 * rep.times["place"] / max(rep.geometry.n_points, 1))
        prev.topology.create_entities(1)
        straight, *_ = bisect.refine(prev, None)  # the snapper's refinement, not snapped
        inverted += inverted_cells(mesh.geometry.x, straight.geometry.x, mesh.geometry.dofmaps[0], tdim).size
    lv = snapper._level
    sel = np.flatnonzero(lv.snapped)
    nodes, root = lv.boundary.nodes[sel], lv.records.root
    _, first = np.unique(np.c_[nodes.ravel(), np.repeat(root, nodes.shape[1])], axis=0, return_index=True)
    P = mesh.geometry.x[nodes].reshape(-1, 3)[first]
    F = np.repeat(root, nodes.shape[1])[first]
    d = occ.face_distance(F, P) if tdim == 3 else occ.edge_distance(geo._curve_edges[F], P)
    worst = float(d.max()) / occ.size
    return {"faces": geo.num_entities, "vertices": nv, "attach_hint": t_hint, "attach_search": t_search,
            "place": place_us[-1], "points": rep.geometry.n_points, "worst": worst,
            "inverted": inverted, "short": rep.partially_moved}


def holes_plate(path: str, n: int = 10) -> None:
    """A 100 x 100 x 5 plate with an ``n x n`` array of through-holes (gmsh's OpenCASCADE), as STEP."""
    with gmsh_session("holes_plate"):
        occ = gmsh.model.occ
        box = occ.addBox(0, 0, 0, 100, 100, 5)
        pitch = 100.0 / n
        holes = [(3, occ.addCylinder(pitch * (i + 0.5), pitch * (j + 0.5), -1, 0, 0, 7, 0.3 * pitch))
                 for i in range(n) for j in range(n)]
        occ.cut([(3, box)], holes)
        occ.synchronize()
        gmsh.write(path)


def bracket(path: str, nx: int = 10, ny: int = 6) -> None:
    """A machined block of 275 faces (gmsh's OpenCASCADE), as STEP: a 200 x 120 x 20 block with
    every edge filleted (cylinders, corner spheres), ``nx x ny`` counterbored holes with a
    chamfer (cylinders, planes, cones), a slot swept along a B-spline and three round bosses."""
    with gmsh_session("bracket"):
        occ = gmsh.model.occ
        L, W, H = 200.0, 120.0, 20.0
        box = occ.addBox(0, 0, 0, L, W, H)
        occ.synchronize()
        body = [(3, occ.fillet([box], [t for _, t in gmsh.model.getEntities(1)], [3.0])[0][1])]
        cutters = []
        for i in range(nx):
            for j in range(ny):
                x, y = 10 + 130 * (i + 0.5) / nx, W * (j + 0.5) / ny
                cutters += [(3, occ.addCylinder(x, y, -1, 0, 0, H + 2, 2.5)),
                            (3, occ.addCylinder(x, y, H - 4, 0, 0, 5, 4.5)),
                            (3, occ.addCone(x, y, H - 0.6, 0, 0, 1.2, 4.5, 5.7))]
        path_pts = [occ.addPoint(150 + 40 * t, 20 + 80 * t + 12 * np.sin(6 * t), H - 8)
                    for t in np.linspace(0, 1, 7)]
        wire = occ.addWire([occ.addBSpline(path_pts)])
        disk = occ.addDisk(150, 20, H - 8, 3.0, 3.0, zAxis=[40, 152, 0])
        cutters += occ.addPipe([(2, disk)], wire)
        occ.remove([(2, disk)], recursive=True)  # the profile, not part of the block
        body, _ = occ.cut(body, cutters)
        bosses = [(3, occ.addCylinder(40 + 60 * k, -8, 10, 0, 8.5, 0, 5.0)) for k in range(3)]
        occ.fuse(body, bosses)
        occ.synchronize()
        gmsh.write(path)


def large_cases(tmp: str) -> list[tuple]:
    """Read ratio and attach per vertex where fixed costs do not dominate.

    Files with many faces (a plate with 10 x 10 holes, 106 faces; a machined
    block of 275, :func:`bracket`) meshed coarsely, and a fine mesh (about
    1.7e4 boundary vertices) of ``plate``.
    """
    rows = []
    holes = os.path.join(tmp, "plate_100_holes.step")
    holes_plate(holes)
    block = os.path.join(tmp, "bracket.step")
    bracket(block)
    plate = str(parts.write_part("plate", tmp, ("step",))["step"])
    for name, path, sf, cu in (("plate_100_holes", holes, 0.05, 8), ("bracket", block, 0.1, 8),
                               ("plate (fine)", plate, 0.01, 16)):
        (occ_t, occ_cpu), (our_t, our_cpu) = read_seconds(path)
        t0 = time.perf_counter()
        cm, geo = mesh_cad(path, MPI.COMM_SELF, size_factor=sf, curvature=cu)
        t_mesh = time.perf_counter() - t0
        t_hint, t_search, nv = attach_timing(cm, geo)
        rows.append((name, geo.num_entities, our_t, occ_t, our_cpu / occ_cpu, nv, t_hint, t_search, t_mesh))
    return rows


def projection_speed(path: str, kinds: set[str], n: int, rng) -> list[tuple]:
    """Our projection vs gmsh/OCC getClosestPoint on faces of the given kinds (same surfaces)."""
    geo = CadGeometry.from_file(path, isolate=False)
    rows = []
    with gmsh_session("projection"):
        import_cad(path)
        tags = [t for _, t in gmsh.model.getEntities(2)]
        for e, face in enumerate(geo.model.faces):
            s = face.surface
            kind = getattr(s, "kind", "nurbs")
            if kind not in kinds:
                continue
            kinds.discard(kind)
            # points near the face: on it, moved off along the normal
            lo, hi = s.bounds[:, 0], s.bounds[:, 1]
            uv = lo + (hi - lo) * rng.random((n, 2))
            S = geo.evaluate(np.zeros(n, dtype=np.int64) + e, uv[:, None, :])[:, 0]
            N = geo.vertex_normals(Records(np.full(n, e), uv[:, None, :]))[:, 0]
            X = S + 1e-3 * geo.size * rng.normal(size=(n, 1)) * N
            # the gmsh face on which these points lie
            tag = min(tags, key=lambda t: np.abs(
                np.reshape(gmsh.model.getClosestPoint(2, t, S[:20].ravel())[0], (-1, 3)) - S[:20]).max())
            seeds = uv + 1e-3 * (hi - lo) * rng.normal(size=uv.shape)  # refinement-like seeds
            # best of 5 on both sides, calls interleaved: one run is at the mercy of the
            # scheduler (consecutive calls of ours on the NURBS face take 1.6-2.7 us/point on a
            # shared machine).  OCC needs ~200-400 us/point on a NURBS, so there it gets the
            # first tenth of the points (its time per point does not depend on n)
            m = n // 10 if kind == "nurbs" else n
            ours = theirs = np.inf
            for _ in range(5):
                t0 = time.perf_counter()
                res = project_points(s, X, seeds)
                ours = min(ours, time.perf_counter() - t0)
                t0 = time.perf_counter()
                cp, _ = gmsh.model.getClosestPoint(2, tag, X[:m].ravel())
                theirs = min(theirs, time.perf_counter() - t0)
            cp = np.reshape(cp, (-1, 3))
            agree = np.abs(np.linalg.norm(cp - X[:m], axis=1) - res.distance[:m]).max() / geo.size
            us_ours, us_theirs = 1e6 * ours / n, 1e6 * theirs / m
            rows.append((kind, us_ours, us_theirs, us_theirs / us_ours, agree))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parts", default=",".join(MESH))
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--no-large", action="store_true", help="skip the larger file and mesh")
    args = ap.parse_args()
    names = args.parts.split(",")
    tmp = tempfile.mkdtemp(prefix="cad_parts_")
    rng = np.random.default_rng(0)
    passed = total = 0
    read_ratios, cpu_ratios, attach_hint = [], [], []
    print(f"{'part':20s} {'format':9s} {'faces':>5s} {'read':>7s} {'OCC':>7s} {'ratio':>6s} "
          f"{'cpu':>7s} {'OCC cpu':>7s} {'ratio':>6s} "
          f"{'verts':>6s} {'att.gmsh':>9s} {'att.search':>10s} {'place':>7s} "
          f"{'dist/size':>9s} {'inv':>4s} {'short':>5s}")
    print(f"{'':20s} {'':9s} {'':5s} {'[s]':>7s} {'[s]':>7s} {'':6s} {'[s]':>7s} {'[s]':>7s} {'':6s} {'':6s} "
          f"{'[us/v]':>9s} {'[us/v]':>10s} {'[us/pt]':>7s} {'':9s} {'':4s} {'':5s}")
    for name in names:
        part = parts.PARTS[name]
        fmts = ["step", "iges" if part.iges_faces_solid else "iges_brep"]
        files = parts.write_part(name, tmp, tuple(fmts))
        for fmt in fmts:
            path = str(files[fmt])
            (occ_t, occ_c), (our_t, our_c) = read_seconds(path)
            r = snap_part(name, fmt, path)
            ok = r["worst"] <= 1e-9 and r["inverted"] == 0 and r["short"] == 0
            passed += ok
            total += 1
            read_ratios.append(our_t / occ_t)
            cpu_ratios.append(our_c / occ_c)
            attach_hint.append(r["attach_hint"])
            print(f"{name:20s} {fmt:9s} {r['faces']:5d} {our_t:7.3f} {occ_t:7.3f} {our_t / occ_t:6.2f} "
                  f"{our_c:7.3f} {occ_c:7.3f} {our_c / occ_c:6.2f} "
                  f"{r['vertices']:6d} {r['attach_hint']:9.1f} {r['attach_search']:10.1f} "
                  f"{r['place']:7.2f} {r['worst']:9.1e} {r['inverted']:4d} {r['short']:5d}{'' if ok else '  FAIL'}",
                  flush=True)
    print(f"read + convert / OCC import, CPU time: median {float(np.median(cpu_ratios)):.2f}, max "
          f"{max(cpu_ratios):.2f} (target <= 2: {'met' if max(cpu_ratios) <= 2 else 'not met'}); wall time: "
          f"median {float(np.median(read_ratios)):.2f}, max {max(read_ratios):.2f}")
    total += 2
    passed += max(cpu_ratios) <= 2
    passed += max(attach_hint) < 20
    print(f"attach with gmsh's classification: max {max(attach_hint):.1f} us/vertex (target < 20)")

    print("\nlarger files and meshes (figures only; the targets above are judged on the parts):")
    print(f"{'case':20s} {'faces':>5s} {'read':>7s} {'OCC':>7s} {'ratio':>6s} {'cpu':>6s} {'verts':>6s} "
          f"{'att.gmsh':>9s} {'att.search':>10s} {'gmsh mesh':>9s}")
    for name, nfaces, our_t, occ_t, cpu_ratio, nv, t_hint, t_search, t_mesh in (
            [] if args.no_large else large_cases(tmp)):
        print(f"{name:20s} {nfaces:5d} {our_t:7.3f} {occ_t:7.3f} {our_t / occ_t:6.2f} {cpu_ratio:6.2f} {nv:6d} "
              f"{t_hint:9.1f} {t_search:10.1f} {t_mesh:8.1f}s", flush=True)

    print(f"\n{'surface':10s} {'ours':>9s} {'OCC':>9s} {'speedup':>8s} {'agree/size':>10s}")
    print(f"{'':10s} {'[us/pt]':>9s} {'[us/pt]':>9s}")
    rows = []
    for name, kinds in (("plate", {"plane"}), ("revolved", {"cylinder", "cone", "sphere", "torus"}),
                        ("lofted_blade", {"nurbs"})):
        path = str(parts.write_part(name, tmp, ("step",))["step"])
        rows += projection_speed(path, set(kinds), args.points, rng)
    for kind, ours, theirs, speed, agree in rows:
        target = 100 if kind == "nurbs" else 10
        total += 1
        passed += speed >= target
        print(f"{kind:10s} {ours:9.3f} {theirs:9.3f} {speed:8.1f} {agree:10.1e}   (target >= {target}x)")
    print(f"cad_parts_ok {passed}/{total}")


if __name__ == "__main__":
    main()
