#!/usr/bin/env python
"""Curves of a triaxial run: deviator and volumetric strain against axial strain.

    python tools/triaxial_plots.py OUTPUT [OUTPUT ...] [--boundary cell] [--png FILE]

Reads ``series_<shear stage>.csv`` of each output directory (the stage in which ``<boundary>.eps_a``
grows) and writes ``triaxial.png`` (in the first directory unless ``--png``) with four panels:
q/p and q against ε_a, ε_v against ε_a (contraction positive), the boundary stresses σ₁, σ₃
against the grains' own (Love–Weber) stresses, and the specimen's outer radius against height at
the start of the shear and at ε_a = ``--profile-at`` (default 15 %: bulging) — and
prints how far the end grains stand past the platens' edge and, with tied ends, the rings' shares;
``triaxial_curves.csv`` (ε_a, q, p, ε_v, σ₁, σ₃ of every row while shearing) and
``triaxial_profile.csv`` beside it. Several outputs (e.g. three confining pressures, or DEM-P
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


def radius_profile(
    x: np.ndarray, r: np.ndarray, centre: np.ndarray, n_z: int = 12
) -> tuple[np.ndarray, np.ndarray]:
    """The specimen's outer radius against height: the grains are cut into ``n_z`` slices between
    the lowest and highest grain surface and, in each slice, into sectors about one grain diameter
    wide along the circumference; a slice's radius is the mean over its sectors of the outermost
    grain's ρ + r (as the membrane finds it). Returns (z of the slice centres, radius)."""
    rho = np.hypot(x[:, 0] - centre[0], x[:, 1] - centre[1])
    theta = np.arctan2(x[:, 1] - centre[1], x[:, 0] - centre[0])
    lo, hi = float((x[:, 2] - r).min()), float((x[:, 2] + r).max())
    edges = np.linspace(lo, hi, n_z + 1)
    n_t = max(int(2 * np.pi * np.percentile(rho + r, 99) / (2 * np.mean(r))), 6)
    zs, radii = [], []
    for k in range(n_z):
        sel = (x[:, 2] >= edges[k]) & (x[:, 2] < edges[k + 1])
        if not sel.any():
            continue
        sector = np.floor((theta[sel] + np.pi) / (2 * np.pi) * n_t).astype(int) % n_t
        outer = np.full(n_t, np.nan)
        np.fmax.at(outer, sector, (rho + r)[sel])
        zs.append(0.5 * (edges[k] + edges[k + 1]))
        radii.append(float(np.nanmean(outer)))
    return np.array(zs), np.array(radii)


def has_frames(out: Path) -> bool:
    """Did the run write HDF5 snapshots (``particles.h5``, or per-rank pieces)?"""
    return (out / "particles.h5").is_file() or any(out.glob("particles.r*.h5"))


