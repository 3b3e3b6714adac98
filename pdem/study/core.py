"""A study: run the spec's grid (resumable, several at a time), then tabulate each run's measured
quantities, their errors against the reference, the wall times, and the stability class of each run."""

from __future__ import annotations

import csv
import math
import re
import statistics
import sys
import threading
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from ..errors import InputError
from .launch import RunRecord, launch, lookup, read_record, reset_stop, series_value, stop_all, summary_of
from .spec import Quantity, RunPlan, StudySpec, load_spec, plan_runs

__all__ = ["Study", "RunResult"]

# the overlap check's message ("dt = X s, stability estimate Y s") and the live bound's ("dt = X s
# is … the law's estimate Y s does not see them")
# the live step bound's stop (pdem.simulation.Simulation.check_stiffness): a run stopped before it went
# wrong, told apart from one that blew up
_BOUND_STOP = "the step is too large for the contacts"
_DT_IN_MESSAGE = re.compile(
    r"dt = ([0-9.eE+-]+) s(?:, stability estimate| is .*?the law's estimate) ([0-9.eE+-]+) s"
)


@dataclass
class RunResult:
    """A planned run with what is known of it on disk."""

    plan: RunPlan
    record: RunRecord | None
    summary: dict[str, Any] | None

    @property
    def status(self) -> str:
        return "not run" if self.record is None else self.record.status

    @property
    def ok(self) -> bool:
        return self.record is not None and self.record.status == "ok" and self.summary is not None

    def wall(self, kind: str) -> float | None:
        if self.record is None:
            return None
        if kind == "run" and self.summary is not None:
            # the stepping (stepping_time_s; summaries before it had only wall_time_s, which was that)
            return float(self.summary.get("stepping_time_s", self.summary.get("wall_time_s", math.nan)))
        return self.record.process_wall_s

    def value(self, q: Quantity) -> float | None:
        """The quantity's value in this run (None: not ok, absent or not finite)."""
        if not self.ok:
            return None
        if q.path is not None:
            return lookup(self.summary, q.path)
        return series_value(self.plan.directory, q)

    @property
    def dt_ratio(self) -> float | None:
        """dt / the law's stability estimate: from summary.json, else from ``run.dt_fraction``."""
        if self.summary is not None:
            dt, crit = self.summary.get("dt"), self.summary.get("dt_critical")
            if isinstance(dt, int | float) and isinstance(crit, int | float) and crit > 0:
                return float(dt) / float(crit)
        frac = self.plan.knobs.get("run.dt_fraction")
        if isinstance(frac, int | float):
            return float(frac)
        # a failed run has no summary: its instability message states both
        m = _DT_IN_MESSAGE.search(self.record.stderr_tail if self.record else "")
        return float(m.group(1)) / float(m.group(2)) if m else None

    @property
    def message(self) -> str:
        """The error pdem printed (the last non-empty stderr line of a failed run)."""
        if self.record is None or self.record.status == "ok":
            return ""
        lines = [ln for ln in self.record.stderr_tail.splitlines() if ln.strip()]
        return lines[-1].strip() if lines else ""


