"""Trimmed faces: is a surface point ``(u, v)`` on its face?

A face is its surface restricted by trimming loops: closed polygons in the
surface's parameter plane (:class:`nagata_snap.cad.topology.Loop`, from the
p-curves of the face's wires; or user polygons for :class:`CadGeometry`
built from NURBS entities).  A parameter point is on the face if it is
inside an odd number of loops (the even-odd rule: inside the outer wire and
outside every hole, whatever the loops' orientation) or within a band of a
loop.

The band covers the difference between the polygon and the true trimming
curve (known per segment from the sampling, see :mod:`~nagata_snap.cad.topology`)
plus an absolute tolerance; it is measured in length units, through the
surface's first derivatives at the query point (``|S_u du + S_v dv|`` for
the parametric offset ``(du, dv)`` to the nearest segment), so that it means
the same on a cylinder's ``u`` (radians) as on its ``v`` (length) and
vanishes in ``u`` at a sphere's pole.  Points on a face boundary shared by
two faces are therefore on both.

Closed (periodic) directions: a query is tested at its parameter and, where
that is outside, one period either side, so loops may lie anywhere in the
periodic plane (OpenCASCADE's p-curves of a full revolution span exactly one
period, the seam edge being used twice).
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np
import numpy.typing as npt

from nagata_snap.mesh.arrays import Groups, ramp

__all__ = ["TrimLoops"]

#: default absolute trimming tolerance, relative to the size of the face's surface
TRIM_RTOL = 1e-6
#: turning angle (radians) above which a vertex of a user polygon is a corner of the
#: loop, not a sample of a smooth trimming curve
CORNER_ANGLE = 0.35
#: work-array budget (entries) of the vectorised loop tests
CHUNK = 400_000


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _segment_distances(Q: np.ndarray, first: np.ndarray, cnt: np.ndarray, su: np.ndarray, sv: np.ndarray,
                       P: np.ndarray, seg: np.ndarray, band: np.ndarray) -> np.ndarray:
    """``(m,)``: per query ``Q[r] (2,)`` the least distance, through the metric ``(su[r], sv[r])``,
    from the segments ``P[j] + t seg[j]`` (``t`` in ``[0, 1]``) ``j`` in ``first[r] ..
    first[r] + cnt[r]``, less their ``band[j]`` (``inf`` for none); the arithmetic of
    :meth:`TrimLoops._distance_all`'s arrays, one query at a time (no work arrays)."""
    out = np.empty(len(Q))
    for r in range(len(Q)):  # loop over queries
        a, b = su[r], sv[r]
        best = np.inf
        for j in range(first[r], first[r] + cnt[r]):  # loop over the segments of its loops
            qx, qy = (Q[r, 0] - P[j, 0]) * a, (Q[r, 1] - P[j, 1]) * b
            sx, sy = seg[j, 0] * a, seg[j, 1] * b
            t = min(max((qx * sx + qy * sy) / max(sx * sx + sy * sy, 1e-300), 0.0), 1.0)
            rx, ry = qx - t * sx, qy - t * sy
            best = min(best, np.sqrt(rx * rx + ry * ry) - band[j])
        out[r] = best
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _slab_crossings(x: np.ndarray, y: np.ndarray, loop: np.ndarray, y0: np.ndarray, dy: np.ndarray,
                    n: np.ndarray, first: np.ndarray, seg: np.ndarray, ptr: np.ndarray, P: np.ndarray,
                    off: np.ndarray, nxt: np.ndarray) -> np.ndarray:
    """``(m,)`` :meth:`_SlabTable.crossings` of the queries ``(x[i], y[i])`` with polygon
    ``loop[i]``, one query at a time (the table's arrays: no work arrays per (query, edge))."""
    out = np.zeros(len(x), dtype=np.int64)
    for i in range(len(x)):  # loop over queries
        lp, yq = loop[i], y[i]
        t = (yq - y0[lp]) / dy[lp]
        if not (t > -1.0 and t < n[lp]):  # the slabs trunc(t) in 0..n-1; NaN is outside
            continue
        s = first[lp] + np.int64(t)
        c = 0
        for k in range(ptr[s], ptr[s + 1]):  # loop over the edges spanning the slab
            e = off[lp] + seg[k]
            ay, by = P[e, 1], P[nxt[e], 1]
            if (ay > yq) != (by > yq) and x[i] < P[e, 0] + (yq - ay) * (P[nxt[e], 0] - P[e, 0]) / (by - ay):
                c += 1
        out[i] = c
    return out


