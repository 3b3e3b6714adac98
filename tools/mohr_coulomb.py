#!/usr/bin/env python
"""Mohr–Coulomb friction angles from several triaxial or direct shear runs.

    python tools/mohr_coulomb.py OUTPUT [OUTPUT ...] [--out PREFIX] [--residual-fraction 0.2]

Each OUTPUT is a run's output directory (``summary.json`` and ``series_*.csv``); the test is found
from the boundary's results: a ``triaxial`` boundary (``q_peak``) or a ``shear_box`` (``peak_ratio``).
Runs of both kinds may be given together; each kind is fitted on its own.

**Triaxial**: at the peak of q, σ₃ is the realised cell pressure and σ₁ = σ₃ + q; at large strain
(the critical state) σ₁ and σ₃ are the means over the last ``--residual-fraction`` of the axial
strain. The envelope of the Mohr circles is fitted as t = s sin φ + c cos φ, with
s = (σ₁ + σ₃)/2 and t = (σ₁ − σ₃)/2 (least squares, R² of that line): φ and the cohesion intercept c.
Each run's own angle is sin φ = (σ₁ − σ₃)/(σ₁ + σ₃).

**Direct shear**: τ/σ at the peak and its mean over the last ``--residual-fraction`` of the
displacement, times the mean normal stress. σ is the normal stress on the shear plane where the run
measured it (``plane_*`` of the shear box: the plate's load plus the weight of the grains above the
plane, less what the upper walls carry by friction), else the plate's; fitted as τ = c + σ tan φ
(R²), and through the origin, τ = σ tan φ (the study's form). The fits on the plate's stress alone
(the lab convention) are given too, as ``peak_applied`` and ``residual_applied``.

Runs all at one stress (seeds of one test; stresses within 5 % of each other) get no envelope: the
tool reports the mean and standard deviation of the runs' own angles (``fits.KIND.one_stress``).

Writes ``PREFIX.json`` (every run and fit), ``PREFIX.csv`` (one row per run) and ``PREFIX.png``
(curves: q and ε_v against ε_a, τ and dilation against u; Mohr circles or τ–σ points with the
envelopes). ``PREFIX`` defaults to ``mohr_coulomb`` in the first OUTPUT.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

import numpy as np


def _series(out: Path, key: str) -> dict[str, np.ndarray]:
    """Rows of the stage files of ``out`` where column ``key`` > 0 (the shear), in stage order."""
    from pdem.io.series import read_series

    rows: dict[str, list] = {}
    for path in sorted(out.glob("series_*.csv"), key=lambda p: p.stat().st_mtime):
        s = read_series(path)
        if key not in s:
            continue
        sel = np.asarray(s[key], dtype=float) > 0
        if not sel.any():
            continue
        for k, v in s.items():
            rows.setdefault(k, []).append(np.asarray(v, dtype=float)[sel])
    if not rows:
        raise SystemExit(f"{out}: no series rows with {key} > 0 (did the shear stage run?)")
    return {k: np.concatenate(v) for k, v in rows.items()}


def moving_average(x: np.ndarray, y: np.ndarray, width: float) -> np.ndarray:
    """The mean of ``y`` over the rows whose ``x`` lies within ``width``/2 of each row's (a centred
    window in the curve's own abscissa, so rows every step and rows every 200 steps are averaged
    over the same strain or displacement); NaN rows are left out."""
    x = np.maximum.accumulate(np.asarray(x, dtype=float))
    y = np.asarray(y, dtype=float)
    lo = np.searchsorted(x, x - 0.5 * width, "left")
    hi = np.searchsorted(x, x + 0.5 * width, "right")
    good = np.isfinite(y)
    c = np.concatenate([[0.0], np.cumsum(np.where(good, y, 0.0))])
    n = np.concatenate([[0], np.cumsum(good)])
    cnt = n[hi] - n[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, (c[hi] - c[lo]) / np.maximum(cnt, 1), np.nan)


def read_run(out: Path, residual_fraction: float, smooth: float = 0.0) -> dict:
    """One run: its kind, boundary, stresses at the peak and at large strain, and its curves.

    ``smooth`` > 0: the peak is the largest value of the curve averaged over a window that wide
    (axial strain for the triaxial test, shear displacement [m] for the shear box), not the largest
    row: a noisy curve (DEM-C's unconverged solves, its free plate's jitter) would otherwise report
    its noise's highest excursion, and the more rows, the higher."""
    path = out / "summary.json"
    if not path.is_file():
        raise SystemExit(f"{out}: no summary.json (not a finished pdem run)")
    summary = json.loads(path.read_text())
    for name, res in summary.get("results", {}).items():
        if "q_peak" in res:
            s = _series(out, f"{name}.eps_a")
            ea, q, s3 = (s[f"{name}.{k}"] for k in ("eps_a", "q", "sigma3"))
            ev = s[f"{name}.eps_v"]
            if smooth > 0:
                q = moving_average(ea, q, smooth)
            k = int(np.nanargmax(q))
            late = ea >= (1.0 - residual_fraction) * ea.max()
            s3_peak, s1_peak = float(s3[k]), float(s3[k] + q[k])
            s3_cs, s1_cs = float(s3[late].mean()), float((s3[late] + q[late]).mean())
            return {
                "kind": "triaxial", "output": str(out), "boundary": name,
                "sigma3": float(s3.mean()), "peak": (s1_peak, s3_peak), "critical": (s1_cs, s3_cs),
                "eps_a_peak": float(ea[k]), "eps_v_final": float(ev[-1]), "smooth": smooth,
                "phi_peak_deg": _phi_triax(s1_peak, s3_peak), "phi_cs_deg": _phi_triax(s1_cs, s3_cs),
                "wall_time_s": summary.get("wall_time_s"), "dt": summary.get("dt"),
                "curves": {"x": ea, "y": q, "v": ev},
            }  # fmt: skip
        if "peak_ratio" in res:
            s = _series(out, f"{name}.displacement")
            keys = ("displacement", "ratio", "normal_stress", "dilation")
            u, ratio, sn, dil = (s[f"{name}.{k}"] for k in keys)
            applied = float(sn.mean())
            peak, residual = float(res["peak_ratio"]), float(res["residual_ratio"])
            # on the shear plane where measured (the plate's load + the upper grains' weight − wall
            # friction), else the applied stress
            on_plane = "peak_plane_ratio" in res
            sigma = float(res["plane_normal_stress_mean"]) if on_plane else applied
            ppeak = float(res["peak_plane_ratio"]) if on_plane else peak
            pres = float(res["residual_plane_ratio"]) if on_plane else residual
            u_peak = float(res["peak_displacement"])
            if smooth > 0:
                peak = float(np.nanmax(moving_average(u, ratio, smooth)))
                plane = s.get(f"{name}.plane_ratio") if on_plane else None
                sm = moving_average(u, plane if plane is not None else ratio, smooth)
                k = int(np.nanargmax(sm))
                ppeak, u_peak = float(sm[k]), float(u[k])
            return {
                "kind": "direct_shear", "output": str(out), "boundary": name, "sigma": sigma,
                "sigma_applied": applied, "on_plane": on_plane,
                "peak_ratio": ppeak, "residual_ratio": pres,
                "peak_ratio_applied": peak, "residual_ratio_applied": residual,
                "tau_peak": ppeak * sigma, "tau_residual": pres * sigma,
                "tau_peak_applied": peak * applied, "tau_residual_applied": residual * applied,
                "u_peak": u_peak, "dilation_max": float(res["max_dilation"]), "smooth": smooth,
                "phi_peak_deg": math.degrees(math.atan(ppeak)),
                "phi_residual_deg": math.degrees(math.atan(pres)),
                "wall_time_s": summary.get("wall_time_s"), "dt": summary.get("dt"),
                "curves": {"x": u, "y": ratio * sn, "v": dil},
            }  # fmt: skip
    raise SystemExit(f"{out}: summary.json has no triaxial (q_peak) or shear box (peak_ratio) results")


