"""The exact reductions that make APGD partition-independent (pdem/parallel/exact.py): a rank's dot
product reduced to a few doubles whose sum is exact (dot_partials), ranks' lists combined by
math.fsum (exact_reduce). The result must be the correctly rounded exact sum for any split of the
terms over ranks and any order."""

from __future__ import annotations

import math
import threading

import numpy as np

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


def _spmd(contributions):
    """exact_reduce(sums, maxima) called on every 'rank' at once; each rank's results."""
    k = len(contributions)
    shared = {"slots": [None] * k, "barrier": threading.Barrier(k, timeout=30)}
    results = [None] * k
    errors = []

    def run(r):
        try:
            results[r] = exact_reduce(_ThreadComm(r, shared), *contributions[r])
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