def bulge_at(out: Path, boundary: str, eps: float) -> dict | None:
    """The radius profile at the stored frame nearest ε_a = ``eps`` and at the start of the shear
    (frames by time, from the series): the specimen bulges when its middle grows more than its ends."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from render import particle_files, read_frame  # noqa: E402

    try:
        import tomllib

        deck = tomllib.loads((out / "deck.resolved.toml").read_text())
        centre = np.asarray(deck["boundaries"][boundary].get("base_center", [0.0, 0.0, 0.0]), float)
    except (OSError, KeyError):
        centre = np.zeros(3)
    s = shear_rows(out, boundary)
    ea, t = s[f"{boundary}.eps_a"], s["time"]
    if ea.max() < eps:
        return None
    t_eps, t0 = float(t[np.argmax(ea >= eps)]), float(t[0])  # t0: the first row of the shear
    import h5py

    with h5py.File(particle_files(out)[0], "r", locking=False) as f:  # particles.h5, or rank 0's piece
        keys = sorted(f["frames"])
        times = np.array([float(f["frames"][k].attrs["time"]) for k in keys])
    frames = {}
    for name, when in (("start", t0), ("now", t_eps)):
        snap = read_frame(out, int(np.argmin(np.abs(times - when))))
        z, rad = radius_profile(np.asarray(snap.particles["x"]), np.asarray(snap.particles["r"]), centre)
        ea_frame = float(np.interp(snap.time, t, ea, left=0.0))
        frames[name] = {"time": snap.time, "eps_a": ea_frame, "z": z, "radius": rad}
    rad0, rad = frames["start"]["radius"], frames["now"]["radius"]
    n = len(rad)
    mid = slice(n // 2 - max(n // 6, 1), n // 2 + max(n // 6, 1))
    r0 = float(np.mean(rad0))
    return {
        "frames": frames,
        "r0": r0,
        "mid": float(np.mean(rad[mid])),
        "ends": float(0.5 * (rad[0] + rad[-1])),
        "bulge": (float(np.mean(rad[mid])) - 0.5 * float(rad[0] + rad[-1])) / r0,
        "growth": (float(np.mean(rad)) - r0) / r0,
        "spread": float(np.ptp(rad)) / r0,
        "spread0": float(np.ptp(rad0)) / r0,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outputs", type=Path, nargs="+")
    ap.add_argument("--boundary", default="cell", help="the triaxial boundary's name (default: cell)")
    ap.add_argument("--png", type=Path, default=None)
    ap.add_argument("--profile-at", type=float, default=0.15, help="ε_a of the radius profile (default 0.15)")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b = args.boundary
    fig, ax = plt.subplots(1, 4, figsize=(18, 4.2))
    for out in args.outputs:
        s = shear_rows(out, b)
        ea, q, p, ev = (s[f"{b}.{k}"] for k in ("eps_a", "q", "p", "eps_v"))
        label = out.name
        ax[0].plot(100 * ea, q / p, label=f"{label}: q/p")
        ax[1].plot(100 * ea, 100 * ev, label=label)
        ax[2].plot(100 * ea, s[f"{b}.sigma1"] / 1e3, label=f"{label}: σ1 (cap)")
        ax[2].plot(100 * ea, s[f"{b}.lw_szz"] / 1e3, "--", label=f"{label}: σzz (grains)")
        ax[2].plot(100 * ea, s[f"{b}.sigma3"] / 1e3, label=f"{label}: σ3 (membrane)")
        ax[2].plot(100 * ea, s[f"{b}.lw_srr"] / 1e3, "--", label=f"{label}: σrr (grains)")
        with open(out / "triaxial_curves.csv", "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["eps_a", "q", "p", "eps_v", "sigma1", "sigma3", "lw_szz", "lw_srr"])
            for row in zip(ea, q, p, ev, s[f"{b}.sigma1"], s[f"{b}.sigma3"], s[f"{b}.lw_szz"],
                           s[f"{b}.lw_srr"], strict=True):  # fmt: skip
                w.writerow([f"{v:.8g}" for v in row])
        prof = bulge_at(out, b, args.profile_at) if has_frames(out) else None
        if prof is not None:
            f0, f1 = prof["frames"]["start"], prof["frames"]["now"]
            for f, ls in ((f0, ":"), (f1, "-")):
                ax[3].plot(1e3 * f["radius"], 1e3 * f["z"], ls, marker="o", ms=3,
                           label=f"{label}: ε_a = {100 * f['eps_a']:.1f} %")  # fmt: skip
            with open(out / "triaxial_profile.csv", "w", newline="") as fh:
                w = csv.writer(fh)
                w.writerow(["z", f"radius_eps_a_{f0['eps_a']:.4f}", f"radius_eps_a_{f1['eps_a']:.4f}"])
                for row in zip(f1["z"], np.interp(f1["z"], f0["z"], f0["radius"]), f1["radius"], strict=True):
                    w.writerow([f"{v:.8g}" for v in row])
            print(f"{out}: radius at ε_a = {100 * f1['eps_a']:.1f} %: middle third "
                  f"{1e3 * prof['mid']:.2f} mm, "
                  f"ends {1e3 * prof['ends']:.2f} mm, at the start of the shear {1e3 * prof['r0']:.2f} mm "
                  f"(mean); bulge (middle − ends) / r0 = {100 * prof['bulge']:.1f} %; mean radius "
                  f"+{100 * prof['growth']:.1f} %, max − min over the height {100 * prof['spread']:.1f} % "
                  f"of r0 (at the start {100 * prof['spread0']:.1f} %)")  # fmt: skip
        over = s.get(f"{b}.end_overhang")
        if over is not None and np.isfinite(over).any():  # > 0: an end grain past the platen's edge
            line = (f"{out}: end grains (centres within one diameter of a platen): furthest "
                    f"{1e3 * np.nanmax(over):+.2f} mm beyond the platen radius plus their own radius "
                    f"({'none past the edge' if np.nanmax(over) <= 0 else 'past the edge'})")  # fmt: skip
            ring, axial = s.get(f"{b}.ring_srr"), s.get(f"{b}.ring_axial_share")
            if ring is not None and np.isfinite(ring).any():
                share = ring / s[f"{b}.sigma3"]
                line += (f"; the rings carry {100 * np.nanmean(share):.1f} % of σ3 radially (max "
                         f"{100 * np.nanmax(share):.1f} %)")  # fmt: skip
            if axial is not None and np.isfinite(axial).any():
                line += (f" and {100 * np.nanmean(axial):.1f} % of the cap's axial load (max "
                         f"{100 * np.nanmax(axial):.1f} %)")  # fmt: skip
            print(line)
    ax[0].set(xlabel="axial strain ε_a [%]", ylabel="q / p", title="stress ratio")
    ax[1].set(xlabel="axial strain ε_a [%]", ylabel="volumetric strain ε_v [%] (contraction > 0)",
              title="volume change")  # fmt: skip
    ax[2].set(xlabel="axial strain ε_a [%]", ylabel="stress [kPa]", title="boundary vs grains (Love–Weber)")
    ax[3].set(xlabel="outer radius [mm]", ylabel="height [mm]", title="radius profile (membrane grains)")
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
