"""Boundary vertices that slide on the geometry (nagata_snap.smoothing.slide, the repair's slide stage).

The problem (tests/mpi/slide_mpi.py): on a unit disk with two snapped
levels (Nagata and CAD mode), the boundary vertex at 22.5 degrees is prescribed a place on its
Nagata curve at 36 degrees, past its neighbour at 33.75 degrees.  The
boundary edge between them turns over; interior motion cannot repair that,
only boundary vertices moving along the curve can.
"""

import importlib.util
import json
import os
import pathlib
import subprocess
import sys

import mpi4py.MPI as MPI
import numpy as np
import pytest

from nagata_snap.mesh.corners import corner_vertices

REPO = pathlib.Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("slide_mpi", REPO / "tests" / "mpi" / "slide_mpi.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def check(out):
    """What a successful slide must give (serial or parallel)."""
    s, n = out["slide"], out["no_slide"]
    # without sliding the vertex cannot get there: left short (reported)
    assert n["stage"] == "partial" and n["n_short"] >= 1 and n["n_inverted"] == 0
    # with sliding: valid, nobody short, and vertices did slide
    assert s["stage"] == "slide" and s["n_short"] == 0 and s["n_inverted"] == 0 and s["slid"] >= 2
    # every snapped vertex is exactly where its updated record puts it (no drift later),
    # within the Nagata curves' own distance from the circle (sampled)
    assert s["records_gap"] <= 1e-13
    assert s["on_circle"] <= s["geometry_error"] * (1 + 1e-9)
    assert s["coarse_moved"] == 0.0  # coarse vertices (creases / ends of the curves) never slide
    ang = np.array(s["angles"])
    assert np.all(np.diff(ang) > 1.0)  # still in order along the circle, none overtaken
    assert np.count_nonzero((ang > 22.5 + 1e-6) & (ang < 45.0 - 1e-6)) == 2


@pytest.mark.parametrize("mode", ["nagata", "cad"])
def test_slide_repairs_an_overtaken_boundary_vertex(mode):
    mod = _script()
    out = {"slide": mod.run(MPI.COMM_SELF, True, mode), "no_slide": mod.run(MPI.COMM_SELF, False, mode)}
    check(out)


@pytest.mark.mpi
@pytest.mark.parametrize("mode, split", [("nagata", False), ("cad", False), ("nagata", True),
                                         ("cad", True)])
def test_slide_mpi_same_as_serial(mode, split):
    """Sliding under ``mpiexec -n 2`` as serially; with ``split`` the disk is partitioned
    through the sliding region, so that the processes exchange the facets at the sliding
    vertices they share (``SlideFacets``)."""
    mpiexec = pathlib.Path(sys.executable).parent / "mpiexec"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([str(mpiexec), "-n", "2", sys.executable,
                           str(REPO / "tests" / "mpi" / "slide_mpi.py"), mode] + (["split"] if split else []),
                          capture_output=True, text=True, timeout=600, env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = json.loads([ln for ln in proc.stdout.splitlines() if ln.startswith("{")][-1])
    assert out["size"] == 2
    if split:
        assert out["par"]["slide"]["received_facets"] > 0
    check(out["par"])
    check(out["ser"])
    for k in ("stage", "slid", "n_short"):
        assert out["par"]["slide"][k] == out["ser"]["slide"][k]
    np.testing.assert_allclose(out["par"]["slide"]["angles"], out["ser"]["slide"]["angles"],
                               rtol=0, atol=1e-8)


def test_cad_project_keeps_vertices_on_their_feature(tmp_path):
    """What sliding asks of a 3D CadGeometry (OpenCASCADE): every facet vertex pushed
    off the part comes back onto its own face, a vertex on a CAD edge onto that edge
    (on both its faces).  Checked on the concave cylinder (groove r = 0.6, axis
    y = 0.5, z = 1) against its exact faces; a CAD vertex (on three faces) stays
    on all three."""
    import warnings

    import hard_parts
    from nagata_snap import Snapper
    from nagata_snap.cad import CadGeometry

    path = hard_parts.write_iges("concave_cylinder", str(tmp_path / "cc.igs"))
    md = hard_parts.from_iges(MPI.COMM_SELF, path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        geo = CadGeometry.from_iges(path)
    level = Snapper(md.mesh, md.facet_tags, geo)._level  # the coarse facets and their records
    nodes = level.boundary.nodes[level.snapped]
    x = md.mesh.geometry.x[nodes]  # (nf, 3, 3)
    push = np.random.default_rng(0).normal(size=(int(nodes.max()) + 1, 3))
    out, _ = geo.project(level.records, x + 0.03 * push[nodes])  # one push per vertex

    def r(p):
        return np.hypot(p[..., 1] - 0.5, p[..., 2] - 1.0)

    def on(p):  # which exact faces a point lies on
        return np.stack([np.abs(p[..., 0]) < 1e-9, np.abs(p[..., 0] - 2) < 1e-9,
                         np.abs(p[..., 1]) < 1e-9, np.abs(p[..., 1] - 1) < 1e-9,
                         np.abs(p[..., 2]) < 1e-9, np.abs(r(p) - 0.6) < 1e-9], axis=-1)

    before, after = on(x), on(out)
    assert np.all(before.sum(-1) >= 1) and np.all(before.sum(-1) <= 3)
    corner = before.sum(-1) == 3
    edge = before.sum(-1) == 2
    assert edge.any() and corner.any()
    # the slide stage's corner rule finds exactly the CAD vertices
    rule = corner_vertices(nodes.ravel(), np.repeat(level.records.root, 3), int(nodes.max()) + 1, 3)
    np.testing.assert_array_equal(rule[nodes], corner)
    # still on every face it was on (an edge vertex on both faces of its edge)
    assert np.all(after[before])
    # an edge vertex gets the same point from all its facets
    for v in np.unique(nodes[edge]):
        p = out[edge & (nodes == v)]
        assert np.abs(p - p[0]).max() < 1e-9
    assert np.abs(out - x)[edge].max() > 1e-3  # they did move (along their edge)


def test_cad_project_keeps_corners_at_their_cad_vertex(tmp_path):
    """``CadGeometry.project`` on a real part (``meshes/parts.py`` "plate": holes,
    counterbores, a pocket; STEP through OpenCASCADE, meshed by gmsh): every vertex
    pushed tangentially comes back so that a mesh vertex at a CAD vertex stays on
    that vertex and a vertex on two faces stays on both (OCC's own distances).
    On this mesh most CAD-vertex mesh vertices have no facet with two edges on CAD
    edges (checked below): the corner rule must come from all facets of the vertex."""
    import parts
    from occ_reference import OccShape
    from OCP.BRep import BRep_Tool
    from OCP.TopoDS import TopoDS

    from nagata_snap import Snapper
    from nagata_snap.cad import mesh_cad
    from nagata_snap.cad.read import shape_maps

    path = str(parts.write_part("plate", tmp_path, ("step",))["step"])
    cm, geo = mesh_cad(path, MPI.COMM_SELF, size_factor=0.3, curvature=8)
    level = Snapper(cm.mesh, cm.facet_tags, geo)._level
    nodes = level.boundary.nodes[level.snapped]  # (nf, 3)
    x = cm.mesh.geometry.x[nodes]
    root = np.repeat(level.records.root, 3)
    occ = OccShape(path, cm.unit or "MM")
    vm = shape_maps(occ.shape)[2]
    corners = np.array([[c.X(), c.Y(), c.Z()] for c in (
        BRep_Tool.Pnt_s(TopoDS.Vertex(vm.FindKey(i))) for i in range(1, vm.Extent() + 1))])
    tol = 1e-9 * occ.size

    d = np.linalg.norm(x[:, :, None] - corners[None, None], axis=3)
    at = d.min(axis=2) < tol  # (nf, 3) slots of mesh vertices at a CAD vertex
    target = corners[d.argmin(axis=2)]
    n = int(nodes.max()) + 1
    two = np.zeros(n, dtype=bool)  # a facet of the vertex has both its edges there on CAD edges
    two[nodes[np.count_nonzero(level.records.params[..., 2:] == 1.0, axis=2) >= 2]] = True
    assert at.any() and np.count_nonzero(~two[np.unique(nodes[at])]) >= 4

    # one tangential push per vertex, a tenth of its shortest facet edge
    e = x - np.roll(x, 1, axis=1)
    h = np.full(n, np.inf)
    np.minimum.at(h, nodes, np.repeat(np.linalg.norm(e, axis=2).min(axis=1, keepdims=True), 3, axis=1))
    nrm = np.ones((n, 3))  # in the plane of one of the vertex's facets
    nrm[nodes] = np.repeat(np.cross(e[:, 1], e[:, 2])[:, None], 3, axis=1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    push = np.random.default_rng(1).normal(size=(n, 3))
    push -= np.einsum("ij,ij->i", push, nrm)[:, None] * nrm
    push *= (0.1 * h / np.linalg.norm(push, axis=1))[:, None]
    out, _ = geo.project(level.records, x + push[nodes])

    assert np.linalg.norm(out - target, axis=2)[at].max() <= tol
    # vertices on exactly two faces: on both (OCC's distance to each face)
    pairs = np.unique(np.stack([nodes.ravel(), root], 1), axis=0)
    nfaces = np.bincount(pairs[:, 0], minlength=n)
    on_edge = nfaces[pairs[:, 0]] == 2
    pos = np.zeros((n, 3))
    pos[nodes.ravel()] = out.reshape(-1, 3)
    dist = occ.face_distance(pairs[on_edge, 1], pos[pairs[on_edge, 0]])
    assert on_edge.sum() >= 20 and dist.max() <= tol
    # and every slot of a vertex got the same point
    assert np.abs(out.reshape(-1, 3) - pos[nodes.ravel()]).max() <= tol
