"""DEM-P's Hertz–Mindlin pair kernel in passes over columns against the generic pair loop.

``HertzMindlin.pair_kernel`` tests every listed pair, gathers the touching ones into columns,
computes their forces without branches (vectorized) and scatters them in list order. It must give
exactly what the generic loop (:func:`pdem.api.pair_forces` with :func:`hertz_mindlin_force`, one
pair at a time) gives: forces, torques, pair forces, histories and flags, bit for bit, on pairs
that take every path (apart, touching, fixed pairs, sliding and sticking, springs of zero length or
along the normal, attractive damping with and without the clamp, rolling and spinning resistance,
both parameterisations, several materials).
"""

from __future__ import annotations

import numpy as np
import pytest

from pdem.contact._kernels import FLAG_COINCIDENT, FLAG_OVERLAP
from pdem.laws.hertz_mindlin import (
    HertzMindlin,
    hertz_mindlin_pair_kernel,
    hertz_mindlin_pair_kernel_generic,
)
from pdem.materials import Material, MaterialTable

R = 1e-3


def materials(rolling: bool) -> MaterialTable:
    table = MaterialTable()
    extra = {"rolling_friction": 0.2, "spinning_friction": 0.1} if rolling else {}
    table.add(Material("a", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3,
                       friction=0.5, **extra))  # fmt: skip
    table.add(Material("b", density=7800.0, youngs_modulus=2e8, poisson_ratio=0.25, restitution=0.8,
                       friction=0.2))  # fmt: skip
    table.add(Material("c", density=1000.0, youngs_modulus=1e7, poisson_ratio=0.4, restitution=0.05,
                       friction=0.0))  # fmt: skip
    return table


