"""Hertz–Mindlin viscoelastic contact with tangential history and a Coulomb cap (DEM-P).

Physics reference §2 (the form of Chrono's SMC Hertz model, LIGGGHTS ``hertz`` and LAMMPS
``hertz/material`` + ``mindlin``). With a = sqrt(R* δ):

* from materials (``parameterisation = "material"``, default)::

      k_n = 4/3 E* a     S_n = 2 E* a     k_t = 8 G* a
      β = ln e / sqrt(ln² e + π²)
      c_n = −2 sqrt(5/6) β sqrt(S_n m*)    c_t = −2 sqrt(5/6) β sqrt(k_t m*)
      F_n = k_n δ − c_n v_n

* from user coefficients (``parameterisation = "coefficients"``, the study's equation 1)::

      F_n = a (K_n δ − C_n m* v_n)         k_t = a K_t,  c_t = a C_t m*

Tangential spring ξ (per contact, global frame, zero when the contact starts): rotated onto the
current tangent plane keeping its length, then ξ += v_t dt, F_t = −k_t ξ − c_t v_t on j; if
|F_t| > μ max(F_n, 0) it is scaled to the cap and the spring follows the slider, ξ = −F_t/k_t
(the spring alone carries the Coulomb force, as in LIGGGHTS).

This departs on purpose from ξ = −(F_t + c_t v_t)/k_t (physics reference §2, LAMMPS ``mindlin``):
early in a damped sliding contact c_t|v_t| > μF_n, so that rule stores a spring pointing against
the slip; since k_t ∝ δ^½ grows faster than c_t ∝ δ^¼, the next trial force reverses and friction
then *drives* the slip (measured: spin after an oblique impact 14 % low at e = 0.5, 32 % low at
e = 0.3). With ξ = −F_t/k_t the gross-sliding closed forms hold (``tests/test_physics_impacts.py``).

**Tangential options** (``tangential``; names and rules of LAMMPS ``pair_style granular``'s
tangential models, LAMMPS documentation "Models for tangential friction in granular
interactions"; k_t = 8 G* a, the Mindlin (1949) no-slip stiffness, in every option):

* ``"linear_history"`` (default): the total spring above, F_t = −k_t ξ − c_t v_t. Since k_t ∝ a,
  the force changes with the overlap even at a fixed ξ (LAMMPS ``mindlin`` behaves alike).
* ``"mindlin_rescale"``: the same, but while the contact radius shrinks (a < a_old, the previous
  step's radius, kept as a fourth history float) ξ is first scaled by a/a_old, so that the elastic
  force unloads with the contact (LAMMPS ``mindlin_rescale``; its force then falls as a²).
* ``"mindlin_force"``: the history is the elastic tangential force F_e, incremental:
  rotated onto the tangent plane like ξ, F_e += −k_t v_t dt, F_t = F_e − c_t v_t, Coulomb cap as
  above with F_e = F_t at the cap (LAMMPS ``mindlin/force``; the incremental form of Di Renzo &
  Di Maio 2005 and Thornton et al. 2011, 2013 (eq. 18) for the Mindlin & Deresiewicz 1953 load
  paths: a stiffness change acts on increments only, so unloading the normal force does not
  release stored tangential force).
* ``"mindlin_rescale_force"``: ``mindlin_force`` whose F_e is scaled by a/a_old = k_t,new/k_t,old
  while the contact radius shrinks (LAMMPS ``mindlin_rescale/force``; Thornton et al. 2013
  eq. 18b).

The slider rule is pdem's (the elastic part carries the Coulomb force alone), not LAMMPS's, for the
reason above. ``mindlin_force`` reproduces an independent incremental Mindlin law (YADE's) in
Chung & Ooi's (2011) oblique-impact test within 0.21° and 2.1 % at every angle, where
``linear_history`` is 1.3° and 66 % (spin) off at 5° (``tests/test_chung_ooi.py``).

**Normal force sign.** By default the damped normal force is *not* clamped: it may become briefly
attractive at the end of a contact (as in LAMMPS ``pair_style granular`` without
``limit_damping``). ``clamp_normal = true`` clamps F_n ≥ 0, which raises the realised restitution
above the input e (tested in ``tests/test_physics_impacts.py``). ``limit_damping = true`` is the
same switch under LAMMPS's name: LAMMPS's ``limit_damping`` zeroes the normal force where it would
be attractive, and its Coulomb cap then vanishes with it. pdem's cap is μ max(F_n, 0) whether or not
F_n is clamped (LAMMPS uses μ |F_n| without ``limit_damping``), so in an attractive tail F_t = 0 and
the history follows the slider to zero (ξ = 0, F_e = 0) in both cases; clamping changes only the
normal force, and with it the Coulomb relation of a sliding impact: the friction impulse is μ times
the whole normal impulse only when F_n is clamped (``tests/test_chung_ooi.py``, test 6).

**Rolling resistance** (off unless a material has ``rolling_friction`` > 0): a torque on j of
−μ_r R* max(F_n, 0) ω_roll/|ω_roll|, with ω_roll the tangential part of ω_j − ω_i, limited in
magnitude to I* |ω_roll| / dt so that it cannot reverse the relative rolling within a step.

**Spinning resistance** (off unless a material has ``spinning_friction`` > 0): likewise a torque on
j of −μ_s R* max(F_n, 0) sign(ω_n) n about the normal, ω_n = n·(ω_j − ω_i), limited to
I* |ω_n| / dt.

Coefficient row layout: ``[form, E*|K_n, G*|K_t, β|C_n, sqrt(4G*/E*)|C_t, μ, μ_r, clamp, μ_s,
force, rescale]`` (the last two: 1.0 for the ``mindlin_*force`` / ``mindlin_rescale*`` options).
History per contact: ξ (or F_e) in the global frame, and with the rescale options the previous a.

References: R. D. Mindlin & H. Deresiewicz (1953), Elastic spheres in contact under varying oblique
forces, J. Appl. Mech. 20:327–344; A. Di Renzo & F. P. Di Maio (2005), An improved integral
non-linear model for the contact of particles in distinct element simulations, Chem. Eng. Sci.
60:1303–1312; C. Thornton, S. J. Cummins & P. W. Cleary (2011), An investigation of the comparative
behaviour of alternative contact force models during elastic collisions, Powder Technol. 210:189–197,
and (2013) … during inelastic collisions, Powder Technol. 233:30–46; C.-Y. Chung & J. Y. Ooi (2011),
Benchmark tests for verifying discrete element modelling codes at particle impact level, Granular
Matter 13:643–656.
"""

