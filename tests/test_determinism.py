"""Bitwise determinism: run-to-run, and independence from the order particles are stored in memory.

Every particle's force is a sum over its contacts in partner-id order, then walls in order, then body
forces, so permuting the storage (what spatial sorting and, later, MPI migration do) must not change a
single bit of the trajectory.
"""

import numpy as np
import pytest

import pdem
from pdem.geometry.shapes import Rectangle, box_planes
from pdem.sources import BoxRegion, Uniform, hcp, random_fill


def make_pile(shuffle_seed: int | None = None) -> pdem.Simulation:
    # a slightly compressed hcp block (contacts from step 0) below the shelf, a loose fill above it
    x1, r1 = hcp(BoxRegion((0, 0, 0), (0.012, 0.006, 0.0094)), 0.5e-3)
    r1 = r1 * 1.005
    x2, r2 = random_fill(BoxRegion((0.002, 0, 0.01012), (0.01, 0.006, 0.0135)), Uniform(0.4e-3, 0.6e-3),
                         n=60, seed=4)
    x, r = np.concatenate([x1, x2]), np.concatenate([r1, r2])
    sim = pdem.Simulation()
    sim.add_material("glass", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.5, rolling_friction=0.05)
    rng = np.random.default_rng(7)
    sim.add_particles(x, r, velocities=rng.normal(0, 0.05, (len(r), 3)))
    for k, plane in enumerate(box_planes((0, 0, 0), (0.012, 0.006, 0.03))):
        sim.add_wall(plane, name=f"w{k}")
    sim.add_wall(Rectangle((0.006, 0.003, 0.0101), (0, 0, 1), (1, 0, 0), (0.003, 0.003)), name="shelf")
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 2e-6
    sim.skin = 5e-5
    if shuffle_seed is not None:
        sim.prepare()
        perm = np.random.default_rng(shuffle_seed).permutation(sim.n_particles)
        sim.permute_storage(perm)  # the next step rebuilds
    return sim


def state(sim: pdem.Simulation) -> dict[str, np.ndarray]:
    p = sim.get_particles()
    out = {k: p[k] for k in ("id", "x", "v", "w")}
    for name, wall in sim.walls.items():
        out["load_" + name] = np.concatenate([wall.force, wall.torque])
    return out


def assert_bitwise_equal(a, b):
    for key in a:
        if not np.array_equal(a[key], b[key]):
            i = int(np.argmax(np.any(np.atleast_2d(a[key] != b[key]).reshape(len(a[key]), -1), axis=1)))
            pytest.fail(f"field {key} differs first at row {i}: {a[key][i]!r} vs {b[key][i]!r}")


def test_run_to_run_identical():
    a = make_pile().run(steps=1500)
    b = make_pile().run(steps=1500)
    assert a.n_rebuilds > 2, "the scene must move enough to rebuild the neighbour list"
    assert_bitwise_equal(state(a), state(b))


def test_storage_order_does_not_change_results():
    ref = make_pile().run(steps=1500)
    shuffled = make_pile(shuffle_seed=11).run(steps=1500)
    # the permutation really happened
    assert not np.array_equal(shuffled.particles.id, ref.particles.id)
    assert_bitwise_equal(state(ref), state(shuffled))
    # and the scene is not trivial: particles touch each other and the walls
    assert len(ref.contacts()["id_i"]) > 100
    assert ref.walls["w4"].n_contacts > 10  # the floor
    assert ref.walls["shelf"].n_contacts >= 1
