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
   With ``--meshes K`` each surface is also meshed K ways per h (gmsh
   algorithm 6 Frontal-Delaunay, 5 Delaunay, 6 at size 1.01 h, 1 MeshAdapt;
   :data:`MESHES`): gmsh meshes of
   successive h are not nested and the largest distance is an extreme
   value, so the order of one pair scatters from mesh to mesh; the spread
   of the finest-pair order over the meshes is printed.
3. Where the exact-normal error sits: the largest distance of the samples
   on the patch edges and of those inside, on the gmsh meshes and on nested
   structured meshes (a torus angle grid; the octahedron subdivisions
   scaled to the ellipsoid) that have no mesh noise.  The Nagata curves of
   the edges are fourth order; the patch is the quadratic its three edge
   curves determine, so a cubic part of the surface that vanishes on the
   edges (a multiple of ``lambda1 lambda2 lambda3``) is left over inside:
   third order at the centroid wherever it does not vanish (it does on the
   sphere and the cylinder).
4. 2D: polygons inscribed in an ellipse 1 x 0.5 (unequal segments).

Each patch is sampled on a barycentric grid and the largest distance of a
sample from the exact surface is reported.  Observed orders are log2 of
successive error ratios (h halves from one row to the next).

Last lines: ``nagata_order_sphere <order on the finest pair, exact normals>``
and ``nagata_order_estimated <smallest order on the finest pair over the
three surfaces, estimated normals>``.

Usage: ``python benchmarks/nagata_convergence.py [--hmin 0.025] [--surfaces torus,...]
[--schemes jet,mwselr,...] [--meshes 1] [--nested 64]`` (the default runs every
surface and estimate down to h = 0.025 on gmsh's default meshes, and the
nested meshes down to a 160 x 64 torus grid; ``--hmin 0.0125 --surfaces
torus,ellipsoid --schemes jet --meshes 3`` adds the next level on three
meshes per h: about 4 minutes a torus mesh at h = 0.0125).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
import warnings

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))

from surfaces import (
    barycentric_grid,
    closed_cylinder,
    ellipse_polygon,
    ellipsoid_exact,
    gmsh_surface,
    nagata_surface_error,
    sphere_octahedron,
    torus_exact,
)

from nagata_snap import NagataGeometry
from nagata_snap.nagata.normals import SCHEMES

SURFACES = ("torus", "ellipsoid", "cylinder")
#: gmsh ``(Mesh.Algorithm, size / h)`` of the i-th mesh per h (``--meshes``): Frontal-Delaunay,
#: Delaunay, Frontal-Delaunay at 1.01 h, MeshAdapt (slow: minutes at h = 0.025).
MESHES = ((6, 1.0), (5, 1.0), (6, 1.01), (1, 1.0))


def surface_errors(points, tris, exact, tags=None, snap=None, samples=16):
    """Max distance from the exact surface of sampled Nagata and flat patches."""
    geo = NagataGeometry.from_surface(points, tris, tags, snap, normals=exact.normal)
    lam = np.broadcast_to(barycentric_grid(3, samples), (geo.num_patches, *barycentric_grid(3, samples).shape))
    curved = geo.evaluate(np.arange(geo.num_patches), lam)
    flat = np.einsum("pkv,pvi->pki", lam, geo.x)
    side = geo.snap
    h = np.max(np.linalg.norm(geo.x[side][:, [1, 2, 0]] - geo.x[side], axis=2))
    return h, exact.distance(curved).max(), exact.distance(flat).max()


