"""Progress lines before the stepping: a pour (``source = "pluviate"``) and a large fill print where
they are, on the runner's progress stream, in runs and in ``pdem check``; short phases print nothing.
The interval is shortened here (``setup_every``, ``SETUP_PROGRESS_EVERY``) so that a pour of a few
dozen spheres shows lines."""

from __future__ import annotations

import io
import json
import re

import pytest

from pdem.cli import main
from pdem.deck import load_deck
from pdem.runner import Runner, _PhaseTicker

# 40 spheres poured into a small cylinder; settled as soon as the RMS speed is below 5 cm/s
POUR_DECK = """\
[run]
gravity = [0.0, 0.0, -9.81]
[materials.glass]
density = 2500.0
youngs_modulus = 5e7
poisson_ratio = 0.3
restitution = 0.3
friction = 0.3
[[particles]]
source = "pluviate"
material = "glass"
region = { type = "cylinder", base_center = [0.0, 0.0, 0.0], radius = 3.5e-3, height = 0.03 }
sizes = { type = "uniform", r_min = 0.45e-3, r_max = 0.55e-3 }
n = 40
rest_speed = 0.05
[boundaries.floor]
type = "plane"
material = "glass"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
[[stages]]
name = "rest"
[stages.end]
steps = 10
[output]
every_steps = 10
series_every_steps = 10
"""

LINE = re.compile(r"^\[setup\] particles\.0 \(source 'pluviate'\)(: .*)? \(\d+ s so far\)$")


def _deck(tmp_path, text=POUR_DECK):
    path = tmp_path / "deck.toml"
    path.write_text(text)
    return path


def test_pour_prints_progress_lines(tmp_path):
    stream = io.StringIO()
    runner = Runner(load_deck(_deck(tmp_path)), progress=stream, dry=True)
    runner.progress.setup_every = 0.01
    runner.check_scene()
    lines = stream.getvalue().splitlines()
    pour = [ln for ln in lines if ln.startswith("[setup] particles.0")]
    assert len(pour) > 1 and all(LINE.match(ln) for ln in pour[:-1]), lines
    assert re.fullmatch(r"\[setup\] particles\.0 \(source 'pluviate'\): done \(\d+ s\)", pour[-1]), lines
    # the source's own report: the settling (after the column is filled, which reports a fraction);
    # its first words name the spheres falling, later ones the time simulated, and on a loaded machine
    # the first report may come after the first settling report was due
    reports = (": settling, 40 spheres falling from a ", ": settling, t = ")
    assert any(r in ln for ln in pour for r in reports), lines


def test_settling_detail_bounds_the_wait_by_max_time():
    from pdem.sources.pluviation import _settling_detail

    text = _settling_detail(0.5, 0.02, 0.001, 2.0, 10.0)
    assert text == (
        "t = 0.5 s simulated, RMS speed 0.02 m/s (at rest below 0.001 m/s); gives up at max_time = 2 s, "
        "at most 30 s from now"
    )


def test_short_setup_prints_nothing(tmp_path):
    """At the default interval (seconds), a pour of 40 spheres ends before a line is due."""
    stream = io.StringIO()
    Runner(load_deck(_deck(tmp_path)), progress=stream, dry=True).check_scene()
    assert "[setup]" not in stream.getvalue()


def test_check_prints_progress_during_the_pour(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("pdem.runner.SETUP_PROGRESS_EVERY", 0.01)
    code = main(["check", str(_deck(tmp_path))])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "40 particles at the start" in out
    assert "[setup] particles.0 (source 'pluviate')" in err and "settling" in err, err


def test_run_prints_progress_and_times_the_setup(tmp_path, capsys, monkeypatch):
    """A run prints the pour's lines too (rank 0, on stderr), and summary.json's wall time includes
    the pour: wall_time_s = setup_time_s + stepping_time_s."""
    monkeypatch.setattr("pdem.runner.SETUP_PROGRESS_EVERY", 0.01)
    out = tmp_path / "out"
    code = main([str(_deck(tmp_path)), "--output", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "[setup] particles.0 (source 'pluviate')" in err, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["setup_time_s"] > 0 and summary["stepping_time_s"] > 0
    assert summary["wall_time_s"] == pytest.approx(summary["setup_time_s"] + summary["stepping_time_s"])
    assert summary["steps_per_second"] == pytest.approx(summary["steps_run"] / summary["stepping_time_s"])


def test_quiet_run_prints_no_progress(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("pdem.runner.SETUP_PROGRESS_EVERY", 0.01)
    code = main([str(_deck(tmp_path)), "--output", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 0 and "[setup]" not in err, err


def test_line_has_fraction_and_eta():
    """A source that reports a fraction gets a percentage and an ETA from the rate within the
    phase; the phase's start is where its fraction was first known."""
    ticker = _PhaseTicker(io.StringIO(), "particles.3 (source 'random_fill')", 5.0)
    start = ticker._start
    ticker.report("placing spheres", 0.0, "0 of 1000 placed")
    ticker._phase_start = ("placing spheres", start, 0.0)  # pinned times: a deterministic ETA
    ticker._state = ("placing spheres", 0.25, "250 of 1000 placed", start + 10.0)
    line = ticker.line(start + 10.0)
    assert line == (
        "[setup] particles.3 (source 'random_fill'): placing spheres, 250 of 1000 placed, 25% done, "
        "ETA 30 s (10 s so far)"
    )
    ticker.report("settling", None, "t = 0.1 s simulated")  # a new phase: no fraction, no ETA
    line = ticker.line(ticker._state[3])
    assert ": settling, t = 0.1 s simulated (" in line and "ETA" not in line and "%" not in line
