"""Load a deck: read TOML, apply ``--set`` overrides, validate everything, return a ResolvedDeck.

Validation runs in full before anything else and reports every problem at once in one
:class:`~pdem.errors.DeckError` (``.problems`` = ``[(key path, message), ...]``):

1. TOML syntax (line and column);
2. ``--set`` overrides that cannot be parsed or applied;
3. the schema (:mod:`pdem.deck.schema`, pydantic strict JSON mode) with its rules and cross-checks
   (materials, stages and boundaries referred to by name exist, stage names unique, …);
4. the particle count and memory the sources need, against ``run.max_particles``
   (:mod:`pdem.deck.capacity`);
5. the plugin sections: the contact law named by ``contact.law``, the particle source named by each
   ``particles.N.source`` and the boundary plugin named by each ``boundaries.NAME.type`` must be
   installed (entry points), and their keys are validated by the plugin's own ``Params`` model,
   errors prefixed with the section's path; then the periodic box is checked against the sources'
   largest radius and extent.

A problem under a path that a ``--set`` override wrote is marked ``(from --set …)``.

Before any of that, the deck's shape is bounded (docs/deck.md, "Limits"): a deck file of at most
:data:`MAX_DECK_BYTES`, that is a regular file (not a directory, a device or a named pipe); no
dotted key or nesting of tables and arrays deeper than :data:`~pdem.deck.schema.MAX_DEPTH` levels,
no integer outside TOML's 64-bit range. Those are refused with one problem before the deck is copied
or validated, which recurse.
"""

from __future__ import annotations

import copy
import json
import math
import re
import tomllib
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from .. import plugins
from ..errors import PdemError, PluginError
from ..textutil import clip, file_problem, quote
from . import toml_writer
from .capacity import check_capacity
from .overrides import Override, apply_overrides
from .problems import (
    Loc,
    integer_digits_message,
    make_deck_error,
    shape_problems,
    show,
    sort_problems,
    toml_nesting_problem,
    toml_text_problem,
    translate,
)
from .schema import (
    KNOWN_WRITERS,
    MAX_DEPTH,
    MAX_MAGNITUDE,
    BoundaryEntry,
    ContactSection,
    Deck,
    OutputSection,
    Stage,
    did_you_mean,
    periodic_source_checks,
)

__all__ = ["ResolvedDeck", "load_deck", "validate_deck", "deck_json_schema", "installed_writers"]

DEFAULT_LAW = "hertz_mindlin"
#: largest deck file read [bytes]; a real deck is a few kB
MAX_DECK_BYTES = 64 * 1024 * 1024
_PLUGIN_LABEL = {
    "contact_laws": "contact law",
    "boundaries": "boundary type",
    "writers": "writer",
    "sources": "particle source",
}


@dataclass
class ResolvedDeck:
    """A validated deck.

    ``deck``: the validated :class:`~pdem.deck.schema.Deck` (``output.directory`` filled in; each entry
    of ``deck.particles`` is its source plugin's validated ``Params``);
    ``law_params``: the contact law's validated ``Params``; ``boundaries``: name → the boundary plugin's
    validated ``Params`` (deck order); ``law_class`` / ``boundary_classes`` / ``source_classes`` (one
    per ``[[particles]]`` table): the plugin classes;
    ``path``: the deck file (None for a deck given as a dict); ``base_dir``: the directory relative
    paths in the deck are resolved against; ``overrides``: the ``--set`` texts applied; ``step_key``:
    the deck key that gave ``run.dt`` (``contact.<law>.dt`` when the law's own table gave it).
    """

    deck: Deck
    law_params: BaseModel
    boundaries: dict[str, BaseModel]
    path: Path | None
    base_dir: Path
    law_class: type | None = None
    boundary_classes: dict[str, type] = field(default_factory=dict)
    overrides: tuple[str, ...] = ()
    source_classes: list[type] = field(default_factory=list)
    step_key: str = "run.dt"

    def make_law(self) -> Any:
        """A new instance of the contact law with the deck's parameters."""
        return self.law_class(**self.law_params.model_dump())

    def make_boundaries(self) -> dict[str, Any]:
        """New instances of every boundary plugin, by name, in deck order."""
        return {name: self.boundary_classes[name](name, params) for name, params in self.boundaries.items()}

    def make_sources(self) -> list[Any]:
        """New instances of the source plugin of every ``[[particles]]`` table, in deck order."""
        return [cls(params) for cls, params in zip(self.source_classes, self.deck.particles, strict=True)]

    def output_for(self, stage: str | int) -> OutputSection:
        """The ``[output]`` settings in force during ``stage`` (name or index), overrides applied."""
        st = self.stage(stage)
        return self.deck.output.merged(st.output)

    def stage(self, stage: str | int) -> Stage:
        if isinstance(stage, int):
            return self.deck.stages[stage]
        for st in self.deck.stages:
            if st.name == stage:
                return st
        raise KeyError(f"no stage named {stage!r}; stages: {self.deck.stage_names()}")

    def resolved_dict(self) -> dict[str, Any]:
        """The whole deck as plain data with defaults filled in (keys without a value left out)."""
        data = self.deck.model_dump(mode="json", exclude_none=True)
        data["particles"] = [{"source": p.pop("source"), **p} for p in data["particles"]]
        if not data.get("domain", {}).get("periodic"):  # no periodic axes: the section is its default
            data.pop("domain", None)
        # empty sections are their defaults; TOML would have to write them as `key = []` up front
        return {k: v for k, v in data.items() if v != [] and v != {}}

    def resolved_toml(self) -> str:
        """TOML text of :meth:`resolved_dict`; loading it gives an equivalent deck."""
        head = ["resolved pdem deck: every default filled in"]
        if self.path is not None:
            head.append(f"from: {self.path.resolve()}")
        head += [f"--set {o}" for o in self.overrides]
        return toml_writer.dumps(self.resolved_dict(), "\n".join(head))


