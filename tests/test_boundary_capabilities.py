"""What a boundary tells pdem's checks goes through the boundary contract's hooks (``loading``,
``extent``, ``sample_size``, ``wall_materials``) and a source's through ``estimate_count``, never
through a plugin's name: a third-party boundary (the servo-plate example plugin) gets the advice of
a built-in device with the same loading, and a third-party source the memory check."""

from __future__ import annotations

import ast
import math
import tomllib
from pathlib import Path

import pytest

from pdem.advise import advise
from pdem.advise.scene import deck_scene
from pdem.api import Boundary, BoundaryParams, Extent, Loading, SampleSize, SceneFacts, SizeCheck
from pdem.deck import capacity, load_deck
from pdem.plugins import available

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(
    "servo_plate" not in available("boundaries"),
    reason="the pdem-servo-plate example plugin is not installed",
)

HEAD = """\
[run]
gravity = [0.0, 0.0, -9.81]
seed = 1
max_particles = LIMIT
[contact]
law = "hertz_mindlin"
[materials.glass]
density = 2550.0
youngs_modulus = 4.0e7
poisson_ratio = 0.22
restitution = 0.87
friction = 0.18
[materials.wall]
rigid = true
friction = 0.1
[[particles]]
source = "random_fill"
material = "glass"
region = { type = "box", lo = [0.003, 0.003, 0.003], hi = [0.045, 0.045, 0.094] }
sizes = { type = "single", radius = 0.003 }
n = 350
"""

STAGES = """\
[[stages]]
name = "fill"
[stages.end]
kinetic_energy_below = 1.0e-6
time = 0.4
[[stages]]
name = "consolidate"
[stages.end]
time = 0.35
[[stages]]
name = "shear"
[stages.end]
time = 0.2
[output]
directory = "out/capabilities"
"""

# a built-in device whose top plate holds 3100 Pa at up to 0.3 m/s from "consolidate" on
BUILT_IN = """\
[boundaries.box]
type = "shear_box"
material = "wall"
corner = [0.0, 0.0, 0.0]
length = 0.048
width = 0.048
lower_height = 0.014
upper_height = 0.082
gap = 0.0015
normal_stress = 3100.0
shear_speed = 0.003
max_displacement = 0.004
max_speed = 0.3
consolidation_stage = "consolidate"
shear_stage = "shear"
"""

# the same loading by the example plugin: walls and a servo plate of the box's area
PLUGIN = """\
[boundaries.walls]
type = "box"
material = "wall"
lo = [0.0, 0.0, 0.0]
hi = [0.048, 0.048, 0.2]
open_faces = ["zhi"]
[boundaries.lid]
type = "servo_plate"
material = "wall"
point = [0.0, 0.0, 0.096]
normal = [0.0, 0.0, -1.0]
area = 0.002304
target_stress = 3100.0
max_speed = 0.3
stages = ["consolidate", "shear"]
"""

# the built-in's labels, as the plugin's boundary names its keys
RENAME = {
    "boundaries.box.normal_stress": "boundaries.lid.target_stress",
    "boundaries.box.": "boundaries.lid.",
    "boundaries.box": "boundaries.lid",  # the boundary named in a finding's reason
}


def _deck(tmp_path: Path, name: str, boundaries: str, limit: int = 1_000_000) -> Path:
    path = tmp_path / f"{name}.toml"
    path.write_text(HEAD.replace("LIMIT", str(limit)) + boundaries + STAGES)
    return path


