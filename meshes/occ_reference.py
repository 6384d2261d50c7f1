"""OpenCASCADE's own closest points and normals: the reference for the CAD tests and benchmarks.

Everything here comes from OpenCASCADE alone (through OCP or through gmsh),
independent of the package's surfaces, loops and projections.  Two entry
points, by how the faces are numbered:

* :class:`OccShape`, numbered as the package's
  :class:`~nagata_snap.cad.CadGeometry` of the same file;
* gmsh's current model (a file imported by gmsh, e.g. for a
  :class:`nagata_snap.meshing.CadMesh`), numbered by gmsh's face tags:
  :func:`gmsh_face_distance` (``gmsh.model.getClosestPoint``),
  :func:`gmsh_curved_faces`, :class:`GmshFaceNormals` (``gmsh.model.getNormal``).

:class:`OccShape` takes the shape the package's reader walks: OpenCASCADE's
healed shape (:func:`nagata_snap.cad.read.load_shape`), or, where the reader
sewed a faces-only file by joining its data (:mod:`nagata_snap.cad.sewing`),
the unsewn shape as read, whose faces are the model's in the same order and
whose edge copies give each model edge the one whose 3D curve it keeps (the
model edge's ``source``): the numbering comes from the reader, the geometry
stays OpenCASCADE's own.  Its closest point on the whole shape
(:meth:`OccShape.closest_split`) is ``BRepExtrema_DistShapeShape``'s on the
faces and, where the faces have C0 lines inside (creases of B-spline faces at
their knots, next to which ``BRepExtrema`` misses closest points), on the faces
split there by ``ShapeUpgrade_ShapeDivideContinuity``, the nearer of the two;
a face whose edge curves lie off it (a file's loose tolerance,
:attr:`OccShape.loose`) is measured as its surface within its p-curves: its
surface's extrema inside it and the curves its p-curves trace on the surface.
Its distances to one face are
``BRepExtrema_DistShapeShape`` between a vertex and the trimmed face (or
edge), and, because that Extrema is off by up to ~1e-6 within ~1e-8 of a
periodic surface's seam in its parameter, the surface's own projection
``GeomAPI_ProjectPointOnSurf`` when its foot point is on the face
(``BRepClass_FaceClassifier``: in or on); the nearer of the two (both are
points of the face).  For edges: ``GeomAPI_ProjectPointOnCurve`` within the
edge's range likewise.
"""

from __future__ import annotations

import functools

import numpy as np

from nagata_snap.cad.read import load_shape, read_shape, shape_maps


#: samples per edge at which :attr:`OccShape.loose` compares an edge's 3D curve with its curve on the face
GAP_SAMPLES = 17


def _distance(vertex, shape):
    """``BRepExtrema_DistShapeShape`` of a vertex and a shape, None where it finds nothing."""
    from OCP.BRepExtrema import BRepExtrema_DistShapeShape

    ds = BRepExtrema_DistShapeShape(vertex, shape)
    return ds if ds.IsDone() and ds.NbSolution() > 0 else None


