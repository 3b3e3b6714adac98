"""Damaged checkpoints are refused before anything is written; intact ones resume bit for bit.

A tiny run (64 grains on a lattice above a floor, two stages of 20 steps, stopped at step 30) leaves
two checkpoints, step 20 and step 30 (``latest.h5``). Its output folder is copied, the step-30
checkpoint damaged in one way, and ``pdem resume`` run on it: it must exit with code 2, name what is
wrong and suggest the step-20 checkpoint, and leave every file of the folder byte for byte as it was.
Format-2 checkpoints carry checksums (a one-bit change is caught); format-1 files (no checksums) are
still read, checked structurally only. ``run.max_overlap`` may be changed on resume.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest
from decks import TINY_LATTICE_TWO_STAGES

from pdem.cli import main
from pdem.deck.load import validate_deck
from pdem.io.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKSUMS_ATTR,
    FORMAT_ATTR,
    BadCheckpointError,
    read_checkpoint,
)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from determinism import compare  # noqa: E402

# 64 spheres on a simple cubic lattice above a floor; two stages of 20 steps (~0.3 s once the kernels
# are cached)
TINY = TINY_LATTICE_TWO_STAGES
STOP = 30  # the run is stopped here: checkpoints at step 20 (end of "drop") and 30
EARLIER = "step_0000000020.h5"


def tree(directory: Path) -> dict[str, str]:
    """Every entry under ``directory``: the SHA-256 of a file's bytes, a link's target."""
    out = {}
    for path in sorted(directory.rglob("*")):
        key = str(path.relative_to(directory))
        if path.is_symlink():
            out[key] = "link → " + os.readlink(path)
        elif path.is_file():
            out[key] = hashlib.sha256(path.read_bytes()).hexdigest()
        else:
            out[key] = "dir"
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The run stopped at step 30, and the same run uninterrupted."""
    base = tmp_path_factory.mktemp("integrity")
    deck = base / "deck.toml"
    deck.write_text(TINY)
    assert main([str(deck), "--output", str(base / "stopped"), "--quiet", "--steps", str(STOP)]) == 0
    assert main([str(deck), "--output", str(base / "full"), "--quiet"]) == 0
    return {"stopped": base / "stopped", "full": base / "full"}


def copy_run(runs, tmp_path: Path, name: str = "run") -> tuple[Path, Path]:
    """A copy of the stopped run's output, and its step-30 checkpoint (``latest.h5``)."""
    out = tmp_path / name
    shutil.copytree(runs["stopped"], out, symlinks=True)
    latest = out / "checkpoints" / "latest.h5"
    assert latest.resolve().name == f"step_{STOP:010d}.h5"
    return out, latest


def as_format_1(path: Path) -> None:
    """Make ``path`` a format-1 checkpoint: no checksums."""
    with h5py.File(path, "r+") as fh:
        del fh.attrs[CHECKSUMS_ATTR]
        fh.attrs[FORMAT_ATTR] = 1


def final_state(out: Path) -> dict:
    return read_checkpoint(out / "checkpoints" / "latest.h5")[0]


# ------------------------------------------------------------------------------ damage
def flip_bit_in_x(path: Path) -> None:
    """The lowest mantissa bit of one coordinate: a plausible value, 1 ulp away."""
    with h5py.File(path, "r+") as fh:
        x = fh["particles/x"][()]
        before = x[7, 2]
        x.view(np.uint64)[7, 2] ^= np.uint64(1)
        assert x[7, 2] != before and np.isfinite(x[7, 2]) and abs(x[7, 2] - before) < 1e-15
        fh["particles/x"][...] = x


def negative_step(path: Path) -> None:
    with h5py.File(path, "r+") as fh:
        fh["scalars/step"][()] = -5


def delete_velocities(path: Path) -> None:
    with h5py.File(path, "r+") as fh:
        del fh["particles/v"]


def other_deck(path: Path) -> None:
    """The deck of a smaller scene (32 grains, valid in itself) instead of the run's own."""
    with h5py.File(path, "r+") as fh:
        text = fh.attrs["deck"]
        other = text.replace("hi = [0.004, 0.004, 0.004]", "hi = [0.004, 0.004, 0.002]")
        assert other != text
        validate_deck(tomllib.loads(other))  # a valid deck, just not this checkpoint's
        fh.attrs["deck"] = other


