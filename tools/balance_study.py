#!/usr/bin/env python
"""Dynamic load balancing, shown: the hopper on 2 ranks cut along z, with and without balancing.

    python tools/balance_study.py [--ranks 2] [--beads 2000] [--out docs/images/hopper_balance.png]

The grid is forced to (1, 1, ranks), cut along the vertical: the first cuts sit at quantiles of the
loose fill, and as the grains drain downward they pile onto the lowest rank unless the cut planes
move. Both runs give bitwise-identical grains (checked); the plot shows the work imbalance
(max/mean over ranks of the estimated force work) against time, and the wall time of each run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(ranks: int, beads: int, balance: bool, out: Path) -> dict:
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or "mpiexec"
    sets = [
        f"particles.0.n={beads}",
        f"particles.0.region.height={0.030 * beads / 4000:.6f}",
        f"run.decomposition=[1, 1, {ranks}]",
        "output.every_time=0.1",
        "output.series_every_steps=200",
        f"stages.discharge.end.above={1.0e-5 * beads:.6f}",  # about 95 % of the beads' mass
        f"run.balance_threshold={1.05 if balance else 1e9}",
    ]
    cmd = [
        mpiexec,
        "-n",
        str(ranks),
        sys.executable,
        "-m",
        "pdem.cli",
        str(ROOT / "inputs" / "hopper.toml"),
        "--output",
        str(out),
        "--quiet",
        "--overwrite",
    ]
    for s in sets:
        cmd += ["--set", s]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"run failed:\n{proc.stderr[-3000:]}")
    return json.loads((out / "summary.json").read_text())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ranks", type=int, default=2)
    ap.add_argument("--beads", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "hopper_balance.png")
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from pdem.io.checkpoint import read_checkpoint
    from pdem.io.series import read_series

    work = Path(tempfile.mkdtemp(prefix="pdem-balance-"))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    finals = {}
    for balance in (False, True):
        out = work / ("on" if balance else "off")
        summary = run(args.ranks, args.beads, balance, out)
        t, imb = [], []
        for stage in ("fill", "discharge"):
            s = read_series(out / f"series_{stage}.csv")
            t.append(s["time"])
            imb.append(s["imbalance_work"])
        t, imb = np.concatenate(t), np.concatenate(imb)
        label = (
            f"{'with' if balance else 'without'} balancing: wall time {summary['wall_time_s']:.0f} s, "
            f"mean imbalance {imb.mean():.2f}"
        )
        print(label)
        ax.plot(t, imb, label=label)
        finals[balance], _ = read_checkpoint(out / "checkpoints" / "latest.h5")
    same = all(
        np.array_equal(finals[True][k], finals[False][k]) for k in finals[True] if k.startswith("particles/")
    )
    print(f"grains bitwise identical with and without balancing: {same}")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("work imbalance (max / mean over ranks)")
    ax.set_title(f"Hopper, {args.beads} beads, {args.ranks} ranks cut along z")
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.legend()
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")
    shutil.rmtree(work, ignore_errors=True)
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
