"""Verlet pair list: the cell-grid kernel against the O(n²) oracle, and a running simulation whose
touching pairs are all in its pair list."""

from __future__ import annotations

import numpy as np
import pytest
from physics_helpers import E_MOD, NU, RHO, brute_force_touching, random_spheres

import pdem
from pdem.geometry.shapes import box_planes
from pdem.neighbor import _kernels as nk


def _grid(x: np.ndarray, r: np.ndarray, skin: float, max_cells: int | None = None):
    """lo, inv_cell, dims chosen like Simulation._rebuild."""
    n = x.shape[0]
    lo = x.min(axis=0) - 1e-12
    hi = x.max(axis=0) + 1e-12
    cell = 2.0 * float(r.max()) + skin
    ext = np.maximum(hi - lo, cell)
    limit = 4 * n + 1000 if max_cells is None else max_cells
    while True:
        dims = np.maximum((ext / cell).astype(np.int64), 1)
        if int(np.prod(dims)) <= limit:
            break
        cell *= 1.26
    return lo, 1.0 / cell, dims


def _id_pairs(pi, pj, ids) -> list[tuple[int, int]]:
    return [(int(ids[a]), int(ids[b])) for a, b in zip(pi, pj, strict=True)]


def _check(x, r, ids, skin, lo, inv_cell, dims, n_owned=None):
    n = x.shape[0]
    n_owned = n if n_owned is None else n_owned
    pi, pj, count = nk.build_pairs(x, r, ids, n_owned, n, skin, lo, inv_cell, dims, 64 * n)
    assert count <= 64 * n
    got = _id_pairs(pi[:count], pj[:count], ids)
    bi, bj = nk.brute_force_pairs(x, r, ids, n, skin)
    want = {p for p in _id_pairs(bi, bj, ids)}
    if n_owned < n:  # pairs of two ghosts are not listed
        want = {(a, b) for (a, b), i, j in zip(_id_pairs(bi, bj, ids), bi, bj, strict=True)
                if i < n_owned or j < n_owned}
    # independent check of the oracle itself with numpy
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    close = np.triu(d < r[:, None] + r[None] + skin, k=1)
    a, b = np.nonzero(close)
    numpy_pairs = {(int(min(ids[p], ids[q])), int(max(ids[p], ids[q]))) for p, q in zip(a, b, strict=True)
                   if n_owned == n or p < n_owned or q < n_owned}
    assert want == numpy_pairs
    # identical sets, each pair once, id_lo < id_hi, sorted by (id_lo, id_hi)
    assert set(got) == want
    assert len(got) == len(want)
    assert all(lo_ < hi_ for lo_, hi_ in got)
    assert got == sorted(got)
    return pi, pj, count, got


