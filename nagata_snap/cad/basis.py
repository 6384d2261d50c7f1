"""Compiled B-spline kernels (numba): basis functions with derivatives, and the homogeneous
sums of NURBS curves and surfaces.

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

import numba
import numpy as np

__all__ = ["basis", "curve_sums", "surface_points"]

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
        _basis_at(knots_u, p, su[k], u[k], nderiv, Nu, LR, lv, inv, D)
        _basis_at(knots_v, q, sv[k], v[k], nderiv, Nv, LR, lv, inv, D)
        base = (su[k] - p) * nv + sv[k] - q
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
            continue
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
    return out
