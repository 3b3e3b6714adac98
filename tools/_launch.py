"""Shared by the study scripts in tools/: the command line of one pdem run (serial or under the
venv's mpiexec). To be replaced by the ``pdem study`` API (issue 13)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path


def command(deck: Path, out: Path, sets: list[str], ranks: int) -> list[str]:
    """``python -m pdem DECK --output OUT --overwrite --quiet --set …``, under ``mpiexec -n RANKS``
    when ranks > 1 (the mpiexec next to the interpreter first: the ``mpich`` wheel's)."""
    pdem = [sys.executable, "-m", "pdem"]
    if ranks > 1:
        mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
        if mpiexec is None:
            raise SystemExit("--ranks > 1 needs mpiexec (pip install mpich)")
        pdem = [mpiexec, "-n", str(ranks), *pdem]
    cmd = [*pdem, str(deck), "--output", str(out), "--overwrite", "--quiet"]
    for s in sets:
        cmd += ["--set", s]
    return cmd


def run_once(cmd: list[str], run_dir: Path, tag: str) -> int:
    """Run ``cmd`` unless ``run_dir`` holds a finished run (its summary.json): resumable studies.
    Progress and wall time on stderr; returns the exit code (0 for a run kept from before)."""
    if (run_dir / "summary.json").is_file():
        print(f"{tag} {run_dir}: done before, kept", file=sys.stderr)
        return 0
    print(f"{tag} {' '.join(cmd)}", file=sys.stderr)
    t0 = time.perf_counter()
    code = subprocess.call(cmd)
    if code != 0:
        print(f"{tag} {run_dir} failed (exit {code})", file=sys.stderr)
    else:
        print(f"{tag} {run_dir}: {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return code
