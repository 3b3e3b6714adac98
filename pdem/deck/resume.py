"""The deck of a resumed run: the resolved deck stored in the checkpoint, with the changes a resume allows.

``pdem resume CHECKPOINT --set KEY=VALUE`` needs only the checkpoint: its ``deck`` attribute holds the
resolved deck of the run that wrote it (every default filled in, file paths absolute), so the deck
file may have moved or changed since. The ``--set`` overrides are applied to that deck and the result
is validated like any deck; then :func:`resume_changes` compares the two resolved decks key by key.

What a resume may change is what decides *how the run goes on*, never the scene the checkpoint holds:

* the current stage's end conditions (``stages.<name>.end.*``, e.g. a ``max_time`` that was reached),
  its ``dt``, its ``output`` cadence and its solver settings (``stages.<name>.contact.*``);
  everything about the stages after it (they have not started),
  and stages added at the end;
* ``output.*`` (snapshot cadence, formats, fields, series, checkpoints) except ``output.directory``
  (``pdem resume --output DIR`` chooses where the continuation goes);
* ``run.dt`` (the stability limit is checked when the run starts), ``run.force_dt``,
  ``run.stiffness_limit``, ``run.max_overlap`` (the overlap that stops the run as unstable: it changes
  when a run is stopped, never its trajectory), ``run.max_particles``, ``run.balance_threshold``,
  ``run.decomposition``; and ``title``;
* the contact law's solver settings that it lists as resumable (``LawParams.resumable``: DEM-C's
  solver, tolerance, iteration cap, …), e.g. to continue a run with a tighter solve.

Everything else (materials, the contact law, particle sources, boundaries, the domain, gravity, skin,
seed, the stages that have already run) describes the scene: changing it would not continue the same
run, so it is refused with the key named.
"""

from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import DeckError
from .load import ResolvedDeck, validate_deck
from .overrides import apply_overrides
from .problems import Loc, make_deck_error
from .stage_roles import stage_key_changes, switch_off_problems

__all__ = ["ResumePoint", "resume_deck", "resume_changes", "RESUMABLE_RUN_KEYS"]

#: keys of [run] a resume may change
RESUMABLE_RUN_KEYS = frozenset(
    {
        "dt",
        "force_dt",
        "stiffness_limit",
        "max_overlap",
        "max_particles",
        "balance_threshold",
        "decomposition",
    }
)

ALLOWED = (
    "a resume may change the current stage's end conditions, dt, output and solver settings "
    "(stages.<name>.end.*, stages.<name>.dt, stages.<name>.output.*, stages.<name>.contact.*), "
    "anything in later stages, stages added at the end, "
    "output.* (not output.directory: use --output DIR), run.dt, run.force_dt, run.stiffness_limit, "
    "run.max_overlap, run.max_particles, run.balance_threshold, run.decomposition, title and the "
    "contact law's solver settings (DEM-C: "
    "contact.solver, tolerance, max_iterations, check_every, apgd_start, relaxation, scaling, "
    "load_tolerance, load_mass_scaling); to change anything else start a new run"
)


@dataclass(frozen=True)
class ResumePoint:
    """Where a checkpoint stands: ``stage_index`` (the stage it is in, or the next one to start when
    ``started`` is False; the number of stages for a finished run), ``step`` and ``time``."""

    stage_index: int
    started: bool
    step: int
    time: float

    @classmethod
    def from_checkpoint(cls, state: dict, meta: dict) -> ResumePoint:
        return cls(
            stage_index=int(meta["stage_index"]),
            started=bool(int(meta.get("stage_started", 1))),
            step=int(state["scalars/step"]),
            time=float(state["scalars/time"]),
        )

    def has_run(self, index: int) -> bool:
        """Did stage ``index`` start before the checkpoint?"""
        return index < self.stage_index or (index == self.stage_index and self.started)


def _stage_index(data: dict) -> dict[str, int]:
    stages = data.get("stages")
    return {
        s["name"]: k
        for k, s in enumerate(stages if isinstance(stages, list) else [])
        if isinstance(s, dict) and isinstance(s.get("name"), str)
    }


