"""OpenCASCADE's own answers for the CAD tests: distances to faces and edges of a shape.

The shape is read and healed as :func:`nagata_snap.cad.read.load_shape` does,
so its faces and edges are numbered as in the :class:`~nagata_snap.cad.CadGeometry`
of the same file; the distances come from OpenCASCADE alone, independent of
the package's surfaces, loops and projections: ``BRepExtrema_DistShapeShape``
between a vertex and the trimmed face (or edge), and, because that Extrema is
off by up to ~1e-6 within ~1e-8 of a periodic surface's seam in its parameter,
the surface's own projection ``GeomAPI_ProjectPointOnSurf`` when its foot point
is on the face (``BRepClass_FaceClassifier``: in or on); the nearer of the
two (both are points of the face).  For edges: ``GeomAPI_ProjectPointOnCurve``
within the edge's range likewise.
"""

from __future__ import annotations

import numpy as np

from nagata_snap.cad.read import load_shape, shape_maps


class OccShape:
    """Faces and edges of a CAD file as OpenCASCADE shapes."""

    def __init__(self, path: str, unit: str = "MM"):
        from OCP.TopoDS import TopoDS

        self.shape, info = load_shape(path, unit)
        self.size = info["size"]
        fm, em, vm, _ = shape_maps(self.shape)
        self.faces = [TopoDS.Face(fm.FindKey(i)) for i in range(1, fm.Extent() + 1)]
        self.edges = [TopoDS.Edge(em.FindKey(i)) for i in range(1, em.Extent() + 1)]

    @staticmethod
    def _distance(shapes, index, points) -> np.ndarray:
        from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeVertex
        from OCP.BRepExtrema import BRepExtrema_DistShapeShape
        from OCP.gp import gp_Pnt

        out = np.empty(len(points))
        for k, (i, p) in enumerate(zip(np.asarray(index), np.asarray(points, dtype=float))):
            v = BRepBuilderAPI_MakeVertex(gp_Pnt(*p)).Vertex()
            d = BRepExtrema_DistShapeShape(v, shapes[int(i)])
            out[k] = d.Value() if d.IsDone() else np.inf
        return out

    def face_distance(self, faces, points) -> np.ndarray:
        """``(n,)`` distance of each point to OCC's closest point on face ``faces[i]``."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepClass import BRepClass_FaceClassifier
        from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
        from OCP.TopAbs import TopAbs_State
        from OCP.gp import gp_Pnt, gp_Pnt2d

        d = self._distance(self.faces, faces, points)
        for k, (i, p) in enumerate(zip(np.asarray(faces), np.asarray(points, dtype=float))):
            f = self.faces[int(i)]
            pr = GeomAPI_ProjectPointOnSurf(gp_Pnt(*p), BRep_Tool.Surface_s(f))
            if pr.NbPoints() == 0 or not pr.LowerDistance() < d[k]:
                continue
            u, v = pr.LowerDistanceParameters()
            st = BRepClass_FaceClassifier(f, gp_Pnt2d(u, v), 1e-9).State()
            if st in (TopAbs_State.TopAbs_IN, TopAbs_State.TopAbs_ON):
                d[k] = pr.LowerDistance()
        return d

    def edge_distance(self, edges, points) -> np.ndarray:
        """``(n,)`` distance of each point to OCC's closest point on edge ``edges[i]``."""
        from OCP.BRep import BRep_Tool
        from OCP.BRepAdaptor import BRepAdaptor_Curve
        from OCP.GeomAPI import GeomAPI_ProjectPointOnCurve
        from OCP.gp import gp_Pnt

        d = self._distance(self.edges, edges, points)
        for k, (i, p) in enumerate(zip(np.asarray(edges), np.asarray(points, dtype=float))):
            e = self.edges[int(i)]
            if BRep_Tool.Degenerated_s(e):
                continue
            a = BRepAdaptor_Curve(e)
            t0, t1 = a.FirstParameter(), a.LastParameter()
            pr = GeomAPI_ProjectPointOnCurve(gp_Pnt(*p), BRep_Tool.Curve_s(e, t0, t1), t0, t1)
            if pr.NbPoints() and pr.LowerDistance() < d[k]:
                d[k] = pr.LowerDistance()
        return d
