"""Users' files are safe: --overwrite replaces only pdem's output, one run per output directory at
a time, and a failed resume leaves the directory as it was.

Every check compares the whole directory tree before and after (file contents by hash; HDF5 frame
files by their datasets, since a resume moves frame groups inside them).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from decks import SHORT_HOPPER_SETS

from pdem.cli import main
from pdem.io.paths import MARKER, lock_holder

ROOT = Path(__file__).resolve().parents[1]
HOPPER = ROOT / "inputs" / "hopper.toml"
# the short hopper of tests/test_resume.py: ~6,600 steps, a checkpoint every 1,000
SETS = list(SHORT_HOPPER_SETS)
SET_ARGS = [a for s in SETS for a in ("--set", s)]
IGNORED = {".pdem-lock"}  # the lock file's content names the last process that held it


def _h5_digest(path: Path) -> str:
    """A digest of an HDF5 file's groups, datasets and attributes (not of its byte layout)."""
    h = hashlib.sha256()

    def visit(name, obj):
        h.update(name.encode())
        for k in sorted(obj.attrs):
            h.update(k.encode() + repr(np.asarray(obj.attrs[k]).tolist()).encode())
        if isinstance(obj, h5py.Dataset):
            a = np.asarray(obj[()])
            h.update(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())

    with h5py.File(path, "r") as f:
        for k in sorted(f.attrs):
            h.update(k.encode() + repr(np.asarray(f.attrs[k]).tolist()).encode())
        f.visititems(visit)
    return h.hexdigest()


def tree(directory: Path) -> dict[str, str]:
    """Relative path -> digest of every file and link below ``directory``."""
    out = {}
    for p in sorted(Path(directory).rglob("*")):
        rel = str(p.relative_to(directory))
        if p.name in IGNORED:
            continue
        if p.is_symlink():
            out[rel] = "-> " + os.readlink(p)
        elif p.is_file():
            if p.suffix == ".h5" and p.parent.name != "checkpoints":
                out[rel] = _h5_digest(p)
            else:
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[rel] = "dir"
    return out


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("safety") / "full"
    assert main([str(HOPPER), *SET_ARGS, "--output", str(out), "--quiet"]) == 0
    return out


# ------------------------------------------------------------------------------ --overwrite
def _tiny(tmp_path: Path) -> Path:
    deck = tmp_path / "deck.toml"
    shutil.copy(HOPPER, deck)
    return deck


@pytest.mark.parametrize("where", ["deck_inside", "home_like", "cwd"])
def test_overwrite_refuses_a_folder_pdem_did_not_make(tmp_path, run_pdem, monkeypatch, where):
    folder = tmp_path / "ow"
    folder.mkdir()
    deck = _tiny(folder if where == "deck_inside" else tmp_path)
    if where == "home_like":
        (folder / ".bashrc").write_text("export PATH\n")
        (folder / "Documents").mkdir()
        (folder / "Documents" / "thesis.tex").write_text("\\documentclass{article}\n")
        (folder / "checkpoints").mkdir()  # even names pdem uses are not pdem's without the marker
        (folder / "summary.json").write_text("{}\n")
    (folder / "notes.txt").write_text("mine\n")
    out: Path | str = folder
    if where == "cwd":
        monkeypatch.chdir(folder)
        out = "."
    before = tree(tmp_path)
    code, _, err = run_pdem([deck, *SET_ARGS, "--steps", "10", "--output", out, "--overwrite", "--quiet"])
    assert code == 2, err
    assert "not made by pdem" in err and "nothing in it was touched" in err, err
    assert tree(tmp_path) == before


def test_overwrite_replaces_only_pdem_output(tmp_path, run_pdem):
    folder = tmp_path / "run"
    assert run_pdem([HOPPER, *SET_ARGS, "--steps", "300", "--output", folder, "--quiet"])[0] == 0
    assert (folder / MARKER).is_file()
    listed = set(json.loads((folder / MARKER).read_text())["entries"])
    assert {"checkpoints", "particles.h5", "series_fill.csv", "summary.json"} <= listed
    # the user adds a deck, notes and a plot to the output folder, then reruns from the deck in it
    deck = _tiny(folder)
    (folder / "notes.txt").write_text("mine\n")
    (folder / "plot.png").write_bytes(b"\x89PNG fake")
    old_summary = (folder / "summary.json").read_text()
    code, _, err = run_pdem([deck, *SET_ARGS, "--steps", "200", "--output", folder, "--overwrite", "--quiet"])
    assert code == 0, err
    assert deck.read_text() == HOPPER.read_text()
    assert (folder / "notes.txt").read_text() == "mine\n" and (folder / "plot.png").exists()
    assert (folder / "summary.json").read_text() != old_summary
    steps = sorted(p.name for p in (folder / "checkpoints").glob("step_*.h5"))
    assert steps[-1] == "step_0000000200.h5" and "step_0000000300.h5" not in steps  # the old run's: gone
    listed = set(json.loads((folder / MARKER).read_text())["entries"])
    assert not listed & {"deck.toml", "notes.txt", "plot.png"}


