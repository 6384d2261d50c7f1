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

The per-file, per-face and per-edge Python cost is kept down by building
things of a kind together: the analytic surfaces of all faces
(:func:`~nagata_snap.cad.surfaces.analytic_surfaces`), the lines and circles
of all edges (:func:`~nagata_snap.cad.curves.analytic_curves`), the B-spline
edges (:meth:`NurbsCurve.many <nagata_snap.cad.nurbs.NurbsCurve.many>`) and
the p-curves of all uses of all faces: lines and circles from per-use
coefficient arrays, B-splines packed end to end and evaluated together
(:class:`_Splines`, :class:`NurbsCurve.Packed <nagata_snap.cad.nurbs.NurbsCurve.Packed>`),
their checks done together and repeated one by one only to name an invalid
one.  Everything built so is the same, to the last bit, as built one by one.

A planar 2D model (every face a plane in ``z = 0``,
:meth:`CadModel.is_planar_2d`) is meshed and snapped onto its edge curves,
which need only the wires' edge uses and senses: its loop polygons are
sampled when first read (:class:`Loop`), for all faces at once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np

from nagata_snap.cad.curves import Circle, Line, analytic_curve, analytic_curves
from nagata_snap.cad.nurbs import NurbsCurve, NurbsError, NurbsSurface
from nagata_snap.cad.surfaces import _SURFACES, AnalyticSurface, Plane, analytic_surface, analytic_surfaces, fill_boxes
from nagata_snap.mesh.arrays import dot

__all__ = ["CadModel", "Face", "Edge", "Loop", "nurbs_curve", "nurbs_surface"]

#: samples of a circular p-curve per radian (``pi / 16`` steps)
CIRCLE_STEP = np.pi / 16
#: samples of a B-spline p-curve per knot span (before refinement)
SPLINE_SAMPLES = 8
#: their fractions of the span, ``np.linspace(0, 1, SPLINE_SAMPLES + 1)[:-1]``
_SPAN_STEPS = np.linspace(0.0, 1.0, SPLINE_SAMPLES + 1)[:-1]
#: trimming polygons are refined until every chord is within this fraction of the
#: face's size of its p-curve (``SAMPLE_RTOL x size``; at most :data:`MAX_REFINE`
#: halvings of a segment)
SAMPLE_RTOL = 1e-5
MAX_REFINE = 10


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
        uses: ``(k,)`` the edge of each edge use of the wire, in wire order
            (default: :attr:`edges`, one use per segment).
        use_senses: ``(k,)`` the sense of each use (default: :attr:`senses`).
        pcurves: per use its p-curve's description (``read_shape``'s ``"pcurve"``, in the
            file's parameters: a face's ``uv_map`` maps them), or None.

    The polygon (:attr:`points`, :attr:`edges`, :attr:`band`, :attr:`senses`)
    of a planar 2D model's faces is sampled when one of them is first read,
    for all faces of the model at once (:meth:`CadModel.from_data`: a 2D
    geometry snaps onto the edge curves and needs only the uses).
    """

    def __init__(self, points: np.ndarray | None, edges: np.ndarray | None, band: np.ndarray | None,
                 senses: np.ndarray | None, outer: bool = False, uses: np.ndarray | None = None,
                 use_senses: np.ndarray | None = None, pcurves: Sequence[dict] | None = None):
        self._polygon = None if points is None else (points, edges, band, senses)
        self.pcurves = None if pcurves is None else list(pcurves)
        self.outer = outer
        uses, use_senses = edges if uses is None else uses, senses if use_senses is None else use_senses
        assert uses is not None and use_senses is not None, "a loop without a polygon has its uses"
        self.uses, self.use_senses = uses, use_senses
        #: samples the polygons of all loops of the model when one is first read (lazy loops)
        self._sampler: _LazyLoops | None = None

    def _sampled(self) -> tuple:
        if self._polygon is None:
            assert self._sampler is not None, "a loop without a polygon has a sampler"
            self._sampler.fill()
        assert self._polygon is not None
        return self._polygon

    @property
    def points(self) -> np.ndarray:
        return self._sampled()[0]

    @property
    def edges(self) -> np.ndarray:
        return self._sampled()[1]

    @property
    def band(self) -> np.ndarray:
        return self._sampled()[2]

    @property
    def senses(self) -> np.ndarray:
        return self._sampled()[3]

    def __repr__(self) -> str:
        what = "not sampled" if self._polygon is None else f"{len(self.points)} points"
        return f"Loop({'outer' if self.outer else 'inner'}, {len(self.uses)} uses, {what})"


@dataclass
class Edge:
    """A CAD edge: its 3D curve (``None`` if degenerate), vertices, faces.

    ``source``: the OpenCASCADE edge whose 3D curve it is, by its index in the
    shape read (:func:`~nagata_snap.cad.read.read_shape`: the unsewn shape
    where its faces were joined by :mod:`~nagata_snap.cad.sewing`, else the
    healed shape, i.e. its own index).
    """

    curve: Line | Circle | NurbsCurve | None
    vertices: tuple[int, int]
    faces: tuple[int, ...] = ()
    tolerance: float = 0.0
    source: int = -1

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
    poles = np.asarray(desc["poles"], dtype=float)  # (n, 2) poles get z = 0 (NurbsCurve)
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


class _FaceError(ValueError):
    """A face's geometry cannot be used: ``face`` its index (the message names the rest)."""

    def __init__(self, face: int, message: str):
        super().__init__(message)
        self.face = face


