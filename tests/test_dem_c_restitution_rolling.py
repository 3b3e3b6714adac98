"""DEM-C restitution, rolling and spinning friction against closed forms.

* Newton's impact law: a sphere dropped from H on a floor rebounds to e² H (first apex), for
  e = 0.3–0.9 with each solver; below the restitution threshold contacts are perfectly inelastic, so
  a bouncing sphere stops after the bounce whose impact speed falls below it and a resting sphere
  stays at rest. (The head-on impact of two spheres, e × the approach speed, is in
  tests/test_dem_c.py.)
* Rolling friction, torque bound μ_r R* F_n (R* = r on a wall), the meaning of the material key in
  DEM-P: a sphere rolling on a plane decelerates at a = (5/7) μ_r g (m a = −F,
  I a/r = F r − μ_r r m g with I = 2/5 m r²), and on an incline it stays at rest while
  tan θ ≤ μ_r and rolls at (5/7) g (sin θ − μ_r cos θ) above; DEM-P gives the same deceleration.
* Spinning friction, torque bound μ_s R* F_n about the normal: a sphere spinning on a floor stops
  after ω0 / (2.5 μ_s g / r), in DEM-C and DEM-P.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import pdem
from pdem.geometry import shapes

G = 9.81
R = 1e-3
SOLVERS = ["jacobi", "apgd", "gauss_seidel"]


def make_sim(solver="jacobi", dt=1e-4, e=0.5, mu=0.5, mu_r=0.0, mu_s=0.0, law="complementarity",
             gravity=(0.0, 0.0, -G), **params):  # fmt: skip
    if law == "complementarity":
        params = {"solver": solver, "tolerance": 1e-10, "max_iterations": 500} | params
    sim = pdem.Simulation(law=law, **params)
    sim.add_material(
        "glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=e, friction=mu,
        rolling_friction=mu_r, spinning_friction=mu_s,
    )  # fmt: skip
    sim.gravity = gravity
    sim.dt = dt
    return sim


def hertz_overlap(r_eff, e_star):
    """Static Hertz overlap of a sphere's weight: m g = (4/3) E* sqrt(R*) δ^(3/2)."""
    m = 4 / 3 * math.pi * R**3 * 2500.0
    return (m * G / (4 / 3 * e_star * math.sqrt(r_eff))) ** (2 / 3)


E_STAR = 5e7 / (2 * (1 - 0.3**2))  # two glass bodies (the floor is glass too)


def floor(sim, normal=(0.0, 0.0, 1.0)):
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), normal), material="glass", name="floor")


# ----------------------------------------------------------------------------------- restitution
def first_rebound(e, solver="jacobi", height=0.01, dt=1e-5):
    """Drop a sphere from ``height`` (gap to the floor); the apex gap of its first rebound."""
    sim = make_sim(solver, dt=dt, e=e)
    sim.add_particles([[0.0, 0.0, R + height]], R, material="glass")
    floor(sim)
    sim.prepare()
    bounced = False
    apex = 0.0
    for _ in range(int(2.0 * math.sqrt(2 * height / G) * (1 + e) / dt)):
        sim.step()
        vz = sim.particles.v[0, 2]
        if vz > 0:
            bounced = True
        if bounced:
            apex = max(apex, sim.particles.x[0, 2] - R)
            if vz < 0:
                break
    assert bounced
    return apex


@pytest.mark.parametrize(
    "e", [0.3, pytest.param(0.5, marks=pytest.mark.integration),
          pytest.param(0.7, marks=pytest.mark.integration), 0.9]
)
def test_dropped_sphere_rebounds_to_e_squared_of_its_height(e):
    """Impact at 0.44 m/s (above the 0.1 m/s threshold); h = 1e-5 s. The first apex is e² H within
    1 % (measured: +0.38 % at e = 0.3, +0.12 % at 0.5, +0.04 % at 0.7, +0.01 % at 0.9; the error is the
    gap left at the impact step, at most a step's travel, relative to e² H)."""
    height = 0.01
    ratio = first_rebound(e, height=height) / height
    assert ratio == pytest.approx(e * e, rel=0.01)


@pytest.mark.integration
@pytest.mark.parametrize("solver", ["apgd", "gauss_seidel"])
def test_rebound_with_the_serial_solvers(solver):
    """The other solvers give the same rebound (e = 0.5) to within their tolerance."""
    assert first_rebound(0.5, solver) == pytest.approx(first_rebound(0.5, "jacobi"), rel=1e-6)


