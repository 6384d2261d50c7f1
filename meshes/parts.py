"""Machined test parts built with gmsh's OpenCASCADE kernel (test and benchmark support).

Every part is a few calls of ``gmsh.model.occ`` in the current gmsh model,
followed by a synchronisation: primitives, booleans, fillets and chamfers,
revolutions, extrusions and lofts, i.e. the faces a real machined part is made
of (planes, cylinders, cones with their apex, spheres with their poles, tori,
B-spline surfaces; seams, trimmed faces with holes, tangent blends, sharp
and re-entrant edges).  All lengths are in millimetres; gmsh writes STEP and
IGES files with the unit ``MM`` and OpenCASCADE reads them back in
millimetres by default (``Geometry.OCCTargetUnit`` empty), so the written
files reproduce the coordinates below.

``PARTS`` maps a name to a :class:`Part`; :func:`write_part` writes one as
STEP, IGES and BREP (by gmsh's OpenCASCADE), :func:`build_part` builds one in
a fresh gmsh model, :func:`model_size` gives its bounding-box diagonal.

Planar parts (``dim == 2``) are one face in the plane z = 0, ready for a 2D
(gdim 2) mesh; the others are solids (the assembly: two solids sharing one
face).  Which issue uses which part is in ``Part.features`` and in the
registry below (issue 11: real CAD, 12: untangling smoother, 13: normal
estimation).

Run ``python meshes/parts.py [outdir]`` to write every part and print its
face count and volume (area for planar parts).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import gmsh

HERE = Path(__file__).resolve().parent
if str(HERE.parent) not in sys.path:  # the package, when run as a script
    sys.path.insert(0, str(HERE.parent))

__all__ = ["PARTS", "Part", "build_part", "write_part", "model_size", "part_model"]

#: file name ending written by :func:`write_part` for each format
EXTENSIONS = {"step": ".step", "iges": ".igs", "brep": ".brep", "iges_brep": ".brep.igs"}


@dataclass(frozen=True)
class Part:
    """A test part.

    Attributes:
        name: registry key (also the file stem of :func:`write_part`).
        dim: 2 (one planar face in z = 0) or 3 (solid(s)).
        description: what it is, with its main dimensions [mm].
        features: the CAD features it exercises (face types, seams, poles, ...).
        build: creates the part in the current gmsh model with
            ``gmsh.model.occ`` and synchronises.
        issues: the issues whose tests use it.
        iges_faces_solid: whether gmsh (OCC) makes the solid(s) again from the
            faces-only IGES that ``gmsh.write`` produces (False for faces ending
            at a pole or apex, whose sewing fails or loses the pole region, and
            for the assembly, which faces-only IGES cannot carry as two solids);
            the B-rep IGES (``"iges_brep"``) and STEP/BREP always re-read as solids.
    """

    name: str
    dim: int
    description: str
    features: tuple[str, ...]
    build: Callable[[], None] = field(repr=False)
    issues: tuple[int, ...] = (11,)
    iges_faces_solid: bool = True


# ----------------------------------------------------------------------
# small construction helpers
# ----------------------------------------------------------------------
def _curves_in_box(lo, hi, dim: int = 1) -> list[int]:
    """Tags of the entities of dimension ``dim`` inside the box ``lo``-``hi`` (model synchronised)."""
    eps = 1e-6
    ents = gmsh.model.getEntitiesInBoundingBox(
        lo[0] - eps, lo[1] - eps, lo[2] - eps, hi[0] + eps, hi[1] + eps, hi[2] + eps, dim)
    return [t for _, t in ents]


def _only_volume(dimtags) -> int:
    vols = [t for d, t in dimtags if d == 3]
    if len(vols) != 1:
        raise RuntimeError(f"expected one solid, got {len(vols)}")
    return vols[0]


def _polygon_wire(points, closed: bool = True) -> list[int]:
    """Lines through ``points`` ((x, y) in z = 0); returns the curve tags."""
    occ = gmsh.model.occ
    pts = [occ.addPoint(x, y, 0.0) for x, y in points]
    n = len(pts)
    return [occ.addLine(pts[i], pts[(i + 1) % n]) for i in range(n if closed else n - 1)]


# ----------------------------------------------------------------------
# 2D parts (one planar face in z = 0)
# ----------------------------------------------------------------------
def _profile_2d() -> None:
    """Lines, two 8 mm corner fillets, a semicircular notch and a B-spline top."""
    occ = gmsh.model.occ
    P = {k: occ.addPoint(x, y, 0.0) for k, (x, y) in {
        "A": (8, 0), "B": (72, 0), "C": (80, 8), "D": (80, 30), "E": (0, 30), "F": (0, 20),
        "G": (0, 10), "H": (0, 8), "cBC": (72, 8), "cHA": (8, 8), "notch": (5, 15)}.items()}
    top = [occ.addPoint(x, y, 0.0) for x, y in ((60, 42), (40, 34), (20, 44))]
    curves = [
        occ.addLine(P["A"], P["B"]),
        occ.addCircleArc(P["B"], P["cBC"], P["C"]),  # fillet, tangent to both lines
        occ.addLine(P["C"], P["D"]),
        occ.addBSpline([P["D"], *top, P["E"]]),
        occ.addLine(P["E"], P["F"]),
        occ.addCircleArc(P["F"], P["notch"], P["G"], center=False),  # notch through (5, 15)
        occ.addLine(P["G"], P["H"]),
        occ.addCircleArc(P["H"], P["cHA"], P["A"]),  # fillet
    ]
    occ.addPlaneSurface([occ.addCurveLoop(curves)])
    occ.synchronize()


def _slot(x0: float, x1: float, yc: float, r: float) -> int:
    """Curve loop of a rounded slot: straight from x0 to x1 at yc +- r, semicircular ends."""
    occ = gmsh.model.occ
    a, b = occ.addPoint(x0, yc - r, 0), occ.addPoint(x1, yc - r, 0)
    c, d = occ.addPoint(x1, yc + r, 0), occ.addPoint(x0, yc + r, 0)
    e1, e0 = occ.addPoint(x1 + r, yc, 0), occ.addPoint(x0 - r, yc, 0)
    return occ.addCurveLoop([
        occ.addLine(a, b), occ.addCircleArc(b, e1, c, center=False),
        occ.addLine(c, d), occ.addCircleArc(d, e0, a, center=False)])


def _plate_holes_2d() -> None:
    """100 x 60 plate, 6 mm rounded corners, three circular holes and a rounded slot."""
    occ = gmsh.model.occ
    plate = occ.addRectangle(0, 0, 0, 100, 60, roundedRadius=6)
    # circles (addDisk would make ellipses of equal radii)
    holes = [occ.addPlaneSurface([occ.addCurveLoop([occ.addCircle(x, y, 0, r)])])
             for x, y, r in ((20, 30, 8), (80, 15, 5), (80, 45, 5))]
    slot = occ.addPlaneSurface([_slot(42, 58, 30, 5)])
    occ.cut([(2, plate)], [(2, h) for h in holes] + [(2, slot)])
    occ.synchronize()


# ----------------------------------------------------------------------
# 3D parts for issue 11
# ----------------------------------------------------------------------
def _box_fillet_chamfer() -> None:
    """60 x 40 x 30 box, vertical edges filleted (r 6), the top face's edges chamfered (2)."""
    occ = gmsh.model.occ
    box = occ.addBox(0, 0, 0, 60, 40, 30)
    occ.synchronize()
    vertical = [t for t in _curves_in_box((0, 0, 0), (60, 40, 30))
                if abs(_extent(1, t)[2] - 30) < 1e-6]
    out = occ.fillet([box], vertical, [6.0])
    occ.synchronize()
    vol = _only_volume(out)
    top_face = _curves_in_box((0, 0, 30), (60, 40, 30), dim=2)[0]
    top_edges = [t for _, t in gmsh.model.getBoundary([(2, top_face)], oriented=False)]
    occ.chamfer([vol], top_edges, [top_face] * len(top_edges), [2.0])
    occ.synchronize()


