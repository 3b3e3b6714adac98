"""Binary impacts against closed forms (physics.md §2) and an independent RK4 reference.

* elastic Hertz impact (e = 1, μ = 0), sphere–sphere head-on and sphere–wall: peak force, maximum
  overlap and contact duration within 1 % of the Hertz closed forms (dt = t_c/500);
* restitution sweep, unclamped and clamped normal force: the realised rebound ratio within 1 % of a
  fine RK4 integration of the same normal-force ODE written here (dt = t_c/1000; the damping force
  sees the half-step velocity, so the error of the realised e is O(dt/t_c): ~0.5 % at t_c/500 for
  e = 0.1);
* oblique impact on a wall in the gross-sliding regime: tangential restitution within 1 % and
  spin within 1 % of the rigid-body formulas, damped cases included: they caught a reversal of
  friction at the start of damped sliding contacts under the slider rule ξ = −(F_t + c_t v_t)/k_t,
  which pdem therefore replaced by ξ = −F_t/k_t (see pdem/laws/hertz_mindlin.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from physics_helpers import (
    E_MOD,
    NU,
    RHO,
    e_star,
    hertz_impact,
    normal_impact_rk4,
    parabolic_peak,
    positive_interval,
    reduced,
    sphere_mass,
)

import pdem
from pdem.geometry.shapes import Plane

R = 1e-3  # sphere radius [m]
V = 1.0  # approach speed [m/s]


def _material(sim: pdem.Simulation, restitution: float, friction: float, name: str = "glass",
              youngs_modulus: float = E_MOD, poisson_ratio: float = NU) -> None:
    sim.add_material(name, density=RHO, youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio,
                     restitution=restitution, friction=friction, rolling_friction=0.0)


def _head_on(restitution: float, dt: float, gap: float, clamp: bool = False) -> pdem.Simulation:
    """Two equal spheres on the x axis, gap apart, approaching each other at relative speed V."""
    sim = pdem.Simulation(clamp_normal=clamp) if clamp else pdem.Simulation()
    _material(sim, restitution, 0.0)
    sim.add_particles([[-R - gap / 2, 0, 0], [R + gap / 2, 0, 0]], R,
                      velocities=[[V / 2, 0, 0], [-V / 2, 0, 0]])
    sim.dt = dt
    return sim


# ---------------------------------------------------------------------------------------------
# elastic Hertz impact
# ---------------------------------------------------------------------------------------------


def test_elastic_hertz_impact_sphere_sphere():
    m = sphere_mass(R)
    m_eff, r_eff, es = reduced(m, m), reduced(R, R), e_star()
    alpha, fmax, tc = hertz_impact(m_eff, r_eff, es, V)
    dt = tc / 500
    sim = _head_on(1.0, dt, gap=3.5 * V * dt)
    rec = []

    def sample(s):
        p = s.get_particles()
        c = s.contacts()
        overlap = 2 * R - float(np.linalg.norm(p["x"][1] - p["x"][0]))
        fn = float(c["normal_force"][0]) if c["normal_force"].size else 0.0
        if c["normal_force"].size:
            assert (int(c["id_i"][0]), int(c["id_j"][0])) == (0, 1)
        rec.append((s.time, overlap, fn))

    sim.run(steps=0)
    sample(sim)
    sim.run(until=1.4 * tc, callback=sample)
    t, overlap, fn = np.array(rec).T
    t0, t1 = positive_interval(t, overlap)
    err_alpha = parabolic_peak(overlap) / alpha - 1
    err_f = parabolic_peak(fn) / fmax - 1
    err_tc = (t1 - t0) / tc - 1
    print(f"sphere-sphere: alpha {err_alpha:+.2e}, F_max {err_f:+.2e}, t_c {err_tc:+.2e}")
    assert abs(err_alpha) < 0.01
    assert abs(err_f) < 0.01
    assert abs(err_tc) < 0.01
    # the contact starts when the gap closes
    assert t0 == pytest.approx(3.5 * dt, rel=1e-3)
    # elastic: the spheres separate with the approach speed
    p = sim.get_particles()
    assert p["v"][1, 0] - p["v"][0, 0] == pytest.approx(V, rel=1e-4)


def test_elastic_hertz_impact_sphere_wall():
    """Different wall material: E* mixes both, R* = r, m* = m."""
    e_wall, nu_wall = 2e8, 0.25
    m = sphere_mass(R)
    es = e_star(E_MOD, NU, e_wall, nu_wall)
    alpha, fmax, tc = hertz_impact(m, R, es, V)
    dt = tc / 500
    sim = pdem.Simulation()
    _material(sim, 1.0, 0.0)
    _material(sim, 1.0, 0.0, name="steel", youngs_modulus=e_wall, poisson_ratio=nu_wall)
    floor = sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), material="steel", name="floor")
    sim.add_particles([[0, 0, R + 3.5 * V * dt]], R, material="glass", velocities=[[0, 0, -V]])
    sim.dt = dt
    rec = []

    def sample(s):
        p = s.get_particles()
        rec.append((s.time, R - p["x"][0, 2], -floor.force[2], floor.n_contacts))

    sim.run(steps=0)
    sample(sim)
    sim.run(until=1.4 * tc, callback=sample)
    t, overlap, fz, nc = np.array(rec).T
    assert np.all((nc > 0) == (overlap > 0))
    t0, t1 = positive_interval(t, overlap)
    err_alpha = parabolic_peak(overlap) / alpha - 1
    err_f = parabolic_peak(fz) / fmax - 1
    err_tc = (t1 - t0) / tc - 1
    print(f"sphere-wall: alpha {err_alpha:+.2e}, F_max {err_f:+.2e}, t_c {err_tc:+.2e}")
    assert abs(err_alpha) < 0.01
    assert abs(err_f) < 0.01
    assert abs(err_tc) < 0.01
    assert sim.get_particles()["v"][0, 2] == pytest.approx(V, rel=1e-4)
    assert np.allclose(floor.force, 0.0)


# ---------------------------------------------------------------------------------------------
# restitution
# ---------------------------------------------------------------------------------------------

RESTITUTIONS = [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0]
HORIZON = 2.5  # run for this many elastic contact times after the contact starts


def _rebound(e: float, clamp: bool) -> tuple[float, float, float]:
    """Run the head-on impact for HORIZON t_c after first touch. Returns the relative normal
    velocity (separating positive) / V, the overlap at the end and the time since first touch."""
    m = sphere_mass(R)
    tc = hertz_impact(reduced(m, m), reduced(R, R), e_star(), V)[2]
    dt = tc / 1000
    gap = 3.5 * V * dt
    sim = _head_on(e, dt, gap, clamp=clamp)
    sim.run(until=gap / V + HORIZON * tc)
    p = sim.get_particles()
    ratio = (p["v"][1, 0] - p["v"][0, 0]) / V
    overlap = 2 * R - float(np.linalg.norm(p["x"][1] - p["x"][0]))
    return ratio, overlap, sim.time - gap / V


def _reference(e: float, clamp: bool, t_end: float) -> dict[str, float]:
    m = sphere_mass(R)
    args = (e, reduced(m, m), reduced(R, R), e_star(), V, t_end)
    fine = normal_impact_rk4(*args, steps_per_tc=2000, clamp=clamp)
    coarse = normal_impact_rk4(*args, steps_per_tc=1000, clamp=clamp)
    # the reference itself is converged
    assert abs(fine["rate"] - coarse["rate"]) < 1e-4 * V
    return fine


@pytest.fixture(scope="module")
def rebounds():
    out = {}
    for clamp in (False, True):
        for e in RESTITUTIONS:
            ratio, overlap, t_end = _rebound(e, clamp)
            ref = _reference(e, clamp, t_end)
            out[clamp, e] = (ratio, overlap, ref)
    return out


@pytest.mark.parametrize("clamp", [False, True], ids=["unclamped", "clamped"])
@pytest.mark.parametrize("e", RESTITUTIONS)
def test_restitution_matches_rk4_reference(rebounds, e, clamp):
    ratio, overlap, ref = rebounds[clamp, e]
    ref_ratio = -ref["rate"] / V
    print(f"e={e} clamp={clamp}: realised {ratio:.6f}, RK4 {ref_ratio:.6f}, "
          f"rel. err {ratio / ref_ratio - 1:+.2e}")
    assert ratio == pytest.approx(ref_ratio, rel=0.01)
    # same state of the contact at the end: separated, or (e = 0, unclamped) still touching
    assert (overlap > 0) == (not ref["ended"])


def test_unclamped_restitution_equals_input(rebounds):
    """Unclamped, the damping reproduces the input e (physics.md §2); for e = 0 the spheres do
    not separate within the horizon but creep apart slowly (rebound < 2 % of V)."""
    for e in RESTITUTIONS:
        ratio, overlap, ref = rebounds[False, e]
        if e == 0.0:
            assert not ref["ended"] and overlap > 0
            assert 0.0 < ratio < 0.02
            assert -ref["rate"] / V < 0.02
        else:
            assert ref["ended"]
            # the RK4 reference: realised e equals the input e
            assert -ref["rate"] / V == pytest.approx(e, rel=1e-4)
            assert ratio == pytest.approx(e, rel=0.01)
    # and a part of the normal impulse is attractive when 0 < e < 1
    assert rebounds[False, 0.5][2]["attractive_impulse"] < 0.0


def test_clamped_restitution_exceeds_unclamped(rebounds):
    """Clamping F_n ≥ 0 removes the attractive end of the contact: the realised e is higher than
    unclamped for every e < 1 (much higher at small e: the RK4 reference gives ≈ 0.135 at e = 0,
    ≈ 0.253 at e = 0.1, ≈ 0.550 at e = 0.5) and identical at e = 1."""
    for e in RESTITUTIONS:
        clamped = rebounds[True, e][0]
        unclamped = rebounds[False, e][0]
        if e < 1.0:
            assert clamped > unclamped
            assert rebounds[True, e][2]["ended"]
            assert -rebounds[True, e][2]["rate"] / V > e
        else:
            assert clamped == pytest.approx(unclamped, rel=1e-12)
        print(f"e={e}: clamped {clamped:.4f} unclamped {unclamped:.4f}")


# ---------------------------------------------------------------------------------------------
# oblique impact with gross sliding
# ---------------------------------------------------------------------------------------------




@pytest.mark.parametrize("e, mu, theta_deg, clamp", [
    (1.0, 0.1, 45.0, False),
    (0.9, 0.05, 30.0, False),
    (0.5, 0.2, 60.0, True),
    (0.5, 0.2, 60.0, False),
    (0.3, 0.1, 45.0, False),
])
def test_oblique_impact_gross_sliding(e, mu, theta_deg, clamp):
    """Sphere hitting a floor at angle θ from the normal with tan θ ≥ 3.5 μ (1 + e): rigid-body
    gross sliding gives e_t = 1 − μ (1 + e)/tan θ and ω' = (5/2) μ (1 + e) v_n / r; both within 1 %.

    Here 1 + e stands for the repulsive normal impulse / (m v_n) of the contact, from the RK4
    reference of the same normal law: 1 + e_n with e_n the realised normal restitution, plus, when
    F_n is not clamped, the attractive impulse at the end of the contact, during which the Coulomb
    cap μ max(F_n, 0) is zero (≈ 0.2 % of 1 + e at e = 0.9, 3.4 % at e = 0.5)."""
    theta = math.radians(theta_deg)
    assert math.tan(theta) >= 3.5 * mu * (1 + e)
    vn = 0.1  # small overlaps (δ/r < 1 %), so that the lever arm r − δ/2 is ≈ r
    vt = vn * math.tan(theta)
    m = sphere_mass(R)
    es = e_star()
    tc = hertz_impact(m, R, es, vn)[2]
    dt = tc / 500
    sim = pdem.Simulation(clamp_normal=clamp) if clamp else pdem.Simulation()
    _material(sim, e, mu)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_particles([[0, 0, R + 3.5 * vn * dt]], R, velocities=[[vt, 0, -vn]])
    sim.dt = dt
    sim.run(until=3.5 * dt + 2.0 * tc)
    p = sim.get_particles()
    ref = normal_impact_rk4(e, m, R, es, vn, 2.0 * tc, clamp=clamp)
    assert ref["ended"]
    e_n = -ref["rate"] / vn
    assert p["v"][0, 2] / vn == pytest.approx(e_n, rel=0.01)
    assert p["x"][0, 2] > R  # left the floor
    one_plus_e = 1 + e_n - ref["attractive_impulse"] / (m * vn)
    e_t = p["v"][0, 0] / vt
    e_t_ref = 1 - mu * one_plus_e / math.tan(theta)
    w_ref = 2.5 * mu * one_plus_e * vn / R
    w = p["w"][0, 1]
    print(f"e={e} mu={mu} theta={theta_deg} clamp={clamp}: e_t {e_t:.5f} vs {e_t_ref:.5f} "
          f"({e_t / e_t_ref - 1:+.2e}), spin {w:.4f} vs {w_ref:.4f} ({w / w_ref - 1:+.2e})")
    assert e_t == pytest.approx(e_t_ref, rel=0.01)
    assert w == pytest.approx(w_ref, rel=0.01)
    # still sliding at separation, and no spin about other axes
    assert p["v"][0, 0] - w * R > 0.0
    assert abs(p["w"][0, 0]) < 1e-9 * abs(w) and abs(p["w"][0, 2]) < 1e-9 * abs(w)
    assert abs(p["v"][0, 1]) < 1e-12


def test_friction_never_drives_the_slip():
    """During a sliding contact the friction force on the sphere must oppose the slip velocity of
    its contact point at every step (Coulomb). Sampled every step of a damped oblique impact."""
    e, mu, vn = 0.5, 0.2, 0.1
    vt = vn * math.tan(math.radians(60.0))
    m = sphere_mass(R)
    tc = hertz_impact(m, R, e_star(), vn)[2]
    dt = tc / 500
    sim = pdem.Simulation()
    _material(sim, e, mu)
    floor = sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_particles([[0, 0, R + 3.5 * vn * dt]], R, velocities=[[vt, 0, -vn]])
    sim.dt = dt
    wrong = []

    def check(s):
        p = s.get_particles()
        slip = p["v"][0, 0] - p["w"][0, 1] * (R - max(R - p["x"][0, 2], 0.0) / 2)
        friction_on_sphere = -floor.force[0]
        if friction_on_sphere * slip > 0.0:
            wrong.append((s.step_count, friction_on_sphere, -floor.force[2]))

    sim.run(until=2.0 * tc, callback=check)
    print(f"{len(wrong)} steps with friction along the slip; first: {wrong[:3]}")
    assert not wrong, f"friction drove the slip in {len(wrong)} steps, first: {wrong[:3]}"
