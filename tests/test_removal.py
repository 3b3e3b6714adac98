"""Removed particles (outflows) leave without a neighbour-list rebuild, bit for bit as with one.

``Simulation.remove_particles`` parks the removed rows far away and sets their wall candidates
aside until the next rebuild compacts them (it used to force a rebuild at the next step, which made
rebuilds most of a hopper's DEM-P run). The reference here is that old behaviour: the same scene
with a rebuild forced after every removal must give the same bits, with many more rebuilds.
"""

from __future__ import annotations

import numpy as np
import pytest
from physics_helpers import E_MOD, NU, RHO

import pdem
from pdem.api import REMOVED
from pdem.boundaries.builtin import OutflowBoundary, OutflowParams
from pdem.geometry import shapes
from pdem.geometry.walls import RigidBody
from pdem.state.removal import Removals

R = 0.5e-3
SIDE = 5.5e-3


def _beads(law: str, seed: int) -> pdem.Simulation:
    """A jittered column of 150 beads, moving a little."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(6), indexing="ij"), -1).reshape(-1, 3)
    x = (g + 0.5) * 1.08 * R * 2 + rng.normal(0.0, 0.03 * R, g.shape)
    x[:, 2] += 1.5e-3
    r = R * rng.uniform(0.9, 1.0, len(x))
    sim = pdem.Simulation(law=law)
    sim.add_material(
        "glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU, restitution=0.5, friction=0.4
    )
    sim.add_particles(x, r, velocities=rng.normal(0.0, 0.05, x.shape))
    return sim


def _sink_and_gravity(sim: pdem.Simulation, law: str) -> pdem.Simulation:
    """An outflow plane 1.2 mm above the floor takes the beads as they fall and settle onto it."""
    sink = OutflowParams(type="outflow", point=(0.0, 0.0, 1.2e-3), normal=(0.0, 0.0, 1.0))
    sim.add_boundary(OutflowBoundary("sink", sink))
    sim.gravity = (0.0, 0.0, -9.81)
    if law == "complementarity":
        sim.dt = 2e-5
    return sim


def _scene(law: str, floor: str, seed: int = 3) -> pdem.Simulation:
    """The beads in a box with a plane or mesh floor, above an outflow plane: they leave a few at a
    time."""
    sim = _beads(law, seed)
    sim.add_wall(shapes.Plane((0, 0, 0), (1, 0, 0)))
    sim.add_wall(shapes.Plane((0, 0, 0), (0, 1, 0)))
    sim.add_wall(shapes.Plane((0, SIDE, 0), (0, -1, 0)))
    # a side that is a rigid body moved by its load (heavy: it barely moves): the walls' kernels
    # take its contacts with fixed grains too, so a removed grain must leave its candidates
    heavy = RigidBody(mass=50.0, fixed_translation="yz")
    sim.add_wall(shapes.Plane((SIDE, 0, 0), (-1, 0, 0)), name="side", motion=heavy)
    if floor == "plane":
        sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.1, 0.0, 1.0)), name="floor")
    else:  # two facets, sloping: beads slide along it and touch both near the diagonal
        v = np.array([[0, 0, 0], [SIDE, 0, 0.4e-3], [SIDE, SIDE, 0.4e-3], [0, SIDE, 0]])
        sim.add_wall(shapes.TriangleMesh(v, [[0, 1, 2], [0, 2, 3]]), name="floor")
    return _sink_and_gravity(sim, law)


def _old_removal(removals, idx):
    """The behaviour before parking: a rebuild at the start of the next step."""
    removals.sim.request_rebuild()


def _run(law, floor, steps, old_way, monkeypatch):
    if old_way:
        monkeypatch.setattr(Removals, "park", _old_removal)
    sim = _scene(law, floor)
    states = []
    for _ in range(4):
        sim.run(steps=steps // 4)
        d = sim.get_particles()
        states.append((d["id"], d["x"], d["v"], d["w"], sim.walls["floor"].force, sim.walls["side"].force))
    monkeypatch.undo()
    return sim, states


@pytest.mark.parametrize("law,steps", [("hertz_mindlin", 4000), ("complementarity", 800)])
@pytest.mark.parametrize("floor", [pytest.param("plane", marks=pytest.mark.integration), "mesh"])
def test_removal_without_rebuild_gives_the_same_bits(law, steps, floor, monkeypatch):
    sim, got = _run(law, floor, steps, False, monkeypatch)
    ref, want = _run(law, floor, steps, True, monkeypatch)
    removed = 150 - sim.n_particles
    assert removed > 20, "the scene must remove beads along the way"
    assert sim.n_particles > 10
    for (i1, x1, v1, w1, f1, s1), (i2, x2, v2, w2, f2, s2) in zip(got, want, strict=True):
        assert np.array_equal(i1, i2)
        assert np.array_equal(x1, x2) and np.array_equal(v1, v2) and np.array_equal(w1, w2)
        assert np.array_equal(f1, f2) and np.array_equal(s1, s2)
    assert sim.n_rebuilds < ref.n_rebuilds, (sim.n_rebuilds, ref.n_rebuilds)


def test_parked_particles_are_out_of_every_query():
    """Between a removal and the next rebuild the removed rows stay in the storage: they must not
    show in outputs, counts or contacts, no wall may keep them as candidates, and nothing may touch
    them."""
    sim = _scene("hertz_mindlin", "plane")
    sim.run(steps=800)
    p = sim.particles
    cs = sim.contact_store
    live = p.motion[: p.n_owned] != REMOVED
    # grains that are wall candidates now, and touch other grains: removing them must take them
    # out of both
    cand = np.unique(cs.cand[cs.cand >= 0])
    pairs = sim.contacts()
    touching_ids = np.union1d(pairs["id_i"], pairs["id_j"])
    pick = [i for i in cand if live[i] and p.id[i] in touching_ids][:3]
    assert len(pick) >= 2, "the scene must have grains near walls that touch other grains"
    k = len(pick)
    mask = np.zeros(p.n_owned, dtype=bool)
    mask[pick] = True
    n_before, rebuilds = sim.n_particles, sim.n_rebuilds
    count, _ = sim.remove_particles(mask)
    assert count == k
    gone = np.array(pick)
    assert sim.n_particles == n_before - k
    assert sim.get_particles()["id"].size == n_before - k
    cand = cs.cand
    assert not np.isin(cand[cand >= 0], gone).any(), "a removed grain is still a wall candidate"
    assert np.all(p.x[gone, 0] > 100 * SIDE)  # parked far away
    sim.run(steps=1)
    assert sim.n_rebuilds == rebuilds, "a removal no longer forces a rebuild"
    assert np.all(p.motion[gone] == REMOVED)
    assert np.all(p.f[gone] == 0.0) and np.all(p.v[gone] == 0.0)  # no contact reached them
    ids = sim.contacts()
    assert not np.isin(ids["id_i"], p.id[gone]).any() and not np.isin(ids["id_j"], p.id[gone]).any()
    assert not np.isin(sim.wall_contacts()["id"], p.id[gone]).any()


@pytest.mark.parametrize("law,steps", [("hertz_mindlin", 8000), ("complementarity", 1500)])
def test_removal_in_a_periodic_box_gives_the_same_bits(law, steps, monkeypatch):
    """Periodic in x and y (images of the parked grains are ghost rows): parking moves a removed
    grain out of the box until the rebuild compacts it, which must change nothing."""

    def scene():
        sim = _beads(law, 5)
        sim.set_periodic((0.0, 0.0, 0.0), (SIDE, SIDE, 0.0), axes="xy")
        sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), name="floor")
        return _sink_and_gravity(sim, law)

    runs = []
    for old_way in (False, True):
        if old_way:
            monkeypatch.setattr(Removals, "park", _old_removal)
        sim = scene()
        sim.run(steps=steps)
        d = sim.get_particles()
        runs.append((sim, d["id"], d["x"], d["v"], sim.walls["floor"].force))
        monkeypatch.undo()
    (new, *a), (old, *b) = runs
    assert 150 - new.n_particles > 10, 150 - new.n_particles
    for u, w in zip(a, b, strict=True):
        assert np.array_equal(u, w)
    assert new.n_rebuilds < old.n_rebuilds


def test_a_lost_particle_is_named_by_its_id():
    """The count check's error names the first id no rank holds nor removed (found by block counts,
    not by gathering every id)."""
    from pdem.errors import LostParticleError

    sim = pdem.Simulation()
    sim.add_material("glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU)
    x = np.stack([np.arange(5000) * 3e-3, np.zeros(5000), np.zeros(5000)], axis=1)
    sim.set_periodic([-1.5e-3, -0.1, -0.1], [15.0 - 1.5e-3, 0.1, 0.1], axes="x")  # (the count is kept
    sim.add_particles(x, 1e-3, material="glass")  # with a decomposition: MPI, or a periodic box)
    sim.dt = 1e-7
    sim.run(steps=1)
    sim.check_particle_count()  # nothing lost
    p = sim.particles
    p.n_ghost = 0  # (the images go; the next rebuild makes them again)
    row = int(np.flatnonzero(p.id[: p.n_owned] == 3170)[0])
    last = p.n_owned - 1
    p.swap_rows(np.array([row]), np.array([last]))
    p.n_owned = last  # particle 3170 vanishes from the storage
    with pytest.raises(LostParticleError, match=r"1 particle\(s\) lost .*first id 3170"):
        sim.check_particle_count()


def test_an_outflow_checkpoints_partials_of_the_removed_mass_not_every_mass():
    """The outflow's checkpoint state holds the count and a few partials whose exact sum is the
    removed mass, not one entry per removed grain; restored, it measures the same bits, and goes on
    adding removals to them exactly."""
    import math

    rng = np.random.default_rng(8)
    masses = list(rng.uniform(1e-7, 3e-6, 20000) * np.exp2(rng.integers(-20, 20, 20000)))
    params = OutflowParams.model_validate({"type": "outflow", "point": [0, 0, 0], "normal": [0, 0, 1]})
    sink = OutflowBoundary("out", params)
    sink.removed_masses, sink.removed_here = list(masses), len(masses)
    state = sink.state()
    assert state["removed_count"] == 20000 and len(state["removed_partials"]) < 100
    sim = pdem.Simulation()
    before = sink.measurements(sim)
    again = OutflowBoundary("out", params)
    again.restore(state)
    assert again.measurements(sim) == before
    assert before["removed_mass"] == math.fsum(masses)
    more = list(rng.uniform(1e-7, 3e-6, 500))
    sink.removed_masses += more
    again.removed_masses += more
    assert again.measurements(sim)["removed_mass"] == sink.measurements(sim)["removed_mass"]
    assert sink.measurements(sim)["removed_mass"] == math.fsum(masses + more)