# -------------------------------------------------------------------------------------------------
# entry points
# -------------------------------------------------------------------------------------------------


def load_deck(
    path: str | Path, overrides: Iterable[str] = (), *, writers: Collection[str] | None = None
) -> ResolvedDeck:
    """Read, override and validate the deck at ``path``; raise one DeckError listing every problem.

    ``overrides``: ``key.path=value`` texts (see :mod:`pdem.deck.overrides`). ``writers``: the output
    formats to accept (default: ``hdf5``, ``vtk`` and the installed ``pdem.writers`` entry points).
    """
    p = Path(path)
    text = _read_deck_text(p)
    problem = toml_text_problem(text)
    if problem is not None:
        raise make_deck_error([((), f"invalid deck {problem}")], str(p))
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise make_deck_error([((), _toml_message(exc))], str(p)) from None
    except RecursionError:
        where = toml_nesting_problem(text) or f"nested more than {MAX_DEPTH} levels deep"
        raise make_deck_error([((), f"invalid deck {where}")], str(p)) from None
    except (ValueError, MemoryError) as exc:  # e.g. an integer of more than 4,300 digits
        why = integer_digits_message(exc) if isinstance(exc, ValueError) else None
        raise make_deck_error([((), f"invalid TOML: {why or clip(str(exc))}")], str(p)) from None
    return validate_deck(data, path=p, overrides=overrides, writers=writers)


def _read_deck_text(p: Path) -> str:
    """The deck file's text: a regular file of at most :data:`MAX_DECK_BYTES`, UTF-8 (a BOM is
    dropped). Only the path is looked at before reading, so a FIFO or /dev/zero is refused, not
    read."""
    problem = file_problem(p)
    if problem is not None:
        raise make_deck_error([((), f"deck file {quote(str(p))} {problem}; give a deck file (TOML)")], str(p))
    try:
        with open(p, "rb") as fh:
            raw = fh.read(MAX_DECK_BYTES + 1)
    except OSError as exc:
        message = f"cannot read deck file {quote(str(p))}: {exc.strerror or exc}"
        raise make_deck_error([((), message)], str(p)) from None
    if len(raw) > MAX_DECK_BYTES:
        raise make_deck_error(
            [
                (
                    (),
                    f"deck file {quote(str(p))} is larger than {MAX_DECK_BYTES // 2**20} MB, the most pdem "
                    "reads (a deck is a few kB; particles belong in a packing file: source = 'file')",
                )
            ],
            str(p),
        )
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        message = (
            f"deck file {quote(str(p))} is not UTF-8 text (byte {exc.start:,}, line {line:,}); is it a "
            "deck? Save it as UTF-8"
        )
        raise make_deck_error([((), message)], str(p)) from None


def _toml_message(exc: tomllib.TOMLDecodeError) -> str:
    text = str(exc)
    m = re.search(r"\(at line (\d+), column (\d+)\)", text)
    if m:
        reason = text[: m.start()].strip()
        return f"invalid TOML at line {m.group(1)}, column {m.group(2)}: {reason}"
    return f"invalid TOML: {text}"


def installed_writers() -> list[str]:
    """Output formats accepted by default: the known built-ins plus installed pdem.writers entry points."""
    try:
        names = set(plugins.available("writers"))
    except Exception:  # noqa: BLE001 - a broken metadata entry must not stop validation
        names = set()
    return sorted(set(KNOWN_WRITERS) | names)


