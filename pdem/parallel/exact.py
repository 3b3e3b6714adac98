"""Partition-independent reductions.

A floating-point sum depends on the order of its terms, hence on how particles are spread over
ranks. Anything that can change the trajectory (stage end conditions, servo inputs) or that is
reported (wall loads, energies, discharged mass) is therefore summed *exactly*: every rank's terms
are gathered and :func:`math.fsum` returns the correctly rounded value of their exact sum, which does
not depend on their order or partition.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit

__all__ = ["exact_sum", "exact_sums", "global_count", "dot_partials", "exact_reduce"]


def exact_sum(comm, values) -> float:
    """Correctly rounded sum of ``values`` over all ranks (a collective call)."""
    local = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if comm.size == 1:
        return math.fsum(local)
    return math.fsum(np.concatenate(comm.allgather(local)))


def exact_sums(comm, rows: np.ndarray) -> np.ndarray:
    """Column-wise correctly rounded sums of a (k, m) array over all ranks (collective)."""
    rows = np.ascontiguousarray(rows, dtype=np.float64)
    if comm.size > 1:
        rows = np.concatenate(comm.allgather(rows.reshape(-1, rows.shape[-1] if rows.ndim > 1 else 1)))
    if rows.ndim == 1:
        rows = rows[:, None]
    return np.array([math.fsum(rows[:, c]) for c in range(rows.shape[1])])


def global_count(comm, n: int) -> int:
    """Sum of an integer over ranks (exact)."""
    return int(n) if comm.size == 1 else int(comm.allreduce(int(n)))


# ------------------------------------------------------------------ exact partial sums (O(P) reductions)
# A rank's terms are reduced locally to a Shewchuk expansion: a few non-overlapping doubles whose sum
# is exactly the sum of the terms (the ``partials`` of math.fsum). Gathering the ranks' expansions
# and applying math.fsum to all of them gives the correctly rounded value of the exact global sum,
# whatever the partition and the order of the terms, while each rank sends a few numbers instead of
# its terms. A nonoverlapping expansion of doubles has at most ~2,100 components (one per bit of the
# exponent range); in practice a handful.
_EXPANSION_CAP = 2112


@njit(inline="always")
def _grow(part, m, x):
    """Add x to the expansion part[:m] (increasing magnitude, nonoverlapping): Shewchuk's
    grow-expansion with zero elimination, as math.fsum. Returns the new length."""
    i = 0
    for k in range(m):
        y = part[k]
        if abs(x) < abs(y):
            x, y = y, x
        hi = x + y
        lo = y - (hi - x)
        if lo != 0.0:
            part[i] = lo
            i += 1
        x = hi
    part[i] = x
    return i + 1


@njit
def dot_partials(a, b, rows):
    """The exact expansion of Σ_{c in rows} Σ_k a[c, k] b[c, k] (each product rounded once, as
    ``np.sum(a * b)`` forms it) and the plain sum of non-finite products (0.0 if none).

    Returns (partials, special); combine ranks' results with :func:`exact_reduce`."""
    part = np.empty(_EXPANSION_CAP)
    m = 0
    special = 0.0
    for q in range(rows.shape[0]):
        c = rows[q]
        for k in range(a.shape[1]):
            x = a[c, k] * b[c, k]
            if x == 0.0:
                continue
            if not math.isfinite(x):
                special += x
                continue
            m = _grow(part, m, x)
    return part[:m].copy(), special


def exact_reduce(comm, sums, maxima=()) -> tuple[list[float], list[float]]:
    """Global values of several local reductions in one collective call.

    ``sums``: (partials, special) pairs from :func:`dot_partials`; each result is the correctly
    rounded exact sum over all ranks (NaN or ±inf if any term was not finite). ``maxima``: local
    floats; each result is the global maximum (NaN if any rank's is NaN). Every result is independent
    of the partition and of the order of the ranks, so every rank takes the same decisions from them."""
    local = (list(sums), [float(v) for v in maxima])
    every = comm.allgather(local) if comm.size > 1 else [local]
    out_sums = []
    for k in range(len(local[0])):
        special = 0.0
        for s, _ in every:
            special += s[k][1]  # ±inf and NaN: the same result in any order
        if special != 0.0 or special != special:
            out_sums.append(special)
            continue
        try:
            out_sums.append(math.fsum(np.concatenate([s[k][0] for s, _ in every])))
        except OverflowError:  # the exact sum is beyond the double range
            out_sums.append(math.nan)
    out_max = []
    for k in range(len(local[1])):
        vals = [m[k] for _, m in every]
        out_max.append(math.nan if any(v != v for v in vals) else max(vals))
    return out_sums, out_max
