"""Conservation laws of the DEM-P step with friction on (spins, tangential history).

* free cloud of 200 polydisperse spheres (no walls, no gravity): total linear momentum to
  round-off, total angular momentum about the origin (orbital + spin) to round-off as well
  (velocity Verlet conserves it exactly when both lever arms end at the same contact point,
  a_i = (r_i − δ/2) n and a_j = −(r_j − δ/2) n), and the mechanical energy never increases;
* the same cloud in a closed box: ΔP of the particles = −∫ Σ wall forces dt (trapezoidal rule,
  which is what velocity Verlet integrates).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from physics_helpers import (
    E_MOD,
    NU,
    RHO,
    angular_momentum,
    e_star,
    random_spheres,
)

import pdem
from pdem.geometry.shapes import box_planes

N = 200
SIDE = 17e-3
SHIFT = np.array([5e-3, -3e-3, 2e-3])  # the cloud is off the origin: orbital momentum matters


def _cloud(seed: int = 1):
    rng = np.random.default_rng(seed)
    x, r = random_spheres(rng, N, [-SIDE / 2] * 3, [SIDE / 2] * 3, 0.5e-3, 1.5e-3)
    v = rng.normal(0.0, 0.5, (N, 3)) + np.array([0.2, -0.1, 0.3])
    w = rng.normal(0.0, 300.0, (N, 3))
    return x + SHIFT, r, v, w


def _sim(x, r, v, w, walls: bool) -> pdem.Simulation:
    sim = pdem.Simulation()
    sim.add_material("glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU, restitution=0.5,
                     friction=0.5, rolling_friction=0.0)
    sim.add_particles(x, r, velocities=v, angular_velocities=w)
    if walls:
        for plane in box_planes(SHIFT - SIDE / 2, SHIFT + SIDE / 2):
            sim.add_wall(plane)
    return sim


def _momentum(p):
    return np.sum(p["mass"][:, None] * p["v"], axis=0)


def _hertz_energy(sim: pdem.Simulation) -> float:
    """Elastic energy of the normal springs, (8/15) E* sqrt(R*) δ^{5/2} per contact."""
    p = sim.get_particles()
    c = sim.contacts()
    ri, rj = p["r"][c["id_i"]], p["r"][c["id_j"]]
    r_eff = ri * rj / (ri + rj)
    return math.fsum(8.0 / 15.0 * e_star() * np.sqrt(r_eff) * c["overlap"] ** 2.5)


def test_free_cloud_conserves_momenta_and_dissipates():
    x, r, v, w = _cloud()
    sim = _sim(x, r, v, w, walls=False)
    p0 = sim.get_particles()
    assert np.array_equal(p0["id"], np.arange(N))
    mom0 = _momentum(p0)
    ang0 = angular_momentum(p0)
    e0 = sum(sim.kinetic_energy())
    # scales for relative errors (the totals themselves could be small by accident)
    mom_scale = math.fsum(p0["mass"] * np.linalg.norm(p0["v"], axis=1))
    ang_scale = math.fsum(p0["mass"] * np.linalg.norm(np.cross(p0["x"], p0["v"]), axis=1)) + math.fsum(
        0.4 * p0["mass"] * p0["r"] ** 2 * np.linalg.norm(p0["w"], axis=1))
    energies = []
    pairs = set()
    worst = {"mom": 0.0, "ang": 0.0}

    def sample(s):
        p = s.get_particles()
        worst["mom"] = max(worst["mom"], float(np.linalg.norm(_momentum(p) - mom0)) / mom_scale)
        worst["ang"] = max(worst["ang"], float(np.linalg.norm(angular_momentum(p) - ang0)) / ang_scale)
        energies.append(sum(s.kinetic_energy()) + _hertz_energy(s))
        c = s.contacts()
        pairs.update(zip(c["id_i"].tolist(), c["id_j"].tolist(), strict=True))

    sim.run(steps=3000, callback=sample, every=5)
    energies = np.array(energies)
    print(f"momentum drift {worst['mom']:.2e}, angular momentum drift {worst['ang']:.2e}, "
          f"{len(pairs)} distinct contacts, E_end/E_0 = {energies[-1] / e0:.4f}, "
          f"largest rise between samples {np.max(np.diff(energies)) / e0:.2e} E_0")
    # the scene really collides and spins
    assert len(pairs) > 100
    assert abs(sum(sim.kinetic_energy()[1:])) > 0
    assert worst["mom"] < 1e-12
    assert worst["ang"] < 1e-12
    # dissipative contacts: the mechanical energy (kinetic + Hertz springs) never exceeds the start
    # and decreases overall; between samples it may rise only by what the tangential springs release
    assert np.all(energies <= e0 * (1 + 1e-9))
    assert energies[-1] < 0.9 * e0
    assert np.max(np.diff(energies)) < 1e-3 * e0


def test_closed_box_momentum_balance():
    x, r, v, w = _cloud(seed=2)
    sim = _sim(x, r, v, w, walls=True)
    sim.run(steps=0)  # prepare: wall loads at t = 0
    walls = list(sim.walls.values())
    assert len(walls) == 6

    def wall_total():
        return np.sum([wl.force for wl in walls], axis=0)

    mom0 = _momentum(sim.get_particles())
    state = {"prev": wall_total(), "impulse": np.zeros(3), "abs": 0.0, "hits": 0}
    dt = sim.dt

    def accumulate(s):
        now = wall_total()
        state["impulse"] += 0.5 * dt * (state["prev"] + now)
        state["abs"] += dt * sum(float(np.linalg.norm(wl.force)) for wl in walls)
        state["hits"] += sum(wl.n_contacts for wl in walls)
        state["prev"] = now

    sim.run(steps=4000, callback=accumulate)
    dmom = _momentum(sim.get_particles()) - mom0
    err = float(np.linalg.norm(dmom + state["impulse"])) / float(np.linalg.norm(state["impulse"]))
    print(f"wall impulse {state['impulse']}, |ΔP + J|/|J| = {err:.2e}, wall contact-steps {state['hits']}")
    assert state["hits"] > 1000
    assert float(np.linalg.norm(state["impulse"])) > 0.1 * float(np.linalg.norm(mom0))
    assert err < 1e-6
    # all particles stayed in the box
    p = sim.get_particles()
    assert np.all(p["x"] > SHIFT - SIDE / 2) and np.all(p["x"] < SHIFT + SIDE / 2)


@pytest.mark.parametrize("walls", [False, True])
def test_momentum_unchanged_without_contacts(walls):
    """Control: a single sphere away from everything keeps its momentum bit for bit."""
    sim = _sim(np.array([SHIFT]), 1e-3, np.array([[0.1, 0.2, -0.3]]), np.array([[1.0, 2.0, 3.0]]), walls)
    p0 = sim.get_particles()
    sim.run(steps=100)
    p = sim.get_particles()
    assert np.array_equal(p["v"], p0["v"]) and np.array_equal(p["w"], p0["w"])
