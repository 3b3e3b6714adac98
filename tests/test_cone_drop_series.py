"""tools/cone_drop_series.py: the power-law fit recovers known parameters, and --compare puts two
finished series side by side (depth ratios per tip and height, a missing run as NaN, bad input as
exit code 2)."""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

import cone_drop_series  # noqa: E402


def test_power_law_fit_gives_the_parameters_back():
    total = np.array([0.025, 0.057, 0.108, 0.31])
    a, n = cone_drop_series.fit_power_law(total, 0.014 * total**0.24)
    assert n == pytest.approx(0.24, abs=1e-12) and a == pytest.approx(0.014, rel=1e-10)
    assert all(math.isnan(v) for v in cone_drop_series.fit_power_law(total[:1], total[:1]))


def _series(path: Path, depths: dict[tuple[str, float], float]) -> Path:
    runs = [
        {"tip": tip, "H_m": h, "depth_m": d, "total_drop_m": h + d, "wall_time_s": 10.0 * (k + 1)}
        for k, ((tip, h), d) in enumerate(depths.items())
    ]
    path.mkdir(parents=True)
    (path / "drop_series.json").write_text(json.dumps({"fits": {}, "runs": runs}))
    return path


def test_compare_two_series(tmp_path, capsys):
    p = _series(tmp_path / "p", {("sphere", 0.02): 0.005, ("sphere", 0.1): 0.008, ("cone60", 0.1): 0.012})
    c = _series(tmp_path / "c", {("sphere", 0.02): 0.0045, ("sphere", 0.1): 0.0088})
    out = tmp_path / "cmp"
    assert cone_drop_series.main(["--compare", str(p), str(c), "--labels", "P", "C", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "drop_compare.csv").open()))
    assert [(r["tip"], float(r["H_m"])) for r in rows] == [("sphere", 0.02), ("sphere", 0.1), ("cone60", 0.1)]
    assert float(rows[0]["C / P"]) == pytest.approx(0.9, rel=1e-12)
    assert float(rows[1]["C / P"]) == pytest.approx(1.1, rel=1e-12)
    assert math.isnan(float(rows[2]["C / P"]))  # no DEM-C run for that one
    assert (out / "drop_compare.png").stat().st_size > 0
    assert "C/P 0.900" in capsys.readouterr().out


