"""Reading CAD files: errors named, malformed files survived (nagata_snap.cad.read / .worker).

* every way a file can be unusable (missing, unknown extension, unreadable,
  empty shape, a face that cannot be converted, a mesh that does not match)
  gives :class:`CadError` naming the file, face or facet;
* fuzzing: mutated STEP and IGES files (truncated, garbled bytes, deleted
  chunks, wrong entity references, NaN and huge coordinates) read through
  :meth:`CadGeometry.from_file` give a geometry or :class:`CadError`, never
  another exception; OpenCASCADE crashes and hangs on some of them, which the
  reader process reports as :class:`CadError` (this process survives).
"""

from __future__ import annotations

import os
import random
import re
from pathlib import Path

import gmsh
import numpy as np
import pytest

from nagata_snap.cad import CadError, CadGeometry
from nagata_snap.cad import read as cad_read

#: mutated files per format and test run
FUZZ_PER_FORMAT = 250
#: seconds a mutated file may keep the reader busy
FUZZ_TIMEOUT = 1.0


def build_part(path: str) -> None:
    """A small part: a box with a round hole, a filleted edge and a spherical dimple."""
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        b = occ.addBox(0, 0, 0, 1, 0.6, 0.3)
        h = occ.addCylinder(0.3, 0.3, -1, 0, 0, 3, 0.1)
        s = occ.addSphere(0.75, 0.3, 0.3, 0.12)
        out, _ = occ.cut([(3, b)], [(3, h), (3, s)])
        occ.synchronize()
        occ.fillet([out[0][1]], [1], [0.05])
        occ.synchronize()
        gmsh.write(path)
    finally:
        gmsh.finalize()


@pytest.fixture(scope="module")
def sources(tmp_path_factory):
    d = tmp_path_factory.mktemp("src")
    out = {}
    for ext in ("step", "igs"):
        p = str(d / f"part.{ext}")
        build_part(p)
        out[ext] = p
    return out


def build_vase(path: str) -> None:
    """A solid of revolution of a profile with a cone and a B-spline (no analytic surface), with
    a B-spline prism beside it (a linear extrusion of a B-spline curve)."""
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        occ = gmsh.model.occ
        pts = [occ.addPoint(x, 0, z) for x, z in ((0, 0), (1.0, 0), (1.2, 0.3), (1.4, 0.6), (0.8, 0.9),
                                                  (0.9, 1.2), (0, 1.2))]
        loop = occ.addCurveLoop([occ.addLine(pts[0], pts[1]), occ.addLine(pts[1], pts[2]),  # a cone
                                 occ.addBSpline(pts[2:6]), occ.addLine(pts[5], pts[6]), occ.addLine(pts[6], pts[0])])
        occ.revolve([(2, occ.addPlaneSurface([loop]))], 0, 0, 0, 0, 0, 1, 2 * np.pi)
        base = [occ.addPoint(3 + x, y, 0) for x, y in ((0, 0), (1, 0.2), (1.2, 1), (0.3, 0.8))]
        prism = occ.addCurveLoop([occ.addBSpline(base[:3]), occ.addLine(base[2], base[3]),
                                  occ.addLine(base[3], base[0])])
        occ.extrude([(2, occ.addPlaneSurface([prism]))], 0, 0, 0.5)
        occ.synchronize()
        gmsh.write(path)
    finally:
        gmsh.finalize()


