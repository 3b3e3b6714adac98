"""Stage roles of boundaries (pdem.deck.stage_roles): a stage added on resume may not switch a
boundary off without the deck saying so, a resume may name it in the boundary's stage keys, the
triaxial cell shears on through ``later_shear_stages``, and a summary takes each value from the
rows of its own stage."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

import pdem
from pdem.boundaries.api import STAGE_COLUMN, BoundaryParams, merge_series, stage_rows
from pdem.boundaries.triaxial import TriaxialCell, TriaxialParams
from pdem.deck import stage_roles as sr
from pdem.deck.load import load_deck, validate_deck
from pdem.deck.resume import ResumePoint, resume_changes, resume_deck
from pdem.errors import DeckError, InputError

ROOT = Path(__file__).resolve().parents[1]
TRIAXIAL = ROOT / "tests" / "data" / "triaxial_small.toml"
MORE = ("stages.3.name=more", "stages.3.end.steps=100")
FINISHED = ResumePoint(stage_index=3, started=False, step=1600, time=0.0032)

WALL_DECK = """\
[run]
dt = 2e-6
[materials.glass]
youngs_modulus = 5e7
[[particles]]
source = "lattice"
lattice = "sc"
material = "glass"
radius = 1e-3
region = {{ type = "box", lo = [0.0, 0.0, 0.001], hi = [0.004, 0.004, 0.004] }}
[boundaries.floor]
type = "plane"
material = "glass"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
{floor_stages}
[boundaries.lid]
type = "plane"
material = "glass"
point = [0.0, 0.0, 0.01]
normal = [0.0, 0.0, -1.0]
stages = ["fill"]
[[stages]]
name = "fill"
[stages.end]
steps = 10
[[stages]]
name = "rest"
[stages.end]
steps = 10
"""


def _resumed(deck: Path, point: ResumePoint, *sets: str, tmp_path: Path):
    """(checkpoint's deck, continuation's deck), validated as a resume validates them but without
    its refusals, which :func:`_resume_path` goes through."""
    old = load_deck(deck)
    new = validate_deck(tomllib.loads(old.resolved_toml()), path=deck, base_dir=deck.parent, overrides=sets)
    return old, new


def _resume_path(deck: Path, point: ResumePoint, *sets: str, tmp_path: Path):
    """pdem's own resume path (resume_deck) from a checkpoint's metadata, without running anything."""
    old = load_deck(deck)
    meta = {"deck": old.resolved_toml(), "deck_path": str(deck)}
    return resume_deck(meta, tuple(sets), point, tmp_path / "latest.h5")


def test_triaxial_roles_per_stage():
    r = load_deck(TRIAXIAL, overrides=list(MORE))
    assert sr.roles(r, "cell") == ["mould", "consolidate", "shear", None]
    on = load_deck(TRIAXIAL, overrides=[*MORE, 'boundaries.cell.later_shear_stages=["more"]'])
    assert sr.roles(on, "cell") == ["mould", "consolidate", "shear", "shear"]
    off = load_deck(TRIAXIAL, overrides=[*MORE, 'boundaries.cell.off_stages=["more"]'])
    assert sr.roles(off, "cell") == ["mould", "consolidate", "shear", None]


def test_a_stage_added_to_a_finished_triaxial_is_refused_naming_the_keys(tmp_path):
    """The tester's resume (`--set stages.3.name=more …`, as a finished run's refusal suggests): the
    cell held the specimen in 'shear' and no key names 'more'. Refused at the cell, with both ways
    out spelled as --set options."""
    old, new = _resumed(TRIAXIAL, FINISHED, *MORE, tmp_path=tmp_path)
    assert sr.new_stage_indices(old, new) == [3]
    problems = sr.switch_off_problems(old, new)
    assert [loc for loc, _ in problems] == [("boundaries", "cell")]
    msg = problems[0][1]
    print(msg)
    assert "on in stage 'shear' (shear)" in msg and "switched off in stage 'more'" in msg
    assert """--set 'boundaries.cell.later_shear_stages=["more"]'""" in msg
    assert """--set 'boundaries.cell.off_stages=["more"]'""" in msg
    with pytest.raises(DeckError) as info:
        sr.check_new_stages(old, new, "resumed")
    assert isinstance(info.value, InputError) and info.value.exit_code == 2
    assert "boundaries.cell" in str(info.value)
    # pdem's resume path refuses it, and takes either remedy
    with pytest.raises(DeckError) as info:
        _resume_path(TRIAXIAL, FINISHED, *MORE, tmp_path=tmp_path)
    assert "boundaries.cell" in str(info.value) and "later_shear_stages" in str(info.value)
    for key in ("later_shear_stages", "off_stages"):
        _resume_path(TRIAXIAL, FINISHED, *MORE, f'boundaries.cell.{key}=["more"]', tmp_path=tmp_path)


@pytest.mark.parametrize("key", ["later_shear_stages", "off_stages"])
def test_naming_the_added_stage_is_a_change_a_resume_may_make(key):
    """The remedy keys change only what the cell does in the added stage: resume_changes refuses
    them as scene changes, stage_key_changes lets them through, and nothing is switched off silently
    any more."""
    old = load_deck(TRIAXIAL)
    new = load_deck(TRIAXIAL, overrides=[*MORE, f'boundaries.cell.{key}=["more"]'])
    raw = resume_changes(old.resolved_dict(), new.resolved_dict(), FINISHED)
    assert [loc for loc, _ in raw] == [("boundaries", "cell", key)]  # today's refusal
    assert sr.stage_key_changes(old, new, FINISHED, raw) == []
    assert sr.switch_off_problems(old, new) == []


@pytest.mark.parametrize(
    "override,stage",
    [("boundaries.cell.shear_stage=more", "shear"), ('boundaries.cell.off_stages=["shear", "more"]', "shear"),
     ('boundaries.cell.mould_stages=["consolidate"]', "settle")],
)  # fmt: skip
def test_a_stage_key_change_that_rewrites_a_stage_already_run_stays_refused(override, stage):
    old = load_deck(TRIAXIAL)
    new = load_deck(TRIAXIAL, overrides=[*MORE, override])
    raw = resume_changes(old.resolved_dict(), new.resolved_dict(), FINISHED)
    kept = sr.stage_key_changes(old, new, FINISHED, raw)
    assert len(kept) == 1, kept
    assert f"did in stage '{stage}', which has run" in kept[0][1]


def test_stage_keys_may_name_stages_still_to_come_mid_run():
    """Checkpoint inside 'consolidate': the shear stage has not started, so a resume may move the
    cell's role out of it (its roles in 'settle' and 'consolidate' stay)."""
    point = ResumePoint(stage_index=1, started=True, step=500, time=0.001)
    old = load_deck(TRIAXIAL)
    new = load_deck(TRIAXIAL, overrides=['boundaries.cell.off_stages=["shear"]'])
    raw = resume_changes(old.resolved_dict(), new.resolved_dict(), point)
    assert raw and sr.stage_key_changes(old, new, point, raw) == []


