"""The deck layer: a full deck loads and round-trips; malformed decks report every problem at once,
each with its exact key path and a message naming the bad value and what is allowed."""

from __future__ import annotations

import copy
import dataclasses
import json
import re
import tomllib
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from pdem.deck import Deck, deck_json_schema, load_deck, parse_override, validate_deck
from pdem.deck.toml_writer import dumps
from pdem.errors import DeckError, InputError
from pdem.materials import Material

ROOT = Path(__file__).resolve().parent.parent

FULL = """\
title = "Conical hopper discharge"

[run]
dt = 1e-5
force_dt = false
gravity = [0, 0, -9.81]
skin = 1e-4
max_overlap = 0.25
seed = 3

[contact]
law = "hertz_mindlin"
clamp_normal = true

[materials.glass]
density = 2500
youngs_modulus = 1e7
poisson_ratio = 0.3
restitution = 0.1
friction = 0.3
rolling_friction = 0.0

[materials.steel]
density = 7800

[[material_pairs]]
materials = ["glass", "steel"]
friction = 0.4

[[particles]]
source = "random_fill"
material = "glass"
stage = "fill"
motion = "free"
velocity = [0, 0, 0]
region = { type = "cylinder", base_center = [0, 0, 0.06], radius = 0.04, height = 0.1 }
sizes = { type = "uniform", r_min = 0.9e-3, r_max = 1.1e-3 }
n = 5000

[[particles]]
source = "lattice"
material = "steel"
motion = "fixed"
lattice = "hex2d"
radius = 1e-3
n_cols = 10
n_rows = 3

[[particles]]
source = "file"
material = "glass"
path = "packing.txt"

[[particles]]
source = "pluviate"
material = "glass"
region = { type = "box", lo = [0, 0, 0], hi = [0.02, 0.02, 0.02] }
sizes = { type = "table", radii = [1e-3, 1.5e-3], mass_fractions = [0.4, 0.6] }
n = 200
fill_fraction = 0.2

[boundaries.cone]
type = "hopper"
material = "steel"
orifice_center = [0, 0, 0.05]
orifice_diameter = 0.012
half_angle_deg = 30
top_diameter = 0.09
barrel_height = 0.1
open_at_stage = "discharge"
outflow_depth = 0.02

[boundaries.floor]
type = "plane"
material = "steel"
point = [0, 0, 0]
normal = [0, 0, 1]
stages = ["fill"]
motion = { type = "constant_velocity", velocity = [0, 0, 0.1] }

[[stages]]
name = "fill"
[stages.end]
kinetic_energy_below = 1e-7
max_time = 2.0

[[stages]]
name = "discharge"
dt = 2e-5
[stages.end]
quantity = "cone.discharged_mass"
above = 0.05
max_time = 5.0
[stages.output]
every_time = 0.01

[output]
directory = "out/hopper"
formats = ["hdf5", "vtk"]
every_steps = 500
fields = ["x", "v", "r", "id"]
series_every_steps = 50
checkpoint_every_steps = 100000
"""


@pytest.fixture
def deck_dir(tmp_path: Path) -> Path:
    (tmp_path / "packing.txt").write_text("x y z diameter\n0 0 0.01 0.002\n0.01 0 0.01 0.002\n")
    (tmp_path / "hopper.toml").write_text(FULL)
    return tmp_path


@pytest.fixture
def base() -> dict:
    return tomllib.loads(FULL)


def problems_of(deck_dir: Path, data: dict | None = None, text: str | None = None,
                overrides: tuple[str, ...] = ()) -> list[tuple[str, str]]:
    """The problems of a deck given as data (validated as if it were deck_dir/deck.toml) or text."""
    path = deck_dir / "deck.toml"
    with pytest.raises(DeckError) as info:
        if text is not None:
            path.write_text(text)
            load_deck(path, overrides)
        else:
            validate_deck(data, path=path, overrides=overrides)
    err = info.value
    lines = str(err).splitlines()
    assert len(lines) == len(err.problems) + 1, "one line per problem after the header"
    return err.problems


