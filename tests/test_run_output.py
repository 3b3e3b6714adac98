"""The output directory's bookkeeping on its own (pdem.io.run_output.RunOutput): the start checks of
an existing directory, nothing created before it opens, series rows written once per step, and the
frame bounds that only grow. The runs themselves are in test_output_safety.py and test_resume.py."""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
from decks import TINY_LATTICE

from pdem.deck import validate_deck
from pdem.errors import InputError
from pdem.io.run_output import RunOutput
from pdem.parallel.comm import SerialComm


def _output(out, **kwargs) -> RunOutput:
    resolved = validate_deck(tomllib.loads(TINY_LATTICE))
    return RunOutput(
        out,
        comm=SerialComm(),
        resolved=resolved,
        deck_text=resolved.resolved_toml(),
        stage_names=["drop"],
        **kwargs,
    )


def test_refuses_a_directory_that_is_not_empty(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="exists and is not empty; pass --overwrite"):
        _output(tmp_path)
    with pytest.raises(InputError, match="was not made by pdem"):
        _output(tmp_path, overwrite=True)
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]
    _output(tmp_path, dry=True)  # pdem check: the directory is not looked at


def test_nothing_is_created_before_it_opens(tmp_path):
    out = tmp_path / "a" / "b"
    output = _output(out)
    assert not (tmp_path / "a").exists()
    output.undo()  # nothing opened: nothing to remove, no error
    assert list(tmp_path.iterdir()) == []


def test_series_rows_once_per_step(tmp_path):
    output = _output(tmp_path / "out")
    assert output.series_due("drop", 10) and not output.series_due("drop", 10)
    assert output.series_due("drop", 20) and output.series_due("rest", 20)


def test_frame_bounds_only_grow():
    output = _output_dry()
    lo, hi = output.grow_bounds(np.zeros(3), np.ones(3))
    lo, hi = output.grow_bounds(np.full(3, 0.5), np.full(3, 2.0))
    assert lo.tolist() == [0.0] * 3 and hi.tolist() == [2.0] * 3
    assert [b.tolist() for b in output.bounds] == [[0.0] * 3, [2.0] * 3]
    fresh = _output_dry()
    lo, hi = fresh.grow_bounds(np.full(3, np.inf), np.full(3, -np.inf))  # nothing to draw yet
    assert lo.tolist() == [0.0] * 3 and hi.tolist() == [1.0] * 3


def _output_dry() -> RunOutput:
    from pathlib import Path

    return _output(Path("unused"), dry=True)
