"""The pdem command against hostile input: bad output targets, file permissions, --steps,
run.decomposition on the wrong rank count, absurd step counts, huge titles, integer count columns in
the series, and `pdem schema --output` over an existing file.

Every refusal must exit 2 with one message naming the key or path and the remedy (no traceback:
called in-process, an unexpected exception fails the test) and must leave nothing behind.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from decks import TINY_LATTICE

from pdem.cli import main
from pdem.io.series import read_series

ROOT = Path(__file__).resolve().parent.parent

# 64 spheres on a simple cubic lattice above a floor, 20 steps: ~0.2 s once the kernels are cached
TINY = TINY_LATTICE

# the same scene ending by time instead of steps (the step count follows from dt)
TIMED = TINY.replace("steps = 20\n", "time = 4e-5\n")


def write_deck(directory: Path, text: str = TINY, name: str = "deck.toml") -> Path:
    path = directory / name
    path.write_text(text)
    return path


def tree(directory: Path) -> list[str]:
    """Every path under ``directory`` (relative, sorted), to check that nothing was added."""
    return sorted(str(p.relative_to(directory)) for p in directory.rglob("*"))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """The latest checkpoint of a tiny run stopped after 10 steps."""
    tmp = tmp_path_factory.mktemp("hostile_ckpt")
    deck = write_deck(tmp)
    assert main([str(deck), "--output", str(tmp / "out"), "--steps", "10", "--quiet"]) == 0
    return tmp / "out" / "checkpoints" / "latest.h5"


# ------------------------------------------------------------------------------ 1. output targets
def _bad_target(kind: str, tmp_path: Path) -> Path:
    if kind == "regular_file":
        target = tmp_path / "results.txt"
        target.write_text("not a directory")
        return target
    if kind == "dev_null":
        return Path("/dev/null")
    if kind == "under_regular_file":  # cannot be created (root may write anywhere, but not under a file)
        (tmp_path / "blocker").write_text("a file where a directory would have to be")
        return tmp_path / "blocker" / "sub" / "out"
    raise AssertionError(kind)


BAD_TARGETS = ["regular_file", "dev_null", "under_regular_file"]


def _assert_refused_output(code: int, err: str, target: Path) -> None:
    assert code == 2, err
    assert str(target) in err and "--output DIR" in err, err
    assert "Traceback" not in err and err.count("\n") == 1, err


@pytest.mark.parametrize("kind", BAD_TARGETS)
def test_run_refuses_bad_output_target(tmp_path, run_pdem, kind):
    deck = write_deck(tmp_path)
    target = _bad_target(kind, tmp_path)
    before = tree(tmp_path)
    for extra in ([], ["--overwrite"]):  # --overwrite never replaces a file either
        code, _, err = run_pdem([deck, "--output", target, "--quiet", *extra])
        _assert_refused_output(code, err, target)
        assert tree(tmp_path) == before
    if kind == "regular_file":
        assert target.read_text() == "not a directory"
        assert "regular file" in err
    if kind == "dev_null":
        assert stat.S_ISCHR(os.stat("/dev/null").st_mode) and "character device" in err
    if kind == "under_regular_file":
        assert "cannot be created" in err and str(tmp_path / "blocker") in err


@pytest.mark.parametrize("kind", BAD_TARGETS)
def test_resume_refuses_bad_output_target(tmp_path, run_pdem, checkpoint, kind):
    target = _bad_target(kind, tmp_path)
    before = tree(tmp_path)
    ckpt_dir_before = tree(checkpoint.parent.parent)
    code, _, err = run_pdem(["resume", checkpoint, "--output", target, "--quiet"])
    _assert_refused_output(code, err, target)
    assert tree(tmp_path) == before and tree(checkpoint.parent.parent) == ckpt_dir_before


def test_deck_output_directory_that_is_a_file(tmp_path, run_pdem):
    """The same rule for output.directory from the deck (no --output): the message names the key."""
    deck = write_deck(tmp_path)
    (tmp_path / "taken").write_text("x")
    code, _, err = run_pdem([deck, "--set", f'output.directory="{tmp_path / "taken"}"', "--quiet"])
    assert code == 2 and "output.directory" in err and "regular file" in err, err
    assert (tmp_path / "taken").read_text() == "x"


def test_bad_output_target_real_process(tmp_path):
    """Exit code 2 and one line on stderr from the installed command, not a traceback."""
    deck = write_deck(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "pdem.cli", str(deck), "--output", "/dev/null", "--quiet"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("pdem: error: output path /dev/null") and "Traceback" not in proc.stderr


# ------------------------------------------------------------------------------ 2. file modes
def test_output_files_follow_the_umask(tmp_path, run_pdem):
    """Index files written atomically (XDMF, PVD, PVTU-less VTU, metadata) get 0666 minus the umask
    like every other output file, not mkstemp's 0600."""
    deck = write_deck(tmp_path)
    out = tmp_path / "out"
    old = os.umask(0o027)
    try:
        code, _, err = run_pdem([deck, "--output", out, "--quiet", "--set", 'output.formats=["hdf5", "vtk"]'])
    finally:
        os.umask(old)
    assert code == 0, err
    files = [p for p in out.rglob("*") if p.is_file() and not p.is_symlink()]
    names = {p.name for p in files}
    for expected in ("particles.xdmf", "walls.xdmf", "particles.pvd", "walls.pvd", "metadata.json"):
        assert expected in names
    assert any(p.suffix == ".vtu" for p in files)
    modes = {str(p.relative_to(out)): oct(stat.S_IMODE(p.stat().st_mode)) for p in files}
    assert set(modes.values()) == {oct(0o640)}, modes
    hidden = {p.name for p in out.rglob(".*")} - {".pdem-output.json", ".pdem-lock"}  # marker and lock
    assert not hidden, f"temporary files left behind: {hidden}"


