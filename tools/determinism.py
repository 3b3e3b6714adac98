#!/usr/bin/env python
"""Run one deck on several rank counts and compare the final states bit for bit.

    python tools/determinism.py DECK --ranks 1 2 3 4 --steps N [--set KEY=VALUE ...]

Each run is ``mpiexec -n K pdem DECK --steps N`` (ranks may be oversubscribed); the final checkpoint
of every run (particles ordered by id, contact history keyed by id pairs, wall histories) is compared
with the first run's. Exit code 0 only if every field of every particle is bitwise identical;
otherwise the first differing particle id and field are named (exit 1). Exit 2 if a run fails.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def run(deck: Path, ranks: int, steps: int, sets: list[str], out: Path, timeout: float) -> Path:
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    if mpiexec is None:
        raise SystemExit("mpiexec not found (pip install mpich)")
    cmd = [
        mpiexec,
        "-n",
        str(ranks),
        sys.executable,
        "-m",
        "pdem.cli",
        str(deck),
        "--steps",
        str(steps),
        "--output",
        str(out),
        "--quiet",
        "--overwrite",
    ]
    for s in sets:
        cmd += ["--set", s]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        print(
            f"run on {ranks} rank(s) failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}", file=sys.stderr
        )
        raise SystemExit(2)
    return out / "checkpoints" / "latest.h5"


def compare(ref: dict, other: dict) -> str | None:
    """None if identical, else a description of the first difference."""
    ids = ref["particles/id"]
    if not np.array_equal(ids, other.get("particles/id")):
        return f"different particle sets: {len(ids)} vs {len(other.get('particles/id', []))} particles"
    for key in sorted(ref):
        a, b = ref[key], other.get(key)
        if b is None or a.shape != b.shape:
            return f"field {key}: shape {a.shape} vs {None if b is None else b.shape}"
        if not np.array_equal(a, b):
            if key.startswith("particles/") or (key.startswith("walls/") and key.endswith("/hist")):
                rows = np.flatnonzero(np.any((a != b).reshape(a.shape[0], -1), axis=1))
                i = rows[0]
                return (
                    f"particle id {ids[i]}, field {key}: {a[i]!r} vs {b[i]!r} ({len(rows)} particles differ)"
                )
            return f"field {key} differs"
    return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("deck", type=Path)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 3, 4])
    ap.add_argument("--steps", type=int, required=True)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs' output here")
    ap.add_argument("--timeout", type=float, default=1800.0)
    args = ap.parse_args(argv)
    from pdem.io.checkpoint import read_checkpoint

    base = args.keep or Path(tempfile.mkdtemp(prefix="pdem-determinism-"))
    results = {}
    for k in args.ranks:
        path = run(args.deck, k, args.steps, args.sets, base / f"ranks{k}", args.timeout)
        results[k], _ = read_checkpoint(path)
        print(
            f"{k} rank(s): {len(results[k]['particles/id'])} particles "
            f"at step {int(results[k]['scalars/step'])}"
        )
    ref = args.ranks[0]
    ok = True
    for k in args.ranks[1:]:
        diff = compare(results[ref], results[k])
        if diff is None:
            print(f"{ref} vs {k} ranks: bitwise identical")
        else:
            ok = False
            print(f"{ref} vs {k} ranks: DIFFERENT: {diff}")
    if args.keep is None:
        shutil.rmtree(base, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
