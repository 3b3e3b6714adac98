"""A small TOML emitter for resolved decks (the standard library reads TOML but does not write it).

Layout: in each table, plain keys first, then sub-tables. At the top level every table becomes a
``[section]``; lists of tables become ``[[arrays]]``; deeper tables that carry a ``type`` key (regions,
size distributions, wall motions) are written inline when they fit on one line, other tables as
``[dotted.headers]``. Strings are basic strings, floats use ``repr`` (round-trip exact), non-finite
floats ``inf``/``nan``. ``None`` has no TOML form: leave such keys out before emitting.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

__all__ = ["dumps", "key", "value"]

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")
_INLINE_WIDTH = 100


def key(k: str) -> str:
    """``k`` as a TOML key segment: bare when it may be, else a quoted string."""
    return k if _BARE.match(k) else _string(k)


def _string(s: str) -> str:
    # JSON escapes (\" \\ \n \uXXXX …) are valid in TOML basic strings; DEL must be escaped too
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def value(v: Any) -> str:
    """The TOML text of one value (scalars, arrays, inline tables)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _string(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(value(x) for x in v) + "]"
    if isinstance(v, dict):
        if not v:
            return "{}"
        return "{ " + ", ".join(f"{key(str(k))} = {value(x)}" for k, x in v.items()) + " }"
    if v is None:
        raise TypeError("None has no TOML representation; leave the key out")
    raise TypeError(f"cannot write a {type(v).__name__} as TOML: {v!r}")


def _is_table_list(v: Any) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _as_subtable(v: Any, depth: int) -> bool:
    """Whether ``v`` (a value at ``depth`` below the root) is written as a [table] / [[array]]."""
    if _is_table_list(v):
        return True
    if not isinstance(v, dict) or not v:
        return False
    if depth == 0 or "type" not in v:
        return True
    try:
        return len(value(v)) > _INLINE_WIDTH or any(_is_table_list(x) for x in v.values())
    except TypeError:
        return True


def _emit(lines: list[str], path: tuple[str, ...], table: dict, header: str | None) -> None:
    depth = len(path)
    plain = [(k, v) for k, v in table.items() if v is not None and not _as_subtable(v, depth)]
    subs = [(k, v) for k, v in table.items() if v is not None and _as_subtable(v, depth)]
    if header is not None and (plain or not subs):  # a table holding only tables needs no header
        if lines:
            lines.append("")
        lines.append(header)
    for k, v in plain:
        lines.append(f"{key(str(k))} = {value(v)}")
    for k, v in subs:
        sub = path + (str(k),)
        dotted = ".".join(key(p) for p in sub)
        if isinstance(v, dict):
            _emit(lines, sub, v, f"[{dotted}]")
        else:
            for item in v:
                _emit(lines, sub, item, f"[[{dotted}]]")


def dumps(data: dict, header_comment: str | None = None) -> str:
    """TOML text of ``data`` (a dict of plain Python values), optionally after a ``#`` comment block."""
    lines: list[str] = []
    if header_comment:
        lines += [f"# {line}".rstrip() for line in header_comment.splitlines()]
    _emit(lines, (), data, None)
    return "\n".join(lines) + "\n"
