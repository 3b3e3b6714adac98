"""Particle sources as plugins (entry-point group pdem.sources): pdem's own come through entry points,
an external package adds a source that a deck validates and runs end to end, the contract is
enforced, and a name registered by two distributions is an error that names both."""

from __future__ import annotations

import json
import re
import sys
import tomllib
from importlib.metadata import EntryPoint
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import pdem.plugins as plugins
from pdem.cli import main
from pdem.deck import deck_json_schema, load_deck, validate_deck
from pdem.errors import DeckError, PluginError
from pdem.io.checkpoint import read_checkpoint
from pdem.materials import Material
from pdem.sources.api import Source, SourceOutput, SourceParams, produce

ROOT = Path(__file__).resolve().parent.parent

# An external source plugin, as a package would ship it: n spheres of radius r along +x.
LINE_MODULE = """
from typing import Literal

import numpy as np
from pydantic import Field

from pdem.sources.api import Float, Int, Source, SourceOutput, SourceParams, Vec3


class LineParams(SourceParams):
    source: Literal["line"] = Field(description="source kind")
    n: Int = Field(gt=0, description="number of spheres")
    radius: Float = Field(gt=0, description="sphere radius [m]")
    start: Vec3 = Field((0.0, 0.0, 0.0), description="centre of the first sphere (x, y, z) [m]")
    spacing: Float | None = Field(None, gt=0, description="centre distance along x [m]; default 2 radius")

    @classmethod
    def rules(cls, data, context):
        r, s = data.get("radius"), data.get("spacing")
        if isinstance(r, int | float) and isinstance(s, int | float) and s < 2 * r:
            return [(("spacing",), f"spacing = {s} is below the diameter {2 * r}; the spheres would overlap")]
        return []


class LineSource(Source):
    Params = LineParams

    def generate(self, *, base_dir, seed, material):
        p = self.params
        step = p.spacing if p.spacing is not None else 2.0 * p.radius
        x = np.zeros((p.n, 3))
        x[:, 0] = np.arange(p.n) * step
        x += np.asarray(p.start)
        return SourceOutput(x, np.full(p.n, p.radius))

    def r_max(self):
        return self.params.radius

    def bounds(self):
        p = self.params
        step = p.spacing if p.spacing is not None else 2.0 * p.radius
        lo = np.asarray(p.start) - p.radius
        hi = np.asarray(p.start) + p.radius
        hi[0] += (p.n - 1) * step
        return lo, hi


class NotASource:
    class Params:  # not a pydantic model
        pass
"""

LINE_DECK = """\
title = "a line of spheres from an external source plugin"
[run]
gravity = [0.0, 0.0, 0.0]
seed = 1
[materials.glass]
density = 2500.0
youngs_modulus = 5e7
[[particles]]
source = "line"
material = "glass"
n = 7
radius = 1e-3
start = [0.0, 0.0, 0.01]
[[stages]]
name = "still"
[stages.end]
steps = 20
[output]
every_steps = 10
"""


def _dist_info(root: Path, dist: str, module: str | None, entries: str) -> None:
    """A minimal installed distribution: ``<dist>.dist-info`` with METADATA and entry_points.txt."""
    info = root / f"{dist.replace('-', '_')}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(entries)
    if module is not None:
        (root / "pdem_line_source.py").write_text(module)


@pytest.fixture
def line_plugin(tmp_path, monkeypatch):
    """pdem-line-source 'installed' on sys.path: registers source 'line' through real entry points."""
    site = tmp_path / "site"
    _dist_info(site, "pdem-line-source", LINE_MODULE, "[pdem.sources]\nline = pdem_line_source:LineSource\n")
    monkeypatch.syspath_prepend(str(site))
    yield site
    sys.modules.pop("pdem_line_source", None)


# ------------------------------------------------------------------------------------------- built-ins


