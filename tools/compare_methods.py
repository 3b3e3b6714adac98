#!/usr/bin/env python
"""Run one deck with both contact methods and compare what it measures.

    python tools/compare_methods.py DECK [--set KEY=VALUE ...] [--p-set ...] [--c-set ...]
                                    [--ranks N] [--out DIR] [--steps N]

The deck runs twice through the ``pdem`` command: once with ``contact.law = "hertz_mindlin"``
(DEM-P, plus ``--p-set`` overrides) and once with ``contact.law = "complementarity"`` (DEM-C, plus
``--c-set``); ``--set`` applies to both. For each run it prints the step size, the number of steps,
the wall time and every result the deck's boundaries report in ``summary.json`` (e.g. the hopper's
steady flow rate), then the relative difference of each numeric result, DEM-C against DEM-P.
``DIR/compare.json`` keeps the table. Exit code: 0 if both runs completed, 1 otherwise.

Example (the hopper, each method at the deck's settings: DEM-C's step ~64× DEM-P's)::

    python tools/compare_methods.py inputs/hopper.toml --out out/compare_hopper
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pdem.study import launch

METHODS = {"DEM-P": "hertz_mindlin", "DEM-C": "complementarity"}


def run_method(deck: Path, law: str, sets: list[str], out: Path, ranks: int, steps: int | None) -> dict:
    """One run through ``pdem.study.launch`` (the process, its record and its logs in ``out``)."""
    extra = ["--steps", str(steps)] if steps is not None else []
    record, _ = launch(deck, out, [f"contact.law={law}", *sets], ranks=ranks, extra=extra, rerun=True)
    summary_path = out / "summary.json"
    summary = json.loads(summary_path.read_text()) if summary_path.exists() else {}
    lines = [ln for ln in record.stderr_tail.splitlines() if ln.strip()]
    return {
        "law": law,
        "exit_code": record.exit_code,
        "error": lines[-1] if record.exit_code and lines else "",
        "elapsed_s": record.process_wall_s,
        "summary": summary,
    }


def _flatten(results: dict, prefix: str = "") -> dict[str, float]:
    out = {}
    for k, v in results.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        elif isinstance(v, int | float) and not isinstance(v, bool):
            out[key] = float(v)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("deck", type=Path)
    ap.add_argument("--set", dest="sets", action="append", default=[], help="override for both runs")
    ap.add_argument("--p-set", dest="p_sets", action="append", default=[], help="override for DEM-P only")
    ap.add_argument("--c-set", dest="c_sets", action="append", default=[], help="override for DEM-C only")
    ap.add_argument("--ranks", type=int, default=1, help="MPI ranks for both runs (default 1)")
    ap.add_argument("--steps", type=int, default=None, help="stop each run after this many steps")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default out/compare_<deck>)")
    args = ap.parse_args(argv)
    out = args.out or Path("out") / f"compare_{args.deck.stem}"
    out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for label, law in METHODS.items():
        extra = args.p_sets if label == "DEM-P" else args.c_sets
        print(f"running {label} ({law}) ...", flush=True)
        runs[label] = run_method(args.deck, law, [*args.sets, *extra], out / label, args.ranks, args.steps)
    rows = []
    print()
    print(f"{'':28s} {'DEM-P':>14s} {'DEM-C':>14s} {'C/P':>8s}")
    res = {k: _flatten(r["summary"].get("results", {})) for k, r in runs.items()}
    general = {
        k: {
            "dt [s]": r["summary"].get("dt", float("nan")),
            "steps": r["summary"].get("steps", float("nan")),
            "wall time [s]": r["summary"].get("wall_time_s", float("nan")),
        }
        for k, r in runs.items()
    }
    for name in ("dt [s]", "steps", "wall time [s]"):
        p, c = general["DEM-P"][name], general["DEM-C"][name]
        ratio = c / p if p else float("nan")
        rows.append({"quantity": name, "DEM-P": p, "DEM-C": c, "ratio": ratio})
    for name in sorted(set(res["DEM-P"]) | set(res["DEM-C"])):
        p = res["DEM-P"].get(name, float("nan"))
        c = res["DEM-C"].get(name, float("nan"))
        rows.append({"quantity": name, "DEM-P": p, "DEM-C": c, "ratio": c / p if p else float("nan")})
    for row in rows:
        print(f"{row['quantity']:28s} {row['DEM-P']:14.6g} {row['DEM-C']:14.6g} {row['ratio']:8.3f}")
    solver = runs["DEM-C"]["summary"].get("solver")
    if solver:
        print(
            f"\nDEM-C solver {solver['solver']}: mean {solver['mean_iterations']:.1f} iterations per step, "
            f"{solver['unconverged_steps']} of {solver['steps']} steps at the cap "
            f"({solver['max_iterations']}) without reaching {solver['tolerance']:g} m/s"
        )
    ok = True
    for label, r in runs.items():
        if r["exit_code"] != 0:
            ok = False
            print(f"{label} failed (exit {r['exit_code']}): {r['error']}")
        elif not r["summary"].get("completed", False):
            ok = False
            print(f"{label} stopped before its last stage ended (--steps)")
    (out / "compare.json").write_text(json.dumps({"rows": rows, "runs": runs}, indent=2) + "\n")
    print(f"\ntable: {out / 'compare.json'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
