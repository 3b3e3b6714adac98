"""Run a validated deck: build the simulation, go through the stages, write what is due.

Per stage: insert the stage's particles, switch boundaries on or off, then step until one end
condition holds (time, steps, kinetic energy below a threshold, a measured quantity above or below a
value). Snapshots (HDF5 + XDMF and/or VTK), a CSV time series per stage (energies and every
boundary's measurements), periodic checkpoints and one at the end of every stage. ``max_steps``
(the CLI's ``--steps``) stops early, writing final output and a checkpoint.

Nothing is written before the run has passed the checks that can only be made once the scene exists
(the time step against the law's stability estimate, every stage's dt, initial overlaps between
grains and with walls, the packing files): the first stage's particles are inserted and the
simulation prepared first, then the output directory is created. If the run still fails before its
first step, what it created is removed (never what was there before), so the corrected run needs no
``--overwrite``.

Resuming (``resume=(state, meta)``): the simulation is rebuilt from the checkpoint. With ``append``
the output goes on in the run's own directory as one time series: series rows, snapshots and
checkpoints the previous run wrote after the checkpoint's step are dropped (they belong to a future
that is being replaced), everything up to it is kept unchanged, and new rows and frames follow.

Thermo lines (``output.thermo_every = N``): every N steps rank 0 prints one line on stdout with the
columns of ``output.thermo`` (step, time, dt, particles, kinetic energies, contacts, any measured
quantity ``<boundary>.<key>``), after a header line at the start of each stage, as LAMMPS does.

Snapshots under MPI are either gathered (every rank's particles collected, ordered by id, and written
by rank 0) or written per rank (each rank writes the particles it owns with writers constructed with
``comm``; rank 0 writes the index joining the pieces): ``output.parallel``, decided once when output
starts (``auto``: by the particle count then) and recorded in ``summary.json`` as ``output_parallel``.

Output directory layout::

    deck.resolved.toml      the deck with every default filled in (a resume that changed keys keeps
                            the previous one as deck.resolved.until-step-<N>.toml)
    particles.h5/.xdmf      snapshots (ParaView: open the .xdmf), walls.h5/.xdmf
    particles.rRRRR.h5      instead of particles.h5 with output.parallel = "per_rank": one file per
                            rank, joined by particles.xdmf
    particles.pvd, …        (with formats = ["vtk"])
    series_<stage>.csv      time series
    checkpoints/            step_<n>.h5, latest.h5 → newest
    summary.json            results derived by boundaries (e.g. a hopper's flow rate), run facts
"""

from __future__ import annotations

import json
import math
import shlex
import sys
import threading
import time as _time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from . import __version__
from .errors import InputError, PdemError
from .io.frame import Frame, WallState
from .io.run_output import RunOutput
from .plugins import load
from .simulation import Simulation

__all__ = [
    "Runner",
    "StageLimitError",
    "StageSettings",
    "build_particles",
    "resolve_stages",
    "MAX_STAGE_STEPS",
]

#: most steps a stage may take (as the deck check, with the dt known once the scene exists)
MAX_STAGE_STEPS = 10**10

#: seconds between progress lines while the particles are made or a stage is prepared
SETUP_PROGRESS_EVERY = 5.0


class StageLimitError(PdemError):
    """A stage reached its ``max_time`` safety cap without meeting its end condition (exit code 3:
    the run failed to reach its goal; a checkpoint is written first, to resume with a larger cap)."""

    exit_code = 3


# ---------------------------------------------------------------------------------------- sources
def build_particles(
    spec: Any, base_dir: Path, seed: int, material
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Positions, radii and optional velocities of one ``[[particles]]`` source.

    ``spec``: the source plugin's validated ``Params`` or a table (``{"source": …, …}``, validated
    here with that plugin's ``Params``). Kept for callers of the former built-in-only function; the
    runner calls the plugins (:mod:`pdem.sources.api`) directly.
    """
    from .sources.api import SourceParams, produce

    if isinstance(spec, SourceParams):
        params = spec
        cls = load("sources", params.source)
    else:
        cls = load("sources", spec["source"])
        params = cls.Params.model_validate(dict(spec), context={"base_dir": str(base_dir)})
    out = produce(cls(params), base_dir=Path(base_dir), seed=seed, material=material)
    return out.positions, out.radii, out.velocities


# ---------------------------------------------------------------------------------------- stages
@dataclass(frozen=True)
class StageSettings:
    """The settings one stage runs with, resolved from the deck once, before the run
    (:func:`resolve_stages`; :attr:`Runner.stages`).

    ``dt``: the stage's own ``dt``, else ``run.dt`` (None: the current step is kept, the law's
    estimate or the dt of an earlier stage); ``dt_key``: the deck key that gives it
    (``stages.<name>.dt`` or ``run.dt``); ``output``: ``[output]`` with ``[stages.output]`` on top;
    ``law_params``: the contact law's parameters, ``[contact]`` with ``[stages.contact]`` on top, and
    ``contact_given`` whether the stage's table gives the law any value; ``materials``: per material
    the contact properties that may change between stages (``[stages.materials.NAME]`` where given,
    else ``[materials.NAME]``); ``sources``: the indices of the ``[[particles]]`` tables inserted at
    the stage's start.
    """

    index: int
    stage: Any
    dt: float | None
    dt_key: str
    output: Any
    law_params: Any
    contact_given: bool
    materials: dict[str, dict[str, Any]]
    sources: tuple[int, ...]

    @property
    def name(self) -> str:
        return self.stage.name


def resolve_stages(resolved: Any) -> list[StageSettings]:
    """Every stage's :class:`StageSettings`, in deck order (validated with the deck: pure, no I/O)."""
    from .deck.load import stage_contact_values

    deck = resolved.deck
    stages = list(deck.stages)
    first = stages[0].name if stages else None
    keys = Simulation.MUTABLE_MATERIAL_KEYS
    base_materials = {name: spec.to_material(name) for name, spec in deck.materials.items()}
    out = []
    for index, stage in enumerate(stages):
        values = stage_contact_values(stage.contact, deck.contact.law) if stage.contact else {}
        params = resolved.law_params
        if values:
            params = type(params)(**{**params.model_dump(), **values})
        materials = {}
        for name, base in base_materials.items():
            props = {k: getattr(base, k) for k in keys}
            if name in stage.materials:
                props.update(stage.materials[name].values())
            materials[name] = props
        sources = tuple(k for k, src in enumerate(deck.particles or []) if (src.stage or first) == stage.name)
        out.append(
            StageSettings(
                index=index,
                stage=stage,
                dt=stage.dt if stage.dt is not None else deck.run.dt,
                dt_key=f"stages.{stage.name}.dt" if stage.dt is not None else resolved.step_key,
                output=resolved.output_for(stage.name),
                law_params=params,
                contact_given=bool(values),
                materials=materials,
                sources=sources,
            )
        )
    return out