def validate_deck(
    data: dict[str, Any],
    *,
    path: str | Path | None = None,
    base_dir: str | Path | None = None,
    overrides: Iterable[str] = (),
    writers: Collection[str] | None = None,
) -> ResolvedDeck:
    """Validate a deck given as parsed TOML (``data`` is not modified); see :func:`load_deck`.

    ``base_dir`` (relative paths in the deck) defaults to the deck file's directory, or the current
    directory for a deck without a file.
    """
    p = Path(path) if path is not None else None
    source = str(p) if p is not None else None
    if not isinstance(data, dict):
        raise make_deck_error([((), f"a deck is a table of sections; got {type(data).__name__}")], source)
    shape = shape_problems(data)
    if shape:  # before anything recurses into it
        raise make_deck_error(shape, source)
    base = Path(base_dir) if base_dir is not None else (p.parent if p is not None else Path.cwd())
    base = base.resolve()
    data = copy.deepcopy(data)
    overrides = tuple(overrides)
    applied, problems = apply_overrides(data, overrides)
    shape = shape_problems(data)
    if shape:  # an override made the deck too deep (a long key path, a deeply nested value)
        raise make_deck_error(_mark_overrides(shape, applied), source)
    try:
        return _validate(data, p, base, overrides, applied, problems, writers)
    except RecursionError:  # a safety net: the shape checks above should make this impossible
        raise make_deck_error(
            [((), f"the deck is nested too deeply to validate; keep it within {MAX_DEPTH} levels")], source
        ) from None


def _validate(
    data: dict,
    p: Path | None,
    base: Path,
    overrides: tuple[str, ...],
    applied: list[Override],
    problems: list[tuple[Loc, str]],
    writers: Collection[str] | None,
) -> ResolvedDeck:
    allowed = tuple(writers) if writers is not None else tuple(installed_writers())
    context = {"base_dir": str(base), "writers": allowed}

    step_key, step_problems = _fold_law_steps(data, applied)
    problems += step_problems
    deck: Deck | None = None
    try:
        deck = Deck.model_validate(data, context=context)
    except ValidationError as exc:
        problems += translate(exc, Deck)

    law_class, law_params, law_problems = _validate_law(data)
    problems += law_problems
    if law_params is not None:
        problems += _validate_stage_contact(data, law_class, law_params)
    source_classes, sources, src_problems = _validate_sources(data, context)
    problems += src_problems
    boundary_classes, boundaries, bnd_problems = _validate_boundaries(data)
    problems += bnd_problems
    problems += _validate_per_rank_writers(data)
    problems += _capacity(data, base, problems)

    if problems:
        problems = _mark_overrides(_dedupe(problems), applied)
        source = str(p) if p is not None else None
        raise make_deck_error(sort_problems(problems, data), source)

    assert deck is not None and law_params is not None and len(sources) == len(deck.particles)
    # the plugin sections of the deck hold the validated parameters, defaults filled in
    deck.contact = ContactSection(law=deck.contact.law, **_plain(law_params))
    for name, params in boundaries.items():
        table = _plain(params)
        table.pop("type", None)
        deck.boundaries[name] = BoundaryEntry(type=deck.boundaries[name].type, **table)
    deck.particles = [sources[k] for k in range(len(sources))]
    if deck.output.directory is None:
        stem = p.stem if p is not None else "deck"
        deck.output.directory = f"out/{stem}"
    return ResolvedDeck(
        deck=deck,
        law_params=law_params,
        boundaries=boundaries,
        path=p,
        base_dir=base,
        law_class=law_class,
        boundary_classes=boundary_classes,
        overrides=overrides,
        source_classes=[source_classes[k] for k in range(len(sources))],
        step_key=step_key,
    )


#: the step keys a law's own table ([contact.<law>]) may give, for that law only
LAW_STEP_KEYS = ("dt", "dt_fraction")


