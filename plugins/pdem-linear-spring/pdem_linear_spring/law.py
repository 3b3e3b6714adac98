"""Linear spring–dashpot contact with tangential history and a Coulomb cap (DEM-P).

The classic Cundall–Strack law with constant stiffnesses (a pdem plugin; see docs/plugins.md).
With the pair's effective mass m*, restitution e and friction μ (mixed by the material table)::

    β   = ln e / sqrt(ln² e + π²)              (−1 for e = 0)
    k_t = kt_over_kn · k_n
    c_n = −2 β sqrt(k_n m*)                     c_t = c_n sqrt(k_t/k_n) = −2 β sqrt(k_t m*)
    F_n = k_n δ − c_n v_n                        (v_n = v·n < 0 while approaching)

so that the normal contact is the damped linear oscillator m* δ'' + c_n δ' + k_n δ = 0: it lasts
t_c = π / sqrt(k_n/m* − (c_n/(2 m*))²) and the spheres separate with exactly e times their approach
speed (unclamped). The tangential dashpot gives the tangential spring the same damping ratio with
respect to m*.

Tangential spring ξ (3 floats of history per contact, global frame, zero when the contact starts):
rotated onto the current tangent plane keeping its length, then ξ += v_t dt, F_t = −k_t ξ − c_t v_t
on j; if |F_t| > μ max(F_n, 0) it is scaled to the cap and the spring follows the slider,
ξ = −F_t/k_t (the spring alone carries the Coulomb force, exactly as pdem's built-in Hertz–Mindlin:
storing ξ = −(F_t + c_t v_t)/k_t would let friction reverse and drive the slip at the start of a
damped sliding contact; see ``pdem.laws.hertz_mindlin``). No rolling resistance: a material pair
with ``rolling_friction`` > 0 is refused rather than silently ignored.

``clamp_normal = true`` forbids the brief attractive normal force at the end of a damped contact
(F_n ≥ 0); the realised restitution is then higher than e.

**Time step.** ``critical_dt`` is the linear stability limit, under pdem's velocity Verlet (the
dashpots see the half-step velocity), of the stiffest packing the law can meet: an FCC crystal of
the lightest spheres, 12 contacts each, every contact at the smallest restitution of the material
table (ζ = −β). For a mode of frequency Ω and damping rate 2Γ the scheme is stable for
dt ≤ 2 (sqrt(Ω² + Γ²) − Γ)/Ω², and the crystal's two extreme modes are, with ω₂ = sqrt(k_n/m*),
m* = m_min/2 and ρ = k_t/k_n::

    translation at the zone boundary:  Ω² = 4 (1 + ρ) ω₂²     Γ = 4 ζ (1 + sqrt ρ) ω₂
    uniform rotation (tangential):     Ω² = 20 ρ ω₂²          Γ = 20 ζ sqrt(ρ) ω₂

``critical_dt`` is the smaller of the two limits (a Bloch-wave analysis of the damped crystal over
the whole Brillouin zone gives the same number to 4 digits). Relative to the two-body limit
2 sqrt(m*/k_n) of an undamped pair, the factor is 0.42 at e = 1, 0.36 at e = 0.9, 0.18 at e = 0.5
and 0.046 at e = 0 (default ρ = 2/7, where the rotation mode is the stiffer one). Random packings
have fewer contacts and are more stable. ``suggested_dt`` = min(0.5 critical_dt, t_c/50), with t_c
the undamped contact duration π sqrt(m*/k_n) of the two lightest spheres: stable with a margin of 2
and at least 50 steps per contact. Accuracy is first order in dt/t_c because the dashpot sees the
half-step velocity; measured head-on (dt as a fraction of the damped t_c), the realised restitution
is low by 0.8 % (e = 0.2), 1.5 % (e = 0.5), 0.04 % (e = 0.9) at t_c/50 and by 0.07 %, 0.14 %,
0.003 % at t_c/500.

Coefficient row layout: ``[k_n, k_t, β, sqrt(k_t/k_n), μ, clamp]``.
"""

from __future__ import annotations

import math

import numpy as np
from pdem.api import (
    ContactLaw,
    InputError,
    LawParams,
    MaterialTable,
    damping_ratio,
    njit,
    pair_forces,
    tangential_spring,
    wall_forces,
)
from pydantic import Field

