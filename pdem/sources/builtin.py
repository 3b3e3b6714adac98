"""pdem's own particle sources, registered as plugins of group ``pdem.sources`` in pdem's
``pyproject.toml`` exactly like third-party ones: ``random_fill``, ``lattice``, ``file`` and
``pluviate``.

Each is a :class:`~pdem.sources.api.Source` with a ``Params`` model (``RandomFillParams``, …): the
keys, defaults, rules and messages of the deck's ``[[particles]]`` tables (docs/deck.md).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from ..deck import capacity as _capacity
from ..deck.rules import REGION_MODELS as _REGION_MODELS
from ..deck.rules import SIZE_MODELS as _SIZE_MODELS
from ..deck.rules import context_of as _ctx
from ..deck.rules import fit_problem as _fit_problem
from ..deck.rules import given as _given
from ..deck.rules import is_number as _is_num
from ..deck.rules import try_build as _try_build
from ..deck.schema import (
    Float,
    Int,
    Problems,
    RegionSpec,
    SizeSpec,
    Str,
    Vec3,
    radius_problem,
)
from ..materials import Material
from ..textutil import quote
from .api import Sampler, Source, SourceOutput, SourceParams, SourcePart, Survey

__all__ = [
    "BUILTIN_SOURCES",
    "RSA_LIMIT",
    "RandomFillParams",
    "LatticeParams",
    "FileParams",
    "PluviateParams",
    "RandomFillSource",
    "LatticeSource",
    "FileSource",
    "PluviateSource",
]

#: pdem's own sources, in the order the documentation (and an unknown-source message) lists them
BUILTIN_SOURCES = ("random_fill", "lattice", "file", "pluviate")

#: above this solid fraction random sequential addition cannot succeed (it jams near 0.38 for equal spheres)
RSA_LIMIT = 0.5


class RandomFillParams(SourceParams):
    """Non-overlapping spheres placed at random (random sequential addition) in a region."""

    source: Literal["random_fill"] = Field(description="source kind")
    region: RegionSpec = Field(description="region to fill: {type = 'box', …} or {type = 'cylinder', …}")
    sizes: SizeSpec = Field(
        description="size distribution: {type = 'single' | 'uniform' | 'normal' | 'table', …}"
    )
    n: Int | None = Field(
        None, gt=0, description="number of spheres (give exactly one of n, volume_fraction)"
    )
    volume_fraction: Float | None = Field(
        None,
        gt=0,
        lt=RSA_LIMIT,
        description=f"target solid volume fraction of the region [-], < {RSA_LIMIT} (random sequential "
        "addition jams near 0.38 for equal spheres); exactly one of n, volume_fraction",
    )
    gap: Float = Field(0.0, ge=0, description="minimum clearance between sphere surfaces [m]")

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out: Problems = []
        if _given(data, "n") == _given(data, "volume_fraction"):
            which = "both" if _given(data, "n") else "neither"
            loc = ("volume_fraction",) if which == "both" else ()
            out.append((loc, f"give exactly one of n (number of spheres) and volume_fraction; {which} given"))
        sizes = _try_build(_SIZE_MODELS, data.get("sizes"))
        if sizes is not None:
            out += _fit_problem(data.get("region"), sizes.r_max, "the largest radius", "sizes")
            region = _try_build(_REGION_MODELS, data.get("region"))
            n = data.get("n")
            if (
                region is not None
                and isinstance(n, int)
                and not isinstance(n, bool)
                and n > 0
                and not _given(data, "volume_fraction")
            ):
                frac = n * sizes.mean_volume() / region.volume
                if frac >= RSA_LIMIT:
                    out.append(
                        (
                            ("n",),
                            f"{n} spheres would fill {frac:.3g} of the region's volume; random "
                            f"sequential addition cannot exceed about 0.38 (limit {RSA_LIMIT}); "
                            "use fewer spheres, a larger region, or source = 'pluviate'",
                        )
                    )
        return out


class LatticeParams(SourceParams):
    """Equal spheres on a regular lattice: sc, fcc or hcp in a 3-D region, or a hex2d plane."""

    source: Literal["lattice"] = Field(description="source kind")
    lattice: Literal["sc", "fcc", "hcp", "hex2d"] = Field(
        description="'sc' (simple cubic), 'fcc', 'hcp' (in `region`) or 'hex2d' (n_cols × n_rows in a plane)"
    )
    radius: Float = Field(gt=0, description="sphere radius [m]")
    spacing: Float | None = Field(
        None, gt=0, description="centre distance of nearest neighbours [m], >= 2 radius; default 2 radius"
    )
    region: RegionSpec | None = Field(None, description="region to fill (sc, fcc, hcp only)")
    n_cols: Int | None = Field(None, ge=1, description="spheres per row (hex2d only)")
    n_rows: Int | None = Field(None, ge=1, description="number of rows (hex2d only)")
    origin: Vec3 | None = Field(
        None, description="centre of the first sphere [m] (hex2d only; default 0, 0, 0)"
    )
    plane: Literal["xy", "xz", "yz"] | None = Field(
        None, description="coordinate plane, row axis then stacking axis (hex2d only; default 'xz')"
    )
    fixed_edges: list[Literal["bottom", "top", "left", "right"]] | None = Field(
        None,
        description="hex2d only: edges whose spheres never move (motion 'fixed'): 'bottom' (row 0), "
        "'top' (the last row), 'left' (the first sphere of every row), 'right' (the last of every row)",
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        out: Problems = []
        too_small_or_large = radius_problem(data.get("radius"))
        if too_small_or_large is not None:
            return [(("radius",), too_small_or_large)]
        lattice = data.get("lattice")
        if lattice == "hex2d":
            out += [
                ((k,), f"required for lattice = 'hex2d': {k}")
                for k in ("n_cols", "n_rows")
                if not _given(data, k)
            ]
            if _given(data, "region"):
                out.append(
                    (
                        ("region",),
                        "a 'hex2d' lattice takes n_cols, n_rows, origin and plane, not a "
                        "region; remove region",
                    )
                )
        elif lattice in ("sc", "fcc", "hcp"):
            if not _given(data, "region"):
                out.append((("region",), f"required for lattice = '{lattice}': region (box or cylinder)"))
            for k in ("n_cols", "n_rows", "origin", "plane", "fixed_edges"):
                if _given(data, k):
                    out.append(((k,), f"{k} applies to lattice = 'hex2d' only; remove it for '{lattice}'"))
            radius = data.get("radius")
            if _is_num(radius) and radius > 0:
                out += _fit_problem(data.get("region"), radius, "radius", "radius")
        radius, spacing = data.get("radius"), data.get("spacing")
        if _is_num(radius) and _is_num(spacing) and spacing < 2 * radius * (1 - 1e-12):
            out.append(
                (
                    ("spacing",),
                    f"spacing = {spacing} is smaller than the diameter {2 * radius}; "
                    "neighbouring spheres would overlap (use spacing >= 2 radius or "
                    "omit it)",
                )
            )
        return out

    @model_validator(mode="after")
    def _hex2d_defaults(self) -> LatticeParams:
        if self.lattice == "hex2d":
            if self.origin is None:
                self.origin = (0.0, 0.0, 0.0)
            if self.plane is None:
                self.plane = "xz"
        return self


class FileParams(SourceParams):
    """Spheres read from a packing file (text ``x y z diameter [vx vy vz]`` or HDF5)."""

    source: Literal["file"] = Field(description="source kind")
    path: Str = Field(
        description="packing file, relative to the deck's directory (stored as an absolute path once "
        "validated); must exist"
    )
    velocity: Vec3 | None = Field(
        None,
        description="initial velocity (x, y, z) [m/s] used when the file has no velocity columns; "
        "default zero",
    )
    order: Literal["file", "spatial"] = Field(
        "spatial",
        description="the order in which the spheres get their ids: 'spatial' (default), sorted by "
        "cells of 2 r_max (z, then y, then x; pdem.sources.spatial_order), so a file in any row order "
        "gives the same ids and the same results as a spatially sorted copy, and runs as fast; 'file', "
        "the file's rows (ids = rows; DEM-P's sums follow the ids: a shuffled 68k-sphere column ran "
        "1.08-1.10x slower than its sorted copy). Either way each grain's file row is kept as the "
        "particle field 'row', written to every output",
    )

    @field_validator("path")
    @classmethod
    def _absolute(cls, value: str, info: ValidationInfo) -> str:
        base = _ctx(info).get("base_dir")
        p = Path(value).expanduser()
        if not p.is_absolute():
            p = Path(base if base is not None else ".") / p
        try:
            return str(p.resolve())
        except (OSError, RuntimeError, ValueError):  # a symlink loop, …: the rule below reports it
            return os.path.abspath(p)

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        from .files import packing_file_problem

        value = data.get("path")
        if isinstance(value, str) and value:
            base = Path(context.get("base_dir", "."))
            p = Path(value).expanduser()
            full = p if p.is_absolute() else base / p
            problem = packing_file_problem(full)
            if problem is not None:
                looked = "" if p.is_absolute() else f" (looked for {quote(str(full))})"
                return [
                    (
                        ("path",),
                        f"file {quote(value)} {problem}{looked}; give a packing file (text or HDF5); "
                        "paths are relative to the deck's directory",
                    )
                ]
        elif isinstance(value, str):
            return [(("path",), "path is empty; give the packing file's name")]
        return []


class PluviateParams(SourceParams):
    """Spheres poured into a container and settled under gravity (a dense random packing)."""

    source: Literal["pluviate"] = Field(description="source kind")
    region: RegionSpec = Field(
        description="the container: box or cylinder; its footprint and floor are used, its height is not"
    )
    sizes: SizeSpec = Field(description="size distribution")
    n: Int = Field(gt=0, description="number of spheres")
    fill_fraction: Float = Field(
        0.3, ge=0.05, le=0.35, description="solid fraction of the loose column the spheres rain from [-]"
    )
    max_time: Float = Field(2.0, gt=0, description="settling time allowed before giving up [s]")
    rest_speed: Float | None = Field(
        None,
        gt=0,
        description="settled when the fastest sphere is slower than this [m/s]; default 0.01 sqrt(g d_mean)",
    )
    friction: Float | None = Field(
        None,
        ge=0,
        description="friction μ between the spheres (and with the container) while they are poured [-]; "
        "default the material's. Low friction pours a dense packing, high friction a loose one",
    )

    @classmethod
    def rules(cls, data: dict, context: dict) -> Problems:
        sizes = _try_build(_SIZE_MODELS, data.get("sizes"))
        region = _try_build(_REGION_MODELS, data.get("region"))
        if sizes is None or region is None:
            return []
        lo, hi = region.bounds
        room = region.radius if hasattr(region, "radius") else 0.5 * float(min(hi[0] - lo[0], hi[1] - lo[1]))
        if sizes.r_max > room:
            return [
                (
                    ("sizes",),
                    f"the largest radius {sizes.r_max!r} m does not fit in the container's "
                    f"footprint (largest radius that fits: {room!r} m)",
                )
            ]
        return []


# -------------------------------------------------------------------------------------------------
# the plugins
# -------------------------------------------------------------------------------------------------


class RandomFillSource(Source):
    """``source = "random_fill"``: :func:`pdem.sources.random_fill` in a region."""

    Params = RandomFillParams
    starts_loose = True

    @classmethod
    def estimate_count(cls, data: dict, context: dict) -> tuple[float, str] | None:
        """``n``, or ``volume_fraction`` × the region's volume / the mean sphere volume."""
        return _capacity.fill_count(data, by_fraction=True)

    def generate(self, *, base_dir: Path, seed: int, material: Material) -> SourceOutput:
        from . import random_fill

        p = self.params
        x, r = random_fill(
            p.region.build(), p.sizes.build(), n=p.n, volume_fraction=p.volume_fraction, seed=seed, gap=p.gap
        )
        return SourceOutput(x, r)

    def _plan(self, seed: int):
        """The fill's plan, kept for the seed last asked: the survey and the part share it (a fill
        of one block is then made once)."""
        from .random_fill import fill_plan

        kept = getattr(self, "_kept_plan", None)
        if kept is None or kept[0] != seed:
            p = self.params
            plan = fill_plan(p.region.build(), p.sizes.build(), n=p.n, volume_fraction=p.volume_fraction,
                             seed=seed, gap=p.gap)  # fmt: skip
            kept = self._kept_plan = (seed, plan)
        return kept[1]

    #: a fill of more than BLOCK_SPHERES spheres is made in blocks: each rank makes those over its
    #: subdomain, and surveys the others one at a time (a fill of one block is made whole)
    partitioned = True

    def survey(self, *, base_dir: Path, seed: int, material: Material) -> Survey:
        return self._plan(seed).survey()

    def generate_part(self, *, base_dir: Path, seed: int, material: Material, lo, hi) -> SourcePart:
        x, r, index, total = self._plan(seed).part(lo, hi)
        return SourcePart(SourceOutput(x, r), index, total)