def _fold_law_steps(data: dict, applied: list[Override]) -> tuple[str, list[tuple[Loc, str]]]:
    """``dt`` / ``dt_fraction`` in a ``[contact.<law>]`` table: the step of that law only, so that a deck
    carries each method's step and ``contact.law`` alone switches both (DEM-P at its stability
    estimate, DEM-C at the step its accuracy allows). They are taken out of every law's table (they are
    not the law's parameters); the selected law's are moved into ``[run]``, where the schema checks
    them as ``[run]``'s own. When ``[run]`` gives a step as well, a ``--set`` of one of the two wins
    (``--set run.dt=…`` steps a deck whose law table gives its step; the other is dropped); both in
    the deck file, or both set, is an error: the step is set in one place.
    Returns the deck key that gives the step (for messages) and the problems found."""

    def by_set(path: tuple) -> bool:
        return any(o.loc == path[: len(o.loc)] for o in applied)

    contact = data.get("contact")
    if not isinstance(contact, dict):
        return "run.dt", []
    law = contact.get("law", DEFAULT_LAW)
    known = set(plugins.available("contact_laws"))
    run = data.get("run", {})
    problems: list[tuple[Loc, str]] = []
    step_key = "run.dt"
    for name in [k for k, v in contact.items() if isinstance(v, dict) and k in known]:
        table = contact[name]
        given = {k: table.pop(k) for k in LAW_STEP_KEYS if k in table}
        if not given:
            continue
        used = "" if name == law else f" (used when contact.law = '{name}')"
        bad = False
        for k, v in given.items():
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and 0 < v <= 1e6
            if not ok:
                bad = True
                what = "[s]" if k == "dt" else "as a multiple of its stability estimate"
                problems.append(
                    (("contact", name, k), f"must be a number > 0 (the {name} law's time step {what}); "
                     f"got {show(v)}{used}")
                )
        if len(given) == 2:
            bad = True
            problems.append(
                (
                    ("contact", name, "dt_fraction"),
                    f"dt_fraction and dt are both given; give one: dt (seconds) or dt_fraction (a multiple "
                    f"of the law's stability estimate){used}",
                )
            )
        if name != law or bad or not isinstance(run, dict):
            continue
        clash = [k for k in LAW_STEP_KEYS if k in run]
        run_set = any(by_set(("run", k)) for k in clash)
        law_set = any(by_set(("contact", name, k)) for k in given)
        if clash and run_set != law_set:
            if run_set:
                continue  # --set run.dt=… steps this run; the law table's step is dropped
            for k in clash:
                del run[k]
            clash = []
        if clash:
            (mine, value), = given.items()
            problems.append(
                (
                    ("contact", name, mine),
                    f"contact.{name}.{mine} = {show(value)} and run.{clash[0]} = {show(run[clash[0]])} both "
                    f"set the time step; give it in one place: [run] for every contact law, "
                    f"[contact.{name}] for this law only",
                )
            )
            continue
        data.setdefault("run", run).update(given)
        step_key = f"contact.{name}.dt" if "dt" in given else "run.dt"
    return step_key, problems


# -------------------------------------------------------------------------------------------------
# plugin sections
# -------------------------------------------------------------------------------------------------


def _capacity(data: dict, base: Path, problems: list[tuple[Loc, str]]) -> list[tuple[Loc, str]]:
    """:func:`~pdem.deck.capacity.check_capacity`, which reads the raw deck: on values the schema
    refuses anyway (a radius of 1e-300, a path too long for the file system) it may fail; then its
    estimate is left out when other problems are reported, and is a problem itself otherwise."""
    try:
        return check_capacity(data, base)
    except (ArithmeticError, OSError, ValueError, TypeError, RuntimeError) as exc:
        if problems:
            return []
        return [
            (
                ("particles",),
                f"cannot estimate how many particles the sources make ({type(exc).__name__}: "
                f"{clip(str(exc))}); check the sizes, regions and packing files of [[particles]]",
            )
        ]


def _plain(params: BaseModel) -> dict[str, Any]:
    """A plugin's validated parameters as plain TOML-able data (unset optional keys left out)."""
    return params.model_dump(mode="json", exclude_none=True)


def _to_json(data: Any) -> str:
    return json.dumps(data, default=str, allow_nan=True)


def _load_plugin(group: str, name: str) -> tuple[Any, str | None]:
    """(class, None) or (None, message): an unknown name lists the installed plugins."""
    try:
        return plugins.load(group, name), None
    except PluginError as exc:
        try:
            installed = sorted(plugins.available(group))
        except PluginError as listing_error:  # e.g. a name registered by two distributions
            return None, str(listing_error)
        except Exception:  # noqa: BLE001
            installed = []
        if name in installed:
            return None, str(exc)
        label = _PLUGIN_LABEL.get(group, group)
        if group == "sources":  # pdem's own in the documented order, then the others by name
            from ..sources.builtin import BUILTIN_SOURCES

            own = [n for n in BUILTIN_SOURCES if n in installed]
            listing = ", ".join(f"'{n}'" for n in own + [n for n in installed if n not in own])
            return None, (
                f"unknown {label} {quote(name)}{did_you_mean(name, installed, True)}; must be one of "
                f"{listing or '(none)'} (the installed entry points of group pdem.sources). "
                "Install the package that provides it (pip install …) or fix the name"
            )
        listing = ", ".join(f"'{n}'" for n in installed) or "(none)"
        return None, (
            f"unknown {label} {quote(name)}{did_you_mean(name, installed, True)}; installed: {listing}. "
            "Install the package that provides it (pip install …) or fix the name"
        )


def _non_finite(value: Any, loc: Loc) -> list[tuple[Loc, str]]:
    """Plugin models may accept inf/nan, or numbers too large for any product or square of them to
    stay finite; a deck never does (the first few such numbers of a table are reported)."""
    return _bad_numbers(value, loc)[0]


