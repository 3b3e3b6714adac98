"""The periodic box: which axes wrap, where, and the position grid that makes images exact.

Periodic images are ghost particles shifted by ±L (see :mod:`pdem.parallel.exchange`). For the
results to be bitwise identical on any number of ranks, a contact across the periodic boundary must
be computed from the same numbers wherever it is computed: rank A, owning i, sees the image
x_j + s L of j; rank B, owning j, sees the image x_i − s L of i; in serial both copies exist. With
arbitrary floating-point positions (x_j + s L) − x_i and x_j − (x_i − s L) round differently.

So along a periodic axis positions live on a fixed grid of spacing ``q`` (a power of two chosen from
the box, ~1e-16 of its size), and the box edges sit on the grid of spacing 2q:

* a shift by ±L is exact, so both copies of a contact get the same relative vector bit for bit
  (the difference of two grid values of this magnitude is exact), hence the same force, with
  opposite signs, and the same contact history;
* wrapping a position into [lo, hi) is exact, so it does not matter when it happens (at which
  neighbour-list rebuild, before or after a checkpoint): the trajectory does not change;
* each step moves a particle by ``dt v`` rounded to the grid (``initial_integrate`` with
  ``snap``): ``round(d) = (d + C) − C`` with ``C = 1.5·2⁵²·q`` (IEEE round-to-nearest, fastmath
  off), translation-invariant because L is a multiple of 2q.

The price is a position resolution of q along periodic axes (~3e-17 m in a 5 cm box: about eight
times coarser than a double near the box edge, finer than any physical length).

A pair of particles may interact with one image of each other only: every periodic length must be at
least twice the largest pair cutoff (the ghost width 2 r_max + skin). Then the id pair is a unique key
of the physical contact, whichever image carries it; in particular, a contact keeps its history when
one of its particles is wrapped (the image that carries it changes, the contact does not).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .errors import InputError

__all__ = ["PeriodicBox", "parse_axes"]

_AXES = "xyz"


def parse_axes(axes) -> tuple[bool, bool, bool]:
    """``"xy"``, ``["x", "y"]`` or three booleans → a mask of periodic axes."""
    if isinstance(axes, str):
        names = list(axes)
    else:
        names = list(axes)
        if len(names) == 3 and all(isinstance(a, bool | np.bool_) for a in names):
            return tuple(bool(a) for a in names)  # type: ignore[return-value]
    bad = [a for a in names if a not in _AXES]
    if bad:
        raise InputError(f"periodic axes {names!r}: {bad[0]!r} is not an axis; use 'x', 'y' and/or 'z'")
    if len(set(names)) != len(names):
        raise InputError(f"periodic axes {names!r}: an axis is listed twice")
    return tuple(a in names for a in _AXES)  # type: ignore[return-value]


class PeriodicBox:
    """Periodic axes ``periodic`` (3 booleans) of the box ``lo <= x < hi`` [m].

    Only the periodic components of ``lo``/``hi`` are used. They are rounded to the position grid
    (a relative change below 1e-15); ``lo``, ``hi``, ``length`` hold the values in force.
    ``q[d]``: grid spacing along axis d (0 on non-periodic axes); ``snap[d]``: the rounding constant
    1.5·2⁵²·q passed to the integrator (0: no rounding).
    """

    def __init__(self, lo: Sequence[float], hi: Sequence[float], axes=("x", "y", "z")) -> None:
        self.periodic = np.array(parse_axes(axes), dtype=bool)
        lo_a = np.asarray(lo, dtype=np.float64).reshape(-1)
        hi_a = np.asarray(hi, dtype=np.float64).reshape(-1)
        if lo_a.shape != (3,) or hi_a.shape != (3,):
            raise InputError(
                f"periodic box: lo = {lo!r} and hi = {hi!r} must be three numbers each (x, y, z) [m]"
            )
        self.lo = np.full(3, -np.inf)
        self.hi = np.full(3, np.inf)
        self.length = np.zeros(3)
        self.q = np.zeros(3)
        self.snap = np.zeros(3)
        for d in np.flatnonzero(self.periodic):
            a, b = float(lo_a[d]), float(hi_a[d])
            if not (math.isfinite(a) and math.isfinite(b) and b > a):
                raise InputError(
                    f"periodic box along {_AXES[d]}: hi = {b!r} must be finite and above lo = {a!r} [m]"
                )
            size = max(abs(a), abs(b), b - a)
            # positions (images included) stay within 4·2^e of zero; q = 2^(e-51) keeps every sum and
            # difference of them exact (below 2^53 q)
            e = math.frexp(size)[1]
            q = math.ldexp(1.0, e - 51)
            a = round(a / (2 * q)) * (2 * q)
            b = round(b / (2 * q)) * (2 * q)
            self.lo[d], self.hi[d], self.length[d] = a, b, b - a
            self.q[d] = q
            self.snap[d] = 1.5 * 2.0**52 * q
        if not self.periodic.any():
            raise InputError("periodic box: no periodic axis given; name at least one of 'x', 'y', 'z'")

    @property
    def axes(self) -> list[str]:
        """Names of the periodic axes, e.g. ``["x", "y"]``."""
        return [_AXES[d] for d in np.flatnonzero(self.periodic)]

    def __repr__(self) -> str:
        parts = [f"{_AXES[d]}: [{self.lo[d]!r}, {self.hi[d]!r})" for d in np.flatnonzero(self.periodic)]
        return f"PeriodicBox({', '.join(parts)})"

    # ------------------------------------------------------------------ positions
    def snap_positions(self, x: np.ndarray) -> None:
        """Round positions (n, 3) to the grid along periodic axes, in place (idempotent)."""
        for d in np.flatnonzero(self.periodic):
            q = self.q[d]
            x[:, d] = np.rint(x[:, d] / q) * q  # exact: scaling by a power of two, rint to even

    def wrap(self, x: np.ndarray) -> int:
        """Bring grid positions (n, 3) into [lo, hi) along periodic axes, in place; exact.

        Returns the number of coordinates moved. A shift by k L is exact on the grid, so wrapping
        never changes a trajectory."""
        moved = 0
        for d in np.flatnonzero(self.periodic):
            lo, hi, length = self.lo[d], self.hi[d], self.length[d]
            col = x[:, d]
            out = (col < lo) | (col >= hi)
            if not out.any():
                continue
            moved += int(out.sum())
            k = np.floor((col[out] - lo) / length)
            v = col[out] - k * length
            # floor of a rounded quotient can be off by one at the edges: settle exactly
            v = np.where(v >= hi, v - length, v)
            v = np.where(v < lo, v + length, v)
            col[out] = v
        return moved

    def wrapped(self, x: np.ndarray) -> np.ndarray:
        """A wrapped copy of positions (n, 3)."""
        out = np.array(x, dtype=np.float64, copy=True)
        self.wrap(out)
        return out

    def minimum_image(self, d: np.ndarray) -> np.ndarray:
        """Relative vectors (n, 3) reduced to the nearest image along periodic axes (a copy)."""
        out = np.array(d, dtype=np.float64, copy=True)
        for a in np.flatnonzero(self.periodic):
            out[:, a] -= np.rint(out[:, a] / self.length[a]) * self.length[a]
        return out

    def check_width(self, width: float) -> None:
        """Every periodic length must be at least twice the ghost width (the largest pair cutoff)."""
        for d in np.flatnonzero(self.periodic):
            if self.length[d] < 2.0 * width:
                ax = _AXES[d]
                raise InputError(
                    f"the periodic box is {self.length[d]:.4g} m long along {ax} (domain.hi − domain.lo), "
                    f"less than twice the largest pair cutoff 2 r_max + skin = {width:.4g} m, so a pair of "
                    f"particles could interact with two images of each other; make the box at least "
                    f"{2.0 * width:.4g} m long along {ax} (domain.lo/domain.hi, or set_periodic), or use "
                    "smaller particles or a smaller run.skin"
                )

    def check_walls(self, walls, width: float) -> None:
        """Walls are not periodic: along a periodic axis a wall must look the same from every image
        of a particle (an infinite plane parallel to the axis), or stay ``width`` (the ghost width)
        away from the box faces (so that no particle near a face can touch it)."""
        from .geometry.shapes import Cylinder, Plane

        box, w = self, width
        for wall in walls:
            for d in np.flatnonzero(box.periodic):
                ax = "xyz"[d]
                if isinstance(wall.shape, Cylinder) and abs(wall.shape.axis[d]) == 1.0:
                    continue  # an infinite cylinder along the axis (a periodic pipe)
                if isinstance(wall.shape, Plane):
                    if wall.shape.normal[d] != 0.0:
                        raise InputError(
                            f"wall '{wall.name}' is a plane with a normal component along the periodic axis "
                            f"{ax}; walls are not periodic, so such a plane would cut the periodic box. Use "
                            f"planes parallel to {ax} (normal along a non-periodic axis), or drop {ax} from "
                            "the periodic axes"
                        )
                    continue
                lo, hi = wall.bounding_box()
                if not (lo[d] >= box.lo[d] + w and hi[d] <= box.hi[d] - w):
                    raise InputError(
                        f"wall '{wall.name}' spans [{lo[d]:.4g}, {hi[d]:.4g}] m along the periodic axis "
                        f"{ax}, closer than the ghost width {w:.4g} m to the box faces {box.lo[d]:.4g} / "
                        f"{box.hi[d]:.4g} m; walls are not periodic (a particle and its image would see "
                        "different walls). Keep finite walls inside the box away from its faces, or use "
                        f"infinite planes parallel to {ax} or an infinite cylinder along {ax}"
                    )

    def state(self) -> dict[str, np.ndarray]:
        """Checkpoint entries."""
        return {
            "domain/periodic": self.periodic.copy(),
            "domain/lo": self.lo.copy(),
            "domain/hi": self.hi.copy(),
        }
