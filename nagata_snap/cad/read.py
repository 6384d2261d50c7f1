"""Read STEP, IGES and BREP files with OpenCASCADE (OCP) into plain numpy data.

This is the only module that calls OpenCASCADE.  It imports nothing from
the package but :mod:`nagata_snap.cad.sewing` (numpy and scipy, loaded from
its file where this module runs alone), so that
:mod:`nagata_snap.cad.worker` can run it in a child process that never
initialises MPI: OpenCASCADE can crash or hang on malformed files, and a
crash there must not take the user's process down.

Faces that share no edge (faces-only IGES files) are sewn into shells and
the closed shells made solids.  Where the faces meet cleanly the walked
data of the unsewn shape are joined by :mod:`nagata_snap.cad.sewing`
(vectorised, on plain data); anything else is sewn by
OpenCASCADE (``BRepBuilderAPI_Sewing``, ``ShapeFix_Solid``, ``ShapeFix_Shape``),
as every file was before; ``healed["method"]`` says which.

:func:`read_shape` returns a dict of plain Python/numpy data describing the
B-rep (every face, edge and vertex of the shape, numbered as in
``TopExp::MapShapes``), which :mod:`nagata_snap.cad.topology` turns into
surfaces, curves and trimming loops:

* ``faces``: per face its surface (``"plane"``, ``"cylinder"``, ``"cone"``,
  ``"sphere"``, ``"torus"`` with the face's placement, else ``"bspline"``:
  poles, weights and flat knot vectors of a non-periodic B-spline), the
  face's ``(u, v)`` bounds, its orientation in the shape (``reversed``), and
  its wires: for each edge use, in the order of ``BRepTools_WireExplorer``,
  the edge index, the sense and the edge's p-curve in the face's parameter
  plane (``"line"``, ``"circle"`` or ``"bspline"`` with its parameter range;
  where the faces were joined, ``opposed``: the p-curve is parametrised
  against the edge's 3D curve, so the use runs along the curve where
  ``reversed`` and ``opposed`` differ).  Seam edges appear twice in a wire,
  once per p-curve.  A face whose surface
  is neither analytic nor a B-spline (surface of revolution or extrusion,
  offset surface, ...) but is a plane, cylinder, cone, sphere or torus
  (``GeomConvert_SurfToAnaSurf``, as IGES files write them) gets that
  analytic surface and the affine map of its own parameters onto the
  surface's (``"uv_map"``); a Bezier surface becomes a B-spline with the
  same parameters; any other surface whose B-spline form
  (``GeomConvert::SurfaceToBSplineSurface`` of the face's parameter box) keeps
  its parameters, as a linear extrusion of a B-spline curve does, becomes that
  B-spline (checked inside every knot span, where a reparametrisation would
  show; the p-curves stay valid); anything else is converted with
  ``BRepBuilderAPI_NurbsConvert``, together with its p-curves, and marked
  ``converted`` (its ``(u, v)`` then differ from the file's).
* ``edges``: the 3D curve (``"line"``, ``"circle"``, else a B-spline from
  ``GeomConvert``) and parameter range of every edge, its two vertices and
  tolerance; degenerate edges (sphere poles, cone apexes) have no curve;
  ``source``: the index of the OpenCASCADE edge the curve is taken from, in
  the shape walked (the unsewn shape where the faces were joined, whose
  faces are numbered as here; else the edge itself).
* ``vertices``: ``(nv, 3)`` points.

Lengths are in ``unit`` (OpenCASCADE's ``xstep.cascade.unit``: STEP and IGES
coordinates are converted to it from the file's own unit, which is reported
in ``file_units``; gmsh's OpenCASCADE import does the same with its option
``Geometry.OCCTargetUnit``, whose default is also millimetres).  BREP files
carry no unit: their coordinates are taken as they are.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import math
import os
import time
from collections.abc import Iterable, Iterator, Sequence
from types import SimpleNamespace
from typing import Any

import numpy as np

__all__ = ["ReadError", "read_shape", "load_shape", "shape_maps", "preload", "FORMATS", "UNITS"]

#: file name extensions and their formats
FORMATS = {".step": "step", ".stp": "step", ".igs": "iges", ".iges": "iges", ".brep": "brep",
           ".brp": "brep"}
#: length units understood by ``xstep.cascade.unit`` (millimetres per unit)
UNITS = {"MM": 1.0, "CM": 10.0, "M": 1000.0, "KM": 1e6, "INCH": 25.4, "IN": 25.4, "FT": 304.8,
         "MI": 1609344.0, "MIL": 0.0254, "UM": 1e-3, "NM": 1e-6}


class ReadError(Exception):
    """The file cannot be read or converted; the message names the file and the face."""


def preload() -> None:
    """Import the OpenCASCADE modules :func:`read_shape` uses, and :mod:`nagata_snap.cad.sewing` with
    scipy (a forked reader starts warm)."""
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    STEPControl_Reader()  # registers the static parameters (xstep.cascade.unit, ...)
    IGESControl_Reader()
    _occ()
    _sewing()


@functools.cache
def _occ() -> SimpleNamespace:
    """The OpenCASCADE classes used once per face, edge or edge use, imported once (lazily:
    importing this module does not load OpenCASCADE), and the integer values of the enums
    compared there (comparing pybind11 enums costs several times more than their ints), with
    the surface types' names by their values and the classifier's states (``IN``, ``OUT``) by
    :func:`_checks`' codes (0, 1; any other state: 2)."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Curve, BRepAdaptor_Curve2d, BRepAdaptor_Surface
    from OCP.BRepTools import BRepTools, BRepTools_WireExplorer
    from OCP.ElSLib import ElSLib
    from OCP.Geom import (
        Geom_ConicalSurface,
        Geom_CylindricalSurface,
        Geom_Plane,
        Geom_RectangularTrimmedSurface,
        Geom_SphericalSurface,
        Geom_ToroidalSurface,
        Geom_TrimmedCurve,
    )
    from OCP.Geom2d import Geom2d_TrimmedCurve
    from OCP.Geom2dConvert import Geom2dConvert
    from OCP.GeomAbs import GeomAbs_CurveType as C
    from OCP.GeomAbs import GeomAbs_SurfaceType as S
    from OCP.GeomConvert import GeomConvert, GeomConvert_ApproxSurface, GeomConvert_SurfToAnaSurf
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_Orientation, TopAbs_State, TopAbs_VERTEX, TopAbs_WIRE
    from OCP.TopExp import TopExp, TopExp_Explorer
    from OCP.TopoDS import TopoDS

    return SimpleNamespace(
        BRep_Tool=BRep_Tool, BRepAdaptor_Curve=BRepAdaptor_Curve, BRepAdaptor_Curve2d=BRepAdaptor_Curve2d,
        BRepAdaptor_Surface=BRepAdaptor_Surface,
        BRepTools=BRepTools, BRepTools_WireExplorer=BRepTools_WireExplorer,
        Geom_TrimmedCurve=Geom_TrimmedCurve, Geom2d_TrimmedCurve=Geom2d_TrimmedCurve,
        Geom2dConvert=Geom2dConvert, GeomConvert=GeomConvert, TopExp=TopExp, TopExp_Explorer=TopExp_Explorer,
        ElSLib=ElSLib, GeomConvert_SurfToAnaSurf=GeomConvert_SurfToAnaSurf,
        GeomConvert_ApproxSurface=GeomConvert_ApproxSurface,
        Geom_RectangularTrimmedSurface=Geom_RectangularTrimmedSurface,
        ELEMENTARY=(("plane", Geom_Plane), ("cylinder", Geom_CylindricalSurface), ("cone", Geom_ConicalSurface),
                    ("sphere", Geom_SphericalSurface), ("torus", Geom_ToroidalSurface)),
        TopoDS=TopoDS, WIRE=TopAbs_WIRE, EDGE=TopAbs_EDGE, VERTEX=TopAbs_VERTEX, FACE=TopAbs_FACE,
        REVERSED=int(TopAbs_Orientation.TopAbs_REVERSED),
        STATES={int(TopAbs_State.TopAbs_IN): 0, int(TopAbs_State.TopAbs_OUT): 1},  # face classifier -> ours
        LINE=int(C.GeomAbs_Line), CIRCLE=int(C.GeomAbs_Circle), BSPLINE_CURVE=int(C.GeomAbs_BSplineCurve),
        BSPLINE_SURFACE=int(S.GeomAbs_BSplineSurface), BEZIER_SURFACE=int(S.GeomAbs_BezierSurface),
        ANALYTIC={int(getattr(S, f"GeomAbs_{kind.capitalize()}")): kind for kind in _ANALYTIC_FIELDS},
        SURFACE_NAMES={int(t): t.name.replace("GeomAbs_", "") for t in S.__members__.values()})


def _xyz(p) -> list[float]:
    """The coordinates of a ``gp_Pnt`` / ``gp_Dir`` (3) or ``gp_Pnt2d`` / ``gp_Dir2d`` (2)."""
    return list(p.Coord())


def _check_finite(values: np.ndarray, what: str) -> None:
    if not np.isfinite(values).all():
        raise ReadError(f"{what} has NaN or infinite coordinates")


