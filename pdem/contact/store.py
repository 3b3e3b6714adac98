"""The contacts of one rank: grain pairs and wall candidates, with history keyed by ids.

**Pairs.** ``pi``/``pj`` are storage rows with ``id[pi] < id[pj]``, built sorted by the id pair;
``keys`` are ``id_lo·2³² + id_hi``; ``hist`` holds the law's history per pair (``history_size``
floats); ``force`` the force on the higher-id particle from the last evaluation. A scheduled list
(DEM-P, :meth:`ContactStore.set_pairs`) is in another order that gives every particle its pairs
in the same order; ``key_order`` then lists its rows in key order (``None``: the list is sorted).

**Walls.** ``walls`` in the order they were added. Each wall owns one or more geometry **rows**
(one for a primitive shape, one per facet of a mesh), rows of wall w being
``wall_rows[w]:wall_rows[w + 1]``. The kernels read the stacked rows (:meth:`pack_walls`):
``kinds``, ``params``, ``vel`` (translation; column 3 the rate of the radius; column 4 the mass of
a wall that is a free rigid body, 0 for an immovable one), ``omega``,
``centre`` (the wall's reference point), ``wmat``; candidate particles ``cand[cstart[k]:cstart[k+1]]``
of row k, sorted by particle id; their history ``wall_hist``, keyed by ``wall_keys`` = k·2³² + id.
History is therefore sparse: one row per particle near a wall, not rows × particles. ``cand_step``
is ``cand`` with the candidates a mesh sets aside this step (a grain touching several facets
counts once) marked as negative; removed particles are marked so in ``cand`` itself until the next
rebuild (:meth:`ContactStore.drop_wall_candidates`). Each contact's load goes to ``out_idx``/``out_val`` rows
(``counts[k]`` per row), summed exactly by :class:`Wall` (per wall and per facet).

At a rebuild the new lists take the history of the keys they share with the old ones (a linear
merge of two sorted key lists, :func:`pdem.neighbor._kernels.carry_history`); a particle that
changes rank carries the rows of its keys (:meth:`rows_of`); the receiver sets them aside until the
rebuild that follows (:meth:`merge`), whose carry takes them with its own. Nothing here depends on
where a particle is stored, so results do not depend on the storage order or the partition.
"""

from __future__ import annotations

import numpy as np

from ..neighbor import _kernels as nk

__all__ = ["ContactStore"]

_LOW = np.int64(0xFFFFFFFF)