def _wall_deck(tmp_path: Path, floor_stages: str = "") -> Path:
    path = tmp_path / "walls.toml"
    path.write_text(WALL_DECK.format(floor_stages=floor_stages))
    return path


def test_plain_walls_added_stage(tmp_path):
    """The lid (stages = ["fill"]) was already off in 'rest', so a stage after 'rest' leaves it as
    it is; the floor on in every stage (no list) stays on; a floor listing its stages is refused,
    with the remedy `stages` (keep it) or `off_stages`."""
    point = ResumePoint(stage_index=2, started=False, step=20, time=4e-5)
    deck = _wall_deck(tmp_path)
    old, new = _resumed(deck, point, "stages.2.name=more", "stages.2.end.steps=5", tmp_path=tmp_path)
    assert sr.switch_off_problems(old, new) == []
    deck = _wall_deck(tmp_path, 'stages = ["fill", "rest"]')
    old, new = _resumed(deck, point, "stages.2.name=more", "stages.2.end.steps=5", tmp_path=tmp_path)
    problems = sr.switch_off_problems(old, new)
    assert [loc for loc, _ in problems] == [("boundaries", "floor")]
    assert """--set 'boundaries.floor.stages=["fill", "rest", "more"]'""" in problems[0][1]
    assert """--set 'boundaries.floor.off_stages=["more"]'""" in problems[0][1]


