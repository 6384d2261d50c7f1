"""The file's own tolerances (``nagata_snap.cad.tolerance``) against OpenCASCADE's, and the CLI's
distance report on a file whose faces meet only within them."""

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from occ_reference import OccShape

from nagata_snap.cad import CadGeometry
from nagata_snap.cad.projection import evaluate_params, normalize_params
from nagata_snap.cad.tolerance import FAR_RTOL, count_far, tolerance_gaps

CORPUS = Path(__file__).resolve().parents[1] / "meshes" / "corpus"
#: a netgen-exported screw whose edges and vertices carry tolerances up to 3e-4 mm (size 51 mm):
#: its faces meet only within them, and snapped vertices on its edges show it
SCREW = CORPUS / "screw_euclid_netgen.step"


@pytest.fixture(scope="module")
def screw():
    if not SCREW.is_file():
        pytest.skip("corpus file missing")
    return CadGeometry.from_file(SCREW, isolate=False), OccShape(str(SCREW))


def _probes(model, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(face, point, expected kind)``: per face and edge of it, the edge's middle point pushed
    off across the edge by 0.5 and 3 times its tolerance tube's radius (inside, outside), and
    per vertex of those edges a point 0.7 of its tolerance off it (kind 0 in an edge tube, 1
    outside every tube, 2 near a vertex)."""
    floor = FAR_RTOL * model.size
    faces, points, kinds = [], [], []
    for i, f in enumerate(model.faces):  # loop over faces and their edges (a few dozen probes)
        for e in f.edges.tolist():
            edge = model.edges[e]
            t = normalize_params(edge.curve, np.array([[edge.curve.bounds[0].mean()]]))
            C, T = evaluate_params(edge.curve, t, 1)
            d = np.cross(T[0, 0], rng.normal(size=3))
            d /= np.linalg.norm(d)
            r = max(edge.tolerance, floor)
            for s, k in ((0.5, 0), (3.0, 1)):
                faces.append(i)
                points.append(C[0] + s * r * d)
                kinds.append(k)
            for v in edge.vertices:
                u = rng.normal(size=3)
                faces.append(i)
                points.append(model.vertices[v] + 0.7 * max(model.vertex_tolerance[v], floor) * u / np.linalg.norm(u))
                kinds.append(2)
    return np.array(faces), np.array(points), np.array(kinds)


def test_tolerance_gaps_agree_with_occ(screw):
    """Our tubes (the model's edge curves and vertices with OpenCASCADE's tolerances) give each
    point the gap OpenCASCADE's own (BRepExtrema to the face's edges and vertices) gives."""
    geo, occ = screw
    model = geo.model
    faces, points, kinds = _probes(model, np.random.default_rng(1))
    ours = tolerance_gaps(model, faces, points)
    truth = occ.tolerance_gaps(faces, points)
    floor = FAR_RTOL * model.size
    assert (truth[kinds == 0] > floor).any() and (truth[kinds == 2] > floor).any()  # the test can fail
    np.testing.assert_allclose(ours, truth, rtol=1e-6)  # (an edge and its vertex: 3.002696046e-4, 3.002696036e-4)
    # a point 3 tolerances off an edge is in no tube of that edge; counted beyond unless another holds it
    far, within = count_far(model, faces, points, np.full(len(faces), 2.0 * floor), model.size)
    assert far == len(faces) and within == int(np.count_nonzero(truth >= 2.0 * floor))
    assert count_far(None, faces, points, np.full(len(faces), 2.0 * floor), model.size) == (len(faces), 0)


def test_cli_report_names_the_files_tolerances(screw):
    """On the screw (one coarse level), vertices farther than 1e-9 of the size from their face
    all lie inside the file's edge tolerances, and the CLI's summary says so (rather than
    reporting them as off their faces); none is farther than OpenCASCADE's largest tolerance
    of the file's edges and vertices."""
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_VERTEX

    r = subprocess.run([sys.executable, "-m", "nagata_snap.cli", str(SCREW), "--levels", "1", "--curvature", "6"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    line = next(s for s in r.stdout.splitlines() if "summary" in s)
    m = re.search(r"from its CAD face (\S+) .*; (\d+) farther than 1e-9 of it \((\d+) of them inside the file's own "
                  r"edge tolerances\)", line)
    assert m, line
    dmax, far, within = float(m[1]), int(m[2]), int(m[3])
    assert far > 0 and within == far, line
    _, occ = screw
    largest = max(BRep_Tool.MaxTolerance_s(f, kind) for f in occ.faces for kind in (TopAbs_EDGE, TopAbs_VERTEX))
    assert dmax <= largest


def _on_both_surfaces(occ, faces, p, sweeps: int = 50):
    """``p`` moved onto the intersection of two faces' surfaces by alternating OpenCASCADE
    projections (``GeomAPI_ProjectPointOnSurf``), or None if it does not settle within 1e-12
    of the size of both."""
    from OCP.BRep import BRep_Tool
    from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
    from OCP.gp import gp_Pnt

    surfs = [BRep_Tool.Surface_s(occ.faces[f]) for f in faces]
    for _ in range(sweeps):
        for s in surfs:
            p = np.array(GeomAPI_ProjectPointOnSurf(gp_Pnt(*p), s).NearestPoint().Coord())
    dist = [GeomAPI_ProjectPointOnSurf(gp_Pnt(*p), s).LowerDistance() for s in surfs]
    return p if max(dist) <= 1e-12 * occ.size else None


def test_meeting_gaps_agree_with_occ():
    """Where an edge's faces meet: on the CATIA V5 bolt, whose edge curves lie off their faces by
    nearly (and on some edges beyond) their tolerance, points on the intersection of an edge's
    two faces' surfaces (found by OpenCASCADE) get the gap ``t / sin(theta / 2)`` of
    OpenCASCADE's own tolerance, normals and edge distance (:meth:`OccShape.meeting_gaps`;
    none where the faces are tangent: the cylinder's halves), and some of them lie beyond
    the edge's tolerance tube (the case the gap is for)."""
    from nagata_snap.cad.tolerance import meeting_gaps

    path = CORPUS / "bolt_catia_v5_cax_if.stp"
    if not path.is_file():
        pytest.skip("corpus file missing")
    model = CadGeometry.from_file(path, isolate=False).model
    occ = OccShape(str(path))
    faces, points = [], []
    for e in model.edges:  # loop over the edges (a dozen), a few points each
        if e.curve is None or len(e.faces) != 2:
            continue
        t0, t1 = e.curve.bounds[0]
        C = evaluate_params(e.curve, normalize_params(e.curve, np.linspace(t0, t1, 9)[1:-1, None]))
        for c in C:
            p = _on_both_surfaces(occ, e.faces, c)
            if p is not None:
                faces += list(e.faces)
                points += [p, p]
    faces, points = np.array(faces), np.array(points)
    assert len(faces) >= 40
    ours = meeting_gaps(model, faces, points)
    truth = occ.meeting_gaps(faces, points)
    np.testing.assert_allclose(ours, truth, rtol=1e-9)
    tube = tolerance_gaps(model, faces, points)
    beyond = tube <= FAR_RTOL * model.size
    assert np.count_nonzero(beyond) >= 2  # beyond every tube: the case is there
    assert np.all(truth[beyond] > FAR_RTOL * model.size)  # and where the faces meet
    np.testing.assert_array_equal(tolerance_gaps(model, faces, points, meet=True), np.maximum(tube, ours))