__all__ = [
    "LinearSpring",
    "LinearSpringParams",
    "linear_spring_force",
    "force_numpy",
    "stable_dt",
    "contact_duration",
]


@njit(inline="always")
def linear_spring_force(delta, nx, ny, nz, vx, vy, vz, wx, wy, wz, r_eff, m_eff, i_eff, coef, mi, mj,
                        hist, k, dt):
    k_n = coef[mi, mj, 0]
    k_t = coef[mi, mj, 1]
    vn = vx * nx + vy * ny + vz * nz
    vtx = vx - vn * nx
    vty = vy - vn * ny
    vtz = vz - vn * nz
    # c_n = −2 β sqrt(k_n m*), c_t = c_n sqrt(k_t/k_n)
    c_n = -2.0 * coef[mi, mj, 2] * math.sqrt(k_n * m_eff)
    c_t = c_n * coef[mi, mj, 3]
    fn = k_n * delta - c_n * vn
    if coef[mi, mj, 5] != 0.0 and fn < 0.0:
        fn = 0.0
    fcap = coef[mi, mj, 4] * fn if fn > 0.0 else 0.0
    ftx, fty, ftz = tangential_spring(hist, k, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt)
    return (fn * nx + ftx, fn * ny + fty, fn * nz + ftz, 0.0, 0.0, 0.0)


# fmt: off
@njit
def linear_spring_pair_kernel(pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt,
                              max_overlap):
    return pair_forces(linear_spring_force, pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair,
                       dt, max_overlap)


@njit
def linear_spring_wall_kernel(kinds, params, vel, omega, centre, wmat, cstart, cand, hist, x, v, w, r, inv_m,
                              inv_i, mat, coef, f, t, dt, max_overlap, out_idx, out_val, counts):
    return wall_forces(linear_spring_force, kinds, params, vel, omega, centre, wmat, cstart, cand, hist, x, v,
                       w, r, inv_m, inv_i, mat, coef, f, t, dt, max_overlap, out_idx, out_val, counts)
# fmt: on


def force_numpy(delta, n, vrel, wrel, r_eff, m_eff, i_eff, c, hist, dt):
    """Plain-Python twin of :func:`linear_spring_force` (vectors as arrays), for contract tests.

    ``c`` is the coefficient row of the pair; ``hist`` (3 floats) is updated in place. Returns
    (force on j, extra torque on j) — the torque is always zero (no rolling resistance).
    """
    n = np.asarray(n, float)
    vrel = np.asarray(vrel, float)
    k_n, k_t, beta, mu, clamp = c[0], c[1], c[2], c[4], c[5]
    vn = float(vrel @ n)
    vt = vrel - vn * n
    c_n = -2.0 * beta * math.sqrt(k_n * m_eff)
    c_t = -2.0 * beta * math.sqrt(k_t * m_eff)
    fn = k_n * delta - c_n * vn
    if clamp != 0.0:
        fn = max(fn, 0.0)
    s = np.array(hist[:3], float)
    old = np.linalg.norm(s)
    if old > 0:
        s = s - (s @ n) * n
        new = np.linalg.norm(s)
        if new > 0:
            s *= old / new
    s = s + vt * dt
    ft = -k_t * s - c_t * vt
    cap = mu * max(fn, 0.0)
    if np.linalg.norm(ft) > cap:
        ft = ft * (cap / np.linalg.norm(ft))
        s = -ft / k_t
    hist[:3] = s
    return fn * n + ft, np.zeros(3)


def stable_dt(kn: float, kt_over_kn: float, m_eff: float, zeta: float) -> float:
    """Stability limit [s] of an FCC crystal of spheres with pair mass ``m_eff`` (see module docstring).

    ``zeta`` = −β ≥ 0 is the damping ratio of a two-body contact."""
    rho = kt_over_kn
    modes = ((4.0 * (1.0 + rho), 4.0 * zeta * (1.0 + math.sqrt(rho))),
             (20.0 * rho, 20.0 * zeta * math.sqrt(rho)))
    factor = min(2.0 * (math.sqrt(om2 + g * g) - g) / om2 for om2, g in modes)
    return factor * math.sqrt(m_eff / kn)


