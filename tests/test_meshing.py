"""nagata_snap.meshing.mesh_cad_file: gmsh meshes of CAD files with each boundary facet's CAD entity.

Truth is OpenCASCADE's geometry through gmsh, in a model re-imported from the
same file (the same entity tags): every facet vertex must lie on its facet's
entity (``gmsh.model.getClosestPoint``), the (u, v) / t handed back must map
to the vertex (``gmsh.model.getValue``), a vertex classified on a CAD corner
must be that corner and one on a CAD edge must lie on it, and the facet
tags must equal the facet entities.  The parts are meshes/parts.py's, meshed
coarsely (default size: 0.1 of the diagonal, 12 elements per 2 pi).
"""

from __future__ import annotations

import math
import os
import subprocess
import sys

import gmsh
import numpy as np
import pytest
from mpi4py import MPI

import parts  # meshes/ is on sys.path (conftest.py)
from nagata_snap.meshing import MAX_MOVE_RATIO, CadMesh, gmsh_session, import_cad, mesh_cad_file

HERE = os.path.dirname(os.path.abspath(__file__))
TOL = 1e-9  # relative to the model size


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    out = tmp_path_factory.mktemp("cad")
    return {name: parts.write_part(name, out, ("step", "iges", "brep", "iges_brep")) for name in parts.PARTS}


def _facet_tag_values(cm: CadMesh) -> np.ndarray:
    facets = cm.facets.facet_indices(cm.mesh)
    pos = np.searchsorted(cm.facet_tags.indices, facets)
    assert np.array_equal(cm.facet_tags.indices[pos], facets)  # every boundary facet is tagged
    return cm.facet_tags.values[pos]


def check_on_cad(cm: CadMesh, path, tol: float = TOL, per_face_tags: bool = True) -> dict:
    """Assert the facet/vertex data against OCC (gmsh model of the same file); return the worst figures."""
    tdim = cm.mesh.topology.dim
    fdim = tdim - 1
    x = cm.mesh.geometry.x
    X = x[cm.facets.nodes]  # (nf, nfv, 3)
    nf = len(cm.facet_entity)
    assert cm.node_params.shape == (nf, tdim, fdim)
    assert cm.node_entity_dim.shape == cm.node_entity_tag.shape == (nf, tdim)
    size = cm.model_size
    worst = {"closest": 0.0, "value": 0.0, "edge": 0.0, "corner": 0.0}
    with gmsh_session("truth"):
        import_cad(path, cm.unit or "MM")
        faces = {t for _, t in gmsh.model.getEntities(fdim)}
        assert set(np.unique(cm.facet_entity)) <= faces
        for e in np.unique(cm.facet_entity):  # one batched OCC call per CAD face
            sel = cm.facet_entity == e
            P = X[sel].reshape(-1, 3)
            cp, _ = gmsh.model.getClosestPoint(fdim, int(e), P.ravel())
            worst["closest"] = max(worst["closest"], np.abs(np.reshape(cp, (-1, 3)) - P).max() / size)
            uv = cm.node_params[sel].reshape(-1, fdim)
            S = np.reshape(gmsh.model.getValue(fdim, int(e), uv.ravel()), (-1, 3))
            worst["value"] = max(worst["value"], np.abs(S - P).max() / size)
            # the facet's own (u, v) triangle is the one gmsh meshed: no jump across a seam
            c = np.reshape(gmsh.model.getValue(fdim, int(e), cm.node_params[sel].mean(axis=1).ravel()), (-1, 3))
            diam = np.linalg.norm(X[sel] - X[sel][:, :1], axis=2).max(axis=1)
            assert np.all(np.linalg.norm(c - X[sel].mean(axis=1), axis=1) <= diam + tol * size)
            # every vertex is classified on the face or on its closure
            closure = {(fdim, int(e))} | set(gmsh.model.getBoundary([(fdim, int(e))], combined=False,
                                                                    oriented=False))
            closure |= set(gmsh.model.getBoundary([d for d in closure if d[0] == 1], combined=False,
                                                  oriented=False)) if tdim == 3 else set()
            got = set(zip(cm.node_entity_dim[sel].ravel().tolist(), cm.node_entity_tag[sel].ravel().tolist(),
                          strict=True))
            assert got <= closure
        for (d, t) in set(zip(cm.node_entity_dim.ravel().tolist(), cm.node_entity_tag.ravel().tolist(), strict=True)):
            P = X[(cm.node_entity_dim == d) & (cm.node_entity_tag == t)]
            if d == 0:
                corner = np.asarray(gmsh.model.getValue(0, t, []))
                worst["corner"] = max(worst["corner"], np.abs(P - corner).max() / size)
            elif d < fdim:
                cp, _ = gmsh.model.getClosestPoint(1, t, P.ravel())
                worst["edge"] = max(worst["edge"], np.abs(np.reshape(cp, (-1, 3)) - P).max() / size)
        for (d, t), info in cm.entities.items():  # samples on their entities, inside the bounding box
            assert info.kind == gmsh.model.getType(d, t)
            assert np.all(info.points >= info.bbox[0] - tol * size) and np.all(info.points <= info.bbox[1] + tol * size)
            if d > 0:
                S = np.reshape(gmsh.model.getValue(d, t, info.params.ravel()), (-1, 3))
                assert np.abs(S - info.points).max() <= tol * size
    for key, value in worst.items():
        assert value <= tol, (key, value)
    if per_face_tags:
        assert np.array_equal(_facet_tag_values(cm), cm.facet_entity)
    return worst


