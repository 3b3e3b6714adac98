#!/usr/bin/env python
"""Curves of a triaxial run: deviator and volumetric strain against axial strain.

    python tools/triaxial_plots.py OUTPUT [OUTPUT ...] [--boundary cell] [--png FILE]

Reads ``series_<shear stage>.csv`` of each output directory (the stage in which ``<boundary>.eps_a``
grows) and writes ``triaxial.png`` (in the first directory unless ``--png``) with three panels:
q/p and q against ε_a, ε_v against ε_a (contraction positive), and the boundary stresses σ₁, σ₃
against the grains' own (Love–Weber) stresses — and ``triaxial_curves.csv`` beside it (ε_a, q, p,
ε_v, σ₁, σ₃ of every row while shearing). Several outputs (e.g. three confining pressures, or DEM-P
and DEM-C) are drawn on the same axes, labelled by directory name.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np


def shear_rows(out: Path, boundary: str) -> dict[str, np.ndarray]:
    """The series rows while shearing (ε_a > 0) of the stage files of ``out``, in order."""
    from pdem.io.series import read_series

    rows: dict[str, list] = {}
    for path in sorted(out.glob("series_*.csv"), key=lambda p: p.stat().st_mtime):
        s = read_series(path)
        key = f"{boundary}.eps_a"
        if key not in s or not np.any(np.asarray(s[key]) > 0):
            continue
        sel = np.asarray(s[key]) > 0
        for k, v in s.items():
            rows.setdefault(k, []).append(np.asarray(v, dtype=float)[sel])
    if not rows:
        raise SystemExit(f"{out}: no series with {boundary}.eps_a > 0 (was the shear stage run?)")
    return {k: np.concatenate(v) for k, v in rows.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outputs", type=Path, nargs="+")
    ap.add_argument("--boundary", default="cell", help="the triaxial boundary's name (default: cell)")
    ap.add_argument("--png", type=Path, default=None)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b = args.boundary
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
    for out in args.outputs:
        s = shear_rows(out, b)
        ea, q, p, ev = (s[f"{b}.{k}"] for k in ("eps_a", "q", "p", "eps_v"))
        label = out.name
        ax[0].plot(100 * ea, q / p, label=f"{label}: q/p")
        ax[1].plot(100 * ea, 100 * ev, label=label)
        ax[2].plot(100 * ea, s[f"{b}.sigma1"] / 1e3, label=f"{label}: σ1 (platen)")
        ax[2].plot(100 * ea, s[f"{b}.lw_szz"] / 1e3, "--", label=f"{label}: σzz (grains)")
        ax[2].plot(100 * ea, s[f"{b}.sigma3"] / 1e3, label=f"{label}: σ3 (membrane)")
        ax[2].plot(100 * ea, s[f"{b}.lw_srr"] / 1e3, "--", label=f"{label}: σrr (grains)")
        with open(out / "triaxial_curves.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["eps_a", "q", "p", "eps_v", "sigma1", "sigma3", "lw_szz", "lw_srr"])
            for row in zip(ea, q, p, ev, s[f"{b}.sigma1"], s[f"{b}.sigma3"], s[f"{b}.lw_szz"],
                           s[f"{b}.lw_srr"], strict=True):  # fmt: skip
                w.writerow([f"{v:.8g}" for v in row])
    ax[0].set(xlabel="axial strain ε_a [%]", ylabel="q / p", title="stress ratio")
    ax[1].set(xlabel="axial strain ε_a [%]", ylabel="volumetric strain ε_v [%] (contraction > 0)",
              title="volume change")  # fmt: skip
    ax[2].set(xlabel="axial strain ε_a [%]", ylabel="stress [kPa]", title="boundary vs grains (Love–Weber)")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    png = args.png or (args.outputs[0] / "triaxial.png")
    fig.savefig(png, dpi=120)
    print(f"wrote {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
