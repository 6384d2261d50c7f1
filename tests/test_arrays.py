"""nagata_snap.mesh.arrays against plain Python loops (its docstring examples: tests/test_doctests.py)."""

import numpy as np
import pytest

from nagata_snap.mesh.arrays import best_per_group, dot, dot_last, row_index, unique_rows


def _best_by_loop(group, keys, n, mask):
    """Row of the lexicographically smallest key tuple per group, first row on ties."""
    out = [-1] * n
    for row in range(len(group)):
        if not mask[row]:
            continue
        g = group[row]
        key = tuple(k[row] for k in keys)
        if out[g] < 0 or key < tuple(k[out[g]] for k in keys):
            out[g] = row
    return np.array(out)


@pytest.mark.parametrize("seed", range(5))
def test_best_per_group_matches_a_loop(seed):
    rng = np.random.default_rng(seed)
    m, n = 200, 40  # some groups empty, many ties (scores drawn from few values)
    group = rng.integers(0, n, m)
    first, second = rng.integers(0, 2, m).astype(bool), rng.integers(0, 5, m).astype(float)
    mask = rng.random(m) < 0.7
    assert np.array_equal(best_per_group(group, second, n), _best_by_loop(group, [second], n, np.ones(m, bool)))
    assert np.array_equal(best_per_group(group, (first, second), n, mask),
                          _best_by_loop(group, [first, second], n, mask))


def test_best_per_group_without_rows():
    assert np.array_equal(best_per_group(np.array([1, 1]), np.array([0.0, 1.0]), 3, np.zeros(2, bool)),
                          [-1, -1, -1])


def test_dot_products_match_sums():
    rng = np.random.default_rng(0)
    a, b = rng.random((3, 7)), rng.random((3, 7))
    expected = np.array([sum(a[d, i] * b[d, i] for d in range(3)) for i in range(7)])
    assert np.allclose(dot(a, b), expected)
    assert np.allclose(dot(list(a), list(b)), expected)
    assert np.allclose(dot_last(a.T, b.T), expected)


@pytest.mark.parametrize("high", [3, 2**20, 2**21, 2**40])
@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.float64])
def test_row_index_numbers_rows_in_lexicographic_order(high, dtype):
    """Packed integer keys (narrow ids) and the generic path (wide ids, floats) agree with
    sorting the distinct rows as tuples, and ``unique_rows`` with ``np.unique(axis=0)``."""
    rng = np.random.default_rng(high % 97)
    rows = rng.integers(0, high, (300, 3))
    rows[100:200] = rows[:100]  # repeated rows
    rows[0, :] = high - 1  # the widest id present
    rows = rows.astype(dtype)
    ranked = {r: i for i, r in enumerate(sorted({tuple(r) for r in rows.tolist()}))}
    assert np.array_equal(row_index(rows), [ranked[tuple(r)] for r in rows.tolist()])
    first, inverse, distinct = unique_rows(rows)
    want, want_first = np.unique(rows, axis=0, return_index=True)
    assert np.array_equal(first, want_first) and np.array_equal(distinct, want)
    assert np.array_equal(distinct[inverse], rows)


def test_linspaces_are_each_rows_linspace():
    """``linspaces`` gives every row what ``np.linspace`` gives it alone, to the last bit, also
    beside empty rows (where ``np.linspace`` on arrays switches every row to another formula)
    and for a signed zero."""
    from nagata_snap.mesh.arrays import linspaces

    rng = np.random.default_rng(5)
    a = rng.uniform(-10, 10, 500) * 10.0 ** rng.integers(-3, 3, 500)
    b = a + rng.uniform(0, 10, 500)
    b[::7] = a[::7]
    a[5] = b[5] = -0.0
    for n in (2, 3, 17, 65):
        want = np.array([np.linspace(x, y, n) for x, y in zip(a, b, strict=True)])
        assert linspaces(a, b, n).tobytes() == want.tobytes()


def test_ragged_rows_are_the_lists():
    """``Ragged`` from lists of Python ints, integer arrays, tuples and empty rows: its rows
    (``take``, in any order, repeated) are the lists given."""
    from nagata_snap.mesh.arrays import Ragged

    rng = np.random.default_rng(3)
    lists = [rng.integers(-5, 50, rng.integers(0, 6)) for _ in range(40)]
    rows = [a.tolist() if i % 3 == 0 else tuple(a.tolist()) if i % 3 == 1 else a for i, a in enumerate(lists)]
    r = Ragged(rows)
    assert r.flat.dtype == np.int64 and r.ptr.dtype == np.int64 and r.counts.tolist() == [len(a) for a in lists]
    pick = rng.integers(0, 40, 60)
    cnt, vals = r.take(pick)
    assert cnt.tolist() == [len(lists[i]) for i in pick]
    assert vals.tolist() == [v for i in pick for v in lists[i].tolist()]
    empty = Ragged([])
    assert empty.flat.shape == (0,) and empty.ptr.tolist() == [0]


@pytest.mark.parametrize("clash", [False, True])
def test_unique_rows_of_floats_by_hash(monkeypatch, clash):
    """Float rows (found by a hash of each row, ``clash``: every row given the same hash, so
    the columns are sorted instead): ``unique_rows`` as ``np.unique(axis=0)`` on rows without
    signed zeros or NaN, and by hand on rows with them (``-0.0 == 0.0``; a row with NaN is a
    group of its own, ranked after the equal rows without)."""
    from nagata_snap.mesh import arrays

    if clash:
        monkeypatch.setattr(arrays, "_mix64", lambda x: np.multiply(x, 0, out=x))
    rng = np.random.default_rng(11)
    values = rng.normal(size=(40, 6))
    rows = values[rng.integers(0, 40, 500)]
    rows[:, 2] = np.round(rows[:, 2])  # columns that tie
    first, inverse, distinct = unique_rows(rows)
    want, want_first, want_inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    assert np.array_equal(first, want_first) and np.array_equal(distinct, want)
    assert np.array_equal(inverse, want_inverse.reshape(-1))
    rows = np.array([[1.0, np.nan], [0.0, 2.0], [-0.0, 2.0], [1.0, np.nan], [1.0, 3.0], [0.0, 2.0]])
    first, inverse, _ = unique_rows(rows)
    assert first.tolist() == [1, 4, 0, 3] and inverse.tolist() == [2, 0, 0, 3, 1, 0]
