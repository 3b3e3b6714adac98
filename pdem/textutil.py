"""Helpers for messages about user input: bounded quoting, and what a path that is not a file is.

A message names the bad value, but a value may be a 20 MB string, a packing file's line or a key
path thousands of levels long: every message quotes at most :data:`QUOTE_LIMIT` characters of it
(:func:`clip`, :func:`quote`), and :func:`clip_middle` bounds a whole message line while keeping
its end, where the remedy is.

:func:`file_problem` says why a path given as an input file (a deck, a packing file) cannot be read
as one: missing, a directory, a device, a named pipe, a symbolic-link loop, … It only looks at the
path (``stat``), so it never reads ``/dev/zero`` nor blocks on a FIFO.
"""

from __future__ import annotations

import errno
import os
import stat

__all__ = ["QUOTE_LIMIT", "MESSAGE_LIMIT", "clip", "quote", "clip_middle", "printable", "file_problem"]

#: most characters of one piece of user input quoted in a message
QUOTE_LIMIT = 200
#: most characters of one message line (a problem of a deck, a packing file's error)
MESSAGE_LIMIT = 2000


def printable(text: str) -> str:
    """``text`` with control characters escaped (``\\n``, ``\\x00``…), so that a quote stays on one
    line and cannot drive the terminal."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text)


def clip(text: str, limit: int = QUOTE_LIMIT) -> str:
    """``text`` (control characters escaped) cut to ``limit`` characters, ending with ``…`` and its
    full length when cut: ``abc… (20,000,000 characters)``."""
    limit = max(int(limit), 8)
    shown = printable(text[: limit + 1])
    if len(text) <= limit and len(shown) <= limit:
        return shown
    return f"{shown[: limit - 1]}… ({len(text):,} characters)"


def quote(text: str, limit: int = QUOTE_LIMIT) -> str:
    """``text`` in single quotes, clipped as by :func:`clip`: ``'abc…' (20,000,000 characters)``."""
    limit = max(int(limit), 8)
    shown = printable(text[: limit + 1])
    if len(text) <= limit and len(shown) <= limit:
        return f"'{shown}'"
    return f"'{shown[: limit - 1]}…' ({len(text):,} characters)"


def clip_middle(text: str, limit: int = MESSAGE_LIMIT) -> str:
    """``text`` cut to about ``limit`` characters by dropping its middle (``[…]``), so that both the
    beginning (what and where) and the end (the remedy) of a message stay."""
    if len(text) <= limit:
        return text
    keep = max(limit - 40, 20)
    head, tail = keep * 2 // 3, keep - keep * 2 // 3
    return f"{text[:head]} […{len(text) - head - tail:,} characters…] {text[-tail:]}"


_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISSOCK, "a socket"),
)


def file_problem(path: str | os.PathLike[str]) -> str | None:
    """None if ``path`` is a regular file this process may read; else what is wrong, as the end of a
    sentence about it (``"is a directory, not a regular file"``, ``"does not exist"``, …)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            try:
                target = os.readlink(path)
            except OSError:
                target = "?"
            return f"is a symbolic link to {quote(target)}, which does not exist"
        return "does not exist"
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            return "is a symbolic-link loop (links that lead back to themselves), not a file"
        if exc.errno == errno.ENAMETOOLONG:
            return "is too long for the file system (a name of more than 255 bytes, or a path too long)"
        if exc.errno == errno.ENOTDIR:
            return "does not exist (a part of the path is a file, not a directory)"
        if exc.errno == errno.EACCES:
            return "cannot be reached (permission denied on a directory of the path)"
        return f"cannot be read ({exc.strerror or exc})"
    except ValueError:  # an embedded NUL character
        return "is not a valid path (it holds a NUL character)"
    for test, kind in _KINDS:
        if test(st.st_mode):
            return f"is {kind}, not a regular file"
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file"
    if not os.access(path, os.R_OK):
        return "cannot be read (permission denied)"
    return None
