#!/usr/bin/env python
"""Plot the time series of a pdem output directory (matplotlib, Agg: no display needed).

    python tools/plot_series.py OUTPUT_DIR [--out PNG] [--discharge-out PNG]

Reads every ``series_<stage>.csv`` of OUTPUT_DIR (stages in deck order, from
``deck.resolved.toml``; else by start time) and draws, against time:

* the kinetic energy (translational, rotational and total) on a log scale;
* every measured quantity: the particle count, and each boundary measurement. A wall's force
  components ``NAME.fx/.fy/.fz`` share one panel, and so do the contact counts of a boundary's
  walls; every other column gets its own panel;

with the stage boundaries marked as dashed vertical lines in every panel (stage names on top).
Written to ``--out`` (default ``OUTPUT_DIR/series.png``).

When a ``<boundary>.discharged_mass`` column exists (hopper, silo) a second figure shows the
discharged mass against time with the steady flow-rate fit of ``summary.json``
(``results.<boundary>.flow_rate`` [kg/s]): the fitted line over the 20–80 % window of the final mass,
annotated with W in g/s. (When the summary holds no flow rate yet, e.g. a run still going, the same
fit is made from the series and labelled so.) Written to ``--discharge-out`` (default
``OUTPUT_DIR/discharge.png``, or ``<out stem>_discharge.png`` beside ``--out``).

Importable: ``plot_series(output_dir, path=None) -> Path`` and
``plot_discharge(output_dir, path=None) -> Path | None`` (None when there is no discharge column).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["read_stages", "plot_series", "plot_discharge", "main"]

_BASE = ("time", "step", "ke_trans", "ke_rot")
_FORCE = ("fx", "fy", "fz")


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return {}
    header, body = rows[0], [r for r in rows[1:] if len(r) == len(rows[0])]
    out: dict[str, np.ndarray] = {}
    for i, name in enumerate(header):
        try:
            out[name] = np.array([float(r[i]) if r[i] != "" else math.nan for r in body])
        except ValueError:  # a text column: not plotted
            continue
    return out


def _deck(output_dir: Path) -> dict:
    try:
        return tomllib.loads((output_dir / "deck.resolved.toml").read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return {}


def read_stages(output_dir: Path | str) -> list[tuple[str, dict[str, np.ndarray]]]:
    """``[(stage, {column: values})]`` for every ``series_<stage>.csv``, in stage order."""
    output_dir = Path(output_dir)
    found = {p.name[len("series_") : -len(".csv")]: p for p in output_dir.glob("series_*.csv")}
    if not found:
        raise FileNotFoundError(f"no series_<stage>.csv in {output_dir}: is it a pdem output directory?")
    order = [s.get("name") for s in _deck(output_dir).get("stages", [])]
    stages = [(name, _read_csv(found[name])) for name in order if name in found]
    rest = [(name, _read_csv(p)) for name, p in found.items() if name not in order]
    rest.sort(key=lambda item: float(item[1]["time"][0]) if len(item[1].get("time", [])) else math.inf)
    return [(n, d) for n, d in stages + rest if len(d.get("time", []))]


def _merged(stages: list[tuple[str, dict[str, np.ndarray]]]) -> dict[str, np.ndarray]:
    keys: list[str] = []
    for _, d in stages:
        keys += [k for k in d if k not in keys]
    return {k: np.concatenate([d.get(k, np.full(len(d["time"]), math.nan)) for _, d in stages]) for k in keys}


def _unit(column: str) -> str:
    leaf = column.rsplit(".", 1)[-1]
    if leaf in _FORCE:
        return "N"
    if leaf.endswith("mass"):
        return "kg"
    if leaf.startswith("t") and leaf[1:] in ("x", "y", "z"):
        return "N m"
    if leaf in ("contacts", "particles") or leaf.endswith("count"):
        return "count"
    if leaf.endswith(("height", "position", "gap", "depth")):
        return "m"
    if leaf.endswith(("velocity", "speed")):
        return "m/s"
    if leaf.endswith(("energy", "work")):
        return "J"
    return ""


def _panels(columns: list[str]) -> list[tuple[str, str, list[tuple[str, str]]]]:
    """Group the measured columns: ``[(title, unit, [(column, legend label)])]``."""
    panels: dict[str, tuple[str, str, list[tuple[str, str]]]] = {}
    for c in columns:
        if c in _BASE:
            continue
        parts = c.split(".")
        if len(parts) >= 2 and parts[-1] in _FORCE:
            key = ".".join(parts[:-1]) + " force"
            label = parts[-1]
        elif len(parts) >= 3 and parts[-1] == "contacts":
            key = parts[0] + " wall contacts"
            label = ".".join(parts[1:-1])
        else:
            key, label = c, ""
        if key not in panels:
            panels[key] = (key, _unit(c), [])
        panels[key][2].append((c, label))
    return list(panels.values())


def _mark_stages(ax, starts: list[tuple[str, float]], t_end: float, label: bool = False) -> None:
    """Dashed lines at the stage starts, every other stage lightly shaded, names inside the top."""
    for i, (name, t0) in enumerate(starts):
        t1 = starts[i + 1][1] if i + 1 < len(starts) else t_end
        if i > 0:
            ax.axvline(t0, color="0.35", ls="--", lw=0.9, zorder=0)
        if i % 2:
            ax.axvspan(t0, t1, color="0.5", alpha=0.07, lw=0, zorder=0)
        if label:
            ax.text(
                t0,
                0.97,
                f" {name}",
                transform=ax.get_xaxis_transform(),
                fontsize=8.5,
                color="0.25",
                ha="left",
                va="top",
                style="italic",
            )


def plot_series(output_dir: Path | str, path: Path | str | None = None) -> Path:
    """Energies and every measured quantity against time, one panel each; returns the PNG path."""
    output_dir = Path(output_dir)
    stages = read_stages(output_dir)
    data = _merged(stages)
    t = data["time"]
    starts = [(name, float(d["time"][0])) for name, d in stages]
    t_end = float(np.nanmax(t))
    panels = _panels(list(data))
    n = 1 + len(panels)
    ncols = 1 if n <= 3 else 2
    nrows = math.ceil(n / ncols)
    fig, axes = plt.subplots(
        nrows, ncols, figsize=(6.4 * ncols, 2.6 * nrows + 0.8), sharex=True, squeeze=False
    )
    flat = axes.ravel()

    ax = flat[0]
    ke_t = data.get("ke_trans", np.full(len(t), math.nan))
    ke_r = data.get("ke_rot", np.zeros(len(t)))
    for y, lab, style in (
        (ke_t + ke_r, "total", "-"),
        (ke_t, "translational", "--"),
        (ke_r, "rotational", ":"),
    ):
        y = np.where(y > 0, y, np.nan)
        if np.isfinite(y).any():
            ax.plot(t, y, style, label=lab, lw=1.4 if lab == "total" else 1.0)
    ax.set_yscale("log")
    ax.set_ylabel("kinetic energy [J]")
    ax.set_title("kinetic energy (stages marked)", fontsize=10, loc="left")
    ax.legend(fontsize=8, loc="lower right")
    _mark_stages(ax, starts, t_end, label=True)

    for ax, (title, unit, cols) in zip(flat[1:], panels, strict=False):
        for c, lab in cols:
            ax.plot(t, data[c], lw=1.2, label=lab or None)
        if any(lab for _, lab in cols):
            ax.legend(fontsize=8, loc="best", ncols=min(3, len(cols)))
        ax.set_ylabel(f"[{unit}]" if unit else "")
        ax.set_title(title, fontsize=10, loc="left")
        _mark_stages(ax, starts, t_end)
    for ax in flat[n:]:
        ax.set_visible(False)
    for ax in flat[:n]:
        ax.grid(alpha=0.3)
        ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4))
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
        ax.xaxis.set_tick_params(labelbottom=True)
    if n % ncols and nrows > 1:  # the panel above the hidden one gets the x labels
        above = axes[-2, -1]
        above.set_xlabel("time [s]")
        above.xaxis.set_tick_params(labelbottom=True)
    title = _deck(output_dir).get("title") or output_dir.name
    fig.suptitle(f"{title}\ntime series ({', '.join(n for n, _ in stages)})", fontsize=11)
    fig.tight_layout()
    path = Path(path) if path is not None else output_dir / "series.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _fit_window(t: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Rows inside the 20–80 % window of the final mass (as the hopper's summary fit uses)."""
    final = m[-1]
    return (m >= 0.2 * final) & (m <= 0.8 * final)


