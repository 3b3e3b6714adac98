"""Walls: a geometric shape (:mod:`pdem.geometry.shapes`), a material and a motion.

A wall is an infinite-mass, infinite-radius contact partner that uses the simulation's contact
law. Its geometry is one or more packed rows (one for a primitive shape, one per facet for a mesh)
and its **pose**: a translation ``offset`` of its reference point, a rotation ``rotation`` (3 × 3,
about the initial reference point) and named **sizes** (``radius``, ``length``, … as the shape
declares them). A :class:`Motion` changes the pose every step (translate, turn, resize) and sets
the velocities the contact law sees: ``velocity`` (translation of the reference point [m/s]),
``omega`` (angular velocity [rad/s], about the reference point) and ``size_rate`` (rate of the
radius [m/s] for cylinders, surfaces of revolution and spheres). A wall built with ``omega`` and no
motion only spins its surface (a rotating drum): its shape does not turn.

The neighbour-list rebuild test uses :meth:`Wall.displacement_since_build`, a bound on how far any
point of the surface (within reach of the particles) has moved since the last rebuild: the net
translation, plus |angle| × reach for rotations, plus |Δsize| for size changes.

After every step ``Wall.force`` [N] and ``Wall.torque`` [N m] (about the wall's current reference
point) hold the total load the particles put on it, summed exactly (correctly rounded, hence
independent of summation order and of the number of MPI ranks); ``Wall.facet_loads()`` gives the
load of each row (each facet of a mesh).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ._kernels import PARAM_LAYOUT

__all__ = [
    "Wall",
    "Motion",
    "Fixed",
    "ConstantVelocity",
    "VelocityFunction",
    "PositionFunction",
    "Controlled",
    "Rotation",
    "Resize",
    "RigidBody",
    "Follow",
    "rotation_matrix",
]


def rotation_matrix(theta) -> np.ndarray:
    """Rotation by the angle vector ``theta`` (axis × angle [rad]), Rodrigues' formula."""
    th = np.asarray(theta, dtype=float)
    a = math.sqrt(float(th @ th))
    if a == 0.0:
        return np.eye(3)
    k = th / a
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(a) * kx + (1.0 - math.cos(a)) * (kx @ kx)


# ---------------------------------------------------------------------------------------------
# motions
# ---------------------------------------------------------------------------------------------