# ----------------------------------------------------------------------
# reading and healing
# ----------------------------------------------------------------------
@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """OpenCASCADE's own messages below warnings (the IGES reader's entity counts on stdout)
    not printed while reading; the printers' levels are restored after."""
    from OCP.Message import Message, Message_Gravity

    seq = Message.DefaultMessenger_s().Printers()
    printers = [seq.Value(i) for i in range(1, len(seq) + 1)]  # (list(seq), seq.Size(): 0.1-0.5 ms through OCP)
    levels = [p.GetTraceLevel() for p in printers]
    for p in printers:
        p.SetTraceLevel(Message_Gravity.Message_Warning)
    try:
        yield
    finally:
        for p, level in zip(printers, levels, strict=True):
            p.SetTraceLevel(level)


def _read(path: str, fmt: str, unit: str):
    """``(shape, the file's own length unit names, unit of the shape's coordinates)``."""
    from OCP.BRep import BRep_Builder
    from OCP.BRepTools import BRepTools
    from OCP.IFSelect import IFSelect_ReturnStatus
    from OCP.Interface import Interface_Static
    from OCP.TopoDS import TopoDS_Shape

    if fmt == "brep":
        shape = TopoDS_Shape()
        if not BRepTools.Read_s(shape, path, BRep_Builder()):
            raise ReadError(f"{path}: OpenCASCADE cannot read it as a BREP file")
        return shape, [], unit
    from OCP.IGESControl import IGESControl_Reader
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader() if fmt == "step" else IGESControl_Reader()
    Interface_Static.SetCVal_s("xstep.cascade.unit", "MM" if unit == "FILE" else unit)
    if fmt == "iges":  # keep B-splines whole (OpenCASCADE splits them at C0 knots by default)
        Interface_Static.SetIVal_s("read.iges.bspline.continuity", 0)
    status = reader.ReadFile(path)
    if status != IFSelect_ReturnStatus.IFSelect_RetDone:
        raise ReadError(f"{path}: OpenCASCADE cannot read it as a {fmt.upper()} file ({status.name})")
    file_units = _file_units(reader, fmt)
    if unit == "FILE":  # the file's own unit: set it (IGES applies it while reading: read again)
        own = _unit_key(file_units[0]) if len(file_units) == 1 else None
        if own is None:
            raise ReadError(f"{path}: cannot keep the file's length unit {file_units} (give unit=)")
        Interface_Static.SetCVal_s("xstep.cascade.unit", own)
        if fmt == "iges":
            reader = IGESControl_Reader()
            reader.ReadFile(path)
        unit = own
    reader.TransferRoots()
    if reader.NbShapes() == 0:
        raise ReadError(f"{path}: the file holds no shape OpenCASCADE can transfer (empty shape)")
    return reader.OneShape(), file_units, unit


#: unit names of STEP (``FileUnits``) and IGES (global section) files -> :data:`UNITS` keys
_UNIT_NAMES = {"millimetre": "MM", "millimeter": "MM", "metre": "M", "meter": "M",
               "centimetre": "CM", "centimeter": "CM", "kilometre": "KM", "kilometer": "KM",
               "inch": "INCH", "foot": "FT", "mile": "MI", "micrometre": "UM", "micrometer": "UM",
               "nanometre": "NM", "nanometer": "NM", "mil": "MIL"}


#: IGES unit flags (Global parameter 14)
_IGES_FLAGS = {1: "INCH", 2: "MM", 4: "FT", 5: "MI", 6: "M", 7: "KM", 8: "MIL", 9: "UM", 10: "CM"}


def _unit_key(name: str) -> str | None:
    n = name.strip()
    return _UNIT_NAMES.get(n.lower()) or (n.upper() if n.upper() in UNITS else None)


def _file_units(reader, fmt: str) -> list[str]:
    """The file's own length unit names (STEP: of every representation; IGES: global section)."""
    if fmt == "step":
        from OCP.OCP.collections import Sequence_TCollection_AsciiString as Names

        names, angles, solid = Names(), Names(), Names()
        reader.FileUnits(names, angles, solid)
        # len(): the sequence's Length() costs ~0.2 ms through OCP, len() a call
        return sorted({names.Value(i + 1).ToCString() for i in range(len(names))})
    g = reader.IGESModel().GlobalSection()
    name = g.UnitName().ToCString() if g.UnitName() is not None else ""
    if not _unit_key(name):  # the unit flag (IGES 5.3 Global parameter 14) names it
        name = _IGES_FLAGS.get(g.UnitFlag(), name)
    return [name] if name else []


#: sewing tolerances tried, relative to the model size: the first that leaves no free
#: edge is used (IGES edge curves of faces of revolution can be ~1e-5 off their
#: neighbours'), else the last
SEW_RTOL = (1e-5, 1e-4)


def _heal(shape, size: float, sew: bool | None):
    """Faces that share no edge (IGES files) are sewn, closed shells made solids, and the
    result fixed with ``ShapeFix_Shape``.  STEP and IGES transfers already run
    OpenCASCADE's shape processing (``FixShape``), so other shapes are kept."""
    from OCP.BRep import BRep_Builder, BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Sewing
    from OCP.ShapeFix import ShapeFix_Shape, ShapeFix_Solid
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS, TopoDS_Compound

    if not _needs_sewing(shape, sew):
        return shape, {"sewn": False}
    for rtol in SEW_RTOL:
        s = BRepBuilderAPI_Sewing(rtol * size)
        s.Add(shape)
        s.Perform()
        if s.NbFreeEdges() == 0:
            break
    done = {"sewn": True, "tolerance": rtol * size, "free_edges": s.NbFreeEdges(), "solids": 0}
    sewn = s.SewedShape()
    # closed shells -> solids (oriented outward), the rest as it is
    comp, b = TopoDS_Compound(), BRep_Builder()
    b.MakeCompound(comp)
    ex = TopExp_Explorer(sewn, TopAbs_SHELL)
    shells = 0
    while ex.More():
        shell = TopoDS.Shell(ex.Current())
        shells += 1
        if BRep_Tool.IsClosed_s(shell):
            b.Add(comp, ShapeFix_Solid().SolidFromShell(shell))
            done["solids"] += 1
        else:
            b.Add(comp, shell)
        ex.Next()
    ex = TopExp_Explorer(sewn, TopAbs_FACE, TopAbs_SHELL)  # faces in no shell
    while ex.More():
        b.Add(comp, ex.Current())
        ex.Next()
    fix = ShapeFix_Shape(comp if shells else sewn)
    fix.Perform()
    return fix.Shape(), done


def _count(shape, kind) -> int:
    from OCP.OCP.collections import (
        IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as IMap,
    )
    from OCP.TopExp import TopExp

    m = IMap()
    TopExp.MapShapes_s(shape, kind, m)
    return m.Extent()


def _has(shape, kind) -> bool:
    """Whether ``shape`` has a sub-shape of type ``kind`` (``_count(shape, kind) > 0`` without
    mapping them all)."""
    return _occ().TopExp_Explorer(shape, kind).More()


def _size(shape) -> float:
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box)
    if box.IsVoid():
        return 0.0
    lo, hi = box.CornerMin(), box.CornerMax()
    return math.dist(_xyz(lo), _xyz(hi))


# ----------------------------------------------------------------------
# geometry descriptions
# ----------------------------------------------------------------------
def _ax3(ax) -> dict:
    return {"origin": _xyz(ax.Location()), "x": _xyz(ax.XDirection()), "y": _xyz(ax.YDirection()),
            "z": _xyz(ax.Direction())}


def _bspline_surface(s) -> dict:
    """Poles, weights and flat knots of a (non-periodic copy of a) Geom_BSplineSurface."""
    if s.IsUPeriodic() or s.IsVPeriodic():
        s = s.Copy()
        if s.IsUPeriodic():
            s.SetUNotPeriodic()
        if s.IsVPeriodic():
            s.SetVNotPeriodic()
    nu, nv = s.NbUPoles(), s.NbVPoles()
    ij = list(itertools.product(range(1, nu + 1), range(1, nv + 1)))  # u major
    poles = _floats(itertools.chain.from_iterable(p.Coord() for p in itertools.starmap(s.Pole, ij)), 3 * nu * nv)
    weights = None
    if s.IsURational() or s.IsVRational():
        weights = _floats(itertools.starmap(s.Weight, ij), nu * nv).reshape(nu, nv)
    return {"type": "bspline", "degree": (s.UDegree(), s.VDegree()), "poles": poles.reshape(nu, nv, 3),
            "weights": weights, "knots_u": _values(s.UKnotSequence()), "knots_v": _values(s.VKnotSequence())}


def _bspline_curve(c, dim: int) -> dict:
    """Poles, weights and flat knots of a (non-periodic copy of a) B-spline curve."""
    if c.IsPeriodic():
        c = c.Copy()
        c.SetNotPeriodic()
    n = c.NbPoles()
    poles = _floats(itertools.chain.from_iterable(p.Coord() for p in map(c.Pole, range(1, n + 1))), dim * n)
    weights = _floats(map(c.Weight, range(1, n + 1)), n) if c.IsRational() else None
    return {"type": "bspline", "degree": c.Degree(), "poles": poles.reshape(n, dim), "weights": weights,
            "knots": _values(c.KnotSequence())}


