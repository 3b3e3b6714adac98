#!/usr/bin/env python
"""Run a direct shear deck at several normal stresses and fit the Mohr–Coulomb envelope.

    python tools/direct_shear_study.py [DECK] [--stress 3100 6400 12500 24200] [--out out/shear_study]
                                       [--set KEY=VALUE ...]

Each run is ``pdem DECK --set boundaries.box.normal_stress=S`` (plus the extra ``--set``s) into
``OUT/sigma_S``; the summaries' peak and residual τ are fitted by τ = σ tan φ (through the origin)
and by τ = c + σ tan φ (with R²). Prints a table and writes ``OUT/mohr_coulomb.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from pdem.cli import main as pdem_main


def fit(sigma: np.ndarray, tau: np.ndarray) -> dict[str, float]:
    """Friction angle through the origin, and a line τ = c + σ tan φ with its R²."""
    phi0 = math.degrees(math.atan(float(sigma @ tau) / float(sigma @ sigma)))
    out = {"phi_origin_deg": phi0}
    if len(sigma) >= 2:
        slope, c = np.polyfit(sigma, tau, 1)
        pred = c + slope * sigma
        ss = float(((tau - tau.mean()) ** 2).sum())
        out |= {"phi_deg": math.degrees(math.atan(slope)), "cohesion_pa": float(c),
                "r2": 1.0 - float(((tau - pred) ** 2).sum()) / ss if ss > 0 else 1.0}  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("deck", nargs="?", default="inputs/direct_shear.toml")
    p.add_argument("--stress", type=float, nargs="+", default=[3100.0, 6400.0, 12500.0, 24200.0])
    p.add_argument("--out", type=Path, default=Path("out/shear_study"))
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    rows = []
    for s in args.stress:
        out = args.out / f"sigma_{s:g}"
        cmd = [args.deck, "--output", str(out), "--quiet", "--set", f"boundaries.box.normal_stress={s}"]
        for o in args.overrides:
            cmd += ["--set", o]
        if pdem_main(cmd) != 0:
            print(f"run at {s:g} Pa failed", file=sys.stderr)
            return 1
        res = json.loads((out / "summary.json").read_text())["results"]["box"]
        rows.append((s, res))
        print(
            f"sigma = {s:8.0f} Pa  peak ratio {res['peak_ratio']:.3f}  residual {res['residual_ratio']:.3f}"
            f"  normal-stress error mean {res['mean_abs_error']:.4f} p95 {res['p95_abs_error']:.4f}"
        )
    sigma = np.array([s for s, _ in rows])
    result = {
        "runs": {f"{s:g}": r for s, r in rows},
        # τ/σ_n is area-independent; fit the ratios × the applied stress
        "peak": fit(sigma, sigma * np.array([r["peak_ratio"] for _, r in rows])),
        "residual": fit(sigma, sigma * np.array([r["residual_ratio"] for _, r in rows])),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "mohr_coulomb.json").write_text(json.dumps(result, indent=2) + "\n")
    for k in ("peak", "residual"):
        print(k, {a: round(b, 4) for a, b in result[k].items()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
