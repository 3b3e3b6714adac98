"""Partition-independent reductions.

A floating-point sum depends on the order of its terms, hence on how particles are spread over
ranks. Anything that can change the trajectory (stage end conditions, servo inputs) or that is
reported (wall loads, energies, discharged mass) is therefore summed *exactly*: the result is the
correctly rounded value of the terms' exact sum, which does not depend on their order or partition.
Serially :func:`math.fsum` gives it; on several ranks each rank reduces its terms to a few partials
(a fixed-point accumulator, below) and only those are gathered, so no rank holds another's terms.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit

__all__ = [
    "exact_sum", "exact_sums", "exact_column_sums", "global_count", "dot_partials", "dot_partials_columns",
    "exact_reduce",
    "exact_accumulator", "exact_add", "exact_add_many", "exact_bins", "exact_partials",
]  # fmt: skip


def exact_sum(comm, values) -> float:
    """Correctly rounded sum of ``values`` over all ranks (a collective call). On several ranks each
    sends only the partials of its terms (:func:`exact_column_sums`), never the terms."""
    local = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if comm.size == 1:
        return math.fsum(local)
    return float(exact_column_sums(comm, local[:, None])[0])


def exact_sums(comm, rows: np.ndarray) -> np.ndarray:
    """Column-wise correctly rounded sums of a (k, m) array over all ranks (collective)."""
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    if rows.ndim == 1:
        rows = rows[:, None]
    if comm.size > 1:
        return exact_column_sums(comm, rows)
    return np.array([math.fsum(rows[:, c]) for c in range(rows.shape[1])])


def global_count(comm, n: int) -> int:
    """Sum of an integer over ranks (exact)."""
    return int(n) if comm.size == 1 else int(comm.allreduce(int(n)))


# ------------------------------------------------------------------ exact partial sums (O(P) reductions)
# A rank's terms are reduced locally to a few doubles whose sum is exactly the sum of the terms.
# Gathering the ranks' lists and applying math.fsum to all of them gives the correctly rounded value of
# the exact global sum, whatever the partition and the order of the terms, while each rank sends a few
# numbers instead of its terms. The local reduction is a long fixed-point accumulator (Kulisch;
# Collange et al.'s "superaccumulator"): every double is an integer multiple of 2⁻¹⁰⁷⁴, so its
# 53-bit significand (read from its bits) is added, split into 32-bit digits, to int64 bins of
# weight 2^(32k − 1130). Integer additions are exact and commutative; each adds < 2³², so 2³¹ terms
# fit before a bin could overflow. In the hopper APGD scene it took a third of the time of
# Shewchuk's expansion (math.fsum's partials), 0.57 s against 1.7 s of 57,479 dot products.
_OFFSET = 1130  # the bit position of 2⁰ in the accumulator: the smallest double, 2⁻¹⁰⁷⁴, sits at p = 56
_BINS = 72  # p ≤ 1024 − 53 + 1130 = 2101: digit bins up to 67, room for the carries


@njit(inline="always")
def _acc_add(acc, bits):
    """acc += x exactly, x a finite nonzero double given by its IEEE bits (int64)."""
    ex = (bits >> 52) & 0x7FF
    mi = bits & 0xFFFFFFFFFFFFF  # |x| = mi 2^(ex − 1075), with the hidden bit for normal numbers
    if ex == 0:
        ex = 1  # subnormal
    else:
        mi |= np.int64(1) << 52
    _acc_add_digits(acc, np.int64(-1) if bits < 0 else np.int64(1), mi, ex)


@njit(inline="always")
def _acc_add_digits(acc, sgn, a, ex):
    """acc += sgn a 2^(ex − 1075) exactly, for 0 ≤ a < 2⁶³: a split into the three 32-bit digits it
    spans (a shifted by up to 31 bits has at most 94)."""
    p = ex - 1075 + _OFFSET  # a 2^(ex − 1075) = a 2^(p − OFFSET)
    k = p >> 5
    s = p & 31
    d0 = (a & ((np.int64(1) << (32 - s)) - 1)) << s
    rest = a >> (32 - s)
    acc[k] += sgn * d0
    acc[k + 1] += sgn * (rest & 0xFFFFFFFF)
    acc[k + 2] += sgn * (rest >> 32)


@njit
def _acc_digits(acc):
    """The accumulator as a list of exact doubles: carries propagated so that every digit has the
    sign of the total (then no digit exceeds the total in magnitude, and none overflows unless the
    total does), each digit times its weight."""
    for k in range(_BINS - 1):
        c = acc[k] >> 32
        acc[k] -= c << 32
        acc[k + 1] += c
    neg = False
    for k in range(_BINS - 1, -1, -1):
        if acc[k] != 0:
            neg = acc[k] < 0
            break
    if neg:  # digits of −total, all ≥ 0 after the carries, then negated
        for k in range(_BINS):
            acc[k] = -acc[k]
        for k in range(_BINS - 1):
            c = acc[k] >> 32
            acc[k] -= c << 32
            acc[k + 1] += c
        for k in range(_BINS):
            acc[k] = -acc[k]
    n = 0
    for k in range(_BINS):
        if acc[k] != 0:
            n += 1
    out = np.empty(n)
    n = 0
    for k in range(_BINS):
        if acc[k] != 0:
            out[n] = math.ldexp(float(acc[k]), 32 * k - _OFFSET)
            n += 1
    return out


@njit(inline="always")
def exact_accumulator():
    """A new exact accumulator for kernels: (acc, scratch, scratch bits), all three to be passed to
    :func:`exact_add`; read it with :func:`exact_partials`."""
    buf = np.empty(1)
    return np.zeros(_BINS, dtype=np.int64), buf, buf.view(np.int64)


@njit(inline="always")
def exact_add(acc, buf, bits, x):
    """acc += x exactly (x a double); returns x if it is not finite (sum those apart, as
    :func:`dot_partials` does), else 0.0.

    No branch touches an array: a zero or non-finite x adds the digits of +0 (nothing). An inlined
    helper whose arrays are used only on some paths keeps numba's reference counting inside the
    caller's loop (atomic operations per term), which made the APGD sums four times slower."""
    buf[0] = x
    b = bits[0]
    finite = math.isfinite(x)
    if not finite:
        b = 0
    _acc_add(acc, b)
    return 0.0 if finite else x