def _floats(values: Iterable[float], n: int) -> np.ndarray:
    """``(n,)`` array of the ``n`` floats ``values`` (read by numpy as they come: no list, no
    nested tuples to inspect)."""
    return np.fromiter(values, dtype=float, count=n)


def _values(seq) -> np.ndarray:
    """The values of an OpenCASCADE array of reals (``TColStd_Array1OfReal``), here the flat
    knots of a non-periodic B-spline (``KnotSequence``: each knot repeated as its
    multiplicity): one call per value (iterating the array through OCP costs far more)."""
    lo, hi = seq.Lower(), seq.Upper()
    return _floats(map(seq.Value, range(lo, hi + 1)), hi - lo + 1)


#: analytic surfaces kept as such: their parameters, by the OCC accessor of each
#: (the same names on the gp primitives and on their Geom_ surfaces)
_ANALYTIC_FIELDS: dict[str, dict[str, str]] = {
    "plane": {},
    "cylinder": {"radius": "Radius"},
    "cone": {"radius": "RefRadius", "semi_angle": "SemiAngle"},
    "sphere": {"radius": "Radius"},
    "torus": {"major": "MajorRadius", "minor": "MinorRadius"},
}


def _analytic(kind: str, s) -> dict:
    """Description of the analytic surface ``s`` of type ``kind`` (a gp primitive or a Geom_ surface)."""
    return {"type": kind, **_ax3(s.Position()), **{k: getattr(s, m)() for k, m in _ANALYTIC_FIELDS[kind].items()}}


def _elementary(s) -> dict | None:
    """Description of an OpenCASCADE elementary surface (``Geom_Plane``, ...), else None."""
    for kind, cls in _occ().ELEMENTARY:
        if isinstance(s, cls):
            return _analytic(kind, s)
    return None


#: samples per direction of the grid on which a recognised surface's parameter map is checked
MAP_SAMPLES = 4
TWO_PI = 2.0 * math.pi
#: the gp primitive of each analytic Geom_ surface, and its periodic parameters
_PRIMITIVES = {"plane": ("Pln", ()), "cylinder": ("Cylinder", (0,)), "cone": ("Cone", (0,)),
               "sphere": ("Sphere", (0,)), "torus": ("Torus", (0, 1))}


def _max_gap(geo, other, uv: Sequence[tuple[float, float]], uv_other: Sequence[tuple[float, float]]) -> float:
    """Largest distance between ``geo`` at the ``(u, v)`` pairs ``uv`` and ``other`` at
    ``uv_other`` (two OpenCASCADE surfaces, one evaluation each per sample)."""
    from OCP.gp import gp_Pnt

    a, b, gap = gp_Pnt(), gp_Pnt(), 0.0
    for (u, v), (s, t) in zip(uv, uv_other, strict=True):  # samples
        geo.D0(u, v, a)
        other.D0(s, t, b)
        gap = max(gap, a.Distance(b))
    return gap


def _pairs(us: Sequence[float], vs: Sequence[float]) -> list[tuple[float, float]]:
    """The grid ``us x vs`` as ``(u, v)`` pairs, ``u`` major (a few samples: plain floats)."""
    return [(u, v) for u in us for v in vs]


def _recognised(geo, size: float, uv: Sequence[float]) -> dict | None:
    """An analytic twin of a face's other surface ``geo`` (surface of revolution or extrusion,
    ...; ``BRep_Tool::Surface``, with the face's location applied).

    ``GeomConvert_SurfToAnaSurf`` finds the plane, cylinder, cone, sphere or
    torus within 1e-9 of the model size.  Its parameters differ from the
    face's by an affine map ``(u', v') = [u, v, 1] M`` where the face is a
    surface of revolution or extrusion of a line or circle: ``M`` is read off
    three points (the centre of the face's ``(u, v)`` box and a quarter of the
    box along each direction; their analytic parameters by ``ElSLib``, turns
    unwrapped, whole turns chosen so that the image of the box's corner
    ``(u0, v0)`` is in ``[0, 2 pi)``) and kept (``"uv_map"``, ``(3, 2)``) if it maps a
    :data:`MAP_SAMPLES` x :data:`MAP_SAMPLES` grid over the box onto the
    surface's points within 1e-9 of the model size; else None (a plane swept
    by a radial line has polar parameters: no affine map).  A handful of
    numbers per face: plain floats, not numpy.  ``uv``: the face's ``(u0, u1, v0, v1)``
    box (``BRepTools::UVBounds``).
    """
    o = _occ()
    try:
        conv = o.GeomConvert_SurfToAnaSurf(geo)
        ana = conv.ConvertToAnalytical(1e-9 * size)
    except Exception:
        return None
    desc = None if ana is None else _elementary(ana)
    if desc is None or not conv.Gap() <= 1e-9 * size:
        return None
    accessor, periodic = _PRIMITIVES[desc["type"]]
    prim = getattr(ana, accessor)()
    u0, u1, v0, v1 = uv
    du, dv = 0.25 * (u1 - u0), 0.25 * (v1 - v0)
    if not (du > 0 and dv > 0):
        return None
    uc, vc = u0 + 2 * du, v0 + 2 * dv
    (a0, b0), (a1, b1), (a2, b2) = (o.ElSLib.Parameters_s(prim, geo.Value(u, v))
                                    for u, v in ((uc, vc), (uc + du, vc), (uc, vc + dv)))
    step = [[a1 - a0, b1 - b0], [a2 - a0, b2 - b0]]  # the images of (du, 0) and (0, dv)
    for a in periodic:  # turns unwrapped: a quarter of the box is less than half a turn
        for row in step:
            row[a] -= TWO_PI * round(row[a] / TWO_PI)
    lin = [[step[0][0] / du, step[0][1] / du], [step[1][0] / dv, step[1][1] / dv]]
    off = [a0 - uc * lin[0][0] - vc * lin[1][0], b0 - uc * lin[0][1] - vc * lin[1][1]]
    for a in periodic:  # whole turns: the image of the box's corner (u0, v0) in [0, 2 pi) (to 1e-9)
        off[a] -= TWO_PI * math.floor((u0 * lin[0][a] + v0 * lin[1][a] + off[a]) / TWO_PI + 1e-9)
    g = [i / (MAP_SAMPLES - 1) for i in range(MAP_SAMPLES)]
    samples = _pairs([u0 + t * (u1 - u0) for t in g], [v0 + t * (v1 - v0) for t in g])
    image = [(u * lin[0][0] + v * lin[1][0] + off[0], u * lin[0][1] + v * lin[1][1] + off[1]) for u, v in samples]
    if not (all(map(math.isfinite, lin[0] + lin[1] + off)) and _max_gap(geo, ana, samples, image) <= 1e-9 * size):
        return None
    desc["uv_map"] = np.array([lin[0], lin[1], off])
    return desc


#: where inside every knot span (fractions of the span, in each direction) a B-spline twin
#: is compared with its surface: off the span's middle, where the reparametrisation of a
#: symmetric arc (a rational circle) agrees with the arc as it does at the span's ends
TWIN_AT = (1.0 / 3.0, 2.0 / 3.0)


def _bspline_twin(geo, size: float, uv: Sequence[float]) -> dict | None:
    """A face's surface ``geo`` (``BRep_Tool::Surface``) as a B-spline with the same
    parameters, or None.

    ``GeomConvert::SurfaceToBSplineSurface`` of the surface restricted to the
    face's ``(u, v)`` box ``uv`` (``(u0, u1, v0, v1)``) is exact for some surfaces
    (a linear extrusion of a B-spline curve) and reparametrises others (the
    rational circles of a surface of revolution).  It is kept if it reproduces
    the surface within 1e-9 of the model size on the grid of the points
    :data:`TWIN_AT` inside every knot span in both directions: a
    reparametrisation agrees at the spans' ends (and, for a symmetric arc, at
    their middles) and differs elsewhere inside them.
    """
    o = _occ()
    try:
        twin = o.GeomConvert.SurfaceToBSplineSurface_s(o.Geom_RectangularTrimmedSurface(geo, *uv))
        desc = _bspline_surface(twin)
    except Exception:  # OpenCASCADE's construction and domain errors: not convertible this way
        return None
    # the non-empty spans of the flat knots (sorted: a repeated knot spans nothing)
    grids = [[a + t * (b - a) for a, b in itertools.pairwise(knots.tolist()) if b > a for t in TWIN_AT]
             for knots in (desc["knots_u"], desc["knots_v"])]
    samples = _pairs(*grids)
    return desc if _max_gap(geo, twin, samples, samples) <= 1e-9 * size else None


