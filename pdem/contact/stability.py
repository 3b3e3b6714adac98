"""The step a penalty scene can bear now, from the stiffness of its actual contacts.

The law's :meth:`~pdem.contact.law.ContactLaw.critical_dt` is a property of the material (for
Hertz–Mindlin the Rayleigh time T_R): it knows neither how hard the grains press on each other nor
how many neighbours each has nor that friction couples rotation to translation. The step studies
(docs/study/) measured DEM-P failing from 0.5–0.7 T_R in dense, frictional scenes (hopper, triaxial,
direct shear) but only beyond 2 T_R in a frictionless chain. This module bounds the largest
frequency of the contact network as it is, in the manner of YADE's ``GlobalStiffnessTimeStepper``
but as a rigorous bound:

Linearise each touching contact c between particles i and j: a normal spring S_n = dF_n/dδ and a
tangential spring k_t acting on the relative displacement of the contact point, which involves the
translations (masses m) and, for the tangential part, the rotations (inertias I, lever arms r). In
mass-weighted coordinates the contact's stiffness matrix has two distinct nonzero eigenvalues::

    λ_n = S_n (1/m_i + 1/m_j)                                  (along the normal)
    λ_t = k_t (1/m_i + 1/m_j + r_i²/I_i + r_j²/I_j)            (in the tangent plane)

and since the network's matrix is the sum of the contacts' and each contact touches two particles,
its largest eigenvalue is at most Ω² = max over particles of Σ_{c ∋ i} max(λ_n, λ_t) (the quadratic
form of every contact is at most its λ_c times the squared weighted displacement of its two
particles). Velocity Verlet is stable for an undamped mode of frequency Ω if dt ≤ 2/Ω, so::

    dt_stiffness = 2 / Ω

is a lower bound of the undamped linear limit. Walls count as infinitely massive; a frictionless
contact has no tangential spring. The dashpots are left out on purpose: assembled the same way,
they would bound the explicit-damping limit 2 (sqrt(Ω² + Γ²) − Γ)/Ω², which in the hopper
(e = 0.1) is 0.06 T_R at the fill's impact, while that hopper runs at 0.5 T_R and fails at 0.6 T_R;
the undamped bound there is 0.35 T_R. (A damped contact opens, and a tangential one slides at its
Coulomb cap, before an explicit-damping oscillation can grow.) It is no guarantee for the
nonlinear, history-dependent law, and it is loose: Ω is 1.55–1.6× the exact largest frequency of
small jammed clusters (tests/test_stiffness_bound.py); docs/study/stability.md compares it with the
step at which each experiment fails.

A law opts in by implementing :meth:`ContactLaw.contact_stiffness`; for laws that do not, the bound
is not computed.

The same linearisation, summed over one wall's contacts with the dashpots this time
(:meth:`ContactLaw.contact_damping`), caps the gain of the velocity servos that hold a wall's load
(:func:`wall_stiffness`, :func:`servo_gain`; the triaxial platen, the shear box plate, the
servo-plate plugin): there the dashpots see the wall's velocity directly and matter most.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._jit import njit
from ..boundaries._geometry import wall_contact
from ..parallel.comm import all_max
from ..parallel.exact import exact_sums

__all__ = [
    "SERVO_LOOP_GAIN", "STIFFNESS_LIMIT", "network_bound", "servo_gain", "step_bound", "supported",
    "wall_stiffness",
]

#: default ``run.stiffness_limit``: a run stops when dt exceeds this multiple of the bound (the
#: bound is conservative; docs/study/stability.md gives the measured failures it was chosen from)
STIFFNESS_LIMIT = 1.25


def supported(law: Any) -> bool:
    """Whether the bound can be computed for this law: a penalty law that implements
    :meth:`ContactLaw.contact_stiffness` (the same answer on every rank)."""
    from .law import ContactLaw

    own = type(law).contact_stiffness is not ContactLaw.contact_stiffness
    return getattr(law, "kind", "") == "penalty" and own


def _per_contact(law, coef, mi, mj, r_eff, m_eff, overlap, inv_n, inv_t):
    """λ_c [1/s²] per contact, with inv_n = 1/m_i + 1/m_j and inv_t = inv_n + the lever arms' r²/I."""
    got = law.contact_stiffness(coef, mi, mj, r_eff, m_eff, overlap)
    s_n, k_t = (np.broadcast_to(np.asarray(a, dtype=np.float64), overlap.shape) for a in got)
    return np.maximum(s_n * inv_n, k_t * inv_t)


_NONE = (np.zeros(0, dtype=np.int64), np.zeros(0))


