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

__all__ = ["exact_sum", "exact_sums", "global_count"]


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
