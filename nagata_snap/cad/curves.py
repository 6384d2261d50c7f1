"""Analytic curves of CAD edges: line segments and circular arcs.

With OpenCASCADE's parametrisation (``ElCLib``): a line ``C(t) = O + t D``
(``D`` unit, ``t`` arc length) and a circle ``C(t) = c + R (cos t X + sin t
Y)``, both on the edge's range ``[t0, t1]``.  The closest point of the
*bounded* curve is found in closed form and vectorised: ``t = (P - O).D``
clamped to the range; ``t = atan2((P - c).Y, (P - c).X)`` wrapped into
``[t0, t0 + 2 pi)``, and outside a partial arc the nearer end.  A point on
the circle's axis takes the seed (every point of the circle is equally near).

Many curves of a kind are built at once (:meth:`Line.many`, :meth:`Circle.many`,
:func:`analytic_curves`: the checks, unit directions and bounding boxes
vectorised over the curves, as a file's edges are); one curve is a batch of
one.

Both classes follow the curve protocol of :class:`nagata_snap.cad.nurbs.NurbsCurve`
(``param_dim = 1``, ``bounds``, ``closed``, ``bbox``, ``bbox_size``,
``distinct_knots``, ``_eval_soa``, ``_evaluate_inside``), so they can be the
entities of a 2D :class:`~nagata_snap.cad.CadGeometry` (a profile's edges) as
well as the edges of a 3D one.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from nagata_snap.mesh.arrays import float_array, linspaces, norms

__all__ = ["Line", "Circle", "ArcBatch", "analytic_curve", "analytic_curves"]

TWO_PI = 2.0 * np.pi
#: samples of the curve's range whose box (plus their sagitta) is a circle's bounding box
BOX_SAMPLES = 65


def _vecs(a, n: int, what: str) -> np.ndarray:
    """``(k, 3)`` from ``k`` finite ``n``- or 3-vectors (``(k, n)`` or ``(k, 3)``; z = 0 for ``n = 2``)."""
    a = np.asarray(a, dtype=float)
    a = a.reshape(len(a), -1)
    if a.shape[1] not in (n, 3) or not np.isfinite(a).all():
        bad = a[np.flatnonzero(~np.isfinite(a).all(axis=1))[0]] if a.shape[1] in (n, 3) else a[0]
        raise ValueError(f"{what} must be a finite {n}- or 3-vector, got {bad.tolist()}")
    if a.shape[1] == 3:
        return a
    v = np.zeros((len(a), 3))
    v[:, :n] = a
    return v


def _fields(values: tuple, n: int, whats: tuple[str, ...]) -> np.ndarray:
    """``(f, k, 3)``: ``f`` fields of ``k`` curves, each ``k`` ``n``- or 3-vectors, as :func:`_vecs`
    gives them: converted and checked together where they all are finite 3-vectors, else field
    by field (:func:`_vecs`, raising its error for the first invalid field, ``whats`` naming it)."""
    V = float_array(values)
    if V is None or V.ndim != 3 or V.shape[2] != 3 or not np.isfinite(V).all():
        V = np.array([_vecs(a, n, what) for a, what in zip(values, whats, strict=True)])
    return V


class _Curve:
    param_dim = 1
    kind = "curve"
    #: the tangent of a line or circle never vanishes
    can_degenerate = False
    bounds: np.ndarray
    limits: np.ndarray
    #: ``(lo, hi)`` bounding box of the curve on its range, and its diagonal
    bbox: tuple[np.ndarray, np.ndarray]
    bbox_size: float

    @staticmethod
    def _ranges(t0: npt.ArrayLike, t1: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """``(t0 (k,), t1 (k,))``: the ranges of ``k`` curves, checked."""
        t0, t1 = np.asarray(t0, dtype=float).reshape(-1), np.asarray(t1, dtype=float).reshape(-1)
        ok = np.isfinite(t0) & np.isfinite(t1) & (t1 > t0)
        if not ok.all():
            i = np.argmin(ok)
            raise ValueError(f"curve range must be finite with t0 < t1, got ({t0[i]}, {t1[i]})")
        return t0, t1

    @classmethod
    def _make(cls, t0: np.ndarray, t1: np.ndarray, lo: np.ndarray, hi: np.ndarray, **fields: Any) -> list:
        """``k`` curves of class ``cls``: ranges ``t0, t1 (k,)`` (checked, :meth:`_ranges`), boxes
        ``lo, hi (k, 3)`` (and their diagonals), and the per-curve values of ``fields``."""
        bounds = np.empty((len(t0), 1, 2))
        bounds[:, 0, 0], bounds[:, 0, 1] = t0, t1
        keys = ("bounds", "bbox", "bbox_size", *fields)
        curves = [cls.__new__(cls) for _ in range(len(t0))]
        for c, *row in zip(curves, bounds, zip(lo, hi, strict=True), norms(hi - lo).tolist(), *fields.values(),
                           strict=True):  # loop over curves (their attributes, one row each)
            d = c.__dict__
            d.update(zip(keys, row, strict=True))
            d["limits"] = row[0]
        return curves

    def _copy_from(self, other: _Curve) -> None:
        """``__init__`` of one curve: the attributes of the batch of one that built it."""
        self.__dict__.update(other.__dict__)

    closed = (False,)

    @property
    def distinct_knots(self) -> np.ndarray:
        """Breakpoints of the search samples (a curve of this kind has no knots)."""
        t0, t1 = self.bounds[0]
        return np.linspace(t0, t1, self._pieces() + 1)

    def _pieces(self) -> int:
        return 1

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        """``params (1, k)`` -> ``(nderiv + 1, 3, k)``: ``C, C', C''``."""
        raise NotImplementedError  # pragma: no cover - abstract

    def _closest_t(self, X: np.ndarray, seed: np.ndarray) -> np.ndarray:
        """``(k,)`` parameters of the closest points of ``X (k, 3)`` (``seed`` where free)."""
        raise NotImplementedError  # pragma: no cover - abstract

    def _points(self, t: np.ndarray) -> np.ndarray:
        return self._eval_soa(np.asarray(t, dtype=float)[None, :], 0)[0].T

    def _evaluate_inside(self, t: np.ndarray, nderiv: int) -> np.ndarray:
        """``(nderiv + 1, k, 3)``: ``C, C', C''``."""
        return self._eval_soa(t[None, :], nderiv).transpose(0, 2, 1)

    def evaluate(self, t: npt.ArrayLike, nderiv: int = 0) -> np.ndarray:
        """Points and derivatives at ``t (k,)`` (not clamped), ``(nderiv + 1, k, 3)``."""
        return self._evaluate_inside(np.atleast_1d(np.asarray(t, dtype=float)), int(nderiv))

    def closest(self, points: npt.ArrayLike, seeds: npt.ArrayLike | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points on the bounded curve: ``(t (k, 1), points (k, 3), distances (k,))``."""
        X = np.asarray(points, dtype=float).reshape(-1, 3)
        seed = (np.full(len(X), self.bounds[0, 0]) if seeds is None
                else np.asarray(seeds, dtype=float).reshape(len(X)))
        seed = np.where(np.isfinite(seed), seed, self.bounds[0, 0])
        t = self._closest_t(X, seed)
        C = self._points(t)
        return t[:, None], C, np.linalg.norm(C - X, axis=1)

    def tangents(self, t: npt.ArrayLike) -> np.ndarray:
        """``(k, 3)`` unit tangents ``C'/|C'|``."""
        T = self._eval_soa(np.asarray(t, dtype=float).reshape(1, -1), 1)[1].T
        return T / np.linalg.norm(T, axis=1, keepdims=True)


class Line(_Curve):
    """``C(t) = O + t D`` on ``[t0, t1]``."""

    kind = "line"
    origin: np.ndarray
    direction: np.ndarray

    def __init__(self, origin, direction, t0: float, t1: float):
        self._copy_from(Line.many([origin], [direction], [t0], [t1])[0])

    @classmethod
    def many(cls, origins: npt.ArrayLike, directions: npt.ArrayLike, t0: npt.ArrayLike,
             t1: npt.ArrayLike) -> list[Line]:
        """``k`` lines from ``origins, directions (k, 2|3)`` (directions are normalised) and
        ranges ``t0, t1 (k,)``; their boxes are their end points' (exact: linear in ``t``)."""
        O, D = _fields((origins, directions), 2, ("line origin", "line direction"))
        n = norms(D)
        if not n.all():
            raise ValueError("line direction must be non-zero")
        D = D / n[:, None]
        t0, t1 = cls._ranges(t0, t1)
        a, b = O + D * t0[:, None], O + D * t1[:, None]
        return cls._make(t0, t1, np.minimum(a, b), np.maximum(a, b), origin=O, direction=D)

    @property
    def affine(self) -> tuple[np.ndarray, np.ndarray]:
        """``(origin (3,), axes (1, 3))``: ``C = origin + t direction``, as
        :attr:`nagata_snap.cad.surfaces.Plane.affine`."""
        return self.origin, self.direction[None, :]

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        t = params[0]
        out = np.zeros((nderiv + 1, 3, t.shape[0]))
        out[0] = self.origin[:, None] + self.direction[:, None] * t
        if nderiv >= 1:
            out[1] = self.direction[:, None]
        return out

    def _closest_t(self, X, seed):
        return np.clip((X - self.origin) @ self.direction, *self.bounds[0])


class Circle(_Curve):
    """``C(t) = c + R (cos t X + sin t Y)`` on ``[t0, t1]`` (a full circle if ``t1 - t0 = 2 pi``)."""

    kind = "circle"
    center: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    radius: float

    def __init__(self, center, x, y, radius: float, t0: float, t1: float):
        self._copy_from(Circle.many([center], [x], [y], [radius], [t0], [t1])[0])

    @classmethod
    def many(cls, centers: npt.ArrayLike, xs: npt.ArrayLike, ys: npt.ArrayLike, radii: npt.ArrayLike,
             t0: npt.ArrayLike, t1: npt.ArrayLike) -> list[Circle]:
        """``k`` circles from ``centers, xs, ys (k, 2|3)`` (``xs, ys`` are normalised), ``radii (k,)``
        and ranges ``t0, t1 (k,)``.  Box: :data:`BOX_SAMPLES` points on the range, widened by the
        sagitta ``R (1 - cos(dt / 2))`` of their spacing ``dt``."""
        V = _fields((centers, xs, ys), 2, ("circle centre", "circle x direction", "circle y direction"))
        C, (X, Y) = V[0], V[1:] / norms(V[1:])[..., None]
        R = np.asarray(radii, dtype=float).reshape(-1)
        ok = np.isfinite(R) & (R > 0)
        if not ok.all():
            raise ValueError(f"circle radius must be positive, got {np.reshape(radii, -1)[np.argmin(ok)]}")
        a, b = np.asarray(t0, dtype=float).reshape(-1), np.asarray(t1, dtype=float).reshape(-1)
        dt = b - a
        long = dt > TWO_PI * (1 + 1e-12)
        if long.any():
            i = np.argmax(long)
            raise ValueError(f"circle range longer than 2 pi: ({a[i]}, {b[i]})")
        full = np.abs(dt - TWO_PI) <= 1e-12 * TWO_PI
        t0, t1 = cls._ranges(a, b)
        t = linspaces(t0, t1, BOX_SAMPLES)  # (k, s)
        # (3, k, s): the samples' coordinates, each along the last (contiguous) axis
        P = C.T[:, :, None] + R[:, None] * (X.T[:, :, None] * np.cos(t) + Y.T[:, :, None] * np.sin(t))
        pad = R * (1 - np.cos(dt / (BOX_SAMPLES - 1) / 2))
        return cls._make(t0, t1, P.min(axis=2).T - pad[:, None], P.max(axis=2).T + pad[:, None], center=C, X=X, Y=Y,
                         radius=R.tolist(), closed=[(f,) for f in full.tolist()])

    def _pieces(self) -> int:
        return max(1, int(np.ceil((self.bounds[0, 1] - self.bounds[0, 0]) / (np.pi / 4))))

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        t = params[0]
        c, s = np.cos(t), np.sin(t)
        R = self.radius
        out = np.empty((nderiv + 1, 3, t.shape[0]))
        out[0] = self.center[:, None] + R * (self.X[:, None] * c + self.Y[:, None] * s)
        if nderiv >= 1:
            out[1] = R * (-self.X[:, None] * s + self.Y[:, None] * c)
        if nderiv >= 2:
            out[2] = -R * (self.X[:, None] * c + self.Y[:, None] * s)
        return out

    def _closest_t(self, X, seed):
        t0, t1 = self.bounds[0]
        return _arc_params(X, self.center, self.X, self.Y, self.radius, t0, t1, np.array(self.closed[0]), seed)


def _arc_points(center: np.ndarray, x: np.ndarray, y: np.ndarray, R, t: np.ndarray) -> np.ndarray:
    """``(k, 3)`` points ``c + R (cos t X + sin t Y)`` of circles given per row (``center, x, y
    (k, 3)``, ``R (k, 1)``) or one circle (``(3,)``, a float), at ``t (k,)``: the operations of
    :meth:`Circle._eval_soa`, so the same bits."""
    return center + R * (x * np.cos(t)[:, None] + y * np.sin(t)[:, None])


def _arc_params(X: np.ndarray, center: np.ndarray, x: np.ndarray, y: np.ndarray, R, t0, t1,
                closed: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """``(k,)`` parameters of the closest points of ``X (k, 3)`` on circular arcs given per row
    (``center, x, y (k, 3)``, ``R (k, 1)``, ranges ``t0, t1 (k,)``, ``closed (k,)``) or one arc
    (the same as scalars and ``(3,)`` vectors): ``atan2`` of the point's coordinates in the
    arc's plane, wrapped into ``[t0, t0 + 2 pi)``; beyond a partial arc its nearer end; on the
    axis ``seed (k,)``.  The coordinates are sums of products, row by row (one arc or many:
    the same bits)."""
    q = X - center
    qx = q[:, 0] * x[..., 0] + q[:, 1] * x[..., 1] + q[:, 2] * x[..., 2]
    qy = q[:, 0] * y[..., 0] + q[:, 1] * y[..., 1] + q[:, 2] * y[..., 2]
    t = t0 + np.mod(np.arctan2(qy, qx) - t0, TWO_PI)
    t = np.where(np.hypot(qx, qy) <= 1e-300, seed, t)
    out = np.flatnonzero(~closed & (t > t1))  # beyond the arc: the nearer end
    if out.size:
        def row(a):
            return a[out] if np.ndim(a) == 2 else a
        Ro = R[out] if np.ndim(R) == 2 else R
        lo, hi = np.broadcast_to(t0, t.shape)[out], np.broadcast_to(t1, t.shape)[out]
        d0 = np.linalg.norm(X[out] - _arc_points(row(center), row(x), row(y), Ro, lo), axis=1)
        d1 = np.linalg.norm(X[out] - _arc_points(row(center), row(x), row(y), Ro, hi), axis=1)
        t[out] = np.where(d0 < d1, lo, hi)
    return np.where(closed, t, np.clip(t, t0, t1))


class ArcBatch:
    """Closest points on many circles at once (:class:`Circle` entities of a geometry): their
    centres, axes, radii and ranges stacked once, so one call serves the points of every arc
    (the same results as each arc's :meth:`Circle.closest`, to the bit).

    Args:
        entities: all entities of a geometry (those that are not circles are not used).
    """

    def __init__(self, entities) -> None:
        sel = [i for i, e in enumerate(entities) if type(e) is Circle]
        n = len(entities)
        self.has = np.zeros(n, dtype=bool)
        self.has[sel] = True
        self.center, self.x, self.y = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        self.radius, self.t0, self.t1 = np.ones((n, 1)), np.zeros(n), np.ones(n)
        self.closed = np.zeros(n, dtype=bool)
        for i in sel:  # loop over the circles (their attributes, once)
            c = entities[i]
            self.center[i], self.x[i], self.y[i], self.radius[i] = c.center, c.X, c.Y, c.radius
            self.t0[i], self.t1[i] = c.bounds[0]
            self.closed[i] = c.closed[0]

    def closest(self, ent: np.ndarray, X: np.ndarray, seeds: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(params (n, 1), foot points (n, 3), distances (n,))`` of ``X (n, 3)`` on the circles
        ``ent (n,)`` (``seeds (n,)``: the parameter of a point on an arc's axis; NaN: its start)."""
        t0 = self.t0[ent]
        seed = np.where(np.isfinite(seeds), seeds, t0)
        c, x, y, R = self.center[ent], self.x[ent], self.y[ent], self.radius[ent]
        t = _arc_params(X, c, x, y, R, t0, self.t1[ent], self.closed[ent], seed)
        C = _arc_points(c, x, y, R, t)
        return t[:, None], C, np.linalg.norm(C - X, axis=1)


def analytic_curve(desc: dict):
    """A :class:`Line` or :class:`Circle` from an edge description of :func:`~nagata_snap.cad.read.read_shape`."""
    if desc["type"] not in ("line", "circle"):
        raise ValueError(f"not an analytic curve type: {desc['type']!r}")
    return analytic_curves([desc])[0]


#: description fields of the analytic curves, in the order of the ``many`` constructors
_FIELDS: dict[str, tuple[Any, tuple[str, ...]]] = {
    "line": (Line, ("origin", "direction")), "circle": (Circle, ("center", "x", "y", "radius"))}


def analytic_curves(descs: list[dict]) -> list:
    """:func:`analytic_curve` of every description of ``descs`` (lines and circles only), the
    curves of a kind built together (:meth:`Line.many`, :meth:`Circle.many`).

    Raises:
        ValueError: an invalid description (the message is :func:`analytic_curve`'s on it;
            with several invalid ones, the first of a kind).
    """
    out: list = [None] * len(descs)
    for kind, (cls, names) in _FIELDS.items():
        sel = [i for i, d in enumerate(descs) if d["type"] == kind]
        if not sel:
            continue
        cols = [[descs[i][name] for i in sel] for name in names]
        rng = np.array([descs[i]["range"] for i in sel], dtype=float).reshape(-1, 2)
        for i, c in zip(sel, cls.many(*cols, rng[:, 0], rng[:, 1]), strict=True):
            out[i] = c
    return out