def _crossings(poly: np.ndarray, pts: np.ndarray, slabs: _Slabs | None = None) -> np.ndarray:
    """Number of polygon edges crossed by the ray ``+x`` from each point, ``(m,)``.

    With ``slabs`` (:class:`_Slabs` of the polygon) only the edges in the
    point's horizontal slab are tested.
    """
    a, b = poly, np.roll(poly, -1, axis=0)
    if slabs is not None:
        pt, seg = slabs.candidates(pts[:, 1])
        y, x = pts[pt, 1], pts[pt, 0]
        ay, by = a[seg, 1], b[seg, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = a[seg, 0] + (y - ay) * (b[seg, 0] - a[seg, 0]) / (by - ay)
        hit = ((ay > y) != (by > y)) & (x < xint)
        return np.bincount(pt[hit], minlength=len(pts))
    out = np.zeros(len(pts), dtype=np.int64)
    step = max(1, CHUNK // max(len(poly), 1))
    for i in range(0, len(pts), step):  # chunks bound the (c, k) work arrays
        x, y = pts[i:i + step, 0:1], pts[i:i + step, 1:2]
        ay, by = a[None, :, 1], b[None, :, 1]
        crosses = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = a[None, :, 0] + (y - ay) * (b[None, :, 0] - a[None, :, 0]) / (by - ay)
        out[i:i + step] = np.count_nonzero(crosses & (x < xint), axis=1)
    return out


class _Slabs:
    """Horizontal slabs of a polygon: the edges spanning each slab (CSR), for crossing tests.

    A query point's ray ``+x`` can only cross edges whose ``y`` range holds the
    point's ``y``: those listed for its slab (``k / 2`` slabs for ``k`` edges; horizontal
    edges, which no such ray crosses, in none).

    Attributes:
        y0, dy, n: the slabs ``[y0 + i dy, y0 + (i + 1) dy)``, ``i < n``.
        seg, ptr: CSR lists of the edges spanning each slab.
    """

    y0: float
    dy: float
    n: int
    seg: np.ndarray
    ptr: np.ndarray

    def __init__(self, P: np.ndarray):
        built = _Slabs.many([P])[0]
        self.y0, self.n, self.dy, self.seg, self.ptr = built.y0, built.n, built.dy, built.seg, built.ptr

    @classmethod
    def many(cls, polys: Sequence[np.ndarray]) -> list[_Slabs]:
        """The slabs of every polygon ``(k_i, 2)`` of ``polys``, built together (no loop per polygon
        but the slicing of the result)."""
        if not polys:
            return []
        P, m = np.concatenate(polys), np.array([len(P) for P in polys])
        return cls._many(P, m, *_closing(m))

    @classmethod
    def _many(cls, P: np.ndarray, m: np.ndarray, off: np.ndarray, nxt: np.ndarray) -> list[_Slabs]:
        """:meth:`many` of the polygons ``P (sum m, 2)``, polygon ``i`` the next ``m[i]`` rows
        (``off``, ``nxt``: :func:`_closing` of ``m``)."""
        return cls._split(_SlabTable.build(P, m, off, nxt))

    @classmethod
    def _split(cls, tab: _SlabTable) -> list[_Slabs]:
        """Every polygon's :class:`_Slabs`, slices of the table of all of them."""
        out = []
        f, s0 = tab.first.tolist(), tab.ptr[tab.first].tolist()
        for i, (a, b, c) in enumerate(zip(tab.y0.tolist(), tab.n.tolist(), tab.dy.tolist(), strict=True)):
            sl = cls.__new__(cls)  # (loop over polygons)
            sl.y0, sl.n, sl.dy = a, b, c
            sl.seg, sl.ptr = tab.seg[s0[i]:s0[i + 1]], tab.ptr[f[i]:f[i + 1] + 1] - s0[i]
            out.append(sl)
        return out

    def candidates(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(point, edge)`` pairs to test for query ordinates ``y``."""
        t = (y - self.y0) / self.dy
        inside = (t > -1.0) & (t < self.n)  # the slabs trunc(t) in 0..n-1; NaN is outside
        s = np.where(inside, t, 0.0).astype(np.int64)
        cnt = np.where(inside, self.ptr[s + 1] - self.ptr[s], 0)
        pt = np.repeat(np.arange(len(y)), cnt)
        off = ramp(cnt)
        return pt, self.seg[np.repeat(self.ptr[s], cnt) + off]


class _SlabTable:
    """The :class:`_Slabs` of many polygons in one table, for crossing tests of queries on
    different polygons at once (:meth:`crossings`).

    Attributes:
        y0, dy, n: ``(w,)`` per polygon its slabs ``[y0 + i dy, y0 + (i + 1) dy)``, ``i < n``.
        first: ``(w + 1,)`` number of each polygon's first slab in the table.
        seg, ptr: CSR lists of the edges (numbered within their polygon) spanning each slab.
        P, off, nxt: the polygons' vertices, :func:`_closing`'s offsets and next vertices.
    """

    y0: np.ndarray
    dy: np.ndarray
    n: np.ndarray
    first: np.ndarray
    seg: np.ndarray
    ptr: np.ndarray
    P: np.ndarray
    off: np.ndarray
    nxt: np.ndarray

    @classmethod
    def build(cls, P: np.ndarray, m: np.ndarray, off: np.ndarray, nxt: np.ndarray) -> _SlabTable:
        """The table of the polygons ``P (sum m, 2)``, polygon ``i`` the next ``m[i]`` rows
        (``off``, ``nxt``: :func:`_closing` of ``m``)."""
        lid = np.arange(len(m)).repeat(m)
        y = P[:, 1]
        ends = np.empty((2, len(P)))  # the lower and upper ordinate of each edge
        yn = y[nxt]
        np.minimum(y, yn, out=ends[0])
        np.maximum(y, yn, out=ends[1])
        y0, y1 = np.minimum.reduceat(ends[0], off[:-1]), np.maximum.reduceat(ends[1], off[:-1])
        n = np.minimum(np.maximum(m // 2, 1), 4096)
        dy = np.maximum((y1 - y0) / n, 1e-300)
        # the first and the last slab of each edge (of its polygon's, clamped to them)
        s = ((ends - y0[lid]) / dy[lid]).astype(np.int64)
        np.maximum(s, 0, out=s)
        np.minimum(s, (n - 1)[lid], out=s)
        # (a horizontal edge, or one with a NaN end, is listed in no slab: the ray +x from a
        # point crosses an edge where exactly one of its ends is above the point, never there)
        cnt = np.where(ends[0] < ends[1], s[1] - s[0] + 1, 0)
        first = np.zeros(len(n) + 1, dtype=np.int64)  # global number of each polygon's first slab
        n.cumsum(out=first[1:])
        seg = (np.arange(len(P)) - off[lid]).repeat(cnt)
        # the slabs of each edge's entries: its first one plus 0..cnt-1 (ramp(cnt) with one repeat:
        # the entries of edge j start at end[j] - cnt[j])
        end = cnt.cumsum()
        slab = (s[0] + first[lid] + cnt - end).repeat(cnt)
        slab += np.arange(len(seg))
        # by slab, stably (a radix sort where the slab numbers fit 16 bits: the same order)
        seg = seg[(slab.astype(np.uint16) if first[-1] <= 0xFFFF else slab).argsort(kind="stable")]
        ptr = np.zeros(int(first[-1]) + 1, dtype=np.int64)
        np.bincount(slab, minlength=int(first[-1])).cumsum(out=ptr[1:])
        tab = cls.__new__(cls)
        tab.y0, tab.dy, tab.n, tab.first, tab.seg, tab.ptr = y0, dy, n, first, seg, ptr
        tab.P, tab.off, tab.nxt = P, off, nxt
        return tab

    def crossings(self, loop: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """``(m,)``: edges of polygon ``loop[i]`` crossed by the ray ``+x`` from ``pts[i]``
        (``pts (m, 2)``), as :func:`_crossings` with the polygon's slabs, for all at once."""
        pts = np.asarray(pts, dtype=float)
        return _slab_crossings(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                               np.asarray(loop, dtype=np.int64), self.y0, self.dy, self.n, self.first,
                               self.seg, self.ptr, self.P, self.off, self.nxt)


#: the parameter shifts of :meth:`TrimLoops._shifts`, in periods: 0 and one either way in each direction
_SHIFTS = np.array([(du, dv) for du in (0.0, -1.0, 1.0) for dv in (0.0, -1.0, 1.0)])


class _Domains:
    """The parameter domains of many surfaces, to wrap or clamp the parameters of points on
    different surfaces at once (:func:`~nagata_snap.cad.projection.normalize_params` of each).

    Attributes:
        ok: every entity has two parameters (surfaces): :meth:`normalize` applies.
    """

    def __init__(self, entities: Sequence):
        from nagata_snap.cad.projection import entity_limits, entity_periods

        self.ok = all(e.param_dim == 2 for e in entities)
        if not self.ok or not entities:
            return
        self.lo = np.array([e.bounds[:, 0] for e in entities], dtype=float)
        self.period = np.array([entity_periods(e) for e in entities], dtype=float)
        self.limits = np.array([entity_limits(e) for e in entities], dtype=float)

    def normalize(self, ent: np.ndarray, params: np.ndarray) -> np.ndarray:
        """``(n, 2)``: ``params`` of points on entities ``ent`` wrapped into ``[lo, lo + period)``
        in closed directions (where outside ``[lo, lo + period]``), clamped to the limits in open ones."""
        p = np.array(params, dtype=float)
        lo, per, lim = self.lo[ent], self.period[ent], self.limits[ent]
        closed = np.isfinite(per)
        with np.errstate(invalid="ignore"):
            out = closed & ((p < lo) | (p > lo + per))
            wrapped = lo + np.mod(p - lo, np.where(closed, per, 1.0))
        return np.where(out, wrapped, np.where(closed, p, np.clip(p, lim[..., 0], lim[..., 1])))


def _closing(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(off (len(m) + 1,), nxt (sum m,))`` of closed polygons of ``m`` vertices each, stored
    one after the other: polygon ``i`` is rows ``off[i]:off[i + 1]``, and vertex ``j`` is
    followed by vertex ``nxt[j]`` (each polygon closes on its first vertex)."""
    off = np.zeros(len(m) + 1, dtype=np.int64)
    m.cumsum(out=off[1:])
    nxt = np.arange(1, int(off[-1]) + 1)
    nxt[off[1:] - 1] = off[:-1]
    return off, nxt


def _user_band(P: np.ndarray) -> np.ndarray:
    """Parametric sagitta bound of a user polygon's segments (no true curve known).

    Between two vertices the trimming curve deviates from the chord by about
    ``L phi / 8`` (``L`` the chord, ``phi`` the larger turning angle at its
    ends; vertices turning by more than :data:`CORNER_ANGLE` are corners,
    which add nothing); twice that is the band.
    """
    seg = np.roll(P, -1, axis=0) - P
    L = np.linalg.norm(seg, axis=1)
    prev = np.roll(seg, 1, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.einsum("ij,ij->i", prev, seg) / (np.roll(L, 1) * L)
    phi = np.arccos(np.clip(np.nan_to_num(c, nan=1.0), -1.0, 1.0))
    phi[phi > CORNER_ANGLE] = 0.0
    return 2.0 * L * np.maximum(phi, np.roll(phi, -1)) / 8.0


class TrimLoops:
    """Trimming loops of several entities and the on-face test.

    Args:
        entities: the surfaces (entity protocol of :mod:`nagata_snap.cad.nurbs`).
        loops: per entity a list of closed polygons ``(k, 2)`` (an empty list:
            the whole surface is the face).
        bands: per entity, per loop, ``(k,)`` bound (length units) on the
            distance between each segment and the true trimming curve; default
            estimated from the polygon's turning angles (:func:`_user_band`).
        rtol: absolute tolerance, relative to each surface's size.
    """

    def __init__(self, entities: Sequence, loops: Sequence[Sequence[np.ndarray]],
                 bands: Sequence[Sequence[np.ndarray]] | None = None, rtol: float = TRIM_RTOL):
        from nagata_snap.cad.projection import entity_periods

        n = len(entities)
        if len(loops) != n:
            raise ValueError(f"{len(loops)} loop lists for {n} entities")
        self.entities = list(entities)
        self.rtol = float(rtol)
        fast = self._checked_together(loops, bands)
        ent, m, P, band = self._checked(loops, bands) if fast is None else fast
        off, nxt = _closing(m)
        seg = P[nxt] - P  # the edge vectors of all loops
        self._table = _SlabTable.build(P, m, off, nxt)
        self._seg, self._band = seg, band
        slabs = _Slabs._split(self._table)
        o = off.tolist()
        self._loops: list[list[tuple]] = [[] for _ in range(n)]
        for i, (e, sl) in enumerate(zip(ent, slabs, strict=True)):  # loop over loops (their records)
            a, b = o[i], o[i + 1]
            self._loops[e].append((P[a:b], seg[a:b], band[a:b], sl))
        self.trimmed = np.array([bool(lp) for lp in self._loops])
        self._period = np.array([entity_periods(ent) for ent in self.entities])
        # each entity's loops (numbered as the table's, by entity: they were gathered so)
        lent = np.asarray(ent, dtype=np.int64)
        self._loop_start = np.searchsorted(lent, np.arange(n + 1)) if (np.diff(lent) >= 0).all() else None
        self._domain = _Domains(self.entities)

    def _checked(self, loops: Sequence[Sequence[np.ndarray]], bands: Sequence[Sequence[np.ndarray]] | None
                 ) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray]:
        """``(entity, m, P, band)``: per loop its entity and size ``m (w,)``, and the polygons
        ``P (sum m, 2)`` (a repeated first vertex dropped) and their bands plus the absolute
        tolerance ``(sum m,)``, concatenated; checked loop by loop.

        Raises:
            ValueError: naming the first loop that is not a finite ``(k, 2)`` polygon of at
                least 2 vertices.
        """
        ent: list[int] = []
        polys: list[np.ndarray] = []
        bs: list[np.ndarray] = []
        for e in range(len(loops)):  # loop over entities (checks and bands)
            for k, poly in enumerate(loops[e] or []):
                P = np.asarray(poly, dtype=float)
                if P.ndim != 2 or P.shape[1] != 2 or not np.isfinite(P).all():
                    raise ValueError(f"entity {e}: trimming loop {k} must be a finite (k, 2) polygon, got {P.shape}")
                if len(P) > 1 and P[0, 0] == P[-1, 0] and P[0, 1] == P[-1, 1]:  # closed on its first vertex
                    P = P[:-1]
                if len(P) < 2:
                    raise ValueError(f"entity {e}: trimming loop {k} has fewer than 2 vertices")
                if bands is None or bands[e] is None:
                    band = self._param_band(e, P)
                else:
                    band = np.asarray(bands[e][k], dtype=float).reshape(len(P))
                ent.append(e)
                polys.append(P)
                bs.append(band + self.rtol * self.entities[e].bbox_size)
        m = np.array([len(P) for P in polys], dtype=np.int64)
        return ent, m, np.concatenate([*polys, np.zeros((0, 2))]), np.concatenate([*bs, np.zeros(0)])

    def _checked_together(self, loops: Sequence[Sequence[np.ndarray]],
                          bands: Sequence[Sequence[np.ndarray]] | None
                          ) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray] | None:
        """:meth:`_checked` for loops that all have their bands (a model's), the checks and the
        tolerances of all loops done together; None if one is not as expected (then
        :meth:`_checked` decides, loop by loop)."""
        if bands is None:
            return None
        ent: list[int] = []
        polys: list[np.ndarray] = []
        bs: list[np.ndarray] = []
        for e, lps in enumerate(loops):  # loop over entities (gathering their loops)
            if not lps:
                continue
            be = bands[e]
            if be is None or len(be) != len(lps):
                return None
            ent += [e] * len(lps)
            polys += lps
            bs += be
        if not polys:
            return [], np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros(0)
        try:  # the checks of every loop's shape, on them concatenated
            P, band = np.concatenate(polys, dtype=float), np.concatenate(bs, dtype=float)
        except (ValueError, TypeError):  # not all of one number of dimensions (or not real)
            return None
        m = np.fromiter(map(len, polys), dtype=np.int64, count=len(polys))
        if P.ndim != 2 or P.shape[1] != 2 or band.ndim != 1 or (m < 2).any():
            return None
        end = m.cumsum()
        uv = P.view(np.complex128)[:, 0]  # each vertex as u + iv: equal when both coordinates are
        closed = uv[end - m] == uv[end - 1]  # closed on its first vertex
        m -= closed
        if not np.isfinite(P).all() or (m < 2).any() or list(map(len, bs)) != m.tolist():
            return None
        if closed.any():
            keep = np.ones(len(P), dtype=bool)
            keep[(end - 1)[closed]] = False
            P = P[keep]
        tol = self.rtol * np.array([self.entities[e].bbox_size for e in ent])
        return ent, m, P, band + tol.repeat(m)

    @classmethod
    def from_outer_holes(cls, entities, outer=None, holes=None, rtol: float = TRIM_RTOL) -> TrimLoops:
        """Loops from per-entity ``outer`` polygons (or ``None``) and lists of ``holes``."""
        n = len(entities)
        for name, arr in (("trim_loops", outer), ("trim_holes", holes)):
            if arr is not None and len(arr) != n:
                raise ValueError(f"{name} has {len(arr)} entries for {n} entities")
        loops = []
        for e in range(n):
            lp = [] if outer is None or outer[e] is None else [outer[e]]
            lp += [] if holes is None or holes[e] is None else list(holes[e])
            loops.append(lp)
        return cls(entities, loops, None, rtol)

    def _param_band(self, e: int, P: np.ndarray) -> np.ndarray:
        """:func:`_user_band` converted to length units at the segment midpoints."""
        band = _user_band(P)
        mid = 0.5 * (P + np.roll(P, -1, axis=0))
        su, sv = self._scales(e, mid)
        return band * np.maximum(su, sv)

    def _scales(self, e: int, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``|S_u|, |S_v|`` at ``params (m, 2)`` of entity ``e``."""
        from nagata_snap.cad.projection import evaluate_params, normalize_params

        ent = self.entities[e]
        _, T = evaluate_params(ent, normalize_params(ent, params), 1)
        return np.linalg.norm(T[:, 0], axis=1), np.linalg.norm(T[:, 1], axis=1)

    def _excess(self, e: int, q: np.ndarray, su: np.ndarray, sv: np.ndarray) -> np.ndarray:
        """Distance (length units) outside face ``e`` beyond the band, ``(m,)``.

        ``<= 0`` on the face; ``-inf`` inside the loops (no distance computed).
        """
        loops = self._loops[e]
        cross = np.zeros(len(q), dtype=np.int64)
        for P, _, _, slabs in loops:
            cross += _crossings(P, q, slabs)
        ex = np.full(len(q), -np.inf)
        out = np.flatnonzero(cross % 2 == 0)
        if out.size:
            ex[out] = self._beyond(e, q, su, sv, out)
        return ex

    def _beyond(self, e: int, q: np.ndarray, su: np.ndarray, sv: np.ndarray, out: np.ndarray) -> np.ndarray:
        """``(len(out),)`` distance (length units, through the metric ``su, sv``) of the points
        ``q[out]`` from the nearest loop segment of face ``e``, less that segment's band."""
        best = np.full(out.size, np.inf)
        for P, seg, band, _ in self._loops[e]:
            step = max(1, CHUNK // len(P))
            for i in range(0, out.size, step):  # chunks bound the (c, k, 2) work arrays
                sel = out[i:i + step]
                s = np.stack([su[sel], sv[sel]], axis=1)[:, None, :]  # (c, 1, 2) metric
                qq = (q[sel, None, :] - P[None]) * s
                ss = seg[None] * s
                L2 = np.maximum(np.einsum("ckj,ckj->ck", ss, ss), 1e-300)
                t = np.clip(np.einsum("ckj,ckj->ck", qq, ss) / L2, 0.0, 1.0)
                r = qq - t[:, :, None] * ss
                d = np.sqrt(np.einsum("ckj,ckj->ck", r, r)) - band[None]
                best[i:i + step] = np.minimum(best[i:i + step], d.min(axis=1))
        return best

    def _shifts(self, e: int) -> list[np.ndarray]:
        """The parameter shifts under which face ``e``'s loops are tested: 0 first, then one
        period either way in each closed direction (at most 9)."""
        shifts = [np.zeros(2)]
        for a in range(2):
            if np.isfinite(self._period[e, a]):
                d = np.zeros(2)
                d[a] = self._period[e, a]
                shifts = [s + k * d for s in shifts for k in (0.0, -1.0, 1.0)]
        return shifts

    def loop_distance(self, ent: npt.ArrayLike, params: npt.ArrayLike, enough: float | None = None,
                      scales: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """``(n,)`` distance (length units) of ``params (n, 2)`` from the nearest trimming
        loop of face ``ent (n,)``, less the loop's band, inside or outside (``inf`` for an
        untrimmed face): where it is positive, :meth:`inside` does not depend on the band.
        ``enough``: a point whose distance at the wrapped parameter is at most this is not
        tested one period either side (its value is then an upper bound).  ``scales``: ``|S_u|,
        |S_v|`` ``(n,)`` at the points, where known (else evaluated here)."""
        from nagata_snap.cad.projection import normalize_params

        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        out = np.full(len(ent), np.inf)
        if len(ent) == 0:
            return out
        params = np.asarray(params, dtype=float).reshape(len(ent), -1)[:, :2]
        rows = np.flatnonzero(self.trimmed[ent])
        if self._loop_start is not None and self._domain.ok and rows.size:
            q0 = self._domain.normalize(ent[rows], params[rows])
            if scales is not None:
                su, sv = np.asarray(scales[0], dtype=float)[rows], np.asarray(scales[1], dtype=float)[rows]
            else:
                g = Groups(ent[rows])
                su, sv = np.empty(len(rows)), np.empty(len(rows))
                for e, gs in g:  # loop over trimmed entities (their metric at the points)
                    sel = g.order[gs]
                    su[sel], sv[sel] = self._scales(e, q0[sel])
            out[rows] = self._distance_all(ent[rows], q0, su, sv)
            return out
        g = Groups(ent[rows])
        for e, gs in g:  # loop over trimmed entities
            sel = rows[g.order[gs]]
            q0 = normalize_params(self.entities[e], params[sel])
            su, sv = self._scales(e, q0)
            best = np.full(len(sel), np.inf)
            todo = np.arange(len(sel))
            for sh in self._shifts(e):  # the first is 0
                best[todo] = np.minimum(best[todo], self._beyond(e, q0 + sh, su, sv, todo))
                if enough is not None:
                    todo = todo[best[todo] > enough]
                if todo.size == 0:
                    break
            out[sel] = best
        return out

    def excess(self, ent: npt.ArrayLike, params: npt.ArrayLike) -> np.ndarray:
        """``(n,)`` distance (length units) of ``params (n, 2)`` outside face ``ent (n,)``.

        ``<= 0`` means on the face (``-inf`` inside its loops or for untrimmed
        surfaces); a positive value is the distance to the nearest loop
        beyond its band.
        """
        from nagata_snap.cad.projection import normalize_params

        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        params = np.asarray(params, dtype=float).reshape(len(ent), -1)[:, :2]
        out = np.full(len(ent), -np.inf)
        if len(ent) == 0 or not self.trimmed.any():
            return out
        rows = np.flatnonzero(self.trimmed[ent])
        g = Groups(ent[rows])
        for e, gs in g:  # loop over trimmed entities
            sel = rows[g.order[gs]]
            q0 = normalize_params(self.entities[e], params[sel])
            su, sv = self._scales(e, q0)
            shifts = self._shifts(e)
            best = np.full(len(sel), np.inf)
            todo = np.arange(len(sel))
            for sh in shifts:  # at most 9 (both directions closed); the first is 0
                ex = self._excess(e, q0[todo] + sh, su[todo], sv[todo])
                best[todo] = np.minimum(best[todo], ex)
                todo = todo[ex > 0]
                if todo.size == 0:
                    break
            out[sel] = best
        return out

    def inside(self, ent: npt.ArrayLike, params: npt.ArrayLike, band: bool = True) -> np.ndarray:
        """``(n,)`` bool: ``params`` lies on face ``ent`` (within its band; without
        ``band``: inside the polygons, even-odd, at the wrapped parameter or one period
        either side, as the band test: a face's loops may cross the period's end, as those
        of a periodic B-spline face whose parameters run past its knots' period do)."""
        from nagata_snap.cad.projection import normalize_params

        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        params = np.asarray(params, dtype=float).reshape(len(ent), -1)[:, :2]
        if band:
            return self._within_band(ent, params)
        out = np.ones(len(ent), dtype=bool)
        rows = np.flatnonzero(self.trimmed[ent])
        if self._loop_start is not None and self._domain.ok:
            for i in range(0, len(rows), CHUNK // 8):  # chunks bound the (query, edge) work arrays
                sel = rows[i:i + CHUNK // 8]
                out[sel] = self._inside_all(ent[sel], self._domain.normalize(ent[sel], params[sel]))
            return out
        g = Groups(ent[rows])
        for e, gs in g:  # loop over trimmed entities
            sel = rows[g.order[gs]]
            q = normalize_params(self.entities[e], params[sel])
            res = np.zeros(len(sel), dtype=bool)
            todo = np.arange(len(sel))
            for sh in self._shifts(e):  # at most 9 (both directions closed); the first is 0
                qs = q[todo] + sh
                res[todo] = sum(_crossings(P, qs, slabs) for P, _, _, slabs in self._loops[e]) % 2 == 1
                todo = todo[~res[todo]]
                if todo.size == 0:
                    break
            out[sel] = res
        return out

    def _within_band(self, ent: np.ndarray, params: np.ndarray) -> np.ndarray:
        """:meth:`inside` with the band: ``excess <= 0``, i.e. inside the polygons at some shift
        or within a loop's band at some shift; with every face's loops in one table, all
        queries at once (:meth:`inside` without the band, then :meth:`loop_distance` of the
        queries outside the polygons: the arithmetic of :meth:`_excess` per shift), not face
        by face."""
        if self._loop_start is None or not self._domain.ok:
            return self.excess(ent, params) <= 0.0
        out = np.ones(len(ent), dtype=bool)
        rows = np.flatnonzero(self.trimmed[ent])
        ins = np.zeros(rows.size, dtype=bool)
        for i in range(0, len(rows), CHUNK // 8):  # chunks bound the (query, edge) work arrays
            sel = rows[i:i + CHUNK // 8]  # inside at the wrapped parameter (most points) first
            ins[i:i + CHUNK // 8] = self._inside_all(ent[sel], self._domain.normalize(ent[sel], params[sel]),
                                                     shift=False)
        rest = rows[~ins]
        if rest.size:
            near = rest[~self.inside(ent[rest], params[rest], band=False)]
            out[near] = self.loop_distance(ent[near], params[near]) <= 0.0
        return out

    def _shifted(self, ent: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(qi (k,), Q (k, 2))``: every query of ``q (n, 2)`` (on entities ``ent``) at every shift
        of :meth:`_shifts` (``qi``: the query's row, ascending)."""
        per = self._period[ent]
        closed = np.isfinite(per)
        valid = ((_SHIFTS[None, :, 0] == 0) | closed[:, None, 0]) & ((_SHIFTS[None, :, 1] == 0) | closed[:, None, 1])
        qi, sj = np.nonzero(valid)
        return qi, q[qi] + _SHIFTS[sj] * np.where(closed, per, 0.0)[qi]

    def _distance_all(self, ent: np.ndarray, q: np.ndarray, su: np.ndarray, sv: np.ndarray) -> np.ndarray:
        """``(n,)`` :meth:`loop_distance` (every shift tested) of the wrapped parameters ``q (n, 2)``
        on the trimmed entities ``ent``, through the metric ``su, sv (n,)``: the distance from every
        segment of the entity's loops less its band, all queries at once (compiled:
        :func:`_segment_distances`)."""
        qi, Q = self._shifted(ent, q)
        off, start = self._table.off, self._loop_start
        assert start is not None  # (the caller's condition)
        first = off[start[ent[qi]]]
        cnt = off[start[ent[qi] + 1]] - first  # the entity's loop vertices: contiguous
        best = _segment_distances(Q, first, cnt, su[qi], sv[qi], self._table.P, self._seg, self._band)
        return np.minimum.reduceat(best, np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]]))

    def _inside_all(self, ent: np.ndarray, q: np.ndarray, shift: bool = True) -> np.ndarray:
        """``(n,)`` :meth:`inside` (no band) of the wrapped parameters ``q (n, 2)`` on the trimmed
        entities ``ent (n,)``: the even-odd test of every query at every shift of
        :meth:`_shifts` (without ``shift``: at ``q`` only) against its entity's loops, all at
        once (one :meth:`_SlabTable.crossings`)."""
        qi, Q = self._shifted(ent, q) if shift else (np.arange(len(q)), q)
        # every (shifted query, loop of its entity) pair
        assert self._loop_start is not None  # (the caller's condition)
        start = self._loop_start[ent[qi]]
        nl = self._loop_start[ent[qi] + 1] - start
        pair = np.repeat(np.arange(len(Q)), nl)
        cross = self._table.crossings(np.repeat(start, nl) + ramp(nl), Q[pair])
        odd = np.bincount(pair, weights=cross, minlength=len(Q)).astype(np.int64) % 2 == 1
        return np.bincount(qi[odd], minlength=len(ent)) > 0

    def _sides(self, e: int) -> list[np.ndarray]:
        """Per loop of face ``e``, ``(k,)`` the side of each segment the face is not on: +1 its
        left (the segment's direction turned by +90 degrees in ``(u, v)``), -1 its right, 0
        both or neither (a seam, used twice); from :meth:`inside` (no band) a millionth of
        the segment's length either side of its midpoint, or, where that puts both on one
        side (a segment on the end of an open direction, where the test point beyond it is
        clamped), from the polygons' own even-odd test.  Built once per face."""
        if not hasattr(self, "_side_cache"):
            self._side_cache: dict[int, list[np.ndarray]] = {}
        if e not in self._side_cache:
            loops = self._loops[e]
            P = np.concatenate([lp[0] for lp in loops])
            seg = np.concatenate([lp[1] for lp in loops])
            left = 1e-6 * np.stack([-seg[:, 1], seg[:, 0]], axis=1)
            mid = P + 0.5 * seg
            ent = np.full(2 * len(P), e)
            inl, inr = np.split(self.inside(ent, np.concatenate([mid + left, mid - left]), band=False), 2)
            side = np.where(inr & ~inl, 1, np.where(inl & ~inr, -1, 0)).astype(np.int64)
            # a segment on the end of an open parameter direction: the test point beyond it is
            # clamped onto it; the polygons' own even-odd test (no wrapping, no clamping) tells
            zero = np.flatnonzero(side == 0)
            if zero.size:
                q = np.concatenate([mid[zero] + left[zero], mid[zero] - left[zero]])
                raw = sum(_crossings(Q, q, slabs) for Q, _, _, slabs in loops) % 2 == 1
                inl, inr = np.split(raw, 2)
                side[zero] = np.where(inr & ~inl, 1, np.where(inl & ~inr, -1, 0))
            self._side_cache[e] = np.split(side, np.cumsum([len(lp[0]) for lp in loops])[:-1])
        return self._side_cache[e]

    def _outward(self, e: int, q: np.ndarray, su: np.ndarray, sv: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """At the loop point of face ``e`` nearest each ``q (m, 2)`` (segments between the
        face and the outside only, through the metric ``su, sv (m,)``): ``(distance (m,),
        normal (m, 2))``, the normal the unit outward one in the scaled
        parameters ``(su du, sv dv)`` (at a polygon vertex: the normalised sum of its two
        segments' normals); distance ``inf`` where the face has no such segment."""
        m = len(q)
        best, nrm = np.full(m, np.inf), np.zeros((m, 2))
        s = np.stack([su, sv], axis=1)
        for (P, seg, _, _), side in zip(self._loops[e], self._sides(e), strict=True):  # loop over loops
            bnd = np.flatnonzero(side != 0)
            if bnd.size == 0:
                continue
            step = max(1, CHUNK // bnd.size)
            for i in range(0, m, step):  # chunks bound the (c, k, 2) work arrays
                c = slice(i, i + step)
                ss = seg[None, bnd] * s[c, None, :]
                qq = (q[c, None, :] - P[None, bnd]) * s[c, None, :]
                L2 = np.maximum(np.einsum("ckj,ckj->ck", ss, ss), 1e-300)
                t = np.clip(np.einsum("ckj,ckj->ck", qq, ss) / L2, 0.0, 1.0)
                r = qq - t[:, :, None] * ss
                d = np.einsum("ckj,ckj->ck", r, r)
                j = d.argmin(axis=1)
                rows = np.arange(d.shape[0])
                dj = np.sqrt(d[rows, j])
                near = dj < best[c]
                if not near.any():
                    continue
                k, tj = bnd[j], t[rows, j]
                # the end of the segment the nearest point is at (at a vertex), or none
                other = np.where(tj <= 0.0, (k - 1) % len(P), np.where(tj >= 1.0, (k + 1) % len(P), k))
                n = np.zeros((len(k), 2))
                for kk in (k, other):  # the segment's normal, plus its neighbour's at a vertex
                    sk = seg[kk] * s[c]
                    nk = side[kk, None] * np.stack([-sk[:, 1], sk[:, 0]], axis=1)
                    n += nk / np.maximum(np.linalg.norm(nk, axis=1, keepdims=True), 1e-300)
                n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
                sel = np.arange(m)[c][near]
                best[sel], nrm[sel] = dj[near], n[near]
        return best, nrm

    def outside_by(self, ent: npt.ArrayLike, ref: npt.ArrayLike, params: npt.ArrayLike) -> np.ndarray:
        """``(n,)`` signed distance (length units, to first order) of ``params (n, 2)`` beyond
        the trimming curve through ``ref (n, 2)`` of face ``ent (n,)``: positive outside the
        face, negative inside, along the outward normal of the loop there.

        ``ref`` is a point *on* the true trimming curve (e.g. the parameters of a point of the
        face's edge curve), ``params`` a point near it: the polygon's chord gives only the
        normal's direction, so the sign is exact where the polygon's test is not (within the
        band of a loop).  ``nan`` for an untrimmed face or one whose loops are all seams.
        """
        from nagata_snap.cad.projection import normalize_params

        ent = np.asarray(ent, dtype=np.int64).reshape(-1)
        if len(ent) == 0:
            return np.zeros(0)
        ref = np.asarray(ref, dtype=float).reshape(len(ent), -1)[:, :2]
        params = np.asarray(params, dtype=float).reshape(len(ent), -1)[:, :2]
        out = np.full(len(ent), np.nan)
        rows = np.flatnonzero(self.trimmed[ent])
        g = Groups(ent[rows])
        for e, gs in g:  # loop over trimmed entities
            sel = rows[g.order[gs]]
            r0 = normalize_params(self.entities[e], ref[sel])
            su, sv = self._scales(e, r0)
            best, nrm = np.full(len(sel), np.inf), np.zeros((len(sel), 2))
            for sh in self._shifts(e):  # at most 9; the loop copies one period either side
                d, n = self._outward(e, r0 + sh, su, sv)
                near = d < best
                best[near], nrm[near] = d[near], n[near]
            per = self._period[e]
            off = params[sel] - ref[sel]
            closed = np.isfinite(per)
            off[:, closed] -= per[closed] * np.round(off[:, closed] / per[closed])  # the nearest copy
            val = (off[:, 0] * su * nrm[:, 0] + off[:, 1] * sv * nrm[:, 1])
            out[sel] = np.where(np.isfinite(best), val, np.nan)
        return out

    def loop_points(self, e: int) -> np.ndarray | None:
        """All loop vertices of surface ``e`` ``(k, 2)``, or ``None`` if untrimmed."""
        if not self._loops[e]:
            return None
        return np.concatenate([lp[0] for lp in self._loops[e]])
