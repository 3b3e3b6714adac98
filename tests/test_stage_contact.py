"""Solver settings that change between stages (``[stages.contact]``): e.g. DEM-C's iteration cap,
larger where grains land hard (a fill) than in a flow (a discharge). Only the keys a resume may
change are accepted; a stage without the table runs with ``[contact]``; a resume inside a stage may
change them."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from pdem.cli import main
from pdem.deck import load_deck
from pdem.errors import DeckError

R = 0.005

DECK = f"""
[run]
seed = 1
gravity = [0.0, 0.0, -9.81]
dt = 1.0e-3
[contact]
law = "complementarity"
[contact.complementarity]
solver = "jacobi"
tolerance = 1.0e-14         # never reached: every step runs to its cap
max_iterations = 40
[materials.bead]
density = 2500.0
youngs_modulus = 1.0e7
poisson_ratio = 0.3
restitution = 0.0
friction = 0.5
[[particles]]
source = "lattice"
lattice = "hex2d"
material = "bead"
radius = {R}
n_cols = 4
n_rows = 3
origin = [0.0, 0.0, {R}]
[boundaries.floor]
type = "plane"
material = "bead"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
[[stages]]
name = "a"
[stages.end]
steps = 20
[[stages]]
name = "b"
[stages.contact.complementarity]
max_iterations = 3
[stages.end]
steps = 20
[[stages]]
name = "c"
[stages.end]
steps = 20
[output]
formats = []
series_every_steps = 10
"""


def _iterations(out: Path, stage: str) -> list[int]:
    with open(out / f"solver_{stage}.csv") as fh:
        return [int(row["iterations"]) for row in csv.DictReader(fh)]


def _deck(tmp_path: Path, text: str = DECK) -> Path:
    path = tmp_path / "pile.toml"
    path.write_text(text)
    return path


def test_a_stage_caps_its_own_iterations_and_the_next_gets_the_deck_back(tmp_path, capsys):
    out = tmp_path / "out"
    assert main([str(_deck(tmp_path)), "--output", str(out)]) == 0
    a, b, c = (_iterations(out, s) for s in "abc")
    assert len(a) == len(b) == len(c) == 20
    assert max(b) == 3 and min(b) == 3
    assert max(a[1:]) == 40 and max(c) == 40  # (a's first step has no contact to solve yet)
    assert "their stage's max_iterations" in capsys.readouterr().out


def test_a_dem_p_deck_ignores_another_laws_stage_table(tmp_path):
    r = load_deck(_deck(tmp_path), ['contact.law="hertz_mindlin"'])
    assert r.deck.stages[1].contact == {"complementarity": {"max_iterations": 3}}


@pytest.mark.parametrize(
    ("override", "where", "words"),
    [
        ("stages.b.contact.complementarity.max_travel=0.5", "stages.1.contact.complementarity.max_travel",
         "a stage can change: apgd_start, check_every"),
        ("stages.b.contact.complementarity.max_iterations=0",
         "stages.1.contact.complementarity.max_iterations", "must be > 0"),
        ('stages.b.contact.solver="sor"', "stages.1.contact.solver", "must be one of"),
        ("stages.b.contact.cone=1", "stages.1.contact.cone", "a stage can change"),
        ("stages.b.contact.complementarity.tolerance=inf", "stages.1.contact.complementarity.tolerance",
         "must be a finite number"),
    ],
)  # fmt: skip
def test_bad_stage_settings_name_the_key(tmp_path, override, where, words):
    with pytest.raises(DeckError) as err:
        load_deck(_deck(tmp_path), [override])
    msg = str(err.value)
    assert where in msg and words in msg, msg


def test_a_law_without_stage_settings_says_so(tmp_path):
    with pytest.raises(DeckError) as err:
        load_deck(_deck(tmp_path), ['contact.law="hertz_mindlin"', "stages.b.contact.tolerance=1e-3"])
    assert "stages.1.contact.tolerance" in str(err.value)
    assert "no settings a stage can change" in str(err.value)


def test_a_resume_inside_a_stage_may_change_its_settings(tmp_path):
    deck = _deck(tmp_path, DECK.replace("[output]", "[output]\ncheckpoint_every_steps = 10"))
    out = tmp_path / "out"
    assert main([str(deck), "--output", str(out), "--quiet", "--steps", "30"]) == 0
    assert main(["resume", str(out / "checkpoints" / "latest.h5"), "--quiet",
                 "--set", "stages.b.contact.complementarity.max_iterations=5"]) == 0  # fmt: skip
    b = _iterations(out, "b")
    assert b[:10] == [3] * 10 and b[10:] == [5] * 10
    assert max(_iterations(out, "c")) == 40


def test_a_resume_may_name_the_laws_keys_in_their_table(tmp_path):
    """The checkpoint's resolved deck holds DEM-C's keys in [contact] itself; a resume may still name
    them in the law's table, as a deck does (``contact.complementarity.max_iterations``)."""
    deck = _deck(tmp_path, DECK.replace("[output]", "[output]\ncheckpoint_every_steps = 10"))
    out = tmp_path / "out"
    assert main([str(deck), "--output", str(out), "--quiet", "--steps", "30"]) == 0
    assert main(["resume", str(out / "checkpoints" / "latest.h5"), "--quiet",
                 "--set", "contact.complementarity.max_iterations=7"]) == 0  # fmt: skip
    assert _iterations(out, "b") == [3] * 20  # the stage's own cap holds
    assert _iterations(out, "c") == [7] * 20


@pytest.mark.integration
def test_a_stage_may_switch_solver_and_stays_identical_on_2_ranks(tmp_path):
    import shutil
    import subprocess
    import sys

    import numpy as np

    from pdem.io.checkpoint import read_checkpoint

    deck = _deck(tmp_path, DECK.replace("max_iterations = 3\n", 'max_iterations = 7\nsolver = "apgd"\n'))
    runs = {}
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    for n in (1, 2) if mpiexec else (1,):
        out = tmp_path / f"out{n}"
        cmd = [sys.executable, "-m", "pdem", str(deck), "--output", str(out), "--quiet"]
        proc = subprocess.run([mpiexec, "-n", str(n), *cmd] if n > 1 else cmd, capture_output=True, text=True,
                              timeout=300)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert max(_iterations(out, "b")) == 7 and max(_iterations(out, "c")) == 40
        state, _ = read_checkpoint(out / "checkpoints" / "latest.h5")
        runs[n] = np.asarray(state["particles/x"]), np.asarray(state["particles/v"])
    if 2 in runs:
        assert all(np.array_equal(a, b) for a, b in zip(runs[1], runs[2], strict=True))
