"""The penetrometer (pdem.boundaries.penetrometer): the cone's load on single grains against Hertz on
the facet planes (tip, shaft, the rim counted once), a dropped ball in free fall against ballistic
kinematics and at rest on a grain layer (DEM-P and DEM-C), hostile keys, and the small deck
bitwise identical on 1 and 3 ranks through the CLI."""

from __future__ import annotations

import csv
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import pdem
from pdem.api import DeckError, InputError
from pdem.boundaries.penetrometer import Penetrometer, PenetrometerParams, cone_mesh
from pdem.cli import main
from pdem.deck import load_deck
from pdem.plugins import available

ROOT = Path(__file__).resolve().parents[1]
SMALL = ROOT / "tests" / "data" / "cone_small.toml"
DECKS = [
    ROOT / "inputs" / n for n in ("cone_penetration.toml", "cone_penetration_full.toml", "cone_drop.toml")
]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")

E, NU, R_GRAIN = 1e8, 0.3, 1.5e-3
E_STAR = E / (1 - NU**2)  # a grain against a rigid wall


def _series(path: Path) -> dict[str, np.ndarray]:
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def _scene(law: str = "hertz_mindlin", e: float = 1.0, **keys):
    """A simulation with a penetrometer ``pen`` (rigid, frictionless; e = 1: no damping)."""
    sim = pdem.Simulation(law=law)
    sim.add_material("bead", density=2500, youngs_modulus=E, poisson_ratio=NU, restitution=e, friction=0.0)
    sim.add_material(pdem.Material.rigid_wall("steel", friction=0.0, restitution=e))
    params = dict(type="penetrometer", material="steel", penetration_stage="go", start_gap=0.0)
    params.update(keys)
    pen = Penetrometer("pen", PenetrometerParams(**params))
    return sim, pen


def _facet_plane(pen, facet: int):
    """Unit outward normal and a point of facet ``facet`` of the penetrometer's mesh, now: computed
    from the mesh vertices, independently of pdem's contact kernels."""
    verts, tris, _ = cone_mesh(
        pen.diameter, pen.params.apex_deg, pen.params.shaft_length, pen.params.segments
    )
    verts = verts + pen.body.offset + (pen.params.axis[0], pen.params.axis[1], 0.0)
    a, b, c = verts[tris[facet]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n)
    mid = (a + b + c) / 3.0
    axis_pt = np.array([pen.params.axis[0], pen.params.axis[1], mid[2]])
    if n @ (mid - axis_pt) < 0:  # outward: away from the axis
        n = -n
    return n, a


def _hertz(delta: float) -> float:
    return 4.0 / 3.0 * E_STAR * math.sqrt(R_GRAIN) * delta**1.5


def _press(sim, pen, centre, facet, overlap):
    """Place the grain so that it overlaps facet ``facet`` by ``overlap`` (the body is moved), take
    one step of 1e-8 s (the grain moves ~1e-13 m) and return (grain position, load on the body)."""
    sim.add_particles([centre], R_GRAIN, material="bead")
    sim.add_boundary(pen)
    sim.set_stage("go")
    n, a = _facet_plane(pen, facet)
    # move the body down so that n·(c − a) = r − overlap (a tip facet: n_z ≠ 0)
    gap = n @ (np.asarray(centre) - a) - (R_GRAIN - overlap)
    off = pen.body.offset.copy()
    off[2] += gap / n[2]
    pen.body.set_offset(off)
    pen.motion.velocity = np.zeros(3)
    sim.dt = 1e-8
    sim.step()
    x = sim.get_particles()["x"][0]
    return x, pen.body.facet_loads()


