#!/usr/bin/env python3
"""Chart where DEM-P fails in each experiment against the two step estimates.

    python tools/stability_chart.py docs/study/stability/steps.csv docs/study/stability/steps.png

The CSV has one row per run: ``experiment``, ``dt_over_TR`` (the step over the Rayleigh time),
``outcome`` (stable, drift, silent, caught) and, on one row per experiment, ``bound_over_TR``: the
smallest live step bound of a stable run (pdem.contact.stability), over T_R. Each experiment is a
row of the chart: its runs as markers along a log step axis, the Rayleigh estimate (1) and the
live bound (a bar) drawn over them. Also prints, per experiment, the interval in which the run
fails (last run that is not silent or caught, first that is) over each estimate.
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

STYLE = {
    "stable": dict(marker="o", color="#2a7", label="stable"),
    "drift": dict(marker="o", color="#db2", label="drift (off by more than the scatter)"),
    "silent": dict(marker="X", color="#c22", label="silent failure (ends normally, results wrong)"),
    "caught": dict(marker="s", color="#555", label="caught (exit 3)"),
}


def read(path: Path) -> dict[str, dict]:
    out: dict[str, dict] = {}
    with path.open(newline="") as fh:
        for row in csv.DictReader(fh):
            e = out.setdefault(row["experiment"], {"runs": [], "bound": math.nan})
            e["runs"].append((float(row["dt_over_TR"]), row["outcome"].strip()))
            if row.get("bound_over_TR"):
                e["bound"] = float(row["bound_over_TR"])
    return out


def failure_interval(runs: list[tuple[float, str]]) -> tuple[float, float]:
    """(largest step that did not fail, smallest that did); a failure is silent or caught."""
    good = [x for x, o in runs if o in ("stable", "drift")]
    bad = [x for x, o in runs if o in ("silent", "caught")]
    return (max(good) if good else math.nan, min(bad) if bad else math.nan)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("csv", type=Path)
    ap.add_argument("out", type=Path, help="PNG (an SVG is written beside it)")
    args = ap.parse_args(argv)
    data = read(args.csv)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(data)
    fig, ax = plt.subplots(figsize=(8, 0.8 + 0.7 * len(names)))
    seen = set()
    print(f"{'experiment':14s} {'fails in (dt/T_R)':>20s} {'bound/T_R':>10s} {'failure/bound':>16s}")
    for k, name in enumerate(names):
        y = len(names) - 1 - k
        e = data[name]
        for x, outcome in e["runs"]:
            st = STYLE[outcome]
            ax.scatter([x], [y], s=60, marker=st["marker"], color=st["color"], zorder=3,
                       label=st["label"] if outcome not in seen else None)
            seen.add(outcome)
        b = e["bound"]
        if math.isfinite(b):
            ax.plot([b, b], [y - 0.3, y + 0.3], color="#15c", lw=3, zorder=2,
                    label="live step bound" if "bound" not in seen else None)
            seen.add("bound")
        lo, hi = failure_interval(e["runs"])
        print(f"{name:14s} {f'({lo:.3g}, {hi:.3g}]':>20s} {b:10.3g} {f'({lo / b:.2f}, {hi / b:.2f}]':>16s}")
    ax.axvline(1.0, color="#888", ls="--", lw=1, label="Rayleigh estimate T_R")
    ax.set_yticks(range(len(names)))
    ax.set_yticklabels(names[::-1])
    ax.set_xscale("log")
    ax.set_xlabel("dt / T_R")
    ax.set_ylim(-0.6, len(names) - 0.4)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.set_title("DEM-P: where each experiment fails, against the two step estimates", fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=130)
    fig.savefig(args.out.with_suffix(".svg"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
