"""NURBS curves and surfaces: vectorised evaluation of points and derivatives.

Everything here is evaluated for many parameter values at once (arrays over
the points); the basis functions and the sums over the control net are compiled
kernels (:mod:`nagata_snap.cad.basis`) that loop over the points.

Formulas (quoted from the project's source documents):

* B-spline basis, Cox--de Boor recurrence: Kadir (2010), Appendix A, eq. (A.3)
  and Herrero Adan & Cardoso (2020), eqs. (5)-(6)::

      N_{i,0}(u) = 1 if u_i <= u < u_{i+1}, else 0
      N_{i,p}(u) = (u - u_i)/(u_{i+p} - u_i) N_{i,p-1}(u)
                   + (u_{i+p+1} - u)/(u_{i+p+1} - u_{i+1}) N_{i+1,p-1}(u)

  with the usual convention 0/0 := 0.  In the span ``[u_s, u_{s+1})`` only
  ``N_{s-p,p} .. N_{s,p}`` are non-zero (Kadir, A.4), which is what is computed.
* Basis derivatives: Neto (2010), Appendix C, eq. (46)::

      N^{(k)}_{i,p} = p [ N^{(k-1)}_{i,p-1}/(u_{i+p} - u_i)
                          - N^{(k-1)}_{i+1,p-1}/(u_{i+p+1} - u_{i+1}) ]

* NURBS curve / surface: Kadir, Appendix A.5 (rational basis
  ``R = N w / sum N w``) and Herrero Adan & Cardoso eqs. (1)-(4).
* Rational derivatives: Neto (2010), Appendix C, eqs. (42)-(45), the quotient
  rule for ``R = A / B``.  Because ``S = sum R_ij P_ij`` is linear in the
  control points, summing (42)-(44) over the net gives, with the homogeneous
  sums ``A(u,v) = sum N_i N_j w_ij P_ij`` and ``B(u,v) = sum N_i N_j w_ij``
  (eq. 41) and their derivatives (eq. 45)::

      S     = A / B
      S_u   = (A_u  - B_u S) / B                                  (from 42)
      S_uu  = (A_uu - 2 B_u S_u - B_uu S) / B                     (from 43)
      S_uv  = (A_uv - B_u S_v - B_v S_u - B_uv S) / B             (from 44)

  (the same with ``v`` for ``S_v``, ``S_vv``; the curve case drops ``v``).
  Expanding ``S_u`` in the last lines reproduces (43)/(44) term by term; this
  form needs one division per point instead of one per control point.

Parameters outside the domain are wrapped modulo the period in closed
directions and clamped in open ones (Kadir, Appendix B.1, last paragraph).
The end of the knot range is evaluated with the last non-empty span, so
``C(u_max)`` is the exact one-sided (left) limit.

Closedness (a curve's two ends, a surface's two boundary curves of a
direction, within :data:`CLOSED_RTOL` of the control net's size) is decided
from the control net where the knots are clamped and the net leaves no
doubt (rows far within or corners far beyond the tolerance, compared with a
bound on the evaluation's rounding: :func:`_closed_by_net`), else by
evaluating the ends (curves) or sampling the boundary curves (surfaces); the
outcome is the evaluation's in both cases.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

from nagata_snap.cad import basis as _kernels

__all__ = [
    "NurbsError",
    "NurbsCurve",
    "NurbsSurface",
    "basis_functions",
    "find_span",
    "circle",
    "cylinder",
    "sphere",
    "torus",
]

#: relative tolerance (to the control-polygon bounding-box diagonal) under
#: which two boundary points are considered coincident (closedness tests).
CLOSED_RTOL = 1e-9


#: derivative orders (a, b) = (d/du)^a (d/dv)^b returned for nderiv = 0, 1, 2
_ORDERS = {
    0: [(0, 0)],
    1: [(0, 0), (1, 0), (0, 1)],
    2: [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)],
}
#: the same as ``(a (n,), b (n,))`` int64 arrays, for the compiled sums
_ORDER_ARRAYS = {n: tuple(np.array(c, dtype=np.int64) for c in zip(*o, strict=True)) for n, o in _ORDERS.items()}


class NurbsError(ValueError):
    """Invalid NURBS data (knots, weights, control points, degree)."""


# ----------------------------------------------------------------------
# knot vectors and basis functions
# ----------------------------------------------------------------------
def _check_knots(knots: np.ndarray, degree: int, n_ctrl: int, what: str) -> None:
    if int(degree) != degree or degree < 1:
        raise NurbsError(f"{what}: degree must be an integer >= 1, got {degree!r}")
    if knots.ndim != 1:
        raise NurbsError(f"{what}: knot vector must be 1-D, got shape {knots.shape}")
    if n_ctrl < degree + 1:
        raise NurbsError(
            f"{what}: {n_ctrl} control points are too few for degree {degree} "
            f"(need at least {degree + 1})"
        )
    m = knots.shape[0]
    if m != n_ctrl + degree + 1:
        raise NurbsError(
            f"{what}: {m} knots given, but {n_ctrl} control points of degree {degree} "
            f"need n + p + 1 = {n_ctrl + degree + 1}"
        )
    if not np.isfinite(knots).all():
        raise NurbsError(f"{what}: knot vector contains NaN or infinite values")
    dk = knots[1:] - knots[:-1]
    if (dk < 0).any():
        i = int(np.flatnonzero(dk < 0)[0])
        raise NurbsError(
            f"{what}: knot vector must be non-decreasing, but knot[{i}]={knots[i]!r} "
            f"> knot[{i + 1}]={knots[i + 1]!r}"
        )
    # every basis function needs a non-empty support [u_i, u_{i+p+1})
    supp = knots[degree + 1 :] - knots[: n_ctrl]
    if (supp <= 0).any():
        i = int(np.flatnonzero(supp <= 0)[0])
        raise NurbsError(
            f"{what}: knot {knots[i]!r} has multiplicity > degree + 1 = {degree + 1} "
            f"(basis function {i} would vanish identically)"
        )
    if not knots[degree] < knots[n_ctrl]:
        raise NurbsError(
            f"{what}: empty parameter domain [knot[p], knot[n]] = "
            f"[{knots[degree]!r}, {knots[n_ctrl]!r}]"
        )


def _span_table(knots: np.ndarray, degree: int, n_ctrl: int) -> np.ndarray:
    """``(m + 1,)`` span of a parameter by its ``searchsorted(knots, u, side="right")`` index ``i``:
    the largest non-empty span ``s <= clip(i - 1, p, n - 1)`` with ``p <= s <= n - 1``.

    One gather after the ``searchsorted`` then gives the span (:func:`find_span`), and
    the top end of the domain gets the correct one-sided span.
    """
    k = knots.tolist()
    # spans[i - p]: the last non-empty span s <= i for p <= i <= n - 1, else the first one
    last = next(s for s in range(degree, n_ctrl) if k[s] < k[s + 1])  # exists: the domain is non-empty
    spans = []
    for i in range(degree, n_ctrl):  # loop over knots (tiny), not over points
        if k[i] < k[i + 1]:
            last = i
        spans.append(last)
    # clip(i - 1, p, n - 1) - p for i = 0 .. m: p + 2 times 0, then 1 .. n - 1 - p, then m - n times n - 1 - p
    return np.array([spans[0]] * (degree + 2) + spans[1:] + [spans[-1]] * (len(k) - n_ctrl), dtype=np.int64)


def find_span(
    knots: np.ndarray,
    degree: int,
    n_ctrl: int,
    u: np.ndarray,
    table: np.ndarray | None = None,
) -> np.ndarray:
    """Knot span index ``s`` with ``u_s <= u < u_{s+1}`` for each ``u`` (vectorised).

    Args:
        knots: ``(m,)`` knot vector, ``m = n_ctrl + degree + 1``.
        degree: polynomial degree ``p``.
        n_ctrl: number of control points ``n``.
        u: ``(k,)`` parameters, assumed inside ``[u_p, u_n]``.
        table: optional precomputed :func:`_span_table`.

    Returns:
        ``(k,)`` int64 span indices in ``[p, n-1]``; ``u == u_n`` (end of the
        range) gets the last non-empty span, so the evaluation there is the
        exact left limit.
    """
    if table is None:
        table = _span_table(knots, degree, n_ctrl)
    return table[knots.searchsorted(u, side="right")]


def _basis_soa(
    knots: np.ndarray, p: int, span: np.ndarray, u: np.ndarray, nderiv: int,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Non-zero basis functions and derivatives as ``(nderiv+1, p+1, k)`` (points last),
    into ``out`` if given: eqs. (A.3)/(6) and (46) by the compiled kernel
    :func:`nagata_snap.cad.basis.basis` (its docstring gives the arrangement)."""
    if out is None:
        out = np.empty((nderiv + 1, p + 1, u.shape[0]))
    return _kernels.basis(knots, p, np.ascontiguousarray(span, dtype=np.int64), u, nderiv, out)


