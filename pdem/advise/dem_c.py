"""DEM-C's solver settings for a deck: what it carries, and what to give a deck that carries none.

Each stage is classified from what the scene knows (:mod:`pdem.advise.scene`: the boundaries'
:class:`~pdem.boundaries.api.Loading` and :meth:`~pdem.boundaries.api.Boundary.extent`, the sources'
``starts_loose`` and ``settles``), never from a boundary's type, in this order:

* ``wave``: a boundary launches or times a wave. Rigid grains carry none: nothing is proposed;
* ``impact``: a boundary drops a free body into the grains (its mass over the grains' is reported);
* ``fill``: loose grains inserted in the stage fall under gravity (even inside a device that holds
  them later);
* ``confined``: a device holds the sample (its ``extent``); with a stress carried by a plate on the
  grains (an ``on_weight`` loading), the plate's settings;
* ``flow``: a loading whose rate gravity sets (a ``note`` and no quasi-static rate: a discharge);
* ``push``: a quasi-static rate outside a device (a body pushed into a bed): no measured settings;
* ``prepares``: nothing of its own (a settling): the settings of the stage it prepares;
* ``none``: no rule fits: the library defaults.

Every kind's settings are a shipped deck's measured ones (:mod:`pdem.advise.rules`, ``DEM_C_*``).
The deck-wide table takes the first stage's; a stage whose settings differ gets the keys a stage may
change (``[stages.contact.complementarity]``). The step (``max_travel``, or ``dt`` where the deck's
``[run]`` gives DEM-P's step or the kind sets it from the scene's speed) and the recovery of a poured
bed's overlaps are deck-wide.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from ..deck.toml_writer import key as toml_key
from . import rules
from .scene import Scene

__all__ = ["StageKind", "Proposal", "classify", "propose", "base_params", "stage_params", "has_solver"]

LAW = "complementarity"

#: the solver keys that are measured together; which of them a solver reads
SOLVER_KEYS = ("solver", "tolerance", "max_iterations", "check_every", "apgd_start", "relaxation",
               "load_tolerance")  # fmt: skip
_READS = {
    "apgd": ("solver", "tolerance", "max_iterations", "check_every", "apgd_start", "load_tolerance"),
    "jacobi": ("solver", "tolerance", "max_iterations", "check_every", "relaxation"),
    "gauss_seidel": ("solver", "tolerance", "max_iterations", "relaxation"),
}
#: the keys that give DEM-C's step, and the recovery keys: a deck's own choice is kept
STEP_KEYS = ("dt", "dt_fraction", "max_travel", "reference_speed")
RECOVERY_KEYS = ("recovery_speed", "recovery_steps")

SOURCES = {
    "fill": "docs/dem_c.md, The hopper at each method's best settings (the fill: APGD at 30–45 and Jacobi "
    "at 40–150 iterations failed at h = 1e-3 s)",
    "flow": "docs/experiments/hopper.md, DEM-C (10 block-scaled Jacobi sweeps at ω = 0.4: flow rate +1.85 % "
    "over seeds 1–6); docs/dem_c.md, Block scaling and The hopper at each method's best settings "
    "(2/λ_max ≥ 0.412)",
    "confined": "docs/experiments/triaxial.md, DEM-C (φ within 2° of DEM-P's stiff limit; caps 250–1,000); "
    "docs/dem_c.md, Warm start",
    "plate": "docs/dem_c.md, Sliding contacts (a sheared packing under a free plate, caps 200 and 1,000); "
    "docs/experiments/direct_shear.md, DEM-C",
    "impact": "docs/experiments/cone_penetration.md, Drops with both methods and What the DEM-C depth "
    "depends on; docs/notes/engine.md, commit b45e04c (Jacobi at a mass ratio of 84:1)",
    "push": "docs/experiments/cone_penetration.md, The push; docs/study/cone_penetration.md",
    "wave": "docs/dem_c.md, Where it fails (part 2); docs/study/wave_chain.md; "
    "docs/experiments/shock_wave.md",
    "recovery": "docs/dem_c.md, Initial overlaps and the recovery speed; "
    "docs/experiments/cone_penetration.md, What the DEM-C depth depends on",
}


@dataclass
class StageKind:
    """One stage's kind and the settings proposed for it (empty for a wave)."""

    stage: str
    kind: str
    why: str
    settings: dict[str, Any] = field(default_factory=dict)
    travel: float | None = None  # max_travel: r_min per step at 1 m/s
    dt: float | None = None  # a step set by the scene's own speed [s]
    rule: str = ""
    source: str = ""
    numbers: dict[str, Any] = field(default_factory=dict)
    origin: str = ""  # the stage whose settings it takes (a settling), else its own name

    def label(self) -> str:
        s = self.settings
        if not s:
            return f"{self.kind}: none"
        return f"{self.kind}: {s['solver']} × {s['max_iterations']}"


