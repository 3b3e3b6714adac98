"""Chung & Ooi (2011), Granular Matter 13:643–656, tests 4 and 6: a sphere against a rigid plane.

**Test 4** — oblique impact at a constant speed of 3.9 m/s, 5°–85° from the normal; aluminium oxide
sphere (E = 380 GPa, ν = 0.23, ρ = 4000 kg/m³, r = 2.5 mm), μ = 0.092, e = 0.98; the plane is the
same material with E 1000 times larger (as in YADE's Chung & Ooi scripts). Measured: the rebound
angle of the contact patch, atan((v_t' − r ω')/v_n') (positive: the patch still moves forward;
Chung & Ooi's sign), and the spin ω' (positive in the sense friction drives it; their figure, in
another frame, shows it negative).

References:

* gross sliding (tan θ ≥ 3.5 μ (1 + e), θ ≥ 32.5° here): the rigid-body closed forms of
  physics.md §2, e_t = 1 − μ (1 + e_n)/tan θ and ω' = (5/2) μ (1 + e_n) v_n / r, with e_n the
  realised normal restitution (measured, v_n'/v_n);
* every angle: a peer, YADE 2023.02a's ``Law2_ScGeom_MindlinPhys_Mindlin`` (Hertz normal force and
  an incremental Mindlin tangential force, the scheme of ``tangential = "mindlin_force"``), run by
  ``tools/chung_ooi_yade.py``; its output is ``tests/data/chung_ooi_test4_yade.csv`` (the header
  says how it was made). YADE with a 4 times smaller step moves its rebound angles by ≤ 0.02° and
  ω' by ≤ 1 % (at 5°), so the peer is converged in dt.

With ``tangential = "mindlin_force"`` the rebound angle is within 0.5° and ω' within 5 % of the peer
at every angle (measured at 1000 steps per contact time: at most 0.21° and 2.1 %, both at 10°, where
the patch angle crosses zero). The default ``linear_history`` (total spring, k_t ∝ a) misses the
small-angle regime: 1.3° too high and ω' 66 % too low at 5°, ω' 6.3 % high at 10°, 0.9° and 2.5 % off
at 25°; ``mindlin_rescale`` is further off (1.8° at 25°) and ``mindlin_rescale_force`` (which unloads
the elastic force with the contact radius, unlike YADE) gives ω' 29 % higher at 5° (these are reported,
not asserted). In gross sliding all four options agree with the closed forms.

The paper's own curves (aluminium oxide) are a second reference, read from its figures
(``tests/data/chung_ooi_test4_figure.csv``, which names the reading's source; a second, independent
reading agrees within 2 rad/s at 5° and 10°). Against them ``mindlin_force`` meets ω' within 5 % and the
rebound angle within 0.5° (each plus the reading error, estimated where the closed forms hold) from
15° and 20° on; in the sticking and microslip regime (5°–15°) neither pdem nor YADE lands on the
figure (test_chung_ooi_test4_against_the_papers_figure says by how much). The default
``linear_history`` gives ω' 33 % below the figure at 5° and angles 0.7°–1.05° off at 5°–20°
(at whole degrees, against the figure's nearest points).

**Test 6** — a spinning sphere meets the rigid plane with v_n = 0.2 m/s, no tangential velocity, and
ω from 0.175 to 21 rad/s; aluminium alloy (E = 70 GPa, ν = 0.33, ρ = 2700 kg/m³, r = 0.1 m), μ = 0.4,
plane E 1000 times larger. The restitution used, e = 0.5, is this test's choice (no public copy of the
paper's parameter table was found). Gross sliding throughout the contact (rω ≥ 3.5 μ (1 + e_n) v_n,
ω ≳ 4.3 rad/s) gives the rigid-body relation v_t' = μ (1 + e_n) v_n: the friction impulse is μ times
the normal impulse. With ``limit_damping`` (F_n ≥ 0, so the cap μ F_n acts on the whole normal
impulse) v_t' is within 1 % of it, e_n from an RK4 integration of the clamped normal force
(tests/physics_helpers.py; e_n = 0.550) — measured: within 10⁻⁴. By default the damped normal force
turns attractive at the end of the contact, where the cap μ max(F_n, 0) is zero: v_t' is then 3.35 %
above μ (1 + e_n) v_n (e_n = e = 0.5 realised), the attractive impulse (5.0 % of m v_n) being
missing from the friction. Below the threshold the sphere sticks and v_t' depends on the tangential
compliance (within −10 %…+18 % of the rigid rolling value (2/7) r ω; reported, not asserted).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from physics_helpers import normal_impact_rk4

import pdem
from pdem.geometry.shapes import Plane
from pdem.laws.hertz_mindlin import HertzMindlin
from pdem.materials import Material, MaterialTable

OPTIONS = ["linear_history", "mindlin_rescale", "mindlin_force", "mindlin_rescale_force"]
STEPS = 1000  # time steps per elastic contact time

# test 4
R4, V4, MU4, E4 = 2.5e-3, 3.9, 0.092, 0.98
YADE = Path(__file__).resolve().parent / "data" / "chung_ooi_test4_yade.csv"
FIGURE = Path(__file__).resolve().parent / "data" / "chung_ooi_test4_figure.csv"

# test 6
R6, VN6, MU6, E6 = 0.1, 0.2, 0.4, 0.5
OMEGAS = [0.175, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0, 14.0, 21.0]


def _yade() -> np.ndarray:
    rows = [line.split(",") for line in YADE.read_text().splitlines() if line[:1].isdigit()]
    return np.array(rows, dtype=float)


def _contact_time(m: float, r: float, es: float, vn: float) -> float:
    return 2.868 * (m * m / (r * es * es * vn)) ** 0.2


def _e_star(e: float, nu: float, e_wall: float) -> float:
    return 1.0 / ((1 - nu**2) / e + (1 - nu**2) / e_wall)


def _impact(law: dict, mat: dict, r: float, v: tuple, w: tuple, tc: float, horizon: float):
    """One sphere against the plane z = 0 (material ``mat``, the plane's E 1000 times larger),
    STEPS steps per contact time; returns (v_n', v_t', ω'_y) once it has left the plane."""
    sim = pdem.Simulation(**law)
    sim.add_material("sphere", **mat)
    sim.add_material("plane", **{**mat, "youngs_modulus": 1000.0 * mat["youngs_modulus"]})
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), material="plane", name="plane")
    dt = tc / STEPS
    gap = 0.5 * abs(v[2]) * dt
    sim.add_particles([[0, 0, r + gap]], r, material="sphere", velocities=[v], angular_velocities=[w])
    sim.dt = dt
    sim.run(until=gap / abs(v[2]) + horizon * tc)
    p = sim.get_particles()
    assert p["x"][0, 2] > r  # left the plane
    return float(p["v"][0, 2]), float(p["v"][0, 0]), float(p["w"][0, 1])


