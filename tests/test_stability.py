"""Time-step stability: a too large dt is refused, and a forced one is detected as an instability
with a message that states dt and the estimate; the stored state stays finite."""

from __future__ import annotations

import re

import numpy as np
import pytest
from physics_helpers import E_MOD, NU, RHO, rayleigh_time

import pdem
from pdem.geometry.shapes import box_planes

R = 1e-3
NSIDE = 6


def _dense_pile(seed: int = 0, speed: float = 0.3) -> tuple[pdem.Simulation, float]:
    """6×6×6 nearly touching spheres (gaps 0.1 % of d) in a box, random velocities (rms ``speed``
    per component), gravity.
    Returns the simulation and the smallest radius."""
    rng = np.random.default_rng(seed)
    idx = np.stack(np.meshgrid(*[np.arange(NSIDE)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    x = idx * 2 * R * 1.001 + R * 1.001
    radii = R * rng.uniform(0.9, 1.0, len(x))
    sim = pdem.Simulation()
    sim.add_material("glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU, restitution=0.5,
                     friction=0.5)
    sim.add_particles(x, radii, velocities=rng.normal(0.0, speed, (len(x), 3)))
    for plane in box_planes([0, 0, 0], [2.002 * R * NSIDE, 2.002 * R * NSIDE, 4 * R * NSIDE]):
        sim.add_wall(plane)
    sim.gravity = (0.0, 0.0, -9.81)
    return sim, float(radii.min())


def _numbers_after(label: str, text: str) -> float:
    m = re.search(label + r"\s*=?\s*([0-9.eE+-]+)\s*s", text)
    assert m, f"'{label}' with a value in seconds not found in: {text}"
    return float(m.group(1))


@pytest.mark.parametrize("speed", [0.0, 0.3], ids=["settling", "agitated"])
def test_forced_large_dt_raises_instability_with_dt_and_estimate(speed):
    """At rest the pile blows up while settling under gravity (observed: step ~37, overlap > r);
    agitated it overshoots within a few steps."""
    sim, rmin = _dense_pile(speed=speed)
    estimate = rayleigh_time(rmin)  # independent: T_R of the smallest sphere
    sim.dt = 3.0 * estimate
    sim.force_dt = True
    sim.stiffness_limit = 0.0  # the live bound stops this at step 1 (test_stiffness_bound); here: the blow-up
    with pytest.raises(pdem.InstabilityError) as info:
        sim.run(steps=2000)
    msg = str(info.value)
    print(f"raised at step {sim.step_count}: {msg}")
    assert _numbers_after(r"dt", msg) == pytest.approx(3.0 * estimate, rel=1e-3)
    assert _numbers_after(r"stability estimate", msg) == pytest.approx(estimate, rel=1e-3)
    assert sim.step_count < 2000
    # the stored state is finite after the error (the overlap check fires before values overflow)
    p = sim.get_particles()
    for key in ("x", "v", "w", "f", "t"):
        assert np.all(np.isfinite(p[key])), key


def test_stable_dt_runs():
    """Control: the same pile at 0.2 of the estimate runs without error."""
    sim, rmin = _dense_pile()
    sim.dt = 0.2 * rayleigh_time(rmin)
    sim.run(steps=500)
    p = sim.get_particles()
    assert np.all(np.isfinite(p["x"])) and np.all(np.isfinite(p["v"]))


def test_dt_above_estimate_refused_without_force():
    sim, rmin = _dense_pile()
    estimate = rayleigh_time(rmin)
    sim.dt = 1.5 * estimate
    with pytest.raises(pdem.InputError) as info:
        sim.run(steps=1)
    msg = str(info.value)
    assert not isinstance(info.value, pdem.InstabilityError)
    assert _numbers_after(r"dt", msg) == pytest.approx(1.5 * estimate, rel=1e-3)
    assert _numbers_after(r"stability estimate", msg) == pytest.approx(estimate, rel=1e-3)
    assert sim.step_count == 0
    # nothing moved
    assert np.all(np.isfinite(sim.get_particles()["x"]))


def test_dt_just_below_estimate_accepted():
    sim, rmin = _dense_pile()
    sim.dt = 0.999 * rayleigh_time(rmin)
    sim.run(steps=0)  # prepares without complaint
    assert sim.dt_critical == pytest.approx(rayleigh_time(rmin), rel=1e-12)


@pytest.mark.parametrize("fraction", [0.1, 0.35])
def test_dt_fraction_sets_the_step_from_the_estimate(fraction):
    """``dt_fraction`` takes the step as a multiple of the law's estimate (here the Rayleigh time of
    the smallest sphere, computed independently)."""
    sim, rmin = _dense_pile()
    sim.dt_fraction = fraction
    sim.run(steps=3)
    assert sim.dt == pytest.approx(fraction * rayleigh_time(rmin), rel=1e-3)
    assert sim.dt_critical == pytest.approx(rayleigh_time(rmin), rel=1e-3)


def test_dt_fraction_above_one_needs_force_dt():
    sim, _ = _dense_pile()
    sim.dt_fraction = 1.5
    with pytest.raises(pdem.InputError, match="stability estimate"):
        sim.run(steps=1)


def test_dt_fraction_is_refused_without_a_stability_limit():
    sim, _ = _dense_pile()
    sim.set_law("complementarity")
    sim.dt_fraction = 0.2
    with pytest.raises(pdem.InputError, match=r"run\.dt_fraction = 0\.2.*give run\.dt"):
        sim.run(steps=1)
