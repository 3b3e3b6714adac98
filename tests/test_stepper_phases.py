"""The DEM-C stepper's records and phases: the per-step records stay bounded when nobody drains them,
are handed over complete through the integrator contract (``Integrator.drain_records``) when someone
does, and the phased step keeps the method's invariants (resting contact without penetration,
momentum of a free collision)."""

from __future__ import annotations

import numpy as np
import pytest
from decks import TINY_LATTICE

import pdem
from pdem.complementarity.method import Stepper
from pdem.geometry import shapes
from pdem.integrate.base import Integrator

G = 9.81
R = 1e-3
SOLVERS = ("jacobi", "apgd", "gauss_seidel")


def make_sim(solver="jacobi", gravity=(0.0, 0.0, -G), dt=1e-4, mu=0.5, e=0.5, **params):
    sim = pdem.Simulation(law="complementarity", solver=solver, **params)
    sim.add_material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=e,
                     friction=mu)  # fmt: skip
    sim.gravity = gravity
    sim.dt = dt
    return sim


def resting_sphere(solver="jacobi", **params):
    sim = make_sim(solver, **params)
    sim.add_particles([[0.0, 0.0, R]], R, material="glass")
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
    return sim


# ----------------------------------------------------------------------------------- records
def test_records_stay_bounded_without_a_drain():
    """``Simulation.run`` with nobody draining: the stepper keeps only its last ``log_keep`` records
    (the list is trimmed in blocks: never above 5/4 of them), the newest last, one per step."""
    sim = resting_sphere()
    sim.prepare()
    st = sim.integrator
    st.log_keep = 40
    lengths = []
    for _ in range(30):
        sim.run(steps=20)
        lengths.append(len(st.log))
    assert max(lengths) <= 40 + 40 // 4
    assert min(lengths[3:]) >= 40
    steps = [rec[0] for rec in st.log]
    assert steps == list(range(sim.step_count - len(steps) + 1, sim.step_count + 1))
    assert st.log[-1][1:] == (st.last_iterations, st.last_residual, st.last_contacts)
    assert st.n_steps == 600  # the counters keep the whole run


def test_records_are_bounded_by_default():
    """The default bound holds over a run longer than it (one sphere resting on a floor)."""
    sim = resting_sphere()
    sim.prepare()
    st = sim.integrator
    keep = Stepper.log_keep
    sim.run(steps=keep + keep // 4 + 50)
    assert keep <= len(st.log) <= keep + keep // 4
    assert st.log[-1][0] == sim.step_count


def test_drained_records_are_complete_and_handed_over_once():
    """From the first ``drain_records`` on, every step's record is kept until the next drain, however
    many steps that is (the deck runner drains at its series rows), and each is handed over once."""
    sim = resting_sphere()
    sim.prepare()
    st = sim.integrator
    st.log_keep = 5
    sim.run(steps=12)
    first = st.drain_records()
    assert [rec[0] for rec in first] == list(range(13 - len(first), 13))  # the undrained run's last
    assert 5 <= len(first) <= 6
    assert st.log == []
    sim.run(steps=23)
    got = st.drain_records()
    assert [rec[0] for rec in got] == list(range(13, 36))
    assert all(it >= 1 and res >= 0.0 and nc == 1 for _, it, res, nc in got)
    assert st.drain_records() == []


def test_an_explicit_method_has_no_records():
    """The contract's default: velocity Verlet keeps no records and reports no solver statistics
    (the deck runner then writes no solver columns)."""
    sim = pdem.Simulation()
    sim.add_material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.5)  # fmt: skip
    sim.add_particles([[0.0, 0.0, 0.0]], R, material="glass")
    sim.run(steps=3)
    assert sim.integrator.drain_records() == []
    assert sim.integrator.stats() == {}
    assert Integrator(sim).drain_records() == []


