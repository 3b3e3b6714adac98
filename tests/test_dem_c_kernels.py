"""DEM-C's three-pass Jacobi sweep against a row-by-row reference.

The sweep (``jacobi_gather`` → ``jacobi_project`` → ``accumulate_columns``) projects all contacts
at once on columns and without branches so that it vectorizes. It must give exactly the values of
the scalar, branching helpers it replaced (``project_cone``, ``_residual``, ``_roll_residual``,
``clamp_norm``, ``clamp_abs``, ``accumulate``), applied here one row at a time from Python, on rows
that take every branch: sticking, sliding, separating, frictionless, with and without rolling rows,
pair and wall rows, corrected and relaxed cone, residual formed or not.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pdem.complementarity import _kernels as ck


def random_rows(rng, nc, n, width):
    cb = np.empty((nc, 2), dtype=np.int64)
    cb[:, 0] = rng.integers(0, n, nc)
    cb[:, 1] = (cb[:, 0] + rng.integers(1, n, nc)) % n
    cb[rng.random(nc) < 0.2, 0] = -1  # wall rows
    cn = rng.normal(size=(nc, 3))
    cn /= np.linalg.norm(cn, axis=1)[:, None]
    ca = rng.uniform(0.5e-3, 1.5e-3, (nc, 2))
    cvw = rng.normal(scale=0.1, size=(nc, 6))
    cbias = rng.normal(scale=0.05, size=nc)
    cmu = rng.choice([0.0, 0.1, 0.5, 1.0], nc)
    cscale = rng.uniform(0.5, 2.0, nc) * 1e-5
    croll = np.zeros((nc, 4))
    if width == 8:
        on = rng.random(nc) < 0.7
        croll[on, 0] = rng.uniform(0.0, 0.2, on.sum())
        croll[on, 1] = rng.uniform(0.0, 0.1, on.sum())
        croll[on, 2] = rng.uniform(1e-4, 1e-3, on.sum())
        croll[on, 3] = rng.uniform(0.5, 2.0, on.sum()) * 1e-3
    gam = rng.normal(scale=1e-6, size=(nc, width))
    gam[:, 0] = np.abs(gam[:, 0]) * rng.choice([0.0, 1.0, 3.0], nc)
    v = rng.normal(scale=0.05, size=(n, 3))
    w = rng.normal(scale=50.0, size=(n, 3))
    return cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w


def reference_sweep(rows, nc, omega, corrected, want_res):
    """The fused scalar sweep, row by row: new impulses, the largest residual and every row's."""
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = rows
    width = gam.shape[1]
    u = np.zeros((nc, width))
    ck.contact_velocities_raw(cb, cn, ca, cvw, cbias, croll, cmu, v, w, nc, u, u, False)
    new = gam.copy()
    res = 0.0
    each = np.zeros(nc)
    for c in range(nc):
        b, mu = cscale[c], cmu[c]
        u0, u1, u2, u3 = u[c, :4]
        if corrected:
            u0 += mu * math.sqrt(u1 * u1 + u2 * u2 + u3 * u3)
        g0, g1, g2, g3 = gam[c, :4]
        rc, p0 = ck._residual(g0, g1, g2, g3, u0, u1, u2, u3, b, mu) if want_res else (0.0, g0)
        s = omega * b
        n0, n1, n2, n3 = ck.project_cone(g0 - s * u0, g1 - s * u1, g2 - s * u2, g3 - s * u3, mu)
        new[c, :4] = n0, n1, n2, n3
        if width == 8 and croll[c, 2] > 0.0:
            mu_r, mu_s, _rs, br = croll[c]
            r0, r1, r2, r3 = gam[c, 4:]
            if want_res:
                rr = ck._roll_residual(r0, r1, r2, r3, *u[c, 4:], p0, br, mu_r, mu_s)
                if rr > rc or rr != rr:
                    rc = rr
            s = omega * br
            new[c, 4:7] = ck.clamp_norm(r0 - s * u[c, 4], r1 - s * u[c, 5], r2 - s * u[c, 6], mu_r * n0)
            new[c, 7] = ck.clamp_abs(r3 - s * u[c, 7], mu_s * n0)
        each[c] = rc
        if rc > res or rc != rc:
            res = rc
    return new, res, each


def three_pass_sweep(rows, nc, omega, corrected, want_res):
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = rows
    width = gam.shape[1]
    G = np.ascontiguousarray(gam[:nc].T)
    U = np.empty((width, nc))
    RES = np.empty(nc)
    ck.jacobi_gather(cb, cn, ca, cvw, cbias, croll, v, w, nc, U)
    IB, CR = ck.jacobi_columns(cscale, croll, nc, width == 8)
    ck.jacobi_project(U, G, cmu, cscale, IB, CR, nc, omega, corrected, want_res, RES)
    # RES: the rows' squared residuals
    return G.T.copy(), (math.sqrt(ck.max_nonneg(RES, nc)) if want_res else 0.0), np.sqrt(RES)