@pytest.mark.parametrize("apex", [60.0, 30.0])
def test_cone_tip_load_is_hertz_on_the_facet(apex):
    """A grain pressed by a cone facet: the load on the body is (4/3) E* sqrt(r) δ^{3/2} along the
    facet's inward normal, with δ from the facet plane (vertices of the mesh), all of it on that tip
    facet, none on the shaft; tip_force is its vertical part and q_c = tip_force / base area."""
    sim, pen = _scene(apex_deg=apex, speed=1e-9, segments=48)
    seg = 48
    phi = math.pi / seg  # the middle of facet 0
    rho = 0.6 * 0.5 * pen.diameter
    centre = np.array([rho * math.cos(phi), rho * math.sin(phi), 0.0])
    x, loads = _press(sim, pen, centre, 0, 2e-5)
    n, a = _facet_plane(pen, 0)
    delta = R_GRAIN - n @ (x - a)
    assert delta == pytest.approx(2e-5, rel=1e-6)
    f = loads[0, :3]
    assert np.linalg.norm(f) == pytest.approx(_hertz(delta), rel=1e-9)
    assert np.allclose(f / np.linalg.norm(f), -n, atol=1e-12)  # pushed along the facet normal
    assert np.count_nonzero(np.abs(loads).sum(axis=1)) == 1  # one contact, on the tip facet
    m = pen.measurements(sim)
    assert m["tip_force"] == pytest.approx(f[2], rel=1e-12) and m["shaft_force"] == 0.0
    assert m["qc"] == pytest.approx(f[2] / 323e-6, rel=1e-12)
    assert f[2] > 0  # the grain resists the descent


def test_shaft_load_is_hertz_and_apart_from_the_tip():
    """A grain beside the rod: the load is horizontal, Hertz from the facet plane, all on the shaft;
    the tip carries nothing."""
    sim, pen = _scene(speed=1e-9, segments=48, shaft_length=0.05)
    sim.add_particles([[0.0, 0.0, -0.05]], R_GRAIN, material="bead", motion="fixed")  # the "bed"
    sim.add_boundary(pen)
    sim.set_stage("go")
    phi = math.pi / 48  # the middle of shaft facet pair 0
    sim2, pen2 = sim, pen
    n, a = _facet_plane(pen2, 48)  # the first shaft triangle
    apothem = n @ (a - np.array([0.0, 0.0, a[2]]))
    z = pen2.tip_z() + pen2.cone_length + 0.02
    overlap = 2e-5
    rho = apothem + R_GRAIN - overlap
    centre = np.array([rho * math.cos(phi), rho * math.sin(phi), z])
    # n is horizontal at azimuth π/48 exactly (the facet's middle)
    assert abs(n[2]) < 1e-12 and np.allclose(n[:2], [math.cos(phi), math.sin(phi)], atol=1e-12)
    sim2.add_particles([centre], R_GRAIN, material="bead")
    sim2.dt = 1e-8
    sim2.step()
    ids = sim2.get_particles()
    x = ids["x"][1]
    delta = R_GRAIN - n @ (x - a)
    loads = pen2.body.facet_loads()
    tip, shaft = loads[:48], loads[48:]
    assert np.all(tip == 0.0)
    f = shaft[:, :3].sum(axis=0)
    assert np.count_nonzero(np.abs(shaft).sum(axis=1)) == 1
    assert np.linalg.norm(f) == pytest.approx(_hertz(delta), rel=1e-9)
    assert np.allclose(f / np.linalg.norm(f), -n, atol=1e-12)
    m = pen2.measurements(sim2)
    assert m["tip_force"] == 0.0 and abs(m["shaft_force"]) < 1e-12 * np.linalg.norm(f)


def test_grain_at_the_rim_counts_once():
    """A grain just outside the rim where cone and rod meet (within reach of both surfaces' edges)
    is loaded once, by Hertz against the rim circle."""
    sim, pen = _scene(speed=1e-9, segments=48)
    sim.add_particles([[0.0, 0.0, -0.05]], R_GRAIN, material="bead", motion="fixed")
    sim.add_boundary(pen)
    sim.set_stage("go")
    radius = 0.5 * pen.diameter
    z_rim = pen.tip_z() + pen.cone_length
    # direction from the rim vertex 0 (azimuth 0: a mesh vertex, on the true circle), 10° below
    # the horizontal: between the cone's outward normal (30° below) and the rod's (horizontal)
    ang = math.radians(-10.0)
    overlap = 2e-5
    d = R_GRAIN - overlap
    centre = np.array([radius + d * math.cos(ang), 0.0, z_rim + d * math.sin(ang)])
    sim.add_particles([centre], R_GRAIN, material="bead")
    sim.dt = 1e-8
    sim.step()
    x = sim.get_particles()["x"][1]
    delta = R_GRAIN - np.linalg.norm(x - np.array([radius, 0.0, z_rim]))
    loads = pen.body.facet_loads()
    assert np.count_nonzero(np.abs(loads).sum(axis=1)) == 1  # one row of the mesh carries it
    f = loads[:, :3].sum(axis=0)
    assert np.linalg.norm(f) == pytest.approx(_hertz(delta), rel=1e-6)


