"""Compiled B-spline kernels (numba): basis functions with derivatives, the homogeneous
sums of NURBS curves and surfaces, and the closest-point Newton iteration on a NURBS surface
(:func:`surface_newton`: :func:`nagata_snap.cad.projection.project_newton`'s iteration, one
point at a time).

:mod:`nagata_snap.cad.nurbs` holds the formulas (its module docstring quotes them) and
the data; these kernels evaluate them one parameter value at a time, in registers.  A
projection evaluates a face at the same few points many times (Newton steps, line
search), so the per-call cost matters as much as the per-point cost: the numpy
formulation looped over the degree (about ``p^2`` array operations per call, a millisecond
on a degree-10 face), these loops over points.

The recurrences, in the span ``[u_s, u_{s+1})`` with ``left_j = u - u_{s+1-j}`` and
``right_j = u_{s+j} - u`` (Kadir (2010) eq. (A.3); Neto (2010) eq. (46)):

* degree ``r`` from degree ``r - 1`` (``a = 0..r``, one division per neighbouring pair)::

      N_r[a] = right_{a+1} N_{r-1}[a] / D_r[a] + left_{r-a+1} N_{r-1}[a-1] / D_r[a-1]
      D_r[a] = right_{a+1} + left_{r-a} = u_{s+a+1} - u_{s-r+a+1}

* derivative ``d`` from derivative ``d - 1`` one degree lower (the same ``D_r``)::

      N^{(d)}_r[a] = r (N^{(d-1)}_{r-1}[a-1] / D_r[a-1] - N^{(d-1)}_{r-1}[a] / D_r[a])

In a non-empty span every ``D_r[a]`` is positive (no 0/0 case).  The basis is computed
with the operations of the numpy formulation the project used before, in the same order
(the same bits); the sums agree with it to rounding (``tests/test_nurbs.py``).

Conventions: ``knots (m,)``, spans ``s (k,)`` int64 from :func:`nagata_snap.cad.nurbs.find_span`
(indices into ``knots``), homogeneous control points ``pw (c, n)`` (rows ``w P`` then ``w``;
a surface's net flattened row-major, ``n = nu nv``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["basis", "curve_sums", "surface_points", "surface_newton"]

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")
_inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")


@_inline
def _basis_at(knots: np.ndarray, p: int, s: int, u: float, nderiv: int, N: np.ndarray,
              LR: np.ndarray, lv: np.ndarray, inv: np.ndarray, D: np.ndarray) -> None:
    """``N[d, a]``: derivative ``d <= nderiv`` of the ``a``-th non-zero degree-``p`` function
    at ``u`` in span ``s``.  Work arrays: ``LR (2p,)``, ``lv, inv ((p+1), (p+1))`` and
    ``D (nderiv+1, p+1, p+1)`` (or larger)."""
    for i in range(2 * p):  # LR[i] = left_{p-i} (i < p), right_{i-p+1} (i >= p)
        t = knots[s + 1 - p + i]
        LR[i] = u - t if i < p else t - u
    lv[0, 0] = 1.0
    for r in range(1, p + 1):
        carry = 0.0
        for a in range(r):
            ia = 1.0 / (LR[p + a] + LR[p - r + a])
            inv[r, a] = ia
            temp = lv[r - 1, a] * ia
            lv[r, a] = carry + LR[p + a] * temp
            carry = temp * LR[p - r + a]
        lv[r, r] = carry
    for a in range(p + 1):
        N[0, a] = lv[p, a]
    for d in range(1, nderiv + 1):
        if d > p:  # derivatives of order > p vanish
            for a in range(p + 1):
                N[d, a] = 0.0
            continue
        for r in range(max(p - nderiv + d, d), p + 1):
            prev = 0.0
            for a in range(r + 1):
                t = 0.0
                if a < r:
                    t = (D[d - 1, r - 1, a] if d > 1 else lv[r - 1, a]) * inv[r, a]
                if a == 0:
                    D[d, r, a] = (0.0 - t) * r
                elif a == r:
                    D[d, r, a] = prev * r
                else:
                    D[d, r, a] = (prev - t) * r
                prev = t
        for a in range(p + 1):
            N[d, a] = D[d, p, a]


@_jit
def basis(knots: np.ndarray, p: int, span: np.ndarray, u: np.ndarray, nderiv: int,
          out: np.ndarray) -> np.ndarray:
    """``out (nderiv+1, p+1, k)``: the non-zero functions of degree ``p`` and their
    derivatives at ``u (k,)`` in ``span (k,)`` (points last)."""
    m = p + 1
    N = np.empty((nderiv + 1, m))
    LR, lv, inv, D = np.empty(max(2 * p, 1)), np.empty((m, m)), np.empty((m, m)), np.empty((nderiv + 1, m, m))
    for k in range(u.shape[0]):
        _basis_at(knots, p, span[k], u[k], nderiv, N, LR, lv, inv, D)
        for d in range(nderiv + 1):
            for a in range(m):
                out[d, a, k] = N[d, a]
    return out


@_jit
def curve_sums(knots: np.ndarray, pw: np.ndarray, p: int, span: np.ndarray, first: np.ndarray,
               u: np.ndarray, nderiv: int, H: np.ndarray) -> np.ndarray:
    """``H (nderiv+1, c, k)``: ``sum_a N^{(d)}_a(u) pw[:, first + a]`` (see
    :meth:`nagata_snap.cad.nurbs.NurbsCurve._sums`)."""
    m = p + 1
    ch = pw.shape[0]
    N = np.empty((nderiv + 1, m))
    LR, lv, inv, D = np.empty(max(2 * p, 1)), np.empty((m, m)), np.empty((m, m)), np.empty((nderiv + 1, m, m))
    for k in range(u.shape[0]):
        _basis_at(knots, p, span[k], u[k], nderiv, N, LR, lv, inv, D)
        f = first[k]
        for d in range(nderiv + 1):
            for c in range(ch):
                acc = 0.0
                for a in range(m):
                    acc += N[d, a] * pw[c, f + a]
                H[d, c, k] = acc
    return H


@_inline
def _surface_at(knots_u: np.ndarray, knots_v: np.ndarray, p: int, q: int, nv: int, pw: np.ndarray,
                su: int, sv: int, u: float, v: float, nderiv: int, oa: np.ndarray, ob: np.ndarray,
                out: np.ndarray, k: int, Nu: np.ndarray, Nv: np.ndarray, LR: np.ndarray, lv: np.ndarray,
                inv: np.ndarray, D: np.ndarray, T: np.ndarray, H: np.ndarray) -> None:
    """``out[:, :, k]``: the surface's point and derivatives at ``(u, v)`` in the spans
    ``(su, sv)`` (one point of :func:`surface_points`; the work arrays as allocated there)."""
    ch = pw.shape[0]
    no = oa.shape[0]
    _basis_at(knots_u, p, su, u, nderiv, Nu, LR, lv, inv, D)
    _basis_at(knots_v, q, sv, v, nderiv, Nv, LR, lv, inv, D)
    base = (su - p) * nv + sv - q
    for b in range(nderiv + 1):
        for c in range(ch):
            for i in range(p + 1):
                row = base + i * nv
                acc = 0.0
                for j in range(q + 1):
                    acc += Nv[b, j] * pw[c, row + j]
                T[b, c, i] = acc
    for n in range(no):
        a, b = oa[n], ob[n]
        for c in range(ch):
            acc = 0.0
            for i in range(p + 1):
                acc += Nu[a, i] * T[b, c, i]
            H[n, c] = acc
    if ch == 3:
        for n in range(no):
            for c in range(3):
                out[n, c, k] = H[n, c]
        return
    iB = 1.0 / H[0, 3]
    for c in range(3):
        s0 = H[0, c] * iB
        out[0, c, k] = s0
        if no >= 3:
            s1 = (H[1, c] - H[1, 3] * s0) * iB
            s2 = (H[2, c] - H[2, 3] * s0) * iB
            out[1, c, k], out[2, c, k] = s1, s2
            if no >= 6:
                out[3, c, k] = (H[3, c] - 2.0 * H[1, 3] * s1 - H[3, 3] * s0) * iB
                out[4, c, k] = (H[4, c] - H[1, 3] * s2 - H[2, 3] * s1 - H[4, 3] * s0) * iB
                out[5, c, k] = (H[5, c] - 2.0 * H[2, 3] * s2 - H[5, 3] * s0) * iB


@_jit
def surface_points(knots_u: np.ndarray, knots_v: np.ndarray, p: int, q: int, nv: int, pw: np.ndarray,
                   su: np.ndarray, sv: np.ndarray, u: np.ndarray, v: np.ndarray, nderiv: int,
                   oa: np.ndarray, ob: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``out (orders, 3, k)``: the surface's points and derivatives of the orders ``(oa[n],
    ob[n])`` (``S, Su, Sv, Suu, Suv, Svv`` for ``nderiv`` 2).

    The sums ``H_ab = sum_ij N^{(a)}_i(u) N^{(b)}_j(v) pw[:, i nv + j]`` over the
    ``(p+1) x (q+1)`` block of each point, contracted along ``v`` first, then along ``u``;
    with four rows of ``pw`` (rational: ``A_ab`` and ``B_ab``) the quotient rule of
    :mod:`nagata_snap.cad.nurbs`' module docstring (Neto (2010) eqs. (42)-(44)) per point.
    """
    ch = pw.shape[0]
    no = oa.shape[0]
    m = max(p, q) + 1
    Nu, Nv = np.empty((nderiv + 1, p + 1)), np.empty((nderiv + 1, q + 1))
    LR, lv, inv, D = np.empty(2 * m), np.empty((m, m)), np.empty((m, m)), np.empty((nderiv + 1, m, m))
    T = np.empty((nderiv + 1, ch, p + 1))
    H = np.empty((no, ch))
    for k in range(u.shape[0]):
        _surface_at(knots_u, knots_v, p, q, nv, pw, su[k], sv[k], u[k], v[k], nderiv, oa, ob, out, k,
                    Nu, Nv, LR, lv, inv, D, T, H)
    return out