def test_builtin_sources_are_entry_points():
    found = plugins.available("sources")
    assert {"random_fill", "lattice", "file", "pluviate"} <= set(found)
    for name in ("random_fill", "lattice", "file", "pluviate"):
        assert found[name].distribution == "pdem"
        cls = plugins.load("sources", name)
        assert issubclass(cls, Source) and issubclass(cls.Params, SourceParams)


def test_builtin_source_keys_are_described_and_documented():
    """Every key of pdem's own sources has a description (JSON Schema) and is in docs/deck.md."""
    doc = (ROOT / "docs" / "deck.md").read_text(encoding="utf-8")
    for name in ("random_fill", "lattice", "file", "pluviate"):
        model = plugins.load("sources", name).Params
        for key, f in model.model_fields.items():
            assert f.description, f"{model.__name__}.{key} has no description"
            assert re.search(rf"`{key}`", doc), f"docs/deck.md does not document `{key}` ({model.__name__})"


def test_build_particles_still_importable_from_runner(tmp_path):
    from pdem.runner import build_particles

    spec = {
        "source": "lattice",
        "material": "glass",
        "lattice": "hex2d",
        "radius": 1e-3,
        "n_cols": 4,
        "n_rows": 2,
    }
    x, r, v = build_particles(spec, tmp_path, 0, Material("glass"))
    assert x.shape == (8, 3) and np.all(r == 1e-3) and v is None
    assert np.all(x[:, 1] == 0.0)  # hex2d defaults: the xz plane


# ------------------------------------------------------------------------------------------- external plugin


def test_external_source_plugin_end_to_end(line_plugin, tmp_path, capsys):
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "pdem.sources:" in out and "pdem_line_source:LineSource  (from pdem-line-source)" in out

    deck = tmp_path / "line.toml"
    deck.write_text(LINE_DECK)
    assert main(["check", str(deck)]) == 0
    capsys.readouterr()
    outdir = tmp_path / "out"
    code = main([str(deck), "--output", str(outdir), "--quiet"])
    assert code == 0, capsys.readouterr().err

    summary = json.loads((outdir / "summary.json").read_text())
    assert summary["particles"] == 7 and summary["steps"] == 20 and summary["completed"]
    state, _ = read_checkpoint(outdir / "checkpoints" / "latest.h5")
    x = state["particles/x"][np.argsort(state["particles/id"])]
    expected = np.zeros((7, 3))
    expected[:, 0] = np.arange(7) * 2e-3
    expected[:, 2] = 0.01
    assert np.array_equal(x, expected)  # no gravity, no contacts: the spheres stay where generated
    assert np.all(state["particles/r"] == 1e-3)

    # the resolved deck keeps the plugin's parameters with its defaults, and loads back
    resolved = tomllib.loads((outdir / "deck.resolved.toml").read_text())
    src = resolved["particles"][0]
    assert list(src)[0] == "source" and src["source"] == "line"
    assert src["motion"] == "free" and src["velocity"] == [0.0, 0.0, 0.0] and "spacing" not in src
    again = load_deck(outdir / "deck.resolved.toml")
    assert type(again.deck.particles[0]).__name__ == "LineParams"
    assert type(again.make_sources()[0]).__name__ == "LineSource"

    # a checkpoint of a deck that uses the plugin resumes (its deck is validated again)
    part = tmp_path / "part"
    assert main([str(deck), "--output", str(part), "--quiet", "--steps", "10"]) == 0
    resumed = tmp_path / "resumed"
    code = main(["resume", str(part / "checkpoints" / "latest.h5"), "--output", str(resumed), "--quiet"])
    assert code == 0, capsys.readouterr().err
    b, _ = read_checkpoint(resumed / "checkpoints" / "latest.h5")
    assert int(b["scalars/step"]) == 20 and np.array_equal(b["particles/x"], state["particles/x"])