def expect(problems: list[tuple[str, str]], path: str, *fragments: str) -> str:
    """The message of the problem at exactly ``path`` that contains every fragment."""
    for p, msg in problems:
        if p == path and all(f in msg for f in fragments):
            return msg
    listing = "\n".join(f"  {p}: {m}" for p, m in problems)
    raise AssertionError(f"no problem at {path!r} containing {fragments}; got:\n{listing}")


# ------------------------------------------------------------------------------------------- valid


def test_full_deck_loads(deck_dir):
    r = load_deck(deck_dir / "hopper.toml")
    d = r.deck
    assert d.title == "Conical hopper discharge"
    assert d.run.dt == 1e-5 and d.run.gravity == (0.0, 0.0, -9.81) and d.run.seed == 3
    assert d.materials["glass"].density == 2500.0
    assert d.materials["steel"].youngs_modulus == Material.youngs_modulus  # default from Material
    assert d.material_pairs[0].values() == {"friction": 0.4}
    assert [p.source for p in d.particles] == ["random_fill", "lattice", "file", "pluviate"]
    assert d.particles[1].origin == (0.0, 0.0, 0.0) and d.particles[1].plane == "xz"  # hex2d defaults
    assert d.particles[2].path == str((deck_dir / "packing.txt").resolve())
    assert r.law_params.clamp_normal is True
    assert type(r.law_params).__name__ == "HertzMindlinParams"
    assert list(r.boundaries) == ["cone", "floor"]
    assert r.boundaries["cone"].orifice_diameter == 0.012
    assert r.boundaries["floor"].stages == ["fill"]
    assert r.base_dir == deck_dir.resolve()
    assert r.stage("discharge").end.above == 0.05
    # every_time in a stage replaces the section's every_steps; other keys follow [output]
    out = r.output_for("discharge")
    assert out.every_time == 0.01 and out.every_steps is None and out.series_every_steps == 50
    assert r.output_for(0).every_steps == 500
    law = r.make_law()
    assert law.params.clamp_normal is True
    assert set(r.make_boundaries()) == {"cone", "floor"}


def test_resolved_toml_round_trips(deck_dir):
    r = load_deck(deck_dir / "hopper.toml")
    text = r.resolved_toml()
    data = tomllib.loads(text)  # valid TOML
    assert data["contact"] == {"law": "hertz_mindlin", "parameterisation": "material", "clamp_normal": True,
                               "limit_damping": False, "tangential": "linear_history"}  # fmt: skip
    assert data["materials"]["steel"]["poisson_ratio"] == 0.3  # defaults filled in
    assert data["boundaries"]["cone"]["omega"] == [0.0, 0.0, 0.0]
    assert data["stages"][0]["end"]["check_every"] == 100
    elsewhere = deck_dir / "sub"
    elsewhere.mkdir()
    (elsewhere / "resolved.toml").write_text(text)  # file paths were made absolute
    r2 = load_deck(elsewhere / "resolved.toml")
    assert r2.deck == r.deck
    assert r2.law_params == r.law_params
    assert r2.boundaries == r.boundaries
    assert r2.resolved_dict() == r.resolved_dict()


def test_minimal_deck_gets_defaults(deck_dir):
    text = '[materials.glass]\n\n[[stages]]\nname = "settle"\nend = { steps = 10 }\n'
    (deck_dir / "tiny.toml").write_text(text)
    r = load_deck(deck_dir / "tiny.toml")
    d = r.deck
    assert d.contact.law == "hertz_mindlin" and r.law_params.parameterisation == "material"
    assert d.run.dt is None and d.run.skin is None and d.run.max_overlap == 0.25
    assert d.output.directory == "out/tiny"
    assert d.output.every_steps == 1000 and d.output.formats == ["hdf5"]
    assert d.output.fields == ["x", "v", "w", "r", "material", "f", "contacts", "id"]
    assert d.particles == [] and d.boundaries == {}
    r2 = validate_deck(tomllib.loads(r.resolved_toml()), path=deck_dir / "tiny.toml")
    assert r2.deck == d


