"""A run stopped by run.max_overlap says whether the overlap is static (the stress over the
stiffness: stiffer grains or a larger max_overlap) or dynamic (the step or the impact speed), and a
non-finite state is reported as such (which particle, which field), not as an infinite overlap.

References are Hertz closed forms (tests/physics_helpers.py), not pdem's force code."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from physics_helpers import e_star, hertz_impact, hertz_stiffness, reduced, sphere_mass

import pdem
from pdem.boundaries.api import Boundary, BoundaryParams
from pdem.geometry.shapes import Plane
from pdem.geometry.walls import ConstantVelocity

R = 1e-3
NU = 0.3


def _sim(e_mod: float) -> pdem.Simulation:
    sim = pdem.Simulation()
    sim.add_material("grain", density=2500.0, youngs_modulus=e_mod, poisson_ratio=NU, restitution=0.5,
                     friction=0.5)  # fmt: skip
    return sim


def _number(pattern: str, text: str) -> float:
    m = re.search(pattern, text)
    assert m, f"{pattern!r} not found in: {text}"
    return float(m.group(1))


@pytest.mark.parametrize("n", [2, 1], ids=["pair", "wall"])
def test_a_slow_squeeze_past_the_limit_is_static(n):
    """Soft grains (E = 1 MPa) stacked between the floor and a plate coming down at 5 mm/s (a
    contact period is 0.7 ms: quasi-static), no gravity: every contact carries the same force F,
    and the overlap grows with it until one passes 0.25 r. Two grains: the pair contact (R* = r/2)
    is the deepest, (F²/R*)^{1/3}; one grain: a wall contact. The message says static, quotes the
    overlap that the load holds at rest (Hertz: (F / (4/3 E* sqrt R*))^{2/3}, from the contact
    force read back), and advises stiffer grains or a larger run.max_overlap, not a smaller dt."""
    e_mod = 1e6
    sim = _sim(e_mod)
    sim.add_particles([[0.0, 0.0, R + 2 * R * k] for k in range(n)], R)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_wall(Plane((0, 0, 2 * R * n), (0, 0, -1)), name="press", motion=ConstantVelocity((0, 0, -0.005)))
    with pytest.raises(pdem.InstabilityError) as info:
        sim.run(until=1.0)
    msg = str(info.value)
    print(msg)
    assert "static overlap exceeded run.max_overlap = 0.25" in msg
    assert "The overlap is static" in msg and "stiffer grains" in msg and "run.max_overlap (e.g." in msg
    assert "reduce dt" not in msg and "dynamic" not in msg
    assert ("particles 0 and 1" in msg) if n == 2 else re.search(r"particle 0 and wall '(floor|press)'", msg)
    measured = _number(r"of the radius: ([0-9.]+) of the radius", msg)
    assert 0.25 < measured < 0.26
    # the overlap the load holds at rest, against Hertz from the contact's force read back
    if n == 2:
        force = float(sim.contacts()["normal_force"][0])
        r_eff = R / 2
    else:
        force = float(np.linalg.norm(sim.walls["floor"].force))
        r_eff = R
    es = e_star(e_mod, NU, e_mod, NU)
    at_rest = (force / hertz_stiffness(es, r_eff)) ** (2 / 3) / R
    quoted = _number(r"holds ([0-9.]+) of the radius at rest", msg)
    assert quoted == pytest.approx(at_rest, rel=0.02)
    assert quoted == pytest.approx(measured, rel=0.03)  # at rest: the load holds all of it
    # stiffer by (F / F(0.2 r)) holds it at 0.2 r (Hertz: F ∝ E* at a given overlap)
    factor = _number(r"contacts about ([0-9.]+) times stiffer", msg)
    assert factor == pytest.approx((at_rest / 0.2) ** 1.5, rel=0.05)


def test_a_sudden_load_past_the_limit_is_static():
    """A grain on the floor under a constant force (a boundary load switched on at once) whose
    static Hertz overlap is 0.4 r: the overlap passes 0.25 r while the grain still accelerates, but
    the load holds 0.4 r at rest, so the message says static (the load over the stiffness), with a
    smaller step of no use."""
    e_mod = 1e7
    es = e_star(e_mod, NU, e_mod, NU)
    load = hertz_stiffness(es, R) * (0.4 * R) ** 1.5

    class Press(Boundary):
        def apply_forces(self, sim):
            p = sim.particles
            p.f[: p.n_owned, 2] -= load

    sim = _sim(e_mod)
    sim.add_particles([[0.0, 0.0, R]], R)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_boundary(Press("press", BoundaryParams(type="press")))
    with pytest.raises(pdem.InstabilityError) as info:
        sim.run(steps=2000)
    msg = str(info.value)
    print(msg)
    assert "The overlap is static" in msg and "particle 0 and wall 'floor'" in msg
    assert _number(r"push ([0-9.e+-]+) N into it", msg) == pytest.approx(load, rel=1e-3)
    assert _number(r"holds ([0-9.]+) of the radius at rest", msg) == pytest.approx(0.4, rel=0.01)


def _impact(speed: float, gap: float, dt_share: float) -> tuple[pdem.Simulation, str]:
    """A grain (E = 10 MPa) at ``speed`` towards the floor, ``gap`` r above it, at ``dt_share`` of
    the stability estimate (forced, the live step bound off)."""
    sim = _sim(1e7)
    sim.add_particles([[0.0, 0.0, (1.0 + gap) * R]], R, velocities=[[0.0, 0.0, -speed]])
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.prepare()
    sim.force_dt = True
    sim.stiffness_limit = 0.0
    sim.dt = dt_share * sim.dt_critical
    with pytest.raises(pdem.InstabilityError) as info:
        sim.run(steps=500)
    msg = str(info.value)
    print(msg)
    return sim, msg


def test_a_fast_impact_at_a_large_step_is_dynamic():
    """2 m/s at 4 times the stability estimate: the grain moves 0.69 r a step and lands 0.49 r deep
    in one; the Hertz impact itself would reach only 0.14 r, so the step is the cause: a dynamic
    overlap, reduce dt."""
    sim, msg = _impact(2.0, 0.2, 4.0)
    assert "a dynamic overlap exceeded run.max_overlap = 0.25" in msg and "The overlap is dynamic" in msg
    assert "reduce dt (0.1–0.3 of the estimate)" in msg and "static" not in msg
    assert "particle 0 and wall 'floor'" in msg
    assert _number(r"closes at ([0-9.]+) m/s", msg) == pytest.approx(2.0, rel=1e-3)
    assert _number(r"\(([0-9.]+) of it\)", msg) == pytest.approx(4.0, rel=1e-3)
    es = e_star(1e7, NU, 1e7, NU)
    alpha, _, _ = hertz_impact(sphere_mass(R), R, es, 2.0)
    assert alpha < 0.25 * R  # the reference: the impact alone stays within the limit


def test_an_impact_too_hard_for_the_grains_says_so_whatever_the_step():
    """20 m/s: the Hertz impact overlap (15 m v² / (16 E* sqrt R))^{2/5} is 0.87 r, past the limit
    at any step; the message quotes it and adds that the step (0.9 of the estimate) adds to it."""
    sim, msg = _impact(20.0, 0.05, 0.9)
    assert "The overlap is dynamic" in msg and "whatever the step" in msg and "reduce dt too" in msg
    es = e_star(1e7, NU, 1e7, NU)
    alpha, _, _ = hertz_impact(sphere_mass(R), R, es, 20.0)
    reached = _number(r"approach alone reaches ([0-9.]+) of the radius", msg)
    assert reached == pytest.approx(alpha / R, rel=0.02)


def test_two_grains_colliding_use_the_pair_impact():
    """Two grains closing at 20 m/s head-on (m* = m/2, R* = r/2): the impact overlap quoted is the
    pair's Hertz closed form."""
    sim = _sim(1e7)
    sim.add_particles([[0.0, 0.0, 0.0], [0.0, 0.0, 2.1 * R]], R, velocities=[[0, 0, 10.0], [0, 0, -10.0]])
    sim.prepare()
    sim.dt = 0.5 * sim.dt_critical
    with pytest.raises(pdem.InstabilityError) as info:
        sim.run(steps=500)
    msg = str(info.value)
    print(msg)
    assert "particles 0 and 1" in msg and "The overlap is dynamic" in msg
    m = sphere_mass(R)
    alpha, _, _ = hertz_impact(reduced(m, m), R / 2, e_star(1e7, NU, 1e7, NU), 20.0)
    reached = _number(r"approach alone reaches ([0-9.]+) of the radius", msg)
    assert reached == pytest.approx(alpha / R, rel=0.02)


