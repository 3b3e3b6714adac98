"""``pdem advise``: the findings, the changes they make, the report, and ``--apply``.

See ``docs/advise.md`` for what each number means and where each rule comes from; the numbers
themselves live in :mod:`pdem.advise.rules`.
"""

from __future__ import annotations

import copy
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..contact.stability import STIFFNESS_LIMIT
from ..errors import InputError
from . import dem_c, rules
from .scene import Scene, deck_scene, run_probe

__all__ = ["Finding", "Advice", "advise", "apply"]

VERDICTS = ("ok", "warn", "change")


@dataclass
class Finding:
    """One thing the advice looked at.

    ``topic``: what (``step``, ``overlap``, ``inertial``, ``stage_ends``, ``sample_size``, ``method``,
    ``dem_c_settings``, ``scene``, ``probe``); ``where``: the stage, boundary, material or deck table it
    belongs to; ``numbers``: the values (SI units, names as in docs/advise.md); ``verdict``: ``ok``,
    ``warn`` or ``change``; ``reason``: why, in words; ``source``: the rule's source; ``changes``: the
    ``--set`` changes it makes (applied by ``--apply``); ``suggestions``: changes it proposes but does
    not apply.
    """

    topic: str
    where: str
    verdict: str
    reason: str
    source: str = ""
    numbers: dict[str, Any] = field(default_factory=dict)
    changes: dict[str, Any] = field(default_factory=dict)
    suggestions: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "topic": self.topic,
            "where": self.where,
            "verdict": self.verdict,
            "reason": self.reason,
            "source": self.source,
            "numbers": {k: _plain(v) for k, v in self.numbers.items()},
            "changes": {k: _plain(v) for k, v in self.changes.items()},
            "suggestions": {k: _plain(v) for k, v in self.suggestions.items()},
        }


def _plain(v: Any) -> Any:
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    return v


@dataclass
class Advice:
    """The advice on one deck: its findings, the changes (deck key path → new value, as ``--set``
    overrides) that ``--apply`` writes, and suggestions it does not apply."""

    deck: str
    overrides: tuple[str, ...]
    findings: list[Finding]
    scene: dict[str, Any]
    probe: dict[str, Any]
    raw: dict = field(repr=False, default_factory=dict)
    resolved: Any = field(repr=False, default=None)

    def _merged(self, kind: str) -> dict[str, Any]:
        """Every finding's ``changes`` or ``suggestions``, later findings winning."""
        out: dict[str, Any] = {}
        for f in self.findings:
            out.update(getattr(f, kind))
        return out

    @property
    def changes(self) -> dict[str, Any]:
        return self._merged("changes")

    @property
    def suggestions(self) -> dict[str, Any]:
        return self._merged("suggestions")

    def set_args(self, which: str = "changes") -> list[str]:
        """The changes (or suggestions) as ``--set KEY=VALUE`` texts."""
        from ..deck.toml_writer import value

        items = self.changes if which == "changes" else self.suggestions
        return [f"{k}={value(v)}" for k, v in items.items()]

    def to_dict(self) -> dict[str, Any]:
        return {
            "deck": self.deck,
            "overrides": list(self.overrides),
            "scene": _plain(self.scene),
            "probe": _plain(self.probe),
            "findings": [f.to_dict() for f in self.findings],
            "changes": {k: _plain(v) for k, v in self.changes.items()},
            "suggestions": {k: _plain(v) for k, v in self.suggestions.items()},
        }

    def report(self) -> str:
        s = self.scene
        lines = [
            f"pdem advise: {self.deck}"
            + (f" (--set {' --set '.join(self.overrides)})" if self.overrides else ""),
            f"  scene: {s['particles']:,.0f} grains ({s['counted']}), d = "
            f"{_mm(s['d_min'])}–{_mm(s['d_max'])} mm "
            f"(mean {_mm(s['d_mean'])} mm), law {s['law']}, stages {', '.join(s['stages'])}",
        ]
        probe = self.probe
        if probe.get("ran"):
            lines.append(
                f"  probe: {probe['steps']} steps of the first stage in {probe['wall_seconds']:.1f} s"
                + (" (cut at the time budget)" if probe.get("cut") else "")
                + f": {probe['particles']:,} grains, "
                + f"{probe['contacts_per_particle']:.2f} contacts per grain, "
                f"fastest {probe['max_speed']:.3g} m/s; the engine's stability estimate "
                f"{probe['dt_critical']:.4g} s"
            )
        else:
            lines.append(f"  probe: not run ({probe.get('reason', 'disabled')})")
        for f in self.findings:
            if f.topic in ("scene", "probe"):
                continue
            lines.append("")
            lines.append(f"[{f.verdict}] {f.topic} — {f.where}")
            nums = ", ".join(f"{k} = {_fmt(v)}" for k, v in f.numbers.items())
            if nums:
                lines.extend(_wrap(nums, "    "))
            lines.extend(_wrap(f.reason, "    "))
            if f.source:
                lines.extend(_wrap(f"source: {f.source}", "    "))
        lines.append("")
        changes = self.set_args("changes")
        if changes:
            lines.append("changes (pdem advise DECK --apply OUT.toml writes them; or run with):")
            lines.extend(f"  --set {c}" for c in changes)
        else:
            lines.append("changes: none")
        sugg = self.set_args("suggestions")
        if sugg:
            lines.append("suggestions (not applied; they change the cost or the physics, see above):")
            lines.extend(f"  --set {c}" for c in sugg)
        return "\n".join(lines)


def _mm(v: float) -> str:
    return f"{v * 1e3:.3g}" if math.isfinite(v) else "?"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if not math.isfinite(v):
            return "n/a" if math.isnan(v) else "inf"
        return f"{v:.3g}"
    return str(v)


def _wrap(text: str, indent: str, width: int = 100) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width=width, initial_indent=indent, subsequent_indent=indent) or [indent]


# ---------------------------------------------------------------------------------------------
# advise
# ---------------------------------------------------------------------------------------------