def _renamed(value):
    if isinstance(value, str):
        for old, new in RENAME.items():
            value = value.replace(old, new)
        return value
    if isinstance(value, dict):
        return {_renamed(k): _renamed(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_renamed(v) for v in value]
    return value


def test_the_servo_plate_plugin_gets_the_advice_of_a_built_in_servo(tmp_path):
    built_in = advise(_deck(tmp_path, "shear_box", BUILT_IN), probe=False)
    plugin = advise(_deck(tmp_path, "servo_plate", PLUGIN), probe=False)
    # what the boundary imposes: the same stress and the same speeds in every stage, the same area
    scenes = []
    for path in (tmp_path / "shear_box.toml", tmp_path / "servo_plate.toml"):
        resolved = load_deck(path)
        scenes.append(deck_scene(resolved, tomllib.loads(path.read_text())))
    a, b = scenes
    assert a.footprint == pytest.approx(0.048 * 0.048) and b.footprint == pytest.approx(a.footprint)
    assert b.packed_height == pytest.approx(a.packed_height)
    for sa, sb in zip(a.stages, b.stages, strict=True):
        assert sb.stress == pytest.approx(sa.stress), sa.name
        assert _renamed(sa.stress_from) == sb.stress_from
        assert max(sb.speeds)[0] == pytest.approx(max(sa.speeds)[0]), sa.name
    assert a.stages[1].stress > 3100.0  # the plate's target on the grains' weight
    assert b.stages[1].stress_from == "boundaries.lid.target_stress + the grains' weight"
    assert ("boundaries.lid.max_speed (servo)" in dict((lbl, v) for v, lbl in b.stages[1].speeds))

    # the findings that follow from the loading are the built-in's, modulo the boundary's names
    def kept(advice):
        return [
            _renamed(f.to_dict()) if advice is built_in else f.to_dict()
            for f in advice.findings
            if f.topic not in ("inertial", "sample_size")  # the shear and the ASTM box: the device's own
        ]

    fa, fb = kept(built_in), kept(plugin)
    assert [(f["topic"], f["where"], f["verdict"]) for f in fa] == [
        (f["topic"], f["where"], f["verdict"]) for f in fb
    ]
    assert fa == fb
    assert {f.topic for f in plugin.findings} >= {"overlap", "step", "method"}
    # the overlap is sized at the plate's stress, named by the plugin's key
    overlap = next(f for f in plugin.findings if f.topic == "overlap")
    assert "boundaries.lid.target_stress" in overlap.numbers["stress at"]
    # the device's own checks: the shear box has them (the shear, ASTM D3080); the plate declares none
    assert {f.topic for f in built_in.findings} >= {"inertial", "sample_size"}
    assert not [f for f in plugin.findings if f.topic in ("inertial", "sample_size")]


def test_the_servo_plate_deck_gets_the_same_capacity_check(tmp_path):
    a = _deck(tmp_path, "shear_box", BUILT_IN, limit=100)
    b = _deck(tmp_path, "servo_plate", PLUGIN, limit=100)
    pa = capacity.check_capacity(tomllib.loads(a.read_text()), tmp_path)
    pb = capacity.check_capacity(tomllib.loads(b.read_text()), tmp_path)
    assert pa and pa == pb
    assert "random_fill with n = 350 makes about 350 particles" in pa[0][1]


def test_the_plugin_hooks_describe_the_servo_plate():
    from pdem_servo_plate import ServoPlate, ServoPlateParams

    p = ServoPlateParams(type="servo_plate", material="steel", point=(0, 0, 0.1), normal=(0, 0, -1),
                         area=2e-3, target_stress=500.0, max_speed=0.05)  # fmt: skip
    facts = SceneFacts(stages=("a", "b"))
    [ld] = ServoPlate.loading("lid", p, facts)
    assert ld.stages == ("a", "b") and ld.stress == 500.0 and ld.on_weight and ld.speed == 0.05
    assert ServoPlate.extent(p).footprint == 2e-3
    assert ServoPlate.sample_size("lid", p, facts) is None
    assert ServoPlate.wall_materials(p) == ["steel"]


def test_a_boundary_without_hooks_says_nothing_known():
    class Bare(Boundary):
        Params = BoundaryParams

    p = BoundaryParams(type="bare")
    facts = SceneFacts(stages=("s",))
    assert Bare.loading("b", p, facts) == []
    assert Bare.extent(p) is None
    assert Bare.sample_size("b", p, facts) is None
    assert Bare.wall_materials(p) == []


def test_a_user_boundary_gets_its_own_size_check_and_rate(tmp_path, monkeypatch):
    """A boundary written outside pdem that declares a test's minimum size and a loading rate gets the
    sample-size and inertial-number findings (the advice asks the class the deck resolved)."""

    class Press(Boundary):
        Params = BoundaryParams

        @classmethod
        def loading(cls, name, params, facts):
            return [Loading(stages=facts.stages_from("shear"), speed=1e-3, speed_from=f"boundaries.{name}.v",
                            stress=2000.0, stress_from=f"boundaries.{name}.sigma", rate_key="v", rate=1e-3,
                            shear_rate=1e-3 / (10 * facts.d_mean), rate_how="I = v / (10 d) d sqrt(ρ/σ)")]

        @classmethod
        def extent(cls, params):
            return Extent(lo=(0, 0, 0), hi=(0.048, 0.048, 0.1))

        @classmethod
        def sample_size(cls, name, params, facts):
            return SampleSize("press", (SizeCheck("width / d_max", 0.048 / facts.d_max, 100.0, "a rule"),))

    import pdem.deck.load as load_mod

    real = load_mod._load_plugin

    def fake(group, name):
        return (Press, None) if (group, name) == ("boundaries", "press") else real(group, name)

    monkeypatch.setattr(load_mod, "_load_plugin", fake)
    deck = _deck(tmp_path, "press", '[boundaries.p]\ntype = "press"\n')
    advice = advise(deck, probe=False)
    size = next(f for f in advice.findings if f.topic == "sample_size")
    assert size.where == "boundaries.p (press)" and size.verdict == "warn" and "a rule" in size.source
    inertial = next(f for f in advice.findings if f.topic == "inertial")
    assert inertial.numbers["key"] == "boundaries.p.v" and inertial.numbers["stage"] == "shear"
    assert inertial.numbers["stress [Pa]"] == 2000.0
    assert advice.scene["packed_height"] == pytest.approx(
        350 * 4 / 3 * math.pi * 0.003**3 / (0.6 * 0.048 * 0.048)
    )


def test_a_user_source_gets_the_memory_check(tmp_path, monkeypatch):
    from pdem.sources.api import Source

    class Cloud(Source):
        @classmethod
        def estimate_count(cls, data, context):
            return float(data["n"]), f"a cloud of {data['n']:,} grains"

    monkeypatch.setattr(capacity, "_source_class", lambda name: Cloud if name == "cloud" else None)
    data = {"run": {"max_particles": 10}, "particles": [{"source": "cloud", "n": 1000}]}
    [(loc, msg)] = capacity.check_capacity(data, tmp_path)
    assert loc == ("particles", 0) and "a cloud of 1,000 grains makes about 1,000 particles" in msg
    # a source that does not say is left out
    monkeypatch.setattr(capacity, "_source_class", lambda name: Source)
    assert capacity.check_capacity(data, tmp_path) == []


def _branches_on_names(path: Path, names: set[str]) -> list[str]:
    """Comparisons (==, !=, in) of anything with a string literal that is a plugin's name."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.Compare):
            continue
        for part in (node.left, *node.comparators):
            consts = [part] if isinstance(part, ast.Constant) else getattr(part, "elts", [])
            for c in consts:
                if isinstance(c, ast.Constant) and c.value in names:
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno}: {c.value!r}")
    return out


def test_advise_and_capacity_do_not_branch_on_boundary_names():
    names = set(available("boundaries")) - {"box", "plane", "cylinder"}  # also region and shape types
    files = [*(ROOT / "pdem" / "advise").glob("*.py"), ROOT / "pdem" / "deck" / "capacity.py"]
    found = [hit for f in files for hit in _branches_on_names(f, names)]
    assert not found, "branches on boundary plugin names:\n" + "\n".join(found)
    cap = _branches_on_names(ROOT / "pdem" / "deck" / "capacity.py", set(available("sources")))
    assert not cap, "branches on source plugin names:\n" + "\n".join(cap)


def test_advise_does_not_branch_on_source_or_law_names():
    """Sources and laws too are known by their capabilities (``Source.starts_loose``, ``settles``,
    ``path_keys``, ``known_radii``; ``ContactLaw.rigid``, ``hertz_from_materials``)."""
    names = (set(available("sources")) | set(available("contact_laws"))) - {"box", "plane", "cylinder"}
    files = [*(ROOT / "pdem" / "advise").glob("*.py"), ROOT / "pdem" / "deck" / "capacity.py"]
    found = [hit for f in files for hit in _branches_on_names(f, names)]
    assert not found, "branches on source or law plugin names:\n" + "\n".join(found)
