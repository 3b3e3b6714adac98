"""``pdem study``: spec validation, the run grid, resumability (a killed study keeps its finished
runs), errors against closed-form and finest-run references, the stability classes of failing runs,
charts and the Pareto front (against brute force)."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pdem.cli import main
from pdem.errors import InputError
from pdem.study import Study, load_spec, plan_runs
from pdem.study.charts import pareto_front

RHO, R, G = 2500.0, 1.0e-3, 9.81

# 2 × 2 × 2 spheres of r = 1 mm on a lattice, dropped a little onto the floor of a box; heavily damped
# so that they are at rest well before the end: the floor then carries their weight, 8 ρ (4/3)π r³ g.
PILE = """
title = "eight spheres settling"
[run]
gravity = [0.0, 0.0, -9.81]
[materials.glass]
density = 2500.0
youngs_modulus = 1.0e7
poisson_ratio = 0.3
restitution = 0.05
friction = 0.5
[[particles]]
source = "lattice"
material = "glass"
lattice = "sc"
spacing = 0.0022
radius = 0.001
region = { type = "box", lo = [0.0001, 0.0001, 0.0001], hi = [0.0044, 0.0044, 0.0044] }
[boundaries.box]
type = "box"
material = "glass"
lo = [0.0, 0.0, 0.0]
hi = [0.0055, 0.0055, 0.01]
[[stages]]
name = "settle"
[stages.end]
time = 0.06
[output]
directory = "out/pile"
formats = ["hdf5"]
every_time = 0.03
series_every_steps = 20
"""

WEIGHT = 8 * RHO * 4.0 / 3.0 * math.pi * R**3 * G


def _spec(tmp_path: Path, body: str, deck: str = PILE) -> Path:
    (tmp_path / "pile.toml").write_text(deck)
    spec = tmp_path / "study.toml"
    spec.write_text(f'deck = "pile.toml"\noutput = "{(tmp_path / "out").as_posix()}"\n' + body)
    return spec


STEP_STUDY = f"""
title = "pile: floor load against the step"
[quantities.floor_load]
column = "box.zlo.fz"
reduce = "mean"
window = 0.25
reference = {{ value = -{WEIGHT!r}, source = "closed form: the weight of the eight spheres" }}
tolerance = 0.01

[[series]]
name = "dem_p"
set = {{ "run.force_dt" = true }}
vary = {{ "run.dt_fraction" = [0.1, 0.3, 6.0] }}

[stability]
x = "run.dt_fraction"
"""


def test_spec_errors_name_the_key_and_the_remedy(tmp_path):
    bad = _spec(tmp_path, "[quantities.q]\npath = \"results.x\"\nreference = { value = 1.0 }\n"
                "[[series]]\nname = \"a\"\nvary = { \"run.dt\" = [] }\nbogus = 1\n")
    with pytest.raises(InputError) as info:
        load_spec(bad)
    text = str(info.value)
    assert "quantities.q.reference" in text and "source" in text  # a value without its source
    assert "vary" in text and "empty" in text
    assert "bogus" in text
    # a reference to a series that does not exist, and a missing deck
    spec = _spec(tmp_path, "[quantities.q]\npath = \"results.x\"\nreference = { series = \"nope\" }\n"
                 "[[series]]\nname = \"a\"\n")
    with pytest.raises(InputError, match="'nope'"):
        load_spec(spec)
    spec.write_text(spec.read_text().replace('deck = "pile.toml"', 'deck = "missing.toml"').replace(
        '"nope"', '"a"'))
    with pytest.raises(InputError, match="missing.toml"):
        load_spec(spec)


def test_cli_refuses_a_bad_spec_with_exit_2(tmp_path, capsys):
    spec = _spec(tmp_path, "jobs = 0\n[quantities.q]\npath = \"results.x\"\n"
                 "reference = { finest = \"a\", by = \"run.dt\" }\n[[series]]\nname = \"a\"\n")
    assert main(["study", str(spec)]) == 2
    err = capsys.readouterr().err
    assert "jobs" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_grid_is_the_product_of_each_series_with_methods(tmp_path):
    spec = _spec(tmp_path, """