@_inline
def _wrap_or_clamp(x: float, a: int, bounds: np.ndarray, periods: np.ndarray, limits: np.ndarray) -> float:
    """Parameter ``x`` of direction ``a`` wrapped into ``[lo, lo + period]`` (closed: only if
    outside, as ``lo + mod(x - lo, period)``) or clamped to ``limits[a]`` (open)."""
    per = periods[a]
    if math.isfinite(per):
        lo = bounds[a, 0]
        if x < lo or x > lo + per:
            x = lo + np.mod(x - lo, per)
        return x
    return min(max(x, limits[a, 0]), limits[a, 1])


@_inline
def _step_length(E: np.ndarray, d0: float, d1: float) -> float:
    """``|d0 S_u + d1 S_v|`` at the evaluation ``E (6, 3, 1)``."""
    acc = 0.0
    for c in range(3):
        w = E[1, c, 0] * d0 + E[2, c, 0] * d1
        acc += w * w
    return math.sqrt(acc)


@_inline
def _distance(E: np.ndarray, X: np.ndarray, k: int, r: np.ndarray) -> float:
    """``r = S - X[:, k]`` (into ``r (3,)``) and its length."""
    for c in range(3):
        r[c] = E[0, c, 0] - X[c, k]
    return math.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])


@_jit
def surface_newton(knots_u: np.ndarray, knots_v: np.ndarray, p: int, q: int, nv: int, pw: np.ndarray,
                   spans_u: np.ndarray, spans_v: np.ndarray, bounds: np.ndarray, periods: np.ndarray,
                   limits: np.ndarray, X: np.ndarray, P: np.ndarray, max_iter: int, tols: np.ndarray,
                   max_halvings: int, S: np.ndarray, dist: np.ndarray, iters: np.ndarray,
                   conv: np.ndarray) -> None:
    """Closest points of ``X (3, k)`` on a NURBS surface by seeded Newton, one point at a time:
    the iteration of :func:`nagata_snap.cad.projection.project_newton` (its ``_newton_step``,
    ``_retire`` and ``_backtrack``) with the same operations in the same order, so the same
    iterates; ``P (2, k)`` the seeds (wrapped / clamped) on entry, the parameters on exit,
    ``S (3, k)``, ``dist``, ``iters``, ``conv (k,)`` filled.  ``tols``: ``(step, zero, cos, acc,
    slack)`` of ``projection._Tolerances``; ``periods`` NaN where open."""
    m = max(p, q) + 1
    Nu, Nv = np.empty((3, p + 1)), np.empty((3, q + 1))
    LR, lv, inv, D = np.empty(2 * m), np.empty((m, m)), np.empty((m, m)), np.empty((3, m, m))
    T = np.empty((3, pw.shape[0], p + 1))
    H = np.empty((6, pw.shape[0]))
    oa = np.array([0, 1, 0, 2, 1, 0], dtype=np.int64)
    ob = np.array([0, 0, 1, 0, 1, 2], dtype=np.int64)
    E, En = np.empty((6, 3, 1)), np.empty((6, 3, 1))
    r, rn = np.empty(3), np.empty(3)
    tol, zero, cos_tol, acc_tol, slack = tols[0], tols[1], tols[2], tols[3], tols[4]
    cap0, cap1 = 0.25 * (bounds[0, 1] - bounds[0, 0]), 0.25 * (bounds[1, 1] - bounds[1, 0])
    tiny = np.finfo(np.float64).tiny
    for k in range(X.shape[1]):
        u, v = P[0, k], P[1, k]
        _surface_at(knots_u, knots_v, p, q, nv, pw, spans_u[np.searchsorted(knots_u, u, side="right")],
                    spans_v[np.searchsorted(knots_v, v, side="right")], u, v, 2, oa, ob, E, 0,
                    Nu, Nv, LR, lv, inv, D, T, H)
        d = _distance(E, X, k, r)
        sprev = np.inf
        its = 0
        for it in range(max_iter + 1):
            # _newton_system and _solve_step
            g0 = r[0] * E[1, 0, 0] + r[1] * E[1, 1, 0] + r[2] * E[1, 2, 0]
            g1 = r[0] * E[2, 0, 0] + r[1] * E[2, 1, 0] + r[2] * E[2, 2, 0]
            G0 = E[1, 0, 0] * E[1, 0, 0] + E[1, 1, 0] * E[1, 1, 0] + E[1, 2, 0] * E[1, 2, 0]
            G1 = E[1, 0, 0] * E[2, 0, 0] + E[1, 1, 0] * E[2, 1, 0] + E[1, 2, 0] * E[2, 2, 0]
            G2 = E[2, 0, 0] * E[2, 0, 0] + E[2, 1, 0] * E[2, 1, 0] + E[2, 2, 0] * E[2, 2, 0]
            a = G0 + (r[0] * E[3, 0, 0] + r[1] * E[3, 1, 0] + r[2] * E[3, 2, 0])
            b = G1 + (r[0] * E[4, 0, 0] + r[1] * E[4, 1, 0] + r[2] * E[4, 2, 0])
            c = G2 + (r[0] * E[5, 0, 0] + r[1] * E[5, 1, 0] + r[2] * E[5, 2, 0])
            det = a * c - b * b
            pd = (a > 0) and (c > 0) and (det > 1e-12 * a * c)
            tr = G0 + G2
            psd = (a >= -1e-12 * tr) and (c >= -1e-12 * tr) and (det >= -1e-12 * tr * tr)
            if not pd:
                mu = 1e-10 * (G0 + G2) + tiny
                a, b, c = G0 + mu, G1, G2 + mu
                det = a * c - b * b
            s0, s1 = -(c * g0 - b * g1) / det, -(a * g1 - b * g0) / det
            if not (math.isfinite(s0) and math.isfinite(s1)):
                s0, s1 = 0.0, 0.0
            scale = min(min(1.0, cap0 / max(abs(s0), 1e-300)), min(1.0, cap1 / max(abs(s1), 1e-300)))
            s0, s1 = s0 * scale, s1 * scale
            # _apply_step, the criteria
            n0 = _wrap_or_clamp(P[0, k] + s0, 0, bounds, periods, limits)
            n1 = _wrap_or_clamp(P[1, k] + s1, 1, bounds, periods, limits)
            d0 = s0 if math.isfinite(periods[0]) else n0 - P[0, k]
            d1 = s1 if math.isfinite(periods[1]) else n1 - P[1, k]
            length = _step_length(E, d0, d1)
            pred = length * length * length / max(sprev * sprev, 1e-300) if math.isfinite(sprev) else length
            small = pd and (length <= tol) and (pred <= acc_tol)
            cos = 0.0
            den = math.sqrt(G0) * d
            if den > 0:
                cos = max(cos, abs(g0) / den)
            den = math.sqrt(G2) * d
            if den > 0:
                cos = max(cos, abs(g1) / den)
            done = small or (d <= zero) or (psd and cos <= cos_tol)
            if it == max_iter or done or length == 0.0:  # _retire
                acc = 0.0
                for ci in range(3):
                    sf = E[0, ci, 0] + ((d0 * E[1, ci, 0] + d1 * E[2, ci, 0]) if small else 0.0)
                    S[ci, k] = sf
                    rf = sf - X[ci, k]
                    acc += rf * rf
                if small:
                    P[0, k], P[1, k] = n0, n1
                    if length > zero:
                        its += 1
                dist[k], conv[k] = math.sqrt(acc), done
                break
            # _backtrack
            _surface_at(knots_u, knots_v, p, q, nv, pw, spans_u[np.searchsorted(knots_u, n0, side="right")],
                        spans_v[np.searchsorted(knots_v, n1, side="right")], n0, n1, 2, oa, ob, En, 0,
                        Nu, Nv, LR, lv, inv, D, T, H)
            dn = _distance(En, X, k, rn)
            alpha = 1.0
            for _h in range(max_halvings):
                if not dn > d + slack:
                    break
                alpha *= 0.5
                n0 = _wrap_or_clamp(P[0, k] + alpha * s0, 0, bounds, periods, limits)
                n1 = _wrap_or_clamp(P[1, k] + alpha * s1, 1, bounds, periods, limits)
                h0 = alpha * s0 if math.isfinite(periods[0]) else n0 - P[0, k]
                h1 = alpha * s1 if math.isfinite(periods[1]) else n1 - P[1, k]
                _surface_at(knots_u, knots_v, p, q, nv, pw, spans_u[np.searchsorted(knots_u, n0, side="right")],
                            spans_v[np.searchsorted(knots_v, n1, side="right")], n0, n1, 2, oa, ob, En, 0,
                            Nu, Nv, LR, lv, inv, D, T, H)
                dn = _distance(En, X, k, rn)
                length = _step_length(E, h0, h1)
            if dn > d + slack:  # stalled: the old iterate, not converged
                for ci in range(3):
                    S[ci, k] = E[0, ci, 0]
                dist[k], conv[k] = d, False
                break
            its += 1
            P[0, k], P[1, k] = n0, n1
            E[:, :, :] = En
            r[:] = rn
            d, sprev = dn, length
        iters[k] = its
