"""Weighted least-squares height fits of a surface (curve) around each vertex, vectorised.

The pieces of :class:`~nagata_snap.fitted.geometry.FittedGeometry`, after
Jiao & Wang (2012, "Reconstructing high-order surfaces for meshing",
weighted averaging of local fittings):

* **Surface fits** (:func:`fit_surfaces`).  In the frame ``(t1, t2, n)`` of
  a vertex (``n`` its estimated normal, :mod:`nagata_snap.nagata.jets`) the
  surface near the vertex is ``w + sum_j c_j phi_j(u, v, w) = 0`` with the
  jets' terms: the quadric terms, the monomials of degree 3 .. ``p`` in
  ``(u, v)`` and ``u, v`` (no constant: the fit passes through the vertex;
  the linear terms correct the normal).  It contains every height
  polynomial of degree ``p`` and every quadric, so it is exact on planes,
  spheres, cylinders, cones and ellipsoids (the faces of most machined
  parts) however coarse the mesh; quadratic in ``w``, it is evaluated as a
  height (:func:`surface_height`).  Weighted least squares with weights
  ``(1 + d^2 / h^2)^-2`` (``d`` the distance from the vertex, ``h`` its
  mean edge length), coordinates scaled by ``h``, solved by the
  column-scaled batched QR of :func:`nagata_snap.nagata.jets._weighted_lstsq`
  (one solver for both: no penalty while the design is determined, all but
  the linear terms penalised where it is not).  A 2D polygon is the same
  with ``v = 0`` (circles exact).
* **Curve fits** (:func:`fit_curves`).  A crease (or tag boundary) is a
  space curve; in the frame of a chord ``T`` through the vertex its two
  offsets ``(y1, y2)`` are fitted as polynomials of degree ``p`` in the
  abscissa ``s`` through the vertices along the crease.
* **Levels** (:func:`fit_levels`).  A stencil with too few points for the
  degree (a one-sided stencil at a crease, a small face) is widened by one
  ring, then the degree is lowered (surfaces down to 2, the quadric; curves
  down to 1); the degree each fit got is returned.

Everything runs over stacked small matrices (``(S, m, q)``), batched by
:data:`BATCH`; nothing loops in Python over vertices.
"""

from __future__ import annotations

from collections.abc import Callable

import numba
import numpy as np

from nagata_snap.nagata.jets import _basis, _weighted_lstsq

__all__ = ["exponents", "monomials", "terms", "model_terms", "plane_value", "term_columns",
           "fit_surfaces", "slope_rows", "surface_height", "fit_levels", "fit_curves", "height", "BATCH",
           "MIN_CREASE_SINE"]

#: Stencils per batch (bounds memory: ``batch * points * terms`` doubles).
BATCH = 4096

#: A fit of ``q`` unknowns needs at least ``q + EXTRA_POINTS`` stencil points
#: (besides the vertex itself), else a wider stencil or a lower degree is used.
EXTRA_POINTS = 2

#: Weights ``(1 + d^2 / h^2)^-WEIGHT_POWER`` of the stencil points, ``d`` their
#: distance from the vertex, ``h`` its mean edge length: the second ring counts
#: about 1/25 of the first (power 1: 1/5 was 1.4x less accurate on gmsh torus meshes).
WEIGHT_POWER = 2


def exponents(degree: int, planar: bool) -> np.ndarray:
    """Exponents ``(q, 2)`` of the monomials ``u^i v^j``, ``1 <= i + j <= degree``.

    Ordered by degree from 2 up, the linear terms last (``u, v``; planar: ``u``),
    as :func:`~nagata_snap.nagata.jets._weighted_lstsq` expects them.
    """
    if planar:
        e = [(k, 0) for k in range(2, degree + 1)] + [(1, 0)]
    else:
        e = [(k - j, j) for k in range(2, degree + 1) for j in range(k + 1)] + [(1, 0), (0, 1)]
    return np.array(e, dtype=np.int64).reshape(-1, 2)


def monomials(u: np.ndarray, v: np.ndarray, exps: np.ndarray) -> np.ndarray:
    """``u^i v^j`` for every row of ``exps (q, 2)``: shape ``u.shape + (q,)``."""
    top = int(exps.max()) if len(exps) else 0
    pu = u[..., None] ** np.arange(top + 1)
    pv = v[..., None] ** np.arange(top + 1)
    return pu[..., exps[:, 0]] * pv[..., exps[:, 1]]


