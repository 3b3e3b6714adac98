"""The work model of one rank: what its particles cost, measured and modelled, and the migration
that rebalances the subdomains when the ranks' work is uneven.

The cut planes of :class:`~pdem.parallel.decomposition.Decomposition` follow per-particle weights.
A rank's work since the last rebuild is its measured contact time (``add_time``); per particle it is
modelled from the last force evaluation (:meth:`WorkModel.particle_work`: a particle, its listed
pairs, its touching contacts) and scaled to that measured time, so that the balance is on time.
Weights are modelled only when a rebalance is due (modelling them at every rebuild had cost ~0.7 ms
per rebuild on the DEM-C hopper, which rebuilds at every step).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["WorkModel"]


class WorkModel:
    """The work model of ``sim``'s rank (``sim.work``)."""

    # cost model of a step, fitted to per-rank kernel times on the 20k column collapse (units of ~5 ns):
    # a particle 2 (integration, bookkeeping: ~11 ns), a neighbour-list pair 2 (~12 ns), a touching
    # contact 10 more (~51 ns); pair costs are split between the pair's two ends
    W_PARTICLE, W_PAIR_END, W_TOUCH_END = 2, 1, 5

    def __init__(self, sim: Any) -> None:
        self.sim = sim
        self.force_time = 0.0  # contact time measured since the last rebuild [s]
        self._weight_ids = np.zeros(0, dtype=np.int64)
        self._weights = np.zeros(0, dtype=np.int64)

    def add_time(self, seconds: float) -> None:
        self.force_time += seconds

    def particle_work(self) -> np.ndarray:
        """Estimated work of the last force evaluation per owned particle (cost-model units)."""
        p = self.sim.particles
        n = p.n_owned
        w = np.full(n, self.W_PARTICLE, dtype=np.int64)
        cs = self.sim.contact_store
        if cs.pi.size and cs.force.shape[0] == cs.pi.size and n:
            touching = np.any(cs.force != 0.0, axis=1)
            for ends, inc in (
                (np.concatenate([cs.pi, cs.pj]), self.W_PAIR_END),
                (np.concatenate([cs.pi[touching], cs.pj[touching]]), self.W_TOUCH_END),
            ):
                ends = ends[ends < n]
                w += inc * np.bincount(ends, minlength=n)  # integers: as np.add.at, ~10x faster
        return w

    def rank_work(self) -> float:
        """This rank's work since the last rebuild: its measured force time, or (none measured yet)
        the modelled work of its particles."""
        return self.force_time if self.force_time > 0.0 else float(self.particle_work().sum())

    def note_weights(self) -> None:
        """Note the work of the last force evaluation per owned particle (by id, which survives the
        migration that follows), scaled to this rank's measured force time since the last rebuild."""
        p = self.sim.particles
        n = p.n_owned
        self._weight_ids = p.id[:n].copy()
        w = self.particle_work()
        total = float(w.sum())
        if self.force_time > 0.0 and total > 0.0:
            w = np.maximum(np.rint(w * (1e7 * self.force_time / total)), 1).astype(np.int64)
        self._weights = w

    def weights_now(self) -> np.ndarray:
        """Weights of the particles owned after migration (those received use the base weight)."""
        p = self.sim.particles
        n = p.n_owned
        w = np.full(n, self.W_PARTICLE, dtype=np.int64)
        if self._weight_ids.size:
            order = np.argsort(self._weight_ids)
            sorted_ids = self._weight_ids[order]
            pos = np.searchsorted(sorted_ids, p.id[:n])
            ok = (pos < sorted_ids.size) & (sorted_ids[np.minimum(pos, sorted_ids.size - 1)] == p.id[:n])
            w[ok] = self._weights[order[pos[ok]]]
        return w

    def migrate(self) -> None:
        """Move particles to the ranks that own their positions (collective): first rebalancing the
        cut planes when the ranks' work since the last rebuild is uneven (above
        ``sim.balance_threshold``), then migrating again."""
        from .exchange import migrate

        sim = self.sim
        decomp = sim.decomposition
        due = False
        if sim.comm.size > 1 and sim.balance_threshold:
            due = decomp.imbalance(self.rank_work()) > sim.balance_threshold
            if due:
                self.note_weights()
        self.force_time = 0.0
        migrate(sim)
        if due:
            decomp.rebalance(sim.particles.x[: sim.particles.n_owned], self.weights_now())
            migrate(sim)