from __future__ import annotations

import math
import threading
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from .. import api as pk
from ..api import (
    ContactLaw,
    LawParams,
    njit,
    pair_forces,
    tangential_mindlin_values,
    tangential_spring_values,
    wall_forces,
)
from ..materials import MaterialTable, damping_ratio, effective_moduli, rayleigh_time

__all__ = ["HertzMindlin", "hertz_mindlin_force", "force_numpy", "damping_ratio"]

SQRT56 = math.sqrt(5.0 / 6.0)
#: tangential options whose history is the elastic force, and those that rescale it on unloading
FORCE = ("mindlin_force", "mindlin_rescale_force")
RESCALE = ("mindlin_rescale", "mindlin_rescale_force")
Tangential = Literal["linear_history", "mindlin_rescale", "mindlin_force", "mindlin_rescale_force"]


@njit(inline="always")
def hertz_mindlin_normal(delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7):
    """The normal part of a contact on scalars: (a, F_n, k_t, c_t, the Coulomb cap μ max(F_n, 0), v_t).
    ``c0``–``c7``: the pair's coefficient row (form, E*|K_n, G*|K_t, β|C_n, sqrt(4G*/E*)|C_t, μ, –,
    clamp). Both parameterisations are computed and one selected, without branches, so that a loop
    over contacts in columns vectorizes; the values are those of branching code, bit for bit."""
    a = math.sqrt(r_eff * delta)
    vn = vx * nx + vy * ny + vz * nz
    vtx = vx - vn * nx
    vty = vy - vn * ny
    vtz = vz - vn * nz
    # from materials: c_n = −2 sqrt(5/6) β sqrt(S_n m*), S_n = 2 E* a;
    # c_t = c_n sqrt(k_t/S_n) = c_n sqrt(4 G*/E*)
    k_t_m = 8.0 * c2 * a
    c_n = -2.0 * SQRT56 * c3 * math.sqrt(2.0 * c1 * a * m_eff)
    fn_m = (4.0 / 3.0) * c1 * a * delta - c_n * vn
    c_t_m = c_n * c4
    # from coefficients (the study's equation 1)
    fn_c = a * (c1 * delta - c3 * m_eff * vn)
    k_t_c = a * c2
    c_t_c = a * c4 * m_eff
    material = c0 == 0.0
    fn = fn_m if material else fn_c
    k_t = k_t_m if material else k_t_c
    c_t = c_t_m if material else c_t_c
    # clamp_normal / limit_damping: no attractive normal force (the cap is then zero too)
    fn = 0.0 if ((c7 != 0.0) & (fn < 0.0)) else fn
    fcap = c5 * fn if fn > 0.0 else 0.0
    return a, fn, k_t, c_t, fcap, vtx, vty, vtz


@njit(inline="always")
def hertz_mindlin_values(
    delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7, sx, sy, sz, dt
):
    """The normal and tangential force of a contact on scalars, tangential ``linear_history``: (F on
    j, F_n, the new tangential spring). ``c0``–``c7`` as in :func:`hertz_mindlin_normal`. Branch-free
    (a loop over contacts in columns vectorizes)."""
    a, fn, k_t, c_t, fcap, vtx, vty, vtz = hertz_mindlin_normal(
        delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7
    )
    ftx, fty, ftz, sx, sy, sz = tangential_spring_values(
        sx, sy, sz, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt
    )
    return fn * nx + ftx, fn * ny + fty, fn * nz + ftz, fn, sx, sy, sz