def test_overrides_apply(deck_dir):
    r = load_deck(deck_dir / "hopper.toml", [
        "run.dt=2e-6", "stages.fill.end.time=0.1", "stages.1.end.above = 0.02", 'contact.law="hertz_mindlin"',
        "run.gravity=[0, 0, -1]", "materials.glass.friction=0.6", "contact.parameterisation=material",
        "output.every_steps=20", "stages.discharge.output.series_every_steps=7"])
    d = r.deck
    assert d.run.dt == 2e-6 and d.run.gravity == (0.0, 0.0, -1.0)
    assert d.stages[0].end.time == 0.1 and d.stages[1].end.above == 0.02
    assert d.materials["glass"].friction == 0.6
    assert d.output.every_steps == 20 and r.output_for("discharge").series_every_steps == 7
    assert r.overrides[0] == "run.dt=2e-6"
    assert "# --set run.dt=2e-6" in r.resolved_toml()


def test_parse_override():
    assert parse_override("run.dt=1e-5") == (["run", "dt"], 1e-5)
    quoted = parse_override('materials."glass beads".density = 2400')
    assert quoted == (["materials", "glass beads", "density"], 2400)
    assert parse_override("contact.law=hertz_mindlin") == (["contact", "law"], "hertz_mindlin")
    assert parse_override("output.formats=['hdf5']") == (["output", "formats"], ["hdf5"])


def test_toml_writer_round_trips_awkward_values():
    data = {"a": 'quote " back \\ tab\t nl\n é \x7f', "weird key": {"x.y": [1, 2.5, -0.0, 1e300]},
            "t": {"inner": {"type": "box", "lo": [0.0, 0.0, 0.0]}, "flag": False},
            "arr": [{"name": "s", "end": {"steps": 1}}], "empty": [], "nested": {"deep": {"k": 1}}}
    assert tomllib.loads(dumps(data)) == data


def test_material_keys_match_material_dataclass():
    fields = {f.name for f in dataclasses.fields(Material)} - {"name"}
    assert set(Deck.model_fields["materials"].annotation.__args__[1].model_fields) == fields


# ------------------------------------------------------------------------------------------- malformed


def test_invalid_toml_syntax(deck_dir):
    probs = problems_of(deck_dir, text='[run]\ndt = 1e-5\ngravity = [0, 0, -9.81\nseed = 1\n')
    assert len(probs) == 1
    expect(probs, "", "invalid TOML at line", "column")


def test_missing_deck_file(tmp_path):
    with pytest.raises(DeckError, match="does not exist"):
        load_deck(tmp_path / "nope.toml")


def test_wrong_type_string_for_dt(deck_dir, base):
    base["run"]["dt"] = "1e-5"
    expect(problems_of(deck_dir, base), "run.dt", "expected a number", "'1e-5'")


def test_wrong_type_float_for_int_and_string_for_bool(deck_dir, base):
    base["run"]["seed"] = 1.5
    base["run"]["force_dt"] = "yes"
    probs = problems_of(deck_dir, base)
    expect(probs, "run.seed", "expected an integer", "1.5")
    expect(probs, "run.force_dt", "expected true or false", "'yes'")


def test_negative_radius_in_sizes(deck_dir, base):
    base["particles"][0]["sizes"] = {"type": "single", "radius": -1e-3}
    expect(problems_of(deck_dir, base), "particles.0.sizes.radius", "must be > 0", "-0.001")


@pytest.mark.parametrize("dt", [0, -1e-5])
def test_zero_and_negative_dt(deck_dir, base, dt):
    base["run"]["dt"] = dt
    expect(problems_of(deck_dir, base), "run.dt", "must be > 0", f"got {dt}")


def test_stage_dt_must_be_positive(deck_dir, base):
    base["stages"][1]["dt"] = 0.0
    expect(problems_of(deck_dir, base), "stages.1.dt", "must be > 0")


def test_unknown_law_lists_installed(deck_dir, base):
    base["contact"]["law"] = "hertz"
    expect(problems_of(deck_dir, base), "contact.law", "unknown contact law 'hertz'", "installed:",
           "'hertz_mindlin'")


def test_unknown_boundary_type(deck_dir, base):
    base["boundaries"]["cone"]["type"] = "hoper"
    expect(problems_of(deck_dir, base), "boundaries.cone.type", "unknown boundary type 'hoper'",
           "did you mean 'hopper'?", "'plane'")


