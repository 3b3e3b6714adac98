#!/usr/bin/env python
"""Drop a sphere and cones from several heights onto the bed and fit depth against drop distance.

    python tools/cone_drop_series.py [DECK] [--tips sphere cone60 cone30] [--heights 0.02 0.05 0.1 0.3]
                                     [--ranks N] [--out DIR] [--set KEY=VALUE ...] [--render] [--dry-run]
    python tools/cone_drop_series.py --compare DIR1 DIR2 [...] [--labels DEM-P DEM-C] [--out DIR]

Each run is ``pdem DECK --set boundaries.pen.tip=... --set boundaries.pen.release_height=H`` (plus
``apex_deg`` and ``shaft_length`` = ``--cone-shaft`` for a cone: by default 0, solid cones of the
standard base (D = 20.3 mm) and density 700 kg/m³ like the ball; plus the extra ``--set``s) into
``OUT/<tip>_H<cm>``, one after the other
(``mpiexec -n N`` with ``--ranks``). A run whose ``summary.json`` exists is kept and skipped, so the
series can be stopped and started again; a failed run stops it with its exit code. DECK defaults to
``inputs/cone_drop.toml`` (reduced bed); OUT to ``out/cone_drop_series``.

Then, from every run's ``summary.json`` (``results.pen``): the final depth d of the tip below the
bed surface and the total drop distance H + d, and per tip a least-squares power law
d = A (H + d)^n in log–log (exponent n; Uehara et al., PRL 90, 194301, 2003, report n = 1/3 for
spheres in loose beads). Written: ``OUT/drop_series.csv`` (tip, H, d, H + d, impact speed, mass,
how long the body has been at rest at the end, wall time), ``OUT/drop_series.json`` (the fits)
and ``OUT/drop_series.png``. ``--render`` draws each run's last frame cut through the axis
(``tools/render.py --clip-y``: the crater and the body) into ``OUT/<run>/crater.png``.

``--compare`` runs nothing: it reads the ``drop_series.json`` of finished series (e.g. DEM-P and
DEM-C) and writes ``OUT/drop_compare.csv`` (each tip and height: every series' depth and wall time,
and each depth over the first series') and ``OUT/drop_compare.png`` (all on one log–log plot).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pdem.study import command, launch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

TIPS = {
    "sphere": ["boundaries.pen.tip=sphere"],
    "cone60": ["boundaries.pen.tip=cone", "boundaries.pen.apex_deg=60.0"],
    "cone30": ["boundaries.pen.tip=cone", "boundaries.pen.apex_deg=30.0"],
}
CONES = ("cone60", "cone30")


def fit_power_law(total: np.ndarray, depth: np.ndarray) -> tuple[float, float]:
    """(A, n) of depth = A total^n, least squares in log–log over the positive pairs."""
    ok = (total > 0) & (depth > 0)
    if ok.sum() < 2:
        return math.nan, math.nan
    n, log_a = np.polyfit(np.log(total[ok]), np.log(depth[ok]), 1)
    return float(math.exp(log_a)), float(n)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("deck", nargs="?", type=Path, default=ROOT / "inputs" / "cone_drop.toml")
    ap.add_argument("--tips", nargs="+", choices=sorted(TIPS), default=["sphere", "cone60", "cone30"])
    ap.add_argument("--heights", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.3], help="H [m]")
    ap.add_argument("--ranks", type=int, default=1)
    ap.add_argument("--out", type=Path, default=Path("out") / "cone_drop_series")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--cone-shaft", type=float, default=0.0,
                    help="rod length above the cones [m] (default 0: solid cones, like the ball; the "
                    "deck's 0.1 drops the whole penetrometer)")  # fmt: skip
    ap.add_argument("--render", action="store_true", help="crater picture of each run (pyvista)")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    ap.add_argument("--compare", type=Path, nargs="+", metavar="DIR",
                    help="compare finished series (their drop_series.json) instead of running")  # fmt: skip
    ap.add_argument("--labels", nargs="+", help="with --compare: one label per DIR (default: the names)")
    args = ap.parse_args(argv)
    if args.compare:
        return compare(args.compare, args.labels, args.out)
    runs = [(tip, h) for tip in args.tips for h in args.heights]
    rows = []
    for k, (tip, h) in enumerate(runs):
        run_dir = args.out / f"{tip}_H{h * 100:g}cm"
        sets = [*TIPS[tip], f"boundaries.pen.release_height={h!r}"]
        if tip in CONES:
            sets.append(f"boundaries.pen.shaft_length={args.cone_shaft!r}")
        sets += args.overrides
        cmd = command(args.deck, run_dir, sets, args.ranks)
        if args.dry_run:
            print(" ".join(cmd))
            continue
        record, ran = launch(args.deck, run_dir, sets, ranks=args.ranks)
        print(f"[{k + 1}/{len(runs)}] {run_dir}: {record.status}"
              f" ({f'{record.process_wall_s:.0f} s' if ran else 'done before, kept'})", file=sys.stderr)
        if record.status != "ok":
            print(record.stderr_tail, file=sys.stderr)
            return record.exit_code or 1
        summary = json.loads((run_dir / "summary.json").read_text())
        res = summary["results"]["pen"]
        rows.append({"tip": tip, "H_m": h, "depth_m": res["final_depth"], "total_drop_m": res["total_drop"],
                     "impact_velocity_m_s": res.get("impact_velocity"), "mass_kg": res["mass"],
                     "rest_time_s": res.get("rest_time"), "completed": summary.get("completed"),
                     "wall_time_s": summary.get("wall_time_s"),
                     "run": run_dir.name})  # fmt: skip
        if args.render and not (run_dir / "crater.png").is_file():
            subprocess.call([sys.executable, str(ROOT / "tools" / "render.py"), str(run_dir), "--clip-y",
                             "--field", "speed", "--out", str(run_dir / "crater.png")])  # fmt: skip
    if args.dry_run or not rows:
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    with (args.out / "drop_series.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    fits = {}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5))
    for tip in args.tips:
        sel = [r for r in rows if r["tip"] == tip]
        tot = np.array([r["total_drop_m"] for r in sel])
        dep = np.array([r["depth_m"] for r in sel])
        a, n = fit_power_law(tot, dep)
        fits[tip] = {"A": a, "exponent": n, "runs": len(sel)}
        print(f"{tip}: d = {a:.4g} (H + d)^{n:.3f} over {len(sel)} heights; depths "
              + ", ".join(f"{r['H_m'] * 100:g} cm -> {r['depth_m'] * 1000:.2f} mm" for r in sel))  # fmt: skip
        line = ax.loglog(tot * 100, dep * 1000, "o", label=f"{tip}: n = {n:.2f}")[0]
        if math.isfinite(n):
            xs = np.geomspace(tot.min(), tot.max(), 20)
            ax.loglog(xs * 100, a * xs**n * 1000, "-", color=line.get_color(), lw=0.8)
    ax.set_xlabel("total drop distance H + d [cm]")
    ax.set_ylabel("final depth d [mm]")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "drop_series.png", dpi=120)
    (args.out / "drop_series.json").write_text(json.dumps({"fits": fits, "runs": rows}, indent=2) + "\n")
    print(f"wrote {args.out / 'drop_series.csv'}, .json, .png", file=sys.stderr)
    return 0


def compare(dirs: list[Path], labels: list[str] | None, out: Path) -> int:
    """Depths of several finished series side by side (see the module doc); 2 on missing input."""
    labels = labels or [d.name for d in dirs]
    if len(labels) != len(dirs):
        print(f"--labels: {len(labels)} label(s) for {len(dirs)} director(ies)", file=sys.stderr)
        return 2
    series = []
    for d in dirs:
        f = d / "drop_series.json"
        if not f.is_file():
            print(f"{f}: not found; run the series into {d} first", file=sys.stderr)
            return 2
        series.append({(r["tip"], r["H_m"]): r for r in json.loads(f.read_text())["runs"]})
    keys = list(dict.fromkeys(k for runs in series for k in runs))
    rows = []
    for tip, h in keys:
        row: dict[str, object] = {"tip": tip, "H_m": h}
        ref = series[0].get((tip, h))
        for lab, runs in zip(labels, series, strict=True):
            r = runs.get((tip, h))
            row[f"depth_m {lab}"] = r["depth_m"] if r else math.nan
            row[f"wall_time_s {lab}"] = r.get("wall_time_s") if r else math.nan
            if lab != labels[0]:
                row[f"{lab} / {labels[0]}"] = r["depth_m"] / ref["depth_m"] if r and ref else math.nan
        rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "drop_compare.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    for row in rows:
        print(f"{row['tip']:7s} H = {row['H_m'] * 100:4g} cm: " + ", ".join(
            f"{lab} {row[f'depth_m {lab}'] * 1000:.2f} mm" for lab in labels) + "".join(
            f"; {lab}/{labels[0]} {row[f'{lab} / {labels[0]}']:.3f}" for lab in labels[1:]))  # fmt: skip
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5))
    tips = list(dict.fromkeys(t for t, _ in keys))
    colours = {t: f"C{k}" for k, t in enumerate(tips)}
    for m, (lab, runs) in enumerate(zip(labels, series, strict=True)):
        for tip in tips:
            sel = [runs[k] for k in keys if k[0] == tip and k in runs]
            if sel:
                tot = np.array([r["total_drop_m"] for r in sel]) * 100
                dep = np.array([r["depth_m"] for r in sel]) * 1000
                style = "os^v"[m % 4] + "-:"[m % 2]
                ax.loglog(tot, dep, style, color=colours[tip], mfc="none" if m else None, lw=0.8,
                          label=f"{tip}, {lab}")  # fmt: skip
    ax.set_xlabel("total drop distance H + d [cm]")
    ax.set_ylabel("final depth d [mm]")
    for axis in (ax.xaxis, ax.yaxis):  # plain numbers: the decades here are few
        axis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xticks([2, 3, 5, 10, 20, 30])
    ax.set_yticks([5, 7, 10, 15, 20, 30])
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "drop_compare.png", dpi=120)
    print(f"wrote {out / 'drop_compare.csv'}, .png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