@njit(inline="always")
def hertz_mindlin_values_mindlin(
    delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7, sx, sy, sz, a_old, dt, force,
    rescale,
):  # fmt: skip
    """:func:`hertz_mindlin_values` with the tangential options ``mindlin_force`` (``force``: the
    history is the elastic tangential force, updated incrementally) and ``mindlin_rescale`` /
    ``mindlin_rescale_force`` (``rescale``: the history scaled by a/a_old while the contact radius
    shrinks; ``a_old`` the previous step's a, 0 for a new contact): see
    :func:`pdem.contact._tangential.tangential_mindlin_values`. Returns (F on j, F_n, the new
    history, a). Branch-free."""
    a, fn, k_t, c_t, fcap, vtx, vty, vtz = hertz_mindlin_normal(
        delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7
    )
    ftx, fty, ftz, sx, sy, sz, a = tangential_mindlin_values(
        sx, sy, sz, a_old, a, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt, force, rescale
    )
    return fn * nx + ftx, fn * ny + fty, fn * nz + ftz, fn, sx, sy, sz, a


@njit(inline="always")
def hertz_mindlin_moments(mu_r, mu_s, fn, nx, ny, nz, wx, wy, wz, r_eff, i_eff, dt):
    """Rolling and spinning resistance: the pure torque on j (zero unless μ_r or μ_s > 0 and
    F_n > 0)."""
    mx = 0.0
    my = 0.0
    mz = 0.0
    if mu_r > 0.0 and fn > 0.0:
        wn = wx * nx + wy * ny + wz * nz
        rx = wx - wn * nx
        ry = wy - wn * ny
        rz = wz - wn * nz
        wr = math.sqrt(rx * rx + ry * ry + rz * rz)
        if wr > 0.0:
            mag = min(mu_r * r_eff * fn, i_eff * wr / dt)
            mx = -mag * rx / wr
            my = -mag * ry / wr
            mz = -mag * rz / wr
    if mu_s > 0.0 and fn > 0.0:
        wn = wx * nx + wy * ny + wz * nz
        if wn != 0.0:
            mag = min(mu_s * r_eff * fn, i_eff * abs(wn) / dt)
            if wn > 0.0:
                mag = -mag
            mx += mag * nx
            my += mag * ny
            mz += mag * nz
    return mx, my, mz


@njit(inline="always")
def hertz_mindlin_force(
    delta, nx, ny, nz, vx, vy, vz, wx, wy, wz, r_eff, m_eff, i_eff, coef, mi, mj, hist, k, dt
):
    c0 = coef[mi, mj, 0]
    c1 = coef[mi, mj, 1]
    c2 = coef[mi, mj, 2]
    c3 = coef[mi, mj, 3]
    c4 = coef[mi, mj, 4]
    c5 = coef[mi, mj, 5]
    c6 = coef[mi, mj, 6]
    c7 = coef[mi, mj, 7]
    c8 = coef[mi, mj, 8]
    c9 = coef[mi, mj, 9]
    c10 = coef[mi, mj, 10]
    if c9 == 0.0 and c10 == 0.0:  # tangential = "linear_history" (the default)
        fx, fy, fz, fn, sx, sy, sz = hertz_mindlin_values(
            delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7, hist[k, 0], hist[k, 1],
            hist[k, 2], dt,
        )  # fmt: skip
    else:
        wide = hist.shape[1] > 3  # the previous contact radius is kept (the rescale options)
        a_old = hist[k, 3] if wide else 0.0
        fx, fy, fz, fn, sx, sy, sz, a = hertz_mindlin_values_mindlin(
            delta, nx, ny, nz, vx, vy, vz, r_eff, m_eff, c0, c1, c2, c3, c4, c5, c7, hist[k, 0], hist[k, 1],
            hist[k, 2], a_old, dt, c9 != 0.0, (c10 != 0.0) & wide,
        )  # fmt: skip
        if wide:
            hist[k, 3] = a
    hist[k, 0] = sx
    hist[k, 1] = sy
    hist[k, 2] = sz
    mx, my, mz = hertz_mindlin_moments(c6, c8, fn, nx, ny, nz, wx, wy, wz, r_eff, i_eff, dt)
    return (fx, fy, fz, mx, my, mz)


@njit
def hertz_mindlin_coefficient_columns(tk, m, pi, pj, mat, coef, K):
    """The coefficients the column passes need (form, E*|K_n, G*|K_t, β|C_n, sqrt(4G*/E*)|C_t, μ,
    clamp, μ_r, μ_s), one column per touching pair."""
    for q in range(m):
        k = tk[q]
        mi = mat[pi[k]]
        mj = mat[pj[k]]
        K[0, q] = coef[mi, mj, 0]
        K[1, q] = coef[mi, mj, 1]
        K[2, q] = coef[mi, mj, 2]
        K[3, q] = coef[mi, mj, 3]
        K[4, q] = coef[mi, mj, 4]
        K[5, q] = coef[mi, mj, 5]
        K[6, q] = coef[mi, mj, 7]
        K[7, q] = coef[mi, mj, 6]
        K[8, q] = coef[mi, mj, 8]


