"""Deck problems: pydantic errors turned into ``(key path, message)`` pairs, and the DeckError.

A *location* (``loc``) is a tuple of keys and array indices, e.g. ``("particles", 0, "sizes", "r_min")``;
it is shown as ``particles.0.sizes.r_min`` (keys that are not bare TOML keys are quoted). Messages name
the bad value and what is allowed; an unknown key comes with the closest valid key (difflib).

Pydantic puts the tag of a discriminated union into its error locations
(``particles.0.random_fill.n``); :func:`translate` walks the model's annotations along the location to
drop those tags, to find the valid keys of the table an unknown key was found in, and to describe a
missing key from its field description.
"""

from __future__ import annotations

import math
import re
import types
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from ..errors import DeckError
from ..textutil import QUOTE_LIMIT, clip, clip_middle, quote
from .schema import MAX_DEPTH, MAX_ENTRIES, RULE_ERROR, did_you_mean

__all__ = [
    "Loc",
    "format_path",
    "show",
    "translate",
    "make_deck_error",
    "SECTION_ORDER",
    "MAX_LISTED_PROBLEMS",
    "shape_problems",
    "toml_nesting_problem",
    "toml_text_problem",
    "integer_digits_message",
]

Loc = tuple[str | int, ...]

#: order in which problems are listed (by top-level key)
SECTION_ORDER = (
    "--set",
    "",
    "title",
    "run",
    "contact",
    "materials",
    "material_pairs",
    "particles",
    "boundaries",
    "stages",
    "output",
)

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")
#: most problems a DeckError lists (the count of the others follows)
MAX_LISTED_PROBLEMS = 100
#: most errors of one pydantic validation turned into problems (the rest are counted)
MAX_TRANSLATED = 1000
#: integers a deck may hold: TOML's 64-bit range
_INT_RANGE = (-(2**63), 2**63 - 1)


def format_path(loc: Loc) -> str:
    """``("materials", "glass", "density")`` → ``materials.glass.density``."""
    parts = []
    for p in loc:
        if isinstance(p, int) or _BARE.match(p):
            parts.append(str(p))
        else:
            parts.append('"' + p.replace("\\", "\\\\").replace('"', '\\"') + '"')
    return ".".join(parts)


def show(value: Any, limit: int = 80) -> str:
    """A value as it would be written in TOML (strings in single quotes), shortened to ``limit``
    (control characters escaped; a long array or table is not written out beyond ``limit``)."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = "'" + clip(value[: limit + 1], limit + 1) + "'"
    elif isinstance(value, float):
        text = repr(value) if math.isfinite(value) else str(value)
    elif isinstance(value, int) and value.bit_length() > 64:
        text = f"an integer of about {value.bit_length() * 0.30103:.0f} digits"
    elif isinstance(value, list | tuple):
        text = "[" + ", ".join(_items((show(v, limit) for v in value), limit)) + "]"
    elif isinstance(value, dict):
        items = (f"{clip(str(k), limit)} = {show(v, limit)}" for k, v in value.items())
        text = "{" + ", ".join(_items(items, limit)) + "}"
    else:
        text = clip(str(value), limit + 1)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _items(texts: Any, limit: int) -> list[str]:
    """The first of ``texts`` up to about ``limit`` characters in all (a 10⁶-entry array is not
    written out to show 80 characters of it)."""
    out: list[str] = []
    size = 0
    for t in texts:
        out.append(t)
        size += len(t) + 2
        if size > limit:
            break
    return out


def _kind(value: Any) -> str:
    if isinstance(value, bool):
        return "the boolean "
    if isinstance(value, str):
        return "the string "
    if isinstance(value, list | tuple):
        return "the array "
    if isinstance(value, dict):
        return "a table "
    return ""


# -------------------------------------------------------------------------------------------------
# walking annotations along an error location
# -------------------------------------------------------------------------------------------------


def _unwrap(tp: Any) -> Any:
    """Strip ``Annotated`` and ``Optional``; a real union is returned as is."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
            continue
        if origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp


def _is_union(tp: Any) -> bool:
    return get_origin(tp) in (Union, types.UnionType)


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _tags(member: Any) -> dict[str, str]:
    """Literal values of a union member's fields: {value: field name}."""
    out: dict[str, str] = {}
    member = _unwrap(member)
    if _is_model(member):
        for name, f in member.model_fields.items():
            if get_origin(f.annotation) is Literal:
                for v in get_args(f.annotation):
                    out.setdefault(str(v), name)
    return out


def _fixed_tuple_len(tp: Any) -> int | None:
    tp = _unwrap(tp)
    if get_origin(tp) is tuple:
        args = get_args(tp)
        if args and args[-1] is not Ellipsis:
            return len(args)
    return None


class _Walk:
    """Result of walking a model's annotations along an error location."""

    def __init__(self, root: Any, loc: Loc, keep_unmatched: bool = False) -> None:
        self.parts: list[str | int] = []
        self.types: list[Any] = []  # unwrapped type *at* each kept part's parent, then the leaf type
        self.field: FieldInfo | None = None
        tp: Any = root
        for part in loc:
            tp = _unwrap(tp)
            if _is_union(tp):
                # pydantic inserts the tag (or a type name) of the member it tried
                member = next((m for m in get_args(tp) if str(part) in _tags(m)), None)
                if member is not None or not keep_unmatched:
                    tp = _unwrap(member) if member is not None else None
                    continue
                tp = None  # a key of the member (locations written by rules carry no label)
            self.types.append(tp)
            self.parts.append(part)
            self.field = None
            if _is_model(tp):
                info = tp.model_fields.get(part) if isinstance(part, str) else None
                self.field = info
                tp = info.annotation if info is not None else None
            elif get_origin(tp) in (list, set, frozenset) and isinstance(part, int):
                tp = get_args(tp)[0] if get_args(tp) else None
            elif get_origin(tp) is tuple and isinstance(part, int):
                args = get_args(tp)
                if args and args[-1] is Ellipsis:
                    tp = args[0]
                else:
                    tp = args[part] if part < len(args) else None
            elif get_origin(tp) is dict:
                tp = get_args(tp)[1] if get_args(tp) else None
            else:
                tp = None
        self.leaf = _unwrap(tp) if tp is not None else None

    @property
    def parent(self) -> Any:
        return self.types[-1] if self.types else None


def _literal_choices(tp: Any) -> list[str]:
    tp = _unwrap(tp)
    if get_origin(tp) is Literal:
        return [str(v) for v in get_args(tp)]
    if get_origin(tp) in (list, set, tuple) and get_args(tp):
        return _literal_choices(get_args(tp)[0])
    return []


def _bounds(field: FieldInfo | None, ctx: dict) -> str:
    """``"> 0"``, ``"in (-1, 0.5)"`` … from the field's constraints (or the error's context)."""
    lower = upper = None
    metas = list(field.metadata) if field is not None else []
    for m in metas:
        for attr, sym in (("gt", ">"), ("ge", ">=")):
            if getattr(m, attr, None) is not None:
                lower = (sym, getattr(m, attr))
        for attr, sym in (("lt", "<"), ("le", "<=")):
            if getattr(m, attr, None) is not None:
                upper = (sym, getattr(m, attr))
    for attr, sym in (("gt", ">"), ("ge", ">=")):
        if attr in ctx and lower is None:
            lower = (sym, ctx[attr])
    for attr, sym in (("lt", "<"), ("le", "<=")):
        if attr in ctx and upper is None:
            upper = (sym, ctx[attr])

    def num(v: Any) -> str:
        if isinstance(v, float) and v.is_integer() and abs(v) < 1e15:
            return str(int(v))
        return show(v)

    if lower and upper:
        left = "(" if lower[0] == ">" else "["
        right = ")" if upper[0] == "<" else "]"
        return f"in {left}{num(lower[1])}, {num(upper[1])}{right}"
    if lower:
        return f"{lower[0]} {num(lower[1])}"
    if upper:
        return f"{upper[0]} {num(upper[1])}"
    return "in range"