def _surface(face, size: float = 1.0, uv: Sequence[float] | None = None) -> tuple[dict, bool]:
    """Description of a face's surface; ``(desc, needs NurbsConvert)``.  ``uv``: the face's
    ``(u0, u1, v0, v1)`` box if known (``BRepTools::UVBounds``, which costs a pass over the
    face's p-curves), else found where needed."""
    o = _occ()
    a = o.BRepAdaptor_Surface(face, False)
    t = int(a.GetType())
    kind = o.ANALYTIC.get(t)
    if kind is not None:  # a.Plane(), a.Cylinder(), ...: the gp primitive
        return _analytic(kind, getattr(a, kind.capitalize())()), False
    if t == o.BSPLINE_SURFACE:
        return _bspline_surface(a.BSpline()), False
    if t == o.BEZIER_SURFACE:
        return _bspline_surface(o.GeomConvert.SurfaceToBSplineSurface_s(a.Bezier())), False
    name = o.SURFACE_NAMES[t]
    if uv is None:
        uv = o.BRepTools.UVBounds_s(face)
    geo = o.BRep_Tool.Surface_s(face)  # with the face's location applied
    desc = _recognised(geo, size, uv) or _bspline_twin(geo, size, uv)
    if desc is not None:
        desc["source"] = name
        return desc, False
    return {"type": name}, True


def _basis(face, size: float, uv: Sequence[float]) -> dict | None:
    """Description of the surface a face's surface trims or offsets, with the face's
    parameters, or None if it neither trims nor offsets one (or that one cannot be described).

    A ``Geom_RectangularTrimmedSurface`` has its basis surface's parameters, and
    ``Geom_OffsetSurface.Surface()`` is the equivalent surface (an offset plane,
    cylinder, ... with the same parameters) where OpenCASCADE knows one; the
    result is described as an elementary or B-spline surface, else as in
    :func:`_surface` (recognised analytic surface, B-spline twin).
    """
    from OCP.Geom import Geom_BSplineSurface, Geom_OffsetSurface

    o = _occ()
    geo = o.BRep_Tool.Surface_s(face)  # with the face's location applied
    changed = False
    for _ in range(8):  # (a chain of wrappers: trimmed offset of a trimmed ...)
        if isinstance(geo, o.Geom_RectangularTrimmedSurface):
            geo = geo.BasisSurface()
        elif isinstance(geo, Geom_OffsetSurface) and geo.Surface() is not None:
            geo = geo.Surface()
        else:
            break
        changed = True
    if not changed:
        return None
    if isinstance(geo, Geom_BSplineSurface):
        return _bspline_surface(geo)
    desc = _elementary(geo) or _recognised(geo, size, uv) or _bspline_twin(geo, size, uv)
    if desc is not None:
        desc.setdefault("source", "basis")
    return desc


#: tolerance of :func:`_approximated`, relative to the model size
APPROX_RTOL = 1e-10


def _approximated(face, size: float, uv: Sequence[float]) -> dict | None:
    """A B-spline within :data:`APPROX_RTOL` of the model size of the face's surface over its
    ``(u, v)`` box, with the surface's parameters (``GeomConvert_ApproxSurface``), or None.

    For surfaces no NURBS reproduces (an offset of a B-spline surface), whose
    ``BRepBuilderAPI_NurbsConvert`` is an approximation to OpenCASCADE's own
    tolerance (~1e-7 of the size).
    """
    from OCP.GeomAbs import GeomAbs_Shape

    o = _occ()
    geo = o.Geom_RectangularTrimmedSurface(o.BRep_Tool.Surface_s(face), *uv)
    try:
        ap = o.GeomConvert_ApproxSurface(geo, APPROX_RTOL * size, GeomAbs_Shape.GeomAbs_C2, GeomAbs_Shape.GeomAbs_C2,
                                         9, 9, 400, 1)
    except Exception:  # OpenCASCADE's construction errors: not approximable this way
        return None
    if not (ap.IsDone() or ap.HasResult()) or not ap.MaxError() <= APPROX_RTOL * size * 10:
        return None
    desc = _bspline_surface(ap.Surface())
    desc["source"] = "approximation"
    return desc


#: OpenCASCADE's samples per face for its verification (:func:`_checks`): a
#: ``CHECK_GRID x CHECK_GRID`` grid over the face's ``(u, v)`` box (coarser on OpenCASCADE's
#: own analytic primitives, :func:`_check_grid`), and on one edge use of
#: every wire and others up to ``CHECK_USES`` in all a point of the p-curve and two beside it
CHECK_GRID = 4
CHECK_USES = 4
#: the points beside a p-curve are this fraction of the face's extent (or ten times the
#: edge's tolerance, if more) off it, across the p-curve
CHECK_OFFSET = 1e-3


def _check_uses(wires: Sequence[Sequence[tuple]]) -> list[tuple]:
    """The edge uses :func:`_checks` samples, of the ``(edge, p-curve adaptor, first, last, seam)`` of each
    wire's non-degenerate uses (as :func:`_wires` walked them): the first one of every wire
    (every loop is checked), then others spread over the face's uses, up to
    :data:`CHECK_USES` in all."""
    picked = [w[0] for w in wires if w]
    rest = [e for w in wires for e in w[1:]]
    extra = CHECK_USES - len(picked)
    if extra > 0 and rest:
        picked += rest[::max(1, math.ceil(len(rest) / extra))][:extra]
    return picked


def _check_grid(surface: dict, convert: bool, fallback: str | None) -> int:
    """Samples per direction of a face's check grid (:func:`_checks`): :data:`CHECK_GRID`, but
    for a face whose description is OpenCASCADE's own analytic primitive (its axes and radii
    copied, not recognised from another surface nor a fallback), whose conversion is exact by
    construction: 2 for a plane (affine in ``(u, v)``: three points fix it), 3 for a cylinder,
    cone, sphere or torus (three distinct angles fix ``a cos + b sin + c``).  Every face keeps
    its samples on and beside its p-curves."""
    if convert or fallback is not None or "source" in surface or surface["type"] not in _PRIMITIVES:
        return CHECK_GRID
    return 2 if surface["type"] == "plane" else 3


def _clamp_box(a) -> tuple[float, float, float, float]:
    """``(u0, u1, v0, v1)`` into which :func:`_checks` clamps its parameters on the surface of the
    adaptor ``a``: a B-spline's (or Bezier's) knots in its open directions (a p-curve may leave
    them by its tolerance; both sides clamp there), infinite elsewhere (other surfaces
    extrapolate, as ours do)."""
    o = _occ()
    ulo, uhi, vlo, vhi = (-math.inf, math.inf) * 2
    if int(a.GetType()) in (o.BSPLINE_SURFACE, o.BEZIER_SURFACE):
        if not a.IsUPeriodic():
            ulo, uhi = a.FirstUParameter(), a.LastUParameter()
        if not a.IsVPeriodic():
            vlo, vhi = a.FirstVParameter(), a.LastVParameter()
    return ulo, uhi, vlo, vhi


class _Placed:
    """OpenCASCADE's samples (:func:`_checks`) of faces that are placed instances of one face
    (an assembly's parts: one ``TopoDS_TShape`` under several ``TopLoc_Location``), taken once
    per shared face and moved to every other instance by the rigid motion between the
    instances' locations (:func:`_placed_checks`).

    Attributes:
        keys: the faces seen, each at the identity location (an indexed map: instances of
            one face have one index).
        first: per ``(index, grid, uv box)`` the first instance's samples, the inverse of its
            location's transformation, :func:`_clamp_box` of its surface and its spot samples
            (their rows and ``(u, v)``).
    """

    def __init__(self) -> None:
        from OCP.OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as IMap
        from OCP.TopLoc import TopLoc_Location

        self.keys = IMap()
        self.identity = TopLoc_Location()
        self.first: dict[tuple, tuple[dict, Any, tuple[float, float, float, float], tuple[list[int], list]]] = {}


#: largest difference, relative to the model size or the point's largest coordinate (points)
#: or to the derivatives' largest component, between OpenCASCADE's own point and derivatives
#: at an instance's spot samples and the first instance's moved there
#: (:func:`_placed_checks`): rounding of the motion only
PLACED_RTOL = 1e-12


