"""tools/scaling.py: the measurement runs on 1 and 2 ranks, counts every rank's work and traffic, and
the model reproduces the counts of a uniform scene (a small periodic fcc box)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
pytestmark = pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")


def test_the_scaling_tool_measures_and_models_1_and_2_ranks(tmp_path):
    tool = ROOT / "tools" / "scaling.py"
    cmd = [sys.executable, str(tool), "measure", "--scene", "periodic", "--n", "2000", "--ranks", "1", "2",
           "--steps", "30", "--warmup", "5", "--out", str(tmp_path)]  # fmt: skip
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "bitwise identical on every rank count: True" in proc.stdout
    data = json.loads((tmp_path / "measure_periodic_dem-p.json").read_text())
    two = next(r for r in data["runs"] if r["ranks"][0]["ranks"] == 2)["ranks"]
    assert sum(r["owned"] for r in two) == data["runs"][0]["ranks"][0]["owned"] == 2048
    for r in two:  # each rank forwards its ghosts to its neighbour every step, and reduces once a step
        assert r["calls"]["Isend"] >= 30 and r["bytes"]["Isend"] >= 72 * 30
        assert r["calls"]["Allreduce"] >= 30 and r["ghosts"] > 0 and r["pairs_with_ghost"] > 0
    proc = subprocess.run([sys.executable, str(tool), "model", str(tmp_path / "measure_periodic_dem-p.json")],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "strong scaling, 1e+08 grains" in proc.stdout and "weak scaling" in proc.stdout
    row = next(line for line in proc.stdout.splitlines() if line.strip().startswith("2 ["))
    owned = float(row.split("]")[1].split()[0].split(";")[0])
    assert abs(owned - 1.0) < 1e-9  # model / measured owned grains
