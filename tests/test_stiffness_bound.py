"""The live step bound from the contacts' stiffness (pdem.contact.stability).

Checked against independent references: the law's force differentiated numerically (S_n, k_t),
the largest eigenvalue of the assembled mass-weighted stiffness matrix of small packings (the bound
must lie above it: it is a Gershgorin-type bound), and a linear oscillator's stability limit under
pdem's own velocity Verlet.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from decks import TRIAXIAL_SMALL_PACKED

import pdem
from pdem.contact.stability import network_bound, step_bound, supported
from pdem.errors import InstabilityError
from pdem.laws.hertz_mindlin import force_numpy
from pdem.materials import effective_moduli


def _glass(sim, **kw):
    props = dict(density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.6, friction=0.5)
    props.update(kw)
    sim.add_material("glass", **props)


@pytest.mark.parametrize("form", ["material", "coefficients"])
def test_contact_stiffness_is_the_derivative_of_the_kernels_force(form):
    """S_n = dF_n/dδ and k_t = dF_t/dξ of the law's own force (plain-Python twin), at several
    overlaps, for both parameterisations."""
    params = {} if form == "material" else dict(
        parameterisation="coefficients", kn=2e7, kt=1.5e7, cn=40.0, ct=20.0
    )
    sim = pdem.Simulation(law="hertz_mindlin", **params)
    _glass(sim)
    sim.add_particles([[0, 0, 0]], [1e-3], material="glass")
    sim.prepare()
    law, coef = sim.law, sim.coefficients
    r_eff, m_eff = 5e-4, 4e-6
    for delta in (1e-7, 1e-6, 1e-5):
        s_n, k_t = law.contact_stiffness(
            coef, np.array([0]), np.array([0]), np.array([r_eff]), np.array([m_eff]), np.array([delta])
        )
        n = np.array([0.0, 0.0, 1.0])
        z = np.zeros(3)

        def force(d, vrel=z, hist=None, n=n, z=z):
            h0 = np.zeros(3) if hist is None else hist
            return force_numpy(d, n, vrel, z, r_eff, m_eff, 1e-12, coef[0, 0], h0, 1.0)[0]

        h = delta * 1e-6
        assert s_n[0] == pytest.approx((force(delta + h)[2] - force(delta - h)[2]) / (2 * h), rel=1e-5)
        # the tangential spring: a slip speed s over dt = 1 from a spring at ξ0 gives
        # F_t = −k_t (ξ0 + s) − c_t s: two springs at the same speed give k_t
        s = 1e-9  # below the Coulomb cap at every δ here
        vt = np.array([s, 0.0, 0.0])
        f1 = force(delta, vt, np.zeros(3))[0]
        f2 = force(delta, vt, vt.copy())[0]
        assert k_t[0] == pytest.approx(-(f2 - f1) / s, rel=1e-4)


def test_frictionless_contact_has_no_tangential_spring():
    sim = pdem.Simulation()
    _glass(sim, friction=0.0)
    sim.add_particles([[0, 0, 0]], [1e-3], material="glass")
    sim.prepare()
    _, k_t = sim.law.contact_stiffness(
        sim.coefficients, np.array([0]), np.array([0]), np.array([5e-4]), np.array([1e-6]), np.array([1e-6])
    )
    assert k_t[0] == 0.0


def _packing(seed: int, n_side: int = 3, squeeze: float = 0.985):
    """A jittered simple-cubic cluster of slightly different spheres, squeezed into contact."""
    rng = np.random.default_rng(seed)
    r = 1e-3 * (1.0 + 0.1 * rng.random(n_side**3))
    g = np.stack(np.meshgrid(*[np.arange(n_side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = g * 2e-3 * squeeze + 1e-5 * rng.standard_normal(g.shape)
    return x, r


def _exact_top(sim) -> float:
    """Largest eigenvalue of M^-1/2 K M^-1/2 for the touching pairs, assembled from scratch."""
    p = sim.get_particles()
    x, r, m = p["x"], p["r"], p["mass"]
    mat = sim.materials[0]
    e_star, g_star = effective_moduli(mat, mat)
    n = len(r)
    inertia = 0.4 * m * r * r
    k = np.zeros((6 * n, 6 * n))
    for i in range(n):
        for j in range(i + 1, n):
            d = x[j] - x[i]
            dist = np.linalg.norm(d)
            delta = r[i] + r[j] - dist
            if delta <= 0:
                continue
            nv = d / dist
            a = math.sqrt(r[i] * r[j] / (r[i] + r[j]) * delta)
            c = 2 * e_star * a * np.outer(nv, nv) + 8 * g_star * a * (np.eye(3) - np.outer(nv, nv))
            # relative displacement of the contact point: u_j + φ_j × (−r_j n) − u_i − φ_i × (r_i n)
            def skew(v):
                return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

            b = np.zeros((3, 6 * n))
            b[:, 6 * j : 6 * j + 3] = np.eye(3)
            b[:, 6 * j + 3 : 6 * j + 6] = skew(r[j] * nv)  # φ × (−r n) = (r n) × φ
            b[:, 6 * i : 6 * i + 3] = -np.eye(3)
            b[:, 6 * i + 3 : 6 * i + 6] = skew(r[i] * nv)  # −φ × (r n) = (r n) × φ
            k += b.T @ c @ b
    w = np.repeat(np.stack([m, m, m, inertia, inertia, inertia], 1).reshape(-1), 1)
    s = 1.0 / np.sqrt(w)
    return float(np.linalg.eigvalsh(s[:, None] * k * s[None, :]).max())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bound_lies_above_the_networks_largest_eigenvalue(seed):
    """The bound's Ω² is ≥ the exact largest eigenvalue of the linearised network (rigorous), and
    not absurdly above it (≤ 4×: Ω within 2×)."""
    sim = pdem.Simulation()
    _glass(sim, restitution=1.0)
    x, r = _packing(seed)
    sim.add_particles(x, r, material="glass")
    sim.dt = 1e-9
    sim.max_overlap = 1.0
    sim.run(steps=1)
    top = network_bound(sim)
    exact = _exact_top(sim)
    assert exact > 0
    assert top >= exact * (1 - 1e-9)
    assert top <= 4.0 * exact
    assert step_bound(sim) == pytest.approx(2.0 / math.sqrt(top))


def test_sliding_contact_linearisation_is_what_the_bound_assumes():
    """At the Coulomb cap the law's own force (plain-Python twin) has no stiffness for further slip,
    k_t across it, and a tangential force that follows the normal one at a slope of at most μ S_n
    (μ S_n unloading, μ S_n/3 loading, as the spring's k_t grows slower than F_n); contact_slip flags
    exactly that state, with the spring's direction and the slope μ S_n, and not a spring below it."""
    sim = pdem.Simulation()
    _glass(sim, restitution=1.0)  # μ = 0.5, no dashpots
    sim.add_particles([[0, 0, 0]], [1e-3], material="glass")
    sim.prepare()
    law, coef = sim.law, sim.coefficients
    r_eff, m_eff, delta, mu = 5e-4, 4e-6, 1e-6, 0.5
    one = [np.array([v]) for v in (0, 0, r_eff, m_eff)]
    got = law.contact_stiffness(coef, one[0], one[1], one[2], one[3], np.array([delta]))
    s_n, k_t = (float(q[0]) for q in got)
    n, z = np.array([0.0, 0.0, 1.0]), np.zeros(3)

    def force(d, move=z, xi=None):
        h0 = np.zeros(3) if xi is None else xi.copy()
        return force_numpy(d, n, move, z, r_eff, m_eff, 1e-12, coef[0, 0], h0, 1.0)[0]

    cap = mu * force(delta)[2]
    xi = np.array([cap / k_t, 0.0, 0.0])
    dirs, slope = law.contact_slip(
        coef, one[0], one[1], one[2], one[3], np.array([delta]), np.zeros(1), xi[None, :]
    )
    assert np.allclose(dirs[0], [1.0, 0.0, 0.0]) and slope[0] == pytest.approx(mu * s_n)
    dirs, slope = law.contact_slip(coef, one[0], one[1], one[2], one[3], np.array([delta]), np.zeros(1),
                                   0.5 * xi[None, :])  # fmt: skip
    assert not np.any(dirs) and slope[0] == 0.0
    base = force(delta, xi=xi)
    assert base[0] == pytest.approx(-cap, rel=1e-12)
    h = 1e-4 * xi[0]
    assert force(delta, np.array([h, 0.0, 0.0]), xi)[0] == pytest.approx(base[0], rel=1e-12)  # slip on
    across = (force(delta, np.array([0.0, h, 0.0]), xi)[1] - base[1]) / h
    assert across == pytest.approx(-k_t, rel=1e-3)
    hd = 1e-5 * delta
    unload = (force(delta - hd, xi=xi)[0] - base[0]) / -hd
    load = (force(delta + hd, xi=xi)[0] - base[0]) / hd
    assert unload == pytest.approx(-mu * s_n, rel=1e-3)
    assert abs(load) == pytest.approx(mu * s_n / 3, rel=1e-3)


def _flat_pair(slide: bool):
    """Two spheres in the xz plane (2-D mode: no y translation, no turning about x or z), pressed
    along a normal 30° off z; one step with the upper sphere moving across the normal (fast enough
    to slide, or not)."""
    sim = pdem.Simulation()
    _glass(sim, restitution=1.0)
    r = 1e-3
    nrm = np.array([math.sin(math.pi / 6), 0.0, math.cos(math.pi / 6)])
    tan = np.array([nrm[2], 0.0, -nrm[0]])
    speed = 2.0 if slide else 1e-5  # per step 2e-6 m (the cap's spring is 8e-7 m) or 1e-11 m
    sim.add_particles(
        [[0, 0, 0], (1.9 * r - 2e-6) * nrm], [r, 0.9 * r], material="glass",
        velocities=[[0, 0, 0], speed * tan], fixed_translation="y", fixed_rotation="xz",
    )  # fmt: skip
    sim.dt = 1e-6
    sim.max_overlap = 1.0
    sim.run(steps=1)
    return sim


def _locked_norm(sim) -> float:
    """‖M^-½ K M^-½‖₂ over the free axes, K assembled from scratch for the one contact: normal spring
    S_n, tangential k_t, or at the cap no stiffness along the spring, k_t across it and the coupling
    −μ S_n (force on j along the spring per unit of normal separation)."""
    p = sim.get_particles()
    x, r, m = p["x"], p["r"], p["mass"]
    mat = sim.materials[0]
    e_star, g_star = effective_moduli(mat, mat)
    d = x[1] - x[0]
    dist = np.linalg.norm(d)
    nv = d / dist
    delta = r[0] + r[1] - dist
    r_eff = r[0] * r[1] / (r[0] + r[1])
    a = math.sqrt(r_eff * delta)
    s_n, k_t = 2 * e_star * a, 8 * g_star * a
    xi = sim.contact_store.hist[0, :3]
    cap = 0.5 * 4 / 3 * e_star * a * delta
    if k_t * np.linalg.norm(xi) >= cap * (1 - 1e-9):
        t1 = xi / np.linalg.norm(xi)
        t2 = np.cross(nv, t1)
        c = s_n * np.outer(nv, nv) - 0.5 * s_n * np.outer(t1, nv) + k_t * np.outer(t2, t2)
    else:
        c = s_n * np.outer(nv, nv) + k_t * (np.eye(3) - np.outer(nv, nv))

    def skew(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    b = np.zeros((3, 12))
    b[:, 6:9] = np.eye(3)
    b[:, 9:12] = skew(r[1] * nv)
    b[:, 0:3] = -np.eye(3)
    b[:, 3:6] = skew(r[0] * nv)
    k = b.T @ c @ b
    w = np.concatenate([[mi] * 3 + [0.4 * mi * ri * ri] * 3 for mi, ri in zip(m, r, strict=True)])
    s = 1.0 / np.sqrt(w)
    k = s[:, None] * k * s[None, :]
    free = np.array([True, False, True, False, True, False] * 2)  # x, z translation; turning about y
    return float(np.linalg.norm(k[np.ix_(free, free)], 2))


@pytest.mark.parametrize("slide", [False, True])
def test_locked_axes_and_sliding_single_contact_matches_the_assembled_norm(slide):
    """One contact (so the bound is the contact's norm itself): the 3 × 3 Gram route of the bound
    equals the norm of the 12 × 12 matrix assembled over the free axes; sliding in the plane leaves
    the normal spring and the coupling (the out-of-plane direction is locked): for ν = 0.3 and
    μ = 0.5, λ_n sqrt(1 + 3.5 μ²) = 1.37 λ_n against λ_t = 2.88 λ_n sticking, 2.1× less."""
    sim = _flat_pair(slide)
    xi = sim.contact_store.hist[0, :3]
    assert abs(xi[1]) < 1e-12 * np.linalg.norm(xi)  # the spring is in the plane
    assert network_bound(sim) == pytest.approx(_locked_norm(sim), rel=1e-9)
    if slide:
        stuck = _flat_pair(False)
        assert network_bound(stuck) > 2.0 * network_bound(sim)


def test_bound_lies_above_the_spectral_radius_of_a_flat_bed():
    """A hexagonal layer in 2-D mode, squeezed, with random in-plane velocities (some contacts slide):
    the bound is ≥ the spectral radius of the assembled, non-symmetric linearised network over the
    free axes, and within 4× of it."""
    sim = pdem.Simulation()
    _glass(sim, restitution=1.0, friction=0.3)
    rng = np.random.default_rng(3)
    r = 1e-3
    rows, cols = 5, 6
    pts = [
        [(2 * c + (q % 2)) * r * 0.995, 0.0, q * math.sqrt(3) * r * 0.995]
        for q in range(rows)
        for c in range(cols)
    ]
    n = len(pts)
    v = rng.normal(0.0, 1.0, (n, 3))  # ~1e-6 m a step, past the cap's spring (~1e-6 m at δ = 1e-5 m)
    v[:, 1] = 0.0
    sim.add_particles(pts, r, material="glass", velocities=v, fixed_translation="y", fixed_rotation="xz")
    sim.dt = 1e-6
    sim.max_overlap = 1.0
    sim.run(steps=3)
    p = sim.get_particles()
    x, m = p["x"], p["mass"]
    mat = sim.materials[0]
    e_star, g_star = effective_moduli(mat, mat)
    cs = sim.contact_store
    ids = sim.particles.id
    row_of = {int(i): k for k, i in enumerate(p["id"])}
    k_full = np.zeros((6 * n, 6 * n))
    sliding = 0

    def skew(q):
        return np.array([[0, -q[2], q[1]], [q[2], 0, -q[0]], [-q[1], q[0], 0]])

    for c in range(cs.pi.shape[0]):
        i, j = row_of[int(ids[cs.pi[c]])], row_of[int(ids[cs.pj[c]])]
        d = x[j] - x[i]
        dist = np.linalg.norm(d)
        delta = 2 * r - dist
        if delta <= 0:
            continue
        nv = d / dist
        a = math.sqrt(0.5 * r * delta)
        s_n, k_t = 2 * e_star * a, 8 * g_star * a
        xi = cs.hist[c, :3]
        cap = 0.3 * 4 / 3 * e_star * a * delta
        if k_t * np.linalg.norm(xi) >= cap * (1 - 1e-9):
            sliding += 1
            t1 = xi / np.linalg.norm(xi)
            t2 = np.cross(nv, t1)
            cm = s_n * np.outer(nv, nv) - 0.3 * s_n * np.outer(t1, nv) + k_t * np.outer(t2, t2)
        else:
            cm = s_n * np.outer(nv, nv) + k_t * (np.eye(3) - np.outer(nv, nv))
        b = np.zeros((3, 6 * n))
        b[:, 6 * j : 6 * j + 3] = np.eye(3)
        b[:, 6 * j + 3 : 6 * j + 6] = skew(r * nv)
        b[:, 6 * i : 6 * i + 3] = -np.eye(3)
        b[:, 6 * i + 3 : 6 * i + 6] = skew(r * nv)
        k_full += b.T @ cm @ b
    w = np.repeat(np.stack([m, m, m, 0.4 * m * r * r, 0.4 * m * r * r, 0.4 * m * r * r], 1).reshape(-1), 1)
    s = 1.0 / np.sqrt(w)
    k_full = s[:, None] * k_full * s[None, :]
    free = np.tile([True, False, True, False, True, False], n)
    rho = float(np.abs(np.linalg.eigvals(k_full[np.ix_(free, free)])).max())
    assert 0 < sliding < cs.pi.shape[0]
    top = network_bound(sim)
    assert rho <= top * (1 + 1e-9)
    assert top <= 4.0 * rho


def test_sphere_on_floor_closed_form():
    """One sphere pressed into a floor, frictionless: Ω² = S_n/m exactly (the dashpot of e = 0.5
    does not enter)."""
    sim = pdem.Simulation()
    _glass(sim, friction=0.0, restitution=0.5)
    r = 1e-3
    delta = 2e-6
    sim.add_particles([[0, 0, r - delta]], [r], material="glass")
    sim.add_wall(pdem.shapes.Plane((0, 0, 0), (0, 0, 1)), material="glass", name="floor")
    sim.dt = 1e-9
    sim.run(steps=1)
    p = sim.get_particles()
    m = float(p["mass"][0])
    ov = r - float(p["x"][0, 2])
    mat = sim.materials[0]
    e_star, _ = effective_moduli(mat, mat)  # the wall is glass too
    s_n = 2 * e_star * math.sqrt(r * ov)
    expect = 2 / math.sqrt(s_n / m)
    assert step_bound(sim) == pytest.approx(expect, rel=1e-9)


def _squeezed(frac_of_bound: float | None, bound: float = 0.0):
    """A sphere between a floor and a ceiling 2 (r − 1e-5) apart, started 5e-6 off centre: a
    frictionless, undamped nonlinear oscillator whose stiffest state is the start."""
    sim = pdem.Simulation()
    _glass(sim, friction=0.0, restitution=1.0)
    r = 1e-3
    gap = 1e-5
    sim.add_particles([[0, 0, r - gap - 5e-6]], [r], material="glass")
    sim.add_wall(pdem.shapes.Plane((0, 0, 0), (0, 0, 1)), material="glass", name="floor")
    sim.add_wall(pdem.shapes.Plane((0, 0, 2 * (r - gap)), (0, 0, -1)), material="glass", name="ceiling")
    sim.max_overlap = 0.5
    sim.stiffness_every = 1
    if frac_of_bound is None:
        sim.dt = 1e-10
    else:
        sim.force_dt = True
        sim.dt = frac_of_bound * bound
    return sim


def test_oscillator_is_stable_below_the_bound_and_not_far_above():
    """pdem's velocity Verlet on the squeezed sphere: at 0.9 of the bound (taken at the stiffest
    state) the motion stays bounded over many periods; at 2.5× it grows without bound or is caught."""
    probe = _squeezed(None)
    probe.run(steps=1)
    bound = probe.stiffness["min_dt"]
    assert math.isfinite(bound)

    def amplitude(frac):
        sim = _squeezed(frac, bound)
        top = 0.0
        try:
            for _ in range(40):
                sim.run(steps=25)
                top = max(top, abs(float(sim.get_particles()["v"][0, 2])))
        except InstabilityError:
            return math.inf
        return top

    stable = amplitude(0.9)
    assert math.isfinite(stable) and stable < 1.0
    assert amplitude(2.5) > 10 * stable


def test_supported_laws():
    sim = pdem.Simulation()
    assert supported(sim.law)
    sim_c = pdem.Simulation(law="complementarity")
    assert not supported(sim_c.law)


# ---------------------------------------------------------------------------------------------
# through the CLI: a step the contacts cannot bear is stopped, or warned of when allowed
# ---------------------------------------------------------------------------------------------

DECK = Path(__file__).parent / "data" / "triaxial_small.toml"  # 300 beads, E = 5e7 Pa, dt = 2e-6 s
RUN = [DECK, *TRIAXIAL_SMALL_PACKED]  # the deck with its beads read from the shared packing


def _pdem(*args):
    return subprocess.run([sys.executable, "-m", "pdem", *map(str, args)], capture_output=True, text=True,
                          timeout=600)


@pytest.mark.integration
def test_run_below_the_bound_records_it(tmp_path):
    proc = _pdem(*RUN, "--output", tmp_path / "ok", "--quiet")
    assert proc.returncode == 0, proc.stderr
    s = json.loads((tmp_path / "ok" / "summary.json").read_text())
    b = s["stiffness_bound"]
    assert b["checks"] == 16 + 7 and b["checks_exceeded"] == 0  # every 100 of 1,600 steps, and 1, 2, …, 64
    # the bound is below the Rayleigh estimate in this dense, frictional sample, and the deck's
    # step is below the bound
    assert s["dt"] < b["dt_min"] < s["dt_critical"]
    assert "warning" not in proc.stdout


def test_step_above_the_limit_stops_with_exit_3_and_keeps_the_output(tmp_path):
    out = tmp_path / "big"
    proc = _pdem(*RUN, "--output", out, "--set", "run.dt=1e-5")
    assert proc.returncode == 3, proc.stdout + proc.stderr
    msg = proc.stderr
    assert "run.stiffness_limit = 1.25" in msg and "dt = 1e-05 s" in msg and "run.dt_fraction" in msg
    assert "Traceback" not in msg
    # what was written before the stop stays readable
    series = np.genfromtxt(out / "series_settle.csv", delimiter=",", names=True)
    assert series.size > 0 and np.all(np.isfinite(series["time"]))
    assert (out / "checkpoints" / "latest.h5").exists()


def test_limit_zero_lets_the_run_go_on_with_a_warning(tmp_path):
    out = tmp_path / "allowed"
    proc = _pdem(*RUN, "--output", out, "--set", "run.dt=1e-5", "--set", "run.stiffness_limit=0")
    assert proc.returncode == 0, proc.stderr
    b = json.loads((out / "summary.json").read_text())["stiffness_bound"]
    assert b["checks_exceeded"] > 0 and b["dt_over_bound"] > 1.3
    assert "warning: dt = 1e-05 s exceeded the step the contact network bore" in proc.stdout


@pytest.mark.integration
def test_resumed_run_keeps_the_record(tmp_path):
    """The smallest bound and its counts survive a checkpoint: a run stopped after 700 steps and
    resumed reports what the uninterrupted run reports."""
    whole = _pdem(*RUN, "--output", tmp_path / "whole", "--quiet")
    assert whole.returncode == 0, whole.stderr
    part = _pdem(*RUN, "--output", tmp_path / "part", "--quiet", "--steps", "700")
    assert part.returncode == 0, part.stderr
    res = _pdem("resume", tmp_path / "part" / "checkpoints" / "latest.h5", "--quiet")
    assert res.returncode == 0, res.stderr
    a = json.loads((tmp_path / "whole" / "summary.json").read_text())["stiffness_bound"]
    b = json.loads((tmp_path / "part" / "summary.json").read_text())["stiffness_bound"]
    assert a == b


@pytest.mark.integration
def test_advise_predicts_the_bound_of_a_deck_it_was_not_fitted_on(tmp_path):
    """pdem advise predicts the live bound from the overlap at the scene's stress, with a prefactor
    taken from the shipped triaxial deck (E = 1e8 Pa, 100 kPa, 1,400 beads). On this small triaxial
    deck (E = 5e7 Pa, 20 kPa, 300 beads) the prediction must be below the measured bound (it is
    used to warn) and not far below it; and the deck pressed 100× harder at 2.5× its step gets a
    warning with a smaller step."""
    from pdem.advise import advise

    proc = _pdem(*RUN, "--output", tmp_path / "run", "--quiet")
    assert proc.returncode == 0, proc.stderr
    measured = json.loads((tmp_path / "run" / "summary.json").read_text())["stiffness_bound"]["dt_min"]

    def step_findings(*sets):
        adv = advise(DECK, sets, probe=False)
        return [f for f in adv.findings if f.topic == "step"]

    found = step_findings()
    predicted = found[0].numbers["live bound predicted [s]"]
    assert 0.7 * measured < predicted <= measured
    assert all("live step bound" not in f.reason for f in found)
    hard = step_findings("boundaries.cell.sigma3=2e6", "run.dt=5e-6")
    warned = [f for f in hard if f.verdict == "warn" and "live step bound" in f.reason]
    assert warned and all(f.suggestions["run.dt"] < 0.8 * f.numbers["live bound predicted [s]"] * 1.0001
                          for f in warned)


@pytest.mark.integration
def test_stop_under_mpi_is_collective_and_the_bound_does_not_depend_on_ranks(tmp_path):
    """On 2 ranks the check stops at the same step with the same bound as in serial (a max over
    ranks of per-particle sums), every rank exits 3, nothing hangs."""
    import shutil

    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    if mpiexec is None:
        pytest.skip("mpiexec not found (pip install mpich)")
    serial = _pdem(*RUN, "--output", tmp_path / "s", "--set", "run.dt=1e-5")
    par = subprocess.run(
        [mpiexec, "-n", "2", sys.executable, "-m", "pdem", *map(str, RUN), "--output", str(tmp_path / "p"),
         "--set", "run.dt=1e-5"],
        capture_output=True, text=True, timeout=300,
    )
    assert serial.returncode == 3 and par.returncode == 3, par.stderr[-2000:]

    def stop(text):
        line = [ln for ln in text.splitlines() if "the step is too large" in ln][0]
        return line[line.index("at step") : line.index("above run.stiffness_limit")]

    assert stop(serial.stderr) == stop(par.stderr)


@pytest.mark.integration
def test_flat_bed_bound_does_not_depend_on_ranks(tmp_path):
    """The 2-D shock-wave bed's first 250 steps (the struck grain's contacts slide, every grain is
    locked in the plane; 2 ranks cut the bed at the struck grain): the same record, bit for bit, on
    1, 2 and 3 ranks."""
    import shutil

    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    if mpiexec is None:
        pytest.skip("mpiexec not found (pip install mpich)")
    deck = Path(__file__).parents[1] / "inputs" / "shock_wave.toml"
    records = []
    for n in (1, 2, 3):
        out = tmp_path / f"r{n}"
        proc = subprocess.run(
            [mpiexec, "-n", str(n), sys.executable, "-m", "pdem", str(deck), "--output", str(out), "--quiet",
             "--set", "stages.impact.end.time=2e-5"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        records.append(json.loads((out / "summary.json").read_text())["stiffness_bound"])
    assert records[0]["checks"] == 9 and math.isfinite(records[0]["dt_min"])
    assert records[1] == records[0] and records[2] == records[0]


def _two_on_a_floor(law, particles=True):
    from pdem.geometry.shapes import Plane

    sim = pdem.Simulation(law=law)
    sim.add_material("glass", density=2500, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.5)  # fmt: skip
    if particles:
        sim.add_particles([[0, 0, 0.0011], [0, 0, 0.0032]], 1e-3)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0, 0, -9.81)
    sim.dt = 1e-5 if law == "hertz_mindlin" else 1e-4
    return sim


@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_checkpoint_state_before_any_bound_is_finite(law):
    """Until a bound is measured (before the first check; always with DEM-C) the record's smallest
    bound is +inf. A checkpoint leaves it out: a failed DEM-C run's files were taken for a blown-up
    state by the study's scan for non-finite numbers. Restored, the record is +inf again."""
    sim = _two_on_a_floor(law)
    sim.run(steps=20)
    assert sim.stiffness["min_dt"] == math.inf
    state = sim.state_dict()
    floats = {k: np.asarray(v) for k, v in state.items() if np.asarray(v).dtype.kind == "f"}
    assert floats and all(np.all(np.isfinite(v)) for v in floats.values()), [
        k for k, v in floats.items() if not np.all(np.isfinite(v))
    ]
    other = _two_on_a_floor(law, particles=False)
    other.load_state(state)
    assert other.stiffness["min_dt"] == math.inf
    assert other.stiffness["checks"] == sim.stiffness["checks"]  # 0 with DEM-C; steps 1, 2, 4, 8, 16


def test_touching_pairs_kernel_matches_the_vectorised_geometry():
    """network_bound's pair filter (a numba loop) gives the contacts, overlaps,
    normals and normal velocities of a vectorised reference with the force loops' arithmetic
    (|d|² = dx² + dy² + dz², left to right), bit for bit and in the pair order given, on a random
    cloud with massless grains and a shuffled pair order."""
    from pdem.contact.stability import _touching_pairs

    rng = np.random.default_rng(5)
    n = 400
    x = rng.uniform(0.0, 0.01, (n, 3))
    v = rng.normal(0.0, 0.5, (n, 3))
    r = rng.uniform(0.4e-3, 0.6e-3, n)
    inv_m = np.where(rng.random(n) < 0.1, 0.0, rng.uniform(1e3, 2e3, n))
    i, j = np.triu_indices(n, 1)
    near = np.flatnonzero(np.linalg.norm(x[j] - x[i], axis=1) < 1.6e-3)
    pi, pj = i[near], j[near]
    order = rng.permutation(pi.size).astype(np.int64)
    a_, b_ = pi[order], pj[order]
    d = x[b_] - x[a_]
    dist = np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2])
    overlap = r[a_] + r[b_] - dist
    touch = np.flatnonzero(overlap > 0.0)
    touch = touch[inv_m[a_[touch]] + inv_m[b_[touch]] > 0.0]
    nrm_ref = d[touch] / dist[touch, None]
    dv = v[b_[touch]] - v[a_[touch]]
    vn_ref = dv[:, 0] * nrm_ref[:, 0] + dv[:, 1] * nrm_ref[:, 1] + dv[:, 2] * nrm_ref[:, 2]
    assert 50 < touch.size < pi.size and np.any(inv_m[a_[touch]] == 0.0)
    m_ = pi.size
    rows, ov, nrm, vn = np.empty(m_, np.int64), np.empty(m_), np.empty((m_, 3)), np.empty(m_)
    m = _touching_pairs(order, pi, pj, x, v, r, inv_m, rows, ov, nrm, vn)
    assert m == touch.size
    assert np.array_equal(rows[:m], order[touch])
    assert np.array_equal(ov[:m], overlap[touch])
    assert np.array_equal(nrm[:m], nrm_ref)
    assert np.array_equal(vn[:m], vn_ref)