def test_compare_refuses_missing_series_and_mismatched_labels(tmp_path, capsys):
    p = _series(tmp_path / "p", {("sphere", 0.02): 0.005})
    assert cone_drop_series.main(["--compare", str(p), str(tmp_path / "none"), "--out", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err
    assert cone_drop_series.main(["--compare", str(p), "--labels", "A", "B", "--out", str(tmp_path)]) == 2
    assert "--labels" in capsys.readouterr().err


def test_the_bed_size_study_writes_decks_pdem_accepts(tmp_path):
    """tools/drop_bed_size.py: the bed deck (random fill, settle to a kinetic energy per bead) and
    the drop deck (inputs/cone_drop.toml reading the bed's packing, its box as wide as the bed) are
    valid decks; the drop deck's box and settle threshold follow the bed."""
    import tomllib

    import drop_bed_size as tool

    from pdem.cli import main as pdem
    from pdem.sources import write_spheres_text

    half = 0.04
    bed = tmp_path / "bed.txt"
    x = np.array([[0.0, 0.0, 0.0015], [0.004, 0.0, 0.0015]])
    write_spheres_text(bed, x, np.full(2, tool.R_BEAD))
    deck = tmp_path / "drop.toml"
    deck.write_text(tool.drop_deck(bed, 2 * half, 2))
    parsed = tomllib.loads(deck.read_text())
    assert parsed["particles"][0] == {"source": "file", "material": "bead", "path": "bed.txt"}
    assert parsed["boundaries"]["box"]["lo"][:2] == [-half, -half]
    assert parsed["boundaries"]["box"]["hi"][:2] == [half, half]
    assert parsed["stages"][0]["end"]["kinetic_energy_below"] == 2 * tool.REST_ENERGY_PER_BEAD
    assert pdem(["check", str(deck)]) == 0
    bed_deck = tmp_path / "bed.toml"
    bed_deck.write_text(tool._bed_deck(0.1, 0.06, 1, 1000))
    assert pdem(["check", str(bed_deck), "--deck-only"]) == 0
    parsed = tomllib.loads(bed_deck.read_text())
    assert parsed["particles"][0]["region"]["lo"] == [-0.05, -0.05, 0.0]
    assert parsed["particles"][0]["region"]["hi"][2] == pytest.approx(0.144)
    lift = tmp_path / "lift.toml"  # a second lift: the first lift's grains, then a fill above them
    lift.write_text(tool._with_file_source(tool._bed_deck(0.1, 0.06, 1001, 2000, bottom=0.065), str(bed)))
    assert pdem(["check", str(lift), "--deck-only"]) == 0
    parsed = tomllib.loads(lift.read_text())
    assert [p["source"] for p in parsed["particles"]] == ["file", "random_fill"]
    assert parsed["particles"][1]["region"]["lo"][2] == 0.065
    assert parsed["particles"][1]["region"]["hi"][2] == pytest.approx(0.065 + 0.144)
    assert parsed["boundaries"]["box"]["hi"][2] == pytest.approx(0.065 + 0.18)
    assert parsed["run"]["seed"] == 1001


def test_a_bed_in_lifts_fills_each_lift_above_the_last(tmp_path):
    """tools/drop_bed_size.py --lifts: a bed of two lifts is the first lift's settled grains with a
    second, equal fill above them, settled again; each lift is kept once made."""
    import drop_bed_size as tool

    from pdem.sources import read_spheres

    bed = tool.make_bed(tmp_path / "bed", 0.02, 0.004, 1, 3, lifts=2)
    first = read_spheres(tmp_path / "bed" / "lift1" / "bed.txt")
    both = read_spheres(bed)
    n1 = len(first["radii"])
    assert n1 > 10
    assert len(both["radii"]) == 2 * n1  # the same fill volume twice
    top1 = float(np.max(first["positions"][:, 2] + first["radii"]))
    deck = (tmp_path / "bed" / "lift2" / "bed.toml").read_text()
    assert f"{top1!r}]" in deck and "seed = 1003" in deck
    assert float(np.max(both["positions"][:, 2])) > top1  # the second lift lies on the first
    assert np.all(np.abs(both["positions"][:, :2]) <= 0.01 - tool.R_BEAD + 1e-6)
    mtime = bed.stat().st_mtime_ns
    assert tool.make_bed(tmp_path / "bed", 0.02, 0.004, 1, 3, lifts=2) == bed
    assert bed.stat().st_mtime_ns == mtime


def test_lifts_and_a_cut_are_refused_together(tmp_path, capsys):
    import drop_bed_size as tool

    with pytest.raises(SystemExit) as exc:
        tool.main(["--lifts", "--carve", "2", "--out", str(tmp_path / "study")])
    assert exc.value.code == 2
    assert "--lifts" in capsys.readouterr().err
    assert not (tmp_path / "study").exists()


def test_a_cut_bed_is_settled_again_before_it_is_dropped_on(tmp_path):
    """tools/drop_bed_size.py --carve: the beads wholly inside the central square and the top layers
    of a packing are cut out, lowered onto the floor and settled in their own box until at rest
    (the bed deck's kinetic-energy criterion), and that settled packing is the cut bed."""
    import drop_bed_size as tool

    from pdem.sources import read_spheres, write_spheres_text

    r = tool.R_BEAD
    idx = np.stack(np.meshgrid(np.arange(6), np.arange(6), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    x = (idx - np.array([2.5, 2.5, 0.0])) * 2.0 * r + np.array([0.0, 0.0, r + 0.002])  # 2 mm above z = 0
    source = tmp_path / "big.txt"
    write_spheres_text(source, x, np.full(len(x), r))
    bed = tool.carve_bed(tmp_path / "cut", source, 0.012, 0.006, 1)
    cut = read_spheres(tmp_path / "cut" / "cut.txt")
    settled = read_spheres(bed)
    assert len(cut["radii"]) == len(settled["radii"]) == 4 * 4 * 2  # the inner columns, top two layers
    assert cut["positions"][:, 2].min() == pytest.approx(r)  # lowered onto the floor
    assert np.all(np.abs(settled["positions"][:, :2]) <= 0.006 - r + 1e-9)
    assert settled["positions"][:, 2].min() == pytest.approx(r, abs=1e-5)  # resting on it
    summary = json.loads((tmp_path / "cut" / "run" / "summary.json").read_text())
    assert summary["completed"]
    assert tool.carve_bed(tmp_path / "cut", source, 0.012, 0.006, 1) == bed  # kept, not made again


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--cut", "0.1", "0.2"], "--carve"),
        (["--carve", "2", "--cut", "0.1", "-0.2"], "positive"),
        (["--carve", "2", "--cut", "0.1", "nan"], "positive"),
        (["--carve", "2", "--cut", "0.25", "0.06"], "wider"),
    ],
)
def test_a_cut_of_another_size_is_checked_before_anything_runs(tmp_path, capsys, argv, message):
    """tools/drop_bed_size.py --cut W D: without --carve, with a length that is not positive, or
    wider than the bed it is cut from, the study stops at once with a message naming the option."""
    import drop_bed_size as tool

    with pytest.raises(SystemExit) as exc:
        tool.main([*argv, "--out", str(tmp_path / "study")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--cut" in err and message in err
    assert not (tmp_path / "study").exists()
