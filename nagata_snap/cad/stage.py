"""What the stages of :class:`~nagata_snap.cad.geometry.CadGeometry` share of it.

The geometry's work is split over modules of its own: :mod:`~nagata_snap.cad.attach`
(coarse facets onto their faces), :mod:`~nagata_snap.cad.place` (snapping after a
refinement) and :mod:`~nagata_snap.cad.features` (CAD edges and corners).  Each is a set
of functions of the geometry; they read it through :class:`StageGeometry`, the
members they use, so that they need not import the class that imports them.
:class:`CadTopology` (the model's edges and vertices as arrays) is one of those
members, built with the geometry.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

from nagata_snap.cad.projection import GlobalSearcher, entity_periods
from nagata_snap.mesh.arrays import Ragged

if TYPE_CHECKING:
    from nagata_snap.cad.topology import CadModel
    from nagata_snap.cad.trimming import TrimLoops

__all__ = ["StageGeometry", "CadTopology"]


class StageGeometry(Protocol):
    """The members of :class:`~nagata_snap.cad.geometry.CadGeometry` its stages read
    (see there for their meaning; read-only here)."""

    @property
    def entities(self) -> Sequence[Any]: ...
    @property
    def param_dim(self) -> int: ...
    @property
    def tol_factor(self) -> float: ...
    @property
    def max_iter(self) -> int: ...
    @property
    def trims(self) -> TrimLoops | None: ...
    @property
    def searcher(self) -> GlobalSearcher: ...
    @property
    def size(self) -> float: ...
    @property
    def _period(self) -> np.ndarray: ...
    @property
    def topology(self) -> CadTopology | None: ...
    @property
    def record_width(self) -> int: ...
    @property
    def num_entities(self) -> int: ...
    @property
    def _accept(self) -> Callable[[np.ndarray, np.ndarray], np.ndarray] | None: ...
    def evaluate(self, root: npt.ArrayLike, params: np.ndarray) -> np.ndarray: ...


class CadTopology:
    """Edges and vertices of a 3D model, as arrays over the geometry's faces.

    Attributes:
        curves: 3D curves of the non-degenerate edges (their order = curve index).
        curve_of_edge: ``(ne,)`` curve index of each model edge (-1 if degenerate).
        face_curves: per face: curve indices of its edges (:class:`Ragged`).
        face_vertices: per face: indices into :attr:`points` of its CAD vertices (:class:`Ragged`).
        points: ``(nv, 3)`` CAD vertices.
        feature_faces: the faces of each curve's edge (rows ``0..nc-1``), then
            the faces around each CAD vertex (rows ``nc + v``) (:class:`Ragged`).
        feature_tolerance: ``(nc + nv,)`` the file's tolerance of each feature, rows as
            :attr:`feature_faces` (OpenCASCADE's ``BRep_Tool::Tolerance`` of the edge or
            vertex, length units; 0 where unknown).
        curve_range: ``(nc, 2)`` each curve's parameter range.
        curve_closed: ``(nc,)`` the curve is closed (periodic).
        searcher: closest points on given edges (closed form / Newton); None without curves.
        lo, hi: ``(nc, 3)`` bounding boxes of the curves.
        faces: the model's faces (their surfaces, loops' p-curves and ``uv_map``).
        pcurves: the curves the faces' p-curves trace on their surfaces, built by
            :mod:`~nagata_snap.cad.boundary` where first needed (None before).
    """

    def __init__(self, model: CadModel):
        edges = model.edges
        curve_of_edge = [-1] * len(edges)  # Python lists in the set-up loops (no numpy call per face)
        self.curves: list[Any] = []
        for i, e in enumerate(edges):
            if e.curve is not None:
                curve_of_edge[i] = len(self.curves)
                self.curves.append(e.curve)
        self.curve_of_edge = np.array(curve_of_edge, dtype=np.int64)
        self.points = model.vertices
        self.faces = model.faces
        self.pcurves: Any = None
        ends = [e.vertices for e in edges]
        face_curves, face_vertices = [], []
        for f in model.faces:  # loop over CAD faces (set-up)
            own = f.edges.tolist()
            face_curves.append([curve_of_edge[e] for e in own if curve_of_edge[e] >= 0])
            face_vertices.append(sorted({v for e in own for v in ends[e] if v >= 0}))
        curve_faces = [edges[i].faces for i, c in enumerate(curve_of_edge) if c >= 0]
        around: list[list[int]] = [[] for _ in range(len(self.points))]
        for f, vs in enumerate(face_vertices):  # faces in order, each vertex once: sorted lists
            for v in vs:
                around[v].append(f)
        self.face_curves, self.face_vertices = Ragged(face_curves), Ragged(face_vertices)
        self.feature_faces = Ragged(curve_faces + around)
        self.feature_tolerance = np.concatenate([
            np.array([edges[i].tolerance for i, c in enumerate(curve_of_edge) if c >= 0], dtype=float),
            np.asarray(model.vertex_tolerance, dtype=float).reshape(len(self.points))])
        self.curve_range = np.array([c.bounds[0] for c in self.curves], dtype=float).reshape(-1, 2)
        self.curve_closed = np.isfinite([entity_periods(c)[0] for c in self.curves]).astype(bool)
        self.searcher = GlobalSearcher(self.curves) if self.curves else None
        # the curves' boxes, as the searcher has them
        self.lo = np.zeros((0, 3)) if self.searcher is None else self.searcher.bbox_lo
        self.hi = np.zeros((0, 3)) if self.searcher is None else self.searcher.bbox_hi

    def feature_rows(self, fid: np.ndarray) -> np.ndarray:
        """Rows of :attr:`feature_faces` of features ``fid`` (``c + 1``: curve ``c``, ``-(v + 1)``: vertex ``v``)."""
        return np.where(fid > 0, fid - 1, len(self.curves) - fid - 1)