_TYPE_WORDS = {
    "float_type": "a number",
    "float_parsing": "a number",
    "int_type": "an integer",
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "bool_type": "true or false",
    "bool_parsing": "true or false",
    "string_type": "a string",
    "list_type": "an array",
    "tuple_type": "an array",
    "set_type": "an array",
    "dict_type": "a table",
    "model_type": "a table",
    "model_attributes_type": "a table",
}


def _valid_keys(tp: Any) -> list[str]:
    tp = _unwrap(tp)
    if _is_model(tp):
        return list(tp.model_fields)
    return []


def _one(err: dict, root: Any, prefix: Loc, extra_keys: tuple[str, ...]) -> tuple[Loc, str]:
    kind = err["type"]
    ctx = err.get("ctx") or {}
    value = err.get("input")
    walk = _Walk(root, tuple(err["loc"]), keep_unmatched=kind == RULE_ERROR)
    parts = list(walk.parts)
    got = f"; got {_kind(value)}{show(value)}"

    if kind == RULE_ERROR:
        msg = err["msg"]
    elif kind == "extra_forbidden":
        key = str(parts[-1])
        parent = tuple(prefix) + tuple(parts[:-1])
        valid = _valid_keys(walk.parent) + (list(extra_keys) if len(parts) == 1 else [])
        where = f"in {_path_text(parent)}" if parent else "at the top level"
        hint = did_you_mean(key, valid) or (f"; allowed keys: {', '.join(valid)}" if valid else "")
        msg = f"unknown key {quote(key, 80)} {where}{hint}"
    elif kind == "missing":
        size = _fixed_tuple_len(walk.parent) if parts and isinstance(parts[-1], int) else None
        if size is not None:
            parts = parts[:-1]
            n = len(value) if isinstance(value, list | tuple) else "?"
            msg = f"must have exactly {size} items; got {n}: {show(value)}"
        else:
            desc = walk.field.description if walk.field is not None and walk.field.description else ""
            msg = f"required key '{parts[-1]}' is missing" + (f": {desc}" if desc else "")
    elif kind in _TYPE_WORDS:
        msg = f"expected {_TYPE_WORDS[kind]}{got}"
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        field = walk.field if parts and isinstance(parts[-1], str) else None
        msg = f"must be {_bounds(field, ctx)}{got}"
    elif kind == "literal_error":
        on_field = walk.field is not None and isinstance(parts[-1], str)
        choices = _literal_choices(walk.field.annotation if on_field else walk.leaf)
        allowed = ", ".join(f"'{c}'" for c in choices) if choices else ctx.get("expected", "?")
        msg = f"must be one of {allowed}; got {show(value)}{did_you_mean(str(value), choices)}"
    elif kind in ("too_short", "too_long"):
        size = _fixed_tuple_len(walk.leaf)
        actual = ctx.get("actual_length", len(value) if hasattr(value, "__len__") else "?")
        if size is not None:
            msg = f"must have exactly {size} items; got {actual}: {show(value)}"
        elif kind == "too_short":
            least = ctx.get("min_length")
            msg = f"needs at least {least} entr{'y' if least == 1 else 'ies'}; got {actual}"
        else:
            msg = f"accepts at most {ctx.get('max_length')} entries; got {actual}"
    elif kind in ("string_too_long", "string_too_short"):
        actual = f"{len(value):,}" if isinstance(value, str) else "?"
        if kind == "string_too_long":
            limit = ctx.get("max_length")
            msg = f"is {actual} characters long, more than the {limit:,} allowed; shorten it"
        else:
            msg = f"must be at least {ctx.get('min_length')} characters long; got {actual}"
    elif kind in ("union_tag_invalid", "union_tag_not_found"):
        disc = str(ctx.get("discriminator", "type")).strip("'")
        tags = []
        if _is_union(walk.leaf):
            for m in get_args(walk.leaf):
                tags += [t for t, f in _tags(m).items() if f == disc]
        allowed = ", ".join(f"'{t}'" for t in tags) or ctx.get("expected_tags", "?")
        parts.append(disc)
        if isinstance(value, dict) and disc in value:
            tag = value[disc]
            hint = did_you_mean(tag, tags) if isinstance(tag, str) else ""
            msg = f"must be one of {allowed}; got {show(tag)}{hint}"
        elif kind == "union_tag_invalid":
            tag = ctx.get("tag", "?")
            msg = f"must be one of {allowed}; got {quote(str(tag), 80)}{did_you_mean(str(tag), tags)}"
        else:
            msg = f"required key '{disc}' is missing (one of {allowed})"
    elif kind in ("value_error", "assertion_error"):
        msg = re.sub(r"^(Value error|Assertion failed), ", "", err["msg"])
    elif kind == "finite_number":
        msg = f"must be a finite number{got}"
    elif kind == "string_pattern_mismatch":
        msg = f"must match the pattern {ctx.get('pattern')}{got}"
    else:
        msg = f"{err['msg']}{got}"
    return tuple(prefix) + tuple(parts), msg


