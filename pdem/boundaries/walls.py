"""Walls: a geometric shape (:mod:`pdem.boundaries.shapes`), a material and a prescribed motion.

A wall is an infinite-mass, infinite-radius contact partner that uses the simulation's contact
law. Its motion is a translation of the whole shape (``offset``, m) at velocity ``velocity``
(m/s) plus an optional spin ``omega`` (rad/s) about its reference point, which only gives the
surface a velocity (a rotating drum): the shape itself does not rotate.

After every step ``Wall.force`` [N] and ``Wall.torque`` [N m] (about the wall's current reference
point) hold the total load the particles put on it, summed exactly (correctly rounded, hence
independent of summation order and of the number of MPI ranks).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

__all__ = [
    "Wall",
    "Motion",
    "Fixed",
    "ConstantVelocity",
    "VelocityFunction",
    "PositionFunction",
    "Controlled",
]


class Motion:
    """Prescribed translation of a wall. ``advance`` returns (new offset, velocity over the step)."""

    def advance(self, t: float, dt: float, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


class Fixed(Motion):
    def advance(self, t, dt, offset):
        return offset, np.zeros(3)


@dataclass
class ConstantVelocity(Motion):
    """Constant translational velocity [m/s]."""

    velocity: tuple[float, float, float]

    def advance(self, t, dt, offset):
        v = np.asarray(self.velocity, dtype=float)
        return offset + v * dt, v


@dataclass
class VelocityFunction(Motion):
    """Velocity [m/s] as a function of time [s], sampled at mid-step."""

    function: Callable[[float], tuple[float, float, float]]

    def advance(self, t, dt, offset):
        v = np.asarray(self.function(t + 0.5 * dt), dtype=float)
        return offset + v * dt, v


@dataclass
class PositionFunction(Motion):
    """Displacement [m] from the initial placement as a function of time [s]."""

    function: Callable[[float], tuple[float, float, float]]
    _origin: np.ndarray | None = field(default=None, repr=False)

    def advance(self, t, dt, offset):
        if self._origin is None:
            self._origin = np.asarray(self.function(0.0), dtype=float)
        new = np.asarray(self.function(t + dt), dtype=float) - self._origin
        return new, (new - offset) / dt


@dataclass
class Controlled(Motion):
    """Velocity set from outside each step (servo controllers, boundary plugins)."""

    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def advance(self, t, dt, offset):
        v = np.asarray(self.velocity, dtype=float)
        return offset + v * dt, v


class Wall:
    """A wall in a simulation (created by :meth:`pdem.Simulation.add_wall`)."""

    def __init__(
        self, shape, material: int, name: str, motion: Motion | None = None, omega=(0.0, 0.0, 0.0)
    ) -> None:
        self.shape = shape
        self.material = material
        self.name = name
        self.motion = motion or Fixed()
        self.active = True
        self.omega = np.asarray(omega, dtype=float)
        if self.omega.shape != (3,) or not np.all(np.isfinite(self.omega)):
            raise InputError(f"wall '{name}': omega = {omega!r} must be three finite numbers [rad/s]")
        self.offset = np.zeros(3)
        self.velocity = np.zeros(3)
        self.offset_build = np.zeros(3)
        self._load: np.ndarray | None = np.zeros(6)
        self.n_contacts = 0
        self._buf_val = np.zeros((0, 6))
        # every primitive keeps its anchor point in params[0:3]: a translation moves only those
        self._base_params = np.asarray(shape.params(np.zeros(3)), dtype=float)
        self._base_ref = np.asarray(shape.reference_point, dtype=float)
        self.params = self._base_params.copy()
        self.reference_point = self._base_ref.copy()

    @property
    def moving(self) -> bool:
        return not isinstance(self.motion, Fixed)

    def set_offset(self, offset) -> None:
        """Place the wall at ``offset`` [m] from its initial position."""
        self.offset = np.asarray(offset, dtype=float)
        self.params = self._base_params.copy()
        self.params[0:3] += self.offset
        self.reference_point = self._base_ref + self.offset

    def advance(self, t: float, dt: float) -> bool:
        """Move over one step; returns whether the wall moved."""
        if not self.moving:
            return False
        offset, self.velocity = self.motion.advance(t, dt, self.offset)
        self.set_offset(offset)
        return True

    def displacement_since_build(self) -> float:
        d = self.offset - self.offset_build
        return math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])

    def record_load(self, count: int, values: np.ndarray | None = None) -> None:
        """Note that ``values[:count]`` holds this step's contributions (summed lazily, exactly)."""
        self.n_contacts = count
        if values is not None:
            self._buf_val = values
        self._load = None

    def _reduced(self) -> np.ndarray:
        if self._load is None:
            vals = self._buf_val[: self.n_contacts]
            comm = getattr(self, "_comm", None)
            if comm is not None and comm.size > 1:  # collective: every rank reads the load together
                from ..parallel.exact import exact_sums

                self._load = exact_sums(comm, vals.reshape(-1, 6))
            else:
                self._load = np.array([math.fsum(vals[:, c]) for c in range(6)])
        return self._load

    @property
    def force(self) -> np.ndarray:
        """Total force the particles exert on the wall in the last step [N] (exact sum; under MPI a
        collective call: every rank must read it)."""
        return self._reduced()[:3].copy()

    @property
    def torque(self) -> np.ndarray:
        """Total torque on the wall about its reference point in the last step [N m] (exact sum)."""
        return self._reduced()[3:].copy()
