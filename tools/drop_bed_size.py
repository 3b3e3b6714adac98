#!/usr/bin/env python
"""Does the drop bed set the answer? Drop the ball on a bed and on one twice as wide and deep.

    python tools/drop_bed_size.py [--width 0.1] [--depth 0.06] [--heights 0.02 0.05 0.1 0.3]
                                  [--ranks 2] [--out out/drop_bed] [--set KEY=VALUE ...]
                                  [--beds 1 2] [--carve S [--cut W D] | --lifts]

For each bed scale s in ``--beds`` (1: the given width and depth; 2: both doubled):

1. **Bed.** A deck (written to ``OUT/bed_s<s>/bed.toml``) fills a box ``s·width`` square at random
   with the 3 mm beads of ``inputs/cone_drop.toml`` (same material), at a solid fraction of 0.25 up
   to 2.4 × ``s·depth`` (which settles to about ``s·depth``), lets them fall and settle until
   their kinetic energy is below 3e-11 J per bead (about 1.3 mm/s each), and the settled bed is
   written as a packing file ``OUT/bed_s<s>/bed.txt``. Both beds are made the same way.
2. **Drops.** ``inputs/cone_drop.toml`` with its particles read from that file, its box the bed's,
   and its settle stage ending at the same kinetic energy per bead, is dropped from each height
   with :mod:`tools.cone_drop_series` (1-inch sphere, ``--tips sphere``), into ``OUT/drops_s<s>``.

With ``--carve S``, the first bed is not filled on its own but cut out of the bed of scale S
(its central ``width`` square and its top ``depth`` + 8 %, the grains wholly inside; lowered onto
the floor and settled again to the same rest criterion, in ``OUT/bed_s1_cut``), so that both beds
have the same surface packing and only the walls and the floor differ: what then changes the depth
is the bed's size, not how it was made. (Without the second settling the cut's rough underside
sags onto the floor during the drop deck's settle stage, which ends at its time limit with the bed
still moving.)

Finished steps are kept (a bed whose packing exists, a drop whose ``summary.json`` exists), so the
study can be stopped and started again. Last, ``OUT/bed_size.csv`` gives, for each height, the
final depth on each bed and the change from the first bed to the others, and ``OUT/bed_size.json``
the power-law fits d = A (H + d)^n of each bed.

``--cut W D`` (with ``--carve S``) cuts a bed of another width and depth, e.g. one as deep as the
large bed but narrower (only the walls differ) or as wide but shallower (only the floor differs),
into ``OUT/bed_cut_<W>x<D>mm``; its table is ``OUT/bed_size_cut_<W>x<D>mm.csv``.

``--lifts`` fills the bed of scale S in S lifts instead (``OUT/bed_s<S>_lifts``): each lift is
filled as the first bed is, at 0.25 up to 2.4 × ``depth`` above the last lift's highest bead, and
settled before the next, so that the top of every bed, where the ball stops, is made alike however
deep the bed (a one-lift fill of a deeper bed drops its beads from higher). Its table is
``OUT/bed_size_lifts.csv``.

Extra ``--set``s go to the drops (e.g. ``contact.law=complementarity``).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
R_BEAD = 0.0015  # m, the drop deck's beads
BEAD_MASS = 2500.0 * 4.0 / 3.0 * math.pi * R_BEAD**3
REST_ENERGY_PER_BEAD = 3e-11  # J: 1/2 m v² at v ≈ 1.3 mm/s

BED_DECK = """\
# A drop bed, made by tools/drop_bed_size.py: 3 mm beads filled at random and settled.
title = "Drop bed {width:.3g} x {width:.3g} m, {depth:.3g} m deep"

[run]
gravity = [0.0, 0.0, -9.81]
seed = {seed}

[contact]
law = "hertz_mindlin"

[contact.hertz_mindlin]
dt = 1.0e-5

[materials.bead]
density = 2500.0
youngs_modulus = 1.0e8
poisson_ratio = 0.3
restitution = 0.1
friction = 0.3

[materials.steel]
rigid = true
friction = 0.3

[[particles]]
source = "random_fill"
material = "bead"
region = {{ type = "box", lo = [{lo}, {lo}, {fill_bottom}], hi = [{hi}, {hi}, {fill_top}] }}
sizes = {{ type = "single", radius = {r} }}
volume_fraction = 0.25

[boundaries.box]
type = "box"
material = "steel"
lo = [{lo}, {lo}, 0.0]
hi = [{hi}, {hi}, {box_top}]
open_faces = ["zhi"]