def fewer_velocity_rows(path: Path) -> None:
    with h5py.File(path, "r+") as fh:
        v = fh["particles/v"][()]
        del fh["particles/v"]
        fh["particles/v"] = v[:-1]


def narrow_spins(path: Path) -> None:
    with h5py.File(path, "r+") as fh:
        w = fh["particles/w"][()]
        del fh["particles/w"]
        fh["particles/w"] = w[:, :2]


def truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


DAMAGE = [
    pytest.param(flip_bit_in_x, ["'particles/x'", "checksum"], id="one-bit-flip-in-x"),
    pytest.param(negative_step, ["'scalars/step'", "-5", ">= 0"], id="step-minus-5"),
    pytest.param(delete_velocities, ["'particles/v'", "missing"], id="deleted-velocities"),
    pytest.param(other_deck, ["attribute 'deck'", "checksum"], id="another-valid-deck"),
    pytest.param(fewer_velocity_rows, ["'particles/v'", "(63, 3)", "64"], id="shape-rows"),
    pytest.param(narrow_spins, ["'particles/w'", "(64, 2)", "(64, 3)"], id="shape-width"),
    pytest.param(truncate, ["cannot read", "truncated"], id="truncated-file"),
]


@pytest.mark.parametrize(("damage", "fragments"), DAMAGE)
def test_damaged_checkpoint_is_refused_and_nothing_changes(runs, tmp_path, run_pdem, damage, fragments):
    out, latest = copy_run(runs, tmp_path)
    damage(latest.resolve())
    before = tree(tmp_path)
    code, _, err = run_pdem(["resume", latest, "--quiet"])
    assert code == 2, err
    assert "Traceback" not in err and err.startswith("pdem: error: ")
    assert str(latest) in err, err  # the checkpoint named
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    assert f"pdem resume {out / 'checkpoints' / EARLIER}" in err, err  # the remedy: the earlier one
    assert tree(tmp_path) == before
    # elsewhere too: --output DIR is not created
    code, _, err = run_pdem(["resume", latest, "--quiet", "--output", tmp_path / "elsewhere"])
    assert code == 2, err
    assert tree(tmp_path) == before


def test_the_suggested_earlier_checkpoint_resumes(runs, tmp_path, run_pdem):
    """The remedy works: the step-20 checkpoint of the damaged run's folder continues the run to
    the uninterrupted run's state (the damaged later checkpoint is replaced)."""
    out, latest = copy_run(runs, tmp_path)
    flip_bit_in_x(latest.resolve())
    code, _, err = run_pdem(["resume", latest, "--quiet"])
    assert code == 2
    command = err[err.index("pdem resume ") :].split(" (step")[0]
    code, _, err = run_pdem([*command.split()[1:], "--quiet"])
    assert code == 0, err
    assert compare(final_state(runs["full"]), final_state(out)) is None


def test_no_earlier_checkpoint_says_rerun(runs, tmp_path, run_pdem):
    out, latest = copy_run(runs, tmp_path)
    (out / "checkpoints" / EARLIER).unlink()
    negative_step(latest.resolve())
    code, _, err = run_pdem(["resume", latest, "--quiet"])
    assert code == 2
    assert "no earlier checkpoint" in err and "rerun the deck from the start" in err, err


