#!/usr/bin/env python
"""Wave speeds from runs of ``inputs/wave_chain.toml`` and ``inputs/shock_wave.toml`` (experiments.md §1):
tables (CSV) and figures (PNG, matplotlib Agg).

    python tools/wave_analysis.py chain RUN_DIR [RUN_DIR ...] [--out DIR]
    python tools/wave_analysis.py bed RUN_DIR [--out DIR]
    python tools/wave_analysis.py dem-c [--out DIR] [--iterations 1 2 5 ...] [--steps 1e-6 1e-5 ...]

``chain``: per run (a chain struck at some speed), from its ``summary.json`` (the ``sensors``
boundary, one sensor per bead) and ``deck.resolved.toml`` (the material, the radius, the striker's
speed): over the middle of the chain (sensors from 25 % to 75 % of it, ``--lo``/``--hi``)

* ``V_s``: the inverse slope of the beads' speed-peak times against their distance (least squares);
  also from the contact-force peaks and from the arrivals (first speed above the threshold);
* ``F_m``: the mean of the beads' largest contact force (its spread is reported);
* ``V_nesterenko`` = 0.6802 (2E/(d(1 − ν²)))^{1/3} F_m^{1/6} ρ^{−1/2} and the relative difference;
* the pulse width: the full width at half maximum of each middle bead's velocity against time,
  times V_s, in diameters (``fwhm_d``), and the width of Nesterenko's cos⁴ profile with that
  FWHM (``width_d`` = 2.747 fwhm_d; the profile's whole extent is 5π/√10 = 4.97 d); and the number
  of beads moving faster than 1 % of the peak speed when the peak is at the middle bead.

With several runs, the exponent of V_s ∝ F_m^α (least squares on logarithms; Nesterenko: 1/6).
Writes ``chain_speeds.csv``, ``chain_speeds.png`` (V_s against F_m, log-log, with the closed form)
and ``chain_profile.png`` (the first run's bead velocities against time).

``bed``: the 2-D bed's ``surface`` and ``depth`` sensors (sensor k at 10 k spacings from the
impact): arrival and peak times against distance → speeds; ``bed_arrivals.csv`` and
``bed_arrivals.png``.

``dem-c``: runs the chain deck with ``contact.law = complementarity`` (small runs, one at a time)
for each projected-Jacobi iteration cap and step h, with a tolerance too small to stop earlier, and
with Gauss–Seidel sweeping along and against the wave (the sweep follows contact order, i.e. id
pairs: the striker is moved to the far end to sweep against it). The apparent front speed is the
inverse slope of arrival time (speed above 1e-4 m/s) against distance over the middle of the chain;
a front that crosses the whole middle within one step has no finite slope and is reported as
``inf``. Writes ``dem_c_front.csv`` and ``dem_c_front.png`` (apparent speed against the bound of
one contact per iteration, N_iter d / h, and the physical V_s).

Importable: ``analyse_chain(run_dir)``, ``analyse_bed(run_dir)``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NESTERENKO = 0.6802
COS4_WIDTH = (math.pi / 2.0) / math.acos(0.5**0.25)  # whole width / FWHM of cos^4 = 2.747

__all__ = ["analyse_chain", "analyse_bed", "nesterenko_speed", "fit_speed", "main"]


def nesterenko_speed(E: float, nu: float, rho: float, d: float, f_m: float) -> float:
    """V_s = 0.6802 (2E/(d(1 − ν²)))^{1/3} F_m^{1/6} ρ^{−1/2} [m/s]."""
    return NESTERENKO * (2.0 * E / (d * (1.0 - nu * nu))) ** (1.0 / 3.0) * f_m ** (1.0 / 6.0) / math.sqrt(rho)


def fit_speed(dist, times) -> float:
    """Inverse slope of ``times`` against ``dist`` (least squares over finite values); inf when the
    times do not grow (a front crossing everything at once), nan with fewer than two points."""
    dist, times = np.asarray(dist, float), np.asarray(times, float)
    ok = np.isfinite(times) & np.isfinite(dist)
    if np.count_nonzero(ok) < 2 or np.ptp(dist[ok]) <= 0:
        return math.nan
    slope = np.polyfit(dist[ok], times[ok], 1)[0]
    return 1.0 / slope if slope > 1e-12 * np.ptp(times[ok] + 1.0) / np.ptp(dist[ok]) else math.inf


def _load(run: Path) -> tuple[dict, dict]:
    summary = json.loads((run / "summary.json").read_text())
    deck = tomllib.loads((run / "deck.resolved.toml").read_text())
    return summary, deck


def _arr(values) -> np.ndarray:
    return np.array([math.nan if v is None else v for v in values], float)


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    data = np.array([[float(c) if c else math.nan for c in r] for r in body if len(r) == len(header)])
    return {name: data[:, i] for i, name in enumerate(header)}


def _fwhm(t: np.ndarray, y: np.ndarray) -> float:
    """Full width at half maximum of a single pulse y(t), with linear interpolation."""
    k = int(np.nanargmax(y))
    half = 0.5 * y[k]
    i = k
    while i > 0 and y[i] > half:
        i -= 1
    j = k
    while j < len(y) - 1 and y[j] > half:
        j += 1
    if y[i] > half or y[j] > half:
        return math.nan
    t0 = t[i] + (half - y[i]) / (y[i + 1] - y[i]) * (t[i + 1] - t[i])
    t1 = t[j - 1] + (half - y[j - 1]) / (y[j] - y[j - 1]) * (t[j] - t[j - 1])
    return t1 - t0


def analyse_chain(run_dir, sensors: str = "chain", lo: float = 0.25, hi: float = 0.75) -> dict:
    """The chain figures of one run (see the module doc)."""
    run = Path(run_dir)
    summary, deck = _load(run)
    res = summary["results"][sensors]
    mat = next(iter(deck["materials"].values()))
    E, nu, rho = mat["youngs_modulus"], mat["poisson_ratio"], mat["density"]
    d = 2.0 * deck["particles"][0]["radius"]
    v0 = float(np.linalg.norm(deck["particles"][1]["velocity"]))
    n = len(res["ids"])
    mid = np.arange(int(round(lo * n)), int(round(hi * n)) + 1)
    dist = _arr(res["distance"])
    peak_t, fpeak_t, arr_t = _arr(res["peak_time"]), _arr(res["force_peak_time"]), _arr(res["arrival_time"])
    fm_all = _arr(res["peak_force"])[mid]
    f_m = float(np.mean(fm_all))
    v_s = fit_speed(dist[mid], peak_t[mid])
    v_n = nesterenko_speed(E, nu, rho, d, f_m)
    out = {
        "run": str(run),
        "striker_speed": v0,
        "beads": n,
        "middle": f"{int(mid[0])}-{int(mid[-1])}",
        "F_m": f_m,
        "F_m_spread": float(np.ptp(fm_all) / f_m),
        "V_s": v_s,
        "V_s_force": fit_speed(dist[mid], fpeak_t[mid]),
        "V_s_arrival": fit_speed(dist[mid], arr_t[mid]),
        "V_nesterenko": v_n,
        "error": v_s / v_n - 1.0,
        "peak_speed": float(np.nanmean(_arr(res["peak_speed"])[mid])),
        "wall_time_s": summary.get("wall_time_s"),
        "dt": summary.get("dt"),
    }
    csvs = sorted(run.glob(f"{sensors}.*.csv"))
    if csvs:
        data = _read_csv(csvs[0])
        t = data["time"]
        widths = []
        for k in mid:
            col = f"s{k}.vx" if f"s{k}.vx" in data else f"s{k}.speed"
            widths.append(_fwhm(t, np.abs(data[col])))
        fwhm_d = float(np.nanmean(widths)) * v_s / d
        out["fwhm_d"] = fwhm_d
        out["width_d"] = fwhm_d * COS4_WIDTH
        kc = int(mid[len(mid) // 2])
        row = int(np.argmin(np.abs(t - peak_t[kc])))
        cols = [f"s{k}.vx" if f"s{k}.vx" in data else f"s{k}.speed" for k in range(n)]
        prof = np.abs(np.array([data[c][row] for c in cols]))
        out["beads_above_1pct"] = int(np.count_nonzero(prof > 0.01 * prof.max()))
    return out


def _write_csv(path: Path, rows: list[dict]) -> None:
    keys = list(rows[0])
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, keys)
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(float(v)) if isinstance(v, float) else v) for k, v in r.items()})


def chain(runs: list[Path], out: Path, lo: float, hi: float) -> dict:
    rows = [analyse_chain(r, lo=lo, hi=hi) for r in runs]
    rows.sort(key=lambda r: r["F_m"])
    result: dict = {"runs": rows}
    if len(rows) >= 2:
        lf = np.log([r["F_m"] for r in rows])
        lv = np.log([r["V_s"] for r in rows])
        result["exponent"] = float(np.polyfit(lf, lv, 1)[0])
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(out / "chain_speeds.csv", rows)
    first = rows[0]
    mat_run = Path(first["run"])
    _, deck = _load(mat_run)
    mat = next(iter(deck["materials"].values()))
    d = 2.0 * deck["particles"][0]["radius"]
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    fm = np.array([r["F_m"] for r in rows])
    grid = np.geomspace(fm.min() / 1.5, fm.max() * 1.5, 50)
    ax[0].loglog(
        grid,
        [nesterenko_speed(mat["youngs_modulus"], mat["poisson_ratio"], mat["density"], d, f) for f in grid],
        "k-",
        label="Nesterenko 0.6802 (2E/(d(1-ν²)))^{1/3} F_m^{1/6} ρ^{-1/2}",
    )
    ax[0].loglog(fm, [r["V_s"] for r in rows], "o", color="C3", label="pdem DEM-P (peak times)")
    for r in rows:
        ax[0].annotate(
            f"{r['striker_speed']:g} m/s",
            (r["F_m"], r["V_s"]),
            textcoords="offset points",
            xytext=(5, -12),
            fontsize=8,
        )
    title = "solitary wave speed"
    if "exponent" in result:
        title += f": exponent {result['exponent']:.4f} (theory 1/6 = 0.1667)"
    ax[0].set(xlabel="peak contact force F_m [N]", ylabel="V_s [m/s]", title=title)
    ax[0].xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax[0].yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax[0].legend(fontsize=8)
    csvs = sorted(mat_run.glob("chain.*.csv"))
    if csvs:
        data = _read_csv(csvs[0])
        for k in range(10, first["beads"], 10):
            col = f"s{k}.vx" if f"s{k}.vx" in data else f"s{k}.speed"
            ax[1].plot(data["time"] * 1e3, data[col], lw=1, label=f"bead {k}")
        ax[1].set(
            xlabel="time [ms]",
            ylabel="bead velocity [m/s]",
            title=f"striker {first['striker_speed']:g} m/s; pulse FWHM {first.get('fwhm_d', math.nan):.2f} d",
        )
        ax[1].legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "chain_speeds.png", dpi=120)
    plt.close(fig)
    (out / "chain_speeds.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def analyse_bed(run_dir, spacing: float | None = None) -> dict:
    """Arrival and peak times of the bed's ``surface`` and ``depth`` sensors (see the module doc)."""
    run = Path(run_dir)
    summary, deck = _load(run)
    if spacing is None:
        src = deck["particles"][0]
        spacing = src.get("spacing") or 2.0 * src["radius"]
    out: dict = {
        "run": str(run),
        "spacing": spacing,
        "wall_time_s": summary.get("wall_time_s"),
        "particles": summary.get("particles"),
        "steps": summary.get("steps"),
        "lines": {},
    }
    for name in ("surface", "depth"):
        res = summary["results"].get(name)
        if not res:
            continue
        dist = _arr(res["distance"])
        line = {
            "distance_spacings": (dist / spacing).tolist(),
            "arrival_time": _arr(res["arrival_time"]).tolist(),
            "peak_time": _arr(res["peak_time"]).tolist(),
            "force_peak_time": _arr(res["force_peak_time"]).tolist(),
            "peak_speed": _arr(res["peak_speed"]).tolist(),
            "peak_force": _arr(res["peak_force"]).tolist(),
            "speed_arrival": fit_speed(dist[1:], _arr(res["arrival_time"])[1:]),
            "speed_peak": fit_speed(dist[1:], _arr(res["peak_time"])[1:]),
            "speed_force_peak": fit_speed(dist[1:], _arr(res["force_peak_time"])[1:]),
        }
        out["lines"][name] = line
    return out


