"""The Hertz–Mindlin law's tangential options in a packing: the rescale options keep a fourth history
value per contact (the previous contact radius), which must travel with the contact through
migration, ghosts and checkpoints like the spring itself. A settling bed of frictional grains, run
with each rescaling option on 1 and 2 ranks and resumed from a mid-run checkpoint on 2 ranks, ends in
the same bits."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from decks import settling_bed

from pdem.io.checkpoint import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from determinism import compare  # noqa: E402

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")

DECK = settling_bed(
    0.012, 5000, "every_steps = 2500\ncheckpoint_every_steps = 2500", seed=5, friction=0.5
)


def _pdem(args: list[str], cwd: Path, ranks: int = 1) -> None:
    cmd = [sys.executable, "-m", "pdem", *args, "--quiet"]
    if ranks > 1:
        cmd = [MPIEXEC, "-n", str(ranks), *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-3000:]


@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
@pytest.mark.parametrize(
    "option", [pytest.param("mindlin_rescale", marks=pytest.mark.integration), "mindlin_rescale_force"]
)
def test_rescale_history_survives_ranks_and_resume(tmp_path, option):
    deck = tmp_path / "bed.toml"
    deck.write_text(DECK)
    opt = ["--set", f"contact.tangential={option}"]
    _pdem([str(deck), "--output", str(tmp_path / "one"), *opt], tmp_path)
    _pdem([str(deck), "--output", str(tmp_path / "two"), *opt], tmp_path, ranks=2)
    shutil.copytree(tmp_path / "one", tmp_path / "resumed")
    _pdem(["resume", str(tmp_path / "resumed" / "checkpoints" / "step_0000002500.h5")], tmp_path, ranks=2)
    ref, _ = read_checkpoint(tmp_path / "one" / "checkpoints" / "latest.h5")
    hist = [k for k in ref if "hist" in k and getattr(ref[k], "ndim", 0) == 2]
    assert any(ref[k].shape[1] == 4 and ref[k].shape[0] > 500 for k in hist), {k: ref[k].shape for k in hist}
    for other in ("two", "resumed"):
        state, _ = read_checkpoint(tmp_path / other / "checkpoints" / "latest.h5")
        assert compare(ref, state) is None, (other, compare(ref, state))