def test_external_source_plugin_validation(line_plugin, tmp_path):
    data = tomllib.loads(LINE_DECK)
    data["particles"][0].update(n=0, spacing=1e-3, radiuss=1.0)
    data["particles"].append({"source": "lien", "material": "glass"})
    with pytest.raises(DeckError) as info:
        validate_deck(data, path=tmp_path / "deck.toml")
    probs = dict(info.value.problems)
    assert probs["particles.0.n"].startswith("must be > 0; got 0")
    assert probs["particles.0.radiuss"] == "unknown key 'radiuss' in particles.0; did you mean 'radius'?"
    assert "below the diameter 0.002" in probs["particles.0.spacing"]
    msg = probs["particles.1.source"]
    assert "unknown particle source 'lien'" in msg and "did you mean 'line'?" in msg
    assert "must be one of 'random_fill', 'lattice', 'file', 'pluviate', 'line'" in msg


def test_external_source_in_periodic_box_uses_r_max_and_bounds(line_plugin, tmp_path):
    data = tomllib.loads(LINE_DECK)
    # 7 spheres of 1 mm along x span 14 mm: wider than a 10 mm box; 2 r_max = 2 mm needs >= 4 mm along y
    data["domain"] = {"periodic": ["x", "y"], "lo": [-0.001, -0.001, 0.0], "hi": [0.009, 0.002, 0.0]}
    with pytest.raises(DeckError) as info:
        validate_deck(data, path=tmp_path / "deck.toml")
    probs = info.value.problems
    assert any(p == "domain.hi" and "along y" in m and "two images" in m for p, m in probs)
    assert any(
        p == "particles.0" and "source's extent is 0.014 m wide" in m and "axis x" in m for p, m in probs
    )


def test_json_schema_covers_installed_sources(line_plugin):
    schema = deck_json_schema()
    entry = schema["$defs"]["ParticleEntry"]
    tags = [c["if"]["properties"]["source"]["const"] for c in entry["allOf"]]
    assert {"random_fill", "lattice", "file", "pluviate", "line"} <= set(tags)
    assert "LineParams" in schema["$defs"]
    builtin = deck_json_schema(builtin_only=True)
    assert "line" not in [
        c["if"]["properties"]["source"]["const"] for c in builtin["$defs"]["ParticleEntry"]["allOf"]
    ]


def test_params_that_break_the_contract(tmp_path, monkeypatch, line_plugin):
    real = plugins.entry_points
    bad = EntryPoint(name="not_a_source", value="pdem_line_source:NotASource", group="pdem.sources")

    def fake(group):
        eps = list(real(group=group))
        return eps + [bad] if group == "pdem.sources" else eps

    monkeypatch.setattr(plugins, "entry_points", fake)
    data = tomllib.loads(LINE_DECK)
    data["particles"][0] = {"source": "not_a_source", "material": "glass"}
    with pytest.raises(DeckError, match=r"particles\.0\.source: .*no pydantic Params model"):
        validate_deck(data, path=tmp_path / "deck.toml")


def test_generate_must_return_a_source_output():
    class Tuple(Source):
        def generate(self, *, base_dir, seed, material):
            return np.zeros((2, 3)), np.ones(2)

    params = SourceParams(source="tuple", material="glass")
    with pytest.raises(
        PluginError, match=r"particle source 'tuple' \(particles.3\): generate\(\) returned tuple"
    ):
        produce(Tuple(params), base_dir=Path("."), seed=0, material=Material("glass"), where="particles.3")
    with pytest.raises(PluginError, match=r"radii must have shape \(2,\)"):
        SourceOutput(np.zeros((2, 3)), np.ones(3))
    with pytest.raises(PluginError, match=r"positions must have shape \(n, 3\)"):
        SourceOutput(np.zeros((2, 2)), np.ones(2))
    out = SourceOutput([[0, 0, 0]], [1])
    assert out.positions.dtype == np.float64 and len(out) == 1 and out.velocities is None


