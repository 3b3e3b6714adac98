"""The pdem command under MPI (issue 9, item 7): the progress line counts every rank's particles.

The count is a collective, so every rank joins it at the same steps; rank 0 decides when a line is
due and broadcasts the decision. Printed with a 10 ms interval here so that many lines are decided
during a short run: a protocol in which ranks disagreed would hang (the timeout catches it).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from test_cli_hostile import TINY

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
pytestmark = pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")

_OFTEN = textwrap.dedent(
    """
    import sys
    import pdem.runner as runner
    from pdem.cli import main

    original = runner._Progress.update

    def often(self, *args, **kwargs):
        self.every = 0.01
        return original(self, *args, **kwargs)

    runner._Progress.update = often
    sys.exit(main(sys.argv[1:]))
    """
)


def test_progress_counts_every_rank(tmp_path):
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY.replace("steps = 20\n", "steps = 400\n"))
    script = tmp_path / "often.py"
    script.write_text(_OFTEN)
    cmd = [MPIEXEC, "-n", "2", sys.executable, str(script), str(deck), "--output", str(tmp_path / "out")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("[drop]")]
    assert len(lines) >= 3, proc.stderr
    assert all(", 64 particles," in ln for ln in lines), lines  # not rank 0's 32
    assert "on rank 0" not in proc.stderr
