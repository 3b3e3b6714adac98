"""The servo plate holds its target stress, with both methods, from Python and from a deck."""

from __future__ import annotations

import json
import math
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


@pytest.mark.integration
@pytest.mark.parametrize("law, control, dt, settle, hold", [
    ("hertz_mindlin", "velocity", 1e-5, 0.2, 0.05),  # 0.15 of the Rayleigh time
    ("complementarity", "force", 2e-4, 0.1, 0.05),
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


def _run_deck(tmp_path, dt: float) -> dict:
    """The plate pressing 70 beads through the CLI at the step ``dt``: its summary."""
    deck = tmp_path / "press.toml"
    deck.write_text(textwrap.dedent(f"""
        [run]
        gravity = [0.0, 0.0, -9.81]
        dt = {dt}
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
    return json.loads((out / "summary.json").read_text())["results"]["lid"]


def test_plugin_is_registered():
    """Installed with pip, the plugin is found by its entry point (its deck runs in the tests
    below)."""
    assert "servo_plate" in available("boundaries")


@pytest.mark.integration
@pytest.mark.parametrize("capped", [True, False])
def test_deck_at_a_five_times_larger_step(tmp_path, monkeypatch, capped):
    """The plugin runs from a deck (through the CLI). dt = 1e-5 s, five times the step the deck
    was first written for: the plate's dashpots alone give a loop gain 2 gain C / A ≈ 1.9, its springs
    0.15 more, past the limit 2: without the gain cap the plate chatters (its velocity alternating
    every step) and held 500 Pa with a mean error of 75 %; with it, 0.5 % (measured)."""
    if not capped:
        monkeypatch.setattr("pdem.contact.stability.SERVO_LOOP_GAIN", math.inf)
    err = _run_deck(tmp_path, 1e-5)["mean_abs_error"]
    if capped:
        assert err < 0.02
    else:
        assert err > 0.5  # the defect the cap removes: this test's deck can fail


E, NU, RHO, R = 1e7, 0.3, 2500.0, 1e-3
AREA_1 = 1e-6  # the plate's nominal area over the one sphere [m²]
TARGET_1 = 1000.0  # Pa: 1 mN on the sphere


def _plate_on_a_sphere(restitution: float, gain: float, steps: int, dt: float = 1e-5):
    """One sphere on a floor (no gravity) under a plate 1 µm above it, servoed to 1 mN with a given
    gain (at max_speed 0.01 m/s it touches after 10 steps). Returns the plate, the stress and the
    loop gain of every step."""
    sim = pdem.Simulation(law="hertz_mindlin")
    sim.add_material("glass", density=RHO, youngs_modulus=E, poisson_ratio=NU, restitution=restitution,
                     friction=0.0)  # fmt: skip
    sim.add_particles([[0, 0, R]], [R])
    sim.add_wall(shapes.Plane((0, 0, 0), (0, 0, 1)))
    plate = ServoPlate("lid", ServoPlateParams(
        type="servo_plate", material="glass", point=(0, 0, 2 * R + 1e-6), normal=(0, 0, -1), area=AREA_1,
        target_stress=TARGET_1, max_speed=0.01, gain=gain))  # fmt: skip
    sim.add_boundary(plate)
    sim.dt = dt
    rows = []
    sim.run(steps=steps, callback=lambda s: rows.append((plate.stress(), plate.loop_gain)))
    stress, loop = np.array(rows).T
    return plate, stress, loop


def _hertz(force: float, restitution: float) -> tuple[float, float]:
    """(S_n, c_n) of the sphere–plate contact carrying ``force``, in closed form."""
    e_star = E / (2 * (1 - NU * NU))
    delta = (3 * force / (4 * e_star * math.sqrt(R))) ** (2 / 3)
    s_n = 2 * e_star * math.sqrt(R * delta)
    le = math.log(restitution)
    beta = le / math.sqrt(le * le + math.pi * math.pi)
    m = RHO * 4 / 3 * math.pi * R**3
    return s_n, -2 * math.sqrt(5 / 6) * beta * math.sqrt(s_n * m)


@pytest.mark.parametrize("capped", [True, False])
def test_loop_gain_of_an_elastic_sphere_is_gain_k_dt_over_a(monkeypatch, capped):
    """Elastic contacts (e = 1: no dashpots): the controller's loop gain is gain K dt / A with K the
    Hertz stiffness S_n = 2 E* sqrt(R δ) of the contact under the plate's load; at gain = 7e-4 m/(s
    Pa) it is 4, unstable: uncapped the load chatters at the max_speed limit (±5 % here), capped
    it settles on the target."""
    if not capped:
        monkeypatch.setattr("pdem.contact.stability.SERVO_LOOP_GAIN", math.inf)
    dt, gain = 1e-5, 7e-4
    plate, stress, loop = _plate_on_a_sphere(1.0, gain, 3000, dt)
    assert loop[0] == 0.0
    k, _ = _hertz(stress[-2] * AREA_1, 1.0)  # a step's loop gain is read from the last step's contacts
    assert loop[-1] == pytest.approx(gain * k * dt / AREA_1, rel=1e-6)
    assert loop[-1] > 3.5
    tail = np.abs(stress[-200:] / TARGET_1 - 1)
    if capped:
        assert plate.gain_used == pytest.approx(AREA_1 / (k * dt), rel=1e-6)  # g = 1
        assert tail.max() < 1e-4
    else:
        assert plate.gain_used == gain
        assert tail.max() > 0.03


@pytest.mark.parametrize("capped", [True, False])
def test_damped_sphere_is_pressed_without_overshoot(monkeypatch, capped):
    """e = 0.5: the contact's dashpot c_n = −2 sqrt(5/6) β sqrt(S_n m) dominates the loop gain
    gain (K dt + 2 C) / A (≈ 46 here, closed form). Capped to 1, the load rises to the target
    (measured: never falling back by more than 0.08 % in a step, overshooting by 0.004 %) and stays
    there; uncapped it swings ±30 % every step."""
    if not capped:
        monkeypatch.setattr("pdem.contact.stability.SERVO_LOOP_GAIN", math.inf)
    dt, gain = 1e-5, 7e-4
    plate, stress, loop = _plate_on_a_sphere(0.5, gain, 1500, dt)
    touch = int(np.flatnonzero(stress > 0)[0])
    if capped:
        k, c = _hertz(stress[-2] * AREA_1, 0.5)
        assert loop[-1] == pytest.approx(gain * (k * dt + 2 * c) / AREA_1, rel=1e-6)
        s = stress[touch:] / TARGET_1
        assert np.all(np.diff(s) > -2e-3)  # monotone, up to the sphere's own rebound ...
        assert s.max() < 1 + 1e-4  # ... and no overshoot worth the name
        assert abs(s[-1] - 1) < 1e-6
    else:
        tail = stress[-200:] / TARGET_1 - 1
        assert tail.max() > 0.2 and tail.min() < -0.2