def _mesh_measure(cm: CadMesh) -> float:
    """Total volume (area) of the cells, on every process."""
    tdim = cm.mesh.topology.dim
    nc = cm.mesh.topology.index_map(tdim).size_local
    p = cm.mesh.geometry.x[cm.mesh.geometry.dofmaps[0][:nc, : tdim + 1]][:, :, :tdim]
    m = np.abs(np.linalg.det(p[:, 1:] - p[:, :1])).sum() / math.factorial(tdim)
    return cm.mesh.comm.allreduce(m)


@pytest.mark.parametrize("name", list(parts.PARTS))
def test_mesh_step_part(files, name):
    part = parts.PARTS[name]
    cm = mesh_cad_file(files[name]["step"], MPI.COMM_WORLD)
    tdim = cm.mesh.topology.dim
    assert tdim == part.dim and cm.mesh.geometry.dim == part.dim
    assert cm.unit == "MM"
    assert cm.model_size == pytest.approx(parts.model_size(name), rel=1e-6)
    assert cm.size == pytest.approx(0.1 * cm.model_size)
    # every exterior facet of the DOLFINx mesh is in cm.facets (and has an entity)
    cm.mesh.topology.create_connectivity(tdim - 1, tdim)
    from dolfinx.mesh import exterior_facet_indices
    assert len(cm.facet_entity) == len(exterior_facet_indices(cm.mesh.topology)) > 0
    check_on_cad(cm, files[name]["step"])
    # every CAD face of the part carries facets; cells tagged by their volume
    with parts.part_model(name):
        n_faces, _ = parts.measure(part.dim)
        volumes = [t for _, t in gmsh.model.getEntities(part.dim)]
    mass = parts.occ_mass(files[name]["brep"], part.dim)
    exterior = n_faces - (1 if name == "assembly" else 0)  # the shared disk is interior
    assert len(np.unique(cm.facet_entity)) == exterior
    assert set(np.unique(cm.cell_tags.values)) == set(volumes)
    assert _mesh_measure(cm) == pytest.approx(mass, rel=0.05)  # coarse straight cells


CATIA_CONE = os.path.join(HERE, "..", "meshes", "corpus", "cone_catia_v5.igs")


def test_faces_beside_the_sewn_solid_removed(monkeypatch):
    """A faces-only IGES file from CATIA V5 (corpus): gmsh's sewing adds a solid with copies of two
    of its faces and keeps the originals beside it; meshed, their nodes are in no tetrahedron and
    DOLFINx aborted the whole MPI job.  They are removed; where such faces remained, the mesher
    names them (a RuntimeError, not an abort)."""
    import nagata_snap.meshing as meshing

    cm = mesh_cad_file(CATIA_CONE, MPI.COMM_WORLD)
    check_on_cad(cm, CATIA_CONE, tol=1e-6)
    assert len(np.unique(cm.facet_entity)) == 3  # the cone's two halves and its base
    monkeypatch.setattr(meshing, "_remove_free_faces", lambda: None)
    with pytest.raises(RuntimeError, match=r"surfaces 1, 2 are meshed but bound no tetrahedron"):
        mesh_cad_file(CATIA_CONE, MPI.COMM_WORLD)


