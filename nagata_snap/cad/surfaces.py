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

import math
from collections.abc import Callable, Sequence
from itertools import pairwise
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from nagata_snap.mesh.arrays import float_array, linspaces, norms

__all__ = ["AnalyticSurface", "Plane", "Cylinder", "Cone", "Sphere", "Torus", "analytic_surface",
           "analytic_surfaces", "fill_boxes"]

TWO_PI = 2.0 * np.pi
#: samples per direction of the grid whose box (plus its sagitta) is a curved face's bounding box
BOX_GRID = 17


def _positive(value, what: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be positive, got {value}")
    return v


def _norm2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sqrt(a^2 + b^2)`` (coordinates are at most 1e100: no overflow; faster than ``hypot``)."""
    out = a * a
    out += b * b
    return np.sqrt(out, out=out)


def _wrap(t: np.ndarray, lo: float, top: float = np.pi) -> np.ndarray:
    """Angles ``t`` in ``[-pi, top]`` (``top <= 2 pi``) wrapped into ``[lo, lo + 2 pi)``, in place.

    Where ``lo`` is within a turn of the range (every face read so far) one
    masked shift by ``2 pi`` each way suffices; else the general ``floor``.
    Returns ``t``.
    """
    if -np.pi - TWO_PI < lo <= -np.pi + TWO_PI - max(top - np.pi, 0.0):
        np.add(t, TWO_PI, out=t, where=t < lo)
        if top >= lo + TWO_PI:
            np.subtract(t, TWO_PI, out=t, where=t >= lo + TWO_PI)
        return np.maximum(t, lo, out=t)  # t + 2 pi rounded: not below lo
    t -= lo
    q = t * (1.0 / TWO_PI)
    np.floor(q, out=q)
    q *= TWO_PI
    t -= q
    np.maximum(t, 0.0, out=t)  # t/2pi rounded up to an integer: -1 ulp, not below lo
    t += lo
    return t


#: the periods of the surfaces by their closedness (``AnalyticSurface.periods``)
_PERIODS: dict[tuple[bool, bool], np.ndarray] = {}

#: rows per block of :func:`_add_rows`
_ROW_BLOCK = 256


def _add_rows(a: np.ndarray, c: np.ndarray) -> None:
    """``a += c`` in place for a C-contiguous ``(k, m)`` array and a ``(m,)`` vector.

    Done on blocks of :data:`_ROW_BLOCK` rows viewed as one long row against ``c``
    tiled, because a broadcast over rows runs numpy's inner loop over only ``m``
    (2 or 3) elements at a time, several times slower.
    """
    k, m = a.shape
    q = k - k % _ROW_BLOCK
    if q:
        body = a[:q].reshape(-1, _ROW_BLOCK * m)
        body += np.tile(c, _ROW_BLOCK)
    a[q:] += c


class AnalyticSurface:
    """Common part of the analytic surfaces: frame, bounds, periods, evaluation.

    Args:
        origin, x, y, z: the placement (``gp_Ax3``: origin and the three
            directions; ``y`` need not be ``z x x``: left-handed frames are kept).
        bounds: ``(2, 2)`` face parameter box ``[[u0, u1], [v0, v1]]``.
    """

    param_dim = 2
    kind = "analytic"
    #: a tangent ``S_u`` or ``S_v`` can vanish (sphere poles, cone apex)
    can_degenerate = True
    #: hard parameter limits (``normalize_params`` clamps there), ``(2, 2)``
    limits = np.array([[-np.inf, np.inf], [-np.inf, np.inf]])
    # set by :meth:`_place`: the placement and the face's ``(2, 2)`` parameter box
    origin: np.ndarray
    X: np.ndarray
    Y: np.ndarray
    Z: np.ndarray
    bounds: np.ndarray
    #: +1 for a right-handed frame, -1 for a left-handed one
    hand: float
    # the local frame of :meth:`_coords`: its angle origin, rows and origin in it
    _shift: float
    _frame: np.ndarray
    _o_local: np.ndarray
    _frame4: np.ndarray
    #: ``(lo, hi, diagonal)`` of :attr:`bbox`, computed on first use (:func:`fill_boxes`)
    _box: tuple[np.ndarray, np.ndarray, float] | None

    def __init__(self, origin, x, y, z, bounds):
        AnalyticSurface._place([self], [origin], [(x, y, z)], [bounds])

    def _shape(self, shape: Sequence, bounds: npt.ArrayLike) -> None:
        """Set (and check) the shape fields of the class from their values ``shape`` (the
        arguments between the frame and the bounds; none for a plane)."""

    @staticmethod
    def _place(surfaces: Sequence[AnalyticSurface], origins: Sequence, axes: Sequence,
               bounds: Sequence | np.ndarray) -> None:
        """Set the placement, bounds and local frame of ``k`` surfaces (any classes, their
        shape fields set, :meth:`_shape`), and the planes' projection data, computed for all
        of them at once.

        Args:
            surfaces: the surfaces.
            origins: per surface its origin (3,).
            axes: per surface its directions ``(x, y, z)`` (3, 3) (normalised here).
            bounds: per surface its ``(2, 2)`` face parameter box.

        Raises:
            ValueError: a zero or non-finite direction, a non-finite origin, bounds not finite
                or not ordered (the first such surface of the first failing check).
        """
        k = len(surfaces)
        O = _rows(origins, (3,))
        A = np.array(axes, dtype=float).reshape(k, 3, 3)
        n = norms(A)
        bad = ~np.isfinite(n) | (n == 0.0)
        if bad.any():
            i, j = np.argwhere(bad)[0]
            raise ValueError(f"{'xyz'[j]} must be a finite non-zero vector, got {A[i, j].tolist()}")
        A = A / n[..., None]
        X, Y, Z = A[:, 0], A[:, 1], A[:, 2]
        if not np.isfinite(O).all():
            raise ValueError(f"origin must be finite, got {O[np.argmin(np.isfinite(O).all(axis=1))].tolist()}")
        (x0, x1, x2), (y0, y1, y2), (z0, z1, z2) = X.T, Y.T, Z.T
        triple = (x1 * y2 - x2 * y1) * z0 + (x2 * y0 - x0 * y2) * z1 + (x0 * y1 - x1 * y0) * z2  # (X x Y).Z
        B = _rows(bounds, (2, 2))
        if not (np.isfinite(B).all() and (B[:, :, 0] <= B[:, :, 1]).all()):
            bad = ~np.isfinite(B).all(axis=(1, 2)) | (B[:, :, 1] < B[:, :, 0]).any(axis=1)
            raise ValueError(f"bounds must be finite [[u0, u1], [v0, v1]], got {B[np.argmax(bad)].tolist()}")
        # closest points measure the angle from e(u0 + pi): atan2 then lands in
        # [u0, u0 + 2 pi] with one addition, no wrapping
        shift = np.where([sf.closed[0] for sf in surfaces], B[:, 0, 0] + np.pi, 0.0)
        c, sn = np.cos(shift)[:, None], np.sin(shift)[:, None]
        # (3, 3) rows e(shift), e'(shift), Z: the local frame of :meth:`_coords`
        frame = np.stack([c * X + sn * Y, c * Y - sn * X, Z], axis=1)
        o_local = np.matmul(frame, O[:, :, None])[:, :, 0]
        frame4 = np.concatenate([frame, O[:, None]], axis=1)  # [x y z 1] @ _frame4 = O + x e + y e' + z Z
        hand = np.where(triple > 0, 1.0, -1.0).tolist()
        for sf, *fields in zip(surfaces, O, X, Y, Z, B, hand, shift.tolist(), frame, o_local, frame4,
                               strict=True):  # loop over surfaces (their fields)
            sf.origin, sf.X, sf.Y, sf.Z, sf.bounds, sf.hand, sf._shift, sf._frame, sf._o_local, sf._frame4 = fields
            sf._box = None
        planes = [i for i, sf in enumerate(surfaces) if isinstance(sf, Plane)]
        if planes:
            Plane._axes([cast(Plane, surfaces[i]) for i in planes], O[planes], A[planes])

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` box of the face's parameter box (grid samples plus their sagitta)."""
        if self._box is None:
            fill_boxes([self])
        assert self._box is not None
        return self._box[0], self._box[1]

    @property
    def bbox_size(self) -> float:
        """Diagonal of :attr:`bbox` (length units)."""
        if self._box is None:
            fill_boxes([self])
        assert self._box is not None
        return self._box[2]

    # -- protocol ------------------------------------------------------
    closed = (False, False)

    @property
    def periods(self) -> np.ndarray:
        """``(2,)`` period per direction (NaN where open); read-only, shared by the surfaces
        closed alike."""
        per = _PERIODS.get(self.closed)
        if per is None:
            per = _PERIODS[self.closed] = np.array([TWO_PI if c else np.nan for c in self.closed])
            per.flags.writeable = False
        return per

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

    #: the scalar fields :meth:`_local` reads (besides the frame), per class
    _shape_fields: tuple[str, ...] = ()

    @staticmethod
    def _sample_boxes(surfaces: Sequence[AnalyticSurface]) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)``, each ``(k, 3)``: boxes of the parameter boxes of ``k`` surfaces of
        revolution (any classes, those of a class next to each other), the points of a
        :data:`BOX_GRID` x :data:`BOX_GRID` grid widened by their sagitta.

        A point of a surface of revolution is ``O + a(v) e(u) + b(v) Z``: per class
        :meth:`_local` of one surface whose shape fields are per-sample arrays gives ``a, b``
        at the ``v`` of every grid row, ``e(u)`` is taken at the ``u`` of every column, and
        the grid points are combined from both by broadcasting, with the products and sums
        of :func:`_to_global` in its order (so each point is what its own surface's
        :meth:`_eval_soa` gives, but for the sign of a zero: its ``e'(u)`` term, whose
        coefficient is 0, is left out).  The sagittas of a class are its :meth:`_sagitta`
        of the stacked surfaces, elementwise as well.
        """
        k, g = len(surfaces), BOX_GRID
        B = np.array([sf.bounds for sf in surfaces])
        u, v = linspaces(B[:, 0, 0], B[:, 0, 1], g), linspaces(B[:, 1, 0], B[:, 1, 1], g)  # (k, g) each
        V = v.ravel()
        du, dv = u[:, 1] - u[:, 0], v[:, 1] - v[:, 0]
        local = np.empty((3, k * g))  # a, 0, b at every v (the local point, nderiv 0)
        pad = np.empty((k, 1))
        cls = [type(sf) for sf in surfaces]
        first = [i for i in range(k) if i == 0 or cls[i] is not cls[i - 1]] + [k]
        for i0, i1 in pairwise(first):  # loop over classes (their formulas)
            stack = cls[i0].__new__(cls[i0])  # the surfaces i0 .. i1: their fields, then per v sample
            stack.bounds = B[i0:i1]
            for name in cls[i0]._shape_fields:
                setattr(stack, name, np.array([getattr(sf, name) for sf in surfaces[i0:i1]]))
            pad[i0:i1, 0] = stack._sagitta(du[i0:i1], dv[i0:i1])
            for name in cls[i0]._shape_fields:
                setattr(stack, name, np.repeat(getattr(stack, name), g))
            sl = slice(i0 * g, i1 * g)
            local[:, sl] = stack._local(V[sl], V[sl], V[sl], V[sl], 0)[0]  # u, c, s unused at nderiv 0
        a, b = local[0].reshape(k, 1, g), local[2].reshape(k, 1, g)  # along the grid's v (last axis)
        F = np.array([[sf.X, sf.Y, sf.Z, sf.origin] for sf in surfaces]).transpose(1, 2, 0)[..., None]
        X, Y, Z, O = F  # (3, k, 1) each
        c, sn = np.cos(u), np.sin(u)  # (k, g): along the grid's u
        E = c * X + sn * Y  # (3, k, g): e(u) as _to_global
        S = a * E[..., None]  # (3, k, g, g), u major
        S += b * Z[..., None]
        S += O[..., None]
        S = S.reshape(3, k, g * g)
        return S.min(axis=2).T - pad, S.max(axis=2).T + pad

    def _sagitta(self, du, dv):
        """The sagitta of grid steps ``du, dv`` (scalars, or ``(m,)`` for ``m`` surfaces stacked as in
        :meth:`_sample_boxes`): the most a grid cell's surface bulges beyond its corners' box."""
        return 0.0

    def _evaluate_inside(self, u: np.ndarray, v: np.ndarray, nderiv: int) -> np.ndarray:
        """``(1|3|6, k, 3)``: ``S, Su, Sv, Suu, Suv, Svv`` (as :class:`NurbsSurface`)."""
        return self._eval_soa(np.stack([u, v]), nderiv).transpose(0, 2, 1)

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        """``params (2, k)`` -> ``(1|3|6, 3, k)`` in the global frame."""
        u, v = params[0], params[1]
        c, s = np.cos(u), np.sin(u)
        local = self._local(u, v, c, s, nderiv)  # (nd, 3, k) in the (e, e', Z) basis
        return _to_global(local, c, s, self.X[:, None], self.Y[:, None], self.Z[:, None], self.origin[:, None])

    def _tangents_soa(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(S_u, S_v)``, each ``(3, k)``, at ``params (2, k)``: ``_eval_soa(params, 1)[1:]``
        without its terms of zero coefficients (``S_u`` is along ``e'(u)``, ``S_v`` in the
        meridian plane of ``e(u)`` and ``Z``), so the same values but for the signs of zeros,
        and the same lengths ``|a S_u + b S_v|`` to the last bit."""
        u, v = params[0], params[1]
        c, s = np.cos(u), np.sin(u)
        local = self._local(u, v, c, s, 1)
        X, Y = self.X[:, None], self.Y[:, None]
        return local[1, 1] * (-s * X + c * Y), local[2, 0] * (c * X + s * Y) + local[2, 2] * self.Z[:, None]

    def _points(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self._eval_soa(np.stack([u, v]), 0)[0].T

    def evaluate(self, u: npt.ArrayLike, v: npt.ArrayLike, nderiv: int = 0) -> np.ndarray:
        """Points and derivatives, ``(1|3|6, k, 3)`` (no clamping: the surface is unbounded)."""
        u = np.atleast_1d(np.asarray(u, dtype=float))
        v = np.atleast_1d(np.asarray(v, dtype=float))
        return self._evaluate_inside(u, v, int(nderiv))

    def _local(self, u, v, c, s, nderiv):  # pragma: no cover - abstract
        raise NotImplementedError

    def _closest(self, L: np.ndarray, seed: Callable[[np.ndarray, int], np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(u, v, foot (k, 3), distance)`` from local coordinates ``L`` (:meth:`_coords`);
        ``seed(rows, a)`` gives parameter ``a`` where the point leaves it free."""
        raise NotImplementedError  # pragma: no cover - abstract

    def _coords(self, points: np.ndarray) -> np.ndarray:
        """``(4, k)``: local coordinates ``x, y, z`` (contiguous rows) of ``points (k, 3)`` in the
        frame ``e(shift), e'(shift), Z`` (``shift = u0 + pi`` on closed surfaces, else 0), and a
        spare row (the plane builds its foot in place)."""
        X = np.asarray(points, dtype=float)
        L = np.empty((4, len(X)))  # rows x, y, z and a spare one (the plane's foot reuses L)
        np.matmul(self._frame, X.T, out=L[:3])  # one BLAS pass
        L[:3] -= self._o_local[:, None]
        return L

    def _angle(self, x: np.ndarray, y: np.ndarray, rho: np.ndarray, seed) -> tuple[np.ndarray, np.ndarray]:
        """``(u, axis)``: the angle in ``[u0, u0 + 2 pi)`` of local coordinates ``x, y``
        (:meth:`_coords`), the seed on the axis (``axis``: the rows where ``rho`` is 0)."""
        u = self._from_local(np.arctan2(y, x))
        axis = np.flatnonzero(rho <= 1e-300)
        if axis.size:
            u[axis] = seed(axis, 0)
        return u, axis

    def _from_local(self, t: np.ndarray) -> np.ndarray:
        """Angles ``t`` in ``[-pi, pi]`` from ``e(shift)`` -> ``u`` in ``[u0, u0 + 2 pi)``, in place."""
        lo = self.bounds[0, 0]
        t += self._shift
        np.maximum(t, lo, out=t)  # shift - pi rounded: not below u0
        t[t >= lo + TWO_PI] = lo  # atan2 = pi: the seam
        return t

    def _foot(self, x, y, rho, u, a, b, axis: np.ndarray) -> np.ndarray:
        """``(k, 3)`` foot points ``O + a e(u) + b Z`` of a surface of revolution.

        ``e(u) = (x e + y e') / rho`` (the meridian direction of the point, no
        trigonometry; :meth:`_coords`) where ``rho > 0``, ``e(u)`` on the ``axis``
        rows; ``a`` (scalar or ``(k,)``) is the signed radial coordinate of the
        foot along it.  Built as rows ``(4, k)``, mapped by one BLAS product.
        """
        loc = np.empty((4, len(x)))
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(a, rho, out=loc[3])
            np.multiply(loc[3], x, out=loc[0])
            np.multiply(loc[3], y, out=loc[1])
        loc[2], loc[3] = b, 1.0
        if axis.size:
            aa = a if np.ndim(a) == 0 else a[axis]
            loc[0, axis] = aa * np.cos(u[axis] - self._shift)
            loc[1, axis] = aa * np.sin(u[axis] - self._shift)
        return loc.T @ self._frame4

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
        if seeds is not None:
            seeds = np.asarray(seeds, dtype=float).reshape(len(X), 2)

        def seed(rows: np.ndarray, a: int) -> np.ndarray:  # read only where needed
            if seeds is None:
                return np.full(len(rows), self.bounds[a, 0])
            s = seeds[rows, a]
            return np.where(np.isfinite(s), s, self.bounds[a, 0])

        u, v, S, dist = self._closest(self._coords(X), seed)
        P = np.empty((len(X), 2))
        P[:, 0], P[:, 1] = u, v
        return P, S, dist

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
    can_degenerate = False
    # set by :meth:`_place`: ``(2, 3)`` rows X, Y, their ``(3, 2)`` transpose, the origin's
    # coordinates along them and along Z
    _uv_axes: np.ndarray
    _uv_cols: np.ndarray
    _uv_origin: np.ndarray
    _z_origin: float

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        u, v = params[0], params[1]
        k = u.shape[0]
        out = np.zeros((1 if nderiv == 0 else 3 if nderiv == 1 else 6, 3, k))
        out[0] = (self.origin[:, None] + self.X[:, None] * u + self.Y[:, None] * v)
        if nderiv >= 1:
            out[1] = self.X[:, None]
            out[2] = self.Y[:, None]
        return out

    def closest(self, points: npt.ArrayLike, seeds: npt.ArrayLike | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest points ``O + u X + v Y`` of ``points (k, 3)``, ``u, v = (P - O).X, (P - O).Y``
        (seeds are not needed).  Only the returned arrays are allocated, in three passes
        over ``points``.  Returns ``(params (k, 2), foot points (k, 3), distances (k,))``."""
        X = np.asarray(points, dtype=float).reshape(-1, 3)
        uv = X @ self._uv_cols  # (k, 2)
        _add_rows(uv, -self._uv_origin)
        dist = X @ self.Z  # (k,): signed height over the plane
        dist -= self._z_origin
        S = uv @ self._uv_axes  # the foot O + u X + v Y
        _add_rows(S, self.origin)
        return uv, S, np.abs(dist, out=dist)

    @staticmethod
    def _axes(planes: Sequence[Plane], O: np.ndarray, A: np.ndarray) -> None:
        """Set the projection data of ``planes`` from their origins ``O (k, 3)`` and unit
        directions ``A (k, 3, 3)`` (:meth:`AnalyticSurface._place`), all at once."""
        uv_axes = A[:, :2]  # (k, 2, 3): X, Y
        uv_cols = np.ascontiguousarray(uv_axes.transpose(0, 2, 1))  # (k, 3, 2): contiguous for BLAS
        uv_origin = np.matmul(uv_axes, O[:, :, None])[:, :, 0]
        z_origin = np.vecdot(A[:, 2], O).tolist()
        for i, sf in enumerate(planes):  # loop over planes (their fields)
            sf._uv_axes, sf._uv_cols, sf._uv_origin, sf._z_origin = uv_axes[i], uv_cols[i], uv_origin[i], z_origin[i]

    @property
    def affine(self) -> tuple[np.ndarray, np.ndarray]:
        """``(origin (3,), axes (2, 3))``: ``S = origin + params @ axes``, orthonormal axes
        (projections onto many planes at once: :class:`nagata_snap.cad.projection.AffineBatch`)."""
        return self.origin, self._uv_axes

    @staticmethod
    def _sample_boxes(surfaces: Sequence[AnalyticSurface]) -> tuple[np.ndarray, np.ndarray]:
        """The boxes of the parameter boxes' four corners ``O + u X + v Y`` (exact: the plane is
        linear in ``u, v``), ``(lo, hi)`` each ``(k, 3)``."""
        B = np.array([sf.bounds for sf in surfaces])  # (k, 2, 2)
        u, v = B[:, 0][:, [0, 0, 1, 1], None], B[:, 1][:, [0, 1, 0, 1], None]  # (k, 4, 1)
        F = np.array([(sf.origin, sf.X, sf.Y) for sf in surfaces])  # (k, 3, 3): O, X, Y
        S = F[:, 0, None] + F[:, 1, None] * u + F[:, 2, None] * v
        return S.min(axis=1), S.max(axis=1)

    def normals(self, params):
        P = np.asarray(params, dtype=float).reshape(-1, 2)
        n = np.cross(self.X, self.Y)
        return np.broadcast_to(n / np.linalg.norm(n), (len(P), 3)).copy()


class Cylinder(AnalyticSurface):
    """``S = O + R e(u) + v Z``."""

    kind = "cylinder"
    can_degenerate = False
    closed = (True, False)
    _curved = (True, False)
    _shape_fields = ("radius",)

    def __init__(self, origin, x, y, z, radius, bounds):
        self._shape((radius,), bounds)
        super().__init__(origin, x, y, z, bounds)

    def _shape(self, shape, bounds) -> None:
        self.radius = _positive(shape[0], "cylinder radius")

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

    def _closest(self, L, seed):
        x, y, z = L[0], L[1], L[2]
        rho = _norm2(x, y)
        u, axis = self._angle(x, y, rho, seed)
        S = self._foot(x, y, rho, u, self.radius, z, axis)
        rho -= self.radius
        return u, z, S, np.abs(rho, out=rho)

    def _normal_local(self, u, v):
        return np.ones_like(u), np.zeros_like(u)


class Cone(AnalyticSurface):
    """``S = O + (R + v sin a) e(u) + v cos a Z``, restricted to the nappe of its face."""

    kind = "cone"
    closed = (True, False)
    _curved = (True, False)
    _shape_fields = ("radius", "sin", "cos")

    def __init__(self, origin, x, y, z, radius, semi_angle, bounds):
        self._shape((radius, semi_angle), bounds)
        super().__init__(origin, x, y, z, bounds)

    def _shape(self, shape, bounds) -> None:
        radius, semi_angle = shape
        self.radius = float(radius)
        self.semi_angle = float(semi_angle)
        if not (math.isfinite(self.radius) and self.radius >= 0):
            raise ValueError(f"cone reference radius must be >= 0, got {radius}")
        if not (math.isfinite(self.semi_angle) and 0 < abs(self.semi_angle) < np.pi / 2):
            raise ValueError(f"cone semi-angle must be in (0, pi/2) in magnitude, got {semi_angle}")
        self.sin, self.cos = np.sin(self.semi_angle), np.cos(self.semi_angle)
        #: ``v`` of the apex, where the radius ``R + v sin a`` vanishes
        self.v_apex = -self.radius / self.sin
        v0, v1 = np.asarray(bounds, dtype=float).reshape(2, 2)[1].tolist()
        #: +1 if the face's nappe (its mid-``v``, as ``mean``) has ``v >= v_apex``, else -1
        self.nappe = 1.0 if (v0 + v1) / 2 >= self.v_apex else -1.0
        lo, hi = (self.v_apex, np.inf) if self.nappe > 0 else (-np.inf, self.v_apex)
        self.limits = np.array([[-np.inf, np.inf], [lo, hi]])

    def _sagitta(self, du, dv):
        r = np.abs(self.radius + self.bounds[..., 1, :].T * self.sin).max(axis=0)  # the larger end radius
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

    def _closest(self, L, seed):
        x, y, z = L[0], L[1], L[2]
        # the meridian section is two rays, (r(v), v cos a) in the point's half-plane u and
        # (-r(v), ...) in the opposite one u + pi; r(v) has the sign of sin a times the
        # nappe.  The ray at a <= 0 is at least rho away: tried only where the other is not
        rho = _norm2(x, y)
        zc = z * self.cos
        s0 = 1.0 if self.sin * self.nappe > 0 else -1.0
        v, a, dist = self._generator(rho, zc, z, s0)
        u = self._from_local(np.arctan2(y, x))
        if s0 < 0:
            u = _wrap(u + (np.pi - self.bounds[0, 0]), 0.0, 3 * np.pi) + self.bounds[0, 0]
        other = np.flatnonzero(dist > rho)
        if other.size:
            v2, a2, d2 = self._generator(rho[other], zc[other], z[other], -s0)
            win = d2 < dist[other]
            w = other[win]
            v[w], a[w], dist[w] = v2[win], a2[win], d2[win]
            u[w] = _wrap(u[w] + s0 * np.pi - self.bounds[0, 0], 0.0, 3 * np.pi) + self.bounds[0, 0]
        dv = v - self.v_apex
        free = np.abs(dv, out=dv) <= 1e-15 * max(self.bbox_size, 1e-300) / abs(self.sin)
        free |= rho <= 1e-300
        free = np.flatnonzero(free)
        if free.size:  # u is free at the apex and on the axis: the seed's
            u[free] = seed(free, 0)
            a[free] = np.abs(a[free])  # the foot's direction is then e(u)
        S = self._foot(x, y, rho, u, a, v * self.cos, free)
        return u, v, S, dist

    def _generator(self, rho, zc, z, sign: float):
        """``(v, a, d)``: nearest point of the generator in half-plane ``sign`` (clipped to
        the nappe), its signed radial coordinate and its distance, for meridian
        coordinates ``(sign rho, z)`` (``zc = z cos a``)."""
        lo, hi = self.limits[1]
        v = rho * (sign * self.sin)
        v += zc
        v -= self.radius * self.sin
        np.clip(v, lo, hi, out=v)
        r = v * self.sin
        r += self.radius
        e = rho * sign
        e -= r
        w = v * self.cos
        np.subtract(z, w, out=w)
        if sign < 0:
            np.negative(r, out=r)
        return v, r, _norm2(e, w)

    def _normal_local(self, u, v):
        # S_u x S_v = r (cos a e - sin a Z) in a right-handed frame; sign(r) = nappe
        return np.full_like(u, self.nappe * self.cos), np.full_like(u, -self.nappe * self.sin)


class Sphere(AnalyticSurface):
    """``S = O + R cos v e(u) + R sin v Z``."""

    kind = "sphere"
    closed = (True, False)
    _curved = (True, True)
    _shape_fields = ("radius",)
    limits = np.array([[-np.inf, np.inf], [-np.pi / 2, np.pi / 2]])

    def __init__(self, origin, x, y, z, radius, bounds):
        self._shape((radius,), bounds)
        super().__init__(origin, x, y, z, bounds)

    def _shape(self, shape, bounds) -> None:
        self.radius = _positive(shape[0], "sphere radius")

    def _sagitta(self, du, dv):
        return self.radius * (1 - np.cos(np.maximum(du, dv) / 2))

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

    def _closest(self, L, seed):
        x, y, z = L[0], L[1], L[2]
        rho = _norm2(x, y)
        u, _ = self._angle(x, y, rho, seed)
        t = _norm2(rho, z)
        v = np.arctan2(z, rho)
        R = self.radius
        loc = np.empty((4, len(x)))  # the foot O + (R / t) (x X + y Y + z Z), as rows
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(R, t, out=loc[3])
            for i, c in enumerate((x, y, z)):
                np.multiply(loc[3], c, out=loc[i])
        loc[3] = 1.0
        centre = np.flatnonzero(t <= 1e-300)
        if centre.size:  # u and v are free at the centre: the seeds'
            v[centre] = seed(centre, 1)
            a = R * np.cos(v[centre])
            w = u[centre] - self._shift
            loc[0, centre], loc[1, centre] = a * np.cos(w), a * np.sin(w)
            loc[2, centre] = R * np.sin(v[centre])
        t -= R
        return u, v, loc.T @ self._frame4, np.abs(t, out=t)

    def _normal_local(self, u, v):
        return np.cos(v), np.sin(v)


class Torus(AnalyticSurface):
    """``S = O + (R + r cos v) e(u) + r sin v Z``."""

    kind = "torus"
    closed = (True, True)
    _curved = (True, True)
    _shape_fields = ("major", "minor")

    def __init__(self, origin, x, y, z, major, minor, bounds):
        self._shape((major, minor), bounds)
        super().__init__(origin, x, y, z, bounds)

    def _shape(self, shape, bounds) -> None:
        self.major = _positive(shape[0], "torus major radius")
        self.minor = _positive(shape[1], "torus minor radius")
        #: S_u = (R + r cos v) e'(u) vanishes only on a horn or spindle torus (r >= R)
        self.can_degenerate = self.minor >= self.major

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

    def _closest(self, L, seed):
        x, y, z = L[0], L[1], L[2]
        rho = _norm2(x, y)
        u, axis = self._angle(x, y, rho, seed)
        w = rho - self.major
        t = _norm2(w, z)
        v0 = self.bounds[1, 0]
        v = _wrap(np.arctan2(z, w), v0)
        r = self.minor
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.divide(r, t)
            w *= f
            f *= z
            a, b = w, f
        a += self.major
        tube = np.flatnonzero(t <= 1e-300)
        if tube.size:  # v is free on the tube's centre circle: the seed's
            v[tube] = seed(tube, 1)
            a[tube], b[tube] = self.major + r * np.cos(v[tube]), r * np.sin(v[tube])
        t -= r
        t = np.abs(t, out=t)
        if self.can_degenerate:  # a spindle torus: its other meridian circle is in this half-plane too
            u, v, a, b, t = self._other_circle(x, y, z, rho, u, v, a, b, t)
        return u, v, self._foot(x, y, rho, u, a, b, axis), t

    def _other_circle(self, x, y, z, rho, u, v, a, b, t):
        """On a spindle or horn torus (``r >= R``) the meridian circle of ``u + pi`` reaches into
        the half-plane of ``u``: its nearest point (``(u + pi, v2)``, signed radial coordinate
        ``-(R + r cos v2)`` along ``e(u)``) is taken where it lies in the face's ``(u, v)`` box
        and the first does not, or where both or neither do and it is nearer.  (The face of a
        rounded screw head is such a torus' outer part: the first circle's point, on the
        inner part, would be off the face, and the face never found.)"""
        R, r = self.major, self.minor
        w2 = -rho - R
        t2 = _norm2(w2, z)
        v0 = self.bounds[1, 0]
        v2 = _wrap(np.arctan2(z, w2), v0)
        u2 = self.bounds[0, 0] + np.mod(u + np.pi - self.bounds[0, 0], TWO_PI)
        d2 = np.abs(t2 - r)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(t2 > 1e-300, r / t2, 0.0)
        a2 = -(R + w2 * f)
        b2 = z * f
        take = (self._in_box(u2, v2) & ~self._in_box(u, v)) | \
            ((self._in_box(u2, v2) == self._in_box(u, v)) & (d2 < t))
        return (np.where(take, u2, u), np.where(take, v2, v), np.where(take, a2, a), np.where(take, b2, b),
                np.where(take, d2, t))

    def _in_box(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Parameters (wrapped from the box's lower corner) inside the face's ``(u, v)`` box."""
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        uu = lo[0] + np.mod(u - lo[0], TWO_PI)
        vv = lo[1] + np.mod(v - lo[1], TWO_PI)
        return (uu <= hi[0] + 1e-12) & (vv <= hi[1] + 1e-12)

    def _normal_local(self, u, v):
        sign = np.sign(self.major + self.minor * np.cos(v))
        sign = np.where(sign == 0, 1.0, sign)
        return sign * np.cos(v), sign * np.sin(v)


def _rows(values: Sequence | np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``(k, *shape)`` float array of ``k`` values each reshaped to ``shape``: converted at once
    where they already form that array (lists of numbers, an array), else one by one (each
    reshaped, raising as ``reshape`` does)."""
    k = len(values)
    out = float_array(values)
    if out is None or out.shape != (k, *shape):
        out = np.array([np.asarray(v, dtype=float).reshape(shape) for v in values]).reshape(k, *shape)
    return out


def _to_global(local: np.ndarray, c: np.ndarray, s: np.ndarray, X: np.ndarray, Y: np.ndarray, Z: np.ndarray,
               O: np.ndarray) -> np.ndarray:
    """``(nd, 3, k)`` points and derivatives of a surface of revolution in the global frame.

    ``local (nd, 3, k)``: their components along ``e(u) = c X + s Y``, ``e'(u) = -s X + c Y``
    and ``Z`` (:meth:`AnalyticSurface._local`), ``c, s = cos u, sin u (k,)``; the frame
    ``X, Y, Z`` and the origin ``O`` are ``(3, 1)`` (one surface) or ``(3, k)`` (one per point).
    """
    E = c * X + s * Y  # (3, k)
    Ep = -s * X + c * Y
    out = local[:, 0, None] * E + local[:, 1, None] * Ep + local[:, 2, None] * Z
    out[0] += O
    return out


def revolution_tangents(surfaces: Sequence, face: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points ``(n, 3)`` and tangents ``(n, 2, 3)`` (``S_u``, ``S_v``) of the surfaces of revolution
    ``surfaces[face[r]]`` (cylinders, cones, spheres, tori: any classes) at their parameters
    ``params (n, 2)`` (in their domains, as :func:`~nagata_snap.cad.projection.normalize_params`
    gives them), all at once.

    Per class one :meth:`AnalyticSurface._local` of a surface whose shape fields are the
    per-sample arrays of the samples' surfaces (as :meth:`AnalyticSurface._sample_boxes`), and
    one :func:`_to_global` with per-sample frames: the same numbers, to the bit, as each
    surface's own ``_eval_soa(params, 1)``, without a call per surface.
    """
    n = len(face)
    P, T = np.empty((n, 3)), np.empty((n, 2, 3))
    cls = [type(sf) for sf in surfaces]
    for c in dict.fromkeys(cls[i] for i in np.unique(face).tolist()):  # loop over classes (their formulas)
        mine = np.array([k is c for k in cls])
        rows = np.flatnonzero(mine[face])
        f = face[rows]
        stack = c.__new__(c)
        idx = np.flatnonzero(mine)
        for name in c._shape_fields:  # per sample: its surface's value
            field = np.zeros(len(surfaces))
            field[idx] = [getattr(surfaces[i], name) for i in idx.tolist()]
            setattr(stack, name, field[f])
        frames = np.zeros((len(surfaces), 4, 3))
        frames[idx] = [(surfaces[i].X, surfaces[i].Y, surfaces[i].Z, surfaces[i].origin) for i in idx.tolist()]
        X, Y, Z, O = frames[f].transpose(1, 2, 0)  # (3, k) each
        u, v = params[rows, 0], params[rows, 1]
        cu, su = np.cos(u), np.sin(u)
        D = _to_global(stack._local(u, v, cu, su, 1), cu, su, X, Y, Z, O)  # (3, 3, k)
        P[rows] = D[0].T
        T[rows] = D[1:].transpose(2, 0, 1)
    return P, T


def fill_boxes(surfaces: Sequence) -> None:
    """Compute the bounding boxes of the analytic surfaces among ``surfaces`` that have none yet:
    the planes' together, those of all surfaces of revolution together
    (:meth:`AnalyticSurface._sample_boxes`); others are skipped."""
    todo = [sf for sf in surfaces if isinstance(sf, AnalyticSurface) and sf._box is None]
    planes = [sf for sf in todo if isinstance(sf, Plane)]
    rest = sorted((sf for sf in todo if not isinstance(sf, Plane)), key=lambda sf: type(sf).__name__)
    for group, boxes in ((planes, Plane._sample_boxes), (rest, AnalyticSurface._sample_boxes)):
        if not group:
            continue
        lo, hi = boxes(group)
        size = norms(hi - lo)
        for sf, a, b, d in zip(group, lo, hi, size.tolist(), strict=True):
            sf._box = (a, b, d)


#: per surface type of :func:`nagata_snap.cad.read.read_shape`: its class and the
#: description fields of its shape (the arguments between the frame and the bounds)
_SURFACES: dict[str, tuple[Any, tuple[str, ...]]] = {
    "plane": (Plane, ()), "cylinder": (Cylinder, ("radius",)), "cone": (Cone, ("radius", "semi_angle")),
    "sphere": (Sphere, ("radius",)), "torus": (Torus, ("major", "minor"))}


def analytic_surface(desc: dict, bounds) -> AnalyticSurface:
    """The surface of a face description of :func:`nagata_snap.cad.read.read_shape`
    (:func:`analytic_surfaces` of the one description)."""
    return analytic_surfaces([desc], [bounds])[0]


def analytic_surfaces(descs: Sequence[dict], bounds: Sequence | np.ndarray) -> list[AnalyticSurface]:
    """:func:`analytic_surface` of every description (analytic types only) with its ``(2, 2)``
    bounds, the frames of all surfaces computed together (:meth:`AnalyticSurface._place`);
    only the shape fields are set surface by surface.

    Raises:
        ValueError: an invalid description (with several invalid ones, the first of the
            first failing check).
    """
    out = []
    for d, b in zip(descs, bounds, strict=True):  # loop over the surfaces (their shape fields)
        if d["type"] not in _SURFACES:
            raise ValueError(f"not an analytic surface type: {d['type']!r}")
        cls, fields = _SURFACES[d["type"]]
        sf = cls.__new__(cls)
        sf._shape([d[f] for f in fields], b)
        out.append(sf)
    AnalyticSurface._place(out, [d["origin"] for d in descs], [(d["x"], d["y"], d["z"]) for d in descs], bounds)
    return out