def test_the_runner_drains_every_step_through_the_contract(tmp_path, monkeypatch):
    """A deck run writes every step's record to solver_<stage>.csv even when its series cadence is
    longer than the undrained bound: the runner drains from its first series row on."""
    from pdem.cli import main
    from pdem.io.series import read_series

    monkeypatch.setattr(Stepper, "log_keep", 3)
    deck = tmp_path / "lattice.toml"
    deck.write_text(TINY_LATTICE.replace("steps = 20", "steps = 30"))
    out = tmp_path / "out"
    sets = ["contact.law=complementarity", "run.dt=1e-4", "output.series_every_steps=11",
            "output.formats=[]"]  # fmt: skip
    args = [str(deck), "--output", str(out), "--quiet"]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 0
    log = read_series(out / "solver_drop.csv")
    assert list(log["step"]) == list(range(1, 31))
    series = read_series(out / "series_drop.csv")
    assert list(series["step"]) == [0, 11, 22, 30]
    assert series["solver_iterations"][-1] == log["iterations"][-1]


def test_jacobi_bound_reads_the_last_problem_after_a_drain():
    """The Jacobi bound diagnoses the last step's problem whether or not its record was drained."""
    sim = make_sim("jacobi", tolerance=1e-8, max_iterations=2000)
    x = [[0.0, 0.0, R], [0.0, 0.0, 3 * R], [2.0 * R, 0.0, R]]
    sim.add_particles(x, R, material="glass")
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
    sim.run(steps=5)
    st = sim.integrator
    before = st.jacobi_bound(active=False)
    assert before > 0.0
    st.drain_records()
    assert st.jacobi_bound(active=False) == before


# ----------------------------------------------------------------------------------- invariants
@pytest.mark.parametrize("solver", SOLVERS)
def test_a_resting_column_keeps_zero_penetration(solver):
    """Three spheres stacked on a floor, at rest: through every phase of the step (list, assembly,
    solve, impulses, advance) the column stays put, without penetration, and the floor carries its
    weight."""
    relaxation = 0.3 if solver == "jacobi" else 1.0
    sim = make_sim(solver, tolerance=1e-10, max_iterations=5000, relaxation=relaxation)
    z0 = np.array([R, 3 * R, 5 * R])
    sim.add_particles([[0.0, 0.0, z] for z in z0], R, material="glass")
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
    sim.run(steps=50)
    p = sim.get_particles()
    z = p["x"][:, 2]
    gaps = np.concatenate([[z[0] - R], np.diff(z) - 2 * R])
    assert np.all(np.abs(gaps) < 1e-6 * R), gaps
    assert np.max(np.abs(p["v"])) < 1e-6
    weight = float(np.sum(p["mass"])) * G
    assert -sim.walls["floor"].force[2] == pytest.approx(weight, rel=1e-5)  # the load on the wall: down


@pytest.mark.parametrize("solver", SOLVERS)
def test_a_free_oblique_collision_conserves_momentum(solver):
    """Two spheres collide off-axis without gravity, with friction and restitution: the contact
    impulses are equal and opposite, so the total momentum after the collision is the one before
    (to rounding), and the spheres part."""
    sim = make_sim(solver, gravity=(0.0, 0.0, 0.0), dt=2e-5, tolerance=1e-12, max_iterations=500, mu=0.3,
                   e=0.8)  # fmt: skip
    v = np.array([[1.0, 0.2, 0.0], [-0.5, 0.0, 0.1]])
    sim.add_particles([[-1.05 * R, 0.3 * R, 0.0], [1.05 * R, 0.0, 0.0]], [R, 0.8 * R], material="glass",
                      velocities=v)  # fmt: skip
    before = sim.get_particles()
    p0 = np.sum(before["mass"][:, None] * before["v"], axis=0)
    sim.run(steps=200)
    after = sim.get_particles()
    p1 = np.sum(after["mass"][:, None] * after["v"], axis=0)
    scale = float(np.sum(before["mass"] * np.linalg.norm(before["v"], axis=1)))
    np.testing.assert_allclose(p1, p0, rtol=0.0, atol=1e-12 * scale)
    assert np.any(np.abs(after["v"] - before["v"]) > 0.1)  # they did collide
    assert sim.integrator.summary()["unconverged_steps"] == 0
    d = np.linalg.norm(after["x"][1] - after["x"][0])
    assert d > 1.8 * R  # and parted
