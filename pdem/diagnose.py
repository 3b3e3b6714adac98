"""Why a run stopped: the largest overlap and who has it, a non-finite state, and an overlap past
``run.max_overlap`` told apart as *static* (the stress over the stiffness: stiffer grains or a
larger limit) or *dynamic* (the step, or an impact too hard for the grains).

Functions of a :class:`~pdem.simulation.Simulation` (``sim``), called when a check fails; the
collective ones (every rank calls them) say so. Nothing here runs in a healthy step.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .contact._kernels import FLAG_COINCIDENT, FLAG_NONFINITE, FLAG_OVERLAP
from .errors import InstabilityError
from .state.particles import REMOVED

__all__ = [
    "worst_overlap",
    "worst_contact",
    "global_worst_overlap",
    "overlap_cause",
    "non_finite_state",
    "raise_for_flags",
]


def _bor():
    from mpi4py import MPI

    return MPI.BOR


def worst_overlap(sim: Any) -> tuple[float, str]:
    """Largest overlap / radius over pairs and walls, and who has it (for messages)."""
    worst, who, _ = worst_contact(sim)
    return worst, who


def worst_contact(sim: Any) -> tuple[float, str, tuple | None]:
    """This rank's largest overlap / radius over the listed pairs and the active walls, who has
    it, and where: ``("pair", list row)`` or ``("wall", wall, particle row)`` (None: nothing
    listed). Non-finite geometry (a NaN position) is left out: :func:`non_finite_state` reports
    it as such instead of as an infinite overlap."""
    from .geometry._kernels import wall_gaps

    p = sim.particles
    worst, who, where = -math.inf, "nobody", None
    pi, pj = sim.contact_store.pi, sim.contact_store.pj
    if pi.size:
        d = np.linalg.norm(p.x[pj] - p.x[pi], axis=1)
        ratio = (p.r[pi] + p.r[pj] - d) / np.minimum(p.r[pi], p.r[pj])
        ratio = np.where(np.isfinite(ratio), ratio, -np.inf)
        k = int(np.argmax(ratio))
        if ratio[k] > worst:
            worst, who = float(ratio[k]), f"particles {p.id[pi[k]]} and {p.id[pj[k]]}"
            where = ("pair", k)
    n = p.n_owned
    for wall in sim.contact_store.walls:
        if n == 0:
            break
        if not wall.active:  # a switched-off wall (an opened plug) may cut through the grains
            continue
        rows = zip(wall.kinds, wall.rows, strict=True)
        gap = np.min([wall_gaps(int(kd), row, p.x[:n], p.r[:n]) for kd, row in rows], axis=0)
        ratio = np.where(np.isfinite(gap), -gap / p.r[:n], -np.inf)
        k = int(np.argmax(ratio))
        if ratio[k] > worst:
            worst, who = float(ratio[k]), f"particle {p.id[k]} and wall '{wall.name}'"
            where = ("wall", wall, k)
    return worst, who, where


def global_worst_overlap(sim: Any) -> tuple[float, str]:
    worst, who = worst_overlap(sim)
    if sim.comm.size > 1:
        worst, who = max(sim.comm.allgather((worst, who)), key=lambda t: t[0])
    return worst, who


def contact_detail(sim: Any, where: tuple | None) -> dict[str, Any] | None:
    """What decides whether the overlap at ``where`` (:func:`worst_contact`) is static or
    dynamic, from this rank's arrays: the contact's normal force ``fn`` [N] (from the last force
    evaluation), its closing speed ``vn`` [m/s] during the step's drift (the velocities before the
    last half kick; > 0 while the grains approach), and ``loads``:
    for each free side this rank owns, the push of that grain's *other* forces (contacts,
    gravity, boundary loads) into the contact, (f_total − f_contact)·n [N]. In a grain at rest
    the other forces balance the contact (load ≈ fn); in an impact nothing does (load ≈ 0).
    Also the pair's material indices, R* and m* for the law's elastic curve."""
    from .geometry._kernels import surface_velocity, wall_contact

    if where is None:
        return None
    p = sim.particles
    cs = sim.contact_store
    n = p.n_owned
    loads: list[float] = []

    def drift(row: int) -> np.ndarray:  # the velocity the step's drift moved the grain with
        return p.v[row] - (0.5 * sim.dt * p.inv_m[row]) * p.f[row]

    if where[0] == "pair":
        k = where[1]
        i, j = int(cs.pi[k]), int(cs.pj[k])
        d = p.x[j] - p.x[i]
        dist = float(np.linalg.norm(d))
        if not (dist > 0.0 and k < cs.force.shape[0]):
            return None
        nrm = d / dist
        fc = cs.force[k]  # on j (on i: its negative)
        for row, sign, on in ((i, 1.0, -fc), (j, -1.0, fc)):
            if row < n and p.inv_m[row] > 0.0:
                loads.append(float(np.dot(p.f[row] - on, sign * nrm)))
        inv_sum = float(p.inv_m[i] + p.inv_m[j])
        return {
            "fn": float(np.dot(fc, nrm)), "vn": -float(np.dot(drift(j) - drift(i), nrm)), "loads": loads,
            "r": float(min(p.r[i], p.r[j])), "r_eff": float(p.r[i] * p.r[j] / (p.r[i] + p.r[j])),
            "m_eff": 1.0 / inv_sum if inv_sum > 0.0 else math.inf,
            "mats": (int(p.mat[i]), int(p.mat[j])),
        }  # fmt: skip
    _, wall, k = where
    w = next((q for q, other in enumerate(cs.walls) if other is wall), None)
    if w is None or cs.wall_rows.shape[0] != len(cs.walls) + 1:
        return None
    force = np.zeros(3)
    best, nrm, v_wall, wmat = math.inf, None, np.zeros(3), 0
    x = p.x[k]
    for row in range(int(cs.wall_rows[w]), int(cs.wall_rows[w + 1])):
        a = int(cs.cstart[row]) if row < cs.cstart.shape[0] - 1 else 0
        c = int(cs.counts[row]) if row < cs.counts.shape[0] else 0
        hit = np.flatnonzero(cs.out_idx[a : a + c] == k)
        force += cs.out_val[a + hit, 0:3].sum(axis=0)  # on the wall (on the grain: its negative)
        kind, prm = int(cs.kinds[row]), cs.params[row]
        gap, nx, ny, nz, px, py, pz = wall_contact(kind, prm, x[0], x[1], x[2], p.r[k])
        if gap < best:
            best, nrm, wmat = gap, np.array([nx, ny, nz]), int(cs.wmat[row])
            surface = surface_velocity(kind, prm, cs.vel, cs.omega, cs.centre, row, px, py, pz)
            v_wall = np.array(surface[:3])
    if nrm is None:
        return None
    if p.inv_m[k] > 0.0:  # n points from the centre into the wall
        loads.append(float(np.dot(p.f[k] + force, nrm)))
    return {
        "fn": float(np.dot(force, nrm)), "vn": float(np.dot(drift(k) - v_wall, nrm)), "loads": loads,
        "r": float(p.r[k]), "r_eff": float(p.r[k]),
        "m_eff": 1.0 / float(p.inv_m[k]) if p.inv_m[k] > 0.0 else math.inf,
        "mats": (int(p.mat[k]), wmat),
    }  # fmt: skip


def elastic_curve(sim: Any, detail: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(δ, F(δ), U(δ)) for the contact of ``detail`` on a grid of overlaps from 0 to two radii:
    the law's elastic normal force at rest and its energy, integrated from its normal stiffness
    S_n = dF/dδ (:meth:`ContactLaw.contact_stiffness`); None for a law that does not give it."""
    from .contact.stability import supported

    if not supported(sim.law) or not math.isfinite(detail["m_eff"]):
        return None
    s = 2.0 * detail["r"] * np.linspace(0.0, 1.0, 1601)[1:] ** 2  # fine near first touch
    m = s.size
    mi, mj = detail["mats"]
    try:
        sn = sim.law.contact_stiffness(
            sim.coefficients, np.full(m, mi), np.full(m, mj), np.full(m, detail["r_eff"]),
            np.full(m, detail["m_eff"]), s,
        )[0]  # fmt: skip
    except Exception:  # noqa: BLE001 - a diagnosis only: a plugin law's failure must not hide the error
        return None
    sn = np.broadcast_to(np.asarray(sn, dtype=float), s.shape)
    if not np.all(np.isfinite(sn)) or np.any(sn < 0.0):
        return None
    d = np.concatenate([[0.0], s])
    sn = np.concatenate([[sn[0]], sn])
    force = np.concatenate([[0.0], np.cumsum(0.5 * (sn[1:] + sn[:-1]) * np.diff(d))])
    energy = np.concatenate([[0.0], np.cumsum(0.5 * (force[1:] + force[:-1]) * np.diff(d))])
    return d, force, energy