#: exponent bins of :func:`exact_add_many`: one per biased exponent of a double
_EXP_BINS = 2048
#: terms per call of :func:`exact_add_many`: 2⁶³ / 2⁵³, so that no exponent bin can overflow
EXACT_MANY_MAX = 1024


@njit
def exact_bins():
    """The zeroed work array of :func:`exact_add_many` (it is left zeroed after every call)."""
    return np.zeros(_EXP_BINS, dtype=np.int64)


@njit
def exact_add_many(acc, bins, x, m):
    """acc += x[0] + … + x[m − 1] exactly (m ≤ :data:`EXACT_MANY_MAX`; ``x`` contiguous); returns
    the plain sum of the terms that are not finite, in order (0.0 if none), as :func:`exact_add`
    does term by term. The same accumulator value as m calls of :func:`exact_add`.

    Each term's signed significand is first added to the integer bin of its exponent (``bins``, from
    :func:`exact_bins`: one read-modify-write per term instead of three digits); the bins that were
    touched are then added to the accumulator and zeroed. 1024 significands of 53 bits fit in a
    bin."""
    xb = x.view(np.int64)
    lo = _EXP_BINS
    hi = -1
    special = 0.0
    for q in range(m):
        b = xb[q]
        ex = (b >> 52) & 0x7FF
        finite = ex != 0x7FF
        mi = b & 0xFFFFFFFFFFFFF
        mi = (mi | (np.int64(1) << 52)) if ex != 0 else mi  # the hidden bit of normal numbers
        e = max(ex, np.int64(1))  # subnormals share the exponent of the smallest normals
        val = -mi if b < 0 else mi
        val = val if finite else np.int64(0)
        special += 0.0 if finite else x[q]
        bins[e] += val
        used = val != 0
        lo = min(lo, e) if used else lo
        hi = max(hi, e) if used else hi
    for e in range(lo, hi + 1):
        v = bins[e]
        if v == 0:
            continue
        bins[e] = 0
        sgn = np.int64(-1) if v < 0 else np.int64(1)
        _acc_add_digits(acc, sgn, v * sgn, e)  # |v| < 2⁶³: at most 1024 terms below 2⁵³
    return special