@pytest.mark.parametrize("width", [4, 8])
@pytest.mark.parametrize("corrected", [True, False])
@pytest.mark.parametrize("want_res", [True, False])
@pytest.mark.parametrize("omega", [0.3, 1.0])
def test_three_pass_sweep_is_the_row_by_row_sweep_bit_for_bit(width, corrected, want_res, omega):
    rng = np.random.default_rng(100 * width + 10 * corrected + want_res)
    nc, n = 3000, 400
    rows = random_rows(rng, nc, n, width)
    ref, ref_res, ref_each = reference_sweep(rows, nc, omega, corrected, want_res)
    got, got_res, got_each = three_pass_sweep(rows, nc, omega, corrected, want_res)
    # every branch of the projection was taken
    n_t = np.linalg.norm(ref[:, 1:4], axis=1)
    mu = rows[5]
    sliding = (ref[:, 0] > 0) & (mu > 0) & np.isclose(n_t, mu * ref[:, 0], rtol=1e-12)
    sticking = (ref[:, 0] > 0) & (n_t < mu * ref[:, 0] * (1 - 1e-9))
    assert sliding.sum() > 50 and sticking.sum() > 50 and (ref[:, 0] == 0.0).sum() > 50
    assert np.array_equal(got.view(np.int64), ref.view(np.int64))  # bits, signed zeros included
    # the residual (it only decides when a sweep stops) is formed with fewer divisions: the same
    # within rounding
    nan = math.isnan(got_res) and math.isnan(ref_res)
    assert nan or got_res == pytest.approx(ref_res, rel=1e-12, abs=0.0)
    if want_res:
        assert ref_res > 0.0 and np.count_nonzero(ref_each) > nc // 2
        np.testing.assert_allclose(got_each, ref_each, rtol=1e-12, atol=1e-14 * ref_res)
    # the scatter of column impulses is the row scatter's
    cb, cn, ca, croll = rows[0], rows[1], rows[2], rows[7]
    P1, L1, P2, L2 = (np.full((n, 3), 7.0) for _ in range(4))
    ck.accumulate(cb, cn, ca, croll, ref, nc, P1, L1)
    ck.accumulate_columns(cb, cn, ca, croll, np.ascontiguousarray(ref.T), nc, P2, L2)
    assert np.array_equal(P1, P2) and np.array_equal(L1, L2)


def test_max_nonneg_is_the_maximum_and_sees_nan():
    rng = np.random.default_rng(5)
    x = rng.random(1001) * 1e-3
    assert ck.max_nonneg(x, 1001) == x.max()
    assert ck.max_nonneg(x, 10) == x[:10].max()
    assert ck.max_nonneg(x, 0) == 0.0
    x[[3, 700]] = [np.inf, 0.0]
    assert ck.max_nonneg(x, 1001) == np.inf
    for nan in (np.nan, -np.nan):  # either sign bit
        y = x.copy()
        y[500] = nan
        assert math.isnan(ck.max_nonneg(y, 1001))


@pytest.mark.parametrize("t", [1e-7, 1e-5, 1e-3])
def test_apgd_projected_step_without_rolling_is_the_row_by_row_projection(t):
    """Rows of 4 take a branch-free loop; it must give ``project_cone`` row by row, bit for bit."""
    rng = np.random.default_rng(17)
    nc = 3000
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, 400, 4)
    gy = rng.normal(scale=1e-3, size=(nc, 4))
    gy[::9] = 0.0
    gy[::13, 1:] = -0.0  # signed zeros on the tangential rows
    out = np.full((nc, 4), 9.0)
    ck.project_step(gam, gy, t, cmu, croll, nc, out)
    ref = np.array([ck.project_cone(*(gam[c] - t * gy[c]), cmu[c]) for c in range(nc)])
    assert np.array_equal(out.view(np.int64), ref.view(np.int64))
    inside = (ref[:, 0] > 0) & (np.linalg.norm(ref[:, 1:], axis=1) < cmu * ref[:, 0] * (1 - 1e-9))
    moved = out[:, 0] != gam[:, 0] - t * gy[:, 0]  # projected onto the cone's surface or its apex
    assert inside.sum() > 50 and (ref[:, 0] == 0.0).sum() > 50 and moved.sum() > 50


