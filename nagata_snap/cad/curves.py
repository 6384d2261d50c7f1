"""Analytic curves of CAD edges: line segments and circular arcs.

With OpenCASCADE's parametrisation (``ElCLib``): a line ``C(t) = O + t D``
(``D`` unit, ``t`` arc length) and a circle ``C(t) = c + R (cos t X + sin t
Y)``, both on the edge's range ``[t0, t1]``.  The closest point of the
*bounded* curve is found in closed form and vectorised: ``t = (P - O).D``
clamped to the range; ``t = atan2((P - c).Y, (P - c).X)`` wrapped into
``[t0, t0 + 2 pi)``, and outside a partial arc the nearer end.  A point on
the circle's axis takes the seed (every point of the circle is equally near).

Both classes follow the curve protocol of :class:`nagata_snap.cad.nurbs.NurbsCurve`
(``param_dim = 1``, ``bounds``, ``closed``, ``bbox``, ``bbox_size``,
``distinct_knots``, ``_eval_soa``, ``_evaluate_inside``), so they can be the
entities of a 2D :class:`~nagata_snap.cad.CadGeometry` (a profile's edges) as
well as the edges of a 3D one.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["Line", "Circle", "analytic_curve"]

TWO_PI = 2.0 * np.pi


def _vec(a, n: int, what: str) -> np.ndarray:
    v = np.zeros(3)
    a = np.asarray(a, dtype=float).reshape(-1)
    if a.size not in (n, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be a finite {n}- or 3-vector, got {a.tolist()}")
    v[: a.size] = a
    return v


class _Curve:
    param_dim = 1
    kind = "curve"
    #: the tangent of a line or circle never vanishes
    can_degenerate = False

    def __init__(self, t0: float, t1: float):
        t0, t1 = float(t0), float(t1)
        if not (np.isfinite(t0) and np.isfinite(t1) and t1 > t0):
            raise ValueError(f"curve range must be finite with t0 < t1, got ({t0}, {t1})")
        self.bounds = np.array([[t0, t1]])
        self.limits = self.bounds
        lo, hi = self._box(t0, t1)
        self.bbox = (lo, hi)
        self.bbox_size = float(np.linalg.norm(hi - lo))

    def _box(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` box of the curve on ``[t0, t1]``: 65 samples plus their sagitta."""
        pts = self._points(np.linspace(t0, t1, 65))
        pad = self._sagitta((t1 - t0) / 64)
        return pts.min(axis=0) - pad, pts.max(axis=0) + pad

    closed = (False,)

    def _sagitta(self, dt: float) -> float:
        return 0.0

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

    def __init__(self, origin, direction, t0: float, t1: float):
        self.origin = _vec(origin, 2, "line origin")
        d = _vec(direction, 2, "line direction")
        n = np.linalg.norm(d)
        if n == 0:
            raise ValueError("line direction must be non-zero")
        self.direction = d / n
        super().__init__(t0, t1)

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

    def _box(self, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The box of the two end points (exact: the segment is linear in ``t``)."""
        pts = self._points(np.array([t0, t1]))
        return pts.min(axis=0), pts.max(axis=0)


class Circle(_Curve):
    """``C(t) = c + R (cos t X + sin t Y)`` on ``[t0, t1]`` (a full circle if ``t1 - t0 = 2 pi``)."""

    kind = "circle"

    def __init__(self, center, x, y, radius: float, t0: float, t1: float):
        self.center = _vec(center, 2, "circle centre")
        X, Y = _vec(x, 2, "circle x direction"), _vec(y, 2, "circle y direction")
        self.X, self.Y = X / np.linalg.norm(X), Y / np.linalg.norm(Y)
        self.radius = float(radius)
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"circle radius must be positive, got {radius}")
        if t1 - t0 > TWO_PI * (1 + 1e-12):
            raise ValueError(f"circle range longer than 2 pi: ({t0}, {t1})")
        self.closed = (bool(abs((t1 - t0) - TWO_PI) <= 1e-12 * TWO_PI),)
        super().__init__(t0, t1)

    def _sagitta(self, dt):
        return self.radius * (1 - np.cos(dt / 2))

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
        q = X - self.center
        x, y = q @ self.X, q @ self.Y
        t0, t1 = self.bounds[0]
        t = t0 + np.mod(np.arctan2(y, x) - t0, TWO_PI)
        t = np.where(np.hypot(x, y) <= 1e-300, seed, t)
        if not self.closed[0]:
            out = t > t1  # beyond the arc: the nearer end
            if out.any():
                e0, e1 = self._points(np.array([t0, t1]))
                d0 = np.linalg.norm(X[out] - e0, axis=1)
                d1 = np.linalg.norm(X[out] - e1, axis=1)
                t[out] = np.where(d0 < d1, t0, t1)
            t = np.clip(t, t0, t1)
        return t


def analytic_curve(desc: dict):
    """A :class:`Line` or :class:`Circle` from an edge description of :func:`~nagata_snap.cad.read.read_shape`."""
    t0, t1 = desc["range"]
    if desc["type"] == "line":
        return Line(desc["origin"], desc["direction"], t0, t1)
    if desc["type"] == "circle":
        return Circle(desc["center"], desc["x"], desc["y"], desc["radius"], t0, t1)
    raise ValueError(f"not an analytic curve type: {desc['type']!r}")
