"""Compiled per-cell kernels of the guard (numba): the untangling energy, its derivatives, cell quality.

The numpy formulations (:func:`nagata_snap.smoothing.untangle.energy_numpy`,
:func:`nagata_snap.smoothing.quality.mean_ratio`, the band matrix of
:mod:`nagata_snap.smoothing.smooth`) stay the reference: these kernels
compute the same formulas one cell at a time, in registers, without the
``(m, d, d, d, d)`` temporaries of the batched numpy products (the results
agree to rounding; ``tests/test_kernels.py``).  ``benchmarks/guard_kernels.py``
prints microseconds per cell for both.

Why numba rather than UFL forms compiled by FFCx: the energy is a sum over a
small set of cells (each process's part of the neighbourhood of the bad cells) with
per-cell targets ``W^-1`` and a regularisation ``delta`` that changes
between rounds; assembling it with DOLFINx would need a sub-mesh of the
neighbourhood and a function space on it per problem, whose set-up costs
more than the evaluations (the same reason the band system is not
assembled by DOLFINx, see :mod:`nagata_snap.smoothing.smooth`), and the
Hessian of the regularised mean ratio is not a bilinear form FFCx can
generate without the nonlinear expression being rewritten by hand anyway.
numba compiles the plain loops here once per machine (``cache=True``: the
machine code is kept beside the module in ``__pycache__``).

Conventions: ``x (n, d)`` coordinates, ``cells (m, d + 1)`` int64 node
indices, ``B (m, d + 1, d)`` with ``S = sum_v x_v (x) B_v`` the shape matrix
of :mod:`nagata_snap.smoothing.untangle` (``B_0 = -sum_k W^-1_k``,
``B_{k+1} = W^-1_k``), ``d`` 2 or 3.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["energy_terms", "energy_blocks", "energy_value", "volume_mean_ratio", "band_blocks", "hessian_blocks",
           "sum_hessians", "grow_layer", "graph_sums", "tet_shapes", "rotate_blocks", "warm_up"]

_jit = numba.njit(cache=True, nogil=True, error_model="numpy")
#: per-cell helpers, inlined into their callers (numba IR), so that a call with a
#: literal dimension has constant loop bounds that LLVM unrolls
_inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")


@_inline
def _shape(x: np.ndarray, cell: np.ndarray, Bc: np.ndarray, d: int, S: np.ndarray) -> None:
    """``S[c, j] = sum_k (x[cell[k + 1], c] - x[cell[0], c]) W^-1[k, j]`` (in place; ``W^-1 = B[1:]``)."""
    for c in range(d):
        x0 = x[cell[0], c]
        for j in range(d):
            s = 0.0
            for k in range(d):
                s += (x[cell[k + 1], c] - x0) * Bc[k + 1, j]
            S[c, j] = s


@_inline
def _det_cof(S: np.ndarray, d: int, C: np.ndarray) -> float:
    """``det S``, and its cofactor matrix into ``C``."""
    if d == 2:
        C[0, 0], C[0, 1] = S[1, 1], -S[1, 0]
        C[1, 0], C[1, 1] = -S[0, 1], S[0, 0]
        return S[0, 0] * C[0, 0] + S[1, 0] * C[1, 0]
    for c in range(3):
        c1, c2 = (c + 1) % 3, (c + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            C[c, j] = S[c1, j1] * S[c2, j2] - S[c1, j2] * S[c2, j1]
    return S[0, 0] * C[0, 0] + S[1, 0] * C[1, 0] + S[2, 0] * C[2, 0]


@_inline
def _h(sigma: float, r: float, delta: float) -> float:
    """Escobar's regularised determinant ``(sigma + r) / 2`` (cancellation-free for sigma < 0)."""
    if sigma < 0.0:
        return 2.0 * delta * delta / (r - sigma)
    return 0.5 * (sigma + r)


@_jit
def energy_value(x: np.ndarray, cells: np.ndarray, B: np.ndarray, delta: float
                 ) -> tuple[float, np.ndarray]:
    """``(F, sigma (m,))``: the energy ``sum_K eta_delta`` and the volume ratios."""
    m, d = cells.shape[0], x.shape[1]
    S = np.empty((d, d))
    C = np.empty((d, d))
    sig = np.empty(m)
    F = 0.0
    for k in range(m):
        _shape(x, cells[k], B[k], d, S)
        sigma = _det_cof(S, d, C)
        r = np.sqrt(sigma * sigma + 4.0 * delta * delta)
        hp = _h(sigma, r, delta) ** (-2.0 / d)
        s2 = 0.0
        for c in range(d):
            for j in range(d):
                s2 += S[c, j] * S[c, j]
        F += s2 * hp / d
        sig[k] = sigma
    return F, sig