def test_overwrite_without_flag_still_refused(tmp_path, run_pdem):
    folder = tmp_path / "run"
    assert run_pdem([HOPPER, *SET_ARGS, "--steps", "50", "--output", folder, "--quiet"])[0] == 0
    before = tree(tmp_path)
    code, _, err = run_pdem([HOPPER, *SET_ARGS, "--steps", "50", "--output", folder, "--quiet"])
    assert code == 2 and "--overwrite" in err, err
    assert tree(tmp_path) == before


# ------------------------------------------------------------------------------ the lock
def _start(out: Path, *extra: str) -> subprocess.Popen:
    """A hopper that does not end by itself (its discharge target is never reached)."""
    args = [a for s in SETS[:-2] for a in ("--set", s)]
    cmd = [sys.executable, "-m", "pdem", str(HOPPER), *args, "--set", "stages.discharge.end.above=1",
           "--set", "stages.discharge.end.max_time=1000", "--set", "output.checkpoint_every_steps=500",
           "--output", str(out), "--quiet", *extra]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait_for(pred, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    t0 = time.monotonic()
    while not pred():
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.1)


def test_one_run_per_output_directory(tmp_path, run_pdem, full):
    out = tmp_path / "live"
    proc = _start(out)
    try:
        _wait_for(lambda: (out / "checkpoints" / "latest.h5").exists(), proc)
        holder = lock_holder(out)
        assert holder is not None and str(proc.pid) in holder
        t0 = time.monotonic()
        # a second run, an --overwrite run and a resume into the live folder: refused, nothing touched
        for args in (
            [HOPPER, *SET_ARGS, "--output", out, "--quiet"],
            [HOPPER, *SET_ARGS, "--output", out, "--overwrite", "--quiet"],
            ["resume", out / "checkpoints" / "step_0000000500.h5", "--quiet"],
        ):
            code, _, err = run_pdem(args)
            assert code == 2, err
            assert "in use by process" in err and str(proc.pid) in err, err
        assert time.monotonic() - t0 < 30  # refused at once, not after building the scene
        assert proc.poll() is None  # the live run goes on
        # a resume elsewhere from the live run's checkpoint is fine
        code, _, err = run_pdem(["resume", out / "checkpoints" / "step_0000000500.h5", "--output",
                                 tmp_path / "copy", "--steps", "600", "--quiet"])
        assert code == 0, err
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert lock_holder(out) is None  # a killed run leaves no lock behind
    code, _, err = run_pdem([HOPPER, *SET_ARGS, "--steps", "20", "--output", out, "--overwrite", "--quiet"])
    assert code == 0, err


