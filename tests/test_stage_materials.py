"""Contact properties that change between stages (``[stages.materials.NAME]``,
``Simulation.set_material``) and the pluviation's own friction (``[[particles]] friction``): how a
dense and a loose sample are made from the same grains.

Reference: a sphere sliding on a floor under gravity decelerates at μ g while it slides (closed
form); frictionless, it keeps its speed. A stage's values hold for that stage only, also after a
resume inside it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pdem import Simulation
from pdem.cli import main
from pdem.errors import InputError
from pdem.geometry.shapes import Plane
from pdem.io.checkpoint import read_checkpoint

R, V0, MU, G = 0.005, 1.0, 0.5, 9.81

DECK = f"""
[run]
seed = 1
gravity = [0.0, 0.0, -{G}]
dt = 2.0e-5
[materials.bead]
density = 2500.0
youngs_modulus = 1.0e7
poisson_ratio = 0.3
restitution = 0.5
friction = {MU}
[[particles]]
source = "lattice"
lattice = "hex2d"
material = "bead"
radius = {R}
n_cols = 1
n_rows = 1
origin = [0.0, 0.0, {R}]
velocity = [{V0}, 0.0, 0.0]
[boundaries.floor]
type = "plane"
material = "bead"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
[[stages]]
name = "glide"
[stages.materials.bead]
friction = 0.0
[stages.end]
time = 0.02
[[stages]]
name = "slide"
[stages.end]
time = 0.02
[output]
formats = []
series_every_steps = 100
checkpoint_every_steps = 500
"""


def _run(tmp_path: Path, *extra: str) -> int:
    deck = tmp_path / "slide.toml"
    deck.write_text(DECK)
    return main([str(deck), "--output", str(tmp_path / "out"), "--quiet", *extra])


def _velocity(out: Path, name: str = "latest.h5") -> np.ndarray:
    state, _ = read_checkpoint(out / "checkpoints" / name)
    return np.asarray(state["particles/v"])[0]


def test_friction_holds_for_its_stage_only(tmp_path):
    assert _run(tmp_path) == 0
    out = tmp_path / "out"
    glide = _velocity(out, "step_0000001000.h5")  # the end of the glide (0.02 s at 2e-5 s)
    v = _velocity(out)
    # the 'slide' stage uses [materials]: sliding friction μ g for 0.02 s (it rolls only after
    # 2 v0 / (7 μ g) = 0.058 s)
    expected = V0 - MU * G * 0.02
    assert v[0] == pytest.approx(expected, rel=2e-3)
    assert glide[0] == pytest.approx(V0, rel=1e-9)  # frictionless glide: the speed is kept


def test_a_resume_inside_the_stage_keeps_its_values(tmp_path):
    # stop in the frictionless stage, resume: the glide must still be frictionless
    assert _run(tmp_path, "--steps", "600") == 0
    out = tmp_path / "out"
    assert main(["resume", str(out / "checkpoints" / "latest.h5"), "--quiet"]) == 0
    v_resumed = _velocity(out)
    ref = tmp_path / "ref"
    ref.mkdir()
    assert _run(ref) == 0
    assert np.array_equal(v_resumed, _velocity(ref / "out"))


def test_set_material_from_python():
    sim = Simulation()
    sim.dt, sim.gravity = 2e-5, (0.0, 0.0, -G)
    sim.add_material("bead", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, friction=MU)
    sim.add_particles([[0.0, 0.0, R]], [R], velocities=[[V0, 0.0, 0.0]])
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    assert sim.set_material("bead", friction=0.0) is True
    assert sim.set_material("bead", friction=0.0) is False  # no change
    sim.run(steps=1000)
    assert sim.get_particles()["v"][0, 0] == pytest.approx(V0, rel=1e-9)
    sim.set_material("bead", friction=MU)
    sim.run(steps=1000)
    assert sim.get_particles()["v"][0, 0] == pytest.approx(V0 - MU * G * 0.02, rel=2e-3)
    with pytest.raises(InputError, match="youngs_modulus"):
        sim.set_material("bead", youngs_modulus=1e8)
    with pytest.raises(InputError, match="unknown material"):
        sim.set_material("steel", friction=0.1)
    with pytest.raises(InputError, match="friction"):
        sim.set_material("bead", friction=-1.0)


def test_deck_rejects_an_unknown_stage_material(tmp_path, capsys):
    deck = tmp_path / "bad.toml"
    deck.write_text(DECK.replace("[stages.materials.bead]", "[stages.materials.glass]"))
    assert main(["check", str(deck), "--deck-only"]) == 2
    err = capsys.readouterr().err
    assert "stages.0.materials.glass" in err and "unknown material 'glass'" in err


@pytest.mark.integration
def test_pluviation_friction_makes_a_looser_pour():
    from pdem.materials import Material
    from pdem.sources import pluviate
    from pdem.sources.regions import CylinderRegion
    from pdem.sources.sizes import Uniform

    mat = Material("g", density=2500.0, youngs_modulus=5e6, poisson_ratio=0.3, restitution=0.3, friction=0.0)
    region = CylinderRegion((0.0, 0.0, 0.0), 0.01, 0.05)
    sizes = Uniform(0.9e-3, 1.1e-3)

    def height(mu: float) -> float:
        import dataclasses

        x, r = pluviate(region, sizes, 400, dataclasses.replace(mat, friction=mu), seed=3)
        top = np.sort(x[:, 2] + r)[-40:]  # the free surface, averaged over its 10 % highest grains
        return float(np.mean(top))

    h_dense, h_loose = height(0.0), height(0.8)
    assert h_loose > h_dense * 1.02, (h_dense, h_loose)
    assert math.isfinite(h_dense)