def _extent(dim: int, tag: int) -> tuple[float, float, float]:
    b = gmsh.model.getBoundingBox(dim, tag)
    return (b[3] - b[0], b[4] - b[1], b[5] - b[2])


def _plate_body(fillets: bool) -> None:
    """100 x 60 x 12 plate: 4 through-holes (r 4), 2 counterbores (r 8, 5 deep), a 40 x 20 x 6 pocket.

    With ``fillets``: the plate's vertical edges (r 8), the pocket's vertical
    edges (r 4) and the pocket's floor edges (r 2) are filleted.
    """
    occ = gmsh.model.occ
    plate = occ.addBox(0, 0, 0, 100, 60, 12)
    pocket = occ.addBox(30, 20, 6, 40, 20, 10)
    if fillets:
        occ.synchronize()
        plate = _only_volume(occ.fillet([plate], _vertical_edges(plate, 12), [8.0]))
        pocket = _only_volume(occ.fillet([pocket], _vertical_edges(pocket, 10), [4.0]))
    tools = [(3, occ.addCylinder(x, y, -1, 0, 0, 14, 4)) for x, y in ((12, 12), (88, 12), (12, 48), (88, 48))]
    tools += [(3, occ.addCylinder(x, y, 7, 0, 0, 6, 8)) for x, y in ((12, 12), (88, 48))]
    out, _ = occ.cut([(3, plate)], [*tools, (3, pocket)])
    occ.synchronize()
    vol = _only_volume(out)
    if fillets:  # the pocket floor's edges (its boundary curves at z = 6)
        floor = _curves_in_box((30, 20, 6), (70, 40, 6), dim=2)
        edges = [t for _, t in gmsh.model.getBoundary([(2, f) for f in floor], oriented=False)]
        occ.fillet([vol], edges, [2.0])
        occ.synchronize()


