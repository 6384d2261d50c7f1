"""Nagata surface error against exact geometry, with exact normals (Nagata 2005, Fig. 9).

For a unit sphere (octahedron subdivisions projected on the sphere) and a
closed unit cylinder (R = H = 1, sharp rims handled by multiple normals),
each patch is sampled on a barycentric grid and the largest distance of a
sample from the exact surface is reported, for the Nagata patches and for the
flat (linear) facets.  Observed orders are log2 of successive error ratios
(mesh scale halves from one row to the next).

Last line: ``nagata_order_sphere <observed order on the finest pair>``.
"""

from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "meshes"))

from surfaces import barycentric_grid, closed_cylinder, sphere_octahedron  # noqa: E402

from nagata_snap import NagataGeometry  # noqa: E402


def surface_errors(points, tris, exact, tags=None, snap=None, samples=16):
    """Max distance from the exact surface of sampled Nagata and flat patches."""
    geo = NagataGeometry.from_surface(points, tris, tags, snap, normals=exact.normal)
    lam = np.broadcast_to(barycentric_grid(3, samples), (geo.num_patches, *barycentric_grid(3, samples).shape))
    curved = geo.evaluate(np.arange(geo.num_patches), lam)
    flat = np.einsum("pkv,pvi->pki", lam, geo.x)
    side = geo.snap
    h = np.max(np.linalg.norm(geo.x[side][:, [1, 2, 0]] - geo.x[side], axis=2))
    return h, exact.distance(curved).max(), exact.distance(flat).max()


def table(name, rows):
    print(f"\n{name}")
    print(f"{'h_max':>10} {'nagata err':>12} {'order':>6} {'flat err':>12} {'order':>6}")
    prev = None
    orders = []
    for h, en, ef in rows:
        if prev is None:
            print(f"{h:10.4f} {en:12.4e} {'':>6} {ef:12.4e} {'':>6}")
        else:
            on, of = np.log2(prev[1] / en), np.log2(prev[2] / ef)
            orders.append(on)
            print(f"{h:10.4f} {en:12.4e} {on:6.2f} {ef:12.4e} {of:6.2f}")
        prev = (h, en, ef)
    return orders


def main() -> None:
    sphere = [surface_errors(*sphere_octahedron(level)) for level in range(1, 6)]
    cyl = []
    for n in (8, 16, 32, 64, 128):
        p, t, ex, tg = closed_cylinder(n)
        cyl.append(surface_errors(p, t, ex, tg, [1]))
    o_s = table("unit sphere (octahedron subdivisions, exact normals)", sphere)
    table("closed unit cylinder R = H = 1 (exact normals on the side, sharp rims)", cyl)
    print(f"\nnagata_order_sphere {o_s[-1]:.3f}")


if __name__ == "__main__":
    main()
