"""DEM-C without artificial lift-off: sliding contacts stay closed.

The relaxed cone complementarity problem of Anitescu–Tasora (physics reference §3) gives a sliding
contact a separating normal velocity μ|u_t|: a sphere sliding at 5 m/s on a floor with μ = 0.5 left
it at 1.33 m/s after one step. The corrected cone (``cone = "corrected"``, the default) solves
Coulomb's law itself. References are the closed forms of rigid-body mechanics with Coulomb friction
(a block stops after v0²/(2 μ g), a sphere rolls from 2 v0/(7 μ g) on); each case is also run with
``cone = "relaxed"`` and shown to lift off, so that the tests can fail."""

from __future__ import annotations

import numpy as np
import pytest

import pdem
from pdem.geometry import shapes
from pdem.geometry.walls import ConstantVelocity, RigidBody

G = 9.81
R = 1e-3
MU = 0.5
V0 = 5.0
SOLVERS = ["jacobi", "apgd", "gauss_seidel"]


def make_sim(solver, dt, cone="corrected", mu=MU, **params):
    params = {"tolerance": 1e-9, "max_iterations": 500} | params
    sim = pdem.Simulation(law="complementarity", solver=solver, cone=cone, **params)
    sim.add_material(
        "glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5, friction=mu
    )
    sim.gravity = (0.0, 0.0, -G)
    sim.dt = dt
    return sim


def sphere_on_floor(solver, dt, cone="corrected", v0=V0, locked=True, floor_motion=None):
    sim = make_sim(solver, dt, cone)
    sim.add_particles([[0.0, 0.0, R]], R, material="glass", velocities=[[v0, 0.0, 0.0]])
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor",
                 motion=floor_motion)  # fmt: skip
    sim.prepare()
    if locked:  # infinite moment of inertia: a sphere that cannot turn is a sliding block
        sim.particles.inv_i[:] = 0.0
    return sim


def heights(sim, steps, until=None):
    """Run up to ``steps`` steps (or until ``until(sim)``); the sphere's height after each."""
    z = [sim.particles.x[0, 2]]
    for _ in range(steps):
        sim.step()
        z.append(sim.particles.x[0, 2])
        if until is not None and until(sim):
            break
    return np.array(z)


# ----------------------------------------------------------------------------------- a sliding block
@pytest.mark.parametrize("dt", [1e-3, pytest.param(1e-4, marks=pytest.mark.integration)])
@pytest.mark.parametrize("solver", SOLVERS)
def test_sliding_block_stays_on_the_floor_and_stops_after_v2_over_2_mu_g(solver, dt):
    """A non-rotating sphere launched at 5 m/s along a floor (μ = 0.5): its height changes by less
    than 1e-6 r per step, it stops after v0²/(2 μ g) = 2.548 m (within 1 %; the semi-implicit
    step's own value v0²/(2 μ g) − v0 h/2 within one step's travel) at t = v0/(μ g)."""
    sim = sphere_on_floor(solver, dt)
    t_stop = V0 / (MU * G)
    z = heights(sim, int(1.1 * t_stop / dt), until=lambda s: s.particles.v[0, 0] <= 1e-9)
    assert np.max(np.abs(np.diff(z))) < 1e-6 * R
    assert np.max(np.abs(z - R)) < 1e-6 * R
    assert abs(sim.particles.v[0, 0]) <= 1e-9
    distance = sim.particles.x[0, 0]
    assert distance == pytest.approx(V0**2 / (2 * MU * G), rel=0.01)
    assert abs(distance - (V0**2 / (2 * MU * G) - V0 * dt / 2)) < V0 * dt
    assert sim.time == pytest.approx(t_stop, abs=1.5 * dt)
    assert sim.integrator.n_unconverged == 0


@pytest.mark.parametrize("dt", [1e-3, 1e-4])
@pytest.mark.parametrize("solver", SOLVERS)
def test_relaxed_cone_lifts_the_sliding_block_off(solver, dt):
    """The old formulation, kept as ``cone = "relaxed"``: after one step the block moves up at
    μ |u_t| (the cone relaxation's separation velocity), far more than 1e-6 r per step."""
    sim = sphere_on_floor(solver, dt, cone="relaxed")
    z = heights(sim, 1)
    vx, vz = sim.particles.v[0, 0], sim.particles.v[0, 2]
    assert vz == pytest.approx(MU * vx, rel=1e-6)
    assert z[1] - z[0] == pytest.approx(MU * vx * dt, rel=1e-6)
    assert z[1] - z[0] > 0.1 * R


