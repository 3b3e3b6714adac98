"""The velocity servos' gain cap (pdem.contact.stability.servo_gain) and what it reads.

Independent references: the laws' force differentiated numerically in the normal and tangential
velocity (the dashpots c_n, c_t); Hertz's closed forms for a sphere pressed by a plane
(S_n = 2 E* sqrt(R δ), c_n = −2 sqrt(5/6) β sqrt(S_n m)); the rule gain ≤ 0.5 A / (K dt + 2 C).
The servos themselves are tested in tests/test_triaxial.py, tests/test_shear_box.py and the
servo-plate plugin's tests."""

from __future__ import annotations

import math

import numpy as np
import pytest

import pdem
from pdem.api import shapes
from pdem.contact.law import ContactLaw
from pdem.contact.stability import SERVO_LOOP_GAIN, servo_gain, wall_stiffness
from pdem.laws.hertz_mindlin import SQRT56, HertzMindlin, damping_ratio, force_numpy

E, NU, RHO, R = 1e7, 0.3, 2500.0, 1e-3


@pytest.mark.parametrize("form", ["material", "coefficients"])
def test_contact_damping_is_minus_the_derivative_of_the_kernels_force(form):
    """c_n = −dF_n/dv_n and c_t = −dF_t/dv_t of the law's own force (plain-Python twin; the
    tangential spring is left out with a zero step), at several overlaps, for both forms."""
    params = {} if form == "material" else dict(
        parameterisation="coefficients", kn=2e7, kt=1.5e7, cn=40.0, ct=20.0
    )
    sim = pdem.Simulation(law="hertz_mindlin", **params)
    sim.add_material("glass", density=RHO, youngs_modulus=E, poisson_ratio=NU, restitution=0.4, friction=0.5)
    sim.add_particles([[0, 0, 0]], [R], material="glass")
    sim.prepare()
    law, coef = sim.law, sim.coefficients
    r_eff, m_eff = 5e-4, 4e-6
    n = np.array([0.0, 0.0, 1.0])
    z = np.zeros(3)
    for delta in (1e-7, 1e-6, 1e-5):
        one = (np.array([0]), np.array([0]), np.array([r_eff]), np.array([m_eff]), np.array([delta]))
        c_n, c_t = (q[0] for q in law.contact_damping(coef, *one))

        def force(v, delta=delta):
            return force_numpy(delta, n, v, z, r_eff, m_eff, 1e-12, coef[0, 0], np.zeros(3), 0.0)[0]

        s = 1e-6  # slow: the tangential force stays below the Coulomb cap
        assert c_n > 0.0
        assert c_n == pytest.approx(-(force(s * n)[2] - force(-s * n)[2]) / (2 * s), rel=1e-9)
        assert c_t == pytest.approx(-force(np.array([s, 0.0, 0.0]))[0] / s, rel=1e-9)


def test_frictionless_contact_has_no_tangential_dashpot():
    sim = pdem.Simulation()
    sim.add_material("glass", friction=0.0, restitution=0.5)
    sim.add_particles([[0, 0, 0]], [R])
    sim.prepare()
    one = (np.array([0]), np.array([0]), np.array([5e-4]), np.array([1e-6]), np.array([1e-6]))
    c_n, c_t = sim.law.contact_damping(sim.coefficients, *one)
    assert c_n[0] > 0.0 and c_t[0] == 0.0


def _pressed(law="hertz_mindlin", restitution=0.5, delta=2e-6):
    """One sphere overlapping a floor by δ (and a lid plane above it, not touching), forces
    evaluated: the floor's contact is known in closed form."""
    sim = pdem.Simulation(law=law)
    sim.add_material("glass", density=RHO, youngs_modulus=E, poisson_ratio=NU, restitution=restitution,
                     friction=0.3)  # fmt: skip
    sim.add_particles([[0, 0, R - delta]], [R])
    floor = sim.add_wall(shapes.Plane((0, 0, 0), (0, 0, 1)), name="floor")
    lid = sim.add_wall(shapes.Plane((0, 0, 3 * R), (0, 0, -1)), name="lid")
    sim.dt = 1e-6
    sim.prepare()
    return sim, floor, lid


def test_wall_stiffness_of_a_pressed_sphere_is_hertz():
    delta = 2e-6
    sim, floor, lid = _pressed(delta=delta)
    e_star = E / (2 * (1 - NU * NU))  # sphere against a wall of the same material
    s_n = 2 * e_star * math.sqrt(R * delta)
    m = RHO * 4 / 3 * math.pi * R**3
    c_n = -2 * SQRT56 * damping_ratio(0.5) * math.sqrt(s_n * m)
    k, c = wall_stiffness(sim, floor)
    assert k == pytest.approx(s_n, rel=1e-9)
    assert c == pytest.approx(c_n, rel=1e-9)
    assert wall_stiffness(sim, lid) == (0.0, 0.0)  # nothing touches it
    sim.set_wall_active("floor", False)
    assert wall_stiffness(sim, floor) == (0.0, 0.0)


def test_servo_gain_caps_only_above_the_limit():
    sim, floor, lid = _pressed()
    k, c = wall_stiffness(sim, floor)
    area, dt = 1e-6, sim.dt
    limit = SERVO_LOOP_GAIN * area / (k * dt + 2 * c)  # the largest gain allowed
    low = 0.3 * limit
    got, loop = servo_gain(sim, floor, low, area)
    assert got == low  # unchanged below the cap: the same bits as without it
    assert loop == pytest.approx(low * (k * dt + 2 * c) / area, rel=1e-12)
    got, loop = servo_gain(sim, floor, 10 * limit, area)
    assert got == pytest.approx(limit, rel=1e-12)
    assert loop == pytest.approx(10 * SERVO_LOOP_GAIN, rel=1e-12)
    assert servo_gain(sim, lid, 10 * limit, area) == (10 * limit, 0.0)  # untouched: full gain


def test_no_cap_without_a_stiffness():
    """DEM-C (no stiffness) and a law without ``contact_stiffness`` keep the gain as given; a law
    without ``contact_damping`` is capped by its springs alone."""
    sim, floor, _ = _pressed(law="complementarity")
    got, loop = servo_gain(sim, floor, 1e3, 1e-6)
    assert got == 1e3 and math.isnan(loop)

    class NoStiffness(HertzMindlin):
        contact_stiffness = ContactLaw.contact_stiffness

    class NoDashpots(HertzMindlin):
        contact_damping = ContactLaw.contact_damping

    sim, floor, _ = _pressed(law=NoStiffness())
    assert all(math.isnan(v) for v in wall_stiffness(sim, floor))
    got, loop = servo_gain(sim, floor, 1e3, 1e-6)
    assert got == 1e3 and math.isnan(loop)
    sim, floor, _ = _pressed(law=NoDashpots())
    k, c = wall_stiffness(sim, floor)
    assert k > 0.0 and c == 0.0
    got, _ = servo_gain(sim, floor, 1e3, 1e-6)
    assert got == pytest.approx(SERVO_LOOP_GAIN * 1e-6 / (k * sim.dt), rel=1e-12)
