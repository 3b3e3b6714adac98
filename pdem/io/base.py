"""Base class of output writers and the helpers they share (field selection, atomic writes).

A writer is constructed once per run with an output ``directory``, writes one :class:`Frame`
per :meth:`Writer.write` call and is closed with :meth:`Writer.close` (idempotent; writers are
context managers). Each concrete writer is registered as an entry point of group
``pdem.writers`` under its :attr:`Writer.name`.

Per-rank output (``comm=``): a writer whose class sets :attr:`Writer.supports_per_rank` can be
constructed on every rank of an MPI communicator. It is then collective: every rank calls
:meth:`Writer.write` with a :class:`Frame` holding only *its own* particles (ordered by id; the walls
are the same on every rank) and writes them to its own file (:meth:`Writer._write_piece`); rank 0
then writes the index that joins the pieces into one dataset (:meth:`Writer._write_index`), given a
:class:`Piece` summary (particle count, field shapes and dtypes) of every rank. Only those summaries
travel between ranks, never particle arrays. Errors are collective too: a failure on any rank
raises the same :class:`~pdem.errors.OutputError` on every rank. Without ``comm`` a writer is
serial: one process writes whole frames (under MPI, rank 0 writes frames gathered from every rank).

Field selection: ``fields=None`` writes every particle field present in the frame; otherwise only
the listed ones, plus ``id`` and ``x`` (always written) and ``r`` when the frame has it (needed to
draw the particles as spheres). A name that is not a particle field
(:data:`pdem.io.frame.PARTICLE_FIELDS`) is an :class:`~pdem.errors.OutputError` at construction; a
requested field missing from a frame is an :class:`~pdem.errors.OutputError` at :meth:`write`.

Continuing an output (``pdem resume`` into the run's own directory): a writer whose class sets
:attr:`Writer.supports_append` accepts ``append_after=(step, time)``. Instead of refusing its
existing files it keeps the frames written at or before that step (the checkpoint the run resumes
from), drops those after it (written by the previous run past the checkpoint), and appends new
frames to the same files and indexes, so the directory holds one time series.
:attr:`Writer.last_step` is then the step of the last frame kept (None if none), so the caller does
not write the same step twice.
"""

from __future__ import annotations

import json
import os
import re
import secrets
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar, TypeVar

import numpy as np

from ..errors import OutputError
from .frame import PARTICLE_FIELDS, REQUIRED_FIELDS, Frame, WallState

__all__ = [
    "Piece",
    "Writer",
    "atomic_write_text",
    "make_temp_file",
    "piece_name",
    "safe_key",
    "write_metadata_json",
]

_T = TypeVar("_T")

#: Fields written whatever ``fields`` says, when present in the frame.
_ALWAYS = (*REQUIRED_FIELDS, "r", "row")


def make_temp_file(path: Path, suffix: str = ".tmp") -> tuple[int, str]:
    """Create a new, empty, uniquely named file beside ``path`` to be renamed over it later:
    ``(open file descriptor, its path)``; the caller closes the descriptor.

    Unlike :func:`tempfile.mkstemp` (mode 0600), the file gets the permissions of any new file,
    ``0666`` minus the umask (the kernel applies it, so no process-wide umask call): an output file
    written atomically must be as readable as one written directly.
    """
    path = Path(path)
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}{suffix}"
        try:
            fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        return fd, str(tmp)
    raise FileExistsError(f"no free temporary name for {path} after 100 tries")  # pragma: no cover


def atomic_write_text(path: Path, text: str) -> None:
    """Replace ``path`` with ``text`` atomically (temp file in the same directory + ``os.replace``).

    A reader sees either the previous content or the new one, never a partial file. The file gets
    the usual permissions of a new file (see :func:`make_temp_file`).
    """
    path = Path(path)
    fd, tmp = make_temp_file(path)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_metadata_json(path: Path, metadata: dict[str, str]) -> None:
    """Write ``metadata`` as a JSON object (sorted keys, indented) atomically to ``path``."""
    atomic_write_text(path, json.dumps(metadata, indent=2, sort_keys=True) + "\n")


def safe_key(name: str) -> str:
    """``name`` with every character outside ``[A-Za-z0-9_.-]`` replaced by ``_`` (file/HDF5/XDMF-safe)."""
    key = re.sub(r"[^A-Za-z0-9_.\-]", "_", name)
    return key if key.strip(".") else f"_{key}"


