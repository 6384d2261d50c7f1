"""OpenCASCADE's own answers for the CAD tests: distances to faces and edges of a shape.

The shape is read and healed as :func:`nagata_snap.cad.read.load_shape` does,
so its faces and edges are numbered as in the :class:`~nagata_snap.cad.CadGeometry`
of the same file; the distances come from ``BRepExtrema_DistShapeShape``
between a vertex and the trimmed face (or edge), independent of the
package's surfaces, loops and projections.
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
        return self._distance(self.faces, faces, points)

    def edge_distance(self, edges, points) -> np.ndarray:
        """``(n,)`` distance of each point to OCC's closest point on edge ``edges[i]``."""
        return self._distance(self.edges, edges, points)
