"""Run a validated deck: build the simulation, go through the stages, write what is due.

Per stage: insert the stage's particles, switch boundaries on or off, then step until one end
condition holds (time, steps, kinetic energy below a threshold, a measured quantity above or below a
value). Snapshots (HDF5 + XDMF and/or VTK), a CSV time series per stage (energies and every
boundary's measurements), periodic checkpoints and one at the end of every stage. ``max_steps``
(the CLI's ``--steps``) stops early, writing final output and a checkpoint.

Snapshots under MPI are either gathered (every rank's particles collected, ordered by id, and written
by rank 0) or written per rank (each rank writes the particles it owns with writers constructed with
``comm``; rank 0 writes the index joining the pieces): ``output.parallel``, decided once when output
starts (``auto``: by the particle count then) and recorded in ``summary.json`` as ``output_parallel``.

Output directory layout::

    deck.resolved.toml      the deck with every default filled in
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
from .plugins import load
from .simulation import Simulation

__all__ = ["Runner", "StageLimitError", "build_particles"]


class StageLimitError(PdemError):
    """A stage reached its ``max_time`` safety cap without meeting its end condition."""


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
    stream: TextIO | None
    every: float = 2.0
    _last: float = field(default_factory=_time.perf_counter)
    _last_step: int = 0

    def update(self, sim: Simulation, stage: str, frac: float | None, force: bool = False) -> None:
        if self.stream is None:
            return
        now = _time.perf_counter()
        if not force and now - self._last < self.every:
            return
        rate = (sim.step_count - self._last_step) / max(now - self._last, 1e-9)
        eta = ""
        if frac is not None and 0 < frac < 1 and rate > 0:
            remaining = (1 - frac) / frac * (now - self._stage_start) if hasattr(self, "_stage_start") else 0
            eta = f", ETA {remaining:.0f} s"
        line = (
            f"[{stage}] t = {sim.time:.6g} s, step {sim.step_count}, "
            f"{sim.n_particles} particles{' on rank 0' if sim.comm.size > 1 else ''}, "
            f"{rate:,.0f} steps/s{eta}"
        )
        tty = getattr(self.stream, "isatty", lambda: False)()
        self.stream.write(("\r" + line + "\033[K") if tty else line + "\n")
        self.stream.flush()
        self._last, self._last_step = now, sim.step_count

    def stage_start(self, step: int = 0) -> None:
        self._stage_start = self._last = _time.perf_counter()
        self._last_step = step

    def done(self) -> None:
        if self.stream is not None and getattr(self.stream, "isatty", lambda: False)():
            self.stream.write("\n")


# ---------------------------------------------------------------------------------------- runner
class Runner:
    """Executes a :class:`pdem.deck.ResolvedDeck`.

    ``output`` overrides the deck's ``output.directory``; an existing non-empty directory is refused
    unless ``overwrite``. ``resume`` is ``(state, meta)`` from :func:`pdem.io.checkpoint.read_checkpoint`.
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
    ) -> None:
        from .parallel.comm import SerialComm

        self.resolved = resolved
        self.deck = resolved.deck
        self.comm = comm if comm is not None else SerialComm()
        self.root = self.comm.rank == 0  # only rank 0 touches files
        self.max_steps = max_steps
        self.overrides = tuple(overrides)
        self.resume = resume
        out = output if output is not None else Path(self.deck.output.directory)
        self.out = Path(out)
        problem = None
        if self.root and self.out.exists() and any(self.out.iterdir()):
            if not overwrite:
                problem = (
                    f"output directory {self.out} exists and is not empty; pass --overwrite to "
                    "replace it, or choose another with --output DIR"
                )
            else:
                shutil.rmtree(self.out)
        problem = self.comm.bcast(problem, root=0)
        if problem:
            raise InputError(problem)
        self.deck_text = resolved.resolved_toml()
        if self.root:
            self.out.mkdir(parents=True, exist_ok=True)
            (self.out / "checkpoints").mkdir(exist_ok=True)
            (self.out / "deck.resolved.toml").write_text(self.deck_text)
        self.comm.Barrier()
        self.progress = _Progress(progress if self.root else None)
        self.boundaries: dict[str, Any] = {}
        self.writers: list[Any] = []
        self._gathered_writers: list[Any] = []
        self._per_rank_writers: list[Any] = []
        self.output_parallel: str | None = None
        self.series: dict[str, list[dict[str, float]]] = {}
        self.stopped_early = False
        self._bounds: tuple[np.ndarray, np.ndarray] | None = None

    # ---------------------------------------------------------------------------- building
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
        sim.force_dt = run.force_dt
        sim.gravity = tuple(run.gravity)
        sim.skin = run.skin
        sim.max_overlap = run.max_overlap
        sim.decomposition_dims = tuple(run.decomposition) if run.decomposition else None
        sim.balance_threshold = run.balance_threshold
        if deck.domain.periodic:
            sim.set_periodic(deck.domain.lo, deck.domain.hi, deck.domain.periodic)
        for name, params in self.resolved.boundaries.items():
            cls = load("boundaries", params.type)
            self.boundaries[name] = sim.add_boundary(cls(name, params))
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
            sim.add_particles(
                out.positions, out.radii, material=params.material, velocities=vel, motion=params.motion
            )

    # ---------------------------------------------------------------------------- measuring
    def measurements(self) -> dict[str, float]:
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
        n = sim.particles.n_owned
        work = int(sim.model_work().sum())
        counts = np.array(sim.comm.allgather((n, work)), dtype=float)
        mean = counts.mean(axis=0)
        return {
            "imbalance_particles": float(counts[:, 0].max() / max(mean[0], 1e-300)),
            "imbalance_work": float(counts[:, 1].max() / max(mean[1], 1e-300)),
            "rebalances": float(sim.decomposition.n_rebalances if sim.decomposition else 0),
        }

    def _solver_columns(self, stage: str) -> dict[str, float]:
        """DEM-C: the last step's iterations and residual, the count of unconverged steps; every
        step's values since the last row go to ``solver_<stage>.csv`` (rank 0)."""
        st = self.sim.integrator
        if not hasattr(st, "log"):
            return {}
        log, st.log = st.log, []
        if self.root and log:
            writer = self._series_writers.get(("solver", stage))
            if writer is None:
                from .io.series import SeriesWriter

                writer = SeriesWriter(
                    self.out / f"solver_{stage}.csv", ["step", "iterations", "residual", "contacts_rank0"]
                )
                self._series_writers[("solver", stage)] = writer
            for step, it, res, nc in log:
                writer.append({"step": step, "iterations": it, "residual": res, "contacts_rank0": nc})
        return {
            "solver_iterations": float(st.last_iterations),
            "solver_residual": float(st.last_residual),
            "solver_unconverged": float(st.n_unconverged),
        }

    def _series_row(self, stage: str) -> None:
        sim = self.sim
        ke_t, ke_r = sim.kinetic_energy()
        row = {
            "time": sim.time,
            "step": float(sim.step_count),
            "particles": float(sim.count_particles()),
            "ke_trans": ke_t,
            "ke_rot": ke_r,
            **self._balance_columns(),
            **self._solver_columns(stage),
            **self.measurements(),
        }
        self.series.setdefault(stage, []).append(row)
        if not self.root:
            return
        writer = self._series_writers.get(stage)
        if writer is None:
            from .io.series import SeriesWriter

            writer = SeriesWriter(self.out / f"series_{stage}.csv", list(row))
            self._series_writers[stage] = writer
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
        if self._last_frame_step == self.sim.step_count:
            return
        if self._gathered_output:
            frame = self.frame(stage)  # collective
            for w in self._gathered_writers:  # rank 0 only
                w.write(frame)
        if self._per_rank_writers:
            piece = self.frame(stage, own=True)  # collective
            for w in self._per_rank_writers:
                w.write(piece)  # collective
        self._last_frame_step = self.sim.step_count

    def _checkpoint(self, stage_index: int, stage_start: tuple[float, int], started: bool = True) -> Path:
        sim = self.sim
        meta = {
            "deck": self.deck_text,
            "deck_path": str(Path(self.resolved.path).resolve()),
            "overrides": json.dumps(list(self.overrides)),
            "pdem_version": __version__,
            "stage_index": stage_index,
            "stage_start_time": stage_start[0],
            "stage_start_step": stage_start[1],
            "stage_started": int(started),
            "boundaries": json.dumps({n: b.state() for n, b in self.boundaries.items()}),
            "output": str(self.out.resolve()),
        }
        state = sim.state_dict()  # collective
        path = self.out / "checkpoints" / f"step_{sim.step_count:010d}.h5"
        if self.root:
            write_checkpoint(path, state, meta)
        self.comm.Barrier()
        return path

    # ---------------------------------------------------------------------------- running
    def run(self) -> dict[str, Any]:
        deck = self.deck
        sim = self.build()
        stages = list(deck.stages)
        first = stages[0].name
        start_index = 0
        started = False
        stage_start: tuple[float, int] | None = None
        if self.resume is None:
            self._insert_particles(first, first)
        else:
            state, meta = self.resume
            sim.load_state(state)
            start_index = int(meta["stage_index"])
            started = bool(int(meta.get("stage_started", 1)))
            stage_start = (float(meta["stage_start_time"]), int(meta["stage_start_step"]))
            saved = json.loads(meta.get("boundaries", "{}"))
            for name, b in self.boundaries.items():
                b.restore(saved.get(name, {}))
        self._series_writers: dict[str, Any] = {}
        self._last_frame_step = -1
        out_cfg = deck.output
        self.output_parallel = out_cfg.parallel_mode(sim.count_particles(), self.comm.size)
        self._gathered_output = False  # on every rank: frames are gathered collectively
        for fmt in out_cfg.formats:
            cls = load("writers", fmt)
            kwargs: dict[str, Any] = {
                "fields": out_cfg.fields,
                "metadata": {"deck": self.deck_text, "pdem_version": __version__},
            }
            if self.output_parallel == "per_rank" and getattr(cls, "supports_per_rank", False):
                self._per_rank_writers.append(cls(self.out, comm=self.comm, **kwargs))  # on every rank
            else:  # parallel = "auto" gathers frames for writers without per-rank support
                if self.root:
                    self._gathered_writers.append(cls(self.out, **kwargs))
                self._gathered_output = True
        self.writers = self._gathered_writers + self._per_rank_writers
        t_start = _time.perf_counter()
        steps_start = sim.step_count
        try:
            for index in range(start_index, len(stages)):
                stage = stages[index]
                resumed_here = self.resume is not None and index == start_index and started
                if not resumed_here:
                    if index > 0:
                        self._insert_particles(stage.name, first)
                    stage_start = (sim.time, sim.step_count)
                if not self._run_stage(index, stage, stage_start, resumed_here):
                    self.stopped_early = True
                    break
        finally:
            for w in self.writers:
                w.close()
            for w in self._series_writers.values():
                w.close()
            self.progress.done()
        wall = _time.perf_counter() - t_start
        summary: dict[str, Any] = {
            "pdem_version": __version__,
            "steps": sim.step_count,
            "time": sim.time,
            "wall_time_s": wall,
            "particles": sim.count_particles(),
            "dt": sim.dt,
            "steps_per_second": (sim.step_count - steps_start) / max(wall, 1e-9),
            "completed": not self.stopped_early,
            "output_parallel": self.output_parallel,
            "results": {},
        }
        solver = sim.integrator.summary() if sim.integrator is not None else None
        if solver is not None:
            summary["solver"] = solver
        merged = self._merged_series()
        for name, b in self.boundaries.items():
            res = b.summary(merged)
            if res:
                summary["results"][name] = res
        if self.root:
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary

    def _merged_series(self) -> dict[str, np.ndarray]:
        rows = [r for stage in self.deck.stages for r in self.series.get(stage.name, [])]
        keys = sorted({k for r in rows for k in r})
        return {k: np.array([r.get(k, math.nan) for r in rows]) for k in keys}

    def _run_stage(self, index: int, stage: Any, stage_start: tuple[float, int], resumed: bool) -> bool:
        """Run one stage; False if ``max_steps`` stopped the run."""
        sim = self.sim
        sim.set_stage(stage.name)
        if stage.dt is not None and sim.dt != stage.dt:
            sim.dt = stage.dt  # checked against the law's stability estimate
        sim.prepare()
        end = stage.end
        out = self.resolved.output_for(stage.name)
        every_steps = out.every_steps
        every_time = out.every_time
        series_every = out.series_every_steps
        ckpt_every = out.checkpoint_every_steps
        check_every = getattr(end, "check_every", None) or 100
        target_steps = None
        if end.steps is not None:
            target_steps = end.steps
        if end.time is not None:
            by_time = int(math.ceil(end.time / sim.dt - 1e-9))
            target_steps = by_time if target_steps is None else min(target_steps, by_time)
        self.progress.stage_start(sim.step_count)
        if not resumed:
            self._series_row(stage.name)
            self._write_frame(stage.name)
        next_snapshot_time = (
            (math.floor((sim.time + 1e-12) / every_time) + 1) * every_time if every_time else None
        )
        while True:
            in_stage = sim.step_count - stage_start[1]
            done = target_steps is not None and in_stage >= target_steps
            if not done and in_stage > 0 and in_stage % check_every == 0:
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
            if done:
                break
            if end.max_time is not None and sim.time - stage_start[0] >= end.max_time:
                self._checkpoint(index, stage_start)
                raise StageLimitError(
                    f"stage '{stage.name}' reached max_time = {end.max_time} s without meeting its end "
                    f"condition; raise stages.{stage.name}.end.max_time or revise the condition "
                    f"(a checkpoint was written to {self.out / 'checkpoints'})"
                )
            if self.max_steps is not None and sim.step_count >= self.max_steps:
                self._series_row(stage.name)
                self._write_frame(stage.name)
                self._checkpoint(index, stage_start)
                return False
            sim.step()  # runs the boundaries' hooks
            in_stage = sim.step_count - stage_start[1]
            if in_stage % series_every == 0:
                self._series_row(stage.name)
            if every_steps and sim.step_count % every_steps == 0:
                self._write_frame(stage.name)
            elif next_snapshot_time is not None and sim.time >= next_snapshot_time - 1e-9 * sim.dt:
                self._write_frame(stage.name)
                next_snapshot_time += every_time
            if ckpt_every and sim.step_count % ckpt_every == 0:
                self._checkpoint(index, stage_start)
            frac = in_stage / target_steps if target_steps else None
            self.progress.update(sim, stage.name, frac)
        self._series_row(stage.name)
        self._write_frame(stage.name)
        self._checkpoint(index + 1, (sim.time, sim.step_count), started=False)
        self.progress.update(sim, stage.name, 1.0, force=True)
        return True
