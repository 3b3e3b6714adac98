"""Particle storage: a structure of arrays, owned particles in [0, n_owned), ghosts after.

Fields (SI): ``id`` (int64, unique, < 2³¹), ``x`` position [m], ``v`` velocity [m/s], ``w`` angular
velocity [rad/s], ``f`` force [N], ``t`` torque [N m] (all (n, 3) float64), ``r`` radius [m],
``mass`` [kg], ``inv_m`` [1/kg] and ``inv_i`` [1/(kg m²)] (zero for fixed and prescribed particles,
which act as infinitely massive in contacts), ``mat`` material index (int32), ``motion`` (int8:
:data:`FREE`, :data:`FIXED`, :data:`PRESCRIBED`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ParticleStore", "FREE", "FIXED", "PRESCRIBED", "MOTION_NAMES"]

FREE = 0
FIXED = 1
PRESCRIBED = 2
MOTION_NAMES = {"free": FREE, "fixed": FIXED, "prescribed": PRESCRIBED}

_VEC = ("x", "v", "w", "f", "t", "x_build")
_SCAL = {"r": np.float64, "mass": np.float64, "inv_m": np.float64, "inv_i": np.float64,
         "mat": np.int32, "motion": np.int8, "id": np.int64}


class ParticleStore:
    """Structure of arrays with amortised growth. Arrays are views of length ``n`` (owned + ghosts)."""

    def __init__(self, capacity: int = 0) -> None:
        self.capacity = 0
        self.n_owned = 0
        self.n_ghost = 0
        self._alloc(max(capacity, 16))

    @property
    def n(self) -> int:
        return self.n_owned + self.n_ghost

    def _alloc(self, capacity: int) -> None:
        old_cap = self.capacity
        for name in _VEC:
            new = np.zeros((capacity, 3), dtype=np.float64)
            if old_cap:
                new[:old_cap] = getattr(self, "_" + name)
            setattr(self, "_" + name, new)
        for name, dt in _SCAL.items():
            new = np.zeros(capacity, dtype=dt)
            if old_cap:
                new[:old_cap] = getattr(self, "_" + name)
            setattr(self, "_" + name, new)
        self.capacity = capacity

    def reserve(self, n: int) -> None:
        if n > self.capacity:
            self._alloc(max(n, int(self.capacity * 1.5) + 16))

    def __getattr__(self, name: str):
        # views of the live part; only reached for names not set as attributes
        if name in _VEC or name in _SCAL:
            return self.__dict__["_" + name][: self.n]
        raise AttributeError(name)

    def append_owned(self, ids, x, v, w, r, mass, inv_m, inv_i, mat, motion) -> None:
        """Append owned particles (no ghosts may be present)."""
        if self.n_ghost:
            raise RuntimeError("append_owned with ghosts present")
        k = len(ids)
        self.reserve(self.n_owned + k)
        s = slice(self.n_owned, self.n_owned + k)
        self._id[s] = ids
        self._x[s] = x
        self._v[s] = v
        self._w[s] = w
        self._r[s] = r
        self._mass[s] = mass
        self._inv_m[s] = inv_m
        self._inv_i[s] = inv_i
        self._mat[s] = mat
        self._motion[s] = motion
        self._f[s] = 0.0
        self._t[s] = 0.0
        self._x_build[s] = x
        self.n_owned += k
