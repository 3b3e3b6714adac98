"""The engine's seams for experiment devices: boundaries owned by the simulation whose hooks run
inside the step (forces added between the contact forces and the second half kick in DEM-P, into
the free velocity in DEM-C), the per-particle degree-of-freedom mask, registered fields, stages.

References are closed forms: a constant force on a body on a frictionless floor gives
x(t) = F t²/(2m) (exact for velocity Verlet; semi-implicit Euler gives F h² n(n+1)/(2m) after n
steps), and a sphere that may not turn slides to rest after v0²/(2 μ g)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import pdem
from pdem.boundaries.api import Boundary, BoundaryParams
from pdem.errors import InputError
from pdem.geometry.shapes import Plane
from pdem.state.particles import dof_mask

R = 1e-3
RHO = 2500.0
MASS = RHO * 4.0 / 3.0 * math.pi * R**3


class Push(Boundary):
    """A constant force on particles of one group (hook ``apply_forces``)."""

    def __init__(self, force, group=1, name="push"):
        super().__init__(name, BoundaryParams(type="push"))
        self.force = np.asarray(force, dtype=float)
        self.group = group
        self.calls = 0

    def apply_forces(self, sim):
        self.calls += 1
        p = sim.particles
        n = p.n_owned
        sel = p.group[:n] == self.group
        p.f[:n][sel] += self.force


def _sim(law, friction=0.0, gravity=(0.0, 0.0, -9.81)):
    sim = pdem.Simulation(law=law)
    sim.add_material("glass", density=RHO, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
                     friction=friction)
    sim.gravity = gravity
    return sim


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_boundary_force_inside_the_step_matches_closed_form(law):
    sim = _sim(law)
    sim.add_particles([[0.0, 0.0, R]], R, group=1)
    sim.add_particles([[0.0, 0.01, R]], R)  # group 0: not pushed
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    F = 2e-4  # N, about 2 g·m
    push = sim.add_boundary(Push((F, 0.0, 0.0)))
    dt = 1e-5 if law == "hertz_mindlin" else 1e-4
    sim.dt = dt
    n = 300
    sim.run(steps=n)  # Simulation.run: the hook runs inside step(), no runner needed
    p = sim.get_particles()
    t = n * dt
    if law == "hertz_mindlin":
        expected = F * t**2 / (2 * MASS)  # velocity Verlet is exact for a constant force
    else:
        expected = F * dt**2 * n * (n + 1) / (2 * MASS)  # semi-implicit Euler
    assert p["x"][0, 0] == pytest.approx(expected, rel=1e-9)
    assert p["v"][0, 0] == pytest.approx(F * t / MASS, rel=1e-9)
    assert p["x"][1, 0] == 0.0 and p["v"][1, 0] == 0.0  # the other grain is not pushed
    assert push.calls >= n
    # reported force includes the boundary's (x has no contact or weight component)
    assert p["f"][0, 0] == pytest.approx(F, rel=1e-9)


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_inactive_boundary_adds_nothing(law):
    sim = _sim(law, gravity=(0, 0, 0))
    sim.add_particles([[0.0, 0.0, 0.0]], R, group=1)
    push = sim.add_boundary(Push((1e-3, 0.0, 0.0)))
    push.params = BoundaryParams(type="push", stages=["later"])
    sim.set_stage("now")
    sim.dt = 1e-5
    sim.run(steps=10)
    assert sim.get_particles()["v"][0, 0] == 0.0
    sim.set_stage("later")
    sim.run(steps=10)
    assert sim.get_particles()["v"][0, 0] > 0.0


def test_sliding_sphere_with_rotation_locked_stops_after_v2_over_2mug():
    mu, v0, g = 0.3, 0.2, 9.81
    sim = _sim("hertz_mindlin", friction=mu, gravity=(0, 0, -g))
    sim.add_particles([[0.0, 0.0, R]], R, velocities=[(v0, 0, 0)], fixed_rotation="xyz")
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.dt = 2e-6
    sim.run(until=v0 / (mu * g) * 1.3)
    p = sim.get_particles()
    assert np.all(p["w"] == 0.0)
    assert abs(p["v"][0, 0]) < 1e-3 * v0
    assert p["x"][0, 0] == pytest.approx(v0**2 / (2 * mu * g), rel=0.02)
    # free to turn, it rolls on at 5/7 v0 instead (Coulomb sliding, then rolling)
    sim = _sim("hertz_mindlin", friction=mu, gravity=(0, 0, -g))
    sim.add_particles([[0.0, 0.0, R]], R, velocities=[(v0, 0, 0)])
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.dt = 2e-6
    sim.run(until=v0 / (mu * g) * 1.3)
    assert sim.get_particles()["v"][0, 0] == pytest.approx(5 / 7 * v0, rel=0.02)


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_two_dimensional_mode_keeps_grains_in_their_plane(law):
    """Translation along y and rotation about x and z locked: a colliding heap stays in y = 0 with
    ω only about y, bit for bit, while the grains do move in x and z."""
    rng = np.random.default_rng(3)
    sim = _sim(law, friction=0.4)
    k = np.arange(30)
    x = np.stack([(k % 6) * 2.3 * R, np.zeros(30), 2 * R + (k // 6) * 2.3 * R], axis=1)
    v = rng.normal(0, 0.05, (30, 3))
    w = rng.normal(0, 5.0, (30, 3))
    sim.add_particles(x, R, velocities=v, angular_velocities=w, fixed_translation="y", fixed_rotation="xz")
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_wall(Plane((-R, 0, 0), (1, 0, 0)), name="left")
    sim.dt = 2e-6 if law == "hertz_mindlin" else 1e-4
    sim.run(steps=2000 if law == "hertz_mindlin" else 200)
    p = sim.get_particles()
    assert np.all(p["x"][:, 1] == 0.0) and np.all(p["v"][:, 1] == 0.0)
    assert np.all(p["w"][:, 0] == 0.0) and np.all(p["w"][:, 2] == 0.0)
    assert np.abs(p["x"][:, [0, 2]] - x[:, [0, 2]]).max() > 0.1 * R
    assert np.abs(p["w"][:, 1]).max() > 0.0
    assert np.all(p["dof"] == dof_mask("y", "xz"))


def test_registered_field_survives_checkpoint_and_storage_order():
    sim = _sim("hertz_mindlin", gravity=(0, 0, 0))
    sim.register_field("temperature", "float64", output=True)
    sim.register_field("temperature", "float64", output=True)  # identical: allowed
    with pytest.raises(InputError, match="registered already"):
        sim.register_field("temperature", "int32")
    ids = sim.add_particles(np.arange(12)[:, None] * np.array([[3 * R, 0, 0]]), R,
                            temperature=np.arange(12) * 10.0, group=np.arange(12) % 3)
    sim.permute_storage(np.random.default_rng(1).permutation(12))
    sim.dt = 1e-6
    sim.run(steps=3)
    p = sim.get_particles()
    assert np.array_equal(p["id"], ids)
    assert np.array_equal(p["temperature"], np.arange(12) * 10.0)
    assert np.array_equal(p["group"], np.arange(12) % 3)
    state = sim.state_dict()
    other = _sim("hertz_mindlin", gravity=(0, 0, 0))
    other.register_field("temperature", "float64", output=True)
    other.load_state(state)
    assert np.array_equal(other.get_particles()["temperature"], np.arange(12) * 10.0)
    with pytest.raises(InputError, match="unknown keyword 'pressure'"):
        sim.add_particles([[1.0, 1.0, 1.0]], R, pressure=1.0)


def test_dt_is_validated_when_set():
    sim = _sim("hertz_mindlin")
    for bad in (0.0, -1e-5, math.inf, math.nan, "abc"):
        with pytest.raises(InputError, match="dt = "):
            sim.dt = bad
    sim.add_particles([[0, 0, R]], R)
    sim.dt = 1e-6
    sim.run(steps=1)
    with pytest.raises(InputError, match="exceeds the stability estimate"):
        sim.dt = 1.0  # re-validated against the law's estimate once running
    assert sim.dt == 1e-6
    sim.dt = 2e-6  # a smaller change is fine mid-run
    sim.run(steps=1)


def test_rigid_wall_takes_the_grains_stiffness_and_its_own_friction():
    """A rigid wall: E* = E/(1 − ν²) of the grain alone, the wall's friction where given."""
    from pdem.materials import Material, MaterialTable, effective_moduli

    glass = Material("glass", density=2500, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.5)
    table = MaterialTable()
    for m in (glass, Material.rigid_wall("steel", friction=0.9), Material.rigid_wall("plain")):
        table.add(m)
    e_star, _ = effective_moduli(table[0], table[1])
    assert e_star == pytest.approx(1e7 / (1 - 0.3**2), rel=1e-15)
    assert table.mixed(0, 1, "friction") == 0.9  # the wall's own, not min(0.5, 0.9)
    assert table.mixed(0, 2, "friction") == 0.5  # not given: the grain's
    assert table.mixed(0, 2, "restitution") == 0.5
    sim = _sim("hertz_mindlin")
    sim.add_material(Material.rigid_wall("steel", friction=0.0))
    with pytest.raises(InputError, match="rigid"):
        sim.add_particles([[0, 0, R]], R, material="steel")
    # a grain dropped on a rigid floor rebounds with the grain's restitution
    sim.add_particles([[0, 0, 2 * R]], R, material="glass", velocities=[(0, 0, -0.5)])
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), material="steel", name="floor")
    sim.gravity = (0, 0, 0)
    sim.dt = 2e-7
    sim.run(steps=20000)
    assert sim.get_particles()["v"][0, 2] == pytest.approx(0.5 * 0.5, rel=0.03)


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_wall_contacts_and_solver_stats_are_public(law):
    sim = _sim(law)
    sim.add_particles([[0, 0, R], [3 * R, 0, R]], R)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.dt = 1e-6 if law == "hertz_mindlin" else 1e-4
    sim.run(steps=5)
    c = sim.wall_contacts()
    assert list(c["id"]) == [0, 1] and np.all(c["wall"] == 0)
    assert np.allclose(c["force"].sum(axis=0), sim.walls["floor"].force, rtol=1e-12)
    if law == "hertz_mindlin":
        assert np.all(c["overlap"] > 0)
        assert sim.solver_stats() == {}
    else:
        st = sim.solver_stats()
        assert st["steps"] == 5 and st["iterations"] >= 1 and st["residual"] >= 0.0


def test_one_gravity_rule_for_decks_and_python():
    """No gravity unless it is given, in decks and in Simulation() alike."""
    from pdem.deck.schema import RunSection

    assert tuple(RunSection().gravity) == (0.0, 0.0, 0.0)
    assert tuple(pdem.Simulation().gravity) == (0.0, 0.0, 0.0)


def test_a_failing_boundary_hook_is_a_plugin_error_naming_it():
    from pdem.errors import PluginError

    class Broken(Boundary):
        def after_step(self, sim):
            raise ZeroDivisionError("oops")

    sim = _sim("hertz_mindlin", gravity=(0, 0, 0))
    sim.add_particles([[0, 0, 0]], R)
    sim.add_boundary(Broken("probe", BoundaryParams(type="broken")))
    sim.dt = 1e-6
    with pytest.raises(PluginError, match=r"boundary 'probe' .*Broken\) failed in after_step at step 1: "
                                          r"ZeroDivisionError: oops"):
        sim.run(steps=2)