def height(coef: np.ndarray, exps: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Value of fits ``coef (S, q)`` at scaled coordinates ``u, v (S, k)``: ``(S, k)``."""
    return np.einsum("skq,sq->sk", monomials(u, v, exps), coef)


def _weights(d2: np.ndarray, h: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(1 + d^2 / h^2)^-WEIGHT_POWER`` on the valid points of the stencils, 0 elsewhere."""
    return np.where(mask, 1.0 / (1.0 + d2 / (h[:, None] ** 2)) ** WEIGHT_POWER, 0.0)


def terms(degree: int, planar: bool) -> int:
    """Number of terms of the surface model of :func:`fit_surfaces`."""
    return degree + 2 if planar else (degree + 1) * (degree + 2) // 2 + 2


def model_terms(u: np.ndarray, v: np.ndarray, w: np.ndarray, degree: int, planar: bool) -> np.ndarray:
    """Terms ``(..., q)`` of the local surface model (:func:`fit_surfaces`), linear ones last.

    3D: the jets' (:func:`~nagata_snap.nagata.jets._basis`): ``u^2, uv, v^2,
    uw, vw, w^2``, the monomials of degree 3 .. ``degree`` in ``(u, v)``,
    ``u, v``.  2D: the conic ``u^2, uw, w^2``, ``u^3 .. u^degree``, ``u``
    (the jets' 2D model, circles only, has no parabola).
    """
    if not planar:
        return _basis(u, v, w, degree, planar)[0]
    return np.stack([u * u, u * w, w * w, *(u**k for k in range(3, degree + 1)), u], axis=-1)


def term_columns(degree: int, top: int, planar: bool) -> np.ndarray:
    """Columns of the degree-``degree`` model's terms among the degree-``top`` model's."""
    q, qt, lin = terms(degree, planar), terms(top, planar), 1 if planar else 2
    return np.r_[np.arange(q - lin), qt - lin + np.arange(lin)]


def plane_value(coef: np.ndarray, degree: int, planar: bool, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``sum_j c_j phi_j(u, v, 0)`` (the terms without ``w``) of fits ``coef (S, q)`` at ``u, v (S, k)``.

    The same as ``model_terms(u, v, 0) @ coef`` without forming the ``(S, k, q)``
    terms: a compiled loop over the points (:func:`_model_at`).
    """
    return _run_kernel(coef, degree, planar, u, v, False)


def _run_kernel(coef: np.ndarray, degree: int, planar: bool, u: np.ndarray, v: np.ndarray, root: bool) -> np.ndarray:
    """:func:`_model_kernel` on ``coef (S, q)`` and ``u, v (S, k)`` (``v`` broadcast): ``(S, k)``."""
    u2 = np.ascontiguousarray(u, dtype=float)
    v2 = np.ascontiguousarray(np.broadcast_to(v, u2.shape), dtype=float)
    S = u2.shape[0]
    out = np.empty(u2.shape)
    if u2.size == 0:  # nothing to evaluate (a process without points of this kind)
        return out
    _model_kernel(np.ascontiguousarray(coef, dtype=float).reshape(S, -1), int(degree), bool(planar),
                  u2.reshape(S, -1), v2.reshape(S, -1), out.reshape(S, -1), bool(root))
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _model_at(c: np.ndarray, degree: int, planar: bool, x: float, y: float, pu: np.ndarray, pv: np.ndarray,
              root: bool) -> float:  # pragma: no cover (compiled)
    """At one point ``(x, y)`` of fit ``c (q,)``: ``C``, the terms of :func:`model_terms` without ``w``
    (3D: ``u^2, uv, v^2``, the monomials of degree 3 .. ``degree`` as ordered there, ``u, v``; 2D:
    ``u^2, u^3 .. u^degree, u``), or with ``root`` the height ``w`` of :func:`surface_height`.
    ``pu, pv``: scratch of ``degree + 1``."""
    q = c.shape[0]
    pu[0] = pv[0] = 1.0
    for i in range(1, degree + 1):
        pu[i] = pu[i - 1] * x
        pv[i] = pv[i - 1] * y
    if planar:
        acc = c[0] * pu[2] + c[q - 1] * x
        for j in range(3, degree + 1):
            acc += c[j] * pu[j]
    else:
        acc = c[0] * pu[2] + c[1] * x * y + c[2] * pv[2] + c[q - 2] * x + c[q - 1] * y
        col = 6
        for d in range(3, degree + 1):  # u^d, u^(d-1) v, ..., v^d
            for i in range(d + 1):
                acc += c[col] * (pu[d - i] * pv[i])
                col += 1
    if not root:
        return acc
    if planar:
        A, B = c[2], 1.0 + c[1] * x
    else:
        A, B = c[5], 1.0 + c[3] * x + c[4] * y
    disc = B * B - 4.0 * A * acc
    den = B + (np.sqrt(max(disc, 0.0)) if B >= 0.0 else -np.sqrt(max(disc, 0.0)))
    w = -2.0 * acc / den if den != 0.0 else np.nan
    if disc >= 0.0 and np.isfinite(w):
        return w
    lin = -acc / B if B != 0.0 else np.nan
    return lin if np.isfinite(lin) else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _model_kernel(coef: np.ndarray, degree: int, planar: bool, u: np.ndarray, v: np.ndarray,
                  out: np.ndarray, root: bool) -> None:  # pragma: no cover (compiled)
    """``out[s, k] = _model_at(coef[s], ..., u[s, k], v[s, k])``."""
    S, K = u.shape
    pu = np.empty(degree + 1)
    pv = np.empty(degree + 1)
    for s in range(S):
        for k in range(K):
            out[s, k] = _model_at(coef[s], degree, planar, u[s, k], v[s, k], pu, pv, root)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def blend_kernel(X: np.ndarray, lam: np.ndarray, x0: np.ndarray, frame: np.ndarray, h: np.ndarray,
                 coef: np.ndarray, use: np.ndarray, degree: np.ndarray, planar: bool,
                 out: np.ndarray) -> None:  # pragma: no cover (compiled)
    """``out[p, k] += sum_i lam[p, k, i] w_i n_i`` over the corners ``i`` with ``use[p, i]``.

    ``X (P, k, 3)`` straight points; per facet corner ``x0 (P, nfv, 3)`` the
    vertex, ``frame (P, nfv, 3, 3)`` rows ``t1, t2, n``, ``h (P, nfv)`` the
    length scale, ``coef (P, nfv, q)`` the fit (terms of the largest degree, zero above the
    corner's own ``degree (P, nfv)``, 2 or more: its evaluation stops there); ``w_i`` the fit's height
    (:func:`surface_height`) above the point's projection into the frame, minus
    the point's own height ``w``: the fitted point is ``X + (w_i - w) n_i``.
    """
    P, K, _ = X.shape
    nfv = lam.shape[2]
    top = max(int(degree.max()), 2) if degree.size else 2
    pu = np.empty(top + 1)
    pv = np.empty(top + 1)
    for p in range(P):
        for i in range(nfv):
            if not use[p, i]:
                continue
            fr, c, hh = frame[p, i], coef[p, i], h[p, i]
            for k in range(K):
                d0, d1, d2 = X[p, k, 0] - x0[p, i, 0], X[p, k, 1] - x0[p, i, 1], X[p, k, 2] - x0[p, i, 2]
                u = (d0 * fr[0, 0] + d1 * fr[0, 1] + d2 * fr[0, 2]) / hh
                v = (d0 * fr[1, 0] + d1 * fr[1, 1] + d2 * fr[1, 2]) / hh
                w = (d0 * fr[2, 0] + d1 * fr[2, 1] + d2 * fr[2, 2]) / hh
                dw = (_model_at(c, degree[p, i], planar, u, v, pu, pv, True) - w) * hh * lam[p, k, i]
                for j in range(3):
                    out[p, k, j] += dw * fr[2, j]


def fit_surfaces(
    x0: np.ndarray, frame: np.ndarray, pts: np.ndarray, mask: np.ndarray, h: np.ndarray, degree: int,
    planar: bool, explicit: bool = False, normals: np.ndarray | None = None, slope_weight: float = 1.0,
) -> np.ndarray:
    """Implicit local surfaces ``w + sum_j c_j phi_j(u, v, w) = 0`` of degree ``degree`` in each vertex's frame.

    ``phi`` are :func:`model_terms`: the quadric (2D: conic) terms, the
    monomials of degree 3 .. ``degree`` in ``(u, v)``, the linear terms.  No
    constant term: the surface passes through the vertex.  It contains every
    height polynomial of degree ``degree`` and every quadric (exact on planes,
    spheres, cylinders, cones, ellipsoids; 2D: conics).

    Args:
        x0: ``(S, 3)`` vertices; frame: ``(S, 3, 3)`` rows ``t1, t2, n`` (planar: ``t2 = 0``).
        pts: ``(S, m, 3)`` stencil points, ``mask (S, m)`` the valid ones (not ``x0``).
        h: ``(S,)`` length scale (the coordinates are divided by it).
        degree: ``>= 2``.
        planar: 2D (a curve in the plane of ``t1, n``).
        explicit: a height polynomial only (the terms in ``w`` left out, their
            coefficients 0; the others lightly penalised): the fallback where
            the implicit fit is not a height function over the stencil
            (:func:`height_valid`).
        normals: optional ``(S, m + 1, 3)`` (3D): unit normals of the surface at
            ``x0`` (row 0) and at the stencil points, NaN where unknown; each
            known one adds two slope equations ``grad F x n = 0`` (Hermite data,
            weighted ``slope_weight`` times the point's position; :func:`slope_rows`).

    Returns:
        ``(S, q)`` coefficients (:func:`terms`), in coordinates scaled by ``h``;
        NaN rows where the linear terms are not determined (implicit fits that
        are no height function over their stencil included); zero rows for
        stencils in the vertex's tangent plane (:data:`FLAT`).
    """
    d = pts - x0[:, None, :]
    loc = np.matmul(d, frame.transpose(0, 2, 1)) / h[:, None, None]
    wt = _weights(np.einsum("smi,smi->sm", d, d), h, mask)
    c = np.zeros((len(x0), terms(degree, planar)))
    # a planar stencil is its tangent plane: no solve
    fit = np.flatnonzero((np.abs(loc[..., 2]) > FLAT).any(axis=1, where=mask))
    u, v, w = loc[fit, :, 0], loc[fit, :, 1], loc[fit, :, 2]
    P = model_terms(u, v, 0.0 * u if explicit else w, degree, planar)
    z, W = -w, wt[fit]
    if normals is not None and not planar and not explicit:
        P, z, W = slope_rows(P, z, W, loc[fit], wt[fit], normals[fit], frame[fit], degree, slope_weight)
    # no ridge penalty while the design is determined (exact on its own model); the
    # solver's fallback penalises all but the linear terms where it is not (always
    # when explicit: the terms in w are zero columns)
    cf = _weighted_lstsq(P, z, W, np.zeros(P.shape[-1], dtype=bool), 1 if planar else 2)
    if explicit:
        cf[:, [1, 2] if planar else [3, 4, 5]] = 0.0
    else:
        cf[~height_valid(cf, degree, planar, u, v, mask[fit])] = np.nan
    c[fit] = cf
    return c


def slope_rows(P: np.ndarray, z: np.ndarray, W: np.ndarray, loc: np.ndarray, wt: np.ndarray, normals: np.ndarray,
               frame: np.ndarray, degree: int, weight: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The design ``P (S, m, q)``, right side ``z`` and weights ``W (S, m)`` of a 3D fit with slope rows appended.

    At the vertex (``normals[:, 0]``) and each stencil point ``loc (S, m, 3)``
    (scaled local coordinates, weights ``wt``) with a known normal ``n`` (local
    ``(a, b, c)``): ``F_u c - F_w a = 0`` and ``F_v c - F_w b = 0``, ``F`` the
    model of :func:`fit_surfaces` (``F_w = 1 + ...``), i.e. rows
    ``phi_u c - phi_w a`` (right side ``a``) and ``phi_v c - phi_w b`` (``b``).
    Weighted ``weight`` times the point's position weight (the vertex's: the largest).
    """
    S = len(P)
    known = np.isfinite(normals).all(axis=2)
    k = max(int(known.sum(axis=1).max(initial=0)), 1)
    keep = np.argsort(~known, axis=1, kind="stable")[:, :k]  # the points with a normal, first
    known = np.take_along_axis(known, keep, axis=1)
    pts = np.take_along_axis(np.concatenate([np.zeros((S, 1, 3)), loc], axis=1), keep[..., None], axis=1)
    wk = np.take_along_axis(np.concatenate([wt.max(axis=1, keepdims=True), wt], axis=1), keep, axis=1)
    nk = np.take_along_axis(np.nan_to_num(normals), keep[..., None], axis=1)
    n = np.matmul(nk, frame.transpose(0, 2, 1))  # local components
    ws = weight * np.where(known, wk, 0.0)
    du, dv, dw = _term_derivatives(pts[..., 0], pts[..., 1], pts[..., 2], degree)
    a, b, c = n[..., 0:1], n[..., 1:2], n[..., 2:3]
    rows = np.concatenate([du * c - dw * a, dv * c - dw * b], axis=1)
    return (np.concatenate([P, rows], axis=1), np.concatenate([z, n[..., 0], n[..., 1]], axis=1),
            np.concatenate([W, ws, ws], axis=1))


def _term_derivatives(u: np.ndarray, v: np.ndarray, w: np.ndarray, degree: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``d/du, d/dv, d/dw`` ``(..., q)`` of the 3D :func:`model_terms` (their order)."""
    zero, one = 0.0 * u, 1.0 + 0.0 * u
    du = [2.0 * u, v, zero, w, zero, zero]
    dv = [zero, u, 2.0 * v, zero, w, zero]
    dw = [zero, zero, zero, u, v, 2.0 * w]
    for d in range(3, degree + 1):
        for i in range(d + 1):  # u^(d-i) v^i
            du.append((d - i) * u ** max(d - i - 1, 0) * v**i if d - i > 0 else zero)
            dv.append(i * u ** (d - i) * v ** max(i - 1, 0) if i > 0 else zero)
            dw.append(zero)
    du += [one, zero]
    dv += [zero, one]
    dw += [zero, zero]
    return np.stack(du, axis=-1), np.stack(dv, axis=-1), np.stack(dw, axis=-1)


#: A stencil whose points all lie within ``FLAT`` (in units of the vertex's
#: length scale) of the vertex's tangent plane is fitted by that plane (zero
#: coefficients) without a solve: the planar faces of a machined part, most of
#: its sectors (their fits would be the plane up to rounding).
FLAT = 1e-12


#: An implicit fit is a height function where it is used (its stencil points
#: within ``CHECK_RADIUS`` mean edge lengths of the vertex) when ``B = dF/dw``
#: stays above ``MIN_SLOPE`` there (1 at the vertex) and the quadratic in ``w``
#: has a root.
MIN_SLOPE = 0.5
CHECK_RADIUS = 1.5


def height_valid(coef: np.ndarray, degree: int, planar: bool, u: np.ndarray, v: np.ndarray,
                 mask: np.ndarray) -> np.ndarray:
    """``(S,)`` whether the fits ``coef (S, q)`` are height functions near the vertex, at the points ``u, v (S, m)``.

    ``B = 1 + c_uw u + c_vw v >= MIN_SLOPE`` and a real root of the quadratic
    in ``w`` (:func:`surface_height`) at every valid point: the implicit
    surface does not turn back over the stencil.
    """
    C = plane_value(np.nan_to_num(coef), degree, planar, u, v)
    if planar:
        A, B = coef[:, 2:3], 1.0 + coef[:, 1:2] * u
    else:
        A, B = coef[:, 5:6], 1.0 + coef[:, 3:4] * u + coef[:, 4:5] * v
    ok = (B >= MIN_SLOPE) & (B * B - 4.0 * A * C >= 0.0)
    near = mask & (u * u + v * v <= CHECK_RADIUS**2)
    return np.all(ok | ~near, axis=1) & np.isfinite(coef).all(axis=1)


def surface_height(coef: np.ndarray, degree: int, planar: bool, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Height ``w (S, k)`` of the fitted surfaces ``coef (S, q)`` above scaled ``u, v (S, k)``.

    The model is quadratic in ``w``: ``A w^2 + B w + C = 0`` with ``A = c_ww``,
    ``B = 1 + c_uw u + c_vw v``, ``C`` the terms without ``w``; the root nearest 0 (the branch through the
    vertex), or ``-C / B`` where the quadratic has no real root (far outside
    the fit's stencil).
    """
    return _run_kernel(coef, degree, planar, u, v, True)


def fit_levels(
    levels: list[tuple[int, int, bool]],
    stencil: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]],
    fit: Callable[[np.ndarray, np.ndarray, np.ndarray, int, bool], np.ndarray],
    S: int, columns: Callable[[int], np.ndarray], q: int, comps: int = 1,
    equations: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fits of ``S`` stencils trying ``levels = [(degree, width, variant), ...]`` in turn.

    ``stencil(width, rows) -> (idx (S, m), mask (S, m))`` gives the points of
    the fits ``rows`` (the others' rows may be left empty) at that stencil
    width; ``fit(sel, idx, mask, degree, variant) -> (len(sel), comps, q_d)``
    fits the selected ones (NaN: failed), whose ``q_d`` terms are the columns
    ``columns(degree) (q_d,)`` of the ``q`` of the padded result.  A level takes
    the fits not yet done whose stencil has at least ``q_d + EXTRA_POINTS`` points.

    Returns:
        ``(coef (S, comps, q), degree (S,), level (S,))``: coefficients padded to
        the ``q`` terms of the first level's degree (zeros for the terms a lower
        degree lacks), the degree each fit got (0: none, coefficients 0) and
        the index of its level (-1: none).  ``equations(idx, mask) -> (n,)``: the
    equations per component a stencil gives (default: its points).
    """
    coef = np.zeros((S, comps, q))
    got = np.zeros(S, dtype=np.int64)
    level = np.full(S, -1, dtype=np.int64)
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for li, (degree, width, variant) in enumerate(levels):
        todo = got == 0
        if not todo.any():
            break
        if width not in cache:  # the fits still to do: a later level's are among them
            cache[width] = stencil(width, np.flatnonzero(todo))
        idx, mask = cache[width]
        cols = columns(degree)
        count = mask.sum(axis=1)
        enough = (count if equations is None else equations(idx, mask)) >= len(cols) + EXTRA_POINTS
        todo = np.flatnonzero(todo & enough)
        # stencils of like size together: each batch is padded to its largest (one stencil of 110
        # points among stencils of 28 on a part whose small holes sit in large faces)
        size_class = np.floor(np.log(np.maximum(count[todo], 1)) / np.log(SIZE_CLASS)).astype(np.int64)
        for k in np.unique(size_class):
            group = todo[size_class == k]
            for lo in range(0, len(group), BATCH):
                sel = group[lo:lo + BATCH]
                m = int(count[sel].max())
                order = np.argsort(~mask[sel], axis=1, kind="stable")[:, :m]  # valid points first
                c = fit(sel, np.take_along_axis(idx[sel], order, axis=1),
                        np.take_along_axis(mask[sel], order, axis=1), degree, variant)
                ok = np.isfinite(c).all(axis=(1, 2))
                coef[sel[ok][:, None, None], np.arange(comps)[None, :, None], cols[None, None, :]] = c[ok]
                got[sel[ok]] = degree
                level[sel[ok]] = li
    return coef, got, level


#: Stencils are fitted in groups whose point counts lie within this ratio (padding bounded).
SIZE_CLASS = 1.25


#: Slope equations of a crease curve fit are used where the two faces' normals
#: are at least this far apart (sine of the angle): at a tangency (G1) line
#: their cross product, the curve's tangent, is not determined.
MIN_CREASE_SINE = 0.2


def fit_curves(
    x0: np.ndarray, tangent: np.ndarray, normals: tuple[np.ndarray, np.ndarray], pts: np.ndarray,
    mask: np.ndarray, h: np.ndarray, degree: int, sides: np.ndarray | None = None, circle: bool = False,
) -> np.ndarray:
    """Curve fits: each offset ``y_k`` (along ``normals[k]``) as a planar implicit fit in the abscissa.

    In the plane of ``tangent`` and ``normals[k]`` the projected curve is fitted
    as :func:`fit_surfaces` fits a planar curve, ``y + sum_j c_j phi_j(s, y) = 0``
    with the conic and the powers ``s^3 .. s^degree`` (:func:`model_terms`): a
    planar circle (a fillet's rim, a hole's edge) projects to a conic in each
    such plane, so the fit is exact on it however few segments it has, where a
    polynomial graph over the chord of a quarter arc of 3 segments is 3x less
    accurate than Nagata's curve.

    Args:
        x0: ``(S, 3)`` curve points the fits pass through; tangent: ``(S, 3)``
            unit chords; normals: two ``(S, 3)`` unit vectors completing the frame.
        pts, mask: ``(S, m, 3)``, ``(S, m)`` the other points of each curve.
        h: ``(S,)`` length scale.
        degree: ``>= 2``.
        sides: optional ``(S, m + 1, 2, 3)``: the two faces' unit normals at
            ``x0`` (row 0) and at each point of ``pts``; where they are at least
            :data:`MIN_CREASE_SINE` apart their cross product is the curve's
            tangent there, an equation ``dF/ds (t . T) + dF/dy (t . n_k) = 0``
            each (Hermite data: a chain of 3 segments between corners fits degree 4).
        circle: a circle through ``x0`` in the plane of ``tangent`` and
            ``normals[0]`` (``y + k (s^2 + y^2) + g s = 0``) and a parabola along
            ``normals[1]`` (0 for a planar curve), no slope equations: a tangency
            line's quarter arc of 3 segments, whose faces' normals give no tangent
            (``normals[0]`` should then lie in the curve's plane).

    Returns:
        ``(S, 2, q)`` coefficients (:func:`terms` planar) per offset, scaled by
        ``h``; NaN where undetermined, with fewer than ``q + EXTRA_POINTS``
        equations (a tangency line has no slope equations) or no height
        function near ``x0``.
    """
    d = pts - x0[:, None, :]
    u = np.einsum("smi,si->sm", d, tangent) / h[:, None]
    wt = _weights(np.einsum("smi,smi->sm", d, d), h, mask)
    q = terms(degree, True)
    out = np.full((len(x0), 2, q), np.nan)
    t = None
    count = mask.sum(axis=1)
    if circle:  # y + k (s^2 + y^2) + g s = 0 along normals[0], y + a s^2 + g s = 0 along normals[1]
        for k, (nrm, cols) in enumerate(zip(normals, ([0, 2], [0]), strict=True)):
            w = np.einsum("smi,si->sm", d, nrm) / h[:, None]
            terms_ = model_terms(u, 0.0 * u, w, 2, True)
            P = np.stack([terms_[..., cols].sum(axis=-1), u], axis=-1)
            kg = _weighted_lstsq(P, -w, wt, np.zeros(2, dtype=bool), 1)
            c = np.zeros((len(x0), q))
            c[:, cols] = kg[:, :1]
            c[:, -1] = kg[:, 1]
            c[~height_valid(c, degree, True, u, 0.0 * u, mask) | (count < 3)] = np.nan
            out[:, k] = c
        return out
    if sides is not None:
        t = np.cross(sides[..., 0, :], sides[..., 1, :])
        st = np.linalg.norm(t, axis=-1)
        t = t / np.where(st > 0, st, 1.0)[..., None]
        ws = np.where(np.concatenate([np.ones((len(x0), 1), dtype=bool), mask], axis=1) & (st >= MIN_CREASE_SINE),
                      np.concatenate([np.ones((len(x0), 1)), wt], axis=1), 0.0)
        us = np.concatenate([np.zeros((len(x0), 1)), u], axis=1)
        tT = np.einsum("smi,si->sm", t, tangent)
        count = count + (ws > 0).sum(axis=1)
    for k, nrm in enumerate(normals):
        w = np.einsum("smi,si->sm", d, nrm) / h[:, None]
        P, z, W = model_terms(u, 0.0 * u, w, degree, True), -w, wt
        if t is not None:  # slope rows: phi_u (t . T) + phi_w (t . n_k), right side -(t . n_k)
            tn = np.einsum("smi,si->sm", t, nrm)
            ws_ = np.concatenate([np.zeros((len(x0), 1)), w], axis=1)  # heights (0 at x0)
            pu, pw = _planar_term_derivatives(us, ws_, degree)
            P = np.concatenate([P, pu * tT[..., None] + pw * tn[..., None]], axis=1)
            z = np.concatenate([z, -tn], axis=1)
            W = np.concatenate([W, ws], axis=1)
        c = _weighted_lstsq(P, z, W, np.zeros(q, dtype=bool), 1)
        c[~height_valid(c, degree, True, u, 0.0 * u, mask) | (count < q + EXTRA_POINTS)] = np.nan
        out[:, k] = c
    return out


def _planar_term_derivatives(u: np.ndarray, w: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """``d/du`` and ``d/dw`` ``(..., q)`` of the planar :func:`model_terms` ``u^2, uw, w^2, u^3 .. u^degree, u``."""
    zero, one = 0.0 * u, 1.0 + 0.0 * u
    du = [2.0 * u, w, zero, *(k * u ** (k - 1) for k in range(3, degree + 1)), one]
    dw = [zero, u, 2.0 * w, *(zero for _ in range(3, degree + 1)), zero]
    return np.stack(du, axis=-1), np.stack(dw, axis=-1)