def _stand_in_missing_files(data: dict, point: ResumePoint, stand_in: Path) -> dict[int, str]:
    """File sources inserted before the checkpoint are never read again, so their file may be gone:
    point them at an existing file for validation; returns ``{source index: original path}``."""
    names = _stage_index(data)
    first = next(iter(names), None)
    missing: dict[int, str] = {}
    particles = data.get("particles")
    for k, src in enumerate(particles if isinstance(particles, list) else []):
        if not isinstance(src, dict) or src.get("source") != "file" or not isinstance(src.get("path"), str):
            continue
        index = names.get(src.get("stage") or first, -1)
        if point.has_run(index) and not Path(src["path"]).is_file():
            missing[k] = src["path"]
            src["path"] = str(stand_in)
    return missing


def _law_keys_at_top(data: dict, overrides: tuple[str, ...]) -> tuple[str, ...]:
    """``contact.<law>.KEY=V`` (and a stage's ``stages.S.contact.<law>.KEY=V``) as ``contact.KEY=V``
    for the law the checkpoint runs: its resolved deck holds that law's parameters in [contact]
    itself, where a [contact.<law>] table would clash with them, while a deck, and the documents,
    may name them either way."""
    contact = data.get("contact")
    law = contact.get("law") if isinstance(contact, dict) else None
    if not isinstance(law, str) or isinstance(contact.get(law), dict):
        return overrides
    out = []
    for text in overrides:
        key, sep, value = text.partition("=")
        parts = key.strip().split(".")
        for at in (0, 2):  # contact.<law>.KEY, stages.S.contact.<law>.KEY
            if (
                len(parts) == at + 3
                and (at == 0 or parts[0] == "stages")
                and parts[at] == "contact"
                and parts[at + 1] == law
            ):
                key = ".".join(parts[: at + 1] + parts[at + 2 :])
                break
        out.append(f"{key}{sep}{value}" if sep else text)
    return tuple(out)


def resume_deck(
    meta: dict, overrides: tuple[str, ...], point: ResumePoint, checkpoint: Path
) -> tuple[ResolvedDeck, ResolvedDeck]:
    """``(deck of the checkpoint, deck to continue with)``: the checkpoint's resolved deck, and the
    same with ``overrides`` applied; raises :class:`~pdem.errors.DeckError` naming every key a resume
    may not change (see the module doc)."""
    source = f"stored in checkpoint {checkpoint}"
    text = meta.get("deck")
    if not isinstance(text, str) or not text:
        raise make_deck_error(
            [((), "the checkpoint holds no deck; it was not written by the pdem command")], source
        )
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise make_deck_error([((), f"the checkpoint's deck is not valid TOML: {exc}")], source) from None
    deck_path = Path(str(meta.get("deck_path") or "")) if meta.get("deck_path") else None
    base = deck_path.parent if deck_path is not None else Path.cwd()
    missing = _stand_in_missing_files(data, point, Path(checkpoint).resolve())
    overrides = _law_keys_at_top(data, tuple(overrides))
    try:
        old = validate_deck(copy.deepcopy(data), path=deck_path, base_dir=base)
    except DeckError as exc:
        raise make_deck_error(
            [(loc, f"{msg} (the checkpoint's own deck no longer validates: an installed plugin changed?)")
             for loc, msg in exc.problems],
            source,
        ) from None  # fmt: skip
    new = validate_deck(data, path=deck_path, base_dir=base, overrides=overrides)
    for resolved in (old, new):
        for k, original in missing.items():
            if k < len(resolved.deck.particles):
                resolved.deck.particles[k].path = original
    applied, _ = apply_overrides(copy.deepcopy(data), overrides)
    resumable = frozenset()
    if old.law_class is new.law_class:
        resumable = frozenset(getattr(new.law_class.Params, "resumable", frozenset()))
    problems = resume_changes(old.resolved_dict(), new.resolved_dict(), point, resumable)
    # a boundary's stage keys may change while every stage already run keeps its role, and a stage
    # added (or renamed before it runs) must not switch a boundary off without the deck saying so
    problems = stage_key_changes(old, new, point, problems)
    problems += switch_off_problems(old, new)
    if problems:
        texts = {o.loc: o.text for o in applied}
        marked = []
        for loc, msg in problems:
            src = [
                t for at, t in texts.items() if tuple(loc[: len(at)]) == at or tuple(at[: len(loc)]) == loc
            ]
            marked.append((loc, f"{msg} (from --set {src[-1]})" if src else msg))
        raise make_deck_error(marked, f"resumed from {checkpoint}")
    return old, new


