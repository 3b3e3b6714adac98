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


def block_scales(rng, nc):
    """Random (B_n, B_t, μρ) columns of a block-scaled sweep (B_t < B_n, as the levers make it)."""
    bn = rng.uniform(0.5, 2.0, nc) * 1e-5
    rho = rng.uniform(1.0, 4.0, nc)
    return bn, bn / rho, rho


def reference_sweep(rows, nc, omega, corrected, want_res, block=None):
    """The fused scalar sweep, row by row: new impulses, the largest residual and every row's.
    ``block``: (B_n, B_t, ρ) of a block-scaled update (:func:`ck.project_cone_weighted`)."""
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
        if block is None:
            s = omega * b
            n0, n1, n2, n3 = ck.project_cone(g0 - s * u0, g1 - s * u1, g2 - s * u2, g3 - s * u3, mu)
        else:
            sn, st = omega * block[0][c], omega * block[1][c]
            n0, n1, n2, n3 = ck.project_cone_weighted(
                g0 - sn * u0, g1 - st * u1, g2 - st * u2, g3 - st * u3, mu, mu * block[2][c]
            )
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


def row_residual(gam, u, cmu, cscale, croll, nc):
    """The largest residual of (γ, u) row by row from the scalar helpers (``_residual``,
    ``_roll_residual``), NaN if any row's is NaN: the reference of the residual pass."""
    res = 0.0
    for c in range(nc):
        rc, p0 = ck._residual(*gam[c, :4], *u[c, :4], cscale[c], cmu[c])
        if gam.shape[1] == 8 and croll[c, 2] > 0.0:
            rr = ck._roll_residual(*gam[c, 4:], *u[c, 4:], p0, croll[c, 3], croll[c, 0], croll[c, 1])
            if rr > rc or rr != rr:
                rc = rr
        if rc > res or rc != rc:
            res = rc
    return res


def three_pass_sweep(rows, nc, omega, corrected, want_res, block=None):
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = rows
    width = gam.shape[1]
    G = np.ascontiguousarray(gam[:nc].T)
    U = np.empty((width, nc))
    RES = np.empty(nc)
    ck.jacobi_gather(cb, cn, ca, cvw, cbias, croll, v, w, nc, U)
    IB, CR = ck.jacobi_columns(cscale, croll, nc, width == 8)
    BLK = np.stack([cscale, cscale, cmu]) if block is None else np.stack([block[0], block[1], cmu * block[2]])
    ck.jacobi_project(U, G, cmu, cscale, IB, BLK, CR, nc, omega, corrected, want_res, RES)
    # RES: the rows' squared residuals (left unfilled without want_res)
    if not want_res:
        return G.T.copy(), 0.0, None
    return G.T.copy(), math.sqrt(ck.max_nonneg(RES, nc)), np.sqrt(RES)


@pytest.mark.parametrize("width", [4, 8])
@pytest.mark.parametrize("corrected", [True, False])
@pytest.mark.parametrize("want_res", [True, False])
@pytest.mark.parametrize("omega", [0.3, 1.0])
@pytest.mark.parametrize("block", [False, True])
def test_three_pass_sweep_is_the_row_by_row_sweep_bit_for_bit(width, corrected, want_res, omega, block):
    rng = np.random.default_rng(100 * width + 10 * corrected + want_res)
    nc, n = 3000, 400
    rows = random_rows(rng, nc, n, width)
    blk = block_scales(rng, nc) if block else None
    ref, ref_res, ref_each = reference_sweep(rows, nc, omega, corrected, want_res, blk)
    got, got_res, got_each = three_pass_sweep(rows, nc, omega, corrected, want_res, blk)
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


def _metric_distance(p, y, rho):
    d = p - y
    return d[..., 0] ** 2 + rho * np.sum(d[..., 1:] ** 2, axis=-1)