@pytest.mark.parametrize("name,fmt", [("plate_filleted", "brep"), ("revolved", "brep"),
                                      ("profile_2d", "brep"), ("assembly", "iges_brep"),
                                      ("lofted_blade", "iges_brep"), ("plate_holes_2d", "iges")])
def test_mesh_other_formats(files, name, fmt):
    cm = mesh_cad_file(files[name][fmt], MPI.COMM_WORLD)
    assert cm.unit == (None if fmt == "brep" else "MM")
    check_on_cad(cm, files[name][fmt])


def test_mesh_faces_only_iges(files):
    """Faces-only IGES is sewn: edge nodes sit in the sewing gaps (~1e-8 of the model size)."""
    path = files["plate"]["iges"]
    cm = mesh_cad_file(path, MPI.COMM_WORLD)
    worst = check_on_cad(cm, path, tol=1e-6)
    assert worst["closest"] > 1e-12  # the gaps are real (if this fails, tighten the tolerance)


def test_unit_and_size(files):
    """unit="M" scales STEP coordinates by 1e-3; an explicit size is used as given."""
    mm = mesh_cad_file(files["thin_wall"]["step"], MPI.COMM_WORLD, size=8.0)
    m = mesh_cad_file(files["thin_wall"]["step"], MPI.COMM_WORLD, size=8.0e-3, unit="M")
    assert m.unit == "M" and m.size == 8.0e-3 and mm.size == 8.0
    # (gmsh's bounding boxes are enlarged by OCC's tolerance, 1e-7 in either unit)
    assert m.model_size == pytest.approx(1e-3 * mm.model_size, rel=1e-5)
    assert np.abs(m.mesh.geometry.x.min(axis=0)).max() <= 1e-12  # the wall starts at 0 (x, y, z)
    assert m.mesh.geometry.x.max(axis=0) == pytest.approx([50e-3, 50e-3, 40e-3], rel=1e-9)
    check_on_cad(m, files["thin_wall"]["step"])


def test_whole_boundary_tag_and_order2(files):
    path = files["concave_cylinder"]["step"]
    cm = mesh_cad_file(path, MPI.COMM_WORLD, per_face_tags=False, order=2)
    assert cm.mesh.geometry.cmaps[0].degree == 2
    assert set(np.unique(_facet_tag_values(cm))) == {1}
    assert len(np.unique(cm.facet_entity)) == 8
    check_on_cad(cm, path, per_face_tags=False)
    # the mid-nodes are gmsh's, on the CAD: the curved boundary's nodes lie on the groove
    from dolfinx.mesh import entities_to_geometry
    groove = cm.facets.facet_indices(cm.mesh)[cm.facet_entity == _groove_tag(path)]
    nodes = np.unique(entities_to_geometry(cm.mesh, 2, groove))
    x = cm.mesh.geometry.x[nodes]
    assert np.abs(np.hypot(x[:, 1] - 20, x[:, 2] - 30) - 10).max() <= 1e-9 * cm.model_size


def _groove_tag(path) -> int:
    with gmsh_session("groove"):
        import_cad(path)
        return next(t for _, t in gmsh.model.getEntities(2) if gmsh.model.getType(2, t) == "Cylinder")


def test_gmsh_session_left_as_found(files):
    path = files["thin_wall"]["step"]
    assert not gmsh.isInitialized()
    mesh_cad_file(path, MPI.COMM_SELF)
    assert not gmsh.isInitialized()
    gmsh.initialize(interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 123.0)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 3)
        gmsh.model.add("mine")
        gmsh.model.occ.addSphere(0, 0, 0, 1)
        gmsh.model.occ.synchronize()
        mesh_cad_file(path, MPI.COMM_SELF, curvature=10)
        assert gmsh.isInitialized() and gmsh.model.getCurrent() == "mine"
        assert len(gmsh.model.getEntities(3)) == 1
        assert gmsh.option.getNumber("Mesh.MeshSizeMax") == 123.0
        assert gmsh.option.getNumber("Mesh.MeshSizeFromCurvature") == 3
        assert gmsh.option.getString("Geometry.OCCTargetUnit") == ""
        with pytest.raises(ValueError):
            mesh_cad_file(path.with_suffix(".txt"), MPI.COMM_SELF)
        assert gmsh.model.getCurrent() == "mine"
    finally:
        gmsh.finalize()


