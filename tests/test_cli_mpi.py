"""The pdem command under MPI: the progress line counts every rank's particles.

The count is a collective, so every rank joins it at the same steps; rank 0 decides when a line is
due and broadcasts the decision. Printed with a 10 ms interval here so that many lines are decided
during a short run: a protocol in which ranks disagreed would hang (the timeout catches it).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
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


def _index_ok(out: Path) -> list[float]:
    """The times of particles.xdmf, after checking that they are unique and in order and that every
    dataset it names (XDMF) and every piece the PVD's .pvtu files name exist."""
    import h5py

    root = ET.parse(out / "particles.xdmf").getroot()
    temporal = next(g for g in root.iter("Grid") if g.get("CollectionType") == "Temporal")
    times = []
    for grid in temporal.findall("Grid"):
        times.append(float(grid.find("Time").get("Value")))
        for item in grid.iter("DataItem"):
            if item.get("Format") == "HDF":
                name, path = item.text.strip().split(":")
                with h5py.File(out / name, "r") as fh:
                    assert path in fh, (name, path)
    assert times == sorted(times) and len(set(times)) == len(times), times
    pvd = [d for d in ET.parse(out / "particles.pvd").getroot().iter("DataSet")]
    assert [float(d.get("timestep")) for d in pvd] == times
    for d in pvd:
        for piece in ET.parse(out / d.get("file")).getroot().iter("Piece"):
            assert (out / "particles" / piece.get("Source")).exists()
    return times


@pytest.mark.integration
def test_per_rank_output_continued_on_another_rank_count(tmp_path):
    """2 ranks write per-rank HDF5 and VTK pieces and stop; 3 ranks resume into the same directory:
    one series (each time once, every referenced piece present), bitwise equal to a serial run."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    deck = tmp_path / "deck.toml"
    deck.write_text(TINY.replace("steps = 20\n", "steps = 40\n"))
    sets = ["--set", "output.parallel='per_rank'", "--set", "output.formats=['hdf5', 'vtk']"]
    sets += ["--set", "output.checkpoint_every_steps=10", "--set", "output.contacts=true"]

    def pdem(ranks, *args):
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, "-m", "pdem.cli", *map(str, args), "--quiet"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]

    pdem(1, deck, "--output", "full", *sets)
    pdem(2, deck, "--output", "run", "--steps", 30, *sets)
    pdem(3, "resume", "run/checkpoints/step_0000000020.h5")
    full, _ = read_checkpoint(tmp_path / "full" / "checkpoints" / "latest.h5")
    run, _ = read_checkpoint(tmp_path / "run" / "checkpoints" / "latest.h5")
    assert compare(full, run) is None
    assert _index_ok(tmp_path / "run") == _index_ok(tmp_path / "full")
    assert (tmp_path / "run" / "particles.r0002.h5").exists()  # the third rank's piece
    steps = sorted(int(c.name[5:15]) for c in (tmp_path / "run" / "checkpoints").glob("step_*.h5"))
    assert steps == [10, 20, 30, 40]
    # the contact network, gathered from 2 then 3 ranks, is the serial one line for line
    from test_contact_network import read_lines

    for out in ("full", "run"):
        times = [
            float(d.get("timestep"))
            for d in ET.parse(tmp_path / out / "contacts.pvd").getroot().iter("DataSet")
        ]
        assert times == _index_ok(tmp_path / "full")
    a = read_lines(tmp_path / "full" / "contacts" / "contacts_000004.vtu")
    b = read_lines(tmp_path / "run" / "contacts" / "contacts_000004.vtu")
    assert len(a[1]) > 0 and np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    for key in ("id_i", "id_j", "force", "normal_force", "overlap"):
        assert np.array_equal(a[2][key], b[2][key]), key


@pytest.mark.integration
def test_instability_reported_alike_on_1_and_2_ranks(tmp_path):
    """The deck runner defers each step's stability check to the next step's list test (one
    collective a step less) and checks first in whatever writes the state: a run that blows up fails
    on 1 and 2 ranks with the same error at the same step, and its series ends at the same row."""
    from test_cli import SMALL

    text = SMALL.replace("dt = 2e-6", "dt = 2e-5\nforce_dt = true\nstiffness_limit = 0").replace(
        "velocity = [0.0, 0.0, -0.2]", "velocity = [0.0, 0.0, -3.0]"
    ).replace("series_every_steps = 50", "series_every_steps = 1")
    deck = tmp_path / "deck.toml"
    deck.write_text(text)
    found = {}
    for ranks in (1, 2):
        out = tmp_path / f"out{ranks}"
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, "-m", "pdem.cli", str(deck), "--output", str(out),
               "--quiet"]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 3, proc.stderr[-3000:]
        assert "Traceback" not in proc.stderr
        msg = proc.stderr.split("the run became unstable at step ")[1]
        rows = (out / "series_drop.csv").read_text().splitlines()
        found[ranks] = (int(msg.split()[0]), int(rows[-1].split(",")[1]), len(rows))
    assert found[1] == found[2], found
    at, last, _ = found[1]
    assert at > 5 and last == at - 1  # a row at every step up to the failed one, which has none


@pytest.mark.integration
def test_series_identical_on_1_and_3_ranks(tmp_path):
    """Every measured column of a series, wall contact counts included (each rank counts its own:
    they are summed over ranks), is the same on 1 and 3 ranks; only the balancing columns differ."""
    from test_cli import SMALL

    deck = tmp_path / "deck.toml"
    # long enough for the grains to spread to the side walls on every rank
    text = SMALL.replace("steps = 300", "steps = 3000")
    deck.write_text(text.replace("series_every_steps = 50", "series_every_steps = 500"))
    series = {}
    for ranks in (1, 3):
        out = tmp_path / f"out{ranks}"
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, "-m", "pdem.cli", str(deck), "--output", str(out),
               "--quiet"]  # fmt: skip
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        lines = (out / "series_rest.csv").read_text().splitlines()
        header = lines[0].split(",")
        keep = [k for k, name in enumerate(header) if not name.startswith(("imbalance", "rebalances"))]
        series[ranks] = [[row.split(",")[k] for k in keep] for row in lines]
        contacts = [k for k, name in enumerate(header) if name.endswith("contacts")]
        assert contacts and any(float(lines[-1].split(",")[k]) > 0 for k in contacts)
    assert series[1] == series[3]
