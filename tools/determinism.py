#!/usr/bin/env python
"""Run one deck on several rank counts and compare the final states bit for bit.

    python tools/determinism.py DECK --ranks 1 2 3 4 --steps N [--set KEY=VALUE ...]

Each run is ``mpiexec -n K pdem DECK --steps N`` (ranks may be oversubscribed). A rank count may name
its grid of subdomains, ``4:2x2x1`` (``--set run.decomposition=[2, 2, 1]`` for that run only), to
exercise a split the default choice would not make. The final checkpoint
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


def parse_ranks(text: str) -> tuple[int, tuple[int, int, int] | None]:
    """``"4"`` → (4, None); ``"4:2x2x1"`` → (4, (2, 2, 1))."""
    head, _, dims = text.partition(":")
    try:
        ranks = int(head)
        grid = tuple(int(v) for v in dims.split("x")) if dims else None
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give a rank count, optionally with a grid: 4 or 4:2x2x1"
        ) from None
    if ranks < 1 or (grid is not None and (len(grid) != 3 or grid[0] * grid[1] * grid[2] != ranks)):
        raise argparse.ArgumentTypeError(f"{text!r}: the grid NXxNYxNZ must have as many subdomains as ranks")
    return ranks, grid


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
    ap.add_argument(
        "--ranks", type=parse_ranks, nargs="+", default=["1", "2", "3", "4"], metavar="K[:NXxNYxNZ]"
    )
    ap.add_argument("--steps", type=int, required=True)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs' output here")
    ap.add_argument("--timeout", type=float, default=1800.0)
    args = ap.parse_args(argv)
    from pdem.io.checkpoint import read_checkpoint

    base = args.keep or Path(tempfile.mkdtemp(prefix="pdem-determinism-"))
    results = {}
    runs = [parse_ranks(r) if isinstance(r, str) else r for r in args.ranks]
    labels = []
    for k, grid in runs:
        label = f"{k}" + (f" ({grid[0]}x{grid[1]}x{grid[2]})" if grid else "")
        sets = args.sets + ([f"run.decomposition=[{grid[0]}, {grid[1]}, {grid[2]}]"] if grid else [])
        tag = f"ranks{k}" + (f"_{grid[0]}x{grid[1]}x{grid[2]}" if grid else "")
        path = run(args.deck, k, args.steps, sets, base / tag, args.timeout)
        results[label], _ = read_checkpoint(path)
        labels.append(label)
        print(
            f"{label} rank(s): {len(results[label]['particles/id'])} particles "
            f"at step {int(results[label]['scalars/step'])}"
        )
    ref = labels[0]
    ok = True
    for k in labels[1:]:
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
