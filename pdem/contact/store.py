"""The contacts of one rank: grain pairs and wall candidates, with history keyed by ids.

**Pairs.** ``pi``/``pj`` are storage rows with ``id[pi] < id[pj]``, sorted by the id pair; ``keys``
are ``id_lo·2³² + id_hi``; ``hist`` holds the law's history per pair (``history_size`` floats);
``force`` the force on the higher-id particle from the last evaluation.

**Walls.** ``walls`` in the order they were added; the stacked geometry the wall kernels read
(``kinds``, ``params``, ``vel``, ``omega``, ``centre``, ``wmat``: :meth:`pack_walls`); candidate
particles ``cand[cstart[k]:cstart[k+1]]`` of wall k, sorted by particle id; their history
``wall_hist`` row by row, keyed by ``wall_keys`` = k·2³² + id. History is therefore sparse: it
costs one row per particle near a wall, not walls × particles. Each contact's load on its wall goes
to ``out_idx``/``out_val`` rows (``counts[k]`` per wall), summed exactly by :class:`Wall`.

At a rebuild the new lists take the history of the keys they share with the old ones (a linear
merge of two sorted key lists, :func:`pdem.neighbor._kernels.carry_history`); a particle that
changes rank carries the rows of its keys (:meth:`rows_of`, :meth:`merge`). Nothing here depends on
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
        self.walls: list = []
        self.walls_changed = True
        self.moving: list[int] = []
        self.cstart = np.zeros(1, dtype=np.int64)
        self.cand = z.copy()
        self.wall_keys = z.copy()
        self.wall_hist = np.zeros((0, h))
        self.out_idx = np.zeros(1, dtype=np.int64)
        self.out_val = np.zeros((1, 6))
        self.counts = z.copy()
        self.pack_walls()

    # ------------------------------------------------------------------ walls
    def pack_walls(self) -> None:
        """Stack the walls' geometry and state into the arrays of the wall kernels."""
        walls = self.walls
        nw = len(walls)
        self.kinds = np.array([w.shape.kind for w in walls], dtype=np.int64)
        self.params = (
            np.array([w.params for w in walls], dtype=np.float64).reshape(nw, -1) if nw else np.zeros((0, 1))
        )
        self.vel = np.array([w.velocity for w in walls], dtype=np.float64).reshape(nw, 3)
        self.omega = np.array([w.omega for w in walls], dtype=np.float64).reshape(nw, 3)
        self.centre = np.array([w.reference_point for w in walls], dtype=np.float64).reshape(nw, 3)
        self.wmat = np.array([w.material for w in walls], dtype=np.int64)
        self.moving = [k for k, w in enumerate(walls) if w.moving]
        self.walls_changed = False

    def update_wall(self, k: int) -> None:
        """Copy wall k's current geometry and velocity into the packed arrays."""
        wall = self.walls[k]
        self.params[k] = wall.params
        self.vel[k] = wall.velocity
        self.centre[k] = wall.reference_point
        self.omega[k] = wall.omega

    def reset_wall(self, k: int) -> None:
        """Forget wall k's contact history (switched off; its candidates go at the next rebuild)."""
        self.wall_hist[self.cstart[k] : self.cstart[k + 1]] = 0.0

    # ------------------------------------------------------------------ rebuilds
    def set_pairs(self, pi: np.ndarray, pj: np.ndarray, keys: np.ndarray) -> None:
        """New pair list (sorted by key); history carried over by key."""
        hist = np.empty((keys.shape[0], self.history_size))
        nk.carry_history(self.keys, self.hist, keys, hist)
        self.pi, self.pj, self.keys, self.hist = pi, pj, keys, hist
        self.force = np.zeros((keys.shape[0], 3))

    def set_wall_candidates(self, cands: list[np.ndarray], ids: np.ndarray) -> None:
        """New candidate lists (one array of storage rows per wall; ``ids`` the particle ids by
        row); each list is sorted by id, history carried over by (wall, id)."""
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
        nk.carry_history(self.wall_keys, self.wall_hist, wkeys, hist)
        self.wall_keys, self.wall_hist = wkeys, hist
        total = max(int(self.cstart[-1]), 1)
        self.out_idx = np.empty(total, dtype=np.int64)
        self.out_val = np.empty((total, 6))
        self.counts = np.zeros(len(rows), dtype=np.int64)
        for k, wall in enumerate(self.walls):
            wall.record_load(0, self.out_val[self.cstart[k] : self.cstart[k + 1]])

    # ------------------------------------------------------------------ migration
    def rows_of(self, ids: np.ndarray) -> dict[str, np.ndarray]:
        """The history rows of every pair and wall contact of the particles ``ids`` (to send with
        them to another rank)."""
        if ids.size and self.keys.size:
            rows = np.isin(self.keys >> 32, ids) | np.isin(self.keys & _LOW, ids)
        else:
            rows = np.zeros(self.keys.shape[0], dtype=bool)
        wrows = np.isin(self.wall_keys & _LOW, ids) if ids.size else np.zeros(self.wall_keys.shape[0], bool)
        return {
            "pair_keys": self.keys[rows],
            "pair_hist": self.hist[rows],
            "wall_keys": self.wall_keys[wrows],
            "wall_hist": self.wall_hist[wrows],
        }

    def merge(self, parcel: dict[str, np.ndarray]) -> None:
        """Add received history rows (rows already held are kept: both copies are identical)."""
        for kname, hname, kattr, hattr in (
            ("pair_keys", "pair_hist", "keys", "hist"),
            ("wall_keys", "wall_hist", "wall_keys", "wall_hist"),
        ):
            if not parcel[kname].size:
                continue
            keys = np.concatenate([getattr(self, kattr), parcel[kname]])
            hist = np.concatenate([getattr(self, hattr), parcel[hname]])
            order = np.argsort(keys, kind="stable")
            keys, hist = keys[order], hist[order]
            first = np.ones(keys.shape[0], dtype=bool)
            first[1:] = keys[1:] != keys[:-1]
            setattr(self, kattr, keys[first])
            setattr(self, hattr, hist[first])

    # ------------------------------------------------------------------ checkpoints
    def wall_history_of(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(particle ids, history rows) of wall k's non-zero history on this rank."""
        sel = ((self.wall_keys >> 32) == k) & np.any(self.wall_hist != 0.0, axis=1)
        return self.wall_keys[sel] & _LOW, self.wall_hist[sel]

    def set_wall_history(self, k: int, ids: np.ndarray, hist: np.ndarray) -> None:
        """Add wall k's history rows (by particle id) to the keys carried at the next rebuild."""
        self.merge({
            "pair_keys": np.zeros(0, np.int64), "pair_hist": np.zeros((0, self.history_size)),
            "wall_keys": (np.int64(k) << 32) | np.asarray(ids, dtype=np.int64),
            "wall_hist": np.asarray(hist, dtype=np.float64).reshape(-1, self.history_size),
        })  # fmt: skip