class LatticeSource(Source):
    """``source = "lattice"``: :func:`pdem.sources.simple_cubic`, ``fcc``, ``hcp`` or ``hex2d``."""

    Params = LatticeParams
    starts_loose = True

    @classmethod
    def estimate_count(cls, data: dict, context: dict) -> tuple[float, str] | None:
        """The lattice points the generator makes (:func:`pdem.deck.capacity.lattice_count`)."""
        return _capacity.lattice_count(data)

    def generate(self, *, base_dir: Path, seed: int, material: Material) -> SourceOutput:
        from . import fcc, hcp, hex2d, simple_cubic

        p = self.params
        fixed = None
        if p.lattice == "hex2d":
            x, r = hex2d(p.n_cols, p.n_rows, p.radius, origin=p.origin, plane=p.plane, spacing=p.spacing)
            if p.fixed_edges:
                row, col = np.divmod(np.arange(x.shape[0]), p.n_cols)  # hex2d's order: row by row
                edge = {"bottom": row == 0, "top": row == p.n_rows - 1, "left": col == 0,
                        "right": col == p.n_cols - 1}  # fmt: skip
                fixed = np.logical_or.reduce([edge[e] for e in p.fixed_edges])
        else:
            fn = {"sc": simple_cubic, "fcc": fcc, "hcp": hcp}[p.lattice]
            x, r = fn(p.region.build(), p.radius, spacing=p.spacing)
        return SourceOutput(x, r, fixed=fixed)

    def r_max(self) -> float | None:
        return float(self.params.radius)

    @property
    def partitioned(self) -> bool:  # (a 2-D hex2d bed is made whole: it is small)
        return self.params.lattice != "hex2d"

    def _layers(self):
        from .lattice import lattice_layers

        p = self.params
        return lattice_layers(p.lattice, p.region.build(), p.radius, p.spacing)

    def survey(self, *, base_dir: Path, seed: int, material: Material) -> Survey:
        sampler = Sampler()
        for x in self._layers():
            sampler.add(x)
        return sampler.survey(float(self.params.radius))

    def generate_part(self, *, base_dir: Path, seed: int, material: Material, lo, hi) -> SourcePart:
        xs, index, start = [], [], 0
        for x in self._layers():
            if x.shape[0] and x[0, 2] <= hi[2] and x[-1, 2] >= lo[2]:  # (a layer is one z)
                inside = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))
                xs.append(x[inside])
                index.append(start + inside)
            start += x.shape[0]
        x = np.concatenate(xs) if xs else np.zeros((0, 3))
        index = np.concatenate(index) if index else np.zeros(0, np.int64)
        r = np.full(x.shape[0], float(self.params.radius))
        return SourcePart(SourceOutput(x, r), index.astype(np.int64), start)


