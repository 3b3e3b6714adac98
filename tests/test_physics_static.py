"""Quasi-static closed forms (physics.md §2): a column of spheres on a floor and a sphere on an
incline (gravity tilted, plane horizontal)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from physics_helpers import E_MOD, NU, RHO, e_star, hertz_stiffness, sphere_mass

import pdem
from pdem.geometry.shapes import Plane

R = 1e-3
G = 9.81


def _sim(restitution: float, friction: float) -> tuple[pdem.Simulation, object]:
    sim = pdem.Simulation()
    sim.add_material("glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU,
                     restitution=restitution, friction=friction, rolling_friction=0.0)
    floor = sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    return sim, floor


def test_static_column_hertz_overlaps_and_floor_load():
    """N = 5 equal spheres stacked on the floor, released touching (δ = 0), damped to rest
    (e = 0.1, 50 ms ≈ 20 periods of the slowest mode): contact k from the top carries k m g,
    so δ_k = (k m g / ((4/3) E* sqrt(R*)))^{2/3} with R* = r/2 between spheres and R* = r at the
    floor (k = N); within 1 %. The floor carries N m g (downwards)."""
    n = 5
    sim, floor = _sim(0.1, 0.5)
    sim.add_particles([[0.0, 0.0, R + 2 * R * k] for k in range(n)], R)
    sim.gravity = (0.0, 0.0, -G)
    sim.run(until=0.05)
    p = sim.get_particles()
    m = sphere_mass(R)
    es = e_star()
    z = p["x"][:, 2]
    # at rest
    assert sum(sim.kinetic_energy()) < 1e-12 * m * G * R
    assert np.allclose(p["x"][:, :2], 0.0, atol=0.0)
    # floor contact: bottom sphere, k = n
    floor_ref = (n * m * G / hertz_stiffness(es, R)) ** (2 / 3)
    errs = [(R - z[0]) / floor_ref - 1]
    for b in range(n - 1):  # contact between spheres b and b+1 carries the n-1-b spheres above it
        k = n - 1 - b
        ref = (k * m * G / hertz_stiffness(es, R / 2)) ** (2 / 3)
        errs.append((2 * R - (z[b + 1] - z[b])) / ref - 1)
    # the same overlaps seen through sim.contacts()
    c = sim.contacts()
    assert [(int(i), int(j)) for i, j in zip(c["id_i"], c["id_j"], strict=True)] == [
        (b, b + 1) for b in range(n - 1)]
    for b in range(n - 1):
        assert c["normal_force"][b] == pytest.approx((n - 1 - b) * m * G, rel=1e-6)
    load_err = np.linalg.norm(floor.force - np.array([0.0, 0.0, -n * m * G])) / (n * m * G)
    print(f"overlap rel. errors (floor, then bottom→top): {np.array2string(np.array(errs), precision=2)}, "
          f"floor load error {load_err:.1e}")
    assert np.all(np.abs(errs) < 0.01)
    assert load_err < 1e-6
    assert floor.n_contacts == 1


@pytest.mark.parametrize("theta_deg", [10.0, 30.0, 58.0, 62.0, 75.0])
def test_sphere_on_incline(theta_deg):
    """Rolls without slipping with a = (5/7) g sin θ iff tan θ < 3.5 μ (μ = 0.5: θ < 60.3°),
    otherwise slides with a = g (sin θ − μ cos θ). Released touching; the bounce transient is
    damped (e = 0.1); the acceleration is (v(40 ms) − v(10 ms)) / 30 ms, within 1 %."""
    mu = 0.5
    theta = math.radians(theta_deg)
    rolls = math.tan(theta) < 3.5 * mu
    sim, floor = _sim(0.1, mu)
    sim.add_particles([[0.0, 0.0, R]], R)
    sim.gravity = (G * math.sin(theta), 0.0, -G * math.cos(theta))
    sim.run(until=0.01)
    t1, v1 = sim.time, sim.get_particles()["v"][0].copy()
    sim.run(until=0.04)
    p = sim.get_particles()
    t2, v2 = sim.time, p["v"][0]
    a = (v2[0] - v1[0]) / (t2 - t1)
    a_ref = 5 / 7 * G * math.sin(theta) if rolls else G * (math.sin(theta) - mu * math.cos(theta))
    slip = v2[0] - p["w"][0, 1] * R  # contact-point velocity (ω_y > 0 rolls along +x)
    print(f"theta={theta_deg}: {'rolls' if rolls else 'slides'}, a/a_ref − 1 = {a / a_ref - 1:+.2e}, "
          f"slip/v = {slip / v2[0]:.2e}")
    assert a == pytest.approx(a_ref, rel=0.01)
    if rolls:
        assert abs(slip) < 1e-3 * v2[0]
    else:
        # sliding: spin-up by the friction torque μ m g cos θ r; the slip grows at g (sin θ − 3.5 μ cos θ)
        slip_ref = G * (math.sin(theta) - 3.5 * mu * math.cos(theta)) * t2
        assert slip == pytest.approx(slip_ref, rel=0.03)
        w_rate = 2.5 * mu * G * math.cos(theta) / R
        assert p["w"][0, 1] == pytest.approx(w_rate * t2, rel=0.02)
    # the normal load on the plane is m g cos θ (plus the friction along x)
    m = sphere_mass(R)
    assert -floor.force[2] == pytest.approx(m * G * math.cos(theta), rel=1e-3)
    assert abs(v2[1]) < 1e-12 and abs(v2[2]) < 1e-6
