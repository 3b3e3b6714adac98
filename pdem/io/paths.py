"""Output paths: can a path be (or become) a run's output directory, and what a run put there.

Used by the CLI before a run is built and by :class:`pdem.runner.Runner` (for Python API users), so
that an unusable output path is an :class:`~pdem.errors.InputError` with one message, never a
traceback, and so that a run refused at its start can remove exactly what it created.
"""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

__all__ = ["output_dir_problem", "describe_mode", "entries", "first_missing", "remove_created"]


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
