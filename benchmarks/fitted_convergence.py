"""Fitted surface (issue 30) against Nagata's on the same meshes, estimated normals, no CAD.

Irregular gmsh meshes (``MeshSizeMin = MeshSizeMax = h``, h = 0.2, 0.1, ...
down to ``--hmin``) of the torus R = 1, r = 0.4, the ellipsoid 1 x 0.7 x 0.5
and the closed cylinder R = 1, height 1 with sharp rims (``crease_angle =
80``, as :mod:`benchmarks.nagata_convergence`), the whole surface of each.
For each mesh: the largest distance from the exact surface of the Nagata
patches and of :class:`~nagata_snap.FittedGeometry` (degree ``--degree``,
default 4; also degree 3), sampled on a barycentric grid of every facet
(12 intervals per edge), their observed orders (log2 of successive ratios),
the ratio fitted / Nagata, the cylinder's rim error (largest distance of the
samples on the rim edges from the exact circles), the fits' degrees, the
points whose departure from the facet was bounded, and the set-up and
placement times (geometry construction; evaluating all facets' grid
points, as a refinement level's placement does for its new vertices).

2D: polygons inscribed in the ellipse 1 x 0.5 (unequal segments).

Parts (``--parts``, default ``plate_filleted,plate`` of ``meshes/parts.py`` and
two machined parts of the corpus, the CAx-IF ``io1`` part and the NEMA-17
bracket; STEP/IGES files are taken too), meshed by
:func:`nagata_snap.meshing.mesh_cad_file` (curvature sizing 12 per 2 pi, one
tag per CAD face): the largest distance to the CAD (OpenCASCADE's closest
point on each facet's own face, through gmsh) of both surfaces over the
coarse mesh (6 intervals per edge), over the model size, the ratio fitted /
Nagata, the faces where the fitted surface's largest distance sits, the
points whose departure was bounded, and the set-up + placement seconds (best
of 3) of both; with ``--part-levels N`` also ``N`` uniform levels snapped
with each surface: the largest distance of the vertices on curved faces from
their face and the vertices left short at each level.  Line
``fitted_over_nagata_parts <part> <ratio> ...``.  The cylinder's line
``cylinder_order <finest pair> rim_distance_max <largest rim distance over
all h>``; ``time_ratio <surface> <fitted / Nagata set-up + placement at h =
0.05, best of 3 alternating runs>``.

Last lines: ``fitted_order_estimated <min finest-pair order over the torus and
the ellipsoid>`` and ``fitted_over_nagata <max fitted / Nagata error ratio at
h = 0.05 over the torus and the ellipsoid>`` (the cylinder's is in its table).

Usage: ``python benchmarks/fitted_convergence.py [--hmin 0.025] [--surfaces torus,ellipsoid,cylinder]
[--degree 4] [--parts plate_filleted,plate,FILE] [--part-levels 2]`` (``--parts ""``: none; the
default, down to 0.025 on the three surfaces, takes about 4 minutes).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))

from surfaces import barycentric_grid, ellipse_polygon, gmsh_surface, nagata_surface_error

from nagata_snap import FittedGeometry, NagataGeometry

SURFACES = ("torus", "ellipsoid", "cylinder")

#: the default parts: two of meshes/parts.py and two machined parts of the corpus written by CAD systems
CORPUS = os.path.join(os.path.dirname(__file__), "..", "meshes", "corpus")
PARTS = ("plate_filleted", "plate", os.path.join(CORPUS, "io1_part_cocreate_cax_if.stp"),
         os.path.join(CORPUS, "nema17_bracket_build123d.step"))


def max_distance(geo, dist, per_edge: int = 12) -> tuple[float, float]:
    """Largest ``dist`` of the sampled surface, and seconds spent evaluating it."""
    g = barycentric_grid(3, per_edge)
    err, dt = 0.0, 0.0
    for lo in range(0, geo.num_patches, 4000):  # bounded memory
        s = np.arange(lo, min(lo + 4000, geo.num_patches))
        t0 = time.perf_counter()
        x = geo.evaluate(s, np.broadcast_to(g, (len(s), *g.shape)))
        dt += time.perf_counter() - t0
        err = max(err, float(dist(x).max()))
    return err, dt


def rim_error(geo, per_edge: int = 12) -> float:
    """Largest distance from the exact rim circles (R = 1, z = +-0.5) of samples on the crease edges."""
    cr = np.flatnonzero(geo.crease)
    rf, rv, vid = geo.corners.ridge_facets[cr, 0], geo.corners.ridge_vertices[cr], geo.corners.vertex
    t = np.linspace(0.0, 1.0, per_edge + 1)
    lam = np.zeros((len(cr), len(t), 3))
    for k, w in ((0, 1.0 - t), (1, t)):
        lam[np.arange(len(cr)), :, np.argmax(vid[rf] == rv[:, k, None], axis=1)] = w
    x = geo.evaluate(rf, lam)
    return float(np.hypot(np.hypot(x[..., 0], x[..., 1]) - 1.0, np.abs(x[..., 2]) - 0.5).max())


def study(kind: str, hs: list[float], degrees: tuple[int, ...]) -> list[dict]:
    rows = []
    for h in hs:
        p, t, exact, tags = gmsh_surface(kind, h)
        row: dict = {"h": h, "facets": len(t)}
        t0 = time.perf_counter()
        nag = NagataGeometry.from_surface(p, t, tags, crease_angle=80)
        row["nagata_setup"] = time.perf_counter() - t0
        row["nagata"], row["nagata_place"] = max_distance(nag, exact.distance)
        if kind == "cylinder":
            row["nagata_rim"] = rim_error(nag)
        for d in degrees:
            t0 = time.perf_counter()
            fit = FittedGeometry.from_surface(p, t, tags, crease_angle=80, degree=d)
            row[f"setup{d}"] = time.perf_counter() - t0
            row[f"fit{d}"], row[f"place{d}"] = max_distance(fit, exact.distance)
            row[f"clipped{d}"] = fit.n_clipped
            row[f"summary{d}"] = fit.fit_summary()
            if kind == "cylinder":
                row[f"rim{d}"] = rim_error(fit)
        rows.append(row)
        print(f"  {kind} h = {h}: {len(t)} triangles", flush=True)
    return rows


def orders(values: list[float]) -> list[float]:
    return [float(np.log2(a / b)) for a, b in itertools.pairwise(values)]


def print_table(kind: str, rows: list[dict], degrees: tuple[int, ...]) -> None:
    print(f"\n{kind}: largest distance from the exact surface (order: log2 of successive ratios)")
    head = f"{'h':>7} {'facets':>7} {'nagata':>10} {'ord':>5}"
    for d in degrees:
        head += f" | {'fitted p=' + str(d):>11} {'ord':>5} {'/nagata':>7}"
    if kind == "cylinder":
        head += f" | {'rim nagata':>10} {'ord':>5}" + "".join(f" {'rim p=' + str(d):>10} {'ord':>5}" for d in degrees)
    print(head)
    on = orders([r["nagata"] for r in rows])
    of = {d: orders([r[f"fit{d}"] for r in rows]) for d in degrees}
    if kind == "cylinder":
        rn = orders([r["nagata_rim"] for r in rows])
        rd = {d: orders([r[f"rim{d}"] for r in rows]) for d in degrees}
    for i, r in enumerate(rows):
        def o(seq, i=i):
            return f"{seq[i - 1]:5.2f}" if i else " " * 5
        line = f"{r['h']:7.4f} {r['facets']:7d} {r['nagata']:10.3e} {o(on)}"
        for d in degrees:
            line += f" | {r[f'fit{d}']:11.3e} {o(of[d])} {r[f'fit{d}'] / r['nagata']:7.3f}"
        if kind == "cylinder":
            line += f" | {r['nagata_rim']:10.3e} {o(rn)}" + "".join(
                f" {r[f'rim{d}']:10.3e} {o(rd[d])}" for d in degrees)
        print(line)
    print("times [s] (set-up, placement of the sampled points): " + "; ".join(
        f"h={r['h']}: nagata {r['nagata_setup']:.2f} + {r['nagata_place']:.2f}, " + ", ".join(
            f"p={d} {r[f'setup{d}']:.2f} + {r[f'place{d}']:.2f}" for d in degrees) for r in rows))
    last = rows[-1]
    print("fits on the finest mesh: " + "; ".join(
        f"{last[f'summary{d}']}, bounded points {last[f'clipped{d}']}" for d in degrees))


def ellipse_study(ns, degrees) -> None:
    print("\n2D: polygons inscribed in the ellipse 1 x 0.5 (unequal segments), largest distance")
    print(f"{'segments':>9} {'nagata':>10} {'ord':>5}" + "".join(f" {'fitted p=' + str(d):>11} {'ord':>5}"
                                                             for d in degrees))
    prev = None
    for n in ns:
        p, s, exact = ellipse_polygon(n)
        e = [nagata_surface_error(NagataGeometry.from_surface(p, s), exact.distance)]
        e += [nagata_surface_error(FittedGeometry.from_surface(p, s, degree=d), exact.distance) for d in degrees]
        print(f"{n:9d}" + "".join(
            f" {v:{10 if j == 0 else 11}.3e} " + (f"{np.log2(prev[j] / v):5.2f}" if prev else " " * 5)
            for j, v in enumerate(e)))
        prev = e


def time_ratio(kind: str, h: float, degree: int, reps: int = 3) -> tuple[float, float, float]:
    """Set-up + placement seconds of Nagata and the fitted surface on one mesh, the best of ``reps``
    alternating runs each (a shared machine's load only adds), and their ratio."""
    p, t, exact, tags = gmsh_surface(kind, h)
    best = [np.inf, np.inf]
    for _ in range(reps):
        for i, make in enumerate((lambda: NagataGeometry.from_surface(p, t, tags, crease_angle=80),
                                  lambda: FittedGeometry.from_surface(p, t, tags, crease_angle=80, degree=degree))):
            t0 = time.perf_counter()
            geo = make()
            setup = time.perf_counter() - t0
            best[i] = min(best[i], setup + max_distance(geo, exact.distance)[1])
    return best[0], best[1], best[1] / best[0]


#: a distance above this fraction of the model size is a jump of gmsh's closest point off the face
#: (``occ_reference.gmsh_face_distance``): measured against the neighbouring faces too
JUMP = 1e-3


def part_distances(geo, size: float, per_edge: int = 6) -> np.ndarray:
    """``(F,)`` largest distance of each coarse facet's samples from its own CAD face (current gmsh model;
    a face's neighbours where that exceeds ``JUMP`` of the model ``size``)."""
    from occ_reference import gmsh_face_distance

    g = barycentric_grid(3, per_edge)
    x = geo.evaluate(np.arange(geo.num_patches), np.broadcast_to(g, (geo.num_patches, *g.shape)))
    d = np.zeros(geo.num_patches)
    for tag in np.unique(geo.tag):
        s = np.flatnonzero(geo.tag == tag)
        d[s] = gmsh_face_distance(int(tag), x[s].reshape(-1, 3), JUMP * size).reshape(len(s), -1).max(axis=1)
    return d


def snap_levels(cm, geo, levels: int, faces: list[int]) -> tuple[float, list[int], int]:
    """``levels`` uniform levels snapped onto ``geo``: the largest distance of the last level's vertices on the
    curved ``faces`` from their CAD face (over the model size), the vertices left short at each level, and
    the cells of the last level."""
    from plate_normals import face_distances

    from nagata_snap import Snapper

    snapper = Snapper(cm.mesh, cm.facet_tags, geo)
    mesh, ft, short = cm.mesh, cm.facet_tags, []
    for _ in range(levels):
        mesh, ft, _, _, report = snapper.refine(mesh)
        short.append(int(report.partially_moved))
    d = face_distances(mesh, ft, faces, JUMP * cm.model_size)
    return float(d.max()) / cm.model_size, short, mesh.topology.index_map(3).size_global


def part_study(names: list[str], degree: int, levels: int = 0) -> dict[str, float]:
    """Fitted against Nagata over the coarse meshes of ``names`` (parts of ``meshes/parts.py`` or STEP/IGES
    files): prints a table, returns the ratios.  ``levels``: also snap that many uniform levels with each."""
    import tempfile

    import gmsh
    import parts
    from mpi4py import MPI
    from occ_reference import gmsh_curved_faces

    from nagata_snap.meshing import gmsh_session, import_cad, mesh_cad_file

    print(f"\nparts (coarse mesh, curvature 12): largest distance to the CAD / model size, degree {degree}")
    print(f"{'part':>16} {'faces':>5} {'facets':>6} {'nagata':>10} {'fitted':>10} {'/nagata':>7}  worst faces (fitted)")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in names:
            path = name if os.path.isfile(name) else parts.write_part(name, tmp, formats=("step",))["step"]
            label = os.path.basename(name).split(".")[0][:16]
            with gmsh_session(label):
                import_cad(path)
                cm = mesh_cad_file(path, MPI.COMM_SELF, curvature=12)
                nag = NagataGeometry(cm.mesh, cm.facet_tags)
                fit = FittedGeometry(cm.mesh, cm.facet_tags, degree=degree)
                dn, df = part_distances(nag, cm.model_size), part_distances(fit, cm.model_size)
                g = barycentric_grid(3, 6)
                lam = np.broadcast_to(g, (fit.num_patches, *g.shape))
                best = [np.inf, np.inf]
                for _ in range(3):
                    for i, cls in enumerate((NagataGeometry, FittedGeometry)):
                        t0 = time.perf_counter()
                        cls(cm.mesh, cm.facet_tags).evaluate(np.arange(fit.num_patches), lam)
                        best[i] = min(best[i], time.perf_counter() - t0)
                worst = sorted({(float(df[fit.tag == t].max()), int(t)) for t in np.unique(fit.tag)}, reverse=True)[:3]
                where = ", ".join(f"{t} {gmsh.model.getType(2, t)} {v / cm.model_size:.1e}" for v, t in worst)
                out[label] = df.max() / dn.max()
                print(f"{label:>16} {len(gmsh.model.getEntities(2)):5d} {fit.num_patches:6d} "
                      f"{dn.max() / cm.model_size:10.3e} {df.max() / cm.model_size:10.3e} {out[label]:7.3f}  {where}")
                print(f"{'':>16} {fit.fit_summary()}; bounded points {fit.n_clipped}; set-up + placement nagata "
                      f"{best[0]:.2f} s, fitted {best[1]:.2f} s ({best[1] / best[0]:.2f}x)")
                if levels:
                    faces = gmsh_curved_faces()
                    (a, sa, cells), (b, sb, _) = (snap_levels(cm, geo, levels, faces) for geo in (nag, fit))
                    print(f"{'':>16} {levels} uniform levels snapped ({cells} cells), vertices on the {len(faces)} "
                          f"curved faces: nagata {a:.3e}, fitted {b:.3e} ({b / a:.3f}x); vertices short per level "
                          f"nagata {sa}, fitted {sb}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hmin", type=float, default=0.025, help="finest gmsh mesh size (from 0.2, halving)")
    ap.add_argument("--surfaces", default=",".join(SURFACES), help="comma-separated subset of " + ",".join(SURFACES))
    ap.add_argument("--degree", type=int, default=4, help="fit degree (degree 3 is shown beside it)")
    ap.add_argument("--parts", default=",".join(PARTS),
                    help="comma-separated parts of meshes/parts.py or STEP/IGES files")
    ap.add_argument("--part-levels", type=int, default=0,
                    help="also snap the parts through this many uniform levels with each surface")
    args = ap.parse_args()
    hs = [0.2]
    while hs[-1] / 2 >= args.hmin * (1 - 1e-9):
        hs.append(hs[-1] / 2)
    degrees = tuple(sorted({args.degree, 3}, reverse=True))
    surfaces = [k for k in args.surfaces.split(",") if k]
    print("meshing and fitting:")
    res = {kind: study(kind, hs, degrees) for kind in surfaces}
    for kind in surfaces:
        print_table(kind, res[kind], degrees)
    ellipse_study((48, 96, 192, 384), degrees)
    if surfaces and 0.05 in [round(h, 6) for h in hs]:
        print("\nset-up + placement at h = 0.05, best of 3 alternating runs [s]:")
        tr = {k: time_ratio(k, 0.05, args.degree) for k in surfaces}
        for k, (a, b, r) in tr.items():
            print(f"  {k}: nagata {a:.2f}, fitted {b:.2f}, ratio {r:.2f}")
        print("time_ratio " + " ".join(f"{k} {r:.2f}" for k, (_, _, r) in tr.items()))
    if args.parts:
        ratios = part_study(args.parts.split(","), args.degree, args.part_levels)
        print("fitted_over_nagata_parts " + " ".join(f"{k} {v:.3f}" for k, v in ratios.items()))
    if "cylinder" in surfaces and len(hs) > 1:
        cyl = res["cylinder"]
        print(f"cylinder_order {orders([r[f'fit{args.degree}'] for r in cyl])[-1]:.3f} "
              f"rim_distance_max {max(r[f'rim{args.degree}'] for r in cyl):.3e} (over all h)")
    d = args.degree
    smooth = [k for k in surfaces if k in ("torus", "ellipsoid")]
    if smooth and len(hs) > 1:
        print(f"\nfitted_order_estimated {min(orders([r[f'fit{d}'] for r in res[k]])[-1] for k in smooth):.3f}")
    at = [r for k in smooth for r in res[k] if abs(r["h"] - 0.05) < 1e-9]
    if at:
        print(f"fitted_over_nagata {max(r[f'fit{d}'] / r['nagata'] for r in at):.3f}")


if __name__ == "__main__":
    main()
