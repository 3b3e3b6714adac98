"""How many particles a deck creates and how much memory they take: refused at validation above a limit.

A deck such as ``n = 1000000000000`` in a random fill, or a lattice of 5 µm spheres in a 2 cm box
(≈ 10⁹ spheres), would otherwise run until the machine runs out of memory. :func:`check_capacity`
estimates every ``[[particles]]`` source from its raw table (so it does not depend on the source
models of :mod:`pdem.deck.schema`) and refuses the deck when the total exceeds ``run.max_particles``,
naming the source, the count, the memory it needs and the remedy.

The estimate is the source plugin's own: its ``estimate_count(data, context)`` class method
(:class:`pdem.sources.api.Source`; a source that does not say is left out). pdem's sources estimate
with the helpers of this module (:func:`fill_count`, :func:`lattice_count`, :func:`file_rows`):

========== ==================================================================================
source     estimate
========== ==================================================================================
random_fill ``n``, or ``volume_fraction`` × region volume / mean sphere volume (mean of r³ of the
           size distribution)
pluviate   ``n``
lattice    the lattice points of the region's bounding box that the generator makes (sc, fcc, hcp:
           as :mod:`pdem.sources.lattice` counts them; the part inside a cylinder: × π/4);
           hex2d: ``n_cols × n_rows``
file       HDF5: the length of the position dataset; text: the number of lines (counted when the
           file is below 256 MB, else its size / 16 bytes, the shortest usual row)
========== ==================================================================================

Memory: :data:`BYTES_PER_PARTICLE` = 1,000 bytes. Measured: the peak resident memory of a serial run
(lattice of touching spheres on a floor, 20 steps with snapshots, series and checkpoints) grows by
0.91 kB per particle from 216,000 to 512,000 particles (343 → 569 MB): the particle fields
(222 bytes: id, x, v, w, f, t, r, mass, 1/m, 1/I, material, motion, group, dof, x at the last
rebuild) with the store's spare capacity, the neighbour list and contact history (capacity for 8
pairs per particle), the cell grid, and the copies made to write snapshots and checkpoints (gathered
by id). Rounded up to 1 kB.

Limit: ``run.max_particles`` if the deck gives it; else the machine's physical memory / 1 kB (every
particle of a run passes through one process when snapshots and checkpoints are gathered, so one
machine's memory bounds the run even under MPI), and never above 2³¹ − 1 (particle ids are below
2³¹). A run spread over machines with more memory than this one raises ``run.max_particles``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

__all__ = [
    "BYTES_PER_PARTICLE",
    "ID_LIMIT",
    "check_capacity",
    "default_max_particles",
    "estimate_source",
    "estimate_sources",
    "file_rows",
    "fill_count",
    "lattice_count",
    "machine_memory",
]

#: estimated memory per particle [bytes] (see the module doc for the measurement)
BYTES_PER_PARTICLE = 1000
#: particle ids are below 2³¹ (pair keys pack two ids into an int64)
ID_LIMIT = 2**31 - 1
#: text packing files above this size are not read to count their rows
_COUNT_LINES_BELOW = 256 * 2**20
#: the shortest usual row of a text packing file ("0 0 0 0.002\n" is 12 bytes)
_MIN_ROW_BYTES = 16

Loc = tuple[str | int, ...]


def machine_memory() -> int | None:
    """Physical memory of the machine running pdem [bytes], or None if the system does not say."""
    try:
        pages, size = os.sysconf("SC_PHYS_PAGES"), os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None
    if pages <= 0 or size <= 0:
        return None
    return int(pages) * int(size)


def default_max_particles() -> tuple[int, str]:
    """The limit without ``run.max_particles``, and how it was obtained (for messages)."""
    mem = machine_memory()
    if mem is None:
        return 50_000_000, "the default of 5e7 (this system does not report its memory)"
    n = min(ID_LIMIT, mem // BYTES_PER_PARTICLE)
    return n, f"this computer's memory {_bytes(mem)} / {BYTES_PER_PARTICLE:,} bytes per particle"


def _bytes(n: float) -> str:
    for unit, size in (("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n:.0f} bytes"


def _count(n: float) -> str:
    return f"{n:,.0f}" if n < 1e9 else f"{float(n):.3g}" if n < 1e300 else "more than 1e300"


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return None
    x = float(v)
    return x if math.isfinite(x) else None


def _vec(v: Any) -> list[float] | None:
    if not isinstance(v, list | tuple) or len(v) != 3:
        return None
    out = [_num(c) for c in v]
    return None if any(c is None for c in out) else out  # type: ignore[return-value]


def _region_box(region: Any) -> tuple[list[float], bool, float] | None:
    """(edge lengths of the bounding box, is a cylinder, volume) of a raw region table."""
    if not isinstance(region, dict):
        return None
    if region.get("type") == "box":
        lo, hi = _vec(region.get("lo")), _vec(region.get("hi"))
        if lo is None or hi is None:
            return None
        edges = [h - low for low, h in zip(lo, hi, strict=True)]
        if min(edges) <= 0:
            return None
        return edges, False, math.prod(edges)
    if region.get("type") == "cylinder":
        r, h = _num(region.get("radius")), _num(region.get("height"))
        if r is None or h is None or r <= 0 or h <= 0:
            return None
        return [2 * r, 2 * r, h], True, math.pi * r * r * h
    return None


def _mean_r3(sizes: Any) -> float | None:
    """Mean of r³ over the number distribution of a raw sizes table."""
    if not isinstance(sizes, dict):
        return None
    kind = sizes.get("type")
    if kind == "single":
        r = _num(sizes.get("radius"))
        return r**3 if r is not None and r > 0 else None
    if kind == "uniform":
        a, b = _num(sizes.get("r_min")), _num(sizes.get("r_max"))
        if a is None or b is None or a <= 0 or b < a:
            return None
        return a**3 if b == a else (b**4 - a**4) / (4.0 * (b - a))
    if kind == "normal":
        mu, sd = _num(sizes.get("mean")), _num(sizes.get("std"))
        if mu is None or sd is None or mu <= 0 or sd < 0:
            return None
        lo = _num(sizes.get("r_min"))
        return max(mu**3 + 3.0 * mu * sd * sd, (lo or 0.0) ** 3)
    if kind == "table":
        radii, fractions = sizes.get("radii"), sizes.get("mass_fractions")
        if not isinstance(radii, list) or not isinstance(fractions, list) or len(radii) != len(fractions):
            return None
        rs, fs = [_num(r) for r in radii], [_num(f) for f in fractions]
        if not rs or any(r is None or r <= 0 for r in rs) or any(f is None or f < 0 for f in fs):
            return None
        weight = sum(f / r**3 for r, f in zip(rs, fs, strict=True))  # number ∝ mass fraction / r³
        total = sum(fs)
        return total / weight if weight > 0 and total > 0 else None
    return None


def _steps(length: float, step: float) -> float:
    if length < 0:
        return -1.0
    ratio = length / step + 1e-9
    return math.floor(ratio) if math.isfinite(ratio) else math.inf


def lattice_count(src: dict) -> tuple[float, str] | None:
    """``(count, description)`` of a raw lattice table (sc, fcc, hcp, hex2d), or None."""
    lattice = src.get("lattice")
    if lattice == "hex2d":
        nc, nr = src.get("n_cols"), src.get("n_rows")
        if isinstance(nc, int) and isinstance(nr, int) and not isinstance(nc, bool) and nc > 0 and nr > 0:
            return float(nc) * float(nr), f"a hex2d layer of {nc} × {nr} spheres"
        return None
    r = _num(src.get("radius"))
    box = _region_box(src.get("region"))
    if r is None or r <= 0 or box is None or lattice not in ("sc", "fcc", "hcp"):
        return None
    s = _num(src.get("spacing")) or 2.0 * r
    if s <= 0:
        return None
    edges, cylinder, _ = box
    room = [e - 2.0 * r for e in edges]
    if min(room) < 0:
        return None  # nothing fits: the schema reports it
    if lattice == "sc":
        n = math.prod(_steps(L, s) + 1 for L in room)
    elif lattice == "fcc":
        h = s / math.sqrt(2.0)
        n = 0.5 * math.prod(_steps(L, h) + 1 for L in room)
    else:
        dy, dz = s * math.sqrt(3.0) / 2.0, s * math.sqrt(2.0 / 3.0)
        n = (_steps(room[0], s) + 2) * (_steps(room[1], dy) + 1) * (_steps(room[2], dz) + 1)
    if cylinder:
        n *= math.pi / 4.0
    shape = "×".join(f"{e:.3g}" for e in edges)
    where = (
        f"a cylinder of {edges[0] / 2:.3g} m radius and {edges[2]:.3g} m height"
        if cylinder
        else f"a {shape} m box"
    )
    return n, f"a {lattice} lattice of spheres of radius {r:.3g} m (spacing {s:.3g} m) in {where}"


def file_rows(path: Path) -> tuple[float, str] | None:
    """``(rows, description)`` of a packing file (HDF5 or text), or None if it cannot be read."""
    try:
        if not path.is_file():
            return None  # the schema reports a missing file
    except OSError:  # a name too long, a loop of links: the schema reports what the path is
        return None
    if path.suffix.lower() in (".h5", ".hdf5"):
        try:
            import h5py

            with h5py.File(path, "r") as f:
                for name in ("x", "position", "positions"):
                    if name in f and getattr(f[name], "shape", ()):
                        return float(
                            f[name].shape[0]
                        ), f"the packing file {path.name} ({name}: {f[name].shape[0]:,} rows)"
        except (OSError, ValueError):
            return None  # unreadable: reported when the file is read
        return None
    size = path.stat().st_size
    if size >= _COUNT_LINES_BELOW:
        n = size / _MIN_ROW_BYTES
        return (
            n,
            f"the packing file {path.name} ({_bytes(size)}: up to {_count(n)} rows of {_MIN_ROW_BYTES} B)",
        )
    lines = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            lines += chunk.count(b"\n")
    return float(lines), f"the packing file {path.name} ({lines:,} lines)"


def fill_count(src: dict, by_fraction: bool = True) -> tuple[float, str] | None:
    """``(count, description)`` of a raw table that gives ``n``, or (``by_fraction``) a
    ``volume_fraction`` of its ``region`` filled with spheres of its ``sizes``; None otherwise."""
    kind = src.get("source")
    n = src.get("n")
    if isinstance(n, int) and not isinstance(n, bool) and n > 0:
        return float(n), f"{kind} with n = {n:,}"
    if not by_fraction:
        return None
    vf = _num(src.get("volume_fraction"))
    box = _region_box(src.get("region"))
    r3 = _mean_r3(src.get("sizes"))
    if vf is not None and vf > 0 and box is not None and r3 is not None:
        n = vf * box[2] / (4.0 / 3.0 * math.pi * r3)
        return n, f"{kind} of volume fraction {vf:g} of a {box[2]:.3g} m³ region"
    return None


def _source_class(name: str) -> Any:
    """The source plugin registered as ``name``, or None (the deck reports an unknown source)."""
    from ..errors import PdemError
    from ..plugins import load

    try:
        return load("sources", name)
    except PdemError:
        return None


def estimate_source(src: Any, base_dir: Path) -> tuple[float, str] | None:
    """``(count, description)`` of one raw ``[[particles]]`` table, from its source plugin's
    ``estimate_count``; None if it cannot be estimated (an invalid table: the schema reports it; a
    source that does not say)."""
    if not isinstance(src, dict) or not isinstance(src.get("source"), str):
        return None
    cls = _source_class(src["source"])
    hook = getattr(cls, "estimate_count", None)
    if hook is None:
        return None
    out = hook(src, {"base_dir": str(base_dir)})
    if out is None:
        return None
    n, what = out
    return float(n), str(what)


def estimate_sources(data: dict, base_dir: Path) -> list[tuple[int, float, str]]:
    """``(source index, estimated count, description)`` of every source that can be estimated."""
    particles = data.get("particles") if isinstance(data, dict) else None
    out = []
    for k, src in enumerate(particles if isinstance(particles, list) else []):
        est = estimate_source(src, base_dir)
        if est is not None:
            out.append((k, est[0], est[1]))
    return out


def check_capacity(data: dict, base_dir: Path) -> list[tuple[Loc, str]]:
    """Problems if the deck's sources create more particles than ``run.max_particles`` allows (see the
    module doc); reads the raw deck (any type may be wrong: nothing is assumed)."""
    run = data.get("run") if isinstance(data, dict) else None
    given = run.get("max_particles") if isinstance(run, dict) else None
    if isinstance(given, int) and not isinstance(given, bool) and given >= 1:
        limit, why = given, "run.max_particles"
    else:
        limit, why = default_max_particles()
        why = f"run.max_particles is not given, so {why}"
    estimates = estimate_sources(data, base_dir)
    total = sum(n for _, n, _ in estimates)
    if total <= limit:
        return []
    remedy = (
        "use fewer or larger particles, a smaller region or volume fraction; or, if the run has that much "
        "memory (several machines), raise run.max_particles"
    )
    head = f"limit {limit:,} particles ({why})"
    problems: list[tuple[Loc, str]] = []
    for k, n, what in estimates:
        if n > limit:
            problems.append(
                (
                    ("particles", k),
                    f"{what} makes about {_count(n)} particles, needing about "
                    f"{_bytes(n * BYTES_PER_PARTICLE)} of memory at ~{BYTES_PER_PARTICLE:,} bytes per "
                    f"particle; above the {head}; {remedy}",
                )
            )
    if not problems:
        parts = ", ".join(f"particles.{k}: {_count(n)}" for k, n, _ in estimates if n > 0)
        problems.append(
            (
                ("particles",),
                f"the sources make about {_count(total)} particles together ({parts}), needing about "
                f"{_bytes(total * BYTES_PER_PARTICLE)} of memory at ~{BYTES_PER_PARTICLE:,} bytes per "
                f"particle; above the {head}; {remedy}",
            )
        )
    return problems