def test_bouncing_stops_below_the_threshold_and_the_sphere_then_rests():
    """e = 0.5 from 10 mm (impact at 0.443 m/s), threshold 0.1 m/s: it rebounds at 0.221, 0.111 and
    0.055 m/s; the next landing, at 0.055 m/s, is below the threshold: perfectly inelastic, it stays
    on the floor, at rest to the solver's tolerance (1e-10 m/s) for the rest of the run. A sphere
    resting on a floor with e = 0.9 does not move either."""
    sim = make_sim(dt=1e-4, e=0.5)
    sim.add_particles([[0.0, 0.0, R + 0.01]], R, material="glass")
    floor(sim)
    sim.prepare()
    vz = []
    for _ in range(3000):
        sim.step()
        vz.append(sim.particles.v[0, 2])
    vz = np.array(vz)
    launches = np.flatnonzero((vz[1:] > 1e-6) & (vz[:-1] < 0)) + 1
    assert len(launches) == 3
    v_impact = math.sqrt(2 * G * 0.01)
    for k, idx in enumerate(launches):
        # the rebound speed is e × the impact speed of the discrete fall (within a few steps' g h)
        assert vz[idx] == pytest.approx(0.5 ** (k + 1) * v_impact, abs=3 * G * 1e-4)
    rest = launches[-1] + 200  # after the last landing (0.011 s of flight)
    assert np.max(np.abs(vz[rest:])) < 1e-9
    assert abs(sim.particles.x[0, 2] - R) < 1e-9 * R

    # a sphere resting on a floor with e = 0.9, for 2,000 steps: it does not move
    sim = make_sim(dt=1e-4, e=0.9)
    sim.add_particles([[0.0, 0.0, R]], R, material="glass")
    floor(sim)
    z = []
    for _ in range(2000):
        sim.step()
        z.append(sim.particles.x[0, 2])
    assert np.max(np.abs(np.array(z) - R)) < 1e-9 * R
    assert np.max(np.abs(sim.particles.v[0])) < 1e-9


def test_threshold_key_sets_the_inelastic_limit():
    """With the threshold raised above the impact speed (0.443 m/s), the same drop does not bounce."""
    sim = make_sim(dt=1e-4, e=0.9, restitution_threshold=0.5)
    sim.add_particles([[0.0, 0.0, R + 0.01]], R, material="glass")
    floor(sim)
    vmax_up = 0.0
    for _ in range(700):
        sim.step()
        vmax_up = max(vmax_up, sim.particles.v[0, 2])
    assert vmax_up < 1e-9


# ----------------------------------------------------------------------------------- rolling friction
def rolling_sphere(law, mu_r, v0, dt, solver="jacobi", **params):
    sim = make_sim(solver, dt=dt, e=0.0, mu=0.5, mu_r=mu_r, law=law, **params)
    z0 = R if law == "complementarity" else R - hertz_overlap(R, E_STAR)  # DEM-P: at static overlap
    sim.add_particles([[0.0, 0.0, z0]], R, material="glass", velocities=[[v0, 0.0, 0.0]])
    floor(sim)
    sim.prepare()
    sim.particles.w[0] = (0.0, v0 / R, 0.0)  # rolling without slip
    return sim


def deceleration(sim, t_end, t_fit=(0.2, 0.8)):
    """Run to ``t_end`` and fit v_x(t) over the fraction ``t_fit`` of it: −slope."""
    t, v = [], []
    steps = int(round(t_end / sim.dt))
    for _ in range(steps):
        sim.step()
        t.append(sim.time)
        v.append(sim.particles.v[0, 0])
    t, v = np.array(t), np.array(v)
    sel = (t > t_fit[0] * t_end) & (t < t_fit[1] * t_end)
    return -np.polyfit(t[sel], v[sel], 1)[0], t, v


