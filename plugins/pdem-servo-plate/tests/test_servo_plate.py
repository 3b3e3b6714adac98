"""The servo plate holds its target stress, with both methods, from Python and from a deck."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pdem
import pytest
from pdem.api import shapes
from pdem.cli import main
from pdem.plugins import available
from pdem.sources import BoxRegion, Single, random_fill

from pdem_servo_plate import ServoPlate, ServoPlateParams

L = 0.01  # box side [m]
AREA = L * L
TARGET = 500.0  # Pa: 0.05 N on the plate, ~10 times the grains' weight


def _box_with_plate(law: str, control: str = "velocity"):
    sim = pdem.Simulation(law=law)
    sim.add_material("glass", density=2500, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.3)
    x, r = random_fill(BoxRegion((0.0, 0.0, 0.0), (L, L, 0.012)), Single(0.8e-3), n=70, seed=3)
    sim.add_particles(x, r)
    for plane in shapes.box_planes((0, 0, 0), (L, L, 0.05))[:5]:  # open top
        sim.add_wall(plane)
    sim.gravity = (0, 0, -9.81)
    plate = ServoPlate("lid", ServoPlateParams(type="servo_plate", material="glass", point=(0, 0, 0.0125),
                                               normal=(0, 0, -1), area=AREA, target_stress=TARGET,
                                               max_speed=0.1, control=control))
    sim.add_boundary(plate)
    return sim, plate


@pytest.mark.parametrize("law, control, dt, settle, hold", [
    ("hertz_mindlin", "velocity", 2e-6, 0.2, 0.05),
    ("complementarity", "force", 2e-4, 0.25, 0.1),
])  # fmt: skip
def test_plate_holds_target_stress(law, control, dt, settle, hold):
    sim, plate = _box_with_plate(law, control)
    if law == "complementarity":
        sim.set_law("complementarity", solver="apgd")
    sim.dt = dt
    sim.run(until=settle)
    stresses = []
    sim.run(until=settle + hold, callback=lambda s: stresses.append(plate.stress()))
    s = np.array(stresses)
    assert abs(s.mean() / TARGET - 1) < 0.02
    # rigid grains: the load jitters at the solver's residual (APGD, tolerance 1e-5 m/s). Measured
    # 95th percentiles: 3.8 % with the relaxed cone, 10.1 % with the Coulomb (corrected) cone, the
    # default since the lift-off fix, whose fixed point APGD converges less well (16.5 % at 500
    # iterations: more iterations do not help; docs/dem_c.md)
    assert np.percentile(np.abs(s / TARGET - 1), 95) < (0.05 if law == "hertz_mindlin" else 0.15)
    assert plate.plate.offset[2] < -1e-4  # it moved down onto the grains


def test_plugin_is_registered_and_runs_from_a_deck(tmp_path):
    assert "servo_plate" in available("boundaries")
    deck = tmp_path / "press.toml"
    deck.write_text(textwrap.dedent(f"""
        [run]
        gravity = [0.0, 0.0, -9.81]
        dt = 2e-6
        [materials.glass]
        density = 2500.0
        youngs_modulus = 1.0e7
        poisson_ratio = 0.3
        restitution = 0.3
        friction = 0.3
        [[particles]]
        source = "random_fill"
        material = "glass"
        region = {{ type = "box", lo = [0.0, 0.0, 0.0], hi = [{L}, {L}, 0.012] }}
        sizes = {{ type = "single", radius = 0.8e-3 }}
        n = 70
        [boundaries.box]
        type = "box"
        material = "glass"
        lo = [0.0, 0.0, 0.0]
        hi = [{L}, {L}, 0.05]
        open_faces = ["zhi"]
        [boundaries.lid]
        type = "servo_plate"
        material = "glass"
        point = [0.0, 0.0, 0.0125]
        normal = [0.0, 0.0, -1.0]
        area = {AREA}
        target_stress = {TARGET}
        max_speed = 0.1
        [[stages]]
        name = "press"
        [stages.end]
        time = 0.25
        [output]
        directory = "out"
        formats = ["hdf5"]
        series_every_steps = 250
    """))
    out = tmp_path / "out"
    assert main([str(deck), "--output", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())["results"]["lid"]
    assert summary["mean_abs_error"] < 0.02