def _vertical_edges(vol: int, height: float) -> list[int]:
    edges = [t for _, t in gmsh.model.getBoundary(
        gmsh.model.getBoundary([(3, vol)], oriented=False), combined=False, oriented=False)]
    return sorted({t for t in edges if abs(_extent(1, t)[2] - height) < 1e-6
                   and max(_extent(1, t)[:2]) < 1e-6})


def _revolved() -> None:
    """Turned part around z: spherical cap with its pole at the bottom, a cylinder with a
    toroidal groove (r 5), a cone up to its apex (0, 0, 70); radius 25."""
    occ = gmsh.model.occ
    c = (25.0**2 - 8.0**2) / 16.0  # centre height of the cap's sphere (through (0,-8) and (25,0))
    P = [occ.addPoint(x, 0, z) for x, z in ((0, -8), (25, 0), (25, 15), (25, 25), (25, 40), (0, 70))]
    centre, groove = occ.addPoint(0, 0, c), occ.addPoint(20, 0, 20)
    curves = [
        occ.addCircleArc(P[0], centre, P[1]),  # spherical cap
        occ.addLine(P[1], P[2]),  # cylinder
        occ.addCircleArc(P[2], groove, P[3], center=False),  # toroidal groove through (20, 20)
        occ.addLine(P[3], P[4]),  # cylinder
        occ.addLine(P[4], P[5]),  # cone to the apex
        occ.addLine(P[5], P[0]),  # on the axis
    ]
    face = occ.addPlaneSurface([occ.addCurveLoop(curves)])
    occ.revolve([(2, face)], 0, 0, 0, 0, 0, 1, 2 * math.pi)
    occ.remove([(2, face)], recursive=True)  # the profile stays beside the solid otherwise
    occ.synchronize()


