"""Scene facts for ``pdem advise``: what the deck says (grains, materials, stages, steps, speeds,
stresses), and what a short probe of the first stage measures.

The deck-level facts need no particles: counts come from the same estimate as the memory check
(:mod:`pdem.deck.capacity`), sizes from the sources' size distributions, heights from their regions.
What the boundaries impose (speeds, stresses, loading rates) and the area a device packs the grains
into come from the boundary contract's hooks (:meth:`~pdem.boundaries.api.Boundary.loading`,
:meth:`~pdem.boundaries.api.Boundary.extent`, …), never from a boundary's ``type``.
The probe builds the first stage's scene exactly as ``pdem check`` does (:meth:`Runner.start_stage`,
nothing written) and steps it for a few hundred steps within a wall-time budget.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..boundaries.api import Boundary, Loading, SceneFacts
from ..errors import InputError
from . import rules


@dataclass
class GrainGroup:
    """The grains of one ``[[particles]]`` table."""

    index: int
    source: str
    material: str
    stage: str
    count: float
    counted: str
    r_min: float
    r_max: float
    r_mean: float
    mean_volume: float
    density: float
    youngs_modulus: float
    poisson_ratio: float
    speed: float  # |initial velocity|
    bounds: tuple[np.ndarray, np.ndarray] | None
    footprint: float | None  # horizontal area of its region [m²]
    params: Any = None
    loose: bool = False  # its grains start apart and may fall (Source.starts_loose)
    settles: bool = False  # it settles its grains with pdem before the run (Source.settles)

    @property
    def mass_min(self) -> float:
        return self.density * 4.0 / 3.0 * math.pi * self.r_min**3


@dataclass
class StageFacts:
    name: str
    index: int
    dt_given: float | None  # the dt the deck gives this stage (its own or run.dt)
    dt_key: str | None  # the key that gives it
    speeds: list[tuple[float, str]] = field(default_factory=list)
    stress: float = 0.0
    stress_from: str = "none"
    duration: float | None = None
    duration_from: str = ""


@dataclass
class Scene:
    law: str
    parameterisation: str
    hertzian: bool  # the law's normal force is Hertz's from E and ν (ContactLaw.hertz_from_materials)
    groups: list[GrainGroup]
    stages: list[StageFacts]
    gravity: float
    g_axis: np.ndarray
    boundaries: dict[str, Any]  # name -> validated params
    wall_materials: dict[str, Any]  # name -> MaterialSpec used by boundaries
    materials: dict[str, Any]
    run_dt: float | None
    packed_height: float
    fall_height: float
    footprint: float | None
    probe: dict[str, Any] = field(default_factory=dict)
    #: the deck key that gives run_dt: run.dt, or contact.<law>.dt (the law's own step)
    run_dt_key: str = "run.dt"
    #: run.dt_fraction: stages that give no dt step at this fraction of the law's critical step (T_R)
    dt_fraction: float | None = None
    #: name -> the boundary's plugin class (its hooks describe it; Boundary's defaults if unknown)
    boundary_classes: dict[str, type] = field(default_factory=dict)
    #: the stage names in deck order
    stage_names: tuple[str, ...] = ()
    #: "<boundary>.<key>" -> the largest value a stage ends at when the quantity rises above it
    ends: dict[str, float] = field(default_factory=dict)
    #: the law's grains are rigid (its ``rigid`` capability: no overlap, no stiffness step)
    rigid: bool = False

    @property
    def n(self) -> float:
        return sum(g.count for g in self.groups)

    def mean(self, attr: str) -> float:
        n = self.n
        return sum(g.count * getattr(g, attr) for g in self.groups) / n if n else math.nan

    @property
    def d_mean(self) -> float:
        return 2.0 * self.mean("r_mean")

    @property
    def d_max(self) -> float:
        return 2.0 * max((g.r_max for g in self.groups), default=math.nan)

    @property
    def density(self) -> float:
        return self.mean("density")

    def grain_materials(self) -> list[str]:
        return list(dict.fromkeys(g.material for g in self.groups))

    def r_min_of(self, material: str) -> float:
        return min(g.r_min for g in self.groups if g.material == material)

    def boundary_class(self, name: str) -> type:
        return self.boundary_classes.get(name, Boundary)

    def facts(self) -> SceneFacts:
        """What the boundaries' hooks are told about the grains."""
        return SceneFacts(
            stages=tuple(self.stage_names), gravity=self.gravity, density=self.density, d_mean=self.d_mean,
            d_max=self.d_max, grain_volume=self.mean("mean_volume"), packed_height=self.packed_height,
            footprint=self.footprint, packing_fraction=rules.PACKING_FRACTION, ends=dict(self.ends),
        )  # fmt: skip

    def loadings(self) -> dict[str, list[Loading]]:
        """Every boundary's :meth:`~pdem.boundaries.api.Boundary.loading`, by name (deck order)."""
        facts = self.facts()
        return {
            name: list(self.boundary_class(name).loading(name, params, facts))
            for name, params in self.boundaries.items()
        }

    @property
    def grain_mass(self) -> float:
        """The grains' mean mass [kg] (NaN when no group's count and density are known)."""
        known = [g for g in self.groups if math.isfinite(g.count) and math.isfinite(g.density)]
        n = sum(g.count for g in known)
        return sum(g.count * g.density * g.mean_volume for g in known) / n if n > 0 else math.nan

    def body_mass(self, name: str) -> float | None:
        """The mass [kg] of the free body boundary ``name`` drops, when the boundary says it: its
        instance's ``mass`` (made from the parameters alone, nothing built), else None."""
        try:
            body = self.boundary_class(name)(name, self.boundaries[name])
        except Exception:  # noqa: BLE001 - a boundary that cannot be made without a simulation
            return None
        mass = getattr(body, "mass", None)
        if isinstance(mass, int | float) and not isinstance(mass, bool) and math.isfinite(mass) and mass > 0:
            return float(mass)
        return None

    def acts_in(self, name: str, stage: str) -> bool:
        """Is boundary ``name`` doing something in ``stage`` (its ``stage_roles``)?"""
        p = self.boundaries[name]
        names = list(self.stage_names)
        if stage not in names:
            return False
        return self.boundary_class(name).stage_roles(p, names)[names.index(stage)] is not None