class Study:
    """The Python face of ``pdem study``::

    study = Study.from_file("studies/hopper.toml", jobs=2)
    study.run()                    # resumable: finished runs are kept
    rows = study.table()           # one dict per run
    paths = study.report()         # CSV, charts (PNG + SVG) and a short reading
    """

    def __init__(self, spec: StudySpec) -> None:
        self.spec = spec
        self.plans = plan_runs(spec)

    @classmethod
    def from_file(cls, path: str | Path, **overrides: Any) -> Study:
        return cls(load_spec(path, {k: v for k, v in overrides.items() if v is not None}))

    # ------------------------------------------------------------------ running
    def select(self, series: Iterable[str] | None = None) -> list[RunPlan]:
        """The planned runs of the named series (all with ``None``); an unknown name is an
        :class:`InputError` naming the spec's series."""
        if series is None:
            return list(self.plans)
        wanted = list(series)
        names = [s.name for s in self.spec.series]
        unknown = [n for n in wanted if n not in names]
        if unknown:
            raise InputError(
                f"study: --series {unknown[0]!r} is not a series of the spec; its series are: "
                f"{', '.join(names)}"
            )
        return [p for p in self.plans if p.series in wanted]

    def run(
        self,
        *,
        retry_failed: bool = False,
        series: Iterable[str] | None = None,
        progress: TextIO | None = sys.stderr,
    ) -> list[RunResult]:
        """Run every planned run that has no record yet (and, with ``retry_failed``, those that did
        not end ``ok``), ``spec.jobs`` at a time; with ``series``, only the runs of those series (the
        others are left as they are, run or not). Progress and a time estimate go to ``progress``."""
        spec = self.spec
        plans = self.select(series)
        reset_stop()
        todo = []
        for plan in plans:
            rec = read_record(plan.directory)
            keep = (
                rec is not None and rec.sets == plan.set_args() and (rec.status == "ok" or not retry_failed)
            )
            if not keep:
                todo.append(plan)
        total, kept = len(plans), len(plans) - len(todo)
        lock = threading.Lock()
        durations: list[float] = []
        by_series: dict[str, list[float]] = {}
        finished: set[str] = set()
        done = [kept]
        t_start = time.perf_counter()

        def say(text: str) -> None:
            if progress is not None:
                with lock:
                    print(text, file=progress, flush=True)

        say(
            f"study {spec.title or spec.deck.name}: {total} runs, {kept} kept from before, "
            f"{len(todo)} to run "
            f"({spec.jobs} at a time, {spec.ranks} rank(s) each) in {spec.output}"
        )

        def one(plan: RunPlan) -> RunRecord:
            say(f"  start {plan.name}: {' '.join(plan.set_args())}")
            record, _ = launch(
                spec.deck,
                plan.directory,
                plan.set_args(),
                ranks=spec.ranks,
                timeout=spec.timeout,
                check_finite=spec.check_finite,
                rerun=True,
            )
            return record

        pool = ThreadPoolExecutor(max_workers=spec.jobs)
        try:
            futures = {pool.submit(one, plan): plan for plan in todo}
            for fut in as_completed(futures):
                plan = futures[fut]
                record = fut.result()
                with lock:
                    durations.append(record.process_wall_s)
                    by_series.setdefault(plan.series, []).append(record.process_wall_s)
                    finished.add(plan.name)
                    done[0] += 1
                    # each run still to finish at its series' median so far (else the overall one)
                    left = [p for p in todo if p.name not in finished]
                    work = sum(statistics.median(by_series.get(p.series, durations)) for p in left)
                    eta = work / min(spec.jobs, max(len(left), 1))
                res = RunResult(plan, record, summary_of(plan.directory))
                q = spec.primary
                value = res.value(spec.quantities[q])
                shown = f", {q} = {value:.6g}" if value is not None else ""
                why = f" ({res.message})" if res.message else ""
                say(
                    f"[{done[0]}/{total}] {plan.name}: {record.status}{why} in {record.process_wall_s:.1f} s"
                    f"{shown}; about {_duration(eta)} left"
                )
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            stop_all()
            raise
        pool.shutdown(wait=True)
        say(f"study done in {_duration(time.perf_counter() - t_start)}")
        return self.results()

    # ------------------------------------------------------------------ results
    def results(self) -> list[RunResult]:
        return [RunResult(p, read_record(p.directory), summary_of(p.directory)) for p in self.plans]

    def reference(self, name: str, results: list[RunResult] | None = None) -> tuple[float | None, str]:
        """The reference value of quantity ``name`` and a description of where it comes from."""
        q = self.spec.quantities[name]
        ref = q.reference
        results = results if results is not None else self.results()
        if ref.value is not None:
            return ref.value, f"{ref.value:.6g} ({ref.source})"
        target = ref.series or ref.finest
        pool = [r for r in results if r.plan.series == target and r.value(q) is not None]
        if not pool:
            return None, f"series {target!r} has no finished run with {q.label}"
        if ref.series is not None:
            vals = [r.value(q) for r in pool]
            mean = sum(vals) / len(vals)
            return mean, f"{mean:.6g} (mean of {len(vals)} run(s) of series {target!r})"
        ordered = [r for r in pool if isinstance(r.plan.knobs.get(ref.by), int | float)]
        if not ordered:
            return None, f"series {target!r}: no finished run has a number for {ref.by}"
        best = (max if ref.largest else min)(ordered, key=lambda r: r.plan.knobs[ref.by])
        v = best.value(q)
        return v, f"{v:.6g} (finest run {best.plan.name}, {ref.by} = {best.plan.knobs[ref.by]})"

    def error(self, name: str, value: float | None, ref: float | None) -> float | None:
        if value is None or ref is None:
            return None
        if self.spec.quantities[name].relative:
            return abs(value - ref) / abs(ref) if ref != 0 else None
        return abs(value - ref)

    @staticmethod
    def stability_class(
        status: str, nonfinite: int, err: float | None, drift: float, message: str | None = ""
    ) -> str:
        """stable / drift (error above ``drift``) / stopped (exit 3 from the live step bound, before
        the run could blow up or go silently wrong: its ``message``) / failed (caught: exit 3, nothing
        non-finite on disk) / uncaught (a crash, or non-finite values left on disk) / refused /
        timeout / no value / not run."""
        if status == "ok":
            if err is None:
                return "no value"
            return "stable" if err <= drift else "drift"
        if status == "failed":
            if nonfinite:
                return "uncaught"
            return "stopped" if _BOUND_STOP in (message or "") else "failed"
        if status == "error":
            return "uncaught"
        return status

    def table(self, results: list[RunResult] | None = None) -> list[dict[str, Any]]:
        """One row per run: series, method, knobs, status, wall times, steps, dt / estimate, solver
        iterations, and for each quantity its value and error."""
        results = results if results is not None else self.results()
        refs = {name: self.reference(name, results)[0] for name in self.spec.quantities}
        keys: list[str] = []
        for p in self.plans:
            for k in p.knobs:
                if k not in keys:
                    keys.append(k)
        first = self.spec.maps[0] if self.spec.maps else None
        stab_q = (first.quantity if first else None) or self.spec.primary
        drift = first.drift if first else 0.01
        rows = []
        for r in results:
            s = r.summary or {}
            solver = s.get("solver") if isinstance(s.get("solver"), dict) else {}
            row: dict[str, Any] = {
                "series": r.plan.series,
                "run": r.plan.directory.name,
                "method": r.plan.method,
                **{k: r.plan.knobs.get(k, "") for k in keys},
                "status": r.status,
                "exit_code": "" if r.record is None or r.record.exit_code is None else r.record.exit_code,
                "wall_s": r.wall(self.spec.time),
                "process_wall_s": r.record.process_wall_s if r.record else None,
                "steps": s.get("steps"),
                "dt": s.get("dt"),
                "dt_ratio": r.dt_ratio,
                # the live step bound (DEM-P laws that support it): smallest over the run, and dt / it
                "bound_dt": (s.get("stiffness_bound") or {}).get("dt_min"),
                "dt_over_bound": (s.get("stiffness_bound") or {}).get("dt_over_bound"),
                "mean_iterations": solver.get("mean_iterations"),
                "unconverged_steps": solver.get("unconverged_steps"),
            }
            for name, q in self.spec.quantities.items():
                v = r.value(q)
                row[name] = v
                row[f"{name}_error"] = self.error(name, v, refs[name])
            nonfinite = len(r.record.nonfinite) if r.record else 0
            row["stability"] = self.stability_class(
                r.status, nonfinite, row[f"{stab_q}_error"], drift, r.message
            )
            row["nonfinite"] = nonfinite
            row["message"] = r.message
            rows.append(row)
        return rows

    def report(self, directory: Path | None = None) -> dict[str, Path]:
        """Write ``study.csv``, the charts (PNG and SVG) and ``reading.md`` into ``directory``
        (default ``OUTPUT/report``); returns the paths by kind."""
        from .charts import write_charts

        out = Path(directory) if directory is not None else self.spec.output / "report"
        out.mkdir(parents=True, exist_ok=True)
        results = self.results()
        rows = self.table(results)
        paths: dict[str, Path] = {}
        csv_path = out / "study.csv"
        with open(csv_path, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            for row in rows:
                w.writerow({k: _cell(v) for k, v in row.items()})
        paths["table"] = csv_path
        paths.update(write_charts(self, rows, out))
        reading = out / "reading.md"
        reading.write_text(self.reading(rows, results))
        paths["reading"] = reading
        return paths

    def reading(self, rows: list[dict[str, Any]], results: list[RunResult]) -> str:
        """A short text: the reference, and for each quantity which method reaches its tolerance
        first, in how much wall time, and by what factor."""
        spec = self.spec
        lines = [f"# {spec.title or 'Study'}", "", f"Deck: `{spec.deck.name}`; {len(rows)} runs.", ""]
        counts: dict[str, int] = {}
        for row in rows:
            counts[row["status"]] = counts.get(row["status"], 0) + 1
        lines.append("Runs by status: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) + ".")
        lines.append("")
        for name, q in spec.quantities.items():
            ref, where = self.reference(name, results)
            lines.append(f"## {name} (`{q.label}`)")
            lines.append("")
            lines.append(
                f"Reference: {where}. Accuracy asked: {q.tolerance:g}{' (relative)' if q.relative else ''}."
            )
            lines.append("")
            best: dict[str, tuple[float, dict[str, Any]]] = {}
            for row in rows:
                err, wall = row[f"{name}_error"], row["wall_s"]
                if err is None or wall is None or not math.isfinite(wall) or err > q.tolerance:
                    continue
                m = row["method"]
                if m not in best or wall < best[m][0]:
                    best[m] = (wall, row)
            methods = sorted({row["method"] for row in rows})
            for m in methods:
                if m in best:
                    wall, row = best[m]
                    lines.append(
                        f"- {m}: fastest run within {q.tolerance:g}: `{row['series']}/{row['run']}`, "
                        f"{wall:.1f} s, error {row[f'{name}_error']:.3g}"
                    )
                else:
                    lines.append(f"- {m}: no run within {q.tolerance:g}")
            if len(best) >= 2:
                ordered = sorted(best.items(), key=lambda kv: kv[1][0])
                (m1, (t1, _)), (m2, (t2, _)) = ordered[0], ordered[1]
                lines.append(f"- {m1} reaches {q.tolerance:g} first, {t2 / t1:.2f}× faster than {m2}.")
            lines.append("")
        for cx in spec.crossovers:
            lines += self._crossover_reading(cx, rows)
        failed = [row for row in rows if row["status"] not in ("ok", "not run")]
        if failed:
            lines.append("## Runs that did not end ok")
            lines.append("")
            for row in failed:
                lines.append(
                    f"- `{row['series']}/{row['run']}`: {row['stability']} ({row['status']}, exit "
                    f"{row['exit_code']}): {row['message'][:300]}"
                )
            lines.append("")
        return "\n".join(lines)


    def _crossover_reading(self, cx: Any, rows: list[dict[str, Any]]) -> list[str]:
        from .charts import crossover_fit

        fit = crossover_fit(self, cx, rows)
        lines = [f"## Crossover{' ' + cx.name if cx.name else ''}: wall time against `{cx.x}`", ""]
        if fit["b"] is None or not fit["t_rigid"]:
            lines += ["Not enough finished runs for the fit (two values of x for DEM-P, one DEM-C run).", ""]
            return lines
        within = [u for u in fit["runs"] if u["role"] == "penalty" and u["accurate"]]
        n_pen = sum(u["role"] == "penalty" for u in fit["runs"])
        lines.append(
            f"- DEM-P's wall time grows as x^{fit['b']:.2f} over its runs ({len(within)} of "
            f"{n_pen} within {fit['tolerance']:g} of the reference); "
            f"DEM-C's is {fit['t_rigid']:.1f} s (median), within {fit['tolerance']:g} in "
            f"{sum(fit['rigid_accurate'])} of {len(fit['rigid_accurate'])} run(s)."
        )
        if fit["x_cross"]:
            lines.append(f"- The two cross at x = {fit['x_cross']:.3g}: above it DEM-C takes less wall time.")
        else:
            lines.append("- The fitted DEM-P line does not rise with x: no crossover.")
        x_max = max((u["x"] for u in fit["runs"] if u["role"] == "penalty" and u["x"] is not None),
                    default=math.inf)  # fmt: skip
        for label, m in fit["marks"].items():
            if m["t_penalty"]:
                where = (
                    "extrapolated past its stiffest run" if m["x"] > x_max * (1 + 1e-9)
                    else "within its runs' range"
                )  # fmt: skip
                lines.append(
                    f"- {label} (x = {m['x']:.3g}): DEM-P {m['t_penalty']:.3g} s by the fit ({where}), "
                    f"{m['penalty_over_rigid']:.3g}× DEM-C's."
                )
        lines.append("")
        return lines


def _cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.9g}"
    return v


def _duration(seconds: float) -> str:
    seconds = max(0.0, seconds)
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"
