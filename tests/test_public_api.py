"""The engine's seams stay public: only the simulation/contact-store core touches a simulation's
private state, and plugins (pdem's own, registered by entry points, and the example package under
plugins/) import nothing private from pdem — everything they need is in :mod:`pdem.api`."""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PDEM = ROOT / "pdem"

# the core: the simulation itself and the contact store it owns
CORE = {PDEM / "simulation.py", PDEM / "contact" / "store.py"}
PRIVATE_SIM = re.compile(r"\b(?:sim|simulation|self\.sim)\._[A-Za-z]\w*")


def _python_files():
    for base in (PDEM, ROOT / "plugins", ROOT / "tools", ROOT / "examples"):
        yield from sorted(base.rglob("*.py"))


def test_no_private_simulation_state_outside_the_core():
    offenders = []
    for path in _python_files():
        if path in CORE:
            continue
        for lineno, line in enumerate(path.read_text().splitlines(), 1):
            for m in PRIVATE_SIM.finditer(line.split("#", 1)[0]):
                offenders.append(f"{path.relative_to(ROOT)}:{lineno}: {m.group(0)}")
    assert not offenders, "private simulation state used outside the core:\n" + "\n".join(offenders)


def test_the_check_catches_a_private_access(tmp_path):
    """The pattern is not vacuous."""
    assert PRIVATE_SIM.search("x = sim._pair_hist[0]")
    assert PRIVATE_SIM.search("self.sim._decomp.widen(w)")
    assert not PRIVATE_SIM.search("sim.contact_store.hist")


def _module_of(path: Path) -> str:
    rel = path.relative_to(ROOT / "pdem" if path.is_relative_to(PDEM) else path.parents[1])
    parts = list(rel.with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join((["pdem"] if path.is_relative_to(PDEM) else []) + parts)


def _private_imports(path: Path) -> list[str]:
    """Imported modules or names that are private to another package of pdem."""
    module = _module_of(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text())
    bad = []
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            if src == "__future__":
                continue
            targets = [src] + [f"{src}.{a.name}" for a in node.names if a.name.startswith("_")]
        for t in targets:
            if not t.startswith("pdem"):
                continue
            parts = t.split(".")
            for k, part in enumerate(parts):
                if part.startswith("_") and not part.startswith("__"):
                    owner = ".".join(parts[:k])  # the package the private module belongs to
                    if owner != package:  # a sibling _kernels.py of one's own package is fine
                        bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: {t}")
                    break
    return bad


def _plugin_files() -> list[Path]:
    """pdem's own entry-point targets (a package target: all its modules) and plugins/."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    files: set[Path] = set()
    for group in cfg["project"]["entry-points"].values():
        for target in group.values():
            mod = target.split(":")[0]
            rel = Path(*mod.split(".")[1:])
            if (PDEM / rel / "__init__.py").exists():
                files.update((PDEM / rel).glob("*.py"))
            else:
                files.add(PDEM / rel.with_suffix(".py"))
    files.update((ROOT / "plugins").rglob("*.py"))
    return sorted(files)


def test_plugins_import_nothing_private():
    files = _plugin_files()
    assert PDEM / "laws" / "hertz_mindlin.py" in files and PDEM / "io" / "hdf5.py" in files
    assert any("pdem_linear_spring" in str(f) for f in files)
    bad = [b for f in files for b in _private_imports(f)]
    assert not bad, "plugins importing private pdem modules (use pdem.api):\n" + "\n".join(bad)


@pytest.mark.parametrize(
    "source, flagged",
    [
        ("from pdem._jit import njit", True),
        ("from pdem.contact import _kernels", True),
        ("import pdem.contact._tangential", True),
        ("from pdem.api import njit", False),
        ("from . import _kernels", False),  # a sibling of one's own package
    ],
)
def test_private_import_check_is_not_vacuous(tmp_path, source, flagged, monkeypatch):
    f = PDEM / "complementarity" / "_probe_for_test.py"
    # parse a synthetic module as if it lived in pdem.complementarity, without writing into the tree
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: source if self == f else _orig(self))
    assert bool(_private_imports(f)) == flagged


_orig = Path.read_text


def test_api_exports_resolve():
    import pdem.api as api

    missing = [name for name in api.__all__ if not hasattr(api, name)]
    assert not missing


def _pdem_imports(path: Path) -> list[tuple[int, str]]:
    """Every pdem module a file imports (absolute name), with its line: ``from x import y`` gives
    ``x`` (and ``x.y`` when that is a module)."""
    module = _module_of(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                src = ".".join(base + ([node.module] if node.module else []))
            else:
                src = node.module or ""
            out.append((node.lineno, src))
            for a in node.names:
                sub = f"{src}.{a.name}"
                if (PDEM / Path(*sub.split(".")[1:])).with_suffix(".py").exists():
                    out.append((node.lineno, sub))
    return [(n, m) for n, m in out if m == "pdem" or m.startswith("pdem.")]


def _boundary_plugin_files() -> list[Path]:
    """The modules of pdem's built-in boundaries: the entry-point targets of ``pdem.boundaries``
    and the pdem.boundaries modules they import (their helpers), except the contract itself."""
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    todo = [PDEM / Path(*t.split(":")[0].split(".")[1:]).with_suffix(".py")
            for t in cfg["project"]["entry-points"]["pdem.boundaries"].values()]
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        for _, mod in _pdem_imports(f):
            if mod.startswith("pdem.boundaries.") and mod != "pdem.boundaries.api":
                todo.append(PDEM / Path(*mod.split(".")[1:]).with_suffix(".py"))
    return sorted(seen)


def test_builtin_boundaries_import_only_the_public_api():
    """pdem's own boundaries are written as a user's plugin would be: from pdem they import
    :mod:`pdem.api` and their own helper modules, nothing else."""
    files = _boundary_plugin_files()
    assert PDEM / "boundaries" / "triaxial.py" in files and PDEM / "boundaries" / "builtin.py" in files
    own = {_module_of(f) for f in files} | {"pdem.api", "pdem.boundaries"}
    bad = [f"{f.relative_to(ROOT)}:{n}: {m}" for f in files for n, m in _pdem_imports(f) if m not in own]
    assert not bad, "built-in boundaries importing pdem beyond pdem.api:\n" + "\n".join(bad)


# which packages a package may not import: the layers run one way
#   geometry (wall shapes, motions, contact-geometry kernels) < contact < boundaries
FORBIDDEN = {
    "geometry": ("pdem.contact", "pdem.boundaries", "pdem.neighbor", "pdem.simulation",
                 "pdem.complementarity"),
    "contact": ("pdem.boundaries", "pdem.simulation", "pdem.runner"),
    "neighbor": ("pdem.boundaries", "pdem.runner"),
    "parallel": ("pdem.boundaries", "pdem.contact", "pdem.simulation", "pdem.runner"),
}


def test_layers_run_one_way():
    bad = []
    for pkg, forbidden in FORBIDDEN.items():
        for f in sorted((PDEM / pkg).glob("*.py")):
            for n, mod in _pdem_imports(f):
                if any(mod == x or mod.startswith(x + ".") for x in forbidden):
                    bad.append(f"{f.relative_to(ROOT)}:{n}: {mod}")
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_import_walk_is_not_vacuous(tmp_path, monkeypatch):
    f = PDEM / "contact" / "_probe_for_test.py"
    src = "from ..boundaries import api\nfrom pdem.geometry import walls\nimport numpy\n"
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: src if self == f else _orig(self))
    mods = [m for _, m in _pdem_imports(f)]
    assert "pdem.boundaries.api" in mods and "pdem.geometry.walls" in mods and "numpy" not in mods