def test_missing_material_referenced_by_particles(deck_dir, base):
    base["particles"][0]["material"] = "sand"
    base["boundaries"]["cone"]["material"] = "stel"
    base["material_pairs"][0]["materials"] = ["glass", "iron"]
    probs = problems_of(deck_dir, base)
    expect(probs, "particles.0.material", "unknown material 'sand'", "defined materials: 'glass', 'steel'")
    expect(probs, "boundaries.cone.material", "unknown material 'stel'", "did you mean 'steel'?")
    expect(probs, "material_pairs.0.materials.1", "unknown material 'iron'")


def test_misspelt_key_suggests(deck_dir):
    probs = problems_of(deck_dir, text=FULL.replace("density = 2500", "densty = 2500"))
    msg = expect(probs, "materials.glass.densty")
    assert msg == "unknown key 'densty' in materials.glass; did you mean 'density'?"


def test_unknown_top_level_and_source_keys(deck_dir, base):
    base["outptu"] = {}
    base["particles"][0]["volume_fractoin"] = 0.3
    probs = problems_of(deck_dir, base)
    expect(probs, "outptu", "unknown key 'outptu' at the top level", "did you mean 'output'?")
    expect(probs, "particles.0.volume_fractoin", "in particles.0", "did you mean 'volume_fraction'?")


def test_stage_without_end_condition(deck_dir, base):
    base["stages"][0]["end"] = {"max_time": 2.0}
    base["stages"][1].pop("end")
    probs = problems_of(deck_dir, base)
    expect(probs, "stages.0.end", "at least one end condition", "max_time is a safety cap")
    expect(probs, "stages.1.end", "required key 'end' is missing")


def test_no_stages(deck_dir, base):
    base["stages"] = []
    expect(problems_of(deck_dir, base), "stages", "needs at least 1 entry; got 0")
    del base["stages"]
    expect(problems_of(deck_dir, base), "stages", "required key 'stages' is missing")


def test_duplicate_stage_names(deck_dir, base):
    base["stages"][1]["name"] = "fill"
    probs = problems_of(deck_dir, base)
    expect(probs, "stages.1.name", "duplicate stage name 'fill'", "stages.0.name")


def test_bad_stage_name(deck_dir, base):
    base["stages"][1]["name"] = "2nd stage"
    expect(problems_of(deck_dir, base), "stages.1.name", "must match the pattern")


def test_unknown_stage_in_boundary_stages(deck_dir, base):
    base["boundaries"]["floor"]["stages"] = ["fill", "fil"]
    base["boundaries"]["cone"]["open_at_stage"] = "dischrage"
    base["particles"][0]["stage"] = "later"
    probs = problems_of(deck_dir, base)
    expect(probs, "boundaries.floor.stages.1", "unknown stage 'fil'", "defined stages: 'fill', 'discharge'")
    expect(probs, "boundaries.cone.open_at_stage", "unknown stage 'dischrage'", "did you mean 'discharge'?")
    expect(probs, "particles.0.stage", "unknown stage 'later'")


def test_above_and_below_together(deck_dir, base):
    base["stages"][1]["end"]["below"] = 1.0
    expect(problems_of(deck_dir, base), "stages.1.end.quantity", "exactly one of above / below", "both given")


def test_above_without_quantity(deck_dir, base):
    base["stages"][0]["end"]["above"] = 1.0
    expect(problems_of(deck_dir, base), "stages.0.end.above", "needs quantity")


def test_quantity_naming_unknown_boundary(deck_dir, base):
    base["stages"][1]["end"]["quantity"] = "cnoe.discharged_mass"
    expect(problems_of(deck_dir, base), "stages.1.end.quantity", "names boundary 'cnoe'", "not defined",
           "did you mean 'cone'?")


def test_both_n_and_volume_fraction(deck_dir, base):
    base["particles"][0]["volume_fraction"] = 0.3
    expect(problems_of(deck_dir, base), "particles.0.volume_fraction", "exactly one of n", "both given")
    del base["particles"][0]["n"], base["particles"][0]["volume_fraction"]
    expect(problems_of(deck_dir, base), "particles.0", "exactly one of n", "neither given")


def test_random_fill_too_dense(deck_dir, base):
    base["particles"][0]["n"] = 10_000_000
    expect(problems_of(deck_dir, base), "particles.0.n", "random sequential addition", "pluviate")


