"""Periodic boundaries: images through the ghost exchange, exact shifts and wraps, unique contacts.

The references are independent of the periodic machinery: the same pair in the middle of the box
(no image involved) and without any periodic box, a minimum-image O(n²) search, momentum
conservation, an uninterrupted run for checkpoints.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from physics_helpers import E_MOD, NU, RHO

import pdem
from pdem.geometry.shapes import Plane, Rectangle
from pdem.sources import BoxRegion, Uniform, random_fill

ROOT = Path(__file__).resolve().parents[1]
L = 0.01  # box edge [m]


def _sim(periodic: str | None = "xy", lo=(0.0, 0.0, 0.0), hi=(L, L, L), **mat) -> pdem.Simulation:
    sim = pdem.Simulation()
    props = dict(density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU, restitution=0.5, friction=0.5)
    props.update(mat)
    sim.add_material("glass", **props)
    if periodic:
        sim.set_periodic(lo, hi, periodic)
    return sim


def _by_id(sim: pdem.Simulation, key: str) -> np.ndarray:
    return sim.get_particles()[key]


def _history(sim: pdem.Simulation) -> dict[int, np.ndarray]:
    """Pair history by key (one row per key: copies of a contact must agree)."""
    out: dict[int, np.ndarray] = {}
    for k, h in zip(sim.contact_store.keys, sim.contact_store.hist, strict=True):
        k = int(k)
        if k in out:
            assert np.array_equal(out[k], h), "two copies of a contact disagree"
        out[k] = h.copy()
    return out


# ---------------------------------------------------------------------------------------------
# one contact across the boundary = the same contact in the middle of the box
# ---------------------------------------------------------------------------------------------


def _pair_scene(sim: pdem.Simulation, x: np.ndarray) -> pdem.Simulation:
    n = np.array([math.cos(0.35), math.sin(0.35), 0.0])
    t = np.array([-math.sin(0.35), math.cos(0.35), 0.0])
    drift = np.array([1.0, 0.0, 0.0])  # carries particle 0 across x = L during the contact
    v = np.array([drift + 0.1 * n + 0.03 * t + (0, 0, 0.02), drift - 0.1 * n - 0.03 * t])
    w = np.array([[0.0, 0.0, 40.0], [10.0, -20.0, 0.0]])
    sim.add_particles(x, 1e-3, velocities=v, angular_velocities=w)
    sim.dt = 1e-6
    sim.skin = 2e-5  # a rebuild every ~10 steps, so the wrap happens mid-contact
    return sim


def _pair_positions() -> np.ndarray:
    xi = np.array([L - 0.1e-3, 0.5 * L, 0.5 * L])
    n = np.array([math.cos(0.35), math.sin(0.35), 0.0])
    xj = xi + 1.999e-3 * n  # slightly overlapping; beyond x = L: set_periodic wraps it
    return np.array([xi, xj])


def test_contact_across_boundary_equals_contact_in_middle():
    """Bitwise: the pair straddling x = L (one particle wraps mid-contact) and the same pair shifted
    by L/2 (no image at all) have the same forces, velocities, spins and history at every step; and
    a run without any periodic box agrees to rounding."""
    a = _pair_scene(_sim("xy"), _pair_positions())
    a._prepare()
    xa = a.get_particles()["x"]
    assert xa[1, 0] < 0.5 * L < xa[0, 0], "the pair must straddle the periodic boundary"
    half = np.array([0.5 * a.box.length[0], 0.0, 0.0])  # a.box.length: L on the position grid
    shifted = xa + half  # exact
    middle = a.box.wrapped(shifted)
    assert abs(middle[0, 0] - middle[1, 0]) < 0.25 * L, "the shifted pair sits in the middle"
    b = _pair_scene(_sim("xy"), middle)
    c = _pair_scene(_sim(None), middle)  # not periodic: plain floating point
    wrapped_during_contact = False
    touching_steps = 0
    fmax = 0.0
    for step in range(260):
        before = a.get_particles()["x"][0, 0]
        for s in (a, b, c):
            s.step()
        pa, pb, pc = a.get_particles(), b.get_particles(), c.get_particles()
        for key in ("v", "w", "f", "t"):
            assert np.array_equal(pa[key], pb[key]), f"step {step}: {key} differs"
        assert np.array_equal(a.box.wrapped(pa["x"] + half), pb["x"]), f"step {step}: x"
        ha, hb = _history(a), _history(b)
        assert ha.keys() == hb.keys() and all(np.array_equal(ha[k], hb[k]) for k in ha)
        touching = bool(np.any(pa["f"] != 0.0))
        touching_steps += touching
        fmax = max(fmax, float(np.abs(pb["f"]).max()))
        if touching and pa["x"][0, 0] < before - 0.5 * L:
            wrapped_during_contact = True
            assert any(np.any(h != 0.0) for h in ha.values()), "the tangential history survives the wrap"
        np.testing.assert_allclose(pc["f"], pb["f"], rtol=0, atol=1e-7 * fmax)
        np.testing.assert_allclose(pc["v"], pb["v"], rtol=1e-9, atol=1e-12)
    assert wrapped_during_contact, "particle 0 must cross x = L while the contact lasts"
    assert 50 < touching_steps < 260, "the contact must start and end within the run"
    assert a.n_rebuilds > 10
    # the collision really happened: the approach velocity reversed
    n = np.array([math.cos(0.35), math.sin(0.35), 0.0])
    rel = (pb["v"][0] - pb["v"][1]) @ n
    assert rel < -0.02


# ---------------------------------------------------------------------------------------------
# the neighbour list against a minimum-image brute force
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("axes", ["x", "xy", "xyz", "yz"])
def test_pair_list_is_the_minimum_image_brute_force(axes):
    lo, hi = np.array([-0.002, 0.001, 0.0]), np.array([0.006, 0.0085, 0.007])
    x, r = random_fill(BoxRegion(lo, hi), Uniform(0.3e-3, 0.8e-3), n=220, seed=5)
    sim = _sim(axes, lo, hi)
    sim.add_particles(x, r)
    sim.dt = 1e-6
    sim.skin = 0.4e-3  # many list pairs across the faces
    sim.prepare()
    p = sim.particles
    n = p.n_owned
    ids, pos, rad = p.id, p.x, p.r
    box = sim.box
    # listed pairs: (id_lo, id_hi) -> relative vector, counted per owned end
    listed: dict[tuple[int, int], np.ndarray] = {}
    owned_ends: dict[tuple[int, int], list[int]] = {}
    for i, j in zip(sim.contact_store.pi, sim.contact_store.pj, strict=True):
        key = (int(ids[i]), int(ids[j]))
        assert key[0] < key[1]
        d = pos[j] - pos[i]
        if key in listed:
            assert np.array_equal(listed[key], d), "copies of a pair must have the same relative vector"
        listed[key] = d
        owned_ends.setdefault(key, []).extend(int(ids[e]) for e in (i, j) if e < n)
    sk = sim.contact_store.keys_sorted()[0]  # the list in key order (DEM-P runs it in storage order)
    assert (sk[1:] >= sk[:-1]).all(), "key_order sorts the pair list by (id_lo, id_hi)"
    assert np.array_equal(np.sort(sim.contact_store.keys), sk)
    # brute force over owned particles with the minimum image
    xo, ro, io = pos[:n], rad[:n], ids[:n]
    want: dict[tuple[int, int], np.ndarray] = {}
    for a in range(n):
        d = box.minimum_image(xo - xo[a])
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        cut = ro[a] + ro + sim.skin
        for b in np.flatnonzero((d2 < cut * cut) & (io > io[a])):
            want[(int(io[a]), int(io[b]))] = d[b]
    assert len(want) > 300
    across = sum(1 for k, d in want.items() if not np.array_equal(d, xo[io == k[1]][0] - xo[io == k[0]][0]))
    assert across > 20, "the test needs pairs across the periodic faces"
    assert listed.keys() == want.keys()
    for k, d in want.items():
        assert np.array_equal(listed[k], d), f"pair {k}: {listed[k]} vs minimum image {d}"
        # each owned particle meets each partner exactly once (serial: both ends are owned)
        assert sorted(owned_ends[k]) == sorted(k), f"pair {k} reaches its owned ends {owned_ends[k]}"


# ---------------------------------------------------------------------------------------------
# a periodic gas: momentum, count, positions in the box, crossings
# ---------------------------------------------------------------------------------------------


def _gas(n: int = 400) -> pdem.Simulation:
    x, r = random_fill(BoxRegion((0, 0, 0), (L, L, L)), Uniform(0.4e-3, 0.6e-3), n=n, seed=3)
    sim = _sim("xyz", restitution=0.8, friction=0.4, rolling_friction=0.02)
    rng = np.random.default_rng(1)
    sim.add_particles(
        x, r, velocities=rng.normal(0.0, 0.3, (n, 3)), angular_velocities=rng.normal(0, 50, (n, 3))
    )
    sim.dt = 2e-6
    sim.skin = 5e-5
    return sim


def _momentum(p: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
    mv = p["mass"][:, None] * p["v"]
    return np.array([math.fsum(mv[:, c]) for c in range(3)]), math.fsum(np.abs(mv).ravel())


def test_fully_periodic_gas_conserves_momentum_and_particles():
    sim = _gas()
    p0 = sim.get_particles()
    mom0, scale = _momentum(p0)
    n0 = len(p0["id"])
    box = sim.box
    prev = p0["x"]
    stats = {"crossings": 0, "contacts_across": 0, "contacts": 0}

    def check(s):
        nonlocal prev
        p = s.get_particles()
        assert len(p["id"]) == n0 and s.count_particles() == n0
        assert np.all((p["x"] >= box.lo) & (p["x"] < box.hi)), "positions wrapped into the box"
        stats["crossings"] += int(np.sum(np.abs(p["x"] - prev) > 0.5 * L))
        prev = p["x"]
        c = s.contacts()
        rows_i = np.searchsorted(p["id"], c["id_i"])
        rows_j = np.searchsorted(p["id"], c["id_j"])
        raw = p["x"][rows_j] - p["x"][rows_i]
        stats["contacts"] += len(c["id_i"])
        stats["contacts_across"] += int(np.sum(np.any(box.minimum_image(raw) != raw, axis=1)))
        mom, _ = _momentum(p)
        assert np.all(np.abs(mom - mom0) <= 1e-13 * scale), f"momentum drift {(mom - mom0) / scale}"

    sim.run(steps=3000, callback=check, every=50)
    assert stats["crossings"] > 50, stats
    assert stats["contacts_across"] > 10, stats
    # the gas is not trivial: it dissipated energy in collisions
    p = sim.get_particles()
    assert 0.5 * np.sum(p["mass"] * np.sum(p["v"] ** 2, axis=1)) < 0.5 * np.sum(
        p0["mass"] * np.sum(p0["v"] ** 2, axis=1)
    )


def test_checkpoint_resume_across_the_boundary_is_bitwise():
    full = _gas().run(steps=1600)
    part = _gas().run(steps=800)
    state = part.state_dict()
    x = state["particles/x"]
    assert np.all((x >= part.box.lo) & (x < part.box.hi)), "checkpoint positions are wrapped"
    # contacts across the boundary are in the checkpoint
    keys = state["pairs/keys"]
    ids = state["particles/id"]
    lo_rows, hi_rows = np.searchsorted(ids, keys >> 32), np.searchsorted(ids, keys & 0xFFFFFFFF)
    raw = x[hi_rows] - x[lo_rows]
    assert np.any(np.any(part.box.minimum_image(raw) != raw, axis=1)), "a contact across a face"
    resumed = _sim("xyz", restitution=0.8, friction=0.4, rolling_friction=0.02)
    resumed.load_state(state)
    resumed.run(steps=800)
    a, b = full.state_dict(), resumed.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), f"{k} differs after resume"


def test_checkpoint_needs_the_same_box():
    state = _gas(50).run(steps=10).state_dict()
    other = _sim("xyz", hi=(L, L, 1.01 * L), restitution=0.8, friction=0.4, rolling_friction=0.02)
    with pytest.raises(pdem.errors.CheckpointError, match="periodic box"):
        other.load_state(state)
    plain = _sim(None, restitution=0.8, friction=0.4, rolling_friction=0.02)
    with pytest.raises(pdem.errors.CheckpointError, match="periodic box"):
        plain.load_state(state)


# ---------------------------------------------------------------------------------------------
# setup errors
# ---------------------------------------------------------------------------------------------


def test_box_shorter_than_two_cutoffs_is_rejected():
    # ghost width 2 r_max + skin = 2.2 mm: 4.4 mm is the shortest allowed periodic length
    for length, ok in ((4.39e-3, False), (4.41e-3, True)):
        sim = _sim("x", hi=(length, L, L))
        sim.add_particles([[1e-3, 5e-3, 5e-3], [3.2e-3, 5e-3, 5e-3]], 1e-3)
        sim.dt, sim.skin = 1e-6, 0.2e-3
        if ok:
            sim.run(steps=2)
        else:
            with pytest.raises(pdem.InputError, match=r"along x .*domain\.hi.*at least 0\.0044 m"):
                sim.run(steps=2)


def test_periodic_arguments_are_checked():
    sim = _sim(None)
    with pytest.raises(pdem.InputError, match="'w' is not an axis"):
        sim.set_periodic((0, 0, 0), (1, 1, 1), "xw")
    with pytest.raises(pdem.InputError, match="hi = 0.0 must be finite and above lo"):
        sim.set_periodic((0, 0, 0), (1, 0, 1), "xy")
    sim.add_particles([[0.5, 0.5, 0.5]], 0.01)
    sim.dt = 1e-6
    sim.run(steps=1)
    with pytest.raises(pdem.InputError, match="before the first step"):
        sim.set_periodic((0, 0, 0), (1, 1, 1), "x")


def test_particles_outside_the_box_are_wrapped():
    sim = _sim("xy")
    sim.add_particles([[-0.25 * L, 1.5 * L, 0.5 * L], [3.0 * L + 1e-3, 0.5 * L, 2.0 * L]], 1e-3)
    x = sim.get_particles()["x"]
    np.testing.assert_allclose(
        x, [[0.75 * L, 0.5 * L, 0.5 * L], [1e-3, 0.5 * L, 2.0 * L]], rtol=0, atol=1e-15
    )
    assert x[1, 2] == 2.0 * L, "non-periodic axes are left alone"


@pytest.mark.parametrize(
    ("shape", "message"),
    [
        (Plane((0, 0, 0), (1, 0, 0)), "normal component along the periodic axis x"),
        (Plane((0, 0, 0), (0, 0.6, 0.8)), "normal component along the periodic axis y"),
        (
            Rectangle((0.5 * L, 0.5 * L, 0), (0, 0, 1), (1, 0, 0), (0.5 * L, 0.1 * L)),
            "along the periodic axis x",
        ),
    ],
)
def test_walls_that_cut_the_periodic_box_are_rejected(shape, message):
    sim = _sim("xy")
    sim.add_particles([[0.5 * L, 0.5 * L, 2e-3]], 1e-3)
    sim.add_wall(shape, name="bad")
    sim.dt = 1e-6
    with pytest.raises(pdem.InputError, match=message):
        sim.run(steps=1)


def test_pipe_along_a_periodic_axis_is_allowed():
    from pdem.geometry.shapes import Cylinder

    sim = _sim("z")
    # particle 0 crosses the face z = 0 and bounces off the pipe wall
    sim.add_particles(
        [[1.9e-3, 0.0, 0.05e-3], [0.0, 0.0, 5e-3]], 1e-3, velocities=[(1.0, 0.0, -0.5), (0, 0, 0)]
    )
    sim.add_wall(Cylinder((0, 0, 0), (0, 0, 1), 3e-3), name="pipe")
    sim.dt = 1e-6
    loads = []
    sim.run(steps=300, callback=lambda s: loads.append(s.walls["pipe"].force[0]))
    p = sim.get_particles()
    assert max(loads) > 0.0 and p["v"][0, 0] < 0.0, "the particle hit the pipe and bounced back"
    assert p["x"][0, 2] > 0.5 * L, "and crossed the periodic face z = 0"
    with pytest.raises(pdem.InputError, match="along the periodic axis x"):
        other = _sim("xz")
        other.add_particles([[0.0, 0.0, 1e-3]], 1e-3)
        other.add_wall(Cylinder((0, 0, 0), (0, 0, 1), 3e-3), name="pipe")
        other.dt = 1e-6
        other.run(steps=1)


def test_floor_and_small_obstacle_are_allowed():
    sim = _sim("xy")
    sim.add_particles([[0.5 * L, 0.5 * L, 2e-3]], 1e-3)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_wall(Rectangle((0.5 * L, 0.5 * L, 5e-3), (0, 0, 1), (1, 0, 0), (1e-3, 1e-3)), name="shelf")
    sim.gravity = (0, 0, -9.81)
    sim.dt = 1e-6
    sim.run(steps=5)


# ---------------------------------------------------------------------------------------------
# the example deck: beads cross both periodic faces within the steps tests/test_mpi.py compares
# ---------------------------------------------------------------------------------------------


def test_column_collapse_deck_crosses_the_periodic_faces(tmp_path):
    from pdem.deck import load_deck
    from pdem.runner import Runner

    steps = 1000  # tests/test_mpi.py: PERIODIC_STEPS
    resolved = load_deck(ROOT / "inputs" / "examples" / "periodic_column_collapse.toml")
    runner = Runner(resolved, output=tmp_path, progress=None)
    sim = runner.build()
    runner._insert_particles("collapse", "collapse")
    assert sim.box.axes == ["x", "y"]
    p = sim.get_particles()
    assert np.any(p["x"][:, 0] > 0.5 * sim.box.hi[0]), "the column straddles x = 0: part of it is wrapped"
    prev = p["x"]
    crossings = np.zeros(3, dtype=int)
    across = 0

    def track(s):
        nonlocal prev, across
        q = s.get_particles()
        assert len(q["id"]) == 400
        inside = (q["x"] >= s.box.lo) & (q["x"] < s.box.hi)
        assert np.all(inside[:, :2]), "positions are wrapped into the box along x and y"
        crossings[:] += np.sum(
            np.abs(q["x"] - prev) > 0.5 * np.where(s.box.periodic, s.box.length, np.inf), axis=0
        )
        prev = q["x"]
        c = s.contacts()
        rows_i, rows_j = np.searchsorted(q["id"], c["id_i"]), np.searchsorted(q["id"], c["id_j"])
        raw = q["x"][rows_j] - q["x"][rows_i]
        across += int(np.sum(np.any(s.box.minimum_image(raw) != raw, axis=1)))

    sim.run(steps=steps, callback=track, every=5)
    assert crossings[0] >= 3 and crossings[1] >= 1 and crossings[2] == 0, crossings
    assert across >= 20, across