def _sizes(params: Any) -> tuple[float, float, float, float] | None:
    """(r_min, r_max, r_mean, mean volume) of a source's ``sizes`` / ``radius`` key."""
    sizes = getattr(params, "sizes", None)
    if sizes is not None and hasattr(sizes, "build"):
        dist = sizes.build()
        return float(dist.r_min), float(dist.r_max), float(dist.mean_radius()), float(dist.mean_volume())
    radius = getattr(params, "radius", None)
    if isinstance(radius, int | float):
        r = float(radius)
        return r, r, r, 4.0 / 3.0 * math.pi * r**3
    return None


def _region_footprint(params: Any) -> float | None:
    region = getattr(params, "region", None)
    kind = getattr(region, "type", None)
    if kind == "cylinder":
        return math.pi * float(region.radius) ** 2
    if kind == "box":
        return float((region.hi[0] - region.lo[0]) * (region.hi[1] - region.lo[1]))
    return None


def deck_scene(resolved: Any, raw: dict) -> Scene:
    """The scene as the deck describes it (no particles made)."""
    from ..deck.capacity import estimate_source

    deck = resolved.deck
    names = [s.name for s in deck.stages]
    g = np.asarray(deck.run.gravity, dtype=float)
    gmag = float(np.linalg.norm(g))
    axis = g / gmag if gmag > 0 else np.array([0.0, 0.0, -1.0])
    groups: list[GrainGroup] = []
    raw_particles = raw.get("particles", []) if isinstance(raw.get("particles"), list) else []
    for k, (cls, params) in enumerate(zip(resolved.source_classes, deck.particles, strict=True)):
        mat = deck.materials[params.material]
        sizes = _sizes(params)
        count_est = estimate_source(raw_particles[k] if k < len(raw_particles) else None, resolved.base_dir)
        count, counted = count_est if count_est is not None else (math.nan, "unknown")
        try:
            r = cls(params).known_radii(resolved.base_dir)
        except Exception:  # noqa: BLE001 - radii the advice cannot read are left to the run
            r = None
        if r is not None and len(r):
            r = np.asarray(r, dtype=float)
            sizes = (float(r.min()), float(r.max()), float(r.mean()), float(np.mean(4 / 3 * math.pi * r**3)))
            count, counted = float(len(r)), f"{len(r):,} radii given by the source"
        if sizes is None:
            try:
                rmax = cls(params).r_max()
            except Exception:  # noqa: BLE001
                rmax = None
            if rmax is None:
                continue
            sizes = (rmax, rmax, rmax, 4.0 / 3.0 * math.pi * rmax**3)
        try:
            bounds = cls(params).bounds()
        except Exception:  # noqa: BLE001
            bounds = None
        vel = getattr(params, "velocity", None) or (0.0, 0.0, 0.0)
        groups.append(
            GrainGroup(
                index=k,
                source=str(params.source),
                material=params.material,
                stage=params.stage or names[0],
                count=float(count),
                counted=counted,
                r_min=sizes[0],
                r_max=sizes[1],
                r_mean=sizes[2],
                mean_volume=sizes[3],
                density=float(mat.density) if not mat.rigid else math.nan,
                youngs_modulus=float(mat.youngs_modulus) if not mat.rigid else math.inf,
                poisson_ratio=float(mat.poisson_ratio) if not mat.rigid else 0.0,
                speed=float(np.linalg.norm(np.asarray(vel, dtype=float))),
                bounds=bounds,
                footprint=_region_footprint(params),
                params=params,
                loose=bool(getattr(cls, "starts_loose", False)),
                settles=bool(getattr(cls, "settles", False)),
            )
        )
    boundaries = dict(resolved.boundaries)
    classes = {name: resolved.boundary_classes.get(name, Boundary) for name in boundaries}
    wall_materials = {}
    for bname, params in boundaries.items():
        for name in classes[bname].wall_materials(params):
            if isinstance(name, str) and name in deck.materials:
                wall_materials[name] = deck.materials[name]
    footprint = _footprint(groups, boundaries, classes)
    ends: dict[str, float] = {}
    for st in deck.stages:
        if st.end.quantity and st.end.above is not None:
            ends[st.end.quantity] = max(float(st.end.above), ends.get(st.end.quantity, -math.inf))
    volume = sum(g.count * g.mean_volume for g in groups if math.isfinite(g.count))
    packed = volume / (rules.PACKING_FRACTION * footprint) if footprint else math.nan
    scene = Scene(
        law=deck.contact.law,
        parameterisation=str(getattr(resolved.law_params, "parameterisation", "material")),
        hertzian=bool(
            resolved.law_class is not None and resolved.law_class.hertz_from_materials(resolved.law_params)
        ),
        groups=groups,
        stages=[],
        gravity=gmag,
        g_axis=axis,
        boundaries=boundaries,
        wall_materials=wall_materials,
        materials=dict(deck.materials),
        run_dt=deck.run.dt,
        run_dt_key=resolved.step_key,
        dt_fraction=deck.run.dt_fraction,
        packed_height=packed,
        fall_height=_fall_height(groups, axis),
        footprint=footprint,
        boundary_classes=classes,
        stage_names=tuple(names),
        ends=ends,
        rigid=bool(getattr(resolved.law_class, "rigid", False)),
    )
    scene.stages = [_stage_facts(scene, resolved, k) for k in range(len(deck.stages))]
    return scene