def test_a_fresh_deck_may_end_a_boundary_by_not_naming_a_stage(tmp_path):
    """In a deck its author wrote, a boundary listed in some stages is off in the others on purpose
    (the lid here): nothing is checked unless stages are new. Asked about every stage, the same
    function finds the lid, so the difference is in the stages checked, not in the rule."""
    deck = load_deck(_wall_deck(tmp_path))
    assert sr.new_stage_indices(deck, deck) == []
    found = sr.switched_off(deck, range(len(deck.deck.stages)))
    assert [(f.boundary, f.previous, f.stage) for f in found] == [("lid", "fill", "rest")]


def test_a_stage_named_both_on_and_off_is_a_deck_error(tmp_path):
    with pytest.raises(DeckError, match="both stages and off_stages"):
        load_deck(_wall_deck(tmp_path, 'stages = ["fill", "rest"]\noff_stages = ["rest"]'))
    with pytest.raises(DeckError, match="later_shear_stages"):
        load_deck(TRIAXIAL, overrides=['boundaries.cell.later_shear_stages=["shear"]'])
    with pytest.raises(DeckError, match="unknown stage 'mroe'"):
        load_deck(TRIAXIAL, overrides=[*MORE, 'boundaries.cell.off_stages=["mroe"]'])


def test_penetrometer_holds_in_later_stages():
    from pdem.boundaries.penetrometer import Penetrometer, PenetrometerParams

    p = PenetrometerParams(type="penetrometer", material="steel", penetration_stage="push", speed=0.01,
                           axis=(0.0, 0.0), max_depth=0.01)  # fmt: skip
    assert Penetrometer.stage_roles(p, ["fill", "push", "more"]) == [None, "push", "hold"]
    q = p.model_copy(update={"off_stages": ["more"]})
    assert Penetrometer.stage_roles(q, ["fill", "push", "more", "after"]) == [None, "push", None, None]


# ------------------------------------------------------------------------------ the triaxial cell
MAT = dict(density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3, friction=0.3)


@pytest.fixture(scope="module")
def packing(small_packing):
    return small_packing()


def _cell(packing, **extra):
    x, r = packing
    sim = pdem.Simulation()
    sim.add_material("glass", **MAT)
    sim.add_particles(x, r)
    top = float((x[:, 2] + r).max())
    cell = TriaxialCell("cell", TriaxialParams(
        type="triaxial", material="glass", base_center=(0, 0, 0), radius=3.5e-3, height=top + 1e-5,
        sigma3=2e4, strain_rate=2.0, consolidation_stage="consolidate", shear_stage="shear",
        **extra))  # fmt: skip
    sim.add_boundary(cell)
    sim.dt = 2e-6
    return sim, cell


def test_later_shear_stages_shear_on_with_the_same_strain_references(packing):
    """'shear' then 'more' (a later shear stage): the platen keeps its speed ε̇ H₀, H₀ and V₀ stay
    those of the start of 'shear', so the axial strain grows on at ε̇ (2/s × 40 steps × 2 µs per
    stage); the membrane stays on. A cell restored from the state at the end of 'shear' (a resume)
    takes the same references into 'more'."""
    sim, cell = _cell(packing, later_shear_stages=["more"])
    sim.set_stage("shear")
    sim.run(steps=40)
    h0, v0 = cell.h0, cell.v0
    eps_shear = cell.measurements(sim)["eps_a"]
    assert h0 is not None and v0 is not None
    assert eps_shear == pytest.approx(2.0 * 40 * 2e-6, rel=1e-6)
    saved = cell.state()
    sim.set_stage("more")
    assert cell.phase == "shear" and cell.active and (cell.h0, cell.v0) == (h0, v0)
    sim.run(steps=40)
    assert cell.measurements(sim)["eps_a"] == pytest.approx(2.0 * 80 * 2e-6, rel=1e-6)
    assert np.any(cell._applied[0] != 0.0)  # the membrane loads the grains
    # resumed at the end of 'shear' into 'more'
    sim2, cell2 = _cell(packing, later_shear_stages=["more"])
    cell2.restore(saved)
    sim2.set_stage("more")
    assert cell2.phase == "shear" and (cell2.h0, cell2.v0) == (h0, v0)


def test_off_stages_switch_the_cell_off(packing):
    sim, cell = _cell(packing, off_stages=["more"])
    sim.set_stage("shear")
    assert cell.active and sim.walls["cell.top"].active
    sim.set_stage("more")
    assert not cell.active and cell.phase == "off"
    assert not sim.walls["cell.top"].active and not sim.walls["cell.bottom"].active


