"""Sewing faces-only IGES files by joining the walked data (nagata_snap.cad.sewing) against
OpenCASCADE's own sewing.

The independent truth is OpenCASCADE's path (``BRepBuilderAPI_Sewing``,
``ShapeFix_Solid::SolidFromShell``, ``ShapeFix_Shape``: ``read_shape(path,
join=False)``).  For every 3D part of ``meshes/parts.py`` written as a
faces-only IGES file, and for small shapes made for one case each (two
half-circles between the same vertices, a seam, a pole, an open shell, a
face turned over, an inward shell), the model read with the join equals
OpenCASCADE's in what the pipeline uses: the same surface on every face (faces
matched by their surfaces), the face's orientation, its wires use for use
(edges matched through the uses: a bijection, with the same sense along the
edge's 3D curve, seams and degenerate edges alike), the trimming loops (the
same polygons in the parameter plane, the same edges in the same order and
senses), the faces of every edge, the vertices of every edge (a bijection,
the points within their tolerance), the edge curves (within the edges'
tolerances) and the solids.  Where the join is not clean the reader falls back
to OpenCASCADE (``healed["method"]``), and the result is then OpenCASCADE's
exactly.
"""

from __future__ import annotations

import math
import os

import gmsh
import numpy as np
import pytest

import parts  # meshes/ is on sys.path (conftest.py)

from nagata_snap.cad import read as cad_read
from nagata_snap.cad import sewing
from nagata_snap.cad.projection import evaluate_params, normalize_params
from nagata_snap.cad.read import read_shape
from nagata_snap.cad.topology import CadModel

#: 3D parts, written as faces-only IGES (gmsh.write)
PARTS = [name for name, p in parts.PARTS.items() if p.dim == 3]
#: parts whose faces-only IGES the join does not sew, and why (OpenCASCADE sews them)
FALLS_BACK = {"revolved": "no planar face decides", "assembly": "more than two copies"}


# ----------------------------------------------------------------------
# comparison with OpenCASCADE's sewing
# ----------------------------------------------------------------------
def _close(a, b, atol: float) -> bool:
    """Two surface descriptions (dicts of numbers, arrays, tuples) agree within ``atol``."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_close(a[k], b[k], atol) for k in a)
    if isinstance(a, str) or a is None:
        return a == b
    if isinstance(a, (tuple, list)) and a and not np.isscalar(a[0]) and not isinstance(a[0], (list, tuple)):
        return len(a) == len(b) and all(_close(x, y, atol) for x, y in zip(a, b, strict=True))
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and np.allclose(a, b, rtol=1e-9, atol=atol)


def _face_match(fast: dict, occ: dict) -> np.ndarray:
    """``(nf,)``: the OpenCASCADE face of every face of the join, by surface and bounds."""
    atol = 1e-9 * fast["size"]
    out = []
    for f in fast["faces"]:
        cand = [k for k, g in enumerate(occ["faces"]) if _close(f["surface"], g["surface"], 1e-7 * fast["size"])
                and np.allclose(f["uv"], g["uv"], atol=atol, rtol=1e-9)
                and [len(w["uses"]) for w in f["wires"]] == [len(w["uses"]) for w in g["wires"]]]
        assert len(cand) == 1, (len(out), cand)
        out.append(cand[0])
    assert sorted(out) == list(range(len(occ["faces"])))
    return np.array(out)


def _bijection(pairs) -> dict:
    """``{ours: theirs}`` of ``pairs``, asserting it is one-to-one."""
    fwd: dict = {}
    for a, b in pairs:
        assert fwd.setdefault(a, b) == b, (a, b, fwd[a])
    assert len(set(fwd.values())) == len(fwd)
    return fwd


def _polyline_distance(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``(k,)`` distance of each point of ``P (k, d)`` to the polyline ``Q (m, d)``."""
    A, B = Q[:-1], Q[1:]
    D = B - A
    t = np.clip(np.einsum("kmd,md->km", P[:, None] - A[None], D) / np.maximum(np.sum(D * D, axis=1), 1e-300), 0, 1)
    return np.linalg.norm(A[None] + t[..., None] * D[None] - P[:, None], axis=2).min(axis=1)


