"""Vertex normals from weighted least-squares fits of a local surface (osculating jets).

A weighted average of facet normals (MWSELR and the other weightings Neto
2010 compares, :mod:`nagata_snap.nagata.normals`) is only first-order accurate on
irregular meshes: its error is O(h), and a normal error O(h^p) moves the
Nagata curve coefficient by O(h^(p+1)).  Nagata patches with exact normals
converge at order 3-4, so the normals must be better than second order.

This module fits, for every smooth sector of every vertex at once, a local
surface through the vertices around it and takes the fit's normal:

* **Stencil.** The vertices of the facets within ``k`` rings of the sector's
  facets (3D: ``k = 3`` for the quartic fit), grown only through facets of
  the sector's smooth region (facets joined across non-crease ridges), so a
  face next to a sharp edge is fitted from its own side only.
* **Frame.** Tangent frame of an initial normal (MWSELR), refitted once in
  the frame of the first fit's normal.  Coordinates ``(u, v)`` in the
  tangent plane and ``w`` along the normal, scaled by the stencil's RMS
  radius.
* **Model.** An implicit surface ``f(u, v, w) = w + sum_j c_j phi_j = 0``
  with ``phi``: the quadratic form in ``(u, v, w)`` (``u^2, uv, v^2, uw,
  vw, w^2``), the monomials of degree 3 and 4 in ``(u, v)``, and ``u, v``.
  Without the terms in ``w`` it is a height function (a jet, exact for
  quartic height functions); with them it also contains every quadric, so
  it is exact for vertices on a plane, sphere, cylinder, cone or ellipsoid
  however coarse the mesh (MWSELR: only spheres), which matters on machined
  parts, whose curved faces are mostly quadrics, meshed a few facets wide.
  2D: ``f = w + a (u^2 + w^2) + b u^3 + c u^4 + d u`` through the two
  neighbours on each side, exact on circles (the DFG cylinder keeps its
  exact normals); a conic, exact on ellipses too, cannot follow an
  inflection.  The normal is the gradient at the vertex, ``(c_u, c_v, 1)``
  in the frame.
* **Weights.** ``rho^-4 exp(-(psi/sigma)^2)``: ``rho`` the tangential
  distance, ``psi = 2 atan(|w|/rho)`` the normal turn a sphere through the
  point would have (exact for a sphere).  Distant points and, on coarse
  meshes, points the surface has turned away from count little, so the fit
  stays local where the mesh is coarse and uses its whole stencil where it
  is fine.  The weight is a smooth function of position, so it does not
  lower the order.
* **Solve.** The weighted designs of all sectors, ``(n, m, q)``, column
  scaled, with a small ridge penalty on the monomials of degree 3 and 4,
  reduced by a batched QR and solved: directions a one-sided stencil cannot
  determine (a quartic term across a crease) go to zero rather than being
  amplified, and the quadric terms stay unbiased (exact on quadrics).

Errors (derivatives of order ``p + 1`` times ``rho^p``) give normals of
order 4 for the quartic fit.  :func:`fit_sector_normals` falls back to lower
degrees and finally to the initial normal when a stencil has too few points
or the fit leaves the cone of its own facets' normals (see there).
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse

__all__ = ["padded_rows", "SectorRings", "sector_stencils", "fit_normals", "fit_sector_normals", "JET_LEVELS"]

#: Fit levels tried in order, per space dimension: ``(degree, rings,
#: minimum stencil points, sigma in degrees, coarse only)``, ``degree`` the
#: highest monomial degree.  3D: on coarse interior sectors (own facets
#: spreading by ``COARSE_DEG`` or more) a cubic on two rings first, then
#: everywhere a quartic on three rings, a cubic on two, a quadric on two,
#: and on three (a sector of one facet at a ragged open boundary);
#: 2D: two rings (exactly determined), four rings for one-sided stencils,
#: then lower degrees.
JET_LEVELS = {
    3: ((3, 2, 14, 30.0, True), (4, 3, 19, 15.0, False), (3, 2, 14, 30.0, False), (2, 2, 9, None, False),
        (2, 3, 9, None, False)),
    2: ((4, 2, 4, None, False), (4, 4, 4, None, False), (3, 2, 3, None, False), (2, 2, 2, None, False)),
}

#: Sectors whose own facets' normals spread by at least this many degrees from
#: the initial normal are coarse: the surface turns so much over three rings
#: that the quartic's stencil is mostly weighted away, and the cubic on two
#: rings is more accurate there.
COARSE_DEG = 20.0

#: Ridge penalty of the terms of degree 3 and more (columns scaled to unit norm).
PENALTY = 1.0e-5

#: A fit is accepted when its normal is within ``ACCEPT * spread + ACCEPT_DEG``
#: (degrees) of the initial normal (``spread``: see :func:`fit_sector_normals`).
ACCEPT = 1.0
ACCEPT_DEG = 0.05

#: Stencils per batch (bounds memory: ``batch * points * terms`` doubles).
BATCH = 4096


def padded_rows(csr: scipy.sparse.csr_matrix, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Column indices of CSR rows as a padded array.

    Returns:
        ``(idx (n, m), mask (n, m))``: ``idx[i, :count_i]`` are the columns
        of row ``rows[i]`` (all rows if ``rows`` is None), padding is 0 with
        ``mask`` False.
    """
    csr = csr.tocsr()
    rows = np.arange(csr.shape[0]) if rows is None else np.asarray(rows)
    start = csr.indptr[rows]
    count = csr.indptr[rows + 1] - start
    m = int(count.max()) if len(rows) else 0
    mask = np.arange(m)[None, :] < count[:, None]
    pos = (start[:, None] + np.arange(m)[None, :])[mask]
    idx = np.zeros((len(rows), m), dtype=np.int64)
    idx[mask] = csr.indices[pos]
    return idx, mask


