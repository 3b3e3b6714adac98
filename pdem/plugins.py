"""One registry over ``importlib.metadata`` entry points.

Groups: ``pdem.contact_laws``, ``pdem.boundaries``, ``pdem.writers``, ``pdem.sources``. pdem's
built-ins are registered through pdem's own ``pyproject.toml`` exactly like third-party plugins. The
entry-point name is the value written in a deck (``law = "hertz_mindlin"``, ``source = "lattice"``).
An unknown name is an error that lists the installed names; a plugin that fails to import is
reported, and is fatal only when used.

A name registered in one group by two distributions is an error as soon as the group is consulted
(listed or loaded from): which of the two a deck would get is otherwise undefined, and the same deck
would mean different things on different machines. The message names both distributions and what
to do (uninstall one, or have one of them rename its entry point).
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from typing import Any

from .errors import PluginError

__all__ = ["GROUPS", "PluginInfo", "available", "load", "load_contact_law"]

_SINGULAR = {
    "contact_laws": "contact law",
    "boundaries": "boundary",
    "writers": "writer",
    "sources": "particle source",
}

GROUPS = {
    "contact_laws": "pdem.contact_laws",
    "boundaries": "pdem.boundaries",
    "writers": "pdem.writers",
    "sources": "pdem.sources",
}


@dataclass(frozen=True)
class PluginInfo:
    group: str
    name: str
    value: str
    distribution: str


def _dist_name(ep: EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    name = getattr(dist, "name", None) if dist is not None else None
    return str(name) if name else "?"


def _entries(group: str) -> dict[str, EntryPoint]:
    """The entry points of ``group`` by name; a name registered twice is a PluginError.

    The same (distribution, value) listed twice is one registration, not a conflict.
    """
    found: dict[str, list[EntryPoint]] = {}
    for ep in entry_points(group=GROUPS[group]):
        same = found.setdefault(ep.name, [])
        if not any(_dist_name(e) == _dist_name(ep) and e.value == ep.value for e in same):
            same.append(ep)
    clashes = {name: eps for name, eps in found.items() if len(eps) > 1}
    if clashes:
        name, eps = sorted(clashes.items())[0]
        owners = " and ".join(f"'{_dist_name(e)}' ({e.value})" for e in eps)
        dists = sorted({_dist_name(e) for e in eps})
        more = f" (and {len(clashes) - 1} more duplicated name(s))" if len(clashes) > 1 else ""
        raise PluginError(
            f"{_SINGULAR[group]} '{name}' is registered twice in entry-point group {GROUPS[group]}, "
            f"by {owners}{more}; pdem cannot tell which one a deck means. Uninstall one of them "
            f"(pip uninstall {' or '.join(d for d in dists if d != '?') or '…'}) or ask one author to "
            "rename the entry point"
        )
    return {name: eps[0] for name, eps in found.items()}


def available(group: str) -> dict[str, PluginInfo]:
    """Installed plugins of ``group`` (a key of :data:`GROUPS`), by name."""
    return {name: PluginInfo(group, name, ep.value, _dist_name(ep)) for name, ep in _entries(group).items()}


def load(group: str, name: str) -> Any:
    """Import and return the object registered as ``name`` in ``group``."""
    eps = _entries(group)
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
