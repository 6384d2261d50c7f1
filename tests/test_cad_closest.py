"""Global closest points whose foot lies on a face's boundary curve, against OpenCASCADE.

Points are pushed 1e-3 of the model size in random directions off random
points of the CAD edges of corpus files (OpenCASCADE's own edge curves), so
that for many of them the surface's unconstrained foot point is beyond the
face's trimming loops and the closest point of the trimmed faces is on an
edge.  ``CadGeometry.closest_point`` must find each, at OpenCASCADE's
distance (``BRepExtrema_DistShapeShape`` against all the faces) to 1e-6 of
the size, at a foot point on the face it names (OpenCASCADE's distance from
that trimmed face <= 1e-9 of the size).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from nagata_snap.cad import CadGeometry

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "meshes"))
from occ_reference import OccShape  # noqa: E402

CORPUS = ROOT / "meshes" / "corpus"
#: (file, points, least fraction of surface feet off their face, least fraction found): a
#: single open plane face with curved loops; two open planar sheets (Rhino); rational
#: B-spline patches whose loops are their knot domains (the boundary is where the patches
#: meet, at creases and collapsed knot lines: Newton's stationary points there are not the
#: closest); two CATIA V4 B-spline faces whose edge curves lie off them by up to 5e-3 of
#: the size (the boundary is the curve the p-curves trace on the surface)
FILES = (("plane190_msbo_faces_occ68.igs", 150, 0.2, 1.0), ("planar_sheets_rhino_stdev15.stp", 150, 0.1, 1.0),
         ("rational_patches_3dipsos.igs", 150, 0.0, 1.0), ("bspline_face_catia_v4_t1.igs", 150, 0.0, 1.0),
         ("trimmed_bspline_face_catia_v4.igs", 150, 0.0, 1.0))


def edge_points(occ: OccShape, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` points ``1e-3`` of the size off random points of OpenCASCADE's edge curves
    (edges drawn by length, uniform in the edge's parameter range, random directions)."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.BRepGProp import BRepGProp
    from OCP.GProp import GProp_GProps

    curves, length = [], []
    for e in occ.edges:
        props = GProp_GProps()
        BRepGProp.LinearProperties_s(e, props)
        if props.Mass() > 0.0:
            curves.append(BRepAdaptor_Curve(e))
            length.append(props.Mass())
    w = np.array(length) / sum(length)
    X = np.empty((n, 3))
    for k, c in enumerate(rng.choice(len(curves), size=n, p=w)):
        a = curves[c]
        q = a.Value(a.FirstParameter() + (a.LastParameter() - a.FirstParameter()) * rng.random())
        X[k] = q.X(), q.Y(), q.Z()
    d = rng.normal(size=X.shape)
    return X + 1e-3 * occ.size * d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize(("name", "n", "off_face", "least_found"), FILES)
def test_closest_point_on_face_boundaries_agrees_with_occ(name, n, off_face, least_found):
    """The points found (all, or ``least_found`` of them), none farther than OpenCASCADE's
    closest point (1e-6 of the size) or off the face named (1e-9), none nearer (OpenCASCADE's
    reference: ``BRepExtrema`` on the faces and on the faces split at their C0 lines; a
    face whose edges are off it, as its surface within its p-curves)."""
    path = str(CORPUS / name)
    geo = CadGeometry.from_file(path)
    occ = OccShape(path)
    size = occ.size
    X = edge_points(occ, n, np.random.default_rng(1))
    outside = ~geo.searcher.search(X, accept=geo._accept)[3]  # the surface's foot is off its face
    assert outside.sum() >= off_face * n, f"{name}: only {outside.sum()} feet off their face: the test tests little"
    truth, _ = occ.closest(X)
    ent, par, dist = geo.closest_point(X)
    found = ent >= 0
    assert found.sum() >= least_found * n, f"{name}: {int((~found).sum())} of {n} points not found"
    X, ent, par, dist, truth = X[found], ent[found], par[found], dist[found], truth[found]
    foot = geo.evaluate(ent, par[:, None, :])[:, 0]
    assert np.allclose(np.linalg.norm(foot - X, axis=1), dist, rtol=0, atol=1e-12 * size)
    on = occ.face_distance(ent, foot, accept=1e-9 * size, params=par) / size
    far = (dist - truth) / size
    bad = np.flatnonzero((far > 1e-6) | (on > 1e-9))
    assert bad.size == 0, (f"{name}: {bad.size} of {n} points wrong ({outside.sum()} feet off their face): "
                           f"farther than OpenCASCADE's by up to {far.max():.2e}, off the face by up to "
                           f"{on.max():.2e} of the size")
    nearer = np.flatnonzero(far < -1e-6)
    assert nearer.size == 0, f"{name}: {nearer.size} of {n} points nearer than OpenCASCADE's"


def test_curves_of_p_curves_on_their_surfaces_are_occs():
    """``CurveOnSurface`` (the curve a p-curve traces on its face, the boundary of a face whose
    edge curves lie off it): its points and first two derivatives at OpenCASCADE's parameters
    are ``BRepAdaptor_Curve(edge, face)``'s (points to 1e-9 of the size, derivatives to 1e-7
    relative), for every edge use of two CATIA V4 faces, while the edges' own 3D curves
    are up to 5e-3 of the size off them."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.gp import gp_Pnt, gp_Vec

    from nagata_snap.cad.boundary import CurveOnSurface

    for name in ("bspline_face_catia_v4_t1.igs", "bspline_face_occ52_f45.igs"):
        path = str(CORPUS / name)
        geo = CadGeometry.from_file(path)
        occ = OccShape(path)
        gap = 0.0
        for f, face in enumerate(geo.model.faces):
            for lp in face.loops:
                for e, desc in zip(lp.uses, lp.pcurves, strict=True):
                    ours = CurveOnSurface(desc, face.surface, face.uv_map)
                    theirs = BRepAdaptor_Curve(occ.edges[e], occ.faces[f])
                    own = BRepAdaptor_Curve(occ.edges[e])
                    t = np.linspace(theirs.FirstParameter(), theirs.LastParameter(), 23)
                    C = ours._eval_soa(t[None, :], 2)
                    for k, tk in enumerate(t):
                        p, d1, d2 = gp_Pnt(), gp_Vec(), gp_Vec()
                        theirs.D2(tk, p, d1, d2)
                        assert np.linalg.norm(C[0, :, k] - p.Coord()) <= 1e-9 * occ.size, (name, e, tk)
                        for j, d in ((1, d1), (2, d2)):
                            ref = np.array(d.Coord())
                            err = np.linalg.norm(C[j, :, k] - ref)
                            assert err <= 1e-7 * max(np.linalg.norm(ref), 1.0), (name, e, j)
                        gap = max(gap, own.Value(tk).Distance(p) / occ.size)
        assert gap > 1e-4, f"{name}: edges within {gap:.1e} of the size of their faces: the test tests little"