def test_restitution_above_one(deck_dir, base):
    base["materials"]["glass"]["restitution"] = 1.2
    expect(problems_of(deck_dir, base), "materials.glass.restitution", "must be in [0, 1]", "got 1.2")


def test_poisson_ratio_half(deck_dir, base):
    base["materials"]["glass"]["poisson_ratio"] = 0.5
    expect(problems_of(deck_dir, base), "materials.glass.poisson_ratio", "must be in (-1, 0.5)", "got 0.5")


def test_gravity_with_two_components(deck_dir, base):
    base["run"]["gravity"] = [0, -9.81]
    expect(problems_of(deck_dir, base), "run.gravity", "must have exactly 3 items; got 2")


def test_unknown_output_format(deck_dir, base):
    base["output"]["formats"] = ["csv", "hdf5"]
    expect(problems_of(deck_dir, base), "output.formats.0", "unknown output format 'csv'", "'hdf5', 'vtk'")


def test_unknown_output_field(deck_dir, base):
    base["output"]["fields"] = ["x", "pos"]
    expect(problems_of(deck_dir, base), "output.fields.1", "must be one of 'x', 'v'", "got 'pos'")


def test_snapshot_cadence_exclusive(deck_dir, base):
    base["output"]["every_time"] = 0.1
    expect(problems_of(deck_dir, base), "output.every_time", "at most one of every_time")


def test_file_source_missing_file(deck_dir, base):
    base["particles"][2]["path"] = "missing.txt"
    expect(problems_of(deck_dir, base), "particles.2.path", "file 'missing.txt' does not exist",
           "relative to the deck's directory")


def test_unknown_law_parameter(deck_dir, base):
    base["contact"]["clamp_normall"] = True
    msg = expect(problems_of(deck_dir, base), "contact.clamp_normall")
    assert msg == "unknown key 'clamp_normall' in contact; did you mean 'clamp_normal'?"


def test_unknown_key_in_the_other_laws_table(deck_dir, base):
    """A DEM-P deck's [contact.complementarity] is checked too: a misspelt key there is reported
    now, not only after --set contact.law=complementarity; its valid keys pass."""
    base["contact"]["complementarity"] = {"solver": "apgd", "max_iteratons": 300}
    problems = problems_of(deck_dir, base)
    msg = expect(problems, "contact.complementarity.max_iteratons")
    assert msg == "unknown key 'max_iteratons' in contact.complementarity; did you mean 'max_iterations'?"
    assert len(problems) == 1
    base["contact"]["complementarity"] = {"solver": "apgd", "max_iterations": 300}
    validate_deck(base, path=deck_dir / "deck.toml")  # no error


def test_law_parameter_combination(deck_dir, base):
    base["contact"]["parameterisation"] = "coefficients"
    base["contact"]["kn"] = 1e6
    expect(problems_of(deck_dir, base), "contact", "needs kt, cn, ct")


def test_boundary_plugin_parameters(deck_dir, base):
    base["boundaries"]["cone"]["orifice_diameter"] = -0.01
    del base["boundaries"]["floor"]["normal"]
    base["boundaries"]["floor"]["motion"] = {"type": "spin"}
    base["boundaries"]["floor"]["point"] = [0, float("inf"), 0]
    probs = problems_of(deck_dir, base)
    expect(probs, "boundaries.cone.orifice_diameter", "must be > 0")
    expect(probs, "boundaries.floor.normal", "required key 'normal' is missing")
    expect(probs, "boundaries.floor.motion.type", "must be one of 'fixed', 'constant_velocity'", "'spin'")
    expect(probs, "boundaries.floor.point.1", "finite")


def test_unknown_source_kind(deck_dir, base):
    base["particles"][0]["source"] = "randomfill"
    base["particles"][1]["region"] = {"type": "box", "lo": [0, 0, 0], "hi": [1, 1, 1]}
    base["particles"][3]["sizes"] = {"radius": 1e-3}
    probs = problems_of(deck_dir, base)
    expect(probs, "particles.0.source", "must be one of 'random_fill', 'lattice', 'file', 'pluviate'",
           "did you mean 'random_fill'?")
    expect(probs, "particles.1.region", "'hex2d' lattice", "not a region")
    expect(probs, "particles.3.sizes.type", "required key 'type' is missing", "'single', 'uniform'")