def _bad_numbers(value: Any, loc: Loc) -> tuple[list[tuple[Loc, str]], bool]:
    """(problems, whether a number is too large): non-finite numbers, and numbers larger in
    magnitude than MAX_MAGNITUDE, the first few. Too large a number is refused before the plugin's
    validators compute with it (they would overflow)."""
    out: list[tuple[Loc, str]] = []
    too_large = False
    stack: list[tuple[Any, Loc]] = [(value, loc)]
    while stack and len(out) < 5:
        item, where = stack.pop()
        if isinstance(item, float) and not math.isfinite(item):
            out.append((where, f"must be a finite number; got {show(item)}"))
        elif isinstance(item, int | float) and not isinstance(item, bool) and abs(item) > MAX_MAGNITUDE:
            too_large = True
            out.append(
                (
                    where,
                    f"{show(item)} is larger in magnitude than {MAX_MAGNITUDE:.0e}, the most pdem accepts "
                    "in a plugin's table: squares and products of such numbers overflow double precision",
                )
            )
        elif isinstance(item, dict):
            stack += [(v, where + (k,)) for k, v in reversed(list(item.items()))]
        elif isinstance(item, list):
            stack += [(v, where + (k,)) for k, v in reversed(list(enumerate(item)))]
    return out, too_large


def _params_model(cls: Any, loc: Loc, what: str) -> tuple[type[BaseModel] | None, list[tuple[Loc, str]]]:
    params = getattr(cls, "Params", None)
    if isinstance(params, type) and issubclass(params, BaseModel):
        return params, []
    return None, [
        (
            loc,
            f"{what} {cls!r} has no pydantic Params model; it does not honour the plugin "
            "contract (report this to its author)",
        )
    ]


def _validate_law(data: dict) -> tuple[type | None, BaseModel | None, list[tuple[Loc, str]]]:
    raw = data.get("contact", {})
    if not isinstance(raw, dict):
        return None, None, []  # the schema reports it
    law = raw.get("law", DEFAULT_LAW)
    if not isinstance(law, str):
        return None, None, []
    cls, err = _load_plugin("contact_laws", law)
    if err is not None:
        return None, None, [(("contact", "law"), err)]
    model, problems = _params_model(cls, ("contact", "law"), f"contact law '{law}'")
    if model is None:
        return cls, None, problems
    # [contact.<law>] tables hold one law's parameters, so that a deck can carry those of both
    # methods and switch with the one key contact.law; the selected law's table joins the top level
    known = set(plugins.available("contact_laws"))
    # the other laws' tables are checked for unknown keys now, not only once the deck switches law
    unused = _unused_law_tables(raw, law, known)
    values: dict = {}
    for k, v in raw.items():
        if k == "law" or (isinstance(v, dict) and k in known and k != law):
            continue
        if isinstance(v, dict) and k == law:
            clash = sorted(set(v) & {key for key in raw if key not in known and key != "law"})
            if clash:
                return (
                    cls,
                    None,
                    [
                        (
                            ("contact", law, clash[0]),
                            f"given both in [contact] and in [contact.{law}]; keep one",
                        )
                    ],
                )
            values.update(v)
        else:
            values[k] = v
    table = raw.get(law) if isinstance(raw.get(law), dict) else {}

    def where(found: list[tuple[Loc, str]]) -> list[tuple[Loc, str]]:
        # a key given in [contact.<law>] is named there, as the deck (or --set) wrote it
        named = [(len(loc) > 1 and loc[0] == "contact" and loc[1] in table, loc, msg) for loc, msg in found]
        return [(("contact", law, *loc[1:]) if mine else loc, msg) for mine, loc, msg in named]

    problems = unused + where(_non_finite(values, ("contact",)))
    try:
        params = model.model_validate_json(_to_json(values), strict=True)
    except ValidationError as exc:
        return cls, None, problems + where(translate(exc, model, ("contact",), extra_keys=("law",)))
    if problems:
        return cls, None, problems
    try:  # the law's constructor may check combinations of parameters
        cls(**params.model_dump())
    except PdemError as exc:
        return cls, None, [(("contact",), str(exc))]
    except Exception as exc:  # noqa: BLE001 - a plugin's constructor failing is reported like a bad key
        return (
            cls,
            None,
            [(("contact",), f"contact law '{law}' rejected its parameters: {type(exc).__name__}: {exc}")],
        )
    return cls, params, []


def stage_contact_values(table: dict, law: str, known: set[str] | None = None) -> dict[str, Any]:
    """The law settings a stage's ``[stages.contact]`` table gives law ``law``: its own keys and those
    of its ``[stages.contact.<law>]`` table (the tables of other laws are left out)."""
    if known is None:
        known = set(plugins.available("contact_laws"))
    out: dict[str, Any] = {}
    for k, v in table.items():
        if isinstance(v, dict) and k in known:
            if k == law:
                out.update(v)
        else:
            out[k] = v
    return out


