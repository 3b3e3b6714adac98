"""DEM-C's neighbour list follows the grains' travel: while the fastest grain travels more than half
the skin per step (the next step must rebuild anyway), the list is built without skin and without
headroom on the envelope, so it holds only the pairs within the step's collision envelope. Results
must not depend on that: the reference is the same scene with the older, wider list (1.25 × the
envelope plus the skin at every rebuild), bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
from physics_helpers import E_MOD, NU, RHO

import pdem
from pdem.geometry import shapes
from pdem.geometry.walls import RigidBody

R = 0.5e-3
SIDE = 5.5e-3


def _scene() -> pdem.Simulation:
    """150 beads thrown down at ~0.5 m/s into a box (a sloping floor, a side that is a rigid body
    moved by its load): fast while they land, then settling."""
    rng = np.random.default_rng(5)
    g = np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(6), indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * 1.08 * R * 2 + rng.normal(0.0, 0.03 * R, g.shape)
    x[:, 2] += 1.0e-3
    r = R * rng.uniform(0.9, 1.0, len(x))
    v = rng.normal(0.0, 0.05, x.shape)
    v[:, 2] -= 0.5
    sim = pdem.Simulation(law="complementarity")
    sim.add_material(
        "glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU, restitution=0.5, friction=0.4
    )
    sim.add_particles(x, r, velocities=v)
    sim.add_wall(shapes.Plane((0, 0, 0), (1, 0, 0)))
    sim.add_wall(shapes.Plane((0, 0, 0), (0, 1, 0)))
    sim.add_wall(shapes.Plane((0, SIDE, 0), (0, -1, 0)))
    sim.add_wall(
        shapes.Plane((SIDE, 0, 0), (-1, 0, 0)),
        name="side",
        motion=RigidBody(mass=50.0, fixed_translation="yz"),
    )
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.1, 0.0, 1.0)), name="floor")
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 1e-4
    return sim


def _run(wide: bool, monkeypatch):
    calls = []
    original = pdem.Simulation.set_list_reach

    def recording(self, envelope, force=True, skin=None):
        calls.append((force, skin, self.skin))
        if wide and not force:  # the older narrowing: 1.25 × the envelope (or more), with the skin
            return original(self, 1.25 * envelope, force=False, skin=self.skin)
        return original(self, envelope, force=force, skin=skin)

    monkeypatch.setattr(pdem.Simulation, "set_list_reach", recording)
    sim = _scene()
    states, pairs = [], []
    for _ in range(6):
        sim.run(steps=50)
        d = sim.get_particles()
        states.append((d["x"], d["v"], d["w"], sim.walls["floor"].force, sim.walls["side"].force))
        pairs.append(len(sim.contact_store.pi))
    monkeypatch.undo()
    return sim, states, pairs, calls


@pytest.mark.integration
def test_list_without_skin_while_grains_are_fast_gives_the_same_bits(monkeypatch):
    sim, got, pairs, calls = _run(False, monkeypatch)
    ref, want, ref_pairs, _ = _run(True, monkeypatch)
    narrowed = [c for c in calls if not c[0]]
    assert any(skin == 0.0 for _f, skin, _s in narrowed), "the scene must have fast grains"
    assert any(skin == base > 0.0 for _f, skin, base in narrowed), "and settle to slow ones"
    assert min(b / a for a, b in zip(ref_pairs, pairs, strict=True)) < 0.9  # a shorter list
    for (x1, v1, w1, f1, s1), (x2, v2, w2, f2, s2) in zip(got, want, strict=True):
        assert np.array_equal(x1, x2) and np.array_equal(v1, v2) and np.array_equal(w1, w2)
        assert np.array_equal(f1, f2) and np.array_equal(s1, s2)
    assert sim.integrator.n_resolves == ref.integrator.n_resolves
