"""Errors found when a run starts leave nothing behind, and `pdem check` finds them.

Each bad deck is refused by `pdem check` (exit 2, nothing written) and by a run (exit 2) without
creating the output directory, without touching an existing one (empty, or with an old run that
--overwrite would replace), and the corrected run then works without --overwrite. The same for
`pdem resume`: a refused resume leaves neither a new directory nor a changed one. Item 2 (huge
particle counts) is refused the same way, at validation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pdem.cli import main
from pdem.sources import write_spheres_text

# spheres from a packing file above a floor, 20 steps
FILE_DECK = """\
[run]
gravity = [0.0, 0.0, -9.81]
dt = 2e-6
[materials.glass]
youngs_modulus = 5e7
[[particles]]
source = "file"
material = "glass"
path = "pack.txt"
[boundaries.floor]
type = "plane"
material = "glass"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
[[stages]]
name = "drop"
[stages.end]
steps = 20
[[stages]]
name = "rest"
[stages.end]
steps = 20
[output]
every_steps = 10
series_every_steps = 10
"""


def good_packing(path: Path) -> None:
    x = np.array([[0.0, 0.0, 1e-3], [3e-3, 0.0, 1e-3], [0.0, 3e-3, 1e-3]])
    write_spheres_text(path, x, np.full(3, 0.5e-3))


def bad_packing(kind: str, path: Path) -> None:
    if kind == "overlapping_grains":  # two grains 0.2 mm apart, radius 0.5 mm
        write_spheres_text(path, np.array([[0.0, 0.0, 1e-3], [2e-4, 0.0, 1e-3]]), np.full(2, 0.5e-3))
    elif kind == "grain_outside_the_walls":  # below the floor
        write_spheres_text(path, np.array([[0.0, 0.0, 1e-3], [0.0, 3e-3, -2e-3]]), np.full(2, 0.5e-3))
    elif kind == "nan_in_file":
        path.write_text("x y z diameter\n0 0 0.001 0.001\n0.003 0 nan 0.001\n")
    elif kind == "negative_radius":
        path.write_text("x y z radius\n0 0 0.001 0.0005\n0.003 0 0.001 -0.0005\n")
    else:
        raise AssertionError(kind)


# (case, how to break the deck, fragments of the message)
CASES = [
    ("dt_above_the_limit", ["--set", "run.dt=1e-3"], ["run.dt", "stability estimate"]),
    ("stage_dt_above_the_limit", ["--set", "stages.rest.dt=1e-3"], ["stages.rest.dt", "stability estimate"]),
    ("overlapping_grains", [], ["overlap", "particles 0 and 1"]),
    ("grain_outside_the_walls", [], ["overlap", "wall 'floor'"]),
    ("nan_in_file", [], ["pack.txt", "non-finite"]),
    ("negative_radius", [], ["pack.txt", "-0.0005"]),
    ("huge_lattice", ["--set", "particles.1={source = 'lattice', lattice = 'sc', material = 'glass', "
                      "radius = 5e-6, region = {type = 'box', lo = [0, 0, 0.01], hi = [0.01, 0.01, 0.03]}}"],
     ["particles.1", "2e+09 particles", "TB of memory", "run.max_particles"]),
    ("huge_random_fill", ["--set", "particles.1={source = 'random_fill', material = 'glass', "
                          "n = 1000000000000, sizes = {type = 'single', radius = 1e-3}, "
                          "region = {type = 'box', lo = [-1e3, -1e3, 1], hi = [1e3, 1e3, 1e3]}}"],
     ["particles.1", "1e+12 particles", "PB of memory"]),
]  # fmt: skip


def tree(directory: Path) -> dict[str, bytes | None]:
    return {
        str(p.relative_to(directory)): (p.read_bytes() if p.is_file() else None) for p in directory.rglob("*")
    }


@pytest.mark.parametrize("case, extra, fragments", CASES, ids=[c[0] for c in CASES])
def test_refused_at_start_leaves_nothing(tmp_path, run_pdem, case, extra, fragments):
    deck = tmp_path / "deck.toml"
    deck.write_text(FILE_DECK)
    pack = tmp_path / "pack.txt"
    if case in ("overlapping_grains", "grain_outside_the_walls", "nan_in_file", "negative_radius"):
        bad_packing(case, pack)
    else:
        good_packing(pack)
    # pdem check finds it without writing anything
    before = tree(tmp_path)
    code, _, err = run_pdem(["check", deck, *extra])
    assert code == 2, err
    assert "Traceback" not in err and all(f in err for f in fragments), err
    assert tree(tmp_path) == before
    # a run: no output directory is created
    out = tmp_path / "out"
    code, _, err = run_pdem([deck, "--output", out, "--quiet", *extra])
    assert code == 2, err
    assert all(f in err for f in fragments), err
    assert tree(tmp_path) == before and not out.exists()
    # an existing empty directory stays empty; a nested new one is not created either
    out.mkdir()
    code, _, err = run_pdem([deck, "--output", out, "--quiet", *extra])
    assert code == 2 and list(out.iterdir()) == [], err
    code, _, err = run_pdem([deck, "--output", tmp_path / "a" / "b", "--quiet", *extra])
    assert code == 2 and not (tmp_path / "a").exists(), err
    # an old run's output that --overwrite would replace is kept when the new run is refused
    old = tmp_path / "old"
    old.mkdir()
    (old / "summary.json").write_text("{}")
    code, _, err = run_pdem([deck, "--output", old, "--quiet", "--overwrite", *extra])
    assert code == 2 and tree(old) == {"summary.json": b"{}"}, err
    # the corrected run works without --overwrite
    good_packing(pack)
    code, _, err = run_pdem([deck, "--output", out, "--quiet"])
    assert code == 0, err
    assert (out / "checkpoints" / "latest.h5").exists()


def test_refused_resume_leaves_nothing(tmp_path, run_pdem):
    deck = tmp_path / "deck.toml"
    deck.write_text(FILE_DECK)
    good_packing(tmp_path / "pack.txt")
    run_dir = tmp_path / "run"
    code, _, err = run_pdem([deck, "--output", run_dir, "--quiet", "--steps", "10"])
    assert code == 0, err
    ckpt = run_dir / "checkpoints" / "latest.h5"
    before = tree(tmp_path)
    for args in (
        ["--set", "run.dt=1e-3"],  # above the stability limit
        ["--set", "stages.rest.dt=1e-3"],  # a later stage's dt above it
        ["--set", "run.gravity=[0, 0, -1]"],  # the scene: not changeable
        ["--set", "output.directory='elsewhere'"],  # use --output
        ["--steps", "10"],  # not beyond the checkpoint
        ["--set", "stages.drop.name=fall"],  # a started stage keeps its name
    ):
        for output in ([], ["--output", tmp_path / "copy"]):
            code, _, err = run_pdem(["resume", ckpt, "--quiet", *args, *output])
            assert code == 2, (args, err)
            assert "Traceback" not in err
            assert tree(tmp_path) == before, args  # no '<out>-resumed-N', the run's own output intact
    assert not list(tmp_path.glob("run-resumed*"))
    # refused messages name the key and what may change
    code, _, err = run_pdem(["resume", ckpt, "--quiet", "--set", "run.gravity=[0, 0, -1]"])
    assert "run.gravity: cannot be changed on resume" in err and "stages.<name>.end" in err, err
    code, _, err = run_pdem(["resume", ckpt, "--quiet", "--steps", "10"])
    assert "--steps 10" in err and "step 10 already" in err, err
    # a checkpoint that is not one: exit 2
    code, _, err = run_pdem(["resume", tmp_path / "pack.txt", "--quiet"])
    assert code == 2 and "checkpoint" in err, err
    code, _, err = run_pdem(["resume", tmp_path / "missing.h5", "--quiet"])
    assert code == 2 and "does not exist" in err, err


def test_check_reports_the_scene(tmp_path, capsys):
    deck = tmp_path / "deck.toml"
    deck.write_text(FILE_DECK)
    good_packing(tmp_path / "pack.txt")
    code = main(["check", str(deck)])
    out = capsys.readouterr().out
    assert code == 0 and "3 particles at the start" in out and "stability estimate" in out, out


def test_later_stage_packing_file_checked_at_start(tmp_path, run_pdem):
    """A packing file inserted at a later stage is read when the run starts: a bad one stops the
    run before it writes anything (not when its stage comes)."""
    deck = tmp_path / "deck.toml"
    deck.write_text(
        FILE_DECK + '[[particles]]\nsource = "file"\nmaterial = "glass"\npath = "later.txt"\nstage = "rest"\n'
    )
    good_packing(tmp_path / "pack.txt")
    bad_packing("nan_in_file", tmp_path / "later.txt")
    for args in (["check", deck], [deck, "--output", tmp_path / "out", "--quiet"]):
        code, _, err = run_pdem(args)
        assert code == 2 and "particles.1.path (stage 'rest')" in err and "later.txt" in err, err
    assert not (tmp_path / "out").exists()


def test_failure_after_output_opened_removes_what_the_run_created(tmp_path, run_pdem, monkeypatch):
    """The safety net: a failure between creating the output and the first step (here the first
    snapshot) removes what this run created, and only that."""
    import pdem.runner
    from pdem.errors import OutputError

    def failing(self, stage):
        raise OutputError("injected: the disk is full")

    monkeypatch.setattr(pdem.runner.Runner, "_write_frame", failing)
    deck = tmp_path / "deck.toml"
    deck.write_text(FILE_DECK)
    good_packing(tmp_path / "pack.txt")
    before = tree(tmp_path)
    code, _, err = run_pdem([deck, "--output", tmp_path / "new" / "out", "--quiet"])
    assert code == 1 and "injected" in err, err
    assert tree(tmp_path) == before  # 'new' and 'new/out' were made by the run: both gone
    keep = tmp_path / "keep"
    keep.mkdir()
    (keep / "notes.txt").write_text("mine")
    code, _, err = run_pdem([deck, "--output", keep, "--quiet"])
    assert code == 2 and "not empty" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = run_pdem([deck, "--output", empty, "--quiet"])
    assert code == 1 and list(empty.iterdir()) == [], err


def test_python_api_runner(tmp_path):
    """Runner used directly: an output path that is a file is an InputError (not a traceback from
    mkdir), a deck given as a dict (no file) runs and checkpoints, and a resumed Runner refuses a
    max_steps at or before the checkpoint."""
    import tomllib

    from test_cli_hostile import TINY

    from pdem.deck import validate_deck
    from pdem.errors import InputError
    from pdem.io.checkpoint import read_checkpoint
    from pdem.runner import Runner

    resolved = validate_deck(tomllib.loads(TINY))
    target = tmp_path / "a_file"
    target.write_text("x")
    with pytest.raises(InputError, match="a regular file"):
        Runner(resolved, output=target, progress=None)
    out = tmp_path / "out"
    summary = Runner(resolved, output=out, progress=None, max_steps=10).run()
    assert summary["steps"] == 10
    state, meta = read_checkpoint(out / "checkpoints" / "latest.h5")
    assert meta["deck_path"] == ""
    with pytest.raises(InputError, match="step 10 already"):
        Runner(resolved, output=tmp_path / "more", progress=None, resume=(state, meta), max_steps=10)
    summary = Runner(resolved, output=out, progress=None, resume=(state, meta), append=True).run()
    assert summary["steps"] == 20 and summary["completed"]


def test_stage_too_long_at_the_automatic_dt(tmp_path, run_pdem):
    """Without dt in the deck the step count is known only once the scene exists: a stage of 1e4 s
    at a dt of ~1e-9 s (0.1 µm grains) is refused at the start, before anything is written (it used
    to run for ever, or overflow int())."""
    deck = tmp_path / "deck.toml"
    text = FILE_DECK.replace("dt = 2e-6\n", "").replace("steps = 20\n[[stages]]", "time = 1e4\n[[stages]]", 1)
    deck.write_text(text)
    write_spheres_text(tmp_path / "pack.txt", np.array([[0.0, 0.0, 2e-7]]), np.array([1e-7]))
    for args in (["check", deck], [deck, "--output", tmp_path / "out", "--quiet"]):
        code, _, err = run_pdem(args)
        assert code == 2 and "stages.drop.end.time" in err and "above the limit" in err, err
    assert not (tmp_path / "out").exists()


def test_check_deck_only_skips_the_scene(tmp_path, capsys):
    deck = tmp_path / "deck.toml"
    deck.write_text(FILE_DECK)
    bad_packing("overlapping_grains", tmp_path / "pack.txt")
    assert main(["check", str(deck), "--deck-only"]) == 0
    assert "particles at the start" not in capsys.readouterr().out
    assert main(["check", str(deck)]) == 2
