#!/usr/bin/env python
"""Tip resistance against depth of cone-penetration runs (DEM-P and DEM-C on one plot).

    python tools/penetration_plots.py OUTPUT [OUTPUT ...] [--boundary pen] [--png FILE]
                                      [--from DEPTH] [--to DEPTH] [--bin 0.001] [--label NAME ...]

Reads the series of each output directory (the rows where ``<boundary>.depth`` is finite, in stage
order) and writes ``penetration.png`` (in the first directory unless ``--png``) with q_c and the
shaft force against depth, one curve per run, labelled by ``--label`` or by the run's contact law
and directory, and ``penetration.csv`` beside it: q_c binned by depth (``--bin`` m) for every run
side by side. It prints, for each run, the mean q_c over the depth window [``--from``, ``--to``]
(default: from the cone length — the tip buried — to the deepest depth all runs reached) and, for
two or more runs, each run's mean relative to the first's.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tomllib
from pathlib import Path

import numpy as np


def read_run(out: Path, boundary: str) -> dict[str, np.ndarray]:
    """The rows of ``out``'s series where the penetrometer is active, in stage order."""
    from pdem.io.series import read_series

    deck = tomllib.loads((out / "deck.resolved.toml").read_text())
    cols: dict[str, list] = {}
    for stage in deck.get("stages", []):
        path = out / f"series_{stage['name']}.csv"
        if not path.is_file():
            continue
        s = read_series(path)
        key = f"{boundary}.depth"
        if key not in s:
            continue
        sel = np.isfinite(np.asarray(s[key], dtype=float))
        for k, v in s.items():
            cols.setdefault(k, []).append(np.asarray(v, dtype=float)[sel])
    if not cols:
        raise SystemExit(f"{out}: no series with {boundary}.depth (was the penetration stage run?)")
    run = {k: np.concatenate(v) for k, v in cols.items()}
    run["_law"] = deck.get("contact", {}).get("law", "?")
    summary = out / "summary.json"
    run["_summary"] = json.loads(summary.read_text()) if summary.is_file() else {}
    run["_deck"] = deck
    return run


def cone_length(deck: dict, boundary: str) -> float:
    b = deck["boundaries"][boundary]
    if b.get("tip", "cone") != "cone":
        return 0.0
    d = b.get("diameter") or math.sqrt(4.0 * b.get("base_area", 323e-6) / math.pi)
    return 0.5 * d / math.tan(math.radians(0.5 * b.get("apex_deg", 60.0)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outputs", nargs="+", type=Path)
    ap.add_argument("--boundary", default="pen")
    ap.add_argument("--png", type=Path, default=None)
    ap.add_argument("--from", dest="lo", type=float, default=None, help="window start depth [m]")
    ap.add_argument("--to", dest="hi", type=float, default=None, help="window end depth [m]")
    ap.add_argument("--bin", type=float, default=1e-3, help="depth bin of the CSV [m]")
    ap.add_argument("--label", nargs="*", default=None)
    args = ap.parse_args(argv)
    runs = [read_run(o, args.boundary) for o in args.outputs]
    labels = args.label or [f"{r['_law']} ({o.name})" for r, o in zip(runs, args.outputs, strict=True)]
    b = args.boundary
    lo = args.lo if args.lo is not None else max(cone_length(r["_deck"], b) for r in runs)
    hi = args.hi if args.hi is not None else min(float(np.nanmax(r[f"{b}.depth"])) for r in runs)
    means = []
    for r, lab in zip(runs, labels, strict=True):
        d, q = r[f"{b}.depth"], r[f"{b}.qc"]
        sel = (d >= lo) & (d <= hi)
        m = float(np.mean(q[sel])) if sel.any() else math.nan
        means.append(m)
        wall = r["_summary"].get("wall_time_s")
        print(f"{lab}: mean q_c over {lo * 100:.2f}–{hi * 100:.2f} cm = {m:.1f} Pa ({int(sel.sum())} rows, "
              f"std {float(np.std(q[sel])) if sel.any() else math.nan:.1f} Pa); final depth "
              f"{float(d[-1]) * 100:.2f} cm; stepping {wall if wall is None else round(wall)} s")  # fmt: skip
    for m, lab in zip(means[1:], labels[1:], strict=True):
        print(f"{lab} / {labels[0]}: {m / means[0]:.3f} ({(m / means[0] - 1) * 100:+.1f} %)")
    # binned CSV
    top = max(float(np.nanmax(r[f"{b}.depth"])) for r in runs)
    edges = np.arange(0.0, top + args.bin, args.bin)
    png = args.png or args.outputs[0] / "penetration.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    with (png.parent / "penetration.csv").open("w") as fh:
        fh.write("depth_m," + ",".join(f"qc_Pa[{lab}]" for lab in labels) + "\n")
        for k in range(len(edges) - 1):
            row = [f"{0.5 * (edges[k] + edges[k + 1]):.5f}"]
            for r in runs:
                d, q = r[f"{b}.depth"], r[f"{b}.qc"]
                sel = (d >= edges[k]) & (d < edges[k + 1])
                row.append(f"{float(np.mean(q[sel])):.6g}" if sel.any() else "")
            fh.write(",".join(row) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 5), sharey=True)
    for r, lab in zip(runs, labels, strict=True):
        d = r[f"{b}.depth"] * 100
        ax1.plot(r[f"{b}.qc"] / 1e3, d, lw=1, label=lab)
        ax2.plot(r[f"{b}.shaft_force"], d, lw=1, label=lab)
    for ax in (ax1, ax2):
        ax.axhspan(lo * 100, hi * 100, color="0.9", zorder=0)
        ax.grid(alpha=0.3)
    ax1.invert_yaxis()
    ax1.set_xlabel("tip resistance q_c [kPa]")
    ax1.set_ylabel("tip depth below the bed surface [cm]")
    ax2.set_xlabel("shaft force [N]")
    ax1.legend(fontsize=8)
    ax1.set_title("q_c (shaded: the window of the means)", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    print(f"wrote {png} and {png.parent / 'penetration.csv'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
