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
import os
import re
import shlex
import shutil
import sys
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from . import __version__
from .errors import InputError, PdemError
from .io.checkpoint import write_checkpoint
from .io.frame import Frame, WallState
from .io.journal import Journal, discard, settle_stale
from .io.paths import (
    LOCK,
    MARKER,
    OutputLock,
    entries,
    first_missing,
    is_pdem_output,
    lock_holder,
    named_as_pdem,
    output_dir_problem,
    pdem_entries,
    record_entries,
    remove_created,
    remove_pdem_entries,
)
from .plugins import load
from .simulation import Simulation

__all__ = ["Runner", "StageLimitError", "build_particles", "MAX_STAGE_STEPS"]

#: most steps a stage may take (as the deck check, with the dt known once the scene exists)
MAX_STAGE_STEPS = 10**10


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
        problem = None
        self._before: set[str] | None = None
        self._created_root: Path | None = None
        self._lock = OutputLock(self.out)
        self._journal: Journal | None = None
        self._recorded: set[str] = set()
        self._foreign: set[str] = set()
        self._lock_made = False
        if self.root and not dry:
            problem = output_dir_problem(self.out, "the output directory", "choose another output directory")
            if problem is None:
                self._before = entries(self.out)
                self._created_root = first_missing(self.out)
                problem = self._output_refusal()
        problem = self.comm.bcast(problem, root=0)
        if problem:
            raise InputError(problem)
        self.deck_text = resolved.resolved_toml()
        if resume is not None and _same_deck(resume[1].get("deck"), self.deck_text):
            self.deck_text = resume[1]["deck"]  # unchanged: keep its text (and header) as it was
        self.progress = _Progress(progress if self.root else None, self.comm, enabled=progress is not None)
        self.stdout = (stdout if stdout is not None else sys.stdout) if self.root else None
        self.boundaries: dict[str, Any] = {}
        self.writers: list[Any] = []
        self._gathered_writers: list[Any] = []
        self._per_rank_writers: list[Any] = []
        self._series_writers: dict[Any, Any] = {}
        self._last_series_step: dict[str, int] = {}
        self._last_frame: dict[int, int] = {}  # id(writer) -> step of its last frame
        self.output_parallel: str | None = None
        self.series: dict[str, list[dict[str, float]]] = {}
        self.stopped_early = False
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._output_open = False
        self._setup_done = False
        self._contacts_on = False
        self._contacts_last: int | None = None
        self._contact_writer: Any = None
        self._thermo_header: str | None = None

    def _output_refusal(self) -> str | None:
        """Why the existing output directory cannot take this run (rank 0; looks only): another run
        holds it, or it is not empty and neither continued (a resume's own directory) nor replaceable
        (``--overwrite`` of a directory pdem made)."""
        holder = lock_holder(self.out) if self._before is not None else None
        if holder is not None:
            what = "this resume" if self.resume is not None else "this run"
            return (
                f"output directory {self.out} is in use by {holder}; pdem runs one run at a time per "
                f"output directory, so {what} was refused and nothing there was touched: wait for that "
                "run to end (or stop it), or choose another directory with --output DIR"
            )
        if not self._before or self.append:
            return None
        if not self.overwrite:
            return (
                f"output directory {self.out} exists and is not empty; pass --overwrite to replace "
                "pdem's output there, or choose another with --output DIR"
            )
        if not is_pdem_output(self.out):
            return (
                f"output directory {self.out} was not made by pdem (it has no {MARKER} "
                "marker), so --overwrite does not replace it and nothing in it was touched; choose a new "
                "or empty directory with --output DIR, or empty it yourself (an output of a pdem older "
                "than its marker, too, must be removed by hand)"
            )
        return None

    def _protected(self) -> set[Path]:
        """Paths ``--overwrite`` never removes: the deck being run and the files its sources read."""
        keep: set[Path] = set()
        if self.resolved.path is not None:
            keep.add(Path(self.resolved.path))
        for src in self.deck.particles or []:
            path = getattr(src, "path", None)
            if isinstance(path, str | Path) and str(path):
                keep.add(Path(self.resolved.base_dir) / path)
        return keep

    def _record_output(self) -> None:
        """Add what pdem created in the output directory to its marker (rank 0; cheap when nothing
        changed: one directory listing)."""
        if not self.root or not self._lock.held:
            return
        now = entries(self.out) or set()
        new = now - self._recorded - self._foreign
        if new:
            try:
                record_entries(self.out, new, __version__)
            except OSError:
                return  # the marker is bookkeeping: a full disk is reported by the writes themselves
            self._recorded |= new

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
        for name, params in self.resolved.boundaries.items():
            cls = load("boundaries", params.type)
            self.boundaries[name] = _plugin_call(
                f"boundary '{name}' (type '{params.type}', {_where(cls)})",
                lambda cls=cls, name=name, params=params: sim.add_boundary(cls(name, params)),
            )
        self.sim = sim
        return sim

    def _insert_particles(self, stage: str | None, first_stage: str) -> None:
        """Add the particles of every source inserted at the start of ``stage``: each source plugin
        (entry points of ``pdem.sources``) generates them with seed ``run.seed`` + its index."""
        from .sources.api import produce

        sim = self.sim
        for k, params in enumerate(self.deck.particles or []):
            target = params.stage or first_stage
            if target != stage:
                continue
            source = load("sources", params.source)(params)
            mat = sim.materials[sim.materials.index(params.material)]
            out = produce(
                source,
                base_dir=self.resolved.base_dir,
                seed=self.deck.run.seed + k,
                material=mat,
                where=f"particles.{k}",
            )
            vel = (
                out.velocities
                if out.velocities is not None
                else np.broadcast_to(np.asarray(params.velocity or (0, 0, 0), float), out.positions.shape)
            )
            motion: Any = params.motion
            if out.fixed is not None and out.fixed.any():  # e.g. a lattice's fixed_edges
                motion = np.where(out.fixed, "fixed", params.motion)
            sim.add_particles(
                out.positions,
                out.radii,
                material=params.material,
                velocities=vel,
                motion=motion,
                fixed_translation=getattr(params, "fixed_translation", ""),
                fixed_rotation=getattr(params, "fixed_rotation", ""),
            )

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
        log = st.drain_records()
        if self.root and log:
            writer = self._series_writers.get(("solver", stage))
            if writer is None:
                from .io.series import SeriesWriter

                writer = SeriesWriter(
                    self.out / f"solver_{stage}.csv",
                    ["step", "iterations", "residual", "contacts_rank0"],
                    append=self._series_append,
                )
                self._series_writers[("solver", stage)] = writer
            for step, it, res, nc in log:
                writer.append(
                    {"step": int(step), "iterations": int(it), "residual": res, "contacts_rank0": int(nc)}
                )
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
        if self._last_series_step.get(stage) == sim.step_count:
            return
        self._last_series_step[stage] = sim.step_count
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
        self.series.setdefault(stage, []).append(row)
        self._boundary_records(stage)
        if not self.root:
            return
        writer = self._series_writers.get(stage)
        if writer is None:
            from .io.series import SeriesWriter

            writer = SeriesWriter(self.out / f"series_{stage}.csv", list(row), append=self._series_append)
            self._series_writers[stage] = writer
        writer.append(row)
        self._record_output()

    def _boundary_records(self, stage: str) -> None:
        """Rows the boundaries sampled since the last series row (``Boundary.records``, collective),
        appended by rank 0 to ``<boundary>.<stage>.csv``."""
        for name, b in self.boundaries.items():
            rows = b.records(self.sim)
            if not rows or not self.root:
                continue
            writer = self._series_writers.get(("records", name, stage))
            if writer is None:
                from .io.series import SeriesWriter

                path = self.out / f"{name}.{stage}.csv"
                writer = SeriesWriter(path, list(rows[0]), append=self._series_append)
                self._series_writers[("records", name, stage)] = writer
            for row in rows:
                writer.append(row)

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
        if self._bounds is not None:  # grow only, so infinite walls keep their drawn size
            lo, hi = np.minimum(lo, self._bounds[0]), np.maximum(hi, self._bounds[1])
        if not np.all(np.isfinite(lo) & np.isfinite(hi)):
            lo, hi = np.zeros(3), np.ones(3)
        self._bounds = (lo, hi)
        return Frame(
            time=sim.time, step=sim.step_count, stage=stage, particles=particles, walls=walls, bounds=(lo, hi)
        )

    def _write_frame(self, stage: str) -> None:
        """A snapshot for every writer that has none at this step yet (collective)."""
        self.sim.check_deferred()
        step = self.sim.step_count
        gathered = [w for w in self._gathered_writers if self._last_frame.get(id(w)) != step]
        per_rank = [w for w in self._per_rank_writers if self._last_frame.get(id(w)) != step]
        frame = None
        # every rank decides alike: the writers' last steps are the same everywhere
        if self._gathered_output and self.comm.bcast(bool(gathered), root=0):
            frame = self.frame(stage)  # collective
            for w in gathered:  # rank 0 only
                w.write(frame)
                self._last_frame[id(w)] = step
        if per_rank:
            piece = self.frame(stage, own=True)  # collective
            for w in per_rank:
                w.write(piece)  # collective
                self._last_frame[id(w)] = step
        if self._contacts_on and self._contacts_last != step:
            self._write_contacts(frame)

    def _write_contacts(self, frame: Frame | None) -> None:
        """The contact network at this step (``output.contacts``; collective, rank 0 writes)."""
        from .io.contacts import contact_lines

        sim = self.sim
        contacts = sim.contacts()  # collective: every rank's contacts
        particles = frame.particles if frame is not None else sim.get_particles()  # collective
        if self._contact_writer is not None:
            self._contact_writer.write(contact_lines(contacts, particles, sim.box), sim.time, sim.step_count)
        self._contacts_last = sim.step_count

    def _checkpoint(self, stage_index: int, stage_start: tuple[float, int], started: bool = True) -> Path:
        sim = self.sim
        sim.check_deferred()  # a checkpoint holds only a checked state
        stages = self.deck.stages
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
            "frame_bounds": json.dumps([b.tolist() for b in self._bounds])
            if self._bounds is not None
            else "",
        }
        state = sim.state_dict()  # collective
        path = self.out / "checkpoints" / f"step_{sim.step_count:010d}.h5"
        if self.root:
            write_checkpoint(path, state, meta)
            self._record_output()
        self.comm.Barrier()
        return path

    # ---------------------------------------------------------------------------- output
    def _root_do(self, action) -> Any:
        """Run ``action`` on rank 0; its result, or its error raised on every rank (collective)."""
        result, error = None, None
        if self.root:
            try:
                result = action()
            except PdemError as exc:
                error = (type(exc), str(exc))
            except OSError as exc:
                error = (InputError, f"output directory {self.out}: {exc}")
        result, error = self.comm.bcast((result, error), root=0)
        if error is not None:
            raise error[0](error[1])
        return result

    def _writer_classes(self) -> list[tuple[str, type]]:
        classes = [(fmt, load("writers", fmt)) for fmt in self.deck.output.formats]
        if self.append:
            bad = [fmt for fmt, cls in classes if not getattr(cls, "supports_append", False)]
            if bad:
                raise InputError(
                    f"output format(s) {', '.join(map(repr, bad))} cannot continue an existing output, so "
                    f"the run cannot go on in {self.out}; resume into a new directory with --output DIR"
                )
        return classes

    def _open_output(self, classes: list[tuple[str, type]], start: Any) -> None:
        """Create the output directory (or continue the existing one), writers and series (collective).
        Called once the run has passed its start checks."""
        self._series_append = self.append or self.series_from is not None
        self._output_open = True
        if self.append:
            kept = self._root_do(lambda: self._continue_output(start))
        else:
            kept = self._root_do(lambda: self._new_output(start))
        self._root_do(self._record_output)
        for stage, rows in (kept or {}).items():
            self.series[stage] = rows
            if rows and "step" in rows[-1]:
                self._last_series_step[stage] = int(rows[-1]["step"])
        out_cfg = self.deck.output
        self.output_parallel = out_cfg.parallel_mode(self.sim.count_particles(), self.comm.size)
        self._gathered_output = False  # on every rank: frames are gathered collectively
        for fmt, cls in classes:
            kwargs: dict[str, Any] = {
                "fields": out_cfg.fields,
                "metadata": {"deck": self.deck_text, "pdem_version": __version__},
            }
            if self.append:
                kwargs["append_after"] = (start.step, start.time)
            if self.output_parallel == "per_rank" and getattr(cls, "supports_per_rank", False):
                w = _plugin_call(  # on every rank
                    f"writer '{fmt}' ({_where(cls)})",
                    lambda cls=cls, kw=kwargs: cls(self.out, comm=self.comm, **kw),
                )
                self._per_rank_writers.append(w)
            else:  # parallel = "auto" gathers frames for writers without per-rank support
                self._gathered_output = True
                if not self.root:
                    continue  # rank 0 decides when a gathered frame is due
                w = _plugin_call(
                    f"writer '{fmt}' ({_where(cls)})", lambda cls=cls, kw=kwargs: cls(self.out, **kw)
                )
                self._gathered_writers.append(w)
            if getattr(w, "last_step", None) is not None:
                self._last_frame[id(w)] = int(w.last_step)
        self.writers = self._gathered_writers + self._per_rank_writers
        self._contacts_on = bool(getattr(out_cfg, "contacts", False))
        if self._contacts_on:
            from .io.contacts import ContactNetworkWriter

            def make() -> int | None:
                self._contact_writer = ContactNetworkWriter(
                    self.out, append_after=(start.step, start.time) if self.append else None
                )
                return self._contact_writer.last_step

            self._contacts_last = self._root_do(make)

    def _make_output_dir(self) -> None:
        """Create the output directory and its missing parents, remembering the outermost one this
        process created itself (another process may create the same path at the same moment)."""
        out = Path(os.path.abspath(self.out))
        missing = []
        p = out
        while not os.path.lexists(p) and p.parent != p:
            missing.append(p)
            p = p.parent
        self._created_root = None
        for path in reversed(missing):
            try:
                os.mkdir(path)
            except FileExistsError:
                continue
            if self._created_root is None:
                self._created_root = path
        if self._created_root is None:  # it existed (or another process made it): keep its entries
            self._before = entries(self.out) if self._before is None else self._before

    def _take_lock(self) -> None:
        """Rank 0: the directory's lock, then settle what a killed resume left (see io.journal)."""
        self._lock_made = not os.path.lexists(self.out / LOCK)
        self._lock.acquire("this resume" if self.resume is not None else "this run")
        note = settle_stale(self.out, self.resume_step)
        if note and self.progress.stream is not None:
            self.progress.stream.write(f"pdem: {self.out}: {note}\n")

    def _new_output(self, start: Any) -> dict[str, list]:
        out = self.out
        self._make_output_dir()
        try:
            self._take_lock()
        except InputError:
            if self._created_root is not None:  # an empty folder of ours: leave no trace
                shutil.rmtree(self._created_root, ignore_errors=True)
                self._created_root = None
            self._output_open = False  # nothing of this run's to undo
            raise
        if self._created_root is None:
            present = (entries(out) or set()) - {LOCK}
            if present and self.overwrite:
                # --overwrite: pdem's old output goes only now that the run has started well and
                # holds the lock; whatever pdem did not make (the deck, notes, a user's files) stays
                if not is_pdem_output(out):
                    self._output_open = False
                    raise InputError(self._output_refusal() or f"{out} was not made by pdem")
                remove_pdem_entries(out, self._protected())
            elif present - {MARKER}:
                self._output_open = False  # filled by another process since the start checks
                raise InputError(
                    f"output directory {out} is no longer empty (another process wrote there since this "
                    "run started); choose another with --output DIR"
                )
            # what the undo of a failed start keeps: what was there, less a lock file this run made
            self._before = (entries(out) or set()) - ({LOCK} if self._lock_made else set())
        else:
            self._before = None
        self._foreign = set(self._before or ()) - {LOCK, MARKER}
        record_entries(out, set(), __version__)
        (out / "checkpoints").mkdir(exist_ok=True)
        (out / "deck.resolved.toml").write_text(self.deck_text)
        if self.series_from is None:
            return {}
        return self._seed_series(self.series_from, start)

    def _series_files(self, directory: Path) -> list[tuple[str, Path]]:
        """``(stage, path)`` of the series, solver and boundary-record CSVs in ``directory``."""
        out = []
        for path in sorted(directory.glob("*.csv")):
            m = re.fullmatch(r"(series|solver)_(.+)\.csv", path.name)
            if m:
                out.append((m.group(2), path))
            elif m := re.fullmatch(r"([A-Za-z_][\w-]*)\.([A-Za-z_][\w-]*)\.csv", path.name):
                if m.group(1) in self.boundaries:  # <boundary>.<stage>.csv (Boundary.records)
                    out.append((m.group(2), path))
        return out

    def _stage_ran(self, stage: str, start: Any) -> bool:
        """Did ``stage`` start before the checkpoint (so its rows up to it belong to this run)?"""
        names = [s.name for s in self.deck.stages]
        return stage in names and start.has_run(names.index(stage))

    def _seed_series(self, source: Path, start: Any) -> dict[str, list]:
        """Resuming into a new directory: copy the series rows up to the checkpoint from ``source``."""
        from .io.series import series_rows, truncate_series

        kept: dict[str, list] = {}
        for stage, path in self._series_files(source):
            if not self._stage_ran(stage, start):
                continue
            target = self.out / path.name
            shutil.copyfile(path, target)
            truncate_series(target, start.step)
            if path.name.startswith("series_"):
                kept[stage] = series_rows(target)
        return kept

    def _continue_output(self, start: Any) -> dict[str, list]:
        """Appending to the checkpoint's own output: drop what the previous run wrote after the
        checkpoint (series rows, checkpoints, temporary files; writers drop their frames), keep the
        rest; the rows kept, by stage."""
        from .io.base import atomic_write_text
        from .io.series import series_rows, truncate_series

        out = self.out
        out.mkdir(parents=True, exist_ok=True)
        self._take_lock()
        # what pdem did not make stays out of the marker (in a folder without one, an output of an
        # older pdem, what is named as pdem names its output is taken as pdem's)
        known = set(entries(out) or ())
        own = pdem_entries(out) if is_pdem_output(out) else {n for n in known if named_as_pdem(n)}
        self._foreign = known - own - {LOCK, MARKER}
        self._journal = Journal(out)
        self._journal.begin(start.step)  # from here on, what the resume drops is held, not deleted
        ckdir = out / "checkpoints"
        ckdir.mkdir(exist_ok=True)
        for directory in (out, out / "particles", out / "walls", *sorted(out.glob("particles/r*"))):
            if directory.is_dir():
                for path in directory.iterdir():  # temporary files of writes a kill interrupted
                    if re.fullmatch(r"\..+\.[0-9a-f]{8}(\.tmp|\.vtu)", path.name):
                        discard(out, path)
        later = []
        for path in ckdir.iterdir():
            m = re.fullmatch(r"step_(\d+)\.h5", path.name)
            if path.name.endswith(".tmp"):
                discard(out, path)
            elif m and int(m.group(1)) > start.step:
                later.append(path)
        for path in later:
            discard(out, path)
        latest = ckdir / "latest.h5"
        if latest.is_symlink() and not latest.exists():
            steps = sorted(p.name for p in ckdir.glob("step_*.h5"))
            tmp = ckdir / "latest.h5.tmp"
            if steps:
                os.symlink(steps[-1], tmp)
                os.replace(tmp, latest)
            else:
                latest.unlink()
        kept: dict[str, list] = {}
        for stage, path in self._series_files(out):
            if not self._stage_ran(stage, start):
                discard(out, path)  # held while the resume is undecided
                continue
            truncate_series(path, start.step)
            if path.name.startswith("series_"):
                kept[stage] = series_rows(path)
        resolved = out / "deck.resolved.toml"
        if resolved.exists() and resolved.read_text() != self.deck_text:
            resolved.rename(out / f"deck.resolved.until-step-{start.step}.toml")
        if not resolved.exists():
            atomic_write_text(resolved, self.deck_text)
        return kept

    def _undo_output(self) -> None:
        """The run failed before its first step: remove what it created (rank 0; never what was
        there before it, never a continued output, nothing in a directory whose lock it does not
        hold)."""
        if not self.root or not self._output_open or self.append or not self._lock.held:
            return
        remove_created(self.out, self._before, self._created_root)

    def _settle_journal(self, failed: BaseException | None) -> None:
        """Rank 0, at the end of a resume into its own directory: commit what it wrote, or, when it
        failed and had replaced a future (later checkpoints, rows, frames), put the directory back as
        it was before the resume. A failed resume that replaced nothing keeps what it wrote, as a
        failed run does."""
        journal, self._journal = self._journal, None
        if journal is None or not self.root:
            return
        try:
            if failed is None or isinstance(failed, StageLimitError) or not journal.replaced_anything:
                journal.commit()
                return
            journal.rollback()
        except OSError as exc:  # never hide the run's own error behind the bookkeeping's
            if self.progress.stream is not None:
                self.progress.stream.write(f"pdem: warning: could not settle {journal.path}: {exc}\n")
            return
        if self.progress.stream is not None:
            self.progress.stream.write(
                f"pdem: the resume failed, so {self.out} was put back as it was before it (the later "
                "checkpoints, rows and snapshots it was replacing are kept); to keep a failing attempt's "
                "output, resume into a new directory with --output DIR\n"
            )

    def _finish_output(self, failed: BaseException | None) -> None:
        """Rank 0, last: the journal settled, the marker brought up to date, the lock released."""
        if not self.root:
            return
        try:
            self._settle_journal(failed)
            if failed is None or self._setup_done:
                self._record_output()
        finally:
            self._lock.release()

    # ---------------------------------------------------------------------------- running
    def check_scene(self) -> str:
        """What ``pdem check`` does beyond the deck: build the first stage's scene (its particles are
        made) and run the start checks of :meth:`run` (every stage's dt against the law's stability
        estimate, initial overlaps between grains and with walls, the packing files of later
        stages), writing nothing. A one-line description of the scene."""
        sim = self.build()
        stages = list(self.deck.stages)
        self._check_dt_before_insertion(0)
        self._insert_particles(stages[0].name, stages[0].name)
        self._enter_stage(0, stages[0])
        self._check_stages(0)
        self._check_later_files(0)
        self._check_measured(0)
        return (
            f"{sim.count_particles()} particles at the start, dt = {sim.dt:.4g} s (stability estimate "
            f"{sim.dt_critical:.4g} s)"
        )

    def _check_dt_before_insertion(self, start_index: int) -> None:
        """Refuse, before any source makes its grains (a pour can take minutes), a stage dt above
        the law's stability estimate for the *largest* grains the deck's sources can make: the
        estimate grows with the radius, so such a dt is above it for any grains they make. Sources
        that cannot tell their largest radius beforehand are left to the check after insertion."""
        if self.deck.run.force_dt:
            return
        sim = self.sim
        radii, mats, masses = [], [], []
        for params in self.deck.particles or []:
            try:
                r = load("sources", params.source)(params).r_max()
            except PdemError:
                raise
            except Exception:  # noqa: BLE001 - a plugin's estimate is optional
                r = None
            if r is None or not math.isfinite(r) or r <= 0:
                continue
            k = sim.materials.index(params.material)
            radii.append(r)
            mats.append(k)
            masses.append(4.0 / 3.0 * math.pi * r**3 * sim.materials[k].density)
        if not radii:
            return
        with np.errstate(all="ignore"):
            crit = sim.law.critical_dt(
                sim.materials, np.asarray(radii), np.asarray(mats, dtype=np.int64), np.asarray(masses)
            )
        if not math.isfinite(crit):
            return
        for index, stage in enumerate(self.deck.stages):
            dt = self._stage_dt(stage)
            if index >= start_index and dt is not None and dt > crit:
                raise InputError(
                    f"{self._dt_key(index, stage)}: dt = {dt:.4g} s for stage '{stage.name}' exceeds the "
                    f"stability estimate of law '{sim.law.name}' even for the largest grains the deck's "
                    f"sources make (radius {max(radii):.4g} m: {crit:.4g} s), so for any grains they "
                    f"make; use dt ≤ {crit:.4g} s (practice: 0.1–0.3 of the estimate for the smallest "
                    "grains, which `pdem check` prints), or set run.force_dt = true to run anyway"
                )

    def _check_measured(self, start_index: int) -> None:
        """Every quantity a stage ends on (and every thermo column) is one the boundaries measure:
        a boundary plugin that does not declare its keys is only known once built (collective)."""
        measured = sorted(self.measurements())
        wanted = []
        for index, stage in enumerate(self.deck.stages):
            if index >= start_index and stage.end.quantity is not None:
                wanted.append((f"stages.{stage.name}.end.quantity", stage.end.quantity))
            out = self.resolved.output_for(stage.name)
            for k, key in enumerate(getattr(out, "thermo", None) or ()):
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
                        read_spheres(path)
                    except InputError as exc:
                        raise InputError(f"particles.{k}.path (stage '{stage}'): {exc}") from None

    def run(self) -> dict[str, Any]:
        from .deck.resume import ResumePoint

        deck = self.deck
        sim = self.build()
        stages = list(deck.stages)
        first = stages[0].name
        start_index = 0
        started = False
        stage_start: tuple[float, int] | None = None
        if self.resume is None:
            self._check_dt_before_insertion(0)
            self._insert_particles(first, first)
            start = ResumePoint(0, False, 0, 0.0)
        else:
            state, meta = self.resume
            sim.load_state(state)
            start = ResumePoint.from_checkpoint(state, meta)
            start_index, started = start.stage_index, start.started
            stage_start = (float(meta["stage_start_time"]), int(meta["stage_start_step"]))
            saved = json.loads(meta.get("boundaries", "{}"))
            for name, b in self.boundaries.items():
                b.restore(saved.get(name, {}))
            if meta.get("frame_bounds"):
                lo, hi = json.loads(meta["frame_bounds"])
                self._bounds = (np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))
        self._resume_dt = float(self.resume[0]["scalars/dt"]) if self.resume is not None else None
        # ---- checks that need the scene, before anything is written
        classes = self._writer_classes()
        if start_index < len(stages):
            stage = stages[start_index]
            if not (self.resume is not None and started):
                if start_index > 0:
                    self._insert_particles(stage.name, first)
                stage_start = (sim.time, sim.step_count)
            self._enter_stage(start_index, stage)
            self._check_stages(start_index)
            self._check_later_files(start_index)
            self._check_measured(start_index)
        t_start = _time.perf_counter()
        steps_start = sim.step_count
        try:
            self._open_output(classes, start)
            if start_index >= len(stages):
                self._setup_done = True  # a finished run: nothing left to step
            for index in range(start_index, len(stages)):
                stage = stages[index]
                resumed_here = self.resume is not None and index == start_index and started
                if index != start_index:
                    self._insert_particles(stage.name, first)
                    stage_start = (sim.time, sim.step_count)
                    self._enter_stage(index, stage)
                if not self._run_stage(index, stage, stage_start, resumed_here):
                    self.stopped_early = True
                    break
        except BaseException as exc:
            self._close()
            if not self._setup_done and not self._journal:
                self._undo_output()
            self._finish_output(exc)
            raise
        self._close()
        wall = _time.perf_counter() - t_start
        summary: dict[str, Any] = {
            "pdem_version": __version__,
            "steps": sim.step_count,
            "time": sim.time,
            "wall_time_s": wall,
            "particles": sim.count_particles(),
            "dt": sim.dt,
            "dt_critical": sim.dt_critical if math.isfinite(sim.dt_critical) else None,
            "steps_run": sim.step_count - steps_start,
            "steps_per_second": (sim.step_count - steps_start) / max(wall, 1e-9),
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
        for w in self.writers:
            w.close()
        for w in self._series_writers.values():
            w.close()
        self.progress.done()

    def _merged_series(self) -> dict[str, np.ndarray]:
        """Every stage's series rows in stage order, with a ``stage`` column (the stage's index), so
        that a boundary's summary reads each value from the stage it belongs to."""
        from .boundaries.api import merge_series

        return merge_series(self.series, [s.name for s in self.deck.stages])

    def _stage_dt(self, stage: Any) -> float | None:
        """The dt a stage runs with: its own, else ``run.dt``; None keeps the current step (the law's
        estimate, or the dt of an earlier stage that set its own)."""
        return stage.dt if stage.dt is not None else self.deck.run.dt

    def _dt_key(self, index: int, stage: Any) -> str:
        return f"stages.{stage.name}.dt" if stage.dt is not None else "run.dt"

    def _enter_stage(self, index: int, stage: Any) -> None:
        """Enter a stage: boundaries on or off, its dt, preparation (checks dt against the law's
        stability estimate and initial overlaps: errors name the deck key)."""
        sim = self.sim
        sim.set_stage(stage.name)
        self._stage_materials(stage)
        self._stage_contact(index, stage)
        dt = self._stage_dt(stage)
        try:
            if dt is not None and sim.dt != dt:
                sim.dt = dt  # checked against the law's stability estimate once prepared
            sim.prepare()
        except InputError as exc:
            if "stability estimate" in str(exc) and dt is not None:
                raise type(exc)(f"{self._dt_key(index, stage)}: {exc}") from None
            raise

    def _stage_contact(self, index: int, stage: Any) -> None:
        """The law's solver settings for this stage: ``[contact]`` with ``[stages.contact]`` on top
        (validated with the deck; a stage without the table gets ``[contact]`` back)."""
        from .deck.load import stage_contact_values

        law = self.sim.law
        values = stage_contact_values(stage.contact, self.deck.contact.law) if stage.contact else {}
        params = self.resolved.law_params
        if values:
            params = type(params)(**{**params.model_dump(), **values})
        if getattr(params, "solver", None) == "gauss_seidel" and self.sim.comm.size > 1:
            raise InputError(
                f"stages.{stage.name}.contact.solver: 'gauss_seidel' runs on one rank only (it sweeps the "
                "contacts in one sequence, so results would depend on the partition); use 'jacobi' or "
                "'apgd' under MPI"
            )
        if values or law.params.model_dump() != params.model_dump():
            law.params = params

    def _stage_materials(self, stage: Any) -> None:
        """The materials' contact properties for this stage: ``[stages.materials.NAME]`` where given,
        else ``[materials.NAME]`` (a stage's values hold for that stage only). Also on a resume."""
        keys = self.sim.MUTABLE_MATERIAL_KEYS
        for name, spec in self.deck.materials.items():
            base = spec.to_material(name)
            values = {k: getattr(base, k) for k in keys}
            if name in stage.materials:
                values.update(stage.materials[name].values())
            self.sim.set_material(name, **values)

    def _check_stages(self, start_index: int) -> None:
        """Before anything is written: every stage still to run has a dt within the law's stability
        estimate (as known from the particles now) and a length below :data:`MAX_STAGE_STEPS`."""
        sim = self.sim
        crit = sim.dt_critical
        for index, stage in enumerate(self.deck.stages):
            if index < start_index:
                continue
            dt = self._stage_dt(stage)
            if dt is not None and not self.deck.run.force_dt and math.isfinite(crit) and dt > crit:
                raise InputError(
                    f"{self._dt_key(index, stage)}: dt = {dt:.4g} s for stage '{stage.name}' exceeds the "
                    f"stability estimate {crit:.4g} s of law '{sim.law.name}' for these particles; use "
                    f"dt ≤ {crit:.4g} s (practice: 0.1–0.3 of it), or set run.force_dt = true to run anyway"
                )
            self._stage_target(stage, dt if dt is not None else sim.dt)

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
        out = self.resolved.output_for(stage.name)
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
                values.append(int(len(sim.contacts()["id_i"])))
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