# ---------------------------------------------------------------------------------------- progress
@dataclass
class _Progress:
    """Progress lines on rank 0 (stderr by default): time, step, particles over all ranks, speed, ETA.

    Serial: the wall-clock timer is checked at every step. Under MPI the particle count is a
    collective, so every rank must join it at the same steps: rank 0 decides at agreed steps whether
    a line is due and broadcasts the decision with the number of steps until the next decision (a
    quarter of the print interval at the measured speed), so the cost is one broadcast every few
    hundred steps.
    """

    stream: TextIO | None
    comm: Any = None
    enabled: bool = True
    every: float = 2.0
    _last: float = field(default_factory=_time.perf_counter)
    _last_step: int = 0
    _next_check: int = 0
    _check_step: int = 0
    _check_time: float = field(default_factory=_time.perf_counter)
    _stage_start: float = field(default_factory=_time.perf_counter)
    #: seconds between the lines of a phase before the stepping (None: SETUP_PROGRESS_EVERY)
    setup_every: float | None = None

    @property
    def _parallel(self) -> bool:
        return self.comm is not None and self.comm.size > 1

    def update(self, sim: Simulation, stage: str, frac: float | None, force: bool = False) -> None:
        if not self.enabled:
            return
        now = _time.perf_counter()
        if not self._parallel:
            if self.stream is None or (not force and now - self._last < self.every):
                return
            self._print(sim, stage, frac, sim.n_particles, now)
            return
        if not force and sim.step_count < self._next_check:
            return
        decision = None
        if self.comm.rank == 0:
            rate = (sim.step_count - self._check_step) / max(now - self._check_time, 1e-9)
            interval = int(min(max(rate * self.every / 4.0, 1.0), 100_000.0))
            decision = (force or now - self._last >= self.every, interval)
            self._check_step, self._check_time = sim.step_count, now
        due, interval = self.comm.bcast(decision, root=0)
        self._next_check = sim.step_count + interval
        if not due:
            return
        n = sim.count_particles()  # collective: every rank is here at this step
        if self.stream is not None:
            self._print(sim, stage, frac, n, now)

    def _print(self, sim: Simulation, stage: str, frac: float | None, n: int, now: float) -> None:
        rate = (sim.step_count - self._last_step) / max(now - self._last, 1e-9)
        eta = ""
        if frac is not None and 0 < frac < 1 and rate > 0:
            remaining = (1 - frac) / frac * (now - self._stage_start)
            eta = f", ETA {remaining:.0f} s"
        line = (
            f"[{stage}] t = {sim.time:.6g} s, step {sim.step_count}, {n} particles, {rate:,.0f} steps/s{eta}"
        )
        tty = getattr(self.stream, "isatty", lambda: False)()
        self.stream.write(("\r" + line + "\033[K") if tty else line + "\n")
        self.stream.flush()
        self._last, self._last_step = now, sim.step_count

    def stage_start(self, step: int = 0) -> None:
        self._stage_start = self._last = self._check_time = _time.perf_counter()
        self._last_step = self._check_step = step
        self._next_check = step + 10  # the first steps compile kernels: decide again soon

    def done(self) -> None:
        if self.stream is not None and getattr(self.stream, "isatty", lambda: False)():
            self.stream.write("\n")

    @contextmanager
    def phase(self, label: str) -> Iterator[None]:
        """Progress lines while a phase before the stepping runs (a source making its particles, a
        stage's preparation): on rank 0, from a timer thread, one every ``setup_every`` seconds
        (default :data:`SETUP_PROGRESS_EVERY`) once the phase has run that long, with the latest
        report of the source (:mod:`pdem.sources.progress`: what it does, a fraction done and an
        ETA where it gives one). A short phase prints nothing. Only rank 0 prints, and nothing is
        communicated, so the phase may hold collectives."""
        if not self.enabled or self.stream is None:
            yield
            return
        every = self.setup_every if self.setup_every is not None else SETUP_PROGRESS_EVERY
        ticker = _PhaseTicker(self.stream, label, every)
        from .sources.progress import reporting

        with reporting(ticker.report):
            ticker.start()
            try:
                yield
            finally:
                ticker.stop()


class _PhaseTicker:
    """The timer thread of :meth:`_Progress.phase`: prints the phase's state every ``every`` s."""

    def __init__(self, stream: TextIO, label: str, every: float) -> None:
        self.stream, self.label, self.every = stream, label, max(float(every), 1e-3)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._start = _time.perf_counter()
        self._printed = False
        self._printed_tty = False
        # the latest report: (phase, fraction, detail, when) and where the phase's fraction started
        self._state: tuple[str, float | None, str, float] | None = None
        self._phase_start: tuple[str, float, float | None] | None = None

    def report(self, phase: str, fraction: float | None, detail: str) -> None:
        now = _time.perf_counter()
        with self._lock:
            if self._phase_start is None or self._phase_start[0] != phase:
                self._phase_start = (phase, now, fraction)
            elif self._phase_start[2] is None and fraction is not None:
                self._phase_start = (phase, now, fraction)
            self._state = (phase, fraction, detail, now)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="pdem-progress", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """End the thread; a phase that printed lines ends with one saying it is done."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if not self._printed:
            return
        try:
            self._print(f"[setup] {self.label}: done ({_time.perf_counter() - self._start:.0f} s)")
            if self._printed_tty:
                self.stream.write("\n")
                self.stream.flush()
        except (OSError, ValueError):
            pass

    def _run(self) -> None:
        due = self._start + self.every
        while not self._stop.wait(max(due - _time.perf_counter(), 0.0)):
            try:
                self._print(self.line(_time.perf_counter()))
            except (OSError, ValueError):  # a closed or full stream: progress is not worth an error
                return
            due += self.every * max(1, math.ceil((_time.perf_counter() - due) / self.every))

    def line(self, now: float) -> str:
        """The progress line at ``now``: the phase, the source's latest report, the time elapsed."""
        with self._lock:
            state, start = self._state, self._phase_start
        text = f"[setup] {self.label}"
        if state is not None:
            phase, fraction, detail, when = state
            text += f": {phase}" + (f", {detail}" if detail else "")
            if fraction is not None:
                fraction = min(max(fraction, 0.0), 1.0)
                text += f", {100.0 * fraction:.0f}% done"
                if start is not None and start[2] is not None and fraction > start[2] and fraction < 1.0:
                    rate = (fraction - start[2]) / max(when - start[1], 1e-9)
                    eta = max((1.0 - fraction) / rate - (now - when), 0.0)
                    text += f", ETA {eta:.0f} s"
        return text + f" ({now - self._start:.0f} s so far)"

    def _print(self, line: str) -> None:
        tty = getattr(self.stream, "isatty", lambda: False)()
        self.stream.write(("\r" + line + "\033[K") if tty else line + "\n")
        self.stream.flush()
        self._printed = True
        self._printed_tty = self._printed_tty or tty


