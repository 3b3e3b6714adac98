"""Particles taken out during a run (outflows, sinks), and the global count they are part of.

A :class:`Removals` belongs to one :class:`~pdem.simulation.Simulation` (``sim.removals``).
Removed particles stop interacting at once (marked REMOVED: no mass, not integrated, left out of
every query) and leave the storage at the next neighbour-list rebuild (:meth:`Removals.compact`);
meanwhile they are parked out of every other particle's reach (:meth:`Removals.park`), so the list
stays valid without a rebuild. Their ids are kept: under MPI every rebuild checks that the owned
particles of all ranks and the removed ones add up to all particles ever added
(:meth:`Removals.check_count`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import LostParticleError
from ..parallel.comm import all_sum_int_array
from .particles import REMOVED

__all__ = ["Removals"]


class Removals:
    """The removed particles of ``sim``'s rank: their ids (``removed_ids``, one array per removal;
    ``n_removed`` in all), the removed rows still in the storage (``n_parked``), and the number of
    particles the ranks hold between them, removed ones included (``n_expected``; kept under MPI or
    periodic, from the decomposition on)."""

    def __init__(self, sim: Any) -> None:
        self.sim = sim
        self.removed_ids: list[np.ndarray] = []
        self.n_removed = 0  # Σ len(removed_ids), kept as the lists grow (one per removal)
        self.n_parked = 0  # removed rows still in the storage (parked until the next rebuild)
        self.n_expected = 0

    def remove(self, mask: np.ndarray) -> tuple[int, float]:
        """Remove the owned particles where ``mask`` is true (``Simulation.remove_particles``);
        returns (count, mass)."""
        p = self.sim.particles
        n = p.n_owned
        mask = np.asarray(mask, dtype=bool)[:n] & (p.motion[:n] != REMOVED)
        count = int(mask.sum())
        if count == 0:
            return 0, 0.0
        mass = math.fsum(p.mass[:n][mask])
        self.removed_ids.append(p.id[:n][mask].copy())
        self.n_removed += count
        idx = np.flatnonzero(mask)
        p.motion[idx] = REMOVED
        p.inv_m[idx] = 0.0
        p.inv_i[idx] = 0.0
        p.v[idx] = 0.0
        p.w[idx] = 0.0
        self.park(idx)
        return count, mass

    def park(self, idx: np.ndarray) -> None:
        """Move removed rows ``idx`` out of reach until the next rebuild compacts them away.

        Between rebuilds a particle can only meet the partners listed at the last build, all within
        a ghost width W of it. Parked at x + (1000 W + 3 W id) along x, each is ~1000 W from them
        and at least 2 W from every other parked particle, so no pair touches or enters DEM-C's
        envelope (the ghost copies on other ranks follow at the next forward, before any force is
        computed). ``x_build`` moves with it, so the rebuild test does not see the jump; the walls
        drop it from their candidates (a wall moved by its load would otherwise meet it)."""
        sim = self.sim
        p = sim.particles
        w = float(sim.neighbours.ghost_width)
        p.x[idx, 0] += 1000.0 * w + 3.0 * w * p.id[idx].astype(np.float64)
        p.x_build[idx] = p.x[idx]
        self.n_parked += idx.size
        gone = np.zeros(p.n, dtype=bool)
        gone[idx] = True
        sim.contact_store.drop_wall_candidates(gone)

    def compact(self) -> None:
        """Drop REMOVED particles from the storage (at a rebuild, before migration)."""
        p = self.sim.particles
        n = p.n_owned
        gone = p.motion[:n] == REMOVED
        k = int(gone.sum())
        self.n_parked = 0
        if k == 0:
            return
        p.n_ghost = 0
        p.permute(np.concatenate([np.flatnonzero(~gone), np.flatnonzero(gone)]))
        p.n_owned = n - k

    def _first_missing(self) -> np.ndarray:
        """The smallest id no rank holds or removed, as a 0- or 1-element array (collective): ids
        counted in blocks with one integer reduction, then only the first short block's ids gathered,
        so no rank receives every id."""
        sim = self.sim
        held = np.concatenate([sim.particles.id[: sim.particles.n_owned], *self.removed_ids])
        top = max(int(sim.next_id), 1)
        blocks = min(4096, top)
        edges = np.linspace(0, top, blocks + 1).astype(np.int64)
        counts = np.histogram(held, bins=edges)[0].astype(np.int64)
        counts = all_sum_int_array(sim.comm, counts)
        short = np.flatnonzero(counts < np.diff(edges))
        if not short.size:
            return np.zeros(0, np.int64)
        lo, hi = int(edges[short[0]]), int(edges[short[0] + 1])
        mine = held[(held >= lo) & (held < hi)]
        every = np.concatenate(sim.comm.allgather(mine)) if sim.comm.size > 1 else mine
        return np.setdiff1d(np.arange(lo, hi), every)[:1]

    def check_count(self) -> None:
        """No particle may be lost between ranks: owned counts must add up (collective)."""
        sim = self.sim
        # one reduction of both counts (a hopper removes grains in hundreds of small batches: summing
        # their lengths in Python at every rebuild had cost 4 % of its 2-rank run)
        counts = np.array([sim.particles.n_owned, self.n_removed], dtype=np.int64)
        total, removed = (int(c) for c in all_sum_int_array(sim.comm, counts))
        if total + removed == self.n_expected:
            return
        missing = self._first_missing()
        raise LostParticleError(
            f"{self.n_expected - total - removed} particle(s) lost between ranks at step {sim.step_count} "
            f"(first id {missing[0] if missing.size else '?'}); this is a bug in the exchange, "
            "please report it"
        )