@njit
def _touching(kind, prm, cand, x, r, inv_m, idx, ov):  # pragma: no cover - compiled
    """Of the candidates ``cand``, the free grains that overlap the wall row (kind, prm): their rows
    into ``idx``, overlaps into ``ov``, by the force loop's own geometry kernel. Returns the count."""
    m = 0
    for q in range(cand.shape[0]):
        i = cand[q]
        if inv_m[i] > 0.0:
            gap = wall_contact(kind, prm, x[i, 0], x[i, 1], x[i, 2], r[i])[0]
            if gap < 0.0:
                idx[m] = i
                ov[m] = -gap
                m += 1
    return m


def _row_contacts(sim: Any, row: int) -> tuple[np.ndarray, np.ndarray]:
    """(particle rows, overlaps δ > 0 [m]) of the touching contacts of wall row ``row`` in the last
    force evaluation, free grains only, on this rank (wall candidates are owned grains: each contact
    is on exactly one rank)."""
    cs = sim.contact_store
    c = int(cs.counts[row]) if row < cs.counts.shape[0] else 0
    if c == 0:
        return _NONE
    p = sim.particles
    start = int(cs.cstart[row])
    idx = np.empty(c, dtype=np.int64)
    ov = np.empty(c)
    cand = cs.out_idx[start : start + c]
    m = _touching(int(cs.kinds[row]), cs.params[row], cand, p.x, p.r, p.inv_m, idx, ov)
    return idx[:m], ov[:m]


def network_bound(sim: Any) -> float:
    """Ω² [1/s²]: the largest per-particle sum of the contacts' λ_c over this rank's owned particles
    (the law must be :func:`supported`). Not collective."""
    law = sim.law
    p = sim.particles
    cs = sim.contact_store
    n_rows = p.x.shape[0]
    n_own = p.n_owned
    lam_sum = np.zeros(n_rows)
    coef = sim.coefficients
    # particle pairs
    pi, pj = cs.pi, cs.pj
    if pi.shape[0]:
        d = p.x[pj] - p.x[pi]
        dist = np.sqrt(np.einsum("ij,ij->i", d, d))
        overlap = p.r[pi] + p.r[pj] - dist
        touch = overlap > 0.0
        if np.any(touch):
            a, b, ov = pi[touch], pj[touch], overlap[touch]
            ra, rb = p.r[a], p.r[b]
            ima, imb = p.inv_m[a], p.inv_m[b]
            inv_sum = ima + imb
            live = inv_sum > 0.0
            a, b, ov, ra, rb, ima, imb, inv_sum = (
                q[live] for q in (a, b, ov, ra, rb, ima, imb, inv_sum)
            )
            lam = _per_contact(
                law, coef, p.mat[a], p.mat[b], ra * rb / (ra + rb), 1.0 / inv_sum, ov,
                inv_sum, inv_sum + ra * ra * p.inv_i[a] + rb * rb * p.inv_i[b],
            )
            lam_sum += np.bincount(a, weights=lam, minlength=n_rows)
            lam_sum += np.bincount(b, weights=lam, minlength=n_rows)
    # walls: the partner is infinitely massive (R* = r, m* = m, as in the wall kernel)
    if cs.kinds.shape[0] and cs.counts.shape[0]:
        for row in range(cs.counts.shape[0]):
            idx, ov = _row_contacts(sim, row)
            if idx.size == 0:
                continue
            r = p.r[idx]
            im = p.inv_m[idx]
            lam = _per_contact(
                law, coef, p.mat[idx], np.full(idx.size, int(cs.wmat[row])), r, 1.0 / im, ov,
                im, im + r * r * p.inv_i[idx],
            )
            lam_sum += np.bincount(idx, weights=lam, minlength=n_rows)
    return float(lam_sum[:n_own].max()) if n_own else 0.0


def step_bound(sim: Any) -> float:
    """The step [s] the contact network bears now (see the module docstring): collective; ``inf``
    with no contacts, ``nan`` when the law is not :func:`supported`."""
    if not supported(sim.law):
        return math.nan
    omega2 = all_max(sim.comm, network_bound(sim))
    return 2.0 / math.sqrt(omega2) if omega2 > 0.0 else math.inf



def _damped(law: Any) -> bool:
    from .law import ContactLaw

    return type(law).contact_damping is not ContactLaw.contact_damping