def _extruded_bspline() -> None:
    """Cam: a closed interpolating spline through 8 points (radii 18-30) and a straight flat, 20 high."""
    occ = gmsh.model.occ
    radii = (30, 26, 22, 18, 19, 21, 24, 28)
    angles = [math.radians(20 + 40 * k) for k in range(8)]
    pts = [occ.addPoint(r * math.cos(a), r * math.sin(a), 0) for r, a in zip(radii, angles, strict=True)]
    spline = occ.addSpline(pts)  # first 8 points
    flat = occ.addLine(pts[-1], pts[0])
    face = occ.addPlaneSurface([occ.addCurveLoop([spline, flat])])
    occ.extrude([(2, face)], 0, 0, 20)
    occ.synchronize()


def _blade_section(z: float, chord: float, thick: float, twist: float) -> int:
    """Closed interpolating spline of a symmetric blade section at height z, rotated by ``twist``."""
    occ = gmsh.model.occ
    n = 12
    pts = []
    for k in range(n):
        t = 2 * math.pi * k / n
        x = 0.5 * chord * math.cos(t)
        y = 0.5 * thick * math.sin(t) * (1.0 - 0.3 * math.cos(t))  # thicker at the leading edge
        c, s = math.cos(twist), math.sin(twist)
        pts.append(occ.addPoint(c * x - s * y, s * x + c * y, z))
    curve = occ.addSpline([*pts, pts[0]])
    return occ.addWire([curve])


def _lofted_blade() -> None:
    """Blade lofted (ThruSections, smooth) through 4 sections: chord 40 -> 24, 30 deg twist over 60."""
    occ = gmsh.model.occ
    wires = [_blade_section(z, ch, th, math.radians(tw))
             for z, ch, th, tw in ((0, 40, 10, 0), (20, 34, 8, 10), (40, 29, 6.5, 20), (60, 24, 5, 30))]
    occ.addThruSections(wires, makeSolid=True, makeRuled=False)
    occ.synchronize()


def _crossing_cylinders() -> None:
    """Union of a cylinder r 10 along x (length 60) and a cylinder r 7 along y (length 50)."""
    occ = gmsh.model.occ
    a = occ.addCylinder(-30, 0, 0, 60, 0, 0, 10)
    b = occ.addCylinder(0, -25, 0, 0, 50, 0, 7)
    occ.fuse([(3, a)], [(3, b)])
    occ.synchronize()


def _seamed() -> None:
    """Capsule (cylinder r 10, height 30, hemispherical top) with a torus ring (R 10, r 3)
    around its middle: every curved face is a full turn with a seam."""
    occ = gmsh.model.occ
    cyl = occ.addCylinder(0, 0, 0, 0, 0, 30, 10)
    cap = occ.addSphere(0, 0, 30, 10)
    ring = occ.addTorus(0, 0, 15, 10, 3)
    occ.fuse([(3, cyl)], [(3, cap), (3, ring)])
    occ.synchronize()


def _assembly() -> None:
    """Two solids sharing a face: a 40 x 30 x 20 block and a cylinder (r 8, height 15) on its top,
    fragmented so that the disk between them is one face of both."""
    occ = gmsh.model.occ
    block = occ.addBox(0, 0, 0, 40, 30, 20)
    cyl = occ.addCylinder(20, 15, 20, 0, 0, 15, 8)
    occ.fragment([(3, block)], [(3, cyl)])
    occ.synchronize()


