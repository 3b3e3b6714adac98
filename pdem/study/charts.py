"""Charts of a study (matplotlib, off-screen; each as PNG and SVG):

* ``error_vs_time_<quantity>``: error against wall time, log–log, one colour per method, one marker
  per series, each method's Pareto front (no faster run is more accurate) as a step line, the
  tolerance as a dashed line;
* ``error_vs_<knob>_<quantity>``: error against each varied knob, a line per series;
* ``stability``: the spec's ``[stability]`` map, each run a marker by its class (stable, drift,
  stopped by the live step bound, failed, uncaught, refused, timeout), with ``stability.csv``;
* ``crossover``: the spec's ``[crossover]`` chart, wall time against a stiffness knob: DEM-P's runs
  with a fitted power law extended to ``extend_to``, DEM-C's as one line, the x where they cross,
  with ``crossover.csv`` (the runs) and ``crossover.json`` (the fit).
"""

from __future__ import annotations

import csv
import math
import re
import statistics
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .core import Study

__all__ = ["write_charts", "pareto_front", "crossover_fit"]

COLOURS = {"DEM-P": "#1f77b4", "DEM-C": "#d62728"}
MARKERS = "osD^v<>pP*hX"
CLASSES = {
    "stable": ("#2ca02c", "o"),
    "drift": ("#ff7f0e", "s"),
    "stopped": ("#e377c2", "P"),  # by the live step bound, before it could go wrong
    "failed": ("#d62728", "X"),
    "uncaught": ("#000000", "*"),
    "refused": ("#7f7f7f", "x"),
    "timeout": ("#9467bd", "v"),
    "no value": ("#bcbd22", "d"),
    "not run": ("#dddddd", "."),
}


