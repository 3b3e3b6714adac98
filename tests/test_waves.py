"""Shock waves (experiments.md §1): the sensors and impulse boundaries (pdem.boundaries.probes), fixed
edges and 2-D mode from decks, the 1-D chain against Nesterenko's solitary wave, the 2-D bed bitwise
identical on 1 and 3 ranks, hostile sensor keys."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

import pdem
from pdem.api import DeckError, InputError
from pdem.boundaries.probes import Impulse, ImpulseParams, Sensors, SensorsParams
from pdem.cli import main
from pdem.deck import load_deck

ROOT = Path(__file__).resolve().parents[1]
CHAIN = ROOT / "inputs" / "wave_chain.toml"
BED = ROOT / "inputs" / "shock_wave.toml"
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")


def _tool():
    spec = importlib.util.spec_from_file_location("wave_analysis", ROOT / "tools" / "wave_analysis.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _run(deck: Path, out: Path, *overrides: str) -> dict:
    args = [str(deck), "--output", str(out), "--quiet"]
    for o in overrides:
        args += ["--set", o]
    assert main(args) == 0
    return json.loads((out / "summary.json").read_text())


def _short_chain(n: int = 40, v: float = 1.0, end: float = 4.5e-4) -> list[str]:
    return [
        f"particles.0.n_cols={n}",
        f"boundaries.chain.ids={list(range(n))}",
        f"particles.1.velocity=[{v}, 0.0, 0.0]",
        f"stages.impact.end.time={end}",
        "output.every_steps=100000",
    ]


def _small_bed(n: int = 15, end: float = 2.4e-5) -> list[str]:
    """An n x n bed (n odd), sensors 0, 4 spacings along the surface and 0, 4, 8 down."""
    s, h = 2e-3, 2e-3 * math.sqrt(3.0) / 2.0
    top = [(n // 2) * s, 0.0, (n - 1) * h]
    return [
        f"particles.0.n_cols={n}",
        f"particles.0.n_rows={n}",
        f"boundaries.kick.positions=[{top}]",
        f"boundaries.surface.line.start={top}",
        f"boundaries.surface.line.step=[{4 * s}, 0.0, 0.0]",
        "boundaries.surface.line.count=2",
        f"boundaries.depth.line.start={top}",
        f"boundaries.depth.line.step=[0.0, 0.0, {-4 * s}]",
        "boundaries.depth.line.count=3",
        f"stages.impact.end.time={end}",
        "output.every_time=1.2e-5",
    ]


# ------------------------------------------------------------------------------------ the 1-D chain
@pytest.fixture(scope="module")
def chains(tmp_path_factory):
    """A 40-bead chain struck at 0.5, 1 and 4 m/s (DEM-P)."""
    base = tmp_path_factory.mktemp("chain")
    runs = []
    for v in (0.5, 1.0, 4.0):
        out = base / f"v{v}"
        _run(CHAIN, out, *_short_chain(v=v, end=3.5e-4 if v < 1 else 3.0e-4))
        runs.append(out)
    return runs


def test_chain_speed_is_nesterenkos(chains):
    """V_s from the beads' peak times over the middle of the chain within 3 % of Nesterenko's closed form
    with the run's F_m (the largest contact force), and the exponent of V_s ∝ F_m^α within 1/6 ± 0.02."""
    tool = _tool()
    res = [tool.analyse_chain(r) for r in chains]
    for r in res:
        assert abs(r["error"]) < 0.03, r
        assert r["F_m_spread"] < 0.01  # a steady solitary wave: the same peak force along the middle
        assert 3.5 < r["width_d"] < 6.0  # the pulse: ≈ 5 diameters (cos^4 profile of the same FWHM)
    lf, lv = np.log([r["F_m"] for r in res]), np.log([r["V_s"] for r in res])
    alpha = np.polyfit(lf, lv, 1)[0]
    assert abs(alpha - 1.0 / 6.0) < 0.02, alpha