def bed(run: Path, out: Path, frames: tuple[int, ...] = (2, 4, 6)) -> dict:
    res = analyse_bed(run)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for k, (name, line) in enumerate(res["lines"].items()):
        for i, s in enumerate(line["distance_spacings"]):
            rows.append(
                {
                    "line": name,
                    "distance_spacings": s,
                    "arrival_time": line["arrival_time"][i],
                    "peak_time": line["peak_time"][i],
                    "force_peak_time": line["force_peak_time"][i],
                    "peak_speed": line["peak_speed"][i],
                    "peak_force": line["peak_force"][i],
                }
            )
        x = np.array(line["distance_spacings"])
        ax.plot(
            x,
            np.array(line["arrival_time"]) * 1e6,
            "o-",
            color=f"C{k}",
            label=f"{name}: arrival, {line['speed_arrival']:.0f} m/s",
        )
        ax.plot(
            x,
            np.array(line["peak_time"]) * 1e6,
            "s--",
            color=f"C{k}",
            mfc="none",
            label=f"{name}: speed peak, {line['speed_peak']:.0f} m/s",
        )
    ax.set(
        xlabel="distance from the impact [spacings]",
        ylabel="time [µs]",
        title="2-D hexagonal bed: arrival of the pulse",
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "bed_arrivals.png", dpi=120)
    plt.close(fig)
    if rows:
        _write_csv(out / "bed_arrivals.csv", rows)
    front_picture(run, out / "bed_front.png", res, frames)
    (out / "bed_arrivals.json").write_text(json.dumps(res, indent=2) + "\n")
    return res


