"""The limits of a deck against hostile input: nesting depth, packing paths that are not files, long
names, stage and output counts, the size of quoted input in messages, and values so large or small
that double precision overflows.

Every refusal must exit 2 with one pdem message (no traceback: called in-process, an unexpected
exception fails the test), bounded in length whatever the input's size, naming the key and the
remedy, and must leave nothing behind. docs/deck.md, "Limits", lists the limits.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from decks import TINY_LATTICE

from pdem.deck import validate_deck
from pdem.deck.schema import MAX_NAME_LENGTH, MAX_STAGES
from pdem.errors import DeckError, InputError, OutputError
from pdem.io.series import SeriesWriter
from pdem.sources.files import read_spheres

# 64 spheres on a simple cubic lattice above a floor, 20 steps
TINY = TINY_LATTICE

FILE_SOURCE = '[[particles]]\nsource = "file"\nmaterial = "glass"\npath = "{path}"\n'


class Hang(Exception):
    """A command ran longer than its time limit (e.g. blocked reading a FIFO)."""


def _alarm(signum, frame):
    raise Hang("pdem did not finish within 60 s")


def write_deck(directory: Path, text: str = TINY, name: str = "deck.toml") -> Path:
    path = directory / name
    path.write_text(text, encoding="utf-8")
    return path


def tree(directory: Path) -> list[str]:
    return sorted(str(p.relative_to(directory)) for p in directory.rglob("*"))


def refused(code: int, err: str, *fragments: str, limit: int = 2000) -> None:
    """Exit code 2, one pdem message of bounded length holding every fragment, no traceback."""
    assert code == 2, err[-3000:]
    assert err.startswith("pdem: error:"), err[:500]
    assert "Traceback" not in err and "RuntimeWarning" not in err, err[:3000]
    assert len(err) <= limit, f"{len(err)} characters of stderr: {err[:500]}…"
    for fragment in fragments:
        assert fragment in err, (fragment, err[:3000])


def check_refused(
    tmp_path: Path, run_pdem_guarded, text: str, *fragments: str, sets: tuple = (), limit=2000
) -> str:
    """``pdem check --deck-only`` and a real run refuse the deck alike, and the run leaves nothing."""
    deck = write_deck(tmp_path, text)
    sets_args = [a for s in sets for a in ("--set", s)]
    code, _, err = run_pdem_guarded(["check", "--deck-only", deck, *sets_args])
    refused(code, err, *fragments, limit=limit)
    before = tree(tmp_path)
    code, _, err_run = run_pdem_guarded([deck, "--output", tmp_path / "out", "--quiet", *sets_args])
    refused(code, err_run, *fragments, limit=limit)
    assert tree(tmp_path) == before and not (tmp_path / "out").exists()
    return err


# ------------------------------------------------------------------------------------ 1. nesting depth
def test_table_500_deep_refused(tmp_path, run_pdem_guarded):
    header = "[x" + "".join(f".a{i}" for i in range(500)) + "]\nk = 1\n"
    err = check_refused(tmp_path, run_pdem_guarded, TINY + header, "line 29", "64", "x.a0.a1")
    assert "a499" not in err  # the key path is quoted, truncated


def test_arrays_10000_deep_refused(tmp_path, run_pdem_guarded):
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY + "zz = " + "[" * 10_000 + "]" * 10_000 + "\n",
        "line 29",
        "nested more than 64 deep",
    )


def test_inline_tables_3000_deep_refused(tmp_path, run_pdem_guarded):
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY + "zz = " + "{a = " * 3000 + "1" + "}" * 3000 + "\n",
        "line 29",
        "nested more than 64 deep",
    )


def test_nesting_the_parser_accepts_is_refused_with_its_key_path(tmp_path, run_pdem_guarded):
    """80 levels (a 40-part header and a 40-part dotted key): parsed, then refused by the depth
    check, which names the deepest key path (its first and last parts)."""
    header = "[deep" + "".join(f".h{i}" for i in range(39)) + "]\n"
    key = ".".join(f"k{i}" for i in range(40)) + " = 1\n"
    err = check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY + header + key,
        "80 levels deep",
        "more than the 64",
        "deep.h0.h1",
        "k38.k39",
    )
    assert "h20" not in err  # the middle of the path is left out


def test_long_dotted_key_refused_before_parsing(tmp_path, run_pdem_guarded):
    """Python's TOML parser takes memory quadratic in a dotted key's length; refused before it."""
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY + "x." + ".".join(["a"] * 3000) + " = 1\n",
        "a dotted key of more than 64 parts",
        "line 29",
    )


def test_deep_override_values_and_paths_refused(tmp_path, run_pdem_guarded):
    deck = write_deck(tmp_path)
    for text, fragment in (
        ("run.dt=" + "[" * 10_000 + "]" * 10_000, "nested more than 64 deep"),
        ("run.dt={" + ".".join(["a"] * 3000) + " = 1}", "a dotted key of more than 64 parts"),
        (".".join(["a"] * 3000) + "=1", "3,000 levels deep"),
    ):
        code, _, err = run_pdem_guarded(["check", "--deck-only", deck, "--set", text])
        refused(code, err, fragment)


def test_deep_dict_through_the_api(tmp_path):
    data: dict = {}
    node = data
    for i in range(2000):
        node[f"a{i}"] = {}
        node = node[f"a{i}"]
    with pytest.raises(DeckError, match="2,000 levels deep") as info:
        validate_deck(data, base_dir=tmp_path)
    assert len(str(info.value)) < 1000


def test_deep_arrays_in_a_fresh_process(tmp_path):
    """The refusal does not depend on the stack pytest leaves: a new interpreter, the real command."""
    deck = write_deck(tmp_path, TINY + "zz = " + "[" * 10_000 + "]" * 10_000 + "\n")
    r = subprocess.run(
        [sys.executable, "-m", "pdem", "check", "--deck-only", str(deck)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr and "nested more than 64" in r.stderr, r.stderr


def test_integers_outside_the_toml_range(tmp_path, run_pdem_guarded):
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY.replace("steps = 20", "steps = " + "9" * 400),
        "stages.0.end.steps",
        "about 400 digits",
        "64-bit",
    )
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY.replace("steps = 20", "steps = " + "9" * 5000),
        "more than 4,300 digits",
        "64-bit",
    )


# ----------------------------------------------------------------- 2. packing paths that are not files
def _special(kind: str, tmp_path: Path) -> str:
    if kind == "symlink loop":
        os.symlink("loop", tmp_path / "loop")
        return "loop"
    if kind == "dev zero":
        return "/dev/zero"
    if kind == "fifo":
        os.mkfifo(tmp_path / "pipe")
        return "pipe"
    if kind == "directory":
        (tmp_path / "folder").mkdir()
        return "folder"
    if kind == "dangling link":
        os.symlink("nowhere.txt", tmp_path / "link.txt")
        return "link.txt"
    raise AssertionError(kind)


SPECIAL = {
    "symlink loop": "symbolic-link loop",
    "dev zero": "a character device, not a regular file",
    "fifo": "a named pipe (FIFO), not a regular file",
    "directory": "a directory, not a regular file",
    "dangling link": "is a symbolic link to 'nowhere.txt', which does not exist",
}


@pytest.mark.parametrize("kind", list(SPECIAL))
def test_packing_path_that_is_not_a_file(tmp_path, run_pdem_guarded, kind):
    path = _special(kind, tmp_path)
    err = check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY + FILE_SOURCE.format(path=path),
        "particles.1.path",
        SPECIAL[kind],
        "give a packing file",
    )
    assert "does not exist" not in err or kind == "dangling link"


@pytest.mark.parametrize("kind", ["symlink loop", "dev zero", "fifo", "directory"])
def test_read_spheres_names_what_the_path_is(tmp_path, kind):
    path = _special(kind, tmp_path)
    full = path if path.startswith("/") else tmp_path / path
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(30)
    try:
        with pytest.raises(InputError, match="not a regular file|symbolic-link loop"):
            read_spheres(full)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def test_packing_path_too_long_for_the_file_system(tmp_path, run_pdem_guarded):
    name = "p" * 300 + ".txt"
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY + FILE_SOURCE.format(path=name),
        "particles.1.path",
        "too long for the file system",
        "(304 characters)",
    )


# -------------------------------------------------------------------------------- 3. names in file names
def test_stage_name_of_300_characters_refused(tmp_path, run_pdem_guarded):
    name = "s" * 300
    err = check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY.replace('name = "drop"', f'name = "{name}"'),
        "stages.0.name",
        "300 characters long",
        f"more than the {MAX_NAME_LENGTH}",
        "series_<stage>.csv",
    )
    assert name not in err  # quoted, not written out


def test_boundary_and_material_names_limited(tmp_path, run_pdem_guarded):
    long = "b" * 300
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY.replace("[boundaries.floor]", f"[boundaries.{long}]"),
        "boundaries.",
        "boundary name",
        "300 characters long",
        "<boundary>.<stage>.csv",
    )
    text = TINY.replace("[materials.glass]", f"[materials.{'g' * 300}]").replace('"glass"', f'"{"g" * 300}"')
    check_refused(tmp_path, run_pdem_guarded, text, "material name", "300 characters long")
    text = TINY.replace("[materials.glass]", '[materials."gl\\nass"]').replace('"glass"', '"gl\\nass"')
    check_refused(tmp_path, run_pdem_guarded, text, "control characters", "gl\\nass")


def test_names_at_the_limit_run_and_name_their_files(tmp_path, run_pdem_guarded):
    stage, wall = "s" * MAX_NAME_LENGTH, "w" * MAX_NAME_LENGTH
    text = TINY.replace('name = "drop"', f'name = "{stage}"').replace(
        "[boundaries.floor]", f"[boundaries.{wall}]"
    )
    text = text.replace("[output]", f'[output]\nthermo_every = 10\nthermo = ["step", "{wall}.fz"]')
    deck = write_deck(tmp_path, text)
    code, _, err = run_pdem_guarded([deck, "--output", tmp_path / "out", "--quiet"])
    assert code == 0, err
    assert (tmp_path / "out" / f"series_{stage}.csv").is_file()


def test_series_writer_refuses_a_name_the_file_system_refuses(tmp_path):
    with pytest.raises(OutputError, match="file system refuses this path") as info:
        SeriesWriter(tmp_path / ("series_" + "s" * 300 + ".csv"), ["step"])
    assert len(str(info.value)) < 600


# --------------------------------------------------------------------------- 4. counts that multiply output
def _stages(n: int) -> str:
    head = TINY.split("[[stages]]")[0]
    return head + "".join(f'[[stages]]\nname = "s{i}"\n[stages.end]\nsteps = 1\n' for i in range(n))


def test_stage_count_limited(tmp_path, run_pdem_guarded):
    check_refused(
        tmp_path,
        run_pdem_guarded,
        _stages(MAX_STAGES + 1),
        "stages: 1,001 stages",
        f"more than the {MAX_STAGES:,}",
    )
    code, _, err = run_pdem_guarded(
        ["check", "--deck-only", write_deck(tmp_path, _stages(MAX_STAGES), "ok.toml")]
    )
    assert code == 0, err


@pytest.mark.integration
def test_boundary_count_limited(tmp_path, run_pdem_guarded):
    extra = "".join(
        f'[boundaries.w{i}]\ntype = "plane"\nmaterial = "glass"\npoint = [0, 0, -{i + 1}]\n'
        "normal = [0, 0, 1]\n"
        for i in range(256)
    )
    check_refused(tmp_path, run_pdem_guarded, TINY + extra, "boundaries: 257 boundaries", "more than the 256")


def test_thermo_columns_limited(tmp_path, run_pdem_guarded):
    columns = ", ".join(['"step"'] * 101)
    text = TINY.replace("[output]", f"[output]\nthermo_every = 10\nthermo = [{columns}]")
    check_refused(
        tmp_path, run_pdem_guarded, text, "output.thermo", "101 thermo columns", "more than the 100"
    )
    text = TINY.replace("[output]", '[output]\nthermo_every = 10\nthermo = ["step", "ke", "step"]')
    check_refused(tmp_path, run_pdem_guarded, text, "output.thermo", "more than once: 'step'")


def test_output_of_a_stage_limited(tmp_path, run_pdem_guarded):
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY,
        "output.every_steps",
        "1,000,000,000 snapshots",
        "more than the 100,000",
        "raise output.every_steps",
        sets=("stages.0.end.steps=1000000000", "output.every_steps=1", "output.series_every_steps=1000"),
    )
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY,
        "stages.0.output.every_time",
        "snapshots",
        sets=("stages.0.end={time = 1.0}", "stages.0.output={every_time = 1e-300}"),
    )
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY,
        "output.checkpoint_every_steps",
        "checkpoints",
        sets=(
            "stages.0.end.steps=100000000",
            "output.checkpoint_every_steps=1",
            "output.every_steps=100000",
            "output.series_every_steps=100000",
        ),
    )
    # a stage that may end earlier is not counted: its length is not known before the run
    deck = write_deck(tmp_path, TINY, "open.toml")
    sets = ("stages.0.end.steps=1000000000", "stages.0.end.kinetic_energy_below=1e-9", "output.every_steps=1")
    code, _, err = run_pdem_guarded(["check", "--deck-only", deck, *[a for s in sets for a in ("--set", s)]])
    assert code == 0, err


def test_array_entries_limited(tmp_path, run_pdem_guarded):
    text = TINY.replace("[output]", "[output]\nformats = [" + ", ".join(['"x"'] * 100_001) + "]")
    check_refused(
        tmp_path, run_pdem_guarded, text, "output.formats", "100,001 entries", "more than the 100,000"
    )


# ------------------------------------------------------------------------ 5. bounded quotes of bad input
def test_many_problems_listed_up_to_a_limit(tmp_path, run_pdem_guarded):
    text = TINY.replace("[output]", "[output]\nformats = [" + ", ".join(['"x"'] * 5000) + "]")
    err = check_refused(
        tmp_path, run_pdem_guarded, text, "unknown output format 'x'", "more problems", limit=20_000
    )
    assert err.count("\n") <= 105


def test_huge_key_value_and_override_are_quoted_briefly(tmp_path, run_pdem_guarded):
    marker = "END-OF-THE-HUGE-INPUT"
    huge = "k" * 2_000_000 + marker
    check_refused(
        tmp_path,
        run_pdem_guarded,
        TINY.replace("[run]", f"[run]\n{huge} = 1"),
        "run.",
        "unknown key",
        "characters)",
    )
    text = TINY.replace('material = "glass"\nradius', f'material = "{huge}"\nradius')
    check_refused(tmp_path, run_pdem_guarded, text, "particles.0.material", "unknown material", "characters)")
    deck = write_deck(tmp_path)
    for text in (
        f"run.dt=[{huge}",
        f"run.{huge}=1",
        f"stages.{huge}.end.steps=1",
        f'contact.law="{huge}"',
        f'title="{huge}"',
    ):
        code, _, err = run_pdem_guarded(["check", "--deck-only", deck, "--set", text])
        refused(code, err, "characters)")
        assert marker not in err


def _packing_case(tmp_path: Path, content: bytes, run_pdem_guarded) -> str:
    (tmp_path / "pack.txt").write_bytes(content)
    deck = write_deck(tmp_path, TINY + FILE_SOURCE.format(path="pack.txt"))
    code, _, err = run_pdem_guarded(["check", deck])  # the scene check reads the packing file
    refused(code, err, "pack.txt", limit=600)
    before = tree(tmp_path)
    code, _, err_run = run_pdem_guarded([deck, "--output", tmp_path / "out", "--quiet"])
    refused(code, err_run, "pack.txt", limit=600)
    assert tree(tmp_path) == before
    return err


def test_packing_line_of_20_mb(tmp_path, run_pdem_guarded):
    err = _packing_case(
        tmp_path, b"x y z diameter\n0.01 0 0.002 " + b"1" * 20_000_000 + b"\n", run_pdem_guarded
    )
    assert "line 2 is longer than 10,000 characters" in err


def test_packing_token_quoted_briefly(tmp_path, run_pdem_guarded):
    err = _packing_case(tmp_path, b"x y z diameter\n0.01 0 0.002 " + b"7" * 5000 + b"a\n", run_pdem_guarded)
    assert "cannot read '777" in err and "(5,001 characters)" in err


def test_system_file_as_packing_is_named_not_printed(tmp_path, run_pdem_guarded):
    secret = "root:x:0:0:root:/root:/bin/bash" + "-" * 100 + "SECRET-AFTER-80-CHARACTERS"
    err = _packing_case(
        tmp_path, (secret + "\ndaemon:x:1:1::/usr/sbin:/usr/sbin/nologin\n").encode(), run_pdem_guarded
    )
    assert "is not a packing file" in err and "root:x:0:0" in err and "SECRET" not in err


def test_binary_file_as_packing(tmp_path, run_pdem_guarded):
    err = _packing_case(tmp_path, bytes(range(256)) * 1000, run_pdem_guarded)
    assert "binary data" in err


# ------------------------------------------------------------------- 6. values that overflow double precision
@pytest.mark.parametrize(
    "setting, key",
    [
        ("particles.0.radius=1e-300", "particles.0.radius"),
        ("particles.0.radius=1e300", "particles.0.radius"),
        ("materials.glass.density=1e308", "materials.glass.density"),
        ("materials.glass.density=1e-300", "materials.glass.density"),
        ("materials.glass.youngs_modulus=1e300", "materials.glass.youngs_modulus"),
        ("materials.glass.friction=1e308", "materials.glass.friction"),
        ("particles.0.velocity=[1e200, 0, 0]", "particles.0.velocity.0"),
        ("run.gravity=[0, 0, -1e308]", "run.gravity.2"),
        ("boundaries.floor.point=[0, 0, 1e308]", "boundaries.floor.point.2"),
        ("boundaries.floor.normal=[0, 0, 1e300]", "boundaries.floor.normal.2"),
    ],
)
def test_impossible_values_refused_with_the_key(tmp_path, run_pdem_guarded, setting, key):
    deck = write_deck(tmp_path)
    before = tree(tmp_path)
    run = [deck, "--output", tmp_path / "out", "--quiet", "--set", "run.force_dt=true"]
    for args in (["check", deck], run):
        code, _, err = run_pdem_guarded([*args, "--set", setting])
        refused(code, err, key)
    assert tree(tmp_path) == before


def test_impossible_values_in_a_packing_file(tmp_path, run_pdem_guarded):
    err = _packing_case(tmp_path, b"x y z diameter\n0.01 0 0.002 2e-300\n", run_pdem_guarded)
    assert "line 2" in err and "outside [1e-10, 1e+10] m" in err
    err = _packing_case(
        tmp_path, b"x y z diameter vx vy vz\n0.01 0 0.002 0.001 1e200 0 0\n", run_pdem_guarded
    )
    assert "line 2" in err and "velocity component" in err


def test_values_at_the_limits_run_without_warnings(tmp_path, run_pdem_guarded):
    """Just inside the limits a short run ends with pdem's own verdict (here: it runs, or the step is
    too large for such stiff grains), and no raw numpy warning."""
    deck = write_deck(tmp_path)
    for setting in (
        "materials.glass.friction=1e100",
        "boundaries.floor.point=[0, 0, -1e99]",
        "materials.glass.density=1e20",
    ):
        code, _, err = run_pdem_guarded(
            [
                deck,
                "--output",
                tmp_path / f"out{len(setting)}",
                "--quiet",
                "--set",
                "stages.0.end.steps=5",
                "--set",
                setting,
            ],
        )
        assert code == 0 and "Traceback" not in err, (setting, err)
    sets = ("stages.0.end.steps=5", "materials.glass.youngs_modulus=1e100", "run.force_dt=true")
    args = [deck, "--output", tmp_path / "stiff", "--quiet", *[a for s in sets for a in ("--set", s)]]
    code, _, err = run_pdem_guarded(args)
    assert code == 3 and "Traceback" not in err, err