def _validate_stage_contact(data: dict, cls: type, params: BaseModel) -> list[tuple[Loc, str]]:
    """``[stages.contact]``: only the law's resumable settings, valid with the rest of [contact]; the
    tables of other laws only with their own resumable keys (checked once the deck switches law)."""
    stages = data.get("stages")
    if not isinstance(stages, list):
        return []
    law = data.get("contact", {}).get("law", DEFAULT_LAW)
    known = set(plugins.available("contact_laws"))
    problems: list[tuple[Loc, str]] = []
    base = _plain(params)
    for i, stage in enumerate(stages):
        table = stage.get("contact") if isinstance(stage, dict) else None
        if not isinstance(table, dict) or not table:
            continue
        loc0 = ("stages", i, "contact")
        non_finite = _non_finite(table, loc0)
        if non_finite:
            problems += non_finite
            continue
        for name in sorted(k for k, v in table.items() if isinstance(v, dict) and k in known and k != law):
            other, err = _load_plugin("contact_laws", name)
            other_params = getattr(other, "Params", None)
            allowed = None if err is not None else getattr(other_params, "resumable", frozenset())
            for key in sorted(table[name]) if allowed is not None else []:
                if key not in allowed:
                    problems.append(((*loc0, name, key), _stage_key_message(name, allowed)))
        values = stage_contact_values(table, law, known)
        allowed = frozenset(getattr(cls.Params, "resumable", frozenset()))
        bad = [k for k in values if k not in allowed]
        for key in bad:
            in_table = isinstance(table.get(law), dict) and key in table[law]
            where = (*loc0, law, key) if in_table else (*loc0, key)
            problems.append((where, _stage_key_message(law, allowed)))
        if bad:
            continue
        merged = {**base, **values}
        try:
            cls.Params.model_validate_json(_to_json(merged), strict=True)
        except ValidationError as exc:
            own = table.get(law) if isinstance(table.get(law), dict) else {}
            for loc, msg in translate(exc, cls.Params, loc0):
                key = loc[len(loc0)] if len(loc) > len(loc0) else None
                if key in own:  # given in [stages.contact.<law>]: name that table
                    loc = (*loc0, law, *loc[len(loc0) :])
                problems.append((loc, msg))
    return problems


def _stage_key_message(law: str, allowed: frozenset[str]) -> str:
    if not allowed:
        return f"contact law '{law}' has no settings a stage can change; set them in [contact] (whole run)"
    return (
        f"not a setting of contact law '{law}' that a stage can change; a stage can change: "
        f"{', '.join(sorted(allowed))} (the rest of [contact] holds for the whole run)"
    )


def _unused_law_tables(raw: dict, law: str, known: set[str]) -> list[tuple[Loc, str]]:
    """Unknown keys and invalid values in the tables of the laws the deck does not select
    ([contact.complementarity] of a DEM-P deck): they would otherwise surface only after ``--set
    contact.law=…``."""
    problems: list[tuple[Loc, str]] = []
    for name in sorted(k for k, v in raw.items() if isinstance(v, dict) and k in known and k != law):
        cls, err = _load_plugin("contact_laws", name)
        if err is not None:
            continue
        model, _ = _params_model(cls, ("contact", name), f"contact law '{name}'")
        if model is None:
            continue
        fields = list(model.model_fields)
        unknown = [key for key in raw[name] if key not in fields]
        for key in unknown:
            hint = did_you_mean(key, fields)
            problems.append((("contact", name, key), f"unknown key '{key}' in contact.{name}{hint}"))
        if unknown:
            continue
        # and their values, which would otherwise fail only once the deck runs that law
        found = _non_finite(raw[name], ("contact", name))
        try:
            model.model_validate_json(_to_json(raw[name]), strict=True)
        except ValidationError as exc:
            found += translate(exc, model, ("contact", name))
        problems += [(loc, f"{msg} (used when contact.law = '{name}')") for loc, msg in found]
    return problems


def _validate_per_rank_writers(data: dict) -> list[tuple[Loc, str]]:
    """With ``output.parallel = "per_rank"``, every writer in ``output.formats`` must support it."""
    out = data.get("output")
    if not isinstance(out, dict) or out.get("parallel") != "per_rank":
        return []
    formats = out.get("formats", ["hdf5"])
    if not isinstance(formats, list):
        return []  # the schema reports it
    problems: list[tuple[Loc, str]] = []
    for k, fmt in enumerate(formats):
        if not isinstance(fmt, str):
            continue
        cls, err = _load_plugin("writers", fmt)
        if err is not None:
            continue  # an unknown format is reported by the schema, a broken one when the run starts
        if not getattr(cls, "supports_per_rank", False):
            problems.append(
                (
                    ("output", "formats", k),
                    f"writer '{fmt}' cannot write per-rank files, which output.parallel = \"per_rank\" "
                    f'asks for; use parallel = "auto" (gathers output for the writers that need it) '
                    f"or \"gather\", or remove '{fmt}' from formats",
                )
            )
    return problems


