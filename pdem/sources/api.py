"""The particle-source plugin contract (entry-point group ``pdem.sources``).

A source makes the spheres of one ``[[particles]]`` table. The entry-point name is the deck's
``source``::

    [[particles]]
    source = "lattice"
    material = "glass"
    lattice = "fcc"
    radius = 1e-3
    region = { type = "box", lo = [0, 0, 0], hi = [0.01, 0.01, 0.01] }

A source class derives from :class:`Source` and declares

* ``Params``: a pydantic model derived from :class:`SourceParams`, which holds the keys every source
  has (``source``, ``material``, ``stage``, ``motion``, ``velocity``); unknown keys, non-finite
  numbers and (in a deck) strings for numbers are errors. The deck validates each ``[[particles]]``
  table with the ``Params`` of the plugin its ``source`` names, reporting problems under
  ``particles.<index>.<key>``. Checks across keys go in a ``rules(data, context)`` classmethod that
  returns ``[(relative key path, message), ...]`` for the *raw* table (it runs even when some keys
  have the wrong type, so it never assumes they do; ``context["base_dir"]`` is the deck's directory)
  or in a pydantic ``@model_validator`` that raises ``ValueError``. ``RegionSpec`` and ``SizeSpec``
  (re-exported here) are the deck's region and size-distribution tables.
* ``generate(*, base_dir, seed, material) -> SourceOutput``: the spheres, on an instance built as
  ``cls(params)``.
* optionally ``r_max()`` (the largest radius, if known before generating: the deck checks a periodic
  box against it) and ``bounds()`` (the box ``(lo, hi)`` the spheres lie in, if known: the deck checks
  that it is not wider than a periodic box). The defaults read a ``sizes`` / ``region`` key of the
  parameters when it is a :data:`SizeSpec` / :data:`RegionSpec`, and give None otherwise.
* optionally ``estimate_count(data, context)`` (class method): ``(count, description)`` — about how
  many spheres the *raw* table makes, and how that was estimated (e.g. ``"a fcc lattice of spheres
  of radius 1e-3 m in a 0.1×0.1×0.1 m box"``), or None when it cannot tell (the default; also for a
  table with wrong types: it never assumes they are right). The deck's memory check
  (:mod:`pdem.deck.capacity`) refuses a deck whose sources make more particles than
  ``run.max_particles``, and ``pdem advise`` counts the grains with it; ``context["base_dir"]`` is the
  deck's directory. It must be cheap: it runs before the table is validated, on decks that would
  make 10¹² spheres.

Units are SI (m, m/s). Determinism: ``generate`` must return bitwise the same arrays for the same
parameters and ``seed`` (``run.seed`` plus the index of the table in the deck) on any machine and
process; it is called on every MPI rank, and each rank keeps the spheres in its own subdomain, so it
must not communicate or depend on the rank — unless the class sets ``collective = True``: then
``generate`` is also given ``comm=`` (the run's communicator, a serial one outside MPI), is called by
every rank together, may share its work over the ranks (``pluviate`` runs its pour as one MPI
simulation) and must still return, on every rank, bitwise the arrays it returns serially. Particle
ids are given in the order returned: return the spheres in a spatially coherent order
(:func:`pdem.sources.spatial_order`) so that neighbours in space are near in memory.

**Partitioned sources** (``partitioned = True``) let a run on several ranks make only each rank's
own spheres, so that no rank ever holds them all. Such a class also implements

* ``survey(*, base_dir, seed, material) -> Survey``: how many spheres ``generate`` makes, the box
  of their centres, the largest radius and a deterministic sample of at most
  :data:`SURVEY_SAMPLE` centres (the same on every rank: the run places its cut planes at the
  sample's quantiles before any sphere exists);
* ``generate_part(*, base_dir, seed, material, lo, hi) -> SourcePart``: at least the spheres whose
  centres lie in the closed box [lo, hi] (more are allowed; the run keeps the ones its rank owns),
  each with its ``index`` in ``generate``'s order, and the total count. Every sphere must be
  bitwise the one ``generate`` returns at that index (``pdem.testing.source_contract`` checks it).

Neither may communicate, unless the class is also ``collective``: then both are given ``comm=``
and called by every rank together (``survey`` first, then ``generate_part`` with each rank's own
box; ``generate_part`` may also come without a ``survey`` when an earlier source placed the cut
planes), so the work may be shared — the pour keeps its settled packing spread over the ranks that
poured it and hands each rank the spheres in its box. Sources that are not partitioned are
generated on every rank, each keeping its own spheres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from ..deck.schema import (
    Bool,
    Float,
    Int,
    Problems,
    RegionSpec,
    SizeSpec,
    Str,
    Vec3,
    _DeckModel,
)
from ..errors import PluginError
from ..materials import Material

ROW_FIELD = "row"
"""The particle field that keeps the ``rows`` of sources that set ``keeps_rows``."""

__all__ = [
    "ROW_FIELD",
    "SURVEY_SAMPLE",
    "Survey",
    "SourcePart",
    "produce_part",
    "Source",
    "SourceParams",
    "SourceOutput",
    "produce",
    "RegionSpec",
    "SizeSpec",
    "Float",
    "Int",
    "Bool",
    "Str",
    "Vec3",
    "Problems",
]


class SourceParams(_DeckModel):
    """Keys of every ``[[particles]]`` table; a source's ``Params`` adds its own.

    Derived models may narrow ``source`` to their entry-point name (``Literal["lattice"]``) and change
    the default of ``velocity`` (the file source makes it optional). Unknown keys are errors.
    """

    source: Str = Field(
        description="particle source: an entry point of group pdem.sources (see `pdem plugins`)"
    )
    material: Str = Field(description="name of a material defined under [materials]")
    stage: Str | None = Field(
        None,
        description="name of the stage at whose start the particles are inserted; default: before "
        "the first stage",
    )
    motion: Literal["free", "fixed", "prescribed"] = Field(
        "free",
        description="'free' (integrated), 'fixed' (never move) or 'prescribed' (move at their "
        "initial velocity, unaffected by forces)",
    )
    velocity: Vec3 = Field((0.0, 0.0, 0.0), description="initial velocity (x, y, z) [m/s]")
    fixed_translation: Str = Field(
        "",
        pattern="^[xyz]{0,3}$",
        description="axes along which the particles may not move, e.g. 'y' (with fixed_rotation = "
        "'xz': 2-D motion in the xz plane); default none",
    )
    fixed_rotation: Str = Field(
        "", pattern="^[xyz]{0,3}$", description="axes about which the particles may not turn, e.g. 'xz'"
    )


@dataclass(frozen=True)
class SourceOutput:
    """What a source produces: ``positions`` (n, 3) [m], ``radii`` (n,) [m] and optionally
    ``velocities`` (n, 3) [m/s] (None: every sphere gets the table's ``velocity``), ``fixed``
    (n,) bool: spheres that never move whatever the table's ``motion`` (None: none; a lattice's
    ``fixed_edges``) and ``rows`` (n,) int: each sphere's place in the source's input, counted from
    0 (a packing file's data row), kept by the run as the particle field ``row`` when the source
    class sets ``keeps_rows``. Converted to float64 (bool, int64) arrays; a wrong shape is a
    :class:`~pdem.errors.PluginError`."""

    positions: np.ndarray
    radii: np.ndarray
    velocities: np.ndarray | None = None
    fixed: np.ndarray | None = None
    rows: np.ndarray | None = None

    def __post_init__(self) -> None:
        x = np.ascontiguousarray(np.asarray(self.positions, dtype=np.float64))
        if x.ndim == 1 and x.size == 0:
            x = x.reshape(0, 3)
        if x.ndim != 2 or x.shape[1] != 3:
            raise PluginError(
                f"SourceOutput: positions must have shape (n, 3); got {np.shape(self.positions)}"
            )
        r = np.ascontiguousarray(np.asarray(self.radii, dtype=np.float64))
        if r.shape != (x.shape[0],):
            raise PluginError(
                f"SourceOutput: radii must have shape ({x.shape[0]},), one per position; got {r.shape}"
            )
        v = self.velocities
        if v is not None:
            v = np.ascontiguousarray(np.asarray(v, dtype=np.float64))
            if v.shape != x.shape:
                raise PluginError(f"SourceOutput: velocities must have shape {x.shape}; got {v.shape}")
        object.__setattr__(self, "positions", x)
        object.__setattr__(self, "radii", r)
        object.__setattr__(self, "velocities", v)
        if self.fixed is not None:
            fx = np.ascontiguousarray(np.asarray(self.fixed, dtype=bool))
            if fx.shape != r.shape:
                raise PluginError(f"SourceOutput: fixed must have shape {r.shape}; got {fx.shape}")
            object.__setattr__(self, "fixed", fx)
        if self.rows is not None:
            rows = np.ascontiguousarray(np.asarray(self.rows, dtype=np.int64))
            if rows.shape != r.shape:
                raise PluginError(f"SourceOutput: rows must have shape {r.shape}; got {rows.shape}")
            object.__setattr__(self, "rows", rows)

    def __len__(self) -> int:
        return int(self.radii.shape[0])


#: the most centres a :class:`Survey` samples
SURVEY_SAMPLE = 65536


@dataclass(frozen=True)
class Survey:
    """What a partitioned source tells before making its spheres (see the module docstring):
    ``count``, ``lo`` and ``hi`` (3,) bounding the centres [m], ``r_max`` [m], ``sample`` (k, 3)
    centres, k ≤ :data:`SURVEY_SAMPLE` (k > 0 when count > 0)."""

    count: int
    lo: np.ndarray
    hi: np.ndarray
    r_max: float
    sample: np.ndarray


@dataclass(frozen=True)
class SourcePart:
    """Some of a partitioned source's spheres: ``output`` (a :class:`SourceOutput`), ``index`` (n,)
    their places in ``generate``'s order (increasing), ``total`` the number ``generate`` makes."""

    output: SourceOutput
    index: np.ndarray
    total: int


class Sampler:
    """A deterministic sample of a stream of centres: every stride-th, the stride doubling whenever
    the sample would pass :data:`SURVEY_SAMPLE`; also counts them and bounds them."""

    def __init__(self) -> None:
        self.count = 0
        self.stride = 1
        self.parts: list[np.ndarray] = []
        self.kept = 0
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)

    def add(self, x: np.ndarray) -> None:
        x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
        if not x.shape[0]:
            return
        self.lo = np.minimum(self.lo, x.min(axis=0))
        self.hi = np.maximum(self.hi, x.max(axis=0))
        index = self.count + np.arange(x.shape[0])
        self.count += x.shape[0]
        take = x[index % self.stride == 0]
        self.parts.append(take)
        self.kept += take.shape[0]
        while self.kept > SURVEY_SAMPLE:  # keep every other one: those at multiples of 2 × stride
            self.stride *= 2
            self.parts = [np.concatenate(self.parts)[::2]]
            self.kept = self.parts[0].shape[0]

    def survey(self, r_max: float) -> Survey:
        sample = np.concatenate(self.parts) if self.parts else np.zeros((0, 3))
        return Survey(self.count, self.lo, self.hi, float(r_max), sample)


