"""Tests of the linear spring–dashpot plugin.

(a) discovery through the ``pdem.contact_laws`` entry point and parameter validation;
(b) the njit kernel against its plain-Python twin (``pdem.testing.law_contract``);
(c) closed forms: head-on impacts of the damped linear oscillator (contact duration and restitution,
    sphere–sphere with m* = m/2 and sphere–wall with m* = m), clamping, gross sliding;
(d) a small pile built through ``pdem.Simulation(law="linear_spring", kn=...)`` comes to rest.

Closed forms used (damped linear oscillator m* δ'' + c_n δ' + k_n δ = 0, δ(0) = 0, δ'(0) = V):
ω_d = sqrt(k_n/m* − (c_n/(2 m*))²), contact duration t_c = π/ω_d (δ returns to 0 after half a
damped period) and rebound speed V exp(−c_n t_c/(2 m*)) = e V for c_n = −2 β sqrt(k_n m*),
β = ln e / sqrt(ln² e + π²). For two equal spheres m* = m/2, so k_n/m* = 2 k_n/m and
t_c = π / sqrt(2 k_n/m − (c_n/m*)²/4).
"""

from __future__ import annotations

import math

import numpy as np
import pdem
import pytest
from pdem.errors import InputError
from pdem.geometry.shapes import Plane, box_planes
from pdem.materials import Material, MaterialTable
from pdem.plugins import available, load_contact_law
from pdem.sources import BoxRegion, Uniform, random_fill
from pdem.testing.law_contract import check_law_against_twin

from pdem_linear_spring import LinearSpring, force_numpy, stable_dt

R = 1e-3  # sphere radius [m]
RHO = 2500.0  # density [kg/m³]
KN = 2000.0  # normal stiffness [N/m]
V = 0.1  # approach speed [m/s]; maximum overlap ≈ V sqrt(m*/k_n) ≈ 0.5 % of R
MASS = RHO * 4.0 / 3.0 * math.pi * R**3


def beta_of(e: float) -> float:
    le = math.log(e)
    return le / math.sqrt(le * le + math.pi**2)


def closed_form_duration(e: float, m_eff: float) -> float:
    """t_c = π / sqrt(k_n/m* − (c_n/m*)²/4) with c_n = −2 β sqrt(k_n m*)."""
    c_n = -2.0 * beta_of(e) * math.sqrt(KN * m_eff)
    return math.pi / math.sqrt(KN / m_eff - (c_n / m_eff) ** 2 / 4.0)


# ---------------------------------------------------------------------------------------------
# (a) discovery and parameters
# ---------------------------------------------------------------------------------------------


def test_plugin_is_discoverable():
    info = available("contact_laws")["linear_spring"]
    assert info.distribution == "pdem-linear-spring"
    assert info.value == "pdem_linear_spring:LinearSpring"
    law = load_contact_law("linear_spring", kn=KN)
    assert isinstance(law, LinearSpring)
    assert law.params.kt_over_kn == pytest.approx(2.0 / 7.0)
    assert law.params.clamp_normal is False
    assert law.history_size == 3


@pytest.mark.parametrize("params, fragment", [
    ({}, "kn"),
    ({"kn": -1.0}, "kn"),
    ({"kn": 1e3, "kt_over_kn": 0.0}, "kt_over_kn"),
    ({"kn": 1e3, "k_n": 1e3}, "k_n"),
])
def test_bad_parameters_are_input_errors(params, fragment):
    with pytest.raises(InputError, match=fragment):
        LinearSpring(**params)


def test_rolling_friction_is_refused():
    mt = MaterialTable()
    mt.add(Material("a", rolling_friction=0.1))
    with pytest.raises(InputError, match="no rolling resistance"):
        LinearSpring(kn=KN).coefficients(mt)


def test_spinning_friction_is_refused():
    mt = MaterialTable()
    mt.add(Material("a", spinning_friction=0.1))
    with pytest.raises(InputError, match="no spinning resistance"):
        LinearSpring(kn=KN).coefficients(mt)