def _skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def test_weighted_cone_projection_is_the_closest_point_in_its_metric():
    """Π_M(y) of :func:`ck.project_cone_weighted` against brute force: the point of the cone
    nearest y in the metric M = diag(1, ρ, ρ), found by minimizing over a fine grid of the cone's
    points (γ_n ≥ 0, |γ_t| ≤ μ γ_n, γ_t in the tangent plane in any direction); ρ = 1 is the
    Euclidean projection bit for bit."""
    rng = np.random.default_rng(3)
    # candidates: γ_n on a grid, γ_t = s μ γ_n (cos θ, sin θ) in the tangent plane ⊥ x
    gn = np.linspace(0.0, 4.0, 201)[:, None, None]
    s = np.linspace(0.0, 1.0, 41)[None, :, None]
    th = np.linspace(0.0, 2 * np.pi, 73)[None, None, :]
    for _ in range(40):
        mu = rng.choice([0.1, 0.5, 1.0])
        rho = rng.uniform(1.0, 4.0)
        y = rng.normal(size=4)
        y[1] = 0.0
        got = np.array(ck.project_cone_weighted(*y, mu, mu * rho))
        assert got[0] >= 0.0 and np.linalg.norm(got[1:]) <= mu * got[0] * (1 + 1e-12) + 1e-15
        tx, ty = s * mu * gn * np.cos(th), s * mu * gn * np.sin(th)
        cand = np.stack(np.broadcast_arrays(gn, 0.0 * s, tx, ty), -1).reshape(-1, 4)
        assert _metric_distance(got, y, rho) <= _metric_distance(cand, y, rho).min() + 1e-12
        # a projection: no point of the cone is nearer along any direction (M's variational inequality)
        q = cand[rng.integers(0, cand.shape[0], 2000)]
        m = np.array([1.0, rho, rho, rho])
        assert np.all(((y - got) * m) @ (q - got).T <= 1e-10)
        assert ck.project_cone_weighted(*y, mu, mu) == ck.project_cone(*y, mu)


