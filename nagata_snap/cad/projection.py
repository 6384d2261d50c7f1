"""Closest-point projection onto NURBS curves and surfaces (vectorised Newton).

Newton iteration of Kadir (2010), Appendix B (after Piegl & Tiller 1996):

* curves, eq. (B.1)::

      u_{i+1} = u_i - C'(u_i).(C(u_i) - P) / ( C''(u_i).(C(u_i) - P) + |C'(u_i)|^2 )

* surfaces, eq. (B.2): with ``r = S(u, v) - P`` solve ``f = r.S_u = 0``,
  ``g = r.S_v = 0`` by ``J_i delta_i = kappa_i`` where::

      J = [[|S_u|^2 + r.S_uu,  S_u.S_v + r.S_uv],
           [S_u.S_v + r.S_vu,  |S_v|^2 + r.S_vv]],   kappa = -[f, g]

  (identical to Neto (2010), App. B, eqs. (32)-(36)).

Convergence (Kadir, App. B.1/B.2), per point; converged points are frozen:

1. point coincidence ``|S - P| <= zero_tol``;
2. insignificant parameter change ``|(u_{i+1}-u_i) S_u + (v_{i+1}-v_i) S_v| <= tol``;
3. zero cosine ``|S_a . r| / (|S_a| |r|) <= cos_tol`` for every direction ``a``.

Two refinements of criterion 2 (not in the seed):

* the last, tiny Newton step is still applied, to first order:
  ``S(p + delta) = S(p) + S_a delta_a + O(|delta|^2)``, which costs no
  evaluation and leaves an error far below rounding;
* it is accepted only if a true Newton step (``J`` positive definite) and if
  the error predicted after it, ``C s^2`` with the quadratic-rate estimate
  ``C = s / s_prev^2`` from the last two step lengths, is below ``acc_tol``.
  This matters where the parameterisation degenerates (next to a pole the
  rate constant is ~1/(distance to the axis)); for well-seeded points it
  changes nothing.

An iteration is one Newton update; the final first-order update counts as
one (as in Kadir's counting, the step that meets criterion 2 is an
iteration).  With neighbour seeds (parametric midpoints of the parent edge)
Kadir's Table 4.2 reports mostly 2 iterations.

Parameters leaving the domain are clamped in open directions and wrapped
modulo the period in closed ones (Kadir, App. B.1, last paragraph).

Safeguards not in the seed (they are inactive for well-seeded points and do
not change the iteration there): where ``J`` is not positive definite (far
from a minimum, e.g. near a maximum of the distance) the Gauss-Newton matrix
``[S_a . S_b] + mu I`` replaces it; steps are capped to a quarter of the
parameter domain; a step that increases ``|S - P|`` is halved (at most
``max_halvings`` times).  A point clamped onto a collapsed boundary (the pole
of a sphere, where ``S_v = 0`` and ``v`` cannot be corrected by Newton) with
no descent into the domain is restarted from the ``v`` of steepest descent
(:func:`_escape_collapsed_edges`).

On a :class:`~nagata_snap.cad.nurbs.NurbsSurface` the same iteration runs compiled, one
point at a time (:func:`nagata_snap.cad.basis.surface_newton`: the same operations in the
same order, so the same iterates); curves and other entities run the vectorised loop.

:func:`global_search` finds seeds without brute force: each entity is sampled
once on a modest parameter grid, a KD-tree (``scipy.spatial.cKDTree``) of all
samples gives the ``k_seeds`` nearest samples of every query point, Newton
refines each, the best is kept.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol, TypeGuard, overload

import numpy as np
import numpy.typing as npt
from scipy.spatial import cKDTree

from nagata_snap.cad import basis as _kernels
from nagata_snap.cad.bounds import BoxClasses, cell_boxes
from nagata_snap.cad.curves import ArcBatch
from nagata_snap.cad.nurbs import NurbsSurface
from nagata_snap.mesh.arrays import Groups, best_per_group, dot, norms

__all__ = [
    "ProjectionResult",
    "project_newton",
    "GlobalSearcher",
    "AffineBatch",
    "global_search",
    "sample_entity",
    "normalize_params",
    "evaluate_params",
    "entity_periods",
    "project_points",
    "is_analytic",
]



class Entity(Protocol):
    """What the projection needs of a curve (``param_dim`` 1) or surface (2): a
    :class:`~nagata_snap.cad.nurbs.NurbsCurve`, :class:`~nagata_snap.cad.nurbs.NurbsSurface` or an analytic entity of
    :mod:`~nagata_snap.cad.surfaces` / :mod:`~nagata_snap.cad.curves`."""

    param_dim: int

    @property
    def bounds(self) -> np.ndarray: ...  # (d, 2) parameter box

    @property
    def closed(self) -> tuple[bool, ...]: ...  # per direction

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]: ...

    @property
    def bbox_size(self) -> float: ...

    def _eval_soa(self, params: np.ndarray, nderiv: int) -> np.ndarray: ...  # (d, k) -> (n, 3, k)


class AnalyticEntity(Entity, Protocol):
    """An entity with a closed-form projection (:func:`is_analytic`)."""

    def closest(self, points: npt.ArrayLike, seeds: npt.ArrayLike | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


def _distinct_knots(entity: Entity, a: int) -> np.ndarray:
    """Span boundaries of parameter direction ``a`` (``distinct_knots`` of a curve,
    ``distinct_knots_u`` / ``_v`` of a surface)."""
    name = "distinct_knots" if entity.param_dim == 1 else ("distinct_knots_u", "distinct_knots_v")[a]
    return np.asarray(getattr(entity, name))


#: default step-length tolerance (criterion 2), relative to the entity's bbox size
STEP_RTOL = 1e-9
#: default point-coincidence tolerance (criterion 1), relative to the bbox size
ZERO_RTOL = 1e-14
#: default zero-cosine tolerance (criterion 3)
COS_TOL = 1e-14
#: default accuracy demanded of the error predicted after the last step, relative to the bbox size
ACC_RTOL = 1e-14


@dataclass
class ProjectionResult:
    """Result of :func:`project_newton` for ``k`` points.

    Attributes:
        params: ``(k,)`` (curves) or ``(k, 2)`` (surfaces) parameters of the
            closest points, inside the domain (wrapped in closed directions).
        points: ``(k, 3)`` closest points ``S(params)`` (length units).
        distance: ``(k,)`` residual distance ``|S(params) - P|`` (length units).
        iterations: ``(k,)`` int64, Newton updates applied per point (0 if
            the seed already satisfied a convergence criterion).
        converged: ``(k,)`` bool, a criterion of Kadir App. B was met.
    """

    params: np.ndarray
    points: np.ndarray
    distance: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray


# ----------------------------------------------------------------------
# generic helpers over curves (d = 1) and surfaces (d = 2)
# ----------------------------------------------------------------------
def _params_2d(entity: Entity, params: npt.ArrayLike, k: int | None = None) -> np.ndarray:
    """Parameters as a ``(k, d)`` float array (accepts ``(k,)`` for curves)."""
    d = entity.param_dim
    p = np.asarray(params, dtype=float)
    if d == 1 and p.ndim == 1:
        p = p[:, None]
    if p.ndim != 2 or p.shape[1] != d:
        want = "(k,) or (k, 1)" if d == 1 else "(k, 2)"
        raise ValueError(f"parameters for a {type(entity).__name__} must have shape {want}, got {p.shape}")
    if k is not None and p.shape[0] != k:
        raise ValueError(f"{p.shape[0]} parameter rows for {k} points")
    return p


def entity_periods(entity) -> np.ndarray:
    """``(d,)`` period of each parameter direction (NaN where open).

    Analytic entities give theirs (``periods``: ``2 pi`` even for a face
    spanning part of a revolution); a closed NURBS direction is periodic over
    its knot domain.
    """
    per = getattr(entity, "periods", None)
    if per is not None:
        return np.asarray(per, dtype=float).reshape(entity.param_dim)
    b = entity.bounds
    return np.array([b[a, 1] - b[a, 0] if c else np.nan for a, c in enumerate(entity.closed)])


def entity_limits(entity) -> np.ndarray:
    """``(d, 2)`` hard parameter limits (evaluation clamps there): the knot domain of a
    NURBS, infinite for analytic surfaces (which extend beyond their face)."""
    lim = getattr(entity, "limits", None)
    return entity.bounds if lim is None else lim


def normalize_params(entity: Entity, params: npt.ArrayLike) -> np.ndarray:
    """``(k, d)`` parameters wrapped (closed directions) or clamped (open), as a new array.

    Closed directions are wrapped into ``[lo, lo + period)`` (``lo`` the lower
    bound), open ones clamped to :func:`entity_limits`.
    """
    p = np.array(_params_2d(entity, params), dtype=float)
    b = entity.bounds
    per = entity_periods(entity)
    lim = entity_limits(entity)
    for a in range(entity.param_dim):
        col = p[:, a]
        if math.isfinite(per[a]):
            lo = b[a, 0]
            out = (col < lo) | (col > lo + per[a])
            col[out] = lo + np.mod(col[out] - lo, per[a])
        else:
            col.clip(lim[a, 0], lim[a, 1], out=col)
    return p


@overload
def evaluate_params(entity: Entity, params: np.ndarray, nderiv: Literal[0] = 0) -> np.ndarray: ...
@overload
def evaluate_params(entity: Entity, params: np.ndarray, nderiv: Literal[1]) -> tuple[np.ndarray, np.ndarray]: ...
@overload
def evaluate_params(entity: Entity, params: np.ndarray, nderiv: Literal[2]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...
def evaluate_params(entity: Entity, params: np.ndarray, nderiv: int = 0
                    ) -> np.ndarray | tuple[np.ndarray, ...]:
    """Evaluate at ``(k, d)`` parameters already inside the domain.

    Returns ``S (k, 3)`` for ``nderiv=0``, else ``(S, T, H)`` with tangents
    ``T (k, d, 3)`` (``T[:, a] = dS/dp_a``) and, for ``nderiv=2``, second
    derivatives ``H (k, d, d, 3)`` (``H[:, a, b] = d2S/dp_a dp_b``).
    """
    D = entity._eval_soa(np.ascontiguousarray(params.T), nderiv).transpose(0, 2, 1)  # (n, k, 3)
    if nderiv == 0:
        return D[0]
    if entity.param_dim == 1:
        T = D[1][:, None, :]
        if nderiv == 1:
            return D[0], T
        return D[0], T, D[2][:, None, None, :]
    T = np.stack([D[1], D[2]], axis=1)
    if nderiv == 1:
        return D[0], T
    H = np.stack([np.stack([D[3], D[4]], axis=1), np.stack([D[4], D[5]], axis=1)], axis=1)
    return D[0], T, H


def _eval_soa(entity: Entity, P: np.ndarray, nderiv: int) -> np.ndarray:
    """Kernel evaluation at ``P (d, k)`` inside the domain: ``(1|2|3|6, 3, k)``.

    Order: curves ``[C, C', C'']``; surfaces ``[S, Su, Sv, Suu, Suv, Svv]``.
    """
    return entity._eval_soa(P, nderiv)


def _newton_system(E: np.ndarray, r: np.ndarray, d: int):
    """Gradient ``g (d, k)`` and the matrices ``J`` (B.1/B.2) and ``G`` (Gauss-Newton).

    ``J``/``G`` are returned as tuples of ``(k,)`` arrays: ``(J,)`` for curves,
    ``(J_uu, J_uv, J_vv)`` for surfaces (symmetric since ``S_uv = S_vu``).
    """
    if d == 1:
        C1, C2 = E[1], E[2]
        g = dot(C1, r)[None, :]  # f(u) of (B.1)
        G = dot(C1, C1)
        return g, (G + dot(C2, r),), (G,)
    Su, Sv, Suu, Suv, Svv = E[1], E[2], E[3], E[4], E[5]
    g = np.stack([dot(r, Su), dot(r, Sv)])  # f, g of (B.2)
    Guu, Guv, Gvv = dot(Su, Su), dot(Su, Sv), dot(Sv, Sv)
    J = (Guu + dot(r, Suu), Guv + dot(r, Suv), Gvv + dot(r, Svv))
    return g, J, (Guu, Guv, Gvv)


def _solve_step(g: np.ndarray, J: tuple, G: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Newton step ``-J^{-1} g`` (eq. B.1 / ``J delta = kappa`` of B.2), ``(d, k)``.

    Where ``J`` is not (safely) positive definite the regularised
    Gauss-Newton matrix ``G + mu I`` is used instead (a descent direction).
    Returns ``(step, pd, psd)``: ``pd (k,)`` True where the Newton matrix was
    used; ``psd (k,)`` True where ``J`` is positive semi-definite (up to
    rounding), i.e. the iterate is not at a maximum or saddle of the distance.
    """
    tiny = np.finfo(float).tiny
    if len(J) == 1:
        j, gg = J[0], G[0]
        pd = j > 1e-12 * gg
        psd = j >= -1e-12 * gg
        m = np.where(pd, j, gg * (1.0 + 1e-10) + tiny)
        return -g / m, pd, psd
    a, b, c = J
    det = a * c - b * b
    pd = (a > 0) & (c > 0) & (det > 1e-12 * a * c)
    tr = G[0] + G[2]
    psd = (a >= -1e-12 * tr) & (c >= -1e-12 * tr) & (det >= -1e-12 * tr * tr)
    if not np.all(pd):
        mu = 1e-10 * (G[0] + G[2]) + tiny
        a = np.where(pd, a, G[0] + mu)
        b = np.where(pd, b, G[1])
        c = np.where(pd, c, G[2] + mu)
        det = a * c - b * b
    return np.stack([-(c * g[0] - b * g[1]) / det, -(a * g[1] - b * g[0]) / det]), pd, psd


def _cosine(G: tuple, g: np.ndarray, dist: np.ndarray, d: int) -> np.ndarray:
    """Criterion 3: largest ``|S_a . r| / (|S_a| |r|)``; 0 for a zero tangent.

    ``G`` the Gauss-Newton matrix of :func:`_newton_system` (``|S_a|^2`` on its
    diagonal), ``g (d, k)`` the gradient ``S_a . r``.
    """
    cos = np.zeros_like(dist)
    for a in range(d):
        den = np.sqrt(G[0] if a == 0 else G[2]) * dist
        c = np.divide(np.abs(g[a]), den, out=np.zeros_like(den), where=den > 0)
        np.maximum(cos, c, out=cos)
    return cos


def _apply_step(entity: Entity, P: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(new params, actual step)`` for ``(d, k)`` arrays: clamped in open, wrapped in closed directions."""
    bnd = entity.bounds
    per = entity_periods(entity)
    lim = entity_limits(entity)
    new = P + step
    actual = step
    for a in range(entity.param_dim):
        row = new[a]
        if np.isfinite(per[a]):
            lo = bnd[a, 0]
            out = (row < lo) | (row > lo + per[a])
            if out.any():
                row[out] = lo + np.mod(row[out] - lo, per[a])
        else:
            np.clip(row, lim[a, 0], lim[a, 1], out=row)
            if actual is step:
                actual = step.copy()
            actual[a] = row - P[a]
    return new, actual


def _step_length(E: np.ndarray, actual: np.ndarray, d: int) -> np.ndarray:
    """Criterion 2: ``|sum_a delta_a S_a|`` (physical length of the step)."""
    v = E[1] * actual[0]
    if d == 2:
        v = v + E[2] * actual[1]
    return np.sqrt(dot(v, v))


def _escape_collapsed_edges(
    entity: Entity, X: np.ndarray, out: _Output, max_iter: int, tols: _Tolerances
) -> None:
    """Restart points stuck on a collapsed boundary (a pole) with the wrong free parameter.

    On a boundary ``u = u_b`` of an open direction where ``S_v = 0`` (the
    edge collapses to a point: sphere pole, cone apex), ``S`` does not depend
    on ``v``, so Newton cannot correct ``v``; if the meridian ``S_u(u_b, v)``
    points away from ``P`` the clamped iteration stops at the pole although
    interior points are closer.  For such points ``v`` is chosen with the
    steepest inward descent, ``min_v s r.S_u(u_b, v)`` (``s`` the inward
    sign) over a sample of ``v``, and Newton is restarted there.  Updates
    ``out`` in place (``d = 2`` only).
    """
    bnd = entity.bounds
    size = entity.bbox_size
    for a in range(2):  # loop over the two parameter directions
        if entity.closed[a]:
            continue
        o = 1 - a
        knots_o = _distinct_knots(entity, o)
        olen = bnd[o, 1] - bnd[o, 0]
        for bound, s in ((bnd[a, 0], 1.0), (bnd[a, 1], -1.0)):
            cand = np.flatnonzero((out.P[a] == bound) & (out.dist > tols.zero))
            if cand.size == 0:
                continue
            E = _eval_soa(entity, out.P[:, cand], 1)
            r = E[0] - X[cand].T
            Ta, To = E[1 + a], E[1 + o]
            degen = np.sqrt(dot(To, To)) <= 1e-9 * size / olen
            rate0 = s * dot(r, Ta)
            stuck = degen & (rate0 >= 0.0)
            if not stuck.any():
                continue
            cand, r = cand[stuck], r[:, stuck]
            vs = _direction_samples(knots_o, 8, 32)
            nc, ns = cand.size, vs.size
            P = np.empty((2, nc * ns))
            P[a] = bound
            P[o] = np.tile(vs, nc)
            Ts = _eval_soa(entity, P, 1)[1 + a]
            rate = (s * dot(np.repeat(r, ns, axis=1), Ts)).reshape(nc, ns)
            best = np.argmin(rate, axis=1)
            go = rate[np.arange(nc), best] < 0.0
            if not go.any():
                continue
            cand = cand[go]
            seeds = np.empty((cand.size, 2))
            seeds[:, a] = bound
            seeds[:, o] = vs[best[go]]
            res = project_newton(
                entity, X[cand], seeds, max_iter, tols.step, zero_tol=tols.zero, cos_tol=tols.cos,
                acc_tol=tols.acc, _escape=False,
            )
            better = res.distance < out.dist[cand]
            out.store(cand[better], res.params[better].T, res.points[better].T, res.distance[better],
                      res.converged[better])
            out.iters[cand] += res.iterations


# ----------------------------------------------------------------------
# Newton projection
# ----------------------------------------------------------------------
@dataclass(frozen=True)
class _Tolerances:
    """Convergence tolerances of :func:`project_newton` (length units, but ``cos``)."""

    step: float  # criterion 2: physical length of the last step
    zero: float  # criterion 1: |S - P|
    cos: float  # criterion 3: zero cosine
    acc: float  # error predicted after the last step that criterion 2 accepts
    slack: float  # growth of |S - P| tolerated as rounding (no backtracking)

    @classmethod
    def of(cls, entity: Entity, tol: float | None, zero_tol: float | None, cos_tol: float,
           acc_tol: float | None) -> _Tolerances:
        """Defaults relative to the entity's bbox size (module constants)."""
        size = max(entity.bbox_size, np.finfo(float).tiny)
        return cls(
            STEP_RTOL * size if tol is None else float(tol),
            ZERO_RTOL * size if zero_tol is None else float(zero_tol),
            float(cos_tol),
            ACC_RTOL * size if acc_tol is None else float(acc_tol),
            4.0 * np.finfo(float).eps * size,
        )


@dataclass
class _Output:
    """Results of :func:`project_newton`, ``(d, k)`` / ``(3, k)`` / ``(k,)``, filled as points finish."""

    P: np.ndarray
    S: np.ndarray
    dist: np.ndarray
    iters: np.ndarray
    conv: np.ndarray

    def store(self, ii: np.ndarray, P: np.ndarray, S: np.ndarray, dist: np.ndarray,
              converged: bool | np.ndarray) -> None:
        """Final state of points ``ii`` (columns of ``P (d, m)``, ``S (3, m)``, ``dist (m,)``)."""
        self.P[:, ii], self.S[:, ii], self.dist[ii], self.conv[ii] = P, S, dist, converged

    def result(self, d: int) -> ProjectionResult:
        params = self.P[0].copy() if d == 1 else np.ascontiguousarray(self.P.T)
        return ProjectionResult(params, np.ascontiguousarray(self.S.T), self.dist, self.iters, self.conv)


@dataclass
class _Active:
    """State of the points still iterating (columns), compacted as points finish.

    ``idx (m,)`` their rows in the output, ``X (3, m)`` the points, ``P (d, m)``
    parameters, ``E`` the evaluation there (:func:`_eval_soa` with second
    derivatives), ``r = S - X``, ``dist = |r|``, ``sprev`` the previous step length.
    """

    idx: np.ndarray
    X: np.ndarray
    P: np.ndarray
    E: np.ndarray
    r: np.ndarray
    dist: np.ndarray
    sprev: np.ndarray

    def keep(self, mask: np.ndarray) -> None:
        """Drop the columns where ``mask`` is False."""
        self.idx, self.X, self.P, self.E = self.idx[mask], self.X[:, mask], self.P[:, mask], self.E[:, :, mask]
        self.r, self.dist, self.sprev = self.r[:, mask], self.dist[mask], self.sprev[mask]


@dataclass
class _Step:
    """A Newton update of the active points (columns) and Kadir's criteria for it."""

    step: np.ndarray  # (d, m) the (capped) Newton or Gauss-Newton step
    new: np.ndarray  # (d, m) parameters after it (clamped / wrapped)
    actual: np.ndarray  # (d, m) the step as taken (after clamping)
    length: np.ndarray  # (m,) |sum_a actual_a S_a|
    small: np.ndarray  # (m,) criterion 2 met by this step
    done: np.ndarray  # (m,) some criterion met

    def keep(self, mask: np.ndarray) -> None:
        self.step, self.new, self.actual = self.step[:, mask], self.new[:, mask], self.actual[:, mask]
        self.length, self.small, self.done = self.length[mask], self.small[mask], self.done[mask]


def _newton_step(entity: Entity, a: _Active, tols: _Tolerances) -> _Step:
    """Newton step of every active point (eq. B.1 / B.2, capped to a quarter of the
    domain, clamped or wrapped) and the convergence criteria it meets."""
    d = entity.param_dim
    g, J, G = _newton_system(a.E, a.r, d)
    step, pd, psd = _solve_step(g, J, G)
    step[:, ~np.all(np.isfinite(step), axis=0)] = 0.0
    # cap to a quarter of the domain per direction (uniform scaling)
    max_step = 0.25 * np.diff(entity.bounds, axis=1)  # (d, 1)
    scale = np.min(np.minimum(1.0, max_step / np.maximum(np.abs(step), 1e-300)), axis=0)
    step *= scale
    new, actual = _apply_step(entity, a.P, step)
    length = _step_length(a.E, actual, d)
    # Kadir's criteria: 2 (insignificant change) for the Newton step just computed,
    # with the error predicted after it, C s^2, C ~ s / s_prev^2 (quadratic
    # convergence; without a previous step: s itself); 1 (coincidence) and 3 (zero
    # cosine, only where J >= 0: not at a maximum of the distance) at the iterate
    with np.errstate(invalid="ignore"):  # inf / inf where there was no previous step
        pred = np.where(np.isfinite(a.sprev), length * length * length / np.maximum(a.sprev * a.sprev, 1e-300),
                        length)
    small = pd & (length <= tols.step) & (pred <= tols.acc)
    done = small | (a.dist <= tols.zero) | (psd & (_cosine(G, g, a.dist, d) <= tols.cos))
    return _Step(step, new, actual, length, small, done)


def _retire(a: _Active, s: _Step, stop: np.ndarray, out: _Output, zero_tol: float) -> None:
    """Store the points ``stop`` (converged where ``s.done``) and drop them from ``a``, ``s``.

    A converged point takes its last (tiny) Newton step to first order,
    ``S(p + delta) = S + S_a delta_a + O(|delta|^2)``: no re-evaluation.
    """
    d = a.P.shape[0]
    lin = stop & s.small
    Pf = np.where(lin[None, :], s.new, a.P)
    Sf = a.E[0] + np.where(lin[None, :], np.einsum("ak,ack->ck", s.actual, a.E[1 : 1 + d]), 0.0)
    rf = Sf - a.X
    out.iters[a.idx[lin & (s.length > zero_tol)]] += 1
    out.store(a.idx[stop], Pf[:, stop], Sf[:, stop], np.sqrt(dot(rf, rf))[stop], s.done[stop])
    keep = ~stop
    a.keep(keep)
    s.keep(keep)


def _backtrack(entity: Entity, a: _Active, s: _Step, tols: _Tolerances, max_halvings: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Evaluate at the new parameters, halving the step where ``|S - P|`` grew
    (inactive for well-seeded points).  Returns ``(E, r, dist, stalled)`` at
    ``s.new`` (updated in place, as ``s.length``); ``stalled (m,)``: no halving
    decreased the distance."""
    E = _eval_soa(entity, s.new, 2)
    r = E[0] - a.X
    dist = np.sqrt(dot(r, r))
    worse = np.flatnonzero(dist > a.dist + tols.slack)
    alpha = 1.0
    for _h in range(max_halvings):
        if worse.size == 0:
            break
        alpha *= 0.5
        nw, aw = _apply_step(entity, a.P[:, worse], alpha * s.step[:, worse])
        Ew = _eval_soa(entity, nw, 2)
        rw = Ew[0] - a.X[:, worse]
        dw = np.sqrt(dot(rw, rw))
        s.new[:, worse], E[:, :, worse], r[:, worse], dist[worse] = nw, Ew, rw, dw
        s.length[worse] = _step_length(a.E[:, :, worse], aw, entity.param_dim)
        worse = worse[dw > a.dist[worse] + tols.slack]
    stalled = np.zeros(a.idx.size, dtype=bool)
    stalled[worse] = True
    return E, r, dist, stalled


def _surface_newton(entity: NurbsSurface, X: np.ndarray, out: _Output, max_iter: int, tols: _Tolerances,
                    max_halvings: int) -> None:
    """The iteration of :func:`project_newton` on a NURBS surface by the compiled kernel
    :func:`nagata_snap.cad.basis.surface_newton` (the same operations per point, so the same
    iterates), from the seeds in ``out.P (2, k)`` for the points ``X (3, k)``; fills ``out``.

    The vectorised loop pays a few array operations per iteration whatever the number of
    points still iterating: a few points that run to ``max_iter`` with step halvings (on a
    face's boundary, where the clamped Newton step converges linearly) cost milliseconds per
    iteration; here microseconds.
    """
    e = entity
    tv = np.array([tols.step, tols.zero, tols.cos, tols.acc, tols.slack])
    _kernels.surface_newton(e.knots_u, e.knots_v, e.degree_u, e.degree_v, e.n_ctrl[1], e._pwT, e._spans_u,
                            e._spans_v, np.ascontiguousarray(e.bounds, dtype=float), entity_periods(e),
                            np.ascontiguousarray(entity_limits(e), dtype=float), X, out.P, int(max_iter), tv,
                            int(max_halvings), out.S, out.dist, out.iters, out.conv)


def project_newton(
    entity: Entity,
    points: npt.ArrayLike,
    seeds: npt.ArrayLike,
    max_iter: int = 20,
    tol: float | None = None,
    *,
    zero_tol: float | None = None,
    cos_tol: float = COS_TOL,
    acc_tol: float | None = None,
    max_halvings: int = 12,
    _escape: bool = True,
) -> ProjectionResult:
    """Closest points on one NURBS entity by seeded Newton iteration (vectorised).

    Kadir (2010) App. B, eq. (B.1) for curves and (B.2) for surfaces; all
    points iterate together, converged points are frozen (removed from the
    active set, which is compacted every iteration).  Stages:
    :func:`_newton_step` (step and criteria), :func:`_retire` (finished
    points), :func:`_backtrack` (evaluation at the new iterate, step
    halving), :func:`_escape_collapsed_edges` (restarts at poles).

    Args:
        entity: :class:`~nagata_snap.cad.nurbs.NurbsCurve` or :class:`~nagata_snap.cad.nurbs.NurbsSurface`.
        points: ``(k, 3)`` points to project (``(k, 2)`` accepted, z = 0).
        seeds: ``(k,)`` (curves) or ``(k, 2)`` (surfaces) start parameters;
            wrapped/clamped into the domain first.
        max_iter: maximum number of Newton updates per point.
        tol: criterion 2, physical length of the last step (length units);
            default ``1e-9 * entity.bbox_size``.
        zero_tol: criterion 1, ``|S - P|`` (length units); default
            ``1e-14 * entity.bbox_size``.
        cos_tol: criterion 3, zero cosine between ``S - P`` and the tangents
            (default 1e-14).
        acc_tol: error predicted after the last step that criterion 2 accepts
            (length units); default ``1e-14 * entity.bbox_size``.
        max_halvings: step halvings allowed when a step increases ``|S - P|``.

    Returns:
        :class:`ProjectionResult` (params ``(k,)`` for curves, ``(k, 2)`` for
        surfaces).  Points not converged after ``max_iter`` updates, or whose
        step could not decrease the distance, have ``converged = False`` and
        hold their best iterate.

    Raises:
        ValueError: points that are NaN, infinite or beyond :data:`MAX_COORD`
            (non-finite seeds are allowed: the point is returned unconverged).
    """
    X = _points3(points, single=False)
    k, d = X.shape[0], entity.param_dim
    tols = _Tolerances.of(entity, tol, zero_tol, cos_tol, acc_tol)
    P0 = np.ascontiguousarray(normalize_params(entity, _params_2d(entity, seeds, k)).T)  # (d, k)
    out = _Output(P0, np.empty((3, k)), np.empty(k), np.zeros(k, dtype=np.int64), np.zeros(k, dtype=bool))
    Xa = np.ascontiguousarray(X.T)  # (3, k)
    if type(entity) is NurbsSurface:  # the same iteration, compiled, one point at a time
        _surface_newton(entity, Xa, out, max_iter, tols, max_halvings)
        if _escape:
            _escape_collapsed_edges(entity, X, out, max_iter, tols)
        return out.result(d)
    E = _eval_soa(entity, P0, 2)
    r = E[0] - Xa
    a = _Active(np.arange(k), Xa, P0.copy(), E, r, np.sqrt(dot(r, r)), np.full(k, np.inf))
    for it in range(max_iter + 1):
        if a.idx.size == 0:
            break
        s = _newton_step(entity, a, tols)
        # at the last iteration every point stops; before, also a zero step that meets no
        # criterion (a maximum, or clamped against a bound): it cannot progress
        stop = np.ones(a.idx.size, dtype=bool) if it == max_iter else s.done | (s.length == 0.0)
        if stop.any():
            _retire(a, s, stop, out, tols.zero)
            if a.idx.size == 0:
                break
        E, r, dist, stalled = _backtrack(entity, a, s, tols, max_halvings)
        if stalled.any():  # could not decrease: keep the old iterate, not converged
            out.store(a.idx[stalled], a.P[:, stalled], a.E[0][:, stalled], a.dist[stalled], False)
        ok = ~stalled
        out.iters[a.idx[ok]] += 1
        a.P, a.E, a.r, a.dist, a.sprev = s.new, E, r, dist, s.length
        if not ok.all():
            a.keep(ok)
    if d == 2 and _escape:
        _escape_collapsed_edges(entity, X, out, max_iter, tols)
    return out.result(d)


def is_analytic(entity: object) -> TypeGuard[AnalyticEntity]:
    """The entity projects in closed form (:mod:`~nagata_snap.cad.surfaces`, :mod:`~nagata_snap.cad.curves`)."""
    return hasattr(entity, "closest")


def project_points(
    entity: Entity, points: npt.ArrayLike, seeds: npt.ArrayLike, max_iter: int = 20
) -> ProjectionResult:
    """Closest points on one entity: closed form for analytic entities, else seeded Newton.

    Analytic results count as converged with 0 iterations; their seeds only
    fill parameters the point leaves free (axis, poles, apex).
    """
    if is_analytic(entity):
        X = _points3(points)
        P, S, dist = entity.closest(X, np.asarray(seeds, dtype=float).reshape(len(X), -1))
        k = len(X)
        params = P[:, 0] if entity.param_dim == 1 else P
        return ProjectionResult(params, S, dist, np.zeros(k, dtype=np.int64), np.ones(k, dtype=bool))
    return project_newton(entity, points, seeds, max_iter)


class AffineBatch:
    """Closest points on many affine entities at once (planes, line segments).

    An entity with ``affine = (origin (3,), axes (d, 3))`` (orthonormal axes)
    is ``S(p) = origin + p @ axes``; its closest point to ``X`` has ``p =
    (X - origin) @ axes.T`` clamped to the entity's limits (a segment's ends).
    The frames of all such entities are stacked once, so one projection call
    serves the points of every plane (or line) of a part: no loop over them.

    Args:
        entities: all entities of a geometry (those without ``affine`` are not used).
    """

    def __init__(self, entities: Sequence[Entity]):
        aff = [getattr(e, "affine", None) for e in entities]
        sel = [i for i, a in enumerate(aff) if a is not None]
        frames = [a for a in aff if a is not None]
        n, d = len(aff), entities[0].param_dim if entities else 1
        self.has = np.zeros(n, dtype=bool)
        self.has[sel] = True
        self.origin = np.zeros((n, 3))
        self.axes = np.zeros((n, d, 3))
        self.limits = np.zeros((n, d, 2))
        self.clamped = False
        if sel:  # the frames stacked once (concatenated: no row assignment per entity)
            self.origin[sel] = np.concatenate([a[0] for a in frames]).reshape(-1, 3)
            self.axes[sel] = np.concatenate([a[1] for a in frames]).reshape(-1, d, 3)
            lim = np.concatenate([entity_limits(entities[i]) for i in sel]).reshape(-1, d, 2)
            self.limits[sel] = lim
            self.clamped = bool(np.isfinite(lim).any())

    def closest(self, ent: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(params (n, d), foot points (n, 3), distances (n,))`` of ``X (n, 3)`` on the
        affine entities ``ent (n,)``."""
        ax = self.axes[ent]
        q = X - self.origin[ent]
        P = np.einsum("nc,ndc->nd", q, ax)
        if self.clamped:
            lim = self.limits[ent]
            P.clip(lim[:, :, 0], lim[:, :, 1], out=P)
        r = np.einsum("nd,ndc->nc", P, ax)
        r -= q  # foot minus point
        return P, r + X, norms(r)


# ----------------------------------------------------------------------
# sampling and global search
# ----------------------------------------------------------------------
def _direction_samples(knots: np.ndarray, per_span: int, min_total: int) -> np.ndarray:
    nsp = len(knots) - 1
    n = max(per_span, int(np.ceil(min_total / nsp)))
    t = np.linspace(0.0, 1.0, n + 1)[:-1]
    return np.concatenate([(knots[:-1, None] + np.outer(np.diff(knots), t)).ravel(), knots[-1:]])


def sample_entity(
    entity: Entity, per_span: int | None = None, min_per_direction: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Parameter grid of an entity: ``per_span`` samples in each knot span.

    Args:
        entity: curve or surface.
        per_span: samples per knot span and direction (default 8 for curves,
            6 for surfaces).
        min_per_direction: at least this many samples per direction.

    Returns:
        ``(params (s, d), points (s, 3))``.
    """
    axes, X = _sample_axes(entity, per_span, min_per_direction)
    P = axes[0][:, None] if entity.param_dim == 1 else _grid(*axes)
    return P, evaluate_params(entity, P, 0) if X is None else X


def _sample_axes(entity: Entity, per_span: int | None = None, min_per_direction: int = 16
                 ) -> tuple[list[np.ndarray], np.ndarray | None]:
    """The parameters of :func:`sample_entity`'s grid along each direction, and the grid's
    points where they were evaluated on the way (surfaces), else None."""
    if entity.param_dim == 1:
        per_span = 8 if per_span is None else per_span
        return [_direction_samples(_distinct_knots(entity, 0), per_span, min_per_direction)], None
    per_span = 6 if per_span is None else per_span
    ku, kv = _distinct_knots(entity, 0), _distinct_knots(entity, 1)
    u = _direction_samples(ku, per_span, min_per_direction)
    v = _direction_samples(kv, per_span, min_per_direction)
    X = evaluate_params(entity, _grid(u, v), 0)
    # about as dense in 3D along u as along v: a direction whose samples lie farther apart
    # than the other's (by more than a factor 2) gets that many times more (at most
    # MAX_ANISOTROPY): on a thin torus' tube the nearest samples of a point would
    # otherwise all lie on one row far from it, seeding Newton onto the wrong side
    G = X.reshape(len(u), len(v), 3)
    su = float(np.linalg.norm(np.diff(G, axis=0), axis=2).mean()) if len(u) > 1 else 0.0
    sv = float(np.linalg.norm(np.diff(G, axis=1), axis=2).mean()) if len(v) > 1 else 0.0
    if min(su, sv) > 0 and max(su, sv) > 2.0 * min(su, sv):
        f = int(min(math.ceil(max(su, sv) / min(su, sv)), MAX_ANISOTROPY))
        if su > sv:
            u = _direction_samples(ku, per_span * f, min_per_direction * f)
        else:
            v = _direction_samples(kv, per_span * f, min_per_direction * f)
        X = evaluate_params(entity, _grid(u, v), 0)
    return [u, v], X


def _refined(a: np.ndarray) -> np.ndarray:
    """``(2 n - 1,)``: the parameters ``a (n,)`` with their midpoints between them."""
    out = np.empty(2 * len(a) - 1)
    out[::2] = a
    out[1::2] = 0.5 * (a[:-1] + a[1:])
    return out


#: times more seeds :meth:`GlobalSearcher._past_saddles` tries where Newton stopped at a saddle
SADDLE_SEEDS = 6
#: ... and where its best result is farther than this many times the entity's sample spacing
SADDLE_SPACING = 0.25
#: ... or farther than this fraction of the distance of the point's nearest sample of the entity
SADDLE_SEED = 0.2
#: most times more samples :func:`sample_entity` puts along a surface's sparser direction
MAX_ANISOTROPY = 16
#: a grid cell competes (:meth:`GlobalSearcher._nearer_cells`) where its box is nearer to a point than
#: its best result by more than this fraction of that result's distance
CELL_MARGIN = 1e-6


def _grid(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``(len(u) len(v), 2)``: the parameter grid ``u x v``, ``u`` major."""
    uu, vv = np.meshgrid(u, v, indexing="ij")
    return np.stack([uu.ravel(), vv.ravel()], axis=1)


class GlobalSearcher:
    """KD-tree of parameter-grid samples of several entities, for seeding Newton.

    Built once per geometry and reused for every search; the grids are built
    on first use (an entity's when a search on it needs seeds, all of them at
    the first global search), so that a geometry whose points come with
    their faces and seeds (a mesh made from the CAD) never pays for them.

    Args:
        entities: curves or surfaces (all of the same kind).
        per_span: samples per knot span and direction (see :func:`sample_entity`).
        k_seeds: nearest samples used as Newton seeds per point.
        max_iter: Newton iterations per seed.
        sample_filter: optional ``f(entity_index, params (s, d)) -> (s,) bool``
            keeping only the grid samples of an entity that may seed Newton
            (e.g. those inside a trimmed face); an entity with no sample kept
            keeps them all.
        extra_samples: optional per-entity ``(s_e, d)`` parameters added to the
            grid (before filtering), e.g. the vertices of trimming loops (any
            sequence indexed by entity: it is read when that entity's grid is built).
    """

    def __init__(
        self,
        entities: Sequence[Entity],
        *,
        per_span: int | None = None,
        k_seeds: int = 6,
        max_iter: int = 30,
        sample_filter: Callable[[int, np.ndarray], np.ndarray] | None = None,
        extra_samples: Sequence[np.ndarray | None] | None = None,
    ):
        entities = list(entities)
        if not entities:
            raise ValueError("no entities given")
        dims = {e.param_dim for e in entities}
        if len(dims) != 1:
            raise ValueError("entities must be all curves or all surfaces")
        if extra_samples is not None and len(extra_samples) != len(entities):
            raise ValueError(f"{len(extra_samples)} extra sample sets for {len(entities)} entities")
        self.entities = entities
        self.param_dim = dims.pop()
        self.k_seeds = int(k_seeds)
        self.max_iter = int(max_iter)
        self._per_span = per_span
        self._filter = sample_filter
        self._extra = extra_samples
        #: per entity ``(params (s, d), points (s, 3))``, built on first use
        self._samples: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._trees: dict[int, cKDTree] = {}
        #: per entity its grid's parameters along each direction (with :attr:`_samples`)
        self._axes: dict[int, list[np.ndarray]] = {}
        self._cells: tuple[BoxClasses, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._all: tuple[np.ndarray, np.ndarray, np.ndarray, cKDTree] | None = None
        boxes = [e.bbox for e in entities]  # each computed once
        lo = np.concatenate([b[0] for b in boxes]).reshape(-1, 3)
        hi = np.concatenate([b[1] for b in boxes]).reshape(-1, 3)
        self.bbox_lo, self.bbox_hi = lo, hi
        diag = hi.max(axis=0) - lo.min(axis=0)
        self.size = math.sqrt(diag.dot(diag))  # its norm (as np.linalg.norm computes it)
        self.affine = AffineBatch(entities)
        #: the circles among the entities, stacked (their closed form for all points at once)
        self.arcs = ArcBatch(entities)

    def entity_samples(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """``(params (s, d), points (s, 3))``: the search grid of entity ``i`` (built once)."""
        if i not in self._samples:
            e = self.entities[i]
            axes, X = _sample_axes(e, self._per_span)
            self._axes[i] = axes
            P = axes[0][:, None] if e.param_dim == 1 else _grid(*axes)
            X = evaluate_params(e, P, 0) if X is None else X
            extra = None if self._extra is None else self._extra[i]
            if extra is not None and len(extra):
                Pe = normalize_params(e, np.asarray(extra, dtype=float).reshape(-1, self.param_dim))
                P = np.concatenate([P, Pe])
                X = np.concatenate([X, evaluate_params(e, Pe, 0)])
            if self._filter is not None:
                keep = np.asarray(self._filter(i, P), dtype=bool)
                if keep.any():  # an entity keeps at least its unfiltered grid
                    P, X = P[keep], X[keep]
            self._samples[i] = (P, X)
        return self._samples[i]

    def _all_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, cKDTree]:
        """Samples of every entity, concatenated, and their KD-tree (built on the first global search)."""
        if self._all is None:
            grids = [self.entity_samples(i) for i in range(len(self.entities))]
            params = np.concatenate([P for P, _ in grids])
            pts = np.concatenate([X for _, X in grids])
            ent = np.repeat(np.arange(len(grids)), [len(P) for P, _ in grids])
            self._all = (params, pts, ent, cKDTree(pts))
        return self._all

    @property
    def sample_params(self) -> np.ndarray:
        """``(s, d)`` parameters of all grid samples."""
        return self._all_samples()[0]

    @property
    def sample_points(self) -> np.ndarray:
        """``(s, 3)`` points of all grid samples."""
        return self._all_samples()[1]

    @property
    def sample_entity(self) -> np.ndarray:
        """``(s,)`` entity of each grid sample."""
        return self._all_samples()[2]

    def _spacing(self, e: int) -> float:
        """Mean distance from each search sample of entity ``e`` to its nearest other sample."""
        if not hasattr(self, "_spacings"):
            self._spacings: dict[int, float] = {}
        if e not in self._spacings:
            X = self.entity_samples(e)[1]
            self._spacings[e] = float(self._entity_tree(e).query(X, k=2)[0][:, 1].mean()) if len(X) > 1 else 0.0
        return self._spacings[e]

    def _entity_tree(self, e: int) -> cKDTree:
        if e not in self._trees:
            self._trees[e] = cKDTree(self.entity_samples(e)[1])
        return self._trees[e]

    def refine(
        self,
        pt: np.ndarray,
        ent: np.ndarray,
        seeds: np.ndarray,
        points: np.ndarray,
        max_iter: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Newton from given ``(point, entity, seed)`` triples, grouped by entity.

        Args:
            pt: ``(n,)`` row of ``points`` of each triple.
            ent: ``(n,)`` entity index of each triple.
            seeds: ``(n, d)`` start parameters.
            points: ``(N, 3)`` points.
            max_iter: Newton iterations (default: the searcher's).

        Returns:
            ``(params (n, d), proj (n, 3), dist (n,), iterations (n,), converged (n,))``.
        """
        max_iter = self.max_iter if max_iter is None else int(max_iter)
        n = len(pt)
        d = self.param_dim
        its = np.zeros(n, dtype=np.int64)
        aff = self.affine.has[ent]
        if aff.all():  # planes and segments only: all at once, in the input order
            X = points[pt]
            _check_finite(X, "points")
            params, proj, dist = self.affine.closest(ent, X)
            return params, proj, dist, its, np.ones(n, dtype=bool)
        params = np.zeros((n, d))
        proj = np.zeros((n, 3))
        dist = np.full(n, np.inf)
        conv = np.zeros(n, dtype=bool)
        if aff.any():  # planes and segments: all at once
            rows = aff.nonzero()[0]
            X = points[pt[rows]]
            _check_finite(X, "points")
            params[rows], proj[rows], dist[rows] = self.affine.closest(ent[rows], X)
            conv[rows] = True
        arc = self.arcs.has[ent]
        if arc.any():  # circular arcs: all at once
            rows = arc.nonzero()[0]
            X = points[pt[rows]]
            _check_finite(X, "points")
            sd = np.asarray(seeds, dtype=float).reshape(n, d)[rows, 0]
            params[rows], proj[rows], dist[rows] = self.arcs.closest(ent[rows], X, sd)
            conv[rows] = True
            aff = aff | arc
        rows = (~aff).nonzero()[0]  # the other entities, one sort
        g = Groups(ent[rows])
        rows = rows[g.order]
        X = points[pt[rows]]
        S = np.asarray(seeds, dtype=float).reshape(n, d)[rows]
        m = len(rows)
        P, F, D = np.zeros((m, d)), np.zeros((m, 3)), np.full(m, np.inf)
        it, cv = np.zeros(m, dtype=np.int64), np.zeros(m, dtype=bool)
        for e, sl in g:  # loop over the entities, vectorised inside
            res = project_points(self.entities[e], X[sl], S[sl], max_iter)
            P[sl] = res.params.reshape(-1, d)
            F[sl], D[sl], it[sl], cv[sl] = res.points, res.distance, res.iterations, res.converged
        params[rows], proj[rows], dist[rows], its[rows], conv[rows] = P, F, D, it, cv
        return params, proj, dist, its, conv

    def search(
        self,
        points: npt.ArrayLike,
        k_seeds: int | None = None,
        accept: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> tuple[np.ndarray, ...]:
        """Closest point over all entities; see :func:`global_search`.

        With ``accept(ent (n,), params (n, d)) -> (n,) bool`` (e.g. "inside
        the trimmed face") only accepted Newton results compete; the result
        is then ``(entity, params, distance, accepted)``: a point with no
        accepted result gets its best unaccepted one and ``accepted`` False.
        """
        X = _points3(points)
        n = len(X)
        if n == 0:
            empty = (np.zeros(0, np.int64), np.zeros((0, self.param_dim)), np.zeros(0))
            return empty if accept is None else (*empty, np.zeros(0, dtype=bool))
        pt, ent, params, dist = self.search_rows(X, k_seeds, accept)
        return _pick(n, pt, ent, params, dist, (ent, params), accept)

    def search_rows(
        self,
        points: npt.ArrayLike,
        k_seeds: int | None = None,
        accept: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> tuple[np.ndarray, ...]:
        """Every Newton result of :meth:`search` before the pick: ``(pt (m,), ent (m,),
        params (m, d), dist (m,))``, one row per (point, seed) pair, the point ``pt`` a row
        of ``points (n, 3)`` (rows of one point and entity may repeat)."""
        X = _points3(points)
        pt, ent, params, _, dist, _ = self.search_all(X, k_seeds)
        pt, ent, params, dist = self._nearer_boxes(X, pt, ent, params, dist, k_seeds, accept)
        pt, ent, params, dist = self._nearer_cells(X, pt, ent, params, dist, accept)
        return self._past_saddles(X, pt, ent, params, dist, k_seeds, accept)

    def _past_saddles(self, X: np.ndarray, pt: np.ndarray, ent: np.ndarray, params: np.ndarray, dist: np.ndarray,
                      k_seeds: int | None, accept) -> tuple[np.ndarray, ...]:
        """The results ``(pt, ent, params, dist)``, with more Newton runs where a point's best
        result on a surface that is not analytic is a saddle or a maximum of the distance.

        Newton finds stationary points of the distance; from seeds all on one side
        of a point (the nearest samples of a point inside a narrow region of a
        B-spline face can all lie on one iso-line around it) it can stop at a
        saddle, or at a local minimum farther than the samples resolve.  Where the
        Hessian of ``|S - x|^2 / 2`` (``J^T J + (S - x) . S_ij``) at a point's best
        result is not positive definite, or the result is farther than
        :data:`SADDLE_SPACING` times the entity's sample spacing (a point close to the
        surface between sparse samples) or than :data:`SADDLE_SEED` times the point's nearest
        sample of the entity (seeds on a thin tube's far side: Newton's minimum there is not
        much nearer than they are), or where a tangent vanishes there (a rational
        patch whose span collapses at an interior knot line: Newton's one-sided derivatives
        stop on the line although the other side is nearer), or where the best result is on
        several faces (their common edge: near a crease of a surface, the seeds of one basin
        of the distance find its minimum at the edge, not the other basin's), Newton runs again on that entity from its
        :data:`SADDLE_SEEDS` times more nearest samples.
        """
        if self.param_dim != 2 or len(pt) == 0:
            return pt, ent, params, dist
        ok = np.ones(len(pt), dtype=bool) if accept is None else np.asarray(accept(ent, params), dtype=bool)
        top = best_per_group(pt, (~ok, dist), len(X))
        # the best result of every (point, entity) pair within twice the point's best: a tie (faces
        # meeting at the result) or a stop on a collapsed knot line may hide a nearer minimum
        E = len(self.entities)
        _, pair = np.unique(pt * E + ent, return_inverse=True)
        best = best_per_group(pair.reshape(-1), (~ok, dist), int(pair.max()) + 1)
        best = best[best >= 0]
        lead = top[pt[best]]
        best = best[(ok[best] == ok[lead]) & (dist[best] <= 2.0 * dist[lead] + 1e-12 * self.size)]
        tie = dist[best] <= dist[top[pt[best]]] * (1.0 + 1e-9) + 1e-12 * self.size
        ties = np.bincount(pt[best[tie]], minlength=len(X))  # > 1: the best result is on an edge of faces
        keep = ~self._closed_form[ent[best]] & (dist[best] > 0)
        best, tie = best[keep], tie[keep]
        if best.size == 0:
            return pt, ent, params, dist
        saddle = tie & (ties[pt[best]] > 1)
        g = Groups(ent[best])
        for e, sl in g:  # loop over the entities of those results
            at = g.order[sl]
            rows = best[at]
            S, T, H = evaluate_params(self.entities[e], normalize_params(self.entities[e], params[rows]), 2)
            r = S - X[pt[rows]]
            A = np.einsum("nac,nbc->nab", T, T) + np.einsum("nc,nabc->nab", r, H)
            det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
            tn = np.linalg.norm(T, axis=2)  # (k, 2) |S_u|, |S_v|: one vanishes on a collapsed knot line
            seed = self._entity_tree(e).query(X[pt[rows]])[0]  # the nearest sample of the entity
            far = (dist[rows] > SADDLE_SPACING * self._spacing(e)) | (dist[rows] > SADDLE_SEED * seed)
            saddle[at] |= (tie[at] & ((det <= 0) | (A[:, 0, 0] + A[:, 1, 1] <= 0) | far)) | \
                (tn.min(axis=1) <= 1e-9 * tn.max(axis=1))
        rows = best[saddle]
        if rows.size == 0:
            return pt, ent, params, dist
        k = SADDLE_SEEDS * (self.k_seeds if k_seeds is None else int(k_seeds))
        q, e, par, _, d = self._rows_on(X[pt[rows]], ent[rows], k)
        return (np.concatenate([pt, pt[rows][q]]), np.concatenate([ent, e]), np.concatenate([params, par]),
                np.concatenate([dist, d]))

    @functools.cached_property
    def _analytic(self) -> np.ndarray:
        """``(n_entities,)`` bool: the entity is analytic (:func:`is_analytic`)."""
        return np.array([is_analytic(e) for e in self.entities], dtype=bool)

    @functools.cached_property
    def _closed_form(self) -> np.ndarray:
        """``(n_entities,)`` bool: the entity projects in closed form (analytic or affine)."""
        return self._analytic | self.affine.has

    @functools.cached_property
    def _entity_boxes(self) -> BoxClasses:
        """The entities' bounding boxes, for ball queries (:meth:`_nearer_boxes`)."""
        return BoxClasses(self.bbox_lo, self.bbox_hi)

    def _nearer_boxes(self, X: np.ndarray, pt: np.ndarray, ent: np.ndarray, params: np.ndarray, dist: np.ndarray,
                      k_seeds: int | None, accept) -> tuple[np.ndarray, ...]:
        """The Newton results ``(pt, ent, params, dist)`` of the seeded search, with those on
        every entity whose bounding box is nearer to a point than the point's best (accepted)
        result (:meth:`search_on`: closed form on analytic entities, where no seed of the point
        gave an accepted result on it; the entity's own nearest samples on NURBS, always).

        The nearest grid samples of a point can all lie on small, densely sampled faces
        while its closest point is on a large, coarsely sampled one (a plane beside the
        holes drilled into it): a bound, not the samples, decides which entities compete.
        """
        n = len(X)
        ok = np.ones(len(pt), dtype=bool) if accept is None else np.asarray(accept(ent, params), dtype=bool)
        best = np.full(n, np.inf)
        np.minimum.at(best, pt[ok], dist[ok])
        r = np.where(np.isfinite(best), best, self.size) * (1.0 + 1e-9) + 1e-12 * self.size
        E = len(self.entities)
        p, e = self._entity_boxes.near(X, r)
        if p.size == 0:
            return pt, ent, params, dist
        # closed form: where no seed of the point gave a result on that face; Newton: always (from the
        # face's own samples: the global ones can all lie in the basin of a farther minimum)
        fresh = ~np.isin(p * E + e, pt[ok] * E + ent[ok]) | ~self._closed_form[e]
        p, e = p[fresh], e[fresh]
        if p.size == 0:
            return pt, ent, params, dist
        q, e, par, _, d = self._rows_on(X[p], e, k_seeds)  # every seed's result: some may be on the face
        return (np.concatenate([pt, p[q]]), np.concatenate([ent, e]), np.concatenate([params, par]),
                np.concatenate([dist, d]))

    def _grid_cells(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The cells of surface ``i``'s search grid that may hold points of its face: ``(lo, hi)``
        their boxes (:func:`~nagata_snap.cad.bounds.cell_boxes`, ``(c, 3)`` each), ``(a, b)``
        their parameter rectangles' corners (``(c, 2)`` each).  A cell is kept where one of
        its 3 x 3 points passes the sample filter or an extra sample (a loop vertex) lies in it."""
        e = self.entities[i]
        self.entity_samples(i)  # its grid's axes
        u, v = self._axes[i]
        ur, vr = _refined(u), _refined(v)
        Pr = _grid(ur, vr)
        lo, hi = cell_boxes(evaluate_params(e, Pr, 0).reshape(len(ur), len(vr), 3))
        a = _grid(u[:-1], v[:-1])
        b = _grid(u[1:], v[1:])
        if self._filter is not None:
            on = np.asarray(self._filter(i, Pr), dtype=bool).reshape(len(ur), len(vr))
            win = np.lib.stride_tricks.sliding_window_view(on, (3, 3))[::2, ::2]
            keep = win.any(axis=(2, 3)).reshape(-1)
            extra = None if self._extra is None else self._extra[i]
            if extra is not None and len(extra):
                Pe = normalize_params(e, np.asarray(extra, dtype=float).reshape(-1, 2))
                iu = np.clip(np.searchsorted(u, Pe[:, 0], side="right") - 1, 0, len(u) - 2)
                iv = np.clip(np.searchsorted(v, Pe[:, 1], side="right") - 1, 0, len(v) - 2)
                keep[iu * (len(v) - 1) + iv] = True
            if keep.any():  # as the samples: an entity keeps at least its unfiltered grid
                lo, hi, a, b = lo[keep], hi[keep], a[keep], b[keep]
        return lo, hi, a, b

    def _all_cells(self) -> tuple[BoxClasses, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """The grid cells of every surface that does not project in closed form, for ball
        queries: ``(boxes, entity (c,), a (c, 2), b (c, 2), centre (c, 2))`` (:meth:`_grid_cells`;
        ``centre`` the middle of the parameter rectangle); None if there is none."""
        if self._cells is None:
            todo = [i for i in range(len(self.entities)) if not self._closed_form[i]]
            if self.param_dim != 2 or not todo:
                return None
            cells = [self._grid_cells(i) for i in todo]
            owner = np.repeat(todo, [len(c[0]) for c in cells])
            lo, hi, a, b = (np.concatenate([c[k] for c in cells]) for k in range(4))
            self._cells = (BoxClasses(lo, hi), owner, a, b, 0.5 * (a + b))
        return self._cells

    def _nearer_cells(self, X: np.ndarray, pt: np.ndarray, ent: np.ndarray, params: np.ndarray, dist: np.ndarray,
                      accept) -> tuple[np.ndarray, ...]:
        """The results ``(pt, ent, params, dist)``, with a Newton run from the centre of every
        grid cell of a surface that is not closed-form whose box is nearer to a point than the
        point's best (accepted) result (:mod:`~nagata_snap.cad.bounds`), but the cell that holds
        that result.  A point with no accepted result is bounded by its nearest sample (a
        point of a face).

        The seeds of a point are its nearest samples; where another sheet's samples are
        much denser near it than those of the sheet its closest point lies on, they all
        seed the farther minimum.  The boxes of the cells decide instead which pieces of the
        surfaces compete."""
        cells = self._all_cells()
        n = len(X)
        if cells is None or n == 0:
            return pt, ent, params, dist
        boxes, owner, a, b, centre = cells
        ok = np.ones(len(pt), dtype=bool) if accept is None else np.asarray(accept(ent, params), dtype=bool)
        lead = best_per_group(pt, (~ok, dist), n)
        has = (lead >= 0) & ok[np.maximum(lead, 0)]
        best = np.where(has, dist[np.maximum(lead, 0)], np.inf)
        if not has.all():
            best[~has] = self._all_samples()[3].query(X[~has])[0]
        p, c = boxes.near(X, best * (1.0 - CELL_MARGIN))
        # not the cell that holds the point's best result already
        lp = lead[p]
        held = has[p] & (owner[c] == ent[lp]) & np.all((a[c] <= params[lp]) & (params[lp] <= b[c]), axis=1)
        p, c = p[~held], c[~held]
        if p.size == 0:
            return pt, ent, params, dist
        par, _, d, _, _ = self.refine(p, owner[c], centre[c], X)
        return (np.concatenate([pt, p]), np.concatenate([ent, owner[c]]), np.concatenate([params, par]),
                np.concatenate([dist, d]))

    def search_all(
        self, points: npt.ArrayLike, k_seeds: int | None = None
    ) -> tuple[np.ndarray, ...]:
        """All Newton results from the ``k_seeds`` nearest samples of each point.

        Returns ``(pt, ent, params (n, d), proj (n, 3), dist, converged)`` with
        one row per (point, seed) pair; rows of the same point and entity may
        repeat.
        """
        X = _points3(points)
        sample_params, sample_points, sample_entity, tree = self._all_samples()
        k = min(self.k_seeds if k_seeds is None else int(k_seeds), len(sample_points))
        _, idx = tree.query(X, k=k)
        idx = idx.reshape(len(X), k)
        pt = np.repeat(np.arange(len(X)), k)
        s = idx.ravel()
        ent = sample_entity[s]
        params, proj, dist, _, conv = self.refine(pt, ent, sample_params[s], X)
        return pt, ent, params, proj, dist, conv

    def search_on(
        self,
        points: npt.ArrayLike,
        ent: npt.ArrayLike,
        k_seeds: int | None = None,
        accept: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    ) -> tuple[np.ndarray, ...]:
        """Closest point of each point on a *given* entity (per-entity KD-tree seeds).

        Args:
            points: ``(n, 3)``.
            ent: ``(n,)`` entity index per point.
            accept: optional ``f(ent (m,), params (m, d)) -> (m,) bool``; only
                accepted Newton results compete (see :meth:`search`).

        Returns:
            ``(params (n, d), proj (n, 3), dist (n,))``, with ``accepted (n,)``
            appended when ``accept`` is given (False: no seed gave an accepted
            result; the best unaccepted one is returned).
        """
        X = _points3(points)
        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        n = len(X)
        if ent.shape[0] != n:
            raise ValueError(f"{ent.shape[0]} entity indices for {n} points")
        if n == 0:
            empty = (np.zeros((0, self.param_dim)), np.zeros((0, 3)), np.zeros(0))
            return empty if accept is None else (*empty, np.zeros(0, dtype=bool))
        pt, en, params, proj, dist = self._rows_on(X, ent, k_seeds)
        return _pick(n, pt, en, params, dist, (params, proj), accept)

    def _rows_on(self, X: np.ndarray, ent: np.ndarray, k_seeds: int | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every Newton result of :meth:`search_on` of points ``X (n, 3)`` on entities
        ``ent (n,)``: ``(pt, ent, params, proj, dist)``, one row per (point, seed) pair."""
        kk = self.k_seeds if k_seeds is None else int(k_seeds)
        g = Groups(ent)
        # closed form: one projection per point, no seeds (all such entities at once)
        sel = g.order[self._analytic[ent[g.order]]]
        pts, ents, seeds = [sel], [ent[sel]], [np.full((len(sel), self.param_dim), np.nan)]
        for e, sl in g:  # loop over the entities that need Newton's seeds
            if self._analytic[e]:
                continue
            sel = g.order[sl]
            Pe = self.entity_samples(e)[0]
            ke = min(kk, len(Pe))
            _, idx = self._entity_tree(e).query(X[sel], k=ke)
            pts.append(np.repeat(sel, ke))
            ents.append(np.full(len(sel) * ke, e))
            seeds.append(Pe[idx.reshape(len(sel), ke).ravel()])
        en = np.concatenate(ents)
        order = np.argsort(en, kind="stable")  # grouped by entity, as they were found
        pt, en, sd = np.concatenate(pts)[order], en[order], np.concatenate(seeds)[order]
        params, proj, dist, _, _ = self.refine(pt, en, sd, X)
        return pt, en, params, proj, dist


def _pick(n: int, pt, ent, params, dist, columns: tuple, accept) -> tuple:
    """Per point ``0..n-1`` the rows of ``columns`` and ``dist`` of its nearest result.

    With ``accept(ent, params) -> bool`` accepted results come first and the
    flag is appended (see :meth:`GlobalSearcher.search`).
    """
    if accept is None:
        best = best_per_group(pt, dist, n)
        return (*tuple(c[best] for c in columns), dist[best])
    ok = np.asarray(accept(ent, params), dtype=bool)
    best = best_per_group(pt, (~ok, dist), n)
    return (*tuple(c[best] for c in columns), dist[best], ok[best])


def _points3(points: npt.ArrayLike, single: bool = True) -> np.ndarray:
    """``(k, 3)`` float points (``(k, 2)``: z = 0; with ``single`` one ``(3,)`` point too),
    checked finite."""
    X = np.asarray(points, dtype=float)
    if single and X.ndim == 1 and X.shape[0] in (2, 3):
        X = X[None, :]
    if X.ndim != 2 or X.shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (k, 3), got {X.shape}")
    if X.shape[1] == 2:
        X = np.c_[X, np.zeros(len(X))]
    _check_finite(X, "points")
    return X


#: largest coordinate magnitude accepted: squared distances (and Newton's
#: products of them) stay far from overflow
MAX_COORD = 1e100


def _check_finite(a: np.ndarray, what: str) -> None:
    """``ValueError`` for NaN/infinite entries, or coordinates beyond :data:`MAX_COORD`."""
    if a.size == 0:
        return
    flat = a.reshape(-1)
    # one pass, no temporary: every |a_i| <= sqrt(sum a_i^2) (a rounded sum of non-negative
    # terms is not below its largest term, itself rounded: the 1e-15 margin); NaN, inf and
    # overflow fail it and go to the exact test
    if flat @ flat <= MAX_COORD * MAX_COORD * (1.0 - 1e-15):
        return
    ok = np.isfinite(a) & (np.abs(a) <= MAX_COORD)
    if not ok.all():
        row = int(np.flatnonzero(~ok.reshape(len(a), -1).all(axis=1))[0])
        raise ValueError(
            f"{what} must be finite and at most {MAX_COORD:g} in magnitude; "
            f"{int((~ok.reshape(len(a), -1).all(axis=1)).sum())} rows are not (first: row {row}, "
            f"{a[row].tolist()})"
        )


def global_search(
    entities: Sequence[Entity] | Entity,
    points: npt.ArrayLike,
    *,
    k_seeds: int = 6,
    per_span: int | None = None,
    max_iter: int = 30,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on a set of curves or surfaces (patches), seeded by a KD-tree.

    Each entity is sampled once on a parameter grid (``per_span`` samples per
    knot span and direction, see :func:`sample_entity`); the ``k_seeds``
    nearest samples of each point (``scipy.spatial.cKDTree``) seed Newton
    (:func:`project_newton`); the closest result is kept (ties: lowest entity
    index).  This is Kadir's "evaluate at equally spaced parameters, start from
    the closest" (App. B.1), without the per-point scan of the whole grid.

    Args:
        entities: list of :class:`~nagata_snap.cad.nurbs.NurbsCurve` or of :class:`~nagata_snap.cad.nurbs.NurbsSurface`
            (a single entity is accepted).
        points: ``(k, 3)`` points.

    Returns:
        ``(entity_index (k,) int64, params (k, d), distance (k,))`` with
        ``d = 1`` for curves and ``2`` for surfaces.
    """
    if not isinstance(entities, Sequence):
        entities = [entities]
    ent, params, dist = GlobalSearcher(entities, per_span=per_span, k_seeds=k_seeds, max_iter=max_iter).search(points)
    return ent, params, dist