@njit
def hertz_mindlin_columns(C, K, m, dt, O, FN):
    """The normal and tangential forces of the touching pairs held in columns (vectorized)."""
    d_, nx_, ny_, nz_ = C[pk.COL_DELTA], C[pk.COL_NX], C[pk.COL_NY], C[pk.COL_NZ]
    vx_, vy_, vz_, re_, me_ = C[pk.COL_VX], C[pk.COL_VY], C[pk.COL_VZ], C[pk.COL_REFF], C[pk.COL_MEFF]
    s0_, s1_, s2_ = C[pk.COL_HIST], C[pk.COL_HIST + 1], C[pk.COL_HIST + 2]
    c0_, c1_, c2_, c3_, c4_, c5_, c7_ = K[0], K[1], K[2], K[3], K[4], K[5], K[6]
    fx_, fy_, fz_ = O[pk.OUT_FX], O[pk.OUT_FY], O[pk.OUT_FZ]
    h0_, h1_, h2_ = O[pk.OUT_HIST], O[pk.OUT_HIST + 1], O[pk.OUT_HIST + 2]
    for q in range(m):
        fx_[q], fy_[q], fz_[q], FN[q], h0_[q], h1_[q], h2_[q] = hertz_mindlin_values(
            d_[q], nx_[q], ny_[q], nz_[q], vx_[q], vy_[q], vz_[q], re_[q], me_[q], c0_[q], c1_[q], c2_[q],
            c3_[q], c4_[q], c5_[q], c7_[q], s0_[q], s1_[q], s2_[q], dt,
        )  # fmt: skip


@njit
def hertz_mindlin_columns_uniform(C, c, m, dt, O, FN):
    """:func:`hertz_mindlin_columns` when every pair has the coefficients ``c`` (one material)."""
    d_, nx_, ny_, nz_ = C[pk.COL_DELTA], C[pk.COL_NX], C[pk.COL_NY], C[pk.COL_NZ]
    vx_, vy_, vz_, re_, me_ = C[pk.COL_VX], C[pk.COL_VY], C[pk.COL_VZ], C[pk.COL_REFF], C[pk.COL_MEFF]
    s0_, s1_, s2_ = C[pk.COL_HIST], C[pk.COL_HIST + 1], C[pk.COL_HIST + 2]
    c0, c1, c2, c3, c4, c5, c7 = c[0], c[1], c[2], c[3], c[4], c[5], c[7]
    fx_, fy_, fz_ = O[pk.OUT_FX], O[pk.OUT_FY], O[pk.OUT_FZ]
    h0_, h1_, h2_ = O[pk.OUT_HIST], O[pk.OUT_HIST + 1], O[pk.OUT_HIST + 2]
    for q in range(m):
        fx_[q], fy_[q], fz_[q], FN[q], h0_[q], h1_[q], h2_[q] = hertz_mindlin_values(
            d_[q], nx_[q], ny_[q], nz_[q], vx_[q], vy_[q], vz_[q], re_[q], me_[q], c0, c1, c2, c3, c4, c5, c7,
            s0_[q], s1_[q], s2_[q], dt,
        )  # fmt: skip


@njit
def hertz_mindlin_columns_mindlin(C, K, m, dt, O, FN, force, rescale):
    """:func:`hertz_mindlin_columns` with a ``mindlin_*`` tangential option (the previous contact
    radius in the history's fourth row when ``rescale``)."""
    d_, nx_, ny_, nz_ = C[pk.COL_DELTA], C[pk.COL_NX], C[pk.COL_NY], C[pk.COL_NZ]
    vx_, vy_, vz_, re_, me_ = C[pk.COL_VX], C[pk.COL_VY], C[pk.COL_VZ], C[pk.COL_REFF], C[pk.COL_MEFF]
    s0_, s1_, s2_, s3_ = C[pk.COL_HIST], C[pk.COL_HIST + 1], C[pk.COL_HIST + 2], C[pk.COL_HIST + 3]
    c0_, c1_, c2_, c3_, c4_, c5_, c7_ = K[0], K[1], K[2], K[3], K[4], K[5], K[6]
    fx_, fy_, fz_ = O[pk.OUT_FX], O[pk.OUT_FY], O[pk.OUT_FZ]
    h0_, h1_, h2_, h3_ = O[pk.OUT_HIST], O[pk.OUT_HIST + 1], O[pk.OUT_HIST + 2], O[pk.OUT_HIST + 3]
    for q in range(m):
        fx_[q], fy_[q], fz_[q], FN[q], h0_[q], h1_[q], h2_[q], h3_[q] = hertz_mindlin_values_mindlin(
            d_[q], nx_[q], ny_[q], nz_[q], vx_[q], vy_[q], vz_[q], re_[q], me_[q], c0_[q], c1_[q], c2_[q],
            c3_[q], c4_[q], c5_[q], c7_[q], s0_[q], s1_[q], s2_[q], s3_[q], dt, force, rescale,
        )  # fmt: skip