def test_size_tables_and_regions(deck_dir, base):
    base["particles"][3]["sizes"]["mass_fractions"] = [0.5, 0.6]
    base["particles"][3]["region"]["hi"] = [0.02, 0.02, 0.0]
    base["particles"][0]["sizes"] = {"type": "uniform", "r_min": 2e-3, "r_max": 1e-3}
    probs = problems_of(deck_dir, base)
    expect(probs, "particles.3.sizes.mass_fractions", "sum to 1.1")
    expect(probs, "particles.3.region.hi", "must exceed lo", "along z")
    expect(probs, "particles.0.sizes.r_max", "smaller than r_min")


def test_bad_override_unknown_key(deck_dir):
    probs = problems_of(deck_dir, text=FULL, overrides=("run.dtt=1",))
    expect(probs, "run.dtt", "unknown key 'dtt' in run; did you mean 'dt'?", "(from --set run.dtt=1)")


def test_bad_override_malformed(deck_dir):
    probs = problems_of(deck_dir, text=FULL, overrides=("run.dt", "run.dt=", "=1", "run.dt=1 2"))
    expect(probs, "--set", "malformed override 'run.dt'", "key.path=value")
    expect(probs, "--set", "override 'run.dt='", "no value")
    expect(probs, "--set", "malformed override '=1'")
    expect(probs, "--set", "override 'run.dt=1 2'", "not a TOML value")
    assert len(probs) == 4


def test_bad_override_targets(deck_dir):
    probs = problems_of(deck_dir, text=FULL, overrides=(
        "stages.5.end.time=1", "stages.fil.end.time=1", "run.dt.x=1", "run.dt=-1"))
    expect(probs, "stages.5", "index 5 is out of range")
    expect(probs, "stages.fil", "no entry of stages is named 'fil'", "did you mean 'fill'?")
    expect(probs, "run.dt", "is a float, not a table")
    expect(probs, "run.dt", "must be > 0", "(from --set run.dt=-1)")


def test_override_into_a_name_the_deck_lacks_is_refused(deck_dir):
    """A dotted --set into a material or boundary the deck does not have would make a new, unused
    entry and change nothing (a typo that silently leaves the run as it was): refused, naming the
    entries the deck has. A whole table still adds one."""
    probs = problems_of(deck_dir, text=FULL, overrides=("materials.glas.youngs_modulus=1e9",
                                                        "boundaries.flor.material=\"glass\""))
    expect(probs, "materials.glas", "no material named 'glas'", "did you mean 'glass'?", "'steel'")
    expect(probs, "boundaries.flor", "no boundary named 'flor'", "did you mean 'floor'?")
    assert len(probs) == 2
    (deck_dir / "deck.toml").write_text(FULL)
    added = load_deck(deck_dir / "deck.toml", ("materials.sand={density = 2650.0}",))
    assert added.deck.materials["sand"].density == 2650.0


def test_several_errors_reported_at_once(deck_dir):
    text = (FULL.replace("dt = 1e-5", 'dt = "fast"')
            .replace("poisson_ratio = 0.3", "poisson_ratio = 0.7")
            .replace('material = "steel"\nmotion = "fixed"', 'material = "iron"\nmotion = "fixed"')
            .replace('stages = ["fill"]', 'stages = ["filling"]')
            .replace('formats = ["hdf5", "vtk"]', 'formats = ["hdf5", "pdf"]'))
    probs = problems_of(deck_dir, text=text, overrides=("contact.clamp=true",))
    expect(probs, "run.dt", "expected a number")
    expect(probs, "materials.glass.poisson_ratio", "must be in (-1, 0.5)")
    expect(probs, "particles.1.material", "unknown material 'iron'")
    expect(probs, "boundaries.floor.stages.0", "unknown stage 'filling'")
    expect(probs, "output.formats.1", "unknown output format 'pdf'")
    expect(probs, "contact.clamp", "did you mean 'clamp_normal'?", "from --set")
    assert len(probs) == 6
    # listed in deck order, one line each
    assert [p for p, _ in probs] == ["run.dt", "contact.clamp", "materials.glass.poisson_ratio",
                                     "particles.1.material", "boundaries.floor.stages.0", "output.formats.1"]