# ----------------------------------------------------------------------
# 3D hard cases for issue 12 (the plate with fillets: also issue 13)
# ----------------------------------------------------------------------
def _thin_wall() -> None:
    """Quarter of a cylindrical shell: radius 50, wall 1.5 thick, 40 high."""
    occ = gmsh.model.occ
    r0, r1 = 48.5, 50.0
    o = occ.addPoint(0, 0, 0)
    a, b = occ.addPoint(r0, 0, 0), occ.addPoint(r1, 0, 0)
    c, d = occ.addPoint(0, r1, 0), occ.addPoint(0, r0, 0)
    loop = occ.addCurveLoop([occ.addLine(a, b), occ.addCircleArc(b, o, c),
                             occ.addLine(c, d), occ.addCircleArc(d, o, a)])
    occ.extrude([(2, occ.addPlaneSurface([loop]))], 0, 0, 40)
    occ.remove([(0, o)])
    occ.synchronize()


def _concave_cylinder() -> None:
    """60 x 40 x 30 block with a half-cylindrical groove (r 10, axis along x at y 20, z 30) in its top."""
    occ = gmsh.model.occ
    block = occ.addBox(0, 0, 0, 60, 40, 30)
    bore = occ.addCylinder(-1, 20, 30, 62, 0, 0, 10)
    occ.cut([(3, block)], [(3, bore)])
    occ.synchronize()


def _reentrant_fillet() -> None:
    """L-shaped block (legs 60 and 40, 15 wide, 25 deep) with the re-entrant edge filleted (r 5)."""
    occ = gmsh.model.occ
    face = occ.addPlaneSurface([occ.addCurveLoop(
        _polygon_wire([(0, 0), (60, 0), (60, 15), (15, 15), (15, 40), (0, 40)]))])
    out = occ.extrude([(2, face)], 0, 0, 25)
    occ.synchronize()
    vol = _only_volume(out)
    inner = _curves_in_box((15, 15, 0), (15, 15, 25))
    occ.fillet([vol], inner, [5.0])
    occ.synchronize()


# ----------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------
_LIST = [
    Part("profile_2d", 2, "planar profile 80 x 44: lines, two r 8 fillets, an r 5 notch, a B-spline top",
         ("line", "circular arc", "tangent fillet", "B-spline curve", "corners"), _profile_2d),
    Part("plate_holes_2d", 2, "planar plate 100 x 60, r 6 corners, holes r 8 and 2 x r 5, a 26 x 10 slot",
         ("line", "full circle", "rounded slot", "inner loops"), _plate_holes_2d),
    Part("box_fillet_chamfer", 3, "box 60 x 40 x 30, vertical edges filleted r 6, top edges chamfered 2",
         ("plane", "cylinder (fillet)", "chamfer", "tangent blends", "sharp edges"), _box_fillet_chamfer),
    Part("plate", 3, "plate 100 x 60 x 12, 4 through-holes r 4, 2 counterbores r 8, pocket 40 x 20 x 6",
         ("plane with inner loops", "cylinder", "annular plane", "pocket"), lambda: _plate_body(False)),
    Part("revolved", 3, "turned part r 25, 78 high: spherical cap (pole), cylinder, torus groove, cone (apex)",
         ("sphere pole", "cone apex", "torus", "cylinder", "seam"), _revolved, iges_faces_solid=False),
    Part("extruded_bspline", 3, "cam profile (closed spline, radii 18-30, one flat) extruded 20",
         ("B-spline surface (extrusion)", "plane", "sharp edges"), _extruded_bspline),
    Part("lofted_blade", 3, "blade lofted through 4 spline sections, chord 40 -> 24, 30 deg twist, 60 high",
         ("B-spline surface (loft)", "seam", "thin section", "planar ends"), _lofted_blade),
    Part("crossing_cylinders", 3, "union of cylinders r 10 (along x, 60) and r 7 (along y, 50)",
         ("cylinder", "non-planar intersection curves", "seam"), _crossing_cylinders),
    Part("seamed", 3, "capsule r 10, 30 + hemisphere, torus ring R 10 r 3 at mid-height",
         ("seam on every curved face", "sphere pole", "torus", "cylinder"), _seamed,
         iges_faces_solid=False),
    Part("assembly", 3, "block 40 x 30 x 20 and a cylinder r 8, 15 high on it, sharing the disk face",
         ("two solids", "shared face", "interface edges"), _assembly, iges_faces_solid=False),
    Part("plate_filleted", 3, "plate of 'plate' with filleted corners r 8, pocket corners r 4, pocket floor r 2",
         ("plane with inner loops", "cylinder", "tangent blends (fillets)", "torus and sphere corners",
          "pocket"), lambda: _plate_body(True), issues=(12, 13)),
    Part("thin_wall", 3, "quarter cylindrical shell, radius 50, wall 1.5, 40 high",
         ("thin wall (thickness / radius 0.03)", "cylinder", "convex and concave"), _thin_wall,
         issues=(12,)),
    Part("concave_cylinder", 3, "block 60 x 40 x 30 with a half-cylindrical groove r 10 in its top",
         ("concave cylinder", "sharp concave edges"), _concave_cylinder, issues=(12,)),
    Part("reentrant_fillet", 3, "L-block (legs 60, 40; 15 wide; 25 deep), re-entrant edge filleted r 5",
         ("re-entrant corner", "concave fillet", "sharp edges"), _reentrant_fillet, issues=(12,)),
]