@njit
def hertz_mindlin_columns_uniform_mindlin(C, c, m, dt, O, FN, force, rescale):
    """:func:`hertz_mindlin_columns_mindlin` when every pair has the coefficients ``c``."""
    d_, nx_, ny_, nz_ = C[pk.COL_DELTA], C[pk.COL_NX], C[pk.COL_NY], C[pk.COL_NZ]
    vx_, vy_, vz_, re_, me_ = C[pk.COL_VX], C[pk.COL_VY], C[pk.COL_VZ], C[pk.COL_REFF], C[pk.COL_MEFF]
    s0_, s1_, s2_, s3_ = C[pk.COL_HIST], C[pk.COL_HIST + 1], C[pk.COL_HIST + 2], C[pk.COL_HIST + 3]
    c0, c1, c2, c3, c4, c5, c7 = c[0], c[1], c[2], c[3], c[4], c[5], c[7]
    fx_, fy_, fz_ = O[pk.OUT_FX], O[pk.OUT_FY], O[pk.OUT_FZ]
    h0_, h1_, h2_, h3_ = O[pk.OUT_HIST], O[pk.OUT_HIST + 1], O[pk.OUT_HIST + 2], O[pk.OUT_HIST + 3]
    for q in range(m):
        fx_[q], fy_[q], fz_[q], FN[q], h0_[q], h1_[q], h2_[q], h3_[q] = hertz_mindlin_values_mindlin(
            d_[q], nx_[q], ny_[q], nz_[q], vx_[q], vy_[q], vz_[q], re_[q], me_[q], c0, c1, c2, c3, c4, c5, c7,
            s0_[q], s1_[q], s2_[q], s3_[q], dt, force, rescale,
        )  # fmt: skip


@njit
def hertz_mindlin_column_moments(K, m, C, FN, dt, O):
    """Rolling and spinning torques of the touching pairs (scalar: taken by few scenes)."""
    for q in range(m):
        O[pk.OUT_MX, q], O[pk.OUT_MY, q], O[pk.OUT_MZ, q] = hertz_mindlin_moments(
            K[7, q], K[8, q], FN[q], C[pk.COL_NX, q], C[pk.COL_NY, q], C[pk.COL_NZ, q],
            C[pk.COL_WX, q], C[pk.COL_WY, q], C[pk.COL_WZ, q], C[pk.COL_REFF, q], C[pk.COL_IEFF, q], dt,
        )  # fmt: skip


#: touching pairs per block of columns: the block's columns (~37 rows of 8 bytes) stay in the
#: core's cache from the pass that writes them to the pass that reads them. Not a power of two:
#: rows 4 KiB apart share cache sets and alias in the store buffer (512 or 1024 columns made the
#: kernel 1.8x slower on the 18k column; 248 1.4x; 504, 520, 760 and 1000 alike).
BLOCK = 520


@njit
def _pair_kernel_columns(pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap,
                         C, K, O, FN, tk):  # fmt: skip
    # the rolling and spinning torques need the relative spin and I*: written only if some
    # material pair has them
    angular = False
    for a in range(coef.shape[0]):
        for b in range(coef.shape[1]):
            if coef[a, b, 6] > 0.0 or coef[a, b, 8] > 0.0:
                angular = True
    # one material (the common case): the coefficients are scalars, not columns
    m0 = mat[0] if mat.shape[0] else 0
    uniform = True
    for a in range(mat.shape[0]):
        uniform &= mat[a] == m0
    # the tangential option (a law parameter: the same for every material pair), decided once per call
    force = False
    rescale = False
    if coef.shape[0]:
        force = coef[0, 0, 9] != 0.0
        rescale = (coef[0, 0, 10] != 0.0) & (hist.shape[1] > 3)
    mindlin = force or rescale
    m, flags = pk.touching_pairs(pi, pj, hist, x, r, inv_m, fpair, tk)  # len(tk) ≥ len(pi) ≥ m
    block = C.shape[1]
    for q0 in range(0, m, block):
        n = min(block, m - q0)
        tkb = tk[q0 : q0 + n]
        flags |= pk.fill_pair_columns(tkb, n, pi, pj, hist, x, v, w, r, inv_m, inv_i, max_overlap, C, angular)
        if uniform and not mindlin:
            hertz_mindlin_columns_uniform(C, coef[m0, m0], n, dt, O, FN)
        if uniform and mindlin:
            hertz_mindlin_columns_uniform_mindlin(C, coef[m0, m0], n, dt, O, FN, force, rescale)
        if angular or not uniform:
            hertz_mindlin_coefficient_columns(tkb, n, pi, pj, mat, coef, K)
        if not uniform and not mindlin:
            hertz_mindlin_columns(C, K, n, dt, O, FN)
        if not uniform and mindlin:
            hertz_mindlin_columns_mindlin(C, K, n, dt, O, FN, force, rescale)
        if angular:  # pairs without rolling or spinning friction get zero torques, as without the pass
            hertz_mindlin_column_moments(K, n, C, FN, dt, O)
        pk.scatter_pair_columns(tkb, n, pi, pj, C, O, angular, f, t, fpair, hist)
    return flags


