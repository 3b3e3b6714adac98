"""What each boundary does in each stage, and the stages a resume adds without saying it.

A boundary names the stages it acts in with its stage keys (``stages``, ``off_stages``, and a device's
own roles such as the triaxial cell's ``mould_stages``, ``consolidation_stage``, ``shear_stage`` and
``later_shear_stages``); :meth:`pdem.boundaries.api.Boundary.stage_roles` turns them into a role per
stage (None: off, or idle, doing nothing to the particles). A boundary is therefore switched off in
every stage its keys do not name.

In a deck its author wrote, that is how a device ends (a mould after the settling, a plug after the
fill): nothing is checked. A stage added when a run is resumed (``pdem resume CHECKPOINT --set
stages.3.name=more …``) is different: the boundary's keys were written before the stage existed, so
a boundary on in the stage before would be switched off in it without anyone having said so. A
finished triaxial test resumed that way lost its membrane and servo: the specimen, at 20 kPa, sprang
apart (kinetic energy from 7.7e-4 J to 3.9 J) and the run ended with exit code 0. So a resume must
name every added stage in which such a boundary would go off, with a key that keeps it on or with
``off_stages`` (:func:`switch_off_problems`), and may change the stage keys to do so, as long as the
roles of the stages that have run stay what they were (:func:`stage_key_changes`).

Calls (in :func:`pdem.deck.resume.resume_deck`, on the resolved decks of the checkpoint and of the
continuation)::

    problems = resume_changes(...)
    problems = stage_key_changes(old, new, point, problems)
    problems += switch_off_problems(old, new)
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ..boundaries.api import Boundary, names_stage, stage_keys
from .problems import Loc, make_deck_error

if TYPE_CHECKING:
    from .load import ResolvedDeck

__all__ = [
    "SwitchOff", "check_new_stages", "new_stage_indices", "roles", "stage_key_changes",
    "switch_off_problems", "switched_off",
]


@dataclass(frozen=True)
class SwitchOff:
    """Boundary ``boundary`` plays ``role`` in stage ``previous`` and would be off in ``stage``
    (index ``index``) only because none of its stage keys (``keys``) names it; ``remedies``: (key,
    value, what it then does) from :meth:`Boundary.stage_remedies`."""

    boundary: str
    kind: str
    index: int
    stage: str
    previous: str
    role: str
    keys: tuple[str, ...]
    remedies: tuple[tuple[str, Any, str], ...]


def _stage_names(resolved: ResolvedDeck) -> list[str]:
    return [s.name for s in resolved.deck.stages]


def _roles(cls: type, params: Any, names: Sequence[str]) -> list[str | None]:
    # a plugin class that does not derive from Boundary gets the generic keys' answer
    method = getattr(cls, "stage_roles", Boundary.stage_roles)
    return list(method(params, list(names)))


def _remedies(cls: type, params: Any, stage: str) -> list[tuple[str, Any, str]]:
    method = getattr(cls, "stage_remedies", Boundary.stage_remedies)
    return list(method(params, stage))


def roles(resolved: ResolvedDeck, name: str) -> list[str | None]:
    """The role of boundary ``name`` in each stage of ``resolved``, in deck order (None: off)."""
    return _roles(resolved.boundary_classes[name], resolved.boundaries[name], _stage_names(resolved))


def switched_off(resolved: ResolvedDeck, stages: Iterable[int]) -> list[SwitchOff]:
    """Boundaries on in stage k − 1 and off in stage k, for each index k of ``stages`` (k ≥ 1), only
    because none of their stage keys names stage k. A deck's author may mean it (how a device
    ends): call it for the stages nobody wrote the keys for, those a resume adds
    (:func:`new_stage_indices`)."""
    names = _stage_names(resolved)
    wanted = sorted({k for k in stages if 1 <= k < len(names)})
    out: list[SwitchOff] = []
    if not wanted:
        return out
    for name, params in resolved.boundaries.items():
        cls = resolved.boundary_classes[name]
        role = _roles(cls, params, names)
        for k in wanted:
            if role[k - 1] is None or role[k] is not None or names_stage(params, names[k]):
                continue
            out.append(SwitchOff(
                boundary=name, kind=str(getattr(params, "type", cls.__name__)), index=k, stage=names[k],
                previous=names[k - 1], role=str(role[k - 1]), keys=tuple(stage_keys(params)),
                remedies=tuple(_remedies(cls, params, names[k])),
            ))  # fmt: skip
    return out


def new_stage_indices(old: ResolvedDeck, new: ResolvedDeck) -> list[int]:
    """Indices of the stages of ``new`` that ``old`` does not have at the same place: stages added at
    the end, and stages not yet run that were renamed."""
    before = _stage_names(old)
    return [k for k, s in enumerate(_stage_names(new)) if k >= len(before) or before[k] != s]


def _set_text(loc: str, value: Any) -> str:
    return f"--set '{loc}={json.dumps(value, ensure_ascii=False)}'"


def _message(item: SwitchOff) -> str:
    ways = "; or ".join(
        f"{_set_text(f'boundaries.{item.boundary}.{key}', value)} ({what})"
        for key, value, what in item.remedies
    )
    return (
        f"boundary '{item.boundary}' ({item.kind}) is on in stage '{item.previous}' ({item.role}) and would "
        f"be switched off in stage '{item.stage}', added on resume, only because none of its stage keys "
        f"({', '.join(item.keys)}) names it; say what it does there: {ways}"
    )


def switch_off_problems(old: ResolvedDeck, new: ResolvedDeck) -> list[tuple[Loc, str]]:
    """Deck problems (key path, message) for every boundary that a stage added on resume would
    switch off without saying so (:func:`switched_off` over :func:`new_stage_indices`): each names
    the keys to set, to keep the boundary on or to switch it off explicitly."""
    found = switched_off(new, new_stage_indices(old, new))
    return [(("boundaries", item.boundary), _message(item)) for item in found]


def check_new_stages(old: ResolvedDeck, new: ResolvedDeck, source: str | None = None) -> None:
    """Raise :class:`~pdem.errors.DeckError` (exit code 2) listing :func:`switch_off_problems`."""
    problems = switch_off_problems(old, new)
    if problems:
        raise make_deck_error(problems, source)


def _stage_key_verdict(old: ResolvedDeck, new: ResolvedDeck, point: Any, loc: Loc) -> str | None:
    """For a change at ``loc`` that a resume refuses: ``""`` if it is a boundary's stage key whose
    change leaves the roles of every stage that has run as they were (a resume may make it), a
    message if it is a stage key whose change alters them, None if it is not a stage key."""
    if len(loc) < 3 or loc[0] != "boundaries":
        return None
    name, key = loc[1], loc[2]
    if name not in old.boundaries or name not in new.boundaries:
        return None
    if old.boundary_classes.get(name) is not new.boundary_classes.get(name):
        return None
    if key not in stage_keys(new.boundaries[name]):
        return None
    old_names, new_names = _stage_names(old), _stage_names(new)
    ran = [k for k in range(len(old_names)) if point.has_run(k)]
    if any(k >= len(new_names) or new_names[k] != old_names[k] for k in ran):
        return None  # a stage that has run was changed: resume_changes says so
    before = _roles(old.boundary_classes[name], old.boundaries[name], old_names)
    after = _roles(new.boundary_classes[name], new.boundaries[name], new_names)
    changed = [k for k in ran if before[k] != after[k]]
    if not changed:
        return ""
    k = changed[0]
    return (
        f"would change what boundary '{name}' did in stage '{old_names[k]}', which has run "
        f"({before[k] or 'off'} → {after[k] or 'off'}); a resume may change a boundary's stage keys only "
        "for the stages still to come (e.g. to name a stage added at the end)"
    )


def stage_key_changes(
    old: ResolvedDeck, new: ResolvedDeck, point: Any, problems: list[tuple[Loc, str]]
) -> list[tuple[Loc, str]]:
    """``problems`` (from :func:`pdem.deck.resume.resume_changes`) without the changes of a
    boundary's stage keys that leave the stages already run as they were (``point.has_run(k)``),
    and with a precise message for those that would not."""
    out: list[tuple[Loc, str]] = []
    for loc, msg in problems:
        verdict = _stage_key_verdict(old, new, point, tuple(loc))
        if verdict is None:
            out.append((loc, msg))
        elif verdict:
            out.append((loc, verdict))
    return out