set = { "stages.settle.end.time" = 0.01 }
[quantities.q]
path = "steps"
reference = { finest = "p", by = "run.dt" }
[[series]]
name = "p"
vary = { "run.dt" = [1e-6, 2e-6, 4e-6], "run.seed" = [1, 2] }
[[series]]
name = "c"
set = { "contact.law" = "complementarity" }
vary = { "contact.max_iterations" = [10, 20] }
""")
    plans = plan_runs(load_spec(spec))
    assert len(plans) == 3 * 2 + 2
    assert [p.method for p in plans] == ["DEM-P"] * 6 + ["DEM-C"] * 2
    assert len({p.directory for p in plans}) == len(plans)
    first = plans[0]
    assert first.set_args() == ["stages.settle.end.time=0.01", "run.dt=1e-06", "run.seed=1"]
    assert plans[-1].knobs["contact.max_iterations"] == 20


@pytest.mark.integration
def test_study_errors_against_a_closed_form_and_failures_are_caught(tmp_path):
    study = Study.from_file(_spec(tmp_path, STEP_STUDY), jobs=2)
    study.run(progress=None)
    rows = {r["run.dt_fraction"]: r for r in study.table()}
    # stable steps: the floor carries the weight (closed form) within the tolerance
    for frac in (0.1, 0.3):
        row = rows[frac]
        assert row["status"] == "ok", row
        assert row["floor_load"] == pytest.approx(-WEIGHT, rel=0.01)
        assert row["floor_load_error"] == pytest.approx(abs(row["floor_load"] + WEIGHT) / WEIGHT, rel=1e-12)
        assert row["dt_ratio"] == pytest.approx(frac, rel=1e-9)  # dt / dt_critical from summary.json
    # six times the stability estimate: caught (exit 3), the message states dt and the estimate,
    # nothing non-finite left on disk
    bad = rows[6.0]
    assert bad["status"] == "failed" and bad["exit_code"] == 3
    assert bad["stability"] == "failed" and bad["nonfinite"] == 0
    assert "stability estimate" in bad["message"] and "reduce dt" in bad["message"]
    paths = study.report()
    for kind in ("table", "reading", "error_vs_time_floor_load", "stability", "stability_table"):
        assert paths[kind].is_file() and paths[kind].stat().st_size > 0, kind
    assert (paths["error_vs_time_floor_load"].with_suffix(".svg")).is_file()
    with open(paths["table"]) as fh:
        table = list(csv.DictReader(fh))
    assert [t["status"] for t in table] == ["ok", "ok", "failed"]
    reading = paths["reading"].read_text()
    assert "DEM-P: fastest run within 0.01" in reading and "dt_fraction=6.0" in reading


@pytest.mark.integration
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_killed_study_keeps_finished_runs_and_leaves_no_run_behind(tmp_path, sig):
    spec = _spec(tmp_path, "jobs = 1\n" + STEP_STUDY.replace("[0.1, 0.3, 6.0]", "[0.3, 0.06, 6.0]"))
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "pdem", "study", str(spec)], stderr=subprocess.PIPE,
                            text=True, env=env, start_new_session=True)
    first = tmp_path / "out" / "dem_p" / "dt_fraction=0.3" / "study_run.json"
    second = tmp_path / "out" / "dem_p" / "dt_fraction=0.06"  # ~13,500 steps: still running when killed
    deadline = time.monotonic() + 300
    while not (first.is_file() and second.is_dir()):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "the first run did not finish"
        time.sleep(0.05)
    time.sleep(0.5)
    assert _pdem_runs_for(tmp_path), "the second run should be under way"
    os.kill(proc.pid, sig)  # SIGKILL: the study dies without any chance to clean up
    proc.wait()
    record = first.read_text()
    mtime = first.stat().st_mtime_ns
    # the run under way is stopped with the study (not left running as an orphan)
    deadline = time.monotonic() + 3
    while _pdem_runs_for(tmp_path):
        assert time.monotonic() < deadline, "a run outlived the killed study"
        time.sleep(0.2)
    assert not (second / "study_run.json").exists()
    # the rerun keeps the finished run and completes the rest
    out = subprocess.run([sys.executable, "-m", "pdem", "study", str(spec)], capture_output=True, text=True,
                         env=env, timeout=600)
    assert out.returncode == 0, out.stderr
    assert "1 kept from before, 2 to run" in out.stderr
    assert first.read_text() == record and first.stat().st_mtime_ns == mtime
    assert json.loads((second / "study_run.json").read_text())["status"] == "ok"
    # and a third invocation runs nothing
    again = subprocess.run([sys.executable, "-m", "pdem", "study", str(spec)], capture_output=True, text=True,
                           env=env, timeout=600)
    assert "3 kept from before, 0 to run" in again.stderr


def _pdem_runs_for(tmp_path: Path) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"--output" in cmd and any(str(tmp_path).encode() in c for c in cmd) and b"study" not in cmd:
            found.append(int(entry.name))
    return found


@pytest.mark.integration
def test_finest_reference_and_changed_spec_reruns(tmp_path):
    spec = _spec(tmp_path, """