def test_deck_error_is_input_error(deck_dir, base):
    base["run"]["dt"] = -1.0
    with pytest.raises(InputError) as info:
        validate_deck(base, path=deck_dir / "deck.toml")
    assert info.value.exit_code == 2
    assert str(info.value).startswith("deck '")
    assert "  run.dt: must be > 0; got -1.0" in str(info.value).splitlines()


# ------------------------------------------------------------------------------------------- schema, docs


def _deck_models() -> list[type[BaseModel]]:
    seen: list[type[BaseModel]] = []

    def visit(tp) -> None:
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if tp not in seen:
                seen.append(tp)
                for f in tp.model_fields.values():
                    visit(f.annotation)
            return
        for arg in typing.get_args(tp):
            visit(arg)

    visit(Deck)
    return seen


def test_every_key_is_described_and_documented():
    doc = (ROOT / "docs" / "deck.md").read_text(encoding="utf-8")
    for model in _deck_models():
        for name, f in model.model_fields.items():
            assert f.description, f"{model.__name__}.{name} has no description"
            pattern = rf"`\[*{name}(\.NAME)?\]*`"  # `dt`, `[run]`, `[[stages]]`, `[materials.NAME]`
            assert re.search(pattern, doc), f"docs/deck.md does not document `{name}` ({model.__name__})"


def test_json_schema(deck_dir):
    schema = deck_json_schema()
    json.dumps(schema)
    assert schema["properties"]["run"]["$ref"] == "#/$defs/RunSection"
    run = schema["$defs"]["RunSection"]["properties"]
    assert "stability estimate" in run["dt"]["description"]
    contact = schema["$defs"]["ContactSection"]
    assert any(c["if"]["properties"]["law"]["const"] == "hertz_mindlin" for c in contact["allOf"])
    entry = schema["$defs"]["BoundaryEntry"]
    assert any(c["if"]["properties"]["type"]["const"] == "hopper" for c in entry["allOf"])
    jsonschema = pytest.importorskip("jsonschema")
    validator = jsonschema.Draft202012Validator(schema)
    assert not list(validator.iter_errors(tomllib.loads(FULL)))
    bad = tomllib.loads(FULL)
    bad["materials"]["glass"]["densty"] = 1
    bad["contact"]["clamp_normall"] = True
    assert len(list(validator.iter_errors(bad))) == 2


def test_committed_schema_file_is_valid_json():
    schema = json.loads((ROOT / "docs" / "deck.schema.json").read_text(encoding="utf-8"))
    assert schema["title"] == "pdem deck"
    assert set(schema["properties"]) == set(Deck.model_fields)


def test_committed_schema_file_is_up_to_date():
    """docs/deck.schema.json is what tools/write_deck_schema.py makes from the schema now."""
    import importlib.util

    path = ROOT / "tools" / "write_deck_schema.py"
    spec = importlib.util.spec_from_file_location("write_deck_schema", path)
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    committed = (ROOT / "docs" / "deck.schema.json").read_text(encoding="utf-8")
    assert committed == tool.render(), "docs/deck.schema.json is stale: run python tools/write_deck_schema.py"


def test_docs_example_is_valid(tmp_path):
    """The complete example in docs/deck.md validates."""
    doc = (ROOT / "docs" / "deck.md").read_text(encoding="utf-8")
    start = doc.index("<!-- example:begin -->")
    block = doc[start:doc.index("<!-- example:end -->")]
    text = block.split("```toml\n", 1)[1].split("```", 1)[0]
    data = tomllib.loads(text)
    (tmp_path / "packing.txt").write_text("0 0 0.01 0.002\n")
    r = validate_deck(copy.deepcopy(data), path=tmp_path / "example.toml")
    assert r.deck.stages


# ------------------------------------------------------------------------------------------- [domain]