@_inline
def _cell_hessian(S: np.ndarray, C: np.ndarray, sigma: float, r: float, a: float, b: float,
                  Bk: np.ndarray, sk: np.ndarray, d: int, Sv: np.ndarray, Cv: np.ndarray,
                  Bs: np.ndarray, P: np.ndarray, Hk: np.ndarray) -> None:
    """One cell's Hessian ``Hk[v, c, w, e] = sum_jl B_vj (d^2 eta / dS_cj dS_el) B_wl s_v s_w``.

    The terms of ``d^2 eta / dS^2`` (module docstring of the untangle
    module) contracted with ``B`` one by one: with ``Sv = S B_v`` and
    ``Cv = cof(S) B_v`` (``d``-vectors per vertex), ``a I`` gives
    ``a (B_v . B_w) delta_ce``, ``C (x) C`` gives ``Cv_c Cw_e``, ``S (x) C + C (x) S``
    gives ``Sv_c Cw_e + Cv_c Sw_e``, and ``d cof / d S`` gives, in 3D,
    ``e_cep (S (B_v x B_w))_p`` (in 2D ``e_ce (B_v x B_w)``): about 40
    operations per vertex pair instead of the ``d^4`` product.
    """
    nv = d + 1
    cc = 2.0 * b / (d * r) + b * sigma / (r * r)
    cs = 2.0 * a / (d * r)
    for v in range(nv):  # every term is bilinear in (B_v, B_w): scale B_v by s_v first
        for j in range(d):
            Bs[v, j] = sk[v] * Bk[v, j]
        for c in range(d):
            s1 = 0.0
            s2 = 0.0
            for j in range(d):
                s1 += S[c, j] * Bs[v, j]
                s2 += C[c, j] * Bs[v, j]
            Sv[v, c] = s1
            Cv[v, c] = s2
            P[v, c] = cc * s2 - cs * s1
    for v in range(nv):
        for w in range(v, nv):  # the upper triangle of vertex pairs, mirrored
            bb = 0.0
            for j in range(d):
                bb += Bs[v, j] * Bs[w, j]
            for c in range(d):
                for e in range(d):
                    Hk[v, c, w, e] = Cv[v, c] * P[w, e] - cs * Sv[v, c] * Cv[w, e]
                Hk[v, c, w, c] += a * bb
            if d == 2:
                x2 = b * (Bs[v, 0] * Bs[w, 1] - Bs[v, 1] * Bs[w, 0])
                Hk[v, 0, w, 1] -= x2
                Hk[v, 1, w, 0] += x2
            else:
                u0 = Bs[v, 1] * Bs[w, 2] - Bs[v, 2] * Bs[w, 1]
                u1 = Bs[v, 2] * Bs[w, 0] - Bs[v, 0] * Bs[w, 2]
                u2 = Bs[v, 0] * Bs[w, 1] - Bs[v, 1] * Bs[w, 0]
                t0 = b * (S[0, 0] * u0 + S[0, 1] * u1 + S[0, 2] * u2)
                t1 = b * (S[1, 0] * u0 + S[1, 1] * u1 + S[1, 2] * u2)
                t2 = b * (S[2, 0] * u0 + S[2, 1] * u1 + S[2, 2] * u2)
                # - b e_cep t_p: (0,1) t2, (1,2) t0, (2,0) t1, antisymmetric in (c, e)
                Hk[v, 0, w, 1] -= t2
                Hk[v, 1, w, 0] += t2
                Hk[v, 1, w, 2] -= t0
                Hk[v, 2, w, 1] += t0
                Hk[v, 2, w, 0] -= t1
                Hk[v, 0, w, 2] += t1
            if w != v:
                for c in range(d):
                    for e in range(d):
                        Hk[w, e, v, c] = Hk[v, c, w, e]