def overlap_cause(sim: Any) -> tuple[float, str, dict[str, Any] | None]:
    """The largest overlap over all ranks (collective), who has it and its :func:`contact_detail`
    merged over the ranks that hold a side of it (a pair across ranks: each owns one grain)."""
    worst, who, where = worst_contact(sim)
    try:
        detail = contact_detail(sim, where)
    except Exception:  # noqa: BLE001 - a diagnosis only: never hide the error it explains
        detail = None
    if sim.comm.size > 1:
        found = sim.comm.allgather((worst, who, detail))
        worst, who, _ = max(found, key=lambda t: t[0])
        same = [d for w, h, d in found if h == who and w == worst and d is not None]
        detail = dict(same[0]) if same else None
        if detail is not None:
            detail["loads"] = [x for d in same for x in d["loads"]]
    return worst, who, detail


def non_finite_state(sim: Any) -> list[tuple[int, str, list[float]]]:
    """Owned particles with a non-finite position, velocity, angular velocity or force, over all
    ranks (collective): (id, field, value), ordered by id; at most 8 rows per rank."""
    p = sim.particles
    n = p.n_owned
    live = p.motion[:n] != REMOVED
    bad: list[tuple[int, str, list[float]]] = []
    for name, label in (("x", "position"), ("v", "velocity"), ("w", "angular velocity"), ("f", "force")):
        arr = getattr(p, name)[:n]
        rows = np.flatnonzero(live & ~np.all(np.isfinite(arr), axis=1))
        bad += [(int(p.id[r]), label, [float(c) for c in arr[r]]) for r in rows[:8]]
    if sim.comm.size > 1:
        bad = [b for part in sim.comm.allgather(bad) for b in part]
    return sorted(bad, key=lambda b: b[0])