def _rows(stage_rows_spec):
    """Series rows of the triaxial: (stage, eps_a, sigma1, sigma3) per row."""
    series: dict[str, list[dict[str, float]]] = {}
    for stage, ea, s1, s3 in stage_rows_spec:
        q = s1 - s3
        series.setdefault(stage, []).append({
            "time": 0.0, "cell.eps_a": ea, "cell.sigma1": s1, "cell.sigma3": s3, "cell.q": q,
            "cell.p": (s1 + 2 * s3) / 3, "cell.eps_v": 0.01 * ea,
        })  # fmt: skip
    return series


def _spec(after: tuple[float, float]) -> list[tuple[str, float, float, float]]:
    return [
        ("settle", 0.0, 1e3, math.nan),
        ("consolidate", 0.0, 1.5e4, 2e4),
        ("consolidate", 0.0, 1.99e4, 2e4),
        ("shear", 0.0, 1.99e4, 2e4),
        ("shear", 0.01, 4e4, 2e4),
        ("shear", 0.02, 5e4, 2e4),
        # after the shearing, the cell off and the platen free of the grains
        ("more", after[0], 0.0, 0.0),
        ("more", after[1], 0.0, 0.0),
    ]


@pytest.mark.parametrize("after", [(0.0, 0.0), (0.03, 0.04)], ids=["resumed", "same_run"])
def test_summary_takes_each_value_from_its_own_stage(after):
    """The consolidation's σ₁ is the last row of 'consolidate', not of whatever stage ran last; the
    peak and final strains and σ₃'s accuracy are the shearing's. The rows of 'more' (cell off) read
    eps_a = 0 after a resume (the strain reference is not carried into a stage the cell is off in)
    and go on counting in the same run. Without the stage column (the merged series as it was)
    they count as consolidation (σ₁ = 0: the case reported) or as shearing."""
    names = ["settle", "consolidate", "shear", "more"]
    spec = _spec(after)
    series = merge_series(_rows(spec), names)
    assert list(series[STAGE_COLUMN]) == [s[0] for s in spec]
    params = TriaxialParams(
        type="triaxial", material="glass", base_center=(0, 0, 0), radius=3.5e-3, height=0.01, sigma3=2e4,
        strain_rate=2.0, consolidation_stage="consolidate", shear_stage="shear", off_stages=["more"],
    )  # fmt: skip
    cell = TriaxialCell("cell", params)
    out = cell.summary(series)
    assert out["sigma1_end_of_consolidation"] == 1.99e4
    assert out["q_peak"] == 3e4 and out["eps_a_at_peak"] == 0.02
    assert out["eps_a_final"] == 0.02 and out["eps_v_final"] == pytest.approx(2e-4)
    assert out["sigma3_error_mean"] == 0.0
    blind = cell.summary({k: v for k, v in series.items() if k != STAGE_COLUMN})
    if after[0] == 0.0:
        assert blind["sigma1_end_of_consolidation"] == 0.0
    else:
        assert blind["eps_a_final"] == 0.04 and blind["sigma3_error_mean"] == pytest.approx(1 / 2)
    # shearing on through a later shear stage counts its rows
    on = TriaxialCell("cell", params.model_copy(update={"off_stages": None, "later_shear_stages": ["more"]}))
    assert on.summary(series)["eps_a_final"] == (0.02 if after[0] == 0.0 else 0.04)
    assert on.summary(series)["sigma1_end_of_consolidation"] == 1.99e4


def test_stage_rows_and_merge_series():
    series = merge_series({"b": [{"x": 2.0}], "a": [{"x": 1.0, "y": 5.0}]}, ["a", "b", "c"])
    assert list(series[STAGE_COLUMN]) == ["a", "b"]
    assert np.array_equal(series["x"], [1.0, 2.0]) and math.isnan(series["y"][1])
    assert list(stage_rows(series, "b", 2)) == [False, True]
    assert list(stage_rows(series, ["a", "b"], 2)) == [True, True]
    assert stage_rows({"x": np.zeros(2)}, "a", 2) is None
    assert stage_rows(series, "a", 3) is None