def _diff(a: Any, b: Any, loc: Loc) -> list[Loc]:
    """Locations where ``a`` and ``b`` differ (tables key by key, arrays of tables entry by entry)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[Loc] = []
        for k in list(a) + [k for k in b if k not in a]:
            if k not in a or k not in b:
                out.append(loc + (k,))
            else:
                out += _diff(a[k], b[k], loc + (k,))
        return out
    if (
        isinstance(a, list)
        and isinstance(b, list)
        and len(a) == len(b)
        and any(isinstance(x, dict) for x in a + b)
    ):
        return [p for i, (x, y) in enumerate(zip(a, b, strict=True)) for p in _diff(x, y, loc + (i,))]
    return [] if a == b else [loc]


def resume_changes(
    old: dict, new: dict, point: ResumePoint, law_keys: frozenset[str] = frozenset()
) -> list[tuple[Loc, str]]:
    """Problems for every key that differs between the resolved decks ``old`` and ``new`` and that a
    resume may not change (see the module doc); ``law_keys``: the ``[contact]`` keys of the (same)
    law that may change."""
    problems: list[tuple[Loc, str]] = []
    old_stages = old.get("stages", [])
    new_stages = new.get("stages", [])
    names = [s.get("name") for s in old_stages]
    for loc in _diff(
        {k: v for k, v in old.items() if k != "stages"}, {k: v for k, v in new.items() if k != "stages"}, ()
    ):
        head = loc[0]
        if head == "title":
            continue
        if head == "run" and len(loc) > 1 and loc[1] in RESUMABLE_RUN_KEYS:
            continue
        if head == "contact" and len(loc) > 1 and loc[1] in law_keys:
            continue
        if head == "output" and len(loc) > 1 and loc[1] != "directory":
            continue
        if head == "output":
            problems.append(
                (
                    loc,
                    "cannot be changed on resume: choose where the continued run goes with "
                    "pdem resume CHECKPOINT --output DIR (default: the checkpoint's own output)",
                )
            )
            continue
        problems.append(
            (loc, f"cannot be changed on resume: it is part of the scene the checkpoint holds; {ALLOWED}")
        )
    for i, st in enumerate(old_stages):
        if not point.has_run(i):
            continue  # not started: free to change (or remove)
        name = names[i]
        finished = i < point.stage_index
        if i >= len(new_stages):
            problems.append(
                (
                    ("stages", i),
                    f"stage '{name}' has {'run' if finished else 'started'} in the checkpoint "
                    "and cannot be removed on resume",
                )
            )
            continue
        for loc in _diff(st, new_stages[i], ("stages", i)):
            key = loc[2] if len(loc) > 2 else None
            if finished:
                problems.append(
                    (
                        loc,
                        f"stage '{name}' has finished in the checkpoint (at step {point.step}), so its "
                        f"settings cannot change; add a stage after it instead, e.g. --set "
                        f"stages.{len(new_stages)}.name=more --set stages.{len(new_stages)}.end.time=...",
                    )
                )
            elif key not in ("end", "dt", "output", "contact"):
                problems.append(
                    (
                        loc,
                        f"stage '{name}' is under way in the checkpoint: only its end conditions, dt, "
                        f"output and solver settings may change on resume (stages.{name}.end.*, .dt, "
                        ".output.*, .contact.*)",
                    )
                )
    return problems
