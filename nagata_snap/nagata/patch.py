"""Nagata curves and triangular patches, vectorised over many edges/patches.

All formulas are from T. Nagata, "Simple local interpolation of surfaces
using normal vectors", CAGD 22 (2005) 327-347 (seed 002); equation numbers
below refer to that paper.

Edge curve (eq. 1), for end points ``x0, x1`` and unit normals ``n0, n1``::

    x(xi) = x0 + (d - c) xi + c xi^2 = (1 - xi) x0 + xi x1 - c xi (1 - xi),   d = x1 - x0

The curvature coefficient ``c`` is eq. (15) for one normal per end, or the
generalized-inverse solution eq. (20) (the inverse of eqs. 26-33, computed
from the eigen-decomposition of ``[s]``) when an edge carries several normals
per end (sharp edges, open boundaries); both are bounded by :data:`B_MAX`
where Nagata's formula is ill-determined.

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

from nagata_snap.mesh.arrays import dot_last

__all__ = [
    "EPS",
    "B_MAX",
    "curve_coefficient",
    "curve_coefficient_multi",
    "curve",
    "evaluate",
    "patch_coefficients",
    "patch_tangents",
    "closest_on_curve",
    "closest_on_patch",
    "LOCAL_EDGES",
]

#: Threshold epsilon of Nagata's singular-case rules (sec. 2.1.1 for
#: ``Delta c``, sec. 2.1.2 for the determinant coefficients ``D^(k)``).
#: Both quantities are dimensionless; neither seed gives a value.  1e-10
#: corresponds to normals about 2e-5 rad apart.
EPS = 1.0e-10

#: Bound of the coefficients of eq. (15) relative to the edge length (Nagata,
#: after eq. 33: "similar constraint can be imposed also on the magnitude of
#: the solution c"; see :func:`curve_coefficient`).  It is the only safeguard
#: of the curve coefficient: it keeps nearly parallel estimated normals from
#: bending straight edges and, in :func:`curve_coefficient_multi`, the nearly
#: null eigen-direction of a crease's ``[s]`` from folding coarse patches.
B_MAX = 1.0

#: Local vertex pairs of the edges of a facet with ``nfv`` vertices, in the
#: order c1, c2, c3 of eq. (39): (v1,v2), (v2,v3), (v1,v3).
LOCAL_EDGES = {2: np.array([[0, 1]]), 3: np.array([[0, 1], [1, 2], [0, 2]])}


def curve_coefficient(
    d: npt.ArrayLike, n0: npt.ArrayLike, n1: npt.ArrayLike, eps: float = EPS
) -> np.ndarray:
    """Curvature coefficient ``c(d, n0, n1)`` of the Nagata curve, eq. (15).

    With ``v = (n0 + n1)/2``, ``dv = (n0 - n1)/2`` (eq. 12), ``d = d.v``,
    ``Dd = d.dv`` (eq. 13) and ``Dc = n0.dv`` (eq. 14b)::

        c = Dd / (1 - Dc) v + d / Dc dv

    Singular cases (sec. 2.1.1): the first term is dropped when
    ``1 - Dc < eps`` and the second when ``Dc < eps``; parallel normals thus
    give ``c = 0`` (a straight edge stays exactly straight).

    Nearly parallel (or opposite) normals: by eq. (18) an error ``delta_2``
    in the second coefficient ``b = d / Dc`` changes the orthogonality
    conditions only by ``Dc delta_2``, so as the normals approach each other
    ``b`` becomes ill-determined: a normal error ``e`` changes ``d`` by
    ``|d| e`` and ``b`` by ``|d| e / Dc``, without bound (on a cylinder
    generator, estimated normals 1e-4 apart bend a straight edge by a tenth
    of its length).  Following the suggestion of sec. 2.1.2 to bound the
    solution, ``b`` is clipped to ``|b| <= B_MAX |d| / (1 - Dc)`` and, for
    nearly opposite normals, ``a`` to ``|a| <= B_MAX |d| / Dc`` (in terms of
    :func:`curve_coefficient_multi`: the component along each eigenvector
    of ``[s]`` is bounded by ``B_MAX |d| sqrt(mu) / (1 - mu)``, ``mu`` the
    eigenvalue per normal, ``Dc`` and ``1 - Dc`` here).  On a smooth curve
    ``b ~ -|d| (dR/ds) / 3`` (``R`` the radius of curvature), so the clip
    only acts where the radius changes by more than ``3 B_MAX`` per unit
    length (inflections, nearly straight edges); exact normals on circles,
    spheres and cylinders have ``b = 0``.

    Args:
        d: ``(..., 3)`` edge vectors ``x1 - x0`` (length units).
        n0, n1: ``(..., 3)`` unit normals at the two ends.
        eps: dimensionless singularity threshold.

    Returns:
        ``(..., 3)`` coefficients ``c`` (length units).  The result is the
        same for the reversed edge ``c(-d, n1, n0)``.
    """
    d = np.asarray(d, dtype=float)
    n0 = np.asarray(n0, dtype=float)
    n1 = np.asarray(n1, dtype=float)
    v = 0.5 * (n0 + n1)
    dv = 0.5 * (n0 - n1)
    dd = dot_last(d, v)
    ddelta = dot_last(d, dv)
    dc = dot_last(n0, dv)
    lim = B_MAX * np.linalg.norm(d, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        lim_a = np.where(dc > 0.0, lim / dc, np.inf)
        lim_b = np.where(1.0 - dc > 0.0, lim / (1.0 - dc), np.inf)
        a = np.where(1.0 - dc < eps, 0.0, np.clip(ddelta / (1.0 - dc), -lim_a, lim_a))
        b = np.where(dc < eps, 0.0, np.clip(dd / dc, -lim_b, lim_b))
    return a[..., None] * v + b[..., None] * dv


def curve_coefficient_multi(
    d: npt.ArrayLike, n0: npt.ArrayLike, n1: npt.ArrayLike, eps: float = EPS
) -> np.ndarray:
    """Curvature coefficient for several normals per end, eqs. (20), (32), (33).

    The orthogonality conditions ``n0k.(d - c) = 0`` and ``n1k.(d + c) = 0``
    for all normals ``n0k`` at the first end and ``n1k`` at the second end
    (eq. 32) are solved in the minimum-norm least-squares sense,
    ``c = [n]^+ {d} = [s]^+ [n]^T {d}`` (eq. 20) with ``[s] = [n]^T [n]``
    (eq. 33).  The generalized inverse of the symmetric ``[s]`` is taken from
    its eigen-decomposition ``[s] = sum_i lambda_i e_i e_i^T`` (the same
    inverse as Nagata's closed form, eqs. 26-31): components with
    ``lambda_i < m eps`` (``m`` the number of normals) count as zero (the
    rank test of sec. 2.1.2), and each component ``(e_i.[n]^T{d}) / lambda_i``
    is clipped to ``B_MAX |d| sqrt(mu_i) / (1 - mu_i)``, ``mu_i = lambda_i / m``,
    the bound of :func:`curve_coefficient`, which this function reproduces
    for one normal per end.  Near-duplicate normals (a straight crease whose
    estimated normals along one side differ by rounding) thus cannot bend
    the edge: the four normals of such a crease span space only by a sliver
    (``mu_min`` of the order of the normal error squared), and the component
    along it, ``rhs / lambda_min`` unbounded (many edge lengths: a folded
    patch), is at most ``B_MAX |d| sqrt(mu_min)``, of the order of the normal
    error, as a truncated (rank-2) inverse would give, without a rank
    threshold.  Exact normals of two planes meeting at a straight crease make
    ``[s]`` rank 2 (``lambda_min`` below ``m eps``, dropped: Nagata's case).

    Zero rows are allowed as padding (they add nothing to ``[s]`` nor to
    ``[n]^T{d}``), so edges with different numbers of normals share one array.

    Args:
        d: ``(E, 3)`` edge vectors.
        n0: ``(E, p, 3)`` normals at the first end (unit, or zero padding).
        n1: ``(E, q, 3)`` normals at the second end.
        eps: dimensionless rank threshold.

    Returns:
        ``(E, 3)`` coefficients.
    """
    d = np.asarray(d, dtype=float)
    n0 = np.asarray(n0, dtype=float)
    n1 = np.asarray(n1, dtype=float)
    # [n]^T {d}: rows n0k with right-hand side n0k.d, rows n1k with -n1k.d (eq. 32)
    rhs = np.einsum("epi,ep->ei", n0, dot_last(n0, d[:, None, :])) - np.einsum(
        "eqi,eq->ei", n1, dot_last(n1, d[:, None, :])
    )
    s = np.einsum("epi,epj->eij", n0, n0) + np.einsum("eqi,eqj->eij", n1, n1)  # eq. (33)
    m = np.maximum(np.count_nonzero(np.any(n0 != 0, axis=2), axis=1)
                   + np.count_nonzero(np.any(n1 != 0, axis=2), axis=1), 1)[:, None]
    lam, vec = np.linalg.eigh(s)
    mu = np.clip(lam / m, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lim = np.where(mu < 1.0, B_MAX * np.linalg.norm(d, axis=1)[:, None] * np.sqrt(mu) / (1.0 - mu),
                       np.inf)
        comp = np.where(lam < m * eps, 0.0,
                        np.clip(np.einsum("eij,ei->ej", vec, rhs) / lam, -lim, lim))
    return np.einsum("eij,ej->ei", vec, comp)


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


def patch_tangents(m: dict[str, np.ndarray], eta: np.ndarray, zeta: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Tangents ``x_eta``, ``x_zeta`` of triangular patches from their monomial form (eq. 37).

    ``x_eta = c10 + c11 zeta + 2 c20 eta``, ``x_zeta = c01 + c11 eta + 2 c02 zeta``.

    Args:
        m: :func:`patch_coefficients` of ``P`` patches (``(P, 3)`` arrays).
        eta, zeta: ``(P, k)`` parameters (eq. 34: ``eta = 1 - l1``, ``zeta = l3``).

    Returns:
        ``x_eta``, ``x_zeta``, each ``(P, k, 3)``; their cross product is
        oriented like ``(x2 - x1) x (x3 - x1)``.
    """
    e, z = eta[..., None], zeta[..., None]
    c10, c01, c11, c20, c02 = (m[k][:, None] for k in ("c10", "c01", "c11", "c20", "c02"))
    return c10 + c11 * z + 2.0 * c20 * e, c01 + c11 * e + 2.0 * c02 * z


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
        gn = dot_last(xt, xt)
        step = _newton_step_1d(dot_last(xt, r), gn + 2.0 * dot_last(r, c), gn)
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
        xe, xz = (t[:, 0] for t in patch_tangents(m, e, z))
        a, b, d = dot_last(xe, xe), dot_last(xe, xz), dot_last(xz, xz)  # J^T J
        ha = a + 2.0 * dot_last(r, m["c20"])
        hb = b + dot_last(r, m["c11"])
        hd = d + 2.0 * dot_last(r, m["c02"])
        pd = (ha > 0) & (ha * hd - hb * hb > 1e-2 * (a * d - b * b))
        ha, hb, hd = np.where(pd, ha, a), np.where(pd, hb, b), np.where(pd, hd, d)
        ge, gz = dot_last(xe, r), dot_last(xz, r)
        det = ha * hd - hb * hb
        with np.errstate(divide="ignore", invalid="ignore"):
            de = np.where(det > 0, -(hd * ge - hb * gz) / det, 0.0)
            dz = np.where(det > 0, -(ha * gz - hb * ge) / det, 0.0)
        scale = np.minimum(1.0, 0.5 / np.maximum(np.hypot(de, dz), 1e-300))
        eta = eta + scale * de
        zeta = zeta + scale * dz
    return np.stack([1.0 - eta, eta - zeta, zeta], axis=1)