def test_bad_input(tmp_path, files):
    with pytest.raises(FileNotFoundError, match=r"missing\.step: no such CAD file"):
        mesh_cad_file(tmp_path / "missing.step", MPI.COMM_WORLD)
    garbage = tmp_path / "garbage.step"
    garbage.write_bytes(b"\x00\x01 this is not STEP at all \xff" * 50)
    with pytest.raises(ValueError, match=r"garbage\.step: gmsh/OpenCASCADE cannot read this file"):
        mesh_cad_file(garbage, MPI.COMM_WORLD)
    empty = tmp_path / "empty.step"
    empty.write_text("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nFILE_NAME('empty','',(''),(''),'','','');\n"
                     "FILE_SCHEMA(('AUTOMOTIVE_DESIGN'));\nENDSEC;\nDATA;\nENDSEC;\nEND-ISO-10303-21;\n")
    with pytest.raises(ValueError, match=r"empty\.step: .*(no shapes|cannot read)"):
        mesh_cad_file(empty, MPI.COMM_WORLD)
    with pytest.raises(ValueError, match=r"unknown CAD file suffix '\.stl'"):
        mesh_cad_file(tmp_path / "part.stl", MPI.COMM_WORLD)
    with pytest.raises(ValueError, match="unknown length unit 'parsec'"):
        mesh_cad_file(files["plate"]["step"], MPI.COMM_WORLD, unit="parsec")
    with pytest.raises(ValueError, match="size must be a positive length"):
        mesh_cad_file(files["plate"]["step"], MPI.COMM_WORLD, size=-1.0)
    with pytest.raises(ValueError, match="order must be 1 or 2"):
        mesh_cad_file(files["plate"]["step"], MPI.COMM_WORLD, order=3)
    # an open surface (one cylindrical face, no solid, not planar)
    shell = tmp_path / "shell.step"
    with gmsh_session("shell"):
        gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.model.occ.remove([(3, 1)])
        gmsh.model.occ.remove([(2, 2), (2, 3)], recursive=True)
        gmsh.model.occ.synchronize()
        gmsh.write(str(shell))
    with pytest.raises(ValueError, match=r"shell\.step: no solid in the file and its 1 faces do not close"
                       r"(.|\n)*To try next: export the solid"):
        mesh_cad_file(shell, MPI.COMM_WORLD)


@pytest.mark.mpi
def test_mesh_mpi_matches_serial(tmp_path):
    """mpiexec -n 2: every facet's entity and every vertex's (u, v) and classification equal
    the serial run's (compared by the vertices' input global indices)."""
    mpiexec = os.path.join(os.path.dirname(sys.executable), "mpiexec")
    cmd = [mpiexec, "-n", "2", sys.executable, os.path.join(HERE, "mpi", "meshing_mpi.py"), str(tmp_path)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("meshing_mpi")]
    assert lines == [f"meshing_mpi {name} ok" for name in ("plate_holes_2d", "plate_filleted", "seamed",
                                                          "assembly", "missing")], r.stdout[-3000:]


def test_verbose_progress(files, capfd):
    mesh_cad_file(files["thin_wall"]["step"], MPI.COMM_SELF, verbose=True)
    out = capfd.readouterr().out
    for d in (1, 2, 3):
        assert f"nagata_snap.meshing: thin_wall.step: {d}D mesh," in out
    mesh_cad_file(files["thin_wall"]["step"], MPI.COMM_SELF)
    assert "nagata_snap.meshing" not in capfd.readouterr().out


# ----------------------------------------------------------------------
# retries when gmsh fails
# ----------------------------------------------------------------------
OVERLAP = "Invalid boundary mesh (overlapping facets) on surface 3 surface 7"


def _failing_generate(monkeypatch, fail):
    """Make ``gmsh.model.mesh.generate(d)`` raise gmsh's error where ``fail(call, d)`` says so
    (calls counted from 0 over the 3D steps), else mesh as gmsh does."""
    real = gmsh.model.mesh.generate
    calls = {"3d": 0}

    def generate(dim=3):
        if dim == 3:
            k = calls["3d"]
            calls["3d"] += 1
            if fail(k):
                raise Exception(OVERLAP)
        return real(dim)

    monkeypatch.setattr(gmsh.model.mesh, "generate", generate)
    return calls