def error_split(geo, dist, per_edge=16):
    """Where the patch error sits: ``(3,)`` largest ``dist`` of the samples on the snapped patches' edges,
    of those inside, and the largest patch error over the patch's longest edge cubed (1 / length^2).

    The same barycentric grid as :func:`nagata_surface_error` (its maximum is
    the larger of the first two).  The third figure stays bounded as the
    mesh is refined exactly when the error is at most ``C h_patch^3``.
    """
    g = barycentric_grid(3, per_edge)
    on_edge = (g == 0).any(axis=1)
    sel = np.flatnonzero(geo.snap)
    out = np.zeros(3)
    for s in np.array_split(sel, max(1, len(sel) // 2000)):  # bounded memory on fine meshes
        d = dist(geo.evaluate(s, np.broadcast_to(g, (len(s), *g.shape))))
        h = np.linalg.norm(geo.x[s][:, [1, 2, 0]] - geo.x[s], axis=2).max(axis=1)
        out = np.maximum(out, [d[:, on_edge].max(), d[:, ~on_edge].max(), (d.max(axis=1) / h**3).max()])
    return out


def torus_grid(n, R=1.0, r=0.4):
    """Nested torus meshes: the ``(5n/2) x n`` angle grid (major x minor), each cell cut by one diagonal.

    Returns ``(points (nv, 3) on the torus, triangles (F, 3) outward)``.
    """
    nu = 5 * n // 2
    U, V = np.meshgrid(2 * np.pi * np.arange(nu) / nu, 2 * np.pi * np.arange(n) / n, indexing="ij")
    p = np.stack([(R + r * np.cos(V)) * np.cos(U), (R + r * np.cos(V)) * np.sin(U), r * np.sin(V)], axis=-1)
    i, j = (a.ravel() for a in np.meshgrid(np.arange(nu), np.arange(n), indexing="ij"))

    def vid(a, b):
        return (a % nu) * n + b % n

    a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
    return p.reshape(-1, 3), np.concatenate([np.c_[a, b, c], np.c_[a, c, d]])


def nested_study(n_max):
    """Exact normals on nested structured meshes: ``{name: [(h_max, error, *error_split)]}``."""
    axes = np.array([1.0, 0.7, 0.5])
    finest = int(np.log2(n_max))  # torus grid 2^k ~ octahedron level k - 1 in h
    cases = {"torus grid": ([torus_grid(2**k) for k in range(3, finest + 1)], torus_exact()),
             "ellipsoid (scaled octahedron subdivisions)":
                 ([(p * axes, t) for p, t, _ in (sphere_octahedron(k) for k in range(2, finest))], ellipsoid_exact())}
    res = {}
    for name, (meshes, exact) in cases.items():
        res[name] = []
        for p, t in meshes:
            geo = NagataGeometry.from_surface(p, t, normals=exact.normal)
            e = error_split(geo, exact.distance)
            h = np.linalg.norm(p[t[:, [1, 2, 0]]] - p[t], axis=2).max()
            res[name].append((h, e[:2].max(), *e))
    return res


def print_split(title, rows):
    """Table of the error on the edges and inside: ``rows = [(h, error, edge, interior, error / h^3), ...]``."""
    print(f"\n{title}")
    print(f"{'h':>8} {'error':>10} {'order':>6} {'on edges':>10} {'order':>6} {'inside':>10} {'order':>6}"
          f" {'max err/h_T^3':>13}")
    for i, r in enumerate(rows):
        o = [f"{np.log2(rows[i - 1][k] / r[k]):6.2f}" if i else f"{'':>6}" for k in (1, 2, 3)]
        print(f"{r[0]:8.4f} {r[1]:10.3e} {o[0]} {r[2]:10.3e} {o[1]} {r[3]:10.3e} {o[2]} {r[4]:13.4f}")


def orders(errors):
    return [np.log2(a / b) for a, b in itertools.pairwise(errors)]


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


def estimated_study(hs, schemes, surfaces=SURFACES, meshes=MESHES[:1]):
    """``res[kind][name] = [(h, patch error, normal error deg, seconds), ...]`` per h (first algorithm).

    ``res[kind]["split"]``: ``(h, error, *error_split)`` with exact normals;
    ``res[kind]["meshes"][(algorithm, size factor)]``: ``(h, jet error,
    exact error)`` per gmsh mesh of :data:`MESHES`.
    """
    res = {}
    for kind in surfaces:
        res[kind] = {name: [] for name in ("exact", "flat", "split", *schemes)}
        res[kind]["meshes"] = {m: [] for m in meshes}
        for h in hs:
            for alg in meshes:
                p, t, exact, _ = gmsh_surface(kind, h * alg[1], alg[0])
                err = {}
                for name in ("exact", *(schemes if alg == meshes[0] else ("jet",))):
                    t0 = time.perf_counter()
                    with warnings.catch_warnings():  # the exact side normal is refused at disc corners
                        warnings.simplefilter("ignore")
                        geo = NagataGeometry.from_surface(p, t, crease_angle=80,
                                                          normals=exact.normal if name == "exact" else name)
                    dt = time.perf_counter() - t0
                    split = error_split(geo, exact.distance)
                    err[name] = split[:2].max()
                    if alg == meshes[0]:
                        res[kind][name].append((h, err[name], normal_error_deg(geo, exact, kind == "cylinder"), dt))
                        if name == "exact":
                            res[kind]["split"].append((h, err[name], *split))
                res[kind]["meshes"][alg].append((h, err["jet"], err["exact"]))
                if alg == meshes[0]:
                    g = barycentric_grid(3, 16)
                    flat = np.einsum("kv,fvi->fki", g, p[t])
                    res[kind]["flat"].append((h, float(exact.distance(flat).max()), np.nan, 0.0))
                print(f"  {kind} h = {h} (gmsh algorithm {alg[0]}, size {alg[1]} h): {len(t)} triangles", flush=True)
    return res


def print_spread(res):
    """Finest-pair order per gmsh mesh of :data:`MESHES`, and of the median error over them."""
    print("\nSeveral gmsh meshes per h (Mesh.Algorithm, size): observed order of the finest pair, jet / exact normals,"
          " and jet / exact error at the finest h")
    for kind in res:
        meshes = res[kind]["meshes"]
        cells = []
        for alg, rows in meshes.items():
            o_jet, o_exact = orders([r[1] for r in rows])[-1], orders([r[2] for r in rows])[-1]
            cells.append(f"alg {alg[0]} at {alg[1]} h: {o_jet:.2f} / {o_exact:.2f} ({rows[-1][1] / rows[-1][2]:.3f}x)")
        med = [np.median([rows[i][1] for rows in meshes.values()]) for i in range(len(next(iter(meshes.values()))))]
        spread = max(r[-1][1] for r in meshes.values()) / min(r[-1][1] for r in meshes.values())
        print(f"{kind:>10}  " + "; ".join(cells) + f"; median error: {orders(med)[-1]:.2f};"
              f" errors at the finest h differ by {spread:.2f}x")


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
            cells = " ".join(f"{r[2]:8.2e} {r[1] / e:7.2f}x" for r, e in zip(rows, ex, strict=True))
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
    ap.add_argument("--meshes", type=int, default=1, choices=range(1, len(MESHES) + 1),
                    help="gmsh meshes per h (algorithm, size: 6 h, 5 h, 6 1.01 h, 1 h)")
    ap.add_argument("--nested", type=int, default=64,
                    help="finest nested torus grid, (5n/2) x n cells, a power of 2 (the ellipsoid's as fine)")
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
    wanted = set(SCHEMES) if args.schemes == "all" else set(args.schemes.split(","))
    if wanted - set(SCHEMES):
        raise SystemExit(f"--schemes: unknown {sorted(wanted - set(SCHEMES))}; known: {', '.join(SCHEMES)}")
    schemes = ("jet", *(s for s in SCHEMES if s != "jet" and s in wanted))
    print("\nmeshing and fitting:")
    res = estimated_study(hs, schemes, surfaces, MESHES[:args.meshes])
    print_estimated(res, hs)
    print_schemes(res, hs, schemes)
    if args.meshes > 1:
        print_spread(res)
    print("\nWhere the error sits (exact normals): largest distance of the samples on the patch edges and inside;"
          " largest patch error over its longest edge cubed")
    for kind in surfaces:
        print_split(f"{kind}, gmsh meshes", res[kind]["split"])
    for name, rows in nested_study(args.nested).items():
        print_split(f"{name}, nested structured meshes", rows)
    ellipse_study((48, 96, 192, 384, 768))
    o_est = min(orders([r[1] for r in res[kind]["jet"]])[-1] for kind in surfaces)
    print(f"\nnagata_order_sphere {o_s[-1]:.3f}")
    print(f"nagata_order_estimated {o_est:.3f}")


if __name__ == "__main__":
    main()