def _placed_checks(face, uv: Sequence[float], uses: Sequence[Sequence[tuple]], grid: int, size: float,
                   placed: _Placed) -> dict:
    """:func:`_checks` of a face, shared between the placed instances of one face (``placed``).

    The first instance is sampled as :func:`_checks` samples it.  Another instance, placed
    by a rigid motion ``M`` from the first (``T_i T_1^-1``, scale 1; any other
    transformation is sampled on its own), gets the first's samples with points
    ``M p`` and derivatives ``R S_u``, ``R S_v`` (``R`` the rotation of ``M``): the same
    parameters, classifier states (``IntTools_FClass2d`` classifies in the face's parameter
    plane, forward oriented) and offset.  Each such instance is also evaluated by
    OpenCASCADE itself (its own ``BRepAdaptor_Surface``, with its location) at its first
    grid sample and its first sample on a p-curve, whose values replace the moved ones; if
    they differ from them by more than :data:`PLACED_RTOL`, the instance is sampled in full.
    So every face is compared (by :mod:`nagata_snap.cad.verify`) with OpenCASCADE's points,
    derivatives and classification of that face.
    """
    from OCP.gp import gp_Pnt, gp_Vec

    trsf = face.Location().Transformation()
    key = (placed.keys.Add(face.Located(placed.identity)), grid, tuple(uv))
    first = placed.first.get(key)
    if first is None:
        c = _checks(face, uv, uses, grid)
        a = _occ().BRepAdaptor_Surface(face, False)
        rows = [0, *np.flatnonzero(c["kind"] == 1)[:1].tolist()]  # (a grid sample comes first)
        placed.first[key] = (c, trsf.Inverted(), _clamp_box(a), (rows, c["uv"][rows].tolist()))
        return c
    t0 = time.perf_counter()
    c1, inverse, (ulo, uhi, vlo, vhi), spots = first
    m = trsf.Multiplied(inverse)
    if m.ScaleFactor() != 1.0:
        return _checks(face, uv, uses, grid)
    M = np.array([[m.Value(i, j) for j in range(1, 5)] for i in range(1, 4)])
    d1 = np.dot(c1["d1"], M[:, :3].T)
    d1[:, 0] += M[:, 3]
    a = _occ().BRepAdaptor_Surface(face, False)
    p, su, sv = gp_Pnt(), gp_Vec(), gp_Vec()
    own: list[tuple] = []
    for u, v in spots[1]:  # OpenCASCADE's own point and derivatives at the spot samples
        a.D1(min(max(u, ulo), uhi), min(max(v, vlo), vhi), p, su, sv)
        own += (p.Coord(), su.Coord(), sv.Coord())
    at = np.array(own).reshape(-1, 3, 3)
    dev = np.abs(at - d1[spots[0]]).max(axis=2)  # (spot, point / S_u / S_v)
    scale = np.abs(at).max(axis=2)
    scale[:, 0] = np.maximum(scale[:, 0], size)
    scale[:, 1:] = scale[:, 1:].max(axis=1, keepdims=True)
    if not (dev <= PLACED_RTOL * scale).all():
        return _checks(face, uv, uses, grid)
    d1[spots[0]] = at
    return {**c1, "d1": d1, "time": time.perf_counter() - t0}


def _checks(face, uv: Sequence[float], uses: Sequence[Sequence[tuple]], grid: int = CHECK_GRID) -> dict:
    """OpenCASCADE's samples of a face, against which :mod:`nagata_snap.cad.verify`
    checks its conversion: parameters in the face's own ``(u, v)`` (those of its
    description's p-curves), OpenCASCADE's point and first derivatives and face
    classifier state at each (``IntTools_FClass2d``, formerly ``BRepTopAdaptor_FClass2d``:
    built once per face, it answers ~35 times faster than ``BRepClass_FaceClassifier``, to
    which it defers near the boundary).  ``uses``: the ``(edge, p-curve adaptor, its first and
    last parameters, seam or None)`` of every wire's non-degenerate uses (:func:`_wires`);
    ``grid``: samples per direction of the grid over the face's ``(u, v)`` box
    (:func:`_check_grid`).  (Only OpenCASCADE's calls here, one
    per sample; the arithmetic on the samples is :mod:`~nagata_snap.cad.verify`'s, on all
    faces' at once.)

    Returns:
        ``uv (k, 2)``, ``d1 (k, 3, 3)``: the surface's point, ``S_u`` and ``S_v`` (a B-spline's at
        ``uv`` clamped into its knots in its open directions, as the package's B-splines clamp),
        ``state (k,)`` (0 in, 1 out, 2 on), ``kind (k,)`` (0 grid,
        1 on a p-curve, whose state is 2 without asking, 2 beside one), ``offset``
        (for a converted face also ``gap (k,)``, :func:`_gaps`) (the 3D distance of the points beside
        the p-curves from them) and ``time`` (seconds).
    """
    from OCP.gp import gp_Pnt, gp_Pnt2d, gp_Vec, gp_Vec2d
    from OCP.IntTools import IntTools_FClass2d

    t0 = time.perf_counter()
    o = _occ()
    a = o.BRepAdaptor_Surface(face, False)
    u0, u1, v0, v1 = uv
    fr = [(i + 0.5) / grid for i in range(grid)]
    grid_uv = _pairs([u0 + t * (u1 - u0) for t in fr], [v0 + t * (v1 - v0) for t in fr])
    kind = [0] * len(grid_uv)
    params = [x for uv_ in grid_uv for x in uv_]  # (u, v) of every sample, flat (numpy reads it faster)
    p, su, sv = gp_Pnt(), gp_Vec(), gp_Vec()
    pc, sc, vc, d1 = p.Coord, su.Coord, sv.Coord, a.D1
    ulo, uhi, vlo, vhi = _clamp_box(a)
    clamp = math.isfinite(ulo) or math.isfinite(vlo)  # (else min and max give u and v themselves)
    D: list[float] = []  # per sample its point, S_u and S_v (flat)

    def sample(u: float, v: float) -> tuple[float, ...]:
        """OpenCASCADE's point and derivatives at ``(u, v)`` (clamped where it clamps) onto ``D``;
        returns ``S_u + S_v`` (six numbers)."""
        if clamp:
            u, v = min(max(u, ulo), uhi), min(max(v, vlo), vhi)
        d1(u, v, p, su, sv)
        s_uv = sc() + vc()
        D.extend(pc())
        D.extend(s_uv)
        return s_uv

    for u, v in grid_uv:  # the grid (OpenCASCADE's points and derivatives)
        sample(u, v)
    # the face's extent, roughly: the grid's, scaled to the span of a CHECK_GRID grid's
    xs, ys, zs = D[0::9], D[1::9], D[2::9]
    span = (CHECK_GRID - 1) / CHECK_GRID / ((grid - 1) / grid) if grid > 1 else 1.0
    extent = span * math.dist((min(xs), min(ys), min(zs)), (max(xs), max(ys), max(zs)))
    extent = extent if math.isfinite(extent) else 0.0
    p2, d2 = gp_Pnt2d(), gp_Vec2d()
    offset = CHECK_OFFSET * extent
    tool, EDGE = o.BRep_Tool, o.EDGE
    for e, c, t0_, t1_, seam in _check_uses(uses):  # loop over a few edge uses (their p-curves)
        c.D1(0.5 * (t0_ + t1_), p2, d2)
        u, v = p2.Coord()
        params += (u, v)
        kind.append(1)
        s_uv = sample(u, v)
        if tool.IsClosed_s(e, face) if seam is None else seam:  # a seam: the face on both sides
            continue
        nv, nu = d2.Coord()
        nu = -nu
        # |S_u nu + S_v nv| from the numbers just read (not by gp_Vec arithmetic: five calls)
        x, y, z = s_uv[0] * nu + s_uv[3] * nv, s_uv[1] * nu + s_uv[4] * nv, s_uv[2] * nu + s_uv[5] * nv
        length = math.sqrt(x * x + y * y + z * z)
        if not length > 0:
            continue
        off = max(offset, 10.0 * tool.MaxTolerance_s(e, EDGE)) / length
        for s in (off, -off):
            u_, v_ = u + s * nu, v + s * nv
            params += (u_, v_)
            kind.append(2)
            sample(u_, v_)
    cls = IntTools_FClass2d(face, max(tool.MaxTolerance_s(face, o.FACE), 1e-9 * extent))
    code = o.STATES
    q = gp_Pnt2d()
    at, perform = q.SetCoord, cls.Perform
    state = []
    for (u, v), kd in zip(itertools.batched(params, 2), kind, strict=True):  # the classifier's states
        if kd == 1:  # on a p-curve: on the boundary (not asked: the classifier's slowest case)
            state.append(2)
            continue
        at(u, v)
        state.append(code.get(int(perform(q)), 2))
    k = len(kind)
    return {"uv": np.array(params, dtype=float).reshape(k, 2), "d1": np.array(D).reshape(k, 3, 3),
            "state": np.array(state, dtype=np.int8), "kind": np.array(kind, dtype=np.int8), "offset": offset,
            "time": time.perf_counter() - t0}


def _described(a, dim: int, other, known: tuple[float, float, int] | None = None) -> dict:
    """Description of a curve adaptor (3D edge or 2D p-curve, ``dim`` 3 or 2) with its range.

    Lines and circles in closed form, B-splines as they are, anything else
    as the B-spline ``other(t0, t1)`` returns (``GeomConvert``).  ``known``: the
    adaptor's first and last parameters and type (``int(GetType())``) where already asked.
    """
    o = _occ()
    t0, t1, t = known or (a.FirstParameter(), a.LastParameter(), int(a.GetType()))
    if t == o.LINE:
        ln = a.Line()
        return {"type": "line", "origin": _xyz(ln.Location()), "direction": _xyz(ln.Direction()),
                "range": (t0, t1)}
    if t == o.CIRCLE:
        c = a.Circle()
        ax = c.Position()
        return {"type": "circle", "center": _xyz(ax.Location()), "x": _xyz(ax.XDirection()),
                "y": _xyz(ax.YDirection()), "radius": c.Radius(), "range": (t0, t1)}
    if t == o.BSPLINE_CURVE:
        d = _bspline_curve(a.BSpline(), dim)
    else:
        d = _bspline_curve(other(t0, t1), dim)
        t0, t1 = float(d["knots"][d["degree"]]), float(d["knots"][-d["degree"] - 1])
    d["range"] = (t0, t1)
    return d