class Motion:
    """Moves a wall over one step. Override :meth:`move` (full control: ``wall.translate``,
    ``wall.rotate``, ``wall.resize``, and set ``wall.velocity``/``omega``/``size_rate``), or, for a
    pure translation, ``advance(t, dt, offset) -> (new offset, velocity over the step)``.
    :meth:`state`/:meth:`restore` keep what a checkpoint needs (arrays). ``moved_by_load``: the
    wall is a free body (its contacts with fixed grains count, with its mass)."""

    moved_by_load = False

    def move(self, wall: Wall, t: float, dt: float) -> None:
        offset, velocity = self.advance(t, dt, wall.offset)
        wall.velocity = np.asarray(velocity, dtype=float)
        wall.set_offset(offset)

    def advance(self, t: float, dt: float, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def state(self) -> dict[str, np.ndarray]:
        return {}

    def restore(self, state: dict[str, np.ndarray]) -> None:
        pass


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
    """Velocities set from outside every step (servo controllers, boundary plugins): translation
    ``velocity`` [m/s], rotation ``angular_velocity`` [rad/s] about the wall's reference point, and
    ``size_rates`` {size name: rate [m/s]} (e.g. ``{"radius": -1e-3}`` for a shrinking cylinder)."""

    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size_rates: dict[str, float] = field(default_factory=dict)

    def move(self, wall, t, dt):
        _move(wall, dt, np.asarray(self.velocity, float), np.asarray(self.angular_velocity, float),
              self.size_rates)  # fmt: skip

    def state(self):
        names = sorted(self.size_rates)
        return {
            "velocity": np.asarray(self.velocity, float),
            "angular_velocity": np.asarray(self.angular_velocity, float),
            "size_rates": np.array([self.size_rates[k] for k in names], float),
            "size_names": np.array(names, dtype="S"),
        }

    def restore(self, state):
        if "velocity" in state:
            self.velocity = np.array(state["velocity"], float)
        if "angular_velocity" in state:
            self.angular_velocity = np.array(state["angular_velocity"], float)
        if "size_names" in state:
            raw = np.atleast_1d(state["size_names"])
            names = [n.decode() if isinstance(n, bytes) else str(n) for n in raw]
            rates = (float(v) for v in np.atleast_1d(state["size_rates"]))
            self.size_rates = dict(zip(names, rates, strict=True))


@dataclass
class Rotation(Motion):
    """Constant angular velocity [rad/s] about ``centre`` (default: the wall's reference point); the
    shape turns (a tilting platen, a rotating paddle)."""

    angular_velocity: tuple[float, float, float]
    centre: tuple[float, float, float] | None = None

    def move(self, wall, t, dt):
        om = np.asarray(self.angular_velocity, float)
        if self.centre is None:
            _move(wall, dt, np.zeros(3), om, {})
            return
        c = np.asarray(self.centre, float)
        wall.rotate(om * dt, about=c)
        wall.velocity = np.cross(om, wall.reference_point - c)  # of the reference point, mid-step
        wall.omega = om
        wall.size_rate = 0.0


@dataclass
class Resize(Motion):
    """Sizes changing at constant rates {name: rate [m/s]}, e.g. ``Resize({"radius": -2e-3})``."""

    rates: dict[str, float]

    def move(self, wall, t, dt):
        _move(wall, dt, np.zeros(3), np.zeros(3), self.rates)


def _move(wall: Wall, dt: float, v: np.ndarray, om: np.ndarray, rates: dict[str, float]) -> None:
    if np.any(v != 0.0):
        wall.translate(v * dt)
    if np.any(om != 0.0):
        wall.rotate(om * dt)
    for name, rate in rates.items():
        if rate != 0.0:
            wall.resize(name, wall.sizes[name] + rate * dt)
    wall.velocity = v
    wall.omega = om
    wall.size_rate = float(rates.get("radius", 0.0))


@dataclass
class RigidBody(Motion):
    """A wall that is a free rigid body moved by the particles' load (a dropped penetrometer, a
    floating lid): mass ``mass`` [kg], isotropic moment of inertia ``inertia`` [kg m²] about its
    reference point (None: it does not turn), ``gravity`` [m/s²], an extra constant ``force`` [N],
    initial ``velocity``/``angular_velocity``, and ``fixed_translation``/``fixed_rotation`` axes
    (e.g. ``"xy"``: it moves along z only).

    Each step (symplectic Euler, explicit in the load): v += dt (F/m + g), x += dt v, with F the
    load the particles put on the wall in the previous step; likewise ω += dt T/I and the wall
    turns by ω dt. The load is an exact sum, so the motion is the same on any number of ranks.

    Holding (a boundary's inactive stages, a body parked until it is dropped): :meth:`hold` stops
    the body where it stands: from the next step on it does not move, its velocities are zero and
    it acts as a fixed wall (``moved_by_load`` is false: DEM-C does not solve it with the grains,
    fixed grains do not push it), whatever its load, gravity or ``force``. :meth:`release` resumes
    the integration, from rest or from given velocities; :meth:`set_velocity` sets the velocities
    of a released body (e.g. to stop it before a stage). ``held``, ``velocity_now`` and
    ``angular_velocity_now`` read the state. A held body's checkpoint (:meth:`state`) carries
    ``held``; a state without it (a released body, or a checkpoint written before holding existed)
    restores a released body. Switching a wall off (``Simulation.set_wall_active``) does not hold
    its body: an inactive free body keeps moving under gravity and ``force`` unless held."""

    mass: float
    inertia: float | None = None
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fixed_translation: str = ""
    fixed_rotation: str = ""

    def __post_init__(self) -> None:
        if not (self.mass > 0 and math.isfinite(self.mass)):
            raise InputError(f"RigidBody: mass = {self.mass!r} must be positive and finite [kg]")
        if self.inertia is not None and not (self.inertia > 0 and math.isfinite(self.inertia)):
            raise InputError(f"RigidBody: inertia = {self.inertia!r} must be positive [kg m²] or None")
        self._v = np.asarray(self.velocity, float).copy()
        self._w = np.asarray(self.angular_velocity, float).copy()
        self._free_t = np.array([a not in self.fixed_translation for a in "xyz"], float)
        self._free_r = np.array([a not in self.fixed_rotation for a in "xyz"], float)
        if self.inertia is None:
            self._free_r[:] = 0.0
        self._v *= self._free_t
        self._w *= self._free_r
        self._held = False

    implicit = False  # DEM-C solves the body with the grains (its stepper sets this)

    @property
    def moved_by_load(self) -> bool:  # type: ignore[override]
        """A free body (its contacts with fixed grains count, with its mass), unless held."""
        return not self._held

    @property
    def held(self) -> bool:
        """Whether the body is held (:meth:`hold`): it does not move and its velocities are zero."""
        return self._held

    @property
    def velocity_now(self) -> np.ndarray:
        """The body's velocity [m/s] (a copy; zero while held)."""
        return self._v.copy()

    @property
    def angular_velocity_now(self) -> np.ndarray:
        """The body's angular velocity [rad/s] (a copy; zero while held or without ``inertia``)."""
        return self._w.copy()

    def hold(self) -> None:
        """Hold the body where it stands: from the next step on it does not move and its velocity
        and angular velocity are zero (a fixed wall), until :meth:`release`. Holding a held body
        changes nothing."""
        self._held = True
        self._v = np.zeros(3)
        self._w = np.zeros(3)

    def release(self, velocity=None, angular_velocity=None) -> None:
        """Let the body move again from the next step on: from rest, or from ``velocity`` [m/s] and
        ``angular_velocity`` [rad/s] when given (components along fixed axes are dropped). Releasing
        a body that is not held keeps its velocities unless given (so calling it at the start of
        every stage is harmless)."""
        self._held = False
        self.set_velocity(self._v if velocity is None else velocity, angular_velocity)

    def set_velocity(self, velocity, angular_velocity=None) -> None:
        """Set the body's velocity [m/s] (and angular velocity [rad/s] when given; it stays otherwise)
        from the next step on; components along fixed axes are dropped. A held body must be
        released first (:meth:`release` takes the velocities too)."""
        if self._held:
            raise InputError(
                f"RigidBody.set_velocity: velocity = {velocity!r} was given while the body is held; a "
                "held body stays at rest. Release it with the velocity instead: release(velocity=...)"
            )
        v = _vector3("velocity", velocity, "m/s")
        w = None if angular_velocity is None else _vector3("angular_velocity", angular_velocity, "rad/s")
        self._v = v * self._free_t
        if w is not None:
            self._w = w * self._free_r

    @property
    def free_axes(self) -> np.ndarray:
        return self._free_t

    @property
    def dof_bits(self) -> int:
        """Locked axes as particle ``dof`` bits (rotation always locked in the implicit solve)."""
        return int(sum(1 << c for c in range(3) if self._free_t[c] == 0.0)) | 0b111000

    def free_velocity(self, dt: float) -> np.ndarray:
        """v + dt (g + F/m): the body's velocity before the contact impulses (DEM-C); zero while
        held."""
        if self._held:
            return np.zeros(3)
        acc = np.asarray(self.force, float) / self.mass + np.asarray(self.gravity, float)
        return (self._v + dt * acc) * self._free_t

    def finish(self, wall, v: np.ndarray, dt: float) -> None:
        """After the DEM-C solve: take the solved velocity and move by dt v (held: stay at rest)."""
        self._v = np.zeros(3) if self._held else v * self._free_t
        wall.translate(dt * self._v)
        wall.velocity = self._v.copy()
        wall.omega = np.zeros(3)
        wall.size_rate = 0.0

    def move(self, wall, t, dt):
        if self._held:
            _move(wall, dt, np.zeros(3), np.zeros(3), {})  # at rest: a fixed wall
            return
        if self.implicit:
            return  # moved by the DEM-C stepper after its solve
        load_f = wall.force  # collective under MPI: every rank advances walls together
        load_t = wall.torque
        acc = (load_f + np.asarray(self.force, float)) / self.mass + np.asarray(self.gravity, float)
        self._v = (self._v + dt * acc) * self._free_t
        if self.inertia is not None:
            self._w = (self._w + dt * load_t / self.inertia) * self._free_r
        _move(wall, dt, self._v, self._w, {})

    def state(self):
        out = {"velocity": self._v.copy(), "angular_velocity": self._w.copy()}
        if self._held:  # only then: a released body's checkpoint is as it always was
            out["held"] = np.array(True)
        return out

    def restore(self, state):
        if "velocity" in state:
            self._v = np.array(state["velocity"], float)
            self._w = np.array(state["angular_velocity"], float)
            self._held = bool(state["held"]) if "held" in state else False


def _vector3(key: str, value, unit: str) -> np.ndarray:
    """``value`` as three finite floats, else an InputError naming ``key``."""
    try:
        a = np.array(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        a = np.array([np.nan])
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(
            f"RigidBody: {key} = {value!r} must be three finite numbers [{unit}], e.g. (0, 0, -0.1)"
        )
    return a


class Follow(Motion):
    """Moves with another wall, ``leader``, at a fixed ``delta`` [m] from its offset (a ring tied to a
    platen). Translation only: the follower takes the leader's offset + ``delta`` and its velocity
    each step. The leader must have been added before the follower (walls advance in that order), so
    the follower stands where the leader stands now; a leader moved by the DEM-C solve (a free
    :class:`RigidBody`) moves after the walls advance, and the follower catches up a step later."""

    def __init__(self, leader: Wall, delta=(0.0, 0.0, 0.0)) -> None:
        self.leader = leader
        self.delta = np.asarray(delta, dtype=float)

    def move(self, wall, t, dt):
        wall.velocity = np.asarray(self.leader.velocity, float).copy()
        wall.omega = np.zeros(3)
        wall.size_rate = 0.0
        wall.set_offset(self.leader.offset + self.delta)


# ---------------------------------------------------------------------------------------------
# the wall
# ---------------------------------------------------------------------------------------------


class Wall:
    """A wall in a simulation (created by :meth:`pdem.Simulation.add_wall`); see the module
    docstring for its pose and motions."""

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
        self.size_rate = 0.0
        self.rotation = np.eye(3)
        self.offset_build = np.zeros(3)
        self._swept = 0.0  # rotation and size changes since the last rebuild [m]
        self.reach = math.inf  # distance from the reference point to the farthest particle [m]
        self._load: np.ndarray | None = np.zeros(6)
        self._counts = ()
        self._segments: list[tuple[np.ndarray, int]] = []
        kinds, rows = _rows_of(shape)
        self.kinds = kinds
        self._base_rows = rows
        self._base_ref = np.asarray(shape.reference_point, dtype=float)
        self.sizes: dict[str, float] = dict(getattr(shape, "sizes", lambda: {})())
        self._base_sizes = dict(self.sizes)
        self.rows = rows.copy()
        self.reference_point = self._base_ref.copy()

    # ------------------------------------------------------------------ geometry
    @property
    def params(self) -> np.ndarray:
        """The packed geometry of a one-row wall (a primitive shape); see :attr:`rows`."""
        return self.rows[0]

    @property
    def n_rows(self) -> int:
        return self.rows.shape[0]

    @property
    def moving(self) -> bool:
        return not isinstance(self.motion, Fixed)

    def _update(self) -> None:
        rows = self._base_rows.copy()
        if self.sizes != self._base_sizes:
            for name, value in self.sizes.items():
                self.shape.apply_size(rows, name, value)
        if not np.array_equal(self.rotation, np.eye(3)):
            c = self._base_ref
            rows[:, 0:3] = c + (rows[:, 0:3] - c) @ self.rotation.T
            for r, kind in enumerate(self.kinds):
                for slot in PARAM_LAYOUT[int(kind)]:
                    rows[r, slot : slot + 3] = self.rotation @ rows[r, slot : slot + 3]
        rows[:, 0:3] += self.offset
        self.rows = rows
        self.reference_point = self._base_ref + self.offset

    def set_offset(self, offset) -> None:
        """Place the wall's reference point at ``offset`` [m] from where it was built."""
        self.offset = np.asarray(offset, dtype=float)
        if np.array_equal(self.rotation, np.eye(3)) and self.sizes == self._base_sizes:
            rows = self._base_rows.copy()  # the translation-only path: the anchor moves, nothing else
            rows[:, 0:3] += self.offset
            self.rows = rows
            self.reference_point = self._base_ref + self.offset
        else:
            self._update()

    def translate(self, d) -> None:
        self.set_offset(self.offset + np.asarray(d, dtype=float))

    def rotate(self, theta, about=None) -> None:
        """Turn by the angle vector ``theta`` [rad] about the point ``about`` (default the reference
        point)."""
        th = np.asarray(theta, dtype=float)
        q = rotation_matrix(th)
        c = self.reference_point if about is None else np.asarray(about, dtype=float)
        ref = self.reference_point
        new_ref = c + q @ (ref - c)
        self.rotation = q @ self.rotation
        self._swept += math.sqrt(float(th @ th)) * self.reach
        self.offset = new_ref - self._base_ref
        self._update()

    def resize(self, name: str, value: float) -> None:
        """Set the size ``name`` (see ``shape.sizes()``) to ``value`` [m]."""
        if name not in self.sizes:
            raise InputError(
                f"wall '{self.name}': no size named {name!r}; sizes of a {type(self.shape).__name__}: "
                f"{sorted(self.sizes) or 'none'}"
            )
        value = float(value)
        if not (math.isfinite(value) and value >= 0.0):
            raise InputError(f"wall '{self.name}': {name} = {value!r} must be finite and >= 0 [m]")
        self._swept += abs(value - self.sizes[name])
        self.sizes[name] = value
        self._update()

    def advance(self, t: float, dt: float) -> bool:
        """Move over one step; returns whether the wall moved."""
        if not self.moving:
            return False
        self.motion.move(self, t, dt)
        return True

    def displacement_since_build(self) -> float:
        d = self.offset - self.offset_build
        return math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + self._swept

    def mark_built(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """At a rebuild: reset the displacement and note the reach over the particles' box."""
        self.offset_build = self.offset.copy()
        self._swept = 0.0
        if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)):
            wlo, whi = self.bounding_box()
            ref = self.reference_point
            # the particles' box clipped to the wall's: its farthest corner from the reference point,
            # in Python floats (8 corners; NumPy's per-call overhead made this ~100 µs a rebuild)
            span = []
            for k in range(3):
                a = min(max(float(lo[k]), float(wlo[k])), float(whi[k])) - float(ref[k])
                b = min(max(float(hi[k]), float(wlo[k])), float(whi[k])) - float(ref[k])
                span.append(max(a * a, b * b))
            self.reach = math.sqrt(span[0] + span[1] + span[2])
        else:
            self.reach = 0.0

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box of the surface in its current pose [m] (conservative when turned). Kept
        for the pose it was computed for (offset, rotation and sizes compared by value): a rebuild
        asks every wall, and DEM-C rebuilds at most steps (~55 µs a call on the hopper's walls)."""
        pose = (self.offset.tobytes(), self.rotation.tobytes(), tuple(self.sizes.items()))
        cached = getattr(self, "_bbox_cache", None)
        if cached is not None and cached[0] == pose:
            return cached[1].copy(), cached[2].copy()
        lo, hi = self._bounding_box()
        self._bbox_cache = (pose, np.array(lo, dtype=float), np.array(hi, dtype=float))
        return lo, hi

    def _bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        if np.array_equal(self.rotation, np.eye(3)) and self.sizes == self._base_sizes:
            return self.shape.bounding_box(self.offset)
        lo, hi = self.shape.bounding_box()
        if self.sizes != self._base_sizes:  # grown: pad by the largest growth
            grow = max(0.0, max(self.sizes[k] - self._base_sizes[k] for k in self.sizes))
            lo, hi = lo - grow, hi + grow
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            if np.array_equal(self.rotation, np.eye(3)):
                return lo + self.offset, hi + self.offset
            return np.full(3, -np.inf), np.full(3, np.inf)
        c = self._base_ref
        turned = c + (_corners(lo, hi) - c) @ self.rotation.T + self.offset
        return turned.min(axis=0), turned.max(axis=0)

    # ------------------------------------------------------------------ loads
    def record_load(self, count: int, values: np.ndarray | None = None) -> None:
        """One-row walls: ``values[:count]`` holds this step's contributions (summed lazily)."""
        self.record_rows([count], None if values is None else [values])

    def record_rows(self, counts, buffers=None) -> None:
        """Row by row: ``buffers[r][:counts[r]]`` holds row r's contributions this step."""
        if buffers is not None:
            self._buffers = list(buffers)
        # an array is kept as given (the contact store passes a view of its counts, rewritten at every
        # step, as the buffers are): converting and summing them here cost ~4 µs a wall at every step
        self._counts = counts if isinstance(counts, np.ndarray) else list(counts)
        self._load = None

    @property
    def n_contacts(self) -> int:
        """This rank's contacts with the wall at the last force evaluation."""
        return int(sum(self._counts))

    def _values(self) -> np.ndarray:
        bufs = getattr(self, "_buffers", [])
        parts = [b[:c] for b, c in zip(bufs, self._counts, strict=False)]
        return np.concatenate(parts).reshape(-1, 6) if parts else np.zeros((0, 6))

    def _reduced(self) -> np.ndarray:
        if self._load is None:
            vals = self._values()
            comm = getattr(self, "_comm", None)
            if comm is not None and comm.size > 1:  # collective: every rank reads the load together
                from ..parallel.exact import exact_sums

                self._load = exact_sums(comm, vals)
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

    def facet_loads(self) -> np.ndarray:
        """(rows, 6) load of each row (each facet of a mesh): force [N] and torque about the wall's
        reference point [N m], exact sums (collective under MPI)."""
        bufs = getattr(self, "_buffers", [])
        out = np.zeros((self.n_rows, 6))
        comm = getattr(self, "_comm", None)
        for r in range(self.n_rows):
            # a wall just switched on or off recorded no rows yet (``record_load(0)``): no load
            vals = bufs[r][: self._counts[r]] if r < min(len(bufs), len(self._counts)) else np.zeros((0, 6))
            if comm is not None and comm.size > 1:
                from ..parallel.exact import exact_sums

                out[r] = exact_sums(comm, vals.reshape(-1, 6))
            else:
                out[r] = [math.fsum(vals[:, c]) for c in range(6)]
        return out


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The 8 corners of the box [lo, hi]."""
    return np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])


def _rows_of(shape) -> tuple[np.ndarray, np.ndarray]:
    """(kinds, rows) of a shape: its own ``rows()`` (meshes), else one row."""
    if hasattr(shape, "rows"):
        kinds, rows = shape.rows()
        return np.asarray(kinds, dtype=np.int64), np.asarray(rows, dtype=np.float64)
    return np.array([shape.kind], dtype=np.int64), np.asarray(shape.params(np.zeros(3)), dtype=float)[None, :]
