"""The exact reductions that make APGD partition-independent (pdem/parallel/exact.py): a rank's dot
product reduced to a few doubles whose sum is exact (dot_partials), ranks' lists combined by
math.fsum (exact_reduce). The result must be the correctly rounded exact sum for any split of the
terms over ranks and any order."""

from __future__ import annotations

import math

import numpy as np

from pdem.parallel.comm import SerialComm
from pdem.parallel.exact import dot_partials, exact_reduce


class _Gathered:
    """A stand-in communicator whose allgather returns the given ranks' contributions."""

    def __init__(self, others):
        self.others = others
        self.size = len(others) + 1

    def allgather(self, local):
        return [*self.others, local]


def _split_reduce(a, b, rows, k, rng):
    parts = np.array_split(rng.permutation(rows), k)
    locals_ = [([dot_partials(a, b, np.sort(p).astype(np.int64))], [float(p.size)]) for p in parts]
    order = rng.permutation(k)
    others = [locals_[i] for i in order[1:]]
    mine = locals_[order[0]]
    return exact_reduce(_Gathered(others), mine[0], mine[1])


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
    _, maxima = exact_reduce(_Gathered([([], [math.nan])]), [], [2.0])
    assert math.isnan(maxima[0])