class _Columns(threading.local):
    """Work space of the pair kernel, kept between steps (per thread; allocating it at every step
    would cost page faults): one block of columns, and the list indices of the touching pairs
    (grown with the pair list)."""

    def __init__(self) -> None:
        # history rows: the tangential spring or force, and the previous contact radius (rescale options)
        self.C = np.zeros((pk.COL_HIST + 4, BLOCK))
        self.K = np.empty((9, BLOCK))
        self.O = np.empty((pk.OUT_HIST + 4, BLOCK))
        self.FN = np.empty(BLOCK)
        self.grow(0)

    def grow(self, n: int) -> None:
        self.tk = np.empty(int(n * 1.25) + 256, dtype=np.int64)


_columns = _Columns()


def hertz_mindlin_pair_kernel(
    pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap
):
    """The pair loop of :func:`pdem.api.pair_forces` with this law, in passes over columns (see
    :mod:`pdem.contact._kernels`): the touching pairs' forces are computed four at a time, a block
    of pairs at a time. The same bits as the generic loop (``hertz_mindlin_pair_kernel_generic``;
    tests/test_pair_columns.py)."""
    if not (hist.flags.c_contiguous and fpair.flags.c_contiguous):  # the passes test rows as bits
        return hertz_mindlin_pair_kernel_generic(
            pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap
        )
    cols = _columns
    if cols.tk.shape[0] < pi.shape[0]:  # room for every listed pair: no second call
        cols.grow(pi.shape[0])
    return _pair_kernel_columns(
        pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap, cols.C, cols.K,
        cols.O, cols.FN, cols.tk,
    )  # fmt: skip


# fmt: off
@njit
def hertz_mindlin_pair_kernel_generic(pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt,
                                      max_overlap):
    """The generic pair loop with this law, one contact at a time (the reference of the column
    kernel)."""
    return pair_forces(hertz_mindlin_force, pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair,
                       dt, max_overlap)


@njit
def hertz_mindlin_wall_kernel(kinds, params, vel, omega, centre, wmat, cstart, cand, hist, x, v, w, r, inv_m,
                              inv_i, mat, coef, f, t, dt, max_overlap, out_idx, out_val, counts):
    return wall_forces(hertz_mindlin_force, kinds, params, vel, omega, centre, wmat, cstart, cand, hist, x, v,
                       w, r, inv_m, inv_i, mat, coef, f, t, dt, max_overlap, out_idx, out_val, counts)
# fmt: on


def force_numpy(delta, n, vrel, wrel, r_eff, m_eff, i_eff, c, hist, dt):
    """Plain-Python twin of :func:`hertz_mindlin_force` (vectors as arrays), for contract tests."""
    n = np.asarray(n, float)
    vrel = np.asarray(vrel, float)
    wrel = np.asarray(wrel, float)
    a = math.sqrt(r_eff * delta)
    vn = float(vrel @ n)
    vt = vrel - vn * n
    if c[0] == 0.0:
        s_n = 2 * c[1] * a
        k_t = 8 * c[2] * a
        fn = 4 / 3 * c[1] * a * delta + 2 * SQRT56 * c[3] * math.sqrt(s_n * m_eff) * vn
        c_t = -2 * SQRT56 * c[3] * math.sqrt(k_t * m_eff)
    else:
        fn = a * (c[1] * delta - c[3] * m_eff * vn)
        k_t = a * c[2]
        c_t = a * c[4] * m_eff
    if c[7] != 0.0:
        fn = max(fn, 0.0)
    force = len(c) > 9 and c[9] != 0.0  # the history is the elastic tangential force
    rescale = len(c) > 10 and c[10] != 0.0 and len(hist) > 3
    s = np.array(hist[:3], float)
    if rescale and a < hist[3]:  # unloading: the history shrinks with the contact radius
        s = s * (a / hist[3])
    old = np.linalg.norm(s)
    if old > 0:
        s = s - (s @ n) * n
        new = np.linalg.norm(s)
        if new > 0:
            s *= old / new
    if force:
        s = s + vt * (-k_t * dt)
        ft = s - c_t * vt
    else:
        s = s + vt * dt
        ft = -k_t * s - c_t * vt
    cap = c[5] * max(fn, 0.0)
    if np.linalg.norm(ft) > cap:
        ft = ft * (cap / np.linalg.norm(ft))
        s = ft.copy() if force else -ft / k_t
    hist[:3] = s
    if len(hist) > 3:
        hist[3] = a
    m = np.zeros(3)
    if c[6] > 0 and fn > 0:
        wr = wrel - (wrel @ n) * n
        if np.linalg.norm(wr) > 0:
            mag = min(c[6] * r_eff * fn, i_eff * np.linalg.norm(wr) / dt)
            m = -mag * wr / np.linalg.norm(wr)
    if len(c) > 8 and c[8] > 0 and fn > 0:
        wn = float(wrel @ n)
        if wn != 0.0:
            m = m - min(c[8] * r_eff * fn, i_eff * abs(wn) / dt) * np.sign(wn) * n
    return fn * n + ft, m


