"""The generic contact loops: the pair and wall force loops every penalty law runs.

They are written once and specialised for each contact law by the law's own cached wrappers
(see :mod:`pdem.contact.law`). A law is a small ``@njit`` function

    law(delta, nx, ny, nz, vx, vy, vz, wx, wy, wz, r_eff, m_eff, i_eff, coef, mi, mj, hist, k, dt)
        -> (Fx, Fy, Fz, Mx, My, Mz)

of the contact geometry: overlap ``delta`` [m] > 0, unit normal n from i to j, relative velocity
v = v_j − v_i at the contact point [m/s], relative angular velocity w = ω_j − ω_i [rad/s], effective
radius, mass and moment of inertia, its pre-mixed coefficients ``coef[mi, mj, :]`` and its history
slot ``hist[k, :]`` (updated in place; arrays and indices, so no per-pair view objects). It returns
the force F on j [N] (−F acts on i) and a pure torque M on j [N m] (−M on i), e.g. rolling
resistance. The loops add the lever-arm torques: with
a_i = (r_i − δ/2) n and a_j = −(r_j − δ/2) n, τ_i += a_i × (−F) − M and τ_j += a_j × F + M.

Determinism: pairs are visited in the order of the pair list: sorted by (lower id, higher id), or
(DEM-P) a reordering of it that keeps every particle's pairs in that order
(:func:`pdem.neighbor._kernels.schedule_pairs`). Each particle therefore receives its pair
contributions in partner-id order; wall contributions are added afterwards, wall by wall in deck
order.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit, njit_nocache
from ..geometry._kernels import surface_velocity, wall_contact

FLAG_OVERLAP = 1
FLAG_NONFINITE = 2
FLAG_COINCIDENT = 4


@njit_nocache(inline="always")
def _contact_kinematics(i, j, dx, dy, dz, dist, rsum, v, w, r):
    """Unit normal (i to j), overlap, lever lengths and the relative velocity v_j − v_i at the
    contact point (v + ω × a, with a_i = ai n and a_j = −aj n) of a touching pair at centre distance
    ``dist`` > 0: the geometry :func:`pair_forces` and :func:`pair_columns` share. Array elements
    are read without branches (no reference counting in the callers' loops)."""
    inv_dist = 1.0 / dist
    nx = dx * inv_dist
    ny = dy * inv_dist
    nz = dz * inv_dist
    delta = rsum - dist
    ai = r[i] - 0.5 * delta
    aj = r[j] - 0.5 * delta
    vix = v[i, 0] + ai * (w[i, 1] * nz - w[i, 2] * ny)
    viy = v[i, 1] + ai * (w[i, 2] * nx - w[i, 0] * nz)
    viz = v[i, 2] + ai * (w[i, 0] * ny - w[i, 1] * nx)
    vjx = v[j, 0] - aj * (w[j, 1] * nz - w[j, 2] * ny)
    vjy = v[j, 1] - aj * (w[j, 2] * nx - w[j, 0] * nz)
    vjz = v[j, 2] - aj * (w[j, 0] * ny - w[j, 1] * nx)
    return nx, ny, nz, delta, ai, aj, vjx - vix, vjy - viy, vjz - viz


@njit_nocache(inline="always")
def pair_forces(law, pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap):
    """Accumulate pair forces and torques into ``f`` and ``t``; return a flag word.

    ``fpair[k]`` receives the force on the higher-id particle of pair k (zero when not touching).
    ``max_overlap`` is the largest allowed δ / min(r_i, r_j) before the step is flagged.
    """
    flags = 0
    hsize = hist.shape[1]
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        rsum = r[i] + r[j]
        if d2 >= rsum * rsum or (inv_m[i] == 0.0 and inv_m[j] == 0.0):
            for h in range(hsize):
                hist[k, h] = 0.0
            fpair[k, 0] = 0.0
            fpair[k, 1] = 0.0
            fpair[k, 2] = 0.0
            continue
        dist = math.sqrt(d2)
        if dist == 0.0:
            flags |= FLAG_COINCIDENT
            continue
        nx, ny, nz, delta, ai, aj, vx, vy, vz = _contact_kinematics(i, j, dx, dy, dz, dist, rsum, v, w, r)
        if delta > max_overlap * min(r[i], r[j]):
            flags |= FLAG_OVERLAP
        r_eff = r[i] * r[j] / rsum
        m_eff = 1.0 / (inv_m[i] + inv_m[j])
        i_eff = 1.0 / (inv_i[i] + inv_i[j])
        fx, fy, fz, mx, my, mz = law(
            delta,
            nx,
            ny,
            nz,
            vx,
            vy,
            vz,
            w[j, 0] - w[i, 0],
            w[j, 1] - w[i, 1],
            w[j, 2] - w[i, 2],
            r_eff,
            m_eff,
            i_eff,
            coef,
            mat[i],
            mat[j],
            hist,
            k,
            dt,
        )
        f[i, 0] -= fx
        f[i, 1] -= fy
        f[i, 2] -= fz
        f[j, 0] += fx
        f[j, 1] += fy
        f[j, 2] += fz
        # n × F
        cx = ny * fz - nz * fy
        cy = nz * fx - nx * fz
        cz = nx * fy - ny * fx
        t[i, 0] += -ai * cx - mx
        t[i, 1] += -ai * cy - my
        t[i, 2] += -ai * cz - mz
        t[j, 0] += -aj * cx + mx
        t[j, 1] += -aj * cy + my
        t[j, 2] += -aj * cz + mz
        fpair[k, 0] = fx
        fpair[k, 1] = fy
        fpair[k, 2] = fz
    return flags


# ---------------------------------------------------------------------------------------------
# The pair loop in passes, for laws whose force can be computed on columns (DEM-P's Hertz–Mindlin):
# 1. touching_pairs: the touching test of every listed pair, without branching on the outcome (the
#    touching pairs' list indices compacted in list order; non-touching ones get zero history and
#    force, as in pair_forces, rewritten only if not already +0.0);
# then, a block of touching pairs at a time (the block's columns stay in cache):
# 2. fill_pair_columns: their geometry into columns (one array row per quantity, one column per
#    contact, in list order);
# 3. the law, on the columns (vectorized: no branches, scalars only);
# 4. scatter_pair_columns: forces and torques onto the particles in list order, the pair forces
#    and the new histories into their rows.
# pair_columns is 1 and 2 in one call, for all touching pairs. Each particle receives the same
# terms in the same order as in pair_forces: the same bits.

#: rows of the geometry columns (C); the history follows at COL_HIST
COL_DELTA, COL_NX, COL_NY, COL_NZ, COL_VX, COL_VY, COL_VZ, COL_WX, COL_WY, COL_WZ = range(10)
COL_REFF, COL_MEFF, COL_IEFF, COL_AI, COL_AJ, COL_HIST = range(10, 16)
#: rows of the law's output (O): force on j, torque on j, the new history from OUT_HIST
OUT_FX, OUT_FY, OUT_FZ, OUT_MX, OUT_MY, OUT_MZ, OUT_HIST = range(7)


@njit
def touching_pairs(pi, pj, hist, x, r, inv_m, fpair, tk):
    """Pass 1a over every listed pair, without branches on the outcome: returns (m, flags), m the
    touching pairs whose list indices go to ``tk[:min(m, len(tk))]`` in list order. The other pairs
    get zero history and force, as in :func:`pair_forces` (a row already +0.0 is not rewritten).
    A pair counts as touching as in :func:`pair_forces`: its centres are nearer than r_i + r_j (or
    the distance is not a number) and one of the two is free; coincident centres are flagged and
    left out. ``hist`` and ``fpair`` must be C-contiguous (their rows are tested as bits)."""
    flags = 0
    hsize = hist.shape[1]
    hbits = hist.view(np.int64)  # a row is rewritten unless all of it is +0.0, as bits
    fbits = fpair.view(np.int64)
    last = tk.shape[0] - 1
    m = 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        rsum = r[i] + r[j]
        touch = (not (d2 >= rsum * rsum)) & ((inv_m[i] != 0.0) | (inv_m[j] != 0.0))
        bits = fbits[k, 0] | fbits[k, 1] | fbits[k, 2]
        for h in range(hsize):
            bits |= hbits[k, h]
        if bits != 0 and not touch:  # rare: the pair has just come apart
            for h in range(hsize):
                hist[k, h] = 0.0
            fpair[k, 0] = 0.0
            fpair[k, 1] = 0.0
            fpair[k, 2] = 0.0
        coincident = touch & (d2 == 0.0)
        flags |= FLAG_COINCIDENT if coincident else 0
        if last >= 0:
            tk[min(m, last)] = k
        m += touch & (not coincident)
    return m, flags


@njit
def fill_pair_columns(tk, m, pi, pj, hist, x, v, w, r, inv_m, inv_i, max_overlap, C, angular=True):
    """Pass 1b: the geometry, relative velocities, effective radius, mass and inertia, lever
    lengths and history of the touching pairs ``tk[:m]`` (list indices, e.g. a block of those
    :func:`touching_pairs` found) into columns ``C[:, :m]``, with the arithmetic of
    :func:`pair_forces`; returns the flag word (``FLAG_OVERLAP``). Without ``angular`` the rows
    ``COL_WX``–``COL_WZ`` and ``COL_IEFF`` (a law's extra torques only) are not written."""
    flags = 0
    hsize = hist.shape[1]
    for q in range(m):
        k = tk[q]
        i = pi[k]
        j = pj[k]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        rsum = r[i] + r[j]
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        nx, ny, nz, delta, ai, aj, vx, vy, vz = _contact_kinematics(i, j, dx, dy, dz, dist, rsum, v, w, r)
        flags |= FLAG_OVERLAP if delta > max_overlap * min(r[i], r[j]) else 0
        C[COL_DELTA, q] = delta
        C[COL_NX, q] = nx
        C[COL_NY, q] = ny
        C[COL_NZ, q] = nz
        C[COL_VX, q] = vx
        C[COL_VY, q] = vy
        C[COL_VZ, q] = vz
        if angular:
            C[COL_WX, q] = w[j, 0] - w[i, 0]
            C[COL_WY, q] = w[j, 1] - w[i, 1]
            C[COL_WZ, q] = w[j, 2] - w[i, 2]
            C[COL_IEFF, q] = 1.0 / (inv_i[i] + inv_i[j])
        C[COL_REFF, q] = r[i] * r[j] / rsum
        C[COL_MEFF, q] = 1.0 / (inv_m[i] + inv_m[j])
        C[COL_AI, q] = ai
        C[COL_AJ, q] = aj
        if hsize == 3:  # the tangential spring (decided once per call: the loop is unswitched)
            C[COL_HIST, q] = hist[k, 0]
            C[COL_HIST + 1, q] = hist[k, 1]
            C[COL_HIST + 2, q] = hist[k, 2]
        else:
            for h in range(hsize):
                C[COL_HIST + h, q] = hist[k, h]
    return flags


@njit
def pair_columns(pi, pj, hist, x, v, w, r, inv_m, inv_i, fpair, max_overlap, C, tk, angular=True):
    """Pass 1 in one call: returns (m, flags), m the touching pairs, whose list indices go to
    ``tk[:m]`` and whose columns to ``C[:, :m]`` (:func:`touching_pairs`, then
    :func:`fill_pair_columns`).

    If m exceeds the columns (``C.shape[1]`` or ``len(tk)``), nothing is written to them: call
    again with at least m columns (the pass changes nothing else a second call would see
    differently: it only zeroes the non-touching pairs' history and force)."""
    m, flags = touching_pairs(pi, pj, hist, x, r, inv_m, fpair, tk)
    if m > min(C.shape[1], tk.shape[0]):
        return m, flags
    flags |= fill_pair_columns(tk, m, pi, pj, hist, x, v, w, r, inv_m, inv_i, max_overlap, C, angular)
    return m, flags


@njit
def scatter_pair_columns(tk, m, pi, pj, C, O, moments, f, t, fpair, hist):
    """Pass 3: the law's forces ``O[OUT_F*]`` (and torques ``O[OUT_M*]`` when ``moments``, else
    zero) onto the particles in list order as :func:`pair_forces` adds them; the pair forces and the
    new histories ``O[OUT_HIST:]`` into their rows."""
    hsize = hist.shape[1]
    for q in range(m):
        k = tk[q]
        i = pi[k]
        j = pj[k]
        fx = O[OUT_FX, q]
        fy = O[OUT_FY, q]
        fz = O[OUT_FZ, q]
        mx = O[OUT_MX, q]
        my = O[OUT_MY, q]
        mz = O[OUT_MZ, q]
        if not moments:
            mx = 0.0
            my = 0.0
            mz = 0.0
        nx = C[COL_NX, q]
        ny = C[COL_NY, q]
        nz = C[COL_NZ, q]
        ai = C[COL_AI, q]
        aj = C[COL_AJ, q]
        f[i, 0] -= fx
        f[i, 1] -= fy
        f[i, 2] -= fz
        f[j, 0] += fx
        f[j, 1] += fy
        f[j, 2] += fz
        cx = ny * fz - nz * fy
        cy = nz * fx - nx * fz
        cz = nx * fy - ny * fx
        t[i, 0] += -ai * cx - mx
        t[i, 1] += -ai * cy - my
        t[i, 2] += -ai * cz - mz
        t[j, 0] += -aj * cx + mx
        t[j, 1] += -aj * cy + my
        t[j, 2] += -aj * cz + mz
        fpair[k, 0] = fx
        fpair[k, 1] = fy
        fpair[k, 2] = fz
        for h in range(hsize):
            hist[k, h] = O[OUT_HIST + h, q]


@njit_nocache(inline="always")
def wall_forces(
    law,
    kinds,
    params,
    vel,
    omega,
    centre,
    wmat,
    cstart,
    cand,
    hist,
    x,
    v,
    w,
    r,
    inv_m,
    inv_i,
    mat,
    coef,
    f,
    t,
    dt,
    max_overlap,
    out_idx,
    out_val,
    counts,
):
    """Contacts of candidate particles with every wall, walls in order (one call per step).

    Wall k has geometry ``kinds[k]``/``params[k]`` (see :mod:`pdem.geometry._kernels`), translational
    and angular velocity ``vel[k]``/``omega[k]``, reference point ``centre[k]`` (about which it turns
    and its torque is reported), material ``wmat[k]``, candidates ``cand[cstart[k]:cstart[k+1]]`` and
    history ``hist[q]`` for candidate row q (sparse: one row per candidate, keyed by wall and particle
    id in :class:`pdem.contact.store.ContactStore`). Inactive walls have no candidates.

    A wall is the partner j (infinite mass and radius: R* = r_i, m* = m_i, I* = I_i); the law's force
    F acts on the wall and −F on the particle. Each touching particle's contribution to wall k's
    load ``(Fx, Fy, Fz, Tx, Ty, Tz)`` is written to ``out_val[cstart[k] + c]`` with its particle index
    in ``out_idx``; ``counts[k]`` receives the number of contacts. Returns the flag word.
    """
    flags = 0
    hsize = hist.shape[1]
    for k in range(kinds.shape[0]):
        kind = kinds[k]
        p = params[k]
        base = cstart[k]
        count = 0
        for q in range(cstart[k], cstart[k + 1]):
            i = cand[q]
            if i < 0:  # set aside this step (a mesh counts a grain touching several facets once)
                for h in range(hsize):
                    hist[q, h] = 0.0
                continue
            gap, nx, ny, nz, px, py, pz = wall_contact(kind, p, x[i, 0], x[i, 1], x[i, 2], r[i])
            if gap >= 0.0 or (inv_m[i] == 0.0 and vel[k, 4] == 0.0):
                for h in range(hsize):
                    hist[q, h] = 0.0
                continue
            if inv_m[i] == 0.0:  # a fixed grain against a free rigid body (vel[k, 4]: its mass)
                m_eff = vel[k, 4]
                i_eff = 0.4 * m_eff * r[i] * r[i]
            else:
                m_eff = 1.0 / inv_m[i]
                i_eff = 1.0 / inv_i[i]
            delta = -gap
            if delta > max_overlap * r[i]:
                flags |= FLAG_OVERLAP
            ai = r[i] - 0.5 * delta
            vix = v[i, 0] + ai * (w[i, 1] * nz - w[i, 2] * ny)
            viy = v[i, 1] + ai * (w[i, 2] * nx - w[i, 0] * nz)
            viz = v[i, 2] + ai * (w[i, 0] * ny - w[i, 1] * nx)
            # wall velocity at the contact point: V + Ω × (p − centre) (+ the rate of its radius)
            vwx, vwy, vwz, qx, qy, qz = surface_velocity(kind, p, vel, omega, centre, k, px, py, pz)
            fx, fy, fz, mx, my, mz = law(
                delta,
                nx,
                ny,
                nz,
                vwx - vix,
                vwy - viy,
                vwz - viz,
                omega[k, 0] - w[i, 0],
                omega[k, 1] - w[i, 1],
                omega[k, 2] - w[i, 2],
                r[i],
                m_eff,
                i_eff,
                coef,
                mat[i],
                wmat[k],
                hist,
                q,
                dt,
            )
            f[i, 0] -= fx
            f[i, 1] -= fy
            f[i, 2] -= fz
            cx = ny * fz - nz * fy
            cy = nz * fx - nx * fz
            cz = nx * fy - ny * fx
            t[i, 0] += -ai * cx - mx
            t[i, 1] += -ai * cy - my
            t[i, 2] += -ai * cz - mz
            c = base + count
            out_idx[c] = i
            out_val[c, 0] = fx
            out_val[c, 1] = fy
            out_val[c, 2] = fz
            out_val[c, 3] = qy * fz - qz * fy + mx
            out_val[c, 4] = qz * fx - qx * fz + my
            out_val[c, 5] = qx * fy - qy * fx + mz
            count += 1
        counts[k] = count
    return flags
