"""Single faces of the surface kinds other CAD systems write, built with OpenCASCADE (OCP).

Files written by other systems hold faces our own builder never makes:
``Geom_RectangularTrimmedSurface`` over cylinders, cones, spheres and tori
(with parameter ranges past the period's end), surfaces of revolution of
B-spline curves, offset surfaces, located (moved) faces.  :data:`CASES` builds
each as a ``TopoDS_Face`` (``BRepBuilderAPI_MakeFace`` on the trimmed surface)
or a solid, and :func:`write_case` writes it as STEP, IGES or BREP: the
reader's and the verification's test cases (tests/test_cad_verify.py), while
the public corpus lacks them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable

__all__ = ["CASES", "build", "write_case", "write_shape"]


def _ax3(origin=(0.0, 0.0, 0.0), z=(0.0, 0.0, 1.0), x=(1.0, 0.0, 0.0)):
    from OCP.gp import gp_Ax3, gp_Dir, gp_Pnt

    return gp_Ax3(gp_Pnt(*origin), gp_Dir(*z), gp_Dir(*x))


#: a tilted frame (the faces are not aligned with the axes)
_TILT = {"origin": (0.3, -0.2, 0.5), "z": (0.2, 0.3, 1.0), "x": (1.0, 0.0, -0.2)}


def _face(surface, tol: float = 1e-7):
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace

    mk = BRepBuilderAPI_MakeFace(surface, tol)
    if not mk.IsDone():
        raise RuntimeError("BRepBuilderAPI_MakeFace failed")
    return mk.Face()


def _trimmed(basis, u0: float, u1: float, v0: float, v1: float):
    from OCP.Geom import Geom_RectangularTrimmedSurface

    return _face(Geom_RectangularTrimmedSurface(basis, u0, u1, v0, v1))


def cylinder_rts():
    """A cylinder trimmed past its period's end: ``u`` in [4, 8] (radians)."""
    from OCP.Geom import Geom_CylindricalSurface

    return _trimmed(Geom_CylindricalSurface(_ax3(**_TILT), 0.7), 4.0, 8.0, -0.5, 1.2)


def cone_rts():
    """A cone trimmed across ``u = 0``: ``u`` in [-1, 1.5]."""
    from OCP.Geom import Geom_ConicalSurface

    return _trimmed(Geom_ConicalSurface(_ax3(**_TILT), 0.4, 0.6), -1.0, 1.5, -0.3, 0.9)


def sphere_rts():
    """A sphere trimmed across ``u = 0``."""
    from OCP.Geom import Geom_SphericalSurface

    return _trimmed(Geom_SphericalSurface(_ax3(**_TILT), 0.8), -1.0, 2.0, -0.6, 1.0)


def torus_rts():
    """A torus trimmed past the end of both periods: ``u`` in [5, 7], ``v`` in [-2, 1]."""
    from OCP.Geom import Geom_ToroidalSurface

    return _trimmed(Geom_ToroidalSurface(_ax3(**_TILT), 1.0, 0.3), 5.0, 7.0, -2.0, 1.0)


def _bspline_profile():
    """A B-spline curve in the ``xz`` plane (``x > 0``), for surfaces of revolution."""
    from OCP.Geom import Geom_BSplineCurve
    from OCP.gp import gp_Pnt
    from OCP.OCP.collections import Array1_double as TColStd_Array1OfReal
    from OCP.OCP.collections import Array1_gp_Pnt as TColgp_Array1OfPnt
    from OCP.OCP.collections import Array1_int as TColStd_Array1OfInteger

    pts = [(0.5, 0, -0.4), (0.8, 0, -0.1), (0.6, 0, 0.2), (0.9, 0, 0.5), (0.7, 0, 0.8)]
    poles = TColgp_Array1OfPnt(1, len(pts))
    for i, p in enumerate(pts):
        poles.SetValue(i + 1, gp_Pnt(*p))
    knots, mults = TColStd_Array1OfReal(1, 3), TColStd_Array1OfInteger(1, 3)
    for i, (k, m) in enumerate(((0.0, 4), (0.5, 1), (1.0, 4))):
        knots.SetValue(i + 1, k)
        mults.SetValue(i + 1, m)
    return Geom_BSplineCurve(poles, knots, mults, 3)


def revolution():
    """A surface of revolution of a B-spline curve about a tilted axis, ``u`` in [0.5, 4]."""
    from OCP.Geom import Geom_SurfaceOfRevolution
    from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt

    s = Geom_SurfaceOfRevolution(_bspline_profile(), gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(0, 0, 1)))
    return _trimmed(s, 0.5, 4.0, 0.1, 0.9)


def revolution_full():
    """A full surface of revolution of a B-spline curve (a seam)."""
    from OCP.Geom import Geom_SurfaceOfRevolution
    from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt

    s = Geom_SurfaceOfRevolution(_bspline_profile(), gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(0, 0, 1)))
    return _face(s)


def revolution_line():
    """A surface of revolution of a line (a cone, as IGES files write one)."""
    from OCP.GC import GC_MakeSegment
    from OCP.Geom import Geom_SurfaceOfRevolution
    from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt

    seg = GC_MakeSegment(gp_Pnt(0.4, 0, 0), gp_Pnt(0.8, 0, 1.0)).Value()
    s = Geom_SurfaceOfRevolution(seg, gp_Ax1(gp_Pnt(0.1, 0.2, 0), gp_Dir(0, 0, 1)))
    return _trimmed(s, 1.0, 5.0, 0.0, seg.LastParameter())