# ------------------------------------------------------------------------------ 3. --steps
@pytest.mark.parametrize("command", ["run", "resume"])
def test_negative_steps_refused(tmp_path, capsys, checkpoint, command):
    deck = write_deck(tmp_path)
    head = [deck] if command == "run" else ["resume", checkpoint]
    before = tree(tmp_path)
    with pytest.raises(SystemExit) as exc:  # argparse: usage + one error line, exit code 2
        main([str(a) for a in [*head, "--steps", "-5", "--output", tmp_path / "out", "--quiet"]])
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert "--steps" in err and "negative" in err and "-5" in err and "0 or more" in err, err
    assert tree(tmp_path) == before


def test_zero_steps_writes_the_initial_state_and_resumes(tmp_path, run_pdem):
    """--steps 0 is meaningful (kept): the scene is built, its initial state written with a
    checkpoint, and resuming from it gives the uninterrupted run bit for bit."""
    deck = write_deck(tmp_path)
    code, out, err = run_pdem([deck, "--output", tmp_path / "zero", "--steps", "0", "--quiet"])
    assert code == 0, err
    assert "stopped early" in out and "0 steps" in out
    summary = json.loads((tmp_path / "zero" / "summary.json").read_text())
    assert summary["steps"] == 0 and summary["particles"] == 64 and not summary["completed"]
    ckpt = tmp_path / "zero" / "checkpoints" / "latest.h5"
    code, _, err = run_pdem(["resume", ckpt, "--output", tmp_path / "resumed", "--quiet"])
    assert code == 0, err
    code, _, err = run_pdem([deck, "--output", tmp_path / "whole", "--quiet"])
    assert code == 0, err
    from pdem.io.checkpoint import read_checkpoint

    a, _ = read_checkpoint(tmp_path / "resumed" / "checkpoints" / "latest.h5")
    b, _ = read_checkpoint(tmp_path / "whole" / "checkpoints" / "latest.h5")
    assert a.keys() == b.keys()
    for key in a:
        assert np.array_equal(a[key], b[key]), key


# ------------------------------------------------------------------------------ 4. decomposition
def test_decomposition_must_match_the_rank_count(tmp_path, run_pdem):
    deck = write_deck(tmp_path)
    out = tmp_path / "out"
    code, _, err = run_pdem([deck, "--output", out, "--quiet", "--set", "run.decomposition=[2, 1, 1]"])
    assert code == 2, err
    for fragment in ("run.decomposition", "[2, 1, 1]", "1 rank", "mpiexec -n 2", "remove run.decomposition"):
        assert fragment in err, (fragment, err)
    assert not out.exists()
    # pdem check cannot know the rank count: nothing wrong there
    code, stdout, err = run_pdem(["check", deck, "--set", "run.decomposition=[2, 1, 1]"])
    assert code == 0 and "valid" in stdout, err
    # a matching grid runs
    code, _, err = run_pdem([deck, "--output", out, "--quiet", "--set", "run.decomposition=[1, 1, 1]"])
    assert code == 0, err


