"""The exact reductions that make APGD partition-independent (pdem/parallel/exact.py): a rank's dot
product reduced to a few doubles whose sum is exact (dot_partials), ranks' lists combined by
math.fsum (exact_reduce). The result must be the correctly rounded exact sum for any split of the
terms over ranks and any order."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from pdem.parallel.comm import SerialComm
from pdem.parallel.exact import dot_partials, exact_reduce


class _ThreadComm:
    """k ranks as threads: ``Allgather`` (the buffer interface exact_reduce uses) through shared
    slots and a barrier, so each rank's own call packs its own buffer, as under MPI."""

    def __init__(self, rank, shared):
        self.rank = rank
        self.shared = shared
        self.size = len(shared["slots"])

    def Allgather(self, buf, every):  # noqa: N802 (mpi4py's name)
        slots, barrier = self.shared["slots"], self.shared["barrier"]
        slots[self.rank] = np.array(buf, copy=True)
        barrier.wait()
        for r, b in enumerate(slots):
            every[r] = b  # a size mismatch between ranks fails here, as MPI would
        barrier.wait()


def _on_ranks(k, call):
    """``call(comm, rank)`` on k thread 'ranks' at once; each rank's result."""
    shared = {"slots": [None] * k, "barrier": threading.Barrier(k, timeout=30)}
    results = [None] * k
    errors = []

    def run(r):
        try:
            results[r] = call(_ThreadComm(r, shared), r)
        except Exception as exc:  # reported below
            errors.append(exc)
            shared["barrier"].abort()

    threads = [threading.Thread(target=run, args=(r,)) for r in range(k)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    return results


def _spmd(contributions):
    """exact_reduce(sums, maxima) called on every 'rank' at once; each rank's results."""
    return _on_ranks(len(contributions), lambda comm, r: exact_reduce(comm, *contributions[r]))


def _split_reduce(a, b, rows, k, rng):
    parts = np.array_split(rng.permutation(rows), k)
    locals_ = [([dot_partials(a, b, np.sort(p).astype(np.int64))], [float(p.size)]) for p in parts]
    results = _spmd(locals_) if k > 1 else [exact_reduce(SerialComm(), *locals_[0])]
    assert all(r == results[0] for r in results)  # every rank takes the same decisions
    return results[int(rng.integers(0, k))]


def test_dot_partials_give_the_correctly_rounded_sum_on_any_split():
    rng = np.random.default_rng(3)
    checked = 0
    with np.errstate(over="ignore"):
        for t in range(300):
            n = int(rng.integers(0, 200))
            a = rng.standard_normal((n, 8)) * 10.0 ** rng.integers(-150, 150, (n, 8))
            b = rng.standard_normal((n, 8)) * 10.0 ** rng.integers(-150, 150, (n, 8))
            if t % 5 == 0:  # subnormal terms
                a[:, :2] = 5e-324 * rng.integers(-3, 4, (n, 2))
                b[:, :2] = 1.0
            if t % 7 == 0:  # huge terms that cancel
                a[:, 2] = 1.7e308 * rng.choice([-1.0, 1.0], n)
                b[:, 2] = 1.0
            rows = np.flatnonzero(rng.random(n) < 0.7).astype(np.int64)
            terms = (a[rows] * b[rows]).ravel()
            if not np.all(np.isfinite(terms)):
                continue
            try:
                ref = math.fsum(terms)
            except OverflowError:
                continue
            k = int(rng.integers(1, 5))
            sums, maxima = _split_reduce(a, b, rows, k, rng)
            assert sums[0] == ref, t
            assert maxima[0] == float(max(p.size for p in np.array_split(rows, k))), t
            one, _ = exact_reduce(SerialComm(), [dot_partials(a, b, rows)])
            assert one[0] == ref, t
            checked += 1
    assert checked > 200


def test_non_finite_terms_and_maxima():
    a = np.array([[1.0, np.inf], [2.0, 0.0]])
    b = np.ones((2, 2))
    sums, maxima = exact_reduce(SerialComm(), [dot_partials(a, b, np.arange(2))], [1.0])
    assert sums == [math.inf] and maxima == [1.0]
    a[1, 1] = -np.inf
    sums, _ = exact_reduce(SerialComm(), [dot_partials(a, b, np.arange(2))])
    assert math.isnan(sums[0])
    # a NaN maximum on any rank is the global maximum (as the residual's NaN is in the serial solve)
    for _, maxima in _spmd([([], [math.nan]), ([], [2.0])]):
        assert math.isnan(maxima[0])


def test_long_partials_on_some_ranks_only():
    """A rank whose accumulator has more partials than the first gather carries: every rank sees it
    in the gathered counts and all gather again (the same buffer sizes on every rank)."""
    rng = np.random.default_rng(5)
    terms = rng.standard_normal(40) * 10.0 ** rng.integers(-200, 200, 40)  # many distinct digits
    long_ = dot_partials(terms[:, None], np.ones((40, 1)), np.arange(40, dtype=np.int64))
    short = dot_partials(np.ones((3, 1)), np.ones((3, 1)), np.arange(3, dtype=np.int64))
    assert long_[0].size > 8 >= short[0].size
    results = _spmd([([short, short], [1.0]), ([long_, short], [3.0]), ([short, short], [2.0])])
    for sums, maxima in results:
        assert sums == [math.fsum([*terms, 3.0, 3.0]), 9.0]
        assert maxima == [3.0]



def _hostile_terms(rng, n):
    """Terms over the whole double range: subnormals, signed zeros, the largest doubles of both
    signs, a cancelling pair, and ordinary values."""
    x = rng.normal(size=n) * 10.0 ** rng.integers(-320, 300, n)
    x[::7] = 0.0
    x[::11] = -0.0
    x[5], x[6], x[8] = 5e-324, -2.2250738585072014e-308, 1.7976931348623157e308
    x[9] = -1.7976931348623157e308
    x[12], x[13] = 1e300, -1e300
    return x


@pytest.mark.integration
def test_exact_add_many_is_term_by_term_exact_add():
    """A block added at once (a bin per exponent first) leaves the accumulator with the value of
    the same terms added one by one: the same partials, the same plain sum of non-finite terms; the
    bins are zeroed again."""
    from numba import njit

    from pdem.parallel.exact import (
        EXACT_MANY_MAX,
        exact_accumulator,
        exact_add,
        exact_add_many,
        exact_bins,
        exact_partials,
    )  # fmt: skip

    @njit
    def one_by_one(x):
        a, b, i = exact_accumulator()
        sp = 0.0
        for q in range(x.shape[0]):
            sp += exact_add(a, b, i, x[q])
        return exact_partials(a), sp

    @njit
    def in_blocks(x, bins, block):
        a, _b, _i = exact_accumulator()
        sp = 0.0
        for q0 in range(0, x.shape[0], block):
            m = min(block, x.shape[0] - q0)
            sp += exact_add_many(a, bins, x[q0 : q0 + m], m)
        return exact_partials(a), sp

    rng = np.random.default_rng(7)
    bins = exact_bins()
    big = np.full(3 * EXACT_MANY_MAX, 1.7976931348623157e308)  # full bins of one exponent
    big[EXACT_MANY_MAX:] *= -1.0
    specials = rng.normal(size=3000)
    specials[[10, 20, 30]] = np.inf, -np.inf, np.nan
    cases = [_hostile_terms(rng, 13_000), rng.normal(size=13_000), big, rng.normal(scale=1e-310, size=5000),
             specials, np.zeros(100)]  # fmt: skip
    for x in cases:
        want, want_special = one_by_one(x)
        for block in (1, 500, EXACT_MANY_MAX):
            got, got_special = in_blocks(x, bins, block)
            assert np.array_equal(got, want)
            assert got_special == want_special or (math.isnan(got_special) and math.isnan(want_special))
            assert not bins.any()
    full = np.full(EXACT_MANY_MAX, 1.7976931348623157e308)  # the largest significand, 1024 times
    got, _ = in_blocks(full, bins, EXACT_MANY_MAX)
    assert np.array_equal(got, one_by_one(full)[0])  # the bin held 1024 × (2⁵³ − 1) without wrapping


def test_dot_partials_in_blocks_on_hostile_terms():
    """dot_partials (blocks of products through exact_add_many) against math.fsum of the products."""
    rng = np.random.default_rng(8)
    a = _hostile_terms(rng, 4 * 3001).reshape(-1, 4) * 1e-8
    b = rng.normal(size=a.shape)
    rows = rng.permutation(a.shape[0])[:2500]
    part, special = dot_partials(a, b, rows)
    assert special == 0.0
    assert math.fsum(part) == math.fsum((a[rows] * b[rows]).ravel())


@pytest.mark.parametrize("width", [1, 4, 8])
def test_dot_partials_of_columns_are_those_of_the_rows(width):
    """APGD's arrays in columns (a[k, c]): the same exact partials as the rows' dot_partials, over a
    subset of the rows (sorted, as _counted_rows gives them) or all of them; non-finite products go
    to the plain sum alike."""
    from pdem.parallel.exact import dot_partials_columns

    rng = np.random.default_rng(9 + width)
    a = _hostile_terms(rng, width * 2999).reshape(-1, width) * 1e-8
    b = rng.normal(size=a.shape)
    ac, bc = np.ascontiguousarray(a.T), np.ascontiguousarray(b.T)
    some = np.sort(rng.permutation(a.shape[0])[:2500])
    for rows, all_rows in ((some, False), (np.arange(a.shape[0]), True)):
        rows = rows.astype(np.int64)
        part, special = dot_partials_columns(ac, bc, rows, all_rows)
        ref, ref_special = dot_partials(a, b, rows)
        assert special == ref_special == 0.0
        assert math.fsum(part) == math.fsum(ref) == math.fsum((a[rows] * b[rows]).ravel())
    a[7, 0] = np.inf
    part, special = dot_partials_columns(np.ascontiguousarray(a.T), bc, np.arange(a.shape[0]), True)
    assert special == dot_partials(a, b, np.arange(a.shape[0]))[1] and math.isinf(special)


def test_exact_column_sums_are_the_correctly_rounded_column_sums():
    """``exact_column_sums`` (partials per column, one small reduction) gives each column's
    ``math.fsum``: terms over 600 binary orders of magnitude that cancel, more terms than one batch
    of the accumulator, a column of zeros, and non-finite terms (NaN wins; +inf alone gives +inf)."""
    from pdem.parallel.exact import exact_column_sums

    rng = np.random.default_rng(7)
    n = 5000
    big = rng.standard_normal(n) * np.exp2(rng.integers(-300, 300, n))
    rows = np.stack([big, -big + rng.standard_normal(n) * 1e-3, np.zeros(n), rng.standard_normal(n)], axis=1)
    got = exact_column_sums(SerialComm(), rows)
    assert [float(v) for v in got] == [math.fsum(rows[:, c]) for c in range(4)]
    bad = rows.copy()
    bad[10, 0] = np.inf
    bad[20, 3] = np.nan
    got = exact_column_sums(SerialComm(), bad)
    assert got[0] == np.inf and math.isnan(got[3]) and got[1] == math.fsum(rows[:, 1])


@pytest.mark.parametrize("k", [2, 3])
def test_exact_sum_over_ranks_sends_partials_and_gives_the_fsum_of_all_terms(k):
    """``exact_sum`` / ``exact_sums`` on several ranks reduce each rank's terms to partials (no rank
    receives another's terms) and give ``math.fsum`` of all of them, bit for bit, on any split."""
    from pdem.parallel.exact import exact_sum, exact_sums

    rng = np.random.default_rng(11 + k)
    n = 3000
    big = rng.standard_normal(n) * np.exp2(rng.integers(-200, 200, n))
    terms = np.concatenate([big, -big[::-1] + rng.standard_normal(n) * 1e-9])
    rows = np.stack([terms, rng.standard_normal(2 * n)], axis=1)
    order = rng.permutation(2 * n)
    cuts = np.sort(rng.choice(np.arange(1, 2 * n), k - 1, replace=False))
    shares = np.split(order, cuts)
    results = _on_ranks(
        k, lambda comm, r: (exact_sum(comm, terms[shares[r]]), exact_sums(comm, rows[shares[r]]))
    )
    for one, cols in results:
        assert one == math.fsum(terms)
        assert [float(v) for v in cols] == [math.fsum(rows[:, 0]), math.fsum(rows[:, 1])]