def piece_name(rank: int) -> str:
    """The name of rank ``rank``'s piece in per-rank output: ``r0000``, ``r0001``, …"""
    return f"r{int(rank):04d}"


@dataclass(frozen=True)
class Piece:
    """What rank 0 learns about one rank's piece of a frame in per-rank output.

    ``fields`` maps each written particle field to its ``(shape, dtype string)``, e.g.
    ``{"x": ((n, 3), "<f8"), "id": ((n,), "<i8"), …}``, in writing order.
    """

    rank: int
    n: int
    fields: dict[str, tuple[tuple[int, ...], str]]

    @property
    def name(self) -> str:
        return piece_name(self.rank)


class Writer:
    """Base class of writers: validation, field selection, lifecycle.

    Parameters
    ----------
    directory : output directory; created (with parents) if missing.
    fields : particle fields to write (``None``: all present in each frame).
    metadata : strings stored in every output file (e.g. ``{"deck": <TOML>, "pdem_version": ...}``).
    overwrite : replace this writer's existing files in ``directory`` instead of refusing.
    append_after : ``(step, time)``: continue the output already in ``directory`` (see the module
        doc; only for classes with :attr:`supports_append`). ``None``: a new output.
    comm : an MPI communicator (or :class:`pdem.parallel.comm.SerialComm`) for per-rank output:
        the writer is then constructed, written and closed on every rank of ``comm`` together
        (see the module doc). ``None``: serial output of whole frames.

    Subclasses implement :meth:`_write` (and optionally :meth:`_close`) and set :attr:`name`;
    writers that support per-rank output also set :attr:`supports_per_rank` and implement
    :meth:`_write_piece` and :meth:`_write_index`. In per-rank mode, a subclass's constructor runs
    its file set-up through :meth:`_collective` so that every rank raises the same error.
    """

    name: ClassVar[str] = ""
    #: True when the writer can write one file per MPI rank joined by an index (``comm=``).
    supports_per_rank: ClassVar[bool] = False
    #: True when the writer can continue an existing output (``append_after=``).
    supports_append: ClassVar[bool] = False

    def __init__(
        self,
        directory: Path | str,
        *,
        fields: Sequence[str] | None = None,
        metadata: dict[str, str] | None = None,
        overwrite: bool = False,
        comm: Any = None,
        append_after: tuple[int, float] | None = None,
    ) -> None:
        self.directory = Path(directory)
        self.overwrite = bool(overwrite)
        if append_after is not None and not self.supports_append:
            raise OutputError(
                f"{type(self).__name__} ('{self.name}') cannot continue an existing output; write the "
                f"continued run to a new directory (pdem resume ... --output DIR)"
            )
        #: ``(step, time)`` of the checkpoint an appended output continues from, or None
        self.append_after = (
            (int(append_after[0]), float(append_after[1])) if append_after is not None else None
        )
        #: step of the last frame on disk (kept from a previous run when appending), or None
        self.last_step: int | None = None
        if comm is not None and not self.supports_per_rank:
            raise OutputError(
                f"{type(self).__name__} ('{self.name}') cannot write per-rank output files; "
                f'write gathered frames instead (output.parallel = "gather", or construct it without comm)'
            )
        self.comm = comm
        #: this process's rank in ``comm`` (0 for serial output)
        self.rank = int(comm.rank) if comm is not None else 0
        self.n_ranks = int(comm.size) if comm is not None else 1
        if fields is not None:
            if isinstance(fields, str):
                fields = [fields]
            unknown = [f for f in fields if f not in PARTICLE_FIELDS]
            if unknown:
                raise OutputError(
                    f"{type(self).__name__} for '{self.directory}': unknown particle field(s) "
                    f"{', '.join(map(repr, unknown))}; valid fields: {', '.join(PARTICLE_FIELDS)}"
                )
            self.fields: tuple[str, ...] | None = tuple(dict.fromkeys(fields))
        else:
            self.fields = None
        meta = dict(metadata or {})
        bad = [k for k, v in meta.items() if not isinstance(k, str) or not isinstance(v, str)]
        if bad:
            raise OutputError(
                f"{type(self).__name__} for '{self.directory}': metadata keys and values must be strings; "
                f"offending keys: {', '.join(map(repr, bad))}; convert them with str() first"
            )
        self.metadata: dict[str, str] = meta
        self._collective(self._make_directory, root_only=True)
        self.n_frames = 0
        self._closed = False

    def _keeps(self, step: int | None, time: float | None) -> bool:
        """Appending: is a frame at ``step`` (or, when its step is unknown, ``time``) one to keep?"""
        assert self.append_after is not None
        if step is not None:
            return step <= self.append_after[0]
        return time is not None and time <= self.append_after[1]

    def _make_directory(self) -> None:
        if self.directory.exists() and not self.directory.is_dir():
            raise OutputError(
                f"output directory '{self.directory}' exists and is not a directory; "
                f"choose another output path or remove that file"
            )
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"cannot create output directory '{self.directory}': {exc}; check the path and permissions"
            ) from exc

    @property
    def per_rank(self) -> bool:
        """True when this writer writes per-rank pieces joined by an index (constructed with ``comm``)."""
        return self.comm is not None

    # ---------------------------------------------------------------- lifecycle
    def write(self, frame: Frame) -> None:
        """Append one frame to the output (files are complete and readable when this returns).

        Per-rank output: a collective call; ``frame`` holds this rank's particles only.
        """
        if self._closed:
            raise OutputError(
                f"{type(self).__name__} for '{self.directory}' is closed; create a new writer to write more"
            )
        if self.comm is None:
            particles = self._select(frame)
            walls = self._check_walls(frame)
            try:
                self._write(frame, particles, walls)
            except OSError as exc:
                raise OutputError(self._failed(frame, exc)) from exc
        else:

            def piece() -> Piece:
                particles = self._select(frame)
                self._check_walls(frame)
                try:
                    self._write_piece(frame, particles)
                except OSError as exc:
                    raise OutputError(self._failed(frame, exc)) from exc
                fields = {k: (tuple(int(d) for d in a.shape), a.dtype.str) for k, a in particles.items()}
                return Piece(self.rank, int(particles["x"].shape[0]), fields)

            pieces = self._collective(piece)

            def index() -> None:
                try:
                    self._write_index(frame, pieces, list(frame.walls))
                except OSError as exc:
                    raise OutputError(self._failed(frame, exc)) from exc

            self._collective(index, root_only=True)
        self.n_frames += 1
        self.last_step = int(frame.step)

    def _failed(self, frame: Frame, exc: OSError) -> str:
        return (
            f"{type(self).__name__}: writing frame {self.n_frames} (step {frame.step}) to "
            f"'{self.directory}' failed: {exc}; check free disk space and permissions, and that no "
            f"other program holds the files open"
        )

    def _collective(self, action: Callable[[], _T], *, root_only: bool = False) -> list[_T]:
        """Run ``action`` on every rank (on rank 0 only if ``root_only``) and return the results in
        rank order (``[result of rank 0]`` if ``root_only`` or for serial output).

        Per-rank output: a collective call; if ``action`` raised :class:`OutputError` or
        :class:`OSError` on any rank, every rank raises the same :class:`OutputError`, naming the
        ranks. Serial output: ``action``'s exceptions propagate unchanged.
        """
        if self.comm is None:
            return [action()]
        result: Any = None
        error: str | None = None
        if not root_only or self.rank == 0:
            try:
                result = action()
            except OutputError as exc:
                error = str(exc)
            except OSError as exc:
                error = f"{type(self).__name__} in '{self.directory}': {exc}"
        if root_only:
            error, result = self.comm.bcast((error, result), root=0)
            results, errors = [result], [error]
        else:
            gathered = self.comm.allgather((result, error))
            results = [r for r, _ in gathered]
            errors = [e for _, e in gathered]
        failed = [(r, e) for r, e in enumerate(errors) if e is not None]
        if failed:
            if self.n_ranks == 1:
                raise OutputError(failed[0][1])
            raise OutputError("; ".join(f"rank {r}: {e}" for r, e in failed))
        return results

    def close(self) -> None:
        """Finish the output; further calls do nothing."""
        if self._closed:
            return
        self._closed = True
        self._close()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Writer:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    # ---------------------------------------------------------------- for subclasses
    def _write(self, frame: Frame, particles: dict[str, np.ndarray], walls: list[WallState]) -> None:
        raise NotImplementedError  # pragma: no cover

    def _write_piece(self, frame: Frame, particles: dict[str, np.ndarray]) -> None:
        """Per-rank output, every rank: write this rank's ``particles`` of ``frame`` to its own file."""
        raise NotImplementedError  # pragma: no cover

    def _write_index(self, frame: Frame, pieces: list[Piece], walls: list[WallState]) -> None:
        """Per-rank output, rank 0 only, after every rank wrote its piece: write the index joining
        ``pieces`` (one per rank, in rank order) and the walls."""
        raise NotImplementedError  # pragma: no cover

    def _close(self) -> None:
        """Hook called once by :meth:`close`."""

    def _claim(self, paths: Sequence[Path]) -> None:
        """Refuse existing ``paths`` unless ``overwrite``; with ``overwrite`` delete them."""
        existing = [p for p in paths if p.exists() or p.is_symlink()]
        if not existing:
            return
        if not self.overwrite:
            shown = ", ".join(f"'{p}'" for p in existing[:5]) + (" …" if len(existing) > 5 else "")
            raise OutputError(
                f"{type(self).__name__}: output file(s) already exist: {shown}; choose an empty output "
                f"directory, remove them, or pass overwrite=True (--overwrite) to replace them"
            )
        for p in existing:
            try:
                p.unlink()
            except OSError as exc:
                raise OutputError(f"cannot remove existing output '{p}' to overwrite it: {exc}") from exc

    def _select(self, frame: Frame) -> dict[str, np.ndarray]:
        """Validated particle arrays to write, in :data:`PARTICLE_FIELDS` order then extra names."""
        where = f"{type(self).__name__} frame {self.n_frames} (step {frame.step})"
        parts = frame.particles
        for req in REQUIRED_FIELDS:
            if req not in parts:
                raise OutputError(
                    f"{where}: the frame has no particle field '{req}'; frames must carry 'id' and 'x'"
                )
        ids = np.asarray(parts["id"])
        n = ids.shape[0] if ids.ndim == 1 else -1
        if self.fields is None:
            names = [k for k in PARTICLE_FIELDS if k in parts] + [
                k for k in parts if k not in PARTICLE_FIELDS
            ]
        else:
            missing = [k for k in self.fields if k not in parts]
            if missing:
                raise OutputError(
                    f"{where}: requested field(s) {', '.join(map(repr, missing))} not in the frame "
                    f"(it has {', '.join(parts)}); remove them from the output fields"
                )
            names = [k for k in PARTICLE_FIELDS if k in self.fields or (k in _ALWAYS and k in parts)]
        out: dict[str, np.ndarray] = {}
        for k in names:
            if k not in PARTICLE_FIELDS and safe_key(k) != k:
                raise OutputError(
                    f"{where}: extra particle field name {k!r} is not file-safe; use letters, digits, _ . -"
                )
            a = np.asarray(parts[k])
            if a.dtype == np.bool_:
                a = a.astype(np.uint8)
            if a.dtype.kind not in "iuf":
                raise OutputError(f"{where}: particle field '{k}' has dtype {a.dtype}; give numbers")
            if not (a.ndim in (1, 2) and a.shape[0] == n and (a.ndim == 1 or a.shape[1] == 3)):
                raise OutputError(
                    f"{where}: particle field '{k}' has shape {a.shape}; expected ({n},) or ({n}, 3) "
                    f"for {n} particles ('id' has shape {ids.shape})"
                )
            if k == "x" and a.ndim != 2:
                raise OutputError(f"{where}: particle positions 'x' have shape {a.shape}; expected ({n}, 3)")
            out[k] = a
        return out

    def _check_walls(self, frame: Frame) -> list[WallState]:
        where = f"{type(self).__name__} frame {self.n_frames} (step {frame.step})"
        seen: dict[str, str] = {}
        for w in frame.walls:
            key = safe_key(w.name)
            if key in seen:
                raise OutputError(
                    f"{where}: walls '{seen[key]}' and '{w.name}' have the same output name '{key}'; "
                    f"give walls distinct names (letters, digits, _ . -)"
                )
            seen[key] = w.name
            for attr in ("force", "torque"):
                if np.asarray(getattr(w, attr)).shape != (3,):
                    raise OutputError(f"{where}: wall '{w.name}' {attr} must have shape (3,)")
        return list(frame.walls)