def contact_duration(kn: float, m_eff: float, e: float) -> float:
    """t_c = π / sqrt(k_n/m* − (c_n/(2 m*))²) [s] of an unclamped head-on contact (inf for e = 0)."""
    beta = damping_ratio(e)
    c_n = -2.0 * beta * math.sqrt(kn * m_eff)
    omega2 = kn / m_eff - (c_n / (2.0 * m_eff)) ** 2
    return math.pi / math.sqrt(omega2) if omega2 > 0.0 else math.inf


class LinearSpringParams(LawParams):
    """Parameters of :class:`LinearSpring` (unknown keys are errors).

    ``kn``: normal stiffness k_n [N/m]. ``kt_over_kn``: k_t/k_n (2/7 by default: for solid spheres
    the tangential and normal contact oscillations then have the same period). ``clamp_normal``:
    forbid an attractive damped normal force.
    """

    kn: float = Field(gt=0, allow_inf_nan=False, description="normal stiffness k_n [N/m]")
    kt_over_kn: float = Field(default=2.0 / 7.0, gt=0, allow_inf_nan=False,
                              description="tangential over normal stiffness k_t/k_n [-]")
    clamp_normal: bool = Field(default=False, description="clamp the normal force to F_n ≥ 0")


class LinearSpring(ContactLaw):
    """Linear spring–dashpot law with tangential history and a Coulomb cap (see module docstring)."""

    name = "linear_spring"
    kind = "penalty"
    history_size = 3
    n_coef = 6
    Params = LinearSpringParams
    pair_kernel = linear_spring_pair_kernel
    wall_kernel = linear_spring_wall_kernel

    def pair_coefficients(self, materials: MaterialTable, a: int, b: int) -> np.ndarray:
        p = self.params
        for key, what in (("rolling_friction", "rolling"), ("spinning_friction", "spinning")):
            if materials.mixed(a, b, key) > 0.0:
                raise InputError(
                    f"law 'linear_spring' has no {what} resistance, but materials '{materials[a].name}' "
                    f"and '{materials[b].name}' have {key} > 0; set {key} = 0 or use "
                    "law = 'hertz_mindlin'"
                )
        beta = damping_ratio(materials.mixed(a, b, "restitution"))
        clamp = 1.0 if p.clamp_normal else 0.0
        mu = materials.mixed(a, b, "friction")
        return np.array([p.kn, p.kt_over_kn * p.kn, beta, math.sqrt(p.kt_over_kn), mu, clamp])

    def _max_zeta(self, materials: MaterialTable) -> float:
        m = len(materials)
        return max((-damping_ratio(materials.mixed(a, b, "restitution")) for a in range(m) for b in range(m)),
                   default=0.0)

    def contact_stiffness(self, coef, mi, mj, r_eff, m_eff, overlap):
        """Constant springs, for pdem's live step bound: S_n = k_n, k_t (0 where μ = 0)."""
        c = coef[mi, mj]
        return c[:, 0], np.where(c[:, 4] > 0.0, c[:, 1], 0.0)

    def contact_damping(self, coef, mi, mj, r_eff, m_eff, overlap):
        """The dashpots, for pdem's velocity servos: c_n = −2 β sqrt(k_n m*), c_t = c_n sqrt(k_t/k_n)
        (0 where μ = 0)."""
        c = coef[mi, mj]
        c_n = -2.0 * c[:, 2] * np.sqrt(c[:, 0] * m_eff)
        return c_n, np.where(c[:, 4] > 0.0, c_n * c[:, 3], 0.0)

    def critical_dt(self, materials, radii, mat_index, masses) -> float:
        """Stability limit of an FCC crystal of the lightest spheres (module docstring)."""
        if len(masses) == 0:
            return math.inf
        m_eff = 0.5 * float(np.min(masses))
        return stable_dt(self.params.kn, self.params.kt_over_kn, m_eff, self._max_zeta(materials))

    def suggested_dt(self, materials, radii, mat_index, masses) -> float:
        """min(0.5 critical_dt, t_c/50), t_c = π sqrt(m*/k_n) of the two lightest spheres."""
        if len(masses) == 0:
            return math.inf
        m_eff = 0.5 * float(np.min(masses))
        t_c = math.pi * math.sqrt(m_eff / self.params.kn)
        return min(0.5 * self.critical_dt(materials, radii, mat_index, masses), t_c / 50.0)