def _curve3d(edge, adaptor: tuple | None = None) -> dict | None:
    """Description of an edge's 3D curve (None for degenerate edges and edges without one);
    ``adaptor``: the edge's ``BRepAdaptor_Curve`` with its first and last parameters and type
    (``int(GetType())``) if known already (the edge then has a 3D curve and is not degenerate)."""
    o = _occ()
    if adaptor is None and (o.BRep_Tool.Degenerated_s(edge) or not o.BRep_Tool.IsGeometric_s(edge)):
        return None

    def other(t0, t1):  # with the edge's location applied
        geo = o.BRep_Tool.Curve_s(edge, t0, t1)
        return o.GeomConvert.CurveToBSplineCurve_s(o.Geom_TrimmedCurve(geo, t0, t1))

    if adaptor is None:
        return _described(o.BRepAdaptor_Curve(edge), 3, other)
    return _described(adaptor[0], 3, other, adaptor[1:])


def _curve2d(edge, face, adaptor=None, known: tuple[float, float, int] | None = None) -> dict:
    """Description of the p-curve of an (oriented) edge on a face, with its range
    (``adaptor``: its ``BRepAdaptor_Curve2d``, if made already; ``known``: as :func:`_described`'s)."""
    o = _occ()

    def other(t0, t1):
        geo = o.BRep_Tool.CurveOnSurface_s(edge, face, t0, t1)
        return o.Geom2dConvert.CurveToBSplineCurve_s(o.Geom2d_TrimmedCurve(geo, t0, t1))

    return _described(o.BRepAdaptor_Curve2d(edge, face) if adaptor is None else adaptor, 2, other, known)


# ----------------------------------------------------------------------
# topology
# ----------------------------------------------------------------------
def _wires(face, pface, edge_map, edge_of, degenerate: Sequence[bool] | None = None,
           uses_out: list | None = None, joined: bool = False) -> list[dict]:
    """Wires of ``face`` with the p-curves of ``pface`` (the face itself or its NURBS twin).

    ``uses_out``: a list to which the ``(edge of pface, p-curve adaptor, first, last parameter,
    seam)`` of each wire's non-degenerate uses are appended, one list per wire (the uses
    :func:`_checks` samples; ``seam``: ``BRep_Tool::IsClosed`` of the edge on ``pface``, None
    where not asked here).

    ``degenerate``: the degenerate flags of the edges of ``edge_map`` (asked of OpenCASCADE
    once per edge, not per use), else asked here.  ``joined``: the faces walked are to be
    joined (:mod:`nagata_snap.cad.sewing`): a use's ``seam`` is left False for
    :func:`~nagata_snap.cad.sewing.relabel` to set, but on a degenerate edge (which
    stays with its face).  The outer wire is ``BRepTools::OuterWire``'s, asked only of a face
    with several wires (a face's only wire is its outer wire).
    """
    o = _occ()
    tool = o.BRep_Tool
    find, adaptor, degenerated, closed = edge_map.FindIndex, o.BRepAdaptor_Curve2d, tool.Degenerated_s, tool.IsClosed_s
    same = pface is face  # the walked edges are the p-curves' own (not a converted face's)
    ws = []
    ex = o.TopExp_Explorer(face, o.WIRE)
    while ex.More():
        ws.append(o.TopoDS.Wire(ex.Current()))
        ex.Next()
    outer = o.BRepTools.OuterWire_s(face) if len(ws) > 1 else None
    wires = []
    for w in ws:  # loop over the face's wires
        uses = []
        mine = []
        we = o.BRepTools_WireExplorer(w, face)
        while we.More():
            e = we.Current()
            i = find(e) - 1
            deg = degenerated(e) if degenerate is None else degenerate[i]
            seam = closed(e, face) if not joined or deg else False
            pe = edge_of(e)
            a = adaptor(pe, pface)
            known = (a.FirstParameter(), a.LastParameter(), int(a.GetType()))
            uses.append({
                "edge": i,
                "reversed": int(e.Orientation()) == o.REVERSED,
                "seam": seam,
                "degenerate": deg,
                "pcurve": _curve2d(pe, pface, a, known),
            })
            if not deg:  # (whether it is a seam, where asked of these edge and face already)
                mine.append((pe, a, known[0], known[1], seam if same and not joined else None))
            we.Next()
        wires.append({"outer": outer is None or w.IsSame(outer), "uses": uses})
        if uses_out is not None:
            uses_out.append(mine)
    return wires


def _face(face, index: int, edge_map, size: float, degenerate: Sequence[bool] | None = None,
          fallback: str | None = None, check: bool = True, placed: _Placed | None = None,
          joined: bool = False) -> dict:
    """Surface, bounds, orientation and wires of one face (converting it if needed);
    ``degenerate``, ``joined``: see :func:`_wires`.

    ``fallback``: ``"basis"`` describes the surface the face's own one trims or offsets
    (:func:`_basis`), ``"nurbs"`` converts the face with ``BRepBuilderAPI_NurbsConvert``
    (``converted``), ``"approx"`` approximates its surface closely (:func:`_approximated`);
    where the one asked for does not apply, ``"nurbs"`` (the face's ``fallback`` says which
    was used); asked for by :mod:`nagata_snap.cad.verify` for a face whose first
    description failed its check.  ``check``: add OpenCASCADE's samples of the face
    (``"check"``, :func:`_checks`; shared with the other placed instances of the face in
    ``placed``, :func:`_placed_checks`, unless converted).
    """
    o = _occ()
    uv = o.BRepTools.UVBounds_s(face)
    basis = _basis(face, size, uv) if fallback == "basis" else \
        _approximated(face, size, uv) if fallback == "approx" else None
    if basis is not None:
        surface, convert = basis, False
    elif fallback is not None:  # nothing to unwrap (or approximate): OpenCASCADE's NURBS
        surface, convert = {"type": o.SURFACE_NAMES[int(o.BRepAdaptor_Surface(face, False).GetType())]}, True
    else:
        surface, convert = _surface(face, size, uv)
    pface, edge_of = face, (lambda e: e)
    checked: list[list[tuple]] = []  # the uses the check samples (_wires walks them)
    if convert:  # (rare: the class is imported here)
        from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert

        try:
            conv = BRepBuilderAPI_NurbsConvert(face, True)
            pface = o.TopoDS.Face(conv.Shape())
            surface, convert_again = _surface(pface, size)
            if convert_again:
                raise ReadError(f"BRepBuilderAPI_NurbsConvert gave a {surface['type']} surface")
        except ReadError as e:
            raise ReadError(f"face {index} ({surface['type']} surface): cannot be converted to NURBS: {e}") from None
        except Exception as e:
            raise ReadError(
                f"face {index} ({surface['type']} surface): OpenCASCADE cannot convert it to NURBS: "
                f"{type(e).__name__}: {e}") from None

        def edge_of(e, conv=conv):  # the converted edge, used as the original (seams!)
            return o.TopoDS.Edge(conv.ModifiedShape(e).Oriented(e.Orientation()))
        uv = o.BRepTools.UVBounds_s(pface)
    out = {
        "surface": surface,
        "uv": tuple(uv),
        "reversed": int(face.Orientation()) == o.REVERSED,
        "converted": convert,
        "wires": _wires(face, pface, edge_map, edge_of, degenerate, checked, joined),
    }
    if fallback is not None:
        out["fallback"] = "nurbs" if basis is None else fallback
    if check:
        grid = _check_grid(surface, convert, fallback)
        out["check"] = c = _checks(pface, uv, checked, grid) \
            if convert or placed is None or face.Location().IsIdentity() else \
            _placed_checks(face, uv, checked, grid, size, placed)
        if convert:  # the converted face's points against the face's own surface
            t0 = time.perf_counter()
            c["gap"] = _gaps(face, c["d1"][:, 0], (c["kind"] != 2) | (c["state"] == 0))
            c["time"] += time.perf_counter() - t0
    return out


def _gaps(face, points: np.ndarray, which: np.ndarray) -> np.ndarray:
    """``(k,)`` distance of ``points[which]`` from ``face``'s own surface
    (``GeomAPI_ProjectPointOnSurf``; 0 elsewhere): how far a face converted by
    ``BRepBuilderAPI_NurbsConvert``, whose parameters may differ from the face's, is from it."""
    from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
    from OCP.gp import gp_Pnt

    geo = _occ().BRep_Tool.Surface_s(face)
    out = np.zeros(len(points))
    for k in np.flatnonzero(which).tolist():  # a few samples of a converted face
        pr = GeomAPI_ProjectPointOnSurf(gp_Pnt(*points[k].tolist()), geo)
        out[k] = pr.LowerDistance() if pr.NbPoints() else math.inf
    return out


def _ancestors(kind, maps_child, maps_parent) -> list[list[int]]:
    """Indices of the parent shapes (``maps_parent``, e.g. solids) of every ``kind`` sub-shape.

    One explorer per parent (few) rather than ``TopExp::MapShapesAndAncestors``,
    whose per-child lists cost far more to walk through OCP.
    """
    from OCP.TopExp import TopExp_Explorer

    out: list[set[int]] = [set() for _ in range(maps_child.Extent())]
    for j in range(1, maps_parent.Extent() + 1):
        ex = TopExp_Explorer(maps_parent.FindKey(j), kind)
        while ex.More():
            c = maps_child.FindIndex(ex.Current()) - 1
            if c >= 0:
                out[c].add(j - 1)
            ex.Next()
    return [sorted(s) for s in out]


