"""Resume from any checkpoint of the hopper, through the real CLI.

A shortened hopper (300 beads, 0.03 s of fill, discharge until 0.3 g has left: ~6,600 steps, ~2 s) is
run once without interruption. Then the same run is interrupted in every way a user meets and
resumed with ``pdem resume`` into its own output directory:

* before the plug opens (``--steps`` in the fill), and after it (``--steps`` mid-discharge, grains
  below the removed plug);
* after a ``kill -9`` mid-discharge (a subprocess, periodic checkpoints);
* after the discharge's ``max_time`` error, raising the cap with ``--set``;
* from a completed run's ``latest.h5`` (nothing left to run; or with a third stage added).

Each final checkpoint must be bitwise equal to the uninterrupted run's (tools/determinism.py's
``compare``), and the output directory must hold one time series: ``particles.xdmf`` lists every
time once, in order (the uninterrupted run's times, plus the step where the run was stopped), the
series CSVs hold the uninterrupted run's rows, and no checkpoint after the resumed one survives.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import numpy as np
import pytest
from decks import SHORT_HOPPER_SETS

from pdem.cli import main
from pdem.io.checkpoint import read_checkpoint
from pdem.io.series import read_series

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from determinism import compare  # noqa: E402

HOPPER = ROOT / "inputs" / "hopper.toml"
# tests/test_mpi.py's short hopper, ending when 0.3 g has been discharged (~6,600 steps), with
# snapshots every 0.02 s and a checkpoint every 1,000 steps
SETS = list(SHORT_HOPPER_SETS)
FILL_STEPS = 1924  # the fill ends at t = 0.03 s
SET_ARGS = [a for s in SETS for a in ("--set", s)]


def final_state(out: Path) -> dict:
    state, _ = read_checkpoint(out / "checkpoints" / "latest.h5")
    return state


def xdmf_times(path: Path) -> list[tuple[float, int]]:
    """(time, step) of every frame of a particles.xdmf, in file order."""
    root = ET.parse(path).getroot()
    temporal = next(g for g in root.iter("Grid") if g.get("CollectionType") == "Temporal")
    out = []
    for grid in temporal.findall("Grid"):
        t = float(grid.find("Time").get("Value"))
        step = int(next(i.get("Value") for i in grid.findall("Information") if i.get("Name") == "step"))
        out.append((t, step))
    return out


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> Path:
    """The uninterrupted run."""
    out = tmp_path_factory.mktemp("resume") / "full"
    assert main([str(HOPPER), *SET_ARGS, "--output", str(out), "--quiet"]) == 0
    return out


def assert_one_series(out: Path, full: Path, resumed_from: int, stops: tuple[int, ...] = ()) -> None:
    """``out`` holds the uninterrupted run's output as one time series, plus frames where the run
    was stopped (``stops``), and its last run was the resume from step ``resumed_from`` (written
    there, not to a directory beside it)."""
    assert json.loads((out / "summary.json").read_text()).get("resumed_from_step") == resumed_from
    assert not list(out.parent.glob(f"{out.name}-resumed*"))
    frames = xdmf_times(out / "particles.xdmf")
    times = [t for t, _ in frames]
    assert times == sorted(times) and len(set(times)) == len(times), frames  # each time once, in order
    reference = xdmf_times(full / "particles.xdmf")
    assert [f for f in frames if f[1] not in stops] == [f for f in reference if f[1] not in stops]
    walls = [float(g.get("Value")) for g in ET.parse(out / "walls.xdmf").getroot().iter("Time")]
    assert walls == sorted(walls) and len(set(walls)) == len(walls)
    with h5py.File(out / "walls.h5", "r") as a, h5py.File(full / "walls.h5", "r") as b:
        last_a, last_b = sorted(a["frames"])[-1], sorted(b["frames"])[-1]
        for wall in b["frames"][last_b]:  # walls drawn alike (the scene box is kept in checkpoints)
            pa, pb = a["frames"][last_a][wall]["points"][()], b["frames"][last_b][wall]["points"][()]
            assert np.array_equal(pa, pb), wall
    for stage in ("fill", "discharge"):
        a, b = read_series(out / f"series_{stage}.csv"), read_series(full / f"series_{stage}.csv")
        keep = ~np.isin(a["step"], stops) | np.isin(a["step"], b["step"])
        for key in b:
            assert np.array_equal(a[key][keep], b[key], equal_nan=True), (stage, key)
    steps = sorted(int(p.name[5:15]) for p in (out / "checkpoints").glob("step_*.h5"))
    assert steps[-1] == int(final_state(full)["scalars/step"])
    assert not list(out.rglob("*.tmp"))
    assert {p.name for p in out.rglob(".*")} <= {".pdem-output.json", ".pdem-lock"}  # marker and lock
    summary = json.loads((out / "summary.json").read_text())
    reference = json.loads((full / "summary.json").read_text())
    assert summary["results"] == reference["results"]  # the flow rate from the whole series


@pytest.mark.parametrize(
    "stop",
    [
        pytest.param(1000, id="fill-before-plug-opens"),
        pytest.param(FILL_STEPS, id="at-the-stage-boundary"),
        pytest.param(6524, id="discharge-grains-below-the-plug"),
    ],
)
def test_resume_after_steps_appends_to_one_series(tmp_path, full, run_pdem, stop):
    out = tmp_path / "run"
    assert run_pdem([HOPPER, *SET_ARGS, "--output", out, "--quiet", "--steps", stop])[0] == 0
    state = final_state(out)
    assert int(state["scalars/step"]) == stop
    if stop > FILL_STEPS:  # the plug is open and grains are where it was
        x = state["particles/x"]
        assert np.any(x[:, 2] < 0.0), "no grain below the orifice plane yet"
    code = run_pdem(["resume", out / "checkpoints" / "latest.h5", "--quiet"])[0]
    assert code == 0
    assert compare(final_state(full), final_state(out)) is None
    assert_one_series(out, full, stop, stops=(stop,))


def test_resume_from_an_earlier_checkpoint_drops_the_later_output(tmp_path, full, run_pdem):
    """Resuming a finished run from its step-3000 checkpoint replaces what came after it."""
    out = tmp_path / "run"
    shutil.copytree(full, out, symlinks=True)
    code = run_pdem(["resume", out / "checkpoints" / "step_0000003000.h5", "--quiet"])[0]
    assert code == 0
    assert compare(final_state(full), final_state(out)) is None
    assert_one_series(out, full, 3000)


def test_resume_after_kill_9(tmp_path, full, run_pdem):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "pdem.cli", str(HOPPER), *SET_ARGS, "--output", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not (out / "checkpoints" / "step_0000005000.h5").exists():  # mid-discharge
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read().decode()
            time.sleep(0.01)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    # latest.h5 names the newest complete checkpoint: step_0000005000.h5, or the one before it when
    # the kill came between writing that file and pointing latest.h5 at it
    latest = out / "checkpoints" / "latest.h5"
    resumed = int(read_checkpoint(latest)[0]["scalars/step"])
    steps = sorted(int(p.name[5:15]) for p in (out / "checkpoints").glob("step_*.h5"))
    assert resumed in steps[-2:] and FILL_STEPS < resumed < int(final_state(full)["scalars/step"])
    code = run_pdem(["resume", latest, "--quiet"])[0]
    assert code == 0
    assert compare(final_state(full), final_state(out)) is None
    assert_one_series(out, full, resumed)


def test_resume_after_max_time_with_a_larger_cap(tmp_path, full, run_pdem):
    out = tmp_path / "run"
    code, _, err = run_pdem(
        [HOPPER, *SET_ARGS, "--set", "stages.discharge.end.max_time=0.05", "--output", out, "--quiet"]
    )
    assert code == 3, err
    latest = out / "checkpoints" / "latest.h5"
    command = f"pdem resume {latest} --set stages.discharge.end.max_time=0.1"
    assert command in err and "hopper.discharged_mass > 0.0003 (now " in err, err
    stopped = int(read_checkpoint(latest)[0]["scalars/step"])
    # the message's own command, run as it is printed
    code, _, err = run_pdem([*command.split()[1:], "--quiet"])
    assert code == 0, err
    assert compare(final_state(full), final_state(out)) is None
    assert_one_series(out, full, stopped, stops=(stopped,))


def test_resume_a_completed_run(tmp_path, full, run_pdem):
    out = tmp_path / "run"
    shutil.copytree(full, out, symlinks=True)
    code, stdout, err = run_pdem(["resume", out / "checkpoints" / "latest.h5", "--quiet"])
    assert code == 0, err
    assert "nothing left to run" in stdout
    assert compare(final_state(full), final_state(out)) is None
    assert_one_series(out, full, int(final_state(full)["scalars/step"]))


def test_third_stage_with_its_own_dt_runs_and_extends_a_completed_run(tmp_path, full, run_pdem):
    """A third stage that sets dt = 1e-5 re-prepares the simulation after the plug was removed (it
    used to fail on the switched-off plug); the same stage added on resume gives the same result."""
    third = ["--set", "stages.2.name=rest", "--set", "stages.2.dt=1e-5", "--set", "stages.2.end.steps=300"]
    code, _, err = run_pdem([HOPPER, *SET_ARGS, *third, "--output", tmp_path / "three", "--quiet"])
    assert code == 0, err
    out = tmp_path / "extended"
    shutil.copytree(full, out, symlinks=True)
    code, _, err = run_pdem(["resume", out / "checkpoints" / "latest.h5", *third, "--quiet"])
    assert code == 0, err
    a, b = final_state(tmp_path / "three"), final_state(out)
    assert float(a["scalars/dt"]) == 1e-5
    assert compare(a, b) is None
    assert (out / "series_rest.csv").exists()
    assert 'name = "rest"' in (out / "deck.resolved.toml").read_text()
    assert list(out.glob("deck.resolved.until-step-*.toml"))  # the previous deck is kept