# ---------------------------------------------------------------------------------------------
# (b) kernel against the plain-Python twin
# ---------------------------------------------------------------------------------------------


def _table() -> MaterialTable:
    mt = MaterialTable()
    mt.add(Material("a", density=2500, restitution=0.4, friction=0.3))
    mt.add(Material("b", density=7800, restitution=0.7, friction=0.6))
    return mt


@pytest.mark.integration
@pytest.mark.parametrize("params", [
    {"kn": 1e3},
    {"kn": 5e4, "kt_over_kn": 1.0, "clamp_normal": True},
])
@pytest.mark.parametrize("mat", [(0, 0), (0, 1)])
def test_kernel_matches_twin(params, mat):
    branches = {"sliding": 0, "sticking": 0, "attractive": 0}

    def twin(delta, n, vrel, wrel, r_eff, m_eff, i_eff, c, hist, dt):
        force, moment = force_numpy(delta, n, vrel, wrel, r_eff, m_eff, i_eff, c, hist, dt)
        fn = float(force @ n)
        ft = np.linalg.norm(force - fn * n)
        branches["attractive"] += fn < 0.0
        if fn > 0.0 and ft == pytest.approx(c[4] * fn, rel=1e-12):
            branches["sliding"] += 1
        else:
            branches["sticking"] += 1
        return force, moment

    checked = check_law_against_twin(LinearSpring(**params), twin, _table(), mat=mat)
    assert checked >= 100
    # both Coulomb branches were exercised, and the clamp did what it says
    assert branches["sliding"] > 0 and branches["sticking"] > 0
    if params.get("clamp_normal"):
        assert branches["attractive"] == 0


# ---------------------------------------------------------------------------------------------
# (c) closed forms
# ---------------------------------------------------------------------------------------------


def _contact_interval(t: np.ndarray, overlap: np.ndarray) -> tuple[float, float]:
    """Start and end of the (first) contact, interpolated linearly where the overlap changes sign."""
    pos = np.flatnonzero(overlap > 0)
    a, b = pos[0], pos[-1]
    assert np.all(overlap[a:b + 1] > 0), "the contact opened and closed again"
    t0 = t[a - 1] + (t[a] - t[a - 1]) * (-overlap[a - 1]) / (overlap[a] - overlap[a - 1])
    t1 = t[b] + (t[b + 1] - t[b]) * overlap[b] / (overlap[b] - overlap[b + 1])
    return t0, t1


def _head_on(e: float, clamp: bool = False, steps_per_contact: int = 500):
    """Two equal spheres meeting head-on at relative speed V; returns (realised e, t_c, closed-form t_c)."""
    tc = closed_form_duration(e, 0.5 * MASS)
    dt = tc / steps_per_contact
    gap = 3.5 * V * dt
    sim = pdem.Simulation(law="linear_spring", kn=KN, clamp_normal=clamp)
    sim.add_material("glass", density=RHO, restitution=e, friction=0.5)
    sim.add_particles([[-R - gap / 2, 0, 0], [R + gap / 2, 0, 0]], R,
                      velocities=[[V / 2, 0, 0], [-V / 2, 0, 0]])
    sim.dt = dt
    rec = []

    def sample(s):
        x = s.particles.x
        rec.append((s.time, 2 * R - abs(x[1, 0] - x[0, 0])))

    sim.run(steps=0)
    sample(sim)
    sim.run(until=gap / V + 1.5 * tc, callback=sample)
    t, overlap = np.array(rec).T
    t0, t1 = _contact_interval(t, overlap)
    p = sim.get_particles()
    assert np.allclose(p["v"][:, 1:], 0.0) and np.allclose(p["w"], 0.0)
    return (p["v"][1, 0] - p["v"][0, 0]) / V, t1 - t0, tc


