"""Output paths: can a path be (or become) a run's output directory, what a run put there, and who
is writing there now.

Used by the CLI before a run is built and by :class:`pdem.runner.Runner` (for Python API users), so
that an unusable output path is an :class:`~pdem.errors.InputError` with one message, never a
traceback, and so that a run refused at its start can remove exactly what it created.

Every output directory pdem writes holds a marker, ``.pdem-output.json``, listing the entries (files
and folders at its top level) that pdem created there. ``--overwrite`` replaces only a directory that
holds the marker, and removes only what the marker lists or what is named as pdem names its own
output (:func:`pdem_entries`): a folder pdem did not make is refused untouched, and files a user put
into an output folder (a deck, notes, plots) stay.

One run at a time per output directory: :class:`OutputLock` takes an exclusive lock on
``.pdem-lock`` there (``flock``: released by the kernel when the process ends, so a killed run never
leaves it stuck); a second run, a resume into a live run's folder, or an ``--overwrite`` of it is
refused naming the process that holds it.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import shutil
import socket
import stat
import sys
import time
from pathlib import Path

from ..errors import InputError

__all__ = [
    "output_dir_problem",
    "describe_mode",
    "entries",
    "first_missing",
    "remove_created",
    "MARKER",
    "LOCK",
    "is_pdem_output",
    "record_entries",
    "pdem_entries",
    "named_as_pdem",
    "remove_pdem_entries",
    "OutputLock",
    "lock_holder",
]

#: the marker file of a pdem output directory (JSON: what pdem created there)
MARKER = ".pdem-output.json"
#: the lock file of a pdem output directory
LOCK = ".pdem-lock"
#: top-level names pdem gives its own output (what a run killed before it updated the marker made)
_OWN_NAMES = re.compile(
    r"deck\.resolved(\.until-step-\d+)?\.toml|summary\.json|metadata\.json|checkpoints|"
    r"particles(\.r\d+)?\.h5|walls\.h5|(particles|walls|contacts)(\.xdmf|\.pvd)?|"
    r"continuum_[A-Za-z0-9_-]+((\.r\d+)?\.h5|\.xdmf)|"
    r"(series|solver)_[^/]+\.csv|\.pdem-journal|\.[^/]+\.[0-9a-f]{8}(\.tmp|\.vtu)"
)


def describe_mode(mode: int) -> str:
    """``st_mode`` in words: "a regular file", "a character device", …"""
    if stat.S_ISREG(mode):
        return "a regular file"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a directory"


def output_dir_problem(
    out: Path, what: str, remedy: str = "choose a directory path with --output DIR"
) -> str | None:
    """Why ``out`` cannot be (or become) a run's output directory, or None.

    ``what`` says where the path came from (``--output``, ``output.directory = …``), for the message.
    Only looks, creates nothing: an existing directory (empty or not) is fine here, the Runner applies
    the --overwrite rule to it.
    """
    try:
        st = os.stat(out)
    except (FileNotFoundError, NotADirectoryError):  # missing, or under a file: see the ancestors
        st = None
    except OSError as exc:  # a loop of links, a name too long, …
        return f"output path {out} ({what}) cannot be used: {exc.strerror}; {remedy}"
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            if not os.access(out, os.W_OK | os.X_OK):
                return f"output directory {out} ({what}) is not writable; fix its permissions or {remedy}"
            return None
        return (
            f"output path {out} ({what}) exists and is {describe_mode(st.st_mode)}, not a directory; "
            f"pdem writes a directory of files and never replaces a file (not even with --overwrite): "
            f"{remedy}"
        )
    if Path(out).is_symlink():
        return f"output path {out} ({what}) is a symbolic link to a missing target; {remedy}"
    # a new directory: its nearest existing ancestor must be a writable directory
    parent = Path(os.path.abspath(out)).parent
    while True:
        try:
            pst = os.stat(parent)
        except (FileNotFoundError, NotADirectoryError):
            pst = None
        except OSError as exc:
            return f"output directory {out} ({what}) cannot be created: {parent}: {exc.strerror}; {remedy}"
        if pst is not None or parent.parent == parent:
            break
        parent = parent.parent
    if pst is None or not stat.S_ISDIR(pst.st_mode):
        kind = describe_mode(pst.st_mode) if pst is not None else "missing"
        return (
            f"output directory {out} ({what}) cannot be created: {parent} is {kind}, not a "
            f"directory; {remedy}"
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        return (
            f"output directory {out} ({what}) cannot be created: no permission to write in {parent}; {remedy}"
        )
    return None


def entries(directory: Path) -> set[str] | None:
    """Names in ``directory`` (None if it does not exist)."""
    try:
        return set(os.listdir(directory))
    except FileNotFoundError:
        return None


def first_missing(path: Path) -> Path | None:
    """The outermost of ``path`` and its ancestors that does not exist (what ``mkdir(parents=True)``
    would create first), or None if ``path`` exists."""
    path = Path(os.path.abspath(path))
    if os.path.lexists(path):
        return None
    top = path
    while not os.path.lexists(top.parent) and top.parent != top:
        top = top.parent
    return top


def remove_created(directory: Path, before: set[str] | None, created_root: Path | None = None) -> None:
    """Undo what a run created in ``directory``: if it did not exist before (``before`` is None), the
    directories the run made (``created_root``, the outermost one, see :func:`first_missing`; default
    ``directory``); else only the entries that were not in ``before``. Never touches an entry that
    existed before. Errors are ignored (this runs while another error is being reported)."""
    directory = Path(directory)
    if before is None:
        shutil.rmtree(created_root if created_root is not None else directory, ignore_errors=True)
        return
    now = entries(directory) or set()
    for name in sorted(now - before):
        path = directory / name
        try:
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink()
        except OSError:
            pass


# ------------------------------------------------------------------------------------- marker
def _read_marker(directory: Path) -> dict | None:
    try:
        data = json.loads((Path(directory) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("written_by") == "pdem" else None


def is_pdem_output(directory: Path) -> bool:
    """Does ``directory`` hold pdem's output marker (was it made by pdem)?"""
    return _read_marker(directory) is not None