def _load(path: str, unit: str) -> tuple:
    """Read a file (no healing): ``(shape, info)``, ``info`` as :func:`load_shape`'s without
    ``healed`` and the healing time."""
    from OCP.TopAbs import TopAbs_VERTEX

    fmt = FORMATS.get(os.path.splitext(path)[1].lower())
    if fmt is None:
        raise ReadError(f"{path}: unknown CAD file extension (expected one of {', '.join(sorted(FORMATS))})")
    unit = str(unit).upper()
    if unit not in UNITS and unit != "FILE":
        raise ReadError(f"unknown length unit {unit!r} (expected one of {', '.join(UNITS)} or FILE)")
    if not os.path.isfile(path):
        raise ReadError(f"{path}: no such file")
    times = {}
    t0 = time.perf_counter()
    with _quiet():
        shape, file_units, unit = _read(path, fmt, unit)
    times["read"] = time.perf_counter() - t0
    if shape.IsNull() or not _has(shape, TopAbs_VERTEX):
        raise ReadError(f"{path}: the file holds an empty shape (no vertices, edges or faces)")
    size = _size(shape)
    if not (math.isfinite(size) and size > 0):
        raise ReadError(f"{path}: the shape has no finite extent (bounding box diagonal {size})")
    return shape, {"file_units": file_units, "unit": unit, "times": times, "size": size, "format": fmt}


def _needs_sewing(shape, sew: bool | None) -> bool:
    """Whether healing sews ``shape``: as asked, by default when it has several faces and no
    shell (IGES files usually)."""
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SHELL

    if sew is None:
        return not _has(shape, TopAbs_SHELL) and _count(shape, TopAbs_FACE) > 1
    return sew


def load_shape(path: str | os.PathLike, unit: str = "MM", heal: bool = True,
               sew: bool | None = None) -> tuple:
    """Read and heal a file with OpenCASCADE: ``(shape, info)`` (see :func:`read_shape`).

    The shape is OpenCASCADE's own healing (sewing included), whichever path
    :func:`read_shape` takes; ``heal=False`` gives the shape as read.

    ``info``: ``file_units``, ``unit`` (of the coordinates), ``healed``,
    ``times`` and ``size`` (bounding-box diagonal).
    """
    path = os.fspath(path)
    shape, info = _load(path, unit)
    t0 = time.perf_counter()
    healed = {"sewn": False}
    if heal:
        shape, healed = _heal(shape, info["size"], sew)
    info["times"]["heal"] = time.perf_counter() - t0
    info["healed"] = healed
    return shape, info


def shape_maps(shape) -> tuple:
    """``(faces, edges, vertices, solids)`` index maps of a shape (``TopExp::MapShapes``)."""
    from OCP.OCP.collections import (
        IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher as IMap,
    )
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE, TopAbs_SOLID, TopAbs_VERTEX
    from OCP.TopExp import TopExp

    maps = []
    for kind in (TopAbs_FACE, TopAbs_EDGE, TopAbs_VERTEX, TopAbs_SOLID):
        m = IMap()
        TopExp.MapShapes_s(shape, kind, m)
        maps.append(m)
    return tuple(maps)


@functools.cache
def _sewing():
    """:mod:`nagata_snap.cad.sewing` (numpy and scipy only), also where this module runs
    without its package: the worker's reader server loads this file alone (no MPI)."""
    if __package__:
        from nagata_snap.cad import sewing

        return sewing
    import importlib.util
    import sys

    name = "_nagata_snap_cad_sewing"
    spec = importlib.util.spec_from_file_location(name, os.path.join(os.path.dirname(__file__), "sewing.py"))
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # (dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


def _vertices(vmap) -> tuple[np.ndarray, np.ndarray]:
    """``(points (nv, 3), tolerances (nv,))`` of the vertices of ``vmap``."""
    o = _occ()
    n = vmap.Extent()
    vs = [o.TopoDS.Vertex(vmap.FindKey(i)) for i in range(1, n + 1)]
    points = _floats(itertools.chain.from_iterable(o.BRep_Tool.Pnt_s(v).Coord() for v in vs), 3 * n).reshape(n, 3)
    _check_finite(points, "the vertices")
    return points, _floats(_tolerances(vs, o.VERTEX), n)


def _tolerances(shapes: list, kind) -> list[float]:
    """``BRep_Tool::Tolerance`` of each of the vertices or edges ``shapes`` (``kind``:
    ``TopAbs_VERTEX`` or ``TopAbs_EDGE``), as ``BRep_Tool::MaxTolerance`` of the shape over
    its sub-shapes of that type (itself alone: the largest of 0 and its tolerance, the same
    number), which is not overloaded: ``Tolerance`` (of a face, an edge or a vertex) costs
    pybind11 failed tries of the overloads before, several times the call."""
    tol = _occ().BRep_Tool.MaxTolerance_s
    return [tol(s, kind) for s in shapes]


def _ends(edges: list, vmap) -> list[tuple[int, int]]:
    """Indices of each edge's first and last vertex in ``vmap`` (-1: none, a null vertex's
    index being 0)."""
    from OCP.TopoDS import TopoDS_Vertex

    o = _occ()
    v0, v1 = TopoDS_Vertex(), TopoDS_Vertex()
    out = []
    for e in edges:  # loop over edges (two vertices each, into the same two objects)
        o.TopExp.Vertices_s(e, v0, v1)
        out.append((vmap.FindIndex(v0) - 1, vmap.FindIndex(v1) - 1))
    return out


def _walk(shape, size: float, fallback: dict[int, str] | None = None, check: bool = True) -> dict:
    """``vertices``, ``vertex_tolerance``, ``edges``, ``faces`` and ``num_solids`` of a shape."""
    from OCP.BRep import BRep_Tool
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopoDS import TopoDS

    fmap, emap, vmap, smap = shape_maps(shape)
    vertices, vtol = _vertices(vmap)
    occ_edges = [TopoDS.Edge(emap.FindKey(i)) for i in range(1, emap.Extent() + 1)]
    ends, tolerances = _ends(occ_edges, vmap), _tolerances(occ_edges, _occ().EDGE)
    degenerate = [BRep_Tool.Degenerated_s(e) for e in occ_edges]  # (asked once per edge, not per use)
    edges = []
    for i, (e, ve, tol) in enumerate(zip(occ_edges, ends, tolerances, strict=True)):  # loop over CAD edges
        edges.append({
            "curve": _curve3d(e),
            "vertices": ve,
            "tolerance": tol,
            "degenerate": degenerate[i],
            "source": i,
        })
    fb = fallback or {}
    placed = _Placed() if check else None
    faces = [_face(TopoDS.Face(fmap.FindKey(i)), i - 1, emap, size, degenerate, fb.get(i - 1), check, placed)
             for i in range(1, fmap.Extent() + 1)]
    solids = _ancestors(TopAbs_FACE, fmap, smap)
    for f, s in zip(faces, solids, strict=True):
        f["solids"] = s
    return {"num_solids": smap.Extent(), "vertices": vertices, "vertex_tolerance": vtol, "edges": edges,
            "faces": faces}


def _edge_copies(emap, vmap, points: np.ndarray, vtol: np.ndarray) -> tuple:
    """:class:`~nagata_snap.cad.sewing.EdgeCopies` of an unsewn shape, the edges and their
    curve adaptors with their first and last parameters and types (``int(GetType())``; None:
    degenerate or without a 3D curve)."""
    from OCP.gp import gp_Pnt, gp_Vec
    from OCP.Standard import Standard_NullObject

    o = _occ()
    tool = o.BRep_Tool
    n = emap.Extent()
    edges = [o.TopoDS.Edge(emap.FindKey(i)) for i in range(1, n + 1)]
    degenerate = [tool.Degenerated_s(e) for e in edges]
    adaptors: list = [None] * n
    p, v = gp_Pnt(), gp_Vec()
    curved: list[bool] = []
    # per edge: middle point, tangent, quarter points (flat, NaN without a curve: numpy reads it faster)
    xyz: list[float] = []
    for i, e in enumerate(edges):  # loop over the unsewn edges (OCC queries)
        try:  # (an edge without geometry, neither a 3D curve nor a p-curve, has no adaptor)
            a = None if degenerate[i] else o.BRepAdaptor_Curve(e)
        except Standard_NullObject:
            a = None
        if a is None:
            xyz += _NO_CURVE
            curved.append(False)
            continue
        t0, t1, kind = a.FirstParameter(), a.LastParameter(), int(a.GetType())
        adaptors[i] = (a, t0, t1, kind)
        a.D1(0.5 * (t0 + t1), p, v)
        xyz += p.Coord()
        xyz += v.Coord()
        a.D0(0.75 * t0 + 0.25 * t1, p)
        xyz += p.Coord()
        a.D0(0.25 * t0 + 0.75 * t1, p)
        xyz += p.Coord()
        curved.append(kind != o.LINE and kind != o.CIRCLE)
    g = np.array(xyz).reshape(n, 4, 3)
    copies = _sewing().EdgeCopies(
        points, vtol, np.array(_ends(edges, vmap), dtype=np.int64).reshape(-1, 2),
        np.array(_tolerances(edges, o.EDGE)), np.array(degenerate, dtype=bool),
        np.array(curved, dtype=bool), g[:, 0], g[:, 1], g[:, 2:])
    return copies, edges, adaptors