@pytest.mark.parametrize("width", [4, 8])
def test_apgd_trial_sums_are_exact_sums_of_the_row_dot_products(width):
    """The trial's three sums, formed a block of rows at a time, against ``math.fsum`` of the rows'
    dot products (each formed in double, in column order), on more rows than one block."""
    rng = np.random.default_rng(23 + width)
    nc = 1234
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, 400, width)
    scales = (1e-6, 1e-6, 1e-2, 1e-2, 1e-6)
    g_new, y, u_new, gy, gam_k = (rng.normal(scale=s, size=(nc, width)) for s in scales)
    y[::7] = g_new[::7]  # rows whose step is zero
    rows = np.sort(rng.choice(nc, 1100, replace=False)).astype(np.int64)
    args = (g_new, y, u_new, gy, gam_k, rows, cmu, cscale, croll, nc)
    p1, e1, p2, e2, p3, e3, res = ck.apgd_trial_sums(*args, False)
    d1, d2, d3 = [], [], []
    for c in rows:
        kmax = 8 if croll[c, 2] > 0.0 else 4
        a1 = a2 = a3 = 0.0
        for k in range(kmax):
            s = g_new[c, k] - y[c, k]
            a1 += s * (u_new[c, k] - gy[c, k])
            a2 += s * s
            a3 += gy[c, k] * (g_new[c, k] - gam_k[c, k])
        d1.append(a1), d2.append(a2), d3.append(a3)
    for parts, special, terms in ((p1, e1, d1), (p2, e2, d2), (p3, e3, d3)):
        assert special == 0.0
        assert math.fsum(parts) == math.fsum(terms)
    assert res == math.inf
    assert ck.apgd_trial_sums(*args, True)[6] == ck.residual_max(g_new, u_new, cmu, cscale, croll, nc)


@pytest.mark.parametrize("env_factor", [0.0, 2.5e-3])
def test_pairs_entering_the_problem_and_missed_pairs_against_numpy(env_factor):
    """The branch-free pair test of the assembly: which listed pairs enter the problem (gap below
    their envelope, one of the two free), the history of the others zeroed (−0.0 rows too, a row of
    +0.0 left alone), a coincident pair flagged and left out; and the count of missed pairs."""
    rng = np.random.default_rng(31 + int(env_factor > 0))
    n, npairs = 500, 6000
    x = rng.uniform(0.0, 0.011, (n, 3))
    r = rng.uniform(0.8e-3, 1.2e-3, n)
    inv_m = np.where(rng.random(n) < 0.1, 0.0, 1.0)
    pi = rng.integers(0, n, npairs)
    pj = (pi + rng.integers(1, n, npairs)) % n
    x[pj[0]] = x[pi[0]]  # coincident centres
    inv_m[pi[0]] = 1.0
    hist = rng.normal(size=(npairs, 8))
    hist[rng.random(npairs) < 0.5] = 0.0
    hist[::17, 3] = -0.0
    spd = rng.uniform(0.0, 1.0, n) if env_factor else np.zeros(n)
    envelope, env_base = 2e-3, 1e-4
    h0 = hist.copy()
    tk = np.full(npairs, -7, dtype=np.int64)
    m, flags = ck.entering_pairs(pi, pj, hist, x, r, inv_m, envelope, spd, env_base, env_factor, tk)
    d2 = np.sum((x[pj] - x[pi]) ** 2, axis=1)
    env = np.minimum(envelope, np.maximum(env_base, env_factor * np.maximum(spd[pi], spd[pj])))
    if not env_factor:
        env = np.full(npairs, envelope)
    lim = r[pi] + r[pj] + env
    enters = (d2 <= lim * lim) & ((inv_m[pi] != 0) | (inv_m[pj] != 0))
    assert flags == ck.FLAG_COINCIDENT and enters[0]
    expected = np.flatnonzero(enters & (d2 != 0.0))
    assert m == expected.size and np.array_equal(tk[:m], expected)
    assert 0.05 * npairs < m < 0.9 * npairs
    assert np.array_equal(hist[enters].view(np.int64), h0[enters].view(np.int64))
    assert np.array_equal(hist[~enters].view(np.int64), np.zeros_like(h0[~enters]).view(np.int64))
    v = rng.normal(scale=2.0, size=(n, 3))
    h = 1e-3
    missed = ck.missed_pairs(pi, pj, x, v, r, inv_m, h, envelope, spd, env_base, env_factor)
    e = (x[pj] + h * v[pj]) - (x[pi] + h * v[pi])
    ends = np.sum(e * e, axis=1) < (r[pi] + r[pj]) ** 2
    free = (inv_m[pi] != 0) | (inv_m[pj] != 0)
    assert missed == np.count_nonzero(free & ~(d2 <= lim * lim) & ends) > 0