def basis_functions(
    knots: npt.ArrayLike,
    degree: int,
    u: npt.ArrayLike,
    nderiv: int = 0,
    *,
    n_ctrl: int | None = None,
    span: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Non-zero B-spline basis functions and their derivatives (vectorised).

    Cox--de Boor recurrence, Kadir (2010) eq. (A.3) / Herrero Adan eqs. (5)-(6),
    and the derivative recurrence of Neto (2010) eq. (46); see
    :func:`_basis_soa` for the arrangement.

    Args:
        knots: ``(m,)`` non-decreasing knot vector.
        degree: degree ``p >= 1``.
        u: ``(k,)`` parameters inside the domain ``[u_p, u_{m-p-1}]``.
        nderiv: highest derivative order wanted (any ``>= 0``).
        n_ctrl: number of control points (default ``m - p - 1``).
        span: optional precomputed spans (from :func:`find_span`).

    Returns:
        ``(span, N)``: ``span (k,)`` int64 knot-span indices and
        ``N (nderiv+1, k, p+1)`` with ``N[d, j, a] = d^d/du^d N_{span_j - p + a, p}(u_j)``.
    """
    knots = np.asarray(knots, dtype=float)
    u = np.atleast_1d(np.asarray(u, dtype=float))
    p = int(degree)
    if n_ctrl is None:
        n_ctrl = knots.shape[0] - p - 1
    if span is None:
        span = find_span(knots, p, n_ctrl, u)
    return span, _basis_soa(knots, p, span, u, int(nderiv)).transpose(0, 2, 1).copy()


#: :meth:`NurbsCurve.many` packs this many curves or more (fewer: one by one, which costs less)
MANY_MIN = 4



# ----------------------------------------------------------------------
# shared helpers
# ----------------------------------------------------------------------
def _as_float(a: npt.ArrayLike, name: str) -> np.ndarray:
    try:
        arr = np.array(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise NurbsError(f"{name} must be numeric: {exc}") from None
    return arr


def _freeze(obj, name: str, arr: np.ndarray) -> None:
    arr = np.ascontiguousarray(arr)
    arr.flags.writeable = False
    object.__setattr__(obj, name, arr)


def _wrap_or_clamp(u: np.ndarray, lo: float, hi: float, closed: bool) -> np.ndarray:
    """Bring ``u`` into ``[lo, hi]``: modulo the period if closed, else clamp.

    Values already inside are returned unchanged (so ``hi`` stays ``hi``).
    """
    if closed:
        out = (u < lo) | (u > hi)
        if np.any(out):
            u = u.copy()
            u[out] = lo + np.mod(u[out] - lo, hi - lo)
        return u
    return np.clip(u, lo, hi)


def _check_nderiv(nderiv: int) -> int:
    if int(nderiv) != nderiv or not 0 <= nderiv <= 2:
        raise NurbsError(f"nderiv must be 0, 1 or 2, got {nderiv!r}")
    return int(nderiv)


def _bbox_size(points: np.ndarray) -> float:
    """Diagonal of the box of ``points (..., 3)``, reduced coordinate by coordinate over a
    contiguous copy (faster than along the rows; the extents and their norm are exact
    whatever the order, a zero's sign squared away)."""
    pts = np.ascontiguousarray(points.reshape(-1, 3).T)  # (3, n)
    d = pts.max(axis=1) - pts.min(axis=1)
    return float(np.sqrt(d @ d))  # np.linalg.norm(d), to the last bit


#: bound on the rounding of a point evaluated at clamped ends of its knot vectors, in
#: units of the machine epsilon times the largest control-point coordinate and per
#: degree (+ 1) summed over the directions (:func:`_closed_by_net`)
_END_ROUNDING = 64.0
_EPS = float(np.finfo(float).eps)


def _clamped_ends(knots: np.ndarray, p: int, n: int) -> tuple[bool, bool]:
    """Are the (non-decreasing) knots ``knots[1..p]`` all ``knots[p]`` (the start),
    ``knots[n..n+p-1]`` all ``knots[n]`` (the end)?  There the evaluation's basis is one
    function, the others exactly 0 (:func:`_closed_by_net`)."""
    return bool(knots[1] == knots[p]), bool(knots[n] == knots[n + p - 1])


def _closed_by_net(rows_gap: npt.ArrayLike, ends_gap: npt.ArrayLike, scale: npt.ArrayLike,
                   degrees: npt.ArrayLike, size: npt.ArrayLike) -> np.ndarray:
    """Closedness decided from the control net where the sampling test's outcome is certain.

    At a clamped end (:func:`_clamped_ends`) of a knot vector the computed basis is one
    function (within a few roundings of 1), the others exactly 0: a curve's computed end
    point is its end control point, a surface's computed boundary curve the B-spline of
    the net's end row (column), each within ``_END_ROUNDING (degrees + 1) eps scale``
    (length units) of the exact value.  Two boundary rows with equal weights are
    curves with one rational basis, so the boundary curves are at most the rows'
    largest control-point distance apart; two corner points the test evaluates
    (both directions clamped there) are their control points.  So where the rows are
    within the tolerance by more than the rounding bound, every sampled distance is
    (closed), and where corner points are beyond it by more than that bound, one
    sampled distance is (open); the rest is left to the sampling test.

    Args:
        rows_gap: ``(k,)`` largest distance (length units) between the matching control
            points of the two boundary rows (a curve: its two end points); ``inf`` where
            an end is not clamped or the rows' weights differ.
        ends_gap: ``(k,)`` distance between two matching corner points of the rows
            that the test evaluates, at clamped ends (a curve: its end points); NaN
            where there are none.
        scale: ``(k,)`` largest absolute control-point coordinate (length units).
        degrees: ``(k,)`` sum of the degrees.
        size: ``(k,)`` control points' bounding-box diagonal (the tolerance is
            :data:`CLOSED_RTOL` of it).

    Returns:
        ``(k,)`` int8: 1 closed, 0 open, -1 for the sampling test to decide.
    """
    tol = CLOSED_RTOL * np.maximum(size, 1e-300)
    margin = np.multiply(_END_ROUNDING * _EPS, np.add(degrees, 1)) * scale
    closed = np.multiply(rows_gap, 1.0 + 1e-12) + margin <= tol
    opened = np.multiply(ends_gap, 1.0 - 1e-12) - margin > tol * (1.0 + 1e-12)  # False where NaN
    return (2 * closed + opened - 1).astype(np.int8)  # exclusive: the rows' gap bounds the corners' gap


def _control_points(a: npt.ArrayLike, shape_prefix: tuple, what: str) -> np.ndarray:
    cp = _as_float(a, f"{what}: control_points")
    if cp.shape[:-1] != shape_prefix or cp.shape[-1] not in (2, 3):
        raise NurbsError(
            f"{what}: control_points must have shape {(*shape_prefix, 3)}, got {cp.shape}"
        )
    if cp.shape[-1] == 2:  # planar data: z = 0
        cp = np.concatenate([cp, np.zeros((*cp.shape[:-1], 1))], axis=-1)
    if not np.isfinite(cp).all():
        raise NurbsError(f"{what}: control points contain NaN or infinite values")
    return cp


def _weights(a: npt.ArrayLike, shape: tuple, what: str) -> np.ndarray:
    w = _as_float(a, f"{what}: weights")
    if w.shape != shape:
        raise NurbsError(f"{what}: weights must have shape {shape}, got {w.shape}")
    if not ((w > 0) & (w < np.inf)).all():  # positive and finite (NaN fails both)
        bad = np.flatnonzero(~(np.isfinite(w) & (w > 0)).ravel())[0]
        raise NurbsError(
            f"{what}: weights must be positive and finite, got {w.ravel()[bad]!r} "
            f"at flat index {bad}"
        )
    return w


# ----------------------------------------------------------------------
# curves
# ----------------------------------------------------------------------
def _domain(knots: np.ndarray, p: int) -> tuple[float, float]:
    """Parameter domain ``(knots[p], knots[-p-1])`` of a clamped knot vector of degree ``p``."""
    return float(knots[p]), float(knots[-p - 1])


class _ControlNet:
    """The bounding box of a curve's or surface's control points, which contains it."""

    control_points: np.ndarray
    _size: float

    @property
    def bbox_size(self) -> float:
        """Diagonal of the control points' bounding box (length units)."""
        return self._size

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo (3,), hi (3,))`` corners of the control points' bounding box."""
        cp = self.control_points.reshape(-1, 3)
        return cp.min(axis=0), cp.max(axis=0)


@dataclass(frozen=True, eq=False)
class NurbsCurve(_ControlNet):
    """Rational B-spline (NURBS) curve in 3-D (planar curves have z = 0).

    ``C(u) = sum_i N_{i,p}(u) w_i P_i / sum_i N_{i,p}(u) w_i`` (Kadir, A.5.1).

    Attributes:
        degree: polynomial degree ``p >= 1``.
        knots: ``(m,)`` non-decreasing knot vector, ``m = n + p + 1``.
        control_points: ``(n, 3)`` control points (``(n, 2)`` accepted, z = 0).
        weights: ``(n,)`` positive weights.

    Arrays are copied to float64 and made read-only.  Equality is identity.

    Raises:
        NurbsError: inconsistent sizes, decreasing knots, knot multiplicity
            above ``p + 1``, non-positive or non-finite weights, non-finite
            control points or knots.
    """

    degree: int
    knots: np.ndarray
    control_points: np.ndarray
    weights: np.ndarray
    # derived in __post_init__ (homogeneous control points (4, n), span table, bbox size, closedness)
    _pwT: np.ndarray = field(init=False, repr=False)
    _spans: np.ndarray = field(init=False, repr=False)
    _size: float = field(init=False, repr=False)
    #: True if ``C(u0)`` and ``C(u1)`` coincide within 1e-9 x bounding-box size
    is_closed: bool = field(init=False, repr=False)

    #: number of parameters of the entity (1 for curves)
    param_dim = 1
    #: a curve's parameter is fixed by its point even where ``C' = 0`` (only a
    #: surface has iso-lines that collapse to a point, see :attr:`NurbsSurface.can_degenerate`)
    can_degenerate = False

    def __post_init__(self) -> None:
        what = "NurbsCurve"
        if isinstance(self.degree, bool) or int(self.degree) != self.degree:
            raise NurbsError(f"{what}: degree must be an integer, got {self.degree!r}")
        object.__setattr__(self, "degree", int(self.degree))
        knots = _as_float(self.knots, f"{what}: knots")
        cp = _as_float(self.control_points, f"{what}: control_points")
        if cp.ndim != 2:
            raise NurbsError(f"{what}: control_points must have shape (n, 3), got {cp.shape}")
        n = cp.shape[0]
        cp = _control_points(cp, (n,), what)
        w = _weights(self.weights, (n,), what)
        _check_knots(knots, self.degree, n, what)
        _freeze(self, "knots", knots)
        _freeze(self, "control_points", cp)
        _freeze(self, "weights", w)
        # homogeneous control points (w P, w) as (4, n), points last, written in place
        pwT = np.empty((4, n))
        np.multiply(cp.T, w, out=pwT[:3])
        pwT[3] = w
        _freeze(self, "_pwT", pwT)
        _freeze(self, "_spans", _span_table(knots, self.degree, n))
        object.__setattr__(self, "_size", _bbox_size(cp))
        known = -1
        if all(_clamped_ends(knots, self.degree, n)):  # the ends are the end control points
            d = cp[0] - cp[-1]
            gap = np.sqrt(d @ d)
            known = int(_closed_by_net(gap, gap, np.abs(cp).max(), self.degree, self._size))
        if known < 0:
            u0, u1 = self.domain
            ends = self._eval_soa(np.array([[u0, u1]]), 0)[0]  # (3, 2)
            gap = ends[:, 0] - ends[:, 1]
            known = int(np.sqrt(gap @ gap) <= CLOSED_RTOL * max(self._size, 1e-300))
        object.__setattr__(self, "is_closed", bool(known))

    # -- properties ----------------------------------------------------
    @property
    def n_ctrl(self) -> int:
        """Number of control points ``n``."""
        return int(self.control_points.shape[0])

    @property
    def domain(self) -> tuple[float, float]:
        """Parameter domain ``(u0, u1) = (knots[p], knots[-p-1])``."""
        return _domain(self.knots, self.degree)

    @property
    def bounds(self) -> np.ndarray:
        """``(1, 2)`` parameter bounds, the generic form of :attr:`domain`."""
        return np.array([self.domain])

    @property
    def closed(self) -> tuple[bool]:
        """``(is_closed,)``, the generic per-direction form."""
        return (self.is_closed,)

    @property
    def period(self) -> float | None:
        """``u1 - u0`` if closed, else ``None``."""
        u0, u1 = self.domain
        return (u1 - u0) if self.is_closed else None

    @property
    def distinct_knots(self) -> np.ndarray:
        """Distinct knot values inside the domain (span boundaries), ``(s+1,)``."""
        u0, u1 = self.domain
        k = np.unique(self.knots)
        return k[(k >= u0) & (k <= u1)]

    # -- evaluation ----------------------------------------------------
    def wrap(self, u: npt.ArrayLike) -> np.ndarray:
        """Parameters brought into the domain: modulo the period if closed, else clamped."""
        u = np.atleast_1d(np.asarray(u, dtype=float))
        u0, u1 = self.domain
        return _wrap_or_clamp(u, u0, u1, self.is_closed)

    def evaluate(self, u: npt.ArrayLike, nderiv: int = 0) -> np.ndarray:
        """Points and derivatives of the curve, vectorised over ``u``.

        Args:
            u: ``(k,)`` parameters (a scalar is treated as ``k = 1``).  Outside
                the domain they are wrapped (closed curve) or clamped (open).
            nderiv: 0, 1 or 2.

        Returns:
            ``(nderiv+1, k, 3)``: ``C``, ``C'``, ``C''`` (length units, per
            parameter unit to the power of the derivative order).  Rational
            derivatives from Neto (2010) App. C eqs. (42)-(43), see module docs.
        """
        nderiv = _check_nderiv(nderiv)
        return self._evaluate_inside(self.wrap(u), nderiv)

    def _evaluate_inside(self, u: np.ndarray, nderiv: int) -> np.ndarray:
        """``(nderiv+1, k, 3)`` at parameters already inside the domain."""
        return self._eval_soa(u[None, :], nderiv).transpose(0, 2, 1)

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        """Kernel: ``params (1, k)`` inside the domain -> ``(nderiv+1, 3, k)``.

        Homogeneous sums ``A^{(d)} = sum N^{(d)}_i w_i P_i``, ``B^{(d)} = sum N^{(d)}_i w_i``
        and the quotient rule of Neto (2010) eqs. (42)-(43) (see module docs).
        """
        u = np.ascontiguousarray(params[0])
        p = self.degree
        span = find_span(self.knots, p, self.n_ctrl, u, self._spans)
        H = NurbsCurve._sums(self.knots, self._pwT, p, span, span - p, u, nderiv)  # (nd+1, 4, k)
        A, B = H[:, :3], H[:, 3]
        out = np.empty((nderiv + 1, 3, u.shape[0]))
        out[0] = A[0] / B[0]
        if nderiv >= 1:
            out[1] = (A[1] - B[1] * out[0]) / B[0]
        if nderiv >= 2:
            out[2] = (A[2] - 2.0 * B[1] * out[1] - B[2] * out[0]) / B[0]
        return out

    @staticmethod
    def _sums(knots: np.ndarray, pw: np.ndarray, p: int, span: np.ndarray, first: np.ndarray,
              u: np.ndarray, nderiv: int) -> np.ndarray:
        """Homogeneous sums ``(nderiv+1, c, k)``: ``sum_a N^{(d)}_{s-p+a,p}(u) pw[:, first + a]``.

        ``u (k,)`` in the knot spans ``span (k,)`` of ``knots`` (:func:`find_span`),
        whose ``p + 1`` non-zero basis functions (:func:`_basis_soa`) weight the
        columns ``first .. first + p`` of the homogeneous control points ``pw (c, n)``
        (rows ``w P`` and ``w``).  One curve: ``first = span - p``; several curves
        of degree ``p`` packed end to end (their knots concatenated, and their
        columns): ``span`` indexes the concatenated knots, ``first`` the columns.
        """
        H = np.empty((nderiv + 1, pw.shape[0], u.shape[0]))
        return _kernels.curve_sums(knots, pw, p, np.ascontiguousarray(span, dtype=np.int64),
                                   np.ascontiguousarray(first, dtype=np.int64), u, nderiv, H)

    @classmethod
    def many(cls, degrees: Sequence[int], knots: Sequence[Any], control_points: Sequence[Any],
             weights: Sequence[Any]) -> list[NurbsCurve]:
        """``NurbsCurve(degrees[i], knots[i], control_points[i], weights[i])`` for every ``i``
        (weights None: all 1), built together: the checks, the derived data and the ends
        (closedness) of all curves at once (:class:`NurbsCurve.Packed`); the same curves to
        the last bit.  Fewer than :data:`MANY_MIN` curves are built by their constructor
        (packing costs more than their checks).

        Raises:
            NurbsError: the first invalid curve's (then built one by one).
        """
        pk = cls.Packed.checked(degrees, knots, control_points, weights) if len(degrees) >= MANY_MIN else None
        if pk is None:  # few curves, or an invalid (or unusual) one: each checks itself, in order
            return [cls(p, k, P, np.ones(len(P)) if w is None else w)
                    for p, k, P, w in zip(degrees, knots, control_points, weights, strict=True)]
        ns = len(pk.p)
        cs = np.arange(ns)
        closed, size = pk.closed(cs)
        P = pk.P if pk.P.shape[1] == 3 else np.concatenate([pk.P, np.zeros((len(pk.P), 1))], axis=1)
        W = pk.W if pk.P.shape[1] == 3 else np.concatenate([pk.W[:2], np.zeros((1, len(pk.P))), pk.W[2:]])
        spans, soff = pk.span_tables()
        ko, po = pk.koff.tolist(), pk.poff.tolist()
        out = []
        for i, (p, c, sz) in enumerate(zip(pk.p.tolist(), closed.tolist(), size.tolist(), strict=True)):  # objects
            obj = cls.__new__(cls)
            object.__setattr__(obj, "degree", p)
            _freeze(obj, "knots", pk.K[ko[i]:ko[i + 1]])
            _freeze(obj, "control_points", P[po[i]:po[i + 1]])
            _freeze(obj, "weights", pk.w[po[i]:po[i + 1]])
            _freeze(obj, "_pwT", W[:, po[i]:po[i + 1]])
            _freeze(obj, "_spans", spans[soff[i]:soff[i + 1]])
            object.__setattr__(obj, "_size", sz)
            object.__setattr__(obj, "is_closed", c)
            out.append(obj)
        return out

    class Packed:
        """Many NURBS curves packed end to end and evaluated together (no object per curve).

        Curve ``c`` has degree ``p[c]``, knots ``K[koff[c]:koff[c + 1]]``, control
        points ``P[poff[c]:poff[c + 1]]`` (``(N, d)``, ``d`` 2 or 3) with weights ``w``
        (the homogeneous ``W (d + 1, N)``: rows ``w P``, ``w``) and the domain ``[lo[c],
        hi[c]]``.  :meth:`points` evaluates points of all curves as
        :meth:`NurbsCurve._eval_soa` evaluates each, to the last bit: the knot span of a
        point found as :func:`find_span` finds it (the knots of its curve up to it,
        counted by two sorted searches over all curves: one over the distinct knot
        values, a rank, one over the knots' ``(curve, rank)`` keys), the kernel
        :meth:`NurbsCurve._sums` once per distinct degree.

        Args:
            p: ``(n_curves,)`` degrees ``p >= 1``.
            m: ``(n_curves,)`` number of knots of each curve (``n + p + 1``).
            K: the curves' knots, concatenated.
            P: ``(N, d)`` the curves' control points, concatenated.
            w: ``(N,)`` their weights.

        The data is taken as valid (see :meth:`checked`; :meth:`of` packs curve objects).
        """

        def __init__(self, p: np.ndarray, m: np.ndarray, K: np.ndarray, P: np.ndarray, w: np.ndarray):
            self.p, self.n = p, m - p - 1
            self.koff = np.zeros(len(m) + 1, dtype=np.int64)
            np.cumsum(m, out=self.koff[1:])
            self.poff = np.zeros(len(m) + 1, dtype=np.int64)
            np.cumsum(self.n, out=self.poff[1:])
            self.K, self.P, self.w = K, P, w
            self.W = np.empty((P.shape[1] + 1, len(P)))  # rows w P, w
            np.multiply(P.T, w, out=self.W[:-1])
            self.W[-1] = w
            #: curve of every knot
            self.ck = np.repeat(np.arange(len(m)), m)
            start = self.koff[:-1]
            self.lo, self.hi = K[start + p], K[start + self.n]
            # span table (_span_table of every curve): the last non-empty span s <= i with
            # p <= s <= n - 1, else the first non-empty one
            i = np.arange(len(K)) - start[self.ck]
            ok = (i >= p[self.ck]) & (i < self.n[self.ck])
            ok[:-1] &= K[:-1] < K[1:]
            g = np.where(ok, np.arange(len(K)), -1)
            last = np.maximum.accumulate(g)
            g[~ok] = len(K)
            first = np.minimum.reduceat(g, start)
            #: global knot index of the span of each (clipped) ``searchsorted`` result
            self.table = np.where(last >= start[self.ck], last, first[self.ck])
            self.degrees = sorted(set(p.tolist()))

        @cached_property
        def _lookup(self) -> tuple[np.ndarray, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            """``(U, base, key, lo, hi, shift)`` for :meth:`points` (computed when first
            evaluated): the distinct knot values ``U``; the ``(curve, rank)`` key ``curve base +
            rank`` of every knot (its rank: the number of values ``<=`` it); per curve the
            global indices ``lo = koff + p``, ``hi = koff + n - 1`` of its first and last
            span, and ``shift = poff - koff - p`` from its span to its first control point."""
            U = np.sort(self.K)  # np.unique's values (sorted, each once), with less overhead
            U = U[np.concatenate([[True], U[1:] != U[:-1]])]
            base = len(U) + 1
            start = self.koff[:-1]
            return (U, base, self.ck * base + U.searchsorted(self.K, side="right"), start + self.p,
                    start + self.n - 1, self.poff[:-1] - start - self.p)

        @classmethod
        def of(cls, curves: Sequence[NurbsCurve]) -> NurbsCurve.Packed:
            """The curves ``curves`` packed."""
            return cls(np.array([c.degree for c in curves]), np.array([len(c.knots) for c in curves]),
                       np.concatenate([c.knots for c in curves]), np.concatenate([c.control_points for c in curves]),
                       np.concatenate([c.weights for c in curves]))

        @classmethod
        def checked(cls, degrees: Sequence, knots: Sequence, poles: Sequence,
                    weights: Sequence) -> NurbsCurve.Packed | None:
            """The curves packed if every one passes :class:`NurbsCurve`'s checks (done here
            together: an integer degree ``p >= 1``, ``n > p`` finite control points of one
            width 2 or 3 for all, ``n + p + 1`` finite non-decreasing knots of multiplicity
            at most ``p + 1``, a non-empty domain, positive finite weights or None); else
            None (the constructor then decides, curve by curve)."""
            ps: list[int] = []
            ks: list[np.ndarray] = []
            Ps: list[np.ndarray] = []
            rational: list[tuple[int, np.ndarray]] = []
            try:
                for p, k, P, w in zip(degrees, knots, poles, weights, strict=True):  # loop over curves (sizes)
                    k, P = np.asarray(k, dtype=float), np.asarray(P, dtype=float)
                    if isinstance(p, bool) or not isinstance(p, (int, np.integer)) or p < 1 or k.ndim != 1 or \
                            P.ndim != 2 or P.shape[1] not in (2, 3) or len(k) != len(P) + p + 1 or len(P) <= p:
                        return None
                    if w is not None:
                        w = np.asarray(w, dtype=float)
                        if w.shape != (len(P),):
                            return None
                        rational.append((len(Ps), w))
                    ps.append(int(p))
                    ks.append(k)
                    Ps.append(P)
            except (TypeError, ValueError):
                return None
            if not ps or len({P.shape[1] for P in Ps}) != 1:
                return None
            P = np.concatenate(Ps)
            p, n = np.array(ps), np.array([len(a) for a in Ps])
            w = np.ones(len(P))
            if rational:
                poff = np.concatenate([[0], np.cumsum(n)])
                for j, wj in rational:  # loop over rational curves (their weights)
                    w[poff[j]:poff[j + 1]] = wj
            K = np.concatenate(ks)
            m = n + p + 1
            koff = np.concatenate([[0], np.cumsum(m)])
            i = np.arange(len(P)) + np.repeat(koff[:-1] + n - np.cumsum(n), n)  # each support's first knot
            dK = K[1:] - K[:-1]
            dK[koff[1:-1] - 1] = 0.0  # across curves
            ok = (np.isfinite(K).all() and np.isfinite(P).all() and ((w > 0) & (w < np.inf)).all()
                  and (dK >= 0).all() and (K[i + np.repeat(p, n) + 1] > K[i]).all()
                  and (K[koff[:-1] + p] < K[koff[:-1] + n]).all())
            return cls(p, m, K, P, w) if ok else None

        def span_tables(self) -> tuple[np.ndarray, list[int]]:
            """``(tables, offsets)``: every curve's :func:`_span_table` (``m + 1`` entries: the
            span of a parameter by its ``searchsorted`` index ``i``, the last non-empty span
            ``s <= clip(i - 1, p, n - 1)``), concatenated; curve ``c``'s from ``offsets[c]``."""
            m = self.n + self.p + 1
            c = np.repeat(np.arange(len(m)), m + 1)
            i = np.arange(len(c)) - np.repeat(np.cumsum(m + 1) - m - 1, m + 1)  # 0..m per curve
            start = self.koff[c]
            tables = self.table[start + np.minimum(np.maximum(i - 1, self.p[c]), self.n[c] - 1)] - start
            return tables, np.concatenate([[0], np.cumsum(m + 1)]).tolist()

        def points(self, t: np.ndarray, c: np.ndarray) -> np.ndarray:
            """``(k, d)`` points at ``t (k,)`` (inside the domains) of curves ``c (k,)`` (grouped
            by curve, in curve order), as each curve's :meth:`NurbsCurve._eval_soa` gives them."""
            U, base, key, lo, hi, shift = self._lookup
            q = U.searchsorted(t, side="right")
            cnt = key.searchsorted(c * base + q, side="right")  # knots <= t, and those of the curves before
            span = self.table[np.minimum(np.maximum(cnt - 1, lo[c]), hi[c])]
            first = span + shift[c]
            d = self.P.shape[1]
            out = np.empty((len(t), d))
            pc = self.p[c] if len(self.degrees) > 1 else None
            for p in self.degrees:  # loop over the distinct degrees
                sel = slice(None) if pc is None else np.flatnonzero(pc == p)
                H = NurbsCurve._sums(self.K, self.W, p, span[sel], first[sel], t[sel], 0)[0]
                if pc is None:  # one degree: straight into out
                    np.divide(H[:d], H[d], out=out.T)
                else:  # coordinate by coordinate (fancy indexing of rows of 2 or 3 iterates row by row)
                    for j, x in enumerate(H[:d] / H[d]):
                        out[:, j][sel] = x
            return out

        def closed(self, cs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """``(closed, size)`` of curves ``cs (k,)`` (sorted), as :attr:`NurbsCurve.is_closed`
            and :attr:`NurbsCurve.bbox_size`: both ends within :data:`CLOSED_RTOL` of the
            control points' box diagonal ``size``; decided from the end control points where
            the knots are clamped (:func:`_closed_by_net`), else from the evaluated ends."""
            d = self.P.shape[1]
            first, last = self.poff[:-1], self.poff[1:] - 1
            box = np.zeros((len(cs), 3))  # 3-vectors (z = 0 for 2D)
            box[:, :d] = (np.maximum.reduceat(self.P, first) - np.minimum.reduceat(self.P, first))[cs]
            size = np.sqrt(np.vecdot(box, box))
            p, start, end = self.p[cs], self.koff[cs], self.koff[cs] + self.n[cs]
            K = self.K
            clamped = (K[start + 1] == K[start + p]) & (K[end] == K[end + p - 1])  # as _clamped_ends
            e = self.P[first[cs]] - self.P[last[cs]]  # end control points (the ends, if clamped)
            gap = np.sqrt(np.vecdot(e, e))
            scale = np.maximum.reduceat(np.abs(self.P).max(axis=1), first)[cs]
            known = _closed_by_net(np.where(clamped, gap, np.inf), np.where(clamped, gap, np.nan), scale, p, size)
            todo = np.flatnonzero(known < 0)
            if todo.size:  # the ends evaluated
                ct = cs[todo]
                ends = self.points(np.stack([self.lo[ct], self.hi[ct]], axis=1).ravel(), np.repeat(ct, 2))
                g = np.zeros((len(ct), 3))
                g[:, :d] = ends[0::2] - ends[1::2]
                known[todo] = np.sqrt(np.vecdot(g, g)) <= CLOSED_RTOL * np.maximum(size[todo], 1e-300)
            return known == 1, size

    def __repr__(self) -> str:
        return (
            f"NurbsCurve(degree={self.degree}, n_ctrl={self.n_ctrl}, domain={self.domain}, "
            f"closed={self.is_closed})"
        )


# ----------------------------------------------------------------------
# surfaces
# ----------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class NurbsSurface(_ControlNet):
    """Tensor-product NURBS surface (Kadir, A.5.2; Herrero Adan eqs. (2), (4)).

    ``S(u,v) = sum_ij N_{i,p}(u) N_{j,q}(v) w_ij P_ij / sum_ij N_{i,p}(u) N_{j,q}(v) w_ij``.

    Attributes:
        degree_u, degree_v: degrees ``p, q >= 1``.
        knots_u: ``(mu,)`` knots, ``mu = nu + p + 1``.
        knots_v: ``(mv,)`` knots, ``mv = nv + q + 1``.
        control_points: ``(nu, nv, 3)`` control net, first index along ``u``.
        weights: ``(nu, nv)`` positive weights.

    Raises:
        NurbsError: as for :class:`NurbsCurve`.
    """

    degree_u: int
    degree_v: int
    knots_u: np.ndarray
    knots_v: np.ndarray
    control_points: np.ndarray
    weights: np.ndarray
    # derived in __post_init__: control net (channels, nu nv) and whether it is rational,
    # span tables, bbox size, closedness
    _pwT: np.ndarray = field(init=False, repr=False)
    _rational: bool = field(init=False, repr=False)
    _spans_u: np.ndarray = field(init=False, repr=False)
    _spans_v: np.ndarray = field(init=False, repr=False)
    _size: float = field(init=False, repr=False)
    #: True if the boundary curves ``u = u0`` and ``u = u1`` (``v = v0``, ``v = v1``)
    #: coincide within 1e-9 x bounding-box size
    closed_u: bool = field(init=False, repr=False)
    closed_v: bool = field(init=False, repr=False)

    #: number of parameters of the entity (2 for surfaces)
    param_dim = 2

    def __post_init__(self) -> None:
        what = "NurbsSurface"
        for name in ("degree_u", "degree_v"):
            val = getattr(self, name)
            if isinstance(val, bool) or int(val) != val:
                raise NurbsError(f"{what}: {name} must be an integer, got {val!r}")
            object.__setattr__(self, name, int(val))
        ku = _as_float(self.knots_u, f"{what}: knots_u")
        kv = _as_float(self.knots_v, f"{what}: knots_v")
        cp = _as_float(self.control_points, f"{what}: control_points")
        if cp.ndim != 3:
            raise NurbsError(
                f"{what}: control_points must have shape (nu, nv, 3), got {cp.shape}"
            )
        nu, nv = cp.shape[:2]
        cp = _control_points(cp, (nu, nv), what)
        w = _weights(self.weights, (nu, nv), what)
        _check_knots(ku, self.degree_u, nu, f"{what} (u direction)")
        _check_knots(kv, self.degree_v, nv, f"{what} (v direction)")
        _freeze(self, "knots_u", ku)
        _freeze(self, "knots_v", kv)
        _freeze(self, "control_points", cp)
        _freeze(self, "weights", w)
        # control net as (channels, nu * nv), row-major over (i, j): homogeneous (w P, w),
        # or the points alone where every weight is the same (the weights cancel in A / B)
        rational = bool(np.any(w != w.flat[0]))
        object.__setattr__(self, "_rational", rational)
        net = np.concatenate([cp * w[..., None], w[..., None]], axis=-1) if rational else cp
        _freeze(self, "_pwT", net.reshape(nu * nv, -1).T)
        _freeze(self, "_spans_u", _span_table(ku, self.degree_u, nu))
        _freeze(self, "_spans_v", _span_table(kv, self.degree_v, nv))
        object.__setattr__(self, "_size", _bbox_size(cp))
        known = self._closed_by_net()
        object.__setattr__(self, "closed_u", self._boundaries_coincide(0) if known[0] < 0 else bool(known[0]))
        object.__setattr__(self, "closed_v", self._boundaries_coincide(1) if known[1] < 0 else bool(known[1]))

    def _closed_by_net(self) -> np.ndarray:
        """``(2,)`` int8 per direction: the outcome of :meth:`_boundaries_coincide` where the
        control net decides it (:func:`_closed_by_net`: 1 closed, 0 open), else -1."""
        cp, w = self.control_points, self.weights
        nu, nv = cp.shape[:2]
        u0, u1 = _clamped_ends(self.knots_u, self.degree_u, nu)
        v0, v1 = _clamped_ends(self.knots_v, self.degree_v, nv)
        rows, ends = [np.inf, np.inf], [np.nan, np.nan]
        for a, (clamped, c0, c1) in enumerate(((u0 and u1, v0, v1), (v0 and v1, u0, u1))):  # the two directions
            if not clamped:
                continue
            lo, hi = (np.s_[0], np.s_[-1]) if a == 0 else (np.s_[:, 0], np.s_[:, -1])  # the boundary rows
            d = cp[lo] - cp[hi]
            gap = np.sqrt(np.vecdot(d, d))  # (row,) control-point distances
            if not self._rational or (w[lo] == w[hi]).all():
                rows[a] = float(gap.max())
            corners = [g for g, c in ((gap[0], c0), (gap[-1], c1)) if c]
            if corners:
                ends[a] = float(max(corners))
        return _closed_by_net(np.array(rows), np.array(ends), float(np.abs(cp).max()),
                              self.degree_u + self.degree_v, self._size)

    def _boundaries_coincide(self, direction: int) -> bool:
        """Do the boundary curves at both ends of ``direction`` coincide?

        Compared at the distinct knots of the other direction and at 7 points
        inside each of its spans (a sampling test, exact for identical rows).
        :meth:`_closed_by_net` decides most surfaces as this does, from the net.
        """
        (u0, u1), (v0, v1) = self.domain_u, self.domain_v
        other = self.knots_v if direction == 0 else self.knots_u
        lo, hi = (v0, v1) if direction == 0 else (u0, u1)
        k = np.unique(other)
        k = k[(k >= lo) & (k <= hi)]
        t = np.linspace(0.0, 1.0, 9)[:-1]
        s = np.concatenate([(k[:-1, None] + np.outer(np.diff(k), t)).ravel(), [hi]])
        ends = np.repeat([u0, u1] if direction == 0 else [v0, v1], len(s))
        ss = np.tile(s, 2)
        ab = self._eval_soa(np.stack([ends, ss] if direction == 0 else [ss, ends]), 0)[0]  # (3, 2 m), both curves
        gap = np.max(np.linalg.norm((ab[:, :len(s)] - ab[:, len(s):]).T, axis=1))
        return bool(gap <= CLOSED_RTOL * max(self._size, 1e-300))

    # -- properties ----------------------------------------------------
    @cached_property
    def can_degenerate(self) -> bool:
        """Can a parameter be arbitrary at a point (a pole, a collapsed edge)?

        That needs an iso-line collapsed to a point.  At a clamped end, and
        where a knot of full multiplicity makes the surface interpolate a row
        of the net, the iso-line is the B-spline of that row, which is a point
        only if the row's control points coincide.  True if some row or column
        of the net does (within 1e-9 x bounding-box size); then
        :func:`nagata_snap.cad.params.degenerate` evaluates the tangents.  (An
        iso-line between rows collapses only where rows that do not coincide
        blend to one point; this test does not catch that.)
        """
        cp = self.control_points
        tol = CLOSED_RTOL * max(self._size, 1e-300)
        along_u = np.ptp(cp, axis=0).max(axis=-1)  # (nv,): extent of each row of fixed j
        along_v = np.ptp(cp, axis=1).max(axis=-1)  # (nu,)
        return bool(along_u.min() <= tol or along_v.min() <= tol)

    @property
    def n_ctrl(self) -> tuple[int, int]:
        """``(nu, nv)`` control net size."""
        return int(self.control_points.shape[0]), int(self.control_points.shape[1])

    @property
    def domain_u(self) -> tuple[float, float]:
        """``(u0, u1) = (knots_u[p], knots_u[-p-1])``."""
        return _domain(self.knots_u, self.degree_u)

    @property
    def domain_v(self) -> tuple[float, float]:
        """``(v0, v1) = (knots_v[q], knots_v[-q-1])``."""
        return _domain(self.knots_v, self.degree_v)


    @cached_property
    def bounds(self) -> np.ndarray:
        """``(2, 2)`` parameter bounds ``[[u0, u1], [v0, v1]]`` (read-only)."""
        b = np.array([self.domain_u, self.domain_v])
        b.flags.writeable = False
        return b

    @property
    def closed(self) -> tuple[bool, bool]:
        """``(closed_u, closed_v)``."""
        return (self.closed_u, self.closed_v)

    @property
    def distinct_knots_u(self) -> np.ndarray:
        """Distinct ``u`` knots inside the domain."""
        u0, u1 = self.domain_u
        k = np.unique(self.knots_u)
        return k[(k >= u0) & (k <= u1)]

    @property
    def distinct_knots_v(self) -> np.ndarray:
        """Distinct ``v`` knots inside the domain."""
        v0, v1 = self.domain_v
        k = np.unique(self.knots_v)
        return k[(k >= v0) & (k <= v1)]

    # -- evaluation ----------------------------------------------------
    def wrap(self, u: npt.ArrayLike, v: npt.ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """``(u, v)`` brought into the domain: wrapped in closed, clamped in open directions."""
        u = np.atleast_1d(np.asarray(u, dtype=float))
        v = np.atleast_1d(np.asarray(v, dtype=float))
        (u0, u1), (v0, v1) = self.domain_u, self.domain_v
        return (
            _wrap_or_clamp(u, u0, u1, self.closed_u),
            _wrap_or_clamp(v, v0, v1, self.closed_v),
        )

    def evaluate(self, u: npt.ArrayLike, v: npt.ArrayLike, nderiv: int = 0) -> np.ndarray:
        """Points and partial derivatives, vectorised over ``k`` parameter pairs.

        Args:
            u, v: ``(k,)`` parameters (broadcast against each other).  Outside
                the domain they are wrapped/clamped per direction.
            nderiv: 0, 1 or 2.

        Returns:
            ``(1, k, 3)`` ``[S]`` for ``nderiv=0``; ``(3, k, 3)``
            ``[S, Su, Sv]`` for 1; ``(6, k, 3)`` ``[S, Su, Sv, Suu, Suv, Svv]``
            for 2.  Rational derivatives by Neto (2010) App. C eqs. (42)-(45).
        """
        nderiv = _check_nderiv(nderiv)
        u, v = np.broadcast_arrays(
            np.atleast_1d(np.asarray(u, dtype=float)), np.atleast_1d(np.asarray(v, dtype=float))
        )
        u, v = self.wrap(u.ravel(), v.ravel())
        return self._evaluate_inside(u, v, nderiv)

    def _evaluate_inside(self, u: np.ndarray, v: np.ndarray, nderiv: int) -> np.ndarray:
        """``(1|3|6, k, 3)`` at parameters already inside the domain."""
        return self._eval_soa(np.stack([u, v]), nderiv).transpose(0, 2, 1)

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray:
        """Kernel: ``params (2, k)`` inside the domain -> ``(1|3|6, 3, k)``.

        Homogeneous sums ``A_ab = sum_ij N^{(a)}_i(u) N^{(b)}_j(v) w_ij P_ij``
        and ``B_ab`` (Neto 2010, eqs. (40)-(41), (45)) contracted first along
        ``v`` then along ``u``; quotient rule eqs. (42)-(44) (see module docs).
        With equal weights ``B`` is constant and ``S_ab = sum_ij N^{(a)}_i N^{(b)}_j P_ij``
        directly (no quotient).  The chunks share one set of work arrays.
        """
        u, v = params[0], params[1]
        p, q = self.degree_u, self.degree_v
        nu, nv = self.n_ctrl
        su = find_span(self.knots_u, p, nu, u, self._spans_u)
        sv = find_span(self.knots_v, q, nv, v, self._spans_v)
        oa, ob = _ORDER_ARRAYS[nderiv]
        out = np.empty((len(oa), 3, u.shape[0]))
        return _kernels.surface_points(self.knots_u, self.knots_v, p, q, nv, self._pwT, su, sv,
                                       np.ascontiguousarray(u), np.ascontiguousarray(v), nderiv, oa, ob, out)

    def __repr__(self) -> str:
        return (
            f"NurbsSurface(degree=({self.degree_u}, {self.degree_v}), n_ctrl={self.n_ctrl}, "
            f"domain=({self.domain_u}, {self.domain_v}), closed=({self.closed_u}, {self.closed_v}))"
        )


# ----------------------------------------------------------------------
# exact conic constructions (rational quadratic)
# ----------------------------------------------------------------------
#: knots of the 9-point rational quadratic full circle (four 90-degree arcs)
CIRCLE_KNOTS = np.array([0, 0, 0, 0.25, 0.25, 0.5, 0.5, 0.75, 0.75, 1, 1, 1], dtype=float)
#: its weights: 1 at the points on the circle, cos(45 deg) = sqrt(2)/2 at the square's corners
CIRCLE_WEIGHTS = np.array([1, np.sqrt(0.5)] * 4 + [1], dtype=float)
#: unit-square control polygon of the full circle, starting at angle 0, counter-clockwise
_CIRCLE_NET = np.array(
    [[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1], [1, 0]], dtype=float
)
#: half circle from angle -90 to +90 degrees (south to north pole): (radial, axial) net
_HALF_NET = np.array([[0, -1], [1, -1], [1, 0], [1, 1], [0, 1]], dtype=float)
_HALF_KNOTS = np.array([0, 0, 0, 0.5, 0.5, 1, 1, 1], dtype=float)
_HALF_WEIGHTS = np.array([1, np.sqrt(0.5), 1, np.sqrt(0.5), 1], dtype=float)


def _frame(axis: npt.ArrayLike, xaxis: npt.ArrayLike | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z = np.asarray(axis, dtype=float)
    z = z / np.linalg.norm(z)
    if xaxis is None:
        t = np.eye(3)[np.argmin(np.abs(z))]
        xaxis = t - np.dot(t, z) * z
    x = np.asarray(xaxis, dtype=float)
    x = x - np.dot(x, z) * z
    x = x / np.linalg.norm(x)
    return x, np.cross(z, x), z


def circle(
    center: npt.ArrayLike = (0.0, 0.0, 0.0),
    radius: float = 1.0,
    axis: npt.ArrayLike = (0.0, 0.0, 1.0),
    xaxis: npt.ArrayLike | None = (1.0, 0.0, 0.0),
) -> NurbsCurve:
    """Exact full circle: degree 2, 9 control points on a square, weights 1 and sqrt(2)/2.

    The construction of Kadir (2010) App. C.3 (IGES File 1) with exact
    weights.  ``C(0) = center + radius * xaxis``; counter-clockwise about
    ``axis``; parameter domain ``[0, 1]`` (not proportional to the angle).
    """
    x, y, _ = _frame(axis, xaxis)
    c = np.asarray(center, dtype=float)
    P = c + radius * (_CIRCLE_NET[:, :1] * x + _CIRCLE_NET[:, 1:] * y)
    return NurbsCurve(2, CIRCLE_KNOTS, P, CIRCLE_WEIGHTS)


def cylinder(
    center: npt.ArrayLike = (0.0, 0.0, 0.0),
    radius: float = 1.0,
    height: float = 1.0,
    axis: npt.ArrayLike = (0.0, 0.0, 1.0),
    xaxis: npt.ArrayLike | None = (1.0, 0.0, 0.0),
) -> NurbsSurface:
    """Exact cylinder side: ``u`` around the axis (closed circle), ``v`` along it (degree 1).

    As Kadir (2010) App. C.3 (IGES File 2): the circle of :func:`circle`
    extruded by ``height`` along ``axis`` from the base centre ``center``.
    """
    x, y, z = _frame(axis, xaxis)
    c = np.asarray(center, dtype=float)
    ring = radius * (_CIRCLE_NET[:, :1] * x + _CIRCLE_NET[:, 1:] * y)
    P = np.stack([c + ring, c + ring + height * z], axis=1)  # (9, 2, 3)
    W = np.stack([CIRCLE_WEIGHTS, CIRCLE_WEIGHTS], axis=1)
    return NurbsSurface(2, 1, CIRCLE_KNOTS, np.array([0.0, 0.0, 1.0, 1.0]), P, W)


def sphere(
    center: npt.ArrayLike = (0.0, 0.0, 0.0),
    radius: float = 1.0,
    axis: npt.ArrayLike = (0.0, 0.0, 1.0),
    xaxis: npt.ArrayLike | None = (1.0, 0.0, 0.0),
) -> NurbsSurface:
    """Exact sphere: ``u`` the meridian half circle from the south to the north pole
    (open, degenerate at both ends), ``v`` the longitude circle (closed).

    Surface of revolution: control points ``(rho_i cos, rho_i sin, z_i)`` of
    the two nets, weights the products of the two weight vectors.
    """
    x, y, z = _frame(axis, xaxis)
    c = np.asarray(center, dtype=float)
    rho, h = _HALF_NET[:, 0], _HALF_NET[:, 1]
    ring = _CIRCLE_NET[:, :1] * x + _CIRCLE_NET[:, 1:] * y  # (9, 3)
    P = c + radius * (rho[:, None, None] * ring[None] + h[:, None, None] * z)
    W = np.outer(_HALF_WEIGHTS, CIRCLE_WEIGHTS)
    return NurbsSurface(2, 2, _HALF_KNOTS, CIRCLE_KNOTS, P, W)


def torus(
    center: npt.ArrayLike = (0.0, 0.0, 0.0),
    major_radius: float = 2.0,
    minor_radius: float = 1.0,
    axis: npt.ArrayLike = (0.0, 0.0, 1.0),
    xaxis: npt.ArrayLike | None = (1.0, 0.0, 0.0),
) -> NurbsSurface:
    """Exact torus: ``u`` around the tube (closed), ``v`` around the axis (closed).

    The tube circle (radius ``minor_radius`` about ``major_radius`` from the
    axis) revolved about ``axis``; weights are products.
    """
    x, y, z = _frame(axis, xaxis)
    c = np.asarray(center, dtype=float)
    rho = major_radius + minor_radius * _CIRCLE_NET[:, 0]
    h = minor_radius * _CIRCLE_NET[:, 1]
    ring = _CIRCLE_NET[:, :1] * x + _CIRCLE_NET[:, 1:] * y
    P = c + rho[:, None, None] * ring[None] + h[:, None, None] * z
    W = np.outer(CIRCLE_WEIGHTS, CIRCLE_WEIGHTS)
    return NurbsSurface(2, 2, CIRCLE_KNOTS, CIRCLE_KNOTS, P, W)