@pytest.mark.parametrize("e", [0.2, 0.5, 0.9])
def test_head_on_duration_and_restitution(e):
    """Unclamped, dt = t_c/500: contact duration and realised restitution within 0.5 % of the
    closed forms (the residual is the O(dt/t_c) lag of the dashpot, which sees the half-step velocity)."""
    realised, duration, tc = _head_on(e)
    print(f"e = {e}: realised e {realised:.6f} ({realised / e - 1:+.2e}), "
          f"t_c {duration:.6e} s vs {tc:.6e} s ({duration / tc - 1:+.2e})")
    assert realised == pytest.approx(e, rel=5e-3)
    assert duration == pytest.approx(tc, rel=5e-3)


def test_restitution_converges_with_dt():
    """First-order convergence of the realised restitution: halving dt halves the error."""
    errs = [abs(_head_on(0.5, steps_per_contact=n)[0] / 0.5 - 1) for n in (100, 200, 400)]
    print(f"|e_realised/e − 1| at t_c/100, /200, /400: {errs}")
    assert errs[0] > errs[1] > errs[2]
    assert errs[1] / errs[2] == pytest.approx(2.0, rel=0.1)


@pytest.mark.integration
def test_head_on_wall():
    """A sphere on a wall (another material, restitution mixed as the minimum): m* = m."""
    e = 0.5
    tc = closed_form_duration(e, MASS)
    dt = tc / 500
    sim = pdem.Simulation(law="linear_spring", kn=KN)
    sim.add_material("glass", density=RHO, restitution=0.8, friction=0.5)
    sim.add_material("steel", density=7800, restitution=e, friction=0.5)
    floor = sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), material="steel", name="floor")
    sim.add_particles([[0, 0, R + 3.5 * V * dt]], R, material="glass", velocities=[[0, 0, -V]])
    sim.dt = dt
    rec = []
    sample = lambda s: rec.append((s.time, R - s.particles.x[0, 2], floor.n_contacts))
    sim.run(steps=0)
    sample(sim)
    sim.run(until=3.5 * dt + 1.5 * tc, callback=sample)
    t, overlap, nc = np.array(rec).T
    assert np.all((nc > 0) == (overlap > 0))
    t0, t1 = _contact_interval(t, overlap)
    realised = sim.get_particles()["v"][0, 2] / V
    print(f"wall: realised e {realised:.6f}, t_c {(t1 - t0) / tc - 1:+.2e}")
    assert realised == pytest.approx(e, rel=5e-3)
    assert t1 - t0 == pytest.approx(tc, rel=5e-3)


def test_clamped_restitution_exceeds_input():
    """Clamping F_n ≥ 0 removes the attractive end of the contact: the realised e is higher."""
    for e in (0.2, 0.5):
        clamped = _head_on(e, clamp=True)[0]
        print(f"e = {e}: clamped realised e {clamped:.4f}")
        assert clamped > 1.02 * e


def test_oblique_impact_gross_sliding():
    """Clamped normal force, so the cap μ F_n holds throughout and, while the contact point slides,
    the tangential impulse is μ times the normal impulse J_n = m (v_n + v_n') (v_n' measured): then
    v_t' = v_t − μ J_n/m and ω' = (5/2) μ J_n/(m r) (lever arm r − δ/2 ≈ r; δ/r < 0.3 %)."""
    e, mu, theta = 0.5, 0.2, math.radians(60.0)
    vn, vt = V, V * math.tan(theta)
    tc = closed_form_duration(e, MASS)
    dt = tc / 500
    sim = pdem.Simulation(law="linear_spring", kn=KN, clamp_normal=True)
    sim.add_material("glass", density=RHO, restitution=e, friction=mu)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.add_particles([[0, 0, R + 3.5 * vn * dt]], R, velocities=[[vt, 0, -vn]])
    sim.dt = dt
    sim.run(until=3.5 * dt + 2.0 * tc)
    p = sim.get_particles()
    vn_out = p["v"][0, 2]
    assert p["x"][0, 2] > R  # separated
    jn = vn + vn_out  # normal impulse / m
    assert vt > 3.5 * mu * jn  # gross sliding throughout (the slip never stops)
    assert p["v"][0, 0] == pytest.approx(vt - mu * jn, rel=1e-3)
    assert p["w"][0, 1] == pytest.approx(2.5 * mu * jn / R, rel=5e-3)


