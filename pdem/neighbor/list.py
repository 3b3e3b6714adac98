"""The neighbour list of a simulation: its reach (skin and envelope), the storage order, the pair
schedule, the rebuild test and the rebuild, and the ghost forward.

A :class:`NeighbourList` belongs to one :class:`~pdem.simulation.Simulation` (``sim.neighbours``) and
reads its particles, walls, contact store, decomposition and periodic box. The contact method says
what it needs of the list as data (:class:`~pdem.contact.law.ListNeeds`, ``law.list_needs``), never
by its name:

* ``order = "storage"`` (DEM-P): the storage is sorted by cells in space, at the first rebuild and
  whenever the listed pairs have drifted apart in it, and the pair loop follows the storage when a
  loop in id order would jump through it; ``"id"`` (DEM-C): storage and pairs stay in id order.
* ``auto_skin``: with no skin given, the skin is chosen at every rebuild from the fastest grain.
* ``envelope``: the method has a collision envelope (``law.envelope(radii)``) that the list reaches
  beyond touching plus skin.

Results never depend on the list: it holds every pair within ``skin + envelope`` at its build and is
rebuilt before any particle (or wall) may have moved more than the skin allows; non-touching pairs
contribute nothing and contact history is keyed by ids.

The rebuild (collective) compacts removed particles, wraps positions into the periodic box, migrates
particles between ranks (rebalancing first when the ranks' measured work is uneven), orders the
storage, exchanges ghosts, builds the pair list on a cell grid (pairs ordered by id pair) and the
wall candidate lists.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..errors import InputError
from ..parallel.comm import all_max, any_ranks
from ..parallel.exact import exact_sum, global_count
from . import _kernels as nk

__all__ = ["NeighbourList", "SKIN_STEPS", "SKIN_MIN", "SKIN_MAX", "SCHEDULE_JUMPS", "SPREAD_SLACK"]

#: the automatic skin (no ``run.skin``): room for this many steps of the fastest grain, between these
#: fractions of the mean diameter (NeighbourList.choose_skin)
SKIN_STEPS, SKIN_MIN, SKIN_MAX = 25, 0.1, 0.4
# storage-ordered pair loop: follow the storage instead of the ids when a loop in id order would jump
# by more than SCHEDULE_JUMPS rows per pair; sort the storage again when the pairs' mean storage
# distance exceeds twice (+ SPREAD_SLACK rows) its value after the last sort
SCHEDULE_JUMPS, SPREAD_SLACK = 16.0, 64.0


class NeighbourList:
    """The neighbour list of ``sim`` (see the module doc)."""

    def __init__(self, sim: Any) -> None:
        self.sim = sim
        #: the skin [m] (None: chosen at the next preparation)
        self.skin: float | None = None
        #: the skin of the lists built from now on when a method narrows it (set_reach); None: skin
        self.skin_override: float | None = None
        self.auto = False  # the skin follows the fastest grain (choose_skin)
        self.skin_chosen: float | None = None  # the last skin chosen automatically
        self.skin_range = (0.0, 0.0)
        self.envelope = 0.0  # how far beyond touching plus skin the list reaches [m]
        self.reach = 0.0  # skin + envelope: pairs this far apart are listed
        self.ghost_width_base = 0.0  # 2 r_max
        self.ghost_width = 0.0  # 2 r_max + reach
        self.spread_ref = -1.0  # mean storage distance of the pairs after the last sort (< 0: sort due)
        self.n_rebuilds = 0
        self.n_storage_sorts = 0  # spatial sorts of the storage (order_storage)
        self.force_rebuild = False

    @property
    def needs(self) -> Any:
        return self.sim.law.list_needs

    @property
    def follows_storage(self) -> bool:
        """Whether the pair loop follows the storage (``order = "storage"``) rather than the ids."""
        return self.needs.order == "storage"

    # ------------------------------------------------------------------ reach
    def configure(self, r_max: float, n: int) -> None:
        """At a preparation: the skin (chosen when none was given or the last was chosen), the
        envelope and the ghost width for particles up to ``r_max`` (collective)."""
        sim = self.sim
        p = sim.particles
        # no skin given: a method that allows it (and no periodic images) chooses it at every
        # rebuild from the fastest grain (choose_skin); a given skin and periodic boxes keep one. A
        # later preparation (particles or walls added) chooses again, unless the skin was set since
        auto = self.skin is None or self.skin == self.skin_chosen
        self.auto = auto and self.needs.auto_skin and sim.box is None
        if auto:
            d_mean = 2.0 * exact_sum(sim.comm, p.r[:n]) / max(global_count(sim.comm, n), 1)
            self.skin = self.skin_chosen = SKIN_MIN * d_mean
            self.skin_range = (SKIN_MIN * d_mean, SKIN_MAX * d_mean)
        if not (self.skin >= 0 and math.isfinite(self.skin)):
            raise InputError(f"skin = {self.skin!r} is invalid; give a non-negative distance in metres")
        if self.needs.envelope:
            # the list's reach may be wider than this step's envelope (the method keeps it ≥)
            self.envelope = max(self.envelope, sim.envelope_base)
        else:
            self.envelope = 0.0
        self.skin_override = None
        self.reach = self.skin + self.envelope
        self.ghost_width_base = 2.0 * r_max
        self.ghost_width = self.ghost_width_base + self.reach

    def fit_skin_range(self) -> None:
        """The automatic skin: the widest the subdomains leave room for, kept through rebalances."""
        if not self.auto:
            return
        decomp = self.sim.decomposition
        lo, hi = self.skin_range
        room = decomp.narrowest() - self.ghost_width_base - self.envelope
        hi = max(lo, min(hi, room))
        self.skin_range = (lo, hi)
        decomp.widen(self.ghost_width_base + hi + self.envelope)

    def choose_skin(self) -> None:
        """The automatic skin: room for SKIN_STEPS steps of the fastest grain, 2 × SKIN_STEPS × v_max
        × dt, within ``skin_range`` (0.1–0.4 of the mean diameter). The same on every rank (v_max is
        an exact maximum); results do not depend on it, only how often the list is rebuilt and how
        long it is. Measured (docs/deck.md): the hopper as fast as with the best fixed skin, a static
        bed as fast as with the smallest."""
        sim = self.sim
        p = sim.particles
        n = p.n_owned
        v2 = float(np.max(np.einsum("ij,ij->i", p.v[:n], p.v[:n]))) if n else 0.0
        v_max = math.sqrt(all_max(sim.comm, v2))
        lo, hi = self.skin_range
        skin = min(max(2.0 * SKIN_STEPS * v_max * sim.dt, lo), hi)
        self.skin = self.skin_chosen = skin
        self.reach = skin + self.envelope
        self.ghost_width = self.ghost_width_base + self.reach

    def set_reach(self, envelope: float, force: bool = True, skin: float | None = None) -> None:
        """Reach ``skin + envelope`` (see :meth:`pdem.simulation.Simulation.set_list_reach`)."""
        if skin is not None:
            if not (skin >= 0.0 and math.isfinite(skin)):
                raise InputError(f"set_list_reach: skin = {skin!r} is invalid; give a non-negative distance")
            self.skin_override = None if skin == self.skin else float(skin)
        self.envelope = envelope
        self.reach = (self.skin if self.skin_override is None else self.skin_override) + envelope
        self.ghost_width = self.ghost_width_base + self.reach
        if self.sim.decomposition is not None:
            self.sim.decomposition.widen(self.ghost_width)
        if force:
            self.force_rebuild = True

    # ------------------------------------------------------------------ the rebuild test
    def needs_rebuild(self, pending: int | None) -> tuple[bool, bool, bool]:
        """(rebuild due, a non-finite position, the last step unstable) on every rank alike, in one
        reduction (collective). ``pending``: a deferred step's kernel flags (None: none), which
        ride on the same reduction."""
        sim = self.sim
        p = sim.particles
        disp = math.sqrt(nk.max_displacement2(p.x, p.x_build, p.n_owned))
        walls = sim.contact_store.walls
        moving = sim.contact_store.moving
        wall_disp = max((walls[k].displacement_since_build() for k in moving), default=0.0)
        skin = self.skin if self.skin_override is None else self.skin_override
        need = self.force_rebuild or 2.0 * disp > skin or disp + wall_disp > skin
        # a non-finite position (max_displacement2 gives inf for it) cannot be binned: the caller
        # stops as a non-finite state instead of rebuilding the list without the particle
        lost = not math.isfinite(disp)
        if pending is None:
            need, lost = any_ranks(sim.comm, need, lost)
            return need, lost, False
        need, unstable = any_ranks(sim.comm, need, pending != 0 or lost)
        return need, lost, unstable

    # ------------------------------------------------------------------ the rebuild
    def cell_grid(self, x: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """(lo, 1/cell, dims) of the cell grid over positions ``x``: cells of the largest pair reach
        (2 r_max + reach), widened by 1.26× until there are at most 4 n + 1000 of them."""
        lo, hi = nk.bounds(x, x.shape[0])
        lo -= 1e-12
        hi += 1e-12
        cell = 2.0 * float(r.max()) + self.reach
        ext = np.maximum(hi - lo, cell)
        while True:
            dims = np.maximum(np.minimum(ext / cell, 2.0**20).astype(np.int64), 1)  # far-apart grains
            if int(np.prod(dims)) <= 4 * x.shape[0] + 1000:
                break
            cell *= 1.26
        return lo, 1.0 / cell, dims

    def order_storage(self) -> None:
        """Storage order of the owned particles (results do not depend on it; only memory locality
        does). ``order = "storage"``: sorted by cells in space, at the first rebuild and whenever
        pairs have drifted apart in storage (the mean storage distance of the listed pairs more
        than doubled since the last sort); the pair loop follows the storage
        (:meth:`ContactStore.set_pairs`). ``order = "id"``: the loops run in id order, so the
        storage is kept in id order (migration appends received particles)."""
        sim = self.sim
        p = sim.particles
        n = p.n_owned
        if self.follows_storage:
            pi, pj = sim.contact_store.pi, sim.contact_store.pj
            due = self.spread_ref < 0.0 or (
                pi.size and nk.partner_spread(pi, pj) > 2.0 * self.spread_ref + SPREAD_SLACK
            )
            if due and n > 1:
                lo, inv_cell, dims = self.cell_grid(p.x[:n], p.r[:n])
                _, items = nk.bin_particles(p.x[:n], n, lo, inv_cell, dims)
                p.permute(items)
                self.spread_ref = -1.0  # measured on the next list
                self.n_storage_sorts += 1
            return
        ids = p.id[:n]
        if ids.size > 1 and np.any(ids[1:] < ids[:-1]):
            p.permute(np.argsort(ids, kind="stable"))

    def rebuild(self) -> None:
        """Rebuild (collective; see the module doc)."""
        sim = self.sim
        p = sim.particles
        if self.auto:
            self.choose_skin()
        sim.compact_removed()
        if sim.box is not None:
            p.n_ghost = 0
            sim.box.wrap(p.x[: p.n_owned])  # exact, so it does not matter at which rebuild it happens
        if sim.decomposition is not None:
            from ..parallel.exchange import borders

            sim.work.migrate()  # rebalancing first when the ranks' work is uneven
            sim.check_particle_count()
            self.order_storage()
            borders(sim, self.ghost_width)
        else:
            self.order_storage()
        self._build_pairs()
        self._build_wall_candidates()
        self.n_rebuilds += 1

    def _build_pairs(self) -> None:
        sim = self.sim
        p = sim.particles
        n = p.n
        x = p.x
        r = p.r
        store = sim.contact_store
        if n:
            lo, inv_cell, dims = self.cell_grid(x, r)
            while True:
                pi, pj, count = nk.build_pairs(
                    x, r, p.id, p.n_owned, n, self.reach, lo, inv_cell, dims, store.pair_capacity
                )
                if count <= store.pair_capacity:
                    break
                store.pair_capacity = int(count * 1.3) + 64
            pi = pi[:count].copy()
            pj = pj[:count].copy()
        else:
            pi = pj = np.zeros(0, dtype=np.int64)
        keys = nk.pair_keys(pi, pj, p.id)
        if keys.size > 1 and np.any(keys[1:] < keys[:-1]):
            # a particle stored more than once (its periodic images) interleaves its pairs with those
            # of its copies; a stable sort by key restores (id_lo, id_hi) order. Each owned particle
            # meets each partner once (L >= 2 cutoffs), so its contributions stay in partner-id order
            order = np.argsort(keys, kind="stable")
            pi, pj, keys = pi[order], pj[order], keys[order]
        schedule = -1
        if self.follows_storage and nk.row_jumps(pi) > SCHEDULE_JUMPS:
            schedule = n  # the list in id order would jump through the storage: follow the storage
        store.set_pairs(pi, pj, keys, schedule)
        if self.follows_storage and self.spread_ref < 0.0:
            self.spread_ref = nk.partner_spread(store.pi, store.pj)  # the first list after a sort
        p.x_build[:] = x

    def _build_wall_candidates(self) -> None:
        """Particles within the reach of each row of each (active) wall, concatenated."""
        from ..geometry._kernels import wall_gaps
        from ..geometry._mesh import triangle_candidates

        sim = self.sim
        p = sim.particles
        store = sim.contact_store
        x, r = p.x, p.r
        cands = []
        no = p.n_owned
        if no:
            box_lo, box_hi = nk.bounds(x, no)
        else:
            box_lo = box_hi = np.full(3, np.nan)
        for wall in sim.contact_store.walls:
            if no and wall.active and wall.n_rows > 1:
                cands += triangle_candidates(wall.rows, x[:no], r[:no], self.reach)
            elif no and wall.active:
                gap = wall_gaps(int(wall.kinds[0]), wall.params, x[:no], r[:no])
                cands.append(np.flatnonzero(gap < self.reach).astype(np.int64))
            else:
                cands += [np.zeros(0, dtype=np.int64)] * wall.n_rows
            wall.mark_built(box_lo, box_hi)
        if store.walls_changed:
            store.pack_walls()
        store.set_wall_candidates(cands, p.id)

    # ------------------------------------------------------------------ ghosts
    def forward_ghosts(self, positions: bool = True) -> None:
        """Send the ghosts' current state to the ranks (and periodic images) that hold them."""
        if self.sim.decomposition is not None:
            from ..parallel.exchange import forward

            forward(self.sim, positions=positions)
