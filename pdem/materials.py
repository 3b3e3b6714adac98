"""Materials and the mixing rules that turn two materials into one contact.

SI units: density kg/m³, Young's modulus Pa, dimensionless Poisson ratio, restitution and friction.

Mixing rules (documented, used by every built-in law):

* effective moduli (Hertz/Mindlin, physics reference §1)
  ``1/E* = (1 − ν_i²)/E_i + (1 − ν_j²)/E_j`` and
  ``1/G* = 2(2 − ν_i)(1 + ν_i)/E_i + 2(2 − ν_j)(1 + ν_j)/E_j``;
* restitution, friction, rolling and spinning friction of a pair: the **minimum** of the two materials'
  values (the rule of Chrono's SMC contact), unless an explicit pair value is given with
  :meth:`MaterialTable.set_pair`.
A wall has a material like a particle; its density is not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .errors import InputError

__all__ = ["Material", "MaterialTable", "damping_ratio", "effective_moduli", "rayleigh_time"]


@dataclass(frozen=True)
class Material:
    """A granular material.

    Parameters (SI): ``density`` ρ [kg/m³], ``youngs_modulus`` E [Pa], ``poisson_ratio`` ν [-],
    ``restitution`` e ∈ [0, 1], ``friction`` μ ≥ 0 (sliding), ``rolling_friction`` μ_r ≥ 0
    (dimensionless, multiplies R* F_n; 0 disables rolling resistance), ``spinning_friction`` μ_s ≥ 0
    (dimensionless, multiplies R* F_n: the bound of the torque about the contact normal; 0 disables
    it).

    ``rigid``: a wall material of infinite stiffness (:meth:`rigid_wall`): E* of a contact is the
    grain's alone, E/(1 − ν²); its ``restitution``, ``friction``, ``rolling_friction`` and
    ``spinning_friction``, when
    given, are used as they are for its contacts (not mixed as minima), and when None the grain's
    apply. Rigid materials are for walls only.
    """

    name: str
    density: float = 2500.0
    youngs_modulus: float = 1e8
    poisson_ratio: float = 0.3
    restitution: float = 0.5
    friction: float = 0.5
    rolling_friction: float = 0.0
    rigid: bool = False
    spinning_friction: float = 0.0

    @classmethod
    def rigid_wall(
        cls, name: str, *, friction: float | None = None, restitution: float | None = None,
        rolling_friction: float | None = None, spinning_friction: float | None = None,
    ) -> Material:  # fmt: skip
        """A rigid wall material: infinite stiffness; its own friction/restitution/rolling and
        spinning friction where given, else the grain's."""
        return cls(name, density=math.inf, youngs_modulus=math.inf, poisson_ratio=0.0,
                   restitution=restitution, friction=friction, rolling_friction=rolling_friction,
                   rigid=True, spinning_friction=spinning_friction)  # fmt: skip

    def __post_init__(self) -> None:
        if self.rigid:
            for key, lo, hi in (("restitution", 0.0, 1.0), ("friction", 0.0, math.inf),
                                ("rolling_friction", 0.0, math.inf),
                                ("spinning_friction", 0.0, math.inf)):  # fmt: skip
                value = getattr(self, key)
                if value is not None and not (lo <= value <= hi and math.isfinite(value)):
                    raise InputError(
                        f"material '{self.name}': {key} = {value!r} is invalid; give a value in "
                        f"[{lo}, {hi}] or leave it unset (the grain's applies)"
                    )
            if not (self.youngs_modulus == math.inf and self.poisson_ratio == 0.0):
                raise InputError(f"material '{self.name}': a rigid material has E = inf and ν = 0")
            return
        checks = [
            ("density", self.density > 0, "a positive density in kg/m³"),
            ("youngs_modulus", self.youngs_modulus > 0, "a positive Young's modulus in Pa"),
            ("poisson_ratio", -1.0 < self.poisson_ratio < 0.5, "a Poisson ratio in (-1, 0.5)"),
            ("restitution", 0.0 <= self.restitution <= 1.0, "a restitution coefficient in [0, 1]"),
            ("friction", self.friction >= 0, "a friction coefficient ≥ 0"),
            ("rolling_friction", self.rolling_friction >= 0, "a rolling friction coefficient ≥ 0"),
            ("spinning_friction", self.spinning_friction >= 0, "a spinning friction coefficient ≥ 0"),
        ]
        for key, ok, allowed in checks:
            value = getattr(self, key)
            if not (ok and math.isfinite(value)):
                raise InputError(f"material '{self.name}': {key} = {value!r} is invalid; give {allowed}")

    @property
    def shear_modulus(self) -> float:
        """G = E / (2(1 + ν)) [Pa]."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))


def damping_ratio(e: float) -> float:
    """The viscous damping ratio of a restitution coefficient e (Tsuji et al. 1992, Hertzian form):
    β = ln e / sqrt(ln² e + π²) (−1 for e = 0, 0 for e = 1)."""
    if e <= 0.0:
        return -1.0
    le = math.log(e)
    return le / math.sqrt(le * le + math.pi * math.pi)


def effective_moduli(a: Material, b: Material) -> tuple[float, float]:
    """Return (E*, G*) of a contact between materials ``a`` and ``b`` [Pa]."""
    inv_e = (1 - a.poisson_ratio**2) / a.youngs_modulus + (1 - b.poisson_ratio**2) / b.youngs_modulus
    inv_g = (
        2 * (2 - a.poisson_ratio) * (1 + a.poisson_ratio) / a.youngs_modulus
        + 2 * (2 - b.poisson_ratio) * (1 + b.poisson_ratio) / b.youngs_modulus
    )
    if inv_e == 0.0:  # two rigid materials (walls never touch each other)
        return math.inf, math.inf
    return 1.0 / inv_e, 1.0 / inv_g


def rayleigh_time(radius: float, mat: Material) -> float:
    """Rayleigh time T_R = π r sqrt(ρ/G) / (0.1631 ν + 0.8766) [s] of a sphere of ``radius``."""
    return (
        math.pi * radius * math.sqrt(mat.density / mat.shear_modulus) / (0.1631 * mat.poisson_ratio + 0.8766)
    )


@dataclass
class MaterialTable:
    """The materials of a simulation, indexed in the order they were added.

    ``pair_values[(i, j)]`` holds explicit per-pair overrides of ``restitution``, ``friction``,
    ``rolling_friction`` or ``spinning_friction`` (symmetric).
    """

    materials: list[Material] = field(default_factory=list)
    pair_values: dict[tuple[int, int], dict[str, float]] = field(default_factory=dict)

    def add(self, mat: Material) -> int:
        if any(m.name == mat.name for m in self.materials):
            raise InputError(f"material '{mat.name}' is defined twice; give each material a unique name")
        self.materials.append(mat)
        return len(self.materials) - 1

    def index(self, name: str) -> int:
        for k, m in enumerate(self.materials):
            if m.name == name:
                return k
        known = ", ".join(m.name for m in self.materials) or "(none defined)"
        raise InputError(f"unknown material '{name}'; defined materials: {known}")

    def __len__(self) -> int:
        return len(self.materials)

    def __getitem__(self, k: int) -> Material:
        return self.materials[k]

    def set_pair(self, a: str, b: str, **values: float) -> None:
        """Override restitution / friction / rolling_friction / spinning_friction for the pair (a, b)."""
        allowed = {"restitution", "friction", "rolling_friction", "spinning_friction"}
        for key, val in values.items():
            if key not in allowed:
                raise InputError(f"pair ({a}, {b}): unknown key '{key}'; allowed: {sorted(allowed)}")
            lo, hi = (0.0, 1.0) if key == "restitution" else (0.0, math.inf)
            if not (lo <= val <= hi):
                raise InputError(f"pair ({a}, {b}): {key} = {val!r} out of range [{lo}, {hi}]")
        ia, ib = self.index(a), self.index(b)
        self.pair_values.setdefault((min(ia, ib), max(ia, ib)), {}).update(values)

    def mixed(self, i: int, j: int, key: str) -> float:
        """Pair value of ``key`` (restitution, friction, rolling_friction, spinning_friction): override
        or minimum."""
        override = self.pair_values.get((min(i, j), max(i, j)), {})
        if key in override:
            return override[key]
        a, b = self.materials[i], self.materials[j]
        va, vb = getattr(a, key), getattr(b, key)
        if a.rigid != b.rigid:  # a rigid wall: its own value where given, else the grain's
            own, other = (va, vb) if a.rigid else (vb, va)
            return own if own is not None else other
        values = [v for v in (va, vb) if v is not None]
        return min(values) if values else 0.0