def scene(rng, n=4000, npairs=4000, one_material=False):
    """Random spheres; pairs (2q, 2q + 1) placed in contact (overlaps up to 3 %), the other listed
    pairs random (mostly apart), in a random order. Histories and pair forces of some pairs are
    −0.0 (a row is zeroed unless it is +0.0 bit for bit)."""
    x = rng.uniform(0.0, 12 * R, (n, 3))
    r = rng.uniform(0.7 * R, 1.3 * R, n)
    nt = min(n // 2, npairs // 2)
    ti, tj = 2 * np.arange(nt), 2 * np.arange(nt) + 1
    d = rng.normal(size=(nt, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    x[tj] = x[ti] + d * ((r[ti] + r[tj]) * rng.uniform(0.97, 1.0, nt))[:, None]
    pi = np.concatenate([ti, rng.integers(0, n, npairs - nt)])
    pj = np.concatenate([tj, rng.integers(0, n, npairs - nt)])
    keep = pi != pj
    pi, pj = np.minimum(pi[keep], pj[keep]), np.maximum(pi[keep], pj[keep])
    order = rng.permutation(pi.size)
    pi, pj = pi[order], pj[order]
    v = rng.normal(scale=1.0, size=(n, 3))
    w = rng.normal(scale=300.0, size=(n, 3))
    m = 2500.0 * 4.0 / 3.0 * np.pi * r**3
    inv_m = 1.0 / m
    inv_i = 1.0 / (0.4 * m * r * r)
    fixed = rng.random(n) < 0.1
    inv_m[fixed] = 0.0
    inv_i[fixed] = 0.0
    mat = rng.integers(0, 3, n).astype(np.int32)
    if one_material:
        mat[:] = 1
    hist = rng.normal(scale=1e-6, size=(pi.size, 3))
    hist[rng.random(pi.size) < 0.2] = 0.0  # new contacts
    hist[rng.random(pi.size) < 0.05, rng.integers(0, 3)] = -0.0
    along = rng.random(pi.size) < 0.05  # springs along the normal: nothing left after the turn
    d = x[pj] - x[pi]
    hist[along] = 1e-6 * d[along] / np.linalg.norm(d[along], axis=1)[:, None]
    return pi.astype(np.int64), pj.astype(np.int64), x, v, w, r, inv_m, inv_i, mat, hist


def run(kernel, coef, args, dt, max_overlap):
    pi, pj, x, v, w, r, inv_m, inv_i, mat, hist = (a.copy() for a in args)
    n = x.shape[0]
    f = np.full((n, 3), 0.5)
    t = np.full((n, 3), -0.5)
    fpair = np.full((pi.size, 3), 9.0)
    fpair[::7] = 0.0
    fpair[::11, 1] = -0.0
    flags = kernel(pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap)
    return flags, f, t, fpair, hist


def same_bits(a, b):
    return np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).view(np.int64))


@pytest.mark.parametrize("rolling", [False, True])
@pytest.mark.parametrize("parameterisation", ["material", "coefficients"])
@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize("one_material", [False, True])
def test_column_kernel_is_the_generic_loop_bit_for_bit(rolling, parameterisation, clamp, one_material):
    seed = 7 + 2 * rolling + 4 * clamp + 8 * (parameterisation == "material") + 16 * one_material
    rng = np.random.default_rng(seed)
    kw = {"kn": 1e8, "kt": 5e7, "cn": 2e9, "ct": 1e9} if parameterisation == "coefficients" else {}
    law = HertzMindlin(parameterisation=parameterisation, clamp_normal=clamp, **kw)
    coef = law.coefficients(materials(rolling))
    if one_material:  # the material of every particle (b) has rolling friction too
        coef[1, 1, 6], coef[1, 1, 8] = coef[0, 0, 6], coef[0, 0, 8]
    args = scene(rng, one_material=one_material)
    ref = run(hertz_mindlin_pair_kernel_generic, coef, args, 1e-6, 0.02)
    got = run(hertz_mindlin_pair_kernel, coef, args, 1e-6, 0.02)
    assert ref[0] == got[0]
    assert ref[0] & FLAG_OVERLAP  # some overlaps are above 2 % of the smaller radius
    for a, b in zip(ref[1:], got[1:], strict=True):
        assert same_bits(a, b)
    # every path was taken
    fpair = ref[3]
    touching = np.any(fpair != 0.0, axis=1)
    assert 0.2 * len(touching) < touching.sum() < 0.8 * len(touching)
    mu = coef[args[8][args[0]], args[8][args[1]], 5]
    fn = np.einsum("ij,ij->i", fpair, (args[2][args[1]] - args[2][args[0]]))
    assert (mu == 0.0).any() != one_material
    assert (touching & (fn < 0)).any() != clamp  # damping pulls some pairs together unless clamped
    if rolling:  # the torques include rolling and spinning resistance
        no_rolling = coef * [1, 1, 1, 1, 1, 1, 0, 1, 0, 1, 1]
        assert not same_bits(ref[2], run(hertz_mindlin_pair_kernel_generic, no_rolling, args, 1e-6, 0.02)[2])


@pytest.mark.parametrize("tangential", ["mindlin_rescale", "mindlin_force", "mindlin_rescale_force"])
@pytest.mark.parametrize("one_material", [False, True])
def test_mindlin_options_in_columns_are_the_generic_loop_bit_for_bit(tangential, one_material):
    """The tangential options' column passes (elastic-force history, rescaling by the previous
    contact radius kept in a fourth history column) against the generic loop; previous radii above,
    below and at zero (new contacts)."""
    rng = np.random.default_rng(29 + len(tangential) + one_material)
    law = HertzMindlin(tangential=tangential, clamp_normal=one_material)
    coef = law.coefficients(materials(True))
    args = list(scene(rng, one_material=one_material))
    hist = args[-1] * (1e4 if "force" in tangential else 1.0)  # forces of order μ F_n
    if law.history_size == 4:
        a_old = rng.uniform(0.0, 2.5e-4, hist.shape[0])
        a_old[rng.random(hist.shape[0]) < 0.2] = 0.0
        hist = np.column_stack([hist, a_old])
    args[-1] = np.ascontiguousarray(hist)
    ref = run(hertz_mindlin_pair_kernel_generic, coef, args, 1e-6, 0.02)
    got = run(hertz_mindlin_pair_kernel, coef, args, 1e-6, 0.02)
    assert ref[0] == got[0]
    for a, b in zip(ref[1:], got[1:], strict=True):
        assert same_bits(a, b)
    # the option changed the forces, and the rescale options rewrote the radius column
    plain = run(hertz_mindlin_pair_kernel_generic, HertzMindlin(clamp_normal=one_material).coefficients(
        materials(True)), [*args[:-1], np.ascontiguousarray(args[-1][:, :3])], 1e-6, 0.02)  # fmt: skip
    assert not same_bits(plain[1], ref[1])
    if law.history_size == 4:
        touching = np.any(ref[3] != 0.0, axis=1)  # (clamped pairs may touch with zero force)
        assert np.all(ref[4][touching, 3] > 0.0) and (ref[4][:, 3] == 0.0).any()


def test_coincident_pair_is_flagged_and_left_alone_like_the_generic_loop():
    rng = np.random.default_rng(3)
    coef = HertzMindlin().coefficients(materials(False))
    pi, pj, x, v, w, r, inv_m, inv_i, mat, hist = scene(rng, n=50, npairs=200)
    x[pj[0]] = x[pi[0]]
    inv_m[[pi[0], pj[0]]] = 1.0
    args = (pi, pj, x, v, w, r, inv_m, inv_i, mat, hist)
    ref = run(hertz_mindlin_pair_kernel_generic, coef, args, 1e-6, 1.0)
    got = run(hertz_mindlin_pair_kernel, coef, args, 1e-6, 1.0)
    assert ref[0] & FLAG_COINCIDENT and got[0] == ref[0]
    for a, b in zip(ref[1:], got[1:], strict=True):
        assert same_bits(a, b)


def test_touching_list_grows_and_blocks_follow_the_list_order():
    """The list of touching pairs grows with the pair list; the columns hold one block of
    touching pairs (``BLOCK``), so larger scenes run in several blocks, the last one partial."""
    from pdem.laws import hertz_mindlin

    hertz_mindlin._columns.grow(0)
    rng = np.random.default_rng(11)
    coef = HertzMindlin().coefficients(materials(False))
    for npairs in (10, 5000, 300, 20000):
        args = scene(rng, n=8000, npairs=npairs)
        ref = run(hertz_mindlin_pair_kernel_generic, coef, args, 1e-6, 1.0)
        got = run(hertz_mindlin_pair_kernel, coef, args, 1e-6, 1.0)
        for a, b in zip(ref, got, strict=True):
            assert same_bits(a, b)
    assert hertz_mindlin._columns.tk.shape[0] >= 19000
    touching = np.any(ref[3] != 0.0, axis=1).sum()
    assert touching > 2 * hertz_mindlin.BLOCK and touching % hertz_mindlin.BLOCK


def test_nan_positions_reach_the_forces_as_in_the_generic_loop():
    """A pair whose distance is not a number counts as touching (the generic loop's test), so the
    non-finite value reaches the forces, where the step's check finds it."""
    rng = np.random.default_rng(5)
    coef = HertzMindlin().coefficients(materials(False))
    pi, pj, x, v, w, r, inv_m, inv_i, mat, hist = scene(rng, n=60, npairs=200)
    x[pi[3], 1] = np.nan
    inv_m[pi[3]] = 1.0
    args = (pi, pj, x, v, w, r, inv_m, inv_i, mat, hist)
    ref = run(hertz_mindlin_pair_kernel_generic, coef, args, 1e-6, 1.0)
    got = run(hertz_mindlin_pair_kernel, coef, args, 1e-6, 1.0)
    assert np.isnan(ref[1][pi[3]]).any()
    assert ref[0] == got[0]
    for a, b in zip(ref[1:], got[1:], strict=True):
        assert same_bits(a, b)


@pytest.mark.integration
def test_non_contiguous_history_takes_the_generic_loop():
    """The passes read history and pair-force rows as bits, which needs C-contiguous arrays; a view
    of a wider array gets the generic loop, with the same results."""
    rng = np.random.default_rng(13)
    coef = HertzMindlin().coefficients(materials(False))
    pi, pj, x, v, w, r, inv_m, inv_i, mat, hist = scene(rng, n=300, npairs=900)
    wide = np.zeros((hist.shape[0], 5))
    wide[:, :3] = hist
    out = []
    cases = ((hertz_mindlin_pair_kernel_generic, hist.copy()), (hertz_mindlin_pair_kernel, wide[:, :3]))
    for kernel, h in cases:
        f, t = np.zeros((x.shape[0], 3)), np.zeros((x.shape[0], 3))
        fpair = np.full((pi.size, 3), 9.0)
        flags = kernel(pi, pj, h, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, 1e-6, 1.0)
        out.append((flags, f, t, fpair, np.array(h)))
    assert not wide[:, :3].flags.c_contiguous
    for a, b in zip(*out, strict=True):
        assert same_bits(a, b)