def front_picture(
    run: Path, path: Path, res: dict | None = None, frames: tuple[int, ...] = (2, 4, 6)
) -> Path:
    """Grains of the bed coloured by speed (log scale) at a few snapshots, sensors marked."""
    sys.path.insert(0, str(ROOT / "tools"))
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Circle
    from render import read_frame

    fig, axes = plt.subplots(1, len(frames), figsize=(4.6 * len(frames), 4.4), squeeze=False)
    norm = LogNorm(1e-3, 5.0)
    cmap = plt.get_cmap("inferno")
    for ax, k in zip(axes[0], frames, strict=True):
        try:
            snap = read_frame(run, k)
        except ValueError:
            ax.set_visible(False)
            continue
        p = snap.particles
        x, r = p["x"], p["r"]
        speed = np.linalg.norm(p["v"], axis=1)
        for xi, ri, si in zip(x, r, speed, strict=True):
            ax.add_patch(Circle((xi[0] * 1e3, xi[2] * 1e3), ri * 1e3, color=cmap(norm(max(si, 1e-3))), lw=0))
        ax.set_xlim(x[:, 0].min() * 1e3 - 2, x[:, 0].max() * 1e3 + 2)
        ax.set_ylim(x[:, 2].min() * 1e3 - 2, x[:, 2].max() * 1e3 + 2)
        ax.set_aspect("equal")
        ax.set(title=f"t = {snap.time * 1e6:.0f} µs", xlabel="x [mm]", ylabel="z [mm]")
        if res is not None:
            summary, _ = _load(run)
            for name in res["lines"]:
                pos = np.array(summary["results"][name]["positions"])
                ax.plot(pos[:, 0] * 1e3, pos[:, 2] * 1e3, "c+", ms=7, mew=1.5)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=cmap), ax=axes[0].tolist(), label="speed [m/s]")
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------------ DEM-C
def _pdem() -> list[str]:
    exe = shutil.which("pdem", path=str(Path(sys.executable).parent)) or shutil.which("pdem")
    return [exe] if exe else [sys.executable, "-m", "pdem"]