#: :func:`_edge_copies`' middle point, tangent and quarter points of an edge without a 3D curve
_NO_CURVE = (math.nan,) * 12


def _face_uses(faces: list[dict], occ_faces: list) -> Any:
    """:class:`~nagata_snap.cad.sewing.FaceUses` of the walked faces of an unsewn shape
    (``occ_faces``: their ``TopoDS_Face``): their uses (as walked), each face's plane (if it is
    one of its own, as its description says: not a recognised one) and, from OpenCASCADE, its
    bounding box."""
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    flat = [(i, u["edge"], u["reversed"]) for i, f in enumerate(faces) for w in f["wires"] for u in w["uses"]]
    use = np.array(flat, dtype=np.int64).reshape(-1, 3)
    nf = len(faces)
    plane: list[bool] = []
    frames: list[float] = []  # origin and oriented normal of each face (flat)
    box: list[float] = []
    for f in faces:  # loop over faces (their planes)
        s = f["surface"]
        p = s["type"] == "plane" and "source" not in s
        plane.append(p)
        if not p:
            frames += _ZERO_FRAME
            continue
        (x0, x1, x2), (y0, y1, y2) = s["x"], s["y"]  # S_u x S_v = X x Y, negated for a reversed face
        n = (x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0)  # (np.cross on 3 numbers costs more)
        frames += s["origin"]
        frames += (-n[0], -n[1], -n[2]) if f["reversed"] else n
    b = Bnd_Box()
    for face in occ_faces:  # loop over faces (bounding boxes, in one Bnd_Box emptied for each)
        b.SetVoid()
        BRepBndLib.Add_s(face, b)
        box += _VOID_BOX if b.IsVoid() else b.CornerMin().Coord() + b.CornerMax().Coord()
    frame = np.array(frames).reshape(nf, 2, 3)
    return _sewing().FaceUses(use[:, 0], use[:, 1], use[:, 2].astype(bool), nf, np.array(plane, dtype=bool),
                              frame[:, 0], frame[:, 1], np.array(box).reshape(nf, 2, 3))


#: :func:`_face_uses`' origin and normal of a face that is not a plane, and box of a face without one
_ZERO_FRAME = (0.0,) * 6
_VOID_BOX = (math.nan,) * 6


def _walk_joined(shape, size: float, times: dict, fallback: dict[int, str] | None = None,
                 check: bool = True) -> tuple[dict | None, dict]:
    """Walk an unsewn shape and sew it by :mod:`nagata_snap.cad.sewing` (no OpenCASCADE sewing).

    Returns:
        ``(data, healed)``: :func:`_walk`'s data and the ``healed`` info, or ``(None,
        {"join": why not})`` where the join is not clean (then OpenCASCADE sews).  Adds the
        time of the join to ``times["heal"]`` and of the walk to ``times["convert"]``.
    """
    from OCP.TopoDS import TopoDS

    sewing = _sewing()
    t0 = time.perf_counter()
    fmap, emap, vmap, _ = shape_maps(shape)
    points, vtol = _vertices(vmap)
    copies, edges, adaptors = _edge_copies(emap, vmap, points, vtol)
    joined, why = None, []
    for rtol in SEW_RTOL:  # the first tolerance at which the edges join cleanly
        j = sewing.join_edges(copies, rtol * size)
        if not isinstance(j, str):
            joined = j
            break
        why.append(f"{j} (tolerance {rtol:g} x size)")
    t1 = time.perf_counter()
    times["heal"] += t1 - t0
    if joined is None:
        return None, {"join": "; ".join(why)}
    occ_faces = [TopoDS.Face(fmap.FindKey(i)) for i in range(1, fmap.Extent() + 1)]
    degenerate = copies.degenerate.tolist()
    fb = fallback or {}
    placed = _Placed() if check else None
    faces = [_face(f, i, emap, size, degenerate, fb.get(i), check, placed, joined=True)
             for i, f in enumerate(occ_faces)]
    t2 = time.perf_counter()
    j = sewing.join_faces(joined, _face_uses(faces, occ_faces), ~copies.degenerate)
    t3 = time.perf_counter()
    times["heal"] += t3 - t2
    if isinstance(j, str):
        times["convert"] += t2 - t1
        return None, {"join": j}
    sewing.relabel(faces, j)
    out = []
    # (the joined edges' numbers as Python ints and floats by one call each, not one per edge)
    for src, (v0, v1), tol in zip(j.source.tolist(), j.ends.tolist(), j.edge_tolerance.tolist(), strict=True):
        out.append({  # loop over the joined edges (their 3D curves)
            "curve": None if degenerate[src] else _curve3d(edges[src], adaptors[src]),
            "vertices": (v0, v1),
            "tolerance": tol,
            "degenerate": degenerate[src],
            "source": src,
        })
    times["convert"] += t2 - t1 + time.perf_counter() - t3
    healed = {"sewn": True, "method": "join", "tolerance": j.tolerance, "free_edges": 0, "solids": j.num_solids}
    return {"num_solids": j.num_solids, "vertices": j.points, "vertex_tolerance": j.vertex_tolerance,
            "edges": out, "faces": faces}, healed


def read_shape(path: str | os.PathLike, unit: str = "MM", heal: bool = True,
               sew: bool | None = None, join: bool = True, fallback: dict[int, str] | None = None,
               check: bool = True) -> dict:
    """Read a STEP, IGES or BREP file into plain data (see the module docstring).

    Args:
        path: the file; the format is taken from its extension.
        unit: length unit of the coordinates returned (a key of :data:`UNITS`,
            as OpenCASCADE's ``xstep.cascade.unit``), to which STEP and IGES
            coordinates are converted; ``"FILE"`` keeps the file's own unit.
            BREP coordinates are always kept.
        heal: sew faces that share no edge (see ``sew``), make solids of the
            closed shells and, where OpenCASCADE sewed, fix the result
            (``ShapeFix_Shape``).
        sew: sew the faces into shells (``BRepBuilderAPI_Sewing``, at the
            smallest tolerance of :data:`SEW_RTOL` that leaves no free edge);
            default: when the shape has several faces and no shell (IGES files
            usually).
        join: sew by joining the walked data (:mod:`nagata_snap.cad.sewing`)
            where that gives OpenCASCADE's model (closed, consistently and
            outward oriented shells), else with OpenCASCADE; ``False``: always
            with OpenCASCADE.  ``healed["method"]`` says which (``"join"`` or
            ``"occ"``), ``healed["join"]`` why the join was not used.
        fallback: per face index ``"basis"``, ``"nurbs"`` or ``"approx"``: describe that face otherwise
            (see :func:`_face`; :mod:`nagata_snap.cad.verify` asks for it).
        check: add OpenCASCADE's samples of every face (``face["check"]``,
            :func:`_checks`); their time is ``times["check"]``, not part of ``convert``.

    Every edge has a ``source``: the index of the edge whose 3D curve it is in
    the shape walked: the file's unsewn shape (:func:`load_shape` with
    ``heal=False``) where the join sewed it, else the healed shape (its own
    index).

    Raises:
        ReadError: unknown extension, unreadable file, empty shape, a face
            that cannot be converted to NURBS, non-finite geometry.
    """
    path = os.fspath(path)
    shape, info = _load(path, unit)
    size, times = info["size"], info["times"]
    times["heal"] = times["convert"] = 0.0
    data: dict | None = None
    healed: dict = {"sewn": False}
    try:  # the edge and face errors name their entity; the file is named here
        if heal and _needs_sewing(shape, sew):
            healed = {}
            if join:
                try:
                    data, healed = _walk_joined(shape, size, times, fallback, check)
                except Exception as err:  # OpenCASCADE's sewing decides about odd shapes
                    healed = {"join": f"{type(err).__name__}: {err}"}
            if data is None:  # OpenCASCADE sews; healed["join"]: why the join did not
                t0 = time.perf_counter()
                shape, occ = _heal(shape, size, True)
                healed = {**occ, "method": "occ", **healed}
                times["heal"] += time.perf_counter() - t0
        elif heal:
            t0 = time.perf_counter()
            shape, healed = _heal(shape, size, False)
            times["heal"] = time.perf_counter() - t0
        if data is None:
            t0 = time.perf_counter()
            data = _walk(shape, size, fallback, check)
            times["convert"] = time.perf_counter() - t0
        times["check"] = sum(f["check"]["time"] for f in data["faces"]) if check else 0.0
        times["convert"] -= times["check"]
    except ReadError as err:
        raise ReadError(f"{path}: {err}") from None
    return {"path": path, "format": info["format"], "unit": info["unit"], "file_units": info["file_units"],
            "size": size, "healed": healed, "times": times, **data}