def _validate_sources(
    data: dict, context: dict
) -> tuple[dict[int, type], dict[int, BaseModel], list[tuple[Loc, str]]]:
    """Each ``[[particles]]`` table validated by the ``Params`` of the source plugin it names (by the
    table's index); then the periodic-box checks that need the sources' sizes and extents."""
    from ..sources.api import SourceParams

    raw = data.get("particles", [])
    classes: dict[int, type] = {}
    params: dict[int, BaseModel] = {}
    problems: list[tuple[Loc, str]] = []
    if not isinstance(raw, list):
        return classes, params, problems
    for k, table in enumerate(raw):
        if not isinstance(table, dict) or not isinstance(table.get("source"), str):
            continue  # the schema reports a missing / non-string source
        loc: Loc = ("particles", k)
        name = table["source"]
        cls, err = _load_plugin("sources", name)
        if err is not None:
            problems.append((loc + ("source",), err))
            continue
        model, bad = _params_model(cls, loc + ("source",), f"particle source '{name}'")
        if model is not None and not issubclass(model, SourceParams):
            bad = [
                (
                    loc + ("source",),
                    f"particle source '{name}' {cls!r}: its Params does not derive from "
                    "pdem.sources.api.SourceParams; it does not honour the plugin contract (report this "
                    "to its author)",
                )
            ]
            model = None
        problems += bad
        if model is None:
            continue
        nonfinite, too_large = _bad_numbers(table, loc)
        if too_large:  # refused before the plugin's validators compute with such numbers
            problems += nonfinite
            continue
        try:  # like the deck's own models: Python mode, strictness from the Strict-annotated types
            p = model.model_validate(copy.deepcopy(table), context=context)
        except ValidationError as exc:
            problems += nonfinite + translate(exc, model, loc)
            continue
        if nonfinite:
            problems += nonfinite
            continue
        classes[k] = cls
        params[k] = p
    extents: dict[int, tuple[float | None, Any, str | None]] = {}
    for k, p in params.items():
        try:
            source = classes[k](p)
            key = "region" if "region" in type(p).model_fields else None
            extents[k] = (source.r_max(), source.bounds(), key)
        except Exception as exc:  # noqa: BLE001 - a plugin's hook failing is reported like a bad key
            problems.append(
                (
                    ("particles", k),
                    f"particle source '{p.source}' failed to report its size or extent: "
                    f"{type(exc).__name__}: {clip(str(exc))}",
                )
            )
    problems += periodic_source_checks(data, extents)
    return classes, params, problems


def _validate_boundaries(data: dict) -> tuple[dict[str, type], dict[str, BaseModel], list[tuple[Loc, str]]]:
    raw = data.get("boundaries", {})
    classes: dict[str, type] = {}
    params: dict[str, BaseModel] = {}
    problems: list[tuple[Loc, str]] = []
    if not isinstance(raw, dict):
        return classes, params, problems
    for name, table in raw.items():
        if not isinstance(table, dict) or not isinstance(table.get("type"), str):
            continue  # the schema reports a missing / non-string type
        loc: Loc = ("boundaries", name)
        cls, err = _load_plugin("boundaries", table["type"])
        if err is not None:
            problems.append((loc + ("type",), err))
            continue
        model, bad = _params_model(cls, loc + ("type",), f"boundary type '{table['type']}'")
        problems += bad
        if model is None:
            continue
        values = dict(table)
        if "type" not in model.model_fields:
            values.pop("type")
        nonfinite, too_large = _bad_numbers(values, loc)
        if too_large:  # refused before the plugin's validators compute with such numbers
            problems += nonfinite
            continue
        try:
            p = model.model_validate_json(_to_json(values), strict=True)
        except ValidationError as exc:
            extra = () if "type" in model.model_fields else ("type",)
            problems += nonfinite + translate(exc, model, loc, extra_keys=extra)
            continue
        if nonfinite:
            problems += nonfinite
            continue
        classes[name] = cls
        params[name] = p
    problems += _check_quantities(data, classes)
    return classes, params, problems