class FileSource(Source):
    """``source = "file"``: spheres (and velocities, if given) read by :func:`pdem.sources.read_spheres`."""

    Params = FileParams
    path_keys = ("path",)
    keeps_rows = True

    @classmethod
    def estimate_count(cls, data: dict, context: dict) -> tuple[float, str] | None:
        """The rows of the packing file (:func:`pdem.deck.capacity.file_rows`)."""
        p = data.get("path")
        if not isinstance(p, str) or not p:
            return None
        path = Path(p).expanduser()
        return _capacity.file_rows(path if path.is_absolute() else Path(context.get("base_dir", ".")) / path)

    def known_radii(self, base_dir: Path) -> np.ndarray | None:
        """The file's radii."""
        from . import read_spheres

        return np.asarray(read_spheres(Path(base_dir) / self.params.path)["radii"], dtype=float)

    #: each rank reads the file in chunks and keeps its own spheres (three passes for order = "spatial")
    partitioned = True
    #: spheres read at a time when partitioned
    chunk = 65536

    def _chunks(self, base_dir: Path):
        from .files import iter_spheres

        return iter_spheres(Path(base_dir) / self.params.path, self.chunk)

    def survey(self, *, base_dir: Path, seed: int, material: Material) -> Survey:
        sampler, r_max = Sampler(), 0.0
        for c in self._chunks(base_dir):
            sampler.add(c["positions"])
            r_max = max(r_max, float(c["radii"].max()))
        return sampler.survey(r_max)

    def generate_part(self, *, base_dir: Path, seed: int, material: Material, lo, hi) -> SourcePart:
        if self.params.order == "spatial":
            return self._spatial_part(base_dir, np.asarray(lo, float), np.asarray(hi, float))
        def in_box(c):
            return np.flatnonzero(np.all((c["positions"] >= lo) & (c["positions"] <= hi), axis=1)), None

        x, r, v, rows, _, total = self._rows_where(base_dir, in_box)
        return SourcePart(SourceOutput(x, r, v, rows=rows), rows, total)

    def _rows_where(self, base_dir: Path, choose):
        """The file's rows that ``choose(chunk) -> (indices in the chunk, values or None)`` picks,
        read a chunk at a time: positions, radii, velocities (or None), rows, the values, and the
        number of rows in the file."""
        keep: dict[str, list] = {"x": [], "r": [], "v": [], "row": [], "value": []}
        total, has_v = 0, False
        for c in self._chunks(base_dir):
            inside, value = choose(c)
            keep["x"].append(c["positions"][inside])
            keep["r"].append(c["radii"][inside])
            has_v = c["velocities"] is not None
            if has_v:
                keep["v"].append(c["velocities"][inside])
            keep["row"].append(c["start"] + inside)
            if value is not None:
                keep["value"].append(value)
            total += c["radii"].shape[0]
        v = np.concatenate(keep["v"]).reshape(-1, 3) if has_v else None
        value = np.concatenate(keep["value"]) if keep["value"] else None
        x, r = np.concatenate(keep["x"]).reshape(-1, 3), np.concatenate(keep["r"])
        return x, r, v, np.concatenate(keep["row"]).astype(np.int64), value, total

    def _spatial_part(self, base_dir: Path, lo: np.ndarray, hi: np.ndarray) -> SourcePart:
        """The spheres of every cell of :func:`pdem.sources.spatial_order` (edge 2 r_max, from the
        centres' minimum) that meets the box [lo, hi], with their ids in that order: one pass for
        the grid, one counting the spheres of every occupied cell (a cell's first id is the count of
        those before it), one keeping the cells' spheres, ordered within each cell as the whole file
        would be. The cells are kept whole, so the order inside them is known."""
        total, xmin, xmax, r_max = 0, np.full(3, np.inf), np.full(3, -np.inf), 0.0
        for c in self._chunks(base_dir):
            xmin = np.minimum(xmin, c["positions"].min(axis=0))
            xmax = np.maximum(xmax, c["positions"].max(axis=0))
            r_max = max(r_max, float(c["radii"].max()))
            total += c["radii"].shape[0]
        h = 2.0 * r_max
        grid = np.floor((xmax - xmin) / h).astype(np.int64) + 1

        def cells(x):
            return np.floor((x - xmin) / h).astype(np.int64)

        def key(c):
            return (c[:, 2] * grid[1] + c[:, 1]) * grid[0] + c[:, 0]

        keys, counts = [], []
        for c in self._chunks(base_dir):
            k, n = np.unique(key(cells(c["positions"])), return_counts=True)
            keys.append(k)
            counts.append(n)
        k_all = np.concatenate(keys)
        cell_keys, inverse = np.unique(k_all, return_inverse=True)
        cell_counts = np.bincount(inverse, weights=np.concatenate(counts)).astype(np.int64)
        del keys, counts, k_all, inverse
        cell_start = np.concatenate([[0], np.cumsum(cell_counts)[:-1]])
        c_lo = np.clip(np.floor((lo - xmin) / h), -1, grid).astype(np.int64)
        c_hi = np.clip(np.floor((hi - xmin) / h), -1, grid).astype(np.int64)
        def whole_cells(c):
            cc = cells(c["positions"])
            inside = np.flatnonzero(np.all((cc >= c_lo) & (cc <= c_hi), axis=1))
            return inside, key(cc[inside])

        x, r, v, row, k, _ = self._rows_where(base_dir, whole_cells)
        order = np.lexsort((row, x[:, 0], x[:, 1], x[:, 2], k))  # spatial_order's, ties by row
        x, r, row, k = x[order], r[order], row[order], k[order]
        v = None if v is None else v[order]
        first = np.searchsorted(k, k, side="left")  # each sphere's cell's first place among these
        ids = cell_start[np.searchsorted(cell_keys, k)] + (np.arange(k.shape[0]) - first)
        return SourcePart(SourceOutput(x, r, v, rows=row), ids.astype(np.int64), total)

    def generate(self, *, base_dir: Path, seed: int, material: Material) -> SourceOutput:
        from . import read_spheres

        d = read_spheres(Path(base_dir) / self.params.path)  # the validated path is absolute
        x, r, v = d["positions"], d["radii"], d.get("velocities")
        rows = np.arange(r.size, dtype=np.int64)
        if self.params.order == "spatial" and r.size:
            from . import spatial_order

            o = spatial_order(x, 2.0 * float(r.max()))
            x, r, v, rows = x[o], r[o], (None if v is None else v[o]), rows[o]
        return SourceOutput(x, r, v, rows=rows)


