"""The study spec: one deck, series of ``--set`` overrides (a grid each), quantities and references.

A spec is a TOML file::

    title = "Hopper: speed against accuracy"
    deck = "../inputs/hopper.toml"          # relative to the spec file
    output = "out/study/hopper"             # relative to the current directory
    ranks = 1                               # MPI ranks of each run (mpiexec -n RANKS)
    jobs = 1                                # runs at a time
    timeout = 3600                          # s per run; a run past it is stopped and marked "timeout"
    time = "run"                            # wall time charted: "run" (summary.json) or "process"
    set = { "stages.discharge.end.max_time" = 4.0 }   # overrides of every run

    [quantities.flow_rate]                  # measured quantities, from each run's summary.json
    path = "results.hopper.flow_rate"
    reference = { finest = "dem_p", by = "run.dt_fraction" }   # or { value = …, source = "…" },
    tolerance = 0.02                        #    or { series = "reference" } (mean of its runs)

    [[series]]                              # one grid of runs: set (fixed) × vary (product)
    name = "dem_p"
    set = { "contact.law" = "hertz_mindlin" }
    vary = { "run.dt_fraction" = [0.05, 0.1, 0.2, 0.4] }

    [stability]                             # optional: a stability map of these two knobs (or several,
                                            #   as [[stability]] with a name each)
    x = "run.dt_fraction"
    y = "series"
    drift = 0.01

    [crossover]                             # optional: wall time against a stiffness knob, DEM-P's runs
    x = "materials.glass.youngs_modulus"    #   (series varying x; zip = true varies several keys as one)
    penalty = ["dem_p_stiffness"]           #   with a fitted power law, DEM-C's as one line, and where
    rigid = ["dem_c"]                       #   they cross
    extend_to = 7.0e10

Everything is validated before any run starts; an error names the key, the value and the remedy.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ..deck.overrides import OverrideError, apply_overrides, parse_override
from ..deck.toml_writer import value as toml_value
from ..errors import InputError

__all__ = ["StudySpec", "RunPlan", "Crossover", "load_spec", "plan_runs", "method_label"]

_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class Reference(_Model):
    """What a quantity's error is taken against: a value (closed form or published, with its
    source), the mean of a series' runs, or the finest run of a series (smallest ``by``, or largest
    with ``largest = true``)."""

    value: float | None = None
    source: str | None = None
    series: str | None = None
    finest: str | None = None
    by: str | None = None
    largest: bool = False

    @model_validator(mode="after")
    def _one_kind(self) -> Reference:
        kinds = [k for k in ("value", "series", "finest") if getattr(self, k) is not None]
        if len(kinds) != 1:
            raise ValueError(
                "give exactly one of value (with source), series (the mean of that series' runs) or finest "
                "(a series, with by = the knob whose smallest value is the finest run); "
                f"got {kinds or 'none'}"
            )
        if self.value is not None and not self.source:
            raise ValueError('a reference value needs its source (source = "closed form …" or a citation)')
        if self.finest is not None and not self.by:
            raise ValueError('finest needs by = the knob that orders the runs (e.g. "run.dt_fraction")')
        return self


class Quantity(_Model):
    """A measured quantity: a number in summary.json (``path``), or a column of the run's series CSVs
    (``column``, of ``stage`` or of every stage in order) reduced to one number (``reduce``: the last
    row, or the mean / max / min over the last ``window`` fraction of the rows)."""

    path: str | None = Field(None, description="dotted path into summary.json, e.g. results.hopper.flow_rate")
    column: str | None = Field(None, description="a series column, e.g. box.zlo.fz")
    stage: str | None = None
    reduce: Literal["last", "mean", "max", "min"] = "last"
    window: float = Field(1.0, gt=0, le=1)
    reference: Reference
    relative: bool = True
    tolerance: float = Field(0.02, gt=0, description="the accuracy a run must reach to count as accurate")

    @model_validator(mode="after")
    def _source(self) -> Quantity:
        if (self.path is None) == (self.column is None):
            raise ValueError("give one of path (into summary.json) or column (of the series CSVs)")
        return self

    @property
    def label(self) -> str:
        if self.path is not None:
            return self.path
        where = f"series_{self.stage}.csv" if self.stage else "series"
        return f"{self.reduce} of {self.column} ({where})"


class Series(_Model):
    name: str
    set: dict[str, Any] = Field(default_factory=dict)
    vary: dict[str, list[Any]] = Field(default_factory=dict)
    zip: bool = Field(
        False,
        description="take the vary lists together, value k of each in run k (lists of one length), "
        "instead of every combination: e.g. the grains' and the walls' Young's modulus varied as one",
    )

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not _NAME.match(v):
            raise ValueError(f"series name {v!r}: use letters, digits, _ and - (starting with a letter)")
        return v

    @field_validator("vary")
    @classmethod
    def _lists(cls, v: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for key, values in v.items():
            if not values:
                raise ValueError(f"vary.{key} is an empty list; give at least one value")
            if len({toml_value(x) for x in values}) != len(values):
                raise ValueError(f"vary.{key} = {values!r} lists a value twice")
        return v

    @model_validator(mode="after")
    def _zipped(self) -> Series:
        lengths = {key: len(values) for key, values in self.vary.items()}
        if self.zip and len(set(lengths.values())) > 1:
            raise ValueError(f"zip = true takes the vary lists together; give them one length: {lengths}")
        return self

    def combinations(self) -> list[tuple[tuple[str, Any], ...]]:
        """The varied (key, value) pairs of each run, in order."""
        keys = list(self.vary)
        if not keys:
            return [()]
        lists = [self.vary[k] for k in keys]
        combos = zip(*lists, strict=True) if self.zip else itertools.product(*lists)
        return [tuple(zip(keys, combo, strict=True)) for combo in combos]


class Stability(_Model):
    """A stability map: each run placed at (x, y) and marked by its class (stable, drift, failed, …).
    ``x``/``y`` are knobs, ``"series"``, or ``"dt_ratio"`` (dt / the law's stability estimate);
    ``series`` limits the map to some series; ``name`` names its files (``stability_<name>``)."""

    name: str | None = None
    x: str
    y: str = "series"
    series: list[str] | None = None
    drift: float = Field(0.01, gt=0, description="relative change from the reference that counts as drift")
    quantity: str | None = None


class Crossover(_Model):
    """Which method for which stiffness: the wall time of each run of the penalty series (DEM-P, at
    each value of ``x`` with its own stable step) against ``x``, a power law fitted through them and
    extended to ``extend_to``, and the rigid series (DEM-C, whose grains do not depend on ``x``) as
    one line; where the two cross is the stiffness above which the rigid method is cheaper. Each
    run is marked by whether it is within the quantity's tolerance of its reference. ``marks``:
    named values of ``x`` drawn on the chart (e.g. glass at 6.3e10 Pa)."""

    name: str | None = None
    x: str
    quantity: str | None = None
    penalty: list[str] = Field(min_length=1)
    rigid: list[str] = Field(min_length=1)
    extend_to: float | None = Field(None, gt=0)
    marks: dict[str, float] = Field(default_factory=dict)

    @field_validator("marks")
    @classmethod
    def _positive_marks(cls, v: dict[str, float]) -> dict[str, float]:
        bad = {k: x for k, x in v.items() if not x > 0}
        if bad:
            raise ValueError(f"marks must be stiffnesses > 0 (the chart is log-log); got {bad}")
        return v


class StudySpec(_Model):
    title: str = ""
    deck: Path
    output: Path
    ranks: int = Field(1, ge=1, le=64)
    jobs: int = Field(1, ge=1, le=64)
    timeout: float | None = Field(None, gt=0)
    time: Literal["run", "process"] = "run"
    set: dict[str, Any] = Field(default_factory=dict)
    quantities: dict[str, Quantity]
    series: list[Series] = Field(min_length=1)
    stability: Stability | list[Stability] | None = None
    crossover: Crossover | list[Crossover] | None = None
    check_finite: bool = Field(True, description="scan failed runs' HDF5 files for non-finite values")

    @model_validator(mode="after")
    def _cross(self) -> StudySpec:
        names = [s.name for s in self.series]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"series named more than once: {dup}")
        if not self.quantities:
            raise ValueError("at least one [quantities.NAME] is needed")
        for qname, q in self.quantities.items():
            ref = q.reference
            target = ref.series or ref.finest
            if target is not None and target not in names:
                raise ValueError(
                    f"quantities.{qname}.reference names series {target!r}, which is not one of {names}"
                )
            if ref.finest is not None:
                s = next(s for s in self.series if s.name == ref.finest)
                if ref.by not in s.vary and ref.by not in s.set and ref.by not in self.set:
                    raise ValueError(
                        f"quantities.{qname}.reference.by = {ref.by!r} is not a key set or varied in series "
                        f"{ref.finest!r}"
                    )
        for k, st in enumerate(self.maps):
            if st.quantity is not None and st.quantity not in self.quantities:
                raise ValueError(
                    f"stability[{k}].quantity = {st.quantity!r} is not one of {list(self.quantities)}"
                )
            for name in st.series or []:
                if name not in names:
                    raise ValueError(f"stability[{k}].series names {name!r}, which is not one of {names}")
        stems = [st.name or "" for st in self.maps]
        if len(set(stems)) != len(stems):
            raise ValueError("give each [[stability]] map its own name")
        for k, cx in enumerate(self.crossovers):
            if cx.quantity is not None and cx.quantity not in self.quantities:
                raise ValueError(
                    f"crossover[{k}].quantity = {cx.quantity!r} is not one of {list(self.quantities)}"
                )
            for role in ("penalty", "rigid"):
                for name in getattr(cx, role):
                    if name not in names:
                        raise ValueError(f"crossover[{k}].{role} names {name!r}, which is not one of {names}")
            for name in cx.penalty:
                s = next(s for s in self.series if s.name == name)
                if cx.x not in s.vary:
                    raise ValueError(
                        f"crossover[{k}].x = {cx.x!r} is not varied in penalty series {name!r}: the chart "
                        "needs its runs at several values of x"
                    )
        stems = [cx.name or "" for cx in self.crossovers]
        if len(set(stems)) != len(stems):
            raise ValueError("give each [[crossover]] chart its own name")
        return self

    @property
    def crossovers(self) -> list[Crossover]:
        """The crossover charts (none, one or several)."""
        if self.crossover is None:
            return []
        return self.crossover if isinstance(self.crossover, list) else [self.crossover]

    @property
    def maps(self) -> list[Stability]:
        """The stability maps (none, one or several)."""
        if self.stability is None:
            return []
        return self.stability if isinstance(self.stability, list) else [self.stability]

    @property
    def primary(self) -> str:
        return next(iter(self.quantities))


@dataclass(frozen=True)
class RunPlan:
    """One run of a study: its series, its overrides (spec-wide, then the series' fixed keys, then its
    varied keys) and its directory."""

    series: str
    sets: tuple[tuple[str, Any], ...]
    varied: tuple[tuple[str, Any], ...]
    directory: Path
    method: str = ""
    knobs: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def name(self) -> str:
        return f"{self.series}/{self.directory.name}"

    def set_args(self) -> list[str]:
        """The ``--set KEY=VALUE`` texts of this run."""
        return [f"{k}={toml_value(v)}" for k, v in self.sets]


def _slug(varied: tuple[tuple[str, Any], ...]) -> str:
    if not varied:
        return "run"
    parts = []
    for key, v in varied:
        text = toml_value(v).strip('"')
        parts.append(f"{key.split('.')[-1]}={text}")
    slug = re.sub(r"[^A-Za-z0-9_.=+-]+", "-", "_".join(parts)).strip("-")
    if len(slug) > 80:
        digest = hashlib.sha256(repr(varied).encode()).hexdigest()[:10]
        slug = f"{slug[:60]}-{digest}"
    return slug


def method_label(law: str) -> str:
    """DEM-P for the penalty law, DEM-C for complementarity, else the law's name."""
    return {"hertz_mindlin": "DEM-P", "complementarity": "DEM-C"}.get(law, law)


def _law_of(raw_deck: dict, sets: tuple[tuple[str, Any], ...]) -> str:
    texts = [f"{k}={toml_value(v)}" for k, v in sets if k.split(".")[0] == "contact"]
    deck = copy.deepcopy(raw_deck)
    _, problems = apply_overrides(deck, texts)
    if problems:
        raise OverrideError("; ".join(msg for _, msg in problems))
    contact = deck.get("contact", {})
    law = contact.get("law", "hertz_mindlin") if isinstance(contact, dict) else "hertz_mindlin"
    return str(law)


def plan_runs(spec: StudySpec) -> list[RunPlan]:
    """Every run of the spec, in order: series by series, the grid in the order keys are listed."""
    try:
        raw = tomllib.loads(spec.deck.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise InputError(
            f"deck = {str(spec.deck)!r}: cannot be read as TOML ({exc}); fix the path or the deck"
        ) from None
    runs: list[RunPlan] = []
    seen: dict[Path, str] = {}
    for s in spec.series:
        for varied in s.combinations():
            merged: dict[str, Any] = {**spec.set, **s.set, **dict(varied)}
            sets = tuple(merged.items())
            directory = spec.output / s.name / _slug(varied)
            if directory in seen:
                raise InputError(
                    f"series {s.name!r}: two runs would share the directory {directory} "
                    f"({seen[directory]} and {varied}); make the varied values distinct"
                )
            seen[directory] = repr(varied)
            try:
                law = _law_of(raw, sets)
            except OverrideError as exc:
                raise InputError(f"series {s.name!r}: an override cannot be applied: {exc}") from None
            runs.append(RunPlan(s.name, sets, varied, directory, method_label(law), knobs=dict(merged)))
    return runs


def load_spec(path: str | Path, overrides: dict[str, Any] | None = None) -> StudySpec:
    """Read and validate a spec file. ``deck`` is taken relative to the spec, ``output`` relative to
    the current directory. ``overrides`` replace top-level keys (``jobs``, ``ranks``, ``output``…)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"study spec {str(path)!r} not found; give the path of a TOML spec") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"study spec {str(path)!r} cannot be read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"study spec {str(path)}: not valid TOML: {exc}") from None
    data.update(overrides or {})
    try:
        spec = StudySpec.model_validate(data)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
            given = err.get("input")
            shown = "" if isinstance(given, dict) else f" (given: {given!r})"
            msg = err["msg"].removeprefix("Value error, ")
            lines.append(f"  {loc}: {msg}{shown}")
        raise InputError(f"study spec {path}: {len(lines)} problem(s):\n" + "\n".join(lines)) from None
    deck = spec.deck if spec.deck.is_absolute() else (path.parent / spec.deck)
    if not deck.is_file():
        raise InputError(
            f"study spec {path}: deck = {str(spec.deck)!r} is not a file (taken relative to the spec)"
        )
    spec = spec.model_copy(update={"deck": deck.resolve()})
    for s in spec.series:
        for key in [*s.set, *s.vary, *spec.set]:
            try:
                parse_override(f"{key}=0")
            except OverrideError as exc:
                raise InputError(f"study spec {path}: series {s.name!r}: key {key!r}: {exc}") from None
    if spec.timeout is not None and not math.isfinite(spec.timeout):
        raise InputError(f"study spec {path}: timeout = {spec.timeout!r}; give seconds")
    return spec