def pareto_front(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The (time, error) points no other point beats on both: sorted by time, each more accurate than
    every faster one."""
    front: list[tuple[float, float]] = []
    best = math.inf
    for t, e in sorted(points):
        if e < best:
            front.append((t, e))
            best = e
    return front


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text)


def _finite(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def write_charts(study: Study, rows: list[dict[str, Any]], out: Path) -> dict[str, Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spec = study.spec
    paths: dict[str, Path] = {}
    series_marker = {s.name: MARKERS[i % len(MARKERS)] for i, s in enumerate(spec.series)}
    title = spec.title or spec.deck.name

    def save(fig: Any, stem: str) -> None:
        for ext in ("png", "svg"):
            path = out / f"{stem}.{ext}"
            fig.savefig(path, dpi=130, bbox_inches="tight")
        paths[stem] = out / f"{stem}.png"
        plt.close(fig)

    for name, q in spec.quantities.items():
        ekey = f"{name}_error"
        fig, ax = plt.subplots(figsize=(6.4, 4.6))
        floor = _floor(rows, ekey)
        for method in sorted({r["method"] for r in rows}):
            colour = COLOURS.get(method, None)
            pts = []
            for s in spec.series:
                sel = [r for r in rows if r["series"] == s.name and r["method"] == method]
                xs, ys, zs = [], [], []
                for r in sel:
                    if _finite(r[ekey]) and _finite(r["wall_s"]):
                        pts.append((r["wall_s"], max(r[ekey], floor)))
                        if r[ekey] > 0:
                            xs.append(r["wall_s"])
                            ys.append(r[ekey])
                        else:
                            zs.append(r["wall_s"])
                marker = series_marker[s.name]
                if xs:
                    ax.scatter(xs, ys, color=colour, marker=marker, label=f"{method}: {s.name}", zorder=3)
                if zs:  # the reference run itself (error 0): hollow, drawn at the floor
                    ax.scatter(zs, [floor] * len(zs), facecolors="none", edgecolors=colour, s=90,
                               marker=marker, label=f"{method}: {s.name}, the reference (error 0)", zorder=3)
            front = pareto_front(pts)
            if len(front) > 1:
                fx, fy = zip(*front, strict=True)
                ax.step(fx, fy, where="post", color=colour, alpha=0.6, lw=1.5, label=f"{method} Pareto front")
        ax.axhline(q.tolerance, color="0.4", ls="--", lw=1, label=f"tolerance {q.tolerance:g}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(f"wall time [s] ({spec.time})")
        ax.set_ylabel(f"{'relative ' if q.relative else ''}error of {name}")
        ax.set_title(
            f"{title}\n{name}: error against wall time (error 0 drawn at {floor:.0e})", fontsize=9
        )
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="best")
        save(fig, f"error_vs_time_{_safe(name)}")

        varied = []
        for s in spec.series:
            for k in s.vary:
                if k not in varied:
                    varied.append(k)
        for knob in varied:
            fig, ax = plt.subplots(figsize=(6.4, 4.6))
            any_point = False
            for s in spec.series:
                if knob not in s.vary:
                    continue
                others = [k for k in s.vary if k != knob]
                groups: dict[tuple, list[dict[str, Any]]] = {}
                for r in rows:
                    if r["series"] == s.name:
                        groups.setdefault(tuple(r[k] for k in others), []).append(r)
                for key, grp in groups.items():
                    pts = sorted(
                        (r[knob], max(r[ekey], floor)) for r in grp if _finite(r[knob]) and _finite(r[ekey])
                    )
                    if not pts:
                        continue
                    any_point = True
                    xs, ys = zip(*pts, strict=True)
                    label = s.name + "".join(
                        f", {k.split('.')[-1]}={v}" for k, v in zip(others, key, strict=True)
                    )
                    ax.plot(
                        xs,
                        ys,
                        marker=series_marker[s.name],
                        color=COLOURS.get(grp[0]["method"]),
                        label=label,
                        alpha=0.85,
                    )
            if not any_point:
                plt.close(fig)
                continue
            xs_all = [r[knob] for r in rows if _finite(r[knob]) and r[knob] > 0]
            if xs_all and max(xs_all) / min(xs_all) > 20:
                ax.set_xscale("log")
            ax.set_yscale("log")
            ax.axhline(q.tolerance, color="0.4", ls="--", lw=1)
            ax.set_xlabel(knob)
            ax.set_ylabel(f"{'relative ' if q.relative else ''}error of {name}")
            ax.set_title(f"{title}\n{name}: error against {knob}", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
            save(fig, f"error_vs_{_safe(knob)}_{_safe(name)}")

    for st in spec.maps:
        paths.update(_stability(study, st, rows, out, save, plt, title))
    for cx in spec.crossovers:
        paths.update(_crossover(study, cx, rows, out, save, plt, title))
    return paths


def crossover_fit(study: Study, cx: Any, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The numbers of a crossover chart: each run of its series (x, wall time, error, within the
    tolerance or not), the power law t = a x^b fitted (least squares in log-log) through the penalty
    runs that ended ok, the rigid runs' median wall time t_rigid, and the x where the law reaches it
    (``x_cross``; None when the law does not rise or the fit has fewer than two values of x)."""
    q = cx.quantity or study.spec.primary
    tol = study.spec.quantities[q].tolerance
    ekey = f"{q}_error"
    runs = []
    for r in rows:
        role = "penalty" if r["series"] in cx.penalty else "rigid" if r["series"] in cx.rigid else None
        if role is None:
            continue
        x = r.get(cx.x) if role == "penalty" else None
        err = r.get(ekey)
        runs.append({
            "role": role, "series": r["series"], "run": r["run"], "method": r["method"],
            "x": x if _finite(x) else None, "wall_s": r["wall_s"] if _finite(r["wall_s"]) else None,
            "status": r["status"], "error": err if _finite(err) else None,
            "accurate": _finite(err) and err <= tol,
        })  # fmt: skip
    pen = [(math.log(u["x"]), math.log(u["wall_s"])) for u in runs if u["role"] == "penalty"
           and u["status"] == "ok" and u["x"] and u["x"] > 0 and u["wall_s"]]  # fmt: skip
    fit: dict[str, Any] = {"quantity": q, "tolerance": tol, "x": cx.x, "runs": runs, "a": None, "b": None}
    if len({lx for lx, _ in pen}) >= 2:
        n = len(pen)
        mx = sum(lx for lx, _ in pen) / n
        my = sum(ly for _, ly in pen) / n
        sxx = sum((lx - mx) ** 2 for lx, _ in pen)
        b = sum((lx - mx) * (ly - my) for lx, ly in pen) / sxx
        fit["b"] = b
        fit["a"] = math.exp(my - b * mx)
    rigid = sorted(u["wall_s"] for u in runs if u["role"] == "rigid" and u["status"] == "ok" and u["wall_s"])
    fit["t_rigid"] = statistics.median(rigid) if rigid else None
    fit["t_rigid_range"] = (rigid[0], rigid[-1]) if rigid else None
    fit["rigid_accurate"] = [u["accurate"] for u in runs if u["role"] == "rigid" and u["status"] == "ok"]
    fit["x_cross"] = None
    if fit["b"] is not None and fit["b"] > 0 and fit["t_rigid"]:
        fit["x_cross"] = (fit["t_rigid"] / fit["a"]) ** (1.0 / fit["b"])
    fit["marks"] = {}
    for label, xm in cx.marks.items():
        t_p = fit["a"] * xm ** fit["b"] if fit["b"] is not None else None
        ratio = t_p / fit["t_rigid"] if t_p and fit["t_rigid"] else None
        fit["marks"][label] = {"x": xm, "t_penalty": t_p, "penalty_over_rigid": ratio}
    return fit


def _crossover(study: Study, cx: Any, rows, out: Path, save, plt, title: str) -> dict[str, Path]:
    import json

    fit = crossover_fit(study, cx, rows)
    stem = f"crossover_{_safe(cx.name)}" if cx.name else "crossover"
    fig, ax = plt.subplots(figsize=(6.8, 4.8))
    pen = [u for u in fit["runs"] if u["role"] == "penalty" and u["x"] and u["wall_s"]]
    for ok, face in ((True, None), (False, "none")):
        sel = [u for u in pen if u["accurate"] is ok]
        if sel:
            label = f"DEM-P runs, {'within' if ok else 'outside'} {fit['tolerance']:g} of the reference"
            ax.scatter([u["x"] for u in sel], [u["wall_s"] for u in sel], color=COLOURS["DEM-P"],
                       facecolors=face, s=50, zorder=3, label=label)  # fmt: skip
    xs = [u["x"] for u in pen]
    hi = max([*xs, cx.extend_to or 0.0, *cx.marks.values()]) if xs else None
    if fit["b"] is not None and xs:
        lo = min(xs)
        grid = [lo * (hi / lo) ** (k / 60) for k in range(61)]
        ax.plot(grid, [fit["a"] * g ** fit["b"] for g in grid], color=COLOURS["DEM-P"], ls="--", lw=1.2,
                label=f"DEM-P fit: t ∝ x^{fit['b']:.2f}")  # fmt: skip
    if fit["t_rigid"]:
        lo_r, hi_r = fit["t_rigid_range"]
        left = min(xs) if xs else 1.0
        right = hi or left * 10
        n_ok, n_c = sum(fit["rigid_accurate"]), len(fit["rigid_accurate"])
        label = f"DEM-C (rigid), median of {n_c} run(s), {n_ok} within {fit['tolerance']:g}"
        ax.axhline(fit["t_rigid"], color=COLOURS["DEM-C"], lw=1.5, label=label)
        if hi_r > lo_r:
            ax.fill_between([left, right], lo_r, hi_r, color=COLOURS["DEM-C"], alpha=0.12, lw=0)
    if fit["x_cross"]:
        ax.axvline(fit["x_cross"], color="0.3", ls=":", lw=1.2, label=f"crossover x = {fit['x_cross']:.3g}")
    top = ax.get_ylim()[1]
    for k, (label, m) in enumerate(fit["marks"].items()):
        ax.axvline(m["x"], color="0.55", ls="-.", lw=0.9)
        ax.annotate(label, (m["x"], top / 1.6**k), rotation=90, va="top", ha="right", fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(cx.x)
    ax.set_ylabel(f"wall time [s] ({study.spec.time})")
    ax.set_title(f"{title}\nwall time against {cx.x}: DEM-P at its stable step, DEM-C as one line",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    save(fig, stem)
    table = out / f"{stem}.csv"
    with open(table, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["role", "series", "run", "method", cx.x, "wall_s", "status", f"{fit['quantity']}_error",
                    "within_tolerance"])  # fmt: skip
        for u in fit["runs"]:
            w.writerow([u["role"], u["series"], u["run"], u["method"], "" if u["x"] is None else u["x"],
                        "" if u["wall_s"] is None else f"{u['wall_s']:.6g}", u["status"],
                        "" if u["error"] is None else f"{u['error']:.6g}", u["accurate"]])  # fmt: skip
    numbers = out / f"{stem}.json"
    numbers.write_text(json.dumps({k: v for k, v in fit.items() if k != "runs"}, indent=2) + "\n")
    return {f"{stem}_table": table, f"{stem}_numbers": numbers}


def _floor(rows: list[dict[str, Any]], ekey: str) -> float:
    pos = [r[ekey] for r in rows if _finite(r[ekey]) and r[ekey] > 0]
    return min(pos) / 3 if pos else 1e-6


def _stability(study: Study, st: Any, rows, out: Path, save, plt, title: str) -> dict[str, Path]:
    q = st.quantity or study.spec.primary
    rows = [
        {
            **r,
            "stability": study.stability_class(
                r["status"], r["nonfinite"] or 0, r[f"{q}_error"], st.drift, r.get("message")
            ),
        }
        for r in rows
        if st.series is None or r["series"] in st.series
    ]
    stem = f"stability_{_safe(st.name)}" if st.name else "stability"
    x_of = (lambda r: r["dt_ratio"]) if st.x in ("dt_ratio",) else (lambda r: r.get(st.x))
    y_of = (lambda r: r["series"]) if st.y == "series" else (lambda r: r.get(st.y))
    ys = []
    for r in rows:
        y = y_of(r)
        if y not in ys:
            ys.append(y)
    fig, ax = plt.subplots(figsize=(6.8, 0.6 * len(ys) + 2.2))
    seen = set()
    for r in rows:
        x = x_of(r)
        if not _finite(x):
            continue
        cls = r["stability"]
        colour, marker = CLASSES.get(cls, ("#17becf", "o"))
        ax.scatter(
            [x],
            [ys.index(y_of(r))],
            color=colour,
            marker=marker,
            s=70,
            label=cls if cls not in seen else None,
            zorder=3,
        )
        seen.add(cls)
    ax.set_yticks(range(len(ys)))
    ax.set_yticklabels([str(y) for y in ys])
    xs = [x_of(r) for r in rows if _finite(x_of(r)) and x_of(r) > 0]
    if xs and max(xs) / min(xs) > 8:  # e.g. steps 1e-6 to 1.6e-5 s
        ax.set_xscale("log")
    if st.x in ("dt_ratio", "run.dt_fraction"):
        ax.axvline(1.0, color="0.3", ls=":", lw=1, label="stability estimate")
    ax.set_xlabel("dt / the law's stability estimate" if st.x == "dt_ratio" else st.x)
    ax.set_ylabel(st.y)
    ax.set_title(f"{title}\nstability (drift: error above {st.drift:g} against the reference)", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    save(fig, stem)
    path = out / f"{stem}.csv"
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([st.y, st.x, "stability", "status", "exit_code", f"{q}_error", "nonfinite", "message"])
        for r in rows:
            w.writerow(
                [
                    y_of(r),
                    x_of(r),
                    r["stability"],
                    r["status"],
                    r["exit_code"],
                    r[f"{q}_error"],
                    r["nonfinite"],
                    r["message"],
                ]
            )
    return {f"{stem}_table": path}