@dataclass
class Proposal:
    kinds: list[StageKind]
    suggestions: dict[str, Any]
    numbers: dict[str, Any]
    reason: str
    source: str


# ---------------------------------------------------------------------------------------------
# the deck's own settings
# ---------------------------------------------------------------------------------------------


def _contact(raw: dict) -> dict:
    return raw.get("contact") if isinstance(raw.get("contact"), dict) else {}


def _table(raw: dict) -> dict:
    sub = _contact(raw).get(LAW)
    return sub if isinstance(sub, dict) else {}


def runs_dem_c(resolved: Any) -> bool:
    """Does the deck run DEM-C (its law's parameters are DEM-C's)?"""
    from ..complementarity.method import Complementarity

    return isinstance(resolved.law_params, Complementarity.Params)


def has_solver(raw: dict, resolved: Any) -> bool:
    """Does the deck choose DEM-C's solver ([contact.complementarity], or [contact] when it runs it)?"""
    return "solver" in _table(raw) or (runs_dem_c(resolved) and "solver" in _contact(raw))


def base_params(resolved: Any, raw: dict) -> tuple[Any, Any]:
    """DEM-C's deck-wide parameters (the law's ``Params``) and its own step (``[contact.complementarity]``
    ``dt`` of a deck that does not run it; None otherwise)."""
    from ..complementarity.method import Complementarity
    from ..deck.load import LAW_STEP_KEYS

    if isinstance(resolved.law_params, Complementarity.Params):  # the deck runs it
        return resolved.law_params, None
    sub = dict(_table(raw))
    own_dt = sub.get("dt")
    sub = {k: v for k, v in sub.items() if k not in LAW_STEP_KEYS}  # steps, not parameters
    try:
        return Complementarity.Params.model_validate(sub), own_dt
    except Exception:  # noqa: BLE001 - refused when the deck switches law; the defaults stand here
        return Complementarity.Params(), own_dt


def stage_params(resolved: Any, index: int, base: Any) -> Any:
    """DEM-C's parameters in stage ``index``: ``base`` with the stage's ``[stages.contact]`` values for
    complementarity on top (its own table, or also the top-level keys when the deck runs DEM-C)."""
    from ..deck.load import stage_contact_values

    stages = resolved.deck.stages
    table = stages[index].contact if index < len(stages) else {}
    if not table:
        return base
    if isinstance(resolved.law_params, type(base)):
        values = stage_contact_values(table, LAW)
    else:  # a DEM-P deck: DEM-C's own table only
        own = table.get(LAW)
        values = dict(own) if isinstance(own, dict) else {}
    try:
        return type(base).model_validate({**base.model_dump(), **values})
    except Exception:  # noqa: BLE001 - checked when the deck switches law; the base settings stand
        return base


# ---------------------------------------------------------------------------------------------
# kinds of stage
# ---------------------------------------------------------------------------------------------


def library() -> tuple[dict[str, Any], float]:
    """The library's value of every solver key, and its max_travel (pdem/complementarity/method.py)."""
    from ..complementarity.method import Complementarity

    p = Complementarity.Params()
    return {k: getattr(p, k) for k in SOLVER_KEYS}, float(p.max_travel)