class HertzMindlinParams(LawParams):
    """Parameters of :class:`HertzMindlin`.

    ``parameterisation``: ``"material"`` (E, ν, e, μ from the materials) or ``"coefficients"``
    (the study's equation 1 with ``kn`` [Pa], ``kt`` [Pa], ``cn`` [1/(m s)], ``ct`` [1/(m s)]).
    ``clamp_normal``: forbid an attractive damped normal force; ``limit_damping``: the same (LAMMPS's
    name). ``tangential``: the tangential history (module docstring).
    """

    parameterisation: Literal["material", "coefficients"] = Field(
        "material", description="'material': E, ν, e, μ from the materials; 'coefficients': kn, kt, cn, ct"
    )
    kn: float | None = Field(default=None, gt=0, description="normal coefficient K_n [Pa] (coefficient form)")
    kt: float | None = Field(
        default=None, gt=0, description="tangential coefficient K_t [Pa] (coefficient form)"
    )
    cn: float | None = Field(
        default=None, ge=0, description="normal damping C_n [1/(m s)] (coefficient form)"
    )
    ct: float | None = Field(
        default=None, ge=0, description="tangential damping C_t [1/(m s)] (coefficient form)"
    )
    clamp_normal: bool = Field(False, description="forbid an attractive damped normal force (F_n ≥ 0)")
    limit_damping: bool = Field(
        False,
        description="LAMMPS's name of clamp_normal: F_n = max(F_n, 0), so the Coulomb cap and the tangential "
        "force are zero where the damped normal force would pull",
    )
    tangential: Tangential = Field(
        "linear_history",
        description="tangential history: 'linear_history' (total spring F_t = −k_t ξ − c_t v_t, "
        "k_t = 8 G* a), "
        "'mindlin_rescale' (ξ scaled by a/a_old while the contact radius shrinks), 'mindlin_force' "
        "(incremental elastic force dF_e = −k_t v_t dt), 'mindlin_rescale_force' (both)",
    )

    @model_validator(mode="after")
    def _coefficients_given(self):
        if self.parameterisation == "coefficients":
            missing = [k for k in ("kn", "kt", "cn", "ct") if getattr(self, k) is None]
            if missing:
                raise ValueError(
                    f"parameterisation = 'coefficients' needs {', '.join(missing)}; give kn, kt [Pa] and "
                    "cn, ct [1/(m s)], or use parameterisation = 'material'"
                )
        return self