@njit(inline="always")
def exact_partials(acc):
    """The accumulator's value as a few doubles whose sum is exact (combine ranks' with
    :func:`exact_reduce`); the accumulator is consumed."""
    return _acc_digits(acc)


@njit
def dot_partials(a, b, rows):
    """Σ_{c in rows} Σ_k a[c, k] b[c, k] (each product rounded once, as ``np.sum(a * b)`` forms
    it) as a few doubles whose sum is exact, and the plain sum of non-finite products (0.0 if none).

    Returns (partials, special); combine ranks' results with :func:`exact_reduce`."""
    acc = np.zeros(_BINS, dtype=np.int64)
    bins = exact_bins()
    ncol = a.shape[1]
    block = max(EXACT_MANY_MAX // max(ncol, 1), 1)  # rows whose products are summed together
    buf = np.empty(block * ncol)
    special = 0.0
    nr = rows.shape[0]
    for q0 in range(0, nr, block):
        m = 0
        for q in range(q0, min(q0 + block, nr)):
            c = rows[q]
            for k in range(ncol):
                buf[m] = a[c, k] * b[c, k]
                m += 1
        special += exact_add_many(acc, bins, buf, m)
    return _acc_digits(acc), special


@njit
def dot_partials_columns(a, b, rows, all_rows):
    """:func:`dot_partials` of arrays held in columns (``a[k, c]``: component k of row c): Σ over
    the rows ``rows`` (every column with ``all_rows``) of Σ_k a[k, c] b[k, c], each product rounded
    once, as a few doubles whose sum is exact, and the plain sum of non-finite products. The same
    result as :func:`dot_partials` of the transposed arrays (the sum is exact, so the order in which
    the products are added does not matter)."""
    acc = np.zeros(_BINS, dtype=np.int64)
    bins = exact_bins()
    ncol = a.shape[0]
    nr = a.shape[1] if all_rows else rows.shape[0]
    block = max(EXACT_MANY_MAX // max(ncol, 1), 1)
    buf = np.empty(block * ncol)
    special = 0.0
    for q0 in range(0, nr, block):
        m = min(block, nr - q0)
        for k in range(ncol):
            ak = a[k]
            bk = b[k]
            o = k * m
            if all_rows:
                for q in range(m):
                    buf[o + q] = ak[q0 + q] * bk[q0 + q]
            else:
                for q in range(m):
                    c = rows[q0 + q]
                    buf[o + q] = ak[c] * bk[c]
        special += exact_add_many(acc, bins, buf, m * ncol)
    return _acc_digits(acc), special


@njit
def column_partials(rows, c):
    """Σ_q rows[q, c] as a few doubles whose sum is exact, and the plain sum of the non-finite terms
    (0.0 if none); combine ranks' results with :func:`exact_reduce`."""
    acc = np.zeros(_BINS, dtype=np.int64)
    bins = exact_bins()
    n = rows.shape[0]
    buf = np.empty(EXACT_MANY_MAX)
    special = 0.0
    for q0 in range(0, n, EXACT_MANY_MAX):
        m = min(EXACT_MANY_MAX, n - q0)
        for q in range(m):
            buf[q] = rows[q0 + q, c]
        special += exact_add_many(acc, bins, buf, m)
    return _acc_digits(acc), special


def exact_column_sums(comm, rows: np.ndarray) -> np.ndarray:
    """Column-wise correctly rounded sums of a (k, m) array over all ranks (collective), as
    :func:`exact_sums` gives them, from each rank's partials: one small gather, whatever k, so no
    rank holds another's terms."""
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    if rows.ndim == 1:
        rows = rows[:, None]
    out, _ = exact_reduce(comm, [column_partials(rows, c) for c in range(rows.shape[1])])
    return np.array(out, dtype=np.float64)


_SHORT = 8  # partials per sum in exact_reduce's first gather


def _gather_packed(comm, lists, maxima, width) -> list[list[float]]:
    """Every rank's (special, count, partials padded to ``width``) per sum, then its maxima."""
    flat: list[float] = []
    for pl, special in lists:
        flat.append(special)
        flat.append(float(len(pl)))
        flat.extend(pl[:width])
        flat.extend([0.0] * (width - min(len(pl), width)))
    flat.extend(float(v) for v in maxima)
    buf = np.array(flat, dtype=np.float64)
    every = np.empty((comm.size, buf.size))
    comm.Allgather(buf, every)
    return every.tolist()


def exact_reduce(comm, sums, maxima=()) -> tuple[list[float], list[float]]:
    """Global values of several local reductions in one collective call.

    ``sums``: (partials, special) pairs from :func:`dot_partials`; each result is the correctly
    rounded exact sum over all ranks (NaN or ±inf if any term was not finite). ``maxima``: local
    floats; each result is the global maximum (NaN if any rank's is NaN). Every result is independent
    of the partition and of the order of the ranks, so every rank takes the same decisions from them."""
    if comm.size == 1:  # the same values as the general path below, without its lists
        out = []
        for part, special in sums:
            if special != 0.0 or special != special:
                out.append(special)
            else:
                try:
                    out.append(math.fsum(part))
                except (OverflowError, ValueError):
                    out.append(math.nan)
        return out, [float(v) for v in maxima]
    # One small fixed-size buffer per rank, gathered with the buffer interface (the pickled gather of
    # Python lists it replaces took ~125 µs on 2 ranks, more than an APGD iteration's kernels; it runs
    # once per line-search trial), and plain Python lists around it (numpy scalar indexing and long
    # buffers cost more than the gather). Per sum: its special value, its number of partials and up to
    # _SHORT of them (an accumulator usually has 2-6 nonzero digits); then the maxima. If any rank has
    # more, every rank sees it in the gathered counts and all gather the full lists again.
    ns = len(sums)
    lists = [
        (part.tolist() if isinstance(part, np.ndarray) else [float(v) for v in part], float(special))
        for part, special in sums
    ]
    width = _SHORT  # the same on every rank (the buffers must have one size)
    ranks = _gather_packed(comm, lists, maxima, width)
    longest = max((int(row[k * (2 + width) + 1]) for row in ranks for k in range(ns)), default=0)
    if longest > width:  # some rank's partials did not fit: all ranks gather again, wider
        width = longest
        ranks = _gather_packed(comm, lists, maxima, width)
    out_sums = []
    for k in range(ns):
        base = k * (2 + width)
        special = 0.0
        for row in ranks:
            special += row[base]  # ±inf and NaN: the same result in any order
        if special != 0.0 or special != special:
            out_sums.append(special)
            continue
        parts: list[float] = []
        for row in ranks:
            parts.extend(row[base + 2 : base + 2 + int(row[base + 1])])
        try:
            out_sums.append(math.fsum(parts))
        except (OverflowError, ValueError):  # the exact sum is beyond the double range
            out_sums.append(math.nan)
    out_max = []
    for k in range(len(maxima)):
        vals = [row[ns * (2 + width) + k] for row in ranks]
        out_max.append(math.nan if any(v != v for v in vals) else max(vals))
    return out_sums, out_max