def _on_surface(surface, params: np.ndarray) -> np.ndarray:
    """``(k, 3)`` points of a face's surface at trimming-loop parameters ``(k, 2)``."""
    return evaluate_params(surface, normalize_params(surface, params), 0)


def _runs(values: np.ndarray) -> list:
    """``values`` with consecutive repeats removed (the edges of a loop, in order)."""
    keep = np.r_[True, values[1:] != values[:-1]]
    return values[keep].tolist()


def _direction(ours, theirs) -> bool:
    """Whether the curve ``ours`` runs against ``theirs`` (the same curve within tolerance):
    their tangents at our middle point."""
    t = np.linspace(*theirs.bounds[0], 4001)
    Q = theirs.evaluate(t)[0]
    p, dp = ours.evaluate([0.5 * sum(ours.bounds[0])], 1)[:, 0]
    k = int(np.argmin(np.linalg.norm(Q - p, axis=1)))
    dq = theirs.evaluate([t[k]], 1)[1, 0]
    assert abs(dp @ dq) >= 0.9 * np.linalg.norm(dp) * np.linalg.norm(dq)
    return bool(dp @ dq < 0)


def assert_same_model(fast: dict, occ: dict) -> None:
    """The joined model ``fast`` is OpenCASCADE's sewn model ``occ`` up to the numbering (of
    faces, edges, vertices, solids) and to the direction of the edge curves kept."""
    size = fast["size"]
    assert fast["num_solids"] == occ["num_solids"] and len(fast["faces"]) == len(occ["faces"])
    perm = _face_match(fast, occ)
    edge = _bijection((u["edge"], v["edge"]) for i, f in enumerate(fast["faces"])
                      for w, x in zip(f["wires"], occ["faces"][perm[i]]["wires"], strict=True)
                      for u, v in zip(w["uses"], x["uses"], strict=True))
    assert len(edge) == len(fast["edges"]) == len(occ["edges"])
    mf, mo = CadModel.from_data(fast), CadModel.from_data(occ)
    flip = {}
    for e, d in edge.items():
        ef, eo = mf.edges[e], mo.edges[d]
        assert sorted(perm[list(ef.faces)].tolist()) == list(eo.faces), e
        assert (ef.curve is None) == (eo.curve is None)
        flip[e] = False
        if ef.curve is not None:  # the curves lie within the tolerances of each other
            Q = ef.curve.evaluate(np.linspace(*ef.curve.bounds[0], 4001))[0]
            P = eo.curve.evaluate(np.linspace(*eo.curve.bounds[0], 41))[0]
            assert _polyline_distance(P, Q).max() <= max(ef.tolerance, eo.tolerance) + 1e-9 * size, e
            assert ef.tolerance >= eo.tolerance - 1e-7 * size
            flip[e] = _direction(ef.curve, eo.curve)
    for i, f in enumerate(fast["faces"]):
        g = occ["faces"][perm[i]]
        assert f["reversed"] == g["reversed"] and f["converted"] == g["converted"]
        for w, x in zip(f["wires"], g["wires"], strict=True):
            assert w["outer"] == x["outer"]
            for u, v in zip(w["uses"], x["uses"], strict=True):
                assert u["seam"] == v["seam"] and u["degenerate"] == v["degenerate"], (i, u["edge"])
                ours = u["reversed"] ^ u.get("opposed", False) ^ flip[u["edge"]]
                assert ours == v["reversed"] ^ v.get("opposed", False), (i, u["edge"])
    solid = _bijection((f["solids"][0], occ["faces"][perm[i]]["solids"][0]) for i, f in enumerate(fast["faces"]))
    assert len(solid) == fast["num_solids"]
    vertex = _bijection((a, b) for e, d in edge.items()
                        for a, b in zip(fast["edges"][e]["vertices"][::-1 if flip[e] else 1],
                                        occ["edges"][d]["vertices"], strict=True))
    for a, b in vertex.items():
        assert np.linalg.norm(fast["vertices"][a] - occ["vertices"][b]) <= fast["vertex_tolerance"][a]
    sign = np.array([-1.0 if flip.get(e, False) else 1.0 for e in range(len(mf.edges))])
    for i, f in enumerate(mf.faces):
        g = mo.faces[perm[i]]
        assert sorted(edge[e] for e in f.edges.tolist()) == g.edges.tolist()
        for a, b in zip(f.loops, g.loops, strict=True):  # the same polygons, on the surface
            A, B = _on_surface(f.surface, a.points), _on_surface(g.surface, b.points)
            d = max(_polyline_distance(A, np.r_[B, B[:1]]).max(), _polyline_distance(B, np.r_[A, A[:1]]).max())
            assert d <= max(a.band.max(), b.band.max()), (i, d)
            assert [edge[e] for e in _runs(a.edges)] == _runs(b.edges), i
            first_a, first_b = np.r_[True, a.edges[1:] != a.edges[:-1]], np.r_[True, b.edges[1:] != b.edges[:-1]]
            assert np.array_equal((a.senses * sign[a.edges])[first_a], b.senses[first_b]), i


