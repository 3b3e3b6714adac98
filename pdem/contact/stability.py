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
mass-weighted coordinates the contact's stiffness matrix A_c has two distinct nonzero eigenvalues::

    λ_n = S_n (1/m_i + 1/m_j)                                  (along the normal)
    λ_t = k_t (1/m_i + 1/m_j + r_i²/I_i + r_j²/I_j)            (in the tangent plane)

and since the network's matrix is the sum of the contacts' and each contact touches two particles,
its largest eigenvalue is at most Ω² = max over particles of Σ_{c ∋ i} ‖A_c‖ (for any matrices,
|y·A_c x| ≤ ‖A_c‖ (|x_i|² + |x_j|² + |y_i|² + |y_j|²)/2; here ‖A_c‖ = max(λ_n, λ_t)). Velocity
Verlet is stable for an undamped mode of frequency Ω if dt ≤ 2/Ω, so::

    dt_stiffness = 2 / Ω

is a lower bound of the undamped linear limit. Walls count as infinitely massive; a frictionless
contact has no tangential spring. Two refinements follow the contact's actual state:

- *Sliding contacts* (:meth:`ContactLaw.contact_slip`, at the Coulomb cap) have no stiffness along
  their slip (the force stays μ F_n whatever the slip) and k_t across it (the cap turns with the
  spring); the normal spring drags the tangential force by μ S_n, a non-symmetric term:
  ‖A_c‖ = max(sqrt(λ_n² + μ² S_n² g_n g_t), λ_t) with g_n, g_t the weights above. In 3-D λ_t still
  wins; in a 2-D scene (below) a sliding contact is left with its normal spring.
- *Locked axes* (the ``dof`` bits: a 2-D mode, grains that may not turn) remove those rows of the
  relative displacement: ‖A_c‖ = ‖G^½ C G^½‖ with G the 3 × 3 Gram matrix of the contact's
  directions over the free axes and C its stiffness in the basis (n, slip, across).