class Source:
    """Base of particle-source plugins: construct with validated ``Params``, then ``generate``."""

    Params: ClassVar[type[SourceParams]] = SourceParams
    #: the grains start apart and may fall before they touch (a random fill, a lattice), rather than
    #: packed (a file, a pour): ``pdem advise`` takes free-fall speeds from such sources
    starts_loose: ClassVar[bool] = False
    #: the source settles its grains with pdem before the run (a pour): ``pdem advise`` predicts the
    #: time that takes
    settles: ClassVar[bool] = False
    #: ``generate`` takes ``comm=`` and is called by every rank together (see the module docstring)
    collective: ClassVar[bool] = False
    #: ``generate`` gives ``rows`` (a file's row of each sphere): a run with such a source keeps them
    #: as the particle field ``row`` (:data:`ROW_FIELD`), written to every output, so that a user can
    #: map the grains back to the input; -1 for grains of sources without rows
    keeps_rows: ClassVar[bool] = False
    #: parameters naming input files relative to the deck (``pdem advise --apply`` makes them absolute)
    path_keys: ClassVar[tuple[str, ...]] = ()
    #: ``survey`` and ``generate_part`` exist: each rank makes only its own spheres (module docstring)
    partitioned: ClassVar[bool] = False

    def __init__(self, params: SourceParams) -> None:
        self.params = params

    def known_radii(self, base_dir: Path) -> np.ndarray | None:
        """The radii the source will make, when it knows them before generating (a packing file: its
        rows), else None (default). ``pdem advise`` sizes its rules from them."""
        return None

    @classmethod
    def estimate_count(cls, data: dict, context: dict) -> tuple[float, str] | None:
        """``(count, description)``: about how many spheres the raw table ``data`` makes, or None
        (default) when the source cannot tell (see the module docstring)."""
        return None

    def generate(self, *, base_dir: Path, seed: int, material: Material) -> SourceOutput:
        """The spheres of this table.

        ``base_dir``: the deck's directory (relative file names in parameters are resolved against
        it); ``seed``: the seed of any random draw (``run.seed`` + the table's index); ``material``:
        the :class:`pdem.materials.Material` named by ``material`` (density, stiffness, … for
        sources that simulate, like ``pluviate``).
        """
        raise NotImplementedError(f"{type(self).__name__} does not implement generate()")

    def r_max(self) -> float | None:
        """The largest radius [m], if known before generating (default: from a ``sizes`` key)."""
        sizes = getattr(self.params, "sizes", None)
        build = getattr(sizes, "build", None)
        if callable(build) and hasattr(sizes, "type"):
            return float(build().r_max)
        return None

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(lo, hi)`` [m] of the box the spheres lie in, if known (default: a ``region`` key's)."""
        region = getattr(self.params, "region", None)
        build = getattr(region, "build", None)
        if callable(build) and hasattr(region, "type"):
            lo, hi = build().bounds
            return np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        return None


def produce_part(
    source: Source,
    *,
    base_dir: Path,
    seed: int,
    material: Material,
    lo,
    hi,
    where: str = "",
    comm: Any = None,
) -> SourcePart:
    """Call a partitioned source's ``generate_part`` and check what it returns against the contract
    (``where`` is named in the error). ``comm``: the run's communicator, given to a ``collective``
    source (None: serial)."""
    label = f"particle source '{source.params.source}'" + (f" ({where})" if where else "")
    kwargs: dict[str, Any] = {}
    if source.collective:
        from ..parallel.comm import SerialComm

        kwargs["comm"] = comm if comm is not None else SerialComm()
    try:
        part: Any = source.generate_part(
            base_dir=Path(base_dir), seed=int(seed), material=material,
            lo=np.asarray(lo, dtype=float), hi=np.asarray(hi, dtype=float), **kwargs,
        )  # fmt: skip
    except PluginError as exc:
        raise PluginError(f"{label}: {exc}") from exc
    ok = isinstance(part, SourcePart) and isinstance(part.output, SourceOutput)
    if ok:
        index = np.asarray(part.index)
        ok = (
            index.shape == (len(part.output),)
            and index.dtype.kind in "iu"
            and (index.size == 0 or (index[0] >= 0 and index[-1] < part.total and np.all(np.diff(index) > 0)))
        )
    if not ok:
        raise PluginError(
            f"{label}: generate_part() did not return a SourcePart whose index lists each sphere's place "
            "in generate()'s order, increasing and below total; it does not honour the plugin contract "
            "(report this to its author)"
        )
    return part


def produce(
    source: Source, *, base_dir: Path, seed: int, material: Material, where: str = "", comm: Any = None
) -> SourceOutput:
    """Call ``source.generate`` and check that it honours the contract (a :class:`SourceOutput`);
    ``where`` (e.g. ``"particles.2"``) is named in the error. ``comm``: the run's communicator, given
    to a ``collective`` source (None: serial)."""
    label = f"particle source '{source.params.source}'" + (f" ({where})" if where else "")
    kwargs: dict[str, Any] = {}
    if source.collective:
        from ..parallel.comm import SerialComm

        kwargs["comm"] = comm if comm is not None else SerialComm()
    try:
        out: Any = source.generate(base_dir=Path(base_dir), seed=int(seed), material=material, **kwargs)
    except PluginError as exc:
        raise PluginError(f"{label}: {exc}") from exc
    if not isinstance(out, SourceOutput):
        raise PluginError(
            f"{label}: generate() returned {type(out).__name__}, not a pdem.sources.api.SourceOutput; "
            "it does not honour the plugin contract (report this to its author)"
        )
    return out