@pytest.fixture(scope="module")
def iges(tmp_path_factory):
    d = tmp_path_factory.mktemp("sew")
    return {name: str(parts.write_part(name, d, ("iges",))["iges"]) for name in PARTS}


@pytest.mark.parametrize("name", PARTS)
def test_parts_join_as_opencascade_sews(iges, name):
    fast, occ = read_shape(iges[name]), read_shape(iges[name], join=False)
    assert occ["healed"]["method"] == "occ" and "join" not in occ["healed"]
    assert occ["num_solids"] >= 1 and occ["healed"]["free_edges"] == 0
    if name in FALLS_BACK:
        assert fast["healed"]["method"] == "occ" and FALLS_BACK[name] in fast["healed"]["join"]
    else:
        assert fast["healed"]["method"] == "join", fast["healed"]
        assert fast["healed"]["tolerance"] == occ["healed"]["tolerance"]
    assert_same_model(fast, occ)


# ----------------------------------------------------------------------
# one case each
# ----------------------------------------------------------------------
def _gmsh_iges(path: str, build) -> str:
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        build(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        gmsh.write(path)
    finally:
        gmsh.finalize()
    return path


def _faces_iges(path: str, faces) -> str:
    """The OCP ``faces`` written as a faces-only IGES file (IGESControl_Writer, faces mode)."""
    from OCP.BRep import BRep_Builder
    from OCP.IGESControl import IGESControl_Controller, IGESControl_Writer
    from OCP.TopoDS import TopoDS_Compound

    comp, b = TopoDS_Compound(), BRep_Builder()
    b.MakeCompound(comp)
    for f in faces:
        b.Add(comp, f)
    IGESControl_Controller.Init_s()
    w = IGESControl_Writer("MM", 0)
    w.AddShape(comp)
    w.ComputeModel()
    assert w.Write(path)
    return path


def _box_faces():
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer

    ex, out = TopExp_Explorer(BRepPrimAPI_MakeBox(2.0, 1.0, 0.5).Shape(), TopAbs_FACE), []
    while ex.More():
        out.append(ex.Current())
        ex.Next()
    return out


def _half_circles(occ) -> None:
    """A disk bounded by two half-circles between the same two vertices, extruded."""
    c, p, q = occ.addPoint(0, 0, 0), occ.addPoint(1, 0, 0), occ.addPoint(-1, 0, 0)
    loop = occ.addCurveLoop([occ.addCircleArc(p, c, q), occ.addCircleArc(q, c, p)])
    occ.extrude([(2, occ.addPlaneSurface([loop]))], 0, 0, 2)
    occ.remove([(0, c)])


def test_half_circles_between_the_same_vertices(tmp_path):
    path = _gmsh_iges(str(tmp_path / "halves.igs"), _half_circles)
    fast, occ = read_shape(path), read_shape(path, join=False)
    assert fast["healed"]["method"] == "join" and fast["num_solids"] == 1
    arcs = [e for e in fast["edges"] if e["curve"]["type"] == "circle"]
    assert len(arcs) == 4 and len(fast["vertices"]) == 4  # two per disk, each a half
    assert_same_model(fast, occ)


def test_seam(tmp_path):
    path = _gmsh_iges(str(tmp_path / "cylinder.igs"), lambda occ: occ.addCylinder(0, 0, 0, 0, 0, 2, 1))
    fast, occ = read_shape(path), read_shape(path, join=False)
    assert fast["healed"]["method"] == "join"
    seams = {u["edge"] for f in fast["faces"] for w in f["wires"] for u in w["uses"] if u["seam"]}
    assert len(seams) == 1  # the lateral face's two copies of its seam: one edge, used twice
    assert sum(u["edge"] in seams for f in fast["faces"] for w in f["wires"] for u in w["uses"]) == 2
    assert_same_model(fast, occ)


def test_pole(tmp_path):
    """A hemisphere on its disk: a degenerate edge at the pole stays with its face."""
    path = _gmsh_iges(str(tmp_path / "dome.igs"), lambda occ: occ.addSphere(0, 0, 0, 1, angle1=0))
    fast, occ = read_shape(path), read_shape(path, join=False)
    assert fast["healed"]["method"] == "join"
    assert sum(e["degenerate"] for e in fast["edges"]) == 1
    assert_same_model(fast, occ)


def test_open_shell_falls_back(tmp_path):
    path = _faces_iges(str(tmp_path / "open.igs"), _box_faces()[1:])
    fast, occ = read_shape(path), read_shape(path, join=False)
    assert fast["healed"]["method"] == "occ" and "free edges" in fast["healed"]["join"]
    assert fast["num_solids"] == 0
    assert {k: v for k, v in fast["healed"].items() if k != "join"} == occ["healed"]


def test_inconsistent_orientation_falls_back(tmp_path):
    faces = _box_faces()
    faces[2] = faces[2].Reversed()
    path = _faces_iges(str(tmp_path / "turned.igs"), faces)
    fast = read_shape(path)
    assert fast["healed"]["method"] == "occ" and "same sense" in fast["healed"]["join"]
    assert fast["num_solids"] == 1  # OpenCASCADE's sewing turns the face back


def test_inward_shell_falls_back(tmp_path):
    path = _faces_iges(str(tmp_path / "inward.igs"), [f.Reversed() for f in _box_faces()])
    fast, occ = read_shape(path), read_shape(path, join=False)
    assert fast["healed"]["method"] == "occ" and "inward" in fast["healed"]["join"]
    assert all(f["reversed"] for f in occ["faces"])  # SolidFromShell reversed the shell
    assert_same_model(fast, occ)


def test_sewing_loads_without_the_package():
    """The worker's reader server loads read.py alone (no MPI); it loads sewing.py alike."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("_standalone_read", cad_read.__file__)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod._sewing().__name__ == "_nagata_snap_cad_sewing" and "_nagata_snap_cad_sewing" in sys.modules
    assert os.path.dirname(mod._sewing().__file__) == os.path.dirname(cad_read.__file__)
    assert math.isclose(mod.SEW_RTOL[0], cad_read.SEW_RTOL[0])


# ----------------------------------------------------------------------
# the join's own decisions, on made-up copies
# ----------------------------------------------------------------------
def _copies(points, ends, mid, tangent, curved=None, quarters=None) -> sewing.EdgeCopies:
    """Edge copies: straight from vertex to vertex (quarter points between them) unless given."""
    P = np.asarray(points, dtype=float)
    ends = np.asarray(ends, dtype=np.int64).reshape(-1, 2)
    n = len(ends)
    if quarters is None:
        a, b = P[ends[:, 0]], P[ends[:, 1]]
        quarters = np.stack([0.75 * a + 0.25 * b, 0.25 * a + 0.75 * b], axis=1)
    return sewing.EdgeCopies(P, np.full(len(P), 1e-7), ends, np.full(n, 1e-7), np.zeros(n, dtype=bool),
                             np.zeros(n, dtype=bool) if curved is None else np.asarray(curved, dtype=bool),
                             np.asarray(mid, dtype=float), np.asarray(tangent, dtype=float),
                             np.asarray(quarters, dtype=float))


def test_join_of_made_up_copies():
    tol = 1e-3
    a, b = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]
    # two copies of a line, the second running the other way: joined, one vertex per end
    j = sewing.join_edges(_copies([a, b, b, a], [[0, 1], [2, 3]], [[0.5, 0, 0]] * 2, [[1, 0, 0], [-1, 0, 0]]), tol)
    assert j.edge.tolist() == [0, 0] and j.opposed.tolist() == [False, True] and j.vertex.tolist() == [0, 1, 1, 0]
    assert j.source.tolist() == [0] and j.ends.tolist() == [[0, 1]]
    # the kept curve: a line or circle rather than a B-spline copy, whichever comes first
    j = sewing.join_edges(_copies([a, b, b, a], [[0, 1], [2, 3]], [[0.5, 0, 0]] * 2, [[1, 0, 0], [-1, 0, 0]],
                                  curved=[True, False]), tol)
    assert j.source.tolist() == [1] and j.ends.tolist() == [[1, 0]] and j.opposed.tolist() == [True, False]
    # a gap between the copies' middle points widens the tolerance
    j = sewing.join_edges(_copies([a, b, b, a], [[0, 1], [2, 3]], [[0.5, 0, 0], [0.5, 4e-4, 0]],
                                  [[1, 0, 0], [-1, 0, 0]]), tol)
    assert j.edge_tolerance[0] == pytest.approx(4e-4)
    # ... and so does one at their quarter points
    j = sewing.join_edges(_copies([a, b, b, a], [[0, 1], [2, 3]], [[0.5, 0, 0]] * 2, [[1, 0, 0], [-1, 0, 0]],
                                  quarters=[[[0.25, 0, 0], [0.75, 0, 0]], [[0.75, 6e-4, 0], [0.25, 0, 0]]]), tol)
    assert j.edge_tolerance[0] == pytest.approx(6e-4)
    # closed copies (a unit circle from b, one vertex twice): their direction by the tangent,
    # their quarter points swapped
    ccw = [[[0.0, 1, 0], [0, -1, 0]]]
    j = sewing.join_edges(_copies([b, b], [[0, 0], [1, 1]], [[-1.0, 0, 0]] * 2, [[0, -1, 0], [0, 1, 0]],
                                  quarters=[ccw[0], ccw[0][::-1]]), tol)
    assert j.edge.tolist() == [0, 0] and j.opposed.tolist() == [False, True]
    out = sewing.join_edges(_copies([b, b], [[0, 0], [1, 1]], [[-1.0, 0, 0]] * 2, [[0, -1, 0], [0, 1, 0]],
                                    quarters=ccw * 2), tol)
    assert isinstance(out, str) and "parametrised differently" in out


@pytest.mark.parametrize("points, ends, mid, tangent, why", [
    # vertices chained wider than the tolerance
    ([[0, 0, 0], [6e-4, 0, 0], [1.2e-3, 0, 0], [1, 0, 0]], [[0, 3], [2, 3]], [[0.5, 0, 0]] * 2,
     [[1, 0, 0]] * 2, "wider than the tolerance"),
    # two vertices just beyond the tolerance: a near miss
    ([[0, 0, 0], [1.5e-3, 0, 0], [1, 0, 0], [1, 0, 0]], [[0, 2], [1, 3]], [[0.5, 0, 0]] * 2,
     [[1, 0, 0]] * 2, "within twice the tolerance"),
    # an edge whose two vertices merge
    ([[0, 0, 0], [5e-4, 0, 0]], [[0, 1]], [[2.5e-4, 0, 0]], [[1, 0, 0]], "shorter than the tolerance"),
    # an edge with no other copy
    ([[0, 0, 0], [1, 0, 0]], [[0, 1]], [[0.5, 0, 0]], [[1, 0, 0]], "free edges"),
    # two half-circles and a third copy of one of them
    ([[1, 0, 0], [-1, 0, 0]] * 3, [[0, 1], [2, 3], [4, 5]], [[0, 1, 0]] * 3, [[-1, 0, 0]] * 3,
     "more than two copies"),
    # two pairs of copies between the same vertices, their middle points 1.5 tol apart: a near miss
    ([[0, 0, 0], [1, 0, 0]] * 4, [[0, 1], [2, 3], [4, 5], [6, 7]], [[0.5, 0, 0]] * 2 + [[0.5, 1.5e-3, 0]] * 2,
     [[1, 0, 0]] * 4, "copies of different edges within twice the tolerance"),
    # copies running the same way by their vertices, the other way by their tangents
    ([[0, 0, 0], [1, 0, 0]] * 2, [[0, 1], [2, 3]], [[0.5, 0, 0]] * 2, [[1, 0, 0], [-1, 0, 0]],
     "directions disagree"),
])
def test_join_names_what_it_cannot_sew(points, ends, mid, tangent, why):
    out = sewing.join_edges(_copies(points, ends, mid, tangent), 1e-3)
    assert isinstance(out, str) and why in out, out


def test_outside_of_a_shell_by_a_supporting_plane():
    """A unit cube's six faces (boxes), the plane z = 0 with its normal: outward if -z."""
    lo = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 0], [0, 1, 0], [0, 0, 0], [1, 0, 0]], dtype=float)
    hi = np.array([[1, 1, 0], [1, 1, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1], [1, 1, 1]], dtype=float)
    box = np.stack([lo, hi], axis=1)
    plane = np.zeros(6, dtype=bool)
    plane[0] = True
    shell = np.zeros(6, dtype=np.int64)

    def uses(normal, origin=(0.0, 0.0, 0.0)):
        n, o = np.zeros((6, 3)), np.zeros((6, 3))
        n[0], o[0] = normal, origin
        return sewing.FaceUses(np.arange(6), np.arange(6), np.zeros(6, dtype=bool), 6, plane, o, n, box)

    assert sewing._outside(uses([0, 0, -1]), shell, 1e-9) is None
    assert "inward" in sewing._outside(uses([0, 0, 1]), shell, 1e-9)
    assert sewing._outside(uses([0, 0, -1], [0, 0, 1e-10]), shell, 1e-9) is None  # within the tolerance
    assert "no planar face" in sewing._outside(uses([0, 0, -1], [0, 0, 1e-8]), shell, 1e-9)  # beyond it
    assert "no planar face" in sewing._outside(uses([1, 0, 0], [0.5, 0, 0]), shell, 1e-9)  # cuts the cube