# ---------------------------------------------------------------------------------------- runner
class Runner:
    """Executes a :class:`pdem.deck.ResolvedDeck`.

    ``output`` overrides the deck's ``output.directory``; an existing non-empty directory is refused
    unless ``overwrite`` (its content is replaced only once the run has passed its start checks),
    and a path that is not, or cannot become, a directory is an :class:`~pdem.errors.InputError`.
    ``resume`` is ``(state, meta)`` from :func:`pdem.io.checkpoint.read_checkpoint`; with ``append``
    the run continues the output already in ``output`` (the checkpoint's own run), see the module
    doc. ``series_from``: resuming into a new directory, the directory whose series (up to the
    checkpoint) the new series continue, so that they hold the whole run. ``max_steps`` counts steps
    from the start of the run (a resumed run included). ``stdout`` receives the thermo lines
    (``output.thermo_every``; default ``sys.stdout``), rank 0 only. ``dry``: only
    :meth:`check_scene` will be called (the output path is not looked at).

    Nothing is created on disk before :meth:`run` has built the scene and passed its checks.

    ``stages``: every stage's settings, resolved from the deck once (:func:`resolve_stages`);
    :meth:`start_stage` starts one. ``output``: the output directory and its bookkeeping (lock,
    marker, journal of a resume, writers, series rows, frame bounds), a
    :class:`pdem.io.run_output.RunOutput`.
    """

    def __init__(
        self,
        resolved: Any,
        *,
        output: Path | None = None,
        overwrite: bool = False,
        max_steps: int | None = None,
        comm=None,
        progress: TextIO | None = sys.stderr,
        resume: tuple[dict, dict] | None = None,
        overrides: tuple[str, ...] = (),
        append: bool = False,
        series_from: Path | None = None,
        stdout: TextIO | None = None,
        dry: bool = False,
    ) -> None:
        from .parallel.comm import SerialComm

        self.resolved = resolved
        self.deck = resolved.deck
        #: every stage's settings, resolved once from the deck (:func:`resolve_stages`)
        self.stages: list[StageSettings] = resolve_stages(resolved)
        self.comm = comm if comm is not None else SerialComm()
        self.root = self.comm.rank == 0  # only rank 0 touches files
        self.max_steps = max_steps
        self.overrides = tuple(overrides)
        self.resume = resume
        self.append = bool(append)
        if self.append and resume is None:
            raise InputError("append=True continues the output of a resumed run; pass resume=(state, meta)")
        self.series_from = Path(series_from) if series_from is not None and not self.append else None
        self.overwrite = bool(overwrite) and not self.append
        out = output if output is not None else Path(self.deck.output.directory)
        self.out = Path(out)
        self.resume_step = int(resume[0]["scalars/step"]) if resume is not None else None
        if resume is not None and max_steps is not None and max_steps <= self.resume_step:
            raise InputError(
                f"--steps {max_steps} would stop the run at step {max_steps}, but the checkpoint is at step "
                f"{self.resume_step} already: --steps counts steps from the start of the run, so give more "
                f"than {self.resume_step} (e.g. --steps {self.resume_step + 1000}), or leave it out to run "
                "every stage"
            )
        self.deck_text = resolved.resolved_toml()
        if resume is not None and _same_deck(resume[1].get("deck"), self.deck_text):
            self.deck_text = resume[1]["deck"]  # unchanged: keep its text (and header) as it was
        self.progress = _Progress(progress if self.root else None, self.comm, enabled=progress is not None)
        #: the output directory and its bookkeeping (checked now: refused here, nothing created)
        self.output = RunOutput(
            self.out,
            comm=self.comm,
            resolved=resolved,
            deck_text=self.deck_text,
            stage_names=[st.name for st in self.stages],
            resume_step=self.resume_step,
            append=self.append,
            overwrite=self.overwrite,
            series_from=self.series_from,
            notes=self.progress.stream,
            dry=dry,
        )
        self.stdout = (stdout if stdout is not None else sys.stdout) if self.root else None
        self.boundaries: dict[str, Any] = {}
        self.stopped_early = False
        self._setup_done = False
        self._thermo_header: str | None = None
        self._checked_before_insertion = False

    @property
    def series(self) -> dict[str, list[dict[str, float]]]:
        """Every series row of the run, by stage (:attr:`RunOutput.series`)."""
        return self.output.series

    @property
    def output_parallel(self) -> str | None:
        """How snapshots are written under MPI, decided when the output opens."""
        return self.output.output_parallel

    @property
    def writers(self) -> list[Any]:
        """The snapshot writers of this rank."""
        return self.output.writers

    def build(self) -> Simulation:
        deck = self.deck
        law_cls = load("contact_laws", deck.contact.law)
        law = law_cls(**self.resolved.law_params.model_dump())
        sim = Simulation(comm=self.comm, law=law)
        for name, mat in deck.materials.items():
            sim.add_material(mat.to_material(name))
        for pair in deck.material_pairs or []:
            values = {k: v for k, v in pair.model_dump().items() if k != "materials" and v is not None}
            sim.materials.set_pair(pair.materials[0], pair.materials[1], **values)
        run = deck.run
        sim.dt = run.dt
        sim.dt_fraction = run.dt_fraction
        sim.force_dt = run.force_dt
        sim.stiffness_limit = run.stiffness_limit
        sim.gravity = tuple(run.gravity)
        sim.skin = run.skin
        sim.max_overlap = run.max_overlap
        sim.decomposition_dims = tuple(run.decomposition) if run.decomposition else None
        sim.balance_threshold = run.balance_threshold
        if deck.domain.periodic:
            sim.set_periodic(deck.domain.lo, deck.domain.hi, deck.domain.periodic)
        if any(load("sources", params.source).keeps_rows for params in deck.particles or []):
            from .sources.api import ROW_FIELD

            sim.register_field(
                ROW_FIELD, "int64", output=True, default=-1,
                doc="the grain's row in its packing file (from 0); -1: from another source",
            )  # fmt: skip
        for name, params in self.resolved.boundaries.items():
            cls = load("boundaries", params.type)
            self.boundaries[name] = _plugin_call(
                f"boundary '{name}' (type '{params.type}', {_where(cls)})",
                lambda cls=cls, name=name, params=params: sim.add_boundary(cls(name, params)),
            )
        self.sim = sim
        return sim

    def _insert_particles(self, stage: str | None, first_stage: str) -> None:
        """Add the particles of every source inserted at the start of the stage named ``stage``
        (sources without a ``stage`` key go to ``first_stage``); :meth:`start_stage` does this."""
        sources = [
            k for k, params in enumerate(self.deck.particles or []) if (params.stage or first_stage) == stage
        ]
        self._insert_sources(sources)

    def _insert_sources(self, sources: Any) -> None:
        """Add the particles of the ``[[particles]]`` tables ``sources`` (indices): each source plugin
        (entry points of ``pdem.sources``) generates them with seed ``run.seed`` + its index. A long
        source (a pour) prints progress lines (:meth:`_Progress.phase`)."""
        for k in sources:
            params = self.deck.particles[k]
            with self.progress.phase(f"particles.{k} (source '{params.source}')"):
                self._insert_source(k, params)

    def _insert_source(self, k: int, params: Any) -> None:
        from .sources.api import produce, produce_part

        sim = self.sim
        source = load("sources", params.source)(params)
        mat = sim.materials[sim.materials.index(params.material)]
        args = dict(base_dir=self.resolved.base_dir, seed=self.deck.run.seed + k, material=mat,
                    where=f"particles.{k}")  # fmt: skip
        part = None
        if sim.comm.size > 1 and source.partitioned:  # each rank makes its own grains only
            dec = sim.decomposition
            box = sim.box
            talk = {"comm": sim.comm} if source.collective else {}  # (a collective source shares its work)
            if dec is None or not dec.placed:
                survey = source.survey(base_dir=args["base_dir"], seed=args["seed"], material=mat, **talk)
                # (a source may place grains outside a periodic box: they are wrapped into it)
                sim.place_decomposition(survey.sample if box is None else box.wrapped(survey.sample))
                dec = sim.decomposition
            # a little wider than the subdomain: positions are snapped to a periodic box's grid
            finite = np.isfinite(dec.sub_hi - dec.sub_lo)
            pad = 1e-9 * np.maximum(np.where(finite, np.abs(dec.sub_hi) + np.abs(dec.sub_lo), 1.0), 1.0)
            lo, hi = dec.sub_lo - pad, dec.sub_hi + pad
            if box is not None:  # along a periodic axis the source's own coordinates may be an image
                bounds = source.bounds()
                for d in np.flatnonzero(box.periodic):
                    if bounds is None or bounds[0][d] < box.lo[d] or bounds[1][d] >= box.hi[d]:
                        lo[d], hi[d] = -np.inf, np.inf
            part = produce_part(source, lo=lo, hi=hi, comm=sim.comm, **args)
            out = part.output
        else:
            out = produce(source, comm=sim.comm, **args)
        vel = (
            out.velocities
            if out.velocities is not None
            else np.broadcast_to(np.asarray(params.velocity or (0, 0, 0), float), out.positions.shape)
        )
        motion: Any = params.motion
        if out.fixed is not None and out.fixed.any():  # e.g. a lattice's fixed_edges
            motion = np.where(out.fixed, "fixed", params.motion)
        extra: dict[str, Any] = {}
        if source.keeps_rows and out.rows is not None:
            from .sources.api import ROW_FIELD

            extra[ROW_FIELD] = out.rows
        kwargs = dict(
            material=params.material,
            velocities=vel,
            motion=motion,
            fixed_translation=getattr(params, "fixed_translation", ""),
            fixed_rotation=getattr(params, "fixed_rotation", ""),
            **extra,
        )
        if part is not None:
            sim.add_particle_part(out.positions, out.radii, part.index, part.total, **kwargs)
        else:
            sim.add_particles(out.positions, out.radii, **kwargs)

    # ---------------------------------------------------------------------------- measuring
    def measurements(self) -> dict[str, float]:
        self.sim.check_deferred()  # the last step's check first (the loop defers it: _run_stage)
        out: dict[str, float] = {}
        for name, b in self.boundaries.items():
            for key, val in b.measurements(self.sim).items():
                out[f"{name}.{key}"] = float(val)
        return out

    def _balance_columns(self) -> dict[str, float]:
        """Under MPI: max/mean over ranks of owned particles and of estimated work (collective)."""
        sim = self.sim
        if sim.comm.size == 1:
            return {}
        n = sim.n_particles  # parked (removed) rows are not counted
        work = int(sim.model_work().sum())
        counts = np.array(sim.comm.allgather((n, work)), dtype=float)
        mean = counts.mean(axis=0)
        return {
            "imbalance_particles": float(counts[:, 0].max() / max(mean[0], 1e-300)),
            "imbalance_work": float(counts[:, 1].max() / max(mean[1], 1e-300)),
            "rebalances": int(sim.decomposition.n_rebalances if sim.decomposition else 0),
        }

    def _solver_columns(self, stage: str) -> dict[str, float]:
        """DEM-C: the last step's iterations and residual, the count of unconverged steps; every
        step's values since the last row go to ``solver_<stage>.csv`` (rank 0)."""
        st = self.sim.integrator
        if st is None or not st.stats():  # an explicit method: no solver columns
            return {}
        self.output.write_solver_rows(stage, st.drain_records())
        return {
            "solver_iterations": int(st.last_iterations),
            "solver_residual": float(st.last_residual),
            "solver_unconverged": int(st.n_unconverged),
        }

    def _series_row(self, stage: str) -> None:
        """One row of ``series_<stage>.csv`` (collective); a step already written is not repeated
        (a stage's last step that is also on the series cadence, a resumed run's first step)."""
        sim = self.sim
        sim.check_deferred()
        if not self.output.series_due(stage, sim.step_count):
            return
        ke_t, ke_r = sim.kinetic_energy()
        row = {
            "time": sim.time,
            "step": int(sim.step_count),
            "particles": int(sim.count_particles()),
            "ke_trans": ke_t,
            "ke_rot": ke_r,
            **self._balance_columns(),
            **self._solver_columns(stage),
            **self.measurements(),
        }
        self.output.keep_row(stage, row)
        self._boundary_records(stage)
        self.output.write_row(stage, row)

    def _boundary_records(self, stage: str) -> None:
        """Rows the boundaries sampled since the last series row (``Boundary.records``, collective),
        appended by rank 0 to ``<boundary>.<stage>.csv``."""
        for name, b in self.boundaries.items():
            self.output.write_records(name, stage, b.records(self.sim))

    def frame(self, stage: str, own: bool = False) -> Frame:
        """The snapshot of every particle (gathered on every rank), or with ``own`` of the particles
        this rank owns (for per-rank writers). The walls and the scene bounds are the same either
        way. A collective call."""
        sim = self.sim
        if own:
            p = sim.own_particles(contacts=True)
            contacts = p.pop("contacts")
        else:
            p = sim.get_particles()
            contacts = np.zeros(len(p["id"]), dtype=np.int32)
            c = sim.contacts()
            if len(c["id_i"]):  # p["id"] is sorted: map contact ends to rows by binary search
                rows = np.searchsorted(p["id"], np.concatenate([c["id_i"], c["id_j"]]))
                contacts = np.bincount(rows, minlength=len(p["id"])).astype(np.int32)
        particles = {
            "id": p["id"],
            "x": p["x"],
            "v": p["v"],
            "w": p["w"],
            "f": p["f"],
            "t": p["t"],
            "r": p["r"],
            "mass": p["mass"],
            "material": p["material"].astype(np.int32),
            "contacts": contacts,
        }
        if "row" in p:  # a packing file's rows (sources with keeps_rows), in every snapshot
            particles["row"] = p["row"]
        walls = [
            WallState(
                w.name, int(w.kinds[0]), (w.rows if w.n_rows > 1 else w.params).copy(), w.force, w.torque
            )
            for w in sim.walls.values()
            if w.active
        ]
        x = p["x"]
        xmin = x.min(axis=0) if len(x) else np.full(3, np.inf)
        xmax = x.max(axis=0) if len(x) else np.full(3, -np.inf)
        rmax = p["r"].max() if len(x) else -np.inf
        if own and self.comm.size > 1:  # min and max are exact: the same bounds as gathered
            ext = self.comm.allgather((xmin, xmax, rmax))
            xmin = np.min([e[0] for e in ext], axis=0)
            xmax = np.max([e[1] for e in ext], axis=0)
            rmax = max(e[2] for e in ext)
        if np.isfinite(rmax):
            lo, hi = xmin - 2 * rmax, xmax + 2 * rmax
        else:
            lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for w in sim.walls.values():
            wlo, whi = w.bounding_box()
            lo = np.minimum(lo, np.where(np.isfinite(wlo), wlo, lo))
            hi = np.maximum(hi, np.where(np.isfinite(whi), whi, hi))
        lo, hi = self.output.grow_bounds(lo, hi)  # grow only, so infinite walls keep their drawn size
        return Frame(
            time=sim.time, step=sim.step_count, stage=stage, particles=particles, walls=walls, bounds=(lo, hi)
        )

    def _write_frame(self, stage: str) -> None:
        """A snapshot for every writer that has none at this step yet (collective)."""
        self.sim.check_deferred()
        step = self.sim.step_count
        frame = self.output.write_frame(step, lambda: self.frame(stage), lambda: self.frame(stage, own=True))
        if self.output.contacts_due(step):
            self._write_contacts(frame)
        if self.output.continuum_on:
            self.output.write_continuum(self.sim, stage, snapshot=True)

    def _write_contacts(self, frame: Frame | None) -> None:
        """The contact network at this step (``output.contacts``; collective, rank 0 writes)."""
        from .io.contacts import contact_lines

        sim = self.sim
        contacts = sim.contacts()  # collective: every rank's contacts
        particles = frame.particles if frame is not None else sim.get_particles()  # collective
        lines = lambda: contact_lines(contacts, particles, sim.box)  # rank 0 only
        self.output.write_contacts(lines, sim.time, sim.step_count)

    def _checkpoint(self, stage_index: int, stage_start: tuple[float, int], started: bool = True) -> Path:
        sim = self.sim
        sim.check_deferred()  # a checkpoint holds only a checked state
        stages = self.deck.stages
        bounds = self.output.bounds
        meta = {
            "deck": self.deck_text,
            "deck_path": str(Path(self.resolved.path).resolve()) if self.resolved.path is not None else "",
            "overrides": json.dumps(list(self.overrides)),
            "pdem_version": __version__,
            "stage_index": stage_index,
            "stage_name": stages[stage_index].name if stage_index < len(stages) else "",
            "stage_start_time": stage_start[0],
            "stage_start_step": stage_start[1],
            "stage_started": int(started),
            "boundaries": json.dumps({n: b.state() for n, b in self.boundaries.items()}),
            "output": str(self.out.resolve()),
            # the scene box snapshots have grown to, so a resumed run draws infinite walls alike
            "frame_bounds": json.dumps([b.tolist() for b in bounds]) if bounds is not None else "",
        }
        state = sim.state_dict(local=sim.comm.size > 1)  # collective; on several ranks each its own share
        return self.output.write_checkpoint(sim.step_count, state, meta)

    # ---------------------------------------------------------------------------- running
    def check_scene(self) -> str:
        """What ``pdem check`` does beyond the deck: build the first stage's scene (its particles are
        made) and run the start checks of :meth:`run` (every stage's dt against the law's stability
        estimate, initial overlaps between grains and with walls, the packing files of later
        stages), writing nothing. A one-line description of the scene."""
        sim = self.build()
        self.start_stage(0)
        self._check_stages(0)
        self._check_later_files(0)
        self._check_measured(0)
        return (
            f"{sim.count_particles()} particles at the start, dt = {sim.dt:.4g} s (stability estimate "
            f"{sim.dt_critical:.4g} s)"
        )

    def _check_dt_before_insertion(self, start_index: int) -> None:
        """Refuse, before any source makes its grains (a pour can take minutes), a stage dt above
        the law's stability estimate for the *largest* grains a source present in that stage can
        make: the estimate grows with the radius, so such a dt is above it for any grains the source
        makes. Sources that cannot tell their largest radius beforehand are left to the check after
        insertion."""
        if self.deck.run.force_dt:
            return
        sim = self.sim
        limits: dict[int, tuple[float, float]] = {}  # source index -> (estimate, its largest radius)
        for k, params in enumerate(self.deck.particles or []):
            try:
                r = load("sources", params.source)(params).r_max()
            except PdemError:
                raise
            except Exception:  # noqa: BLE001 - a plugin's estimate is optional
                r = None
            if r is None or not math.isfinite(r) or r <= 0:
                continue
            m = sim.materials.index(params.material)
            mass = 4.0 / 3.0 * math.pi * r**3 * sim.materials[m].density
            with np.errstate(all="ignore"):
                crit = sim.law.critical_dt(
                    sim.materials, np.asarray([r]), np.asarray([m], dtype=np.int64), np.asarray([mass])
                )
            limits[k] = (float(crit), r)
        present: list[int] = []  # the sources whose grains are there during the stage
        for st in self.stages:
            present += st.sources
            known = [(limits[k], k) for k in present if k in limits]
            if st.index >= start_index and known:
                (crit, r), k = min(known)
                self._check_stage_dt(st, crit, largest=(f"particles.{k}", r))

    def _check_stage_dt(
        self, st: StageSettings, crit: float, largest: tuple[str, float] | None = None
    ) -> None:
        """The check of a stage's dt (its own, else ``run.dt``) against the law's stability estimate
        ``crit`` [s]: above it (and without ``run.force_dt``) an :class:`~pdem.errors.InputError`
        naming the key that gives the dt (``stages.<name>.dt`` or ``run.dt``), its value, the limit
        and the remedy. ``largest``: ``(source key, radius)``, ``crit`` is the estimate for the
        largest grains that source can make (checked before they are made), not for the particles
        present. A stage without a dt of its own or from ``run.dt``, and a law without a finite
        estimate, pass."""
        dt = st.dt
        if dt is None or self.deck.run.force_dt or not math.isfinite(crit) or not dt > crit:
            return
        law = self.sim.law.name
        if largest is None:
            limit = f"the stability estimate {crit:.4g} s of law '{law}' for these particles"
            practice = "practice: 0.1–0.3 of it"
        else:
            limit = (
                f"the stability estimate of law '{law}' even for the largest grains source {largest[0]} "
                f"makes (radius {largest[1]:.4g} m: {crit:.4g} s), so for any grains it makes"
            )
            practice = "practice: 0.1–0.3 of the estimate for the smallest grains, which `pdem check` prints"
        raise InputError(
            f"{st.dt_key}: dt = {dt:.4g} s for stage '{st.name}' exceeds {limit}; use dt ≤ {crit:.4g} s "
            f"({practice}), or set run.force_dt = true to run anyway"
        )

    def _stability_estimate(self) -> float:
        """The law's stability estimate [s] for the particles present now, as the simulation's
        preparation computes it (collective)."""
        from .parallel.comm import all_min

        sim = self.sim
        p = sim.particles
        return all_min(self.comm, sim.law.critical_dt(sim.materials, p.r, p.mat, p.mass))

    def _check_measured(self, start_index: int) -> None:
        """Every quantity a stage ends on (and every thermo column) is one the boundaries measure:
        a boundary plugin that does not declare its keys is only known once built (collective)."""
        measured = sorted(self.measurements())
        wanted = []
        for st in self.stages:
            if st.index >= start_index and st.stage.end.quantity is not None:
                wanted.append((f"stages.{st.name}.end.quantity", st.stage.end.quantity))
            for k, key in enumerate(getattr(st.output, "thermo", None) or ()):
                if "." in key:
                    wanted.append((f"output.thermo.{k}", key))
        for where, key in wanted:
            if key not in measured:
                name = key.split(".", 1)[0]
                mine = [m for m in measured if m.startswith(name + ".")]
                raise InputError(
                    f"{where}: '{key}' is not measured; boundary '{name}' measures "
                    + (", ".join(f"'{m}'" for m in mine) if mine else "nothing")
                )

    def _check_later_files(self, start_index: int) -> None:
        """Read the packing files of the sources of later stages now (they are validated as they are
        read: non-finite values, radii ≤ 0, malformed rows), so a bad file stops the run before it
        writes anything rather than when its stage starts."""
        from .sources import read_spheres

        names = [s.name for s in self.deck.stages]
        for k, src in enumerate(self.deck.particles or []):
            spec = src.model_dump()
            if spec.get("source") != "file" or not spec.get("path"):
                continue
            stage = spec.get("stage") or names[0]
            if stage in names and names.index(stage) > start_index:
                path = Path(self.resolved.base_dir) / spec["path"]
                if path.is_file() and path.stat().st_size < _READ_AHEAD_BELOW:
                    try:
                        with self.progress.phase(f"particles.{k}: reading {path.name} (stage '{stage}')"):
                            read_spheres(path)
                    except InputError as exc:
                        raise InputError(f"particles.{k}.path (stage '{stage}'): {exc}") from None

    def run(self) -> dict[str, Any]:
        from .deck.resume import ResumePoint

        t_begin = _time.perf_counter()
        sim = self.build()
        stages = self.stages
        start_index = 0
        started = False
        stage_start: tuple[float, int] | None = None
        if self.resume is None:
            start = ResumePoint(0, False, 0, 0.0)
        else:
            state, meta = self.resume
            with self.progress.phase(f"loading the checkpoint at step {self.resume_step}"):
                sim.load_state(state)
            start = ResumePoint.from_checkpoint(state, meta)
            start_index, started = start.stage_index, start.started
            stage_start = (float(meta["stage_start_time"]), int(meta["stage_start_step"]))
            saved = json.loads(meta.get("boundaries", "{}"))
            for name, b in self.boundaries.items():
                b.restore(saved.get(name, {}))
            if meta.get("frame_bounds"):
                lo, hi = json.loads(meta["frame_bounds"])
                self.output.bounds = (np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))
        self._resume_dt = float(self.resume[0]["scalars/dt"]) if self.resume is not None else None
        # ---- checks that need the scene, before anything is written
        classes = self.output.writer_classes(self.deck.output.formats)
        if start_index < len(stages):
            resumed_here = self.resume is not None and started
            # a resume has the particles of the stages before its checkpoint (the first's included)
            self.start_stage(
                start_index, insert=not resumed_here and (self.resume is None or start_index > 0)
            )
            if not resumed_here:
                stage_start = (sim.time, sim.step_count)
            self._check_stages(start_index)
            self._check_later_files(start_index)
            self._check_measured(start_index)
        t_start = _time.perf_counter()
        steps_start = sim.step_count
        try:
            with self.progress.phase(f"opening the output in {self.out}"):
                self.output.open(
                    classes,
                    start,
                    out_cfg=self.deck.output,
                    count_particles=sim.count_particles,
                    boundary_names=list(self.boundaries),
                )
            if start_index >= len(stages):
                self._setup_done = True  # a finished run: nothing left to step
            for index in range(start_index, len(stages)):
                resumed_here = self.resume is not None and index == start_index and started
                if index != start_index:
                    self.start_stage(index)
                    stage_start = (sim.time, sim.step_count)
                if not self._run_stage(index, stages[index].stage, stage_start, resumed_here):
                    self.stopped_early = True
                    break
        except BaseException as exc:
            self._close()
            if not self._setup_done and not self.output.continuing:
                self.output.undo()
            self._finish_output(exc)
            raise
        self._close()
        t_end = _time.perf_counter()
        stepping = t_end - t_start
        summary: dict[str, Any] = {
            "pdem_version": __version__,
            "steps": sim.step_count,
            "time": sim.time,
            "wall_time_s": t_end - t_begin,  # the whole run: setup (a pour included) and stepping
            "setup_time_s": t_start - t_begin,  # building the scene, making the particles, the checks
            "stepping_time_s": stepping,  # the stages' steps and their output
            "particles": sim.count_particles(),
            "dt": sim.dt,
            "dt_critical": sim.dt_critical if math.isfinite(sim.dt_critical) else None,
            "steps_run": sim.step_count - steps_start,
            "steps_per_second": (sim.step_count - steps_start) / max(stepping, 1e-9),
            "completed": not self.stopped_early,
            "output_parallel": self.output_parallel,
            "results": {},
        }
        if self.resume is not None:
            summary["resumed_from_step"] = self.resume_step
        rec = sim.stiffness
        if rec["checks"] and math.isfinite(rec["min_dt"]):
            # rounded: the per-particle sums may differ in the last bit between rank counts
            summary["stiffness_bound"] = {
                "dt_min": float(f"{rec['min_dt']:.6g}"),
                "at_step": int(rec["step"]),
                "dt_over_bound": float(f"{sim.dt / rec['min_dt']:.4g}"),
                "checks": int(rec["checks"]),
                "checks_exceeded": int(rec["exceeded"]),
            }
        solver = sim.integrator.summary() if sim.integrator is not None else None
        if solver and any(st.contact for st in self.deck.stages):
            solver["stage_settings"] = True  # [stages.contact]: the settings above are the last stage's
        if solver is not None:
            summary["solver"] = solver
        merged = self._merged_series()
        for name, b in self.boundaries.items():
            res = b.summary(merged)
            if res:
                summary["results"][name] = res
        if self.root:
            try:
                text = json.dumps(json_finite(summary), indent=2, allow_nan=False)
                (self.out / "summary.json").write_text(text + "\n")
            finally:
                self._finish_output(None)
        return summary

    def _close(self) -> None:
        self.output.close()
        self.progress.done()

    def _finish_output(self, failed: BaseException | None) -> None:
        """Rank 0, last: the output's journal settled (a stage that reached its cap keeps what the
        resume wrote), its marker brought up to date, its lock released."""
        self.output.finish(failed, stepped=self._setup_done, keep=isinstance(failed, StageLimitError))

    def _merged_series(self) -> dict[str, np.ndarray]:
        """Every stage's series rows in stage order, with a ``stage`` column (the stage's index), so
        that a boundary's summary reads each value from the stage it belongs to."""
        from .boundaries.api import merge_series

        return merge_series(self.series, [s.name for s in self.deck.stages])

    def start_stage(self, index: int, *, insert: bool = True) -> StageSettings:
        """Start stage ``index`` of the built simulation (:meth:`build`): insert the particles of the
        sources placed at its start (``insert=False``: they are there already, e.g. a resume inside
        the stage), then enter it: the stage's materials and contact settings, boundaries on or off,
        its dt, and the preparation for stepping (initial overlaps, neighbour lists, first forces).

        The stage's dt is checked against the law's stability estimate before it is set; the first
        stage this runner starts with insertion is checked before any source makes its grains (a
        pour can take minutes), for the largest grains the sources can make. Errors name the deck
        key. Returns the stage's :class:`StageSettings`. Used by :meth:`run` for every stage and by
        :meth:`check_scene` (and ``pdem advise``'s probe) for the first."""
        st = self.stages[index]
        if insert:
            if not self._checked_before_insertion:
                self._checked_before_insertion = True
                self._check_dt_before_insertion(index)
            self._insert_sources(st.sources)
        self._enter_stage(st)
        return st

    def _enter_stage(self, st: StageSettings) -> None:
        """Enter a stage: its materials and contact settings, boundaries on or off, its dt (checked
        first against the law's stability estimate, naming the key), preparation (initial overlaps:
        errors name the deck key)."""
        sim = self.sim
        sim.set_stage(st.name)
        self._stage_materials(st)
        self._stage_contact(st)
        if st.dt is not None:
            self._check_stage_dt(st, self._stability_estimate())
            if sim.dt != st.dt:
                sim.dt = st.dt
        with self.progress.phase(f"stage '{st.name}': preparing (neighbour lists, first forces)"):
            sim.prepare()

    def _stage_contact(self, st: StageSettings) -> None:
        """The law's solver settings for this stage: ``[contact]`` with ``[stages.contact]`` on top
        (validated with the deck; a stage without the table gets ``[contact]`` back)."""
        law = self.sim.law
        params = st.law_params
        if getattr(params, "solver", None) == "gauss_seidel" and self.sim.comm.size > 1:
            raise InputError(
                f"stages.{st.name}.contact.solver: 'gauss_seidel' runs on one rank only (it sweeps the "
                "contacts in one sequence, so results would depend on the partition); use 'jacobi' or "
                "'apgd' under MPI"
            )
        if st.contact_given or law.params.model_dump() != params.model_dump():
            law.params = params

    def _stage_materials(self, st: StageSettings) -> None:
        """The materials' contact properties for this stage: ``[stages.materials.NAME]`` where given,
        else ``[materials.NAME]`` (a stage's values hold for that stage only). Also on a resume."""
        for name, values in st.materials.items():
            self.sim.set_material(name, **values)

    def _check_stages(self, start_index: int) -> None:
        """Before anything is written: every stage still to run has a dt within the law's stability
        estimate (as known from the particles now) and a length below :data:`MAX_STAGE_STEPS`."""
        sim = self.sim
        for st in self.stages[start_index:]:
            self._check_stage_dt(st, sim.dt_critical)
            self._stage_target(st.stage, st.dt if st.dt is not None else sim.dt)

    def _stage_target(self, stage: Any, dt: float, done: int = 0, elapsed: float = 0.0) -> int | None:
        """Steps from the stage's start at which its ``steps``/``time`` end it (None: neither given).
        ``done``, ``elapsed``: steps and time into the stage already run at another dt (a resume
        that changed it). Refuses a stage longer than :data:`MAX_STAGE_STEPS`."""
        end = stage.end
        target = end.steps
        if end.time is not None and dt:
            steps = (end.time - elapsed) / dt
            if not math.isfinite(steps) or steps > MAX_STAGE_STEPS:
                raise InputError(
                    f"stages.{stage.name}.end.time: time = {end.time!r} s at dt = {dt:.4g} s is "
                    f"{steps:.3g} steps, above the limit of {MAX_STAGE_STEPS:.0e} steps per stage; "
                    "shorten the stage or use larger particles (a larger dt)"
                )
            by_time = done + max(int(math.ceil(steps - 1e-9)), 0)
            target = by_time if target is None else min(target, by_time)
        return target

    def _describe_end(self, stage: Any) -> str:
        end = stage.end
        conds = []
        if end.time is not None:
            conds.append(f"time = {end.time!r} s")
        if end.steps is not None:
            conds.append(f"steps = {end.steps}")
        if end.kinetic_energy_below is not None:
            ke = sum(self.sim.kinetic_energy())
            conds.append(f"kinetic energy below {end.kinetic_energy_below!r} J (now {ke:.4g} J)")
        if end.quantity is not None:
            val = self.measurements()[end.quantity]
            op, ref = (">", end.above) if end.above is not None else ("<", end.below)
            conds.append(f"{end.quantity} {op} {ref!r} (now {val:.6g})")
        return " or ".join(conds)

    def _run_stage(self, index: int, stage: Any, stage_start: tuple[float, int], resumed: bool) -> bool:
        """Run one (entered) stage; False if ``max_steps`` stopped the run."""
        sim = self.sim
        end = stage.end
        out = self.stages[index].output
        every_steps = out.every_steps
        every_time = out.every_time
        series_every = out.series_every_steps
        series_dt = out.series_every_time  # replaces series_every when given
        ckpt_every = out.checkpoint_every_steps
        check_every = getattr(end, "check_every", None) or 100
        if resumed and self._resume_dt is not None and sim.dt != self._resume_dt:
            # the resume changed dt mid-stage: count the rest of the stage's time at the new dt
            target_steps = self._stage_target(
                stage, sim.dt, sim.step_count - stage_start[1], sim.time - stage_start[0]
            )
        else:
            target_steps = self._stage_target(stage, sim.dt)
        self.progress.stage_start(sim.step_count)
        self._thermo_header = None  # each stage's thermo lines start with a header
        if not resumed:
            self._series_row(stage.name)
            self._write_frame(stage.name)
        self._setup_done = True  # from here on, a failure keeps what was written
        next_snapshot_time = (
            (math.floor((sim.time + 1e-12) / every_time) + 1) * every_time if every_time else None
        )
        quantity_start: float | None = None
        frac_quantity: float | None = None
        first_step = True
        while True:
            in_stage = sim.step_count - stage_start[1]
            done = target_steps is not None and in_stage >= target_steps
            if not done and in_stage > 0 and in_stage % check_every == 0:
                sim.check_deferred()
                if (
                    end.kinetic_energy_below is not None
                    and sum(sim.kinetic_energy()) < end.kinetic_energy_below
                ):
                    done = True
                if end.quantity is not None:
                    val = self.measurements()[end.quantity]
                    if (end.above is not None and val > end.above) or (
                        end.below is not None and val < end.below
                    ):
                        done = True
                    ref = end.above if end.above is not None else end.below
                    if quantity_start is None:
                        quantity_start = val
                    elif ref != quantity_start:  # progress of the quantity toward its target, for an ETA
                        frac_quantity = min(max((val - quantity_start) / (ref - quantity_start), 0.0), 1.0)
            if done:
                break
            if end.max_time is not None and sim.time - stage_start[0] >= end.max_time:
                self._series_row(stage.name)
                self._write_frame(stage.name)
                self._checkpoint(index, stage_start)
                latest = self.out / "checkpoints" / "latest.h5"
                raise StageLimitError(
                    f"stage '{stage.name}' reached max_time = {end.max_time!r} s without meeting its end "
                    f"condition ({self._describe_end(stage)}); a checkpoint was written, so the run can go "
                    f"on from here with a larger cap: pdem resume {shlex.quote(str(latest))} --set "
                    f"stages.{stage.name}.end.max_time={_larger(end.max_time)} (or revise the end "
                    f"condition the same way, e.g. --set stages.{stage.name}.end.<key>=<value>)"
                )
            if self.max_steps is not None and sim.step_count >= self.max_steps:
                self._series_row(stage.name)
                self._write_frame(stage.name)
                self._checkpoint(index, stage_start)
                return False
            t_before = sim.time
            # runs the boundaries' hooks; the step's stability check rides on the next step's list
            # test (one collective a step less on several ranks), or comes first in whatever reads
            # or writes the state before it (series, frames, checkpoints, measurements, thermo)
            if first_step:  # a first run compiles the method's step kernels here (~30 s for DEM-C)
                label = f"stage '{stage.name}': first step (kernels compile on a first run)"
                with self.progress.phase(label):
                    sim.step(defer_check=True)
                self.progress.stage_start(sim.step_count)  # rates and ETAs from the compiled steps
                first_step = False
            else:
                sim.step(defer_check=True)
            in_stage = sim.step_count - stage_start[1]
            if series_dt is not None:
                if _intervals(sim.time, stage_start[0], series_dt, sim.dt) > _intervals(
                    t_before, stage_start[0], series_dt, sim.dt
                ):
                    self._series_row(stage.name)
            elif in_stage % series_every == 0:
                self._series_row(stage.name)
            if every_steps and sim.step_count % every_steps == 0:
                self._write_frame(stage.name)
            elif next_snapshot_time is not None and sim.time >= next_snapshot_time - 1e-9 * sim.dt:
                self._write_frame(stage.name)
                next_snapshot_time += every_time
            if self.output.continuum_on:
                self.output.write_continuum(sim, stage.name, snapshot=False)
            if ckpt_every and sim.step_count % ckpt_every == 0:
                self._checkpoint(index, stage_start)
            self._thermo(stage.name, out)
            frac = in_stage / target_steps if target_steps else frac_quantity
            self.progress.update(sim, stage.name, frac)
        self._series_row(stage.name)
        self._write_frame(stage.name)
        self._checkpoint(index + 1, (sim.time, sim.step_count), started=False)
        self.progress.update(sim, stage.name, 1.0, force=True)
        return True

    def _thermo(self, stage: str, out: Any) -> None:
        """A thermo line on stdout at every multiple of ``output.thermo_every`` steps (see the module
        doc); the values are collective, so every rank computes them."""
        every = getattr(out, "thermo_every", None)
        if not every or self.sim.step_count % every:
            return
        self.sim.check_deferred()
        from .deck.schema import THERMO_DEFAULT

        keys = list(getattr(out, "thermo", None) or THERMO_DEFAULT)
        values = self._thermo_values(keys)
        if self.stdout is None:
            return
        header = "  ".join(f"{k:>14s}" for k in keys)
        if header != self._thermo_header:  # at the first line of each stage
            self.stdout.write(header + "\n")
            self._thermo_header = header
        self.stdout.write("  ".join(_thermo_cell(v) for v in values) + "\n")
        self.stdout.flush()

    def _thermo_values(self, keys: list[str]) -> list[float | int]:
        sim = self.sim
        needs_ke = any(k in ("ke", "ke_trans", "ke_rot") for k in keys)
        ke_t, ke_r = sim.kinetic_energy() if needs_ke else (math.nan, math.nan)
        meas = self.measurements() if any("." in k for k in keys) else {}
        values: list[float | int] = []
        for k in keys:
            if k == "step":
                values.append(int(sim.step_count))
            elif k == "time":
                values.append(sim.time)
            elif k == "dt":
                values.append(sim.dt)
            elif k == "particles":
                values.append(int(sim.count_particles()))
            elif k == "ke":
                values.append(ke_t + ke_r)
            elif k == "ke_trans":
                values.append(ke_t)
            elif k == "ke_rot":
                values.append(ke_r)
            elif k == "contacts":
                values.append(sim.count_contacts())  # counted on each rank: nothing gathered
            else:
                values.append(meas.get(k, math.nan))
        return values