def test_retry_after_gmsh_failure(files, monkeypatch):
    """The first attempt fails as gmsh does on some parts at the default size: the retry with
    half the size meshes the part, says what it retries, and gives the mesh that size gives."""
    path = files["box_fillet_chamfer"]["step"]
    direct = mesh_cad_file(path, MPI.COMM_SELF, size_factor=0.05)  # what the retry must give
    lines = []
    calls = _failing_generate(monkeypatch, lambda k: k == 0)
    cm = mesh_cad_file(path, MPI.COMM_SELF, on_retry=lines.append)
    assert calls["3d"] == 2
    assert len(lines) == 1 and OVERLAP in lines[0] and "the options asked for" in lines[0]
    assert "retrying with 0.5 x the element size" in lines[0]
    assert cm.meshed_with == "0.5 x the element size"
    assert cm.size == pytest.approx(direct.size, rel=1e-12)
    assert cm.mesh.topology.index_map(3).size_global == direct.mesh.topology.index_map(3).size_global
    np.testing.assert_allclose(_mesh_measure(cm), _mesh_measure(direct), rtol=1e-12)
    check_on_cad(cm, path)


def test_each_retry_changes_one_option(files, monkeypatch):
    """All but the last retry fail: each line names the attempt that failed and the next; the
    last one (HXT volume algorithm, the size asked for) meshes the part."""
    path = files["box_fillet_chamfer"]["step"]
    lines = []
    _failing_generate(monkeypatch, lambda k: k < 4)
    cm = mesh_cad_file(path, MPI.COMM_SELF, curvature=12, on_retry=lines.append)
    assert [ln.split("; retrying with ")[1] for ln in lines] == [
        "0.5 x the element size", "curvature sizing off",
        "gmsh's MeshAdapt surface algorithm (Mesh.Algorithm = 1)",
        "gmsh's HXT volume algorithm (Mesh.Algorithm3D = 10)"]
    assert cm.meshed_with == "gmsh's HXT volume algorithm (Mesh.Algorithm3D = 10)"
    assert cm.size == pytest.approx(0.1 * cm.model_size, rel=1e-12)
    check_on_cad(cm, path)
    assert not gmsh.isInitialized()  # the session is closed after the retries


def test_every_retry_fails(files, monkeypatch):
    """gmsh fails every time: the error names gmsh's failure for every attempt and its size."""
    from nagata_snap.errors import MeshingError

    path = files["box_fillet_chamfer"]["step"]
    _failing_generate(monkeypatch, lambda k: True)
    with pytest.raises(MeshingError) as e:
        mesh_cad_file(path, MPI.COMM_SELF, size=20.0)
    msg = str(e.value)
    assert msg.count(OVERLAP) == 5 and "with the options asked for (size 20)" in msg
    assert "nor with 0.5 x the element size (size 10)" in msg and "curvature sizing off" in msg
    assert e.value.sizes == (20.0, 10.0, 20.0, 20.0, 20.0)
    assert isinstance(e.value, RuntimeError)  # callers catching gmsh's RuntimeError still do
    with pytest.raises(MeshingError):  # no retries asked for: the first failure is final
        mesh_cad_file(path, MPI.COMM_SELF, size=20.0, retries=())


def test_retry_in_a_callers_gmsh_session(files, monkeypatch):
    """In a gmsh session the caller opened, a retry re-imports into a new model instead of
    restarting gmsh: the caller's model and options are left as they were."""
    path = files["box_fillet_chamfer"]["step"]
    gmsh.initialize(argv=[], readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("mine")
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.Algorithm", 8)
        _failing_generate(monkeypatch, lambda k: k == 0)
        cm = mesh_cad_file(path, MPI.COMM_SELF)
        assert cm.meshed_with == "0.5 x the element size"
        assert gmsh.isInitialized() and gmsh.model.getCurrent() == "mine"
        assert gmsh.model.getEntities(3) == [(3, 1)]
        assert gmsh.option.getNumber("Mesh.Algorithm") == 8
    finally:
        gmsh.finalize()


def test_points_embedded_in_a_face_are_in_its_closure():
    """gmsh puts a node on a point embedded in a face (a sphere's pole where the file had a
    degenerate edge, in a CATIA V4 STEP): the face's elements use it, and its parameters on
    the face map to the point (gmsh.model.getValue, the truth)."""
    from nagata_snap.meshing import _boundary_table

    with gmsh_session("embedded") as set_option:
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        p = gmsh.model.occ.addPoint(0.5, 0.37, 1.0)
        gmsh.model.occ.synchronize()
        top = next(t for _, t in gmsh.model.getEntities(2)
                   if abs(gmsh.model.getBoundingBox(2, t)[2] - 1.0) < 1e-6
                   and abs(gmsh.model.getBoundingBox(2, t)[5] - 1.0) < 1e-6)
        gmsh.model.mesh.embed(0, [p], 2, top)
        set_option("Mesh.MeshSizeMax", 0.5)
        gmsh.model.mesh.generate(3)
        table = _boundary_table(3)
        node = gmsh.model.mesh.getNodes(0, p)[0][0] - 1
        rows, cols = np.nonzero(table["keys"] == node)
        assert len(rows) >= 3 and set(table["entity"][rows].tolist()) == {top}
        uv = table["params"][rows, cols]  # (k, 2) on the face, one per element using the node
        S = np.reshape(gmsh.model.getValue(2, top, uv.ravel()), (-1, 3))
        assert np.abs(S - [0.5, 0.37, 1.0]).max() < 1e-12


def _tube_step(tmp_path) -> str:
    """A thin tube (radii 1 and 0.95, height 2) as STEP: coarse cells span its wall."""
    path = str(tmp_path / "tube.step")
    with gmsh_session("tube"):
        outer = gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, 2, 1.0)
        inner = gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, 2, 0.95)
        gmsh.model.occ.cut([(3, outer)], [(3, inner)])
        gmsh.model.occ.synchronize()
        gmsh.write(path)
    return path