def _test4(tangential: str, angles=None) -> list[tuple[float, float, float, float, float, float]]:
    """(incidence, v_n, v_t, v_n', v_t', ω') at ``angles`` [deg] (default the peer's)."""
    mat = dict(density=4000.0, youngs_modulus=3.8e11, poisson_ratio=0.23, restitution=E4, friction=MU4)
    m = 4000.0 * 4.0 / 3.0 * math.pi * R4**3
    es = _e_star(3.8e11, 0.23, 3.8e14)
    out = []
    for deg in _yade()[:, 0] if angles is None else angles:
        th = math.radians(deg)
        vn0, vt0 = V4 * math.cos(th), V4 * math.sin(th)
        vn, vt, w = _impact({"tangential": tangential}, mat, R4, (vt0, 0.0, -vn0), (0.0, 0.0, 0.0),
                            _contact_time(m, R4, es, vn0), 1.3)  # fmt: skip
        out.append((deg, vn0, vt0, vn, vt, w))
    return out


def _patch_angle(vn: float, vt: float, w: float) -> float:
    return math.degrees(math.atan((vt - R4 * w) / vn))


def test_limit_damping_is_clamp_normal():
    """``limit_damping`` (LAMMPS's name) and ``clamp_normal`` set the same coefficient: F_n =
    max(F_n, 0), whose Coulomb cap μ max(F_n, 0) is then zero wherever the damping would pull."""
    table = MaterialTable()
    table.add(Material("a", density=2700.0, youngs_modulus=7e10, poisson_ratio=0.33, restitution=0.5,
                       friction=0.4))  # fmt: skip
    plain = HertzMindlin().coefficients(table)
    for a, b in [({"limit_damping": True}, {"clamp_normal": True}),
                 ({"limit_damping": True, "clamp_normal": True}, {"clamp_normal": True})]:  # fmt: skip
        assert np.array_equal(HertzMindlin(**a).coefficients(table), HertzMindlin(**b).coefficients(table))
    assert HertzMindlin(limit_damping=True).coefficients(table)[0, 0, 7] == 1.0 != plain[0, 0, 7]
    # the options' history: three floats, four with the previous contact radius (rescale options)
    assert [HertzMindlin(tangential=t).history_size for t in OPTIONS] == [3, 4, 3, 4]