def translate(
    exc: ValidationError, root: Any, prefix: Loc = (), extra_keys: tuple[str, ...] = ()
) -> list[tuple[Loc, str]]:
    """Problems of a pydantic ValidationError raised by validating model ``root``.

    ``prefix`` is prepended to every location (for plugin sections, e.g. ``("boundaries", "cone")``);
    ``extra_keys`` are valid keys of the root table that the model itself does not know (``law`` in
    ``[contact]``), offered as suggestions for unknown keys.
    """
    out: dict[tuple[Loc, str], None] = {}
    errors = exc.errors(include_url=False)
    for err in errors[:MAX_TRANSLATED]:
        out[_one(err, root, prefix, extra_keys)] = None
    if len(errors) > MAX_TRANSLATED:
        rest = len(errors) - MAX_TRANSLATED
        out[(tuple(prefix), f"{rest:,} more problems of the same validation, not listed")] = None
    return list(out)


def sort_problems(problems: list[tuple[Loc, str]], data: Any) -> list[tuple[Loc, str]]:
    """Stable order: by top-level section, then by array index / table position in the deck."""

    def key(item: tuple[Loc, str]) -> tuple[int, int]:
        loc = item[0]
        head = str(loc[0]) if loc else ""
        rank = SECTION_ORDER.index(head) if head in SECTION_ORDER else len(SECTION_ORDER)
        sub = 0
        if len(loc) > 1:
            if isinstance(loc[1], int):
                sub = loc[1]
            elif isinstance(data, dict) and isinstance(data.get(head), dict):
                keys = list(data[head])
                sub = keys.index(loc[1]) if loc[1] in keys else len(keys)
        return rank, sub

    return sorted(problems, key=key)


def _path_text(loc: Loc | str) -> str:
    """A location as shown in a message: at most about :data:`QUOTE_LIMIT` characters (a key may be
    megabytes long, a path thousands of levels deep)."""
    if isinstance(loc, str):
        return clip(loc)
    if len(loc) > 12:  # the first levels and the last two
        head, tail = format_path(loc[:8]), format_path(loc[-2:])
        return clip(f"{clip(head)}.…({len(loc) - 10:,} levels)….{clip(tail, 60)}", 2 * QUOTE_LIMIT)
    return clip(format_path(tuple(clip(p, 80) if isinstance(p, str) else p for p in loc)), 2 * QUOTE_LIMIT)