def advise(deck_path: str | Path, sets: tuple[str, ...] | list[str] = (), probe: bool = True,
           probe_budget: float = 10.0) -> Advice:  # fmt: skip
    """Advise on the deck at ``deck_path`` (with ``--set`` overrides ``sets``): see the module doc.
    Raises the deck's :class:`~pdem.errors.DeckError` (exit code 2) if it does not validate."""
    from ..deck import load_deck
    from ..deck.overrides import apply_overrides

    path = Path(deck_path)
    sets = tuple(sets)
    resolved = load_deck(path, sets)
    raw = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    apply_overrides(raw, sets)  # validated above: cannot fail
    scene = deck_scene(resolved, raw)
    probe_info: dict[str, Any] = {"ran": False, "reason": "--no-probe"}
    if probe:
        probe_info = run_probe(resolved, scene, budget=probe_budget)
        scene.probe = probe_info
        if probe_info.get("ran"):
            _apply_probe(scene, probe_info, resolved)
    advisor = _Advisor(scene, resolved, raw)
    findings = advisor.run()
    facts = {
        "particles": scene.n,
        "counted": "counted by the probe"
        if probe_info.get("ran") and len(scene.stages)
        else "; ".join(g.counted for g in scene.groups) or "none",
        "d_min": 2 * min((g.r_min for g in scene.groups), default=math.nan),
        "d_max": scene.d_max,
        "d_mean": scene.d_mean,
        "density": scene.density,
        "law": scene.law,
        "stages": [s.name for s in scene.stages],
        "gravity": scene.gravity,
        "packed_height": scene.packed_height,
        "fall_height": scene.fall_height,
    }
    return Advice(
        deck=str(path), overrides=sets, findings=findings, scene=facts, probe=probe_info, raw=raw,
        resolved=resolved,
    )  # fmt: skip


def _apply_probe(scene: Scene, info: dict[str, Any], resolved: Any) -> None:
    """The probe counted the first stage's grains: scale that stage's groups to the count, and
    recompute the stages (the probe's fastest grain is a speed of the first stage)."""
    from .scene import _stage_facts

    first = resolved.deck.stages[0].name
    groups = [g for g in scene.groups if g.stage == first]
    est = sum(g.count for g in groups if math.isfinite(g.count))
    if groups and est > 0 and info["particles"] > 0:
        for g in groups:
            g.count = g.count * info["particles"] / est
    scene.stages = [_stage_facts(scene, resolved, k) for k in range(len(resolved.deck.stages))]