[quantities.floor_load]
column = "box.zlo.fz"
reduce = "last"
reference = { finest = "dem_p", by = "run.dt_fraction" }
[[series]]
name = "dem_p"
set = { "stages.settle.end.time" = 0.02 }
vary = { "run.dt_fraction" = [0.1, 0.2] }
""")
    study = Study.from_file(spec)
    study.run(progress=None)
    rows = study.table()
    ref = rows[0]["floor_load"]
    assert rows[0]["floor_load_error"] == 0.0
    assert rows[1]["floor_load_error"] == pytest.approx(abs(rows[1]["floor_load"] - ref) / abs(ref))
    # the same run directory with other overrides is not taken for a finished run
    spec.write_text(spec.read_text().replace("end.time\" = 0.02", "end.time\" = 0.03"))
    study = Study.from_file(spec)
    results = study.run(progress=None)
    assert all(r.record.sets[0] == "stages.settle.end.time=0.03" for r in results)


@pytest.mark.integration
def test_series_option_runs_only_those_series(tmp_path, capsys):
    """``--series``: the named series run, the others are left unrun (and a later full run does
    them without redoing the first); an unknown name is refused with exit 2, naming the spec's."""
    spec = _spec(tmp_path, """
[quantities.floor_load]
column = "box.zlo.fz"
reduce = "last"
reference = { finest = "a", by = "run.dt_fraction" }
[[series]]
name = "a"
set = { "stages.settle.end.time" = 0.01 }
vary = { "run.dt_fraction" = [0.2] }
[[series]]
name = "b"
set = { "stages.settle.end.time" = 0.01 }
vary = { "run.dt_fraction" = [0.1] }
""")
    assert main(["study", str(spec), "--series", "nope"]) == 2
    assert "'nope' is not a series of the spec; its series are: a, b" in capsys.readouterr().err
    assert main(["study", str(spec), "--series", "b"]) == 0
    study = Study.from_file(spec)
    by = {r.plan.series: r for r in study.results()}
    assert by["b"].record is not None and by["b"].record.status == "ok"
    assert by["a"].record is None
    first = (by["b"].plan.directory / "study_run.json").stat().st_mtime_ns
    results = study.run(progress=None)
    assert all(r.record.status == "ok" for r in results)
    assert (by["b"].plan.directory / "study_run.json").stat().st_mtime_ns == first  # kept, not redone


@pytest.mark.parametrize("seed", range(5))
def test_pareto_front_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    pts = [(float(t), float(e)) for t, e in rng.uniform(0.1, 10, (30, 2))]
    front = set(pareto_front(pts))
    brute = {p for p in pts if not any(q[0] <= p[0] and q[1] <= p[1] and q != p for q in pts)}
    assert front == brute


@pytest.mark.integration
def test_mpi_runs_give_the_serial_values(tmp_path):
    """ranks = 2: each run under mpiexec; pdem's results do not depend on the rank count, so the
    table holds the serial run's value bit for bit."""
    body = """
[quantities.floor_load]
column = "box.zlo.fz"
reference = { series = "p" }
[[series]]
name = "p"
set = { "stages.settle.end.time" = 0.01 }
vary = { "run.seed" = [1] }
"""
    values = {}
    for ranks in (1, 2):
        (tmp_path / str(ranks)).mkdir()
        spec = _spec(tmp_path / str(ranks), body)
        study = Study.from_file(spec, ranks=ranks)
        study.run(progress=None)
        row = study.table()[0]
        assert row["status"] == "ok", row
        values[ranks] = row["floor_load"]
        cmd = study.results()[0].record.command
        assert ("-n" in cmd and cmd[cmd.index("-n") + 1] == "2") == (ranks == 2)
    assert values[1] == values[2]


@pytest.mark.integration
def test_live_bound_columns_and_a_run_it_stops(tmp_path):
    """study.csv carries the live step bound (its smallest value and dt over it); a run the bound
    stops is 'failed' (exit 3), of the stability class 'stopped', and still placed on the step axis
    from its message."""
    deck = (Path(__file__).parent / "data" / "triaxial_small.toml").read_text()
    spec = _spec(tmp_path, """
[quantities.eps_v]
path = "results.cell.eps_v_final"
reference = { finest = "dem_p", by = "run.dt" }
tolerance = 0.05

[[series]]
name = "dem_p"
vary = { "run.dt" = [2e-6, 1e-5] }
""", deck=deck)
    study = Study.from_file(spec, jobs=2)
    study.run(progress=None)
    rows = {r["run.dt"]: r for r in study.table()}
    ok, stopped = rows[2e-6], rows[1e-5]
    assert ok["status"] == "ok" and ok["bound_dt"] > 2e-6 and 0 < ok["dt_over_bound"] < 1
    assert stopped["status"] == "failed" and stopped["exit_code"] == 3
    assert "run.stiffness_limit" in stopped["message"]
    # told apart from a blow-up in the stability class (and on the map)
    assert stopped["stability"] == "stopped"
    assert Study.stability_class("failed", 0, None, 0.01, "the run became unstable at step 3") == "failed"
    assert Study.stability_class("failed", 2, None, 0.01, stopped["message"]) == "uncaught"
    assert stopped["dt_ratio"] == pytest.approx(1e-5 / ok["dt"] * ok["dt_ratio"], rel=1e-3)


SHIPPED = sorted((Path(__file__).resolve().parents[1] / "studies").glob("*.toml"))


@pytest.mark.parametrize("spec", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_specs_plan_valid_decks(spec):
    """Every shipped study spec loads, and every run it plans is a valid deck (its deck with the
    run's overrides passes the deck validation): a misspelt key fails here, not hours into a study."""
    from pdem.deck.load import load_deck

    study = Study.from_file(spec)
    assert study.plans
    for plan in study.plans:
        load_deck(study.spec.deck, plan.set_args())