def _check_quantities(data: dict, classes: dict[str, type]) -> list[tuple[Loc, str]]:
    """``<boundary>.<key>``: if the boundary class declares ``measurement_keys``, the key must be one."""
    out: list[tuple[Loc, str]] = []
    stages = data.get("stages")
    if not isinstance(stages, list):
        return out
    for k, stage in enumerate(stages):
        end = stage.get("end") if isinstance(stage, dict) else None
        q = end.get("quantity") if isinstance(end, dict) else None
        if not isinstance(q, str) or "." not in q:
            continue
        name, key = q.split(".", 1)
        keys = getattr(classes.get(name), "measurement_keys", None)
        if keys and key not in keys:
            out.append(
                (
                    ("stages", k, "end", "quantity"),
                    f"boundary '{name}' measures no '{key}'{did_you_mean(key, list(keys), True)}; "
                    "it measures " + ", ".join(f"'{x}'" for x in keys),
                )
            )
    return out


def _dedupe(problems: list[tuple[Loc, str]]) -> list[tuple[Loc, str]]:
    return list(dict.fromkeys(problems))


def _mark_overrides(problems: list[tuple[Loc, str]], applied: list[Override]) -> list[tuple[Loc, str]]:
    out = []
    for loc, msg in problems:
        src = [o.text for o in applied if tuple(loc[: len(o.loc)]) == o.loc]
        out.append((loc, f"{msg} (from --set {clip(src[-1], 100)})" if src else msg))
    return out


# -------------------------------------------------------------------------------------------------
# JSON Schema for editors
# -------------------------------------------------------------------------------------------------


def deck_json_schema(builtin_only: bool = False) -> dict[str, Any]:
    """JSON Schema (draft 2020-12) of a deck, for editors (e.g. Taplo / Even Better TOML).

    ``[contact]``, ``[[particles]]`` and ``[boundaries.NAME]`` are open objects in the core schema; for
    every installed contact law, particle source and boundary plugin (only pdem's own with
    ``builtin_only``) an ``if``/``then`` clause adds the plugin's own parameter schema, selected by
    ``law`` / ``source`` / ``type``.
    """
    from pydantic.json_schema import models_json_schema

    laws: dict[str, type[BaseModel]] = {}
    bnds: dict[str, type[BaseModel]] = {}
    srcs: dict[str, type[BaseModel]] = {}
    for group, target in (("contact_laws", laws), ("boundaries", bnds), ("sources", srcs)):
        for name, info in sorted(plugins.available(group).items()):
            if builtin_only and info.distribution != "pdem":
                continue
            try:
                cls = plugins.load(group, name)
            except PluginError:
                continue
            model = getattr(cls, "Params", None)
            if isinstance(model, type) and issubclass(model, BaseModel):
                target[name] = model
    models = [Deck, *laws.values(), *srcs.values(), *bnds.values()]
    unique = list(dict.fromkeys(models))
    keys, top = models_json_schema(
        [(m, "validation") for m in unique], ref_template="#/$defs/{model}", title="pdem deck"
    )
    defs = top["$defs"]

    def ref(model: type[BaseModel]) -> dict:
        return keys[(model, "validation")]

    root = copy.deepcopy(defs[ref(Deck)["$ref"].rsplit("/", 1)[-1]])
    contact_name = root["properties"]["contact"].get("$ref", "").rsplit("/", 1)[-1]
    if contact_name in defs:
        contact = defs[contact_name]
        contact["properties"]["law"]["examples"] = sorted(laws) or [DEFAULT_LAW]
        clauses = []
        for name, model in laws.items():
            # the law's Params forbids unknown keys; [contact] adds `law` to them
            then = copy.deepcopy(defs[ref(model)["$ref"].rsplit("/", 1)[-1]])
            then.pop("title", None)
            then.setdefault("properties", {})["law"] = {"const": name}
            clauses.append({"if": {"properties": {"law": {"const": name}}}, "then": then})
        if clauses:
            contact["allOf"] = clauses
    items = root["properties"]["particles"].get("items", {})
    items_name = items.get("$ref", "").rsplit("/", 1)[-1]
    if items_name in defs:
        pdef = defs[items_name]
        pdef["properties"]["source"]["examples"] = sorted(srcs)
        pdef["allOf"] = [
            {"if": {"properties": {"source": {"const": name}}}, "then": ref(model)}
            for name, model in srcs.items()
        ]
    entry = root["properties"]["boundaries"].get("additionalProperties", {})
    entry_name = entry.get("$ref", "").rsplit("/", 1)[-1]
    if entry_name in defs:
        bdef = defs[entry_name]
        bdef["properties"]["type"]["examples"] = sorted(bnds)
        bdef["allOf"] = [
            {"if": {"properties": {"type": {"const": name}}}, "then": ref(model)}
            for name, model in bnds.items()
        ]
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "pdem deck",
        "description": (Deck.__doc__ or "").strip(),
    }
    schema.update({k: v for k, v in root.items() if k not in ("title", "description")})
    schema["$defs"] = {k: v for k, v in defs.items() if k != ref(Deck)["$ref"].rsplit("/", 1)[-1]}
    return schema