def test_two_runs_started_together_on_one_new_folder(tmp_path):
    out = tmp_path / "new" / "run"
    cmd = [sys.executable, "-m", "pdem", str(HOPPER), *SET_ARGS, "--steps", "1500", "--output", str(out),
           "--quiet"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    codes = sorted(code for code, _ in results)
    assert codes in ([0, 0], [0, 2]), results  # one may start after the other ended
    if codes == [0, 2]:
        err = next(e for c, e in results if c == 2)
        assert "in use by" in err or "no longer empty" in err or "not empty" in err, err
    # the winner's output is whole
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 1500
    assert (out / "checkpoints" / "step_0000001500.h5").exists()


# ------------------------------------------------------------------------------ resume failures
def test_failed_resume_leaves_every_file_as_it_was(tmp_path, run_pdem, full):
    out = tmp_path / "run"
    shutil.copytree(full, out, symlinks=True)
    before = tree(out)
    assert any(k.startswith("checkpoints/step_000000600") for k in before)
    # an unstable step from the checkpoint at 3,000: the run fails (exit 3) after writing rows
    code, _, err = run_pdem(["resume", out / "checkpoints" / "step_0000003000.h5", "--set", "run.dt=2e-4",
                             "--set", "run.force_dt=true"])
    assert code == 3, err
    assert "put back as it was" in err, err
    assert tree(out) == before
    assert not (out / ".pdem-journal").exists()
    # and the directory still resumes bitwise: the later checkpoints are the uninterrupted run's
    code, _, err = run_pdem(["resume", out / "checkpoints" / "step_0000005000.h5", "--quiet"])
    assert code == 0, err
    assert (out / "summary.json").read_text().count('"resumed_from_step": 5000') == 1


def test_refused_resume_leaves_every_file_as_it_was(tmp_path, run_pdem, full):
    out = tmp_path / "run"
    shutil.copytree(full, out, symlinks=True)
    before = tree(out)
    code, _, err = run_pdem(["resume", out / "checkpoints" / "step_0000003000.h5",
                             "--set", "materials.glass.density=1"])
    assert code == 2, err
    assert tree(out) == before


def test_resume_killed_mid_way_is_settled_by_the_next(tmp_path, run_pdem, full):
    """A resume killed with SIGKILL leaves a journal; the next resume from an earlier checkpoint undoes
    the killed attempt first, and the run then ends as the uninterrupted one did."""
    out = tmp_path / "run"
    shutil.copytree(full, out, symlinks=True)
    proc = subprocess.Popen(
        [sys.executable, "-m", "pdem", "resume", str(out / "checkpoints" / "step_0000002000.h5"),
         "--set", "stages.discharge.end.above=1", "--set", "stages.discharge.end.max_time=1000",
         "--quiet"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    try:
        _wait_for(lambda: (out / ".pdem-journal").is_dir() and lock_holder(out) is not None, proc)
        time.sleep(1.0)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert (out / ".pdem-journal").is_dir()
    code, _, err = run_pdem(["resume", out / "checkpoints" / "step_0000001000.h5"])
    assert code == 0, err
    assert "interrupted resume from step 2000 was undone" in err, err
    assert not (out / ".pdem-journal").exists()
    a = json.loads((out / "summary.json").read_text())
    b = json.loads((full / "summary.json").read_text())
    assert a["results"] == b["results"] and a["steps"] == b["steps"]


# ------------------------------------------------------------------------------ early refusals, JSON
@pytest.mark.parametrize("command", ["run", "check"])
def test_step_refused_before_the_pour(tmp_path, run_pdem, command):
    """The triaxial's pour takes minutes; a step above the stability estimate for any grains its
    sources make is refused before it, naming the key."""
    deck = ROOT / "inputs" / "triaxial.toml"
    args = [deck, "--set", "run.dt=1"] + (["--output", tmp_path / "o", "--quiet"] if command == "run" else [])
    t0 = time.monotonic()
    code, _, err = run_pdem([*(["check"] if command == "check" else []), *args])
    assert code == 2, err
    assert time.monotonic() - t0 < 20
    assert "run.dt" in err and "dt = 1 s" in err and "force_dt" in err, err
    assert not (tmp_path / "o").exists()


def test_summary_is_strict_json():
    from pdem.runner import json_finite

    value = {"a": float("nan"), "b": [1.0, float("inf"), -float("inf")], "c": np.float64(2.5),
             "d": (np.int64(3), np.array([np.nan, 1.0])), "e": "NaN"}
    text = json.dumps(json_finite(value), allow_nan=False)
    expected = {"a": None, "b": [1.0, None, None], "c": 2.5, "d": [3, [None, 1.0]], "e": "NaN"}
    assert json.loads(text) == expected


def test_summary_file_parses_strictly(full):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    json.loads((full / "summary.json").read_text(), parse_constant=refuse)


def test_journal_counts_cut_rows_as_replaced(tmp_path):
    """Rows after the checkpoint that a resume cuts off (a run killed past its last checkpoint) are
    a future too: a failing resume must put them back; rows only appended are not."""
    from pdem.io.journal import Journal

    csv = tmp_path / "series_fill.csv"
    original = "time,step\n0.0,0\n0.1,100\n0.2,200\n"
    csv.write_text(original)
    journal = Journal(tmp_path)
    journal.begin(200)
    with open(csv, "a") as fh:
        fh.write("0.3,300\n")
    assert not journal.replaced_anything
    journal.commit()
    assert not (tmp_path / ".pdem-journal").exists()
    journal.begin(100)
    csv.write_text("time,step\n0.0,0\n0.1,100\n0.15,150\n")  # cut at step 100, a new row appended
    (tmp_path / "new.csv").write_text("x\n")
    assert journal.replaced_anything
    journal.rollback()
    assert csv.read_text() == original + "0.3,300\n"
    assert not (tmp_path / "new.csv").exists() and not (tmp_path / ".pdem-journal").exists()