class ContactStore:
    """Pair list, wall candidates and their keyed history (see the module docstring)."""

    def __init__(self, history_size: int) -> None:
        h = max(int(history_size), 1)
        self.history_size = h
        z = np.zeros(0, dtype=np.int64)
        self.pi, self.pj, self.keys = z, z.copy(), z.copy()
        self.hist = np.zeros((0, h))
        self.force = np.zeros((0, 3))
        self.pair_capacity = 64
        self.key_order: np.ndarray | None = None  # rows in key order when the list is scheduled
        self.walls: list = []
        self.walls_changed = True
        self.moving: list[int] = []
        self.cstart = np.zeros(1, dtype=np.int64)
        self.cand = z.copy()
        self.cand_step = self.cand
        self.wall_rows = np.zeros(1, dtype=np.int64)
        self.mesh_rows: list[tuple[int, int]] = []
        self.wall_keys = z.copy()
        self.wall_hist = np.zeros((0, h))
        # history received from other ranks (migration) or restored, carried at the next rebuild
        self._pending: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"pair": [], "wall": []}
        # a restored checkpoint's history, carried at every rebuild until its first step ends
        self._held: dict[str, tuple[np.ndarray, np.ndarray]] | None = None
        self.out_idx = np.zeros(1, dtype=np.int64)
        self.out_val = np.zeros((1, 6))
        self.counts = z.copy()
        self.kinds = z.copy()
        self.params = np.zeros((0, 16))
        self.vel = np.zeros((0, 5))
        self.omega = np.zeros((0, 3))
        self.centre = np.zeros((0, 3))
        self.wmat = z.copy()

    # ------------------------------------------------------------------ walls
    def pack_walls(self) -> None:
        """Stack the walls' rows, velocities and materials into the arrays of the wall kernels."""
        walls = self.walls
        sizes = [w.n_rows for w in walls]
        self.wall_rows = np.zeros(len(walls) + 1, dtype=np.int64)
        self.wall_rows[1:] = np.cumsum(sizes)
        nr = int(self.wall_rows[-1])
        self.kinds = np.concatenate([w.kinds for w in walls]) if walls else np.zeros(0, np.int64)
        self.params = np.concatenate([w.rows for w in walls]) if walls else np.zeros((0, 16))
        self.vel = np.zeros((nr, 5))
        self.omega = np.zeros((nr, 3))
        self.centre = np.zeros((nr, 3))
        self.wmat = np.zeros(nr, dtype=np.int64)
        for k, w in enumerate(walls):
            self._fill_wall(k)
            self.wmat[self.wall_rows[k] : self.wall_rows[k + 1]] = w.material
        self.moving = [k for k, w in enumerate(walls) if w.moving]
        self.mesh_rows = [
            (int(self.wall_rows[k]), int(self.wall_rows[k + 1])) for k, w in enumerate(walls) if w.n_rows > 1
        ]
        self.walls_changed = False

    def _fill_wall(self, k: int) -> None:
        wall = self.walls[k]
        a, b = self.wall_rows[k], self.wall_rows[k + 1]
        self.vel[a:b, 0:3] = wall.velocity
        self.vel[a:b, 3] = wall.size_rate
        self.vel[a:b, 4] = getattr(wall.motion, "mass", 0.0) if wall.motion.moved_by_load else 0.0
        self.omega[a:b] = wall.omega
        self.centre[a:b] = wall.reference_point

    def update_wall(self, k: int) -> None:
        """Copy wall k's current geometry and velocities into the packed arrays."""
        self.params[self.wall_rows[k] : self.wall_rows[k + 1]] = self.walls[k].rows
        self._fill_wall(k)

    def reset_wall(self, k: int) -> None:
        """Forget wall k's contact history (switched off; its candidates go at the next rebuild)."""
        if self.walls_changed:
            return  # nothing packed for it yet
        a, b = self.wall_rows[k], self.wall_rows[k + 1]
        if b < self.cstart.shape[0]:
            self.wall_hist[self.cstart[a] : self.cstart[b]] = 0.0

    # ------------------------------------------------------------------ rebuilds
    def set_pairs(self, pi: np.ndarray, pj: np.ndarray, keys: np.ndarray, schedule_rows: int = -1) -> None:
        """New pair list (sorted by key); history carried over by key.

        With ``schedule_rows`` (the number of storage rows, ghosts included) the list is then put
        in :func:`~pdem.neighbor._kernels.schedule_pairs` order: every particle meets its pairs in
        the same order, so the force loop gives the same bits, but it walks the storage instead of
        the ids. ``key_order`` then lists the rows in key order (``None``: they are in key order).
        """
        old_keys, old_hist = self.keys_sorted()
        hist = np.empty((keys.shape[0], self.history_size))
        self._carry("pair", old_keys, old_hist, keys, hist)
        self.key_order = None
        if schedule_rows >= 0 and keys.shape[0] > 1:
            order = nk.schedule_pairs(pi, pj, schedule_rows)
            pi, pj, keys, hist, self.key_order = nk.take_pairs(order, pi, pj, keys, hist)
        self.pi, self.pj, self.keys, self.hist = pi, pj, keys, hist
        self.force = np.zeros((keys.shape[0], 3))

    def keys_sorted(self) -> tuple[np.ndarray, np.ndarray]:
        """(keys, history) of the pairs in key order (views when the list is in key order)."""
        if self.key_order is None:
            return self.keys, self.hist
        return nk.take_keyed(self.key_order, self.keys, self.hist)

    def pair_rows_in_key_order(self) -> np.ndarray | slice:
        """Index of the pair rows in key order: for sums over pairs that must not depend on the
        list's order."""
        return slice(None) if self.key_order is None else self.key_order

    def set_wall_candidates(self, cands: list[np.ndarray], ids: np.ndarray) -> None:
        """New candidate lists (one array of particle storage rows per wall row; ``ids`` the particle
        ids by storage row); each list is sorted by id, history carried over by (row, id)."""
        rows, keys = [], []
        for k, c in enumerate(cands):
            c = c[np.argsort(ids[c], kind="stable")]
            rows.append(c)
            keys.append((np.int64(k) << 32) | ids[c])
        sizes = [c.shape[0] for c in rows]
        self.cstart = np.zeros(len(rows) + 1, dtype=np.int64)
        self.cstart[1:] = np.cumsum(sizes)
        self.cand = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
        wkeys = np.concatenate(keys) if keys else np.zeros(0, dtype=np.int64)
        hist = np.empty((wkeys.shape[0], self.history_size))
        self._carry("wall", self.wall_keys, self.wall_hist, wkeys, hist)
        self.wall_keys, self.wall_hist = wkeys, hist
        total = max(int(self.cstart[-1]), 1)
        self.out_idx = np.empty(total, dtype=np.int64)
        self.out_val = np.empty((total, 6))
        self.counts = np.zeros(len(rows), dtype=np.int64)
        self.cand_step = self.cand
        for k, wall in enumerate(self.walls):
            a, b = self.wall_rows[k], self.wall_rows[k + 1]
            bufs = [self.out_val[self.cstart[r] : self.cstart[r + 1]] for r in range(a, b)]
            wall.record_rows([0] * (b - a), bufs)

    def drop_wall_candidates(self, gone: np.ndarray) -> None:
        """Set aside, until the next rebuild, the wall candidates marked in ``gone`` (a mask over
        storage rows; removed particles, which stay in the storage until then): marked ``-1 - i``
        as a mesh marks its set-aside duplicates, history zeroed. The rows keep their places, so the
        walls' load buffers of this step stay as they are."""
        c = self.cand
        if not c.size:
            return
        live = c >= 0
        hit = np.zeros(c.shape[0], dtype=bool)
        hit[live] = gone[c[live]]
        if hit.any():
            c[hit] = -1 - c[hit]  # in place: cand_step is cand itself unless a mesh filters it
            self.wall_hist[hit] = 0.0

    def filter_meshes(self, x: np.ndarray, r: np.ndarray, inv_m: np.ndarray, reach: float) -> None:
        """This step's candidates: a grain touching (gap < ``reach``) several facets of one mesh
        keeps its face contacts, or, touching no face, its closest edge or vertex contact (the first
        facet among equals); the others are set aside (negative in ``cand_step``)."""
        if not self.mesh_rows:
            self.cand_step = self.cand
            return
        from ..geometry._mesh import filter_mesh_candidates

        step = self.cand.copy()
        for a, b in self.mesh_rows:
            filter_mesh_candidates(
                self.params, self.cstart, self.cand, step, a, b, x, r, inv_m, reach, self.wall_hist
            )
        self.cand_step = step

    def record_wall_loads(self) -> None:
        """Tell every wall how many load rows each of its rows wrote this step."""
        counts = self.counts
        for k, wall in enumerate(self.walls):
            wall.record_rows(counts[self.wall_rows[k] : self.wall_rows[k + 1]])

    # ------------------------------------------------------------------ migration
    def rows_of(self, ids: np.ndarray) -> dict[str, np.ndarray]:
        """The history rows of every pair and wall contact of the particles ``ids`` (to send with
        them to another rank)."""
        ids = np.sort(np.asarray(ids, dtype=np.int64))
        rows = nk.keys_with_ids(self.keys, ids, True)
        wrows = nk.keys_with_ids(self.wall_keys, ids, False)
        out = {
            "pair_keys": self.keys[rows],
            "pair_hist": self.hist[rows],
            "wall_keys": self.wall_keys[wrows],
            "wall_hist": self.wall_hist[wrows],
        }
        # rows received in an earlier migration pass, not yet carried (a particle can move on), and a
        # restored checkpoint's rows while they are held (a first step's migration takes them along)
        for kind, kname, hname in (("pair", "pair_keys", "pair_hist"), ("wall", "wall_keys", "wall_hist")):
            sources = [self._pending_rows(kind)] if ids.size and self._pending[kind] else []
            if ids.size and self._held is not None and self._held[kind][0].size:
                sources.append(self._held[kind])
            for pk, ph in sources:
                sel = nk.keys_with_ids(pk, ids, kind == "pair")
                if sel.size:
                    out[kname] = np.concatenate([out[kname], pk[sel]])
                    out[hname] = np.concatenate([out[hname], ph[sel]])
        return out

    def merge(self, parcel: dict[str, np.ndarray]) -> None:
        """Add received history rows, to be carried at the next rebuild (rows already held are kept:
        both copies are identical). They are set aside rather than merged into the lists: a rebuild
        follows every migration, and merging re-sorted this rank's whole history at each one (1.25 ms
        a migration on the DEM-C hopper, whose 2-rank run migrates at every step)."""
        for kind, kname, hname in (("pair", "pair_keys", "pair_hist"), ("wall", "wall_keys", "wall_hist")):
            if parcel[kname].size:
                self._pending[kind].append((parcel[kname], parcel[hname]))
                if self._held is not None:  # rows of a restored checkpoint, still held, came along
                    keys = np.concatenate([self._held[kind][0], parcel[kname]])
                    hist = np.concatenate([self._held[kind][1], parcel[hname]]).reshape(-1, self.history_size)
                    keys, first = np.unique(keys, return_index=True)
                    self._held[kind] = (keys, hist[first])

    def adopt_received(self) -> None:
        """Make the rows received so far the whole history, held as a restored checkpoint's: after a
        checkpoint read back in shares was spread over the ranks (:func:`pdem.parallel.exchange.scatter`),
        which handed every row (this rank's own included) over as received."""
        self.keys, self.hist = self._pending_rows("pair")
        self._pending["pair"] = []
        self.pi = self.pj = np.zeros(0, dtype=np.int64)
        self.key_order = None
        self.force = np.zeros((0, 3))
        self.hold_restored()

    def clear_rows(self) -> None:
        """Forget every history row (its particles were handed over: :meth:`adopt_received` follows)."""
        self.keys = np.zeros(0, dtype=np.int64)
        self.hist = np.zeros((0, self.history_size))
        self._pending = {"pair": [], "wall": []}

    def _pending_rows(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """The rows set aside for ``kind`` ("pair" or "wall"), sorted by key, each key once."""
        parts = self._pending[kind]
        if not parts:
            return np.zeros(0, dtype=np.int64), np.zeros((0, self.history_size))
        keys = np.concatenate([k for k, _ in parts])
        hist = np.concatenate([h for _, h in parts]).reshape(-1, self.history_size)
        order = np.argsort(keys, kind="stable")
        keys, hist = keys[order], hist[order]
        first = np.ones(keys.shape[0], dtype=bool)
        first[1:] = keys[1:] != keys[:-1]
        return keys[first], hist[first]

    def _carry(self, kind: str, old_keys, old_hist, new_keys, new_hist) -> None:
        """History by key into a new list: a restored checkpoint's rows while held
        (:meth:`hold_restored`), the rows set aside (:meth:`merge`), then this rank's own (later
        ones win where several hold a key, as when the received rows were merged in)."""
        pk, ph = self._pending_rows(kind)
        self._pending[kind] = []
        zero = True
        if self._held is not None and self._held[kind][0].size:
            nk.carry_history(*self._held[kind], new_keys, new_hist)
            zero = False
        if pk.size:
            nk.carry_history(pk, ph, new_keys, new_hist, zero)
            zero = False
        nk.carry_history(old_keys, old_hist, new_keys, new_hist, zero)

    def hold_restored(self) -> None:
        """Keep the history just restored from a checkpoint (every row, on every rank) for every
        rebuild until the first step ends (:meth:`release_held`). The preparation after a restore
        builds its list at its own reach, which can be narrower than the list the checkpointed run
        held: a method whose list reaches beyond touching (DEM-C's envelope, widened for fast grains
        and narrowed only at rebuilds) would otherwise lose the warm start of pairs that the first
        step's list, widened again, holds. Which history a rebuild carries then depends on the state
        alone, not on the reach the list was built at before the checkpoint."""
        self._held = {"pair": self.keys_sorted(), "wall": self._pending_rows("wall")}

    def release_held(self) -> None:
        """The first step after a restore ended: its lists hold what they need (:meth:`hold_restored`)."""
        self._held = None

    # ------------------------------------------------------------------ checkpoints
    def wall_history_of(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row within the wall, particle ids, history) of wall k's non-zero history on this rank."""
        a, b = self.wall_rows[k], self.wall_rows[k + 1]
        row = self.wall_keys >> 32
        sel = (row >= a) & (row < b) & np.any(self.wall_hist != 0.0, axis=1)
        return row[sel] - a, self.wall_keys[sel] & _LOW, self.wall_hist[sel]

    def set_wall_history(self, k: int, rows: np.ndarray, ids: np.ndarray, hist: np.ndarray) -> None:
        """Add wall k's history (row within the wall, particle id) to the keys carried at the next
        rebuild. Call after the walls are packed."""
        if self.walls_changed:
            self.pack_walls()
        rows = np.asarray(rows, dtype=np.int64) + self.wall_rows[k]
        keys = (rows << 32) | np.asarray(ids, dtype=np.int64)
        order = np.argsort(keys, kind="stable")
        self.merge({
            "pair_keys": np.zeros(0, np.int64), "pair_hist": np.zeros((0, self.history_size)),
            "wall_keys": keys[order],
            "wall_hist": np.asarray(hist, dtype=np.float64).reshape(-1, self.history_size)[order],
        })  # fmt: skip