@pytest.mark.parametrize("pair", [(0, 0), (0, 1), (1, 1)])
def test_contact_stiffness_matches_the_twin(pair):
    """The live step bound's input (pdem.contact.stability): S_n and k_t as the twin's force
    differentiated in the overlap and in the spring history."""
    law = LinearSpring(kn=KN)
    coef = law.coefficients(_table())
    a, b = pair
    m_eff, delta = 0.5 * MASS, 1e-6
    s_n, k_t = (q[0] for q in law.contact_stiffness(
        coef, np.array([a]), np.array([b]), np.array([R / 2]), np.array([m_eff]), np.array([delta])
    ))
    n = np.array([0.0, 0.0, 1.0])
    z = np.zeros(3)

    def force(d, vrel=z, hist=None):
        h0 = np.zeros(3) if hist is None else hist
        return force_numpy(d, n, vrel, z, R / 2, m_eff, 1.0, coef[a, b], h0, 1.0)[0]

    assert s_n == pytest.approx((force(2 * delta)[2] - force(delta)[2]) / delta, rel=1e-9)
    s = 1e-9
    vt = np.array([s, 0.0, 0.0])
    f1, f2 = force(delta, vt, np.zeros(3))[0], force(delta, vt, vt.copy())[0]
    assert k_t == pytest.approx(-(f2 - f1) / s, rel=1e-6)



@pytest.mark.parametrize("pair", [(0, 0), (0, 1), (1, 1)])
def test_contact_damping_matches_the_twin(pair):
    """pdem's velocity servos read the dashpots (pdem.contact.stability.servo_gain): c_n and c_t
    as minus the twin's force differentiated in the normal and tangential velocity (zero step: the
    tangential spring left out)."""
    law = LinearSpring(kn=KN)
    coef = law.coefficients(_table())
    a, b = pair
    m_eff, delta = 0.5 * MASS, 1e-6
    c_n, c_t = (q[0] for q in law.contact_damping(
        coef, np.array([a]), np.array([b]), np.array([R / 2]), np.array([m_eff]), np.array([delta])
    ))
    n = np.array([0.0, 0.0, 1.0])
    z = np.zeros(3)

    def force(v):
        return force_numpy(delta, n, v, z, R / 2, m_eff, 1.0, coef[a, b], np.zeros(3), 0.0)[0]

    s = 1e-9
    assert c_n == pytest.approx(-(force(s * n)[2] - force(-s * n)[2]) / (2 * s), rel=1e-6)
    assert c_t == pytest.approx(-force(np.array([s, 0.0, 0.0]))[0] / s, rel=1e-6)

def test_critical_dt_formula():
    """critical_dt is the FCC-crystal limit of stable_dt; the undamped normal-mode bound alone would
    be sqrt(m*/k_n) (half the two-body limit); with ρ = 2/7 the rotation mode is stiffer."""
    law = LinearSpring(kn=KN)
    mt = MaterialTable()
    mt.add(Material("a", density=RHO, restitution=1.0))
    masses = np.array([MASS, 8 * MASS])
    radii = np.array([R, 2 * R])
    mats = np.zeros(2, dtype=np.int32)
    m_eff = MASS / 2
    two_body = 2 * math.sqrt(m_eff / KN)
    crit = law.critical_dt(mt, radii, mats, masses)
    assert crit == pytest.approx(2 / math.sqrt(20 * 2 / 7) * math.sqrt(m_eff / KN), rel=1e-12)
    assert crit / two_body == pytest.approx(0.4183, abs=1e-4)
    assert stable_dt(KN, 0.05, m_eff, 0.0) == pytest.approx(2 / math.sqrt(4 * 1.05) * math.sqrt(m_eff / KN))
    # damping lowers the limit; suggested_dt resolves the contact with 50 steps
    mt.add(Material("b", density=RHO, restitution=0.5))
    assert law.critical_dt(mt, radii, mats, masses) < crit
    assert law.suggested_dt(mt, radii, mats, masses) == pytest.approx(math.pi * math.sqrt(m_eff / KN) / 50)
    assert law.critical_dt(mt, radii[:0], mats[:0], masses[:0]) == math.inf


