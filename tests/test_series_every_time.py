"""``output.series_every_time``: time-series rows at the same times whatever the step (DEM-P's and
DEM-C's steps differ by 10-100x), the same after a resume, and a deck error when both cadences are
given."""

from __future__ import annotations

import csv
import textwrap
from pathlib import Path

import pytest

from pdem.api import DeckError
from pdem.cli import main
from pdem.deck import load_deck

EVERY = 0.0025


def _deck(tmp_path: Path, dt: float, output: str = f"series_every_time = {EVERY}") -> Path:
    deck = tmp_path / f"fall_{dt:g}.toml"
    deck.write_text(textwrap.dedent(f"""
        [run]
        gravity = [0.0, 0.0, -9.81]
        dt = {dt}
        [materials.glass]
        density = 2500.0
        youngs_modulus = 1.0e7
        poisson_ratio = 0.3
        restitution = 0.3
        friction = 0.3
        [[particles]]
        source = "random_fill"
        material = "glass"
        region = {{ type = "box", lo = [0.0, 0.0, 0.0], hi = [0.01, 0.01, 0.01] }}
        sizes = {{ type = "single", radius = 1e-3 }}
        n = 20
        [boundaries.box]
        type = "box"
        material = "glass"
        lo = [0.0, 0.0, 0.0]
        hi = [0.01, 0.01, 0.05]
        open_faces = ["zhi"]
        [[stages]]
        name = "fall"
        [stages.end]
        time = 0.05
        [[stages]]
        name = "rest"
        [stages.end]
        time = 0.0301
        [output]
        {output}
    """))
    return deck


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


@pytest.mark.parametrize("dt", [8e-5, 3e-5, 1.1e-5])
def test_rows_fall_on_the_same_times_at_any_step(tmp_path, dt):
    out = tmp_path / "out"
    assert main([str(_deck(tmp_path, dt)), "--output", str(out), "--quiet"]) == 0
    for name, t0, length in (("fall", 0.0, 0.05), ("rest", None, 0.0301)):
        rows = _rows(out / f"series_{name}.csv")
        times = [float(r["time"]) for r in rows]
        start = times[0] if t0 is None else t0
        # the stage's first row, one at the first step at or after each multiple of EVERY, the last
        expected = 1 + int(length / EVERY + 1e-9) + (0 if (length / EVERY) % 1 < 1e-9 else 1)
        assert len(rows) == expected, (name, len(rows), expected)
        for k, t in enumerate(times[1:-1], start=1):
            assert k * EVERY - 1e-3 * dt <= t - start < k * EVERY + dt, (name, k, t)


def test_resumed_run_writes_the_same_rows(tmp_path):
    deck = _deck(tmp_path, 3e-5)
    assert main([str(deck), "--output", str(tmp_path / "full"), "--quiet"]) == 0
    part = tmp_path / "part"
    assert main([str(deck), "--output", str(part), "--quiet", "--steps", "1000"]) == 0  # mid-fall
    assert main(["resume", str(part / "checkpoints" / "latest.h5"), "--quiet"]) == 0
    for name in ("series_fall.csv", "series_rest.csv"):
        assert (part / name).read_text() == (tmp_path / "full" / name).read_text(), name


def test_both_cadences_in_one_table_is_a_deck_error(tmp_path):
    deck = _deck(tmp_path, 3e-5, f"series_every_time = {EVERY}\nseries_every_steps = 10")
    with pytest.raises(DeckError, match="series_every_time"):
        load_deck(deck)
    # a stage's override of one replaces the other
    loaded = load_deck(_deck(tmp_path, 3e-5), overrides=["stages.1.output.series_every_steps=7"])
    assert loaded.output_for("rest").series_every_time is None
    assert loaded.output_for("rest").series_every_steps == 7
    assert loaded.output_for("fall").series_every_time == EVERY


def test_a_checkpoint_whose_deck_no_longer_validates_names_the_key(tmp_path, capsys):
    """The checkpoint's own deck is validated again on resume; its problems keep their key paths
    (they were once printed one character at a time: 'o.u.t.p.u.t...')."""
    import h5py

    part = tmp_path / "part"
    assert main([str(_deck(tmp_path, 3e-5)), "--output", str(part), "--quiet", "--steps", "10"]) == 0
    ckpt = part / "checkpoints" / "latest.h5"
    with h5py.File(ckpt, "r+") as fh:
        deck = str(fh.attrs["deck"])
        assert f"series_every_time = {EVERY}" in deck
        fh.attrs["deck"] = deck.replace(f"series_every_time = {EVERY}", "series_every_time = -1.0")
        # an unchecked (format-1) file: a format-2 checkpoint's checksums refuse any edit of its deck
        del fh.attrs["pdem_checksums"]
        fh.attrs["pdem_checkpoint_format"] = 1
    capsys.readouterr()
    assert main(["resume", str(ckpt), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "output.series_every_time:" in err and "no longer validates" in err
