"""The B-rep of a CAD file as plain objects: faces, edges, vertices, trimming loops.

:class:`CadModel` is built from the data of :func:`nagata_snap.cad.read.read_shape`
(no OpenCASCADE needed here):

* every face gets its surface: :mod:`~nagata_snap.cad.surfaces` for planes,
  cylinders, cones, spheres and tori, else a
  :class:`~nagata_snap.cad.nurbs.NurbsSurface`;
* every edge its 3D curve: :mod:`~nagata_snap.cad.curves` for lines and
  circles, else a :class:`~nagata_snap.cad.nurbs.NurbsCurve`; degenerate edges
  (sphere poles, cone apexes) have none;
* every face its trimming loops: the p-curves of its wires, in the order of
  the wire, sampled into closed polygons in the face's ``(u, v)`` plane.  Each
  polygon segment remembers the edge it samples and how far (in length
  units, through the surface's first derivatives) the true p-curve may be
  from the chord: lines are exact (2 points); circles (first every ``pi/16``)
  and B-splines (first 8 times per knot span) are refined until the
  deviation, measured at every segment's mid-parameter, is below 1e-5 of the
  face's size.  Seam edges appear twice in a wire, with
  their two p-curves, so a full revolution is a closed polygon of width one
  period.
* the adjacency: the faces of every edge and the (non-degenerate, non-seam)
  edges of every face, the vertices of every edge.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from nagata_snap.cad.curves import Circle, Line, analytic_curve
from nagata_snap.cad.nurbs import NurbsCurve, NurbsError, NurbsSurface
from nagata_snap.cad.surfaces import AnalyticSurface, analytic_surface

__all__ = ["CadModel", "Face", "Edge", "Loop", "sample_pcurve", "sample_pcurves", "nurbs_curve", "nurbs_surface"]

#: samples of a circular p-curve per radian (``pi / 16`` steps)
CIRCLE_STEP = np.pi / 16
#: samples of a B-spline p-curve per knot span (before refinement)
SPLINE_SAMPLES = 8
#: trimming polygons are refined until every chord is within this fraction of the
#: face's size of its p-curve (``SAMPLE_RTOL x size``; at most :data:`MAX_REFINE`
#: halvings of a segment)
SAMPLE_RTOL = 1e-5
MAX_REFINE = 10


@dataclass
class Loop:
    """A closed trimming polygon in a face's ``(u, v)`` plane.

    Attributes:
        points: ``(m, 2)`` vertices; segment ``i`` runs from ``points[i]`` to
            ``points[(i + 1) % m]``.
        edges: ``(m,)`` edge index sampled by each segment.
        band: ``(m,)`` bound on the distance (length units) between each
            segment and the true trimming curve, plus the edge's tolerance.
        senses: ``(m,)`` +1 where the wire runs along its edge's 3D curve,
            -1 where against it (the edge is used reversed).
        outer: the face's outer wire (``BRepTools::OuterWire``).
    """

    points: np.ndarray
    edges: np.ndarray
    band: np.ndarray
    senses: np.ndarray
    outer: bool = False


@dataclass
class Edge:
    """A CAD edge: its 3D curve (``None`` if degenerate), vertices, faces."""

    curve: Line | Circle | NurbsCurve | None
    vertices: tuple[int, int]
    faces: tuple[int, ...] = ()
    tolerance: float = 0.0

    @property
    def degenerate(self) -> bool:
        """A degenerate edge (a pole or an apex) has no 3D curve."""
        return self.curve is None


@dataclass
class Face:
    """A CAD face: surface, trimming loops, orientation and bounding edges.

    Attributes:
        surface: analytic surface or NURBS.
        loops: trimming polygons (:class:`Loop`), outer and inner wires.
        reversed: the face's orientation in the shape is ``REVERSED``: its
            outward normal is ``-(S_u x S_v)``.
        converted: the surface was converted to NURBS from another type, so
            its parameters differ from the file's (and gmsh's).
        edges: ``(k,)`` sorted non-degenerate, non-seam edges bounding the face.
        solids: solids the face belongs to.
        uv_map: ``(3, 2)`` affine map ``[u, v, 1] M`` of the file's (and gmsh's)
            parameters to the surface's, for faces recognised as analytic
            (IGES surfaces of revolution, ...), else None.
    """

    surface: AnalyticSurface | NurbsSurface
    loops: list[Loop]
    reversed: bool = False
    converted: bool = False
    edges: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    solids: tuple[int, ...] = ()
    uv_map: np.ndarray | None = None


def nurbs_curve(desc: dict) -> NurbsCurve:
    """A :class:`NurbsCurve` from a B-spline description (2D poles get z = 0)."""
    poles = np.asarray(desc["poles"], dtype=float)
    if poles.shape[1] == 2:
        poles = np.c_[poles, np.zeros(len(poles))]
    w = desc.get("weights")
    return NurbsCurve(int(desc["degree"]), np.asarray(desc["knots"], dtype=float), poles,
                      np.ones(len(poles)) if w is None else np.asarray(w, dtype=float))


def nurbs_surface(desc: dict) -> NurbsSurface:
    """A :class:`NurbsSurface` from a B-spline surface description."""
    poles = np.asarray(desc["poles"], dtype=float)
    w = desc.get("weights")
    p, q = desc["degree"]
    return NurbsSurface(int(p), int(q), np.asarray(desc["knots_u"], dtype=float),
                        np.asarray(desc["knots_v"], dtype=float), poles,
                        np.ones(poles.shape[:2]) if w is None else np.asarray(w, dtype=float))


def pcurve_evaluator(desc: dict):
    """``f(t (k,)) -> (k, 2)`` points of a p-curve description, and its initial samples."""
    t0, t1 = desc["range"]
    kind = desc["type"]
    if kind == "line":
        o, d = np.asarray(desc["origin"], float), np.asarray(desc["direction"], float)
        return (lambda t: o + np.asarray(t)[:, None] * d), np.array([t0, t1])
    if kind == "circle":
        c, X, Y, R = (np.asarray(desc["center"], float), np.asarray(desc["x"], float),
                      np.asarray(desc["y"], float), float(desc["radius"]))
        n = max(2, int(np.ceil(abs(t1 - t0) / CIRCLE_STEP)))
        return (lambda t: c + R * (np.cos(t)[:, None] * X + np.sin(t)[:, None] * Y)), \
            np.linspace(t0, t1, n + 1)
    curve = nurbs_curve(desc)
    k = np.unique(curve.knots)
    k = np.unique(np.concatenate([[t0, t1], k[(k >= t0) & (k <= t1)]]))
    s = np.linspace(0.0, 1.0, SPLINE_SAMPLES + 1)[:-1]
    t = np.concatenate([(k[:-1, None] + np.outer(np.diff(k), s)).ravel(), [t1]])
    return (lambda t: curve.evaluate(t)[0][:, :2]), t


def sample_pcurve(desc: dict, reverse: bool, surface=None, tol: float = 0.0, uv_map=None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Polygon of one p-curve: :func:`sample_pcurves` of one edge use."""
    return sample_pcurves([desc], [reverse], surface, tol, uv_map)[0]