def _fcc_bloch_limit(kn: float, kt: float, m: float, e: float) -> float:
    """Largest stable dt of an infinite FCC crystal of equal spheres (mass m, 12 contacts each, linear
    normal and tangential springs and dashpots, translations and rotations) under pdem's velocity
    Verlet (the dashpot sees the half-step velocity), by a Bloch-wave analysis: for each wave vector q
    the 18×18 one-step amplification matrix of (u, v, a) must have spectral radius ≤ 1. Independent
    of the law's formula; bisection over dt."""
    a = 1.0
    r = a / (2.0 * math.sqrt(2.0))  # touching spheres: nearest-neighbour distance a/√2 = 2 r
    nbrs = [np.array(v) * a / 2 for v in {(sx * i, sy * j, sz * k)
                                          for i, j, k in ((1, 1, 0), (1, 0, 1), (0, 1, 1))
                                          for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)}]
    assert len(nbrs) == 12
    zeta = -beta_of(e) if e > 0 else 1.0
    m_eff = m / 2
    cn, ct = 2 * zeta * math.sqrt(kn * m_eff), 2 * zeta * math.sqrt(kt * m_eff)
    inv_mass = np.diag([1 / m] * 3 + [1 / (0.4 * m * r * r)] * 3)
    b = 2 * math.pi / a
    # a 4×4×4 grid from Γ to 2π/a along each axis (X = (2π/a)(1, 0, 0) included), plus L
    qs = [np.array(q) * b / 3 for q in np.ndindex(4, 4, 4)] + [np.array([0.5, 0.5, 0.5]) * b]
    ops = []
    for q in qs:
        stiff = np.zeros((6, 6), complex)
        damp = np.zeros((6, 6), complex)
        for d in nbrs:
            n = d / np.linalg.norm(d)
            nn = np.outer(n, n)
            cross = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
            # relative contact displacement u_j − u_i + r n × (θ_i + θ_j), with u_j = u_i e^{iq·d}
            bmat = np.hstack([-np.eye(3), r * cross]) + np.hstack([np.eye(3), r * cross]) * np.exp(1j * q @ d)
            stiff += 0.5 * bmat.conj().T @ (kn * nn + kt * (np.eye(3) - nn)) @ bmat
            damp += 0.5 * bmat.conj().T @ (cn * nn + ct * (np.eye(3) - nn)) @ bmat
        ops.append((-inv_mass @ stiff, -inv_mass @ damp))

    def stable(h: float) -> bool:
        eye, zero = np.eye(6), np.zeros((6, 6))
        for kmat, cmat in ops:
            vh = np.hstack([zero, eye, h / 2 * eye])
            xn = np.hstack([eye, zero, zero]) + h * vh
            an = kmat @ xn + cmat @ vh
            step = np.vstack([xn, vh + h / 2 * an, an])
            if np.abs(np.linalg.eigvals(step)).max() > 1 + 1e-6:
                return False
        return True

    w2 = math.sqrt(kn / m_eff)
    lo, hi = 0.01 / w2, 3.0 / w2
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return lo