# ----------------------------------------------------------------------------------- a free sphere
@pytest.mark.parametrize("dt", [1e-3, 1e-4])
@pytest.mark.parametrize("cone", ["corrected", "relaxed"])
def test_free_sphere_slides_then_rolls_on_the_floor(cone, dt):
    """A sphere launched at 5 m/s without spin slides until v = 5/7 v0 at t = 2 v0/(7 μ g), after
    12 v0²/(49 μ g), then rolls without slip; it stays on the floor (< 1e-6 r per step). The relaxed
    cone instead lifts it off at μ |u_t| = 1.33 m/s in the first step (h = 1e-3 s)."""
    sim = sphere_on_floor("jacobi", dt, cone=cone, locked=False)
    t_roll = 2 * V0 / (7 * MU * G)
    if cone == "relaxed":
        z = heights(sim, 1)
        # one step of the relaxed problem, sliding: v_z = μ u_t with u_t = v0 − 3.5 μ γ_n/m (the
        # friction impulse slows the centre and spins the sphere, I = 0.4 m r²) and γ_n/m = v_z + g h
        vz = MU * (V0 - 3.5 * MU * G * dt) / (1 + 3.5 * MU**2)
        assert (z[1] - z[0]) / dt == pytest.approx(vz, rel=1e-6)
        assert sim.particles.v[0, 2] == pytest.approx(vz, rel=1e-6)  # 1.33 m/s
        assert z[1] - z[0] > 0.1 * R
        return
    z = heights(sim, int(round(1.2 * t_roll / dt)))
    assert np.max(np.abs(np.diff(z))) < 1e-6 * R
    assert np.max(np.abs(z - R)) < 1e-6 * R
    p = sim.particles
    assert p.v[0, 0] == pytest.approx(5 / 7 * V0, rel=1e-3)
    assert p.w[0, 1] * R == pytest.approx(p.v[0, 0], rel=1e-6)  # rolling without slip
    x_roll = 12 * V0**2 / (49 * MU * G)
    assert p.x[0, 0] == pytest.approx(x_roll + 5 / 7 * V0 * (sim.time - t_roll), rel=0.01)
    assert sim.integrator.n_unconverged == 0


# ----------------------------------------------------------------------------------- walls
@pytest.mark.integration
@pytest.mark.parametrize("solver", SOLVERS)
def test_block_sliding_under_a_rigid_body_lid(solver):
    """A block (non-rotating sphere) slides at 2 m/s between a fixed floor and a lid that is a free
    rigid body (RigidBody, solved with the grains; it moves along z only) pressed down by F = 3 m g.
    Coulomb: the lid stays at 2 r, the block on the floor, and friction μ (m g + F) + μ F decelerates
    the block to rest after v0² / (2 a). The relaxed cone lifts both contacts: the lid rises."""
    v0, dt = 2.0, 1e-4
    results = {}
    for cone in ("corrected", "relaxed"):
        sim = make_sim(solver, dt, cone)
        sim.add_particles([[0.0, 0.0, R]], R, material="glass", velocities=[[v0, 0.0, 0.0]])
        sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
        sim.prepare()
        m = float(sim.particles.mass[0])
        sim.particles.inv_i[:] = 0.0
        lid = RigidBody(mass=2 * m, force=(0.0, 0.0, -3 * m * G), fixed_translation="xy")
        sim.add_wall(shapes.Plane((0.0, 0.0, 2 * R), (0.0, 0.0, -1.0)), material="glass", name="lid",
                     motion=lid)  # fmt: skip
        a = MU * (m * G + 3 * m * G) / m + MU * 3 * m * G / m
        steps = 60 if cone == "relaxed" else int(1.1 * v0 / a / dt)
        z = heights(sim, steps, until=lambda s: s.particles.v[0, 0] <= 1e-9)
        lid_z = sim.walls["lid"].reference_point[2]
        results[cone] = (z, lid_z, sim)
        if cone == "corrected":
            assert np.max(np.abs(z - R)) < 1e-6 * R
            assert abs(lid_z - 2 * R) < 1e-6 * R
            assert abs(sim.particles.v[0, 0]) <= 1e-9
            assert sim.particles.x[0, 0] == pytest.approx(v0**2 / (2 * a), rel=0.01)
            # the lid's load is F (it is at rest), the floor's F + m g
            assert -sim.walls["lid"].force[2] == pytest.approx(-3 * m * G, rel=1e-4)
            assert -sim.walls["floor"].force[2] == pytest.approx(4 * m * G, rel=1e-4)
    _, lid_relaxed, _ = results["relaxed"]
    assert lid_relaxed - 2 * R > 0.1 * R


@pytest.mark.integration
@pytest.mark.parametrize("solver", SOLVERS)
def test_block_on_a_moving_floor_is_carried_without_lifting(solver):
    """A conveyor: the floor moves along x at 1 m/s under a block at rest. The block slides on it,
    accelerated by μ g, until it moves with the floor at t = v/(μ g), having moved v²/(2 μ g); it
    stays on the floor. With the relaxed cone it jumps off the moving floor."""
    vw, dt = 1.0, 1e-4
    for cone in ("corrected", "relaxed"):
        sim = sphere_on_floor(solver, dt, cone=cone, v0=0.0, floor_motion=ConstantVelocity((vw, 0.0, 0.0)))
        t_catch = vw / (MU * G)
        z = heights(sim, 30 if cone == "relaxed" else int(round(1.5 * t_catch / dt)))
        if cone == "relaxed":
            assert z[-1] - R > 0.1 * R
            continue
        assert np.max(np.abs(z - R)) < 1e-6 * R
        p = sim.particles
        assert p.v[0, 0] == pytest.approx(vw, abs=1e-9)
        x_catch = vw**2 / (2 * MU * G)
        assert p.x[0, 0] == pytest.approx(x_catch + vw * (sim.time - t_catch), rel=0.01)


