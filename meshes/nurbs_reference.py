"""Reference NURBS data for tests and benchmarks, and their OpenCASCADE twins.

* :func:`herrero_71`: the rational surface of Herrero Adan & Cardoso (2020),
  Appendix D, Example 7.1 (Tables D.2 and D.3), used by Neto/Nagata-style
  accuracy tests and as a hard projection target.
* :func:`occ_bspline`: the same NURBS surface built in gmsh's OpenCASCADE
  kernel, so that ``gmsh.model.getClosestPoint`` / ``getValue`` give an
  independent reference for our evaluation and projection.
"""

from __future__ import annotations

import numpy as np

from nagata_snap.cad.nurbs import NurbsSurface


def herrero_71() -> NurbsSurface:
    """Herrero Adan & Cardoso (2020), Appendix D, Example 7.1 (Tables D.2 and D.3).

    n = 6 (xi, our u), m = 5 (eta, our v), p = q = 2,
    Xi = {0,0,0,0.25,0.5,0.75,1,1,1}, H = {0,0,0,0.5,0.5,1,1,1}.
    Rows of Table D.3 are i = 1..6, columns j = 1..5, entries "x, y, z, w".
    """
    table = [
        [(0, 0, -90, 1), (0, 0, 0, 0.707), (0, 30, 0, 1), (0, 60, 0, 0.707), (0, 60, -30, 1)],
        [(30, 0, -15, 1), (30, 15, 0, 1), (30, 30, 0, 1), (30, 45, 0, 1), (30, 60, -15, 1)],
        [(95, 0, 0, 1), (95, 15, 0, 1), (95, 30, 0, 1), (95, 45, 0, 1), (95, 60, 0, 1)],
        [(150, 0, 0, 6), (137.5, 15, 0, 1), (125, 30, 0, 1), (112.5, 45, 0, 1), (100, 60, 0, 1)],
        [(150, 65, 0, 1), (137.5, 65, 0, 1), (125, 65, 0, 1), (112.5, 65, 0, 1), (100, 65, 0, 1)],
        [(150, 100, 0, 1), (137.5, 100, 0, 1), (125, 100, 0, 1), (112.5, 100, 0, 1), (100, 100, 0, 1)],
    ]
    a = np.array(table, dtype=float)
    return NurbsSurface(
        2, 2, [0, 0, 0, 0.25, 0.5, 0.75, 1, 1, 1], [0, 0, 0, 0.5, 0.5, 1, 1, 1], a[..., :3], a[..., 3]
    )


def occ_bspline(gmsh, surf: NurbsSurface) -> int:
    """Add ``surf`` to the current gmsh model as an OCC B-spline surface; returns its tag.

    gmsh wants the control points with the u index running fastest and the
    knots as distinct values with multiplicities.  The model is synchronised.
    """
    nu, nv = surf.n_ctrl
    tags, w = [], []
    for j in range(nv):  # loop over control points (gmsh: u index fastest)
        for i in range(nu):
            tags.append(gmsh.model.occ.addPoint(*surf.control_points[i, j]))
            w.append(float(surf.weights[i, j]))
    ku, mu = np.unique(surf.knots_u, return_counts=True)
    kv, mv = np.unique(surf.knots_v, return_counts=True)
    tag = gmsh.model.occ.addBSplineSurface(
        tags, nu, degreeU=surf.degree_u, degreeV=surf.degree_v, weights=w,
        knotsU=ku.tolist(), knotsV=kv.tolist(),
        multiplicitiesU=mu.tolist(), multiplicitiesV=mv.tolist(),
    )
    gmsh.model.occ.synchronize()
    return tag