def test_only_a_collective_source_is_given_the_communicator():
    """``generate`` of a source that does not declare ``collective`` is called as the contract has
    always said (no ``comm``: a plugin written before it keeps working); a ``collective`` one is
    given the run's communicator, a serial one when there is none."""
    from pdem.parallel.comm import SerialComm

    seen = []

    class Plain(Source):
        def generate(self, *, base_dir, seed, material):
            return SourceOutput(np.zeros((1, 3)), np.ones(1))

    class Shared(Source):
        collective = True

        def generate(self, *, base_dir, seed, material, comm):
            seen.append(comm)
            return SourceOutput(np.zeros((1, 3)), np.ones(1))

    params = SourceParams(source="x", material="glass")
    mine = SerialComm()
    kw = dict(base_dir=Path("."), seed=0, material=Material("glass"))
    assert len(produce(Plain(params), **kw, comm=mine)) == 1
    produce(Shared(params), **kw, comm=mine)
    produce(Shared(params), **kw)
    assert seen[0] is mine and isinstance(seen[1], SerialComm) and seen[1] is not mine


# ------------------------------------------------------------------------------------------- duplicate names


def _with_dist(ep: EntryPoint, dist: str) -> EntryPoint:
    return ep._for(SimpleNamespace(name=dist))


def test_duplicate_entry_point_names_are_an_error(monkeypatch, capsys):
    real = plugins.entry_points
    a = _with_dist(EntryPoint("lattice", "pdem.sources.builtin:LatticeSource", "pdem.sources"), "pdem")
    b = _with_dist(EntryPoint("lattice", "pdem_lattices:FancyLattice", "pdem.sources"), "pdem-lattices")
    same = _with_dist(EntryPoint("lattice", "pdem.sources.builtin:LatticeSource", "pdem.sources"), "pdem")

    def fake(group):
        eps = [e for e in real(group=group) if e.name != "lattice"]
        return eps + [a, same, b] if group == "pdem.sources" else eps

    monkeypatch.setattr(plugins, "entry_points", fake)
    for call in (lambda: plugins.available("sources"), lambda: plugins.load("sources", "random_fill")):
        with pytest.raises(PluginError) as info:
            call()
        msg = str(info.value)
        assert "particle source 'lattice' is registered twice in entry-point group pdem.sources" in msg
        assert "'pdem' (pdem.sources.builtin:LatticeSource)" in msg
        assert "'pdem-lattices' (pdem_lattices:FancyLattice)" in msg
        assert "Uninstall one of them (pip uninstall pdem or pdem-lattices)" in msg
        assert "rename the entry point" in msg
    # other groups are unaffected
    assert "hertz_mindlin" in plugins.available("contact_laws")
    # `pdem plugins` reports it as an input error, without a traceback
    assert main(["plugins"]) == 2
    assert "registered twice" in capsys.readouterr().err


def test_same_distribution_listed_twice_is_not_a_conflict(monkeypatch):
    real = plugins.entry_points

    def fake(group):
        eps = list(real(group=group))
        return eps + [e for e in eps if e.name == "lattice"] if group == "pdem.sources" else eps

    monkeypatch.setattr(plugins, "entry_points", fake)
    assert plugins.available("sources")["lattice"].distribution == "pdem"


def test_duplicate_from_an_installed_distribution_in_a_deck(line_plugin, tmp_path):
    """A second real distribution registering pdem's own 'lattice': the deck reports it at the key."""
    _dist_info(
        line_plugin, "pdem-dup-lattice", None, "[pdem.sources]\nlattice = pdem_line_source:LineSource\n"
    )
    text = LINE_DECK.replace('source = "line"', 'source = "lattice"')
    deck = tmp_path / "dup.toml"
    deck.write_text(text)
    with pytest.raises(DeckError) as info:
        load_deck(deck)
    msg = dict(info.value.problems)["particles.0.source"]
    assert "'pdem' (pdem.sources.builtin:LatticeSource)" in msg
    assert "'pdem-dup-lattice' (pdem_line_source:LineSource)" in msg
