"""Small vectorised array idioms used across the pipeline, each written once.

>>> import numpy as np
>>> best_per_group(np.array([0, 0, 1, 2]), np.array([3.0, 1.0, 2.0, 5.0]), 4)
array([ 1,  2,  3, -1])
>>> dot(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([[1.0, 1.0], [1.0, 0.0]]))
array([4., 2.])
>>> row_index(np.array([[2, 1], [0, 5], [2, 1]]))
array([1, 0, 1])
>>> ramp(np.array([2, 0, 3]))
array([0, 1, 0, 1, 2])
>>> Ragged([[4, 5], [], [6]]).take(np.array([2, 0]))
(array([1, 2]), array([6, 4, 5]))
>>> g = Groups(np.array([7, 3, 7, 3, 3]))
>>> [(key, g.order[rows].tolist()) for key, rows in g]
[(3, [1, 3, 4]), (7, [0, 2])]
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import chain

import numpy as np

__all__ = ["best_per_group", "dot", "dot_last", "norms", "float_array", "unique_rows", "row_index", "pack_rows",
           "ramp", "linspaces", "Ragged", "Groups"]


def best_per_group(
    group: np.ndarray,
    score: np.ndarray | tuple[np.ndarray, ...],
    n: int,
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """Row of the lowest ``score`` in each group ``0..n-1``.

    Args:
        group: ``(m,)`` group index of each row, in ``0..n-1``.
        score: ``(m,)`` score of each row, or a tuple of ``(m,)`` keys, the
            most significant first (e.g. ``(~accepted, distance)``).
        n: number of groups.
        mask: ``(m,)`` bool, only these rows compete (default: all).

    Returns:
        ``(n,)`` int64 row index per group, ``-1`` for a group without rows.
        Ties go to the first row.  For the highest score pass ``-score``.
    """
    out = np.full(n, -1, dtype=np.int64)
    rows = np.arange(len(group)) if mask is None else np.flatnonzero(mask)
    if rows.size:
        keys = score if isinstance(score, tuple) else (score,)
        order = rows[np.lexsort((*(np.asarray(k)[rows] for k in reversed(keys)), group[rows]))]
        g, first = np.unique(group[order], return_index=True)
        out[g] = order[first]
    return out


def dot(a: Sequence[np.ndarray] | np.ndarray, b: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
    """Dot product over the first axis: ``a``, ``b`` are ``d`` component arrays (a list or ``(d, ...)``)."""
    out = a[0] * b[0]
    for ai, bi in zip(a[1:], b[1:], strict=True):
        out = out + ai * bi
    return out


def dot_last(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot product over the last axis of ``(..., d)`` arrays."""
    return np.einsum("...i,...i->...", a, b)


def norms(V: np.ndarray) -> np.ndarray:
    """Euclidean norms of the rows of ``V (..., d)``: ``np.linalg.norm(V, axis=-1)`` with less
    overhead, as the square root of a dot product (``vecdot``).  Within rounding of it, not
    always to the last bit (the dot product may sum the squares in another order)."""
    return np.sqrt(np.vecdot(V, V))


def float_array(values) -> np.ndarray | None:
    """``np.array(values, dtype=float)``, or None where numpy cannot make one float array of
    them (ragged, or not numbers): for converting many small values at once, checking them
    one by one only where that fails."""
    try:
        return np.array(values, dtype=float)
    except (ValueError, TypeError):
        return None


def unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct rows of ``a (n, k)`` (float or int): ``(first (m,), inverse (n,), rows (m, k))``.

    As ``np.unique(a, axis=0, return_index=True, return_inverse=True)`` (rows
    compared by value: ``-0.0 == 0.0``; a row with NaN is its own group), but
    sorted by one ``np.lexsort`` of the columns instead of as opaque byte
    strings; rows of narrow non-negative integers (vertex ids) by one sort of
    a packed int64 key each (:func:`_packed`, the same order).
    """
    a = np.ascontiguousarray(a)
    first, inverse = _first_inverse(a)
    return first, inverse, a[first]


def _first_inverse(a: np.ndarray, stable: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``(first (m,), inverse (n,))`` of :func:`unique_rows` for contiguous ``a (n, k)``;
    ``stable=False``: ``first`` is any row of each group (the inverse is the same), by a
    faster sort of the packed keys."""
    n = a.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    key = _packed(a)
    if key is None and a.dtype.kind == "f":
        hashed = _float_first_inverse(a)
        if hashed is not None:
            return hashed
    new = np.empty(n, dtype=bool)
    new[0] = True
    if key is None:
        order = np.lexsort(a.T[::-1])  # stable: equal rows keep their input order
        srt = a[order]
        new[1:] = (srt[1:] != srt[:-1]).any(axis=1)
    else:  # equal keys are equal rows
        order = key.argsort(kind="stable" if stable else None)
        srt = key[order]
        np.not_equal(srt[1:], srt[:-1], out=new[1:])
    inverse = np.empty(n, dtype=np.intp)
    inverse[order] = new.cumsum() - 1
    return order[new], inverse