class _Splines:
    """B-spline p-curves packed end to end and evaluated together (no object per curve).

    The curves are a :class:`NurbsCurve.Packed <nagata_snap.cad.nurbs.NurbsCurve.Packed>`,
    whose points are :meth:`NurbsCurve.evaluate <nagata_snap.cad.nurbs.NurbsCurve.evaluate>`'s
    to the last bit, with its parameter wrapping: a parameter beyond a curve's domain
    wraps (closed curve) or is clamped; the closedness, which decides only that, is
    computed for the curves evaluated there, when they are.

    Args:
        descs: per curve its description (``read_shape``'s ``"pcurve"`` of type ``bspline``).
        face: ``(n,)`` face of each curve (named in the error).

    Raises:
        _FaceError: the first invalid description (the checks are done together;
            if one fails, :func:`nurbs_curve` builds the curves one by one and names
            the error).
    """

    def __init__(self, descs: Sequence[dict], face: np.ndarray):
        fields = ([d["degree"] for d in descs], [d["knots"] for d in descs], [d["poles"] for d in descs],
                  [d.get("weights") for d in descs])
        packed = NurbsCurve.Packed.checked(*fields)
        closed = None
        if packed is None:  # an invalid (or unusual) description: NurbsCurve checks each
            curves = []
            for j, d in enumerate(descs):  # loop over p-curves (error path)
                try:
                    curves.append(nurbs_curve(d))
                except (ValueError, NurbsError) as err:
                    raise _FaceError(int(face[j]), str(err)) from None
            packed = NurbsCurve.Packed.of(curves)
            closed = np.array([c.is_closed for c in curves], dtype=np.int8)
        self.packed = pk = packed
        #: per curve: 1 closed, 0 open, -1 not known yet
        self.closed = np.full(len(pk.p), -1, dtype=np.int8) if closed is None else closed
        #: every parameter evaluated is inside its curve's domain (set by :meth:`first_samples`)
        self.inside = False

    def __call__(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
        """``(k, 2)`` points at ``t (k,)`` of curves ``c (k,)`` (grouped by curve, in curve order)."""
        pk = self.packed
        if not self.inside:
            out = np.flatnonzero((t < pk.lo[c]) | (t > pk.hi[c]))
            if out.size:
                t = self._wrap(t, c, out)
        return pk.points(t, c)[:, :2]

    def _wrap(self, t: np.ndarray, c: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``t`` with the rows ``out`` brought into their curve's domain, as ``NurbsCurve.wrap``."""
        pk, co = self.packed, c[out]
        todo = np.unique(co[self.closed[co] < 0])
        if todo.size:
            self.closed[todo] = pk.closed(todo)[0]
        lo, hi, to = pk.lo[co], pk.hi[co], t[out]
        t = t.copy()
        t[out] = np.where(self.closed[co] == 1, lo + np.mod(to - lo, hi - lo), np.clip(to, lo, hi))
        return t

    def first_samples(self, t0: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(counts (n,), t)``: per curve the distinct knots inside its range ``[t0, t1]`` and
        its ends, :data:`SPLINE_SAMPLES` samples per interval between them, then ``t1``;
        ``t`` all curves' samples, concatenated.

        Where every range is inside its curve's domain, so is every parameter evaluated
        (these samples, each within its interval, and the refinement's midpoints of two):
        :attr:`inside` is set and the curves' points skip the domain test."""
        pk = self.packed
        ns, knots, ck = len(pk.p), pk.K, pk.ck
        inside = (knots >= t0[ck]) & (knots <= t1[ck])
        cs = np.arange(ns)
        a, b = np.minimum(t0, t1), np.maximum(t0, t1)
        self.inside = bool(((a >= pk.lo) & (b <= pk.hi)).all())
        v = np.concatenate([a, knots[inside], b])
        grp = np.concatenate([cs, ck[inside], cs])
        order = np.argsort(grp, kind="stable")  # per curve: its start, its knots, its end
        v, grp = v[order], grp[order]
        keep = np.ones(len(v), dtype=bool)
        keep[1:] = (v[1:] != v[:-1]) | (grp[1:] != grp[:-1])
        v, grp = v[keep], grp[keep]
        iv = np.flatnonzero(grp[1:] == grp[:-1])  # intervals: first point
        counts = np.bincount(grp[iv], minlength=ns) * SPLINE_SAMPLES + 1
        end = np.cumsum(counts) - 1
        t = np.empty(int(end[-1]) + 1 if ns else 0)
        spans = np.ones(len(t), dtype=bool)
        spans[end] = False
        t[spans] = (v[iv, None] + np.multiply.outer(v[iv + 1] - v[iv], _SPAN_STEPS)).ravel()
        t[end] = t1
        return counts, t


class _PCurves:
    """The p-curves of many edge uses (of many faces), evaluated together.

    Lines and circles are evaluated for all uses at once from per-use
    coefficient arrays, B-spline p-curves together by :class:`_Splines`.
    Points are mapped by their face's ``uv_map`` (identity where None).

    Args:
        descs: per use its p-curve description (``read_shape``'s ``"pcurve"``).
        face: ``(n,)`` face of each use (uses sorted by face).
        uv_maps: per face its ``(3, 2)`` map or None.
    """

    def __init__(self, descs: Sequence[dict], face: np.ndarray, uv_maps: Sequence[np.ndarray | None]):
        n = len(descs)
        kinds = [_KINDS.get(d["type"], 2) for d in descs]
        self.kind = np.array(kinds, dtype=np.int64)
        self.A, self.B, self.C = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros((n, 2))
        self.R = np.zeros(n)
        self.face = np.asarray(face, dtype=np.int64)
        for kind, names in ((0, ("origin", "direction")), (1, ("center", "x", "y"))):
            sel = [j for j, k in enumerate(kinds) if k == kind]
            if sel:
                for arr, name in zip((self.A, self.B, self.C), names, strict=False):
                    arr[sel] = [descs[j][name] for j in sel]
                if kind == 1:
                    self.R[sel] = [descs[j]["radius"] for j in sel]
        #: the B-spline uses, and the spline (of :attr:`splines`) of every use (-1: none)
        self.spline_uses = np.flatnonzero(self.kind == 2)
        self.spline_of = np.full(n, -1, dtype=np.int64)
        self.spline_of[self.spline_uses] = np.arange(self.spline_uses.size)
        self.splines = (_Splines([descs[j] for j in self.spline_uses.tolist()], self.face[self.spline_uses])
                        if self.spline_uses.size else None)
        mapped = [i for i, m in enumerate(uv_maps) if m is not None]
        self.mapped = np.zeros(len(uv_maps) + 1, dtype=bool)
        self.mapped[mapped] = True
        self.mapped = self.mapped[self.face]
        #: some use is on a mapped face
        self.any_mapped = bool(self.mapped.any())
        #: ``(6, n)`` per use its face's map ``M (3, 2)`` by coordinate (``M[:, 0]``, ``M[:, 1]``;
        #: the identity where none)
        self.M = np.zeros((6, n))
        self.M[0] = self.M[4] = 1.0
        if self.any_mapped:
            maps = np.array([np.asarray(uv_maps[i], dtype=float) for i in mapped]).reshape(-1, 3, 2)
            at = np.searchsorted(mapped, self.face[self.mapped])  # each mapped use's map
            self.M[:, self.mapped] = maps[at].transpose(2, 1, 0).reshape(6, -1)

    def initial(self, descs: Sequence[dict]) -> _Samples:
        """Per use its first samples: the ends (line), every ``pi / 16`` (circle),
        :data:`SPLINE_SAMPLES` per knot span (B-spline, :meth:`_Splines.first_samples`)."""
        rng = np.array([d["range"] for d in descs], dtype=float).reshape(-1, 2)
        steps = np.ones(len(descs), dtype=np.int64)
        c = self.kind == 1
        steps[c] = np.maximum(2, np.ceil(np.abs(rng[c, 1] - rng[c, 0]) / CIRCLE_STEP).astype(np.int64))
        su = self.spline_uses
        if self.splines is None:
            return _Samples(rng, steps, su, np.zeros(0, dtype=np.int64), np.zeros(0))
        counts, t = self.splines.first_samples(rng[su, 0], rng[su, 1])
        return _Samples(rng, steps, su, counts, t)

    def __call__(self, t: np.ndarray, use: np.ndarray, splines: bool = False) -> np.ndarray:
        """``(k, 2)`` points (mapped parameters) at ``t (k,)`` of uses ``use (k,)`` (sorted);
        ``splines``: the uses are known to be B-splines (no kind selection)."""
        if not splines:
            kind = self.kind[use]
            s = np.flatnonzero(kind == 2)
            splines = self.splines is not None and s.size == len(t) and bool(s.size)
        if splines:  # B-splines only: no selection
            assert self.splines is not None
            P = self.splines(t, self.spline_of[use])
        else:
            P = np.empty((len(t), 2))
            ln = np.flatnonzero(kind == 0)
            if ln.size:
                ul = use[ln]
                P[ln] = self.A[ul] + t[ln, None] * self.B[ul]
            c = np.flatnonzero(kind == 1)
            if c.size:  # coordinate by coordinate (no (k, 1) x (k, 2) broadcasts), the same products
                uc, tc = use[c], t[c]
                co, si, r = np.cos(tc), np.sin(tc), self.R[uc]
                for j in range(2):
                    P[c, j] = self.A[uc, j] + r * (co * self.B[uc, j] + si * self.C[uc, j])
            if s.size and self.splines is not None:
                P[s] = self.splines(t[s], self.spline_of[use[s]])
        if self.any_mapped:
            mapped = self.mapped[use]
            if mapped.all():  # no row selection
                P = self._mapped(P, use)
            else:
                m = np.flatnonzero(mapped)
                if m.size:
                    P[m] = self._mapped(P[m], use[m])
        return P

    def _mapped(self, P: np.ndarray, use: np.ndarray) -> np.ndarray:
        """``(k, 2)`` the points ``P (k, 2)`` of uses ``use (k,)`` mapped: ``[u, v, 1] M``
        coordinate by coordinate (einsum's products and sums, half its cost)."""
        M = self.M.take(use, axis=1)
        u, v = P[:, 0], P[:, 1]
        out = np.empty_like(P)
        for j in range(2):
            out[:, j] = u * M[3 * j] + v * M[3 * j + 1] + M[3 * j + 2]
        return out


#: p-curve types evaluated in closed form (the rest: B-splines)
_KINDS = {"line": 0, "circle": 1}


@dataclass
class _Samples:
    """First samples of edge uses: ``steps[j]`` uniform steps over ``range[j] (2,)`` (lines and
    circles; as ``np.linspace(*range[j], steps[j] + 1)``), or, for the B-spline uses
    ``spline_uses (s,)`` (sorted), ``spline_counts (s,)`` samples each, concatenated in ``spline_t``."""

    range: np.ndarray
    steps: np.ndarray
    spline_uses: np.ndarray
    spline_counts: np.ndarray
    spline_t: np.ndarray

    def flat(self, reverses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(t (N,), use (N,))``: every use's samples, grouped by use, each in traversal order
        (backwards where ``reverses``); the uniform ones all at once, to the last bit
        ``linspace``'s (``i step + t0``, the last ``t1``; a line's ends are its range)."""
        cnt = self.steps + 1
        cnt[self.spline_uses] = self.spline_counts
        use = np.repeat(np.arange(len(cnt)), cnt)
        end = np.cumsum(cnt)
        i = np.arange(len(use)) - (end - cnt)[use]  # ramp(cnt), its cumsum and repeat shared
        t0, t1 = self.range[:, 0], self.range[:, 1]
        t = i * ((t1 - t0) / self.steps)[use] + t0[use]
        t[end - 1] = t1
        line = self.steps == 1
        t[(end - cnt)[line]] = t0[line]
        if self.spline_uses.size:
            spline = np.zeros(len(cnt), dtype=bool)
            spline[self.spline_uses] = True
            t[spline[use]] = self.spline_t
        r = reverses[use]
        pos = np.arange(len(t))
        pos[r] = (2 * (end - cnt) + cnt - 1)[use[r]] - pos[r]  # start + (count - 1 - i)
        return t[pos], use


class _Metric:
    """Lengths of parametric offsets on the faces' surfaces (``|S_u du + S_v dv|``).

    Plane tangents are constant: all plane faces are measured at once; other
    surfaces are evaluated per face; where the surface is None, the length
    is parametric.
    """

    def __init__(self, surfaces: Sequence):
        self.surfaces = surfaces
        self.plane = np.array([isinstance(s, Plane) for s in surfaces] + [False], dtype=bool)
        #: ``(3, n_faces)`` the planes' axes by coordinate (0 for other faces)
        self.X = np.array([s.X if isinstance(s, Plane) else np.zeros(3) for s in surfaces]).reshape(-1, 3).T.copy()
        self.Y = np.array([s.Y if isinstance(s, Plane) else np.zeros(3) for s in surfaces]).reshape(-1, 3).T.copy()

    def __call__(self, off: np.ndarray, mid: np.ndarray, face: np.ndarray) -> np.ndarray:
        """``(k,)`` lengths of ``off (k, 2)`` at ``mid (k, 2)`` on ``face (k,)`` (sorted)."""
        on_plane = self.plane[face]
        if on_plane.all():  # planes only (the common case): no row selection
            return _lengths(off[:, 0], off[:, 1], self.X.take(face, axis=1), self.Y.take(face, axis=1))
        dev = np.empty(len(off))
        p = np.flatnonzero(on_plane)
        if p.size:
            fp = face[p]
            dev[p] = _lengths(off[p, 0], off[p, 1], self.X.take(fp, axis=1), self.Y.take(fp, axis=1))
        start = np.flatnonzero(np.diff(face, prepend=-1))  # each face's first row
        stop = np.append(start[1:], len(face))
        curved = ~self.plane[face[start]]
        for f, lo, hi in zip(face[start[curved]].tolist(), start[curved].tolist(), stop[curved].tolist(),
                             strict=True):  # loop over curved faces with curved p-curves
            if self.surfaces[f] is None:
                dev[lo:hi] = np.linalg.norm(off[lo:hi], axis=1)
            else:
                dev[lo:hi] = _lengths(off[lo:hi, 0], off[lo:hi, 1], *_tangents(self.surfaces[f], mid[lo:hi]))
        return dev


def _lengths(a: np.ndarray, b: np.ndarray, U: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``(k,)`` lengths ``|a U + b V|`` (length units) of ``a, b (k,)`` times the vectors
    ``U, V (3, k)`` (by coordinate), coordinate by coordinate: to the last bit
    ``np.linalg.norm(a[:, None] * U.T + b[:, None] * V.T, axis=1)`` (the same products, and
    its sum of the squares in its order, :func:`~nagata_snap.mesh.arrays.dot`), without
    the reduction over a 3-wide axis."""
    v = [a * U[j] + b * V[j] for j in range(3)]
    return np.sqrt(dot(v, v))


def _circles_on_planes(f: _PCurves, first: _Samples, metric: _Metric, tols: np.ndarray) -> np.ndarray:
    """Circular p-curves on (unmapped) planes sampled at once to their final step.

    On a plane the metric is the identity (orthonormal ``X``, ``Y``) and every
    chord of a uniformly sampled circle deviates by its sagitta
    ``R (1 - cos(dt / 2))``: the refinement of :func:`_refine` would halve
    every step ``h`` times, ``h`` the least number (at most
    :data:`MAX_REFINE`) that brings the sagitta within the face's tolerance.

    Returns:
        ``dev (n_uses,)``: those circles' chords' deviation (NaN for the uses still to
        refine); their steps in ``first`` are multiplied.
    """
    done = np.full(len(first.steps), np.nan)
    sel = np.flatnonzero((f.kind == 1) & metric.plane[f.face] & ~f.mapped)
    if sel.size == 0:
        return done
    n0 = first.steps[sel]
    t0, t1 = first.range[sel, 0], first.range[sel, 1]
    dt0 = np.abs(t1 - t0) / n0
    R, tol = np.abs(f.R[sel]), tols[f.face[sel]]
    # the sagittas after 0 .. MAX_REFINE - 1 halvings, all at once: h the first within the
    # tolerance (the refinement's test, not more), else MAX_REFINE
    more = R[:, None] * (1.0 - np.cos(0.5 * dt0[:, None] / 2.0 ** np.arange(max(MAX_REFINE, 1)))) > tol[:, None]
    h = np.where(more.all(axis=1), MAX_REFINE, (~more).argmax(axis=1))
    first.steps[sel] = n0 * 2 ** h
    done[sel] = R * (1.0 - np.cos(0.5 * dt0 / 2.0 ** h))
    return done


def _refine(f: _PCurves, first: _Samples, reverses: np.ndarray, surfaces: Sequence,
            tols: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sample every use's p-curve and refine its chords until within its face's tolerance.

    Segments whose mid-parameter point is farther than ``tols[face]`` from the
    chord's midpoint (:class:`_Metric`) are split, up to :data:`MAX_REFINE`
    times; all uses of all faces are refined together.  Only the halves of the
    segments split are tested again (a segment kept keeps its deviation), and one
    evaluation tests two levels: each segment's midpoint and the midpoints of its
    two halves, whose tests count only where the segment is split (the same
    points and decisions as level by level, in half the calls).  The points are
    carried as complex numbers (:func:`_complex`).

    Returns:
        ``(P (N, 2), use (N,), dev (N,))``: the samples of every use in
        traversal order (reversed for uses with ``reverses``), grouped by use;
        ``dev[k]`` the deviation of the segment from ``P[k]`` to ``P[k + 1]``
        (0 for lines; meaningless at a use's last point).
    """
    metric = _Metric(surfaces)
    done = _circles_on_planes(f, first, metric, tols)
    t, use = first.flat(reverses)
    Z = _complex(f(t, use))  # the points x + iy
    dev = np.where(np.isnan(done), 0.0, done)[use]  # done: NaN or a (finite) sagitta
    todo = (f.kind != 0) & np.isnan(done)  # uses to refine
    splines = f.splines is not None and not (todo & (f.kind == 1)).any()  # they are all B-splines
    k = np.flatnonzero((use[:-1] == use[1:]) & todo[use[:-1]])  # segments (by their first point) to test
    it = 0  # refinement level of the segments tested
    while it <= MAX_REFINE:
        if k.size == 0:
            break
        two = it < MAX_REFINE  # the halves' level is within the refinement limit
        um = use[k]
        fm = f.face[um]
        k1 = k + 1
        Za, Zb = Z[k], Z[k1]
        ta, tb = t[k], t[k1]
        tm = 0.5 * (ta + tb)
        if two:  # midpoints, then the midpoints of both halves, interleaved (uses stay sorted)
            tq = np.empty((len(k), 3))  # columns tm, 0.5 (ta + tm), 0.5 (tm + tb)
            tq[:, 0] = tm
            for j, (lo, hi) in enumerate(((ta, tm), (tm, tb)), start=1):
                np.add(lo, hi, out=tq[:, j])
                tq[:, j] *= 0.5
            Zq = _complex(f(tq.ravel(), um.repeat(3), splines)).reshape(-1, 3)
            Zm = Zq[:, 0]
            mids = np.empty((len(k), 3), dtype=complex)  # chords' midpoints: 0.5 (Za + Zb), 0.5 (Za + Zm), ...
            np.add(Za, Zb, out=mids[:, 0])
            np.add(Za, Zm, out=mids[:, 1])
            np.add(Zm, Zb, out=mids[:, 2])
            mids.view(np.float64)[:] *= 0.5
            dq = metric(_real(Zq - mids), _real(mids), fm.repeat(3)).reshape(-1, 3)
            d = dq[:, 0]
        else:
            mid = Za + Zb
            mid.view(np.float64)[:] *= 0.5
            Zm = _complex(f(tm, um, splines))
            d = metric(_real(Zm - mid), _real(mid), fm)
        dev[k] = d
        split = d > tols[fm]
        if it == MAX_REFINE or not split.any():
            break
        sel = np.flatnonzero(split)
        t, use, Z, dev, new = _split(t, use, Z, dev, k[sel], tm[sel], Zm[sel])
        it += 1
        if two:  # the halves' tests, done: their deviations, then their splits
            halves = np.empty((len(new), 2), dtype=new.dtype)  # (n, 2) first points of both halves
            halves[:, 1] = new
            np.subtract(new, 1, out=halves[:, 0])
            dh = dq.take(sel, axis=0)[:, 1:]
            dev[halves.ravel()] = dh.ravel()
            split2 = dh > tols[fm[sel], None]
            if it == MAX_REFINE or not split2.any():
                break
            t, use, Z, dev, new = _split(t, use, Z, dev, halves[split2], tq.take(sel, axis=0)[:, 1:][split2],
                                         Zq.take(sel, axis=0)[:, 1:][split2])
            it += 1
        k = np.empty(2 * len(new), dtype=new.dtype)  # both halves of every segment split (sorted: the
        np.subtract(new, 1, out=k[0::2])  # midpoints inserted are two rows apart at least)
        k[1::2] = new
    return _real(Z), use, dev


def _complex(P: np.ndarray) -> np.ndarray:
    """``(k,)`` the points ``P (k, 2)`` as complex numbers ``x + iy`` (a view where ``P`` is
    contiguous): a point is gathered, scattered, added or subtracted as one item (a complex
    sum is the sums of the parts, to the last bit), not by numpy's iteration over rows of 2."""
    return np.ascontiguousarray(P).view(np.complex128)[:, 0]


def _real(Z: np.ndarray) -> np.ndarray:
    """``(k, 2)`` the points of contiguous complex ``Z`` (any shape, ``k`` items) as rows ``(x, y)`` (a view)."""
    return Z.view(np.float64).reshape(-1, 2)


def _split(t: np.ndarray, use: np.ndarray, Z: np.ndarray, dev: np.ndarray, k: np.ndarray,
           tm: np.ndarray, Zm: np.ndarray) -> tuple[np.ndarray, ...]:
    """Insert the midpoints ``tm (n,)``, ``Zm (n,)`` (complex points, :func:`_complex`) of the
    segments starting at ``k (n,)`` (sorted) into the samples ``t, use, Z, dev``; returns them
    and the midpoints' positions.

    One scatter per array (the old rows and the midpoints by their positions)."""
    n, m = len(t), len(k)
    at = k + np.arange(1, m + 1)
    old = np.ones(n + m, dtype=bool)
    old[at] = False
    old = old.nonzero()[0]  # the old rows' positions, found once for the four arrays
    t2, use2, dev2 = np.empty(n + m), np.empty(n + m, dtype=use.dtype), np.zeros(n + m)
    Z2 = np.empty(n + m, dtype=complex)
    t2[old], t2[at] = t, tm
    use2[old], use2[at] = use, use[k]
    Z2[old], Z2[at] = Z, Zm
    dev2[old] = dev
    return t2, use2, Z2, dev2, at


def _edge_curves(edges: Sequence[dict], path: str) -> list:
    """The 3D curve of every edge description (None for degenerate edges): lines and circles
    built together (:func:`~nagata_snap.cad.curves.analytic_curves`), B-splines together
    (:meth:`NurbsCurve.many <nagata_snap.cad.nurbs.NurbsCurve.many>`).

    Raises:
        ValueError: naming the first edge (in edge order) whose curve is invalid.
    """
    descs = [e["curve"] for e in edges]
    ana = [i for i, c in enumerate(descs) if c is not None and c["type"] in ("line", "circle")]
    out: list = [None] * len(descs)
    try:
        for i, c in zip(ana, analytic_curves([descs[i] for i in ana]), strict=True):
            out[i] = c
        spl = [i for i, c in enumerate(descs) if c is not None and out[i] is None]
        if spl:
            b = [descs[i] for i in spl]
            built = NurbsCurve.many([d["degree"] for d in b], [d["knots"] for d in b], [d["poles"] for d in b],
                                    [d.get("weights") for d in b])
            for i, c in zip(spl, built, strict=True):
                out[i] = c
    except (ValueError, NurbsError):  # the first invalid edge, built alone, names the error
        for i, c in enumerate(descs):  # loop over edges (error path)
            try:
                None if c is None else (analytic_curve(c) if i in ana else nurbs_curve(c))
            except (ValueError, NurbsError) as err:
                raise ValueError(f"{path}: edge {i} ({c['type']} curve): {err}") from None
        raise  # pragma: no cover - the batch failed, so one of them does
    return out


def _analytic_faces(faces: Sequence[dict]) -> dict[int, tuple[AnalyticSurface, np.ndarray | None]]:
    """:func:`_surface` of the analytic faces, by face index, their surfaces built together
    (:func:`~nagata_snap.cad.surfaces.analytic_surfaces`; the bounds of the recognised ones
    mapped together); empty if one of them is invalid (:func:`_surface` then names it, face
    by face)."""
    sel = [i for i, f in enumerate(faces) if f["surface"]["type"] in _SURFACES]
    try:
        box = np.array([faces[i]["uv"] for i in sel], dtype=float).reshape(-1, 2, 2)
        maps = [faces[i]["surface"].get("uv_map") for i in sel]
        rec = [j for j, M in enumerate(maps) if M is not None]
        if rec:
            M = np.array([maps[j] for j in rec], dtype=float).reshape(-1, 3, 2)
            _map_boxes(box, rec, M)
            for j, Mj in zip(rec, M, strict=True):  # loop over recognised faces (their maps)
                maps[j] = Mj
        built = analytic_surfaces([faces[i]["surface"] for i in sel], box)
    except (ValueError, TypeError, KeyError, IndexError):
        return {}
    return {i: (sf, M) for i, sf, M in zip(sel, built, maps, strict=True)}


def _map_boxes(box: np.ndarray, rows: Sequence[int], M: np.ndarray) -> None:
    """The images of the ``(u, v)`` boxes ``box[rows]`` (``(k, 2, 2)``) under their faces' maps
    ``(u', v') = [u, v, 1] M`` (``M (k, 3, 2)``): the boxes of their corners' images, in place."""
    b = box[rows]
    corners = np.ones((len(rows), 4, 3))
    corners[:, :, 0] = b[:, 0, [0, 0, 1, 1]]
    corners[:, :, 1] = b[:, 1, [0, 1, 0, 1]]
    img = np.matmul(corners, M)  # (k, 4, 2)
    box[rows] = np.stack([img.min(axis=1), img.max(axis=1)], axis=2)


def _surface(desc: dict, uv) -> tuple[AnalyticSurface | NurbsSurface, np.ndarray | None]:
    """The face's surface, and the map of the file's ``(u, v)`` to its parameters (or None).

    A face recognised as analytic (``desc["uv_map"]``, ``(3, 2)``: ``(u', v') = [u, v, 1] M``,
    from :mod:`~nagata_snap.cad.read`) gets the image of its ``(u, v)`` box as its bounds
    (:func:`_map_boxes`).
    """
    if desc["type"] == "bspline":
        return nurbs_surface(desc), None
    box = np.array([[uv[0], uv[1]], [uv[2], uv[3]]], dtype=float)
    M = desc.get("uv_map")
    if M is None:
        return analytic_surface(desc, box), None
    M = np.asarray(M, dtype=float).reshape(3, 2)
    boxes = box[None]
    _map_boxes(boxes, [0], M[None])
    return analytic_surface(desc, boxes[0]), M


@dataclass
class _Wires:
    """The edge uses of every face's wires, gathered (uses sorted by face, then wire).

    Attributes:
        descs: per use its p-curve description.
        face, wire, edge: ``(n,)`` face, wire and edge of each use.
        reverses: ``(n,)`` the use traverses its p-curve backwards.
        opposed: ``(n,)`` its p-curve is parametrised against the edge's 3D curve (a joined
            copy: :mod:`nagata_snap.cad.sewing`).
        seam: ``(n,)`` the use is on a seam (the face on both sides of its edge).
        wires: per wire ``(face, outer)``.
    """

    descs: list[dict]
    face: np.ndarray
    wire: np.ndarray
    edge: np.ndarray
    reverses: np.ndarray
    opposed: np.ndarray
    seam: np.ndarray
    wires: list[tuple[int, bool]]

    @classmethod
    def gather(cls, faces: Sequence[dict]) -> _Wires:
        """The uses of the wires of ``faces`` (``read_shape``'s face descriptions); empty wires skipped."""
        ws = [(i, w) for i, fd in enumerate(faces) for w in fd["wires"] if w["uses"]]
        uses = [u for _, w in ws for u in w["uses"]]  # (one pass per field: no append per use and field)
        wire = np.repeat(np.arange(len(ws), dtype=np.int64), [len(w["uses"]) for _, w in ws])
        return cls([u["pcurve"] for u in uses], np.array([i for i, _ in ws], dtype=np.int64)[wire], wire,
                   np.array([u["edge"] for u in uses], dtype=np.int64),
                   np.array([u["reversed"] for u in uses], dtype=bool),
                   np.array([u.get("opposed", False) for u in uses], dtype=bool),
                   np.array([u["seam"] for u in uses], dtype=bool), [(i, bool(w["outer"])) for i, w in ws])

    def face_edges(self, curved: np.ndarray, n_faces: int) -> tuple[list[np.ndarray], list[tuple[int, ...]]]:
        """Per face the sorted edges of its uses that are not on a seam and whose edge has a 3D
        curve (``curved (n_edges,)``; :attr:`Face.edges`), and per edge the sorted faces having
        it so (:attr:`Edge.faces`): of the uses' (face, edge) pairs, made unique at once."""
        ne = len(curved)
        keep = ~self.seam & curved[self.edge]
        f, e = np.divmod(np.unique(self.face[keep] * ne + self.edge[keep]), ne)  # by face, then edge
        per_face = np.split(e, np.searchsorted(f, np.arange(1, n_faces))) if n_faces else []
        by_edge = np.lexsort((f, e))
        ends = np.searchsorted(e[by_edge], np.arange(ne + 1)).tolist()
        users = f[by_edge].tolist()
        return per_face, [tuple(users[a:b]) for a, b in pairwise(ends)]

    @property
    def senses(self) -> np.ndarray:
        """``(n,)`` -1 where a use runs against its edge's 3D curve (it traverses its p-curve
        backwards, or its p-curve is parametrised against the curve), else +1."""
        return np.where(self.reverses ^ self.opposed, -1.0, 1.0)

    def loops(self, n_faces: int, polygons: list[tuple] | None = None) -> list[list[Loop]]:
        """Per face its :class:`Loop` objects, with their uses and, if given, per wire its
        polygon ``(points, edges, band, senses)``."""
        ends = np.searchsorted(self.wire, np.arange(len(self.wires) + 1)).tolist()
        senses = self.senses
        loops: list[list[Loop]] = [[] for _ in range(n_faces)]
        for w, (i, outer) in enumerate(self.wires):  # loop over wires (Loop objects)
            sl = slice(ends[w], ends[w + 1])
            P, E, band, S = (None, None, None, None) if polygons is None else polygons[w]
            loops[i].append(Loop(P, E, band, S, outer, self.edge[sl], senses[sl], self.descs[sl]))
        return loops


def _polygons(wires: _Wires, surfaces: Sequence, uv_maps: Sequence[np.ndarray | None],
              tolerances: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Closed polygons of all wires: their edge uses' p-curve samples, joined.

    All p-curves of all faces are sampled together (:func:`_refine`, to
    :data:`SAMPLE_RTOL` of each face's size).  Each segment's band is twice
    its deviation from the p-curve (length units) plus the edge's tolerance
    (``tolerances (n_edges,)``).  ``uv_maps``: per face ``(3, 2)`` map of the
    file's parameters to the surface's, or None.

    Returns:
        per wire ``(points (m, 2), edges (m,), band (m,), senses (m,))`` (:class:`Loop`).

    Raises:
        _FaceError: a p-curve that is not a valid B-spline, or a wire with
            fewer than 3 distinct finite points.
    """
    f = _PCurves(wires.descs, wires.face, uv_maps)
    fill_boxes(surfaces)  # the analytic faces' boxes, those of a kind together
    tols = SAMPLE_RTOL * np.array([s.bbox_size for s in surfaces])
    P, use, dev = _refine(f, f.initial(wires.descs), wires.reverses, surfaces, tols)
    keep = np.zeros(len(use), dtype=bool)  # a use's last point starts the next use
    keep[:-1] = use[1:] == use[:-1]
    P, use, dev = P[keep], use[keep], dev[keep]
    E = wires.edge[use]
    S = wires.senses[use]
    ends = np.searchsorted(wires.wire[use], np.arange(len(wires.wires) + 1))
    _check_wires(P, ends, [i for i, _ in wires.wires])
    band = 2.0 * dev + tolerances[E]
    return [(P[i:j], E[i:j], band[i:j], S[i:j]) for i, j in pairwise(ends.tolist())]


class _LazyLoops:
    """The polygons of a model's loops (:func:`_polygons`), sampled when one is first read.

    Args:
        loops: per face its loops (without polygons).
        wires: their uses.
        surfaces, uv_maps, tolerances: as :func:`_polygons`.
        path, faces: the file and its face descriptions (to name an invalid face).
    """

    def __init__(self, loops: list[list[Loop]], wires: _Wires, surfaces: Sequence,
                 uv_maps: Sequence[np.ndarray | None], tolerances: np.ndarray, path: str, faces: Sequence[dict]):
        self._loops = [lp for face in loops for lp in face]
        self._args = (wires, surfaces, uv_maps, tolerances)
        self._path, self._faces = path, faces
        for lp in self._loops:
            lp._sampler = self

    def fill(self) -> None:
        """Sample the polygons of all loops.

        Raises:
            ValueError: naming the face, as :meth:`CadModel.from_data` does.
        """
        try:
            polygons = _polygons(*self._args)
        except _FaceError as err:
            raise ValueError(_face_message(self._path, self._faces, err)) from None
        for lp, poly in zip(self._loops, polygons, strict=True):  # the loops in wire order
            lp._polygon, lp._sampler = poly, None


def _face_message(path: str, faces: Sequence[dict], err: _FaceError) -> str:
    """The message of a :class:`_FaceError`, naming the file, the face and its surface type."""
    return f"{path}: face {err.face} ({faces[err.face]['surface']['type']} surface): {err}"


def _check_wires(P: np.ndarray, ends: np.ndarray, face: Sequence[int]) -> None:
    """Every wire (rows ``ends[w]:ends[w + 1]`` of ``P (m, 2)``) has 3 distinct finite points.

    Points are compared rounded to 1e-12 of the wire's extent.  A quick sufficient test
    first (finite points, and three of each wire distinct: its first, and those a third and
    two thirds along it); the full test where that fails.

    Raises:
        _FaceError: naming the face (``face[w]``) of the first wire that has not.
    """
    if len(ends) < 2:
        return
    start = ends[:-1]
    if len(P) and np.isfinite(P).all():
        x, y = P[:, 0], P[:, 1]
        scale = np.maximum(np.maximum.reduceat(np.maximum(x, y), start) - np.minimum.reduceat(np.minimum(x, y), start),
                           1e-300)
        rows = start[:, None] + (np.diff(ends)[:, None] * np.arange(3)) // 3  # (w, 3)
        R = np.round(P[rows] / scale[:, None, None], 12)
        if ((R[:, 0] != R[:, 1]).any(axis=1) & (R[:, 0] != R[:, 2]).any(axis=1)
                & (R[:, 1] != R[:, 2]).any(axis=1)).all():
            return
    finite = np.isfinite(P).all(axis=1)
    ok = np.bincount(np.repeat(np.arange(len(start)), np.diff(ends))[~finite], minlength=len(start)) == 0
    if len(P):
        x, y = P[:, 0], P[:, 1]
        lo = np.minimum.reduceat(np.where(finite, np.minimum(x, y), np.inf), start)
        hi = np.maximum.reduceat(np.where(finite, np.maximum(x, y), -np.inf), start)
        scale = np.maximum(hi - lo, 1e-300)
        grp = np.repeat(np.arange(len(start)), np.diff(ends))
        with np.errstate(invalid="ignore"):
            ok &= _three_distinct_groups(np.round(P / scale[grp, None], 12), ends)
    if not ok.all():
        raise _FaceError(face[int(np.argmin(ok))], "a trimming wire has fewer than 3 distinct (finite) "
                                                   "points in the parameter plane")


def _three_distinct(R: np.ndarray) -> bool:
    """Rows of ``R (m, 2)`` take at least three distinct values (:func:`_three_distinct_groups`)."""
    return bool(_three_distinct_groups(np.asarray(R).reshape(-1, 2), np.array([0, len(R)]))[0])


def _three_distinct_groups(R: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """``(g,)``: the rows ``ends[i]:ends[i + 1]`` of ``R (m, 2)`` take at least three distinct values.

    No sort, two passes over all groups at once: the rows differing from
    the group's first row ``a``; the first of them ``b``; a third value is a
    row differing from both.
    """
    start, size = ends[:-1], np.diff(ends)
    ok = size >= 3
    if not ok.any():
        return ok
    grp = np.repeat(np.arange(len(size)), size)
    off_a = np.any(R[start[grp]] != R, axis=1)
    first_b = np.minimum.reduceat(np.where(off_a, np.arange(len(R)), len(R)), np.minimum(start, len(R) - 1))
    ok &= first_b < np.minimum(ends[1:], len(R))
    b = np.minimum(first_b, len(R) - 1)
    third = off_a & np.any(R[b[grp]] != R, axis=1)
    return ok & (np.bincount(grp[third], minlength=len(size)) > 0)


def _tangents(surface, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(S_u, S_v)``, each ``(3, k)`` by coordinate: the first derivatives at parameters
    ``params (k, 2)`` (wrapped/clamped for NURBS), from the surface's kernel as
    :func:`~nagata_snap.cad.projection.evaluate_params` evaluates them (a surface of
    revolution's without the terms of zero coefficients, :meth:`AnalyticSurface._tangents_soa
    <nagata_snap.cad.surfaces.AnalyticSurface._tangents_soa>`: the same lengths)."""
    from nagata_snap.cad.projection import normalize_params

    P = np.ascontiguousarray(normalize_params(surface, params).T)
    if isinstance(surface, AnalyticSurface) and not isinstance(surface, Plane):
        return surface._tangents_soa(P)
    D = surface._eval_soa(P, 1)
    return D[1], D[2]


def _planar_2d(surfaces: Sequence, size: float, rtol: float = 1e-9) -> bool:
    """Every surface is a plane in ``z = 0``: origin within ``rtol x size`` of it, normal
    within ``rtol`` of ``z`` (:meth:`CadModel.is_planar_2d`)."""
    tol = rtol * max(size, 1e-300)
    for s in surfaces:
        if getattr(s, "kind", "") != "plane" or abs(s.origin[2]) > tol or abs(abs(s.Z[2]) - 1.0) > rtol:
            return False
    return True


class CadModel:
    """Faces, edges and vertices of a CAD file (see the module docstring).

    Attributes:
        faces: list of :class:`Face`.
        edges: list of :class:`Edge`.
        vertices: ``(nv, 3)`` vertex points.
        vertex_tolerance: ``(nv,)`` OpenCASCADE's tolerance of each vertex (length units; 0
            where not known).
        path, format, unit, file_units: where it came from and its units
            (``unit``: of the coordinates here; ``file_units``: the file's own).
        size: diagonal of the shape's bounding box.
        times: seconds spent in OpenCASCADE (``read``, ``heal``, ``convert``)
            and here (``build``).
        num_solids: solids in the shape.
    """

    def __init__(self, faces, edges, vertices, *, path="", format="", unit="", file_units=(),
                 size=0.0, times=None, num_solids=0, healed=None, vertex_tolerance=None):
        self.faces = list(faces)
        self.edges = list(edges)
        self.vertices = np.asarray(vertices, dtype=float).reshape(-1, 3)
        self.vertex_tolerance = (np.zeros(len(self.vertices)) if vertex_tolerance is None
                                 else np.asarray(vertex_tolerance, dtype=float).reshape(len(self.vertices)))
        self.path, self.format, self.unit = path, format, unit
        self.file_units = list(file_units)
        self.size = float(size)
        self.times = dict(times or {})
        self.num_solids = int(num_solids)
        self.healed = dict(healed or {})
        #: the check of the faces against OpenCASCADE (:mod:`nagata_snap.cad.verify`), if done
        self.verification = None
        self._trim_loops = {}

    def trim_loops(self, rtol: float | None = None):
        """The faces' :class:`~nagata_snap.cad.trimming.TrimLoops` (built once per ``rtol``,
        default :data:`~nagata_snap.cad.trimming.TRIM_RTOL`), or None where no face is trimmed."""
        from nagata_snap.cad.trimming import TRIM_RTOL, TrimLoops

        rtol = TRIM_RTOL if rtol is None else float(rtol)
        if rtol not in self._trim_loops:
            loops = [[lp.points for lp in f.loops] for f in self.faces]
            bands = [[lp.band for lp in f.loops] for f in self.faces]
            self._trim_loops[rtol] = TrimLoops([f.surface for f in self.faces], loops, bands, rtol) \
                if any(loops) else None
        return self._trim_loops[rtol]

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
        edges = [Edge(curve, (int(e["vertices"][0]), int(e["vertices"][1])), (), float(e.get("tolerance", 0.0)),
                      int(e.get("source", i)))
                 for i, (e, curve) in enumerate(zip(data["edges"], _edge_curves(data["edges"], path), strict=True))]
        tol = np.array([e.tolerance for e in edges] + [0.0])
        fdata = data["faces"]
        surfaces, maps = [], []
        bad = None
        built = _analytic_faces(fdata)
        for i, f in enumerate(fdata):  # loop over faces (surfaces)
            try:
                surface, uv_map = built[i] if i in built else _surface(f["surface"], f["uv"])
            except (ValueError, NurbsError) as err:
                bad = _FaceError(i, str(err))
                break
            surfaces.append(surface)
            maps.append(uv_map)
        wires = _Wires.gather(fdata[:len(surfaces)])
        if bad is None and surfaces and _planar_2d(surfaces, float(data.get("size", 0.0))):
            # a 2D geometry snaps onto the edge curves: the polygons when first read
            loops = wires.loops(len(surfaces))
            _LazyLoops(loops, wires, surfaces, maps, tol, path, fdata)
        else:
            try:  # the loops of the faces before a bad surface: their errors come first
                loops = wires.loops(len(surfaces), _polygons(wires, surfaces, maps, tol))
                if bad is not None:
                    raise bad
            except _FaceError as err:
                raise ValueError(_face_message(path, fdata, err)) from None
        own, users = wires.face_edges(np.array([e.curve is not None for e in edges], dtype=bool), len(fdata))
        faces = []
        for f, surface, uv_map, lp, fe in zip(fdata, surfaces, maps, loops, own, strict=True):
            # a map that flips the parameter plane (negative determinant) flips S_u x S_v
            flip = uv_map is not None and bool(uv_map[0, 0] * uv_map[1, 1] < uv_map[0, 1] * uv_map[1, 0])
            faces.append(Face(surface, lp, bool(f["reversed"]) != flip, bool(f["converted"]), fe,
                              tuple(f.get("solids", ())), uv_map))
        for e, u in zip(edges, users, strict=True):
            e.faces = u
        times = dict(data.get("times", {}))
        times["build"] = time.perf_counter() - t0
        model = cls(faces, edges, data["vertices"], path=path, format=data.get("format", ""),
                    unit=data.get("unit", ""), file_units=data.get("file_units", ()),
                    size=data.get("size", 0.0), times=times,
                    num_solids=data.get("num_solids", 0), healed=data.get("healed"),
                    vertex_tolerance=data.get("vertex_tolerance"))
        model.verification = data.get("verification")
        return model

    def curve_edges(self) -> np.ndarray:
        """Indices of the edges with a 3D curve (not degenerate)."""
        return np.array([i for i, e in enumerate(self.edges) if e.curve is not None], dtype=np.int64)

    def is_planar_2d(self, rtol: float = 1e-9) -> bool:
        """All faces are planes in ``z = 0`` (a profile for 2D meshes), or there are no faces."""
        if not self.faces:
            return len(self.curve_edges()) > 0
        return _planar_2d([f.surface for f in self.faces], self.size, rtol)

    def summary(self) -> str:
        kinds: dict[str, int] = {}
        for f in self.faces:
            k = getattr(f.surface, "kind", "nurbs")
            k = "nurbs" if isinstance(f.surface, NurbsSurface) else k
            kinds[k] = kinds.get(k, 0) + 1
        what = ", ".join(f"{n} {k}" for k, n in sorted(kinds.items()))
        free = sum(not f.solids for f in self.faces) if self.num_solids else 0
        return (f"{len(self.faces)} faces ({what}{f'; {free} on no solid' if free else ''}), "
                f"{len(self.curve_edges())} edges, {len(self.vertices)} vertices, {self.num_solids} solids, "
                f"unit {self.unit}{self._verified()}")

    def _verified(self) -> str:
        """The summary's words on the verification (:mod:`nagata_snap.cad.verify`)."""
        v = self.verification
        if v is None:
            return "; faces not verified against OpenCASCADE"
        fb = v["fell_back"]
        how = ", ".join(f"{n} to {k}" for k, n in sorted(v["fallbacks"].items()) if n)
        return (f"; faces verified against OpenCASCADE: {v['verified']} passed, {fb} fell back"
                f"{f' ({how})' if how else ''}, {v['failed']} failed")

    def __repr__(self) -> str:
        return f"CadModel({self.path!r}: {self.summary()})"