@pytest.mark.parametrize("ext", ["step", "igs"])
def test_faces_keep_the_files_parameters_unless_converted(tmp_path, ext):
    """Every face not marked ``converted`` is, at the file's ``(u, v)`` (through the face's
    parameter map where it was recognised as analytic), OpenCASCADE's own surface point
    there; the B-spline extrusion keeps its parameters, the revolved B-spline cannot."""
    from occ_reference import OccShape
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.BRepTools import BRepTools

    path = str(tmp_path / f"vase.{ext}")
    build_vase(path)
    geo = CadGeometry.from_file(path, isolate=False)
    occ = OccShape(path)
    kinds = {}
    rng = np.random.default_rng(3)
    for face, ours in zip(occ.faces, geo.model.faces, strict=True):
        kind = type(ours.surface).__name__
        kinds[kind, ours.converted] = kinds.get((kind, ours.converted), 0) + 1
        if ours.converted:
            continue
        u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
        uv = np.c_[rng.uniform(u0, u1, 40), rng.uniform(v0, v1, 40)]
        a = BRepAdaptor_Surface(face)
        want = np.array([a.Value(u, v).Coord() for u, v in uv])
        mine = uv if ours.uv_map is None else np.c_[uv, np.ones(len(uv))] @ ours.uv_map
        got = ours.surface.evaluate(mine[:, 0], mine[:, 1])[0]
        assert np.abs(got - want).max() <= 1e-9 * occ.size, kind
    assert kinds[("NurbsSurface", False)] == 1  # the extrusion of the B-spline, not converted
    assert kinds[("NurbsSurface", True)] == 1  # the revolved B-spline: rational circles reparametrise
    assert kinds[("Plane", False)] >= 4 and kinds[("Cone", False)] == 1


def test_revolved_radial_line_is_converted_not_refused(tmp_path):
    """A plane face written as a surface of revolution of a radial line (an annulus) has polar
    parameters, no affine map onto the plane: it is converted to NURBS (it was refused), and
    its surface is the exact annulus."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
    from OCP.BRepTools import BRepTools
    from OCP.Geom import Geom_Line, Geom_SurfaceOfRevolution
    from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt

    radial = Geom_Line(gp_Pnt(1, 0, 0), gp_Dir(1, 0, 0))
    surface = Geom_SurfaceOfRevolution(radial, gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(0, 0, 1)))
    path = str(tmp_path / "annulus.brep")
    BRepTools.Write_s(BRepBuilderAPI_MakeFace(surface, 0.0, 1.5, 0.0, 1.0, 1e-7).Face(), path)
    geo = CadGeometry.from_file(path, isolate=False)
    (face,) = geo.model.faces
    assert face.converted
    b = face.surface.bounds
    u, v = np.meshgrid(np.linspace(*b[0], 9), np.linspace(*b[1], 9))
    P = face.surface.evaluate(u.ravel(), v.ravel())[0]
    r = np.hypot(P[:, 0], P[:, 1])
    assert np.abs(P[:, 2]).max() <= 1e-12 and r.min() >= 1 - 1e-9 and r.max() <= 2 + 1e-9
    assert np.arctan2(P[:, 1], P[:, 0]).max() >= 1.4  # the quarter turn is covered


def test_faces_on_no_solid_are_counted(tmp_path):
    """A face left beside the solid (a construction profile written with it) is read and
    counted in the summary as on no solid; the solid's faces name their solid."""
    path = str(tmp_path / "box_and_disk.step")
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 1, 1, 1)
        gmsh.model.occ.addDisk(3, 0, 0, 0.5, 0.5)
        gmsh.model.occ.synchronize()
        gmsh.write(path)
    finally:
        gmsh.finalize()
    model = CadGeometry.from_file(path, isolate=False).model
    free = [f for f in model.faces if not f.solids]
    assert model.num_solids == 1 and len(model.faces) == 7 and len(free) == 1
    assert free[0].surface.kind == "plane" and "7 faces (7 plane; 1 on no solid)" in model.summary()


# ----------------------------------------------------------------------
# errors
# ----------------------------------------------------------------------
def test_valid_files_read(sources):
    for p in sources.values():
        geo = CadGeometry.from_file(p)
        assert geo.param_dim == 2 and geo.num_entities >= 8 and geo.model.num_solids == 1


@pytest.mark.parametrize("isolate", [True, False])
def test_unusable_files_are_named(tmp_path, isolate):
    cases = {
        "missing.step": (None, "does not exist"),
        "notes.txt": ("hello", "unknown CAD file extension"),
        "garbage.step": ("this is not STEP\n" * 20, "cannot read it as a STEP file"),
        "garbage.igs": ("x" * 80 + "\n", "cannot read it as a IGES file|empty shape"),
        "empty.brep": ("", "cannot read it as a BREP file"),
        "empty.step": ("ISO-10303-21;\nHEADER;\nENDSEC;\nDATA;\nENDSEC;\nEND-ISO-10303-21;\n",
                       "no shape|empty shape|cannot read"),
    }
    for name, (text, match) in cases.items():
        p = tmp_path / name
        if text is not None:
            p.write_text(text)
        with pytest.raises(CadError, match=match) as info:
            CadGeometry.from_file(p, isolate=isolate)
        assert os.fspath(p) in str(info.value) or name in str(info.value)