def _mix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser of ``uint64`` values (in place: every input bit reaches every output bit)."""
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return x


def _float_first_inverse(a: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`_first_inverse` of float rows ``a (n, k)`` by one sort of a 64-bit hash of each
    row instead of a ``lexsort`` of its ``k`` columns, the same ``(first, inverse)``: equal rows
    (``-0.0 == 0.0``) share a hash, so they are contiguous after the sort; the distinct rows
    found (few) are then ranked by a ``lexsort`` of their own, ties (rows with NaN, their own
    groups) by their first row, as the stable sort of all rows would.  None where two
    different rows without NaN share a hash (the caller then sorts the columns)."""
    n = a.shape[0]
    canon = a + 0.0  # -0.0 -> 0.0: the same bits for equal values
    bits = canon.view(np.uint64)
    h = _mix64(bits[:, 0].copy())
    for c in range(1, a.shape[1]):  # loop over the columns
        h ^= bits[:, c]
        _mix64(h)
    order = h.argsort(kind="stable")
    srt = np.take(canon, order, axis=0)  # (faster than canon[order] for rows)
    new = np.empty(n, dtype=bool)
    new[0] = True
    new[1:] = (srt[1:] != srt[:-1]).any(axis=1)  # (a row with NaN differs from every row)
    hs = h[order]
    clash = np.flatnonzero(new[1:] & (hs[1:] == hs[:-1])) + 1
    if clash.size and not np.isnan(srt[clash]).any(axis=1).all():
        return None
    first = order[new]  # the first row of each group (the sort is stable)
    rank = np.empty(first.size, dtype=np.intp)
    rank[np.lexsort((first, *np.take(a, first, axis=0).T[::-1]))] = np.arange(first.size)
    inverse = np.empty(n, dtype=np.intp)
    inverse[order] = rank[new.cumsum() - 1]
    out = np.empty(first.size, dtype=np.intp)
    out[rank] = first
    return out, inverse


def row_index(rows: np.ndarray) -> np.ndarray:
    """``(n,)`` id of each row of ``rows (n, k)`` (equal rows, equal ids; ids ``0..m-1`` in
    the lexicographic order of the rows)."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    return _first_inverse(np.ascontiguousarray(rows), stable=False)[1].astype(np.int64, copy=False)


def _packed(rows: np.ndarray) -> np.ndarray | None:
    """``(n,)`` int64 keys of integer ``rows (n, k)`` with ``k`` fields of equal width (the
    first column most significant: keys sort as the rows), or None (not integers, negative,
    or too wide for 63 bits)."""
    if rows.dtype.kind not in "iu" or rows.ndim != 2:
        return None
    lo, hi = int(rows.min()), int(rows.max())
    bits = hi.bit_length()
    if lo < 0 or bits * rows.shape[1] > 63:
        return None
    return pack_rows(rows, bits)


def pack_rows(rows: np.ndarray, bits: int) -> np.ndarray:
    """``(n,)`` int64 keys of non-negative integer ``rows (n, k)`` below ``2**bits``, ``k bits <= 63``:
    the columns side by side, the first most significant (keys sort as the rows)."""
    key = rows[:, 0].astype(np.int64)
    for c in range(1, rows.shape[1]):  # loop over the columns
        key <<= bits
        key |= rows[:, c]
    return key


def ramp(counts: np.ndarray) -> np.ndarray:
    """``[0..c0-1, 0..c1-1, ...]`` for counts ``c`` (vectorised)."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    return np.arange(total) - np.repeat(starts, counts)


def linspaces(start: np.ndarray, stop: np.ndarray, num: int) -> np.ndarray:
    """``(k, num)``: row ``i`` is ``np.linspace(start[i], stop[i], num)`` to the last bit (its
    formula ``j (stop - start) / (num - 1) + start``, the last ``stop``), for ``num >= 2``,
    without ``linspace``'s cost on arrays (nor its other formula for all rows when one is empty)."""
    start, stop = np.asarray(start, dtype=float), np.asarray(stop, dtype=float)
    y = np.arange(num) * ((stop - start) / (num - 1))[:, None]
    y += start[:, None]
    y[:, -1] = stop
    return y


class Ragged:
    """Integer lists of different lengths as one flat array with offsets (CSR).

    ``take(rows)`` gathers many rows at once without a Python loop over them.
    """

    def __init__(self, lists: Sequence[Sequence[int] | np.ndarray]):
        self.counts = np.array([len(a) for a in lists], dtype=np.int64)
        self.ptr = np.zeros(len(lists) + 1, dtype=np.int64)
        np.cumsum(self.counts, out=self.ptr[1:])
        # the values read once, one after the other (fastest from lists of Python ints)
        self.flat = np.fromiter(chain.from_iterable(lists), dtype=np.int64, count=int(self.ptr[-1]))

    def take(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(counts (k,), values (counts.sum(),))``: the rows ``rows (k,)``, concatenated in order."""
        cnt = self.counts[rows]
        return cnt, self.flat[np.repeat(self.ptr[rows], cnt) + ramp(cnt)]


class Groups:
    """Rows with equal keys (e.g. the CAD entity of each point), contiguous after one sort.

    ``order`` sorts the rows by key (stably); iterating gives each distinct key
    with the ``slice`` of ``order`` that holds its rows.  A loop over the
    groups then works on slices of arrays gathered once (``a[order]``)
    instead of a mask and a gather per group, and :meth:`unsort` puts
    results back in the input order.
    """

    def __init__(self, keys: np.ndarray):
        keys = np.asarray(keys).reshape(-1)
        self.order = keys.argsort(kind="stable")
        srt = keys[self.order]
        n = len(srt)
        cut = (srt[1:] != srt[:-1]).nonzero()[0]  # last row of each group but the last one
        self.keys = srt[[*cut.tolist(), n - 1]] if n else srt
        self.bounds = [0, *(cut + 1).tolist(), n] if n else [0]

    def __len__(self) -> int:
        return len(self.keys)

    def __iter__(self):
        for i, key in enumerate(self.keys.tolist()):
            yield key, slice(self.bounds[i], self.bounds[i + 1])

    def unsort(self, a: np.ndarray) -> np.ndarray:
        """Rows ``a (n, ...)`` in sorted order -> in the input order."""
        out = np.empty_like(a)
        out[self.order] = a
        return out