def test_chung_ooi_test4_mindlin_force_matches_the_peer():
    """Rebound angle within 0.5° and ω' within 5 % of YADE's incremental Mindlin law at every angle,
    both in the sticking/microslip regime and in gross sliding."""
    yade = {row[0]: row for row in _yade()}
    worst = (0.0, 0.0)
    for deg, _vn0, _vt0, vn, vt, w in _test4("mindlin_force"):
        ref = yade[deg]
        d_angle = _patch_angle(vn, vt, w) - ref[4]
        d_w = w / ref[3] - 1.0
        print(f"{deg:4.0f}°: patch angle {_patch_angle(vn, vt, w):+8.3f}° (YADE {ref[4]:+8.3f}°, "
              f"{d_angle:+.3f}°), ω' {w:8.2f} rad/s (YADE {ref[3]:8.2f}, {d_w:+.2%})")  # fmt: skip
        assert abs(d_angle) < 0.5
        assert abs(d_w) < 0.05
        worst = (max(worst[0], abs(d_angle)), max(worst[1], abs(d_w)))
    print(f"largest differences: {worst[0]:.3f}°, {worst[1]:.2%}")


def _sliding_refs(vn0: float, vt0: float, vn: float, th: float) -> tuple[float, float]:
    """The rigid-body closed forms in gross sliding, with the realised e_n: (ω', patch angle [deg])."""
    one_plus_e = 1.0 + vn / vn0
    e_t = 1.0 - MU4 * one_plus_e / math.tan(th)
    w_ref = 2.5 * MU4 * one_plus_e * vn0 / R4
    return w_ref, math.degrees(math.atan((e_t * vt0 - R4 * w_ref) / vn))


def test_chung_ooi_test4_against_the_papers_figure():
    """The paper's own curves (aluminium oxide, read from its figures; tests/data says by whom): ω' and
    the rebound angle at the figure's incident angles, with ``mindlin_force``.

    The reading error is taken from the gross-sliding points (tan θ ≥ 3.5 μ (1 + e), with a 5 %
    margin), where the rigid-body closed forms are exact: the largest |figure − closed form| there,
    per quantity (measured: 3.7 rad/s and 0.35°). ω' is within 5 % plus that error from 15° on
    (−1.2 % to +2.0 % up to 70°, −2.9 % at 80°), the rebound angle within 0.5° plus it from 20° on
    (at most 0.57°, at 25°). Not met, printed and not asserted: ω' at 5° and 10° (37.1 and
    198.9 rad/s against the figure's 19.3 and 213.0) and the angle at 5°, 10° and 15° (−0.66°,
    +1.47°, +0.93°), the sticking and microslip regime. YADE's incremental Mindlin law gives what
    pdem gives there (37.6 and 192.0 rad/s, 3.14° and 0.07° at 5° and 10°: the test above), so the
    gap is between this tangential law and the one behind the paper's curve, not in pdem's
    implementation of it.
    """
    rows = [line.split(",") for line in FIGURE.read_text().splitlines() if line[:1].isdigit()]
    fig = np.array(rows, dtype=float)
    omega = {round(r[0], 2): r for r in _test4("mindlin_force", fig[:, 0])}
    angle = {round(r[0], 2): r for r in _test4("mindlin_force", fig[:, 2])}
    slides = lambda deg: math.tan(math.radians(deg)) >= 3.5 * MU4 * (1 + E4) * 1.05  # noqa: E731
    err_w = err_a = 0.0
    for th_w, w_fig, th_a, a_fig in fig:
        if slides(th_w):
            _, vn0, vt0, vn, _, _ = omega[round(th_w, 2)]
            err_w = max(err_w, abs(w_fig - _sliding_refs(vn0, vt0, vn, math.radians(th_w))[0]))
        if slides(th_a):
            _, vn0, vt0, vn, _, _ = angle[round(th_a, 2)]
            err_a = max(err_a, abs(a_fig - _sliding_refs(vn0, vt0, vn, math.radians(th_a))[1]))
    print(f"reading error (gross sliding): ω' {err_w:.2f} rad/s, angle {err_a:.2f}°")
    assert 0.0 < err_w < 5.0 and 0.0 < err_a < 0.6  # a reading, not a copy of a closed form
    for th_w, w_fig, th_a, a_fig in fig:
        w = omega[round(th_w, 2)][5]
        _, _, _, vn, vt, w_a = angle[round(th_a, 2)]
        patch = _patch_angle(vn, vt, w_a)
        print(f"ω' at {th_w:5.2f}°: {w:7.1f} rad/s (figure {w_fig:6.1f}, {w / w_fig - 1:+.1%}); angle at "
              f"{th_a:5.2f}°: {patch:+6.2f}° (figure {a_fig:+6.2f}°, {patch - a_fig:+.2f}°)")  # fmt: skip
        if th_w >= 14.0:
            assert abs(w - w_fig) <= 0.05 * w_fig + err_w
        if th_a >= 19.0:
            assert abs(patch - a_fig) <= 0.5 + err_a