def offset_bspline():
    """An offset (by 0.1) of a bumpy B-spline surface."""
    from OCP.Geom import Geom_BSplineSurface, Geom_OffsetSurface
    from OCP.gp import gp_Pnt
    from OCP.OCP.collections import Array1_double as TColStd_Array1OfReal
    from OCP.OCP.collections import Array1_int as TColStd_Array1OfInteger
    from OCP.OCP.collections import Array2_gp_Pnt as TColgp_Array2OfPnt

    poles = TColgp_Array2OfPnt(1, 4, 1, 4)
    for i in range(4):
        for j in range(4):
            poles.SetValue(i + 1, j + 1, gp_Pnt(i / 3, j / 3, 0.15 * math.sin(2.0 * i + j)))
    knots, mults = TColStd_Array1OfReal(1, 2), TColStd_Array1OfInteger(1, 2)
    for i, (k, m) in enumerate(((0.0, 4), (1.0, 4))):
        knots.SetValue(i + 1, k)
        mults.SetValue(i + 1, m)
    b = Geom_BSplineSurface(poles, knots, knots, mults, mults, 3, 3)
    return _face(Geom_OffsetSurface(b, 0.1))


def offset_cylinder():
    """An offset (by 0.2) of a trimmed cylinder: OpenCASCADE knows its equivalent cylinder."""
    from OCP.Geom import Geom_CylindricalSurface, Geom_OffsetSurface, Geom_RectangularTrimmedSurface

    c = Geom_RectangularTrimmedSurface(Geom_CylindricalSurface(_ax3(**_TILT), 0.5), 1.0, 3.0, 0.0, 1.0)
    return _face(Geom_OffsetSurface(c, 0.2))


def located_torus_solid():
    """A solid torus moved by a location (the face keeps a ``TopLoc_Location``)."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeTorus
    from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt, gp_Trsf, gp_Vec
    from OCP.TopLoc import TopLoc_Location

    s = BRepPrimAPI_MakeTorus(1.0, 0.25, 4.5).Shape()  # an open ring sector (4.5 rad)
    t = gp_Trsf()
    t.SetRotation(gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(1, 1, 0)), 0.7)
    t2 = gp_Trsf()
    t2.SetTranslation(gp_Vec(0.5, -0.3, 0.2))
    return s.Moved(TopLoc_Location(t2.Multiplied(t)))


def holed_plane():
    """A plane face with a round hole and a square hole (loops on a plane)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakePolygon, BRepBuilderAPI_MakeWire
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge
    from OCP.gp import gp_Ax2, gp_Circ, gp_Dir, gp_Pnt

    outer = BRepBuilderAPI_MakePolygon(gp_Pnt(0, 0, 0), gp_Pnt(2, 0, 0), gp_Pnt(2, 1, 0), gp_Pnt(0, 1, 0), True).Wire()
    mk = BRepBuilderAPI_MakeFace(outer, True)
    circ = BRepBuilderAPI_MakeEdge(gp_Circ(gp_Ax2(gp_Pnt(0.5, 0.5, 0), gp_Dir(0, 0, -1)), 0.2)).Edge()
    mk.Add(BRepBuilderAPI_MakeWire(circ).Wire())
    sq = BRepBuilderAPI_MakePolygon(gp_Pnt(1.2, 0.3, 0), gp_Pnt(1.2, 0.7, 0), gp_Pnt(1.6, 0.7, 0),
                                    gp_Pnt(1.6, 0.3, 0), True).Wire()
    mk.Add(sq)
    from OCP.gp import gp_Ax1, gp_Trsf
    from OCP.TopLoc import TopLoc_Location

    t = gp_Trsf()  # tilted: not a planar 2D profile
    t.SetRotation(gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(1, 0.5, 0)), 0.4)
    return mk.Face().Moved(TopLoc_Location(t))


#: name -> builder of a shape
CASES: dict[str, Callable] = {
    "cylinder_rts": cylinder_rts, "cone_rts": cone_rts, "sphere_rts": sphere_rts, "torus_rts": torus_rts,
    "revolution": revolution, "revolution_full": revolution_full, "revolution_line": revolution_line,
    "offset_bspline": offset_bspline, "offset_cylinder": offset_cylinder,
    "located_torus_solid": located_torus_solid, "holed_plane": holed_plane,
}


def build(name: str):
    """The shape of case ``name``."""
    return CASES[name]()


def write_shape(shape, path: str | os.PathLike) -> str:
    """Write ``shape`` as STEP (``.step``), IGES (``.igs``, B-rep mode) or BREP (``.brep``)."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".brep":
        from OCP.BRepTools import BRepTools

        BRepTools.Write_s(shape, path)
    elif ext in (".step", ".stp"):
        from OCP.IFSelect import IFSelect_ReturnStatus
        from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer

        w = STEPControl_Writer()
        w.Transfer(shape, STEPControl_AsIs)
        if w.Write(path) != IFSelect_ReturnStatus.IFSelect_RetDone:
            raise RuntimeError(f"cannot write {path}")
    elif ext in (".igs", ".iges"):
        from OCP.IGESControl import IGESControl_Writer

        w = IGESControl_Writer("MM", 1)  # B-rep mode (faces with their edges)
        w.AddShape(shape)
        w.ComputeModel()
        if not w.Write(path):
            raise RuntimeError(f"cannot write {path}")
    else:
        raise ValueError(f"unknown extension of {path}")
    return path


def write_case(name: str, path: str | os.PathLike) -> str:
    """Write case ``name`` to ``path`` (its format from the extension)."""
    return write_shape(build(name), path)