def test_every_dataset_and_attribute_is_covered(runs, tmp_path):
    """Changing any one dataset (one bit) or attribute of a checkpoint is caught, and named."""
    original = runs["stopped"] / "checkpoints" / f"step_{STOP:010d}.h5"
    path = tmp_path / "checkpoints" / f"step_{STOP:010d}.h5"
    path.parent.mkdir()
    with h5py.File(original, "r") as fh:
        datasets = []
        fh.visititems(lambda name, obj: datasets.append(name) if isinstance(obj, h5py.Dataset) else None)
        attributes = [k for k in fh.attrs if k != CHECKSUMS_ATTR]
    assert len(datasets) > 20 and "particles/x" in datasets and "deck" in attributes
    for name in datasets:
        shutil.copyfile(original, path)
        with h5py.File(path, "r+") as fh:
            a = np.array(fh[name][()])
            if a.size == 0:
                continue
            raw = a.reshape(-1).view(np.uint8)
            raw[-1] ^= 1  # one bit of the last element
            fh[name][...] = a
        with pytest.raises(BadCheckpointError) as exc:
            read_checkpoint(path)
        assert f"'{name}'" in str(exc.value), (name, str(exc.value))
    for name in attributes:
        shutil.copyfile(original, path)
        with h5py.File(path, "r+") as fh:
            value = fh.attrs[name]
            fh.attrs[name] = value + " " if isinstance(value, str) else value + 1
        with pytest.raises(BadCheckpointError) as exc:
            read_checkpoint(path)
        assert f"attribute '{name}'" in str(exc.value), (name, str(exc.value))
    shutil.copyfile(original, path)  # intact: reads back
    state, meta = read_checkpoint(path)
    assert int(state["scalars/step"]) == STOP and meta[FORMAT_ATTR] == CHECKPOINT_FORMAT


def _add_wall(fh):
    fh.create_dataset("walls/ghost/offset", data=np.zeros(3))


@pytest.mark.parametrize(
    ("edit", "fragment"),
    [
        pytest.param(_add_wall, "'walls/ghost/offset'", id="added-dataset"),
        pytest.param(
            lambda fh: fh.attrs.__delitem__("boundaries"), "attribute 'boundaries'", id="deleted-attr"
        ),
        pytest.param(lambda fh: fh.attrs.__delitem__(CHECKSUMS_ATTR), CHECKSUMS_ATTR, id="no-checksums"),
    ],
)
def test_added_or_removed_entries_are_refused(runs, tmp_path, edit, fragment):
    _, latest = copy_run(runs, tmp_path)
    with h5py.File(latest, "r+") as fh:
        edit(fh)
    with pytest.raises(BadCheckpointError) as exc:
        read_checkpoint(latest)
    assert fragment in str(exc.value) and EARLIER in str(exc.value), str(exc.value)


# ------------------------------------------------------------------------------ format 1
def _set(key, value):
    """Replace dataset or attribute ``key`` with ``value`` (its own dtype: 2.5 stays 2.5)."""

    def edit(fh):
        if key in fh:
            del fh[key]
            fh[key] = value
        else:
            fh.attrs[key] = value

    return edit


def _duplicate_id(fh):
    ids = fh["particles/id"][()]
    ids[5] = ids[4]
    fh["particles/id"][...] = ids


def _material(fh):
    mat = fh["particles/mat"][()]
    mat[3] = 7
    fh["particles/mat"][...] = mat


FORMAT_1_DAMAGE = [
    pytest.param(_set("scalars/step", -5), ["'scalars/step'", "-5"], id="step-minus-5"),
    pytest.param(_set("scalars/step", 2.5), ["'scalars/step'", "2.5", "whole number"], id="step-fraction"),
    pytest.param(_set("scalars/time", np.nan), ["'scalars/time'", "nan"], id="time-nan"),
    pytest.param(_set("scalars/time", -1.0), ["'scalars/time'", "-1.0"], id="time-negative"),
    pytest.param(_set("scalars/dt", 0.0), ["'scalars/dt'", "0.0", "> 0"], id="dt-zero"),
    pytest.param(_set("scalars/dt", np.inf), ["'scalars/dt'", "inf"], id="dt-inf"),
    pytest.param(lambda fh: fh.__delitem__("particles/v"), ["'particles/v'", "missing"], id="deleted-v"),
    pytest.param(lambda fh: fh.__delitem__("pairs/hist"), ["'pairs/hist'", "missing"], id="deleted-pairs"),
    pytest.param(lambda fh: fh.__delitem__("walls/floor/offset"), ["'walls/floor/offset'"],
                 id="deleted-wall"),
    pytest.param(_duplicate_id, ["'particles/id'", "unique"], id="duplicate-id"),
    pytest.param(_material, ["'particles/mat'", "7", "1 material"], id="material-index"),
    pytest.param(_set("stage_index", 5), ["attribute 'stage_index'", "5", "2 stage"], id="stage-index"),
    pytest.param(_set("stage_start_step", 31), ["attribute 'stage_start_step'", "31"], id="stage-start"),
    pytest.param(_set("boundaries", '{"floor": {}, "lid": {}}'), ["attribute 'boundaries'", "lid"],
                 id="unknown-boundary"),
    pytest.param(_set("deck", "title = 'x'\n[run"), ["attribute 'deck'", "TOML"], id="deck-not-toml"),
]  # fmt: skip