def _exact_move_ratio(cm: CadMesh) -> float:
    """The first level's largest boundary move over the cell heights, from the exact tube
    (radii 1 and 0.95, axis z): an edge midpoint is |R - |(x, y)|| from a side of radius R,
    0 from a planar end."""
    X = cm.mesh.geometry.x
    P, apex = X[cm.facets.nodes], X[cm.facets.opposite]
    n = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    height = np.abs(np.einsum("ij,ij->i", apex - P[:, 0], n)) / np.linalg.norm(n, axis=1)
    r = np.linalg.norm(P[:, :, :2], axis=2)
    mids = np.linalg.norm(((P + np.roll(P, 1, axis=1)) / 2)[:, :, :2], axis=2)
    dist = np.zeros(len(P))
    for R in (1.0, 0.95):
        side = np.all(np.abs(r - R) < 1e-9, axis=1)
        dist[side] = np.abs(R - mids[side]).max(axis=1)
    return float((dist / height).max())


def test_move_ratio_and_finer_mesh_for_snapping(tmp_path):
    """A thin tube meshed at 12 elements per 2 pi with cells twice as long as its wall is thick:
    the sides' edge midpoints are farther from the cylinders than the cells across the wall are
    high.  ``move_ratio`` equals the exact ratio; above ``max_move_ratio`` the mesher doubles
    the curvature sizing until the ratio is below it and says so, and the exact ratio of the
    mesh it returns is below it too."""
    path = _tube_step(tmp_path)
    kept = mesh_cad_file(path, MPI.COMM_SELF, size=0.5, curvature=12, max_move_ratio=math.inf)
    assert kept.meshed_with == ""
    assert kept.move_ratio > 1.0
    assert kept.move_ratio == pytest.approx(_exact_move_ratio(kept), rel=1e-6)
    assert kept.move_ratio < MAX_MOVE_RATIO  # the default leaves this mesh as it is
    default = mesh_cad_file(path, MPI.COMM_SELF, size=0.5, curvature=12)
    assert default.meshed_with == "" and default.move_ratio == pytest.approx(kept.move_ratio, rel=1e-12)

    lines: list[str] = []
    cm = mesh_cad_file(path, MPI.COMM_SELF, size=0.5, curvature=12, max_move_ratio=1.0,
                       on_retry=lines.append)
    assert lines and "meshing again with 24 elements per 2 pi" in lines[0]
    assert "curvature sizing" in cm.meshed_with and "for snapping" in cm.meshed_with
    assert cm.move_ratio <= 1.0
    assert cm.move_ratio == pytest.approx(_exact_move_ratio(cm), rel=1e-6)
    assert cm.mesh.topology.index_map(3).size_global > kept.mesh.topology.index_map(3).size_global
    check_on_cad(cm, path)

    off = mesh_cad_file(path, MPI.COMM_SELF, size=0.5, curvature=12, max_move_ratio=None)
    assert math.isnan(off.move_ratio) and off.meshed_with == ""
    assert off.mesh.topology.index_map(3).size_global == kept.mesh.topology.index_map(3).size_global