def test_two_solids(tmp_path):
    """Two disjoint bodies: two shells, two solids (OpenCASCADE numbers the faces shell by shell)."""
    def build(occ):
        occ.addBox(0, 0, 0, 1, 1, 1)
        occ.addCylinder(3, 0, 0, 0, 0, 1, 0.5)

    path = _gmsh_iges(str(tmp_path / "two.igs"), build)
    fast, occ = read_shape(path), read_shape(path, join=False)
    assert fast["healed"]["method"] == "join" and fast["num_solids"] == 2
    assert_same_model(fast, occ)


def test_components_are_scipys():
    """The join's components (label propagation) against scipy's connected_components."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(0)
    for _ in range(200):
        n, k = int(rng.integers(1, 60)), int(rng.integers(0, 80))
        pairs = rng.integers(0, n, size=(k, 2))
        ref = connected_components(coo_matrix((np.ones(k), (pairs[:, 0], pairs[:, 1])), shape=(n, n)),
                                   directed=False)[1]
        _, first = np.unique(ref, return_index=True)  # numbered by their lowest node
        rank = np.empty(len(first), dtype=np.int64)
        rank[np.argsort(first)] = np.arange(len(first))
        assert np.array_equal(sewing._components(n, pairs), rank[ref])


def test_lengths_are_numpys_norm():
    """The join's vector lengths are np.linalg.norm's, to the last bit (the decisions at the
    tolerances stay those of the norm), over many magnitudes and shapes."""
    rng = np.random.default_rng(1)
    for shape in [(0, 3), (1, 3), (17, 3), (9, 2, 3)]:
        d = rng.normal(size=shape) * 10.0 ** rng.integers(-150, 150, size=shape)
        assert np.array_equal(sewing._length(d), np.linalg.norm(d, axis=-1))