@pytest.mark.parametrize("e, kt_over_kn", [(1.0, 2 / 7), (0.5, 2 / 7), (0.1, 2 / 7), (0.5, 0.05), (0.3, 1.0)])
def test_critical_dt_is_the_fcc_stability_limit(e, kt_over_kn):
    """critical_dt (closed form over two modes) equals the Bloch-wave stability limit of the crystal."""
    law = LinearSpring(kn=KN, kt_over_kn=kt_over_kn)
    mt = MaterialTable()
    mt.add(Material("a", density=RHO, restitution=e))
    crit = law.critical_dt(mt, np.array([R]), np.zeros(1, np.int32), np.array([MASS]))
    bloch = _fcc_bloch_limit(KN, kt_over_kn * KN, MASS, e)
    print(f"e = {e}, k_t/k_n = {kt_over_kn:.3f}: critical_dt {crit:.6e} s, Bloch {bloch:.6e} s, "
          f"{crit / (2 * math.sqrt(MASS / 2 / KN)):.4f} of the two-body limit")
    assert crit == pytest.approx(bloch, rel=1e-4)


# ---------------------------------------------------------------------------------------------
# (d) a pile comes to rest
# ---------------------------------------------------------------------------------------------


@pytest.mark.integration
def test_pile_comes_to_rest():
    """80 spheres dropped into a box settle: kinetic energy ~0, the walls carry the weight (the floor
    most of it, the side walls the rest through friction), overlaps stay small. A softer k_n than
    the impact tests (overlaps still < 1 % of R) keeps the number of steps down."""
    kn = 200.0
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.01, 0.01, 0.025])
    x, r = random_fill(BoxRegion(lo + 1.1e-3, hi - 1.1e-3), Uniform(0.8e-3, 1.0e-3), n=80, seed=3)
    sim = pdem.Simulation(law="linear_spring", kn=kn)
    sim.add_material("glass", density=RHO, restitution=0.3, friction=0.5)
    sim.add_particles(x, r)
    for plane in box_planes(lo, hi):
        sim.add_wall(plane)
    sim.gravity = (0.0, 0.0, -9.81)
    weight = 9.81 * float(sim.get_particles()["mass"].sum())
    ke_ref = weight * float(np.mean(r))  # energy scale: the pile's weight times a radius
    sim.run(steps=0)
    assert sim.dt == pytest.approx(LinearSpring(kn=kn).suggested_dt(sim.materials, sim.particles.r,
                                                                    sim.particles.mat, sim.particles.mass))
    assert sim.dt < sim.dt_critical
    sim.run(until=0.06)  # the fall from the top takes ~0.06 s
    while sum(sim.kinetic_energy()) > 1e-6 * ke_ref and sim.time < 1.0:
        sim.run(until=sim.time + 0.01)
    ke = sum(sim.kinetic_energy())
    p = sim.get_particles()
    load = sum(w.force for w in sim.walls.values())
    print(f"pile: t = {sim.time:.3f} s, {sim.step_count} steps of {sim.dt:.3g} s, "
          f"KE/(W r) = {ke / ke_ref:.2e}, wall load / weight = {-load[2] / weight:.6f}, "
          f"top z = {p['x'][:, 2].max():.4f} m, "
          f"max overlap/R = {sim.contacts()['overlap'].max() / R:.2e}")
    assert ke < 1e-6 * ke_ref
    assert -load[2] == pytest.approx(weight, rel=1e-3)
    assert np.all((p["x"] > lo) & (p["x"] < hi))
    assert p["x"][:, 2].max() < 0.012  # it fell and packed
    assert sim.contacts()["overlap"].max() < 0.01 * R  # stiff enough: overlaps stay small


def test_example_deck_runs_through_pdem(tmp_path):
    """The example deck that selects this plugin runs to completion through the pdem command."""
    import json
    from pathlib import Path

    from pdem.cli import main

    deck = Path(__file__).resolve().parents[3] / "inputs" / "examples" / "linear_spring_pile.toml"
    out = tmp_path / "out"
    assert main([str(deck), "--output", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["completed"] and summary["particles"] == 300
    resolved = (out / "deck.resolved.toml").read_text()
    assert 'law = "linear_spring"' in resolved
