"""Holding and releasing a free body (:class:`pdem.api.RigidBody`): ``hold()``, ``release()``,
``set_velocity()``, and the held state in checkpoints."""

from __future__ import annotations

import math

import numpy as np
import pytest

import pdem
from pdem.api import InputError, RigidBody, shapes

R = 1e-3
G = 9.81
DT = 2e-5


def _sim(law: str = "hertz_mindlin", grain: bool = True) -> pdem.Simulation:
    sim = pdem.Simulation(law=law)
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.3)  # fmt: skip
    sim.gravity = (0.0, 0.0, -G)
    if law == "complementarity":
        sim.set_law("complementarity", solver="apgd")
    if grain:  # a fixed grain far below, so the run has a particle; the body never reaches it
        sim.add_particles(np.array([[0.0, 0.0, -0.5]]), R, motion="fixed")
    sim.dt = DT
    return sim


def _ball(sim: pdem.Simulation, **kw) -> tuple[RigidBody, object]:
    body = RigidBody(mass=1e-3, gravity=(0.0, 0.0, -G), fixed_translation="xy", **kw)
    wall = sim.add_wall(shapes.Sphere((0.0, 0.0, 0.1), 3 * R), name="ball", motion=body)
    return body, wall


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
@pytest.mark.parametrize("active", [True, False], ids=["active", "inactive"])
def test_held_body_stays_then_falls_freely_after_release(law, active):
    sim = _sim(law)
    body, wall = _ball(sim)
    sim.run(steps=10)  # falling
    assert wall.velocity[2] < 0.0 and wall.offset[2] < 0.0
    if not active:
        sim.set_wall_active("ball", False)  # switched off, a free body keeps falling unless held
    body.hold()
    assert body.held and not body.moved_by_load
    assert np.array_equal(body.velocity_now, np.zeros(3))
    z_held = wall.offset.copy()
    sim.run(steps=50)  # gravity pulls; a held body does not move
    assert np.array_equal(wall.offset, z_held)
    assert np.array_equal(wall.velocity, np.zeros(3)) and np.array_equal(body.velocity_now, np.zeros(3))
    body.release()  # from rest
    assert not body.held and body.moved_by_load
    n = 200
    sim.run(steps=n)
    # symplectic Euler from rest: v_n = -g n dt, x_n = -g dt² n (n + 1) / 2 = -g t²/2 - g t dt/2
    drop = -G * DT * DT * n * (n + 1) / 2
    assert wall.offset[2] - z_held[2] == pytest.approx(drop, rel=1e-12, abs=1e-15)
    assert wall.velocity[2] == pytest.approx(-G * n * DT, rel=1e-12)
    t = n * DT
    assert wall.offset[2] - z_held[2] == pytest.approx(-0.5 * G * t * t, rel=2 * DT / t)
    assert np.array_equal(wall.offset[:2], [0.0, 0.0])


def test_released_body_falls_as_the_never_held_one_bitwise():
    """Holding at rest then releasing is a fresh start from rest: the same bits as a body started
    there; a body never held runs exactly as before holding existed."""
    a, b = _sim(), _sim()
    body_a, wall_a = _ball(a)
    body_b, wall_b = _ball(b)
    body_a.hold()
    a.run(steps=30)
    body_a.release()
    b.run(steps=30)
    body_b.set_velocity((0.0, 0.0, 0.0))
    wall_b.set_offset(np.zeros(3))  # back where it was built, at rest: as the held one
    a.run(steps=40)
    b.run(steps=40)
    assert np.array_equal(wall_a.offset, wall_b.offset)
    assert np.array_equal(wall_a.velocity, wall_b.velocity)


def test_set_velocity_and_release_with_velocity():
    sim = _sim()
    body, wall = _ball(sim)
    body.set_velocity((1.0, 2.0, 0.5))  # x, y fixed: dropped
    assert np.array_equal(body.velocity_now, [0.0, 0.0, 0.5])
    sim.run(steps=1)
    assert wall.velocity[2] == 0.5 - G * DT
    body.hold()
    with pytest.raises(InputError, match=r"velocity = .*held.*release\(velocity="):
        body.set_velocity((0.0, 0.0, 1.0))
    body.release(velocity=(0.0, 0.0, 0.25))
    assert np.array_equal(body.velocity_now, [0.0, 0.0, 0.25])
    z0 = wall.offset[2]
    sim.run(steps=1)
    v1 = 0.25 - G * DT
    assert wall.velocity[2] == v1 and wall.offset[2] == z0 + DT * v1
    body.release()  # not held: keeps its velocity
    assert np.array_equal(body.velocity_now, [0.0, 0.0, v1])
    for bad in [(1.0, 2.0), (0.0, math.nan, 0.0), "fast", None]:
        with pytest.raises(InputError, match="velocity = .* must be three finite numbers"):
            body.set_velocity(bad)


def test_rotation_is_held_and_set_too():
    sim = _sim()
    body = RigidBody(mass=1e-3, inertia=1e-9, angular_velocity=(0.0, 0.0, 3.0))
    wall = sim.add_wall(shapes.Sphere((0.0, 0.0, 0.1), 3 * R), name="spinner", motion=body)
    sim.run(steps=2)
    assert wall.omega[2] == 3.0
    body.hold()
    assert np.array_equal(body.angular_velocity_now, np.zeros(3))
    sim.run(steps=2)
    assert np.array_equal(wall.omega, np.zeros(3))
    body.release(angular_velocity=(0.0, 0.0, -1.0))
    sim.run(steps=1)
    assert np.array_equal(wall.omega, [0.0, 0.0, -1.0])
    body.set_velocity((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    assert np.array_equal(body.angular_velocity_now, [1.0, 0.0, 0.0])


def test_held_state_in_checkpoints():
    body = RigidBody(mass=1.0, gravity=(0.0, 0.0, -G))
    assert "held" not in body.state()  # a released body's state is as it always was
    body.hold()
    state = body.state()
    assert bool(state["held"])
    other = RigidBody(mass=1.0, velocity=(0.0, 0.0, 2.0))
    other.restore(state)
    assert other.held and np.array_equal(other.velocity_now, np.zeros(3))
    old = {"velocity": np.array([0.0, 0.0, -1.0]), "angular_velocity": np.zeros(3)}  # no "held" key
    other.restore(old)
    assert not other.held and np.array_equal(other.velocity_now, [0.0, 0.0, -1.0])
    other.restore({})  # nothing saved for it: unchanged
    assert not other.held


def test_held_state_survives_a_simulation_checkpoint():
    sim = _sim()
    body, wall = _ball(sim)
    sim.run(steps=5)
    body.hold()
    sim.run(steps=5)
    state = sim.state_dict()
    assert bool(state["walls/ball/motion/held"])
    sim2 = _sim(grain=False)  # a checkpoint brings the particles
    body2, wall2 = _ball(sim2)
    sim2.load_state(state)
    assert body2.held
    z = wall2.offset.copy()
    sim2.run(steps=10)
    assert np.array_equal(wall2.offset, z)
    # a checkpoint without the key (written before holding existed, or released): released
    old = {k: v for k, v in state.items() if k != "walls/ball/motion/held"}
    sim3 = _sim(grain=False)
    body3, _ = _ball(sim3)
    body3.hold()
    sim3.load_state(old)
    assert not body3.held