@pytest.mark.parametrize(("solver", "cone"), [(s, "corrected") for s in SOLVERS] + [("jacobi", "relaxed")])
def test_rolling_sphere_decelerates_at_five_sevenths_mu_r_g(solver, cone):
    """μ_r = 0.2, v0 = 0.2 m/s, rolling: a = (5/7) μ_r g = 1.401 m/s² within 1 %, still rolling
    without slip; it stops at t = v0/a and stays at rest (the rolling impulse holds it, it does
    not rock back). The relaxed cone gives the same (the contact sticks: no slip, no lift-off)."""
    mu_r, v0 = 0.2, 0.2
    a = 5 / 7 * mu_r * G
    t_stop = v0 / a
    sim = rolling_sphere("complementarity", mu_r, v0, 1e-4, solver, cone=cone)
    measured, t, v = deceleration(sim, 0.8 * t_stop)
    assert measured == pytest.approx(a, rel=0.01)
    p = sim.particles
    assert p.v[0, 0] == pytest.approx(R * p.w[0, 1], rel=1e-6)  # no slip
    assert abs(p.x[0, 2] - R) < 1e-9 * R
    for _ in range(int(0.4 * t_stop / sim.dt)):
        sim.step()
    assert abs(sim.particles.v[0, 0]) < 1e-9 and abs(sim.particles.w[0, 1]) < 1e-6
    assert sim.particles.x[0, 0] == pytest.approx(v0 * v0 / (2 * a), rel=0.01)


def test_rolling_deceleration_is_the_same_in_dem_p():
    """The key means the same torque bound μ_r R* F_n in both methods: DEM-P (Hertz–Mindlin) on the
    same sphere decelerates at (5/7) μ_r g within 1 % as well."""
    mu_r, v0 = 0.2, 0.2
    a = 5 / 7 * mu_r * G
    sim = rolling_sphere("hertz_mindlin", mu_r, v0, 5e-6)
    measured, _t, _v = deceleration(sim, 0.04)
    assert measured == pytest.approx(a, rel=0.01)


@pytest.mark.parametrize("theta_deg", [5.0, 15.0])
def test_sphere_on_an_incline_with_rolling_friction(theta_deg):
    """μ_r = 0.2 (tan θ = 0.2 at 11.3°): at 5° the sphere stays at rest (the rolling moment carries
    the friction force's moment, tan θ ≤ μ_r); at 15° it rolls at (5/7) g (sin θ − μ_r cos θ)."""
    mu_r = 0.2
    th = math.radians(theta_deg)
    sim = make_sim(dt=1e-4, e=0.0, mu=0.5, mu_r=mu_r, gravity=(G * math.sin(th), 0.0, -G * math.cos(th)))
    sim.add_particles([[0.0, 0.0, R]], R, material="glass")
    floor(sim)
    for _ in range(500):
        sim.step()
    v = sim.particles.v[0, 0]
    if math.tan(th) <= mu_r:
        assert abs(v) < 1e-9 and abs(sim.particles.x[0, 0]) < 1e-9 * R
    else:
        a = 5 / 7 * G * (math.sin(th) - mu_r * math.cos(th))
        assert v == pytest.approx(a * sim.time, rel=1e-3)


@pytest.mark.parametrize("law", ["complementarity", "hertz_mindlin"])
def test_rolling_friction_between_two_spheres(law):
    """A pair's rolling moment is bounded with DEM-P's R* = r_i r_j / (r_i + r_j) = r/2 here: a
    frictionless sphere resting on a fixed one (translation locked sideways), spun at 20 rad/s about
    a horizontal axis, is slowed only by the rolling moment μ_r (r/2) m g, so ω falls at
    α = μ_r (r/2) m g / I = 1.25 μ_r g / r until it stops at ω0/α = 16.3 ms (within 1 %)."""
    mu_r, omega0 = 0.1, 20.0
    dt = 1e-4 if law == "complementarity" else 5e-6
    sim = make_sim(dt=dt, e=0.0, mu=0.0, mu_r=mu_r, law=law)
    sim.add_particles([[0.0, 0.0, 0.0]], R, material="glass", motion="fixed")
    z0 = 2 * R if law == "complementarity" else 2 * R - hertz_overlap(R / 2, E_STAR)
    sim.add_particles([[0.0, 0.0, z0]], R, material="glass", fixed_translation="xy",
                      angular_velocities=[[0.0, omega0, 0.0]])  # fmt: skip
    sim.prepare()
    top = int(np.flatnonzero(sim.particles.id[:2] == 1)[0])
    t_stop = omega0 / (1.25 * mu_r * G / R)
    stopped = None
    for _ in range(int(1.3 * t_stop / dt)):
        sim.step()
        if stopped is None and abs(sim.particles.w[top, 1]) < 1e-6 * omega0:
            stopped = sim.time
    assert stopped == pytest.approx(t_stop, rel=0.01)