def _defaults() -> tuple[dict[str, Any], float]:
    """The library's settings of its default solver (the keys that solver reads), and its max_travel."""
    lib, travel = library()
    return {k: lib[k] for k in _READS.get(str(lib["solver"]), SOLVER_KEYS)}, travel


def classify(scene: Scene) -> list[StageKind]:
    """Every stage's kind (see the module doc), with the settings measured for it."""
    loadings = scene.loadings()
    names = list(scene.stage_names)
    defaults, default_travel = _defaults()
    devices: dict[str, bool] = {}  # boundaries that hold the sample -> a plate carries their stress
    for name, params in scene.boundaries.items():
        try:
            extent = scene.boundary_class(name).extent(params)
        except Exception:  # noqa: BLE001 - a boundary whose extent cannot be told holds nothing here
            extent = None
        if extent is not None:
            devices[name] = any(ld.on_weight and ld.stress > 0 for ld in loadings.get(name, ()))
    r_min = min((g.r_min for g in scene.groups), default=math.nan)
    kinds: list[StageKind] = []
    for s in names:
        active = [
            (n, ld) for n, lds in loadings.items() if scene.acts_in(n, s) for ld in lds if s in ld.stages
        ]
        waves = [n for n, ld in active if ld.wave]
        impacts = [(n, ld) for n, ld in active if ld.impact]
        held = [n for n in devices if scene.acts_in(n, s)]
        flows = [n for n, ld in active if ld.note and ld.rate_key is None and not (ld.wave or ld.impact)]
        pushes = [n for n, ld in active if ld.rate_key]
        fills = [g for g in scene.groups if g.stage == s and g.loose and scene.gravity > 0]
        if waves:
            kinds.append(StageKind(
                s, "wave", f"{_who(waves, 'launches or times', 'launch or time')} a wave",
                rule="none: rigid grains carry no wave; DEM-C's front moves as far per step as its solver "
                "carries an impulse (the method finding names DEM-P). The shipped wave decks run DEM-C "
                "with APGD (the shock-wave bed, where projected Jacobi diverges without a recovery_speed "
                "cap) or Jacobi (the chain), to show that failure", source=SOURCES["wave"]))  # fmt: skip
        elif impacts:
            name, ld = impacts[0]
            mass, grain = scene.body_mass(name), scene.grain_mass
            ratio = mass / grain if mass is not None and grain > 0 else math.nan
            heavy = not ratio <= rules.HEAVY_BODY_MASS_RATIO  # unknown: taken as heavy
            dt = rules.DEM_C_IMPACT_TRAVEL * r_min / ld.speed if ld.speed > 0 else None
            nums = {f"{s}: body mass [kg]": mass if mass is not None else math.nan,
                    f"{s}: body / grain mass": ratio, f"{s}: impact speed [m/s]": ld.speed}  # fmt: skip
            limit = rules.HEAVY_BODY_MASS_RATIO
            if heavy and math.isfinite(ratio):
                why_apgd = (f"the body weighs {ratio:.3g} grain masses, above {limit:g}: projected Jacobi "
                            "did not converge at 84 and 170")  # fmt: skip
            elif heavy:
                why_apgd = ("the body's mass is not known here: taken as heavy (Jacobi did not converge at "
                            "84 and 170 grain masses)")  # fmt: skip
            else:
                why_apgd = (f"the body weighs {ratio:.3g} grain masses, below {limit:g} (Jacobi was not "
                            "measured there); the drop series ran its cones of 37 and 82 grain masses with "
                            "these settings")  # fmt: skip
            step = (f"h = {rules.DEM_C_IMPACT_TRAVEL:.2g} r_min / v at the impact speed {ld.speed:.3g} m/s"
                    if dt else "the automatic step (no impact speed known)")  # fmt: skip
            kinds.append(StageKind(
                s, "impact", f"boundaries.{name} drops a free body into the grains",
                dict(rules.DEM_C_IMPACT), None if dt else default_travel, dt,
                f"APGD capped at {rules.DEM_C_IMPACT['max_iterations']}: {why_apgd}; {step}",
                SOURCES["impact"], nums))  # fmt: skip
        elif fills:
            v = math.sqrt(2 * scene.gravity * scene.fall_height) if scene.fall_height > 0 else 0.0
            travel = rules.DEM_C_FILL_TRAVEL
            if v > rules.DEM_C_FILL_LANDING_SPEED:
                travel = rules.round_sig(travel * rules.DEM_C_FILL_LANDING_SPEED / v, 2, "down")
            groups = ", ".join(f"particles.{g.index}" for g in fills)
            kinds.append(StageKind(
                s, "fill", f"{groups}: loose grains fall under gravity", dict(rules.DEM_C_FILL), travel,
                rule=f"grains landing on a closed bottom: APGD capped at 60, check_every 5, max_travel "
                f"{travel:g}" + (f" (they land at ~{v:.2g} m/s, faster than the hopper's "
                f"{rules.DEM_C_FILL_LANDING_SPEED:g} m/s)" if travel < rules.DEM_C_FILL_TRAVEL else ""),
                source=SOURCES["fill"], numbers={f"{s}: landing speed [m/s]": v}))  # fmt: skip
        elif held:
            plate = any(devices[n] for n in held)
            kinds.append(StageKind(
                s, "confined", f"{_who(held, 'holds', 'hold')} the sample"
                + (" under a free plate resting on the grains" if plate else ""),
                dict(rules.DEM_C_CONFINED_PLATE if plate else rules.DEM_C_CONFINED),
                rules.DEM_C_CONFINED_TRAVEL,
                rule=("a free plate carries the stress: APGD warm at a cap of 1,000 (at 200 its load swung "
                      "0–3× the target), tolerance 1e-5 m/s, check_every 5, stopped when the walls' "
                      "loads settle to 1e-3 (0.28× the iterations), the automatic step"
                      if plate else "quasi-static and confined: APGD warm, cap 500 (250: q_peak −6.1 %, "
                      "1,000: −1.4 % in 1.7× the time), tolerance 1e-4 m/s, stopped when the walls' loads "
                      "settle to 1e-3 (0.36× the iterations), the automatic step"),
                source=SOURCES["plate" if plate else "confined"]))  # fmt: skip
        elif flows:
            kinds.append(StageKind(
                s, "flow", f"{_who(flows, 'lets', 'let')} the grains flow at a rate gravity sets",
                dict(rules.DEM_C_FLOW), rules.DEM_C_FILL_TRAVEL,
                rule="10 block-scaled Jacobi sweeps at relaxation 0.4 (below the loaded contacts' measured "
                "2/λ_max ≥ 0.412 in the hopper's discharge; 0.55 failed: measure another flow's bound with "
                "tools/jacobi_bound.py), max_travel 1.1", source=SOURCES["flow"]))  # fmt: skip
        elif pushes:
            kinds.append(StageKind(
                s, "push", f"{_who(pushes, 'loads', 'load')} the grains at a quasi-static rate, no "
                "device holds them", dict(defaults), default_travel,
                rule="no measured rule: the pushed cone's DEM-C runs (Jacobi capped at 100, h = 1e-4–4e-4 s, "
                "every step at the cap) were 17–29 % below DEM-P's q_c and did not close as the step "
                "shrank; a converged push was not run. The library defaults are proposed (the push deck "
                "carries Jacobi capped at 200, h = 1e-4 s)", source=SOURCES["push"]))  # fmt: skip
        else:
            kinds.append(StageKind(s, "prepares", "nothing of its own: no boundary loads the grains, none "
                                   "are inserted"))  # fmt: skip
    for k, kind in enumerate(kinds):  # a settling takes the settings of the stage it prepares
        if kind.kind != "prepares":
            continue
        later = [o for o in kinds[k + 1 :] if o.settings and o.kind != "prepares"]
        earlier = [o for o in reversed(kinds[:k]) if o.settings and o.kind != "prepares"]
        other = (later or earlier or [None])[0]
        follows = not later
        if other is None and any(o.kind == "wave" for o in kinds):
            kind.rule = "none: the deck measures a wave, which DEM-C does not carry"
            continue
        if other is None:
            kind.kind, kind.settings, kind.travel = "none", dict(defaults), default_travel
            kind.rule = "no rule fits: the library defaults"
            continue
        kind.settings, kind.travel, kind.dt = dict(other.settings), other.travel, other.dt
        kind.origin = other.stage
        if follows:
            kind.rule = f"it follows stage {other.stage} ({other.kind}) and keeps its settings"
        else:
            kind.rule = (f"it prepares stage {other.stage} ({other.kind}) and takes its settings, as every "
                         "measured deck settled with its test's (the drop bed: APGD capped at 300 for "
                         "0.02 s)")  # fmt: skip
    return kinds


