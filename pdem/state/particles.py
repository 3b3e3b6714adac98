"""Particle storage: a structure of arrays, owned particles in [0, n_owned), ghosts after.

Fields (SI): ``id`` (int64, unique, < 2³¹), ``x`` position [m], ``v`` velocity [m/s], ``w`` angular
velocity [rad/s], ``f`` force [N], ``t`` torque [N m] (all (n, 3) float64), ``r`` radius [m],
``mass`` [kg], ``inv_m`` [1/kg] and ``inv_i`` [1/(kg m²)] (zero for fixed and prescribed particles,
which act as infinitely massive in contacts), ``mat`` material index (int32), ``motion`` (int8:
:data:`FREE`, :data:`FIXED`, :data:`PRESCRIBED`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ParticleStore", "FREE", "FIXED", "PRESCRIBED", "REMOVED", "MOTION_NAMES"]

FREE = 0
FIXED = 1
PRESCRIBED = 2
REMOVED = 3  # taken out by an outflow; compacted away at the next neighbour-list rebuild
MOTION_NAMES = {"free": FREE, "fixed": FIXED, "prescribed": PRESCRIBED}

_VEC = ("x", "v", "w", "f", "t", "x_build")
_SCAL = {
    "r": np.float64,
    "mass": np.float64,
    "inv_m": np.float64,
    "inv_i": np.float64,
    "mat": np.int32,
    "motion": np.int8,
    "id": np.int64,
}


class ParticleStore:
    """Structure of arrays with amortised growth. Field attributes are views of length ``n`` (owned +
    ghosts), cached until the counts or the capacity change."""

    def __init__(self, capacity: int = 0) -> None:
        self.capacity = 0
        self._n_owned = 0
        self._n_ghost = 0
        self._views: dict[str, np.ndarray] = {}
        self._alloc(max(capacity, 16))

    @property
    def n(self) -> int:
        return self._n_owned + self._n_ghost

    @property
    def n_owned(self) -> int:
        return self._n_owned

    @n_owned.setter
    def n_owned(self, value: int) -> None:
        self._n_owned = int(value)
        self._invalidate()

    @property
    def n_ghost(self) -> int:
        return self._n_ghost

    @n_ghost.setter
    def n_ghost(self, value: int) -> None:
        self._n_ghost = int(value)
        self._invalidate()

    def _invalidate(self) -> None:
        """Forget the cached views (counts or capacity changed)."""
        d = self.__dict__
        for name in d.get("_views", ()):
            d.pop(name, None)
        d["_views"] = {}

    def _alloc(self, capacity: int) -> None:
        old_cap = self.capacity
        for name in _VEC:
            new = np.zeros((capacity, 3), dtype=np.float64)
            if old_cap:
                new[:old_cap] = self.__dict__["_" + name]
            self.__dict__["_" + name] = new
        for name, dt in _SCAL.items():
            new = np.zeros(capacity, dtype=dt)
            if old_cap:
                new[:old_cap] = self.__dict__["_" + name]
            self.__dict__["_" + name] = new
        self.capacity = capacity
        self._invalidate()

    def reserve(self, n: int) -> None:
        if n > self.capacity:
            self._alloc(max(n, int(self.capacity * 1.5) + 16))

    def __getattr__(self, name: str):
        # only reached for names that are not attributes: a field view not cached yet. The view is
        # then stored as an instance attribute, so later reads are plain attribute lookups (a step
        # reads ~40 fields; through __getattr__ that cost ~35 µs per step)
        views = self.__dict__.get("_views")
        if views is not None and (name in _VEC or name in _SCAL):
            view = self.__dict__["_" + name][: self.n]
            views[name] = view
            self.__dict__[name] = view
            return view
        raise AttributeError(name)

    def append_owned(self, ids, x, v, w, r, mass, inv_m, inv_i, mat, motion) -> None:
        """Append owned particles (no ghosts may be present)."""
        if self.n_ghost:
            raise RuntimeError("append_owned with ghosts present")
        k = len(ids)
        self.reserve(self.n_owned + k)
        s = slice(self.n_owned, self.n_owned + k)
        d = self.__dict__
        d["_id"][s] = ids
        d["_x"][s] = x
        d["_v"][s] = v
        d["_w"][s] = w
        d["_r"][s] = r
        d["_mass"][s] = mass
        d["_inv_m"][s] = inv_m
        d["_inv_i"][s] = inv_i
        d["_mat"][s] = mat
        d["_motion"][s] = motion
        d["_f"][s] = 0.0
        d["_t"][s] = 0.0
        d["_x_build"][s] = x
        self.n_owned = self.n_owned + k
