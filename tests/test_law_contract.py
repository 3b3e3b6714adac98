"""Hertz–Mindlin kernel vs its plain-Python twin, both parameterisations, rolling resistance on;
plus closed forms for rolling resistance and a moving wall."""

import math

import numpy as np
import pytest

import pdem
from pdem.geometry.shapes import Plane
from pdem.geometry.walls import ConstantVelocity
from pdem.laws.hertz_mindlin import HertzMindlin, force_numpy
from pdem.materials import Material, MaterialTable
from pdem.testing.law_contract import check_law_against_twin


def table():
    mt = MaterialTable()
    mt.add(Material("a", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.4, friction=0.3,
                    rolling_friction=0.1))
    mt.add(Material("b", density=7800, youngs_modulus=2e8, poisson_ratio=0.25, restitution=0.7, friction=0.6))
    return mt


@pytest.mark.parametrize("params", [
    {},
    {"clamp_normal": True},
    {"parameterisation": "coefficients", "kn": 2e7, "kt": 1.5e7, "cn": 3e4, "ct": 1e4},
    {"tangential": "mindlin_rescale"},
    {"tangential": "mindlin_force", "limit_damping": True},
    {"tangential": "mindlin_rescale_force"},
    {"tangential": "mindlin_rescale_force", "parameterisation": "coefficients", "kn": 2e7, "kt": 1.5e7,
     "cn": 3e4, "ct": 1e4},
])
@pytest.mark.parametrize("mat", [(0, 0), (0, 1)])
def test_kernel_matches_twin(params, mat):
    assert check_law_against_twin(HertzMindlin(**params), force_numpy, table(), mat=mat) >= 100


def test_coefficient_form_static_overlap():
    """Equation (1) of the study: at rest F_n = sqrt(R* δ) K_n δ; a sphere resting on a floor under
    gravity settles at δ = (m g/(K_n sqrt(r)))^(2/3)."""
    kn, r = 4e7, 1e-3
    # C_n chosen for a damping ratio of order one at this overlap (C_n sqrt(R δ) m ~ sqrt(k m))
    sim = pdem.Simulation(parameterisation="coefficients", kn=kn, kt=kn, cn=6e8, ct=3e8)
    sim.add_material("a", density=2500)
    sim.add_particles([[0, 0, r]], r)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0, 0, -9.81)
    sim.run(until=0.05)
    m = sim.get_particles()["mass"][0]
    delta = r - sim.get_particles()["x"][0, 2]
    assert delta == pytest.approx((m * 9.81 / (kn * math.sqrt(r))) ** (2 / 3), rel=1e-4)


def test_rolling_resistance_deceleration():
    """A sphere rolling on a floor with rolling friction μ_r decelerates at (5/7) μ_r g (torque
    μ_r r m g, rolling without slipping); rolling friction is off by default."""
    r, mu_r, v0 = 1e-3, 0.05, 0.05
    decel = {}
    for rolling in (0.0, mu_r):
        sim = pdem.Simulation()
        sim.add_material("a", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3,
                         friction=0.8, rolling_friction=rolling)
        m = 2500 * 4 / 3 * math.pi * r**3
        delta0 = (m * 9.81 / (4 / 3 * 5e7 / (1 - 0.09) * math.sqrt(r))) ** (2 / 3)
        sim.add_particles([[0, 0, r - delta0]], r, velocities=[[v0, 0, 0]],
                          angular_velocities=[[0, v0 / r, 0]])
        sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
        sim.gravity = (0, 0, -9.81)
        sim.run(until=0.01)
        v1 = sim.get_particles()["v"][0, 0]
        sim.run(until=0.05)
        v2 = sim.get_particles()["v"][0, 0]
        decel[rolling] = (v1 - v2) / 0.04
    assert abs(decel[0.0]) < 1e-3 * 5 / 7 * mu_r * 9.81
    assert decel[mu_r] == pytest.approx(5 / 7 * mu_r * 9.81, rel=0.01)


def test_moving_floor_carries_a_sphere():
    """A sphere resting on a floor that starts moving sideways at U: friction is the only horizontal
    force, so the angular momentum about the contact point stays zero, and once slipping stops the
    sphere rolls with v = (2/7) U and ω = −(5/7) U/r about y (contact point moving with the floor)."""
    r, u = 1e-3, 0.02
    sim = pdem.Simulation()
    sim.add_material("a", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3, friction=0.5)
    sim.add_particles([[0, 0, r * 0.999]], r)
    floor = sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor", motion=ConstantVelocity((u, 0, 0)))
    sim.gravity = (0, 0, -9.81)
    sim.run(until=0.05)
    p = sim.get_particles()
    assert p["v"][0, 0] == pytest.approx(2 / 7 * u, rel=2e-3)
    assert p["w"][0, 1] == pytest.approx(-5 / 7 * u / r, rel=2e-3)
    assert floor.offset[0] == pytest.approx(u * sim.time, rel=1e-9)
    assert -floor.force[2] == pytest.approx(p["mass"][0] * 9.81, rel=1e-3)


def test_readme_api_example_runs():
    """The README's Python API block is runnable as written."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = text.split("## Python API", 1)[1].split("```python", 1)[1].split("```", 1)[0]
    namespace: dict = {}
    exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102 - runs our own documentation
    sim = namespace["sim"]
    assert sim.time >= 0.05 and np.all(np.isfinite(sim.get_particles()["x"]))