def make_deck_error(problems: list[tuple[Loc, str]], source: str | None = None) -> DeckError:
    """One DeckError listing every problem, one per line; ``.problems`` = [(path, message), ...].
    A location is a key path, or a path already formatted (a string, e.g. another error's).

    Bounded whatever the deck holds: paths and messages are clipped (:mod:`pdem.textutil`), and at
    most :data:`MAX_LISTED_PROBLEMS` problems are listed, then how many more there are."""
    pairs = [(_path_text(loc), clip_middle(msg)) for loc, msg in problems]
    where = f"deck {quote(source)}" if source else "deck"
    count = f"{len(pairs):,} problem{'s' if len(pairs) != 1 else ''}"
    lines = [f"{where} is invalid ({count}):"]
    lines += [f"  {path}: {msg}" if path else f"  {msg}" for path, msg in pairs[:MAX_LISTED_PROBLEMS]]
    if len(pairs) > MAX_LISTED_PROBLEMS:
        lines.append(f"  … and {len(pairs) - MAX_LISTED_PROBLEMS:,} more problems (fix these first)")
    err = DeckError("\n".join(lines))
    err.problems = pairs  # type: ignore[attr-defined]
    return err


# -------------------------------------------------------------------------------------------------
# the shape of a deck: nesting depth and integer range, checked before anything walks it recursively
# -------------------------------------------------------------------------------------------------


def shape_problems(data: Any, prefix: Loc = ()) -> list[tuple[Loc, str]]:
    """Problems of a parsed deck's shape, found without recursion: nesting deeper than
    :data:`~pdem.deck.schema.MAX_DEPTH` levels (the deepest path is named) and integers outside
    TOML's 64-bit range (the first few). Both must be refused before the deck is copied or validated,
    which recurse (a 500-level deck exhausts Python's stack)."""
    problems: list[tuple[Loc, str]] = []
    entries: list[tuple[int, str | int]] = []  # (parent entry, key): to rebuild the deepest path
    deepest, deepest_entry = 0, -1
    stack: list[tuple[Any, int, int]] = [(data, 0, -1)]
    big_ints = 0
    seen: set[int] = set()  # containers already walked (a dict built in Python may hold itself)
    large = 0
    while stack:
        node, depth, entry = stack.pop()
        if depth > deepest:  # the deepest value: its key path's length
            deepest, deepest_entry = depth, entry
        if isinstance(node, dict | list | tuple):
            if id(node) in seen:
                continue
            seen.add(id(node))
        if isinstance(node, dict):
            items: Any = node.items()
        elif isinstance(node, list | tuple):
            items = enumerate(node)
        else:
            lo, hi = _INT_RANGE
            if isinstance(node, int) and not isinstance(node, bool) and not lo <= node <= hi:
                big_ints += 1
                if big_ints <= 5:
                    problems.append(
                        (
                            prefix + _rebuild(entries, entry),
                            f"{show(node)} is outside the 64-bit range of TOML integers "
                            "(-9223372036854775808 to 9223372036854775807); give a smaller number",
                        )
                    )
            continue
        if len(node) > MAX_ENTRIES:
            large += 1
            if large <= 5:
                what = "table has" if isinstance(node, dict) else "array has"
                problems.append(
                    (
                        prefix + _rebuild(entries, entry),
                        f"this {what} {len(node):,} entries, more than the {MAX_ENTRIES:,} a deck may hold "
                        "in one; particles belong in a packing file (source = 'file')",
                    )
                )
            continue
        for key, value in items:
            entries.append((entry, key))
            stack.append((value, depth + 1, len(entries) - 1))
    if deepest > MAX_DEPTH:
        path = prefix + _rebuild(entries, deepest_entry)
        problems.insert(
            0,
            (
                path,
                f"nested {deepest + len(prefix):,} levels deep (tables and arrays within each other), "
                f"more than the {MAX_DEPTH} a deck may have (a pdem deck needs about 6); flatten it, or "
                "check that this is the deck you meant",
            ),
        )
    return problems


def integer_digits_message(exc: ValueError) -> str | None:
    """Python's refusal to read an integer of more than 4,300 digits, as a deck message (else None)."""
    if "integer string conversion" not in str(exc):
        return None
    return (
        "an integer of more than 4,300 digits, outside the 64-bit range of TOML integers; give a "
        "smaller number"
    )