# ---------------------------------------------------------------------------------------------
# the proposal
# ---------------------------------------------------------------------------------------------


def _who(names: list[str], one: str, many: str) -> str:
    """``boundaries.a loads`` / ``boundaries.a and boundaries.b load``."""
    names = [f"boundaries.{n}" for n in dict.fromkeys(names)]
    if len(names) == 1:
        return f"{names[0]} {one}"
    return f"{', '.join(names[:-1])} and {names[-1]} {many}"


def _in_contact(table: dict, key: str) -> bool:
    """Does a deck that runs DEM-C give its keys in ``table`` itself ([contact] or a stage's): ``key``
    (which may not be given twice), or any key and no [complementarity] subtable?"""
    mine = [k for k, v in table.items() if k != "law" and not isinstance(v, dict)]
    return key in table or (bool(mine) and not isinstance(table.get(LAW), dict))


def _top_key(raw: dict, resolved: Any, key: str) -> str:
    """Where the deck-wide ``key`` goes: ``[contact]`` when the deck runs DEM-C and gives its keys there,
    else ``[contact.complementarity]`` (always for ``dt``, a step only the law's table may give)."""
    if key != "dt" and runs_dem_c(resolved) and _in_contact(_contact(raw), key):
        return f"contact.{key}"
    return f"contact.{LAW}.{key}"