def _footprint(
    groups: list[GrainGroup], boundaries: dict[str, Any], classes: dict[str, type]
) -> float | None:
    """The horizontal area the grains pack into: the first boundary's that holds the sample (its
    :meth:`~pdem.boundaries.api.Boundary.extent`: a shear box, a triaxial cell, a plate of known
    area), else the largest source region's."""
    for name, params in boundaries.items():
        extent = classes.get(name, Boundary).extent(params)
        area = extent.footprint if extent is not None else None
        if area:
            return float(area)
    areas = [g.footprint for g in groups if g.footprint]
    return max(areas) if areas else None


def _fall_height(groups: list[GrainGroup], axis: np.ndarray) -> float:
    """How far loose grains can fall: from the top of a loose source's region to the lowest point
    of any region, along gravity."""
    boxes = [g.bounds for g in groups if g.bounds is not None]
    loose = [g.bounds for g in groups if g.bounds is not None and g.loose]
    if not loose:
        return 0.0

    def extent(b: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
        corners = np.array(
            [[x, y, z] for x in (b[0][0], b[1][0]) for y in (b[0][1], b[1][1]) for z in (b[0][2], b[1][2])]
        )
        along = corners @ axis  # grows downwards
        return float(along.min()), float(along.max())

    top = min(extent(b)[0] for b in loose)
    bottom = max(extent(b)[1] for b in boxes)
    return max(bottom - top, 0.0)


def _stage_facts(scene: Scene, resolved: Any, k: int) -> StageFacts:
    deck = resolved.deck
    stage = deck.stages[k]
    if stage.dt is not None:
        dt, key = stage.dt, f"stages.{stage.name}.dt"
    elif deck.run.dt is not None:
        dt, key = deck.run.dt, resolved.step_key
    else:
        dt, key = None, None
        for earlier in reversed(deck.stages[:k]):  # "the current step goes on"
            if earlier.dt is not None:
                dt, key = earlier.dt, f"stages.{earlier.name}.dt"
                break
    facts = StageFacts(name=stage.name, index=k, dt_given=dt, dt_key=key)
    g = scene.gravity
    # speeds
    for grp in scene.groups:
        if grp.stage == stage.name:
            if grp.loose and g > 0 and scene.fall_height > 0:
                facts.speeds.append(
                    (
                        math.sqrt(2 * g * scene.fall_height),
                        f"free fall of particles.{grp.index} from {scene.fall_height:.3g} m",
                    )
                )
            if grp.speed > 0:
                facts.speeds.append((grp.speed, f"particles.{grp.index}.velocity"))
    hydro = 0.0
    if g > 0 and math.isfinite(scene.packed_height):
        hydro = rules.PACKING_FRACTION * scene.density * g * scene.packed_height
    facts.stress, facts.stress_from = (
        hydro,
        (f"grains' weight φ ρ g H (H = {scene.packed_height:.3g} m packed)" if hydro > 0 else "none"),
    )
    for name, loadings in scene.loadings().items():
        if not scene.acts_in(name, stage.name):
            continue
        p = scene.boundaries[name]
        motion = getattr(p, "motion", None)  # the generic key of a wall (WallBoundaryParams)
        vel = getattr(motion, "velocity", None)
        if vel is not None:
            facts.speeds.append((float(np.linalg.norm(vel)), f"boundaries.{name}.motion"))
        for ld in loadings:
            if stage.name not in ld.stages:
                continue
            if ld.speed_from:
                facts.speeds.append((float(ld.speed), ld.speed_from))
            if ld.stress_from:
                stress = float(ld.stress) + (hydro if ld.on_weight else 0.0)
                if stress > facts.stress:
                    facts.stress = stress
                    facts.stress_from = ld.stress_from + (" + the grains' weight" if ld.on_weight else "")
    if k == 0 and scene.probe.get("max_speed"):
        facts.speeds.append((scene.probe["max_speed"], "fastest grain in the probe"))
    facts.duration, facts.duration_from = _duration(stage, facts.dt_given, scene)
    return facts


def _duration(stage: Any, dt: float | None, scene: Scene) -> tuple[float | None, str]:
    """Simulated time of a stage, when the deck tells it (an upper bound for a stage that may end
    early on kinetic energy, a quantity or its max_time)."""
    end = stage.end
    q = end.quantity
    if q and end.above is not None and "." in q:
        name, key = q.split(".", 1)
        for ld in scene.loadings().get(name, ()):  # a measurement that grows at a known rate
            if stage.name in ld.stages and key in ld.ends:
                rate, start = ld.ends[key]
                if rate > 0:
                    return (end.above - start) / rate, f"{q} to {end.above:g} at {ld.rate_key or key}"
    if end.time is not None:
        return end.time, "end.time" + (" (or earlier)" if end.kinetic_energy_below or q else "")
    if end.steps is not None and dt is not None:
        return end.steps * dt, "end.steps × dt"
    if end.max_time is not None:
        return end.max_time, "end.max_time (an upper bound)"
    return None, "not known from the deck"


# ---------------------------------------------------------------------------------------------
# the probe
# ---------------------------------------------------------------------------------------------


def _pluviation_seconds(scene: Scene, first: str) -> float:
    """Predicted wall time of the first stage's pluviated packings (they settle with pdem itself)."""
    total = 0.0
    for grp in scene.groups:
        if not grp.settles or grp.stage != first:
            continue
        p = grp.params
        t_r = rules.rayleigh_time(grp.r_min, grp.density, grp.youngs_modulus, grp.poisson_ratio)
        dt = rules.RAYLEIGH_FRACTION * t_r
        area = grp.footprint or 1.0
        column = (
            grp.count * grp.mean_volume / (float(getattr(p, "fill_fraction", 0.3)) * area) + 2 * grp.r_max
        )
        t = math.sqrt(2 * column / 9.81) + 0.3
        total += t / dt * grp.count / rules.PARTICLE_STEPS_PER_SECOND
    return total


def run_probe(resolved: Any, scene: Scene, budget: float = 10.0, steps: int = 300) -> dict[str, Any]:
    """Build the first stage's scene as ``pdem check`` does and step it (at most ``steps`` steps,
    at most ``budget`` seconds of wall time in all). Returns what it measured, or why it did not run.

    The probe runs in a forked child process, so that the budget holds whatever takes the time (a
    first step that compiles DEM-C's solver cold takes tens of seconds): the child reports what it
    has as it goes, and is stopped at the budget."""
    import multiprocessing

    stages = list(resolved.deck.stages)
    predicted = _pluviation_seconds(scene, stages[0].name)
    if predicted > budget:
        return {
            "ran": False,
            "reason": f"the first stage's pluviated packing would take ~{predicted:.0f} s to settle "
            f"(budget {budget:g} s); the numbers below are estimated from the deck",
        }
    t0 = time.perf_counter()
    try:
        ctx = multiprocessing.get_context("fork")
    except ValueError:  # pragma: no cover - no fork on this platform: probe in this process
        return _probe(resolved, budget, steps, lambda msg: None)
    receive, send = ctx.Pipe(duplex=False)
    child = ctx.Process(target=_probe_child, args=(resolved, budget, steps, send), daemon=True)
    child.start()
    send.close()
    out: dict[str, Any] = {"ran": False, "reason": f"the scene was not built within the {budget:g} s budget"}
    deadline = t0 + budget + 2.0
    finished = False
    while True:
        left = deadline - time.perf_counter()
        if left <= 0:
            break
        if receive.poll(min(left, 0.5)):
            try:
                msg = receive.recv()
            except EOFError:
                break
            out.update(msg)
            if msg.get("done"):
                finished = True
                break
        elif not child.is_alive():
            break
    child.join(timeout=1.0 if finished else 0.0)
    if child.is_alive():
        child.terminate()
        child.join(timeout=5)
    if not finished and out.get("ran"):
        out["cut"] = True
    out.pop("done", None)
    out["wall_seconds"] = time.perf_counter() - t0
    return out


def _probe_child(resolved: Any, budget: float, steps: int, send: Any) -> None:
    try:
        _probe(resolved, budget, steps, send.send)
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which goes on without it
        send.send({"ran": False, "done": True, "reason": f"the probe failed: {type(exc).__name__}: {exc}"})
    finally:
        send.close()


def _probe(resolved: Any, budget: float, steps: int, report: Any) -> dict[str, Any]:
    from ..runner import Runner

    t0 = time.perf_counter()
    first = resolved.deck.stages[0]
    runner = Runner(resolved, progress=None, dry=True)
    try:
        sim = runner.build()
        runner.start_stage(0)
    except InputError as exc:
        msg = {"ran": False, "done": True, "reason": f"the scene check refused the deck: {exc}"}
        report(msg)
        return msg

    def facts(done: int) -> dict[str, Any]:
        p = sim.get_particles()
        n = len(p["r"])
        speeds = np.linalg.norm(p["v"], axis=1) if n else np.zeros(0)
        contacts = len(sim.contacts()["id_i"]) if n and done else 0
        return {
            "ran": True,
            "particles": n,
            "r_min": float(p["r"].min()) if n else math.nan,
            "r_max": float(p["r"].max()) if n else math.nan,
            "dt": float(sim.dt),
            "dt_critical": float(sim.dt_critical),
            "steps": done,
            "cut": False,
            "contacts_per_particle": 2.0 * contacts / n if n else 0.0,
            "max_speed": float(speeds.max()) if n else 0.0,
            "build_seconds": time.perf_counter() - t0,
        }

    msg = facts(0)
    report(msg)
    limit = steps if first.end.steps is None else min(steps, first.end.steps)
    done = 0
    try:
        while done < limit:
            if time.perf_counter() - t0 > budget:
                msg["cut"] = True
                break
            chunk = min(10, limit - done)
            sim.run(steps=chunk)
            done += chunk
    except Exception as exc:  # noqa: BLE001 - a probe that fails says so and the advice goes on
        msg = {
            "ran": False,
            "done": True,
            "reason": f"the probe stopped at step {done}: {type(exc).__name__}: {exc}",
        }
        report(msg)
        return msg
    cut = msg["cut"]
    msg = {**facts(done), "build_seconds": msg["build_seconds"], "cut": cut, "done": True}
    report(msg)
    return msg