def wall_stiffness(sim: Any, wall: Any) -> tuple[float, float]:
    """(K [N/m], C [N s/m]): the normal stiffness Σ S_n and the normal dashpots Σ c_n of ``wall``'s
    touching contacts in the last force evaluation (free grains; the wall is the rigid partner,
    R* = r and m* = m as in the wall kernel). For a flat wall moved along its normal at v with the
    grains held still, its load changes by K v dt + C Δv in a step (a contact tilted by θ adds
    S_n cos²θ ≤ S_n: an upper bound for a finite plate's edge contacts). C is 0 for a law without
    :meth:`~pdem.contact.law.ContactLaw.contact_damping`. Collective: exact sums over ranks (each
    wall contact is on one rank), so the same bits on any rank count; (0, 0) when nothing touches
    it, (nan, nan) when the law is not :func:`supported` (e.g. DEM-C, which has no stiffness)."""
    if not supported(sim.law):
        return math.nan, math.nan
    law = sim.law
    damped = _damped(law)
    cs = sim.contact_store
    p = sim.particles
    parts = []
    k = next((i for i, w in enumerate(cs.walls) if w is wall), None)
    if k is not None and wall.active and cs.wall_rows.shape[0] == len(cs.walls) + 1:
        for row in range(int(cs.wall_rows[k]), int(cs.wall_rows[k + 1])):
            idx, ov = _row_contacts(sim, row)
            if idx.size == 0:
                continue
            args = (sim.coefficients, p.mat[idx], np.full(idx.size, int(cs.wmat[row])), p.r[idx],
                    1.0 / p.inv_m[idx], ov)  # fmt: skip
            col = np.empty((idx.size, 2))
            col[:, 0] = law.contact_stiffness(*args)[0]
            col[:, 1] = law.contact_damping(*args)[0] if damped else 0.0
            parts.append(col)
    rows = np.concatenate(parts) if parts else np.zeros((0, 2))
    k_sum, c_sum = exact_sums(sim.comm, rows)
    return float(k_sum), float(c_sum)


#: the largest loop gain g = gain (K dt + 2 C) / A a velocity servo is given (:func:`servo_gain`)
SERVO_LOOP_GAIN = 1.0


def servo_gain(sim: Any, wall: Any, gain: float, area: float) -> tuple[float, float]:
    """A proportional velocity servo's gain [m/(s Pa)] capped for the step, and its loop gain.

    A servo sets ``wall``'s velocity to v_n = gain e_n from the error e = σ_target − σ of the last
    step's load, σ = F/``area`` = A. With the grains held still (they barely move in one step), the
    wall's contacts (:func:`wall_stiffness`) give σ_{n+1} = σ_n + (K dt v_n + C (v_n − v_{n−1}))/A:
    the springs see the displacement, the dashpots the velocity itself. With a = gain K dt / A and
    b = gain C / A the error follows e_{n+1} = (1 − a − b) e_n + b e_{n−1}, stable only for
    g = a + 2b = gain (K dt + 2 C) / A < 2 (past it the wall chatters, its velocity alternating
    every step); without dashpots it is e_{n+1} = (1 − g) e_n, which overshoots for g > 1. Both
    terms matter: a larger step raises a; a lower target (a larger default gain max_speed / target),
    a faster max_speed or a stiffer, more damped material raise both. In the failures measured
    (docs/deck.md) the dashpots' 2b was most of g.

    The gain is capped so that g ≤ :data:`SERVO_LOOP_GAIN` = 1, i.e. gain ≤ A / (K dt + 2 C): for
    springs alone the one-step model then reaches the target without overshoot (g = 1 is its fastest
    monotone response), the alternating part the dashpots add shrinks at least 2-fold per step (the
    negative root of z² − (1 − a − b) z − b is at most ½ in magnitude), and the margin against the
    instability at g = 2 is 2. K and C are read afresh every step, so only what the one-step model
    misses systematically eats the margin: the Hertz S_n and c_n growing with the overlap during the
    step (∝ δ^½, δ^¼), contacts made during the step; the grains' own motion lowers the wall's
    effective stiffness (it helps). Why not lower: a cap of 0.5 doubled the normal-stress error of
    the shipped reduced direct shear deck during shear (0.38 % → 0.85 %; 1: 0.40 %), whose servo
    runs at g = 0.5–1.15, and removed no failure that 1 leaves (docs/deck.md).

    Below the cap the gain is returned unchanged (the same bits as without the cap); it is uncapped
    while nothing touches the wall (K = C = 0: full speed towards the grains) and for laws without
    a stiffness (nan: DEM-C, or a law without ``contact_stiffness``). Collective. Returns (the gain
    to use, g of the given gain: 0 with nothing touching, nan without a stiffness)."""
    k, c = wall_stiffness(sim, wall)
    response = k * sim.dt + 2.0 * c
    if not response > 0.0:
        return gain, (0.0 if response == 0.0 else math.nan)
    loop = gain * response / area
    cap = SERVO_LOOP_GAIN
    if loop > cap:
        return cap * area / response, loop
    return gain, loop