class _Advisor:
    def __init__(self, scene: Scene, resolved: Any, raw: dict) -> None:
        self.scene = scene
        self.resolved = resolved
        self.raw = raw
        self.deck = resolved.deck
        self.findings: list[Finding] = []
        self.e_new: dict[str, float] = {}  # grain material -> proposed E
        self.dt_new: dict[str, float] = {}  # stage -> dt it will run with
        self.dt_old: dict[str, float] = {}
        self.dt_usable: dict[str, float] = {}  # stage -> the step DEM-P can run at (≤ dt_new)
        self.rate_factor: dict[str, float] = {}  # stage -> loading-rate factor
        self.hertz = scene.hertzian

    def run(self) -> list[Finding]:
        if not self.scene.groups:
            self.findings.append(Finding("scene", "particles", "warn", "the deck has no grains to advise on"))
            return self.findings
        self.overlap()
        self.step()
        self.inertial()
        self.stage_lengths()
        self.sample_size()
        self.method()
        self.dem_c_settings()
        return self.findings

    # ------------------------------------------------------------------ helpers
    def _material(self, name: str) -> Any:
        return self.deck.materials[name]

    def _e(self, name: str) -> float:
        return self.e_new.get(name, float(self._material(name).youngs_modulus))

    def _max_stress(self) -> tuple[float, str]:
        best = max(self.scene.stages, key=lambda s: s.stress)
        return best.stress, best.name

    def _stage_speed(self, stage: Any) -> tuple[float, str]:
        if not stage.speeds:
            return 0.0, "nothing moves it"
        return max(stage.speeds, key=lambda x: x[0])

    def _wall_partners(self) -> list[tuple[float, float]]:
        """(E, ν) of the walls' materials (rigid: inf, 0)."""
        out = []
        for spec in self.scene.wall_materials.values():
            out.append(
                (math.inf, 0.0) if spec.rigid else (float(spec.youngs_modulus), float(spec.poisson_ratio))
            )
        return out

    def _collision(self, speed: float) -> tuple[float, str]:
        """Shortest Hertz collision time at ``speed`` over the smallest grain of every grain material,
        grain–grain and grain–wall, with the proposed stiffness."""
        best, what = math.inf, ""
        for name in self.scene.grain_materials():
            mat = self._material(name)
            e, nu = self._e(name), float(mat.poisson_ratio)
            r = self.scene.r_min_of(name)
            m = float(mat.density) * 4.0 / 3.0 * math.pi * r**3
            t = rules.collision_time(m / 2, r / 2, rules.e_star(e, nu, e, nu), speed)
            if t < best:
                best, what = t, f"{name}–{name}"
            for ew, nuw in self._wall_partners():
                t = rules.collision_time(m, r, rules.e_star(e, nu, ew, nuw), speed)
                if t < best:
                    best, what = t, f"{name}–wall"
        return best, what

    def _live_bound(self) -> tuple[float, float]:
        """(predicted live step bound [s], the δ/d it is predicted at): the smallest over the grain
        materials, at the proposed stiffness, from the larger of the static overlap at the scene's
        largest stress and the overlap of its fastest impact (rules.live_bound_ratio)."""
        sc = self.scene
        stress, _ = self._max_stress()
        fastest = max((self._stage_speed(s)[0] for s in sc.stages), default=0.0)
        best, at = math.inf, 0.0
        for name in sc.grain_materials():
            mat = self._material(name)
            e, nu, rho = self._e(name), float(mat.poisson_ratio), float(mat.density)
            r = sc.r_min_of(name)
            ratio = rules.overlap_ratio(stress, 2 * r, e, nu)
            if fastest > 0:
                m = rho * 4.0 / 3.0 * math.pi * r**3
                hit = rules.impact_overlap(m / 2, r / 2, rules.e_star(e, nu, e, nu), fastest)
                ratio = max(ratio, hit / (2 * r))
            bound = rules.live_bound_ratio(ratio) * rules.rayleigh_time(r, rho, e, nu)
            if bound < best:
                best, at = bound, ratio
        return best, at

    def _rayleigh(self, proposed: bool = True) -> float:
        best = math.inf
        for name in self.scene.grain_materials():
            mat = self._material(name)
            e = self._e(name) if proposed else float(mat.youngs_modulus)
            best = min(
                best,
                rules.rayleigh_time(
                    self.scene.r_min_of(name), float(mat.density), e, float(mat.poisson_ratio)
                ),
            )
        return best

    # ------------------------------------------------------------------ overlap and stiffness
    def _wave_boundaries(self) -> list[str]:
        """The boundaries that strike grains or time a wave (its speed is set by the stiffness): their
        :class:`~pdem.boundaries.api.Loading` says ``wave``."""
        return [n for n, lds in self.scene.loadings().items() if any(ld.wave for ld in lds)]

    def _impact_boundaries(self) -> list[str]:
        """The boundaries that drop a body whose impact the advice does not estimate (``impact``)."""
        return [n for n, lds in self.scene.loadings().items() if any(ld.impact for ld in lds)]

    def overlap(self) -> None:
        sc = self.scene
        stress, stage = self._max_stress()
        where_stress = next(s.stress_from for s in sc.stages if s.name == stage)
        if not self.hertz:
            self.findings.append(Finding(
                "overlap", f"law {sc.law}", "ok",
                "the overlap and stiffness rules are for hertz_mindlin with material stiffness; "
                + ("DEM-C grains are rigid (no overlap, no stiffness step)" if sc.rigid
                   else f"law '{sc.law}' ({sc.parameterisation}) is left as it is"),
            ))  # fmt: skip
            return
        waves = self._wave_boundaries()
        drops = self._impact_boundaries()
        fastest = max((self._stage_speed(s) for s in sc.stages), key=lambda x: x[0])
        factors = {}
        for name in sc.grain_materials():
            mat = self._material(name)
            e, nu = float(mat.youngs_modulus), float(mat.poisson_ratio)
            grp_d = (
                2
                * sum(g.count * g.r_mean for g in sc.groups if g.material == name)
                / max(sum(g.count for g in sc.groups if g.material == name), 1e-300)
            )
            ratio = rules.overlap_ratio(stress, grp_d, e, nu)
            r = sc.r_min_of(name)
            m = float(mat.density) * 4.0 / 3.0 * math.pi * r**3
            impact = (
                rules.impact_overlap(m / 2, r / 2, rules.e_star(e, nu, e, nu), fastest[0]) / (2 * r)
                if fastest[0] > 0
                else 0.0
            )
            e_static = rules.modulus_for_overlap(e, ratio, rules.OVERLAP_TARGET) if ratio > 0 else 0.0
            # α ∝ E^(−2/5): the E whose fastest impact reaches IMPACT_OVERLAP_MAX
            e_impact = e * (impact / rules.IMPACT_OVERLAP_MAX) ** 2.5 if impact > 0 else 0.0
            e_needed = max(e_static, e_impact)
            nums = {
                "stress [Pa]": stress, "stress at": f"stage {stage}: {where_stress}",
                "d [m]": grp_d, "E [Pa]": e, "delta/d": ratio,
                "kappa=(E/stress)^(2/3)": rules.stiffness_number(e, stress) if stress > 0 else math.inf,
                "impact delta/d": impact, "impact speed [m/s]": fastest[0],
                "E for delta/d target [Pa]": e_static, "E for impact limit [Pa]": e_impact,
            }  # fmt: skip
            src = ("physics reference §2 (δ/d ≲ 1e-3…1e-2); target calibrated on the triaxial stiffness "
                   "series, docs/experiments/triaxial.md (q_peak ≈ 110 kPa (1 − 4.0 δ/d)); F = π d² σ/(φ Z), "
                   "Rothenburg & Bathurst 1989")  # fmt: skip
            if waves or drops:
                why = (f"boundaries {', '.join(waves)} measure waves, whose speed is set by E (Nesterenko)"
                       if waves else f"the body dropped by boundaries {', '.join(drops)} sets the "
                       "overlaps of its impact, which this advice does not estimate")  # fmt: skip
                self.findings.append(Finding(
                    "overlap", f"materials.{name}", "ok",
                    f"δ/d = {ratio:.2g}; the stiffness is not softened: {why}", src, nums))  # fmt: skip
                continue
            if ratio > rules.OVERLAP_MAX or impact > 2 * rules.IMPACT_OVERLAP_MAX:
                e_stiff = rules.round_sig(max(e_static, e_impact), 2, "up")
                self.findings.append(Finding(
                    "overlap", f"materials.{name}", "warn",
                    f"the grains are too soft: the mean contact overlaps by δ/d = {ratio:.3g} at "
                    f"{stress:.3g} Pa (above {rules.OVERLAP_MAX:g}, where a quasi-static quantity moves by "
                    f"~{4 * ratio:.0%} from its stiff limit) or an impact at {fastest[0]:.3g} m/s by "
                    f"{impact:.2g} d; E = {e_stiff:.3g} Pa gives δ/d = {rules.OVERLAP_TARGET:g} (costlier: "
                    f"the step shrinks as E^-1/2)", src, nums,
                    suggestions={f"materials.{name}.youngs_modulus": e_stiff}))  # fmt: skip
                continue
            if e_needed > 0 and e > rules.CHANGE_FACTOR * e_needed:
                e_prop = rules.round_sig(e_needed, 2, "up")
                factors[name] = e_prop / e
                nums["E proposed [Pa]"] = e_prop
                self.findings.append(Finding(
                    "overlap", f"materials.{name}", "change",
                    f"stiffer than the quantity needs: δ/d = {ratio:.2g} at {stress:.3g} Pa "
                    f"(κ = {nums['kappa=(E/stress)^(2/3)']:.3g}); E = {e_prop:.3g} Pa "
                    f"({e / e_prop:.3g}× softer) "
                    f"gives δ/d ≈ {rules.OVERLAP_TARGET:g} (about 1 % from the stiff limit) and keeps "
                    "impacts at "
                    f"{fastest[0]:.3g} m/s below {rules.IMPACT_OVERLAP_MAX:g} d; the step grows as E^-1/2",
                    src, nums, changes={f"materials.{name}.youngs_modulus": e_prop}))  # fmt: skip
            else:
                self.findings.append(Finding(
                    "overlap", f"materials.{name}", "ok",
                    f"δ/d = {ratio:.2g} at {stress:.3g} Pa is within "
                    f"[{rules.OVERLAP_TARGET / rules.CHANGE_FACTOR:.2g}, "
                    f"{rules.OVERLAP_MAX:g}]: stiff enough, and not more than {rules.CHANGE_FACTOR:g}× "
                    "stiffer "
                    "than needed", src, nums))  # fmt: skip
        if factors:
            gain = self._softening_gain(factors)
            if gain < rules.MIN_GAIN:
                for f in self.findings:
                    if f.topic == "overlap" and f.verdict == "change":
                        f.verdict, f.changes = "ok", {}
                        f.numbers["run faster by"] = gain
                        f.reason += (
                            f". Not proposed: the softer grains would make the run only {gain:.2f}× faster, "
                            "because the step is set by collisions at the scene's speeds (t_c ∝ E^-2/5)"
                        )
                factors = {}
        for name, k in factors.items():
            self.e_new[name] = float(self._material(name).youngs_modulus) * k
        if factors:  # non-rigid wall materials at least as stiff as the grains were keep that ratio
            k = max(factors.values())
            stiffest = max(float(self._material(n).youngs_modulus) for n in factors)
            for wname, spec in sc.wall_materials.items():
                if spec.rigid or wname in sc.grain_materials() or float(spec.youngs_modulus) < stiffest:
                    continue
                new = rules.round_sig(float(spec.youngs_modulus) * k, 2, "up")
                self.findings.append(Finding(
                    "overlap", f"materials.{wname} (walls)", "change",
                    "the wall material was at least as stiff as the grains "
                    f"({float(spec.youngs_modulus):.3g} Pa); "
                    f"softened by the same factor ({1 / k:.3g}×) so that wall contacts keep their ratio",
                    changes={f"materials.{wname}.youngs_modulus": new}))  # fmt: skip

    def _softening_gain(self, factors: dict[str, float]) -> float:
        """How much faster the run gets with the grains softened by ``factors``: the deck's steps as
        it stands against the steps at min(0.2 T_R, t_c/20) of the softer grains, weighted by the
        stages' lengths."""
        default = self._default_fraction() * self._rayleigh(proposed=False)
        before = sum((st.duration or 1.0) / (st.dt_given or default) for st in self.scene.stages)
        saved = dict(self.e_new)
        for name, k in factors.items():
            self.e_new[name] = float(self._material(name).youngs_modulus) * k
        after = self._steps_needed()
        self.e_new = saved
        return before / after if after > 0 else 1.0

    def _default_fraction(self) -> float:
        """The fraction of T_R at which stages that give no dt step: run.dt_fraction, else 0.2."""
        frac = self.scene.dt_fraction
        return float(frac) if frac is not None else rules.RAYLEIGH_FRACTION

    def _steps_needed(self) -> float:
        t_r = self._rayleigh(proposed=True)
        total = 0.0
        for st in self.scene.stages:
            t_c, _ = self._collision(self._stage_speed(st)[0])
            dt = min(rules.RAYLEIGH_FRACTION * t_r, t_c / rules.STEPS_PER_COLLISION)
            total += (st.duration or 1.0) / dt
        return total

    # ------------------------------------------------------------------ step
    def step(self) -> None:
        sc = self.scene
        if not self.hertz:
            if sc.rigid:
                self.findings.append(Finding(
                    "step", "all stages", "ok",
                    "DEM-C: the step is bounded by accuracy (how far grains travel per step), not by a "
                    "stiffness; see the method finding for its cost"))  # fmt: skip
            return
        t_r_old = self._rayleigh(proposed=False)
        t_r = self._rayleigh(proposed=True)
        frac = self._default_fraction()
        by_fraction = sc.dt_fraction is not None
        default_old = frac * t_r_old
        default_new = frac * t_r
        need: dict[str, float] = {}
        info: dict[str, tuple] = {}
        for st in sc.stages:
            v, label = self._stage_speed(st)
            t_c, pair = self._collision(v)
            n = min(rules.RAYLEIGH_FRACTION * t_r, t_c / rules.STEPS_PER_COLLISION)
            need[st.name] = n
            cur = st.dt_given if st.dt_given is not None else default_old
            self.dt_old[st.name] = cur
            info[st.name] = (v, label, t_c, pair, cur)
        given_run = sc.run_dt
        run_key = sc.run_dt_key  # run.dt, or the law table's dt
        own = {st.name for st in sc.stages if st.dt_key and st.dt_key != run_key}
        via_run = [st.name for st in sc.stages if st.dt_key == run_key]
        via_default = [st.name for st in sc.stages if st.dt_key is None]
        changes: dict[str, Any] = {}
        new_dt: dict[str, float] = {}
        if via_run:
            group = min(need[s] for s in via_run)
            if group / given_run >= rules.CHANGE_FACTOR:
                val = rules.round_sig(group, 2, "down")
                changes[run_key] = val
                for s in via_run:
                    new_dt[s] = val
            else:
                for s in via_run:
                    if need[s] / given_run >= rules.CHANGE_FACTOR:
                        changes[f"stages.{s}.dt"] = new_dt[s] = rules.round_sig(need[s], 2, "down")
                    else:
                        new_dt[s] = given_run
        for s in own:
            cur = info[s][4]
            if need[s] / cur >= rules.CHANGE_FACTOR:
                changes[f"stages.{s}.dt"] = new_dt[s] = rules.round_sig(need[s], 2, "down")
            else:
                new_dt[s] = cur
        if by_fraction and via_default:
            # run.dt_fraction steps these stages: too fine (or, with softer grains, too coarse) a
            # fraction is changed as a fraction, the key the deck uses
            group = min(need[s] for s in via_default)
            if group / default_new >= rules.CHANGE_FACTOR or (
                self.e_new and default_new > rules.WARN_FACTOR * group
            ):
                changes["run.dt_fraction"] = rules.round_sig(group / t_r, 2, "down")
            for s in via_default:
                new_dt[s] = changes.get("run.dt_fraction", frac) * t_r
        for s in via_default if not by_fraction else ():
            if self.e_new and default_new > rules.WARN_FACTOR * need[s]:
                changes[f"stages.{s}.dt"] = new_dt[s] = rules.round_sig(need[s], 2, "down")
            else:
                new_dt[s] = default_new
        live, live_at = self._live_bound()
        for st in sc.stages:
            mysugg: dict[str, Any] = {}
            v, label, t_c, pair, cur = info[st.name]
            dt = new_dt[st.name]
            self.dt_new[st.name] = dt
            usable = dt  # lowered below where the deck's step cannot run (past T_R or the live bound)
            nums = {
                "T_R [s]": t_r, "dt [s]": cur, "dt/T_R": cur / t_r_old,
                "speed [m/s]": v, "speed from": label, "t_c [s]": t_c, "t_c pair": pair,
                "steps per t_c": t_c / cur, "dt needed [s]": need[st.name],
            }  # fmt: skip
            if dt != cur:
                nums["dt advised [s]"] = dt
                nums["dt advised/T_R"] = dt / t_r
            nums["live bound predicted [s]"] = live
            nums["live bound at delta/d"] = live_at
            key = st.dt_key or (f"run.dt_fraction = {frac:g}" if by_fraction else "default (0.2 T_R)")
            src = ("physics reference §2: dt ≈ 0.1–0.3 T_R, at least ~20–50 steps per collision "
                   f"(here {rules.STEPS_PER_COLLISION}); t_c = 2.868 (m*²/(R* E*² v))^(1/5)")  # fmt: skip
            mine = {k: v2 for k, v2 in changes.items() if k == f"stages.{st.name}.dt"}
            if run_key in changes and st.name in via_run and st.name == via_run[0]:
                mine[run_key] = changes[run_key]
            if "run.dt_fraction" in changes and st.name in via_default and st.name == via_default[0]:
                mine["run.dt_fraction"] = changes["run.dt_fraction"]
            if cur > t_r_old * (1 + 1e-12) and not self.deck.run.force_dt:
                verdict, reason = (
                    "warn",
                    (
                        f"dt = {cur:.3g} s ({key}) is above the Rayleigh time {t_r_old:.3g} s: pdem "
                        "refuses it "
                        f"(unless run.force_dt); use {need[st.name]:.3g} s"
                    ),
                )
                mysugg = self._dt_setting(st, need[st.name], t_r)
                usable = min(usable, need[st.name])
            elif abs(dt / cur - 1) > 1e-9 and dt <= rules.WARN_FACTOR * need[st.name]:
                via = (st.name in via_run and run_key in changes) or (
                    st.name in via_default and "run.dt_fraction" in changes
                )
                verdict = "change" if (mine or via) else "ok"
                why = (f"softer grains (T_R {t_r_old:.3g} → {t_r:.3g} s)" if t_r > t_r_old * 1.001 else
                       "the step was finer than needed")  # fmt: skip
                limit = ("0.2 T_R" if need[st.name] >= rules.RAYLEIGH_FRACTION * t_r * (1 - 1e-9)
                         else f"{rules.STEPS_PER_COLLISION} steps per collision at {v:.3g} m/s "
                         f"({label})")  # fmt: skip
                fewer = f"{dt / cur:.3g}× fewer steps" if dt > cur else f"{cur / dt:.3g}× more steps"
                reason = f"dt {cur:.3g} → {dt:.3g} s ({fewer}): {why}; the step is now set by {limit}"
                if via and not mine:
                    reason += f" ({'run.dt_fraction' if by_fraction else run_key}, changed above)"
                elif verdict == "ok":
                    reason += (" (run.dt_fraction follows the stiffness)" if by_fraction else
                               " (the deck gives no dt: pdem's default follows the stiffness)")  # fmt: skip
            elif dt > rules.WARN_FACTOR * need[st.name]:
                verdict = "warn"
                reason = (
                    f"dt = {dt:.3g} s ({key}) gives {t_c / dt:.3g} steps per collision at {v:.3g} m/s "
                    f"({label}), fewer than {rules.STEPS_PER_COLLISION}, or is more than "
                    f"{rules.RAYLEIGH_FRACTION:g} "
                    f"T_R; {need[st.name]:.3g} s would resolve it"
                )
                mysugg = {f"stages.{st.name}.dt": rules.round_sig(need[st.name], 2, "down")}
                if by_fraction and st.dt_key is None:
                    mysugg = self._dt_setting(st, need[st.name], t_r)
            else:
                verdict = "ok"
                reason = (f"dt = {cur:.3g} s ({key}) = {cur / t_r_old:.2g} T_R, {t_c / cur:.3g} steps per "
                          f"collision at {v:.3g} m/s ({label}): neither too coarse nor more than "
                          f"{rules.CHANGE_FACTOR:g}× finer than needed")  # fmt: skip
            if dt > STIFFNESS_LIMIT * live:
                verdict = "warn"
                safe = rules.round_sig(0.8 * live, 2, "down")
                reason += (
                    f"; but dt = {dt:.3g} s is {dt / live:.3g}× the live step bound predicted at δ/d = "
                    f"{live_at:.2g} ({live:.3g} s): the run would likely stop at run.stiffness_limit = "
                    f"{STIFFNESS_LIMIT:g}; take {safe:.3g} s"
                )
                mysugg = self._dt_setting(st, safe, t_r)
                usable = min(usable, safe)
                src += "; live bound ≈ 0.092 T_R (δ/d)^(-1/4), docs/study/stability.md"
            self.dt_usable[st.name] = usable
            self.findings.append(
                Finding("step", f"stage {st.name}", verdict, reason, src, nums, mine, mysugg)
            )

    def _stage_dem_c(self, index: int, base: Any) -> Any:
        """DEM-C's parameters in stage ``index`` (:func:`pdem.advise.dem_c.stage_params`)."""
        return dem_c.stage_params(self.resolved, index, base)

    def _dt_setting(self, st, dt: float, t_r: float) -> dict[str, float]:
        """The key and value that give stage ``st`` the step ``dt`` [s] in the deck's own terms:
        its stage or run dt, or run.dt_fraction (a fraction of T_R, rounded down) when that steps it
        (a deck may not give both run.dt and run.dt_fraction)."""
        if st.dt_key is None and self.scene.dt_fraction is not None:
            return {"run.dt_fraction": rules.round_sig(dt / t_r, 2, "down")}
        return {st.dt_key or self.scene.run_dt_key: rules.round_sig(dt, 2, "down")}

    # ------------------------------------------------------------------ inertial number
    def inertial(self) -> None:
        sc = self.scene
        d, rho = sc.d_mean, sc.density
        src = ("physics reference §2 (I ≲ 1e-3); GDR MiDi, Eur. Phys. J. E 14, 341 (2004); da Cruz et al., "
               "Phys. Rev. E 72, 021309 (2005); target calibrated on the rate halvings of "
               "docs/experiments/direct_shear.md (+1.0 % at I = 4.6e-4) and triaxial.md (−0.09 % at "
               "2.4e-4)")  # fmt: skip
        for name, loadings in sc.loadings().items():
            for ld in loadings:
                self._inertial_of(name, ld, d, rho, src)

    def _inertial_of(self, name: str, ld: Any, d: float, rho: float, src: str) -> None:
        """The inertial-number finding of one :class:`~pdem.boundaries.api.Loading` of boundary
        ``name``: its quasi-static rate (``rate_key``), or its note on a rate nothing changes."""
        if ld.rate_key is None:
            if ld.note:
                self.findings.append(Finding("inertial", f"boundaries.{name}", "ok", ld.note, ld.note_source))
            return
        key, rate, stage = ld.rate_key, ld.rate, ld.stages[0] if ld.stages else ""
        shear, stress, how = ld.shear_rate, ld.stress, ld.rate_how
        inert = rules.inertial_number(shear, d, rho, stress)
        nums = {"rate": rate, "key": f"boundaries.{name}.{key}", "stage": stage, "d [m]": d,
                "density [kg/m3]": rho, "stress [Pa]": stress, "I": inert, "I "
                "target": rules.INERTIAL_TARGET}  # fmt: skip
        if not (inert < math.inf):
            self.findings.append(
                Finding(
                    "inertial",
                    f"boundaries.{name}",
                    "warn",
                    "no stress to compute I with (no gravity?)",
                    src,
                    nums,
                )
            )
            return
        k = rules.INERTIAL_TARGET / inert
        if inert > rules.INERTIAL_MAX:
            slow = rules.round_sig(rate * k, 2, "down")
            self.findings.append(Finding(
                "inertial", f"boundaries.{name}", "warn",
                f"{how}: I = {inert:.2g} is above {rules.INERTIAL_MAX:g}, so the loading is not "
                "quasi-static "
                f"(the quantity may move by several %); {key} = {slow:.3g} gives I = "
                f"{rules.INERTIAL_TARGET:g} "
                f"({1 / k:.3g}× slower, costlier)", src, nums,
                suggestions={f"boundaries.{name}.{key}": slow}))  # fmt: skip
        elif k >= rules.CHANGE_FACTOR:
            fast = rules.round_sig(rate * k, 2, "down")
            factor = fast / rate
            self.rate_factor[stage] = factor
            nums["rate proposed"] = fast
            self.findings.append(Finding(
                "inertial", f"boundaries.{name}", "change",
                f"{how}: I = {inert:.2g}, {k:.3g}× below the target {rules.INERTIAL_TARGET:g} "
                "(which keeps the "
                f"quantity within ~1.3 % of its quasi-static limit): {key} {rate:.3g} → {fast:.3g} "
                f"({factor:.3g}× faster); stage '{stage}' ends scaled by the same factor where they "
                "are times "
                "or steps (an end in strain, displacement or depth needs nothing)", src, nums,
                changes={f"boundaries.{name}.{key}": fast}))  # fmt: skip
        else:
            self.findings.append(Finding(
                "inertial", f"boundaries.{name}", "ok",
                f"{how}: I = {inert:.2g}, within {rules.CHANGE_FACTOR:g}× of the target "
                f"{rules.INERTIAL_TARGET:g} and below {rules.INERTIAL_MAX:g}", src, nums))  # fmt: skip

    # ------------------------------------------------------------------ stage ends
    def stage_lengths(self) -> None:
        """Stage ends counted in steps keep their simulated time when dt changes; ends in time of a
        loading stage shrink with its faster loading."""
        changes: dict[str, Any] = {}
        notes = []
        for st in self.deck.stages:
            k = self.rate_factor.get(st.name, 1.0)
            old, new = self.dt_old.get(st.name), self.dt_new.get(st.name)
            end = st.end
            if end.steps is not None and old and new and (abs(new / old - 1) > 1e-9 or k != 1.0):
                steps = max(1, math.ceil(end.steps * old / new / k - 1e-9))
                if steps != end.steps:
                    changes[f"stages.{st.name}.end.steps"] = steps
                    notes.append(
                        f"stages.{st.name}.end.steps {end.steps} → {steps} (same simulated "
                        + ("time" if k == 1.0 else "loading")
                        + ")"
                    )
            if k != 1.0:
                for key in ("time", "max_time"):
                    val = getattr(end, key)
                    if val is not None:
                        changes[f"stages.{st.name}.end.{key}"] = rules.round_sig(val / k, 4, "up")
                        notes.append(
                            f"stages.{st.name}.end.{key} {val:g} → {val / k:.4g} s (loading {k:.3g}× faster)"
                        )
        self._first_checks()
        if changes:
            self.findings.append(Finding(
                "stage_ends", "stages", "change",
                "; ".join(notes) + ". Output cadences in steps are left as they are (they now span more "
                "simulated time per row or frame)", changes=changes))  # fmt: skip

    def _first_checks(self) -> None:
        """A stage that ends on kinetic energy and starts with grains at rest in the air ends at its
        first check if they have not gained that energy yet (check_every steps of a small dt)."""
        sc = self.scene
        if sc.gravity <= 0:
            return
        for st in self.deck.stages:
            end = st.end
            loose = [g for g in sc.groups if g.stage == st.name and g.loose and g.speed == 0]
            if end.kinetic_energy_below is None or not loose or sc.fall_height <= 0:
                continue
            dt = self.dt_new.get(st.name) or self.dt_old.get(st.name)
            if not dt:
                continue
            mass = sum(g.count * g.density * g.mean_volume for g in loose)
            t1 = end.check_every * dt
            t_fall = math.sqrt(2 * sc.fall_height / sc.gravity)
            ke = 0.5 * mass * (sc.gravity * min(t1, t_fall)) ** 2
            if ke >= end.kinetic_energy_below:
                continue
            t_ok = min(math.sqrt(20 * end.kinetic_energy_below / mass) / sc.gravity, t_fall)
            every = math.ceil(t_ok / dt)
            self.findings.append(Finding(
                "stage_ends", f"stage {st.name}", "warn",
                f"the stage ends on kinetic energy below {end.kinetic_energy_below:g} J, checked every "
                f"{end.check_every} steps ({t1:.3g} s at dt = {dt:.3g} s); grains released at rest have "
                f"~{ke:.2g} J by then, so the stage ends at its first check before they have fallen. "
                f"check_every = {every} ({every * dt:.3g} s) lets them fall first",
                numbers={"first check [s]": t1, "free-fall KE then [J]": ke,
                         "threshold [J]": end.kinetic_energy_below},
                suggestions={f"stages.{st.name}.end.check_every": every}))  # fmt: skip

    # ------------------------------------------------------------------ sample size
    def sample_size(self) -> None:
        sc = self.scene
        n = sc.n

        def finding(
            where: str, checks: list[tuple[str, float, tuple[float, str]]], n_min: float | None
        ) -> None:
            nums: dict[str, Any] = {}
            below, far, srcs = [], [], []
            for label, value, (minimum, source) in checks:
                nums[label] = value
                nums[f"{label} minimum"] = minimum
                srcs.append(source)
                if value < minimum:
                    below.append(f"{label} = {value:.3g} < {minimum:g}")
                elif value > 2 * minimum:
                    far.append(f"{label} = {value:.3g} ({value / minimum:.2g}× the minimum)")
            if n_min:
                nums["grains"] = n
                nums["grains at the minimum size"] = n_min
            if below:
                verdict, reason = (
                    "warn",
                    "below the minimum: "
                    + "; ".join(below)
                    + (
                        ". The quantity carries a size effect: treat it as a test of the device, or "
                        "enlarge the sample"
                    ),
                )
            else:
                verdict = "ok"
                reason = "above every minimum" + (
                    f"; {'; '.join(far)}: a smaller sample (down to ~{n_min:,.0f} grains) could be run "
                    "to explore, "
                    "but the quantity's scatter grows as the sample shrinks (not applied)"
                    if far and n_min
                    else ""
                )
            self.findings.append(Finding("sample_size", where, verdict, reason, "; ".join(srcs), nums))

        facts = sc.facts()
        for name, p in sc.boundaries.items():
            size = sc.boundary_class(name).sample_size(name, p, facts)
            if size is None:
                continue
            checks = [(c.label, float(c.value), (float(c.minimum), c.source)) for c in size.checks]
            finding(f"boundaries.{name} ({size.test})", checks, size.grains_min)

    # ------------------------------------------------------------------ method
    def method(self) -> None:
        sc = self.scene
        # DEM-C's deck-wide parameters, and its own step ([contact.complementarity] dt) in a DEM-P deck
        cparams, own_dt = dem_c.base_params(self.resolved, self.raw)
        r_min = min(g.r_min for g in sc.groups)
        if sc.rigid and sc.run_dt:
            h_c = float(sc.run_dt)
        elif isinstance(own_dt, int | float) and not isinstance(own_dt, bool) and own_dt > 0:
            h_c = float(own_dt)
        else:
            h_c = cparams.max_travel * r_min / cparams.reference_speed
        layers = max(sc.packed_height / sc.d_mean, 1.0) if math.isfinite(sc.packed_height) else 10.0
        solver = str(cparams.solver)
        estimate = rules.column_iterations(solver, layers, str(cparams.scaling))
        iterations = float(cparams.max_iterations)
        z = rules.COORDINATION
        contacts = sc.n * z / 2
        t_total, steps_p, steps_p_old, steps_c, unknown = 0.0, 0.0, 0.0, 0.0, []
        # DEM-C's contact work stage by stage: each stage's solver and cap ([stages.contact], e.g.
        # the hopper's APGD fill and 10 Jacobi sweeps in its discharge)
        work_c, per_stage, finer, steps_p_stiff = 0.0, [], [], 0.0
        t_r = self._rayleigh(proposed=True)
        t_r_deck = self._rayleigh(proposed=False)
        for st in sc.stages:
            if st.duration is None:
                unknown.append(st.name)
                continue
            k = self.rate_factor.get(st.name, 1.0)
            t = st.duration / k
            t_total += t
            # DEM-P at the step its grains allow: the deck's, or the advised one where the deck's
            # cannot run (stiffer grains than the deck's step was set for)
            dt_p = self.dt_usable.get(st.name) or self.dt_new.get(st.name) or self._default_fraction() * t_r
            if dt_p < (self.dt_new.get(st.name) or dt_p) * (1 - 1e-9):
                finer.append(st.name)
            steps_p += t / dt_p
            steps_p_stiff += t / (dt_p * min(t_r_deck / t_r, 1.0))  # the deck's grains, unsoftened
            steps_p_old += st.duration / (self.dt_old.get(st.name) or dt_p)
            steps_c += t / h_c
            sp = self._stage_dem_c(st.index, cparams)
            ns_table = rules.NS_PER_CONTACT_ITERATION
            ns_st = ns_table.get(str(sp.solver), max(ns_table.values()))
            iteration_s = rules.ITERATION_OVERHEAD_S + contacts * ns_st * 1e-9
            its = rules.dem_c_iterations(str(sp.solver), int(sp.max_iterations), sp.load_tolerance)
            work_c += t / h_c * (rules.STEP_OVERHEAD_S + its * iteration_s)
            per_stage.append(
                f"{st.name}: {sp.solver} × {sp.max_iterations}"
                + (f" (stopped on the walls' loads: ~{its:.0f})" if its < sp.max_iterations else "")
            )
        if t_total <= 0:
            self.findings.append(
                Finding(
                    "method", "all stages", "ok", "no stage length is known from the deck; no cost estimate"
                )
            )
            return
        per_step_p = rules.STEP_OVERHEAD_S + contacts * rules.NS_PER_CONTACT_DEM_P * 1e-9
        cost_p = steps_p * per_step_p
        ns_c = rules.NS_PER_CONTACT_ITERATION.get(solver, max(rules.NS_PER_CONTACT_ITERATION.values()))
        cost_c = work_c
        ratio = cost_c / cost_p
        softened = steps_p_stiff > steps_p * (1 + 1e-9)  # the overlap finding softens the grains
        ratio_stiff = cost_c / (steps_p_stiff * per_step_p)
        stage_text = "; ".join(per_stage)
        nums = {
            "simulated time [s]": t_total, "contacts (N Z/2)": contacts, "DEM-P steps": steps_p,
            "DEM-P dt": (t_total / steps_p), "DEM-C h [s]": h_c, "DEM-C steps": steps_c, "solver": solver,
            "iterations per step": iterations, "iterations to converge (column estimate)": estimate,
            "iteration cap": cparams.max_iterations, "DEM-C solver × cap by stage": stage_text,
            "DEM-P time [s]": cost_p, "DEM-C time [s]": cost_c, "DEM-C / DEM-P": ratio,
        }  # fmt: skip
        if softened:
            nums["DEM-P steps at the deck's stiffness"] = steps_p_stiff
            nums["DEM-C / DEM-P at the deck's stiffness"] = ratio_stiff
        if finer:
            nums["DEM-P at a finer step than the deck's in"] = ", ".join(finer)
        if self.hertz and steps_p_old > 0:
            nums["DEM-P steps as the deck stands"] = steps_p_old
            nums["predicted speed-up of the changes"] = steps_p_old / steps_p
        winner = "DEM-P (hertz_mindlin)" if ratio > 1 else "DEM-C (complementarity)"
        using = (
            "the deck's"
            if sc.rigid
            else "[contact.complementarity] dt"
            if own_dt is not None and h_c == own_dt
            else "DEM-C's automatic step (max_travel r_min / reference_speed)"
        )
        step_ms = rules.STEP_OVERHEAD_S * 1e3
        iter_ms = rules.ITERATION_OVERHEAD_S * 1e3
        reason = (
            f"{winner} is likely {max(ratio, 1 / ratio):.2g}× faster for this scene"
            + (" with the grains softened as the overlap finding proposes" if softened else "")
            + f": DEM-P {steps_p:,.0f} steps × ({step_ms:g} ms + {contacts:,.0f} contacts × "
            f"{rules.NS_PER_CONTACT_DEM_P} ns); DEM-C {steps_c:,.0f} steps ({using}, h = {h_c:.3g} s) × "
            f"({step_ms:g} ms + each stage's solver and cap ({stage_text}) × ({iter_ms:g} ms + contacts × "
            f"{', '.join(f'{k} {v} ns' for k, v in rules.NS_PER_CONTACT_ITERATION.items())}))."
        )
        if softened:
            other = "DEM-P (hertz_mindlin)" if ratio_stiff > 1 else "DEM-C (complementarity)"
            reason += (
                f" At the deck's own stiffness DEM-P needs {steps_p_stiff:,.0f} steps and {other} is "
                f"{max(ratio_stiff, 1 / ratio_stiff):.2g}× faster: stiff grains favour DEM-C, whose rigid "
                "grains cost the same at any stiffness, softened ones DEM-P."
            )
        if finer:
            reason += (
                f" DEM-P is costed at the step its grains allow in stage(s) {', '.join(finer)}: the deck's "
                "step is past the stability bound there (see the step findings)."
            )
        reason += (
            f" Iterations: the cap ({cparams.max_iterations}), because pdem's measured DEM-C runs end "
            "their solves at or near it (direct shear 632–714 of 1,000, the triaxial's shear at 500), "
            f"or ~{rules.LOAD_STOPPED_ITERATIONS} where APGD stops on the walls' loads (load_tolerance ≥ "
            f"{rules.LOAD_STOPPED_MIN_TOLERANCE:g}: 134–178 measured on the triaxial and direct shear); "
            f"a column of {layers:.0f} grains needs ~{estimate:,.0f} {solver} iterations cold "
            f"({'~N²' if solver != 'apgd' else '~N'}), a lower bound. Z = 5.5 is assumed, and the fixed "
            "costs are one scene's (boundaries that cost more per step, like a membrane, are not "
            "counted), and both methods are costed over the same simulated time. Against pdem's "
            "measured crossover charts (docs/study/crossover.md) the model names the cheaper method in "
            "all but one case: DEM-C/DEM-P 0.15× for the hopper (measured 0.42–0.56×); 2.2× for the "
            "reduced direct shear with its solves stopped on the walls' loads (measured 2.1–2.4×) and "
            "0.043× at glass stiffness (0.11× by the measured fit); 2.8× for the reduced triaxial "
            "(measured 1.1×) and 0.11× at glass stiffness (0.05× by the fit); on the drop with APGD "
            "capped at 300 it gives 0.92× at glass stiffness "
            "where DEM-P was 2.2–2.7× cheaper, DEM-C having simulated 1.3–1.7× DEM-P's time to rest "
            "(docs/advise.md). DEM-C's unconverged solves change the results"
        )
        if unknown:
            reason += f". Stages {', '.join(unknown)} have no length the deck tells and are left out"
        verdict = "ok"
        waves = self._wave_boundaries()
        if waves:  # the cost model is beside the point: only one method has the quantity
            verdict = "warn" if sc.rigid else "ok"
            reason = (
                f"DEM-P (hertz_mindlin): boundaries {', '.join(waves)} measure a wave, and rigid grains "
                "carry none. DEM-C's front moves as far per step as its solver carries an impulse, so its "
                "speed follows the step and the iteration cap, not the material (docs/study/wave_chain.md: "
                "errors of 133–10,860 % over steps 1e-6–1e-5 s and caps 50–500; "
                "docs/study/shock_wave.md for the 2-D bed)"
                + (". This deck runs DEM-C: its wave speeds measure the solver" if sc.rigid
                   else f". (By contact work alone the cost model would rate DEM-C {1 / ratio:.2g}× "
                   f"{'faster' if ratio < 1 else 'slower'}.)")
            )  # fmt: skip
        self.findings.append(Finding(
            "method", "all stages", verdict, reason,
            f"docs/dem_c.md, Kernel costs: {rules.NS_PER_CONTACT_DEM_P} ns per contact (DEM-P) and "
            f"{ns_c} ns per contact and {solver} iteration (tools/dem_c_study.py --parts 3, 4,000 spheres); "
            "iterations of a column, same document part 1; the fixed costs a step and an iteration: the "
            "reduced direct shear's wall times, docs/study/crossover.md", nums))  # fmt: skip

    # ------------------------------------------------------------------ DEM-C settings
    def dem_c_settings(self) -> None:
        """DEM-C's solver settings: the deck's own, named; or, for a deck that does not choose DEM-C's
        solver, the settings measured for each kind of stage, as suggestions (``--apply`` leaves a
        deck's DEM-C table as it is): :mod:`pdem.advise.dem_c`."""
        sc, runs = self.scene, dem_c.runs_dem_c(self.resolved)
        where = "contact.complementarity"
        if dem_c.has_solver(self.raw, self.resolved):
            text, nums = dem_c.describe(self.resolved, self.raw, sc)
            self.findings.append(Finding(
                "dem_c_settings", where, "ok", f"the deck carries DEM-C's settings: {text}",
                "the deck's [contact.complementarity] and [stages.NAME.contact.complementarity]",
                nums))  # fmt: skip
            return
        prop = dem_c.propose(sc, self.resolved, self.raw)
        if runs:
            lib, _ = dem_c.library()
            head = ("the deck runs DEM-C without choosing its solver, so it runs the library's default "
                    f"({lib['solver']} × {lib['max_iterations']})")  # fmt: skip
        else:
            head = "the deck carries no DEM-C solver choice"
        head += (", and none is proposed: " if not prop.suggestions else
                 "; suggested" + ("" if runs else " for --set contact.law=complementarity")
                 + ", by the kind of each stage (docs/advise.md, DEM-C settings): ")  # fmt: skip
        self.findings.append(Finding(
            "dem_c_settings", where, "warn" if runs else "ok", head + prop.reason, prop.source,
            prop.numbers, suggestions=prop.suggestions))  # fmt: skip


