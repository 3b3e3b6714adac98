"""``--set key.path=value`` overrides applied to a raw deck before validation.

* ``key.path`` is a dotted path of TOML keys; a key that is not a bare key may be quoted
  (``materials."glass beads".density``). In an array of tables, a segment is an index (``stages.0``) or,
  for tables that have a ``name`` key, a name (``stages.fill``).
* ``value`` is parsed as a TOML value (``1e-5``, ``true``, ``"hertz_mindlin"``, ``[0, 0, -9.81]``,
  ``{type = "box", lo = [0, 0, 0], hi = [1, 1, 1]}``). A value that is not valid TOML but is a single
  bare word (letters, digits, ``_ - . /``, starting with a letter) is taken as a string, so that
  ``--set contact.law=hertz_mindlin`` works without shell-quoting the quotes.
* Missing intermediate tables are created; the override replaces whatever was there. In an array of
  tables, the index one past the last entry adds a new table: ``--set stages.2.name=rest`` on a deck
  with two stages adds a third (then ``stages.2.end.time=0.5`` or ``stages.rest.end.time=0.5``), and
  so does a whole inline table (``--set 'particles.1={source = "lattice", …}'``).

Keys are not checked here: the validation that follows reports an unknown key (with the closest valid
key) at its path, and :mod:`pdem.deck.load` marks every problem under an overridden path with the
override that caused it. Messages quote at most about 200 characters of an override; a value nested
too deeply for the TOML parser is refused like a deck's (docs/deck.md, "Limits").
"""

from __future__ import annotations

import difflib
import re
import tomllib
from dataclasses import dataclass
from typing import Any

from ..textutil import clip, quote

__all__ = ["Override", "OverrideError", "parse_override", "apply_overrides"]

_SEGMENT = re.compile(r'\s*(?:"((?:[^"\\]|\\.)*)"|([A-Za-z0-9_-]+))\s*')
_BARE_WORD = re.compile(r"^[A-Za-z][A-Za-z0-9_.\-/]*$")


class OverrideError(ValueError):
    """A ``--set`` text that cannot be parsed or applied; ``loc`` is where it points (may be ())."""

    def __init__(self, message: str, loc: tuple[str | int, ...] = ()) -> None:
        super().__init__(message)
        self.loc = loc


@dataclass(frozen=True)
class Override:
    """One applied override: its text, the location it resolved to and the parsed value."""

    text: str
    loc: tuple[str | int, ...]
    value: Any


def _malformed(text: str) -> OverrideError:
    return OverrideError(f"malformed override {quote(text)}: expected key.path=value, e.g. run.dt=1e-5")


def _parse_key(text: str) -> tuple[list[str], str]:
    """Split ``key.path=value`` into key segments and the value text."""
    segments: list[str] = []
    pos = 0
    while True:
        m = _SEGMENT.match(text, pos)
        if not m or m.end() == pos:
            raise _malformed(text)
        quoted, bare = m.group(1), m.group(2)
        segments.append(bare if bare is not None else _unescape(quoted, text))
        pos = m.end()
        if pos < len(text) and text[pos] == ".":
            pos += 1
            continue
        if pos < len(text) and text[pos] == "=":
            return segments, text[pos + 1 :]
        raise _malformed(text)


def _unescape(quoted: str, text: str) -> str:
    try:
        return tomllib.loads(f'k = "{quoted}"')["k"]
    except (tomllib.TOMLDecodeError, ValueError):
        raise OverrideError(f"malformed override {quote(text)}: bad quoted key {quote(quoted, 80)}") from None