def sample_pcurves(descs: Sequence[dict], reverses: Sequence[bool], surface=None, tol: float = 0.0,
                   uv_map=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Polygons of p-curves on one surface, refined until their chords are within ``tol``.

    Segments whose mid-parameter point is farther than ``tol`` from the chord's
    midpoint (in length units through the ``surface``'s first derivatives;
    parametric distance without a surface) are split, up to
    :data:`MAX_REFINE` times.  All curves are refined together: one surface
    derivative evaluation per refinement pass for every segment of every curve.

    Returns:
        per curve ``(points (m, 2), dev (m - 1,))``: samples in traversal order
        (reversed if the edge is used reversed), mapped by ``uv_map``
        ``(3, 2)`` if given, and each segment's deviation.
    """
    n = len(descs)
    fs, ts, Ps, devs = [], [], [], [None] * n
    for i, desc in enumerate(descs):
        f, t = pcurve_evaluator(desc)
        if uv_map is not None:
            f = _mapped(f, uv_map)
        fs.append(f)
        ts.append(t)
        Ps.append(f(t))
        if desc["type"] == "line":  # linear in t: the chord is the curve (deviation 0)
            devs[i] = np.zeros(len(Ps[i]) - 1)
    active = [i for i in range(n) if devs[i] is None]
    for it in range(MAX_REFINE + 1):
        if not active:
            break
        tms = [0.5 * (ts[i][1:] + ts[i][:-1]) for i in active]
        mids = [0.5 * (Ps[i][1:] + Ps[i][:-1]) for i in active]
        off = np.concatenate([fs[i](tm) - m for i, tm, m in zip(active, tms, mids)])  # (s, 2)
        if surface is None:
            dev = np.linalg.norm(off, axis=1)
        else:
            T = _tangents(surface, np.concatenate(mids))
            dev = np.linalg.norm(off[:, 0, None] * T[:, 0] + off[:, 1, None] * T[:, 1], axis=1)
        refine = []
        for i, tm, d in zip(active, tms, np.split(dev, np.cumsum([len(m) for m in mids])[:-1])):
            devs[i] = d
            split = d > tol
            if split.any() and it < MAX_REFINE:
                ts[i] = np.sort(np.concatenate([ts[i], tm[split]]))
                Ps[i] = fs[i](ts[i])
                refine.append(i)
        active = refine
    return [(P[::-1], d[::-1]) if rev else (P, d) for P, d, rev in zip(Ps, devs, reverses)]


def _mapped(f, uv_map: np.ndarray):
    """``f`` followed by the affine map ``[u, v, 1] uv_map`` ``(3, 2)``."""
    return lambda t: np.c_[f(t), np.ones(len(t))] @ uv_map


def _surface(desc: dict, uv) -> tuple[AnalyticSurface | NurbsSurface, np.ndarray | None]:
    """The face's surface, and the map of the file's ``(u, v)`` to its parameters (or None)."""
    bounds = [[uv[0], uv[1]], [uv[2], uv[3]]]
    if desc["type"] == "bspline":
        return nurbs_surface(desc), None
    if "samples" not in desc:
        return analytic_surface(desc, bounds), None
    return fit_uv_map(desc, bounds)


def fit_uv_map(desc: dict, bounds) -> tuple[AnalyticSurface, np.ndarray]:
    """Analytic surface of a recognised face and the affine map of the face's parameters.

    ``desc["samples"] = (uv (k, 2), points (k, 3))``: a grid over the face's
    own ``(u, v)`` box and its points.  Their closed-form parameters on the
    analytic surface (unwrapped along the grid in closed directions) are fitted
    by ``(u', v') = [u, v, 1] M`` (least squares on the grid's interior, clear
    of poles and apexes, where a parameter is free); the map is accepted if
    it reproduces every sample point within 1e-9 of the face's size.

    Returns:
        ``(surface, M (3, 2))``, the surface's bounds the image of the face's box.

    Raises:
        ValueError: no affine map fits (the caller converts to NURBS instead).
    """
    uv, xyz = (np.asarray(a, dtype=float) for a in desc["samples"])
    n = int(round(np.sqrt(len(uv))))
    size = float(np.linalg.norm(xyz.max(axis=0) - xyz.min(axis=0)))
    probe = analytic_surface(desc, [[0.0, 2 * np.pi], [-1.0, 1.0]])
    P = probe.closest(xyz)[0]
    for a, per in enumerate(probe.periods):
        if np.isfinite(per):
            g = np.unwrap(P[:, a].reshape(n, n), period=per, axis=1)
            P[:, a] = np.unwrap(g, period=per, axis=0).ravel()
    inner = np.zeros((n, n), dtype=bool)
    inner[1:-1, 1:-1] = True
    inner = inner.ravel() if n > 2 else np.ones(len(uv), dtype=bool)
    A = np.c_[uv, np.ones(len(uv))]
    M = np.linalg.lstsq(A[inner], P[inner], rcond=None)[0]  # (3, 2)
    err = np.linalg.norm(probe._points(*(A @ M).T) - xyz, axis=1).max()
    if not err <= 1e-9 * max(size, 1e-300):
        raise ValueError(f"no affine parameter map onto the {desc['type']} (error {err:.2e})")
    corners = np.c_[np.array([[b0, b1] for b0 in bounds[0] for b1 in bounds[1]]), np.ones(4)] @ M
    return analytic_surface(desc, np.stack([corners.min(axis=0), corners.max(axis=0)], axis=1)), M


def _loops(face_surface, wires: Sequence[dict], tolerances: np.ndarray, uv_map=None) -> list[Loop]:
    """Closed polygons of a face's wires: their edge uses' p-curve samples, joined.

    Each segment's band is twice its deviation from the p-curve (length
    units, see :func:`sample_pcurves`, all the face's p-curves sampled
    together) plus the edge's tolerance.  ``uv_map`` ``(3, 2)`` maps the
    file's parameters to the surface's.
    """
    wires = [w for w in wires if w["uses"]]
    uses = [u for w in wires for u in w["uses"]]
    samples = iter(sample_pcurves([u["pcurve"] for u in uses], [u["reversed"] for u in uses],
                                  face_surface, SAMPLE_RTOL * face_surface.bbox_size, uv_map))
    loops = []
    for wire in wires:
        pts, dev, edge, sense = [], [], [], []
        for use in wire["uses"]:
            p, d = next(samples)
            pts.append(p[:-1])  # the next use starts where this one ends
            dev.append(d)
            edge.append(np.full(len(d), use["edge"], dtype=np.int64))
            sense.append(np.full(len(d), -1.0 if use["reversed"] else 1.0))
        E = np.concatenate(edge)
        P = np.concatenate(pts)
        if not np.all(np.isfinite(P)) or not _three_distinct(np.round(P / max(np.ptp(P), 1e-300), 12)):
            raise ValueError("a trimming wire has fewer than 3 distinct (finite) points in the "
                             "parameter plane")
        band = 2.0 * np.concatenate(dev) + tolerances[E]
        loops.append(Loop(P, E, band, np.concatenate(sense), bool(wire["outer"])))
    return loops


def _three_distinct(R: np.ndarray) -> bool:
    """Rows of ``R (m, 2)`` take at least three distinct values (no sort: two passes)."""
    if len(R) < 3:
        return False
    off_a = np.any(R[0] != R, axis=1)
    if not off_a.any():
        return False
    b = R[np.argmax(off_a)]
    return bool(np.any(off_a & np.any(b != R, axis=1)))


def _tangents(surface, params: np.ndarray) -> np.ndarray:
    """``(k, 2, 3)`` first derivatives at parameters (wrapped/clamped for NURBS)."""
    from nagata_snap.cad.projection import evaluate_params, normalize_params

    _, T = evaluate_params(surface, normalize_params(surface, params), 1)
    return T


class CadModel:
    """Faces, edges and vertices of a CAD file (see the module docstring).

    Attributes:
        faces: list of :class:`Face`.
        edges: list of :class:`Edge`.
        vertices: ``(nv, 3)`` vertex points.
        path, format, unit, file_units: where it came from and its units
            (``unit``: of the coordinates here; ``file_units``: the file's own).
        size: diagonal of the shape's bounding box.
        times: seconds spent in OpenCASCADE (``read``, ``heal``, ``convert``)
            and here (``build``).
        num_solids: solids in the shape.
    """

    def __init__(self, faces, edges, vertices, *, path="", format="", unit="", file_units=(),
                 size=0.0, times=None, num_solids=0, healed=None):
        self.faces = list(faces)
        self.edges = list(edges)
        self.vertices = np.asarray(vertices, dtype=float).reshape(-1, 3)
        self.path, self.format, self.unit = path, format, unit
        self.file_units = list(file_units)
        self.size = float(size)
        self.times = dict(times or {})
        self.num_solids = int(num_solids)
        self.healed = dict(healed or {})

    @classmethod
    def from_data(cls, data: dict) -> CadModel:
        """Build the model from :func:`~nagata_snap.cad.read.read_shape`'s result.

        Raises:
            ValueError: a face or edge whose geometry is invalid (the message
                names it; e.g. a B-spline with bad knots).
        """
        import time

        t0 = time.perf_counter()
        path = data.get("path", "")
        edges = []
        for i, e in enumerate(data["edges"]):
            c = e["curve"]
            try:
                curve = None if c is None else (
                    analytic_curve(c) if c["type"] in ("line", "circle") else nurbs_curve(c))
            except (ValueError, NurbsError) as err:
                raise ValueError(f"{path}: edge {i} ({c['type']} curve): {err}") from None
            edges.append(Edge(curve, tuple(int(v) for v in e["vertices"]), (),
                              float(e.get("tolerance", 0.0))))
        tol = np.array([e.tolerance for e in edges] + [0.0])
        faces = []
        face_edges: list[set] = []
        for i, f in enumerate(data["faces"]):
            desc = f["surface"]
            try:
                surface, uv_map = _surface(desc, f["uv"])
                loops = _loops(surface, f["wires"], tol, uv_map)
            except (ValueError, NurbsError) as err:
                raise ValueError(f"{path}: face {i} ({desc['type']} surface): {err}") from None
            # a map that flips the parameter plane flips S_u x S_v
            flip = uv_map is not None and np.linalg.det(uv_map[:2]) < 0
            own = {u["edge"] for w in f["wires"] for u in w["uses"]
                   if not u["seam"] and edges[u["edge"]].curve is not None}
            face_edges.append(own)
            faces.append(Face(surface, loops, bool(f["reversed"]) != flip, bool(f["converted"]),
                              np.array(sorted(own), dtype=np.int64), tuple(f.get("solids", ())),
                              uv_map))
        users: list[list[int]] = [[] for _ in edges]
        for i, own in enumerate(face_edges):
            for e in own:
                users[e].append(i)
        for e, u in zip(edges, users):
            e.faces = tuple(sorted(u))
        times = dict(data.get("times", {}))
        times["build"] = time.perf_counter() - t0
        return cls(faces, edges, data["vertices"], path=path, format=data.get("format", ""),
                   unit=data.get("unit", ""), file_units=data.get("file_units", ()),
                   size=data.get("size", 0.0), times=times,
                   num_solids=data.get("num_solids", 0), healed=data.get("healed"))

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def curve_edges(self) -> np.ndarray:
        """Indices of the edges with a 3D curve (not degenerate)."""
        return np.array([i for i, e in enumerate(self.edges) if e.curve is not None], dtype=np.int64)

    def is_planar_2d(self, rtol: float = 1e-9) -> bool:
        """All faces are planes in ``z = 0`` (a profile for 2D meshes), or there are no faces."""
        if not self.faces:
            return len(self.curve_edges()) > 0
        tol = rtol * max(self.size, 1e-300)
        for f in self.faces:
            s = f.surface
            if getattr(s, "kind", "") != "plane" or abs(s.origin[2]) > tol or \
                    abs(abs(s.Z[2]) - 1.0) > rtol:
                return False
        return True

    def summary(self) -> str:
        kinds: dict[str, int] = {}
        for f in self.faces:
            k = getattr(f.surface, "kind", "nurbs")
            k = "nurbs" if isinstance(f.surface, NurbsSurface) else k
            kinds[k] = kinds.get(k, 0) + 1
        what = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items()))
        return (f"{len(self.faces)} faces ({what}), {len(self.curve_edges())} edges, "
                f"{len(self.vertices)} vertices, {self.num_solids} solids, unit {self.unit}")

    def __repr__(self) -> str:
        return f"CadModel({self.path!r}: {self.summary()})"
