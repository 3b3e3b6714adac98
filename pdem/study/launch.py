"""Running one pdem process for a study: the command, a timeout, and a record that makes studies
resumable.

Each run directory gets ``study_run.json`` when its process has ended (written atomically, last): the
overrides, the command, the exit code, the wall time, the status and the tail of stderr. A directory
with a record for the same overrides is a finished run and is kept; one without a record (never
started, or killed with the study) is run again from scratch with ``--overwrite``.

Statuses: ``ok`` (exit 0), ``failed`` (exit 3: a numerical failure pdem caught), ``refused`` (exit 2:
invalid input, e.g. a step above the stability estimate without ``force_dt``), ``error`` (any other
exit code: a crash pdem did not turn into its own error), ``timeout`` (stopped after the spec's
timeout).
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.paths import record_entries

__all__ = ["RunRecord", "command", "launch", "read_record", "scan_nonfinite", "RECORD"]

RECORD = "study_run.json"
STATUS_BY_CODE = {0: "ok", 2: "refused", 3: "failed"}


@dataclass
class RunRecord:
    """What a study keeps of one finished process."""

    sets: list[str]
    command: list[str]
    exit_code: int | None
    status: str
    process_wall_s: float
    stderr_tail: str = ""
    nonfinite: list[str] = field(default_factory=list)
    finished: str = ""

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2) + "\n"


def mpiexec() -> str:
    """The mpiexec beside the interpreter (the ``mpich`` wheel's) first, else the one on PATH."""
    exe = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    if exe is None:
        raise InputError("ranks > 1 needs mpiexec; install the mpich wheel (pip install mpich)")
    return exe


def command(
    deck: Path, out: Path, sets: list[str], ranks: int = 1, extra: list[str] | None = None
) -> list[str]:
    """``python -m pdem DECK --output OUT --overwrite --quiet --set …``, under ``mpiexec -n RANKS``
    when ranks > 1."""
    pdem = [sys.executable, "-m", "pdem"]
    if ranks > 1:
        pdem = [mpiexec(), "-n", str(ranks), *pdem]
    cmd = [*pdem, str(deck), "--output", str(out), "--overwrite", "--quiet", *(extra or [])]
    for s in sets:
        cmd += ["--set", s]
    return cmd


def read_record(run_dir: Path) -> RunRecord | None:
    """The record of a finished run, or None (never run, killed, or unreadable)."""
    path = Path(run_dir) / RECORD
    try:
        data = json.loads(path.read_text())
        return RunRecord(**data)
    except (OSError, ValueError, TypeError):
        return None


def scan_nonfinite(run_dir: Path) -> list[str]:
    """Datasets of the run's HDF5 files (snapshots, checkpoints) holding a non-finite float:
    ``file:dataset`` names. A pdem failure must leave none."""
    import h5py

    bad: list[str] = []
    for path in sorted(Path(run_dir).rglob("*.h5")):
        try:
            with h5py.File(path, "r") as f:

                rel = path.relative_to(run_dir)

                def visit(name: str, obj: Any, rel: Path = rel) -> None:
                    if isinstance(obj, h5py.Dataset) and obj.dtype.kind == "f" and obj.size:
                        if not np.all(np.isfinite(obj[()])):
                            bad.append(f"{rel}:{name}")

                f.visititems(visit)
        except OSError:
            bad.append(f"{path.relative_to(run_dir)}: unreadable")
    return bad


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def launch(
    deck: Path,
    run_dir: Path,
    sets: list[str],
    *,
    ranks: int = 1,
    timeout: float | None = None,
    check_finite: bool = True,
    extra: list[str] | None = None,
    rerun: bool = False,
) -> tuple[RunRecord, bool]:
    """Run ``deck`` with ``sets`` into ``run_dir`` unless a record for the same overrides is there.

    Returns ``(record, ran)``; ``ran`` is False for a run kept from before. ``rerun`` runs again
    whatever is there. Output of the process goes to ``run_dir/stdout.log``; stderr is kept in
    ``run_dir/stderr.log`` and its tail in the record."""
    run_dir = Path(run_dir)
    old = read_record(run_dir)
    if old is not None and old.sets == list(sets) and not rerun:
        return old, False
    cmd = command(deck, run_dir, sets, ranks, extra)
    logs = run_dir.parent / f".{run_dir.name}.logs"
    logs.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    status: str
    with open(logs / "stdout.log", "w") as out, open(logs / "stderr.log", "w") as err:
        proc = subprocess.Popen(
            cmd,
            stdout=out,
            stderr=err,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # its own group: a timeout stops mpiexec and every rank
            preexec_fn=_die_with_parent,
        )
        with _LIVE_LOCK:
            _LIVE.add(proc)
        try:
            code: int | None = proc.wait(timeout=timeout)
            if _STOPPING.is_set():  # stopped with the study: not a result, run again next time
                raise KeyboardInterrupt
            status = STATUS_BY_CODE.get(code, "error")
        except subprocess.TimeoutExpired:
            _kill(proc)
            code, status = None, "timeout"
        except BaseException:
            _kill(proc)
            raise
        finally:
            with _LIVE_LOCK:
                _LIVE.discard(proc)
    wall = time.perf_counter() - t0
    run_dir.mkdir(parents=True, exist_ok=True)  # a run refused at its start leaves no directory
    for name in ("stdout.log", "stderr.log"):
        os.replace(logs / name, run_dir / name)
    logs.rmdir()
    tail = "\n".join((run_dir / "stderr.log").read_text(errors="replace").strip().splitlines()[-12:])
    nonfinite = scan_nonfinite(run_dir) if check_finite and status != "ok" else []
    record = RunRecord(
        sets=list(sets),
        command=cmd,
        exit_code=code,
        status=status,
        process_wall_s=wall,
        stderr_tail=tail,
        nonfinite=nonfinite,
        finished=time.strftime("%Y-%m-%dT%H:%M:%S"),
    )
    _write_atomic(run_dir / RECORD, record.to_json())
    # the run directory is pdem's even when the run was refused before it wrote anything: listed in
    # its marker, the study's files are replaced by the next attempt's --overwrite like the run's
    record_entries(run_dir, {"stdout.log", "stderr.log", RECORD})
    return record, True


_LIVE: set[subprocess.Popen] = set()
_LIVE_LOCK = threading.Lock()


_STOPPING = threading.Event()


def reset_stop() -> None:
    """Allow runs again after :func:`stop_all` (a new :meth:`Study.run` in the same process)."""
    _STOPPING.clear()


def stop_all() -> None:
    """Stop every run this process has under way (the study was interrupted); their ends are not
    recorded, so a rerun does them again."""
    _STOPPING.set()
    with _LIVE_LOCK:
        live = list(_LIVE)
    for proc in live:
        _kill(proc)


def _die_with_parent() -> None:
    """In the child, before exec: get SIGTERM when the study process dies, even by SIGKILL (Linux),
    so that a killed study leaves no run behind."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _kill(proc: subprocess.Popen) -> None:
    """Stop a run and everything it started (mpiexec and its ranks share its session)."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=10)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()


def summary_of(run_dir: Path) -> dict[str, Any] | None:
    try:
        return json.loads((Path(run_dir) / "summary.json").read_text())
    except (OSError, ValueError):
        return None


def lookup(data: Any, path: str) -> float | None:
    """``results.hopper.flow_rate`` in a summary; None when absent or not a finite number."""
    node = data
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    if isinstance(node, bool) or not isinstance(node, int | float):
        return None
    return float(node) if math.isfinite(node) else None


def series_value(run_dir: Path, q: Any) -> float | None:
    """A quantity given as a series column (``q.column``, ``q.stage``, ``q.reduce``, ``q.window``)."""
    run_dir = Path(run_dir)
    files = [run_dir / f"series_{q.stage}.csv"] if q.stage else _stage_files(run_dir)
    values: list[float] = []
    for path in files:
        try:
            with open(path, newline="") as fh:
                for row in csv.DictReader(fh):
                    text = row.get(q.column)
                    if text not in (None, ""):
                        values.append(float(text))
        except (OSError, ValueError):
            return None
    if not values:
        return None
    tail = values[-max(1, math.ceil(q.window * len(values))) :]
    out = {"last": lambda v: v[-1], "mean": lambda v: sum(v) / len(v), "max": max, "min": min}[q.reduce](tail)
    return float(out) if math.isfinite(out) else None


def _stage_files(run_dir: Path) -> list[Path]:
    """Every stage's series file, in the order the stages ran (by their first time)."""
    found = []
    for path in run_dir.glob("series_*.csv"):
        try:
            with open(path, newline="") as fh:
                first = next(csv.DictReader(fh), None)
            t0 = float(first["time"]) if first and first.get("time") else math.inf
        except (OSError, ValueError, KeyError):
            t0 = math.inf
        found.append((t0, path.name, path))
    return [p for _, _, p in sorted(found)]