[[stages]]
name = "settle"
[stages.end]
kinetic_energy_below = {rest}
max_time = 3.0
check_every = 500

[output]
formats = ["hdf5"]
every_time = 0.1
series_every_steps = 500
checkpoint_every_steps = 20000
"""


def bead_count(path: Path) -> int:
    with open(path) as fh:
        return sum(1 for line in fh if line.strip() and not line.lstrip().startswith("#")) - 1


def drop_deck(bed: Path, width: float, n: int) -> str:
    """inputs/cone_drop.toml with its particles read from ``bed`` and its box ``width`` wide."""
    text = (ROOT / "inputs" / "cone_drop.toml").read_text()
    deck = tomllib.loads(text)
    start = text.index("[[particles]]")
    end = text.index("[boundaries.box]")
    table = f'[[particles]]\nsource = "file"\nmaterial = "bead"\npath = "{bed.name}"\n\n'
    text = text[:start] + table + text[end:]
    old_box = deck["boundaries"]["box"]
    half = width / 2.0
    text = text.replace(f"lo = {_toml_list(old_box['lo'])}", f"lo = [{-half!r}, {-half!r}, 0.0]", 1)
    text = text.replace(f"hi = {_toml_list(old_box['hi'])}", f"hi = [{half!r}, {half!r}, 0.3]", 1)
    rest = f"kinetic_energy_below = {REST_ENERGY_PER_BEAD * n!r}"
    text, k = re.subn(r"(?m)^kinetic_energy_below = \S+", rest, text, count=1)
    if k != 1:
        raise SystemExit("drop_bed_size.py: inputs/cone_drop.toml's settle stage has no kinetic_energy_below")
    return text


def _toml_list(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def run(cmd: list[str], cwd: Path | None = None) -> None:
    print("$", " ".join(cmd), flush=True)
    code = subprocess.call(cmd, cwd=cwd)
    if code != 0:
        raise SystemExit(f"drop_bed_size.py: the command above failed with exit code {code}")


def _settle_run(out: Path, deck_name: str, packing: Path, ranks: int) -> tuple[np.ndarray, np.ndarray]:
    """Run ``out/deck_name`` (into ``out/run``) and write its settled grains as ``packing``."""
    from pdem.io.checkpoint import read_checkpoint
    from pdem.sources import write_spheres_text

    bin_dir = Path(sys.executable).parent
    head = [str(bin_dir / "mpiexec"), "-n", str(ranks)] if ranks > 1 else []
    run([*head, str(bin_dir / "pdem"), str(out / deck_name), "--output", str(out / "run"), "--overwrite"])
    state, _ = read_checkpoint(out / "run" / "checkpoints" / "latest.h5")
    x, r = state["particles/x"], state["particles/r"]
    tmp = packing.with_suffix(".tmp")
    write_spheres_text(tmp, x, r)
    tmp.replace(packing)
    return x, r


def _bed_deck(width: float, depth: float, seed: int, n: float, bottom: float = 0.0) -> str:
    """The fill-and-settle deck of a ``width`` square bed: beads filled at 0.25 from ``bottom`` up to
    ``bottom`` + 2.4 ``depth``, settled until their kinetic energy is below the rest threshold of
    ``n`` beads."""
    half = width / 2.0
    return BED_DECK.format(
        width=width, depth=depth, seed=seed, lo=repr(-half), hi=repr(half), fill_bottom=repr(bottom),
        fill_top=repr(bottom + 2.4 * depth), box_top=repr(bottom + 3.0 * depth), r=repr(R_BEAD),
        rest=repr(REST_ENERGY_PER_BEAD * n),
    )  # fmt: skip


def _with_file_source(deck: str, path: str, replace: bool = False) -> str:
    """``deck`` with a file source of ``path`` before its particle tables (the file's grains are
    source 0; the deck's own sources follow, each with the run's seed + its index), or instead of
    them with ``replace``."""
    start = deck.index("[[particles]]")
    rest = deck.index("[boundaries.box]") if replace else start
    table = f'[[particles]]\nsource = "file"\nmaterial = "bead"\npath = "{path}"\n\n'
    return deck[:start] + table + deck[rest:]


def make_bed(out: Path, width: float, depth: float, ranks: int, seed: int, lifts: int = 1) -> Path:
    """The settled bed's packing file (made once). With ``lifts`` > 1 the bed is filled in that
    many lifts, each as the one-lift bed of ``depth`` is made (filled at 0.25 up to 2.4 ``depth``
    above the last lift's highest bead, then settled), so that its top lift falls as far as a
    one-lift bed's beads do whatever the bed's depth."""
    from pdem.sources import read_spheres

    packing = out / "bed.txt"
    if packing.exists():
        return packing
    out.mkdir(parents=True, exist_ok=True)
    n_lift = 0.6 * width * width * depth / (4.0 / 3.0 * math.pi * R_BEAD**3)
    if lifts == 1:
        (out / "bed.toml").write_text(_bed_deck(width, depth, seed, n_lift))
        x, r = _settle_run(out, "bed.toml", packing, ranks)
    else:
        below: Path | None = None
        for k in range(1, lifts + 1):
            lift_dir = out / f"lift{k}"
            lift = lift_dir / "bed.txt"
            if not lift.exists():
                lift_dir.mkdir(parents=True, exist_ok=True)
                if below is None:
                    deck = _bed_deck(width, depth, seed, n_lift)
                else:
                    d = read_spheres(below)
                    top = float(np.max(d["positions"][:, 2] + d["radii"]))
                    # each lift its own random stream: the run's seed, offset per lift
                    deck = _bed_deck(width, depth, seed + 1000 * (k - 1), k * n_lift, bottom=top)
                    deck = _with_file_source(deck, str(below.resolve()))
                (lift_dir / "bed.toml").write_text(deck)
                _settle_run(lift_dir, "bed.toml", lift, ranks)
            below = lift
        assert below is not None
        d = read_spheres(below)
        x, r = d["positions"], d["radii"]
        tmp = packing.with_suffix(".tmp")
        shutil.copyfile(below, tmp)
        tmp.replace(packing)
    top = float(np.max(x[:, 2] + r))
    print(f"bed: {len(r)} beads, highest bead top {top:.4f} m", flush=True)
    return packing


def settle_packing(out: Path, cut: Path, width: float, depth: float, ranks: int) -> Path:
    """``cut`` (a packing in ``out``) settled under gravity in its ``width`` box until its kinetic
    energy is below the beds' rest threshold (as :func:`make_bed` settles a fill), written as
    ``out/bed.txt``."""
    packing = out / "bed.txt"
    deck = _with_file_source(_bed_deck(width, depth, 1, bead_count(cut)), cut.name, replace=True)
    deck = deck.replace("# A drop bed, made by", "# A drop bed cut from a larger one, settled again by", 1)
    (out / "settle.toml").write_text(deck)
    x, r = _settle_run(out, "settle.toml", packing, ranks)
    print(f"cut bed settled: {len(r)} beads, highest bead top {float(np.max(x[:, 2] + r)):.4f} m", flush=True)
    return packing


def carve_bed(out: Path, source: Path, width: float, depth: float, ranks: int) -> Path:
    """The bed cut out of the packing ``source``: grains wholly inside the central ``width`` square
    and within 1.08 ``depth`` of its top (the fill's beds settle about 8 % above ``depth``),
    lowered so that the lowest touches the floor, then settled again to rest
    (:func:`settle_packing`): the cut's underside is rough, so it sags onto the floor, and a drop
    deck's short settle stage does not bring it to rest."""
    from pdem.sources import read_spheres, write_spheres_text

    packing = out / "bed.txt"
    if packing.exists():
        return packing
    out.mkdir(parents=True, exist_ok=True)
    d = read_spheres(source)
    x, r = d["positions"], d["radii"]
    top = float(np.max(x[:, 2] + r))
    half = width / 2.0
    keep = (
        (np.abs(x[:, 0]) + r <= half) & (np.abs(x[:, 1]) + r <= half) & (x[:, 2] - r >= top - 1.08 * depth)
    )
    x, r = x[keep].copy(), r[keep]
    x[:, 2] -= float(np.min(x[:, 2] - r))
    cut = out / "cut.txt"
    tmp = cut.with_suffix(".tmp")
    write_spheres_text(tmp, x, r)
    tmp.replace(cut)
    print(f"bed carved from {source}: {len(r)} beads, top {float(np.max(x[:, 2] + r)):.4f} m", flush=True)
    return settle_packing(out, cut, width, depth, ranks)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=float, default=0.1, help="the first bed's width [m]")
    ap.add_argument("--depth", type=float, default=0.06, help="the first bed's depth [m] (about)")
    ap.add_argument("--heights", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.3], help="H [m]")
    ap.add_argument("--beds", type=int, nargs="+", default=[1, 2], help="bed scales (1: as given)")
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out") / "drop_bed")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--carve", type=int, default=None, metavar="S",
                    help="cut the first bed out of the bed of scale S (made first) instead of "
                    "filling it")  # fmt: skip
    ap.add_argument("--cut", type=float, nargs=2, default=None, metavar=("W", "D"),
                    help="with --carve: cut a W wide, D deep bed [m] instead of the first bed's width "
                    "and depth (D larger than the source bed keeps its whole depth); written to "
                    "OUT/bed_cut_<W>x<D>mm")  # fmt: skip
    ap.add_argument("--lifts", action="store_true",
                    help="fill the bed of scale S in S lifts, each made as the first bed is (filled up "
                    "to 2.4 times its depth above the last lift, then settled), so that every bed's top "
                    "is made alike; written to OUT/bed_s<S>_lifts")  # fmt: skip
    args = ap.parse_args(argv)
    if args.lifts and args.carve is not None:
        ap.error("--lifts and --carve: give one of them (a cut bed is not filled)")
    if args.lifts and any(b < 1 for b in args.beds):
        ap.error(f"--lifts: the bed scales {args.beds} must be whole numbers of lifts (1 or more)")
    if args.carve is not None and args.carve not in args.beds[1:]:
        ap.error(f"--carve {args.carve}: the scale to carve from must be one of the later --beds")
    if args.cut is not None:
        if args.carve is None:
            ap.error("--cut: give --carve S too (the bed to cut from)")
        if not all(math.isfinite(v) and v > 0.0 for v in args.cut):
            ap.error(f"--cut {args.cut[0]} {args.cut[1]}: the width and depth must be positive lengths in m")
        if args.cut[0] > args.carve * args.width:
            ap.error(f"--cut: a width of {args.cut[0]} m is wider than the bed it is cut from "
                     f"({args.carve * args.width} m)")  # fmt: skip
    cut_tag = None if args.cut is None else f"cut_{args.cut[0] * 1000:.0f}x{args.cut[1] * 1000:.0f}mm"
    out = args.out.resolve()
    fits, depths = {}, {}
    order = [args.carve, *[b for b in args.beds if b != args.carve]] if args.carve else args.beds
    for s in order:
        width, depth = s * args.width, s * args.depth
        if args.carve and s == args.beds[0]:
            source = out / f"bed_s{args.carve}" / "bed.txt"
            name = f"bed_s{s}_cut"
            if cut_tag is not None:
                width, depth = args.cut
                name = f"bed_{cut_tag}"
            bed = carve_bed(out / name, source, width, depth, args.ranks)
        elif args.lifts and s > 1:
            bed = make_bed(out / f"bed_s{s}_lifts", width, args.depth, args.ranks, args.seed, lifts=s)
        else:
            bed = make_bed(out / f"bed_s{s}", width, depth, args.ranks, args.seed)
        n = bead_count(bed)
        deck = bed.parent / "drop.toml"
        deck.write_text(drop_deck(bed, width, n))
        series = out / f"drops_{bed.parent.name.removeprefix('bed_')}"
        cmd = [sys.executable, str(ROOT / "tools" / "cone_drop_series.py"), str(deck), "--tips", "sphere",
               "--heights", *map(str, args.heights), "--ranks", str(args.ranks),
               "--out", str(series)]  # fmt: skip
        for o in args.overrides:
            cmd += ["--set", o]
        run(cmd)
        result = json.loads((series / "drop_series.json").read_text())
        fits[s] = {"beads": n, "width": width, "depth": depth, **result["fits"]["sphere"]}
        depths[s] = {round(float(r["H_m"]), 6): float(r["depth_m"]) for r in result["runs"]}
    first = args.beds[0]
    rows = []
    for h in args.heights:
        row = {"H": h}
        for s in args.beds:
            d = depths[s].get(round(h, 6), math.nan)
            row[f"d_s{s}"] = d
            if s != first:
                row[f"change_s{s}"] = d / depths[first].get(round(h, 6), math.nan) - 1.0
        rows.append(row)
    stem = "bed_size" if cut_tag is None else f"bed_size_{cut_tag}"
    if args.lifts:
        stem = "bed_size_lifts"
    with open(out / f"{stem}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (out / f"{stem}.json").write_text(json.dumps({"beds": fits, "rows": rows}, indent=2))
    for row in rows:
        print("  ".join(f"{k} = {v:.4g}" for k, v in row.items()), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
