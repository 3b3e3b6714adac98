"""docs/plugins.md is enough to write a plugin: its Python code imports pdem names from
:mod:`pdem.api` only (names that exist there), and the blocks that define a contact law or a
boundary import, build into a module and construct."""

from __future__ import annotations

import ast
import builtins
import importlib.util
import re
import sys
import textwrap
import typing
from pathlib import Path

import pytest

import pdem
import pdem.api
from pdem.api import Boundary, ContactLaw, Material, MaterialTable, Simulation

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "docs" / "plugins.md"
API = set(pdem.api.__all__)

# names outside pdem.api the guide may import, with where and why
OUTSIDE_API = {
    # the law contract check: a test helper of a law's test suite, not needed at run time
    "pdem.testing.law_contract": ({"check_law_against_twin"}, None),
    # particle sources have their own contract module (its Vec3 is a stricter type than pdem.api's)
    "pdem.sources.api": (None, "Particle sources"),
}


def _blocks() -> list[tuple[int, str, str]]:
    """(line, section heading, code) of every ```python block of the guide."""
    out, section, lines = [], "", GUIDE.read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("## "):
            section = line[3:].strip()
        if line.strip() == "```python":
            start, body = i + 1, []
            i += 1
            while lines[i].strip() != "```":
                body.append(lines[i])
                i += 1
            out.append((start + 1, section, textwrap.dedent("\n".join(body))))
        i += 1
    return out


BLOCKS = _blocks()


def _tree(code: str) -> ast.Module | None:
    try:
        return ast.parse(code)
    except SyntaxError:  # a signature sketch, not a program
        return None


def test_the_guide_has_the_examples():
    assert len(BLOCKS) >= 10
    assert sum(_tree(c) is not None for _, _, c in BLOCKS) >= len(BLOCKS) - 2


@pytest.mark.parametrize("line,section,code", BLOCKS, ids=[f"line{b[0]}" for b in BLOCKS])
def test_pdem_names_come_from_pdem_api(line, section, code):
    tree = _tree(code)
    if tree is None:
        assert not re.search(r"^\s*(from|import)\s+pdem", code, re.M), f"line {line}: unparsable imports"
        return
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "pdem":
            names = {a.name for a in node.names}
            if node.module == "pdem.api":
                problems += [f"{n} is not in pdem.api.__all__" for n in sorted(names - API)]
                continue
            allowed, where = OUTSIDE_API.get(node.module, (set(), None))
            if where is not None:  # a contract module of its own, in its own section
                problems += [f"'from {node.module} import …' outside '{where}'"] if where != section else []
                continue
            problems += [
                f"'from {node.module} import {n}': import it from pdem.api"
                for n in sorted(names)
                if n not in allowed or n in API
            ]
        elif isinstance(node, ast.Import):
            problems += [f"'import {a.name}'" for a in node.names if a.name.startswith("pdem.")]
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "pdem":
            if node.attr != "api" and node.attr not in API:
                problems.append(f"pdem.{node.attr} is not in pdem.api")
        elif (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Attribute)
            and isinstance(node.value.value, ast.Name)
            and node.value.value.id == "pdem"
            and node.value.attr == "api"
            and node.attr not in API
        ):
            problems.append(f"pdem.api.{node.attr} is not in pdem.api.__all__")
    assert not problems, f"docs/plugins.md line {line} ({section}): " + "; ".join(problems)


def test_names_outside_the_api_are_not_in_it():
    """Once pdem.api exports a name, the guide imports it from there."""
    for module, (names, _) in OUTSIDE_API.items():
        assert not (names or set()) & API, f"{module}: now in pdem.api, import it from there"


def test_the_reference_covers_the_members_plugins_use():
    text = GUIDE.read_text()
    ref = text[text.index('<a id="reference"></a>') :]
    members = [
        # ContactLaw
        "name", "kind", "history_size", "n_coef", "Params", "pair_kernel", "wall_kernel", "rigid",
        "list_needs", "pair_coefficients", "coefficients", "critical_dt", "suggested_dt",
        "contact_stiffness", "contact_damping", "contact_slip", "slip_slope_ratio", "make_integrator",
        "materials.mixed", "materials.index", "effective_moduli", "damping_ratio",
        # Boundary
        "params", "walls", "active", "add_wall", "set_active", "build", "on_stage", "before_step",
        "apply_forces", "after_step", "measurements", "summary", "records", "state", "restore",
        "stage_roles", "stage_remedies", "wall_materials", "STAGE_COLUMN", "stage_rows", "listed",
        # the simulation
        "sim.time", "sim.dt", "sim.step_count", "sim.stage", "sim.gravity", "sim.law", "sim.materials",
        "sim.walls", "sim.particles", "n_owned", "sim.get_particles()", "sim.exact_sum", "sim.count",
        "sim.particle_sum", "sim.remove_particles", "sim.register_field", "sim.set_wall_active",
        "sim.set_wall_motion", "sim.add_load_stiffness", "REMOVED", "inv_m",
        # walls and motions
        "offset", "reference_point", "force", "torque", "n_contacts", "facet_loads()", "velocity",
        "Controlled", "RigidBody", "hold()", "release(", "set_velocity(", "velocity_now", "held",
    ]  # fmt: skip
    missing = [m for m in members if f"`{m}" not in ref and f"{m}`" not in ref]
    assert not missing, f"docs/plugins.md's reference does not document: {missing}"


# ------------------------------------------------------------------------- executing the examples


