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
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..parallel.comm import all_max

__all__ = ["STIFFNESS_LIMIT", "network_bound", "step_bound", "supported"]

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
        from ..boundaries._geometry import wall_gaps

        for row in range(cs.counts.shape[0]):
            c = int(cs.counts[row])
            if c == 0:
                continue
            start = int(cs.cstart[row])
            idx = cs.out_idx[start : start + c]
            idx = idx[p.inv_m[idx] > 0.0]
            if idx.size == 0:
                continue
            ov = -wall_gaps(int(cs.kinds[row]), cs.params[row], p.x[idx], p.r[idx])
            keep = ov > 0.0
            idx, ov = idx[keep], ov[keep]
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