def test_chain_resume_keeps_arrivals(tmp_path):
    """The sensors' online state is in checkpoints: a run stopped and resumed reports the same arrival
    and peak times, and its sensor CSV is the uninterrupted one."""
    sets = _short_chain(n=20, end=1.6e-4)
    ref = _run(CHAIN, tmp_path / "ref", *sets)
    out = tmp_path / "cut"
    assert (
        main(
            [
                str(CHAIN),
                "--output",
                str(out),
                "--quiet",
                "--steps",
                "301",
                *sum((["--set", s] for s in sets), []),
            ]
        )
        == 0
    )
    assert main(["resume", str(out / "checkpoints" / "latest.h5"), "--quiet"]) == 0
    got = json.loads((out / "summary.json").read_text())
    assert got["results"]["chain"] == ref["results"]["chain"]
    assert (out / "chain.impact.csv").read_bytes() == (tmp_path / "ref" / "chain.impact.csv").read_bytes()


# ------------------------------------------------------------------------------------ sensors, brute force
def _scene():
    sim = pdem.Simulation()
    sim.add_material(
        "glass", density=2500, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5, friction=0.3
    )
    rng = np.random.default_rng(3)
    k = np.arange(27)
    x = np.stack([k % 3, k // 3 % 3, k // 9], 1) * 2.05e-3 + rng.uniform(-1e-4, 1e-4, (27, 3))
    x[:, 2] += 1.1e-3
    sim.add_particles(x, 1e-3)
    sim.add_wall(pdem.api.shapes.Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0, 0, -9.81)
    sim.dt = 2e-6
    return sim


def test_sensors_match_the_particle_state():
    sim = _scene()
    target = sim.get_particles()["x"][13] + [3e-4, 0, 0]
    # a point exactly between grains 0 and 1: the tie goes to the lower id
    tie = 0.5 * (sim.get_particles()["x"][0] + sim.get_particles()["x"][1])
    params = SensorsParams(type="sensors", ids=[26, 4], positions=[tuple(target), tuple(tie)], threshold=2e-3,
                           force_threshold=1e-3)  # fmt: skip
    probe = sim.add_boundary(Sensors("probe", params))
    speeds, fcs, times = [], [], []
    for _ in range(400):
        sim.step()
        rows = probe.records(sim)
        assert len(rows) == 1
        row = rows[0]
        p = sim.get_particles()
        c = sim.contacts()
        assert probe.ids.tolist()[:3] == [26, 4, 13]
        d = np.linalg.norm(p["x"] - tie, axis=1)
        assert probe.ids[3] == np.flatnonzero(d == d.min()).min()
        sp, fc = [], []
        for k, gid in enumerate(probe.ids):
            i = int(np.flatnonzero(p["id"] == gid)[0])
            v, f = p["v"][i], p["f"][i]
            assert [row[f"s{k}.vx"], row[f"s{k}.vy"], row[f"s{k}.vz"]] == v.tolist()
            assert row[f"s{k}.speed"] == pytest.approx(np.linalg.norm(v), rel=1e-15)
            assert row[f"s{k}.f"] == pytest.approx(np.linalg.norm(f), rel=1e-15)
            mine = (c["id_i"] == gid) | (c["id_j"] == gid)
            expect = max(c["normal_force"][mine].max(), 0.0) if mine.any() else 0.0
            assert row[f"s{k}.fc"] == pytest.approx(expect, rel=1e-12, abs=1e-300)
            sp.append(row[f"s{k}.speed"])
            fc.append(row[f"s{k}.fc"])
        speeds.append(sp)
        fcs.append(fc)
        times.append(sim.time)
    speeds, fcs, times = np.array(speeds), np.array(fcs), np.array(times)
    res = probe.summary({})
    for k in range(len(probe.ids)):
        s = speeds[:, k]
        j = int(np.argmax(s > 2e-3))
        assert s[j] > 2e-3
        t_arr = (
            times[j]
            if j == 0
            else times[j - 1] + (2e-3 - s[j - 1]) / (s[j] - s[j - 1]) * (times[j] - times[j - 1])
        )
        assert res["arrival_time"][k] == pytest.approx(t_arr, rel=1e-12)
        m = int(np.argmax(s))
        assert res["peak_speed"][k] == s[m]
        assert (
            abs(res["peak_time"][k] - times[m]) <= sim.dt / 2
        )  # parabolic refinement stays within a half step
        assert res["peak_force"][k] == fcs[:, k].max()
    meas = probe.measurements(sim)
    assert meas["arrived_count"] == np.count_nonzero(np.isfinite(np.array(res["arrival_time"], float)))


def test_sensors_cost_nothing_between_samples():
    sim = _scene()
    probe = sim.add_boundary(
        Sensors("probe", SensorsParams(type="sensors", ids=[3], threshold=1.0, every=50))
    )
    sim.run(steps=120)
    rows = probe.records(sim)
    assert [r["step"] for r in rows] == [50, 100]


def test_impulse_sets_velocity_once_and_refuses_fixed_grains():
    sim = _scene()
    kick = sim.add_boundary(
        Impulse("kick", ImpulseParams(type="impulse", ids=[5], velocity=(0.0, 0.0, -1.0)))
    )
    sim.set_stage("a")
    assert sim.get_particles()["v"][5].tolist() == [0.0, 0.0, -1.0]
    sim.run(steps=5)
    v = sim.get_particles()["v"][5].copy()
    sim.set_stage("b")  # once per run
    assert sim.get_particles()["v"][5].tolist() == v.tolist()
    assert kick.state() == {"applied": True, "ids": [5]}
    sim2 = pdem.Simulation()
    sim2.add_material("m")
    sim2.add_particles([[0, 0, 0], [3e-3, 0, 0]], 1e-3, motion=["fixed", "free"])
    sim2.add_boundary(
        Impulse("kick", ImpulseParams(type="impulse", positions=[(0, 0, 0)], velocity=(1, 0, 0)))
    )
    with pytest.raises(InputError, match="boundaries.kick: a chosen grain is fixed"):
        sim2.set_stage("a")


# ------------------------------------------------------------------------------------ hostile keys
@pytest.mark.parametrize(
    "override, key",
    [
        ("boundaries.surface.every=0", "boundaries.surface.every"),
        ("boundaries.surface.every=1.5", "boundaries.surface.every"),
        ("boundaries.surface.threshold=-1.0", "boundaries.surface.threshold"),
        ("boundaries.surface.threshold=nan", "boundaries.surface.threshold"),
        ('boundaries.surface.threshold="0.1"', "boundaries.surface.threshold"),
        ("boundaries.surface.force_threshold=0.0", "boundaries.surface.force_threshold"),
        ("boundaries.surface.ids=[-3]", "ids"),
        ("boundaries.surface.ids=[4, 4]", "ids"),
        ("boundaries.surface.ids=[1e3]", "boundaries.surface.ids"),
        ("boundaries.surface.line.count=0", "boundaries.surface.line.count"),
        ("boundaries.surface.line.step=[1.0, 2.0]", "boundaries.surface.line.step"),
        ("boundaries.surface.line.stepp=[1.0, 2.0, 3.0]", "boundaries.surface.line.stepp"),
        ("boundaries.surface.thresold=1.0", "thresold"),
        ('boundaries.surface.quantities=["vq"]', "boundaries.surface.quantities"),
        ("boundaries.surface.quantities=[]", "boundaries.surface.quantities"),
        ("boundaries.surface.positions=[[0.0, 0.0]]", "boundaries.surface.positions"),
        ("boundaries.kick.velocity=[0.0, 0.0, inf]", "boundaries.kick.velocity"),
        ('particles.0.fixed_edges=["middle"]', "particles.0.fixed_edges"),
        ('particles.0.fixed_translation="w"', "particles.0.fixed_translation"),
        ('particles.0.fixed_rotation="xyzx"', "particles.0.fixed_rotation"),
    ],
)
def test_hostile_keys_are_deck_errors_naming_the_key(override, key):
    with pytest.raises(DeckError) as exc:
        load_deck(BED, overrides=[override])
    assert key in str(exc.value), str(exc.value)


def test_no_grains_chosen_and_fixed_edges_off_hex2d(tmp_path):
    text = BED.read_text()
    start = text.index("[boundaries.surface]")
    end = text.index("[boundaries.depth]")
    body = text[start:end].replace("line = {", "# line = {")
    deck = tmp_path / "d.toml"
    deck.write_text(text[:start] + body + text[end:])
    with pytest.raises(DeckError, match=r"boundaries.surface.*choose grains with ids, positions or line"):
        load_deck(deck)
    with pytest.raises(DeckError, match="fixed_edges applies to lattice = 'hex2d' only"):
        load_deck(BED, overrides=["particles.0.lattice=sc",
                                  "particles.0.region={type='box', lo=[0,0,0], hi=[0.01,0.01,0.01]}",
                                  "particles.0.n_cols=2"])  # fmt: skip


@pytest.mark.parametrize(
    "override, message",
    [
        ("boundaries.surface.ids=[999999]", "boundaries.surface.ids: no grain has id 999999"),
        (
            "boundaries.surface.line.step=[1e-5, 0.0, 0.0]",
            "boundaries.surface.line (point 1): the nearest grain",
        ),
        ("boundaries.kick.positions=[[0.0, 0.0, 0.0]]", "boundaries.kick: a chosen grain is fixed"),
    ],
)
def test_bad_choices_stop_the_run_before_it_writes(tmp_path, capsys, override, message):
    out = tmp_path / "o"
    code = main([str(BED), "--output", str(out), "--quiet", *sum((["--set", s] for s in _small_bed()), []),
                 "--set", override])  # fmt: skip
    assert code == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


# ------------------------------------------------------------------------------------ the 2-D bed
@pytest.mark.parametrize("law", ["hertz_mindlin", "complementarity"])
def test_bed_edges_fixed_and_in_plane(tmp_path, law):
    """Both methods: the bottom row and side columns do not move, every grain stays in the xz plane and
    turns about y only, the pulse reaches the sensors."""
    extra = []
    if law == "complementarity":  # rigid grains: the kick spreads at once and is weak far away
        extra = ["contact.law=complementarity", "run.dt=2e-7", "boundaries.depth.threshold=1e-8"]
    out = tmp_path / law
    summary = _run(BED, out, *_small_bed(), *extra)
    with h5py.File(out / "particles.h5", "r") as f:
        keys = sorted(f["frames"])
        first, last = f["frames"][keys[0]], f["frames"][keys[-1]]
        x0, x1, v1 = first["x"][()], last["x"][()], last["v"][()]
        ids = last["id"][()]
    n = 15
    row, col = np.divmod(ids, n)
    edge = (row == 0) | (col == 0) | (col == n - 1)
    assert np.array_equal(x0[edge], x1[edge])
    assert np.all(x1[:, 1] == 0.0) and np.all(v1[:, 1] == 0.0)
    assert np.any(x1[~edge] != x0[~edge])
    arr = summary["results"]["depth"]["arrival_time"]
    assert all(t is not None for t in arr) and arr == sorted(arr)


@pytest.mark.integration
@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
def test_bed_bitwise_identical_on_1_and_3_ranks(tmp_path):
    """DEM-P through the CLI: the sensors' CSV and results and the last snapshot are the same bits."""
    got = {}
    for ranks in (1, 3):
        out = tmp_path / f"r{ranks}"
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, "-m", "pdem", str(BED), "--output", str(out),
               "--quiet", "--set", "output.parallel=gather"]  # fmt: skip
        for s in _small_bed(n=21, end=3.2e-5):
            cmd += ["--set", s]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-3000:]
        with h5py.File(out / "particles.h5", "r") as f:
            last = f["frames"][sorted(f["frames"])[-1]]
            snap = {k: last[k][()] for k in ("id", "x", "v", "f")}
        got[ranks] = (
            json.loads((out / "summary.json").read_text())["results"],
            (out / "surface.impact.csv").read_bytes(),
            (out / "depth.impact.csv").read_bytes(),
            snap,
        )
    (r1, s1, d1, p1), (r3, s3, d3, p3) = got[1], got[3]
    assert r1 == r3 and s1 == s3 and d1 == d3
    for k in p1:
        assert np.array_equal(p1[k], p3[k]), k
    assert all(t is not None for t in r1["depth"]["arrival_time"])