def test_block_columns_are_the_inverse_diagonal_of_the_delassus_block():
    """B_n, B_t of :func:`ck.block_columns` against the contact's 3 × 3 Delassus block formed from
    its Jacobian (the velocities' change per unit impulse, as ``accumulate`` and ``velocities`` apply
    it): diagonal in the contact frame, with B_n = 1/D_nn and B_t = 1/D_tt; and the trace scaling is
    ``cscale``."""
    rng = np.random.default_rng(8)
    nc, n = 50, 30
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, n, 4)
    inv_m = rng.uniform(0.5, 2.0, n) * 1e3
    inv_i = rng.uniform(0.5, 2.0, n) * 1e8
    blk = ck.block_columns(cb, ca, cmu, cscale, inv_m, inv_i, nc, True)
    for c in range(nc):
        i, j = cb[c]
        nvec = cn[c]
        t1 = np.cross(nvec, [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(nvec, t1)
        frame = np.stack([nvec, t1, t2])

        D = np.zeros((3, 3))
        # the contact velocity per unit body velocities, v + ω × r = v − r × ω, in the contact frame
        for body, lever, sign in ((j, -ca[c, 1] * nvec, 1.0), (i, ca[c, 0] * nvec, -1.0)):
            if body < 0:
                continue
            jv, jw = sign * frame, sign * frame @ (-_skew(lever))
            D += inv_m[body] * jv @ jv.T + inv_i[body] * jw @ jw.T
        assert np.allclose(D - np.diag(np.diag(D)), 0.0, atol=1e-12 * np.abs(D).max())
        assert blk[0, c] == pytest.approx(1.0 / D[0, 0], rel=1e-12)
        assert blk[1, c] == pytest.approx(1.0 / D[1, 1], rel=1e-12)
        assert blk[2, c] == pytest.approx(cmu[c] * D[1, 1] / D[0, 0], rel=1e-12)
    trace = ck.block_columns(cb, ca, cmu, cscale, inv_m, inv_i, nc, False)
    assert np.array_equal(trace, np.stack([cscale, cscale, cmu]))


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


NO_BLK = np.empty((3, 0))


def cols(a):
    """Rows (nc, width) as APGD holds them: in columns, C-contiguous (width, nc)."""
    return np.ascontiguousarray(a.T)


def row_dots(g_new, y, u_new, gy, gam_k, croll, rows):
    """A line-search trial's three dot products per row, each formed in double in component order
    (rolling components only where the row has them): the reference of the column kernels."""
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
    return np.array(d1), np.array(d2), np.array(d3)


@pytest.mark.parametrize("width", [4, 8])
@pytest.mark.parametrize("t", [1e-7, 1e-5, 1e-3])
def test_apgd_projected_step_is_the_row_by_row_projection(width, t):
    """Π(y − t ũ(y)) on columns (rows of 4 through a branch-free loop) must give ``project_cone``
    and the rolling clamps row by row (``project_cone_array``), bit for bit; ũ's normal row is held
    apart from u's other rows. The trial's |γ − y|² and ũ(y)·(γ − γ_k) formed in the same pass are
    the row formulas' bits."""
    rng = np.random.default_rng(17 + width)
    nc = 3000
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, 400, width)
    gy = rng.normal(scale=1e-3, size=(nc, width))
    gy[::9] = 0.0
    gy[::13, 1:] = -0.0  # signed zeros on the tangential rows
    gyn = rng.normal(scale=1e-3, size=nc)  # ũ_n(y)
    gyn[::9] = 0.0
    gam_k = rng.normal(scale=1e-6, size=(nc, width))
    out = np.full((width, nc), 9.0)
    D2, D3 = np.full((2, nc), 9.0)
    GY = cols(gy)
    GY[0] = 7.0  # u's own normal row is not read: ũ_n comes from gyn
    ck.apgd_project_step(cols(gam), GY, gyn, cols(gam_k), t, cmu, croll, nc, out, D2, D3, True, NO_BLK, False)
    full = gy.copy()
    full[:, 0] = gyn
    ref = ck.project_cone_array(gam - t * full, cmu, croll)
    assert np.array_equal(out.T.view(np.int64), ref.view(np.int64))
    inside = (ref[:, 0] > 0) & (np.linalg.norm(ref[:, 1:4], axis=1) < cmu * ref[:, 0] * (1 - 1e-9))
    moved = out[0] != gam[:, 0] - t * gyn  # projected onto the cone's surface or its apex
    assert inside.sum() > 50 and (ref[:, 0] == 0.0).sum() > 50 and moved.sum() > 50
    if width == 8:
        assert np.any(out[4:] != 0.0) and np.all(out[4:, croll[:, 2] == 0.0] == 0.0)
    _, d2, d3 = row_dots(ref, gam, full, full, gam_k, croll, range(nc))
    assert np.array_equal(D2.view(np.int64), d2.view(np.int64))
    assert np.array_equal(D3.view(np.int64), d3.view(np.int64))
    out2 = np.full((width, nc), 9.0)
    E2, E3 = np.full((2, nc), 5.0)
    ck.apgd_project_step(
        cols(gam), GY, gyn, cols(gam_k), t, cmu, croll, nc, out2, E2, E3, False, NO_BLK, False
    )
    assert np.array_equal(out2, out) and np.all(E2 == 5.0) and np.all(E3 == 5.0)  # no trial: not formed


@pytest.mark.parametrize("width", [4, 8])
def test_apgd_block_scaled_step_is_the_metric_projection_of_the_scaled_step(width):
    """With the block scaling, APGD's step is Π_M(y − t B ũ(y)), M = B⁻¹ (B = B_n on the normal row,
    B_t on the tangential ones, B_r on the rolling rows), and its |γ − y|² is measured in M: row by
    row from :func:`ck.project_cone_weighted` and the rolling clamps (the same bits), and the
    M-norm within rounding."""
    rng = np.random.default_rng(23 + width)
    nc, t = 2000, 1e-5
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, 400, width)
    bn, bt, rho = block_scales(rng, nc)
    blk = np.stack([bn, bt, cmu * rho])
    gy = rng.normal(scale=1e-3, size=(nc, width)) / bn[:, None]  # steps t B ũ of the impulses' size
    gam_k = rng.normal(scale=1e-6, size=(nc, width))
    out = np.full((width, nc), 9.0)
    D2, D3 = np.full((2, nc), 9.0)
    ck.apgd_project_step(cols(gam), cols(gy), gy[:, 0].copy(), cols(gam_k), t, cmu, croll, nc, out, D2, D3,
                         True, blk, True)  # fmt: skip
    ref = np.zeros((nc, width))
    m2 = np.zeros(nc)
    for c in range(nc):
        y = gam[c, :4] - t * np.array([bn[c], bt[c], bt[c], bt[c]]) * gy[c, :4]
        ref[c, :4] = ck.project_cone_weighted(*y, cmu[c], cmu[c] * rho[c])
        if width == 8 and croll[c, 2] > 0.0:
            r = gam[c, 4:] - t * croll[c, 3] * gy[c, 4:]
            ref[c, 4:7] = ck.clamp_norm(r[0], r[1], r[2], croll[c, 0] * ref[c, 0])
            ref[c, 7] = ck.clamp_abs(r[3], croll[c, 1] * ref[c, 0])
            m2[c] = np.sum((ref[c, 4:] - gam[c, 4:]) ** 2) / croll[c, 3]
        d = ref[c, :4] - gam[c, :4]
        m2[c] += d[0] ** 2 / bn[c] + np.sum(d[1:] ** 2) / bt[c]
    assert np.array_equal(out.T.view(np.int64), ref.view(np.int64))
    moved = (ref[:, 0] == 0.0) | (np.abs(ref[:, 0] - (gam[:, 0] - t * bn * gy[:, 0])) > 0.0)
    assert moved.sum() > 50
    np.testing.assert_allclose(D2, m2, rtol=1e-12)
    counted = np.arange(width) < 4 + 4 * (croll[:, 2:3] > 0)  # the rolling rows where the contact has them
    np.testing.assert_allclose(D3, np.sum(gy * (ref - gam_k) * counted, 1), rtol=1e-12, atol=1e-30)