def _run_chain(out: Path, sets: list[str]) -> tuple[dict | None, float, str]:
    cmd = _pdem() + [str(ROOT / "inputs" / "wave_chain.toml"), "--output", str(out), "--overwrite", "--quiet"]
    for s in sets:
        cmd += ["--set", s]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return None, wall, proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed"
    return json.loads((out / "summary.json").read_text()), wall, ""


def dem_c(
    out: Path, iterations: list[int], steps: list[float], relaxations: list[float], last: int = 40
) -> list[dict]:
    """DEM-C runs of the chain deck (see the module doc); each stops once ``last`` + 1 beads have
    moved (or after 1.2 ms); the apparent speed is fitted over beads 10 … ``last``."""
    out.mkdir(parents=True, exist_ok=True)
    d = 4.76e-3
    common = [
        "contact.law=complementarity",
        "contact.complementarity.tolerance=1e-12",
        "boundaries.chain.threshold=1e-4",
        "boundaries.chain.every=1",
        "boundaries.chain.records=false",
        "run.max_overlap=0.9",
        "stages.impact.end.quantity=chain.arrived_count",
        f"stages.impact.end.above={last + 0.5}",
        "stages.impact.end.check_every=1",
        "output.every_steps=100000",
    ]
    cases = [("jacobi", n, h, w, "along") for w in relaxations for h in steps for n in iterations]
    cases += [("gauss_seidel", 1, h, 1.0, way) for h in steps for way in ("along", "against")]
    rows = []
    for solver, n, h, w, way in cases:
        sets = common + [
            f"contact.complementarity.solver={solver}",
            f"contact.complementarity.max_iterations={n}",
            f"contact.complementarity.relaxation={w}",
            f"run.dt={h}",
        ]
        if way == "against":  # the striker at the far end, moving -x: its contact is swept last
            sets += ["particles.1.origin=[0.3808, 0.0, 0.0]", "particles.1.velocity=[-1.0, 0.0, 0.0]"]
        tag = f"{solver}_n{n}_w{w:g}_h{h:g}_{way}"
        summary, wall, err = _run_chain(out / "runs" / tag, sets)
        speed, steps_run = math.nan, None
        if summary is not None:
            res = summary["results"]["chain"]
            dist = _arr(res["distance"])
            arr = _arr(res["arrival_time"])
            if way == "against":  # bead 79 is struck: distances from it
                dist, arr = dist[-1] - dist[::-1], arr[::-1]
            sel = np.arange(10, last + 1)
            speed = fit_speed(dist[sel], arr[sel])
            steps_run = summary["steps"]
        rows.append(
            {
                "solver": solver,
                "sweep": way,
                "max_iterations": n,
                "relaxation": w,
                "dt": h,
                "bound": n * d / h,
                "apparent_speed": speed,
                "steps": steps_run,
                "run_time_s": wall,
                "failure": err,
            }
        )
        note = f" FAILED: {err[:120]}" if err else ""
        print(
            f"{tag}: apparent front speed {speed:.4g} m/s, bound N d/h = {n * d / h:.4g} m/s{note}",
            flush=True,
        )
    _write_csv(out / "dem_c_front.csv", rows)
    plot_dem_c(rows, out / "dem_c_front.png")
    return rows