# ---------------------------------------------------------------------------------------------
# apply
# ---------------------------------------------------------------------------------------------


def apply(advice: Advice, out_path: str | Path, overwrite: bool = False) -> Path:
    """Write the advised deck to ``out_path``: the deck as loaded, its ``--set`` overrides applied,
    then the advice's changes; emitted with :mod:`pdem.deck.toml_writer` and validated (it loads like
    any deck). Refuses an existing file unless ``overwrite``."""
    from ..deck import validate_deck
    from ..deck.overrides import apply_overrides
    from ..deck.toml_writer import dumps

    out = Path(out_path)
    if out.is_dir():
        raise InputError(
            f"--apply {out} is a directory; give a file name, e.g. --apply {out / 'advised.toml'}"
        )
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise InputError(
            f"--apply {out} already exists; pass --overwrite (overwrite=True) to replace it, or choose "
            "another file"
        )
    data = copy.deepcopy(advice.raw)
    if advice.resolved is not None:  # packing files: the resolved (absolute) path, valid from anywhere
        sources = zip(advice.resolved.source_classes, advice.resolved.deck.particles, strict=True)
        for k, (cls, params) in enumerate(sources):
            for key in getattr(cls, "path_keys", ()):
                if isinstance(data.get("particles"), list) and getattr(params, key, None) is not None:
                    data["particles"][k][key] = str(getattr(params, key))
    texts = advice.set_args("changes")
    applied, problems = apply_overrides(data, texts)
    if problems:  # pragma: no cover - the changes are built from the schema's own keys
        raise InputError(f"the advice's changes cannot be applied: {problems}")
    out_dir = data.get("output", {}).get("directory") if isinstance(data.get("output"), dict) else None
    if isinstance(out_dir, str):
        data["output"]["directory"] = out_dir.rstrip("/") + "_advised"
    head = [f"written by pdem advise from {advice.deck}"]
    head += [f"  --set {o}" for o in advice.overrides]
    head.append("changes:" if texts else "changes: none")
    head += [f"  --set {t}" for t in texts]
    if isinstance(out_dir, str):
        head.append(
            f"output.directory: {out_dir} -> {data['output']['directory']} (not to mix with the original's)"
        )
    head.append("(the original's comments are not kept)")
    text = dumps(data, "\n".join(head))
    validate_deck(tomllib.loads(text), path=out, base_dir=out.parent.resolve() if out.parent else None)
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise InputError(f"cannot write --apply {out}: {exc.strerror or exc}; choose another file") from exc
    return out


def dumps_json(advice: Advice) -> str:
    return json.dumps(advice.to_dict(), indent=2, ensure_ascii=False)
