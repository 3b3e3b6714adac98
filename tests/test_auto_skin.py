"""The automatic skin (no run.skin): chosen at every rebuild from the fastest grain, within 0.1-0.4
of the mean diameter. Checked against the same run with a fixed skin (results must not depend on
the skin, only the rebuild count) and against its own rule's bounds."""

from __future__ import annotations

import numpy as np

import pdem
from pdem.geometry.shapes import Plane
from pdem.simulation import SKIN_MAX, SKIN_MIN, SKIN_STEPS


def _drop(skin):
    """40 grains released 2 cm above a floor, then landing: fast, then at rest."""
    rng = np.random.default_rng(4)
    sim = pdem.Simulation()
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.4)  # fmt: skip
    g = np.stack(np.meshgrid(np.arange(4), np.arange(2), np.arange(5), indexing="ij"), -1).reshape(-1, 3)
    x = g * 2.2e-3 + [1e-3, 1e-3, 0.02] + 1e-5 * rng.standard_normal(g.shape)
    sim.add_particles(x, 1e-3 * rng.uniform(0.9, 1.0, len(x)))
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 2e-5
    sim.skin = skin
    return sim


def test_auto_skin_follows_the_fastest_grain_and_changes_no_result():
    auto, fixed = _drop(None), _drop(1.9e-4)
    skins = []
    for _ in range(60):
        auto.run(steps=100)
        fixed.run(steps=100)
        skins.append(auto.skin)
    d = 2.0 * float(np.mean(auto.get_particles()["r"]))
    pa, pf = auto.get_particles(), fixed.get_particles()
    for key in ("x", "v", "w"):
        assert np.array_equal(pa[key], pf[key]), key  # bit for bit
    assert auto.n_rebuilds < fixed.n_rebuilds
    lo, hi = SKIN_MIN * d, SKIN_MAX * d
    assert all(lo * (1 - 1e-12) <= s <= hi * (1 + 1e-12) for s in skins)
    assert max(skins) > 2 * lo  # falling at ~0.6 m/s: 2 × 25 × v × dt ≈ 0.6 mm
    # settled on the floor (run on until every grain is slower than the floor value allows for)
    for _ in range(100):
        auto.run(steps=100)
        if float(np.abs(auto.get_particles()["v"]).max()) < lo / (2 * SKIN_STEPS * auto.dt) / 2:
            break
    auto.request_rebuild()
    auto.run(steps=1)
    assert auto.skin == lo


def test_auto_skin_stays_automatic_after_particles_are_added():
    """A second preparation (grains added after a run) chooses the skin again, and keeps choosing it
    from the fastest grain; a skin set by hand in between stays as set."""
    sim = _drop(None)
    sim.run(steps=10)  # at rest: the smallest skin
    d = 2.0 * float(np.mean(sim.get_particles()["r"]))
    assert sim.skin == SKIN_MIN * d
    sim.add_particles([[0.02, 0.02, 0.03]], [1e-3], velocities=[[0.0, 0.0, -2.0]])  # a fast newcomer
    sim.run(steps=10)
    assert sim.skin > 2 * SKIN_MIN * d  # followed the new grain (2 × 25 × 2 m/s × dt, capped)
    given = 1.5e-4
    sim.skin = given
    sim.add_particles([[0.03, 0.03, 0.03]], [1e-3])
    sim.run(steps=10)
    assert sim.skin == given