def parse_value(raw: str, text: str = "") -> Any:
    """A TOML value (or a bare word as a string, see the module docstring)."""
    from .problems import integer_digits_message, toml_nesting_problem, toml_text_problem

    raw = raw.strip()
    if not raw:
        raise OverrideError(f"malformed override {quote(text)}: no value after '='; e.g. run.dt=1e-5")
    problem = toml_text_problem(raw)
    if problem is not None:
        raise OverrideError(f"override {quote(text)}: the value has {problem.split(': ', 1)[-1]}")
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError as exc:
        if _BARE_WORD.match(raw):
            return raw
        raise OverrideError(
            f"override {quote(text)}: the value {clip(raw)} is not a TOML value ({exc}); quote strings, "
            f'e.g. contact.law="hertz_mindlin"'
        ) from None
    except RecursionError:
        found = toml_nesting_problem(raw)
        why = found.split(": ", 1)[-1] if found else "arrays or tables nested too deeply"
        raise OverrideError(f"override {quote(text)}: the value has {why}") from None
    except (ValueError, MemoryError) as exc:  # e.g. an integer of more than 4,300 digits
        digits = integer_digits_message(exc) if isinstance(exc, ValueError) else None
        if digits is not None:
            raise OverrideError(f"override {quote(text)}: the value is {digits}") from None
        why = clip(str(exc))
        raise OverrideError(f"override {quote(text)}: the value is not a usable TOML value ({why})") from None


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"run.dt=1e-5"`` → ``(["run", "dt"], 1e-05)``; raises :class:`OverrideError`."""
    if "=" not in text:
        raise _malformed(text)
    segments, raw = _parse_key(text)
    return segments, parse_value(raw, text)


def _kind(v: Any) -> str:
    if isinstance(v, dict):
        return "table"
    if isinstance(v, list):
        return "array"
    return type(v).__name__


def _closest(name: str, known: list[str]) -> str | None:
    """The known name closest to ``name``, if one is close; bounded, as hostile input may be long."""
    if len(name) > 100 or len(known) > 1000:
        return None
    close = difflib.get_close_matches(name, known, n=1)
    return close[0] if close else None


def _index(node: list, seg: str, loc: tuple, text: str) -> int:
    where = clip(".".join(str(p) for p in loc))
    if re.fullmatch(r"\d+", seg):
        k = int(seg)
        tables = all(isinstance(e, dict) for e in node)
        if k == len(node) and tables:  # one past the end: a new entry of an array of tables
            node.append({})
            return k
        if k >= len(node):
            raise OverrideError(
                f"override {quote(text)}: {where} has {len(node)} entr"
                f"{'y' if len(node) == 1 else 'ies'}; index {k} is out of range"
                + (
                    f" (index {len(node)} adds an entry: --set {where}.{len(node)}.KEY=VALUE)"
                    if tables
                    else ""
                ),
                loc + (k,),
            )
        return k
    names = [e.get("name") for e in node if isinstance(e, dict)]
    for k, e in enumerate(node):
        if isinstance(e, dict) and e.get("name") == seg:
            return k
    known = [n for n in names if isinstance(n, str)]
    close = _closest(seg, known)
    hint = f"; did you mean {quote(close, 80)}?" if close else ""
    listing = ", ".join(quote(n, 80) for n in known[:20]) or "(none have a name)"
    listing += f", … ({len(known):,} in all)" if len(known) > 20 else ""
    raise OverrideError(
        f"override {quote(text)}: no entry of {where} is named {quote(seg, 80)}{hint}; give an index "
        f"(0..{len(node) - 1}) or one of {listing}",
        loc + (seg,),
    )


def apply_one(data: dict, text: str) -> Override:
    """Apply one ``key.path=value`` to ``data`` in place."""
    segments, value = parse_override(text)
    node: Any = data
    loc: tuple[str | int, ...] = ()
    for i, seg in enumerate(segments):
        last = i == len(segments) - 1
        if isinstance(node, list):
            key: str | int = _index(node, seg, loc, text)
        elif isinstance(node, dict):
            key = seg
        else:
            where = clip(".".join(str(p) for p in loc))
            raise OverrideError(
                f"override {quote(text)}: {where} is a {_kind(node)}, not a table; it has no key "
                f"{quote(seg, 80)}",
                loc,
            )
        if (
            not last and len(loc) == 1 and loc[0] in NAMED_ENTRIES and isinstance(node, dict)
            and key not in node
        ):  # fmt: skip
            raise _no_such_entry(text, str(loc[0]), str(key), node)
        loc += (key,)
        if last:
            node[key] = value
        else:
            if isinstance(node, dict) and key not in node:
                node[key] = {}
            node = node[key]
    return Override(text, loc, value)


NAMED_ENTRIES = {"materials": "material", "boundaries": "boundary"}
"""Sections whose tables are named by the deck: a dotted ``--set`` into a name the deck does not
have is a typo (it would make a new, unused entry and change nothing), not a way to add one; a whole
table (``--set 'materials.sand={density = 2650.0}'``) still adds one."""


def _no_such_entry(text: str, section: str, name: str, node: dict) -> OverrideError:
    names = sorted(str(k) for k in node)
    close = _closest(name, names)
    hint = f" (did you mean {quote(close, 80)}?)" if close else ""
    have = ", ".join(quote(n, 40) for n in names[:12]) or "none"
    return OverrideError(
        f"override {quote(text)}: the deck has no {NAMED_ENTRIES[section]} named {quote(name, 80)}"
        f"{hint}; it has {have}. A dotted --set changes an entry the deck has; to add one, give it "
        f"whole: --set '{section}.{clip(name, 40)}={{...}}'",
        (section, name),
    )


def apply_overrides(
    data: dict, overrides: list[str] | tuple[str, ...]
) -> tuple[list[Override], list[tuple[tuple[str | int, ...], str]]]:
    """Apply every override in order; return the applied ones and the problems of the others."""
    applied: list[Override] = []
    problems: list[tuple[tuple[str | int, ...], str]] = []
    for text in overrides:
        try:
            applied.append(apply_one(data, text))
        except OverrideError as exc:
            problems.append((exc.loc or ("--set",), str(exc)))
    return applied, problems