def json_finite(value: Any) -> Any:
    """``value`` for strict JSON: non-finite floats (NaN, ±inf) as ``null``, NumPy scalars as Python
    numbers, tuples as lists (``summary.json`` is read by every JSON parser, and bare ``NaN`` is not
    JSON)."""
    if isinstance(value, dict):
        return {str(k): json_finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_finite(v) for v in value]
    if isinstance(value, np.ndarray):
        return [json_finite(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _where(cls: Any) -> str:
    return f"{getattr(cls, '__module__', '?')}.{getattr(cls, '__qualname__', cls)}"


def _plugin_call(what: str, action: Any) -> Any:
    """Call a plugin's constructor (or build): pdem's own errors pass through; any other exception
    is a bug of the plugin, reported as a :class:`~pdem.errors.PluginError` naming it (exit code 2)
    rather than a traceback."""
    from .errors import PluginError

    try:
        return action()
    except PdemError:
        raise
    except Exception as exc:  # noqa: BLE001 - a third-party plugin may raise anything
        raise PluginError(
            f"{what} failed: {type(exc).__name__}: {exc}; the plugin has a bug or does not honour "
            "pdem's plugin contract (docs/plugins.md): report it to its author, or remove it from the deck"
        ) from exc


#: packing files of later stages below this size are read (validated) when the run starts
_READ_AHEAD_BELOW = 256 * 2**20


def _same_deck(text: Any, other: str) -> bool:
    """Do two resolved deck texts hold the same deck (comments, such as the header, aside)?"""
    import tomllib

    if not isinstance(text, str):
        return False
    try:
        return tomllib.loads(text) == tomllib.loads(other)
    except tomllib.TOMLDecodeError:
        return False


def _thermo_cell(v: float | int) -> str:
    if isinstance(v, int):
        return f"{v:>14d}"
    return f"{v:>14.6g}"


def _larger(limit: float) -> str:
    """A max_time to suggest after ``limit`` was reached: twice it, written short."""
    return f"{2.0 * limit:g}"


def _intervals(t: float, t0: float, every: float, dt: float) -> int:
    """How many whole intervals ``every`` lie between the stage's start ``t0`` and ``t`` (a time a
    thousandth of a step short of a multiple counts as reaching it: the sum of steps rounds). The same
    on every rank and after a resume, since it reads only the times."""
    return math.floor((t - t0 + 1e-3 * dt) / every)