def test_shear_box_summary_leaves_out_stages_it_is_off_in():
    from pdem.boundaries.shear_box import ShearBox, ShearBoxParams

    params = ShearBoxParams(
        type="shear_box", material="steel", corner=(0, 0, 0), length=0.01, width=0.01, lower_height=0.005,
        upper_height=0.005, gap=1e-4, normal_stress=1e3, shear_speed=0.01, max_displacement=0.001,
        shear_stage="shear", stages=["shear"],
    )  # fmt: skip
    box = ShearBox("box", params)
    rows = []
    for k, stage in enumerate(["shear"] * 5 + ["more"] * 3):
        u = 1e-4 * (k + 1)
        ratio = 0.5 if stage == "shear" else 5.0  # an off box: nonsense loads
        rows.append((stage, {"time": float(k), "box.displacement": u, "box.ratio": ratio,
                             "box.tau": 500.0 * ratio, "box.dilation": 0.0, "box.error": 0.0,
                             "box.outside": 0.0}))  # fmt: skip
    by_stage: dict[str, list] = {}
    for stage, row in rows:
        by_stage.setdefault(stage, []).append(row)
    out = box.summary(merge_series(by_stage, ["shear", "more"]))
    assert out["peak_ratio"] == 0.5 and out["final_displacement"] == pytest.approx(5e-4)


def test_boundary_params_off_stages_default_is_left_out_of_resolved_decks():
    assert BoundaryParams(type="x").off_stages is None
    assert "off_stages" not in load_deck(TRIAXIAL).resolved_dict()["boundaries"]["cell"]


@pytest.mark.integration
def test_a_finished_triaxial_resumed_with_a_later_shear_stage(tmp_path):
    """End to end on a short triaxial_small: the finished run's checkpoint, resumed with a stage
    'more' added, is refused by the stage check (pdem's resume path, real checkpoint); named as a
    later shear stage (the continuation's deck validated as a resume validates it), the run goes on
    shearing: the axial strain continues from the end of 'shear' at the strain rate (the strain
    references carried through the checkpoint), and the grains stay as calm as they were."""
    import csv
    import tomllib

    from pdem.cli import main
    from pdem.deck.load import validate_deck
    from pdem.io.checkpoint import read_checkpoint
    from pdem.runner import Runner

    out = tmp_path / "full"
    sets = ["stages.settle.end.steps=100", "stages.consolidate.end.steps=200", "stages.shear.end.steps=100",
            "output.series_every_steps=25"]  # fmt: skip
    args = [a for s in sets for a in ("--set", s)]
    assert main([str(TRIAXIAL), "--output", str(out), "--quiet", *args]) == 0
    ck = out / "checkpoints" / "latest.h5"
    state, meta = read_checkpoint(ck)
    point = ResumePoint.from_checkpoint(state, meta)
    assert point.stage_index == 3
    add = ("stages.3.name=more", "stages.3.end.steps=100")
    with pytest.raises(DeckError):  # refused by pdem's resume path
        resume_deck(meta, add, point, ck)
    data = tomllib.loads(meta["deck"])
    old = validate_deck(data, path=Path(meta["deck_path"]), base_dir=TRIAXIAL.parent)
    new = validate_deck(data, path=Path(meta["deck_path"]), base_dir=TRIAXIAL.parent, overrides=add)
    assert [loc for loc, _ in sr.switch_off_problems(old, new)] == [("boundaries", "cell")]
    new = validate_deck(data, path=Path(meta["deck_path"]), base_dir=TRIAXIAL.parent,
                        overrides=(*add, 'boundaries.cell.later_shear_stages=["more"]'))  # fmt: skip
    assert sr.switch_off_problems(old, new) == []
    assert sr.stage_key_changes(old, new, point, resume_changes(old.resolved_dict(), new.resolved_dict(),
                                                                point)) == []  # fmt: skip
    cont = tmp_path / "cont"
    Runner(new, output=cont, resume=(state, meta), series_from=out, progress=None).run()

    def rows(path):
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(path.open())]

    shear, more = rows(cont / "series_shear.csv"), rows(cont / "series_more.csv")
    rate = 2.0  # strain_rate of the deck; H0 from the start of 'shear'
    assert shear[-1]["cell.eps_a"] == pytest.approx(rate * (shear[-1]["time"] - shear[0]["time"]), rel=1e-6)
    for r in more:
        assert r["cell.eps_a"] == pytest.approx(rate * (r["time"] - shear[0]["time"]), rel=1e-6)
    assert more[-1]["cell.eps_a"] > shear[-1]["cell.eps_a"]
    assert max(r["ke_trans"] for r in more) < 3.0 * max(r["ke_trans"] for r in shear)
