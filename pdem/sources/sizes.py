"""Particle size distributions: radii drawn from a :class:`numpy.random.Generator`.

Every distribution has ``r_min``, ``r_max`` (m), ``mean_radius()``, ``mean_volume()`` (m³, the
number-weighted mean sphere volume, used to turn a volume fraction into a particle count) and
``sample(rng, n)`` returning ``n`` radii (float64). Sampling depends only on the generator state,
so the same seed gives bitwise identical radii.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from pdem.errors import InputError

__all__ = ["SizeDistribution", "Single", "Uniform", "Normal", "Table"]

_FOUR_THIRDS_PI = 4.0 * math.pi / 3.0


def _radius(value: float, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} = {value!r} is not a number; give a radius in metres (> 0)") from None
    if not math.isfinite(v) or v <= 0.0:
        raise InputError(f"{name} = {value!r} must be a finite radius > 0 (metres)")
    return v


def _count(n: int) -> int:
    try:
        k = int(n)
    except (TypeError, ValueError):
        raise InputError(f"n = {n!r} is not an integer; give the number of radii to draw (>= 0)") from None
    if k != n or k < 0:
        raise InputError(f"n = {n!r} must be a non-negative integer (number of radii to draw)")
    return k


class SizeDistribution:
    """Base class: a distribution of sphere radii (metres)."""

    r_min: float
    r_max: float

    def mean_radius(self) -> float:  # pragma: no cover - abstract
        """Number-weighted mean radius (m)."""
        raise NotImplementedError

    def mean_volume(self) -> float:  # pragma: no cover - abstract
        """Number-weighted mean sphere volume E[4/3 π r³] (m³)."""
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:  # pragma: no cover
        """``n`` radii drawn with ``rng``."""
        raise NotImplementedError


class Single(SizeDistribution):
    """Monodisperse: every sphere has ``radius``."""

    def __init__(self, radius: float) -> None:
        self.radius = _radius(radius, "radius")
        self.r_min = self.r_max = self.radius

    def __repr__(self) -> str:
        return f"Single(radius={self.radius!r})"

    def mean_radius(self) -> float:
        return self.radius

    def mean_volume(self) -> float:
        return _FOUR_THIRDS_PI * self.radius**3

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        """``n`` copies of the radius (``rng`` is not used)."""
        return np.full(_count(n), self.radius, dtype=np.float64)


class Uniform(SizeDistribution):
    """Radius (equivalently diameter) uniform in ``[r_min, r_max]``."""

    def __init__(self, r_min: float, r_max: float) -> None:
        self.r_min = _radius(r_min, "r_min")
        self.r_max = _radius(r_max, "r_max")
        if self.r_min > self.r_max:
            raise InputError(f"Uniform: r_min = {self.r_min!r} exceeds r_max = {self.r_max!r}; swap them")

    def __repr__(self) -> str:
        return f"Uniform(r_min={self.r_min!r}, r_max={self.r_max!r})"

    def mean_radius(self) -> float:
        return 0.5 * (self.r_min + self.r_max)

    def mean_volume(self) -> float:
        a, b = self.r_min, self.r_max
        if b == a:
            return _FOUR_THIRDS_PI * a**3
        # E[r^3] = (b^4 - a^4) / (4 (b - a)) = (a + b)(a^2 + b^2) / 4
        return _FOUR_THIRDS_PI * (a + b) * (a * a + b * b) / 4.0

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        k = _count(n)
        return self.r_min + (self.r_max - self.r_min) * rng.random(k)


def _phi(z: float) -> float:
    return math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def _Phi(z: float) -> float:  # noqa: N802 (standard notation)
    return 0.5 * math.erfc(-z / math.sqrt(2.0))


class Normal(SizeDistribution):
    """Normal radius distribution of ``mean`` and ``std`` truncated to ``[r_min, r_max]``.

    Draws outside the interval are redrawn (rejection), so the result is the exact truncated
    normal. ``r_min``/``r_max`` default to ``mean ∓ 3 std``; ``r_min`` must stay > 0.
    """

    #: refuse intervals that accept fewer than this fraction of normal draws
    MIN_ACCEPTANCE = 1e-4

    def __init__(self, mean: float, std: float, r_min: float | None = None, r_max: float | None = None):
        self.mean = _radius(mean, "mean")
        try:
            s = float(std)
        except (TypeError, ValueError):
            raise InputError(f"std = {std!r} is not a number; give a standard deviation in metres") from None
        if not math.isfinite(s) or s < 0.0:
            raise InputError(f"std = {std!r} must be a finite standard deviation >= 0 (metres)")
        self.std = s
        if r_min is None:
            r_min = self.mean - 3.0 * s
            if r_min <= 0.0:
                raise InputError(
                    f"Normal: the default r_min = mean - 3 std = {r_min!r} is not positive; "
                    "pass r_min > 0 explicitly"
                )
        if r_max is None:
            r_max = self.mean + 3.0 * s
        self.r_min = _radius(r_min, "r_min")
        self.r_max = _radius(r_max, "r_max")
        if self.r_min > self.r_max:
            raise InputError(f"Normal: r_min = {self.r_min!r} exceeds r_max = {self.r_max!r}; swap them")
        if s == 0.0:
            if not (self.r_min <= self.mean <= self.r_max):
                raise InputError(
                    f"Normal: std = 0 and mean = {self.mean!r} lies outside [r_min, r_max] = "
                    f"[{self.r_min!r}, {self.r_max!r}]; widen the interval or use Single(radius)"
                )
            self._alpha = self._beta = 0.0
            self._accept = 1.0
        else:
            self._alpha = (self.r_min - self.mean) / s
            self._beta = (self.r_max - self.mean) / s
            self._accept = _Phi(self._beta) - _Phi(self._alpha)
            if self._accept < self.MIN_ACCEPTANCE:
                raise InputError(
                    f"Normal: [r_min, r_max] = [{self.r_min!r}, {self.r_max!r}] holds only "
                    f"{self._accept:.3g} of the N({self.mean!r}, {s!r}²) mass; rejection sampling would "
                    "stall. Move the interval towards the mean or use Uniform/Table"
                )

    def __repr__(self) -> str:
        return f"Normal(mean={self.mean!r}, std={self.std!r}, r_min={self.r_min!r}, r_max={self.r_max!r})"

    def _std_moments(self) -> tuple[float, float, float]:
        """E[Z], E[Z²], E[Z³] of the standard normal truncated to [alpha, beta]."""
        if self.std == 0.0:
            return 0.0, 0.0, 0.0
        a, b, z = self._alpha, self._beta, self._accept
        pa, pb = _phi(a), _phi(b)
        m1 = -(pb - pa) / z
        m2 = 1.0 - (b * pb - a * pa) / z
        m3 = 2.0 * m1 - (b * b * pb - a * a * pa) / z
        return m1, m2, m3

    def mean_radius(self) -> float:
        m1, _, _ = self._std_moments()
        return self.mean + self.std * m1

    def mean_volume(self) -> float:
        mu, s = self.mean, self.std
        m1, m2, m3 = self._std_moments()
        er3 = mu**3 + 3.0 * mu * mu * s * m1 + 3.0 * mu * s * s * m2 + s**3 * m3
        return _FOUR_THIRDS_PI * er3

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        k = _count(n)
        if self.std == 0.0:
            return np.full(k, self.mean, dtype=np.float64)
        out = np.empty(k, dtype=np.float64)
        todo = np.arange(k)
        while todo.size:
            draw = rng.normal(self.mean, self.std, todo.size)
            ok = (draw >= self.r_min) & (draw <= self.r_max)
            out[todo[ok]] = draw[ok]
            todo = todo[~ok]
        return out


class Table(SizeDistribution):
    """Discrete radii with given MASS fractions (equal density assumed).

    Number fractions are ∝ ``mass_fraction / r³``, so a table ``radii=(1e-3, 2e-3)``,
    ``mass_fractions=(0.5, 0.5)`` draws eight small spheres for every large one.
    """

    def __init__(self, radii: Sequence[float] | ArrayLike, mass_fractions: Sequence[float] | ArrayLike):
        r = np.asarray(radii, dtype=np.float64).ravel()
        w = np.asarray(mass_fractions, dtype=np.float64).ravel()
        if r.size == 0:
            raise InputError("Table: radii is empty; give at least one radius (metres)")
        if r.shape != w.shape:
            raise InputError(
                f"Table: {r.size} radii but {w.size} mass_fractions; give one mass fraction per radius"
            )
        for i, v in enumerate(r):
            if not math.isfinite(v) or v <= 0.0:
                raise InputError(f"Table: radii[{i}] = {float(v)!r} must be a finite radius > 0 (metres)")
        for i, v in enumerate(w):
            if not math.isfinite(v) or v < 0.0:
                raise InputError(f"Table: mass_fractions[{i}] = {float(v)!r} must be a finite fraction >= 0")
        total = float(w.sum())
        if abs(total - 1.0) > 1e-6:
            raise InputError(
                f"Table: mass_fractions sum to {total!r}, not 1 (tolerance 1e-6); normalise them"
            )
        self.radii = r
        self.mass_fractions = w
        num = w / r**3
        self.number_fractions = num / num.sum()
        used = r[w > 0.0]
        self.r_min = float(used.min())
        self.r_max = float(used.max())
        self._cdf = np.cumsum(self.number_fractions)
        self._cdf[-1] = 1.0

    def __repr__(self) -> str:
        return f"Table(radii={self.radii.tolist()}, mass_fractions={self.mass_fractions.tolist()})"

    def mean_radius(self) -> float:
        return float(np.dot(self.number_fractions, self.radii))

    def mean_volume(self) -> float:
        return _FOUR_THIRDS_PI * float(np.dot(self.number_fractions, self.radii**3))

    def sample(self, rng: np.random.Generator, n: int) -> NDArray[np.float64]:
        k = _count(n)
        idx = np.searchsorted(self._cdf, rng.random(k), side="right")
        idx = np.minimum(idx, self.radii.size - 1)
        return self.radii[idx].copy()