def _stage_key(raw: dict, resolved: Any, stage: str, key: str) -> str:
    stages = raw.get("stages") if isinstance(raw.get("stages"), list) else []
    table = next((t.get("contact") for t in stages if isinstance(t, dict) and t.get("name") == stage), None)
    if runs_dem_c(resolved) and isinstance(table, dict) and _in_contact(table, key):
        return f"stages.{toml_key(stage)}.contact.{key}"
    return f"stages.{toml_key(stage)}.contact.{LAW}.{key}"


def _given(raw: dict, resolved: Any) -> dict[str, Any]:
    """The deck-wide DEM-C keys the deck gives: [contact.complementarity], and [contact] when it runs
    DEM-C."""
    direct = {}
    if runs_dem_c(resolved):
        direct = {k: v for k, v in _contact(raw).items() if k != "law" and not isinstance(v, dict)}
    return {**direct, **_table(raw)}


def _given_in_stage(raw: dict, resolved: Any, stage: str) -> dict[str, Any]:
    """The DEM-C keys stage ``stage``'s ``[stages.contact]`` gives."""
    stages = raw.get("stages") if isinstance(raw.get("stages"), list) else []
    table = next((t.get("contact") for t in stages if isinstance(t, dict) and t.get("name") == stage), None)
    if not isinstance(table, dict):
        return {}
    own = table.get(LAW) if isinstance(table.get(LAW), dict) else {}
    direct = {k: v for k, v in table.items() if not isinstance(v, dict)} if runs_dem_c(resolved) else {}
    return {**direct, **own}


def _reads(settings: dict[str, Any]) -> tuple[str, ...]:
    return _READS.get(str(settings.get("solver")), SOLVER_KEYS)