def _defines_plugin(tree: ast.Module) -> bool:
    bases = {"ContactLaw", "Boundary"}
    return any(
        isinstance(n, ast.ClassDef) and any(isinstance(b, ast.Name) and b.id in bases for b in n.bases)
        for n in tree.body
    )


def _top_names(tree: ast.Module) -> set[str]:
    out = set()
    for n in tree.body:
        if isinstance(n, ast.FunctionDef | ast.ClassDef):
            out.add(n.name)
        elif isinstance(n, ast.Assign):
            out |= {t.id for t in n.targets if isinstance(t, ast.Name)}
        elif isinstance(n, ast.Import | ast.ImportFrom):
            out |= {(a.asname or a.name).split(".")[0] for a in n.names}
    return out


def _used_names(tree: ast.Module) -> set[str]:
    """Names the block reads and binds nowhere (not as an argument, a target or an import)."""
    bound = {n.arg for n in ast.walk(tree) if isinstance(n, ast.arg)}
    bound |= {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and not isinstance(n.ctx, ast.Load)}
    bound |= {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef | ast.ClassDef)}
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Load)}
    return used - bound


def _program(index: int) -> str:
    """The class block ``index`` with the earlier blocks that define the names it uses (the force
    function and the wrappers before a law class), in the guide's order."""
    parsed = [(i, _tree(c)) for i, (_, _, c) in enumerate(BLOCKS)]
    defined = {i: _top_names(t) for i, t in parsed if t is not None and i < index}
    need, chosen = {index}, set()
    while need:
        k = need.pop()
        chosen.add(k)
        tree = parsed[k][1]
        free = _used_names(tree) - _top_names(tree) - set(dir(builtins))
        for name in free:
            owners = [i for i, names in defined.items() if name in names and i not in chosen]
            if owners:
                need.add(max(owners))
    return "\n\n".join(BLOCKS[k][2] for k in sorted(chosen))


PLUGIN_BLOCKS = [
    i for i, (_, _, c) in enumerate(BLOCKS) if (t := _tree(c)) is not None and _defines_plugin(t)
]


def _filled(model) -> dict:
    """Values for the required fields of a parameter model (a material named "glass")."""
    out = {}
    for key, f in model.model_fields.items():
        if not f.is_required() or key == "type":
            continue
        ann = f.annotation
        if ann is str:
            out[key] = "glass"
        elif ann in (float, int) or typing.get_origin(ann) is typing.Union:
            out[key] = 1.0
        else:  # a Vec3
            out[key] = (0.0, 0.0, 1.0)
    return out


def test_the_guide_defines_a_law_and_boundaries():
    kinds = {
        b.id
        for i in PLUGIN_BLOCKS
        for n in _tree(BLOCKS[i][2]).body
        if isinstance(n, ast.ClassDef)
        for b in n.bases
        if isinstance(b, ast.Name)
    }
    assert {"ContactLaw", "Boundary"} <= kinds


@pytest.mark.parametrize("index", PLUGIN_BLOCKS, ids=[f"line{BLOCKS[i][0]}" for i in PLUGIN_BLOCKS])
def test_plugin_examples_import_and_construct(index, tmp_path, monkeypatch):
    line = BLOCKS[index][0]
    path = tmp_path / f"guide_example_{line}.py"
    path.write_text(_program(index))
    monkeypatch.chdir(tmp_path)  # a script's own output (none expected) lands here
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module  # numba caches kernels of importable modules
    try:
        spec.loader.exec_module(module)
    finally:
        sys.modules.pop(path.stem, None)
    classes = [
        c for c in vars(module).values()
        if isinstance(c, type) and c.__module__ == path.stem and issubclass(c, ContactLaw | Boundary)
    ]  # fmt: skip
    assert classes, f"docs/plugins.md line {line}: no law or boundary class"
    for cls in classes:
        if issubclass(cls, ContactLaw):
            law = cls(**_filled(cls.Params))
            mt = MaterialTable()
            mt.add(Material("glass"))
            table = law.coefficients(mt)
            assert table.shape == (1, 1, cls.n_coef)
        else:
            params = cls.Params(type="example", **_filled(cls.Params))
            boundary = cls("example", params)
            sim = Simulation()
            sim.add_material("glass")
            sim.gravity = (0.0, 0.0, -9.81)
            sim.add_boundary(boundary)
            assert boundary.walls, f"{cls.__name__} built no wall"
            boundary.set_active(sim, False)
            boundary.set_active(sim, True)


def test_drop_weight_example_holds_its_body_while_off(tmp_path):
    """The guide's hold/release pattern does what it says."""
    (index,) = [i for i in PLUGIN_BLOCKS if "class DropWeight" in BLOCKS[i][2]]
    namespace: dict = {}
    exec(compile(_program(index), "guide", "exec"), namespace)
    sim = Simulation()
    sim.add_material("glass")
    sim.gravity = (0.0, 0.0, -9.81)
    sim.add_particles([[0.0, 0.0, 0.0]], 1e-3, motion="fixed")
    sim.dt = 1e-5
    b = sim.add_boundary(namespace["DropWeight"]("drop", pdem.api.BoundaryParams(type="drop_weight")))
    b.set_active(sim, False)
    sim.run(steps=20)
    assert b.body.held and b.ball.offset[2] == 0.0
    b.set_active(sim, True)
    sim.run(steps=20)
    assert not b.body.held and b.ball.offset[2] < 0.0
