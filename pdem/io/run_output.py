"""A run's output directory: what :class:`pdem.runner.Runner` writes, and the bookkeeping around it.

:class:`RunOutput` owns the directory of one run: the start checks of an existing directory (another
run's lock, a non-empty directory without ``--overwrite``, a directory pdem did not make), its
creation or continuation (a resume into its own directory drops what the previous run wrote after
the checkpoint, held by the journal until the resume ends), the marker listing what pdem made, the
lock, the writers of snapshots (gathered or per rank), of the series CSVs and of the contact network,
the scene box snapshots have grown to (frame bounds), checkpoints, and at the end the journal
settled, or after a failure before the first step everything this run created removed (never what
was there before it).

The runner computes what is written (the series rows, the frames: collective calls on the
simulation) and hands it here. Only rank 0 touches files; the calls marked collective are made on
every rank.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from .. import __version__
from ..errors import InputError, PdemError
from ..plugins import load
from .checkpoint import write_checkpoint
from .journal import Journal, discard, settle_stale
from .parted import checkpoint_parts, stray_parts, write_parted
from .paths import (
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

__all__ = ["RunOutput"]


class RunOutput:
    """The output directory ``out`` of one run (see the module doc).

    ``comm``: the run's communicator (rank 0 writes); ``resolved``: the deck (its file and the files
    its sources read are never removed by ``overwrite``); ``deck_text``: the resolved deck written
    as ``deck.resolved.toml``; ``stage_names``: the deck's stages in order; ``resume_step``: the
    checkpoint's step of a resumed run (None: a new run); ``append``: continue the checkpoint's own
    output; ``overwrite``: replace pdem's output in a non-empty directory; ``series_from``: resuming
    into a new directory, the directory whose series (up to the checkpoint) are carried over;
    ``notes``: where notes on the directory go (rank 0; None: nowhere); ``dry``: the directory is not
    looked at (``pdem check``).

    Construction checks the directory (collective) and raises :class:`~pdem.errors.InputError` if it
    cannot take the run; nothing is created before :meth:`open`.
    """

    def __init__(
        self,
        out: Path,
        *,
        comm: Any,
        resolved: Any,
        deck_text: str,
        stage_names: list[str],
        resume_step: int | None = None,
        append: bool = False,
        overwrite: bool = False,
        series_from: Path | None = None,
        notes: TextIO | None = None,
        dry: bool = False,
    ) -> None:
        self.out = Path(out)
        self.comm = comm
        self.root = comm.rank == 0
        self.resolved = resolved
        self.deck_text = deck_text
        self.stage_names = list(stage_names)
        self.resume_step = resume_step
        self.append = bool(append)
        self.overwrite = bool(overwrite)
        self.series_from = series_from
        self.notes = notes
        self._before: set[str] | None = None
        self._created_root: Path | None = None
        self._lock = OutputLock(self.out)
        self._journal: Journal | None = None
        self._recorded: set[str] = set()
        self._foreign: set[str] = set()
        self._lock_made = False
        self._output_open = False
        self._series_append = False
        self._boundary_names: set[str] = set()
        self.writers: list[Any] = []
        self._gathered_writers: list[Any] = []
        self._per_rank_writers: list[Any] = []
        self._gathered_output = False
        self._series_writers: dict[Any, Any] = {}
        self._last_series_step: dict[str, int] = {}
        self._last_frame: dict[int, int] = {}  # id(writer) -> step of its last frame
        #: "gathered" or "per_rank", decided when the output opens
        self.output_parallel: str | None = None
        #: every series row kept, by stage (the rows a resume carried over first)
        self.series: dict[str, list[dict[str, float]]] = {}
        #: the scene box snapshots have grown to, (lo, hi); None before the first frame
        self.bounds: tuple[np.ndarray, np.ndarray] | None = None
        self._contacts_on = False
        self._contacts_last: int | None = None
        self._contact_writer: Any = None
        self._continuum: list[Any] = []
        problem = None
        if self.root and not dry:
            problem = output_dir_problem(self.out, "the output directory", "choose another output directory")
            if problem is None:
                self._before = entries(self.out)
                self._created_root = first_missing(self.out)
                problem = self.refusal()
        problem = self.comm.bcast(problem, root=0)
        if problem:
            raise InputError(problem)

    @property
    def resumed(self) -> bool:
        return self.resume_step is not None

    @property
    def continuing(self) -> bool:
        """A resume into its own directory whose journal is still open (rank 0)."""
        return self._journal is not None

    # ------------------------------------------------------------------------------ checks
    def refusal(self) -> str | None:
        """Why the existing output directory cannot take this run (rank 0; looks only): another run
        holds it, or it is not empty and neither continued (a resume's own directory) nor replaceable
        (``--overwrite`` of a directory pdem made)."""
        holder = lock_holder(self.out) if self._before is not None else None
        if holder is not None:
            what = "this resume" if self.resumed else "this run"
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

    def protected(self) -> set[Path]:
        """Paths ``--overwrite`` never removes: the deck being run and the files its sources read."""
        keep: set[Path] = set()
        if self.resolved.path is not None:
            keep.add(Path(self.resolved.path))
        for src in self.resolved.deck.particles or []:
            path = getattr(src, "path", None)
            if isinstance(path, str | Path) and str(path):
                keep.add(Path(self.resolved.base_dir) / path)
        return keep

    def writer_classes(self, formats: list[str]) -> list[tuple[str, type]]:
        """The writer plugin of every format; continuing an output, only those that can append."""
        classes = [(fmt, load("writers", fmt)) for fmt in formats]
        if self.append:
            bad = [fmt for fmt, cls in classes if not getattr(cls, "supports_append", False)]
            if bad:
                raise InputError(
                    f"output format(s) {', '.join(map(repr, bad))} cannot continue an existing output, so "
                    f"the run cannot go on in {self.out}; resume into a new directory with --output DIR"
                )
        return classes

    # ------------------------------------------------------------------------------ marker
    def record(self) -> None:
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

    def root_do(self, action: Callable[[], Any]) -> Any:
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

    # ------------------------------------------------------------------------------ opening
    def open(
        self,
        classes: list[tuple[str, type]],
        start: Any,
        *,
        out_cfg: Any,
        count_particles: Callable[[], int],
        boundary_names: Any,
    ) -> None:
        """Create the output directory (or continue the existing one), writers and series (collective).
        Called once the run has passed its start checks. ``start``: the run's
        :class:`~pdem.deck.resume.ResumePoint`; ``out_cfg``: the deck's ``[output]``;
        ``count_particles()``: the particles now (collective; ``output.parallel = "auto"`` decides
        by it);
        ``boundary_names``: the boundaries (their record CSVs are series too)."""
        from ..runner import _plugin_call, _where

        self._boundary_names = set(boundary_names)
        self._series_append = self.append or self.series_from is not None
        self._output_open = True
        if self.append:
            kept = self.root_do(lambda: self._continue_output(start))
        else:
            kept = self.root_do(lambda: self._new_output(start))
        self.root_do(self.record)
        for stage, rows in (kept or {}).items():
            self.series[stage] = rows
            if rows and "step" in rows[-1]:
                self._last_series_step[stage] = int(rows[-1]["step"])
        self.output_parallel = out_cfg.parallel_mode(count_particles(), self.comm.size)
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
        from .continuum import ContinuumWriter

        self._continuum = [
            ContinuumWriter(
                self.out, name, spec, comm=self.comm,
                metadata={"deck": self.deck_text, "pdem_version": __version__},
                append_after=(start.step, start.time) if self.append else None,
            )
            for name, spec in (getattr(out_cfg, "continuum", None) or {}).items()
        ]  # fmt: skip
        self._contacts_on = bool(getattr(out_cfg, "contacts", False))
        if self._contacts_on:
            from .contacts import ContactNetworkWriter

            def make() -> int | None:
                self._contact_writer = ContactNetworkWriter(
                    self.out, append_after=(start.step, start.time) if self.append else None
                )
                return self._contact_writer.last_step

            self._contacts_last = self.root_do(make)

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
        self._lock.acquire("this resume" if self.resumed else "this run")
        note = settle_stale(self.out, self.resume_step)
        if note and self.notes is not None:
            self.notes.write(f"pdem: {self.out}: {note}\n")

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
                    raise InputError(self.refusal() or f"{out} was not made by pdem")
                remove_pdem_entries(out, self.protected())
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
                if m.group(1) in self._boundary_names:  # <boundary>.<stage>.csv (Boundary.records)
                    out.append((m.group(2), path))
        return out

    def _stage_ran(self, stage: str, start: Any) -> bool:
        """Did ``stage`` start before the checkpoint (so its rows up to it belong to this run)?"""
        names = self.stage_names
        return stage in names and start.has_run(names.index(stage))

    def _seed_series(self, source: Path, start: Any) -> dict[str, list]:
        """Resuming into a new directory: copy the series rows up to the checkpoint from ``source``."""
        from .series import series_rows, truncate_series

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
        from .base import atomic_write_text
        from .series import series_rows, truncate_series

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
                parts = checkpoint_parts(path)  # a per-rank checkpoint's parts go with it
                if parts is not None:
                    later.append(parts)
        for path in later:
            discard(out, path)
        for path in stray_parts(ckdir):  # the parts of a checkpoint whose write a kill interrupted
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

    # ------------------------------------------------------------------------------ series
    def series_due(self, stage: str, step: int) -> bool:
        """Is a row of ``stage`` at ``step`` still to be written? (A step already written is not
        repeated: a stage's last step that is also on the series cadence, a resumed run's first
        step.) Marks it written."""
        if self._last_series_step.get(stage) == step:
            return False
        self._last_series_step[stage] = step
        return True

    def keep_row(self, stage: str, row: dict[str, Any]) -> None:
        """Keep a series row (every rank: the boundaries' summaries read them)."""
        self.series.setdefault(stage, []).append(row)

    def write_row(self, stage: str, row: dict[str, Any]) -> None:
        """Append a row to ``series_<stage>.csv`` (rank 0)."""
        if not self.root:
            return
        writer = self._series_writers.get(stage)
        if writer is None:
            from .series import SeriesWriter

            writer = SeriesWriter(self.out / f"series_{stage}.csv", list(row), append=self._series_append)
            self._series_writers[stage] = writer
        writer.append(row)
        self.record()

    def write_solver_rows(self, stage: str, log: list[tuple]) -> None:
        """DEM-C: every step's iterations, residual and contacts since the last row, appended to
        ``solver_<stage>.csv`` (rank 0)."""
        if not self.root or not log:
            return
        writer = self._series_writers.get(("solver", stage))
        if writer is None:
            from .series import SeriesWriter

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

    def write_records(self, name: str, stage: str, rows: list[dict[str, Any]]) -> None:
        """Rows boundary ``name`` sampled, appended to ``<name>.<stage>.csv`` (rank 0)."""
        if not rows or not self.root:
            return
        writer = self._series_writers.get(("records", name, stage))
        if writer is None:
            from .series import SeriesWriter

            path = self.out / f"{name}.{stage}.csv"
            writer = SeriesWriter(path, list(rows[0]), append=self._series_append)
            self._series_writers[("records", name, stage)] = writer
        for row in rows:
            writer.append(row)

    # ------------------------------------------------------------------------------ frames
    def grow_bounds(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The scene box of a frame: ``(lo, hi)`` grown to hold every earlier frame's (so infinite
        walls keep their drawn size), kept for the next and for checkpoints."""
        if self.bounds is not None:
            lo, hi = np.minimum(lo, self.bounds[0]), np.maximum(hi, self.bounds[1])
        if not np.all(np.isfinite(lo) & np.isfinite(hi)):
            lo, hi = np.zeros(3), np.ones(3)
        self.bounds = (lo, hi)
        return lo, hi

    def write_frame(self, step: int, gathered: Callable[[], Any], own: Callable[[], Any]) -> Any:
        """A snapshot for every writer that has none at ``step`` yet (collective): ``gathered()``
        makes the frame of every particle (collective), ``own()`` this rank's piece (collective).
        The gathered frame if one was made, else None."""
        due = [w for w in self._gathered_writers if self._last_frame.get(id(w)) != step]
        per_rank = [w for w in self._per_rank_writers if self._last_frame.get(id(w)) != step]
        frame = None
        # every rank decides alike: the writers' last steps are the same everywhere
        if self._gathered_output and self.comm.bcast(bool(due), root=0):
            frame = gathered()
            for w in due:  # rank 0 only
                w.write(frame)
                self._last_frame[id(w)] = step
        if per_rank:
            piece = own()
            for w in per_rank:
                w.write(piece)  # collective
                self._last_frame[id(w)] = step
        return frame

    @property
    def continuum_on(self) -> bool:
        """Does the run write continuum fields (``[output.continuum.<name>]``)?"""
        return bool(self._continuum)

    def write_continuum(self, sim: Any, stage: str, *, snapshot: bool) -> None:
        """The continuum fields due now (collective): at a particle snapshot (``snapshot``) the grids
        without their own ``every_steps``, after any step those whose interval it ends; and the
        samples of time averages."""
        step = int(sim.step_count)
        for w in self._continuum:
            every = w.spec.every_steps
            if (snapshot and every is None) or (every is not None and step % every == 0):
                w.write(sim, stage)
            elif (avg := w.spec.average_every_steps) and step % avg == 0:
                w.sample(sim)

    def contacts_due(self, step: int) -> bool:
        """Is the contact network (``output.contacts``) still to be written at ``step``?"""
        return self._contacts_on and self._contacts_last != step

    def write_contacts(self, lines: Callable[[], Any], time: float, step: int) -> None:
        """The contact network at ``step``: ``lines()`` its rows (rank 0 writes)."""
        if self._contact_writer is not None:
            self._contact_writer.write(lines(), time, step)
        self._contacts_last = step

    # ------------------------------------------------------------------------------ checkpoints
    def write_checkpoint(self, step: int, state: dict, meta: dict) -> Path:
        """``checkpoints/step_<step>.h5`` (collective). Serially one file; on several ranks each rank
        writes its share (``state`` from ``state_dict(local=True)``) and rank 0 the manifest
        (:mod:`pdem.io.parted`)."""
        for w in self._continuum:  # the fields' frames held up to here go to disk before the checkpoint,
            w.flush()  # so that a kill loses only frames after it, which a resume writes again
        path = self.out / "checkpoints" / f"step_{step:010d}.h5"
        if self.root and self._journal is not None and path.is_file():  # a resume rewriting the step it
            parts = checkpoint_parts(path)  # resumed from: the old checkpoint is held, so that a
            discard(self.out, path)  # rollback puts it back whole (manifest and parts)
            if parts is not None and parts.is_dir():
                discard(self.out, parts)
        if self.comm.size > 1:
            write_parted(path, state, meta, self.comm)
            if self.root:
                self.record()
            return path
        if self.root:
            write_checkpoint(path, state, meta)
            self.record()
        self.comm.Barrier()
        return path

    # ------------------------------------------------------------------------------ closing
    def close(self) -> None:
        for w in self.writers:
            w.close()
        for w in self._continuum:
            w.close()
        for w in self._series_writers.values():
            w.close()

    def undo(self) -> None:
        """The run failed before its first step: remove what it created (rank 0; never what was
        there before it, never a continued output, nothing in a directory whose lock it does not
        hold)."""
        if not self.root or not self._output_open or self.append or not self._lock.held:
            return
        remove_created(self.out, self._before, self._created_root)

    def _settle_journal(self, failed: BaseException | None, keep: bool) -> None:
        """Rank 0, at the end of a resume into its own directory: commit what it wrote, or, when it
        failed and had replaced a future (later checkpoints, rows, frames), put the directory back as
        it was before the resume. A failed resume that replaced nothing keeps what it wrote, as a
        failed run does; so does one whose failure ``keep`` says is a result (a stage's cap)."""
        journal, self._journal = self._journal, None
        if journal is None or not self.root:
            return
        try:
            if failed is None or keep or not journal.replaced_anything:
                journal.commit()
                return
            journal.rollback()
        except OSError as exc:  # never hide the run's own error behind the bookkeeping's
            if self.notes is not None:
                self.notes.write(f"pdem: warning: could not settle {journal.path}: {exc}\n")
            return
        if self.notes is not None:
            self.notes.write(
                f"pdem: the resume failed, so {self.out} was put back as it was before it (the later "
                "checkpoints, rows and snapshots it was replacing are kept); to keep a failing attempt's "
                "output, resume into a new directory with --output DIR\n"
            )

    def finish(self, failed: BaseException | None, *, stepped: bool, keep: bool = False) -> None:
        """Rank 0, last: the journal settled (``keep``: a failure that keeps the resume's output),
        the marker brought up to date (``stepped``: the run got to its stepping), the lock released."""
        if not self.root:
            return
        try:
            self._settle_journal(failed, keep)
            if failed is None or stepped:
                self.record()
        finally:
            self._lock.release()
