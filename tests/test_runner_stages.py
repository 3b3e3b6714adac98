"""The runner's stages: resolved once before the run (``resolve_stages``), started through one public
method (``Runner.start_stage``), and their dt checked against the law's stability estimate by one
check whose error names the deck key that gives the dt, the value, the limit and the remedy."""

from __future__ import annotations

import numpy as np
import pytest
from decks import TINY_LATTICE_TWO_STAGES

from pdem.deck import load_deck
from pdem.deck.load import ResolvedDeck
from pdem.errors import InputError
from pdem.runner import Runner, StageSettings, resolve_stages
from pdem.sources import write_spheres_text

# the second stage: its own dt, snapshots at another cadence, frictionless grains, and a finer
# lattice inserted at its start (above the first one)
STAGED = TINY_LATTICE_TWO_STAGES.replace(
    'name = "rest"\n',
    'name = "rest"\ndt = 1e-6\n[stages.output]\nevery_steps = 5\n[stages.materials.glass]\nfriction = 0.0\n',
).replace(
    "[boundaries.floor]",
    '[[particles]]\nsource = "lattice"\nlattice = "sc"\nmaterial = "glass"\nradius = 0.1e-3\nstage = "rest"\n'
    'region = { type = "box", lo = [0.0, 0.0, 0.006], hi = [0.001, 0.001, 0.007] }\n[boundaries.floor]',
)


def _resolved(tmp_path, text=STAGED, sets=()):
    path = tmp_path / "deck.toml"
    path.write_text(text)
    return load_deck(path, list(sets))


def test_stages_resolved_once(tmp_path):
    resolved = _resolved(tmp_path)
    drop, rest = resolve_stages(resolved)
    assert isinstance(drop, StageSettings) and (drop.index, drop.name, rest.index, rest.name) == (
        0,
        "drop",
        1,
        "rest",
    )
    assert (drop.dt, drop.dt_key) == (2e-6, "run.dt") and (rest.dt, rest.dt_key) == (1e-6, "stages.rest.dt")
    assert drop.output.every_steps == 10 and rest.output.every_steps == 5
    assert drop.output == resolved.output_for("drop") and rest.output == resolved.output_for("rest")
    assert drop.materials["glass"]["friction"] == 0.5 and rest.materials["glass"]["friction"] == 0.0
    assert drop.sources == (0,) and rest.sources == (1,)
    assert drop.law_params == resolved.law_params and not drop.contact_given


def test_run_does_not_resolve_the_deck_again(tmp_path, monkeypatch):
    """The stages' settings are those resolved when the runner was made: the run never asks the
    deck for a stage's output settings again."""
    runner = Runner(_resolved(tmp_path), output=tmp_path / "out", progress=None, stdout=None)

    def refuse(self, stage):
        raise AssertionError(f"output_for({stage!r}) called during the run")

    monkeypatch.setattr(ResolvedDeck, "output_for", refuse)
    summary = runner.run()
    assert summary["completed"] and summary["steps"] == 40
    assert summary["particles"] == 64 + 125


def test_start_stage_makes_and_enters_the_stage(tmp_path):
    runner = Runner(_resolved(tmp_path), progress=None, dry=True)
    sim = runner.build()
    st = runner.start_stage(0)
    assert st.name == "drop" and sim.count_particles() == 64 and sim.dt == 2e-6
    assert sim.dt_critical > 2e-6
    st = runner.start_stage(1)  # the finer lattice, the stage's dt and friction
    assert st.name == "rest" and sim.count_particles() == 64 + 125 and sim.dt == 1e-6
    assert sim.materials[sim.materials.index("glass")].friction == 0.0


def test_start_stage_without_insertion(tmp_path):
    runner = Runner(_resolved(tmp_path), progress=None, dry=True)
    sim = runner.build()
    runner.start_stage(0)
    runner.start_stage(1, insert=False)
    assert sim.count_particles() == 64 and sim.dt == 1e-6