def raise_for_flags(sim: Any, flags: int, drifted: bool = False) -> None:
    """The error for the kernels' ``flags`` (collective). ``drifted``: raised from the next
    step's rebuild test (a deferred check), after velocity Verlet's drift: the overlap
    quoted is the one found then.

    Non-finite values are reported as such (which particles, which fields). An overlap past
    ``max_overlap`` is told apart as *static* or *dynamic* (:func:`overlap_message`)."""
    bad = non_finite_state(sim)
    if sim.comm.size > 1:
        flags = int(sim.comm.allreduce(flags, op=_bor()))
    if bad:
        raise InstabilityError(non_finite_message(sim, bad))
    worst, who, detail = overlap_cause(sim)
    causes = []
    if flags & FLAG_OVERLAP:
        causes.append(f"an overlap exceeded {sim.max_overlap} of a radius")
    if flags & FLAG_NONFINITE:
        causes.append("a velocity became non-finite")
    if flags & FLAG_COINCIDENT:
        causes.append("two particle centres coincide")
    advice = sim.law.instability_advice(sim)
    if advice is not None:
        # a method that solves for its contacts (DEM-C) finds overlaps when it assembles a step's
        # contacts; the same step's solve pushes them apart, so the state now may show less
        now = (
            f"largest overlap {worst:.3g} of the radius, {who}"
            if worst > sim.max_overlap or not flags & FLAG_OVERLAP
            else f"found when the step's contacts were assembled (after the step's solve the largest "
            f"is {worst:.3g} of the radius, {who})"
        )
        raise InstabilityError(
            f"the run became unstable at step {sim.step_count} (t = {sim.time:.6g} s): "
            f"{' and '.join(causes)}; {now}. dt = {sim.dt:.4g} s, {advice}"
        )
    if flags == FLAG_OVERLAP and detail is not None and worst > sim.max_overlap:
        raise InstabilityError(overlap_message(sim, worst, who, detail, drifted))
    drift_note = " after the next step's drift" if drifted else ""
    raise InstabilityError(
        f"the run became unstable at step {sim.step_count} (t = {sim.time:.6g} s): "
        f"{' and '.join(causes)}; largest overlap {worst:.3g} of the radius"
        f"{drift_note}, {who}. "
        f"dt = {sim.dt:.4g} s, stability estimate {sim.dt_critical:.4g} s; reduce dt (0.1–0.3 of "
        "the estimate), soften the material, or check the initial overlaps and prescribed velocities"
    )


def step_text(sim: Any) -> str:
    """``dt = … s, stability estimate … s (… of it)`` for the messages."""
    est = sim.dt_critical
    share = f" ({sim.dt / est:.2g} of it)" if math.isfinite(est) and est > 0.0 else ""
    return f"dt = {sim.dt:.4g} s, stability estimate {est:.4g} s{share}"


