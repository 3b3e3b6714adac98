"""Particle storage: a structure of arrays, owned particles in [0, n_owned), ghosts after.

Every per-particle array is a registered :class:`Field`: its name, dtype, width (scalar or 3-vector)
and what the engine does with it: carry it when a particle migrates to another rank, copy it onto
ghosts, keep it in checkpoints, write it in snapshots. The built-in fields (SI units):

=========  ======  ==================================================================================
``id``     int64   unique, < 2³¹, assigned in insertion order
``x``      (n, 3)  position [m]
``v``      (n, 3)  velocity [m/s]
``w``      (n, 3)  angular velocity [rad/s]
``f``      (n, 3)  force of the last evaluation [N] (DEM-C: contact impulse / h + weight)
``t``      (n, 3)  torque [N m]
``r``      float   radius [m]
``mass``   float   [kg]
``inv_m``  float   1/mass [1/kg]; 0 for fixed and prescribed particles (infinitely massive in contacts)
``inv_i``  float   1/moment of inertia [1/(kg m²)]; 0 likewise
``mat``    int32   material index
``motion`` int8    :data:`FREE`, :data:`FIXED`, :data:`PRESCRIBED` (or :data:`REMOVED`)
``group``  int32   a user tag (sensors, membrane grains, layers); 0 by default
``dof``    uint8   locked degrees of freedom: bit c (c = 0, 1, 2) locks translation along x, y, z,
                   bit 3 + c rotation about x, y, z (:func:`dof_mask`); 0 = all free
``x_build`` (n, 3) position at the last neighbour-list rebuild (engine bookkeeping)
=========  ======  ==================================================================================

Plugins register their own fields with :meth:`ParticleStore.register` (through
``Simulation.register_field``): they then migrate, are ghosted and checkpointed as declared,
without any other edit.

:func:`new_particles` checks the arguments of ``Simulation.add_particles`` and makes the new
spheres' values of every field (masses and inertias from the material's density).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import GeometryError, InputError

__all__ = [
    "new_particles",
    "ParticleStore",
    "Field",
    "BUILTIN_FIELDS",
    "FREE",
    "FIXED",
    "PRESCRIBED",
    "REMOVED",
    "MOTION_NAMES",
    "dof_mask",
]

FREE = 0
FIXED = 1
PRESCRIBED = 2
REMOVED = 3  # taken out by an outflow; compacted away at the next neighbour-list rebuild
MOTION_NAMES = {"free": FREE, "fixed": FIXED, "prescribed": PRESCRIBED}


def dof_mask(translation: str = "", rotation: str = "") -> int:
    """The ``dof`` bits that lock ``translation`` along and ``rotation`` about the named axes
    (``"xz"``, ``"y"``, ``""``). A 2-D mode in the xz plane: ``dof_mask("y", "xz")``."""
    mask = 0
    for shift, axes, what in ((0, translation, "translation"), (3, rotation, "rotation")):
        for a in axes:
            if a not in "xyz" or not a:
                raise ValueError(f"{what} axes {axes!r}: use letters among x, y, z")
            mask |= 1 << (shift + "xyz".index(a))
    return mask


def new_particles(
    store: ParticleStore,
    materials: Any,
    box: Any,
    first_id: int,
    positions,
    radii,
    material: str | None = None,
    velocities=None,
    angular_velocities=None,
    motion: str | Any = "free",
    group: int = 0,
    fixed_translation: str = "",
    fixed_rotation: str = "",
    fields: dict[str, Any] | None = None,
) -> tuple[dict[str, np.ndarray], int]:
    """The values of every given field of new spheres (``Simulation.add_particles``, whose docstring
    explains the arguments), checked, with ids from ``first_id`` on; and their ``dof`` mask.
    ``materials``: the simulation's :class:`~pdem.materials.MaterialTable`; ``box``: its
    :class:`~pdem.domain.PeriodicBox` (positions are put on its grid and wrapped into it) or None;
    ``fields``: values of registered fields of ``store``."""
    x = np.array(positions, dtype=np.float64, ndmin=2)
    if x.ndim != 2 or x.shape[1] != 3:
        raise GeometryError(f"positions must have shape (n, 3); got {np.shape(positions)}")
    n = x.shape[0]
    r = np.broadcast_to(np.asarray(radii, dtype=np.float64), (n,)).copy()
    if not np.all(np.isfinite(x)):
        raise GeometryError("positions contain non-finite values")
    if box is not None:  # onto the periodic grid and into the box (exact, idempotent)
        x = x.copy()
        box.snap_positions(x)
        box.wrap(x)
    if not np.all((r > 0) & np.isfinite(r)):
        bad = r[~((r > 0) & np.isfinite(r))][0]
        raise GeometryError(f"radius = {bad!r} is invalid; radii must be positive and finite (metres)")
    if material is None:
        if len(materials) != 1:
            raise InputError("add_particles: name the material (several or no materials are defined)")
        mat_idx = 0
    else:
        mat_idx = materials.index(material)
    if materials[mat_idx].rigid:
        raise InputError(
            f"material '{materials[mat_idx].name}' is rigid (Material.rigid_wall): for walls only; "
            "give the particles an elastic material"
        )
    if isinstance(motion, str):
        if motion not in MOTION_NAMES:
            raise InputError(f"motion = {motion!r} is invalid; allowed: {sorted(MOTION_NAMES)}")
        mo = np.full(n, MOTION_NAMES[motion], np.int8)
    else:
        names = np.asarray(motion, dtype=object).reshape(-1)
        if names.shape != (n,):
            raise InputError(f"motion: give one name or one per particle ({n}); got {names.shape[0]}")
        bad = sorted({str(m) for m in names if m not in MOTION_NAMES})
        if bad:
            raise InputError(f"motion = {bad[0]!r} is invalid; allowed: {sorted(MOTION_NAMES)}")
        mo = np.array([MOTION_NAMES[m] for m in names], dtype=np.int8)
    v = (
        np.zeros((n, 3))
        if velocities is None
        else np.broadcast_to(np.asarray(velocities, dtype=float), (n, 3)).copy()
    )
    w = (
        np.zeros((n, 3))
        if angular_velocities is None
        else np.broadcast_to(np.asarray(angular_velocities, dtype=float), (n, 3)).copy()
    )
    rho = materials[mat_idx].density
    mass = rho * 4.0 / 3.0 * math.pi * r**3
    inertia = 0.4 * mass * r**2
    free = mo == FREE
    inv_m = np.where(free, 1.0 / mass, 0.0)
    inv_i = np.where(free, 1.0 / inertia, 0.0)
    try:
        dof = dof_mask(fixed_translation, fixed_rotation)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    ids = np.arange(first_id, first_id + n, dtype=np.int64)
    if ids.size and ids[-1] >= 2**31:
        raise InputError("more than 2**31 particles are not supported")
    values = {
        "id": ids, "x": x, "v": v, "w": w, "r": r, "mass": mass, "inv_m": inv_m, "inv_i": inv_i,
        "mat": np.full(n, mat_idx, np.int32), "motion": mo,
        "group": np.broadcast_to(np.asarray(group, dtype=np.int32), (n,)),
        "dof": np.full(n, dof, np.uint8),
    }  # fmt: skip
    for name, val in (fields or {}).items():
        spec = store.fields.get(name)
        if spec is None or name in values or name == "x_build":
            raise InputError(
                f"add_particles: unknown keyword {name!r}; registered fields: "
                f"{', '.join(sorted(set(store.fields) - set(values) - {'x_build', 'f', 't'}))}"
                " (register_field adds one)"
            )
        values[name] = np.broadcast_to(np.asarray(val, dtype=spec.dtype), spec.shape(n))
    return values, dof


@dataclass(frozen=True)
class Field:
    """A per-particle array.

    ``width`` 0 is a scalar per particle, 3 a vector. ``migrate``: carried to the new owner when a
    particle changes rank (owned particles keep every field; a field that does not migrate restarts
    from ``default`` there). ``ghost``: copied onto ghost copies at neighbour-list rebuilds (only
    positions, velocities and spins are refreshed every step). ``checkpoint``: saved and restored by
    id. ``output``: offered to snapshot writers."""

    name: str
    dtype: str
    width: int = 0
    migrate: bool = True
    ghost: bool = False
    checkpoint: bool = True
    output: bool = False
    default: float = 0
    doc: str = ""

    def __post_init__(self) -> None:
        if not self.name.isidentifier() or self.name.startswith("_"):
            raise ValueError(f"field name {self.name!r} must be an identifier not starting with '_'")
        if self.width not in (0, 3):
            raise ValueError(f"field {self.name!r}: width must be 0 (scalar) or 3 (vector)")
        np.dtype(self.dtype)  # raises TypeError for an unknown dtype

    def shape(self, n: int) -> tuple[int, ...]:
        return (n, self.width) if self.width else (n,)


BUILTIN_FIELDS = (
    Field("id", "int64", ghost=True, output=True, default=-1),
    Field("x", "float64", 3, ghost=True, output=True),
    Field("v", "float64", 3, ghost=True, output=True),
    Field("w", "float64", 3, ghost=True, output=True),
    Field("f", "float64", 3, output=True),
    Field("t", "float64", 3, output=True),
    Field("r", "float64", ghost=True, output=True),
    Field("mass", "float64", ghost=True, output=True),
    Field("inv_m", "float64", ghost=True),
    Field("inv_i", "float64", ghost=True),
    Field("mat", "int32", ghost=True, output=True),
    Field("motion", "int8", ghost=True, output=True),
    Field("group", "int32", ghost=True, output=True),
    Field("dof", "uint8", ghost=True, output=True),
    Field("x_build", "float64", 3, checkpoint=False),
)


class ParticleStore:
    """Structure of arrays with amortised growth. Field attributes (``p.x``, ``p.r``, …) are views
    of length ``n`` (owned + ghosts), cached until the counts or the capacity change."""

    def __init__(self, capacity: int = 0) -> None:
        self.capacity = 0
        self._n_owned = 0
        self._n_ghost = 0
        self._views: dict[str, np.ndarray] = {}
        self.fields: dict[str, Field] = {}
        self._data: dict[str, np.ndarray] = {}
        for spec in BUILTIN_FIELDS:
            self.fields[spec.name] = spec
        self._alloc(max(capacity, 16))

    # ------------------------------------------------------------------ registry
    def register(self, spec: Field) -> None:
        """Add a field (idempotent for an identical spec; a different spec under a used name is an
        error). Existing particles get the field's default."""
        old = self.fields.get(spec.name)
        if old is not None:
            if old != spec:
                raise ValueError(f"particle field {spec.name!r} is registered already, as {old}")
            return
        self.fields[spec.name] = spec
        self._data[spec.name] = np.full(spec.shape(self.capacity), spec.default, dtype=spec.dtype)
        self._invalidate()

    def names(self, *, migrate: bool | None = None, ghost: bool | None = None,
              checkpoint: bool | None = None, output: bool | None = None) -> list[str]:
        """Field names in registration order, filtered by their flags."""
        out = []
        for name, s in self.fields.items():
            if migrate is not None and s.migrate != migrate:
                continue
            if ghost is not None and s.ghost != ghost:
                continue
            if checkpoint is not None and s.checkpoint != checkpoint:
                continue
            if output is not None and s.output != output:
                continue
            out.append(name)
        return out

    # ------------------------------------------------------------------ counts
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
        for name, spec in self.fields.items():
            new = np.full(spec.shape(capacity), spec.default, dtype=spec.dtype)
            if old_cap:
                new[:old_cap] = self._data[name]
            self._data[name] = new
        self.capacity = capacity
        self._invalidate()

    def reserve(self, n: int) -> None:
        if n > self.capacity:
            self._alloc(max(n, int(self.capacity * 1.5) + 16))

    def __getattr__(self, name: str):
        # only reached for names that are not attributes: a field view not cached yet. The view is
        # then stored as an instance attribute, so later reads are plain attribute lookups (a step
        # reads ~40 fields; through __getattr__ that cost ~35 µs per step)
        d = self.__dict__
        data = d.get("_data")
        if data is not None and name in data:
            view = data[name][: self.n]
            d["_views"][name] = view
            d[name] = view
            return view
        raise AttributeError(name)

    # ------------------------------------------------------------------ adding, moving, removing
    def append_owned(self, values: dict[str, np.ndarray]) -> None:
        """Append owned particles (no ghosts may be present). ``values`` maps field names to arrays
        of the new particles (``id`` is required); fields not given take their default, and
        ``x_build`` is ``x``."""
        if self.n_ghost:
            raise RuntimeError("append_owned with ghosts present")
        unknown = set(values) - set(self.fields)
        if unknown:
            raise KeyError(f"unknown particle field(s) {sorted(unknown)}")
        k = len(values["id"])
        self.reserve(self.n_owned + k)
        s = slice(self.n_owned, self.n_owned + k)
        for name, spec in self.fields.items():
            if name in values:
                self._data[name][s] = values[name]
            elif name == "x_build" and "x" in values:
                self._data[name][s] = values["x"]
            else:
                self._data[name][s] = spec.default
        self.n_owned = self.n_owned + k

    def append_ghosts(self, values: dict[str, np.ndarray]) -> None:
        """Append ghost copies (fields not given take their default: forces, torques, …)."""
        n0 = self.n
        k = len(values["id"])
        self.reserve(n0 + k)
        s = slice(n0, n0 + k)
        for name, spec in self.fields.items():
            self._data[name][s] = values[name] if name in values else spec.default
        self.n_ghost = self.n_ghost + k

    def padded(self, name: str, extra: int) -> np.ndarray:
        """The field's array over the particles (owned and ghosts) and ``extra`` rows after them
        (scratch rows, e.g. for rigid bodies solved with the particles; call :meth:`reserve` with
        ``n + extra`` first). The first ``n`` rows are the particles' own storage."""
        if self.n + extra > self.capacity:
            raise RuntimeError("padded: reserve(n + extra) first")
        return self._data[name][: self.n + extra]

    def take(self, idx: np.ndarray, names) -> dict[str, np.ndarray]:
        """Copies of the rows ``idx`` of the named fields."""
        return {name: self._data[name][idx] for name in names}

    def swap_rows(self, a: np.ndarray, b: np.ndarray) -> None:
        """Exchange owned rows ``a[k]`` and ``b[k]`` (disjoint) in every field (no ghosts may be
        present): a reordering that costs the rows moved, not the whole storage."""
        if self.n_ghost:
            raise RuntimeError("storage can only be permuted without ghosts")
        if a.shape[0]:
            for arr in self._data.values():
                tmp = arr[a]
                arr[a] = arr[b]
                arr[b] = tmp

    def permute(self, perm: np.ndarray) -> None:
        """Reorder the owned particles in memory (no ghosts may be present)."""
        if self.n_ghost:
            raise RuntimeError("storage can only be permuted without ghosts")
        n = self.n_owned
        for arr in self._data.values():
            arr[:n] = arr[:n][perm]
