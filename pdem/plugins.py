"""One registry over ``importlib.metadata`` entry points.

Groups: ``pdem.contact_laws``, ``pdem.boundaries``, ``pdem.writers``. pdem's built-ins are
registered through pdem's own ``pyproject.toml`` exactly like third-party plugins. The entry-point
name is the value written in a deck (``law = "hertz_mindlin"``). An unknown name is an error that
lists the installed names; a plugin that fails to import is reported, and is fatal only when used.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

from .errors import PluginError

__all__ = ["GROUPS", "PluginInfo", "available", "load", "load_contact_law"]

_SINGULAR = {"contact_laws": "contact law", "boundaries": "boundary", "writers": "writer"}

GROUPS = {
    "contact_laws": "pdem.contact_laws",
    "boundaries": "pdem.boundaries",
    "writers": "pdem.writers",
}


@dataclass(frozen=True)
class PluginInfo:
    group: str
    name: str
    value: str
    distribution: str


def available(group: str) -> dict[str, PluginInfo]:
    """Installed plugins of ``group`` (a key of :data:`GROUPS`), by name."""
    out: dict[str, PluginInfo] = {}
    for ep in entry_points(group=GROUPS[group]):
        dist = ep.dist.name if ep.dist is not None else "?"
        out[ep.name] = PluginInfo(group, ep.name, ep.value, dist)
    return out


def load(group: str, name: str) -> Any:
    """Import and return the object registered as ``name`` in ``group``."""
    eps = {ep.name: ep for ep in entry_points(group=GROUPS[group])}
    if name not in eps:
        names = sorted(eps)
        close = difflib.get_close_matches(name, names, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        installed = ", ".join(names) or "(none)"
        raise PluginError(
            f"unknown {_SINGULAR[group]} '{name}'.{hint} Installed: {installed}. "
            "Install the package that provides it (pip install …) or fix the name."
        )
    try:
        return eps[name].load()
    except Exception as exc:  # noqa: BLE001 - any import failure of a plugin is reported the same way
        raise PluginError(
            f"{_SINGULAR[group]} '{name}' ({eps[name].value}) failed to import: "
            f"{type(exc).__name__}: {exc}. Reinstall or fix the plugin package."
        ) from exc


def load_contact_law(name: str, **params: Any):
    """Instantiate the contact law registered as ``name`` with ``params``."""
    cls = load("contact_laws", name)
    return cls(**params)