def test_decomposition_mismatch_under_mpi(tmp_path):
    """On 2 ranks, a 1-subdomain grid is refused on every rank together (exit 2), nothing written."""
    mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    if mpiexec is None:
        pytest.skip("mpiexec not found (pip install mpich)")
    deck = write_deck(tmp_path)
    out = tmp_path / "out"
    cmd = [mpiexec, "-n", "2", sys.executable, "-m", "pdem.cli", str(deck), "--output", str(out), "--quiet"]
    proc = subprocess.run(
        [*cmd, "--set", "run.decomposition=[1, 1, 1]"], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2, proc.stderr
    assert "run.decomposition = [1, 1, 1]" in proc.stderr and "2 ranks" in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and not out.exists()


def test_decomposition_entries_must_be_positive(tmp_path, run_pdem):
    """[0, 1, 1] or [-1, -1, 1] (product 1!) is a deck error, found by pdem check too."""
    deck = write_deck(tmp_path)
    for dims, index in (("[0, 1, 1]", 0), ("[-1, -1, 1]", 0)):
        code, _, err = run_pdem(["check", deck, "--set", f"run.decomposition={dims}"])
        assert code == 2 and f"run.decomposition.{index}: must be >= 1" in err, err


def test_decomposition_in_the_deck_file(tmp_path, run_pdem):
    """Given in the deck rather than by --set: the same check, the same message."""
    deck = write_deck(tmp_path, TINY.replace("dt = 2e-6", "dt = 2e-6\ndecomposition = [1, 1, 2]"))
    code, _, err = run_pdem([deck, "--output", tmp_path / "out", "--quiet"])
    assert code == 2 and "run.decomposition = [1, 1, 2]" in err, err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------ 5. absurd step counts
def test_absurd_step_count_refused(tmp_path, run_pdem):
    deck = write_deck(tmp_path, TIMED)
    code, _, err = run_pdem(["check", deck, "--set", "run.dt=1e-300"])
    assert code == 2, err
    for fragment in ("stages.0.end.time", "time = 4e-05", "dt = 1e-300", "run.dt", "4e+295 steps", "1e+10"):
        assert fragment in err, (fragment, err)
    # a stage's own dt, and max_time: both named
    code, _, err = run_pdem(
        ["check", deck, "--set", "stages.0.dt=1e-20", "--set", "stages.0.end.max_time=1.0"]
    )
    assert code == 2 and "stages.0.dt" in err and "stages.0.end.max_time" in err, err
    # the run is refused the same way before anything is written
    code, _, err = run_pdem([deck, "--output", tmp_path / "out", "--set", "run.dt=1e-300", "--quiet"])
    assert code == 2 and "stages.0.end.time" in err and not (tmp_path / "out").exists()


def test_long_stage_bounded_by_steps_or_time_is_fine(tmp_path, run_pdem):
    """Only the stage's bound counts: a huge max_time is harmless when steps or time end it first."""
    deck = write_deck(tmp_path, TINY)  # ends after 20 steps
    code, _, err = run_pdem(["check", deck, "--set", "run.dt=1e-300", "--set", "stages.0.end.max_time=1.0"])
    assert code == 0, err
    deck = write_deck(tmp_path, TIMED, "timed.toml")  # ends at 4e-5 s = 20 steps
    code, _, err = run_pdem(["check", deck, "--set", "stages.0.end.max_time=1e300"])
    assert code == 0, err


# ------------------------------------------------------------------------------ 6. title
def test_title_length_capped(tmp_path, run_pdem):
    long_title = "x" * 1001
    deck = write_deck(tmp_path, TINY.replace('title = "tiny lattice"', f'title = "{long_title}"'))
    code, _, err = run_pdem([deck, "--output", tmp_path / "out", "--quiet"])
    assert code == 2 and "title" in err and "1,001 characters" in err and "1,000" in err, err
    assert len(err) < 1000 and not (tmp_path / "out").exists()  # the title itself is not echoed
    ok = write_deck(tmp_path, TINY.replace('title = "tiny lattice"', f'title = "{"y" * 1000}"'), "ok.toml")
    code, _, err = run_pdem(["check", ok])
    assert code == 0, err


# ------------------------------------------------------------------------------ 7. series columns
def _plot_series_module():
    pytest.importorskip("matplotlib")
    spec = importlib.util.spec_from_file_location("pdem_tools_plot_series", ROOT / "tools" / "plot_series.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_series_count_columns_are_integers(tmp_path, run_pdem):
    deck = write_deck(tmp_path)
    out = tmp_path / "out"
    code, _, err = run_pdem([deck, "--output", out, "--quiet"])
    assert code == 0, err
    with open(out / "series_drop.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["step"] for r in rows] == ["0", "10", "20"]  # the last step is on the cadence: one row
    assert {r["particles"] for r in rows} == {"64"}
    assert all(r["floor.contacts"].isdigit() for r in rows)
    assert rows[0]["ke_trans"] == "0.0" and rows[0]["time"] == "0.0"  # other columns keep float text
    data = read_series(out / "series_drop.csv")
    assert data["step"].dtype == np.int64 and data["particles"].dtype == np.int64
    assert data["time"].dtype == np.float64 and data["ke_trans"].dtype == np.float64
    stages = _plot_series_module().read_stages(out)
    assert [name for name, _ in stages] == ["drop"]
    assert list(stages[0][1]["step"]) == [0.0, 10.0, 20.0]


# ------------------------------------------------------------------------------ 8. pdem schema
def test_schema_refuses_to_overwrite(tmp_path, run_pdem):
    target = tmp_path / "deck.schema.json"
    target.write_text("precious")
    code, _, err = run_pdem(["schema", "--output", target])
    assert code == 2 and str(target) in err and "--overwrite" in err, err
    assert target.read_text() == "precious"
    code, _, err = run_pdem(["schema", "--output", target, "--overwrite"])
    assert code == 0, err
    assert "properties" in json.loads(target.read_text())
    code, _, err = run_pdem(["schema", "--output", tmp_path])
    assert code == 2 and "is a directory" in err, err
    code, _, err = run_pdem(["schema", "--output", tmp_path / "missing" / "s.json"])
    assert code == 2 and "cannot write" in err and not (tmp_path / "missing").exists(), err