class OccShape:
    """Faces and edges of a CAD file as OpenCASCADE shapes, numbered as the package's model."""

    def __init__(self, path: str, unit: str = "MM"):
        from OCP.TopoDS import TopoDS

        data = read_shape(path, unit)
        self.joined = data["healed"].get("method") == "join"
        self.shape, info = load_shape(path, unit, heal=not self.joined)
        self.size = info["size"]
        fm, em, _, _ = shape_maps(self.shape)
        self._fmap = fm
        self.faces = [TopoDS.Face(fm.FindKey(i)) for i in range(1, fm.Extent() + 1)]
        edges = [TopoDS.Edge(em.FindKey(i)) for i in range(1, em.Extent() + 1)]
        self.edges = [edges[e["source"]] for e in data["edges"]]
        if len(self.faces) != len(data["faces"]):
            raise RuntimeError(f"{path}: {len(self.faces)} OpenCASCADE faces, {len(data['faces'])} in the model")

    @staticmethod
    def _extrema(shape, p) -> float:
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.BRepExtrema import BRepExtrema_DistShapeShape
        from OCP.gp import gp_Pnt

        d = BRepExtrema_DistShapeShape(BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex(), shape)
        return d.Value() if d.IsDone() else np.inf

    def face_distance(self, faces, points, accept: float = 0.0, params=None) -> np.ndarray:
        """``(n,)`` distance of each point to OCC's closest point on face ``faces[i]``.

        Cheap upper bounds come first and answer where they are within
        ``accept``: with ``params`` ``(n, 2)`` (the file's parameters of the
        points, e.g. a snapper's), OCC's own surface point there if it is on
        the face (``Value`` and the face classifier); then the surface
        projection (``GeomAPI_ProjectPointOnSurf``) if its foot is on the face;
        else ``BRepExtrema``.
        """
        from OCP.BRep import BRep_Tool
        from OCP.BRepAdaptor import BRepAdaptor_Surface
        from OCP.BRepClass import BRepClass_FaceClassifier
        from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
        from OCP.TopAbs import TopAbs_State
        from OCP.gp import gp_Pnt, gp_Pnt2d

        faces, points = np.asarray(faces), np.asarray(points, dtype=float)
        d = np.full(len(points), np.inf)
        on = (TopAbs_State.TopAbs_IN, TopAbs_State.TopAbs_ON)
        if params is not None:
            adaptors = {}
            for k, (i, p, uv) in enumerate(zip(faces, points, np.asarray(params, dtype=float), strict=True)):
                f = self.faces[int(i)]
                a = adaptors.setdefault(int(i), BRepAdaptor_Surface(f))
                uv = uv.copy()
                for j, (periodic, period, lo) in enumerate(
                        ((a.IsUPeriodic(), a.UPeriod, a.FirstUParameter()),
                         (a.IsVPeriodic(), a.VPeriod, a.FirstVParameter()))):
                    if periodic:  # into the face's own period
                        uv[j] = lo + np.mod(uv[j] - lo, period())
                if np.all(np.isfinite(uv)) and \
                        BRepClass_FaceClassifier(f, gp_Pnt2d(*uv), 1e-9).State() in on:
                    q = a.Value(*uv)
                    d[k] = np.linalg.norm(np.array([q.X(), q.Y(), q.Z()]) - p)
        for k, (i, p) in enumerate(zip(faces, points, strict=True)):
            if d[k] <= accept:
                continue
            f = self.faces[int(i)]
            pr = GeomAPI_ProjectPointOnSurf(gp_Pnt(*p), BRep_Tool.Surface_s(f))
            if pr.NbPoints():
                u, v = pr.LowerDistanceParameters()
                if BRepClass_FaceClassifier(f, gp_Pnt2d(u, v), 1e-9).State() in on:
                    d[k] = min(d[k], pr.LowerDistance())
            if not d[k] <= accept:
                d[k] = min(d[k], self._extrema(f, p))
        return d

    @functools.cached_property
    def compound(self):
        """The faces whose edges lie on them (not in :attr:`loose`) as one compound (not the
        solid: a point inside a solid is at 0 from it); None if there is none."""
        from OCP.BRep import BRep_Builder
        from OCP.TopoDS import TopoDS_Compound

        tight = [f for i, f in enumerate(self.faces) if i not in self.loose]
        if not tight:
            return None
        comp, b = TopoDS_Compound(), BRep_Builder()
        b.MakeCompound(comp)
        for f in tight:
            b.Add(comp, f)
        return comp

    @functools.cached_property
    def loose(self) -> dict[int, list]:
        """The faces with an edge whose 3D curve is farther than 1e-9 of the size from the curve
        its p-curve traces on the face (``BRepAdaptor_Curve(edge)`` against
        ``BRepAdaptor_Curve(edge, face)`` at :data:`GAP_SAMPLES` parameters): per such face
        (its index) the curves on it of its non-degenerate edges (``BRepAdaptor_Curve(edge, face)``).

        Such a file meets only within its tolerances: ``BRepExtrema`` measures a point's
        distance to the 3D curve, which no point of the face reaches.  The face is the surface
        within its p-curves; :meth:`closest_split` measures to that."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepAdaptor import BRepAdaptor_Curve
        from OCP.TopAbs import TopAbs_EDGE
        from OCP.TopExp import TopExp_Explorer
        from OCP.TopoDS import TopoDS

        out: dict[int, list] = {}
        t = np.linspace(0.0, 1.0, GAP_SAMPLES)
        for i, f in enumerate(self.faces):  # loop over faces and their edges (set-up)
            curves, gap = [], 0.0
            ex = TopExp_Explorer(f, TopAbs_EDGE)
            while ex.More():
                e = TopoDS.Edge(ex.Current())
                ex.Next()
                if BRep_Tool.Degenerated_s(e) or not BRep_Tool.IsGeometric_s(e):
                    continue
                c3, cs = BRepAdaptor_Curve(e), BRepAdaptor_Curve(e, f)
                a, b = c3.FirstParameter(), c3.LastParameter()
                for x in a + t * (b - a):  # the same parameters: the edge's range
                    gap = max(gap, c3.Value(x).Distance(cs.Value(x)))
                curves.append(cs)
            if gap > 1e-9 * self.size:
                out[i] = curves
        return out

    @functools.cached_property
    def _loose_boxes(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Per loose face (:attr:`loose`) its bounding box ``(lo (3,), hi (3,))``
        (``BRepBndLib``, widened by the shape's tolerances)."""
        from OCP.Bnd import Bnd_Box
        from OCP.BRepBndLib import BRepBndLib

        out = {}
        for i in self.loose:  # loop over the loose faces (set-up)
            box = Bnd_Box()
            BRepBndLib.Add_s(self.faces[i], box)
            lo, hi = box.CornerMin(), box.CornerMax()
            out[i] = (np.array(lo.Coord()), np.array(hi.Coord()))
        return out

    def surface_face_distance(self, i: int, p) -> float:
        """Distance of ``p (3,)`` from loose face ``i`` (:attr:`loose`) as its surface within its
        p-curves: the nearer of its surface's extrema inside the face
        (``GeomAPI_ProjectPointOnSurf``, ``BRepClass_FaceClassifier``), ``BRepExtrema``'s point
        where it lies inside the face, and the closest points of the curves its edges'
        p-curves trace on it (``Extrema_ExtPC`` and the curves' ends)."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.BRepClass import BRepClass_FaceClassifier
        from OCP.Extrema import Extrema_ExtPC
        from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
        from OCP.TopAbs import TopAbs_FACE, TopAbs_State
        from OCP.gp import gp_Pnt, gp_Pnt2d

        f, q = self.faces[i], gp_Pnt(*p)
        best = np.inf
        pr = GeomAPI_ProjectPointOnSurf(q, BRep_Tool.Surface_s(f))
        for j in range(1, pr.NbPoints() + 1):  # loop over the surface's extrema
            u, v = pr.Parameters(j)
            if BRepClass_FaceClassifier(f, gp_Pnt2d(u, v), 1e-9).State() == TopAbs_State.TopAbs_IN:
                best = min(best, pr.Distance(j))
        ds = _distance(BRepBuilderAPI_MakeVertex(q).Vertex(), f)
        if ds is not None and ds.SupportOnShape2(1).ShapeType() == TopAbs_FACE:
            best = min(best, ds.Value())
        for c in self.loose[i]:  # loop over the face's edges
            a, b = c.FirstParameter(), c.LastParameter()
            best = min(best, q.Distance(c.Value(a)), q.Distance(c.Value(b)))
            ext = Extrema_ExtPC(q, c, a, b)
            if ext.IsDone():
                for j in range(1, ext.NbExt() + 1):
                    best = min(best, float(np.sqrt(ext.SquareDistance(j))))
        return best

    @functools.cached_property
    def split(self):
        """The faces split at the lines where their surfaces (or p-curves) are only C0
        (``ShapeUpgrade_ShapeDivideContinuity`` to C1), as a compound; None where that splits
        nothing.  ``BRepExtrema`` misses closest points next to such a line (a crease inside a
        B-spline face); on the split faces, each side is a face of its own."""
        from OCP.GeomAbs import GeomAbs_Shape
        from OCP.ShapeUpgrade import ShapeUpgrade_ShapeDivideContinuity
        from OCP.TopAbs import TopAbs_FACE
        from OCP.TopExp import TopExp_Explorer

        if self.compound is None:
            return None
        div = ShapeUpgrade_ShapeDivideContinuity(self.compound)
        c1 = GeomAbs_Shape.GeomAbs_C1
        div.SetBoundaryCriterion(c1)
        div.SetPCurveCriterion(c1)
        div.SetSurfaceCriterion(c1)
        div.SetTolerance(1e-9 * self.size)
        if not div.Perform():
            return None
        out, n = div.Result(), 0
        ex = TopExp_Explorer(out, TopAbs_FACE)
        while ex.More():
            n += 1
            ex.Next()
        return out if n > len(self.faces) - len(self.loose) else None

    def closest(self, points) -> tuple[np.ndarray, np.ndarray]:
        """OpenCASCADE's closest point of each point on the whole shape (its trimmed faces):
        ``(distance (n,), face (n,))``, as :meth:`closest_split` (without its third array)."""
        d, face, _ = self.closest_split(points)
        return d, face

    def closest_split(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """OpenCASCADE's closest point of each point on the whole shape (its trimmed faces):
        ``(distance (n,), face (n,), split (n,) bool)``.

        ``BRepExtrema_DistShapeShape`` against the shape's faces, the distance refined on the
        face found (:meth:`face_distance`, against Extrema's error near seams); ``face`` the
        index (as the model's) of the face the closest point lies on, ``-1`` where it lies on
        an edge or a vertex (on two faces or more).  A face whose edges are off it
        (:attr:`loose`) is measured as its surface within its p-curves
        (:meth:`surface_face_distance`), not through ``BRepExtrema``'s 3D edge curves.  Where
        the faces have C0 lines
        (:attr:`split`), ``BRepExtrema`` against the split faces as well, and the nearer of
        the two; ``split`` marks the points where that was the split faces' by more than
        1e-9 of the size (``face`` -1 there: the split faces are not the model's)."""
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.gp import gp_Pnt
        from OCP.TopAbs import TopAbs_FACE

        points = np.asarray(points, dtype=float).reshape(-1, 3)
        d = np.full(len(points), np.inf)
        face = np.full(len(points), -1, dtype=np.int64)
        lower = np.zeros(len(points), dtype=bool)
        split = self.split
        for k, p in enumerate(points):  # loop over points (OCC queries)
            v = BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex()
            ds = _distance(v, self.compound) if self.compound is not None else None
            if ds is not None:
                d[k] = ds.Value()
                faces = set()
                for j in range(1, ds.NbSolution() + 1):
                    s = ds.SupportOnShape2(j)
                    faces.add(self._fmap.FindIndex(s) - 1 if s.ShapeType() == TopAbs_FACE else -1)
                if len(faces) == 1 and -1 not in faces:
                    face[k] = faces.pop()
                    d[k] = min(d[k], self.face_distance([face[k]], [p])[0])
            for i, (lo, hi) in self._loose_boxes.items():  # the faces whose edges are off them
                if np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0)) > d[k]:
                    continue  # (its box is farther than the nearest point found)
                di = self.surface_face_distance(i, p)
                if di < d[k] - 1e-9 * self.size:
                    d[k], face[k] = di, i
            ds = _distance(v, split) if split is not None else None
            if ds is not None and ds.Value() < d[k] - 1e-9 * self.size:
                d[k], face[k], lower[k] = ds.Value(), -1, True
        return d, face, lower

    def edge_distance(self, edges, points, accept: float = 0.0) -> np.ndarray:
        """``(n,)`` distance of each point to OCC's closest point on edge ``edges[i]``
        (the curve's projection within the edge's range first, as for faces)."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepAdaptor import BRepAdaptor_Curve
        from OCP.GeomAPI import GeomAPI_ProjectPointOnCurve
        from OCP.gp import gp_Pnt

        edges, points = np.asarray(edges), np.asarray(points, dtype=float)
        d = np.full(len(points), np.inf)
        for k, (i, p) in enumerate(zip(edges, points, strict=True)):
            e = self.edges[int(i)]
            if not BRep_Tool.Degenerated_s(e):
                a = BRepAdaptor_Curve(e)
                t0, t1 = a.FirstParameter(), a.LastParameter()
                pr = GeomAPI_ProjectPointOnCurve(gp_Pnt(*p), BRep_Tool.Curve_s(e, t0, t1), t0, t1)
                if pr.NbPoints():
                    d[k] = pr.LowerDistance()
            if not d[k] <= accept:
                d[k] = min(d[k], self._extrema(e, p))
        return d

    def tolerance_gaps(self, faces, points, rtol: float = 1e-9) -> np.ndarray:
        """``(n,)`` OpenCASCADE's answer to :func:`nagata_snap.cad.tolerance.tolerance_gaps`: the
        largest ``BRep_Tool::Tolerance`` of an edge or vertex of face ``faces[i]`` whose
        tolerance tube (``BRepExtrema`` distance within the tolerance, at least ``rtol`` of the
        size) holds ``points[i]``, else ``rtol`` of the size."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.BRepExtrema import BRepExtrema_DistShapeShape
        from OCP.TopAbs import TopAbs_EDGE, TopAbs_VERTEX
        from OCP.TopExp import TopExp_Explorer
        from OCP.TopoDS import TopoDS
        from OCP.gp import gp_Pnt

        floor = rtol * self.size
        out = np.full(len(points), floor)
        for k, (f, p) in enumerate(zip(faces, np.asarray(points, dtype=float), strict=True)):
            v = BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex()
            for kind, cast in ((TopAbs_EDGE, TopoDS.Edge), (TopAbs_VERTEX, TopoDS.Vertex)):
                ex = TopExp_Explorer(self.faces[int(f)], kind)
                while ex.More():
                    sub = cast(ex.Current())
                    tol = BRep_Tool.Tolerance_s(sub)
                    if kind == TopAbs_EDGE and BRep_Tool.Degenerated_s(sub):
                        ex.Next()
                        continue
                    ext = BRepExtrema_DistShapeShape(v, sub)
                    if ext.IsDone() and ext.Value() <= max(tol, floor):  # in its tolerance tube
                        out[k] = max(out[k], tol)
                    ex.Next()
        return out

    def meeting_gaps(self, faces, points, rtol: float = 1e-9, rcond: float = 2e-2) -> np.ndarray:
        """``(n,)`` OpenCASCADE's answer to :func:`nagata_snap.cad.tolerance.meeting_gaps`: the
        largest ``t / sin(theta / 2)`` of an edge of face ``faces[i]`` shared by two faces whose
        surfaces hold ``points[i]`` (``GeomAPI_ProjectPointOnSurf`` within ``rtol`` of the size),
        ``t`` its ``BRep_Tool::Tolerance``, ``theta`` the angle of the two surfaces' normals there
        (``GeomLProp_SLProps``; ``tan(theta / 2) >= rcond``), where the point is that close to
        the edge (``BRepExtrema``); else ``rtol`` of the size."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.BRepExtrema import BRepExtrema_DistShapeShape
        from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
        from OCP.GeomLProp import GeomLProp_SLProps
        from OCP.TopAbs import TopAbs_EDGE
        from OCP.TopExp import TopExp_Explorer
        from OCP.TopoDS import TopoDS
        from OCP.gp import gp_Pnt

        floor = rtol * self.size
        _, emap, _, _ = shape_maps(self.shape)
        owners: list[set[int]] = [set() for _ in range(emap.Extent())]  # the faces of each edge
        for g, face in enumerate(self.faces):
            ex = TopExp_Explorer(face, TopAbs_EDGE)
            while ex.More():
                owners[emap.FindIndex(ex.Current()) - 1].add(g)
                ex.Next()

        def on_surface(face, p):
            surf = BRep_Tool.Surface_s(face)
            pr = GeomAPI_ProjectPointOnSurf(gp_Pnt(*p), surf)
            if not pr.NbPoints() or pr.LowerDistance() > floor:
                return None
            props = GeomLProp_SLProps(surf, *pr.LowerDistanceParameters(), 1, 1e-12)
            if not props.IsNormalDefined():
                return None
            n = props.Normal()
            return np.array([n.X(), n.Y(), n.Z()])

        out = np.full(len(points), floor)
        for k, (f, p) in enumerate(zip(faces, np.asarray(points, dtype=float), strict=True)):
            ex = TopExp_Explorer(self.faces[int(f)], TopAbs_EDGE)
            while ex.More():  # loop over the face's edges
                e = TopoDS.Edge(ex.Current())
                ex.Next()
                two = owners[emap.FindIndex(e) - 1]
                if BRep_Tool.Degenerated_s(e) or len(two) != 2:
                    continue
                normals = [on_surface(self.faces[g], p) for g in sorted(two)]
                if any(n is None for n in normals):
                    continue
                c = min(1.0, abs(float(normals[0] @ normals[1])))
                if np.sqrt((1.0 - c) / (1.0 + c)) < rcond:
                    continue
                r = BRep_Tool.Tolerance_s(e) / np.sqrt((1.0 - c) / 2.0)
                ext = BRepExtrema_DistShapeShape(BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex(), e)
                if ext.IsDone() and ext.Value() <= r:
                    out[k] = max(out[k], r)
        return out


def gmsh_face_distance(face: int, points: np.ndarray, jump: float | None = None) -> np.ndarray:
    """``(k,)`` distance of ``points (k, 3)`` from gmsh face ``face`` (OpenCASCADE closest point).

    A point a hair beyond the face's edge, where a twin face continues its
    surface (the two half cylinders of a hole), can get a closest point on the
    face's far edge, a whole diameter away.  With ``jump``, points farther than
    ``jump`` from the face are measured against the faces sharing an edge with
    it too (the nearest counts).
    """
    import gmsh

    points = np.asarray(points, dtype=float)
    p = np.asarray(gmsh.model.getClosestPoint(2, face, points.ravel())[0])
    d = np.linalg.norm(p.reshape(-1, 3) - points, axis=1)
    far = np.flatnonzero(d > jump) if jump is not None else []
    if len(far):
        edges = gmsh.model.getAdjacencies(2, face)[1]
        near = {int(f) for e in edges for f in gmsh.model.getAdjacencies(1, int(e))[0]} - {face}
        for f in sorted(near):
            d[far] = np.minimum(d[far], gmsh_face_distance(f, points[far]))
    return d


def gmsh_curved_faces() -> list[int]:
    """Tags of the current gmsh model's faces that are not planes."""
    import gmsh

    return [t for _, t in gmsh.model.getEntities(2) if gmsh.model.getType(2, t) != "Plane"]


class GmshFaceNormals:
    """The CAD's normals through gmsh, with the ``attach``/``vertex_normals`` of ``CadGeometry``.

    Built from a :class:`nagata_snap.meshing.CadMesh`: every boundary facet's
    gmsh face and its vertices' (u, v) on it; ``vertex_normals`` evaluates
    ``gmsh.model.getNormal`` on the model imported from the same file
    (current while it is used).
    """

    def __init__(self, cm):
        gid = np.asarray(cm.mesh.geometry.input_global_indices, dtype=np.int64)[cm.facets.nodes]
        order = np.argsort(gid, axis=1)
        self.keys = np.take_along_axis(gid, order, axis=1)
        self.params = np.take_along_axis(cm.node_params, order[:, :, None], axis=1)
        self.entity = np.asarray(cm.facet_entity)
        self.lookup = {tuple(k): i for i, k in enumerate(self.keys)}  # coarse facets, built once

    def attach(self, facet_points, nodes=None):
        nodes = np.asarray(nodes, dtype=np.int64)
        order = np.argsort(nodes, axis=1)
        row = np.array([self.lookup[tuple(k)] for k in np.take_along_axis(nodes, order, axis=1)])
        inv = np.argsort(order, axis=1)
        from nagata_snap import Records

        return Records(self.entity[row].astype(np.int64),
                       np.take_along_axis(self.params[row], inv[:, :, None], axis=1))

    def vertex_normals(self, records):
        import gmsh

        out = np.zeros((*records.params.shape[:2], 3))
        for face in np.unique(records.root):  # loop over CAD faces (a few dozen)
            sel = records.root == face
            n = gmsh.model.getNormal(int(face), records.params[sel].ravel())
            out[sel] = np.reshape(n, (-1, records.params.shape[1], 3))
        return out


def pushed_points(path: str, n: int = 400, rel: float = 1e-3, seed: int = 0, size: float | None = None
                  ) -> np.ndarray:
    """``(m, 3)`` points ``rel`` of the model size off the surface nodes of a gmsh mesh of ``path``
    (``m <= n`` chosen at random), along gmsh's (OpenCASCADE's) normal of the node's face, to either
    side at random: the closest-point benchmark's and tests' query points.  ``size``: the model
    size (default: gmsh's bounding box diagonal)."""
    import gmsh

    rng = np.random.default_rng(seed)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(path)
        lo = np.array(gmsh.model.getBoundingBox(-1, -1))
        diag = float(np.linalg.norm(lo[3:] - lo[:3])) if size is None else size
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.05 * diag)
        gmsh.model.mesh.generate(2)
        X, N = [], []
        for _, tag in gmsh.model.getEntities(2):  # loop over gmsh faces
            _, xyz, uv = gmsh.model.mesh.getNodes(2, tag, includeBoundary=False, returnParametricCoord=True)
            if len(xyz) == 0:
                continue
            X.append(np.reshape(xyz, (-1, 3)))
            N.append(np.reshape(gmsh.model.getNormal(tag, uv), (-1, 3)))
    finally:
        gmsh.finalize()
    X, N = np.concatenate(X), np.concatenate(N)
    pick = rng.permutation(len(X))[:n]
    side = rng.choice([-1.0, 1.0], size=len(pick))
    return X[pick] + (rel * diag * side)[:, None] * N[pick]