@pytest.mark.parametrize("law, dt", [("hertz_mindlin", 1e-5), ("complementarity", 1e-4)])
def test_dropped_ball_falls_ballistically_then_rests_on_a_layer(law, dt):
    """A 1-inch ball released 2 cm above a fixed layer of grains: before contact its velocity and
    height follow free fall as integrated (symplectic Euler: v_k = −g k dt, z_k = z_0 − g dt² k(k+1)/2,
    within O(dt) of the ballistic curve); it comes to rest on the layer, its lowest point between
    the grain tops: here on top of the grain under the axis (depth 0 to within its overlap)."""
    sim, pen = _scene(
        law=law, e=0.1, tip="sphere", mode="drop", release_height=0.02, rest_time=0.01, fall="integrate"
    )
    sim.gravity = (0.0, 0.0, -9.81)
    k = np.arange(15 * 15)
    s = 3.02e-3
    x = np.stack([(k % 15 - 7) * s, (k // 15 - 7) * s, np.zeros(k.size)], axis=1)
    sim.add_particles(x, R_GRAIN, material="bead", motion="fixed")
    sim.add_boundary(pen)
    sim.set_stage("go")
    assert pen.surface == pytest.approx(R_GRAIN, abs=1e-15)
    assert pen.mass == pytest.approx(700.0 * math.pi * 0.0254**3 / 6.0, rel=1e-12)
    sim.dt = dt
    g = 9.81
    z0 = pen.tip_z()
    steps = 0
    while pen.tip_z() > R_GRAIN + 1e-3:  # 1 mm above the tops: nothing touched yet
        sim.step()
        steps += 1
        m = pen.measurements(sim)
        t = steps * dt
        assert m["tip_force"] == 0.0
        assert m["velocity"] == pytest.approx(-g * steps * dt, rel=1e-9)
        assert pen.tip_z() == pytest.approx(z0 - g * dt * dt * steps * (steps + 1) / 2, abs=1e-12)
        assert abs(pen.tip_z() - (z0 - 0.5 * g * t * t)) <= g * dt * t  # ballistic within O(dt)
    assert steps * dt == pytest.approx(math.sqrt(2 * (0.02 - 1e-3) / g), abs=2 * dt)
    assert math.isnan(pen.impact_velocity)
    for _ in range(int(0.2 / dt)):
        sim.step()
        if pen.measurements(sim)["at_rest"] == 1.0:
            break
    # the impact velocity is the fall's as the ball meets the grain under the axis (its tip at the
    # grain tops, 2 cm below the release), with either law: a rigid contact stops the ball within
    # its first step, so it is read before that step
    assert pen.impact_velocity == pytest.approx(-math.sqrt(2 * g * 0.02), abs=3 * g * dt)
    m = pen.measurements(sim)
    assert m["at_rest"] == 1.0
    assert -1e-6 <= m["depth"] <= 5e-5
    # at rest the layer carries the ball's weight
    assert m["tip_force"] == pytest.approx(pen.mass * g, rel=0.05)


def test_registered_and_decks_validate():
    assert "penetrometer" in available("boundaries")
    for deck in DECKS:
        load_deck(deck)
    load_deck(DECKS[0], overrides=["contact.law=complementarity", "run.dt=1.0e-4"])
    load_deck(DECKS[0], overrides=["boundaries.pen.apex_deg=30.0"])
    assert main(["check", str(SMALL)]) == 0


@pytest.mark.parametrize(
    "override, words",
    [
        ("boundaries.pen.apex_deg=-30.0", ["apex_deg", "(0, 180)", "60"]),
        ("boundaries.pen.apex_deg=180.0", ["apex_deg", "(0, 180)"]),
        ("boundaries.pen.mode=fall", ["mode", "push", "drop"]),
        ("boundaries.pen.tip=cube", ["tip", "cone", "sphere"]),
        ("boundaries.pen.speed=-0.02", ["speed", "> 0"]),
        ("boundaries.pen.base_area=0.0", ["base_area", "3.23e-4"]),
        ("boundaries.pen.penetration_stage=pentrate", ["penetration_stage", "penetrate"]),
        ("boundaries.pen.apex=60.0", ["apex", "apex_deg"]),
    ],
)
def test_hostile_keys_are_deck_errors(override, words):
    with pytest.raises(DeckError) as err:
        load_deck(SMALL, overrides=[override])
    text = str(err.value)
    for w in words:
        assert w in text, (w, text)


def test_release_into_the_grains_is_an_input_error(tmp_path):
    """A release height below the highest grain under the body names the key and the remedy."""
    deck = load_deck(SMALL)
    assert deck is not None
    sim, pen = _scene(tip="sphere", mode="drop", release_height=1e-4)
    k = np.arange(9)
    sim.add_particles(np.stack([(k % 3 - 1) * 3.02e-3, (k // 3 - 1) * 3.02e-3, 0.0 * k], 1), R_GRAIN,
                      material="bead", motion="fixed")  # fmt: skip
    sim.add_particles([[0.0, 0.0, 2.5e-3]], R_GRAIN, material="bead", motion="fixed")  # one sticks up
    sim.add_boundary(pen)
    with pytest.raises(InputError, match="release_height.*larger release_height"):
        sim.set_stage("go")


def test_small_deck_pushes_and_summarises(tmp_path):
    out = tmp_path / "push"
    assert main([str(SMALL), "--output", str(out), "--quiet"]) == 0
    s = _series(out / "series_penetrate.csv")
    summary = json.loads((out / "summary.json").read_text())["results"]["pen"]
    depth = s["pen.depth"]
    assert np.all(np.diff(depth) > 0)  # pushed down at constant speed
    assert np.allclose(np.diff(depth), 0.5 * 1e-3, rtol=1e-6)  # 0.5 m/s × 100 steps × 1e-5 s
    assert summary["final_depth"] == pytest.approx(depth[-1])
    assert s["pen.qc"][-1] > 0 and s["pen.tip_force"][-1] > 0
    assert np.allclose(s["pen.qc"], s["pen.tip_force"] / (math.pi * 0.005**2), rtol=1e-12)
    assert np.allclose(s["pen.total_force"], s["pen.tip_force"] + s["pen.shaft_force"], rtol=1e-9, atol=1e-12)
    assert "qc_mean" in summary


@pytest.mark.slow
@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
@pytest.mark.parametrize(
    "overrides",
    [
        [],  # DEM-P, pushed
        [
            "contact.law=complementarity",
            "run.dt=1.0e-4",
            "boundaries.pen.mode=drop",
            "boundaries.pen.release_height=0.003",
            "stages.settle.end.steps=30",
            "stages.penetrate.end.steps=150",
            "output.every_steps=180",
            "output.checkpoint_every_steps=180",
            "output.series_every_steps=10",
        ],
    ],
    ids=["dem_p_push", "dem_c_drop"],
)
def test_small_deck_identical_on_1_and_3_ranks(tmp_path, overrides):
    """The small deck through the CLI (placement from the bed, loads split by rows, the dropped body
    solved with the grains): the final checkpoint and the series are bitwise the same on 3 ranks."""
    sys.path.insert(0, str(ROOT / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    states, series = {}, {}
    for ranks in (1, 3):
        out = tmp_path / f"r{ranks}"
        cmd = [sys.executable, "-m", "pdem", str(SMALL), "--output", str(out), "--quiet"]
        for o in overrides:
            cmd += ["--set", o]
        if ranks > 1:
            cmd = [MPIEXEC, "-n", str(ranks), *cmd]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        states[ranks], _ = read_checkpoint(out / "checkpoints" / "latest.h5")
        series[ranks] = _series(out / "series_penetrate.csv")
    assert compare(states[1], states[3]) is None
    for key in series[1]:
        if key.startswith("pen.") or key in ("time", "step"):
            assert np.array_equal(series[1][key], series[3][key], equal_nan=True), key
    assert np.nanmax(np.abs(series[1]["pen.total_force"])) > 0  # the body did meet the grains


def test_analytic_fall_matches_the_stepped_fall():
    """fall = "analytic" starts the ball start_gap above the highest grain with the speed of a free
    fall from H: the stepped fall (fall = "integrate") passes that height at the same speed, to
    O(g dt)."""
    dt, g = 1e-5, 9.81
    speeds = {}
    for fall in ("analytic", "integrate"):
        sim, pen = _scene(e=0.1, tip="sphere", mode="drop", release_height=0.01, fall=fall, start_gap=1e-3)
        sim.gravity = (0.0, 0.0, -g)
        sim.add_particles([[0.0, 0.0, 0.0]], R_GRAIN, material="bead", motion="fixed")
        sim.add_boundary(pen)
        sim.set_stage("go")
        sim.dt = dt
        if fall == "analytic":
            assert pen.tip_z() == pytest.approx(R_GRAIN + 1e-3, abs=1e-15)
            speeds[fall] = pen.motion.velocity_now[2]
        else:
            while pen.tip_z() > R_GRAIN + 1e-3:
                sim.step()
            speeds[fall] = pen.measurements(sim)["velocity"]
    assert speeds["analytic"] == pytest.approx(-math.sqrt(2 * g * (0.01 - 1e-3)), rel=1e-12)
    assert abs(speeds["integrate"] - speeds["analytic"]) < 2 * g * dt


def test_resume_inside_the_drop_is_bitwise(tmp_path):
    """A checkpoint taken while the dropped body moves (its velocity, the surface and the touch are
    boundary state): resuming from it ends bitwise where the uninterrupted run ends."""
    sys.path.insert(0, str(ROOT / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    sets = ["boundaries.pen.mode=drop", "output.checkpoint_every_steps=750", "output.every_steps=750"]
    full, cont = tmp_path / "full", tmp_path / "cont"
    args = [str(SMALL), "--output", str(full), "--quiet"]
    for s in sets:
        args += ["--set", s]
    assert main(args) == 0
    assert (
        main(["resume", str(full / "checkpoints" / "step_0000000750.h5"), "--output", str(cont), "--quiet"])
        == 0
    )
    a, _ = read_checkpoint(full / "checkpoints" / "latest.h5")
    b, _ = read_checkpoint(cont / "checkpoints" / "latest.h5")
    assert int(a["scalars/step"]) == int(b["scalars/step"]) == 1500
    assert compare(a, b) is None
    sa, sb = _series(full / "series_penetrate.csv"), _series(cont / "series_penetrate.csv")
    for key in ("pen.depth", "pen.velocity", "pen.tip_force", "pen.surface"):
        assert np.array_equal(sa[key], sb[key]), key


def test_a_killed_sphere_drop_resumes_and_a_sphere_still_refuses_another_apex(tmp_path):
    """The resolved deck stored in a checkpoint writes apex_deg's default out; resuming a sphere
    drop from it must not read that as the user's apex angle (it did: 'applies to tip = cone
    only'). An explicit other angle on a sphere is still an error naming the key."""
    sets = ["--set", "boundaries.pen.tip=sphere", "--set", "boundaries.pen.mode=drop"]
    out = tmp_path / "run"
    assert main([str(SMALL), "--quiet", "--steps", "5", "--output", str(out), *sets]) == 0
    assert main(["resume", str(out / "checkpoints" / "latest.h5"), "--steps", "8", "--quiet"]) == 0
    with pytest.raises(DeckError, match="apex_deg"):
        load_deck(SMALL, overrides=["boundaries.pen.tip=sphere", "boundaries.pen.apex_deg=30.0"])