class PluviateSource(Source):
    """``source = "pluviate"``: :func:`pdem.sources.pluviate`, poured and settled with pdem itself."""

    Params = PluviateParams
    settles = True
    collective = True  # the pour is one MPI simulation over the run's ranks

    @classmethod
    def estimate_count(cls, data: dict, context: dict) -> tuple[float, str] | None:
        """``n``."""
        return _capacity.fill_count(data, by_fraction=False)

    #: under MPI the settled packing stays spread over the ranks that poured it: ``survey`` pours
    #: (collectively) and keeps the bed, ``generate_part`` hands each rank the spheres in its box
    partitioned = True

    def _pour(self, seed: int, material: Material, comm: Any):
        from .pluviation import pour

        p = self.params
        if p.friction is not None:
            material = dataclasses.replace(material, friction=p.friction)
        return pour(
            p.region.build(),
            p.sizes.build(),
            p.n,
            material,
            seed=seed,
            fill_fraction=p.fill_fraction,
            max_time=p.max_time,
            rest_speed=p.rest_speed,
            comm=comm,
        )

    def generate(self, *, base_dir: Path, seed: int, material: Material, comm: Any = None) -> SourceOutput:
        x, r = self._pour(seed, material, comm).whole()
        return SourceOutput(x, r)

    def survey(self, *, base_dir: Path, seed: int, material: Material, comm: Any = None) -> Survey:
        self._bed = (seed, self._pour(seed, material, comm))  # kept for generate_part
        return self._bed[1].survey()

    def generate_part(
        self, *, base_dir: Path, seed: int, material: Material, lo, hi, comm: Any = None
    ) -> SourcePart:
        kept = getattr(self, "_bed", None)
        if kept is None or kept[0] != seed:  # (cut planes placed by an earlier source: no survey)
            kept = self._bed = (seed, self._pour(seed, material, comm))
        bed = kept[1]
        x, r, index = bed.part(lo, hi)
        return SourcePart(SourceOutput(x, r), index, bed.count)