def _rebuild(entries: list[tuple[int, str | int]], entry: int) -> Loc:
    path: list[str | int] = []
    while entry >= 0:
        entry, key = entries[entry]
        path.append(key)
    return tuple(reversed(path))


_TOML_STRING_OR_COMMENT = re.compile(
    "|".join(
        (
            r'"""(?:[^"\\]|\\.|"(?!""))*(?:"""|\Z)',  # multi-line basic string
            r"'''.*?(?:'''|\Z)",  # multi-line literal string
            r'"(?:[^"\\\n]|\\.)*"?',  # basic string
            r"'[^'\n]*'?",  # literal string
            r"(?P<comment>#[^\n]*)",
        )
    ),
    re.S,
)
_BRACKET = re.compile(r"[\[\]{}]")


def _blank(m: re.Match) -> str:
    """A string as a bare word of the same length (a quoted key is a key), a comment as spaces; new
    lines kept, so that positions stay those of the text."""
    fill = " " if m.group("comment") is not None else "x"
    text = m.group()
    if "\n" not in text:
        return fill * len(text)
    return "\n".join(fill * len(part) for part in text.split("\n"))


def _dotted_chain(limit: int) -> re.Pattern:
    """More than ``limit`` dots between words: a dotted key of more than ``limit + 1`` parts (tried
    only at the start of a word, possessively: linear in the text)."""
    word = r"[A-Za-z0-9_+\-]"
    return re.compile(rf"(?<![A-Za-z0-9_+\-.])(?:{word}++[ \t]*+\.[ \t]*+){{{limit + 1}}}")


def toml_text_problem(text: str, limit: int = MAX_DEPTH) -> str | None:
    """What must be refused in TOML ``text`` before it is parsed at all: a dotted key of more than
    ``limit`` parts (the parser's memory grows with the square of its length). Fast: only lines
    with that many dots are looked at, and a hit is confirmed by :func:`toml_nesting_problem` (the
    dots may be in a string)."""
    if text.count(".") <= limit:
        return None
    chain = _dotted_chain(limit)
    for line in text.split("\n"):
        if line.count(".") > limit and chain.search(line):
            return toml_nesting_problem(text, limit)
    return None


def toml_nesting_problem(text: str, limit: int = MAX_DEPTH) -> str | None:
    """A message if TOML ``text`` nests arrays / inline tables more than ``limit`` deep, or has a
    dotted key of more than ``limit`` parts, naming the line and column; else None.

    Python's TOML parser recurses on nested arrays (10,000 levels exhaust the stack: this names
    where, once it has failed) and takes memory quadratic in a dotted key's length (100,000 parts
    exhaust the machine's: :func:`toml_text_problem` refuses them before parsing). Strings and
    comments are skipped; linear in the text."""
    if text.count("[") + text.count("{") <= limit and text.count(".") <= limit:
        return None
    code = _TOML_STRING_OR_COMMENT.sub(_blank, text)

    def where(pos: int) -> str:
        line = code.count("\n", 0, pos) + 1
        return f"at line {line:,}, column {pos - (code.rfind(chr(10), 0, pos) + 1) + 1:,}"

    depth = 0
    for m in _BRACKET.finditer(code):
        if m.group() in "[{":
            depth += 1
            if depth > limit:
                return (
                    f"{where(m.start())}: arrays or inline tables nested more than {limit} deep (a pdem "
                    "deck needs about 6); flatten it, or check that this is the deck you meant"
                )
        else:
            depth = max(depth - 1, 0)
    chain = _dotted_chain(limit).search(code)
    if chain is not None:
        return (
            f"{where(chain.start())}: a dotted key of more than {limit} parts "
            f"({quote(text[chain.start() : chain.end()], 60)}; a pdem deck needs about 6); shorten it, or "
            "check that this is the deck you meant"
        )
    return None
