"""Nagata curves and triangular patches, vectorised over many edges/patches.

All formulas are from T. Nagata, "Simple local interpolation of surfaces
using normal vectors", CAGD 22 (2005) 327-347 (seed 002); equation numbers
below refer to that paper.

Edge curve (eq. 1), for end points ``x0, x1`` and unit normals ``n0, n1``::

    x(xi) = x0 + (d - c) xi + c xi^2 = (1 - xi) x0 + xi x1 - c xi (1 - xi),   d = x1 - x0

The curvature coefficient ``c`` is eq. (15) for one normal per end, or the
generalized-inverse solution eq. (20) with eqs. (29)-(32) when an edge carries
several normals per end (sharp edges, open boundaries).

Triangular patch (eq. 44), written with barycentric coordinates
``l1 = 1 - eta, l2 = eta - zeta, l3 = zeta``::

    x = l1 x1 + l2 x2 + l3 x3 - c12 l1 l2 - c23 l2 l3 - c13 l1 l3

with ``c12 = c(x2 - x1, n1, n2)`` etc. (eqs. 39a-39c).  The same barycentric
form with a single edge is the curve (eq. 1), so :func:`evaluate` serves both.

Closest points (:func:`closest_on_curve`, :func:`closest_on_patch`) solve
the orthogonality conditions ``x_u . r = x_v . r = 0``, ``r = x(u, v) - p``,
by Newton's method with the Jacobian ``[[|x_u|^2 + r.x_uu, x_u.x_v + r.x_uv],
[x_u.x_v + r.x_uv, |x_v|^2 + r.x_vv]]`` (Neto 2010, eqs. 32-36, written there
for NURBS).  The derivatives: on a curve (eq. 1) ``x_xi = d - c + 2 c xi``,
``x_xixi = 2 c``; on a patch, from the monomial form (eq. 37),
``x_etaeta = 2 c20``, ``x_zetazeta = 2 c02``, ``x_etazeta = c11``.

Arrays: ``(..., 3)`` vectors (a 2D mesh uses ``z = 0``), leading axes are
edges or patches; nothing loops in Python over edges or points.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = [
    "EPS",
    "curve_coefficient",
    "curve_coefficient_multi",
    "curve",
    "evaluate",
    "patch_derivatives",
    "patch_normal",
    "patch_coefficients",
    "closest_on_curve",
    "closest_on_patch",
    "LOCAL_EDGES",
]

#: Threshold epsilon of Nagata's singular-case rules (sec. 2.1.1 for
#: ``Delta c``, sec. 2.1.2 for the determinant coefficients ``D^(k)``).
#: Both quantities are dimensionless; neither seed gives a value.  1e-10
#: corresponds to normals about 2e-5 rad apart.
EPS = 1.0e-10

#: Bound on the second term of eq. (15), ``|d.v| <= TILT_MAX Dc |d|`` (Nagata,
#: after eq. 33: "similar constraint can be imposed also on the magnitude of
#: the solution c").  ``|(d.v) / Dc dv| = |d.v| / sqrt(Dc)`` does not vanish
#: as the normals become parallel: a chord tilted by ``t`` against nearly
#: parallel normals ``phi`` apart gets ``|c| ~ |d| t / phi``.  Exact normals of
#: a smooth curve give ``|d.v| / (Dc |d|) ~ |kappa'| / kappa^2`` (0 on a
#: circle); estimated ones add noise ``t`` independent of ``phi``, e.g. a
#: straight edge on a cylinder with normals 0.3 deg apart got ``|c| = 1.7 |d|``.
TILT_MAX = 1.0

#: Rank threshold of :func:`curve_coefficient_multi`: ``[s]`` counts as rank 2
#: when its smallest eigenvalue is below this fraction of its largest.
#: Estimated normals on both sides of a straight crease are never exactly
#: coplanar at the two ends; the nearly-null direction (along the edge) then
#: carries ``rhs / lambda_min``, a coefficient of many edge lengths (a folded
#: patch), where the exact normals give none.
RANK_TOL = 0.1

#: Local vertex pairs of the edges of a facet with ``nfv`` vertices, in the
#: order c1, c2, c3 of eq. (39): (v1,v2), (v2,v3), (v1,v3).
LOCAL_EDGES = {2: np.array([[0, 1]]), 3: np.array([[0, 1], [1, 2], [0, 2]])}


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def curve_coefficient(
    d: npt.ArrayLike, n0: npt.ArrayLike, n1: npt.ArrayLike, eps: float = EPS,
    tilt_max: float | None = None,
) -> np.ndarray:
    """Curvature coefficient ``c(d, n0, n1)`` of the Nagata curve, eq. (15).

    With ``v = (n0 + n1)/2``, ``dv = (n0 - n1)/2`` (eq. 12), ``d = d.v``,
    ``Dd = d.dv`` (eq. 13) and ``Dc = n0.dv`` (eq. 14b)::

        c = Dd / (1 - Dc) v + d / Dc dv

    Singular cases (sec. 2.1.1): the first term is dropped when
    ``1 - Dc < eps`` and the second when ``Dc < eps``; parallel normals thus
    give ``c = 0`` (a straight edge stays exactly straight).  With
    ``tilt_max`` (for estimated normals, see :data:`TILT_MAX`) the second
    term is bounded, ``|d.v| <= tilt_max Dc |x1 - x0|``; then eq. (6) no
    longer holds exactly where the bound is active.

    Args:
        d: ``(..., 3)`` edge vectors ``x1 - x0`` (length units).
        n0, n1: ``(..., 3)`` unit normals at the two ends.
        eps: dimensionless singularity threshold.
        tilt_max: bound of the second term (None: eq. (15) as published).

    Returns:
        ``(..., 3)`` coefficients ``c`` (length units).  The result is the
        same for the reversed edge ``c(-d, n1, n0)``.
    """
    d = np.asarray(d, dtype=float)
    n0 = np.asarray(n0, dtype=float)
    n1 = np.asarray(n1, dtype=float)
    v = 0.5 * (n0 + n1)
    dv = 0.5 * (n0 - n1)
    dd = _dot(d, v)
    ddelta = _dot(d, dv)
    dc = _dot(n0, dv)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(1.0 - dc < eps, 0.0, ddelta / (1.0 - dc))
        if tilt_max is not None:
            lim = tilt_max * dc * np.linalg.norm(d, axis=-1)
            dd = np.clip(dd, -lim, lim)
        b = np.where(dc < eps, 0.0, dd / dc)
    return a[..., None] * v + b[..., None] * dv


def curve_coefficient_multi(
    d: npt.ArrayLike, n0: npt.ArrayLike, n1: npt.ArrayLike, eps: float = EPS
) -> np.ndarray:
    """Curvature coefficient for several normals per end, eqs. (20), (31), (32).

    The orthogonality conditions ``n0k.(d - c) = 0`` and ``n1k.(d + c) = 0``
    for all normals ``n0k`` at the first end and ``n1k`` at the second end
    (eq. 32) are solved in the minimum-norm least-squares sense,
    ``c = [n]^+ {d}`` (eq. 20), with the generalized inverse from eq. (31):
    ``[s] = [n]^T [n]`` (eq. 33), ``a_i^(0) = s_j x s_k`` (26c),
    ``a_i^(1) = s_j x e_k + e_j x s_k`` (26b), ``D^(2) = e_i.(s_i + a_i^(1))``,
    ``D^(1) = s_i.a_i^(1) + e_i.a_i^(0)``, ``D^(0) = s_i.a_i^(0)`` (29), each
    treated as zero below ``eps`` (sec. 2.1.2).  A nearly rank-2 ``[s]``
    (smallest eigenvalue below :data:`RANK_TOL` of the largest) is solved
    as rank 2: its nearly-null eigen-direction is dropped (the truncated
    pseudo-inverse, which is eq. (31) with ``D^(0) = 0`` for an exactly
    rank-2 ``[s]``).

    Zero rows are allowed as padding (they add nothing to ``[s]`` nor to
    ``[n]^T{d}``), so edges with different numbers of normals share one array.

    Args:
        d: ``(E, 3)`` edge vectors.
        n0: ``(E, p, 3)`` normals at the first end (unit, or zero padding).
        n1: ``(E, q, 3)`` normals at the second end.
        eps: dimensionless threshold for ``D^(k)``.

    Returns:
        ``(E, 3)`` coefficients.
    """
    d = np.asarray(d, dtype=float)
    n0 = np.asarray(n0, dtype=float)
    n1 = np.asarray(n1, dtype=float)
    # [n]^T {d}: rows n0k with right-hand side n0k.d, rows n1k with -n1k.d (eq. 32)
    rhs = np.einsum("epi,ep->ei", n0, _dot(n0, d[:, None, :])) - np.einsum(
        "eqi,eq->ei", n1, _dot(n1, d[:, None, :])
    )
    s = np.einsum("epi,epj->eij", n0, n0) + np.einsum("eqi,eqj->eij", n1, n1)  # eq. (33)
    e = np.eye(3)
    # columns s_i of [s] (eq. 22); (i, j, k) cyclic
    sc = np.moveaxis(s, 2, 1)  # sc[:, i] = s_i
    ijk = [(0, 1, 2), (1, 2, 0), (2, 0, 1)]
    a0 = np.stack([np.cross(sc[:, j], sc[:, k]) for i, j, k in ijk], axis=1)  # (26c)
    a1 = np.stack(
        [np.cross(sc[:, j], e[k]) + np.cross(e[j], sc[:, k]) for i, j, k in ijk], axis=1
    )  # (26b)
    d2 = sc[:, 0, 0] + a1[:, 0, 0]  # (29a) with i = 1
    d1 = _dot(sc[:, 0], a1[:, 0]) + a0[:, 0, 0]  # (29b)
    d0 = _dot(sc[:, 0], a0[:, 0])  # (29c)
    c0 = np.einsum("eij,ej->ei", a0, rhs)
    c1 = np.einsum("eij,ej->ei", a1, rhs)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(
            (np.abs(d0) > eps)[:, None],
            c0 / d0[:, None],
            np.where(
                (np.abs(d1) > eps)[:, None],
                c1 / d1[:, None],
                np.where((np.abs(d2) > eps)[:, None], rhs / d2[:, None], 0.0),
            ),
        )
    near = np.flatnonzero(np.abs(d0) > eps)
    if near.size:
        lam, vec = np.linalg.eigh(s[near])  # ascending eigenvalues
        trunc = lam[:, 0] < RANK_TOL * lam[:, 2]
        if trunc.any():
            lam, vec, r = lam[trunc, 1:], vec[trunc][:, :, 1:], rhs[near[trunc]]
            coef = np.einsum("eik,ei->ek", vec, r) / lam
            c[near[trunc]] = np.einsum("eik,ek->ei", vec, coef)
    return c


def curve(x0: np.ndarray, x1: np.ndarray, c: np.ndarray, xi: npt.ArrayLike) -> np.ndarray:
    """Points of Nagata curves, eq. (1).

    Args:
        x0, x1: ``(E, 3)`` end points; c: ``(E, 3)`` coefficients.
        xi: ``(E, k)`` or ``(k,)`` curve parameters in [0, 1].

    Returns:
        ``(E, k, 3)`` points.
    """
    xi = np.broadcast_to(np.asarray(xi, dtype=float), (x0.shape[0], np.shape(xi)[-1]))[..., None]
    return (1.0 - xi) * x0[:, None] + xi * x1[:, None] - c[:, None] * (xi * (1.0 - xi))


def evaluate(x: np.ndarray, c: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Evaluate Nagata curves (``nfv = 2``) or triangular patches (``nfv = 3``).

    Eq. (44) in barycentric form: ``sum_i l_i x_i - sum_edges c_ab l_a l_b``,
    edges ordered as :data:`LOCAL_EDGES`.  Vertices are reproduced exactly.

    Args:
        x: ``(P, nfv, 3)`` patch vertices.
        c: ``(P, ne, 3)`` edge coefficients (``ne = 1`` or ``3``).
        lam: ``(P, k, nfv)`` barycentric coordinates of the ``k`` points to
            evaluate on each patch.

    Returns:
        ``(P, k, 3)`` points.
    """
    edges = LOCAL_EDGES[x.shape[1]]
    lin = np.einsum("pkv,pvi->pki", lam, x)
    quad = lam[:, :, edges[:, 0]] * lam[:, :, edges[:, 1]]  # (P, k, ne)
    return lin - np.einsum("pke,pei->pki", quad, c)


