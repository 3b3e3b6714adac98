"""The pdem command as users meet it: exit codes, messages without tracebacks, overwrite rule,
plugins and schema listings, and bitwise resume from a checkpoint."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pdem.cli import main
from pdem.io.checkpoint import read_checkpoint

SMALL = """\
title = "small pile"
[run]
gravity = [0.0, 0.0, -9.81]
dt = 2e-6
seed = 3
[contact]
law = "hertz_mindlin"
[materials.glass]
density = 2500.0
youngs_modulus = 5e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.5
[[particles]]
source = "random_fill"
material = "glass"
region = { type = "box", lo = [0.0, 0.0, 0.0], hi = [0.01, 0.01, 0.01] }
sizes = { type = "uniform", r_min = 0.45e-3, r_max = 0.55e-3 }
n = 250
velocity = [0.0, 0.0, -0.2]
[boundaries.box]
type = "box"
material = "glass"
lo = [0.0, 0.0, 0.0]
hi = [0.01, 0.01, 0.02]
[[stages]]
name = "drop"
[stages.end]
steps = 300
[[stages]]
name = "rest"
[stages.end]
steps = 300
[output]
formats = ["hdf5"]
every_steps = 200
series_every_steps = 50
"""


def write(tmp_path: Path, text: str, name: str = "deck.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# Each case: (description, text replacement (old, new) applied to SMALL or a whole text, expected fragments)
MALFORMED = [
    ("invalid TOML", ("[run]", "[run"), ["line"]),
    ("string for dt", ("dt = 2e-6", 'dt = "fast"'), ["run.dt"]),
    ("zero dt", ("dt = 2e-6", "dt = 0.0"), ["run.dt"]),
    ("negative dt", ("dt = 2e-6", "dt = -1e-6"), ["run.dt"]),
    ("negative radius", ("r_min = 0.45e-3", "r_min = -0.45e-3"), ["r_min"]),
    ("unknown law", ('law = "hertz_mindlin"', 'law = "hertz"'), ["contact.law", "hertz_mindlin"]),
    ("unknown boundary type", ('type = "box"\nmaterial', 'type = "boxx"\nmaterial'), ["boundaries.box.type"]),
    (
        "missing material",
        ('source = "random_fill"\nmaterial = "glass"', 'source = "random_fill"\nmaterial = "sand"'),
        ["sand"],
    ),
    ("misspelt key", ("density = 2500.0", "densty = 2500.0"), ["densty", "density"]),
    ("stage without end condition", ("[stages.end]\nsteps = 300\n[[stages]]", "[[stages]]"), ["end"]),
    ("duplicate stage names", ('name = "rest"', 'name = "drop"'), ["drop"]),
    ("restitution above one", ("restitution = 0.5", "restitution = 1.5"), ["restitution"]),
    ("Poisson ratio 0.5", ("poisson_ratio = 0.3", "poisson_ratio = 0.5"), ["poisson_ratio"]),
    (
        "gravity with two components",
        ("gravity = [0.0, 0.0, -9.81]", "gravity = [0.0, -9.81]"),
        ["run.gravity"],
    ),
    ("unknown output format", ('formats = ["hdf5"]', 'formats = ["netcdf"]'), ["netcdf"]),
    (
        "unknown output field",
        ("every_steps = 200", 'every_steps = 200\nfields = ["x", "colour"]'),
        ["colour"],
    ),
    ("both n and volume fraction", ("n = 250", "n = 250\nvolume_fraction = 0.1"), ["volume_fraction"]),
    (
        "unknown law parameter",
        ('law = "hertz_mindlin"', 'law = "hertz_mindlin"\nclamp_normall = true'),
        ["clamp_normall"],
    ),
    (
        "quantity of unknown boundary",
        ("steps = 300\n[[stages]]", 'quantity = "hopper.mass"\nabove = 1.0\n[[stages]]'),
        ["hopper"],
    ),
    (
        "unknown stage in boundary",
        ("hi = [0.01, 0.01, 0.02]", 'hi = [0.01, 0.01, 0.02]\nstages = ["fill"]'),
        ["fill"],
    ),
    ("box with lo above hi", ("hi = [0.01, 0.01, 0.02]", "hi = [0.01, 0.01, -0.02]"), ["boundaries.box"]),
    (
        "file source that does not exist",
        (
            'source = "random_fill"\nmaterial = "glass"\nregion',
            'source = "file"\npath = "nope.txt"\nmaterial = "glass"\nregion',
        ),
        ["nope.txt"],
    ),
]


@pytest.mark.parametrize("name, change, fragments", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_deck_exit_2_without_traceback(tmp_path, run_pdem, name, change, fragments):
    old, new = change
    assert old in SMALL, f"test case '{name}' does not apply"
    deck = write(tmp_path, SMALL.replace(old, new, 1))
    for cmd in (["check", deck], [deck, "--output", tmp_path / "out"]):
        code, _, err = run_pdem(cmd)
        assert code == 2, (name, err)
        assert err.startswith("pdem: error:"), err
        assert "Traceback" not in err
        for frag in fragments:
            assert frag in err, (name, frag, err)
        assert not (tmp_path / "out").exists(), "nothing may be written for an invalid deck"


def test_malformed_deck_real_process(tmp_path):
    """The installed console script: exit code 2, one message, no traceback."""
    deck = write(tmp_path, SMALL.replace("density = 2500.0", "densty = 2500.0"))
    proc = subprocess.run(
        [sys.executable, "-m", "pdem.cli", "check", str(deck)], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and "did you mean 'density'" in proc.stderr


def test_bad_set_override(tmp_path, run_pdem):
    deck = write(tmp_path, SMALL)
    code, _, err = run_pdem(["check", deck, "--set", "run.dtt=1e-6"])
    assert code == 2 and "dtt" in err
    code, _, err = run_pdem(["check", deck, "--set", "run.dt"])
    assert code == 2 and "--set" in err


def test_existing_output_not_overwritten(tmp_path, run_pdem):
    deck = write(tmp_path, SMALL)
    out = tmp_path / "out"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    code, _, err = run_pdem([deck, "--output", out, "--steps", "5", "--quiet"])
    assert code == 2 and "--overwrite" in err
    assert (out / "precious.txt").read_text() == "keep me"
    # --overwrite replaces only pdem's output: a folder pdem did not make is refused untouched
    code, _, err = run_pdem([deck, "--output", out, "--steps", "5", "--quiet", "--overwrite"])
    assert code == 2 and "not made by pdem" in err, err
    assert sorted(p.name for p in out.iterdir()) == ["precious.txt"]
    # in pdem's own output folder it replaces pdem's files and keeps the user's
    made = tmp_path / "made"
    assert run_pdem([deck, "--output", made, "--steps", "5", "--quiet"])[0] == 0
    (made / "precious.txt").write_text("keep me")
    code, _, err = run_pdem([deck, "--output", made, "--steps", "3", "--quiet", "--overwrite"])
    assert code == 0, err
    assert (made / "precious.txt").read_text() == "keep me"
    assert not (made / "checkpoints" / "step_0000000005.h5").exists()


def test_instability_exit_3(tmp_path, run_pdem):
    # the live step bound would stop this at step 1 (its own exit-3 test is in test_stiffness_bound):
    # switched off, the blow-up itself is caught
    text = SMALL.replace("dt = 2e-6", "dt = 6e-5\nforce_dt = true\nstiffness_limit = 0").replace(
        "velocity = [0.0, 0.0, -0.2]", "velocity = [0.0, 0.0, -3.0]"
    )
    deck = write(tmp_path, text)
    code, _, err = run_pdem([deck, "--output", tmp_path / "out", "--quiet"])
    assert code == 3, err
    assert "unstable" in err and "Traceback" not in err
    # what was written before the failure stays readable
    import h5py

    with h5py.File(tmp_path / "out" / "particles.h5", "r") as fh:
        assert len(fh["frames"]) >= 1


def test_plugins_and_schema(tmp_path, run_pdem):
    code, out, _ = run_pdem(["plugins"])
    assert code == 0
    for name in ("hertz_mindlin", "hopper", "box", "hdf5", "vtk"):
        assert name in out
    assert "(from pdem)" in out
    code, _, _ = run_pdem(["schema", "--output", tmp_path / "s.json"])
    schema = json.loads((tmp_path / "s.json").read_text())
    assert code == 0 and "properties" in schema and "materials" in schema["properties"]


def test_run_writes_outputs(tmp_path, run_pdem):
    deck = write(tmp_path, SMALL)
    out = tmp_path / "out"
    code, stdout, _ = run_pdem([deck, "--output", out, "--quiet"])
    assert code == 0
    for name in (
        "deck.resolved.toml",
        "particles.h5",
        "particles.xdmf",
        "walls.xdmf",
        "series_drop.csv",
        "series_rest.csv",
        "summary.json",
        "checkpoints/latest.h5",
    ):
        assert (out / name).exists(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 600 and summary["completed"]
    import tomllib

    resolved = tomllib.loads((out / "deck.resolved.toml").read_text())
    assert resolved["run"]["max_overlap"] == 0.25  # defaults are filled in


def test_resume_is_bitwise_identical(tmp_path, run_pdem):
    """N steps + checkpoint + resume + N steps == 2N steps, crossing a stage boundary."""
    deck = write(tmp_path, SMALL)
    full, part = tmp_path / "full", tmp_path / "part"
    assert run_pdem([deck, "--output", full, "--quiet"])[0] == 0
    assert run_pdem([deck, "--output", part, "--quiet", "--steps", "170"])[0] == 0
    code, _, err = run_pdem(
        ["resume", part / "checkpoints" / "latest.h5", "--output", tmp_path / "resumed", "--quiet"]
    )
    assert code == 0, err
    a, _ = read_checkpoint(full / "checkpoints" / "latest.h5")
    b, _ = read_checkpoint(tmp_path / "resumed" / "checkpoints" / "latest.h5")
    assert int(a["scalars/step"]) == int(b["scalars/step"]) == 600
    for key in a:
        if key.startswith(("particles/", "pairs/", "walls/")):
            assert np.array_equal(a[key], b[key]), key


def test_resume_may_change_the_dem_c_solver_settings_but_not_its_law(tmp_path, run_pdem):
    """A DEM-C run goes on from a checkpoint with a higher iteration cap and a tighter tolerance
    (numerics: LawParams.resumable), which the continued run uses; its cone (the friction law
    solved) is part of the scene and is refused, naming the key (exit 2)."""
    import json

    text = SMALL.replace('law = "hertz_mindlin"', 'law = "complementarity"\nmax_iterations = 20')
    deck = write(tmp_path, text.replace("dt = 2e-6", "dt = 1e-4").replace("steps = 300", "steps = 30"))
    part = tmp_path / "part"
    assert run_pdem([deck, "--output", part, "--quiet", "--steps", "20"])[0] == 0
    ckpt = part / "checkpoints" / "latest.h5"
    code, _, err = run_pdem(["resume", ckpt, "--quiet", "--set", 'contact.cone="relaxed"'])
    assert code == 2 and "contact.cone: cannot be changed on resume" in err, err
    code, _, err = run_pdem(["resume", ckpt, "--quiet", "--set", "contact.max_iterations=300",
                             "--set", "contact.tolerance=1e-9"])  # fmt: skip
    assert code == 0, err
    solver = json.loads((part / "summary.json").read_text())["solver"]
    assert solver["max_iterations"] == 300 and solver["tolerance"] == 1e-9
    assert solver["mean_iterations"] > 20  # the steps after the checkpoint ran past the old cap


def test_resume_needs_only_the_checkpoint(tmp_path, run_pdem):
    """The deck file may change or disappear: the checkpoint holds the resolved deck. A change of
    the scene asked for with --set is refused, naming the key (exit 2, nothing written)."""
    deck = write(tmp_path, SMALL)
    part = tmp_path / "part"
    assert run_pdem([deck, "--output", part, "--quiet", "--steps", "20"])[0] == 0
    deck.write_text(SMALL.replace("friction = 0.5", "friction = 0.4"))
    ckpt = part / "checkpoints" / "latest.h5"
    before = sorted(str(p) for p in tmp_path.rglob("*"))
    code, _, err = run_pdem(["resume", ckpt, "--quiet", "--set", "materials.glass.friction=0.4"])
    assert code == 2, err
    assert "materials.glass.friction: cannot be changed on resume" in err, err
    assert "(from --set materials.glass.friction=0.4)" in err and "Traceback" not in err
    assert sorted(str(p) for p in tmp_path.rglob("*")) == before
    deck.unlink()
    code, _, err = run_pdem(["resume", ckpt, "--quiet", "--steps", "40"])
    assert code == 0, err
    assert int(read_checkpoint(part / "checkpoints" / "latest.h5")[0]["scalars/step"]) == 40


def test_help_lists_every_command(capsys):
    from pdem.cli import SUBCOMMANDS

    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = capsys.readouterr().out
    missing = [c for c in SUBCOMMANDS if f"pdem {c}" not in " ".join(out.split())]
    assert not missing, missing