def test_domain_periodic_box_loads(deck_dir, base):
    base["domain"] = {"periodic": ["x", "y"], "lo": [-0.05, -0.05, 0.0], "hi": [0.05, 0.05, 0.0]}
    r = validate_deck(copy.deepcopy(base), path=deck_dir / "deck.toml")
    assert r.deck.domain.periodic == ["x", "y"]
    box = r.deck.domain.box()
    assert box.axes == ["x", "y"] and abs(box.length[0] - 0.1) < 1e-15
    # round trip through the resolved deck
    again = validate_deck(tomllib.loads(r.resolved_toml()), path=deck_dir / "deck.toml")
    assert again.deck.domain == r.deck.domain
    # without periodic axes the section is left out of the resolved deck
    plain = validate_deck(tomllib.loads(FULL), path=deck_dir / "deck.toml")
    assert "[domain]" not in plain.resolved_toml() and plain.deck.domain.box() is None


def test_domain_problems(deck_dir, base):
    base["domain"] = {"periodic": ["x", "w", "x"], "lo": [0, 0, 0]}
    problems = problems_of(deck_dir, base)
    expect(problems, "domain.periodic.1", "'x'", "'y'", "'z'")
    expect(problems, "domain.periodic", "'x' listed more than once")
    expect(problems, "domain.hi", "needs the box corners lo and hi", "domain.hi")
    base["domain"] = {"periodic": ["y"], "lo": [0, 0.1, 0], "hi": [1, 0.1, 0]}
    expect(problems_of(deck_dir, base), "domain.hi", "must exceed lo", "periodic axis y")
    base["domain"] = {"lo": [0, 0, 0], "hi": [1, 1, 1]}
    expect(problems_of(deck_dir, base), "domain.lo", "only used with periodic axes", "periodic = ['x', …]")


def test_domain_too_small_for_the_particles(deck_dir, base):
    # radii up to 1.1 mm and skin 0.1 mm: periodic lengths of at least 2 (2.2 + 0.1) = 4.6 mm
    base["domain"] = {"periodic": ["x"], "lo": [0, 0, 0], "hi": [0.0045, 0, 0]}
    del base["particles"][1:]
    base["particles"][0]["region"] = {"type": "box", "lo": [0, 0, 0], "hi": [0.0045, 0.04, 0.04]}
    base["particles"][0]["n"] = 50
    msg = expect(problems_of(deck_dir, base), "domain.hi", "along x", "two images", "at least 0.0046 m")
    assert "domain.lo, domain.hi" in msg
    base["domain"]["hi"] = [0.0047, 0, 0]
    base["particles"][0]["region"]["hi"] = [0.0047, 0.04, 0.04]
    validate_deck(copy.deepcopy(base), path=deck_dir / "deck.toml")


def test_source_region_wider_than_the_periodic_box(deck_dir, base):
    base["domain"] = {"periodic": ["x", "y"], "lo": [-0.03, -0.03, 0], "hi": [0.03, 0.03, 0]}
    # the cylinder of the first source is 0.08 m across
    probs = problems_of(deck_dir, base)
    msg = expect(probs, "particles.0.region", "along the periodic axis x", "would overlap")
    assert "wider than the periodic box (0.06 m)" in msg


def test_run_dt_and_dt_fraction_are_exclusive(tmp_path):
    deck = tmp_path / "d.toml"
    deck.write_text(
        '[run]\ndt = 1e-6\ndt_fraction = 0.2\n[materials.m]\n[[particles]]\nsource = "lattice"\n'
        'material = "m"\nlattice = "sc"\nspacing = 0.002\nradius = 0.001\n'
        'region = { type = "box", lo = [0, 0, 0], hi = [0.01, 0.01, 0.01] }\n'
        '[[stages]]\nname = "s"\nend = { steps = 1 }\n'
    )
    with pytest.raises(InputError) as info:
        load_deck(deck)
    assert "run.dt_fraction" in str(info.value) and "give one" in str(info.value)


def test_million_deck_validates_and_makes_a_million_grains_per_rank_output():
    """inputs/examples/million.toml (the deck docs/performance.md measures 10⁶ grains on) validates,
    its source makes 10⁶ grains by the memory check's estimate, and its output is per rank."""
    from pdem.deck.capacity import estimate_sources

    path = ROOT / "inputs" / "examples" / "million.toml"
    resolved = load_deck(path)
    assert resolved.deck.output.parallel == "per_rank"
    assert sum(c for _, c, _ in estimate_sources(tomllib.loads(path.read_text()), path.parent)) == 1_000_000
