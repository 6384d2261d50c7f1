"""Nagata surface error against exact geometry: exact and estimated normals.

1. Exact normals (Nagata 2005, Fig. 9): a unit sphere (octahedron
   subdivisions projected on the sphere) and a closed unit cylinder (R = H = 1,
   sharp rims handled by multiple normals), Nagata patches and flat facets.
2. Estimated normals on irregular gmsh meshes, as a new user gets them:
   ``MeshSizeMin = MeshSizeMax = h`` meshes of one solid (a torus R = 1,
   r = 0.4; an ellipsoid 1 x 0.7 x 0.5; a closed cylinder R = 1, height 1
   with sharp rims), all of its surface snapped, ``crease_angle = 80``.  The
   surface triangles are those gmsh's volume mesh of the solid keeps.  The
   default estimate (``"jet"``, :mod:`nagata_snap.nagata.jets`) next to exact
   normals, then every weighted mean Neto (2010) compares.
3. 2D: polygons inscribed in an ellipse 1 x 0.5 (unequal segments).

Each patch is sampled on a barycentric grid and the largest distance of a
sample from the exact surface is reported.  Observed orders are log2 of
successive error ratios (h halves from one row to the next).

Last lines: ``nagata_order_sphere <order on the finest pair, exact normals>``
and ``nagata_order_estimated <smallest order on the finest pair over the
three surfaces, estimated normals>``.

Usage: ``python benchmarks/nagata_convergence.py [--hmin 0.025] [--surfaces torus,...]
[--schemes jet,mwselr,...]`` (the default runs every surface and estimate
down to h = 0.025; ``--hmin 0.0125 --surfaces torus --schemes jet`` adds the
torus's next level).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))

from surfaces import (  # noqa: E402
    barycentric_grid,
    closed_cylinder,
    ellipse_polygon,
    gmsh_surface,
    nagata_surface_error,
    sphere_octahedron,
)

from nagata_snap import NagataGeometry  # noqa: E402
from nagata_snap.nagata.normals import SCHEMES  # noqa: E402

SURFACES = ("torus", "ellipsoid", "cylinder")


def surface_errors(points, tris, exact, tags=None, snap=None, samples=16):
    """Max distance from the exact surface of sampled Nagata and flat patches."""
    geo = NagataGeometry.from_surface(points, tris, tags, snap, normals=exact.normal)
    lam = np.broadcast_to(barycentric_grid(3, samples), (geo.num_patches, *barycentric_grid(3, samples).shape))
    curved = geo.evaluate(np.arange(geo.num_patches), lam)
    flat = np.einsum("pkv,pvi->pki", lam, geo.x)
    side = geo.snap
    h = np.max(np.linalg.norm(geo.x[side][:, [1, 2, 0]] - geo.x[side], axis=2))
    return h, exact.distance(curved).max(), exact.distance(flat).max()


def orders(errors):
    return [np.log2(a / b) for a, b in zip(errors[:-1], errors[1:])]


def table(name, rows):
    print(f"\n{name}")
    print(f"{'h_max':>10} {'nagata err':>12} {'order':>6} {'flat err':>12} {'order':>6}")
    prev = None
    found = []
    for h, en, ef in rows:
        if prev is None:
            print(f"{h:10.4f} {en:12.4e} {'':>6} {ef:12.4e} {'':>6}")
        else:
            on, of = np.log2(prev[1] / en), np.log2(prev[2] / ef)
            found.append(on)
            print(f"{h:10.4f} {en:12.4e} {on:6.2f} {ef:12.4e} {of:6.2f}")
        prev = (h, en, ef)
    return found


def normal_error_deg(geo, exact, side_only):
    """Largest angle (degrees) between corner normals and exact normals (cylinder: side sector)."""
    n = geo.corner_normal.reshape(-1, 3)
    x = geo.x.reshape(-1, 3)
    sel = np.abs(n[:, 2]) < 0.5 if side_only else slice(None)
    e = exact.normal(x[sel])
    return np.degrees(2 * np.arctan2(np.linalg.norm(n[sel] - e, axis=1), np.linalg.norm(n[sel] + e, axis=1))).max()


def estimated_study(hs, schemes, surfaces=SURFACES):
    """``res[kind][name] = [(h, patch error, normal error deg, seconds), ...]`` per h."""
    res = {}
    for kind in surfaces:
        res[kind] = {name: [] for name in ("exact", "flat", *schemes)}
        for h in hs:
            p, t, exact, _ = gmsh_surface(kind, h)
            for name in ("exact", *schemes):
                t0 = time.perf_counter()
                with warnings.catch_warnings():  # the exact side normal is refused at disc corners
                    warnings.simplefilter("ignore")
                    geo = NagataGeometry.from_surface(p, t, crease_angle=80,
                                                      normals=exact.normal if name == "exact" else name)
                dt = time.perf_counter() - t0
                res[kind][name].append((h, nagata_surface_error(geo, exact.distance, per_edge=16),
                                        normal_error_deg(geo, exact, kind == "cylinder"), dt))
            g = barycentric_grid(3, 16)
            flat = np.einsum("kv,fvi->fki", g, p[t])
            res[kind]["flat"].append((h, float(exact.distance(flat).max()), np.nan, 0.0))
            print(f"  {kind} h = {h}: {len(t)} triangles", flush=True)
    return res


def print_estimated(res, hs):
    print("\nEstimated normals (default jet fit) vs exact normals, gmsh meshes MeshSizeMin = MeshSizeMax = h,"
          " crease_angle = 80")
    print(f"{'surface':>10} {'h':>7} {'estimated':>11} {'exact':>11} {'ratio':>6} "
          f"{'order est':>9} {'order exact':>11} {'flat':>10} {'fit time':>8}")
    for kind in res:
        est, ex, flat = res[kind]["jet"], res[kind]["exact"], res[kind]["flat"]
        oe, ox = orders([r[1] for r in est]), orders([r[1] for r in ex])
        for i, h in enumerate(hs):
            o1 = f"{oe[i - 1]:9.2f}" if i else f"{'':>9}"
            o2 = f"{ox[i - 1]:11.2f}" if i else f"{'':>11}"
            print(f"{kind:>10} {h:7.4f} {est[i][1]:11.3e} {ex[i][1]:11.3e} {est[i][1] / ex[i][1]:6.2f} "
                  f"{o1} {o2} {flat[i][1]:10.3e} {est[i][3]:7.2f}s")


def print_schemes(res, hs, schemes):
    print("\nNormal estimates compared (Neto 2010's weighted means and the jet fit): max normal error (deg) "
          "and Nagata error / exact-normal error, per h")
    for kind in res:
        print(f"  {kind}")
        print(f"{'scheme':>10} " + " ".join(f"{'h=' + format(h, 'g'):>17}" for h in hs) + f" {'order (err)':>12}")
        ex = [r[1] for r in res[kind]["exact"]]
        for name in schemes:
            rows = res[kind][name]
            cells = " ".join(f"{r[2]:8.2e} {r[1] / e:7.2f}x" for r, e in zip(rows, ex))
            print(f"{name:>10} {cells} {orders([r[1] for r in rows])[-1]:12.2f}")


def ellipse_study(ns):
    print("\n2D: polygons inscribed in the ellipse 1 x 0.5 (unequal segments), Nagata curve error")
    print(f"{'segments':>9} {'jet':>11} {'mwselr':>11} {'exact':>11} {'jet/exact':>9} {'mwselr/exact':>12} "
          f"{'order jet':>9} {'order exact':>11}")
    prev = None
    for n in ns:
        p, s, exact = ellipse_polygon(n)
        e = [nagata_surface_error(NagataGeometry.from_surface(p, s, normals=nm), exact.distance)
             for nm in (None, "mwselr", exact.normal)]
        o = f"{np.log2(prev[0] / e[0]):9.2f} {np.log2(prev[2] / e[2]):11.2f}" if prev else f"{'':>9} {'':>11}"
        print(f"{n:9d} {e[0]:11.3e} {e[1]:11.3e} {e[2]:11.3e} {e[0] / e[2]:9.2f} {e[1] / e[2]:12.2f} {o}")
        prev = e


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hmin", type=float, default=0.025, help="finest gmsh mesh size (from 0.2, halving)")
    ap.add_argument("--surfaces", default=",".join(SURFACES), help="comma-separated subset of " + ",".join(SURFACES))
    ap.add_argument("--schemes", default="all", help='"all" or a comma-separated list of normal estimates')
    args = ap.parse_args()
    surfaces = tuple(args.surfaces.split(","))
    sphere = [surface_errors(*sphere_octahedron(level)) for level in range(1, 6)]
    cyl = []
    for n in (8, 16, 32, 64, 128):
        p, t, ex, tg = closed_cylinder(n)
        cyl.append(surface_errors(p, t, ex, tg, [1]))
    o_s = table("unit sphere (octahedron subdivisions, exact normals)", sphere)
    table("closed unit cylinder R = H = 1 (exact normals on the side, sharp rims)", cyl)

    hs = [0.2]
    while hs[-1] / 2 >= args.hmin * (1 - 1e-9):
        hs.append(hs[-1] / 2)
    schemes = ("jet",) + tuple(s for s in SCHEMES if s != "jet" and (args.schemes == "all" or s in args.schemes))
    print("\nmeshing and fitting:")
    res = estimated_study(hs, schemes, surfaces)
    print_estimated(res, hs)
    print_schemes(res, hs, schemes)
    ellipse_study((48, 96, 192, 384, 768))
    o_est = min(orders([r[1] for r in res[kind]["jet"]])[-1] for kind in surfaces)
    print(f"\nnagata_order_sphere {o_s[-1]:.3f}")
    print(f"nagata_order_estimated {o_est:.3f}")


if __name__ == "__main__":
    main()
