"""Analytic surfaces of CAD faces (plane, cylinder, cone, sphere, torus).

Each class evaluates the surface with OpenCASCADE's own parametrisation
(``ElSLib``: the same ``(u, v)`` as the file's p-curves and as gmsh's node
parameters) from the face's placement ``(origin O, X, Y, Z)``, where
``e(u) = cos u X + sin u Y``:

* plane:    ``S = O + u X + v Y``
* cylinder: ``S = O + R e(u) + v Z``
* cone:     ``S = O + (R + v sin a) e(u) + v cos a Z`` (semi-angle ``a``)
* sphere:   ``S = O + R cos v e(u) + R sin v Z``
* torus:    ``S = O + (R + r cos v) e(u) + r sin v Z``

and finds closest points in closed form, vectorised over points and exact to
round-off: with ``q = P - O``, ``x = q.X``, ``y = q.Y``, ``z = q.Z`` and
``rho = hypot(x, y)``, the foot point of a surface of revolution lies in the
meridian half-plane ``u = atan2(y, x)``; there the plane and cylinder are
lines (``v = x, y`` / ``v = z``), the sphere and torus circles
(``v = atan2(z, rho)`` / ``atan2(z, rho - R)``) and the cone the generator
``(R + v sin a, v cos a)`` (``v = (rho - R) sin a + z cos a``).  The cone is
restricted to the nappe of its face (the apex closes it: a point beyond the
apex goes to the apex, or to the generator of the opposite half-plane ``u +
pi`` if that is nearer).  Where a parameter is not determined by the point
(``u`` on the axis, at the poles of a sphere and at the apex; ``v`` at the
centre of a torus tube) it is taken from the seed, so that parametric
midpoints of facets at poles stay sensible.

The classes follow the entity protocol of :mod:`nagata_snap.cad.nurbs`
(``param_dim``, ``bounds``, ``closed``, ``bbox``, ``bbox_size``,
``distinct_knots_u/v``, ``_eval_soa``, ``_evaluate_inside``), so that the
Newton projection and the search grid of :mod:`nagata_snap.cad.projection`
work on them too, and add :meth:`AnalyticSurface.closest` and exact unit
normals.  ``bounds`` is the face's ``(u, v)`` box (where search samples are
taken); evaluation is not clamped to it: the surface extends beyond its face.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["AnalyticSurface", "Plane", "Cylinder", "Cone", "Sphere", "Torus", "analytic_surface"]

TWO_PI = 2.0 * np.pi


def _positive(value, what: str) -> float:
    v = float(value)
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be positive, got {value}")
    return v


def _unit(v: npt.ArrayLike, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(3)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"{what} must be a finite non-zero vector, got {a.tolist()}")
    return a / n


class AnalyticSurface:
    """Common part of the analytic surfaces: frame, bounds, periods, evaluation.

    Args:
        origin, x, y, z: the placement (``gp_Ax3``: origin and the three
            directions; ``y`` need not be ``z x x``: left-handed frames are kept).
        bounds: ``(2, 2)`` face parameter box ``[[u0, u1], [v0, v1]]``.
    """

    param_dim = 2
    kind = "analytic"
    #: hard parameter limits (``normalize_params`` clamps there), ``(2, 2)``
    limits = np.array([[-np.inf, np.inf], [-np.inf, np.inf]])

    def __init__(self, origin, x, y, z, bounds):
        self.origin = np.asarray(origin, dtype=float).reshape(3)
        self.X, self.Y, self.Z = _unit(x, "x"), _unit(y, "y"), _unit(z, "z")
        if not np.all(np.isfinite(self.origin)):
            raise ValueError(f"origin must be finite, got {self.origin.tolist()}")
        #: +1 for a right-handed frame, -1 for a left-handed one
        self.hand = 1.0 if np.dot(np.cross(self.X, self.Y), self.Z) > 0 else -1.0
        b = np.asarray(bounds, dtype=float).reshape(2, 2)
        if not np.all(np.isfinite(b)) or np.any(b[:, 1] < b[:, 0]):
            raise ValueError(f"bounds must be finite [[u0, u1], [v0, v1]], got {b.tolist()}")
        self.bounds = b
        self._frame = np.stack([self.X, self.Y, self.Z])  # (3, 3) rows X, Y, Z
        self._box = None

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` box of the face's parameter box (grid samples plus their sagitta)."""
        if self._box is None:
            self._box = self._sample_box()
        return self._box

    @property
    def bbox_size(self) -> float:
        """Diagonal of :attr:`bbox` (length units)."""
        lo, hi = self.bbox
        return float(np.linalg.norm(hi - lo))

    # -- protocol ------------------------------------------------------
    closed = (False, False)

    @property
    def periods(self) -> np.ndarray:
        """``(2,)`` period per direction (NaN where open)."""
        return np.array([TWO_PI if c else np.nan for c in self.closed])

    @property
    def distinct_knots_u(self) -> np.ndarray:
        """Breakpoints of the search grid in ``u`` (the analytic surface has no knots)."""
        return self._breaks(0)

    @property
    def distinct_knots_v(self) -> np.ndarray:
        """Breakpoints of the search grid in ``v``."""
        return self._breaks(1)

    def _breaks(self, a: int) -> np.ndarray:
        lo, hi = self.bounds[a]
        n = 1 if not self._curved[a] else max(1, int(np.ceil((hi - lo) / (np.pi / 4))))
        return np.linspace(lo, hi, n + 1)

    _curved = (False, False)

    def _sample_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box of the face's parameter box (grid samples plus their sagitta)."""
        u = np.linspace(*self.bounds[0], 17)
        v = np.linspace(*self.bounds[1], 17)
        uu, vv = np.meshgrid(u, v, indexing="ij")
        S = self._points(uu.ravel(), vv.ravel())
        pad = self._sagitta(u[1] - u[0], v[1] - v[0])
        return S.min(axis=0) - pad, S.max(axis=0) + pad

    def _sagitta(self, du: float, dv: float) -> float:
        return 0.0

    def _evaluate_inside(self, u: np.ndarray, v: np.ndarray, nderiv: int) -> np.ndarray:
        """``(1|3|6, k, 3)``: ``S, Su, Sv, Suu, Suv, Svv`` (as :class:`NurbsSurface`)."""
        return self._eval_soa(np.stack([u, v]), nderiv).transpose(0, 2, 1)

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        """``params (2, k)`` -> ``(1|3|6, 3, k)`` in the global frame."""
        u, v = params[0], params[1]
        c, s = np.cos(u), np.sin(u)
        local = self._local(u, v, c, s, nderiv)  # (nd, 3, k) in the (e, e', Z) basis
        # e = c X + s Y, e' = -s X + c Y
        E = c[None, :, None] * self.X + s[None, :, None] * self.Y  # (1, k, 3)
        Ep = -s[None, :, None] * self.X + c[None, :, None] * self.Y
        out = local[:, 0, :, None] * E + local[:, 1, :, None] * Ep + local[:, 2, :, None] * self.Z
        out[0] += self.origin
        return out.transpose(0, 2, 1)

    def _points(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self._eval_soa(np.stack([u, v]), 0)[0].T

    def evaluate(self, u: npt.ArrayLike, v: npt.ArrayLike, nderiv: int = 0) -> np.ndarray:
        """Points and derivatives, ``(1|3|6, k, 3)`` (no clamping: the surface is unbounded)."""
        u = np.atleast_1d(np.asarray(u, dtype=float))
        v = np.atleast_1d(np.asarray(v, dtype=float))
        return self._evaluate_inside(u, v, int(nderiv))

    def _local(self, u, v, c, s, nderiv):  # pragma: no cover - abstract
        raise NotImplementedError

    def _coords(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.asarray(points, dtype=float) - self.origin
        loc = q @ self._frame.T
        return loc[:, 0], loc[:, 1], loc[:, 2]

    def _angle(self, x: np.ndarray, y: np.ndarray, rho: np.ndarray, seed: np.ndarray,
               tiny: float) -> np.ndarray:
        """``atan2(y, x)`` wrapped into ``[u0, u0 + 2 pi)``; the seed where ``rho <= tiny``."""
        u = np.arctan2(y, x)
        u = self.bounds[0, 0] + np.mod(u - self.bounds[0, 0], TWO_PI)
        return np.where(rho <= tiny, seed, u)

    def closest(self, points: npt.ArrayLike, seeds: npt.ArrayLike | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points of ``points (k, 3)`` on the surface, in closed form.

        Args:
            points: ``(k, 3)``.
            seeds: ``(k, 2)`` parameters used where the point does not determine
                them (axis, poles, apex, tube centre); default the lower bounds.

        Returns:
            ``(params (k, 2), foot points (k, 3), distances (k,))``.
        """
        X = np.asarray(points, dtype=float).reshape(-1, 3)
        if seeds is None:
            seed = np.broadcast_to(self.bounds[:, 0], (len(X), 2))
        else:
            seed = np.asarray(seeds, dtype=float).reshape(len(X), 2)
            seed = np.where(np.isfinite(seed), seed, self.bounds[:, 0])
        P = self._closest_params(X, seed)
        S = self._points(P[:, 0], P[:, 1])
        return P, S, np.linalg.norm(S - X, axis=1)

    def normals(self, params: npt.ArrayLike) -> np.ndarray:
        """``(k, 3)`` unit normals along ``S_u x S_v``, exact also where that vanishes."""
        P = np.asarray(params, dtype=float).reshape(-1, 2)
        u, v = P[:, 0], P[:, 1]
        c, s = np.cos(u), np.sin(u)
        a, b = self._normal_local(u, v)  # normal = a e(u) + b Z (times the handedness)
        n = (a * c)[:, None] * self.X + (a * s)[:, None] * self.Y + b[:, None] * self.Z
        return self.hand * n

    def _normal_local(self, u, v):  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(origin={self.origin.tolist()}, bounds={self.bounds.tolist()})"


class Plane(AnalyticSurface):
    """``S = O + u X + v Y``."""

    kind = "plane"

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        u, v = params[0], params[1]
        k = u.shape[0]
        out = np.zeros((1 if nderiv == 0 else 3 if nderiv == 1 else 6, 3, k))
        out[0] = (self.origin[:, None] + self.X[:, None] * u + self.Y[:, None] * v)
        if nderiv >= 1:
            out[1] = self.X[:, None]
            out[2] = self.Y[:, None]
        return out

    def _closest_params(self, X, seed):
        x, y, _ = self._coords(X)
        return np.stack([x, y], axis=1)

    def normals(self, params):
        P = np.asarray(params, dtype=float).reshape(-1, 2)
        n = np.cross(self.X, self.Y)
        return np.broadcast_to(n / np.linalg.norm(n), (len(P), 3)).copy()


class Cylinder(AnalyticSurface):
    """``S = O + R e(u) + v Z``."""

    kind = "cylinder"
    closed = (True, False)
    _curved = (True, False)

    def __init__(self, origin, x, y, z, radius, bounds):
        self.radius = _positive(radius, "cylinder radius")
        super().__init__(origin, x, y, z, bounds)

    def _sagitta(self, du, dv):
        return self.radius * (1 - np.cos(du / 2))

    def _local(self, u, v, c, s, nderiv):
        k = u.shape[0]
        R = self.radius
        out = np.zeros((1 if nderiv == 0 else 3 if nderiv == 1 else 6, 3, k))
        out[0, 0], out[0, 2] = R, v
        if nderiv >= 1:
            out[1, 1] = R
            out[2, 2] = 1.0
        if nderiv >= 2:
            out[3, 0] = -R
        return out

    def _closest_params(self, X, seed):
        x, y, z = self._coords(X)
        rho = np.hypot(x, y)
        return np.stack([self._angle(x, y, rho, seed[:, 0], 1e-300), z], axis=1)

    def _normal_local(self, u, v):
        return np.ones_like(u), np.zeros_like(u)


class Cone(AnalyticSurface):
    """``S = O + (R + v sin a) e(u) + v cos a Z``, restricted to the nappe of its face."""

    kind = "cone"
    closed = (True, False)
    _curved = (True, False)

    def __init__(self, origin, x, y, z, radius, semi_angle, bounds):
        self.radius = float(radius)
        self.semi_angle = float(semi_angle)
        if not (np.isfinite(self.radius) and self.radius >= 0):
            raise ValueError(f"cone reference radius must be >= 0, got {radius}")
        if not (np.isfinite(self.semi_angle) and 0 < abs(self.semi_angle) < np.pi / 2):
            raise ValueError(f"cone semi-angle must be in (0, pi/2) in magnitude, got {semi_angle}")
        self.sin, self.cos = np.sin(self.semi_angle), np.cos(self.semi_angle)
        #: ``v`` of the apex, where the radius ``R + v sin a`` vanishes
        self.v_apex = -self.radius / self.sin
        b = np.asarray(bounds, dtype=float).reshape(2, 2)
        #: +1 if the face's nappe has ``v >= v_apex``, else -1
        self.nappe = 1.0 if b[1].mean() >= self.v_apex else -1.0
        lo, hi = (self.v_apex, np.inf) if self.nappe > 0 else (-np.inf, self.v_apex)
        self.limits = np.array([[-np.inf, np.inf], [lo, hi]])
        super().__init__(origin, x, y, z, bounds)

    def _sagitta(self, du, dv):
        r = np.max(np.abs(self.radius + self.bounds[1] * self.sin))
        return r * (1 - np.cos(du / 2))

    def _local(self, u, v, c, s, nderiv):
        k = u.shape[0]
        r = self.radius + v * self.sin
        out = np.zeros((1 if nderiv == 0 else 3 if nderiv == 1 else 6, 3, k))
        out[0, 0], out[0, 2] = r, v * self.cos
        if nderiv >= 1:
            out[1, 1] = r
            out[2, 0], out[2, 2] = self.sin, self.cos
        if nderiv >= 2:
            out[3, 0] = -r
            out[4, 1] = self.sin
        return out

    def _closest_params(self, X, seed):
        x, y, z = self._coords(X)
        rho = np.hypot(x, y)
        u = self._angle(x, y, rho, seed[:, 0], 1e-300)
        lo, hi = self.limits[1]
        best_u, best_v, best_d = None, None, None
        for sign, shift in ((1.0, 0.0), (-1.0, np.pi)):  # half-planes u and u + pi
            v = np.clip((sign * rho - self.radius) * self.sin + z * self.cos, lo, hi)
            r = self.radius + v * self.sin
            d = np.hypot(sign * rho - r, z - v * self.cos)
            uu = u + shift
            if best_d is None:
                best_u, best_v, best_d = uu, v, d
            else:
                take = d < best_d
                best_u, best_v = np.where(take, uu, best_u), np.where(take, v, best_v)
        best_u = self.bounds[0, 0] + np.mod(best_u - self.bounds[0, 0], TWO_PI)
        apex = np.abs(best_v - self.v_apex) * abs(self.sin) <= 1e-15 * max(self.bbox_size, 1e-300)
        best_u = np.where(apex | (rho <= 1e-300), seed[:, 0], best_u)
        return np.stack([best_u, best_v], axis=1)

    def _normal_local(self, u, v):
        # S_u x S_v = r (cos a e - sin a Z) in a right-handed frame; sign(r) = nappe
        return np.full_like(u, self.nappe * self.cos), np.full_like(u, -self.nappe * self.sin)


class Sphere(AnalyticSurface):
    """``S = O + R cos v e(u) + R sin v Z``."""

    kind = "sphere"
    closed = (True, False)
    _curved = (True, True)
    limits = np.array([[-np.inf, np.inf], [-np.pi / 2, np.pi / 2]])

    def __init__(self, origin, x, y, z, radius, bounds):
        self.radius = _positive(radius, "sphere radius")
        super().__init__(origin, x, y, z, bounds)

    def _sagitta(self, du, dv):
        return self.radius * (1 - np.cos(max(du, dv) / 2))

    def _local(self, u, v, c, s, nderiv):
        k = u.shape[0]
        R = self.radius
        cv, sv = np.cos(v), np.sin(v)
        out = np.zeros((1 if nderiv == 0 else 3 if nderiv == 1 else 6, 3, k))
        out[0, 0], out[0, 2] = R * cv, R * sv
        if nderiv >= 1:
            out[1, 1] = R * cv
            out[2, 0], out[2, 2] = -R * sv, R * cv
        if nderiv >= 2:
            out[3, 0] = -R * cv
            out[4, 1] = -R * sv
            out[5, 0], out[5, 2] = -R * cv, -R * sv
        return out

    def _closest_params(self, X, seed):
        x, y, z = self._coords(X)
        rho = np.hypot(x, y)
        u = self._angle(x, y, rho, seed[:, 0], 1e-300)
        centre = np.hypot(rho, z) <= 1e-300
        v = np.where(centre, seed[:, 1], np.arctan2(z, rho))
        return np.stack([u, v], axis=1)

    def _normal_local(self, u, v):
        return np.cos(v), np.sin(v)


class Torus(AnalyticSurface):
    """``S = O + (R + r cos v) e(u) + r sin v Z``."""

    kind = "torus"
    closed = (True, True)
    _curved = (True, True)

    def __init__(self, origin, x, y, z, major, minor, bounds):
        self.major = _positive(major, "torus major radius")
        self.minor = _positive(minor, "torus minor radius")
        super().__init__(origin, x, y, z, bounds)

    def _sagitta(self, du, dv):
        return (self.major + self.minor) * (1 - np.cos(du / 2)) + self.minor * (1 - np.cos(dv / 2))

    def _local(self, u, v, c, s, nderiv):
        k = u.shape[0]
        R, r = self.major, self.minor
        cv, sv = np.cos(v), np.sin(v)
        rad = R + r * cv
        out = np.zeros((1 if nderiv == 0 else 3 if nderiv == 1 else 6, 3, k))
        out[0, 0], out[0, 2] = rad, r * sv
        if nderiv >= 1:
            out[1, 1] = rad
            out[2, 0], out[2, 2] = -r * sv, r * cv
        if nderiv >= 2:
            out[3, 0] = -rad
            out[4, 1] = -r * sv
            out[5, 0], out[5, 2] = -r * cv, -r * sv
        return out

    def _closest_params(self, X, seed):
        x, y, z = self._coords(X)
        rho = np.hypot(x, y)
        u = self._angle(x, y, rho, seed[:, 0], 1e-300)
        w = rho - self.major
        tube = np.hypot(w, z) <= 1e-300
        v = np.arctan2(z, w)
        v = self.bounds[1, 0] + np.mod(v - self.bounds[1, 0], TWO_PI)
        return np.stack([u, np.where(tube, seed[:, 1], v)], axis=1)

    def _normal_local(self, u, v):
        sign = np.sign(self.major + self.minor * np.cos(v))
        sign = np.where(sign == 0, 1.0, sign)
        return sign * np.cos(v), sign * np.sin(v)


def analytic_surface(desc: dict, bounds) -> AnalyticSurface:
    """The surface of a face description of :func:`nagata_snap.cad.read.read_shape`."""
    kind = desc["type"]
    frame = (desc["origin"], desc["x"], desc["y"], desc["z"])
    if kind == "plane":
        return Plane(*frame, bounds)
    if kind == "cylinder":
        return Cylinder(*frame, desc["radius"], bounds)
    if kind == "cone":
        return Cone(*frame, desc["radius"], desc["semi_angle"], bounds)
    if kind == "sphere":
        return Sphere(*frame, desc["radius"], bounds)
    if kind == "torus":
        return Torus(*frame, desc["major"], desc["minor"], bounds)
    raise ValueError(f"not an analytic surface type: {kind!r}")