class SectorRings:
    """The facets within ``k`` rings of every sector, inside its smooth region, grown one ring at a time.

    Ring 1 is the sector's own facets; each further ring adds the facets
    sharing a vertex with the previous ones (same region).  The rings grown
    for all sectors are kept, so the jets' stencils (rings 1 to 3) and the
    fitted surface's (:mod:`nagata_snap.fitted`, 3 and 4) grow each ring once
    (the object holds their memory until it is dropped).

    Args:
        vid: ``(F, nfv)`` vertex index of each facet corner.
        label: ``(F, nfv)`` sector label of each corner (``0 .. S-1``).
        region: ``(F,)`` smooth-region label of each facet; every sector's
            facets lie in one region.
    """

    def __init__(self, vid: np.ndarray, label: np.ndarray, region: np.ndarray):
        F, nfv = vid.shape
        self.num_sectors = int(label.max()) + 1
        fac = np.repeat(np.arange(F), nfv)
        # int32: the products count paths, and in int8 a sum of 256 wraps to 0 and is dropped
        ones = np.ones(F * nfv, dtype=np.int32)
        self._vf = scipy.sparse.csr_matrix((ones, (vid.ravel(), fac)), shape=(int(vid.max()) + 1, F))
        self._region = region
        self._rings = {1: scipy.sparse.csr_matrix((ones, (label.ravel(), fac)), shape=(self.num_sectors, F))}
        self._ff: scipy.sparse.csr_matrix | None = None
        self._stencils: dict[tuple[int, bool], tuple[np.ndarray, np.ndarray]] = {}

    def _facet_neighbours(self) -> scipy.sparse.csr_matrix:
        """``(F, F)`` facets sharing a vertex, within one region."""
        if self._ff is None:
            ff = (self._vf.T @ self._vf).tocoo()
            keep = self._region[ff.row] == self._region[ff.col]
            F = self._vf.shape[1]
            self._ff = scipy.sparse.csr_matrix(
                (np.ones(int(keep.sum()), dtype=np.int32), (ff.row[keep], ff.col[keep])), shape=(F, F))
        return self._ff

    def facets(self, rings: int, rows: np.ndarray | None = None) -> scipy.sparse.csr_matrix:
        """Sparse ``(S, F)`` (or ``(len(rows), F)``) facets within ``rings`` rings of each sector (of ``rows``).

        Grown from the widest ring already grown for all sectors; only rings
        grown for all sectors (``rows`` None) are kept.
        """
        have = max(k for k in self._rings if k <= rings)
        ring = self._rings[have] if rows is None else self._rings[have][rows]
        for k in range(have + 1, rings + 1):
            ring = ring @ self._facet_neighbours()
            ring.data[:] = 1
            if rows is None:
                self._rings[k] = ring
        return ring

    def stencils(self, rings: int, facets: bool = False, rows: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (or facets) within ``rings`` rings of each sector: ``(idx (S, m), mask (S, m))``.

        Padded (the sector's own vertex included), sorted: identical on every
        process.  With ``rows``, only those sectors' rows are filled (the
        others empty), and nothing is kept.
        """
        key = (rings, facets)
        if rows is None and key in self._stencils:
            return self._stencils[key]
        ring = self.facets(rings, rows)
        if not facets:
            ring = ring @ self._vf.T
        ring.sort_indices()
        out = padded_rows(ring)
        if rows is None:
            self._stencils[key] = out
            return out
        idx = np.zeros((self.num_sectors, out[0].shape[1]), dtype=np.int64)
        mask = np.zeros(idx.shape, dtype=bool)
        idx[rows], mask[rows] = out
        return idx, mask


def sector_stencils(
    vid: np.ndarray, label: np.ndarray, region: np.ndarray, rings: int, facets: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (or facets) within ``rings`` facet rings of each sector, inside its smooth region.

    Args:
        vid: ``(F, nfv)`` vertex index of each facet corner.
        label: ``(F, nfv)`` sector label of each corner (``0 .. S-1``).
        region: ``(F,)`` smooth-region label of each facet; every sector's
            facets lie in one region.
        rings: 1 = the sector's own facets; each further ring adds the facets
            sharing a vertex with the previous ones (same region).
        facets: return the facets instead of their vertices.

    Returns:
        ``(idx (S, m), mask (S, m))`` vertex (facet) indices per sector,
        padded (the sector's own vertex included), sorted: identical on
        every process (:meth:`SectorRings.stencils`).
    """
    return SectorRings(vid, label, region).stencils(rings, facets)


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (radians) between unit vectors ``a, b (..., 3)``, accurate for small angles."""
    return 2.0 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


def _ring_spread(sector_rings: SectorRings, rings: int, facet_normal: np.ndarray, n0: np.ndarray) -> np.ndarray:
    """Largest angle (radians, ``(S,)``) between ``n0`` and the facet normals within ``rings`` rings of each sector."""
    ring, ring_mask = sector_rings.stencils(rings, facets=True)
    return np.where(ring_mask, _angle(facet_normal[ring], n0[:, None, :]), 0.0).max(axis=1)


def _frame(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents ``(t1, t2)`` completing unit normals ``n (S, 3)`` (``t2 = n x t1``)."""
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    return t1, np.cross(n, t1)


def _basis(u: np.ndarray, v: np.ndarray, w: np.ndarray, degree: int, planar: bool) -> tuple[np.ndarray, np.ndarray]:
    """Model terms ``(S, m, q)`` and which carry the ridge penalty ``(q,)``.

    3D: ``u^2, uv, v^2, uw, vw, w^2``, the monomials of degree 3 ..
    ``degree`` in ``(u, v)`` (penalised), ``u, v``.  2D: ``u^2 + w^2``,
    ``u^3 .. u^degree`` (penalised), ``u``.  The last ``gdim - 1`` columns
    are the linear terms.
    """
    if planar:
        cols = [u * u + w * w] + [u**k for k in range(3, degree + 1)] + [u]
        high = np.arange(len(cols)) > 0
        high[-1] = False
        return np.stack(cols, axis=-1), high
    cols = [u * u, u * v, v * v, u * w, v * w, w * w]
    prev = cols[:3]  # monomials of the previous degree, u^(d-i) v^i
    for _ in range(3, degree + 1):
        prev = [p * u for p in prev] + [prev[-1] * v]
        cols += prev
    high = np.arange(len(cols) + 2) >= 6
    high[-2:] = False
    return np.stack([*cols, u, v], axis=-1), high


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _reflect(v: np.ndarray, w: np.ndarray, j: int, n: int, vv: float) -> None:  # pragma: no cover (compiled)
    """``w[j:n] -= 2 (v . w) / vv v`` over ``[j, n)``: the Householder reflection by ``v``
    (``vv = |v|^2``) applied to ``w`` in place."""
    dot = 0.0
    for i in range(j, n):
        dot += v[i] * w[i]
    f = 2.0 * dot / vv
    for i in range(j, n):
        w[i] -= f * v[i]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _householder_lstsq(P: np.ndarray, z: np.ndarray, wt: np.ndarray, rows: np.ndarray, pen: np.ndarray,
                       x: np.ndarray) -> None:  # pragma: no cover (compiled)
    """Minimisers ``x[r] (q,)`` of ``sum_m wt (P c - z)^2 + sum_j pen_j^2 (c_j / scale_j)^2`` for ``r`` in ``rows``.

    ``P (S, M, q)``, ``z, wt (S, M)``; the columns of ``sqrt(wt) P`` are scaled
    to unit norm (``x`` is returned unscaled), ``pen (q,)`` the weights of the
    penalty rows (0: none) on the scaled coefficients.  Householder QR of the
    scaled design and its penalty rows, back substitution; where an ``|R_jj|``
    is at most ``1e-10`` of the largest, ``x[r]`` is NaN (the caller's rank test).
    """
    _, M, q = P.shape
    npen = 0
    for j in range(q):
        if pen[j] != 0.0:
            npen += 1
    a = np.empty((q, M + npen))  # the scaled design, transposed: columns contiguous
    y = np.empty(M + npen)
    scale = np.empty(q)
    diag = np.empty(q)
    for r in rows:
        m = 0  # rows of weight 0 (padding, points weighted out) change nothing: left out
        for i in range(M):
            if wt[r, i] > 0.0:
                sw = np.sqrt(wt[r, i])
                y[m] = sw * z[r, i]
                for j in range(q):
                    a[j, m] = sw * P[r, i, j]
                m += 1
        N = m + npen
        for j in range(q):
            nrm = 0.0
            for i in range(m):
                nrm += a[j, i] * a[j, i]
            scale[j] = 1.0 / np.sqrt(nrm) if nrm > 0.0 else 1.0
            for i in range(m):
                a[j, i] *= scale[j]
        k = m
        for j in range(q):  # penalty rows
            if pen[j] != 0.0:
                for jj in range(q):
                    a[jj, k] = 0.0
                a[j, k] = pen[j]
                y[k] = 0.0
                k += 1
        if q > N:  # fewer equations than unknowns: not determined
            x[r] = np.nan
            continue
        for j in range(q):
            aj = a[j]
            nrm = 0.0
            for i in range(j, N):
                nrm += aj[i] * aj[i]
            nrm = np.sqrt(nrm)
            if nrm == 0.0:
                diag[j] = 0.0
                continue
            alpha = -nrm if aj[j] >= 0.0 else nrm
            vv = 2.0 * nrm * (nrm + abs(aj[j]))  # |v|^2, v = a[j:, j] - alpha e_j
            aj[j] -= alpha
            for kk in range(j + 1, q):
                _reflect(aj, a[kk], j, N, vv)
            _reflect(aj, y, j, N, vv)
            aj[j] = alpha
            diag[j] = abs(alpha)
        top, low = 0.0, np.inf
        for j in range(q):
            top = max(top, diag[j])
            low = min(low, diag[j])
        if top == 0.0 or low <= 1e-10 * top:
            x[r] = np.nan
            continue
        for j in range(q - 1, -1, -1):
            acc = y[j]
            for kk in range(j + 1, q):
                acc -= a[kk, j] * x[r, kk]
            x[r, j] = acc / a[j, j]
        for j in range(q):
            x[r, j] *= scale[j]


def _weighted_lstsq(P: np.ndarray, z: np.ndarray, wt: np.ndarray, high: np.ndarray, linear: int) -> np.ndarray:
    """Minimisers ``c (S, q)`` of ``sum_m wt (P c - z)^2 + PENALTY |c_high|^2`` (columns scaled).

    Columns are scaled to unit weighted norm; the terms flagged in
    ``high (q,)`` (monomials of degree 3 and more) carry a small ridge penalty, so
    directions a stencil cannot determine (a quartic term across a crease,
    or far points weighted away on a coarse mesh) go to zero instead of
    being amplified, while the other terms are not biased: a stencil on a
    quadric (2D: circle) is still fitted exactly.  Where even the quadratic
    terms are not determined (a face one or two facets wide: all points on
    two lines), every term but the last ``linear`` ones is penalised.
    Solved by Householder QR of the scaled design and its penalty rows (no
    squared condition number; compiled, :func:`_householder_lstsq`).
    Stencils whose linear terms are not determined give NaN.
    """
    S, M, q = P.shape
    c = np.full((S, q), np.nan)
    todo = np.arange(S)
    P, z, wt = (np.ascontiguousarray(np.broadcast_to(v, shape), dtype=float)
                for v, shape in ((P, (S, M, q)), (z, (S, M)), (wt, (S, M))))
    for pen in (high, np.arange(q) < q - linear):
        if q > M and not pen.any():  # fewer points than terms and no penalty: not determined
            continue
        _householder_lstsq(P, z, wt, todo, np.sqrt(PENALTY) * pen.astype(float), c)
        todo = todo[~np.isfinite(c[todo]).all(axis=1)]
        if len(todo) == 0:
            break
    return c


def fit_normals(
    x0: np.ndarray,
    pts: np.ndarray,
    mask: np.ndarray,
    n0: np.ndarray,
    degree: int,
    sigma: float | None,
    planar: bool = False,
    iterations: int = 2,
) -> np.ndarray:
    """Normals of weighted least-squares fits through stencils, vectorised.

    Args:
        x0: ``(S, 3)`` the vertices whose normals are fitted.
        pts: ``(S, m, 3)`` stencil points (may contain ``x0`` itself: it gets
            weight 0); ``mask (S, m)`` marks the valid ones.
        n0: ``(S, 3)`` initial unit normals (frame of the first fit).
        degree: 2, 3 or 4.
        sigma: angular width of the weights in degrees (None: no angular factor).
        planar: 2D (points and normals in the plane z = 0).
        iterations: fits, each in the frame of the previous normal.

    Returns:
        ``(S, 3)`` unit normals (NaN where the fit failed).
    """
    d = pts - x0[:, None, :]
    r2 = np.einsum("smi,smi->sm", d, d) * mask
    h = np.sqrt(r2.sum(axis=1) / np.maximum(mask.sum(axis=1), 1))[:, None]
    h = np.where(h > 0, h, 1.0)
    n = n0
    for _ in range(iterations):
        if planar:
            t1 = np.stack([-n[:, 1], n[:, 0], 0.0 * n[:, 0]], axis=1)
            t2 = np.zeros_like(t1)
        else:
            t1, t2 = _frame(n)
        u = np.einsum("smi,si->sm", d, t1) / h
        v = np.einsum("smi,si->sm", d, t2) / h
        w = np.einsum("smi,si->sm", d, n) / h
        rho2 = u * u + v * v
        wt = np.where(mask & (rho2 > 1e-24), 1.0 / np.maximum(rho2, 1e-24) ** 2, 0.0)
        if sigma is not None:
            psi = 2.0 * np.arctan2(np.abs(w), np.sqrt(rho2))
            wt = wt * np.exp(-((psi / np.radians(sigma)) ** 2))
        P, high = _basis(u, v, w, degree, planar)
        c = _weighted_lstsq(P, -w, wt, high, 1 if planar else 2)
        if planar:
            g = n + c[:, -1:] * t1
        else:
            g = n + c[:, -2:-1] * t1 + c[:, -1:] * t2
        with np.errstate(invalid="ignore", divide="ignore"):
            n = g / np.linalg.norm(g, axis=1, keepdims=True)
    return n


def fit_sector_normals(
    vid: np.ndarray,
    x: np.ndarray,
    label: np.ndarray,
    region: np.ndarray,
    n0: np.ndarray,
    facet_normal: np.ndarray,
    interior: np.ndarray,
    sector_rings: SectorRings | None = None,
) -> np.ndarray:
    """Fitted normal of every sector, with fallbacks; vectorised over sectors.

    Each level of :data:`JET_LEVELS` is tried on the sectors no earlier level
    accepted.  A fit is accepted when its stencil has enough points and its
    normal lies within ``ACCEPT * spread + ACCEPT_DEG`` of the initial
    normal, ``spread`` being the largest angle between the initial normal
    and the normals of the facets within two rings of the sector (2D: of its
    own two segments): a safety net against fits that leave the cone of the
    surrounding facets (on the smooth test meshes no accepted fit comes near
    it; the ridge penalty of :func:`_weighted_lstsq` keeps degenerate
    stencils in check; a jagged polygon, neighbouring segments turning by
    50 degrees, can send a fit out of the wider cone).  Sectors
    no level accepts, and planar ones (``spread == 0``: the facet normals
    within two rings agree to rounding), keep ``n0``, so flat faces stay
    exactly flat.

    Args:
        vid: ``(F, nfv)`` vertex indices; x: ``(F, nfv, 3)`` corner coordinates.
        label: ``(F, nfv)`` sector label per corner; region: ``(F,)`` smooth region per facet.
        n0: ``(S, 3)`` initial unit normal per sector (weighted facet-normal mean).
        facet_normal: ``(F, 3)`` unit facet normals.
        interior: ``(S,)`` bool, the sector is the only one at its vertex and
            not on an open boundary (coarse ones try the cubic first).
        sector_rings: the stencils' rings of ``vid, label, region`` (made here if None;
            given, the rings grown here are kept in it).

    Returns:
        ``(S, 3)`` unit normals.
    """
    nfv = vid.shape[1]
    S = len(n0)
    nv = int(vid.max()) + 1
    coords = np.zeros((nv, 3))
    coords[vid.ravel()] = x.reshape(-1, 3)
    centre = np.zeros(S, dtype=np.int64)
    centre[label.ravel()] = vid.ravel()
    # largest facet-normal angle over the facets within two rings, and of the sector itself
    if sector_rings is None:
        sector_rings = SectorRings(vid, label, region)
    spread, own = (_ring_spread(sector_rings, rings, facet_normal, n0) for rings in (2, 1))
    # 2D: without an inflection the normal at a vertex lies between its two
    # segments' normals (each is the curve's normal somewhere on its segment)
    cone = spread if nfv == 3 else own
    out = n0.copy()
    todo = spread > 1e-12
    coarse = interior & (own >= np.radians(COARSE_DEG))
    stencils = {}
    for degree, rings, min_points, sigma, coarse_only in JET_LEVELS[nfv]:
        use = todo & coarse if coarse_only else todo
        if not use.any():
            continue
        if rings not in stencils:
            idx, mask = sector_rings.stencils(rings)
            stencils[rings] = idx, mask & (idx != centre[:, None])
        idx, mask = stencils[rings]
        for lo in range(0, S, BATCH):
            sel = lo + np.flatnonzero(use[lo:lo + BATCH] & (mask[lo:lo + BATCH].sum(axis=1) >= min_points))
            if len(sel) == 0:
                continue
            m = int(mask[sel].sum(axis=1).max())
            order = np.argsort(~mask[sel], axis=1, kind="stable")[:, :m]  # valid points first
            pid = np.take_along_axis(idx[sel], order, axis=1)
            pm = np.take_along_axis(mask[sel], order, axis=1)
            n = fit_normals(coords[centre[sel]], coords[pid], pm, n0[sel], degree, sigma, planar=nfv == 2)
            cos = np.einsum("si,si->s", n, n0[sel])
            ok = np.isfinite(cos) & (cos >= np.cos(np.minimum(ACCEPT * cone[sel] + np.radians(ACCEPT_DEG), np.pi)))
            out[sel[ok]] = n[ok]
            todo[sel[ok]] = False
    return out