@pytest.mark.parametrize("width", [4, 8])
@pytest.mark.parametrize("corrected", [True, False])
def test_apgd_gather_trial_dot_and_residual_are_the_row_formulas(width, corrected):
    """u = Dᵀv + b on columns is ``contact_velocities_raw`` row by row (rolling rows 0.0 where a
    contact has none), ũ_n = u_n + μ|u_t|; the trial's (γ − y)·(ũ(γ) − ũ(y)) formed in the same pass
    is the row formula's, the residual's pass the row formula's; the extrapolated velocities are
    u + β (u − u_k) and their ũ_n: all bit for bit."""
    rng = np.random.default_rng(41 + width + 2 * corrected)
    nc, n = 2000, 300
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, n, width)
    uraw = np.full((nc, width), 5.0)
    u = np.full((nc, width), 5.0)
    ck.contact_velocities_raw(cb, cn, ca, cvw, cbias, croll, cmu, v, w, nc, uraw, u, corrected)
    y = rng.normal(scale=1e-6, size=(nc, width))
    gy = rng.normal(scale=1e-2, size=(nc, width))
    gyn = rng.normal(scale=1e-2, size=nc) if corrected else gy[:, 0].copy()
    U = np.full((width, nc), 9.0)
    UN = np.full(nc, 9.0)
    D1 = np.full(nc, 9.0)
    ck.apgd_gather(cb, cn, ca, cvw, cbias, croll, cmu, v, w, nc, U, UN, corrected, cols(gam), cols(y),
                   cols(gy), gyn, D1, True)  # fmt: skip
    assert np.array_equal(U.T.view(np.int64), uraw.view(np.int64))
    if corrected:
        assert np.array_equal(UN.view(np.int64), u[:, 0].view(np.int64))
        assert not np.array_equal(UN, U[0])
    else:
        assert np.all(UN == 9.0)  # not written
    full_gy = gy.copy()
    full_gy[:, 0] = gyn
    ut = u if corrected else uraw  # ũ (the relaxed cone: u itself; contact_velocities_raw left u alone)
    d1, _, _ = row_dots(gam, y, ut, full_gy, gam, croll, range(nc))
    assert np.array_equal(D1.view(np.int64), d1.view(np.int64))
    # the residual's pass: the row formula's value (rows of 4 without branches)
    ref_res = row_residual(gam, ut, cmu, cscale, croll, nc)
    res = ck.apgd_residual(U.copy(), U, UN if corrected else U[0], cmu, cscale, croll, nc, np.empty(nc))
    assert res == row_residual(U.T.copy(), ut, cmu, cscale, croll, nc)
    res = ck.apgd_residual(cols(gam), U, UN if corrected else U[0], cmu, cscale, croll, nc, np.empty(nc))
    assert ref_res > 0.0 and res == ref_res
    bad = gam.copy()
    bad[77, 1] = np.nan
    res = ck.apgd_residual(cols(bad), U, UN if corrected else U[0], cmu, cscale, croll, nc, np.empty(nc))
    assert math.isnan(res) and math.isnan(row_residual(bad, ut, cmu, cscale, croll, nc))
    none = np.empty((width, 0))
    D1[:] = 9.0
    ck.apgd_gather(cb, cn, ca, cvw, cbias, croll, cmu, v, w, nc, U, UN, corrected, cols(gam), none, none, gyn,
                   D1, False)  # fmt: skip
    assert np.all(D1 == 9.0) and np.array_equal(U.T, uraw)
    uk = rng.normal(size=(nc, width))
    beta = 0.37
    GY = np.empty((width, nc))
    GYN = np.full(nc, 9.0)
    ck.apgd_extrapolate_velocities(U, cols(uk), beta, cmu, nc, GY, GYN, corrected)
    ref = uraw + beta * (uraw - uk)
    assert np.array_equal(GY.T.view(np.int64), ref.view(np.int64))
    if corrected:
        ref_n = ref[:, 0] + cmu * np.sqrt(ref[:, 1] ** 2 + ref[:, 2] ** 2 + ref[:, 3] ** 2)
        np.testing.assert_array_equal(GYN, ref_n)
    Y = np.empty((width, nc))
    ck.apgd_extrapolate(cols(gam), cols(uk), beta, nc, Y)
    assert np.array_equal(Y.T.view(np.int64), (gam + beta * (gam - uk)).view(np.int64))