def read_dem_c(path: Path) -> list[dict]:
    """The rows of a ``dem_c_front.csv``."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k in ("max_iterations",):
            r[k] = int(r[k])
        for k in ("relaxation", "dt", "bound", "apparent_speed", "run_time_s"):
            r[k] = float(r[k])
    return rows


def plot_dem_c(rows: list[dict], path: Path) -> Path:
    """Apparent front speed against N_iter d / h (see the module doc)."""
    steps = sorted({r["dt"] for r in rows})
    relaxations = sorted({r["relaxation"] for r in rows if r["solver"] == "jacobi"})
    fig, ax = plt.subplots(figsize=(7.0, 4.8))
    fin = [r["apparent_speed"] for r in rows if math.isfinite(r["apparent_speed"])]
    top = max(fin + [r["bound"] for r in rows]) * 3
    marks = {w: m for w, m in zip(relaxations, "os^D", strict=False)}
    jac = [r for r in rows if r["solver"] == "jacobi"]
    for k, h in enumerate(steps):
        for w in relaxations:
            sel = [r for r in jac if r["dt"] == h and r["relaxation"] == w]
            b = np.array([r["bound"] for r in sel])
            s = np.array([r["apparent_speed"] for r in sel])
            ok = ~np.isnan(s)
            ax.loglog(b[ok], np.where(np.isinf(s[ok]), top, s[ok]), marks.get(w, "o") + "-", color=f"C{k}",
                      label=f"Jacobi ω = {w:g}, h = {h:g} s")  # fmt: skip
            if np.any(~ok):
                low = np.full(np.count_nonzero(~ok), min(fin) / 3 if fin else 1.0)
                ax.loglog(b[~ok], low, "x", color=f"C{k}",
                          label=f"Jacobi ω = {w:g}, h = {h:g} s: unstable")  # fmt: skip
    bs = np.array([r["bound"] for r in rows])
    grid = np.geomspace(bs.min() / 2, bs.max() * 2, 20)
    ax.loglog(grid, grid, "k--", lw=1, label="bound N_iter d / h")
    ax.axhline(667.8, color="C3", lw=1, label="DEM-P V_s at 1 m/s (667.8 m/s)")
    for r in rows:
        if r["solver"] == "gauss_seidel":
            y = r["apparent_speed"]
            y = top if math.isinf(y) else y
            ax.loglog([r["bound"]], [y], "^" if r["sweep"] == "along" else "v", color="k", ms=8, mfc="none",
                      label=f"Gauss–Seidel {r['sweep']}, 1 sweep, h = {r['dt']:g} s")  # fmt: skip
    ax.set(
        xlabel="N_iter d / h [m/s]",
        ylabel="apparent front speed [m/s]",
        title="DEM-C chain struck at 1 m/s: the front follows the solver",
    )
    ax.legend(fontsize=6.5, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("chain", help="V_s vs Nesterenko, exponent, pulse width")
    c.add_argument("runs", nargs="+", type=Path)
    c.add_argument("--out", type=Path, default=Path("out/wave_analysis"))
    c.add_argument("--lo", type=float, default=0.25)
    c.add_argument("--hi", type=float, default=0.75)
    b = sub.add_parser("bed", help="arrival times in the 2-D bed")
    b.add_argument("run", type=Path)
    b.add_argument("--out", type=Path, default=None)
    b.add_argument("--frames", type=int, nargs="+", default=[2, 4, 6], help="snapshots in the front picture")
    m = sub.add_parser("dem-c", help="DEM-C apparent front speed against iteration cap and step")
    m.add_argument("--out", type=Path, default=Path("out/wave_dem_c"))
    m.add_argument("--iterations", type=int, nargs="+", default=[1, 2, 5, 20])
    m.add_argument("--steps", type=float, nargs="+", default=[1e-6, 1e-5])
    m.add_argument("--relaxations", type=float, nargs="+", default=[0.3, 1.0])
    m.add_argument("--replot", action="store_true", help="redraw the figure from OUT/dem_c_front.csv")
    a = ap.parse_args(argv)
    if a.cmd == "chain":
        res = chain(a.runs, a.out, a.lo, a.hi)
        for r in res["runs"]:
            print(
                f"{r['run']}: striker {r['striker_speed']:g} m/s, F_m = {r['F_m']:.4g} N, "
                f"V_s = {r['V_s']:.2f} m/s, "
                f"Nesterenko {r['V_nesterenko']:.2f} m/s ({100 * r['error']:+.2f} %), pulse FWHM "
                f"{r.get('fwhm_d', math.nan):.3f} d, cos^4 width {r.get('width_d', math.nan):.2f} d, "
                f"{r.get('beads_above_1pct', '?')} beads above 1 %"
            )
        if "exponent" in res:
            print(f"exponent of V_s ~ F_m^a: a = {res['exponent']:.4f} (1/6 = {1 / 6:.4f})")
        print(f"wrote {a.out}/chain_speeds.csv, chain_speeds.png")
    elif a.cmd == "bed":
        res = bed(a.run, a.out or a.run, tuple(a.frames))
        for name, line in res["lines"].items():
            print(
                f"{name}: arrival {line['speed_arrival']:.1f} m/s, speed peak {line['speed_peak']:.1f} m/s, "
                f"force peak {line['speed_force_peak']:.1f} m/s"
            )
    else:
        if a.replot:
            plot_dem_c(read_dem_c(a.out / "dem_c_front.csv"), a.out / "dem_c_front.png")
        else:
            dem_c(a.out, a.iterations, a.steps, a.relaxations)
    return 0


if __name__ == "__main__":
    sys.exit(main())