class HertzMindlin(ContactLaw):
    """Hertz–Mindlin viscoelastic law with tangential history (see module docstring)."""

    name = "hertz_mindlin"
    kind = "penalty"
    history_size = 3  # 4 with the rescale options (the previous contact radius): see __init__
    n_coef = 11
    Params = HertzMindlinParams
    pair_kernel = hertz_mindlin_pair_kernel
    wall_kernel = hertz_mindlin_wall_kernel

    def __init__(self, **params) -> None:
        super().__init__(**params)
        if self.params.tangential in RESCALE:
            self.history_size = 4  # the contact radius of the previous step

    @classmethod
    def hertz_from_materials(cls, params: LawParams) -> bool:
        """Hertz from E and ν unless the coefficient form is chosen."""
        return getattr(params, "parameterisation", "material") == "material"

    def pair_coefficients(self, materials: MaterialTable, a: int, b: int) -> np.ndarray:
        p = self.params
        clamp = 1.0 if (p.clamp_normal or p.limit_damping) else 0.0
        force = 1.0 if p.tangential in FORCE else 0.0
        rescale = 1.0 if p.tangential in RESCALE else 0.0
        mu = materials.mixed(a, b, "friction")
        mu_r = materials.mixed(a, b, "rolling_friction")
        mu_s = materials.mixed(a, b, "spinning_friction")
        if p.parameterisation == "material":
            e_star, g_star = effective_moduli(materials[a], materials[b])
            beta = damping_ratio(materials.mixed(a, b, "restitution"))
            return np.array(
                [0.0, e_star, g_star, beta, math.sqrt(4.0 * g_star / e_star), mu, mu_r, clamp, mu_s, force,
                 rescale]
            )  # fmt: skip
        return np.array([1.0, p.kn, p.kt, p.cn, p.ct, mu, mu_r, clamp, mu_s, force, rescale])

    def contact_stiffness(self, coef, mi, mj, r_eff, m_eff, overlap):
        """S_n = dF_n/dδ and k_t of the kernel's formulas at these overlaps (k_t = 0 where μ = 0:
        the Coulomb cap then holds the tangential force at zero)."""
        c = coef[mi, mj]
        a = np.sqrt(r_eff * overlap)
        material = c[:, 0] == 0.0
        # material form: S_n = 2 E* a, k_t = 8 G* a; coefficient form: F_n = K_n sqrt(R*) δ^1.5 →
        # S_n = 1.5 a K_n, k_t = a K_t
        s_n = np.where(material, 2.0 * c[:, 1] * a, 1.5 * a * c[:, 1])
        k_t = np.where(material, 8.0 * c[:, 2] * a, a * c[:, 2])
        return s_n, np.where(c[:, 5] > 0.0, k_t, 0.0)

    def contact_damping(self, coef, mi, mj, r_eff, m_eff, overlap):
        """c_n and c_t of the kernel's formulas at these overlaps (c_t = 0 where μ = 0)."""
        c = coef[mi, mj]
        a = np.sqrt(r_eff * overlap)
        material = c[:, 0] == 0.0
        # material form: c_n = −2 sqrt(5/6) β sqrt(S_n m*), c_t = c_n sqrt(4 G*/E*); coefficients:
        # c_n = a C_n m*, c_t = a C_t m*
        c_mat = -2.0 * SQRT56 * c[:, 3] * np.sqrt(2.0 * c[:, 1] * a * m_eff)
        c_n = np.where(material, c_mat, a * c[:, 3] * m_eff)
        c_t = np.where(material, c_mat * c[:, 4], a * c[:, 4] * m_eff)
        return c_n, np.where(c[:, 5] > 0.0, c_t, 0.0)

    def slip_slope_ratio(self, coef):
        """μ: the slope of a sliding contact's force is μ S_n."""
        return float(np.max(coef[:, :, 5])) if coef.size else 0.0

    def contact_slip(self, coef, mi, mj, r_eff, m_eff, overlap, vn, hist):
        """Contacts at the Coulomb cap: the kernel stores the slider's spring ξ = −F_t/k_t there (with
        the ``mindlin_*force`` options the elastic force F_e = F_t), so k_t |ξ| = μ F_n, or |F_e| = μ F_n
        (F_n with its dashpot at ``vn``, clamped as the kernel does); within a part in 10⁹ of it counts
        as sliding (rounding; a contact that close to the cap slides at the next
        nudge). Direction ξ/|ξ|, slope μ S_n."""
        c = coef[mi, mj]
        a = np.sqrt(r_eff * overlap)
        material = c[:, 0] == 0.0
        c_mat = -2.0 * SQRT56 * c[:, 3] * np.sqrt(2.0 * c[:, 1] * a * m_eff)
        fn = np.where(material, (4.0 / 3.0) * c[:, 1] * a * overlap - c_mat * vn,
                      a * (c[:, 1] * overlap - c[:, 3] * m_eff * vn))  # fmt: skip
        fn = np.where((c[:, 7] != 0.0) & (fn < 0.0), 0.0, fn)
        fcap = np.where(fn > 0.0, c[:, 5] * fn, 0.0)
        s_n, k_t = self.contact_stiffness(coef, mi, mj, r_eff, m_eff, overlap)
        xi = np.asarray(hist[:, 0:3], dtype=np.float64)
        length = np.sqrt(np.einsum("ij,ij->i", xi, xi))
        # the history is the spring ξ, or with the mindlin_*force options the elastic force itself
        elastic = np.where(c[:, 9] != 0.0, length, k_t * length)
        slide = (fcap > 0.0) & (k_t > 0.0) & (elastic >= fcap * (1.0 - 1e-9))
        dirs = np.zeros_like(xi)
        dirs[slide] = xi[slide] / length[slide, None]
        return dirs, np.where(slide, c[:, 5] * s_n, 0.0)

    def critical_dt(self, materials, radii, mat_index, masses) -> float:
        """Material form: the Rayleigh time min T_R. Coefficient form: 2 sqrt(m*/S_n) with the
        contact stiffness S_n = 1.5 K_n sqrt(R* δ) at δ = 0.1 r for two equal spheres (for the material
        form this estimate and T_R agree within ~10 %)."""
        if len(radii) == 0:
            return math.inf
        best = math.inf
        if self.params.parameterisation == "material":
            for k in np.unique(mat_index):
                sel = mat_index == k
                best = min(best, rayleigh_time(float(radii[sel].min()), materials[int(k)]))
            return best
        kn = self.params.kn
        r = radii
        s_n = 1.5 * kn * np.sqrt(0.5 * r * 0.1 * r)
        return float(np.min(2.0 * np.sqrt(0.5 * masses / s_n)))
