"""Thermo lines on stdout (`[output] thermo_every`, `thermo`): what a LAMMPS user looks at while a
run goes on; the values are those of the series, the columns are validated."""

from __future__ import annotations

import numpy as np
import pytest
from test_cli_hostile import TINY

from pdem.cli import main
from pdem.io.series import read_series

COLUMNS = 'output.thermo=["step", "time", "ke", "contacts", "floor.fz"]'
THERMO = ["--set", "output.thermo_every=5", "--set", COLUMNS]


def test_thermo_lines(tmp_path, capsys):
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY)
    out = tmp_path / "out"
    code = main([str(deck), "--output", str(out), "--quiet", *THERMO])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    lines = [ln.split() for ln in stdout.splitlines() if not ln.startswith("pdem:")]
    assert lines[0] == ["step", "time", "ke", "contacts", "floor.fz"]
    rows = lines[1:]
    assert [int(r[0]) for r in rows] == [5, 10, 15, 20]
    assert all(r[3].isdigit() for r in rows)  # contacts: a count
    series = read_series(out / "series_drop.csv")
    compared = 0
    for r in rows:
        at = np.flatnonzero(series["step"] == int(r[0]))
        if not len(at):
            continue
        k = int(at[0])
        assert float(r[1]) == pytest.approx(series["time"][k], rel=1e-5)
        assert float(r[2]) == pytest.approx(series["ke_trans"][k] + series["ke_rot"][k], rel=1e-5)
        assert float(r[4]) == pytest.approx(series["floor.fz"][k], rel=1e-5)
        compared += 1
    assert compared == 2  # steps 10 and 20


def test_default_columns(tmp_path, capsys):
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY)
    code = main([str(deck), "--output", str(tmp_path / "out"), "--quiet", "--set", "output.thermo_every=10"])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    assert stdout.splitlines()[0].split() == ["step", "time", "particles", "ke", "contacts"]
    assert stdout.splitlines()[1].split()[:3] == ["10", "2e-05", "64"]


@pytest.mark.parametrize(
    "sets, fragment",
    [
        (
            ['output.thermo=["step", "energy"]', "output.thermo_every=5"],
            "output.thermo.1: unknown thermo column",
        ),
        (['output.thermo=["lid.fz"]', "output.thermo_every=5"], "names boundary 'lid', which is not defined"),
        (['output.thermo=["step"]'], "give thermo_every too"),
        (["output.thermo_every=0"], "output.thermo_every: must be > 0"),
        (['output.thermo=["floor.torque"]', "output.thermo_every=5"], "'floor.torque' is not measured"),
    ],
)
def test_thermo_columns_are_checked(tmp_path, capsys, sets, fragment):
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY)
    args = [a for s in sets for a in ("--set", s)]
    for cmd in (
        ["check", str(deck), *args],
        [str(deck), "--output", str(tmp_path / "out"), "--quiet", *args],
    ):
        code = main(cmd)
        err = capsys.readouterr().err
        assert code == 2 and fragment in err, err
    assert not (tmp_path / "out").exists()


def test_progress_eta_for_a_stage_ending_on_a_quantity(tmp_path, capsys, monkeypatch):
    """A stage that ends on a measured quantity gets an ETA from the quantity's progress toward its
    target (here the floor's load growing toward -3e-5 N as the lattice settles)."""
    import pdem.runner as runner

    original = runner._Progress.update

    def often(self, *args, **kwargs):
        self.every = 0.0
        return original(self, *args, **kwargs)

    monkeypatch.setattr(runner._Progress, "update", often)
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY.replace("steps = 20\n", 'quantity = "floor.fz"\nbelow = -3e-5\ncheck_every = 2\n'))
    code = main([str(deck), "--output", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert any(", ETA " in ln for ln in err.splitlines() if ln.startswith("[drop]")), err