@pytest.mark.parametrize("all_rows", [True, False])
def test_apgd_trial_sums_are_exact_sums_of_the_per_contact_dot_products(all_rows):
    """The trial's three sums over the counted rows (all, or a sorted subset as under MPI), on more
    rows than one block, against ``math.fsum``; a non-finite term goes to the plain sum."""
    rng = np.random.default_rng(23 + all_rows)
    nc = 1234
    D = rng.normal(size=(3, nc)) * np.exp(rng.uniform(-60, 10, (3, nc)))
    rows = np.arange(nc) if all_rows else np.sort(rng.choice(nc, 1100, replace=False))
    rows = rows.astype(np.int64)
    p1, e1, p2, e2, p3, e3 = ck.apgd_trial_sums(D[0], D[1], D[2], rows, all_rows, nc)
    for parts, special, terms in ((p1, e1, D[0]), (p2, e2, D[1]), (p3, e3, D[2])):
        assert special == 0.0
        assert math.fsum(parts) == math.fsum(terms[rows])
    D[1, rows[5]] = np.inf
    assert ck.apgd_trial_sums(D[0], D[1], D[2], rows, all_rows, nc)[3] == np.inf


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


@pytest.mark.parametrize("width", [4, 8])
def test_scatter_skips_zero_impulses_without_changing_a_bit(width):
    """``accumulate_columns`` skips contacts whose impulses are all ±0.0 (half the rows of the
    hopper's problems): the sums are still the row scatter's bit for bit, with −0.0 impulses, sums
    that cancel to zero, and bodies that only have zero contacts."""
    rng = np.random.default_rng(61 + width)
    nc, n = 3000, 400
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, v, w = random_rows(rng, nc, n, width)
    gam[rng.random(nc) < 0.5] = 0.0
    gam[rng.random(nc) < 0.1] = -0.0
    gam[5, 0] = -0.0  # one negative zero among non-zero rows
    for k in range(width):  # rows with one non-zero component: not skipped
        gam[20 + k] = 0.0
        gam[20 + k, k] = 1e-6
        croll[20 + k] = (0.1, 0.05, 5e-4, 1e-3) if width == 8 else 0.0
    if width == 8:
        gam[9, :4] = 0.0  # a rolling impulse alone
        croll[9] = (0.1, 0.05, 5e-4, 1e-3)
    # a pair of contacts whose impulses cancel exactly on a body
    cb[10], cb[11] = (3, 4), (3, 5)
    cn[10], cn[11] = cn[12], -cn[12]
    gam[10, :4], gam[11, :4] = (1e-6, 0.0, 0.0, 0.0), (1e-6, 0.0, 0.0, 0.0)
    P1, L1, P2, L2 = (np.full((n, 3), 7.0) for _ in range(4))
    ck.accumulate(cb, cn, ca, croll, gam, nc, P1, L1)
    ck.accumulate_columns(cb, cn, ca, croll, np.ascontiguousarray(gam.T), nc, P2, L2)
    assert np.array_equal(P1.view(np.int64), P2.view(np.int64))
    assert np.array_equal(L1.view(np.int64), L2.view(np.int64))
    assert (P1 == 0.0).any() and not np.signbit(P1[P1 == 0.0]).any()
