"""The snapshot handed to output writers: :class:`Frame` (particles + walls at one instant).

The simulation side builds a :class:`Frame` at each output time; writers (:mod:`pdem.io.base`)
only read it. All quantities are SI: positions [m], velocities [m/s], angular velocities [rad/s],
forces [N], torques [N m], radii [m], masses [kg], times [s].

Particle fields (keys of :attr:`Frame.particles`, arrays indexed by particle, ``n`` rows)
-----------------------------------------------------------------------------------------
``id`` (n,) int64 — always present; ``x`` (n, 3) centres — always present;
optional: ``v`` (n, 3) velocity, ``w`` (n, 3) angular velocity, ``f`` (n, 3) force,
``t`` (n, 3) torque, ``r`` (n,) radius, ``mass`` (n,), ``material`` (n,) int32 material index,
``contacts`` (n,) int32 coordination number.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["PARTICLE_FIELDS", "REQUIRED_FIELDS", "WallState", "Frame"]

#: Every particle field a frame may carry, with its meaning (the names writers accept in ``fields``).
PARTICLE_FIELDS: dict[str, str] = {
    "id": "particle id (int64)",
    "x": "centre position [m], (n, 3)",
    "v": "velocity [m/s], (n, 3)",
    "w": "angular velocity [rad/s], (n, 3)",
    "f": "force [N], (n, 3)",
    "t": "torque [N m], (n, 3)",
    "r": "radius [m]",
    "mass": "mass [kg]",
    "material": "material index (int32)",
    "contacts": "number of contacts (int32)",
    "row": "the grain's row in its packing file, from 0 (int64; -1: from another source); present when a "
    "source reads a file",
}

#: Fields every frame carries and every writer always writes.
REQUIRED_FIELDS: tuple[str, ...] = ("id", "x")


@dataclass
class WallState:
    """One wall at the frame's instant.

    ``kind`` and ``params`` follow :mod:`pdem.geometry._kernels` (``params`` has 16 floats and is
    already translated to the wall's current position). ``force`` [N] and ``torque`` [N m] are the
    load the particles put on the wall (torque about its current reference point).
    """

    name: str
    kind: int
    params: np.ndarray
    force: np.ndarray
    torque: np.ndarray


@dataclass
class Frame:
    """A snapshot of the simulation for output.

    ``bounds`` = (lo, hi) is the scene box [m]; writers use it to draw infinite walls (planes,
    infinite cylinders) as finite patches.
    """

    time: float
    step: int
    stage: str
    particles: dict[str, np.ndarray]
    walls: list[WallState] = field(default_factory=list)
    bounds: tuple[np.ndarray, np.ndarray] = field(
        default_factory=lambda: (np.full(3, -np.inf), np.full(3, np.inf))
    )