On the 2-D shock-wave bed (docs/study/stability.md), whose struck grain's contacts slide in the
plane while the out-of-plane direction is locked, these raised the bound's minimum from 0.82 to
0.94 T_R (the impact's sliding phase no longer sets it; the stuck peak compression does), 1.94–1.97×
below the step at which the bed blows up (1.82–1.85 T_R); in the 3-D experiments (nothing locked,
λ_t ≈ 3 λ_n) they change nothing. A sliding contact is linearised for continued slip: a reversal
sticks it again (k_t), but its force stays capped. The dashpots are left out on purpose: assembled
the same way, they would bound the explicit-damping limit 2 (sqrt(Ω² + Γ²) − Γ)/Ω², which in the hopper
(e = 0.1) is 0.06 T_R at the fill's impact, while that hopper runs at 0.5 T_R and fails at 0.6 T_R;
the undamped bound there is 0.35 T_R. (A damped contact opens, and a tangential one slides at its
Coulomb cap, before an explicit-damping oscillation can grow.) It is no guarantee for the
nonlinear, history-dependent law (the spring's growth with δ, k_t'|ξ| ≤ μ S_n/3, is left out), and
it is loose: Ω is 1.55–1.6× the exact largest frequency of small jammed clusters
(tests/test_stiffness_bound.py); docs/study/stability.md compares it with the step at which each
experiment fails.

A law opts in by implementing :meth:`ContactLaw.contact_stiffness`; for laws that do not, the bound
is not computed.

The same linearisation, summed over one wall's contacts with the dashpots this time
(:meth:`ContactLaw.contact_damping`), caps the gain of the velocity servos that hold a wall's load
(:func:`wall_stiffness`, :func:`servo_gain`; the triaxial platen, the shear box plate, the
servo-plate plugin): there the dashpots see the wall's velocity directly and matter most.

During a run a :class:`StiffnessMonitor` (``sim.stiffness_monitor``) checks the bound every so many
steps, keeps its record and stops a run whose step has grown too large for its contacts; it also
collects the stiffness that boundaries declare for their loads within a step (DEM-C's mass scaling).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._jit import njit
from ..errors import InputError, InstabilityError
from ..geometry._kernels import surface_velocity, wall_contact
from ..parallel.comm import all_max
from ..parallel.exact import exact_sums

__all__ = [
    "SERVO_LOOP_GAIN", "STIFFNESS_LIMIT", "StiffnessMonitor", "network_bound", "servo_gain", "step_bound",
    "supported", "wall_stiffness",
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


def _per_contact(law, coef, mi, mj, r_eff, m_eff, overlap, sides, n, vn, hist):
    """‖A_c‖ [1/s²] per contact (module docstring): the norm of the contact's mass-weighted
    stiffness. ``sides``: one (inv_m, r²/I, dof) triple of arrays per free particle of the contact
    (one for a wall contact); ``n`` the unit normals, ``vn`` the relative normal velocities and
    ``hist`` the history rows, for :meth:`ContactLaw.contact_slip`."""
    got = law.contact_stiffness(coef, mi, mj, r_eff, m_eff, overlap)
    s_n, k_t = (np.broadcast_to(np.asarray(a, dtype=np.float64), overlap.shape) for a in got)
    g_n = sum(side[0] for side in sides)
    g_t = g_n + sum(side[1] for side in sides)
    lam_n, lam_t = s_n * g_n, k_t * g_t
    lam = np.maximum(lam_n, lam_t)  # sticking, nothing locked
    locked = np.zeros(lam.shape, dtype=bool)
    for side in sides:
        locked |= side[2] != 0
    # sliding changes ‖A_c‖ of a contact free in every axis only through the coupling, and only where
    # λ_n sqrt(1 + (slope/S_n)² g_t/g_n) > λ_t: ask the law about those and the locked ones
    ratio = law.slip_slope_ratio(coef)
    ask = locked | (lam_t * lam_t < lam_n * lam_n * (1.0 + ratio * ratio * g_t / np.maximum(g_n, 1e-300)))
    ask &= k_t > 0.0
    sel = np.flatnonzero(ask)
    dirs = slope = None
    if sel.size:
        slip = law.contact_slip(
            coef, mi[sel], mj[sel], r_eff[sel], m_eff[sel], overlap[sel], vn[sel], hist[sel]
        )
        if slip is not None:
            dirs = np.asarray(slip[0], dtype=np.float64)
            slope = np.broadcast_to(np.asarray(slip[1], dtype=np.float64), sel.shape)
    if dirs is not None:
        sl = np.any(dirs != 0.0, axis=1)
        free = sl & ~locked[sel]
        if np.any(free):  # nothing along the slip; the normal force drags the tangential one
            q = sel[free]
            across = np.sqrt(lam_n[q] ** 2 + slope[free] ** 2 * g_t[q] * g_n[q])
            lam = lam.copy()
            lam[q] = np.maximum(across, lam_t[q])
    if np.any(locked):
        lam = lam.copy()
        loc = np.flatnonzero(locked)
        d_all = np.zeros((lam.size, 3))
        s_all = np.zeros(lam.size)
        if dirs is not None:
            d_all[sel], s_all[sel] = dirs, slope
        lam[loc] = _locked_norms(
            s_n[loc], k_t[loc], n[loc], d_all[loc], s_all[loc],
            [(side[0][loc], side[1][loc], side[2][loc]) for side in sides],
        )
    return lam


def _free_axes(dof: np.ndarray, shift: int) -> np.ndarray:
    """(k, 3) of 1.0 where the axis is free, from the ``dof`` bits (translation shift 0, rotation 3)."""
    bits = np.asarray(dof, dtype=np.int64)[:, None] >> (shift + np.arange(3))[None, :]
    return 1.0 - (bits & 1).astype(np.float64)


def _locked_norms(s_n, k_t, n, dirs, slope, sides):
    """‖A_c‖ for contacts of particles with locked axes (a 2-D mode, a particle that may not turn):
    in the contact basis (n, t1, t2), t1 along the slip of a sliding contact, the relative
    displacement of the contact point is D x with D D^T = G, the Gram matrix of the free axes'
    mass-weighted rows, and the contact's stiffness is D^T C D, so ‖A_c‖ = ‖G^½ C G^½‖ (3 × 3)."""
    k = n.shape[0]
    sliding = np.zeros(k, dtype=bool) if dirs is None else np.any(dirs != 0.0, axis=1)
    if dirs is not None:  # a spring (nearly) along the normal has no slip direction: count it stuck
        along = dirs - np.einsum("ij,ij->i", dirs, n)[:, None] * n
        sliding &= np.einsum("ij,ij->i", along, along) > 1e-12
    helper = np.where(np.abs(n[:, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.where(sliding[:, None], dirs if dirs is not None else helper, helper)
    t1 = t1 - np.einsum("ij,ij->i", t1, n)[:, None] * n
    t1 /= np.sqrt(np.einsum("ij,ij->i", t1, t1))[:, None]
    t2 = np.cross(n, t1)
    basis = np.stack([n, t1, t2], axis=1)  # rows: the directions a
    turn = np.stack([np.zeros_like(n), t2, -t1], axis=1)  # n × a: the lever of a rotation on a
    gram = np.zeros((k, 3, 3))
    for inv_m, rot, dof in sides:
        free_t, free_r = _free_axes(dof, 0), _free_axes(dof, 3)
        gram += inv_m[:, None, None] * np.einsum("kac,kc,kbc->kab", basis, free_t, basis)
        gram += rot[:, None, None] * np.einsum("kac,kc,kbc->kab", turn, free_r, turn)
    c = np.zeros((k, 3, 3))
    c[:, 0, 0] = s_n
    c[:, 1, 0] = np.where(sliding, -slope, 0.0)  # on j along t1 = the spring's direction: −μ F_n; δ = −ρ_n
    c[:, 1, 1] = np.where(sliding, 0.0, k_t)
    c[:, 2, 2] = k_t
    w, v = np.linalg.eigh(gram)
    half = np.einsum("kab,kb,kcb->kac", v, np.sqrt(np.clip(w, 0.0, None)), v)
    x = half @ c @ half
    top = np.linalg.eigvalsh(np.transpose(x, (0, 2, 1)) @ x)[:, -1]
    return np.sqrt(np.clip(top, 0.0, None))


_NONE = (np.zeros(0, dtype=np.int64), np.zeros(0))


@njit
def _touching(kind, prm, cand, x, r, inv_m, idx, ov):  # pragma: no cover - compiled
    """Of the candidates ``cand``, the free grains that overlap the wall row (kind, prm): their rows
    into ``idx``, overlaps into ``ov``, by the force loop's own geometry kernel. Returns the count."""
    m = 0
    for q in range(cand.shape[0]):
        i = cand[q]
        if i >= 0 and inv_m[i] > 0.0:
            gap = wall_contact(kind, prm, x[i, 0], x[i, 1], x[i, 2], r[i])[0]
            if gap < 0.0:
                idx[m] = i
                ov[m] = -gap
                m += 1
    return m


@njit
def _touching_full(kind, prm, k, vel, omega, centre, cand, x, v, r, inv_m, idx, ov, q_of, nrm, vn):  # pragma: no cover # noqa: E501
    """:func:`_touching` with, per contact, its candidate slot ``q_of`` (its history row), the
    normal ``nrm`` (into the wall) and the normal velocity ``vn`` = (v_wall − v_i)·n at the contact
    point, as the force loop computes them."""
    m = 0
    for q in range(cand.shape[0]):
        i = cand[q]
        if i >= 0 and inv_m[i] > 0.0:
            gap, nx, ny, nz, px, py, pz = wall_contact(kind, prm, x[i, 0], x[i, 1], x[i, 2], r[i])
            if gap < 0.0:
                vwx, vwy, vwz, _, _, _ = surface_velocity(kind, prm, vel, omega, centre, k, px, py, pz)
                idx[m] = i
                ov[m] = -gap
                q_of[m] = q
                nrm[m, 0] = nx
                nrm[m, 1] = ny
                nrm[m, 2] = nz
                vn[m] = (vwx - v[i, 0]) * nx + (vwy - v[i, 1]) * ny + (vwz - v[i, 2]) * nz
                m += 1
    return m


@njit
def _touching_pairs(order, pi, pj, x, v, r, inv_m, rows, ov, nrm, vn):  # pragma: no cover - compiled
    """Of the listed pairs ``order[k]`` (pair rows, in key order), those that overlap with a free
    grain on either side: their pair rows into ``rows``, overlaps δ, unit normals (i → j) and normal
    velocities (v_j − v_i)·n, in that order. |d| = sqrt(dx² + dy² + dz²) summed left to right, as
    the force loops do, so these are exactly the contacts the last force evaluation saw (NumPy's
    einsum, used before, summed in another order and differed in the last bit for ~1 pair in 10).
    Returns the count."""
    m = 0
    for k in range(order.shape[0]):
        q = order[k]
        i = pi[q]
        j = pj[q]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        dist = np.sqrt(dx * dx + dy * dy + dz * dz)
        overlap = r[i] + r[j] - dist
        if overlap > 0.0 and inv_m[i] + inv_m[j] > 0.0:
            nx = dx / dist
            ny = dy / dist
            nz = dz / dist
            rows[m] = q
            ov[m] = overlap
            nrm[m, 0] = nx
            nrm[m, 1] = ny
            nrm[m, 2] = nz
            vn[m] = (v[j, 0] - v[i, 0]) * nx + (v[j, 1] - v[i, 1]) * ny + (v[j, 2] - v[i, 2]) * nz
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


def _row_contacts_full(sim: Any, row: int):
    """:func:`_row_contacts` over the row's candidates, with normals, normal velocities and history
    rows: (idx, δ, n, vn, hist) or ``None`` when nothing touches."""
    cs = sim.contact_store
    a, b = int(cs.cstart[row]), int(cs.cstart[row + 1])
    if b <= a:
        return None
    p = sim.particles
    cand = cs.cand_step[a:b]  # as the force loop saw them (set-aside mesh duplicates < 0)
    c = cand.shape[0]
    idx = np.empty(c, dtype=np.int64)
    ov = np.empty(c)
    q_of = np.empty(c, dtype=np.int64)
    nrm = np.empty((c, 3))
    vn = np.empty(c)
    m = _touching_full(int(cs.kinds[row]), cs.params[row], row, cs.vel, cs.omega, cs.centre, cand, p.x, p.v,
                       p.r, p.inv_m, idx, ov, q_of, nrm, vn)  # fmt: skip
    if m == 0:
        return None
    return idx[:m], ov[:m], nrm[:m], vn[:m], cs.wall_hist[a + q_of[:m]]


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
    # particle pairs, in key order: the per-particle sums below do not depend on the list's order
    ko = cs.pair_rows_in_key_order()
    n_pairs = cs.pi.shape[0]
    if n_pairs:
        order = np.arange(n_pairs, dtype=np.int64) if isinstance(ko, slice) else ko
        rows = np.empty(n_pairs, dtype=np.int64)
        ov = np.empty(n_pairs)
        n = np.empty((n_pairs, 3))
        vn = np.empty(n_pairs)
        m = _touching_pairs(order, cs.pi, cs.pj, p.x, p.v, p.r, p.inv_m, rows, ov, n, vn)
        if m:
            rows, ov, n, vn = rows[:m], ov[:m], n[:m], vn[:m]
            a, b = cs.pi[rows], cs.pj[rows]
            ra, rb = p.r[a], p.r[b]
            ima, imb = p.inv_m[a], p.inv_m[b]
            inv_sum = ima + imb
            sides = [(ima, ra * ra * p.inv_i[a], p.dof[a]), (imb, rb * rb * p.inv_i[b], p.dof[b])]
            lam = _per_contact(
                law, coef, p.mat[a], p.mat[b], ra * rb / (ra + rb), 1.0 / inv_sum, ov, sides, n, vn,
                cs.hist[rows],
            )
            lam_sum += np.bincount(a, weights=lam, minlength=n_rows)
            lam_sum += np.bincount(b, weights=lam, minlength=n_rows)
    # walls: the partner is infinitely massive (R* = r, m* = m, as in the wall kernel)
    if cs.kinds.shape[0]:
        for row in range(min(cs.kinds.shape[0], cs.cstart.shape[0] - 1)):
            got = _row_contacts_full(sim, row)
            if got is None:
                continue
            idx, ov, n, vn, hist = got
            r = p.r[idx]
            im = p.inv_m[idx]
            lam = _per_contact(
                law, coef, p.mat[idx], np.full(idx.size, int(cs.wmat[row])), r, 1.0 / im, ov,
                [(im, r * r * p.inv_i[idx], p.dof[idx])], n, vn, hist,
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


class StiffnessMonitor:
    """The live step bound of one simulation's run (``sim.stiffness_monitor``), and the stiffness
    of its boundaries' loads within a step.

    ``every``: check the bound (:func:`step_bound`) every this many steps for penalty laws that
    support it (0: never), and at steps 1, 2, 4, … below it (a run's first steps are often its
    impact: a coarse run of ~100 steps saw it only once). ``limit``: stop (InstabilityError) when
    dt exceeds this multiple of the bound; 0: never. ``record``: the smallest bound [s], the step
    it was met, how many checks were made and at how many the step exceeded the bound. ``load``:
    per owned particle, the stiffness [N/m] the boundaries declared for this step's loads
    (:meth:`add_load`), or None."""

    def __init__(self, sim: Any, every: int = 100, limit: float = STIFFNESS_LIMIT) -> None:
        self.sim = sim
        self.every = every
        self.limit = limit
        self.record = self.fresh_record()
        self.load: np.ndarray | None = None

    @staticmethod
    def fresh_record() -> dict[str, float]:
        """The record before any check."""
        return {"min_dt": math.inf, "step": -1.0, "checks": 0.0, "exceeded": 0.0}

    def restore(self, saved: dict[str, Any]) -> None:
        """Start from a checkpoint's record (``saved``: name → value; names it lacks start afresh)."""
        self.record = self.fresh_record()
        for name in self.record:
            if name in saved:
                self.record[name] = float(saved[name])

    def due(self, step: int) -> bool:
        """Whether the bound is checked at the end of step number ``step``."""
        every, n = self.every, step
        return bool(every and (n % every == 0 or (n < every and n & (n - 1) == 0)))

    def check(self) -> float:
        """The step the contact network bears now (:func:`step_bound`), recorded in :attr:`record`
        (collective; ``nan`` for laws without the bound)."""
        sim = self.sim
        if not supported(sim.law):
            return math.nan
        bound = step_bound(sim)
        rec = self.record
        rec["checks"] += 1
        if bound < rec["min_dt"]:
            rec["min_dt"], rec["step"] = bound, float(sim.step_count)
        dt = sim.dt
        if dt > bound:
            rec["exceeded"] += 1
            if self.limit > 0 and dt > self.limit * bound:
                raise InstabilityError(
                    f"the step is too large for the contacts at step {sim.step_count} "
                    f"(t = {sim.time:.6g} s): dt = {dt:.4g} s is {dt / bound:.3g} times the "
                    "step the contact network bears "
                    f"now ({bound:.4g} s, from the contacts' stiffness, coordination and friction; the law's "
                    f"estimate {sim.dt_critical:.4g} s does not see them), above run.stiffness_limit = "
                    f"{self.limit:g}. Runs past it can end wrong without blowing up. Take dt ≤ "
                    f"{0.8 * bound:.3g} s (0.8 of the bound: it moves with the packing; run.dt, or "
                    f"run.dt_fraction = {0.8 * bound / sim.dt_critical:.3g}), or soften the material; "
                    "run.stiffness_limit = 0 lets the run go on"
                )
        return bound

    @property
    def wanted(self) -> bool:
        """Whether the method steps with the boundaries' load stiffness (its integrator's
        ``wants_load_stiffness``)."""
        return bool(getattr(self.sim.integrator, "wants_load_stiffness", False))

    def add_load(self, rows: np.ndarray, k: np.ndarray) -> None:
        """Add stiffnesses ``k`` [N/m] of owned particles ``rows`` to this step's :attr:`load`
        (``Simulation.add_load_stiffness``)."""
        n = self.sim.particles.n_owned
        rows = np.asarray(rows, dtype=np.int64)
        k = np.asarray(k, dtype=float)
        if rows.shape != k.shape:
            raise InputError(f"add_load_stiffness: {rows.shape[0]} rows but {k.shape} stiffnesses")
        if rows.size and (rows.min() < 0 or rows.max() >= n):
            raise InputError("add_load_stiffness: rows must index owned particles")
        if not np.all(np.isfinite(k)) or (k.size and k.min() < 0.0):
            raise InputError("add_load_stiffness: stiffnesses must be finite and ≥ 0 [N/m]")
        added = np.bincount(rows, weights=k, minlength=n)
        if self.load is None or self.load.shape[0] != n:
            self.load = added
        else:
            self.load += added