def propose(scene: Scene, resolved: Any, raw: dict) -> Proposal:
    """The settings for a deck that does not choose DEM-C's solver: see the module doc."""
    kinds = classify(scene)
    _, default_travel = _defaults()
    table = _table(raw)
    numbers: dict[str, Any] = {f"stage {k.stage}": k.label() for k in kinds}
    for k in kinds:
        numbers.update(k.numbers)
    used = [k for k in kinds if k.settings]
    if not used:
        return Proposal(kinds, {}, numbers, _kinds_text(kinds), SOURCES["wave"])
    lib, _ = library()
    given = _given(raw, resolved)
    sugg: dict[str, Any] = {}
    top = used[0]
    for key in _reads(top.settings):  # the kind's keys, and the library's where the deck gives another
        want = top.settings.get(key, lib[key])
        if want is not None and (key in top.settings or (key in given and given[key] != want)):
            sugg[_top_key(raw, resolved, key)] = want
    effective = {**lib, **given, **{k: top.settings.get(k, lib[k]) for k in _reads(top.settings)}}
    for k in used[1:]:
        here = {**effective, **_given_in_stage(raw, resolved, k.stage)}
        for key in _reads(k.settings):
            want = k.settings.get(key, lib[key])
            if here.get(key) != want and want is not None:  # (an option's "off" cannot be written)
                sugg[_stage_key(raw, resolved, k.stage, key)] = want
    notes: list[str] = []
    # the step, deck-wide: the smallest any stage asks for
    r_min = min(g.r_min for g in scene.groups)
    steps = [(k.dt, "dt", k) if k.dt else ((k.travel or default_travel) * r_min, "travel", k) for k in used]
    h, how, who = min(steps, key=lambda x: x[0])
    numbers["DEM-C h [s]"] = h
    run = raw.get("run") if isinstance(raw.get("run"), dict) else {}
    own_step = [k for k in STEP_KEYS if k in table] + (
        [f"run.{k}" for k in ("dt", "dt_fraction") if k in run] if runs_dem_c(resolved) else []
    )
    if own_step:
        notes.append(f"the deck's own DEM-C step ({', '.join(own_step)}) is kept")
    elif how == "dt" or any(k in run for k in ("dt", "dt_fraction")):
        sugg[_top_key(raw, resolved, "dt")] = dt = rules.round_sig(h, 2, "down")
        notes.append(f"step dt = {dt:.2g} s (stage {who.origin or who.stage}"
                     + (", as [contact.complementarity] dt: [run] gives DEM-P's step" if how != "dt" else "")
                     + ")")  # fmt: skip
    else:
        sugg[_top_key(raw, resolved, "max_travel")] = who.travel
        notes.append(f"step max_travel = {who.travel:g} (h = {h:.2g} s at r_min = {r_min:.3g} m; stage "
                     f"{who.origin or who.stage})")  # fmt: skip
    # a bed poured with soft grains that a body enters
    sources = list(dict.fromkeys(k.source for k in used if k.source))
    packed = [g for g in scene.groups if g.settles or _from_file(resolved, g.index)]
    entering = [k.stage for k in kinds if k.kind in ("impact", "push")]
    confined = [k.stage for k in kinds if k.kind == "confined"]
    if packed and entering and not confined:
        mine = [k for k in RECOVERY_KEYS if k in table]
        if mine:
            notes.append(f"the deck's own {', '.join(mine)} kept")
        else:
            sugg[_top_key(raw, resolved, "recovery_speed")] = rules.DEM_C_RECOVERY_SPEED
            sugg[_top_key(raw, resolved, "recovery_steps")] = rules.DEM_C_RECOVERY_STEPS
            notes.append(
                f"recovery_speed = {rules.DEM_C_RECOVERY_SPEED:g} m/s with recovery_steps = "
                f"{rules.DEM_C_RECOVERY_STEPS}: particles.{packed[0].index} is a packing made with soft "
                f"grains that stage {entering[0]} enters; removed within a step its overlaps throw the "
                "bed's top up. Settle such a bed briefly with DEM-C: the drop bed settled 0.1 s at the "
                "solver's residual let the ball in 7 % less deep than after 0.02 s"
            )
        sources.append(SOURCES["recovery"])
    elif packed:
        notes.append(
            f"particles.{packed[0].index} is a packing made with soft grains: its overlaps are removed over "
            "recovery_steps (50) steps, the default"
            + (" (no recovery_speed cap: in a device the solver's residual may exceed it, and a cap below "
               "the residual piles up penetrations)" if confined else "")
        )  # fmt: skip
    reason = _kinds_text(kinds) + ". " + "; ".join(notes)
    own = [k.stage for k in used[1:] if any(s.startswith(f"stages.{toml_key(k.stage)}.") for s in sugg)]
    if own:
        reason += (f". [contact.complementarity] holds stage {top.stage}'s settings; "
                   + (f"stage {own[0]} gets its" if len(own) == 1 else f"stages {', '.join(own)} get their")
                   + " own ([stages.contact.complementarity], the keys a stage may change)")  # fmt: skip
    return Proposal(kinds, sugg, numbers, reason, "; ".join(sources))