# ----------------------------------------------------------------------------------- spinning friction
@pytest.mark.parametrize("law", ["complementarity", "hertz_mindlin"])
def test_spinning_sphere_stops_after_the_closed_form_time(law):
    """μ_s = 0.1, a sphere spinning about the floor normal at 100 rad/s: the torque μ_s r m g
    decelerates it at 2.5 μ_s g / r, so it stops at t = ω0 r / (2.5 μ_s g) = 40.8 ms (within 1 %),
    and stays stopped; DEM-P (the same key) gives the same time."""
    mu_s, omega0 = 0.1, 100.0
    dt = 1e-4 if law == "complementarity" else 5e-6
    sim = make_sim(dt=dt, e=0.0, mu=0.5, mu_s=mu_s, law=law)
    z0 = R if law == "complementarity" else R - hertz_overlap(R, E_STAR)
    sim.add_particles([[0.0, 0.0, z0]], R, material="glass")
    floor(sim)
    sim.prepare()
    sim.particles.w[0] = (0.0, 0.0, omega0)
    t_stop = omega0 * R / (2.5 * mu_s * G)
    stopped = None
    for _ in range(int(1.3 * t_stop / dt)):
        sim.step()
        if stopped is None and abs(sim.particles.w[0, 2]) < 1e-6 * omega0:
            stopped = sim.time
    assert stopped is not None
    assert stopped == pytest.approx(t_stop, rel=0.01)
    assert abs(sim.particles.w[0, 2]) < 1e-6 * omega0


# ----------------------------------------------------------------------------------- checkpoints
def test_a_checkpoint_with_the_old_four_column_history_resumes():
    """Before rolling friction DEM-C kept 4 floats of history per contact (γ_n, γ_t); a checkpoint
    written then resumes with zero rolling impulses: without rolling friction, bitwise as from the
    same checkpoint with 8 columns."""
    import test_dem_c as base

    kw = {"tolerance": 1e-6, "max_iterations": 60}
    sim = base._packing("jacobi", v0=-1.0, **kw)
    sim.run(steps=20)
    state = sim.state_dict()
    old = dict(state)
    for k in old:
        if k == "pairs/hist" or (k.startswith("walls/") and k.endswith("/hist")):
            assert np.all(np.asarray(old[k])[:, 4:] == 0.0)
            old[k] = np.asarray(old[k])[:, :4]
    runs = []
    for st in (state, old):
        resumed = base._packing("jacobi", add=False, **kw)
        resumed.load_state(st)
        resumed.run(steps=10)
        runs.append(resumed.state_dict())
    assert runs[1]["pairs/hist"].shape[1] == 8
    for k in runs[0]:
        assert np.array_equal(np.asarray(runs[0][k]), np.asarray(runs[1][k])), k


# ------------------------------------------------------------------------- rows of 4 and of 8 columns
@pytest.mark.parametrize("solver", SOLVERS)
def test_rows_without_rolling_give_the_bits_of_rows_of_eight(solver, monkeypatch):
    """Without rolling or spinning friction the contact rows hold 4 impulses instead of 8 (half the
    data streamed per iteration). The results must be the bits of the 8-column rows, also when rolling
    friction is switched on mid-run (the rows widen, the warm start carries over)."""
    from pdem.complementarity.method import Stepper

    def run():
        sim = make_sim(solver, dt=2e-4, e=0.3, max_iterations=30)
        floor(sim)
        rng = np.random.default_rng(3)
        x = np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(3)), -1).reshape(-1, 3) * 2.2 * R
        x = x + rng.uniform(-0.1 * R, 0.1 * R, x.shape) + [0.0, 0.0, 1.2 * R]
        sim.add_particles(x, R, material="glass", velocities=rng.uniform(-0.05, 0.05, x.shape))
        widths = []
        for k in range(2):
            if k == 1:
                sim.set_material("glass", rolling_friction=0.1, spinning_friction=0.05)
            sim.run(steps=40)
            widths.append(sim.integrator.gam.shape[1])
        p = sim.get_particles()
        return widths, {f: np.asarray(p[f]).copy() for f in ("x", "v", "w")}

    widths, natural = run()
    assert widths == [4, 8]
    monkeypatch.setattr(Stepper, "_row_width", lambda self: 8)
    widths8, eight = run()
    assert widths8 == [8, 8]
    assert np.any(natural["v"] != 0.0)
    for f in natural:
        assert np.array_equal(natural[f], eight[f]), f
