"""The simulation: particles, walls, a contact law, and the time step written once.

Python API (SI units throughout)::

    import pdem
    sim = pdem.Simulation()
    sim.add_material("glass", density=2500, youngs_modulus=5e7, poisson_ratio=0.3,
                     restitution=0.5, friction=0.5)
    sim.add_particles(positions, radii, material="glass")
    sim.add_wall(pdem.shapes.Plane((0, 0, 0), (0, 0, 1)), material="glass", name="floor")
    sim.set_periodic(lo=(0, 0, 0), hi=(0.05, 0.02, 0), axes="xy")   # optional: periodic sides
    sim.gravity = (0, 0, -9.81)      # none unless set, here and in a deck's [run] alike
    sim.run(steps=1000)            # or sim.run(until=0.1)
    p = sim.get_particles()        # arrays ordered by particle id
    sim.walls["floor"].force       # load on the floor [N]

The DEM-P time step (velocity Verlet, ARCHITECTURE.md)::

    initial_integrate   v += a dt/2; x += v dt; ω half step
    move walls
    if max displacement (particles + walls) > skin/2 → wrap into the periodic box, migrate, ghosts
                        and periodic images, rebuild neighbours, carry history
    forces              pairs (sorted by id pair) → walls (in order) → body forces
    final_integrate     v += a dt/2; ω
    check flags         overlap runaway, non-finite state → InstabilityError
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from collections.abc import Callable
from typing import Any

import numpy as np

from . import diagnose as _diag
from .contact._kernels import FLAG_NONFINITE
from .contact.law import ContactLaw
from .contact.stability import StiffnessMonitor
from .contact.store import ContactStore
from .domain import PeriodicBox
from .errors import GeometryError, InputError, PdemError
from .geometry.walls import Motion, Wall
from .integrate import _kernels as integ
from .materials import Material, MaterialTable
from .neighbor.list import SKIN_MAX, SKIN_MIN, SKIN_STEPS, NeighbourList  # noqa: F401 - re-exported
from .parallel.comm import SerialComm, all_max, all_min, any_rank, gather_by_id
from .parallel.exact import exact_column_sums, exact_sum, global_count
from .parallel.work import WorkModel
from .plugins import load_contact_law
from .state.particles import FREE, REMOVED, Field, ParticleStore, dof_mask, new_particles
from .state.removal import Removals

__all__ = ["Simulation"]


class Simulation:
    """A DEM simulation. See the module docstring for the API and the time step.

    Parameters
    ----------
    comm:
        MPI communicator (default: a one-rank serial communicator). On several ranks space is
        decomposed (:mod:`pdem.parallel.decomposition`) and results are bitwise those of one rank.
    law:
        Contact-law name (an entry point of ``pdem.contact_laws``) or a :class:`ContactLaw`.
    """

    def __init__(self, comm=None, law: str | ContactLaw = "hertz_mindlin", **law_params: Any) -> None:
        self.comm = comm if comm is not None else SerialComm()
        self._decomp = None  # a Decomposition when running on several ranks, or periodic
        self._share = None  # (layout, saved forces) of a checkpoint share being restored
        self._early_decomp = False  # placed before the first preparation (place_decomposition)
        self.box: PeriodicBox | None = None  # periodic axes (set_periodic)
        self._snap = np.zeros(3)  # per-axis displacement rounding of the integrator (periodic axes)
        self.removals = Removals(self)  # particles taken out (outflows), and the global count
        self.decomposition_dims: tuple[int, int, int] | None = None
        self.balance_threshold = 1.05  # rebalance when max/mean estimated work exceeds this
        self.materials = MaterialTable()
        self.particles = ParticleStore()
        self.walls: dict[str, Wall] = {}
        self._wall_list: list[Wall] = []
        self.boundaries: dict[str, Any] = {}
        self._hooks: dict[str, list] = {"before_step": [], "apply_forces": [], "after_step": []}
        self.stage: str | None = None
        self.contact_store = ContactStore(1)
        self._started = False
        self.set_law(law, **law_params)
        self.gravity = (0.0, 0.0, 0.0)
        self._dt: float | None = None
        #: with no dt: the step as this multiple of the law's stability estimate (None: the law's choice)
        self.dt_fraction: float | None = None
        self.force_dt = False
        self.max_overlap = 0.25
        self.time = 0.0
        self.step_count = 0
        self._next_id = 0
        self._prepared = False
        # a step's kernel flags left for the next collective (step(defer_check=True)); None: none
        self._pending_flags: int | None = None
        self._defer_check = False
        self.dt_critical = math.nan
        #: the live step bound from the contacts' stiffness and the boundary loads' stiffness
        self.stiffness_monitor = StiffnessMonitor(self)
        self.integrator = None  # made by the law at preparation (velocity Verlet, DEM-C stepper, …)
        self.envelope = 0.0  # collision envelope of DEM-C [m]: pairs this far apart enter the problem
        self.neighbours = NeighbourList(self)  # the list, its reach, storage order and rebuild
        self.work = WorkModel(self)  # this rank's work, for the load balance

    # ------------------------------------------------------------------ setup
    def set_law(self, law: str | ContactLaw, **params: Any) -> None:
        """Choose the contact law by entry-point name (``"hertz_mindlin"``) or instance (before the
        first step)."""
        if self._started:
            raise InputError("set_law must be called before the first step (the run has started)")
        self.law = load_contact_law(law, **params) if isinstance(law, str) else law
        walls = self.contact_store.walls
        self.contact_store = ContactStore(self.law.history_size)
        self.contact_store.walls = walls
        self.integrator = None
        self._prepared = False

    # ------------------------------------------------------------------ time step, gravity
    @property
    def dt(self) -> float | None:
        """The time step [s] (None: chosen by the law at the first step). Checked when set: positive
        and finite, and once the run is prepared not above the law's stability estimate
        ``dt_critical`` unless ``force_dt``."""
        return self._dt

    @dt.setter
    def dt(self, value: float | None) -> None:
        if value is None:
            if self._started:
                raise InputError("dt cannot be unset once the run has started")
            self._dt = None
            return
        try:
            value = float(value)
        except (TypeError, ValueError):
            raise InputError(f"dt = {value!r} is invalid; give a positive time step in seconds") from None
        if not (value > 0 and math.isfinite(value)):
            raise InputError(f"dt = {value!r} is invalid; give a positive time step in seconds")
        if self._prepared:
            self._check_dt(value)
        self._dt = value

    def _check_dt(self, dt: float) -> None:
        if dt > self.dt_critical and not self.force_dt:
            raise InputError(
                f"dt = {dt:.4g} s exceeds the stability estimate {self.dt_critical:.4g} s of law "
                f"'{self.law.name}'; use dt ≤ {self.dt_critical:.4g} s (practice: 0.1–0.3 of it), or set "
                "force_dt = true to run anyway"
            )

    @property
    def g(self) -> np.ndarray:
        """Gravity as a validated array [m/s²] (set ``gravity``; checked at preparation)."""
        return self._g

    @property
    def position_snap(self) -> np.ndarray:
        """Per-axis rounding constants of displacements along periodic axes (0: not periodic); see
        :mod:`pdem.domain`. Integrators pass it to their position update."""
        return self._snap

    @property
    def decomposition(self):
        """The :class:`~pdem.parallel.decomposition.Decomposition` (None in a serial non-periodic run)."""
        return self._decomp

    # ------------------------------------------------------------------ boundaries
    _HOOKS = ("before_step", "apply_forces", "after_step")

    def add_boundary(self, boundary: Any, build: bool = True) -> Any:
        """Add a boundary (an instance of :class:`pdem.boundaries.api.Boundary`): its ``build`` is
        called now (unless ``build=False``), and its hooks run inside every :meth:`step`, whether the
        step is driven by a deck's runner or by :meth:`run`: ``before_step`` (servo control),
        ``apply_forces`` (adds forces and torques to owned particles after the contact forces;
        DEM-C takes them into the free velocity) and ``after_step`` (sinks, probes). Boundaries run
        in the order they were added; inactive ones (``set_stage``) are skipped."""
        name = boundary.name
        if name in self.boundaries:
            raise InputError(f"boundary name '{name}' is used twice; give each boundary a unique name")
        self.boundaries[name] = boundary
        if build:
            boundary.build(self)
        from .boundaries.api import Boundary

        for hook in self._HOOKS:
            impl = getattr(type(boundary), hook, None)
            if impl is not None and impl is not getattr(Boundary, hook, None):
                self._hooks[hook].append(boundary)
        self._prepared = False
        return boundary

    def set_stage(self, name: str) -> None:
        """Enter stage ``name``: every boundary is told (``on_stage``) and switches itself on or off."""
        self.stage = name
        for b in self.boundaries.values():
            b.on_stage(self, name)

    def _run_hooks(self, hook: str) -> None:
        for b in self._hooks[hook]:
            if b.active:
                try:
                    getattr(b, hook)(self)
                except PdemError:
                    raise
                except Exception as exc:  # a plugin's bug: say whose, not a bare traceback
                    from .errors import PluginError

                    raise PluginError(
                        f"boundary '{b.name}' ({type(b).__module__}.{type(b).__name__}) failed in "
                        f"{hook} at step {self.step_count}: {type(exc).__name__}: {exc}. This is a "
                        "fault of the boundary plugin; fix or update it"
                    ) from exc

    # ------------------------------------------------------------------ per-particle fields
    def register_field(self, name: str, dtype: str = "float64", width: int = 0, **flags: Any) -> Field:
        """Register a per-particle field (see :class:`pdem.state.particles.Field` for the flags
        ``migrate``, ``ghost``, ``checkpoint``, ``output``, ``default``); it is then the array
        ``sim.particles.<name>`` (storage order, owned particles first), kept through migration,
        ghosting and checkpoints as declared. Registering an identical field twice is allowed."""
        spec = Field(name, dtype, width, **flags)
        try:
            self.particles.register(spec)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        return spec

    def set_dof(self, ids, translation: str = "", rotation: str = "") -> None:
        """Lock the translation along and the rotation about the named axes (``"xyz"``, ``"y"``, ``""``:
        free) of the particles with ``ids`` (all ranks call it alike). Locked velocity components are
        set to zero and stay zero, in both methods. 2-D motion in the xz plane:
        ``set_dof(ids, translation="y", rotation="xz")``."""
        try:
            mask = dof_mask(translation, rotation)
        except ValueError as exc:
            raise InputError(str(exc)) from None
        p = self.particles
        n = p.n_owned
        rows = np.flatnonzero(np.isin(p.id[:n], np.asarray(ids, dtype=np.int64)))
        p.dof[rows] = mask
        self._zero_locked(rows)

    def _zero_locked(self, rows: np.ndarray) -> None:
        p = self.particles
        for c in range(3):
            lock_t = (p.dof[rows] >> c) & 1 == 1
            p.v[rows[lock_t], c] = 0.0
            lock_r = (p.dof[rows] >> (3 + c)) & 1 == 1
            p.w[rows[lock_r], c] = 0.0

    def set_periodic(self, lo, hi, axes="xyz") -> PeriodicBox:
        """Make the box ``lo <= x < hi`` [m] periodic along ``axes`` (``"xy"``, ``["x", "z"]``, …).

        Only the components of ``lo``/``hi`` along periodic axes are used; they are rounded to the
        position grid of :mod:`pdem.domain` (a relative change below 1e-15; ``sim.box`` holds the
        values in force). Particles outside the box along a periodic axis are wrapped into it.
        Every periodic length must be at least twice the largest pair cutoff 2 r_max + skin
        (checked when the run starts). Walls are not periodic: along a periodic axis use infinite
        planes parallel to it, and keep finite walls a ghost width away from the box faces.
        Call before the first step.
        """
        if self._started:
            raise InputError("set_periodic must be called before the first step (the run has started)")
        self.box = PeriodicBox(lo, hi, axes)
        self._snap = self.box.snap.copy()
        self._prepared = False
        return self.box

    def add_material(self, material: Material | str, **props: float) -> int:
        """Add a :class:`Material` (or build one from a name and keyword properties)."""
        mat = material if isinstance(material, Material) else Material(material, **props)
        self._prepared = False
        return self.materials.add(mat)

    #: material properties :meth:`set_material` may change during a run (no mass, stiffness or step change)
    MUTABLE_MATERIAL_KEYS = ("friction", "restitution", "rolling_friction", "spinning_friction")

    def set_material(self, name: str, **values: float) -> bool:
        """Change the ``friction``, ``restitution``, ``rolling_friction`` or ``spinning_friction`` of
        material ``name`` from
        the next force evaluation on (e.g. frictionless grains while a sample is prepared, then the
        real friction for the test). Density and stiffness cannot change: they set masses and the
        time step. The law's coefficient table is rebuilt in place; contact histories are kept (a
        tangential spring above the new Coulomb cap is cut back at its next evaluation). Every rank
        must make the same call. Returns True if anything changed."""
        k = self.materials.index(name)
        old = self.materials[k]
        bad = sorted(set(values) - set(self.MUTABLE_MATERIAL_KEYS))
        if bad:
            raise InputError(
                f"set_material('{name}'): cannot change {', '.join(bad)} during a run; changeable: "
                f"{', '.join(self.MUTABLE_MATERIAL_KEYS)}"
            )
        new = dataclasses.replace(old, **values)  # validates the ranges
        if new == old:
            return False
        self.materials.materials[k] = new
        if self._prepared:
            self.coefficients = self.law.coefficients(self.materials)
        return True

    def add_particles(
        self,
        positions,
        radii,
        material: str = None,
        velocities=None,
        angular_velocities=None,
        motion: str | Any = "free",
        group: int = 0,
        fixed_translation: str = "",
        fixed_rotation: str = "",
        **fields: Any,
    ) -> np.ndarray:
        """Add spheres; returns their ids (consecutive, in the order given).

        ``radii`` may be a scalar. ``motion``: ``"free"`` (integrated), ``"fixed"`` (never moves) or
        ``"prescribed"`` (moves with its given velocity, unaffected by forces), for all particles or
        one name per particle (a bed whose edge grains are fixed). Fixed and prescribed particles act
        as infinitely massive in contacts. ``group``: an integer tag (scalar or per
        particle). ``fixed_translation``/``fixed_rotation``: axes along/about which the particles may
        not move or turn (see :meth:`set_dof`). Other keywords give values of registered fields
        (all checked by :func:`pdem.state.particles.new_particles`).
        """
        values, dof = new_particles(
            self.particles, self.materials, self.box, self._next_id, positions, radii, material, velocities,
            angular_velocities, motion, group, fixed_translation, fixed_rotation, fields,
        )  # fmt: skip
        ids = values["id"]
        self._keep_batch(values, dof, ids.size)
        return ids

    def _keep_batch(self, values: dict[str, np.ndarray], dof: int, total: int) -> np.ndarray:
        """Append the new particles ``values`` (a batch of ``total``, all of it or this rank's part
        of it) that this rank owns; the ids advance by ``total``. Returns the ids kept."""
        self._next_id += int(total)
        if self._decomp is not None:  # every rank is given the batch (or its part) and keeps its own
            keep = self._decomp.owned_mask(values["x"])
            values = {k: a[keep] for k, a in values.items()}
            self.particles.n_ghost = 0
            self.removals.n_expected += int(total)
        n0 = self.particles.n_owned
        self.particles.append_owned(values)
        if dof:
            self._zero_locked(np.arange(n0, self.particles.n_owned))
        self._prepared = False
        return values["id"]

    def place_decomposition(self, sample) -> None:
        """Split space over the ranks before the particles exist, at the quantiles of ``sample``
        (centres, the same on every rank: a partitioned source's survey), so that each rank can make
        only its own particles (:meth:`add_particle_part`). Collective; nothing happens serially
        without a periodic box or once the cut planes are placed."""
        from .parallel.decomposition import Decomposition

        sample = np.asarray(sample, dtype=float).reshape(-1, 3)
        if self._decomp is None:
            if self.comm.size == 1 and self.box is None:
                return
            p = self.particles
            n = p.n_owned  # particles of earlier sources, the same on every rank until now
            dims = self.decomposition_dims
            self._decomp = Decomposition(self.comm, sample, dims, min_width=0.0, box=self.box)
            self._early_decomp = True
            keep = self._decomp.owned_mask(p.x[:n])
            p.permute(np.concatenate([np.flatnonzero(keep), np.flatnonzero(~keep)]))
            p.n_owned = int(keep.sum())
            self.removals.n_expected = n
        elif not self._decomp.placed:
            self._decomp.owned_mask(sample)  # places the provisional planes at the sample (collective)

    def add_particle_part(
        self,
        positions,
        radii,
        index,
        total: int,
        material: str = None,
        velocities=None,
        angular_velocities=None,
        motion: str | Any = "free",
        group: int = 0,
        fixed_translation: str = "",
        fixed_rotation: str = "",
        **fields: Any,
    ) -> np.ndarray:
        """Add this rank's share of a batch of ``total`` new particles: ``positions`` and ``radii``
        (and the other arguments of :meth:`add_particles`, per particle or scalar) of some of them,
        ``index`` their places in the batch (ids are ``next_id + index``, as :meth:`add_particles` of
        the whole batch would give); each rank keeps the ones it owns (given at least those).
        Collective in effect: every rank calls it for the same batch, after
        :meth:`place_decomposition`. Returns the ids kept."""
        values, dof = new_particles(
            self.particles, self.materials, self.box, self._next_id, positions, radii, material, velocities,
            angular_velocities, motion, group, fixed_translation, fixed_rotation, fields,
        )  # fmt: skip
        if self._decomp is None and len(values["id"]) != int(total):
            raise InputError(
                f"add_particle_part: {len(values['id'])} of a batch of {total} particles given to a run "
                "without a decomposition (serial): give the whole batch, or use add_particles"
            )
        values["id"] = self._next_id + np.asarray(index, dtype=np.int64)
        return self._keep_batch(values, dof, total)

    def add_wall(
        self,
        shape,
        material: str = None,
        name: str | None = None,
        motion: Motion | None = None,
        omega=(0.0, 0.0, 0.0),
    ) -> Wall:
        """Add a wall of the given shape; ``motion`` prescribes its translation."""
        if name is None:
            name = f"{getattr(shape, 'name_hint', 'wall')}{len(self._wall_list)}"
        if name in self.walls:
            raise InputError(f"wall name '{name}' is used twice; give each wall a unique name")
        if material is None:
            if len(self.materials) != 1:
                raise InputError(f"wall '{name}': name its material (several or no materials are defined)")
            mat_idx = 0
        else:
            mat_idx = self.materials.index(material)
        wall = Wall(shape, mat_idx, name, motion, omega)
        self.walls[name] = wall
        self._wall_list.append(wall)
        self.contact_store.walls = self._wall_list
        self.contact_store.walls_changed = True
        self._prepared = False
        return wall

    def set_wall_active(self, name: str, active: bool) -> None:
        """Switch a wall on or off (an inactive wall exerts no force; its contact history is reset)."""
        if name not in self.walls:
            raise InputError(f"no wall named '{name}'; walls: {', '.join(self.walls) or '(none)'}")
        wall = self.walls[name]
        if wall.active == active:
            return
        wall.active = active
        self.contact_store.reset_wall(self._wall_list.index(wall))
        wall.record_load(0)
        self.neighbours.force_rebuild = True
        self.contact_store.walls_changed = True

    def set_wall_motion(self, name: str, motion: Motion) -> None:
        """Give wall ``name`` a new motion from the next step on (e.g. a servo during one stage, a
        constant velocity during the next). Its pose is kept."""
        if name not in self.walls:
            raise InputError(f"no wall named '{name}'; walls: {', '.join(self.walls) or '(none)'}")
        self.walls[name].motion = motion
        self.contact_store.walls_changed = True

    def remove_particles(self, mask: np.ndarray) -> tuple[int, float]:
        """Remove the owned particles where ``mask`` is true (an outflow); returns (count, mass).

        They stop interacting at once (marked REMOVED: no mass, not integrated, left out of every
        query) and leave the storage at the next neighbour-list rebuild. Meanwhile each is parked
        far from every grain (:meth:`pdem.state.removal.Removals.park`) and out of the walls'
        candidates, so no contact can reach it and the list stays valid without a rebuild (a hopper
        removes grains at most steps of its discharge; forcing a rebuild each time had made rebuilds
        most of DEM-P's). Contact history of the remaining pairs is kept (it is keyed by particle ids).
        """
        return self.removals.remove(mask)

    def compact_removed(self) -> None:
        """Drop REMOVED particles from the storage (at a rebuild, before migration)."""
        self.removals.compact()

    # ------------------------------------------------------------------ preparation
    def prepare(self) -> None:
        """Validate and set up for stepping if anything changed since the last preparation
        (particles, walls, materials, boundaries added): the time step against the law's stability
        estimate, initial overlaps, decomposition, the neighbour list, the first forces. ``step`` and
        ``run`` call it when needed."""
        if not self._prepared:
            self._prepare()

    def _prepare(self) -> None:
        p = self.particles
        n = p.n_owned
        if len(self.materials) == 0:
            raise InputError("no material defined; add one with add_material()")
        self.coefficients = self.law.coefficients(self.materials)
        self.dt_critical = all_min(self.comm, self.law.critical_dt(self.materials, p.r, p.mat, p.mass))
        if self._dt is None and self.dt_fraction is not None:
            if not (self.dt_fraction > 0 and math.isfinite(self.dt_critical)):
                raise InputError(
                    f"run.dt_fraction = {self.dt_fraction!r}: law '{self.law.name}' has no finite "
                    f"stability estimate ({self.dt_critical:.4g} s) to take a fraction of; give run.dt in "
                    "seconds instead"
                )
            self.dt = self.dt_fraction * self.dt_critical
        if self._dt is None:
            # (the smallest over the ranks: a rank may own no particle yet)
            dt = all_min(self.comm, self.law.suggested_dt(self.materials, p.r, p.mat, p.mass))
            if not math.isfinite(dt):
                raise InputError("no time step given and none can be estimated without particles; set dt")
            self.dt = dt
        self._check_dt(self._dt)
        nl = self.neighbours
        r_max = all_max(self.comm, float(p.r[:n].max()) if n else 0.0)
        if self.law.list_needs.envelope:  # the method's collision envelope (DEM-C)
            r_min = all_min(self.comm, float(p.r[:n].min()) if n else math.inf)
            self.envelope_base = self.law.envelope(
                np.array([r_min]) if math.isfinite(r_min) else np.zeros(0)
            )
            self.envelope = self.envelope_base
        else:
            self.envelope = 0.0
        # the list holds every pair within skin + envelope at the build; it is rebuilt when particles
        # may have moved more than the skin, so every pair within the envelope is always listed
        nl.configure(r_max, n)
        if self.box is not None:
            self.box.check_width(nl.ghost_width)
            self.box.check_walls(self._wall_list, nl.ghost_width)
            self.box.snap_positions(p.x[:n])  # particles added before set_periodic
            self.box.wrap(p.x[:n])
        if (self.comm.size > 1 or self.box is not None) and self._decomp is None:
            self._decompose()
            n = p.n_owned
        elif self._decomp is not None:  # a later preparation: the skins the subdomains leave room for
            if self._early_decomp:  # placed before the ghost width was known
                self._early_decomp = False
                self._decomp.widen(nl.ghost_width)
                self._decomp.check_ghost_width(nl.ghost_width)
            nl.fit_skin_range()
        self._g = np.asarray(self.gravity, dtype=float)
        if self._g.shape != (3,) or not np.all(np.isfinite(self._g)):
            raise InputError(f"gravity = {self.gravity!r} must be three finite numbers [m/s²]")
        store = self.contact_store
        if not self._started:  # first preparation; later ones (particles or walls added) keep history
            store.pair_capacity = max(8 * n, 64, store.pair_capacity)
            self._started = True
        store.walls_changed = True
        for wall in self._wall_list:  # its loads are summed over the ranks (collective reads)
            wall._comm = self.comm
        self._prepared = True
        nl.rebuild()
        self._check_initial_overlaps()
        if self.integrator is None:
            self.integrator = self.law.make_integrator(self)
            self.integrator.restore(getattr(self, "_restored", {}))
        self.integrator.prepare()

    def _decompose(self) -> None:
        """Split space over the ranks (first preparation: every rank still holds every particle)."""
        from .parallel.decomposition import Decomposition

        p = self.particles
        n = p.n_owned
        if self._share is not None:  # a checkpoint read back in shares: no rank holds every particle
            from .parallel.exchange import scatter

            layout, saved = self._share
            width = self.neighbours.ghost_width
            self._decomp = Decomposition.from_shares(
                self.comm, p.x[:n], layout, self.decomposition_dims, min_width=width, box=self.box
            )
            self._decomp.check_ghost_width(width)
            self.neighbours.fit_skin_range()
            self._share = scatter(self, saved)
            self.removals.n_expected = global_count(self.comm, p.n_owned)
            return
        self._decomp = Decomposition(
            self.comm, p.x[:n], self.decomposition_dims, min_width=self.neighbours.ghost_width, box=self.box
        )
        self._decomp.check_ghost_width(self.neighbours.ghost_width)
        self.neighbours.fit_skin_range()
        keep = self._decomp.owned_mask(p.x[:n])
        self.particles.permute(np.concatenate([np.flatnonzero(keep), np.flatnonzero(~keep)]))
        p.n_owned = int(keep.sum())
        self.removals.n_expected = global_count(self.comm, p.n_owned)

    def exact_sum(self, values) -> float:
        """Correctly rounded sum over all ranks (collective; independent of the partition)."""
        return exact_sum(self.comm, values)

    def exact_column_sums(self, rows) -> np.ndarray:
        """Column-wise correctly rounded sums of a (k, m) array over all ranks (collective;
        independent of the partition). Each rank sends only a few partials per column, so a sum over
        many terms (every contact) holds no other rank's terms."""
        return exact_column_sums(self.comm, rows)

    def particle_sum(self, values) -> float:
        """Correctly rounded sum of a per-particle quantity of the owned particles over all ranks
        (collective; independent of the partition). Unlike :meth:`exact_sum` it is right before an
        MPI run's first step too, while every rank still holds every particle (one copy is summed)."""
        if self.comm.size > 1 and self._decomp is None:
            from .parallel.comm import SerialComm

            return exact_sum(SerialComm(), values)
        return exact_sum(self.comm, values)

    def count(self, n: int) -> int:
        """Sum of an integer over all ranks (collective)."""
        return global_count(self.comm, n)

    def count_particles(self) -> int:
        """Number of particles over all ranks (collective)."""
        p = self.particles
        return global_count(self.comm, int(np.count_nonzero(p.motion[: p.n_owned] != REMOVED)))

    # ------------------------------------------------------------------ checkpoint state
    def state_dict(self, local: bool = False) -> dict[str, object]:
        """Everything needed to continue bitwise-identically: particles ordered by id (every field
        registered with ``checkpoint``; forces included: velocity Verlet starts a step from them),
        contact history keyed by id pairs, per-wall history by particle id, wall positions, time and
        step. Independent of the storage order and (with MPI) of the number of ranks
        (:func:`pdem.io.state.simulation_state`; collective). Every rank gets the whole state, unless
        ``local``: then each gets its own particles and their contacts
        (:class:`pdem.io.state.CheckpointShare`), which :meth:`load_state` also takes, on any number
        of ranks."""
        from .io.state import simulation_state

        return simulation_state(self, local=local)

    def decomposition_layout(self) -> dict | None:
        """The decomposition's ranks, grid and cut planes (None without one)."""
        return self._decomp.layout() if self._decomp is not None else None

    def load_state(self, state: dict[str, object]) -> None:
        """Restore :meth:`state_dict` into a simulation built with the same materials, law and walls
        but no particles (:func:`pdem.io.state.restore_simulation`), and prepare it to go on."""
        from .io.state import CheckpointShare, restore_forces, restore_simulation

        saved = restore_simulation(self, state)
        self._next_id = int(state["scalars/next_id"])
        self._restored = {k: v for k, v in state.items() if k.startswith("solver/")}
        self._started = True
        if isinstance(state, CheckpointShare) and self.comm.size > 1:  # spread by the first preparation
            self._share = (state.layout, saved)
        self._prepare()
        saved, self._share = (self._share or saved), None
        restore_forces(self.particles, saved)

    @property
    def next_id(self) -> int:
        """The id the next added particle gets (ids are consecutive, from 0, over all ranks)."""
        return self._next_id

    def _check_initial_overlaps(self) -> None:
        worst, who = _diag.global_worst_overlap(self)
        if worst > self.max_overlap:
            raise GeometryError(
                f"{who} overlap by {worst:.3g} of the radius at the start (limit {self.max_overlap}); "
                "separate them (fill regions clear of the walls, or use a random-fill or lattice source)"
            )

    # ------------------------------------------------------------------ neighbours
    def permute_storage(self, perm: np.ndarray) -> None:
        """Reorder owned particles in memory (ids unchanged); no ghosts may be present, and a rebuild
        must follow before the next force evaluation.

        Results do not depend on the storage order: every sum is ordered by particle ids and all
        history is keyed by ids (this is what MPI migration relies on). The neighbour list orders
        the storage itself at its rebuilds (:class:`pdem.neighbor.list.NeighbourList`), which the
        next step makes first.
        """
        self.particles.permute(perm)
        self.neighbours.force_rebuild = True

    def request_rebuild(self) -> None:
        """Rebuild the neighbour list (and exchange ghosts) at the start of the next step, e.g. after
        particles were moved or changed by hand."""
        self.neighbours.force_rebuild = True

    def model_work(self) -> np.ndarray:
        """Estimated work of the last force evaluation per owned particle (cost-model units;
        :class:`pdem.parallel.work.WorkModel`)."""
        return self.work.particle_work()

    def check_particle_count(self) -> None:
        """No particle may be lost between ranks: owned counts must add up (collective)."""
        self.removals.check_count()

    def _needs_rebuild(self) -> bool:
        """The list's rebuild test; the last step's deferred flags ride on its reduction
        (step(defer_check=True)): one collective a step. A non-finite position cannot be binned: it
        stops the run as a non-finite state instead of a rebuild without the particle."""
        pending, self._pending_flags = self._pending_flags, None
        need, lost, unstable = self.neighbours.needs_rebuild(pending)
        if pending is None:
            if lost:
                _diag.raise_for_flags(self, FLAG_NONFINITE)
        elif unstable:
            flags = pending | (FLAG_NONFINITE if lost else 0)
            _diag.raise_for_flags(self, flags, drifted=self.integrator.drifts_before_check)
        return need

    # ------------------------------------------------------------------ the integrator's API
    # What an Integrator (pdem.integrate) calls during a step; plugins implementing a new method use
    # these, never private state.
    def compute_forces(self) -> int:
        """Zero the forces of owned and ghost particles, then add: pair contacts (in id-pair order),
        wall contacts (walls in order), the boundaries' ``apply_forces`` hooks. Body forces are the
        integrator's. Returns the kernels' flag word (combine, then :meth:`check_flags`)."""
        t0 = _time.perf_counter()
        flags = self._contact_forces()
        # the load balancer weighs ranks by this time: contacts only (a boundary hook may wait in a
        # collective call, which would make the emptier rank look busier and drain it further)
        self.work.add_time(_time.perf_counter() - t0)
        self.stiffness_monitor.load = None
        self._run_hooks("apply_forces")
        return flags

    def external_forces(self) -> bool:
        """Zero the forces, then let the boundaries' ``apply_forces`` hooks add theirs (DEM-C: these
        enter the free velocity). Returns whether any boundary has such a hook."""
        p = self.particles
        integ.zero_forces(p.f, p.t, p.n)
        self.stiffness_monitor.load = None
        if not self._hooks["apply_forces"]:
            return False
        self._run_hooks("apply_forces")
        return True

    def add_load_stiffness(self, rows: np.ndarray, k: np.ndarray) -> None:
        """Declare how stiff the loads just added by an ``apply_forces`` hook are: ``k`` [N/m] per
        owned particle ``rows``, a bound on the largest |eigenvalue| of ∂F_i/∂x_i (how fast the
        particle's own load changes as it moves, e.g. a membrane's pressure over the grains it
        drapes). Summed over the boundaries of a step, cleared at the next step.

        DEM-C uses it: its load enters the free velocity explicitly, which is stable only while
        h² k/m stays below ~4, and at DEM-C's large steps a membrane's loads are stiffer than that
        (docs/dem_c.md, "Stiff boundary loads"). With ``load_mass_scaling`` (default) the step gives
        each such particle the mass max(m, h² k) in its solve (mass scaling: static loads and
        contact forces unchanged, the particle's dynamics slowed). DEM-P's step is far below these
        limits and ignores it. Call it on every rank (``rows`` may be empty)."""
        self.stiffness_monitor.add_load(rows, k)

    @property
    def load_stiffness_wanted(self) -> bool:
        """Whether the method steps with the boundaries' load stiffness (DEM-C with
        ``load_mass_scaling``): a boundary may skip computing it when not (DEM-P ignores it)."""
        return self.stiffness_monitor.wanted

    @property
    def load_stiffness(self) -> np.ndarray | None:
        """Per owned particle, the stiffness [N/m] of this step's boundary loads
        (:meth:`add_load_stiffness`), or ``None`` when no boundary declared one."""
        return self.stiffness_monitor.load

    def _contact_forces(self) -> int:
        p = self.particles
        cs = self.contact_store
        integ.zero_forces(p.f, p.t, p.n)
        flags = self.law.pair_kernel(
            cs.pi, cs.pj, cs.hist, p.x, p.v, p.w, p.r, p.inv_m, p.inv_i, p.mat, self.coefficients, p.f,
            p.t, cs.force, self.dt, self.max_overlap,
        )  # fmt: skip
        if self._wall_list:
            if cs.walls_changed:
                cs.pack_walls()
            cs.filter_meshes(p.x, p.r, p.inv_m, 0.0)
            flags |= self.law.wall_kernel(
                cs.kinds, cs.params, cs.vel, cs.omega, cs.centre, cs.wmat, cs.cstart, cs.cand_step,
                cs.wall_hist, p.x, p.v, p.w, p.r, p.inv_m, p.inv_i, p.mat, self.coefficients, p.f, p.t,
                self.dt, self.max_overlap, cs.out_idx, cs.out_val, cs.counts,
            )  # fmt: skip
            self.record_wall_loads()
        return flags

    def add_body_forces(self) -> None:
        """f += m g for the free particles (owned and ghosts)."""
        p = self.particles
        g = self._g
        integ.add_body_forces(p.f, p.mass, p.motion, g[0], g[1], g[2], p.n)

    def record_wall_loads(self) -> None:
        """Tell every wall how many load rows this step wrote for it (summed lazily, exactly)."""
        self.contact_store.record_wall_loads()

    def add_work_time(self, seconds: float) -> None:
        """Account time spent on contacts (the load balancer weighs ranks by it)."""
        self.work.add_time(seconds)

    # ------------------------------------------------------------------ the time step
    def step(self, defer_check: bool = False) -> None:
        """Advance one time step: the boundaries' ``before_step`` hooks, the integrator's step (DEM-P
        velocity Verlet or the law's own, e.g. DEM-C), the ``after_step`` hooks.

        ``defer_check``: on several ranks, the step's stability check (its kernels' flags, a
        collective) is left to the next step's neighbour-list test, which then makes one reduction
        of both; the error, if any, is raised there, naming this step. Call :meth:`check_deferred`
        before reading or writing the state in between (``run`` and the deck runner do). A serial
        run, a step with ``after_step`` hooks or a stiffness check checks at once."""
        if not self._prepared:
            self._prepare()
        if self._hooks["before_step"]:
            self.check_deferred()  # the hooks see a checked state
            self._run_hooks("before_step")
        self._defer_check = defer_check and self.comm.size > 1 and not self._hooks["after_step"]
        try:
            self.integrator.step()
        finally:
            self._defer_check = False
        if self._hooks["after_step"]:
            self._run_hooks("after_step")

    def finish_step(self, flags: int) -> None:
        """End of an integrator's step: advance time and the step counter, then turn the kernels'
        flags into an error on every rank alike (collective; left to the next step's list test under
        ``step(defer_check=True)``)."""
        self.check_deferred()  # an integrator that skipped update_neighbours left them unchecked
        self.time += self._dt
        self.step_count += 1
        self.contact_store.release_held()  # a restored history serves the first step only
        stiffness_due = self.stiffness_monitor.due(self.step_count)
        if self._defer_check and not stiffness_due:
            self._pending_flags = int(flags)
        else:
            self.check_flags(flags)
        if stiffness_due:
            self.check_stiffness()

    def check_deferred(self) -> None:
        """Raise, on every rank, the error of the last step if its check was deferred
        (``step(defer_check=True)``) and any rank's kernels flagged a problem (collective, and a
        no-op on every rank when nothing is deferred)."""
        pending = self._pending_flags
        if pending is not None:
            self._pending_flags = None
            self.check_flags(pending)

    def check_stiffness(self) -> float:
        """The step the contact network bears now (:func:`pdem.contact.stability.step_bound`),
        recorded in :attr:`stiffness` (collective; ``nan`` for laws without the bound)."""
        return self.stiffness_monitor.check()

    @property
    def stiffness(self) -> dict[str, float]:
        """The live step bound's record over the run: the smallest bound [s] (``min_dt``), the
        ``step`` it was met, how many ``checks`` were made and at how many the step ``exceeded`` it."""
        return self.stiffness_monitor.record

    @property
    def stiffness_every(self) -> int:
        """Check the live step bound every this many steps, and at steps 1, 2, 4, … below it (0:
        never; :class:`pdem.contact.stability.StiffnessMonitor`)."""
        return self.stiffness_monitor.every

    @stiffness_every.setter
    def stiffness_every(self, value: int) -> None:
        self.stiffness_monitor.every = value

    @property
    def stiffness_limit(self) -> float:
        """Stop (InstabilityError) when dt exceeds this multiple of the live step bound; 0: never."""
        return self.stiffness_monitor.limit

    @stiffness_limit.setter
    def stiffness_limit(self, value: float) -> None:
        self.stiffness_monitor.limit = value

    def advance_walls(self, dt: float) -> None:
        """Move the walls with prescribed motion over [t, t + dt] (positions and velocities)."""
        cs = self.contact_store
        if cs.walls_changed:
            cs.pack_walls()
        for k in cs.moving:
            self._wall_list[k].advance(self.time, dt)
            cs.update_wall(k)

    def update_neighbours(self, before_rebuild: Callable[[], Any] | None = None) -> None:
        """Rebuild the neighbour list (and migrate, re-send ghosts) if anything may have moved more
        than the skin allows, else forward the ghosts' current state (collective)."""
        if self._needs_rebuild():
            if before_rebuild is not None:
                before_rebuild()
            self.neighbours.force_rebuild = False
            self.neighbours.rebuild()
        else:
            self.neighbours.forward_ghosts()

    def forward_ghosts(self, positions: bool = True) -> None:
        """Send the ghosts' current x, v, ω to the ranks (and periodic images) that hold them;
        without ``positions`` only v, ω (a third less to send), for a caller that has moved no
        particle since the last forward (``update_neighbours`` forwards positions, or rebuilds), e.g.
        a solver's sweeps within a step."""
        self.neighbours.forward_ghosts(positions)

    def set_list_reach(self, envelope: float, force: bool = True, skin: float | None = None) -> None:
        """Make the neighbour list reach ``skin + envelope`` (DEM-C's collision envelope); a wider
        reach needs a rebuild (``force``) and, under MPI, wider ghost layers and subdomains. ``skin``:
        the skin of the lists built from now on, which the rebuild test then uses (e.g. 0 when the
        method knows the next step must rebuild anyway; the list then holds exactly the pairs within
        ``envelope``); ``None`` keeps the current one; :attr:`skin` restores the simulation's."""
        self.neighbours.set_reach(envelope, force, skin)

    @property
    def list_envelope(self) -> float:
        """The envelope the neighbour list reaches beyond touching plus skin [m]."""
        return self.neighbours.envelope

    @property
    def skin(self) -> float | None:
        """The neighbour list's skin [m] (None until chosen: :class:`pdem.neighbor.list.NeighbourList`)."""
        return self.neighbours.skin

    @skin.setter
    def skin(self, value: float | None) -> None:
        self.neighbours.skin = value

    @property
    def n_rebuilds(self) -> int:
        """Neighbour-list rebuilds so far."""
        return self.neighbours.n_rebuilds

    @property
    def n_storage_sorts(self) -> int:
        """Spatial sorts of the storage so far (a list with ``order = "storage"``)."""
        return self.neighbours.n_storage_sorts

    def run(
        self,
        steps: int | None = None,
        until: float | None = None,
        callback: Callable[[Simulation], Any] | None = None,
        every: int = 1,
    ) -> Simulation:
        """Run ``steps`` steps, or until simulated time ``until`` [s]. ``callback(sim)`` runs every
        ``every`` steps."""
        if not self._prepared:
            self._prepare()
        if (steps is None) == (until is None):
            raise InputError("run: give exactly one of steps= or until=")
        if steps is None:
            steps = max(0, int(math.ceil((until - self.time) / self.dt - 1e-9)))
        if steps < 0:
            raise InputError(f"run: steps = {steps} must be ≥ 0")
        for k in range(steps):
            due = callback is not None and (k + 1) % every == 0
            self.step(defer_check=not due)  # a step handed to the callback is checked at once
            if due:
                callback(self)
        self.check_deferred()
        return self

    def check_flags(self, flags: int) -> None:
        """Raise :class:`InstabilityError` on every rank if any rank's kernels flagged a problem
        (collective: every rank must call it)."""
        if any_rank(self.comm, flags != 0):
            _diag.raise_for_flags(self, flags)

    # ------------------------------------------------------------------ inspection
    def get_particles(self) -> dict[str, np.ndarray]:
        """Copies of the particle arrays of all ranks, ordered by id: id, x, v, w, r, mass, f, t,
        material, motion, group, dof, and every registered field marked ``output``. Under MPI this
        is a collective call. (``sim.particles`` holds this rank's arrays in storage order, which
        is not id order: use this method, or :meth:`own_particles`, to read results.)"""
        p = self.particles
        n = p.n_owned
        live = p.motion[:n] != REMOVED
        local = {name: getattr(p, name)[:n][live].copy() for name in p.names(output=True)}
        if self.box is not None:  # between rebuilds a particle may be up to skin/2 past a face
            self.box.wrap(local["x"])
        out = gather_by_id(self.comm, local)
        out["material"] = out.pop("mat")
        return out

    def own_particles(self, contacts: bool = False) -> dict[str, np.ndarray]:
        """Copies of the particle arrays this rank owns, ordered by id (not collective): the keys of
        :meth:`get_particles`; with ``contacts``, also ``contacts`` (int32), each particle's number of
        touching contacts as :meth:`contacts` reports them. The ranks' results, concatenated and
        ordered by id, are :meth:`get_particles`."""
        p = self.particles
        n = p.n_owned
        live = p.motion[:n] != REMOVED
        out = {name: getattr(p, name)[:n][live] for name in p.names(output=True)}
        if contacts:
            if not self._prepared:
                self._prepare()
            # every contact of an owned particle is in this rank's pair list (ghosts reach further)
            pi, pj, _, _, touching = self._touching()
            count = np.bincount(np.concatenate([pi[touching], pj[touching]]), minlength=p.n)
            out["contacts"] = count[:n][live].astype(np.int32)
        order = np.argsort(out["id"], kind="stable")
        out = {k: v[order] for k, v in out.items()}  # fancy indexing copies
        out["material"] = out.pop("mat")
        return out

    def _touching(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pair list rows, centre offsets, distances and the touching mask of this rank's pairs."""
        p = self.particles
        cs = self.contact_store
        pi, pj = cs.pi, cs.pj
        d = p.x[pj] - p.x[pi]
        dist = np.linalg.norm(d, axis=1)
        touching = np.any(cs.force != 0, axis=1)
        if not self.law.rigid:
            # a penalty force with a gap is stale (the pair parted after the evaluation); rigid grains
            # (DEM-C) carry impulses at a zero or slightly positive gap: the impulse decides
            touching &= p.r[pi] + p.r[pj] - dist > 0
        touching &= (p.motion[pi] != REMOVED) & (p.motion[pj] != REMOVED)
        return pi, pj, d, dist, touching

    def contacts(self) -> dict[str, np.ndarray]:
        """Touching particle pairs of the last force evaluation: ``id_i < id_j``, overlap [m],
        normal force [N] (positive = repulsive) and force on j [N] (on i: its negative). With DEM-C,
        every pair that carried an impulse (impulse / h), whatever its gap (rigid grains touch at a
        zero or small positive gap: the overlap is then ≤ 0)."""
        if not self._prepared:
            self._prepare()
        p = self.particles
        pi, pj, d, dist, touching = self._touching()
        overlap = p.r[pi] + p.r[pj] - dist
        n = d[touching] / dist[touching, None]
        force = self.contact_store.force[touching]
        local = {
            "id_i": p.id[pi[touching]].copy(),
            "id_j": p.id[pj[touching]].copy(),
            "overlap": overlap[touching],
            "normal_force": np.einsum("ij,ij->i", force, n),
            "force": force.copy(),
        }
        # a contact across ranks is computed on both, one across the periodic boundary by each end's
        # image: keep one copy (they are identical)
        if self.comm.size == 1:
            allc = local
        else:
            parts = self.comm.allgather(local)
            allc = {k: np.concatenate([q[k] for q in parts]) for k in local}
        key = (allc["id_i"] << 32) | allc["id_j"]
        _, first = np.unique(key, return_index=True)
        return {k: v[first] for k, v in allc.items()}

    def own_contacts(self) -> dict[str, np.ndarray]:
        """This rank's share of :meth:`contacts` (not collective): every touching pair is counted on
        exactly one rank, the one that owns its lower-id grain (a pair that meets across a periodic
        face is counted once). The keys of :meth:`contacts`, and ``branch`` [m], the vector from
        grain i's centre to grain j's (through the periodic face where they meet there). The ranks'
        shares together are :meth:`contacts`; a sum over them with :meth:`exact_column_sums` is the
        same on any rank count, with no rank holding every contact."""
        p = self.particles
        pi, pj, d, dist, keep = self._own_touching()
        ids_i, ids_j = p.id[pi], p.id[pj]
        flip = ids_i[keep] > ids_j[keep]  # orient every contact as id_i < id_j, as contacts() does
        sign = np.where(flip, -1.0, 1.0)[:, None]
        force = self.contact_store.force[keep] * sign
        branch = d[keep] * sign
        dk = dist[keep]
        return {
            "id_i": np.where(flip, ids_j[keep], ids_i[keep]),
            "id_j": np.where(flip, ids_i[keep], ids_j[keep]),
            "overlap": p.r[pi[keep]] + p.r[pj[keep]] - dk,
            "normal_force": np.einsum("ij,ij->i", force, branch / dk[:, None]),
            "force": force,
            "branch": branch,
        }

    def count_contacts(self) -> int:
        """Number of touching pairs over all ranks, each once (collective; ``len`` of
        :meth:`contacts` without gathering them)."""
        return self.count(int(np.count_nonzero(self._own_touching()[4])))

    def _own_touching(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_touching` with the mask narrowed to the pairs this rank counts: those whose
        lower-id grain it owns (one copy of a pair across ranks or a periodic face)."""
        if not self._prepared:
            self._prepare()
        p = self.particles
        pi, pj, d, dist, touching = self._touching()
        lower = np.where(p.id[pi] < p.id[pj], pi, pj)
        return pi, pj, d, dist, touching & (lower < p.n_owned)

    def wall_contacts(self) -> dict[str, np.ndarray]:
        """Wall contacts of the last step, all ranks (collective), ordered by (wall, row, id):
        ``wall`` (index into ``list(sim.walls)``), ``row`` (facet of a mesh wall, else 0), ``id`` of
        the particle, ``overlap`` [m] (DEM-C: may be slightly negative, a contact in the envelope),
        ``force`` on the wall [N] (on the particle: its negative) and ``torque`` on the wall about its
        reference point [N m]."""
        local = self.own_wall_contacts()
        del local["x"], local["r"]
        if self.comm.size > 1:
            gathered = self.comm.allgather(local)
            local = {k: np.concatenate([q[k] for q in gathered]) for k in local}
        order = np.lexsort((local["id"], local["row"], local["wall"]))
        return {k: v[order] for k, v in local.items()}

    def own_wall_contacts(self) -> dict[str, np.ndarray]:
        """This rank's wall contacts (not collective; its own grains'), ordered by (wall, row, id):
        the keys of :meth:`wall_contacts`, and the grain's centre ``x`` [m] and radius ``r`` [m]."""
        from .geometry._kernels import wall_gaps

        if not self._prepared:
            self._prepare()
        p = self.particles
        cs = self.contact_store
        parts = {k: [] for k in ("wall", "row", "id", "x", "r", "overlap", "force", "torque")}
        for k in range(len(self._wall_list)):
            for row in range(int(cs.wall_rows[k]), int(cs.wall_rows[k + 1])):
                a = int(cs.cstart[row]) if row < cs.cstart.shape[0] - 1 else 0
                c = int(cs.counts[row]) if row < cs.counts.shape[0] else 0
                idx = cs.out_idx[a : a + c]
                gap = wall_gaps(int(cs.kinds[row]), cs.params[row], p.x[idx], p.r[idx]) if c else np.zeros(0)
                parts["wall"].append(np.full(c, k, np.int64))
                parts["row"].append(np.full(c, row - int(cs.wall_rows[k]), np.int64))
                parts["id"].append(p.id[idx].copy())
                parts["x"].append(p.x[idx].copy())
                parts["r"].append(p.r[idx].copy())
                parts["overlap"].append(-gap)
                parts["force"].append(cs.out_val[a : a + c, 0:3].copy())
                parts["torque"].append(cs.out_val[a : a + c, 3:6].copy())
        vectors = ("x", "force", "torque")
        local = {
            k: np.concatenate(v) if v else (np.zeros((0, 3)) if k in vectors else np.zeros(0))
            for k, v in parts.items()
        }
        order = np.lexsort((local["id"], local["row"], local["wall"]))
        return {k: v[order] for k, v in local.items()}

    def solver_stats(self) -> dict[str, float]:
        """The time integrator's statistics: for DEM-C the last step's ``iterations`` and
        ``residual`` [m/s], and over the run ``steps``, ``unconverged_steps``, ``mean_iterations``,
        ``max_residual`` (every step's values: ``sim.integrator.drain_records()``); empty for DEM-P."""
        return self.integrator.stats() if self.integrator is not None else {}

    def kinetic_energy(self) -> tuple[float, float]:
        """(translational, rotational) kinetic energy of the free particles [J]."""
        p = self.particles
        n = p.n_owned
        free = p.motion[:n] == FREE
        m = p.mass[:n][free]
        et = 0.5 * exact_sum(self.comm, m * np.einsum("ij,ij->i", p.v[:n][free], p.v[:n][free]))
        er = 0.5 * exact_sum(
            self.comm, 0.4 * m * p.r[:n][free] ** 2 * np.einsum("ij,ij->i", p.w[:n][free], p.w[:n][free])
        )
        return et, er

    @property
    def n_particles(self) -> int:
        """Particles this rank owns, not counting those removed since the last rebuild (they stay
        in the storage until then: ``particles.n_owned`` counts the rows)."""
        return self.particles.n_owned - self.removals.n_parked

    def __repr__(self) -> str:
        return (
            f"Simulation({self.n_particles} particles, {len(self._wall_list)} walls, "
            f"law={self.law.name}, dt={self.dt}, t={self.time:.6g} s, step={self.step_count})"
        )