def record_entries(
    directory: Path, names: set[str] | frozenset[str], version: str = "", replace: bool = False
) -> None:
    """Write (or update) the marker of ``directory``, adding ``names`` to the entries pdem created
    (``replace``: listing only ``names``); atomic: a kill leaves the old marker or the new one."""
    directory = Path(directory)
    data = _read_marker(directory) or {
        "written_by": "pdem",
        "note": "pdem output directory; pdem --overwrite removes only the entries listed here",
        "entries": [],
    }
    old = set(data.get("entries") or [])
    new = (set() if replace else old) | {n for n in names if n not in (MARKER, LOCK)}
    if new == old and data.get("pdem_version") == version and (directory / MARKER).exists():
        return
    data["entries"] = sorted(new)
    if version:
        data["pdem_version"] = version
    tmp = directory / f"{MARKER}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, directory / MARKER)


def named_as_pdem(name: str) -> bool:
    """Is ``name`` one pdem gives its own output at the top of an output directory?"""
    return bool(_OWN_NAMES.fullmatch(name))


def pdem_entries(directory: Path) -> set[str]:
    """The entries of a pdem output ``directory`` that pdem made: those its marker lists, and those
    named as pdem names its own output; the marker and the lock aside. Empty for a folder without
    the marker."""
    data = _read_marker(directory)
    if data is None:
        return set()
    present = entries(directory) or set()
    listed = {str(n) for n in data.get("entries") or []}
    own = {n for n in present if _OWN_NAMES.fullmatch(n)}
    return (present & listed | own) - {MARKER, LOCK}


def remove_pdem_entries(directory: Path, keep: set[Path] = frozenset()) -> list[str]:
    """``--overwrite``: remove what pdem made in ``directory`` (:func:`pdem_entries`), never an entry
    that is or holds a path in ``keep`` (the deck being run, the packing files it reads); the names
    removed."""
    directory = Path(directory)
    real_keep = [os.path.realpath(p) for p in keep]
    removed = []
    for name in sorted(pdem_entries(directory)):
        path = directory / name
        real = os.path.realpath(path)
        if any(k == real or k.startswith(real + os.sep) for k in real_keep):
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
        removed.append(name)
    record_entries(directory, pdem_entries(directory), replace=True)  # what it kept, if anything
    return removed


# ------------------------------------------------------------------------------------- lock
def _holder_text(path: Path) -> str:
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
        return (
            f"process {info.get('pid')} on {info.get('host')} (started {info.get('started')}: "
            f"{str(info.get('command', ''))[:160]})"
        )
    except (OSError, ValueError):
        return "another process"


def lock_holder(directory: Path) -> str | None:
    """Who holds the lock of ``directory`` now (a description), or None if nobody does. Only looks:
    creates nothing."""
    path = Path(directory) / LOCK
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return _holder_text(path)
        except OSError:
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


class OutputLock:
    """The exclusive lock of one output directory, held by this process until :meth:`release` (or
    its end: the kernel drops ``flock`` locks of a dead process)."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self.path = self.directory / LOCK
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self, what: str = "this run") -> None:
        """Take the lock or raise :class:`~pdem.errors.InputError` naming who holds it."""
        if self._fd is not None:
            return
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise InputError(
                f"output directory {self.directory} is in use by {_holder_text(self.path)}; pdem runs "
                f"one run at a time per output directory, so {what} was refused and nothing there was "
                "touched: wait for that run to end (or stop it), or choose another directory with "
                "--output DIR"
            ) from None
        info = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": " ".join(sys.argv),
        }
        os.ftruncate(fd, 0)
        os.write(fd, (json.dumps(info) + "\n").encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
        finally:
            os.close(self._fd)
            self._fd = None