def closest_agreement(geo, occ: OccShape, points: np.ndarray, rtol: float = 1e-6) -> dict:
    """How far the package's global ``closest_point`` agrees with OpenCASCADE's on ``points``.

    OpenCASCADE's closest point is :meth:`OccShape.closest_split` (``BRepExtrema`` on the
    faces, and on the faces split at their C0 lines where that is nearer).  A point
    *agrees* where our distance is within ``rtol`` of the model size of OpenCASCADE's and
    our foot point lies on the face we name (its OpenCASCADE distance from that trimmed
    face, :meth:`OccShape.face_distance`, at most 1e-9 of the size; a closest point on
    another face at the same distance agrees: equidistant faces).  It is *wrong* where we
    report a point of a face at a distance OpenCASCADE's point beats by more than that, or a
    foot that is not on the face we name (the silent error).  *nearer*: found, on the face
    (by OpenCASCADE's own evaluation and classifier), and nearer than OpenCASCADE's closest
    point by more than the tolerance: OpenCASCADE's point is then demonstrably not the
    closest one (it counts neither as agreeing nor as wrong).

    Returns:
        ``{"n", "found", "agree", "wrong", "nearer", "split" (points whose reference is the
        split faces'), "worst" (largest |difference| / size), "bad" (indices of the points
        that do not agree)}``, counts as ints.
    """
    size = occ.size
    ent, par, dist = geo.closest_point(points)
    found = ent >= 0
    foot = np.full((len(points), 3), np.nan)
    if found.any():
        foot[found] = geo.evaluate(ent[found], par[found][:, None, :])[:, 0]
    on_face = np.zeros(len(points), dtype=bool)
    on_face[found] = occ.face_distance(ent[found], foot[found], accept=1e-9 * size,
                                       params=par[found]) <= 1e-9 * size
    d_occ, _, split = occ.closest_split(points)
    tol = rtol * size
    diff = np.abs(dist - d_occ)
    agree = found & (diff <= tol) & on_face
    wrong = found & ((dist > d_occ + tol) | ~on_face)
    nearer = found & on_face & (dist < d_occ - tol)
    fin = np.isfinite(diff)
    return {"n": len(points), "found": int(found.sum()), "agree": int(agree.sum()), "wrong": int(wrong.sum()),
            "nearer": int(nearer.sum()), "split": int(split.sum()),
            "worst": float(diff[fin].max() / size) if fin.any() else float("inf"),
            "bad": np.flatnonzero(~agree)}