@_inline
def _terms(x: np.ndarray, cells: np.ndarray, B: np.ndarray, delta: float, hessian: bool,
           scale: np.ndarray, d: int, g: np.ndarray, sig: np.ndarray, Hx: np.ndarray,
           slot: np.ndarray, Hb: np.ndarray) -> float:
    """The loop of :func:`energy_terms` over the cells; returns ``F``.

    With ``slot`` of ``m`` rows (:func:`hessian_blocks`) each cell Hessian is
    added into its matrix blocks ``Hb`` (as :func:`sum_hessians`, in cell
    order) instead of being stored into ``Hx``.
    """
    nv = d + 1
    summed = slot.shape[0] > 0
    Hk = np.empty((nv, d, nv, d))
    S = np.empty((d, d))
    C = np.empty((d, d))
    dS = np.empty((d, d))
    Sv = np.empty((nv, d))
    Cv = np.empty((nv, d))
    Bs = np.empty((nv, d))
    P = np.empty((nv, d))
    F = 0.0
    for k in range(cells.shape[0]):
        cell, Bk = cells[k], B[k]
        _shape(x, cell, Bk, d, S)
        sigma = _det_cof(S, d, C)
        r = np.sqrt(sigma * sigma + 4.0 * delta * delta)
        hp = _h(sigma, r, delta) ** (-2.0 / d)
        s2 = 0.0
        for c in range(d):
            for j in range(d):
                s2 += S[c, j] * S[c, j]
        eta = s2 * hp / d
        F += eta
        sig[k] = sigma
        a = (2.0 / d) * hp
        b = (2.0 / d) * eta / r
        for c in range(d):
            for j in range(d):
                dS[c, j] = a * S[c, j] - b * C[c, j]
        for v in range(nv):
            node = cell[v]
            for c in range(d):
                s = 0.0
                for j in range(d):
                    s += dS[c, j] * Bk[v, j]
                g[node, c] += s
        if hessian and summed:
            _cell_hessian(S, C, sigma, r, a, b, Bk, scale[k], d, Sv, Cv, Bs, P, Hk)
            _add_blocks(Hk, slot[k], Hb)
        elif hessian:
            _cell_hessian(S, C, sigma, r, a, b, Bk, scale[k], d, Sv, Cv, Bs, P, Hx[k])
    return F