def _packing(seed: int, n: int, side: float, shuffle_ids: bool):
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, side, (n, 3))
    x[: n // 10] = rng.uniform(-0.5, side + 0.5, (n // 10, 3))  # some on / beyond the edges
    x[n // 10 : n // 10 + 8, 0] = 0.0  # exactly on the lower faces of the grid
    x[n // 10 + 8 : n // 10 + 16, 1] = x[:, 1].max()
    r = rng.uniform(0.5, 1.5, n)  # radii vary by a factor 3
    ids = rng.choice(2**31 - 1, size=n, replace=False).astype(np.int64) if shuffle_ids else np.arange(n)
    return x, r, ids


@pytest.mark.parametrize("shuffle_ids", [False, True], ids=["ids=index", "shuffled-ids"])
@pytest.mark.parametrize("skin", [0.0, 0.05, 0.3, 2.0])
def test_build_pairs_matches_brute_force(skin, shuffle_ids):
    for seed in range(3):
        x, r, ids = _packing(seed, 400, 14.0, shuffle_ids)
        lo, inv_cell, dims = _grid(x, r, skin)
        _, _, count, _ = _check(x, r, ids, skin, lo, inv_cell, dims)
        assert count > 400  # a real test: many pairs


@pytest.mark.parametrize("skin", [0.0, 0.5])
def test_build_pairs_coarse_and_partial_grids(skin):
    """Grids that do not match the particles: cells enlarged (few cells), and a grid covering only
    the middle of the cloud, so that particles outside it are clamped into the border cells."""
    x, r, ids = _packing(7, 300, 12.0, shuffle_ids=True)
    # coarse: at most 8 cells
    lo, inv_cell, dims = _grid(x, r, skin, max_cells=8)
    assert 1.0 / inv_cell > 2.0 * r.max() + skin
    _check(x, r, ids, skin, lo, inv_cell, dims)
    # partial: the grid starts inside the cloud and ends before its far side
    cell = 2.0 * float(r.max()) + skin
    ext = x.max(axis=0) - x.min(axis=0)
    lo = x.min(axis=0) + 0.25 * ext
    dims = np.maximum((0.4 * ext / cell).astype(np.int64), 1)
    assert np.any(x < lo) and np.any(x > lo + dims * cell)
    _check(x, r, ids, skin, lo, 1.0 / cell, dims)
    # everything in one cell
    _check(x, r, ids, skin, x.min(axis=0), 1.0 / cell, np.array([1, 1, 1], dtype=np.int64))


def test_build_pairs_with_ghosts():
    """Pairs of two ghosts (local index ≥ n_owned) are not listed; all others are."""
    x, r, ids = _packing(3, 300, 12.0, shuffle_ids=True)
    lo, inv_cell, dims = _grid(x, r, 0.2)
    _, _, count, got = _check(x, r, ids, 0.2, lo, inv_cell, dims, n_owned=200)
    full = _check(x, r, ids, 0.2, lo, inv_cell, dims)[3]
    assert len(got) < len(full)


def test_build_pairs_capacity_overflow():
    """With too small a capacity the true count is returned (count > capacity), with arrays of
    ``capacity`` entries (their contents unspecified: the caller retries), and a retry at that count
    gives the complete list."""
    x, r, ids = _packing(5, 300, 12.0, shuffle_ids=True)
    skin = 0.3
    lo, inv_cell, dims = _grid(x, r, skin)
    pi, pj, count, _ = _check(x, r, ids, skin, lo, inv_cell, dims)
    for cap in (0, 1, count // 3, count - 1):
        qi, qj, c2 = nk.build_pairs(x, r, ids, x.shape[0], x.shape[0], skin, lo, inv_cell, dims, cap)
        assert c2 == count > cap
        assert qi.shape[0] == qj.shape[0] == cap
    qi, qj, c3 = nk.build_pairs(x, r, ids, x.shape[0], x.shape[0], skin, lo, inv_cell, dims, count)
    assert c3 == count and np.array_equal(qi, pi[:count]) and np.array_equal(qj, pj[:count])


def test_running_simulation_lists_every_touching_pair():
    """A pile collapsing in a box under gravity, with a small skin (many rebuilds): at every
    sample the touching pairs reported by sim.contacts() are exactly the overlapping pairs found
    by brute force on sim.get_particles(), with the same overlaps."""
    rng = np.random.default_rng(11)
    n = 300
    x, r = random_spheres(rng, n, [0, 0, 0], [10e-3, 10e-3, 60e-3], 0.5e-3, 1.5e-3)
    sim = pdem.Simulation()
    sim.add_material("glass", density=RHO, youngs_modulus=E_MOD, poisson_ratio=NU, restitution=0.3,
                     friction=0.5)
    sim.add_particles(x, r, velocities=rng.normal(0.0, 0.3, (n, 3)) + np.array([0.0, 0.0, -1.0]))
    for plane in box_planes([0, 0, 0], [10e-3, 10e-3, 70e-3]):
        sim.add_wall(plane)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.skin = 0.05e-3
    checked = {"samples": 0, "max_contacts": 0}

    def check(s):
        p = s.get_particles()
        c = s.contacts()
        got = list(zip(c["id_i"].tolist(), c["id_j"].tolist(), strict=True))
        assert len(set(got)) == len(got)
        want = brute_force_touching(p["x"], p["r"], p["id"])
        assert set(got) == want
        d = np.linalg.norm(p["x"][c["id_j"]] - p["x"][c["id_i"]], axis=1)
        assert np.allclose(c["overlap"], p["r"][c["id_i"]] + p["r"][c["id_j"]] - d, rtol=0, atol=1e-15)
        checked["samples"] += 1
        checked["max_contacts"] = max(checked["max_contacts"], len(got))

    sim.run(steps=6000, callback=check, every=200)
    print(f"{checked['samples']} samples, up to {checked['max_contacts']} contacts, "
          f"{sim.n_rebuilds} rebuilds")
    assert checked["samples"] == 30
    assert checked["max_contacts"] > 100
    assert sim.n_rebuilds > 50


CACHE_ORDER = """
import sys
import numpy as np
from pdem.neighbor import _kernels as nk

first = sys.argv[1]  # a process that compiles the other kernels of the module before build_pairs
rng = np.random.default_rng(3)
n = 400
x = rng.uniform(0.0, 10.0, (n, 3))
r = np.full(n, 0.5)
ids = 1000 + rng.permutation(n).astype(np.int64)  # ids are not storage rows
if first == "others":
    keys = (ids[:50] << 32) | ids[50:100]
    nk.keys_with_ids(keys, np.sort(ids[:10]), True)
    nk.keys_with_ids(keys, np.sort(ids[:10]) + (1 << 20), False)
    nk.carry_history(np.sort(keys), np.zeros((50, 3)), np.sort(keys), np.zeros((50, 3)))
    nk.schedule_pairs(np.arange(5), np.arange(1, 6), 6)
lo = x.min(axis=0) - 1e-12
dims = np.maximum(((x.max(axis=0) - lo) / 1.2).astype(np.int64), 1)
pi, pj, count = nk.build_pairs(x, r, ids, n, n, 0.2, lo, 1.0 / 1.2, dims, 64 * n)
bi, bj = nk.brute_force_pairs(x, r, ids, n, 0.2)
got = sorted(zip(ids[pi[:count]].tolist(), ids[pj[:count]].tolist()))
want = sorted(zip(ids[bi].tolist(), ids[bj].tolist()))
assert got == want, "build_pairs disagrees with brute force"
"""


@pytest.mark.integration
def test_kernels_are_right_whichever_were_cached_by_an_earlier_process(tmp_path):
    """numba names some internal helpers (its sort and argsort) alike in every module: a kernel
    loaded from the cache into a process that has just compiled another kernel can call that
    kernel's helper. This happened to build_pairs (np.argsort) after a migration compiled a
    np.sort in keys_with_ids: it listed ids as storage rows on rank 1. One process caches
    build_pairs, a second compiles the module's other kernels first, then loads build_pairs."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, PDEM_NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    script = tmp_path / "order.py"
    script.write_text(CACHE_ORDER)
    for first in ("build_pairs", "others"):
        out = subprocess.run([sys.executable, str(script), first], env=env, capture_output=True, text=True,
                             timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]


def test_bounds_are_numpys_min_and_max_with_nan():
    """``bounds`` (the rebuild's box of the positions) is x[:n].min/max(axis=0), NaN included."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(500, 3))
    for n in (1, 2, 499, 500):
        lo, hi = nk.bounds(x, n)
        assert np.array_equal(lo, x[:n].min(axis=0)) and np.array_equal(hi, x[:n].max(axis=0))
    for row in (0, 250, 499):
        y = x.copy()
        y[row, 1] = np.nan
        lo, hi = nk.bounds(y, 500)
        assert np.isnan(lo[1]) and np.isnan(hi[1])
        assert lo[0] == y[:, 0].min() and hi[2] == y[:, 2].max()


@pytest.mark.parametrize("n", [0, 1, 2, 7, 2048, 5000])
def test_id_order_is_the_argsort_of_the_first_n_ids(n):
    """The build's radix sort of rows by id against numpy's sort: ids in random order, sorted, with
    a span needing three 11-bit passes, and negative; only the first n rows count."""
    rng = np.random.default_rng(n)
    cases = [
        rng.permutation(n + 10).astype(np.int64),
        np.arange(n + 3, dtype=np.int64),
        rng.choice(10**12, n + 5, replace=False).astype(np.int64) - 5 * 10**11,
        (rng.permutation(n + 1) * 3 - 10**9).astype(np.int64),
    ]
    for ids in cases:
        assert np.array_equal(nk.id_order(ids, n), np.argsort(ids[:n], kind="stable"))


def test_take_pairs_and_take_keyed_are_numpy_gathers():
    """The rebuild's gathers against NumPy's indexing, with history of 3 and of 0 columns."""
    rng = np.random.default_rng(4)
    m = 1000
    order = rng.permutation(m)
    pi, pj = rng.integers(0, 500, m), rng.integers(0, 500, m)
    keys = rng.choice(10**9, m, replace=False).astype(np.int64)
    for hist in (rng.normal(size=(m, 3)), np.zeros((m, 0))):
        a, b, k, h, inv = nk.take_pairs(order, pi, pj, keys, hist)
        assert np.array_equal(a, pi[order]) and np.array_equal(b, pj[order])
        assert np.array_equal(k, keys[order]) and np.array_equal(h, hist[order])
        assert np.array_equal(inv[order], np.arange(m))
        k2, h2 = nk.take_keyed(inv, k, h)
        assert np.array_equal(k2, keys) and np.array_equal(h2, hist)