def _phi_triax(s1: float, s3: float) -> float:
    return math.degrees(math.asin((s1 - s3) / (s1 + s3)))


def line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least squares y = a x + b: (a, b, R²); R² is nan for fewer than 3 points (a line through two
    points says nothing about its fit)."""
    a, b = np.polyfit(x, y, 1)
    ss = float(((y - y.mean()) ** 2).sum())
    r2 = 1.0 - float(((y - (a * x + b)) ** 2).sum()) / ss if ss > 0 and len(x) >= 3 else math.nan
    return float(a), float(b), r2


def fit_triaxial(pairs: list[tuple[float, float]]) -> dict[str, float]:
    """Envelope of Mohr circles (σ₁, σ₃) by t = s sin φ + c cos φ."""
    s1, s3 = np.array(pairs).T
    a, b, r2 = line_fit(0.5 * (s1 + s3), 0.5 * (s1 - s3))
    if not -1 < a < 1:
        return {"phi_deg": math.nan, "cohesion_pa": math.nan, "r2": r2}
    phi = math.asin(a)
    return {"phi_deg": math.degrees(phi), "cohesion_pa": b / math.cos(phi), "r2": r2}


def fit_shear(sigma: np.ndarray, tau: np.ndarray) -> dict[str, float]:
    """τ = c + σ tan φ (R²) and τ = σ tan φ through the origin."""
    a, b, r2 = line_fit(sigma, tau)
    origin = float(sigma @ tau) / float(sigma @ sigma)
    return {"phi_deg": math.degrees(math.atan(a)), "cohesion_pa": b, "r2": r2,
            "phi_origin_deg": math.degrees(math.atan(origin))}  # fmt: skip


#: an envelope needs stresses that differ: below this spread (max − min over max) the runs are
#: repeats at one stress (e.g. seeds), whose line through nearly equal abscissae is noise
MIN_STRESS_SPREAD = 0.05


def _spread(stresses: list[float]) -> bool:
    s = np.abs(np.asarray(stresses, dtype=float))
    return s.size >= 2 and float(s.max() - s.min()) > MIN_STRESS_SPREAD * float(s.max())


def _repeats(runs: list[dict], keys: tuple[str, str]) -> dict:
    """Runs at one stress: the mean and standard deviation of their own angles, no envelope."""
    out = {}
    for name, key in zip(("peak", keys[0]), ("phi_peak_deg", keys[1]), strict=True):
        a = np.array([r[key] for r in runs], dtype=float)
        std = float(a.std(ddof=1)) if a.size > 1 else 0.0
        out[name] = {"phi_deg_mean": float(a.mean()), "phi_deg_std": std, "runs": int(a.size)}
    return out


def analyse(runs: list[dict]) -> dict:
    """Fits for each kind of test present; runs all at one stress get the mean of their own angles
    instead (``one_stress``)."""
    out: dict = {}
    tri = sorted((r for r in runs if r["kind"] == "triaxial"), key=lambda r: r["sigma3"])
    if len(tri) >= 1 and not _spread([r["sigma3"] for r in tri]):
        out["triaxial"] = {"one_stress": _repeats(tri, ("critical", "phi_cs_deg"))}
    elif len(tri) >= 2:
        out["triaxial"] = {"peak": fit_triaxial([r["peak"] for r in tri]),
                           "critical": fit_triaxial([r["critical"] for r in tri])}  # fmt: skip
    ds = sorted((r for r in runs if r["kind"] == "direct_shear"), key=lambda r: r["sigma"])
    if len(ds) >= 1 and not _spread([r["sigma_applied"] for r in ds]):
        out["direct_shear"] = {"one_stress": _repeats(ds, ("residual", "phi_residual_deg"))}
    elif len(ds) >= 2:
        sigma = np.array([r["sigma"] for r in ds])
        applied = np.array([r["sigma_applied"] for r in ds])
        out["direct_shear"] = {
            name: fit_shear(sigma, np.array([r[key] for r in ds]))
            for name, key in (("peak", "tau_peak"), ("residual", "tau_residual"))
        } | {  # the lab convention: the stress the plate applies
            f"{name}_applied": fit_shear(applied, np.array([r[f"{key}_applied"] for r in ds]))
            for name, key in (("peak", "tau_peak"), ("residual", "tau_residual"))
        }
    return out


def _envelope(ax, name: str, fit: dict, smax: float, color: str) -> None:
    """The fitted line τ = c + σ tan φ from σ = 0 to ``smax``, labelled with its figures."""
    s = np.linspace(0.0, smax, 50)
    phi, c0 = math.radians(fit["phi_deg"]), fit["cohesion_pa"]
    label = f"{name}: φ = {fit['phi_deg']:.1f}°, c = {c0:.0f} Pa, R² = {fit['r2']:.4f}"
    ax.plot(s / 1e3, (c0 + s * math.tan(phi)) / 1e3, "--", color=color, label=label)


def plot(runs: list[dict], fits: dict, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = [k for k in ("triaxial", "direct_shear") if any(r["kind"] == k for r in runs)]
    fig, axes = plt.subplots(len(kinds), 3, figsize=(15, 4.3 * len(kinds)), squeeze=False)
    for row, kind in zip(axes, kinds, strict=True):
        sel = [r for r in runs if r["kind"] == kind]
        tri = kind == "triaxial"
        for r in sel:
            c = r["curves"]
            scale = 100.0 if tri else 1e3
            label = f"{Path(r['output']).name} ({(r['sigma3'] if tri else r['sigma']) / 1e3:.3g} kPa)"
            row[0].plot(scale * c["x"], c["y"] / 1e3, label=label)
            row[1].plot(scale * c["x"], (100.0 if tri else 1e3) * c["v"], label=label)
        row[0].set_xlabel("axial strain ε_a [%]" if tri else "shear displacement u [mm]")
        row[0].set_ylabel("deviator q [kPa]" if tri else "shear stress τ [kPa]")
        row[1].set_xlabel(row[0].get_xlabel())
        row[1].set_ylabel("volumetric strain ε_v [%] (contraction +)" if tri else "dilation [mm]")
        row[0].legend(fontsize=7)
        ax = row[2]
        f = fits.get(kind, {})
        if tri:
            smax = 0.0
            for r in sel:
                for (s1, s3), ls in ((r["peak"], "-"), (r["critical"], ":")):
                    t = np.linspace(0, np.pi, 90)
                    cx, rad = 0.5 * (s1 + s3), 0.5 * (s1 - s3)
                    color = "C0" if ls == "-" else "C1"
                    ax.plot((cx + rad * np.cos(t)) / 1e3, rad * np.sin(t) / 1e3, ls, color=color)
                    smax = max(smax, s1)
            for name, color in (("peak", "C0"), ("critical", "C1")):
                if name in f and math.isfinite(f[name]["phi_deg"]):
                    _envelope(ax, name, f[name], smax, color)
            ax.set_xlabel("normal stress σ [kPa]")
            ax.set_aspect("equal")
        else:
            sig = np.array([r["sigma"] for r in sel])
            for name, key, color in (("peak", "tau_peak", "C0"), ("residual", "tau_residual", "C1")):
                ax.plot(sig / 1e3, np.array([r[key] for r in sel]) / 1e3, "o", color=color)
                if name in f:
                    _envelope(ax, name, f[name], 1.05 * sig.max(), color)
            ax.set_xlabel("normal stress σ_n [kPa]")
        ax.set_ylabel("shear stress τ [kPa]")
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
        if ax.get_legend_handles_labels()[0]:  # (no envelope at one stress)
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("outputs", type=Path, nargs="+")
    ap.add_argument("--out", type=Path, default=None, help="prefix of the .json/.csv/.png written")
    ap.add_argument("--residual-fraction", type=float, default=0.2)
    ap.add_argument("--smooth", type=float, default=0.0, metavar="WIDTH",
                    help="peaks of the curves averaged over this window (axial strain, or shear "
                    "displacement in m), not of single rows; default 0: the largest row")  # fmt: skip
    args = ap.parse_args(argv)
    if not args.smooth >= 0:
        ap.error(f"--smooth: {args.smooth!r} must be a width >= 0")
    runs = [read_run(o, args.residual_fraction, args.smooth) for o in args.outputs]
    fits = analyse(runs)
    prefix = args.out or args.outputs[0] / "mohr_coulomb"
    prefix.parent.mkdir(parents=True, exist_ok=True)
    plain = [{k: v for k, v in r.items() if k != "curves"} for r in runs]
    Path(f"{prefix}.json").write_text(json.dumps({"runs": plain, "fits": fits}, indent=2) + "\n")
    cols = ["output", "kind", "sigma3", "sigma", "phi_peak_deg", "phi_cs_deg", "phi_residual_deg",
            "eps_a_peak", "eps_v_final", "u_peak", "dilation_max", "wall_time_s"]  # fmt: skip
    with open(f"{prefix}.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, cols, extrasaction="ignore")
        w.writeheader()
        w.writerows(plain)
    plot(runs, fits, Path(f"{prefix}.png"))
    for r in plain:
        stress = r.get("sigma3", r.get("sigma"))
        other = r.get("phi_cs_deg", r.get("phi_residual_deg"))
        print(f"{r['kind']:12s} {stress / 1e3:8.2f} kPa  φ_peak {r['phi_peak_deg']:5.1f}°  "
              f"φ_large-strain {other:5.1f}°  {r['output']}")  # fmt: skip
    for kind, f in fits.items():
        if "one_stress" in f:
            for name, v in f["one_stress"].items():
                print(f"{kind:12s} {name:9s} one stress, {v['runs']} run(s): no envelope; their own angles "
                      f"φ = {v['phi_deg_mean']:.2f}° ± {v['phi_deg_std']:.2f}° (mean ± s.d.)")  # fmt: skip
            continue
        for name, v in f.items():
            print(f"{kind:12s} {name:9s} φ = {v['phi_deg']:.2f}°  c = {v['cohesion_pa']:.1f} Pa  "
                  f"R² = {v['r2']:.4f}")  # fmt: skip
    print(f"wrote {prefix}.json, .csv, .png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