@_jit
def energy_terms(x: np.ndarray, cells: np.ndarray, B: np.ndarray, delta: float,
                 hessian: bool, scale: np.ndarray
                 ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """``(F, gradient (n, d), sigma (m,), cell Hessians (m, d+1, d, d+1, d))``.

    With ``hessian`` False the Hessian array is ``(0, d+1, d, d+1, d)``.  Each
    cell's Hessian block ``[v, c, w, e]`` is multiplied by
    ``scale[k, v] * scale[k, w]`` (``scale (m, d + 1)``; ones for the
    Hessian in coordinates, the node scales for scaled variables).
    """
    m, n, d = cells.shape[0], x.shape[0], x.shape[1]
    nv = d + 1
    g = np.zeros((n, d))
    sig = np.empty(m)
    Hx = np.empty((m if hessian else 0, nv, d, nv, d))
    slot = np.empty((0, nv, nv), dtype=np.int64)
    Hb = np.empty((0, d, d))
    if d == 3:  # (a literal dimension: the inlined loops have constant bounds)
        F = _terms(x, cells, B, delta, hessian, scale, 3, g, sig, Hx, slot, Hb)
    else:
        F = _terms(x, cells, B, delta, hessian, scale, 2, g, sig, Hx, slot, Hb)
    return F, g, sig, Hx


@_jit
def energy_blocks(x: np.ndarray, cells: np.ndarray, B: np.ndarray, delta: float,
                  scale: np.ndarray, slot: np.ndarray, nblocks: int
                  ) -> tuple[float, np.ndarray, np.ndarray]:
    """``(F, gradient (n, d), Hessian blocks (nblocks, d, d))`` in one pass over the cells.

    :func:`energy_terms` followed by :func:`sum_hessians` with the same bits
    (each block gets its cells' contributions in the same order), without
    the ``(m, d+1, d, d+1, d)`` array of cell Hessians between them
    (``slot (m, d+1, d+1)`` from :func:`hessian_blocks`).
    """
    m, n, d = cells.shape[0], x.shape[0], x.shape[1]
    nv = d + 1
    g = np.zeros((n, d))
    sig = np.empty(m)
    Hx = np.empty((0, nv, d, nv, d))
    Hb = np.zeros((nblocks, d, d))
    if d == 3:
        F = _terms(x, cells, B, delta, True, scale, 3, g, sig, Hx, slot, Hb)
    else:
        F = _terms(x, cells, B, delta, True, scale, 2, g, sig, Hx, slot, Hb)
    return F, g, Hb


@_jit
def volume_mean_ratio(x: np.ndarray, cells: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """``(signed volumes (m,), mean ratios (m,))`` of P1 cells (``x (n, 3)``).

    The formulas of :func:`nagata_snap.mesh.simplex.signed_volumes` and
    :func:`nagata_snap.smoothing.quality.mean_ratio` (0 for a cell with
    no finite ratio, at most 1).
    """
    m = cells.shape[0]
    vol = np.empty(m)
    q = np.empty(m)
    e = np.empty((d + 1, 3))
    for k in range(m):
        cell = cells[k]
        for v in range(d + 1):
            for c in range(d):
                e[v, c] = x[cell[v], c]
        l2 = 0.0
        for v in range(d + 1):
            for w in range(v + 1, d + 1):
                for c in range(d):
                    t = e[w, c] - e[v, c]
                    l2 += t * t
        if d == 2:
            ax, ay = e[1, 0] - e[0, 0], e[1, 1] - e[0, 1]
            bx, by = e[2, 0] - e[0, 0], e[2, 1] - e[0, 1]
            V = 0.5 * (ax * by - ay * bx)
            qq = 4.0 * np.sqrt(3.0) * abs(V) / l2
        else:
            ax, ay, az = e[1, 0] - e[0, 0], e[1, 1] - e[0, 1], e[1, 2] - e[0, 2]
            bx, by, bz = e[2, 0] - e[0, 0], e[2, 1] - e[0, 1], e[2, 2] - e[0, 2]
            cx, cy, cz = e[3, 0] - e[0, 0], e[3, 1] - e[0, 1], e[3, 2] - e[0, 2]
            V = (ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)) / 6.0
            qq = 12.0 * np.cbrt(3.0 * abs(V)) ** 2 / l2
        vol[k] = V
        q[k] = min(qq, 1.0) if np.isfinite(qq) else 0.0
    return vol, q


@_jit
def band_blocks(G: np.ndarray, w: np.ndarray, row: np.ndarray, col: np.ndarray, model: int,
                mu: float, lmbda: float, n_rows: int, n_cols: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The band matrix's free-free node blocks, summed per node pair, as block CSR.

    Args:
        G: ``(nc, nv, d)`` hat-function gradients; w: ``(nc,)`` ``E |K|``.
        row: ``(nc, nv)`` block row of each cell vertex (``0..n_rows-1``, -1: not a row).
        col: ``(nc, nv)`` block column of each cell vertex (``0..n_cols-1``, -1: constrained).
        model: 0 elastic, 1 harmonic, 2 graph (the models of ``smooth._summed_blocks``).

    Returns:
        ``(indptr (n_rows + 1,), columns (nnzb,), blocks (nnzb, d, d))``, columns
        ascending within each row.  The contributions to a block are added in
        ascending cell order, so the result depends only on the cells' order.
        Temporaries: the row -> cell adjacency (``nc nv`` integers) and one
        marker per column; no per-(cell, pair) array.
    """
    nc, nv, d = G.shape[0], G.shape[1], G.shape[2]
    # row -> cells adjacency (ascending cells)
    rp = np.zeros(n_rows + 1, dtype=np.int64)
    for k in range(nc):
        for a in range(nv):
            if row[k, a] >= 0 and col[k, a] >= 0:
                rp[row[k, a] + 1] += 1
    for r in range(n_rows):
        rp[r + 1] += rp[r]
    rc = np.empty(rp[n_rows], dtype=np.int64)  # packed cell * nv + local vertex
    fill = rp[:-1].copy()
    for k in range(nc):
        for a in range(nv):
            r = row[k, a]
            if r >= 0 and col[k, a] >= 0:
                rc[fill[r]] = k * nv + a
                fill[r] += 1
    # pass 1: distinct columns per row
    mark = np.full(n_cols, -1, dtype=np.int64)
    indptr = np.zeros(n_rows + 1, dtype=np.int64)
    for r in range(n_rows):
        n = 0
        for t in range(rp[r], rp[r + 1]):
            k = rc[t] // nv
            for b in range(nv):
                cb = col[k, b]
                if cb >= 0 and mark[cb] != r:
                    mark[cb] = r
                    n += 1
        indptr[r + 1] = indptr[r] + n
    # pass 2: columns (ascending) and summed blocks
    cols = np.empty(indptr[n_rows], dtype=np.int64)
    blocks = np.zeros((indptr[n_rows], d, d))
    mark[:] = -1
    P = np.empty((d, d))
    for r in range(n_rows):
        lo = indptr[r]
        n = 0
        for t in range(rp[r], rp[r + 1]):
            k = rc[t] // nv
            for b in range(nv):
                cb = col[k, b]
                if cb >= 0 and mark[cb] < lo:
                    mark[cb] = lo + n
                    cols[lo + n] = cb
                    n += 1
        cols[lo:lo + n].sort()
        for q in range(n):
            mark[cols[lo + q]] = lo + q
        for t in range(rp[r], rp[r + 1]):
            k, a = rc[t] // nv, rc[t] % nv
            for b in range(nv):
                cb = col[k, b]
                if cb < 0:
                    continue
                blk = blocks[mark[cb]]
                if model == 2:
                    val = (nv - 1.0) if a == b else -1.0
                    for i in range(d):
                        blk[i, i] += val
                    continue
                tr = 0.0
                for i in range(d):
                    for j in range(d):
                        P[i, j] = G[k, a, i] * (w[k] * G[k, b, j])
                    tr += P[i, i]
                for i in range(d):
                    for j in range(d):
                        if model == 1:
                            if i == j:
                                blk[i, j] += tr
                        else:
                            blk[i, j] += mu * ((tr if i == j else 0.0) + P[j, i]) + lmbda * P[i, j]
    return indptr, cols, blocks


@_jit
def hessian_blocks(var: np.ndarray, nb: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The matrix pattern of the moving variables' Hessian, by ``d x d`` blocks, duplicates merged.

    Args:
        var: ``(m, nv)`` variable block of each cell vertex (-1: the vertex does not move).
        nb: number of variable blocks (moving nodes).

    Returns:
        ``(slot, brow, bcol)``: ``slot (m, nv, nv)`` the matrix block of each
        vertex pair of each cell (-1 where a vertex does not move), and
        ``brow, bcol (q,)`` the block row and column of each of the ``q``
        distinct blocks (block rows in order, the columns of a row in order of
        first appearance).  One pass over the cells of each moving node, no
        sort: :func:`sum_hessians` then adds the cell Hessians into the
        ``q d^2`` distinct entries in cell order.
    """
    m, nv = var.shape
    cnt = np.zeros(nb + 1, dtype=np.int64)  # the cells of each block (CSR)
    for k in range(m):
        for v in range(nv):
            if var[k, v] >= 0:
                cnt[var[k, v] + 1] += 1
    for i in range(nb):
        cnt[i + 1] += cnt[i]
    fill = cnt[:-1].copy()
    cell_of = np.empty(cnt[nb], dtype=np.int64)
    vert_of = np.empty(cnt[nb], dtype=np.int64)
    for k in range(m):
        for v in range(nv):
            i = var[k, v]
            if i >= 0:
                cell_of[fill[i]], vert_of[fill[i]] = k, v
                fill[i] += 1
    slot = np.full((m, nv, nv), -1, dtype=np.int64)
    seen = np.full(nb, -1, dtype=np.int64)  # the row that last met each column block
    at = np.empty(nb, dtype=np.int64)  # its block number in that row
    brow = np.empty(cnt[nb] * nv, dtype=np.int64)
    bcol = np.empty(cnt[nb] * nv, dtype=np.int64)
    q = 0
    for i in range(nb):
        for t in range(cnt[i], cnt[i + 1]):
            k, v = cell_of[t], vert_of[t]
            for w in range(nv):
                j = var[k, w]
                if j < 0:
                    continue
                if seen[j] != i:
                    seen[j], at[j] = i, q
                    brow[q], bcol[q] = i, j
                    q += 1
                slot[k, v, w] = at[j]
    return slot, brow[:q].copy(), bcol[:q].copy()


@_jit
def sum_hessians(H: np.ndarray, slot: np.ndarray, nblocks: int) -> np.ndarray:
    """``(nblocks, d, d)``: the cell Hessians ``H (m, nv, d, nv, d)`` added into their matrix blocks.

    ``slot (m, nv, nv)`` from :func:`hessian_blocks`; cells are added in
    order, so the sums do not depend on anything but the cells' order.
    """
    out = np.zeros((nblocks, H.shape[2], H.shape[2]))
    for k in range(H.shape[0]):
        _add_blocks(H[k], slot[k], out)
    return out


@_inline
def _add_blocks(Hk: np.ndarray, sk: np.ndarray, out: np.ndarray) -> None:
    """One cell's Hessian ``Hk (nv, d, nv, d)`` added into the blocks ``out`` of its vertex
    pairs ``sk (nv, nv)`` (-1: a pair without a block, a vertex that does not move)."""
    nv, d = Hk.shape[0], Hk.shape[1]
    for v in range(nv):
        for w in range(nv):
            b = sk[v, w]
            if b < 0:
                continue
            for c in range(d):
                for e in range(d):
                    out[b, c, e] += Hk[v, c, w, e]


@_jit
def grow_layer(cells: np.ndarray, mark: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One layer of a node mask: ``(mark plus the nodes of every cell touching it (n,), those
    cells (nc,))``, one pass over ``cells (nc, nv)`` (no ``(nc,)`` temporaries per column)."""
    nc, nv = cells.shape
    new = mark.copy()
    touch = np.zeros(nc, dtype=np.bool_)
    for k in range(nc):
        for v in range(nv):
            if mark[cells[k, v]]:
                touch[k] = True
                break
        if touch[k]:
            for v in range(nv):
                new[cells[k, v]] = True
    return new, touch


@_jit
def graph_sums(cells: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``(k, g)``: at each node, the sum over its cells of their other vertices' ``u``.

    ``cells (nc, nv)`` node indices ``0..k-1``, ``u (k, g)``: the product of
    the graph-Laplacian's off-diagonal part (edge weight = cells sharing the
    edge) with ``u``, one pass over the cells, no ``(nc, nv, g)`` temporary.
    """
    nc, nv = cells.shape
    k, g = u.shape
    out = np.zeros((k, g))
    s = np.empty(g)
    for q in range(nc):
        for c in range(g):
            t = 0.0
            for v in range(nv):
                t += u[cells[q, v], c]
            s[c] = t
        for v in range(nv):
            a = cells[q, v]
            for c in range(g):
                out[a, c] += s[c] - u[a, c]
    return out


@_inline
def _cross_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]


@_jit
def tet_shapes(x: np.ndarray, cells: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(signed volume, min and max dihedral angle [rad], radius ratio, sum of squared edges)`` (each ``(m,)``).

    The formulas of ``quality._tetrahedron_shapes`` (``x (n, 3)``,
    ``cells (m, 4)``), one cell at a time: the dihedral angles from the
    cosines between the cofactor vectors of the faces (a zero-area face
    counts as cosine 1), the radius ratio ``216 V^2 / (S sqrt(P))`` (0 where
    it is not finite).
    """
    m = cells.shape[0]
    vol, amin, amax = np.empty(m), np.empty(m), np.empty(m)
    rr, l2s = np.empty(m), np.empty(m)
    p = np.empty((4, 3))
    e = np.empty((6, 3))
    cof = np.empty((4, 3))
    nrm = np.empty(4)
    le = np.empty(6)
    ea = np.array([0, 0, 0, 1, 1, 2])  # TET_EDGES
    eb = np.array([1, 2, 3, 2, 3, 3])
    fa = np.array([2, 1, 1, 0, 0, 0])  # TET_EDGE_FACETS
    fb = np.array([3, 3, 2, 3, 2, 1])
    for k in range(m):
        for v in range(4):
            for c in range(3):
                p[v, c] = x[cells[k, v], c]
        l2 = 0.0
        for q in range(6):
            t = 0.0
            for c in range(3):
                e[q, c] = p[eb[q], c] - p[ea[q], c]
                t += e[q, c] * e[q, c]
            le[q] = np.sqrt(t)
            l2 += t
        _cross_into(e[1], e[2], cof[1])
        _cross_into(e[2], e[0], cof[2])
        _cross_into(e[0], e[1], cof[3])
        for c in range(3):
            cof[0, c] = -(cof[1, c] + cof[2, c] + cof[3, c])
        V = (e[0, 0] * cof[1, 0] + e[0, 1] * cof[1, 1] + e[0, 2] * cof[1, 2]) / 6.0
        for f in range(4):
            nrm[f] = np.sqrt(cof[f, 0] ** 2 + cof[f, 1] ** 2 + cof[f, 2] ** 2)
        cmin, cmax = np.inf, -np.inf
        for q in range(6):
            den = nrm[fa[q]] * nrm[fb[q]]
            cs = 1.0
            if den > 0:
                cs = (cof[fa[q], 0] * cof[fb[q], 0] + cof[fa[q], 1] * cof[fb[q], 1]
                      + cof[fa[q], 2] * cof[fb[q], 2]) / den
            cmin = min(cmin, cs)
            cmax = max(cmax, cs)
        amin[k] = np.pi - np.arccos(min(max(cmin, -1.0), 1.0))
        amax[k] = np.pi - np.arccos(min(max(cmax, -1.0), 1.0))
        S = 0.5 * (nrm[0] + nrm[1] + nrm[2] + nrm[3])
        a, b, c3 = le[0] * le[5], le[1] * le[4], le[2] * le[3]
        Pp = (a + b + c3) * (a + b - c3) * (a - b + c3) * (-a + b + c3)
        r = 216.0 * V * V / (S * np.sqrt(max(Pp, 0.0)))
        rr[k] = r if np.isfinite(r) else 0.0
        vol[k] = V
        l2s[k] = l2
    return vol, amin, amax, rr, l2s


@_jit
def rotate_blocks(Hb: np.ndarray, R: np.ndarray, brow: np.ndarray, bcol: np.ndarray,
                  sel: np.ndarray) -> None:
    """``Hb[b] <- R[brow[b]]^T Hb[b] R[bcol[b]]`` for the blocks ``sel (k,)`` (in place).

    ``Hb (q, d, d)`` the matrix blocks of :func:`sum_hessians`, ``R (nb, d,
    d)`` the variable basis of each block row / column (``R[i, c, a]``:
    component ``c`` of basis vector ``a``): the Hessian in the tangent
    variables of sliding nodes.  The basis is a node's, not a cell's, so the
    summed blocks are rotated (fewer than the cells' vertex pairs).
    """
    d = Hb.shape[1]
    T = np.empty((d, d))
    for q in range(sel.shape[0]):
        b = sel[q]
        i, j = brow[b], bcol[b]
        for a in range(d):  # T = R_i^T H_b
            for e in range(d):
                t = 0.0
                for c in range(d):
                    t += R[i, c, a] * Hb[b, c, e]
                T[a, e] = t
        for a in range(d):  # H_b = T R_j
            for f in range(d):
                t = 0.0
                for e in range(d):
                    t += T[a, e] * R[j, e, f]
                Hb[b, a, f] = t


def warm_up() -> None:
    """Load every kernel's machine code (from numba's cache) with the argument types the guard uses.

    numba loads a cached kernel at its first call, about 0.7 s for the first
    one in a process (numba's own set-up) and a few milliseconds for each
    later one; :class:`~nagata_snap.snapper.Snapper` calls this once when
    it is built, so that the cost is the process's, not a level's.
    """
    for d in (2, 3):
        nv = d + 1
        x = np.eye(nv, d, -1)  # (nv, d): the origin and the unit vectors
        cells = np.arange(nv, dtype=np.int64)[None, :]
        B = np.ascontiguousarray(np.concatenate([-np.ones((1, d)), np.eye(d)])[None])
        ones = np.ones((1, nv))
        energy_terms(x, cells, B, 1e-4, True, ones)
        energy_value(x, cells, B, 1e-4)
        x3 = np.zeros((nv, 3))
        x3[:, :d] = x
        volume_mean_ratio(x3, cells.astype(np.int32), d)
        slot, brow, bcol = hessian_blocks(cells, nv)
        Hb = sum_hessians(np.zeros((1, nv, d, nv, d)), slot, brow.size)
        energy_blocks(x, cells, B, 1e-4, ones, slot, brow.size)
        rotate_blocks(Hb, np.zeros((nv, d, d)), brow, bcol, np.zeros(1, np.int64))
        graph_sums(cells, x)
        grow_layer(cells.astype(np.int32), np.ones(nv, dtype=bool))
        if d == 3:
            tet_shapes(x3, cells)
        G = np.ascontiguousarray(B.transpose(0, 1, 2))
        band_blocks(G, np.ones(1), cells, cells, 0, 0.5, 0.5, nv, nv)