@pytest.mark.parametrize("tangential", OPTIONS)
def test_chung_ooi_test4_gross_sliding_closed_forms(tangential):
    """Above tan θ = 3.5 μ (1 + e) every option slides throughout the contact: e_t, ω' and the patch
    angle of the rigid-body closed forms (with the realised e_n). The small angles are reported
    against the peer (the default's miss there is the reason for the Mindlin options)."""
    yade = {row[0]: row for row in _yade()}
    for deg, vn0, vt0, vn, vt, w in _test4(tangential):
        th = math.radians(deg)
        patch = _patch_angle(vn, vt, w)
        if math.tan(th) < 3.5 * MU4 * (1 + E4) * 1.05:
            ref = yade[deg]
            print(
                f"{tangential} {deg:4.0f}°: patch angle {patch:+8.3f}° (YADE {ref[4]:+8.3f}°, "
                f"{patch - ref[4]:+.3f}°), ω' {w:8.2f} (YADE {ref[3]:8.2f}, {w / ref[3] - 1:+.2%})"
            )
            continue
        one_plus_e = 1.0 + vn / vn0
        e_t = 1.0 - MU4 * one_plus_e / math.tan(th)
        w_ref = 2.5 * MU4 * one_plus_e * vn0 / R4
        patch_ref = math.degrees(math.atan((e_t * vt0 - R4 * w_ref) / vn))
        assert vt / vt0 == pytest.approx(e_t, rel=1e-3)
        assert w == pytest.approx(w_ref, rel=0.01)
        assert abs(patch - patch_ref) < 0.5
        assert w == pytest.approx(yade[deg][3], rel=0.01)  # the peer slides alike


def _test6(law: dict) -> list[tuple[float, float, float, float]]:
    mat = dict(density=2700.0, youngs_modulus=7e10, poisson_ratio=0.33, restitution=E6, friction=MU6)
    m = 2700.0 * 4.0 / 3.0 * math.pi * R6**3
    tc = _contact_time(m, R6, _e_star(7e10, 0.33, 7e13), VN6)
    return [(w0, *_impact(law, mat, R6, (0.0, 0.0, -VN6), (0.0, w0, 0.0), tc, 2.0)) for w0 in OMEGAS]


def test_chung_ooi_test6_limited_damping_keeps_the_coulomb_impulse():
    """Spinning sphere, gross sliding: v_t' = μ (1 + e_n) v_n within 1 % with ``limit_damping`` (e_n of
    the clamped normal force, RK4); by default the friction misses the attractive tail's impulse."""
    m = 2700.0 * 4.0 / 3.0 * math.pi * R6**3
    es = _e_star(7e10, 0.33, 7e13)
    tc = _contact_time(m, R6, es, VN6)
    for limit in (True, False):
        ref = normal_impact_rk4(E6, m, R6, es, VN6, 2.0 * tc, steps_per_tc=4000, clamp=limit)
        e_n = -ref["rate"] / VN6
        tail = -ref["attractive_impulse"] / (m * VN6)  # ≥ 0: the attractive part of the normal impulse
        for tangential in ("linear_history", "mindlin_force"):
            law = {"tangential": tangential, "limit_damping": limit}
            for w0, vn, vt, _w in _test6(law):
                sliding = R6 * w0 > 3.5 * MU6 * (1 + e_n) * VN6 * 1.5
                v_ref = MU6 * (1 + e_n) * VN6
                print(
                    f"limit_damping={limit} {tangential} ω={w0:6.3f}: v_t' {vt:.6f} "
                    f"(μ(1+e_n)v_n {v_ref:.6f}, {vt / v_ref - 1:+.4%}; rolling (2/7)rω "
                    f"{2 / 7 * R6 * w0:.6f}), v_n' {vn:.6f}"
                )
                if not sliding:
                    continue
                assert vn / VN6 == pytest.approx(e_n, rel=2e-3)
                if limit:
                    assert vt == pytest.approx(v_ref, rel=0.01)
                    assert vt == pytest.approx(MU6 * (VN6 + vn), rel=0.01)  # Coulomb: Δv_t = μ Δv_n
                else:
                    # friction acts on the repulsive impulse only, 1 + e_n + tail (3.35 % above)
                    assert vt == pytest.approx(MU6 * (1 + e_n + tail) * VN6, rel=0.01)
                    assert vt > MU6 * (VN6 + vn) * 1.02