def _kinds_text(kinds: list[StageKind]) -> str:
    """The stages' kinds and rules in words, stages of the same kind and rule together."""
    groups: list[tuple[list[str], StageKind]] = []
    for k in kinds:
        if groups and (groups[-1][1].kind, groups[-1][1].why, groups[-1][1].rule) == (k.kind, k.why, k.rule):
            groups[-1][0].append(k.stage)
        else:
            groups.append(([k.stage], k))
    return "; ".join(
        f"stage{'s' if len(names) > 1 else ''} {', '.join(names)}: {k.kind} ({k.why}) → {k.rule}"
        for names, k in groups
    )


def _from_file(resolved: Any, index: int) -> bool:
    """Does ``[[particles]]`` table ``index`` read its grains from a file (a packing from elsewhere)?"""
    classes = getattr(resolved, "source_classes", [])
    return index < len(classes) and bool(getattr(classes[index], "path_keys", ()))


def describe(resolved: Any, raw: dict, scene: Scene) -> tuple[str, dict[str, Any]]:
    """The settings the deck carries, stage by stage, in words and numbers; and where the rules here
    would choose another solver."""
    base, own_dt = base_params(resolved, raw)
    parts, numbers = [], {}
    kinds = {k.stage: k for k in classify(scene)}
    differ = []
    for i, st in enumerate(resolved.deck.stages):
        p = stage_params(resolved, i, base)
        extra = [f"tolerance {p.tolerance:g}"]
        if p.solver == "apgd":
            extra.append(f"apgd_start {p.apgd_start}")
        else:
            extra.append(f"relaxation {p.relaxation:g}")
        if p.check_every != 1:
            extra.append(f"check_every {p.check_every}")
        parts.append(f"{st.name}: {p.solver} × {p.max_iterations} ({', '.join(extra)})")
        numbers[f"stage {st.name}"] = f"{p.solver} × {p.max_iterations}"
        k = kinds.get(st.name)
        if k is not None and k.settings and k.settings["solver"] != p.solver:
            differ.append(f"{st.name} ({k.kind}: {k.settings['solver']})")
    r_min = min(g.r_min for g in scene.groups)
    if scene.rigid and scene.run_dt:
        step = f"h = {scene.run_dt:.3g} s ({scene.run_dt_key})"
    elif isinstance(own_dt, int | float) and not isinstance(own_dt, bool):
        step = f"h = {own_dt:.3g} s ([contact.complementarity] dt)"
    elif scene.run_dt:
        step = f"h = {scene.run_dt:.3g} s ({scene.run_dt_key}, both methods' step)"
    elif scene.dt_fraction is not None:
        step = f"run.dt_fraction = {scene.dt_fraction:g} (both methods')"
    else:
        step = f"max_travel {base.max_travel:g} (h = {base.max_travel * r_min / base.reference_speed:.2g} s)"
    text = "; ".join(parts) + f"; step {step}"
    if base.recovery_speed is not None:
        text += f"; recovery_speed {base.recovery_speed:g} m/s over {base.recovery_steps} step(s)"
    if differ:
        text += (". The rules of this finding would choose another solver for stage(s) " + ", ".join(differ)
                 + "; the deck's own settings are kept")  # fmt: skip
    return text, numbers