@pytest.mark.parametrize(
    "key, stage, source, radius",
    [("run.dt", "drop", "particles.0", "0.0005"), ("stages.rest.dt", "rest", "particles.1", "0.0001")],
)
def test_dt_above_the_estimate_before_the_particles_are_made(tmp_path, key, stage, source, radius):
    """Above the estimate for the largest grains of a source present in the stage: refused before
    any source makes its grains, naming the source that sets the limit."""
    runner = Runner(_resolved(tmp_path, sets=[f"{key}=1e-3"]), progress=None, dry=True)
    sim = runner.build()
    with pytest.raises(InputError) as info:
        runner.start_stage(0)
    msg = str(info.value)
    assert msg.startswith(f"{key}: dt = 0.001 s for stage '{stage}' exceeds the stability estimate"), msg
    assert f"largest grains source {source} makes (radius {radius} m: " in msg and "use dt ≤ " in msg, msg
    assert "run.force_dt = true" in msg, msg
    assert sim.count_particles() == 0  # nothing made


def test_later_source_does_not_limit_an_earlier_stage(tmp_path):
    """The finer grains come at the second stage: the first stage's dt is checked against the
    grains present in it only."""
    probe = Runner(_resolved(tmp_path), progress=None, dry=True)
    probe.build()
    probe.start_stage(0)
    coarse = probe.sim.dt_critical
    dt = 0.5 * coarse  # within the estimate of the 0.5 mm grains, above that of the 0.1 mm ones
    text = STAGED.replace('name = "drop"\n', f'name = "drop"\ndt = {dt!r}\n')
    runner = Runner(_resolved(tmp_path, text), progress=None, dry=True)
    runner.build()
    runner.start_stage(0)
    assert runner.sim.dt == dt


def test_stage_dt_above_the_estimate_once_its_particles_are_there(tmp_path):
    """A stage dt within the estimate for the grains present at the start but above it for the
    finer grains the stage inserts from a file (whose sizes are known only once read): refused when
    the stage starts, naming its key, the value and the limit for these particles."""
    probe = Runner(_resolved(tmp_path), progress=None, dry=True)
    probe.build()
    probe.start_stage(0)
    coarse = probe.sim.dt_critical
    dt = 0.5 * coarse  # within the estimate of the 0.5 mm grains, above that of the 0.1 mm ones
    write_spheres_text(
        tmp_path / "fine.txt", np.array([[0.0, 0.0, 0.006], [0.001, 0.0, 0.006]]), np.full(2, 1e-4)
    )
    lattice = STAGED[
        STAGED.index("[[particles]]", STAGED.index("[[particles]]") + 1) : STAGED.index("[boundaries")
    ]
    text = STAGED.replace(
        lattice, '[[particles]]\nsource = "file"\nmaterial = "glass"\npath = "fine.txt"\nstage = "rest"\n'
    )
    resolved = _resolved(tmp_path, text, sets=[f"stages.rest.dt={dt!r}"])
    runner = Runner(resolved, output=tmp_path / "out", progress=None, stdout=None)
    with pytest.raises(InputError) as info:
        runner.run()
    msg = str(info.value)
    assert msg.startswith(f"stages.rest.dt: dt = {dt:.4g} s for stage 'rest' exceeds the stability estimate ")
    assert "for these particles" in msg and "practice: 0.1–0.3 of it" in msg, msg
    assert "run.force_dt = true" in msg, msg
    limit = float(msg.split("use dt ≤ ")[1].split(" s")[0])
    assert limit < dt and limit == pytest.approx(coarse / 5, rel=1e-3)  # Rayleigh time ∝ radius


def test_force_dt_lets_the_stage_run(tmp_path):
    runner = Runner(
        _resolved(tmp_path, sets=["stages.rest.dt=1e-3", "run.force_dt=true"]), progress=None, dry=True
    )
    runner.build()
    runner.start_stage(0)
    runner.start_stage(1)
    assert runner.sim.dt == 1e-3