def _column() -> pdem.Simulation:
    sim = _sim(1e7)
    sim.add_particles([[0.0, 0.0, R], [0.0, 0.0, 3 * R - 1e-6], [2.5 * R, 0.0, R]], R)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0.0, 0.0, -9.81)
    sim.run(steps=10)
    return sim


def _row(sim: pdem.Simulation, pid: int) -> int:
    p = sim.particles
    return int(np.flatnonzero(p.id[: p.n_owned] == pid)[0])


def test_a_nan_position_is_reported_as_non_finite():
    """A NaN written into the position of grain 1 (resting on grain 0): the run stops at the next
    step naming grain 1 and its position, not an infinite overlap; the step is 0.2 of the estimate,
    so the remedy points at what wrote the value before the step."""
    sim = _column()
    sim.particles.x[_row(sim, 1), 2] = math.nan
    with pytest.raises(pdem.InstabilityError) as info:
        sim.step()
    msg = str(info.value)
    print(msg)
    assert "non-finite position" in msg and "particle 1's position is (0, 0, nan)" in msg
    assert "overlap" not in msg and "inf " not in msg
    assert "set from outside the integration" in msg


def test_a_nan_velocity_is_reported_with_its_particle():
    """A NaN velocity of the lone grain 2: its position follows in the drift; both are named."""
    sim = _column()
    sim.particles.v[_row(sim, 2), 0] = math.nan
    with pytest.raises(pdem.InstabilityError) as info:
        sim.step()
    msg = str(info.value)
    print(msg)
    assert "particle 2's position is (nan, 0, " in msg and "particle 2's velocity is (nan, 0, " in msg
    assert "particles 0 and" not in msg and "overlap" not in msg


def test_a_nan_force_from_a_boundary_is_reported():
    """A boundary that adds a NaN force to grain 0 (in contact with the floor and grain 1): the
    velocity flag fires within the step; the message names grain 0's force and velocity first, and
    the grains the NaN reached through the contacts after it."""

    class Broken(Boundary):
        def apply_forces(self, sim):
            p = sim.particles
            if sim.step_count >= 10:
                p.f[_row(sim, 0), 0] += math.nan

    sim = _sim(1e7)
    sim.add_particles([[0.0, 0.0, R], [0.0, 0.0, 3 * R - 1e-6], [2.5 * R, 0.0, R]], R)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_boundary(Broken("broken", BoundaryParams(type="broken")))
    with pytest.raises(pdem.InstabilityError) as info:
        sim.run(steps=50)
    msg = str(info.value)
    print(msg)
    assert sim.step_count == 11
    assert "particle 0's velocity is (nan" in msg and "particle 0's force is (nan" in msg
    assert "particle 2" not in msg  # not in contact: untouched