#: all parts by name
PARTS: dict[str, Part] = {p.name: p for p in _LIST}


# ----------------------------------------------------------------------
# gmsh helpers
# ----------------------------------------------------------------------
@contextlib.contextmanager
def part_model(name: str) -> Iterator[Part]:
    """Build part ``name`` in a new gmsh model (gmsh initialised if needed); remove it afterwards.

    gmsh is left as found: a session this function opened is finalised, a
    caller's session gets its current model back.
    """
    from nagata_snap.meshing import gmsh_session

    with gmsh_session(f"part_{name}"):
        yield build_part(name)


def build_part(name: str) -> Part:
    """Build part ``name`` in the current gmsh model (which must be initialised); returns the Part.

    Construction points (arc centres, spline points) and other entities that
    bound nothing of the part's dimension are removed.
    """
    part = _lookup(name)
    part.build()
    _drop_loose(part.dim)
    return part


def _drop_loose(dim: int) -> None:
    """Remove the entities of dimension < ``dim`` that bound nothing (e.g. an arc's centre)."""
    for d in range(dim - 1, -1, -1):
        loose = [(d, t) for _, t in gmsh.model.getEntities(d) if len(gmsh.model.getAdjacencies(d, t)[0]) == 0]
        if loose:
            gmsh.model.occ.remove(loose, recursive=True)
            gmsh.model.occ.synchronize()


def _lookup(name: str) -> Part:
    try:
        return PARTS[name]
    except KeyError:
        raise KeyError(f"unknown part {name!r}; parts: {', '.join(PARTS)}") from None