def non_finite_message(sim: Any, bad: list[tuple[int, str, list[float]]]) -> str:
    """A non-finite state: which particles and fields, and the remedy."""
    ids = sorted({b[0] for b in bad})
    fields = {b[1] for b in bad}
    # a position first: velocities and forces follow from it through the contacts
    order = {"position": 0, "velocity": 1, "angular velocity": 2, "force": 3}
    shown = sorted(bad, key=lambda b: (order[b[1]], b[0]))[:4]
    listed = "; ".join(
        f"particle {i}'s {field} is ({', '.join(f'{c:.4g}' for c in value)})" for i, field, value in shown
    )
    tail = ", …" if len(ids) > 10 else ""
    more = f" ({len(ids)} particles in all, ids {', '.join(map(str, ids[:10]))}{tail})"
    est = sim.dt_critical
    large = not (math.isfinite(est) and est > 0.0) or sim.dt > 0.5 * est
    if large:
        remedy = (
            "reduce dt (0.1–0.3 of the estimate); if a smaller step does not help, look for a "
            "non-finite force, velocity or position set from outside the integration (a boundary "
            "plugin, a script writing sim.particles, an input file)"
        )
    else:
        remedy = (
            "the step is well within the estimate, so look first for a non-finite force, velocity or "
            "position set from outside the integration (a boundary plugin's apply_forces or "
            "before_step, a script writing sim.particles, an input file), then for the prescribed "
            "velocities"
        )
    what = " and ".join(f for f in ("position", "velocity", "angular velocity", "force") if f in fields)
    return (
        f"the run became unstable at step {sim.step_count} (t = {sim.time:.6g} s): a non-finite "
        f"{what} (NaN or infinite): {listed}{more if len(ids) > 1 else ''}. {step_text(sim)}. "
        f"A non-finite value spreads through the contacts from where it first appears: {remedy}"
    )