# ----------------------------------------------------------------------------------- a sheared layer
def dragged_layer(law, cone=None, solver=None, v_s=0.5, mu_plate=0.2, load=0.05):
    """A layer of 4 free grains seated in the pockets of a 3 × 3 layer of touching grains that moves
    along x at ``v_s`` (prescribed), under a plate that is a free rigid body (along z only) pressed
    down by ``load`` [N] and held in x: the layer is carried along and slides under the plate
    (μ_plate · 1.707 < μ = 0.5, so the grains neither climb out of their pockets nor roll out)."""
    kw = {} if law != "complementarity" else {"solver": solver, "cone": cone, "max_iterations": 5000,
                                               "tolerance": 1e-8 if solver == "apgd" else 1e-9}  # fmt: skip
    sim = pdem.Simulation(law=law, **kw)
    for name, mu in (("glass", MU), ("plate", mu_plate)):
        sim.add_material(name, density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5,
                         friction=mu)  # fmt: skip
    sim.gravity = (0.0, 0.0, -G)
    g = np.stack(np.meshgrid(np.arange(3), np.arange(3), indexing="ij"), -1).reshape(-1, 2)
    sim.add_particles(np.column_stack([g * 2 * R, np.full(9, R)]), R, material="glass", motion="prescribed",
                      velocities=np.tile([v_s, 0.0, 0.0], (9, 1)))  # fmt: skip
    g = np.stack(np.meshgrid(np.arange(2), np.arange(2), indexing="ij"), -1).reshape(-1, 2)
    z = R + np.sqrt(2.0) * R  # seated on four grains
    sim.add_particles(np.column_stack([(g + 0.5) * 2 * R, np.full(4, z)]), R, material="glass",
                      velocities=np.tile([v_s, 0.0, 0.0], (4, 1)))  # fmt: skip
    mass = 2500.0 * 4.0 / 3.0 * np.pi * R**3
    plate = RigidBody(mass=5 * mass, force=(0.0, 0.0, -load), fixed_translation="xy")
    sim.add_wall(shapes.Plane((0.0, 0.0, z + R), (0.0, 0.0, -1.0)), material="plate", name="plate",
                 motion=plate)  # fmt: skip
    if law == "complementarity":
        sim.dt = 2e-4
    return sim


def plate_rise(sim, duration):
    plate = sim.walls["plate"]
    z0 = plate.reference_point[2]
    rise = []
    while sim.time < duration - 1e-12:
        sim.step()
        rise.append(plate.reference_point[2] - z0)
    return np.array(rise)


@pytest.mark.parametrize("solver", SOLVERS)
def test_layer_sliding_under_a_loaded_plate_does_not_lift_it(solver):
    """Grains carried along at 0.5 m/s slide under a plate that carries a constant load (a free rigid
    body, solved with the grains). Coulomb: the plate stays where it is (< 1e-6 r), the layer moves
    with its carrier, the plate's load is the applied one and its friction μ_plate × load. The relaxed
    cone holds every sliding contact open by μ_plate |u_t| h (0.02 r at h = 2e-4 s), the gap the
    confined lift-off leaves; DEM-P (Hertz) only lets the plate settle into the grains."""
    v_s, mu_p, load, duration = 0.5, 0.2, 0.05, 0.012
    sim = dragged_layer("complementarity", "corrected", solver, v_s, mu_p, load)
    rise = plate_rise(sim, duration)
    assert np.max(np.abs(rise)) < 1e-6 * R
    p = sim.get_particles()
    assert np.allclose(p["v"][:, 0], v_s, atol=1e-6)
    assert np.allclose(p["v"][:, 1:], 0.0, atol=1e-6)
    assert sim.walls["plate"].force[2] == pytest.approx(load, rel=1e-5)
    assert sim.walls["plate"].force[0] == pytest.approx(mu_p * load, rel=1e-5)
    relaxed = dragged_layer("complementarity", "relaxed", solver, v_s, mu_p, load)
    rise_relaxed = plate_rise(relaxed, duration)
    assert rise_relaxed[-1] == pytest.approx(mu_p * v_s * relaxed.dt, rel=1e-3)
    assert rise_relaxed[-1] > 1e4 * np.max(np.abs(rise))
    if solver == "jacobi":
        dem_p = dragged_layer("hertz_mindlin", v_s=v_s, mu_plate=mu_p, load=load)
        assert np.max(plate_rise(dem_p, duration)) <= 0.0