def patch_derivatives(
    x: np.ndarray, c: np.ndarray, eta: np.ndarray, zeta: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Tangents ``x_eta``, ``x_zeta`` of triangular patches, eq. (45).

    Args:
        x: ``(P, 3, 3)`` vertices ``x00, x10, x11`` (eq. 35).
        c: ``(P, 3, 3)`` edge coefficients ``c1, c2, c3`` (eq. 39).
        eta, zeta: ``(P, k)`` parameters with ``0 <= zeta <= eta <= 1`` (eq. 34).

    Returns:
        ``x_eta``, ``x_zeta``, each ``(P, k, 3)``.
    """
    d1 = (x[:, 1] - x[:, 0])[:, None]
    d2 = (x[:, 2] - x[:, 1])[:, None]
    c1, c2, c3 = (c[:, i][:, None] for i in range(3))
    eta = eta[..., None]
    zeta = zeta[..., None]
    x_eta = d1 + c1 * ((eta - zeta) - (1.0 - eta)) + (c3 - c2) * zeta  # (45a)
    x_zeta = d2 + c2 * (zeta - (eta - zeta)) + (c1 - c3) * (1.0 - eta)  # (45b)
    return x_eta, x_zeta


def patch_normal(x: np.ndarray, c: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """Unit normals ``x_eta x x_zeta / |.|`` of triangular patches at barycentric points.

    Args:
        x: ``(P, 3, 3)`` vertices; c: ``(P, 3, 3)`` edge coefficients.
        lam: ``(P, k, 3)`` barycentric coordinates (``eta = 1 - l1``, ``zeta = l3``).

    Returns:
        ``(P, k, 3)`` unit normals, oriented like ``(x2 - x1) x (x3 - x1)``.
    """
    eta = 1.0 - lam[..., 0]
    zeta = lam[..., 2]
    xe, xz = patch_derivatives(x, c, eta, zeta)
    n = np.cross(xe, xz)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def patch_coefficients(x: np.ndarray, c: np.ndarray) -> dict[str, np.ndarray]:
    """Monomial coefficients ``c00 .. c02`` of eq. (37) from eq. (43).

    Args:
        x: ``(P, 3, 3)`` vertices ``x00, x10, x11``; c: ``(P, 3, 3)`` ``c1, c2, c3``.

    Returns:
        dict of ``(P, 3)`` arrays keyed ``c00, c10, c01, c11, c20, c02``.
    """
    d1 = x[:, 1] - x[:, 0]
    d2 = x[:, 2] - x[:, 1]
    c1, c2, c3 = c[:, 0], c[:, 1], c[:, 2]
    return {
        "c00": x[:, 0].copy(),  # (43a)
        "c10": d1 - c1,  # (43b)
        "c01": d2 + c1 - c3,  # (43c)
        "c11": c3 - c1 - c2,  # (43d)
        "c20": c1.copy(),  # (43e)
        "c02": c2.copy(),  # (43f)
    }


#: Newton iterations of the closest-point kernels (quadratic convergence
#: from a seed within a cell size: 2-4 are used, the rest are no-ops).
CLOSEST_ITERATIONS = 12


def _newton_step_1d(g: np.ndarray, h: np.ndarray, gn: np.ndarray) -> np.ndarray:
    """Step ``-g / h``, with the Gauss-Newton curvature ``gn`` where ``h`` is not safely positive."""
    h = np.where(h > 0.1 * gn, h, gn)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(h > 0, -g / h, 0.0)


def closest_on_curve(x0: np.ndarray, x1: np.ndarray, c: np.ndarray, xi: np.ndarray,
                     p: np.ndarray, iterations: int = CLOSEST_ITERATIONS) -> np.ndarray:
    """Parameter of the closest point of Nagata curves to points, kept in [0, 1].

    Newton on ``f(xi) = x_xi . (x(xi) - p) = 0`` (Neto 2010, eqs. 32-36 in one
    variable), ``x_xi = d - c + 2 c xi``, ``x_xixi = 2 c`` (eq. 1); a step
    where the second derivative of the distance is not positive falls back to
    Gauss-Newton, steps are at most 0.5 and the parameter is clipped to the
    curve, so a point beyond an end converges to that end.

    Args:
        x0, x1: ``(P, 3)`` end points; c: ``(P, 3)`` coefficients.
        xi: ``(P,)`` seeds in [0, 1]; p: ``(P, 3)`` points.

    Returns:
        ``(P,)`` parameters in [0, 1].
    """
    d = x1 - x0
    t = np.clip(np.asarray(xi, dtype=float), 0.0, 1.0)
    for _ in range(iterations):
        tt = t[:, None]
        r = x0 + (d - c) * tt + c * tt * tt - p
        xt = d - c + 2.0 * c * tt
        gn = _dot(xt, xt)
        step = _newton_step_1d(_dot(xt, r), gn + 2.0 * _dot(r, c), gn)
        t = np.clip(t + np.clip(step, -0.5, 0.5), 0.0, 1.0)
    return t


def closest_on_patch(x: np.ndarray, c: np.ndarray, lam: np.ndarray, p: np.ndarray,
                     iterations: int = CLOSEST_ITERATIONS) -> np.ndarray:
    """Barycentric coordinates of the closest point of triangular patches, unconstrained.

    Newton in ``(eta, zeta)`` (``eta = 1 - l1``, ``zeta = l3``, eq. 34) on the
    orthogonality conditions (Neto 2010, eqs. 32-36) with the monomial
    derivatives of eq. (37): ``x_eta = c10 + c11 zeta + 2 c20 eta``,
    ``x_zeta = c01 + c11 eta + 2 c02 zeta``, ``x_etaeta = 2 c20``,
    ``x_zetazeta = 2 c02``, ``x_etazeta = c11``.  Where the Jacobian is not
    positive definite the Gauss-Newton matrix ``J^T J`` is used; steps are at
    most 0.5 in parameter length.  The result may lie outside the triangle
    (a negative coordinate): the caller decides (:meth:`NagataGeometry.project`
    continues on the nearest edge).

    Args:
        x: ``(P, 3, 3)`` patch vertices; c: ``(P, 3, 3)`` edge coefficients.
        lam: ``(P, 3)`` barycentric seeds; p: ``(P, 3)`` points.

    Returns:
        ``(P, 3)`` barycentric coordinates (rows sum to one).
    """
    m = patch_coefficients(x, c)
    eta = 1.0 - lam[:, 0]
    zeta = lam[:, 2].copy()
    for _ in range(iterations):
        e, z = eta[:, None], zeta[:, None]
        r = m["c00"] + m["c10"] * e + m["c01"] * z + m["c11"] * e * z + m["c20"] * e * e \
            + m["c02"] * z * z - p
        xe = m["c10"] + m["c11"] * z + 2.0 * m["c20"] * e
        xz = m["c01"] + m["c11"] * e + 2.0 * m["c02"] * z
        a, b, d = _dot(xe, xe), _dot(xe, xz), _dot(xz, xz)  # J^T J
        ha = a + 2.0 * _dot(r, m["c20"])
        hb = b + _dot(r, m["c11"])
        hd = d + 2.0 * _dot(r, m["c02"])
        pd = (ha > 0) & (ha * hd - hb * hb > 1e-2 * (a * d - b * b))
        ha, hb, hd = np.where(pd, ha, a), np.where(pd, hb, b), np.where(pd, hd, d)
        ge, gz = _dot(xe, r), _dot(xz, r)
        det = ha * hd - hb * hb
        with np.errstate(divide="ignore", invalid="ignore"):
            de = np.where(det > 0, -(hd * ge - hb * gz) / det, 0.0)
            dz = np.where(det > 0, -(ha * gz - hb * ge) / det, 0.0)
        scale = np.minimum(1.0, 0.5 / np.maximum(np.hypot(de, dz), 1e-300))
        eta = eta + scale * de
        zeta = zeta + scale * dz
    return np.stack([1.0 - eta, eta - zeta, zeta], axis=1)