def overlap_message(sim: Any, worst: float, who: str, detail: dict[str, Any], drifted: bool) -> str:
    """An overlap past ``max_overlap``, told apart as static or dynamic.

    *Static*: the load the rest of the grain's forces push into the contact (in a grain at rest,
    the contact's own force) holds more than the limit at rest, or at least half the overlap while
    the approach's kinetic energy is small beside the contact's elastic energy: the stress over
    the stiffness sets the overlap, and a smaller step changes nothing. *Dynamic*: nothing
    balances the contact (an impact, or a step too large for the contact's stiffness), or the
    grains close fast. With the
    law's elastic curve (:func:`elastic_curve`) the message gives the overlap the load holds at
    rest and, for a dynamic one, the overlap the approach reaches when its kinetic energy is
    stored (from the overlap before the step's drift): past the limit, the impact itself is too
    hard for these grains whatever the step."""
    lim = sim.max_overlap
    r = detail["r"]
    delta = worst * r
    fn, vn, m_eff = detail["fn"], detail["vn"], detail["m_eff"]
    loads = [x for x in detail["loads"] if math.isfinite(x)]
    load = min(loads) if loads else math.nan
    kinetic = 0.5 * m_eff * vn * vn if vn > 0.0 and math.isfinite(m_eff) else 0.0
    curve = elastic_curve(sim, detail)
    rest = impact = math.nan
    if curve is not None:
        d, force, energy = curve
        if loads:
            rest = float(np.interp(max(load, 0.0), force, d, right=math.inf))
        stored = float(np.interp(delta, d, energy))
        before = float(np.interp(max(delta - max(vn, 0.0) * sim.dt, 0.0), d, energy))
        impact = float(np.interp(before + kinetic, energy, d, right=math.inf))
        # the load alone holds more than the limit at rest (however gently it came), or most of
        # the overlap while the approach brings little energy
        static = bool(loads) and (rest > lim * r or (rest >= 0.5 * delta and kinetic <= 0.25 * stored))
    else:
        stored = 0.4 * max(fn, 0.0) * delta  # a Hertz contact's energy, 2/5 F δ
        static = bool(loads) and load >= 0.5 * fn and kinetic <= 0.25 * stored
    drift_note = " after the next step's drift" if drifted else ""
    shown = f"{worst:.4g}" if float(f"{worst:.4g}") > lim else f"{worst:.8g}"  # visibly past it
    head = (
        f"at step {sim.step_count} (t = {sim.time:.6g} s): a {'static' if static else 'dynamic'} "
        f"overlap exceeded run.max_overlap = {lim} of the radius: {shown} of the radius"
        f"{drift_note}, {who}. {step_text(sim)}. The contact carries {fn:.4g} N and "
    )
    head += (
        f"closes at {vn:.3g} m/s ({vn * sim.dt / r:.2g} of the radius per step)"
        if vn > 0.0 else f"opens at {-vn:.3g} m/s"
    )

    def radii(x: float) -> str:
        return f"{x / r:.3g} of the radius" if math.isfinite(x) else "more than two radii"

    if static:
        holds = f", which holds {radii(rest)} at rest under this contact law" if curve is not None else ""
        if curve is not None and rest < 0.9 * delta:
            holds += f" (their motion adds the other {(delta - rest) / r:.2g}; it settles with them)"
        elif kinetic > 0.25 * stored:
            holds += " (and the grains close fast: a load switched on at once overshoots it)"
        stiffer = ""
        if curve is not None and load > 0.0:
            at_target = float(np.interp(0.8 * lim * r, d, force))
            if at_target > 0.0 and load > at_target:
                factor = load / at_target
                hertz = type(sim.law).hertz_from_materials(sim.law.params)  # E sets the stiffness
                stiffer = (
                    f" (contacts about {factor:.2g} times stiffer"
                    f"{f', youngs_modulus × {factor:.2g},' if hertz else ''} hold that load at "
                    f"{0.8 * lim:.2g} of the radius)"
                )
        deepest = max(worst, rest / r if math.isfinite(rest) else worst)
        suggest = min(0.9, math.ceil(100.0 * max(1.3 * deepest, lim + 0.05)) / 100.0)
        return (
            f"the run stopped {head}; the grain's other forces push {load:.4g} N into it{holds}. "
            "The overlap is static: the stress over the stiffness sets it, not the time step, and a "
            f"smaller dt would not change it. Use stiffer grains{stiffer}, or allow larger overlaps "
            f"with a larger run.max_overlap (e.g. {suggest:g}){resume_hint('max_overlap', suggest)}"
        )
    if loads and curve is not None:
        held = f"the grain's other forces push {load:.4g} N into it (holding {radii(rest)} at rest)"
    elif loads:
        held = f"the grain's other forces push only {load:.4g} N into it"
    else:
        held = "nothing but the contact holds the grain"
    est = sim.dt_critical
    share = sim.dt / est if math.isfinite(est) and est > 0.0 else math.inf
    # the step matters when it is a large part of the estimate or moves the grains by a good part of
    # the allowed overlap
    step_big = share > 0.3 or max(vn, 0.0) * sim.dt > 0.25 * lim * r
    if share > 1.0:  # the step is above the estimate: its speeds are the instability's own
        remedy = (
            f"dt is {share:.2g} times the stability estimate, so the explicit step itself is unstable "
            "(the closing speed above is its product, not the scene's): reduce dt (0.1–0.3 of the "
            "estimate), or leave run.force_dt unset so that such a step is refused at the start"
        )
    elif impact > lim * r:
        remedy = (
            f"at that speed the approach alone reaches {radii(impact)} under this contact law, whatever "
            "the step: slow the impact (prescribed velocities, inserted or moving grains), use stiffer "
            "grains, or allow it with a larger run.max_overlap"
        )
        if step_big:
            remedy += "; the step adds to it: reduce dt too (0.1–0.3 of the estimate)"
    elif step_big:
        remedy = (
            "the step lets the grains overrun the contact: reduce dt (0.1–0.3 of the estimate), or "
            "check the initial overlaps and prescribed velocities"
        )
    else:
        remedy = (
            "neither the step nor this approach alone explains it: check the initial overlaps, the "
            "prescribed velocities and loads that jump (a boundary's force switched on at once), "
            "or reduce dt"
        )
    return f"the run became unstable {head}, and {held}. The overlap is dynamic: {remedy}"


def resume_hint(key: str, value: float) -> str:
    """How to continue with ``run.<key>`` changed, when a resume accepts that key."""
    try:
        from .deck.resume import RESUMABLE_RUN_KEYS
    except ImportError:  # pragma: no cover - the deck package is part of pdem
        return ""
    if key not in RESUMABLE_RUN_KEYS:
        return ""
    return f"; pdem resume CHECKPOINT --set run.{key}={value:g} continues from the last checkpoint"
