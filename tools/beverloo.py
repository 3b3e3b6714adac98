#!/usr/bin/env python
"""Fit Beverloo's law to a hopper study: W = A (D − k d)^b with A = C ρ_b sqrt(g).

    python tools/beverloo.py studies/beverloo.toml [--out DIR] [--d 0.002] [--phi 0.6]

Reads the study's runs (``pdem study studies/beverloo.toml`` first): the orifice diameter D of each
run (the knob ``boundaries.<name>.orifice_diameter``), its steady flow rate W
(``results.<name>.flow_rate``), its method. For each method it fits

* the free exponent: A, k and b by least squares on ln W (for each k the problem is linear in ln A and
  b; k is found by a bounded scalar search, then refined), with standard errors from the Jacobian at
  the optimum (s² (JᵀJ)⁻¹, s² = RSS/(n − 3));
* Beverloo's form, b = 5/2 fixed: A and k.

C = A / (ρ_b sqrt(g)) with ρ_b = φ ρ (``--phi``, default 0.6: a loose random packing; say so when
quoting C). Writes ``beverloo.csv`` (the runs), ``beverloo.json`` (the fits) and ``beverloo.png/.svg``
(W against D − k d on log–log axes, both methods, the fitted lines) in DIR (default the study's
report directory).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import tomllib
from pathlib import Path

import numpy as np

G = 9.81


def _lin(lnw: np.ndarray, x: np.ndarray) -> tuple[float, float, float]:
    """ln W = a + b ln x by least squares: (a, b, RSS)."""
    lx = np.log(x)
    M = np.column_stack([np.ones_like(lx), lx])
    coef, *_ = np.linalg.lstsq(M, lnw, rcond=None)
    res = lnw - M @ coef
    return float(coef[0]), float(coef[1]), float(res @ res)


def fit(D: np.ndarray, W: np.ndarray, d: float, exponent: float | None = None) -> dict[str, float]:
    """Fit W = A (D − k d)^b (``exponent`` None: b free; else b fixed). Returns A, k, b, their standard
    errors (``*_err``; NaN where the data leave none), the RSS of ln W and R² of ln W."""
    D = np.asarray(D, float)
    W = np.asarray(W, float)
    if len(D) < (3 if exponent is None else 2) or np.any(W <= 0):
        raise ValueError("need at least 3 (free exponent) or 2 positive flow rates")
    lnw = np.log(W)
    k_hi = float(D.min() / d) * (1 - 1e-9)

    def rss(k: float) -> tuple[float, float, float]:
        x = D - k * d
        if exponent is None:
            return _lin(lnw, x)
        a = float(np.mean(lnw - exponent * np.log(x)))
        r = lnw - a - exponent * np.log(x)
        return a, exponent, float(r @ r)

    # a grid, then golden-section refinement around the best grid point (RSS(k) is smooth)
    grid = np.linspace(-2.0, k_hi, 801)
    vals = [rss(k)[2] for k in grid]
    i = int(np.argmin(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    phi = (math.sqrt(5) - 1) / 2
    for _ in range(100):
        a_, b_ = hi - phi * (hi - lo), lo + phi * (hi - lo)
        if rss(a_)[2] < rss(b_)[2]:
            hi = b_
        else:
            lo = a_
    k = 0.5 * (lo + hi)
    a, b, r = rss(k)
    x = D - k * d
    cols = (
        [-np.ones_like(x), b * d / x] if exponent is not None else [-np.ones_like(x), -np.log(x), b * d / x]
    )
    J = np.column_stack(cols)
    n, p = len(D), J.shape[1]
    errs = [math.nan] * p
    if n > p:
        s2 = r / (n - p)
        try:
            cov = s2 * np.linalg.inv(J.T @ J)
            errs = [float(math.sqrt(max(c, 0.0))) for c in np.diag(cov)]
        except np.linalg.LinAlgError:
            pass
    tss = float(((lnw - lnw.mean()) ** 2).sum())
    out = {
        "A": math.exp(a),
        "k": k,
        "b": b,
        "rss_lnW": r,
        "r2_lnW": 1 - r / tss if tss > 0 else math.nan,
        "n": n,
    }
    out["A_rel_err"] = errs[0]  # ln A's standard error = A's relative error
    if exponent is None:
        out["b_err"], out["k_err"] = errs[1], errs[2]
    else:
        out["b_err"], out["k_err"] = 0.0, errs[1]
    return out


def _diameter(deck: Path) -> float:
    data = tomllib.loads(deck.read_text())
    sizes = [p.get("sizes") for p in data.get("particles", []) if isinstance(p, dict)]
    for s in sizes:
        if isinstance(s, dict) and s.get("type") == "uniform":
            return float(s["r_min"] + s["r_max"])
    raise SystemExit(f"{deck}: no uniform size distribution to take the mean diameter from; give --d")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("spec", type=Path, help="the study spec (e.g. studies/beverloo.toml)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--d", type=float, default=None, help="mean grain diameter [m] (default: from the deck)")
    ap.add_argument("--phi", type=float, default=0.6, help="solid fraction for ρ_b = φ ρ (default 0.6)")
    args = ap.parse_args(argv)
    from pdem.study import Study

    study = Study.from_file(args.spec)
    d = args.d or _diameter(study.spec.deck)
    deck = tomllib.loads(study.spec.deck.read_text())
    rho = float(next(iter(deck["materials"].values()))["density"])
    rows = []
    for r in study.table():
        D = next((v for k, v in r.items() if k.endswith(".orifice_diameter") and isinstance(v, float)), None)
        if D is None or r["flow_rate"] is None:
            continue
        rows.append(
            {
                "method": r["method"],
                "series": r["series"],
                "D_m": D,
                "D_over_d": D / d,
                "flow_rate_kg_s": r["flow_rate"],
                "wall_s": r["wall_s"],
                "status": r["status"],
            }
        )
    if not rows:
        print("no finished run with an orifice diameter and a flow rate", file=sys.stderr)
        return 1
    out = args.out or study.spec.output / "report"
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "beverloo.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    fits: dict[str, dict] = {}
    for method in sorted({r["method"] for r in rows}):
        sel = sorted((r["D_m"], r["flow_rate_kg_s"]) for r in rows if r["method"] == method)
        D = np.array([s[0] for s in sel])
        W = np.array([s[1] for s in sel])
        res: dict[str, dict] = {}
        if len(D) >= 3:
            res["free_exponent"] = fit(D, W, d)
        if len(D) >= 2:
            res["beverloo_b_2.5"] = fit(D, W, d, exponent=2.5)
        for f in res.values():
            f["C"] = (
                f["A"] / (args.phi * rho * math.sqrt(G)) * (1.0 if abs(f["b"] - 2.5) < 1e-12 else math.nan)
            )
        fits[method] = res
    (out / "beverloo.json").write_text(
        json.dumps({"d_m": d, "phi": args.phi, "rho": rho, "fits": fits}, indent=2) + "\n"
    )
    _plot(rows, fits, d, out)
    for method, res in fits.items():
        for name, f in res.items():
            print(
                f"{method} {name}: b = {f['b']:.3f} ± {f['b_err']:.3f}, k = {f['k']:.2f} ± {f['k_err']:.2f}, "
                f"A = {f['A']:.4g} (±{100 * f['A_rel_err']:.0f} %), C = {f['C']:.3g}, "
                f"R²(ln W) = {f['r2_lnW']:.5f}, n = {f['n']}"
            )
    print(f"wrote {out / 'beverloo.json'}, {out / 'beverloo.csv'}, {out / 'beverloo.png'}")
    return 0


def _plot(rows: list[dict], fits: dict, d: float, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {"DEM-P": "#1f77b4", "DEM-C": "#d62728"}
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    for method, res in fits.items():
        sel = [r for r in rows if r["method"] == method]
        D = np.array([r["D_m"] for r in sel])
        W = np.array([r["flow_rate_kg_s"] for r in sel])
        c = colours.get(method)
        ax.scatter(D / d, W * 1e3, color=c, label=f"{method} runs", zorder=3)
        grid = np.linspace(D.min(), D.max(), 100)
        for name, style in (("free_exponent", "-"), ("beverloo_b_2.5", ":")):
            if name in res:
                f = res[name]
                ax.plot(
                    grid / d,
                    1e3 * f["A"] * (grid - f["k"] * d) ** f["b"],
                    style,
                    color=c,
                    label=f"{method}: b = {f['b']:.2f}"
                    + (f" ± {f['b_err']:.2f}" if name == "free_exponent" else " (fixed)")
                    + f", k = {f['k']:.2f}",
                )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("D / d")
    ax.set_ylabel("steady flow rate W [g/s]")
    ax.set_title("Hopper discharge against orifice diameter: W = A (D − k d)^b", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    for ext in ("png", "svg"):
        fig.savefig(out / f"beverloo.{ext}", dpi=130, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