def plot_discharge(output_dir: Path | str, path: Path | str | None = None) -> Path | None:
    """Discharged mass vs time with the steady flow-rate fit; None without a ``*.discharged_mass`` column."""
    output_dir = Path(output_dir)
    stages = read_stages(output_dir)
    data = _merged(stages)
    columns = [c for c in data if c.endswith(".discharged_mass")]
    if not columns:
        return None
    try:
        summary = json.loads((output_dir / "summary.json").read_text())
    except (OSError, json.JSONDecodeError):
        summary = {}
    t = data["time"]
    starts = [(name, float(d["time"][0])) for name, d in stages]
    fig, ax = plt.subplots(figsize=(8.0, 5.0))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    notes = []
    for k, col in enumerate(columns):
        boundary = col[: -len(".discharged_mass")]
        m = data[col]
        ok = np.isfinite(m)
        tt, mm = t[ok], m[ok]
        color = colors[k % len(colors)]
        ax.plot(tt, 1e3 * mm, color=color, lw=1.6, label=f"{boundary}: discharged mass")
        if len(mm) < 3 or mm[-1] <= 0:
            continue
        w = summary.get("results", {}).get(boundary, {}).get("flow_rate")
        source = "summary.json"
        sel = _fit_window(tt, mm)
        if w is None and sel.sum() >= 3:
            w = float(np.polyfit(tt[sel], mm[sel], 1)[0])
            source = "fit of the series (no flow rate in summary.json)"
        if w is None or sel.sum() < 2:
            continue
        # the least-squares line passes through the centroid of the fitted points
        tc, mc = float(tt[sel].mean()), float(mm[sel].mean())
        t0, t1 = float(tt[sel].min()), float(tt[sel].max())
        pad = 0.08 * (t1 - t0)
        tl = np.array([t0 - pad, t1 + pad])
        ax.plot(tl, 1e3 * (mc + w * (tl - tc)), "--", color="crimson", lw=1.8, label=f"steady fit ({source})")
        ax.axhspan(1e3 * 0.2 * mm[-1], 1e3 * 0.8 * mm[-1], color=color, alpha=0.08, lw=0)
        ax.text(
            0.01,
            1e3 * 0.8 * mm[-1],
            "fit window:\n20–80 % of the final mass",
            fontsize=8,
            color="0.3",
            va="top",
            ha="left",
            transform=ax.get_yaxis_transform(),
        )
        notes.append(f"W = {1e3 * w:.3g} g/s")
        ax.annotate(
            f"W = {1e3 * w:.3g} g/s",
            xy=(tc, 1e3 * mc),
            xytext=(-25, 40),
            textcoords="offset points",
            ha="right",
            fontsize=13,
            arrowprops=dict(arrowstyle="->", color="black"),
            bbox=dict(boxstyle="round,pad=0.3", fc="white", ec="0.6"),
        )
    _mark_stages(ax, starts, float(np.nanmax(t)), label=True)
    ax.set_xlabel("time [s]")
    ax.ticklabel_format(axis="x", style="sci", scilimits=(-3, 4))
    ax.set_ylabel("discharged mass [g]")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=9)
    title = _deck(output_dir).get("title") or output_dir.name
    ax.set_title(f"{title}\n" + ("; ".join(notes) if notes else "discharge"), fontsize=10)
    fig.tight_layout()
    path = Path(path) if path is not None else output_dir / "discharge.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Plot the time series of a pdem output directory.")
    ap.add_argument("output_dir", type=Path, help="pdem output directory (with series_<stage>.csv)")
    ap.add_argument(
        "--out", type=Path, default=None, help="PNG for the series (default OUTPUT_DIR/series.png)"
    )
    ap.add_argument(
        "--discharge-out",
        type=Path,
        default=None,
        help="PNG for the discharge plot (default OUTPUT_DIR/discharge.png, or beside --out)",
    )
    args = ap.parse_args(argv)
    try:
        print(plot_series(args.output_dir, args.out))
        dis = args.discharge_out
        if dis is None and args.out is not None:
            dis = args.out.with_name(args.out.stem + "_discharge.png")
        done = plot_discharge(args.output_dir, dis)
    except FileNotFoundError as exc:
        print(f"plot_series: {exc}", file=sys.stderr)
        return 2
    if done is not None:
        print(done)
    return 0


if __name__ == "__main__":
    sys.exit(main())