def test_unknown_unit(sources):
    with pytest.raises(CadError, match="unknown length unit 'FURLONG'"):
        CadGeometry.from_file(sources["step"], unit="furlong", isolate=False)


def test_face_that_cannot_be_converted_is_named(sources, monkeypatch):
    """A face neither analytic nor recognised, whose NURBS conversion fails."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert  # noqa: F401

    real = cad_read._surface

    def odd(face, *args):
        d, _ = real(face, *args)
        if d["type"] == "cylinder":
            return {"type": "OtherSurface"}, True
        return d, False

    class Failing:
        def __init__(self, *a, **k):
            raise RuntimeError("Standard_ConstructionError")

    monkeypatch.setattr(cad_read, "_surface", odd)
    monkeypatch.setattr("OCP.BRepBuilderAPI.BRepBuilderAPI_NurbsConvert", Failing)
    with pytest.raises(CadError, match=r"face \d+ \(OtherSurface surface\): OpenCASCADE cannot "
                                       r"convert it to NURBS: RuntimeError"):
        CadGeometry.from_file(sources["step"], isolate=False)


def test_mesh_that_does_not_match_the_cad(sources):
    """Facets off every face by more than the tolerance: the facet is named."""
    geo = CadGeometry.from_file(sources["step"])
    tri = np.array([[[0.2, 0.0, 0.1], [0.25, 0.0, 0.12], [0.22, 0.0, 0.15]],   # on the face y = 0
                    [[0.2, -0.05, 0.1], [0.25, -0.05, 0.12], [0.22, -0.05, 0.15]]])  # 0.05 off
    with pytest.raises(CadError, match=r"1 of 2 boundary facets do not lie on the CAD geometry; "
                                       r"e.g. facet 1 .* is 5\.000e-02 from the nearest entity"):
        geo.attach(tri)
    with pytest.raises(CadError, match="wrong file, units or placement"):
        geo.attach(1000 * tri[:1])


# ----------------------------------------------------------------------
# fuzzing
# ----------------------------------------------------------------------
NUM = re.compile(rb"-?\d+\.\d*(?:E[-+]?\d+)?")
REF = {"step": re.compile(rb"#\d+"), "igs": re.compile(rb"\b\d+P\d{7}|,\d+,")}


def mutate(src: bytes, rng: random.Random, fmt: str) -> bytes:
    b = bytearray(src)
    op = rng.randrange(7)
    if op == 0:  # truncation
        return bytes(b[: rng.randrange(len(b))])
    if op == 1:  # garbled bytes
        for _ in range(rng.randrange(1, 30)):
            b[rng.randrange(len(b))] = rng.choice(b"0123456789.,;()#=E-+ \nHPD'")
        return bytes(b)
    if op == 2:  # a deleted chunk
        i = rng.randrange(len(b))
        del b[i:i + rng.randrange(1, 600)]
        return bytes(b)
    if op == 3:  # wrong references
        refs = [m.start() for m in REF[fmt].finditer(b)]
        for i in rng.sample(refs, min(len(refs), rng.randrange(1, 8))):
            b[i + 1:i + 2] = str(rng.randrange(1, 999)).encode()
        return bytes(b)
    if op == 4:  # NaN, infinite and huge numbers
        nums = list(NUM.finditer(b))
        out, last = bytearray(), 0
        for m in sorted(rng.sample(nums, min(len(nums), rng.randrange(1, 10))), key=lambda m: m.start()):
            out += b[last:m.start()] + rng.choice([b"NaN", b"1.E400", b"-1.E308", b"1.E-320", b"0."])
            last = m.end()
        return bytes(out + b[last:])
    if op == 5:  # lines swapped
        lines = b.split(b"\n")
        for _ in range(rng.randrange(1, 6)):
            i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        return b"\n".join(lines)
    lines = b.split(b"\n")  # lines duplicated
    i = rng.randrange(len(lines))
    lines[i:i] = lines[i:i + rng.randrange(1, 5)]
    return b"\n".join(lines)


@pytest.mark.parametrize("fmt", ["step", "igs"])
def test_fuzzed_files_give_a_geometry_or_cad_error(sources, tmp_path, fmt):
    rng = random.Random({"step": 1, "igs": 2}[fmt])
    src = Path(sources[fmt]).read_bytes()
    outcome = {"geometry": 0, "error": 0, "crash": 0, "timeout": 0}
    for k in range(FUZZ_PER_FORMAT):
        p = tmp_path / f"m{k}.{fmt}"
        p.write_bytes(mutate(src, rng, fmt))
        try:
            geo = CadGeometry.from_file(p, timeout=FUZZ_TIMEOUT)
        except CadError as e:
            msg = str(e)
            assert str(p) in msg, msg
            outcome["crash" if "crashed" in msg else "timeout" if "did not finish" in msg else "error"] += 1
            continue
        # a geometry came back: it must be usable
        assert geo.num_entities > 0 and np.isfinite(geo.size)
        outcome["geometry"] += 1
    print(fmt, outcome)
    assert sum(outcome.values()) == FUZZ_PER_FORMAT
    assert outcome["geometry"] > 0 and outcome["error"] > 0
    if fmt == "step":  # OpenCASCADE does crash on some of them; this process is still here,
        assert outcome["crash"] > 0  # and the reader still works
    assert CadGeometry.from_file(sources[fmt]).num_entities >= 8


def _outcome(path) -> str:
    """What reading ``path`` gives: ``geometry <entities>`` or the error (without the path)."""
    try:
        return f"geometry {CadGeometry.from_file(path, timeout=FUZZ_TIMEOUT).num_entities}"
    except CadError as e:
        return str(e).replace(str(path), "<file>")


def test_reads_do_not_depend_on_earlier_files(sources, tmp_path):
    """Mutated IGES files read forwards, then backwards: each gives the same result both times.

    OpenCASCADE keeps state across reads in one process (with one reader
    process serving many files, a malformed file read twice gave a geometry,
    then an empty shape); every file now gets a fresh reader.  Time-outs
    depend on the machine's load and are not compared.
    """
    rng = random.Random(2)  # the IGES mutations of the fuzz test
    src = Path(sources["igs"]).read_bytes()
    paths = []
    for k in range(140):
        paths.append(tmp_path / f"m{k}.igs")
        paths[-1].write_bytes(mutate(src, rng, "igs"))
    forward = {p: _outcome(p) for p in paths}
    backward = {p: _outcome(p) for p in reversed(paths)}
    timeout = "did not finish"
    differ = {p.name: (forward[p], backward[p]) for p in paths
              if forward[p] != backward[p] and timeout not in forward[p] + backward[p]}
    assert not differ, differ
    assert len({o.split(" ")[0] for o in forward.values()}) > 1  # geometries and errors both


def test_from_file_pauses_the_collector_and_restores_it(sources, monkeypatch):
    """``from_file`` builds with the cyclic collector off (``worker.collector_paused``) and leaves
    it as it found it: on after a read, on after a failed read, off if it was off."""
    import gc

    from nagata_snap.cad import verify as cad_verify

    seen = []
    read = cad_verify.read_verified

    def spy(*args, **kwargs):
        seen.append(gc.isenabled())
        return read(*args, **kwargs)

    monkeypatch.setattr(cad_verify, "read_verified", spy)
    was = gc.isenabled()
    try:
        gc.enable()
        CadGeometry.from_file(sources["step"], isolate=False)
        assert gc.isenabled()
        with pytest.raises(CadError):
            CadGeometry.from_file(sources["step"] + ".missing.step", isolate=False)
        assert gc.isenabled()
        gc.disable()
        CadGeometry.from_file(sources["step"], isolate=False)
        assert not gc.isenabled()
    finally:
        (gc.enable if was else gc.disable)()
    assert seen == [False, False, False]