def write_part(name: str, directory: str | Path,
               formats: tuple[str, ...] = ("step", "iges", "brep")) -> dict[str, Path]:
    """Write part ``name`` as ``<directory>/<name>.step|.igs|.brep`` (gmsh's OpenCASCADE writers).

    ``"iges"`` is what ``gmsh.write`` writes: trimmed surfaces (entities 144,
    128, 120, 108, ...) without solids.  ``"iges_brep"`` (``<name>.brep.igs``)
    is the B-rep flavour many CAD exporters write (manifold solid, shells,
    faces, loops, edges and vertices: entities 186, 502-514), written by
    OpenCASCADE through OCP (``IGESControl_Writer`` in B-rep mode) from the
    part's BREP; it needs the ``OCP`` module (``cadquery-ocp``).

    Returns:
        ``{format: path}`` for the formats asked for.
    """
    bad = [f for f in formats if f not in EXTENSIONS]
    if bad:
        raise ValueError(f"unknown formats {bad}; use any of {list(EXTENSIONS)}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {fmt: directory / f"{name}{EXTENSIONS[fmt]}" for fmt in formats}
    with part_model(name), _quiet_stdout():
        for fmt, path in paths.items():
            gmsh.write(str(path if fmt != "iges_brep" else path.with_suffix("")))  # .brep for OCP
    if "iges_brep" in paths:
        with _quiet_stdout():
                _write_brep_iges(paths["iges_brep"].with_suffix(""), paths["iges_brep"])
        if "brep" not in paths:
            paths["iges_brep"].with_suffix("").unlink()
    return paths


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    """Silence OpenCASCADE's writers, which print transfer statistics to the C-level stdout."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _write_brep_iges(brep: Path, out: Path) -> None:
    """Write the shape of the BREP file ``brep`` as B-rep IGES (mode 1, unit MM) with OCP."""
    from OCP.BRep import BRep_Builder
    from OCP.BRepTools import BRepTools
    from OCP.IGESControl import IGESControl_Controller, IGESControl_Writer
    from OCP.TopoDS import TopoDS_Shape

    shape = TopoDS_Shape()
    if not BRepTools.Read_s(shape, str(brep), BRep_Builder()):
        raise RuntimeError(f"OCP could not read {brep}")
    IGESControl_Controller.Init_s()
    writer = IGESControl_Writer("MM", 1)  # 1: B-rep mode (186, 502-514)
    writer.AddShape(shape)
    writer.ComputeModel()
    if not writer.Write(str(out)):
        raise RuntimeError(f"OCP could not write {out}")


def model_size(name: str) -> float:
    """Bounding-box diagonal of part ``name`` [mm]."""
    with part_model(name):
        b = gmsh.model.getBoundingBox(-1, -1)
    return math.dist(b[:3], b[3:])


def occ_mass(brep: str | Path, dim: int) -> float:
    """Volume (dim 3) or area (dim 2) of the shape in a BREP file, by OpenCASCADE's adaptive
    integration (OCP ``BRepGProp``, relative error 1e-9).

    gmsh's ``occ.getMass`` uses OpenCASCADE's fixed-order Gauss integration:
    exact on analytic faces, but 1e-5 (profile_2d) to 5.7e-3 (extruded_bspline)
    off on B-spline faces and 17 % low on the lofted blade (9365 against 11216
    mm^3; the blade's mesh and Simpson's rule on its four sections give 11180
    and 11200).
    """
    from OCP.BRep import BRep_Builder
    from OCP.BRepGProp import BRepGProp
    from OCP.BRepTools import BRepTools
    from OCP.GProp import GProp_GProps
    from OCP.TopoDS import TopoDS_Shape

    shape = TopoDS_Shape()
    if not BRepTools.Read_s(shape, str(brep), BRep_Builder()):
        raise RuntimeError(f"OCP could not read {brep}")
    props = GProp_GProps()
    (BRepGProp.VolumeProperties_s if dim == 3 else BRepGProp.SurfaceProperties_s)(shape, props, 1e-9)
    return props.Mass()


def measure(dim: int) -> tuple[int, float]:
    """(number of faces, total volume (dim 3) or area (dim 2) by gmsh's ``occ.getMass``) of the
    current gmsh model; faces are curves for dim 2."""
    faces = len(gmsh.model.getEntities(2)) if dim == 3 else len(gmsh.model.getEntities(1))
    mass = sum(gmsh.model.occ.getMass(dim, t) for _, t in gmsh.model.getEntities(dim))
    return faces, mass


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("parts_out")
    for part in PARTS.values():
        write_part(part.name, out)
        with part_model(part.name):
            n, m = measure(part.dim)
            vols = len(gmsh.model.getEntities(3))
        kind = "curves" if part.dim == 2 else "faces"
        print(f"{part.name:20s} dim {part.dim}  {n:3d} {kind}  {vols} solids  "
              f"{'area' if part.dim == 2 else 'volume'} {m:.6g}")
