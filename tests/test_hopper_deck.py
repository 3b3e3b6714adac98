"""inputs/hopper.toml, shortened with --set, runs through the pdem command: the fill settles, the plug
opens, grains leave through the orifice, the flow rate is reported, and (where ParaView's pvpython
exists) ParaView opens the snapshot series. The full deck is the README's main job; its figures are
in the closing notes, not asserted here."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import textwrap
from pathlib import Path

import pytest

from pdem.cli import main
from pdem.io.series import read_series

DECK = Path(__file__).resolve().parents[1] / "inputs" / "hopper.toml"

# 600 beads, the fill ends on time rather than kinetic energy, a short discharge
SHORT = [
    "particles.0.n=600",
    "particles.0.region.height=0.012",
    "stages.fill.end.time=0.12",
    "stages.fill.end.kinetic_energy_below=1e-12",
    "stages.discharge.end.time=0.25",
    "output.every_time=0.05",
]


@pytest.fixture(scope="module")
def hopper_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("hopper") / "out"
    args = [str(DECK), "--output", str(out), "--quiet"]
    for s in SHORT:
        args += ["--set", s]
    assert main(args) == 0
    return out


def test_hopper_discharges(hopper_run):
    fill = read_series(hopper_run / "series_fill.csv")
    dis = read_series(hopper_run / "series_discharge.csv")
    # nothing leaves while the plug is in
    assert fill["hopper.discharged_mass"].max() == 0.0
    # grains leave once it opens, and the discharged mass never decreases
    assert dis["hopper.discharged_mass"][-1] > 0.0
    assert (dis["hopper.discharged_mass"][1:] >= dis["hopper.discharged_mass"][:-1]).all()
    # bookkeeping: removed by the sink = 600 − particles left; discharged = removed + those still falling
    removed = 600 - dis["particles"][-1]
    falling = dis["hopper.discharged_count"][-1] - removed
    assert removed > 0 and 0 <= falling <= dis["particles"][-1]
    m_bead = 2500.0 * 4.0 / 3.0 * 3.141592653589793 * (0.9e-3) ** 3  # lightest bead
    assert dis["hopper.discharged_mass"][-1] >= dis["hopper.discharged_count"][-1] * m_bead
    summary = json.loads((hopper_run / "summary.json").read_text())
    assert summary["results"]["hopper"]["discharged_mass"] == dis["hopper.discharged_mass"][-1]
    assert summary["completed"]


_PV = textwrap.dedent(
    """
    import json, sys
    from paraview import simple as pv
    r = pv.XDMFReader(FileNames=[sys.argv[1] + "/particles.xdmf"])
    w = pv.XDMFReader(FileNames=[sys.argv[1] + "/walls.xdmf"])
    times = [float(t) for t in r.TimestepValues]
    counts = []
    for t in times:
        r.UpdatePipeline(t)
        counts.append(r.GetDataInformation().GetNumberOfPoints())
    w.UpdatePipeline(times[-1])
    print("RESULT " + json.dumps({"times": times, "points": counts,
                                  "wall_cells": w.GetDataInformation().GetNumberOfCells()}))
    """
)


@pytest.mark.skipif(
    shutil.which("pvpython") is None,
    reason="pvpython (ParaView) not installed; Debian: apt-get install paraview python3-paraview",
)
def test_paraview_opens_hopper_output(hopper_run, tmp_path):
    script = tmp_path / "probe.py"
    script.write_text(_PV)
    proc = subprocess.run(
        ["pvpython", "--force-offscreen-rendering", str(script), str(hopper_run)],
        capture_output=True,
        text=True,
        timeout=180,
        env={**os.environ, "PYTHONPATH": ""},
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, proc.stderr
    res = json.loads(lines[-1][len("RESULT ") :])
    assert len(res["times"]) >= 5
    assert res["points"][0] == 600 and res["points"][-1] < 600  # grains left through the orifice
    assert res["wall_cells"] > 100


def test_snapshot_contact_counts_match_brute_force(hopper_run):
    """The 'contacts' field of the snapshot at the end of the fill (a settled pile in the closed
    hopper) equals a brute-force count of overlapping pairs."""
    import h5py
    import numpy as np

    with h5py.File(hopper_run / "particles.h5", "r") as fh:
        frames = [fh["frames"][k] for k in sorted(fh["frames"])]
        fill = [f for f in frames if f.attrs["stage"] == "fill"][-1]
        x, r, counts = fill["x"][()], fill["r"][()], fill["contacts"][()]
    d = np.linalg.norm(x[:, None, :] - x[None, :, :], axis=2)
    touching = (d < r[:, None] + r[None, :]) & ~np.eye(len(r), dtype=bool)
    assert touching.sum() > 1000  # a settled pile: ~4 contacts per bead
    assert np.array_equal(counts, touching.sum(axis=1))