@pytest.mark.parametrize(("edit", "fragments"), FORMAT_1_DAMAGE)
def test_format_1_is_checked_structurally(runs, tmp_path, run_pdem, edit, fragments):
    out, latest = copy_run(runs, tmp_path)
    as_format_1(latest.resolve())
    with h5py.File(latest, "r+") as fh:
        edit(fh)
    before = tree(tmp_path)
    code, _, err = run_pdem(["resume", latest, "--quiet"])
    assert code == 2, err
    for fragment in fragments:
        assert fragment in err, (fragment, err)
    assert EARLIER in err, err
    assert tree(tmp_path) == before


def test_format_1_shape_mismatch(runs, tmp_path, run_pdem):
    _, latest = copy_run(runs, tmp_path)
    as_format_1(latest.resolve())
    fewer_velocity_rows(latest.resolve())
    before = tree(tmp_path)
    code, _, err = run_pdem(["resume", latest, "--quiet"])
    assert code == 2, err
    assert "'particles/v'" in err and "(63, 3)" in err and "64 particles" in err, err
    assert tree(tmp_path) == before


# ------------------------------------------------------------------------------ intact checkpoints
@pytest.mark.parametrize("fmt", [CHECKPOINT_FORMAT, 1])
def test_intact_checkpoint_resumes_bitwise(runs, tmp_path, run_pdem, fmt):
    out, latest = copy_run(runs, tmp_path)
    if fmt == 1:
        as_format_1(latest.resolve())
    state, meta = read_checkpoint(latest)
    assert meta[FORMAT_ATTR] == fmt and int(state["scalars/step"]) == STOP
    code, _, err = run_pdem(["resume", latest, "--quiet"])
    assert code == 0, err
    assert compare(final_state(runs["full"]), final_state(out)) is None
    with h5py.File(out / "checkpoints" / "latest.h5", "r") as fh:  # new checkpoints: current format
        assert fh.attrs[FORMAT_ATTR] == CHECKPOINT_FORMAT
        assert set(json.loads(fh.attrs[CHECKSUMS_ATTR])["datasets"]) == set(final_state(out))


# ------------------------------------------------------------------------------ run.max_overlap
def test_max_overlap_can_be_set_on_resume(runs, tmp_path, run_pdem):
    out, latest = copy_run(runs, tmp_path)
    # a tiny limit is applied: the grains resting on the floor already overlap it by more
    before = tree(tmp_path)
    code, _, err = run_pdem(["resume", latest, "--quiet", "--set", "run.max_overlap=1e-6"])
    assert code == 2, err
    assert "limit 1e-06" in err and "cannot be changed" not in err, err
    assert tree(tmp_path) == before
    # a larger one: the run goes on as before (the limit decides when a run stops, not how it moves)
    code, _, err = run_pdem(["resume", latest, "--quiet", "--set", "run.max_overlap=0.3"])
    assert code == 0, err
    assert compare(final_state(runs["full"]), final_state(out)) is None
    _, meta = read_checkpoint(out / "checkpoints" / "latest.h5")
    assert tomllib.loads(meta["deck"])["run"]["max_overlap"] == 0.3


def test_refused_resume_change_lists_max_overlap(runs, tmp_path, run_pdem):
    _, latest = copy_run(runs, tmp_path)
    code, _, err = run_pdem(["resume", latest, "--quiet", "--set", "materials.glass.friction=0.9"])
    assert code == 2, err
    assert "materials.glass.friction" in err and "run.max_overlap" in err, err
