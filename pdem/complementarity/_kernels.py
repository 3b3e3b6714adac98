"""DEM-C kernels: contact assembly, impulse accumulation, cone projection, solver sweeps.

Contacts are stored as flat arrays (``nc`` rows), pair contacts first in pair-list order (sorted by
id pair), then wall contacts wall by wall; a particle therefore receives its impulses in the same
order on any partition, as in the DEM-P pair loop (architecture: determinism).

Per contact c:

* ``cb[c] = (i, j)``: bodies; ``i = -1`` for a wall (immovable, moving with velocity ``cvw[c]`` at
  the contact point), ``j`` always a particle;
* ``cn[c]``: unit normal from i to j; ``ca[c] = (a_i, a_j)``: lever lengths (radii), contact point
  x_i + a_i n = x_j − a_j n;
* ``cbias[c]``: b = φ/h, φ the gap (negative when penetrating); a penetration within ``slack``
  (an overlap the run started from, still allowed: ``Stepper.recovery_slack``) is held, not removed
  (b = min(φ + slack, 0)/h), and with a cap b ≥ −v_recovery;
* ``cmu[c]``: friction coefficient; ``cscale[c]``: B = 3 / trace(N_cc);
* ``gam[c] = (γ_n, γ_tx, γ_ty, γ_tz, ρ_x, ρ_y, ρ_z, σ)``: normal impulse and tangential impulse
  vector (⊥ n), applied as G = γ_n n + γ_t on j and −G on i; then the rolling (ρ ⊥ n) and spinning
  (σ, about n) impulses, scaled by R*: the moment impulse R*(ρ + σ n) acts on j and its opposite on i;
* ``croll[c] = (μ_r, μ_s, R*, B_r)``: rolling and spinning friction, effective radius
  R* = a_i a_j/(a_i + a_j) (a wall: a_j) and the Jacobi scale B_r = 1/(R*² (I_i⁻¹ + I_j⁻¹)) of the
  rolling rows; R* = 0 when the contact has neither (or no body can turn): its rolling rows are
  skipped;
* ``cvw[c] = (V_w, Ω_w)``: a wall's velocity at the contact point and its angular velocity.

The contact velocity u = Dᵀv + b has u_n = n·v_rel + b and u_t = v_rel − (n·v_rel) n with
v_rel = (v_j + ω_j × (−a_j n)) − (v_i + ω_i × (a_i n)) (physics reference §3). The rolling rows'
velocities are R* times the relative angular velocity ω_rel = ω_j − ω_i (a wall: ω_j − Ω_w): u_r its
tangential part, u_s its normal part (both in m/s).

Rolling and spinning friction (Tasora & Anitescu, Meccanica 48, 2013, as Chrono NSC solves it):
|ρ| ≤ μ_r γ_n, |σ| ≤ μ_s γ_n (moment bounds μ_r R* γ_n and μ_s R* γ_n, the torque bound μ_r R* F_n
of DEM-P's rolling resistance), each opposing its rolling or spinning velocity. Every update first
projects (γ_n, γ_t) onto the friction cone, then clamps ρ and σ to the bounds of the new γ_n
(Chrono's projection): the rolling rows never change γ_n, so they cause no dilation.

Restitution (Newton's impact law, as Chrono NSC): a contact whose normal velocity at the start of
the step v_n⁻ approaches faster than the threshold (v_n⁻ < −v_th) and would close within the step
(b + v_n⁻ < 0) gets the bias min(b, e v_n⁻): the solve then gives u_n ≥ 0 with v_n⁺ ≥ e |v_n⁻|.
Other contacts keep b (perfectly inelastic).

``corrected`` (the law's ``cone = "corrected"``): the solver works with ũ = (u_n + μ|u_t|, u_t)
instead of u (De Saxcé's change of variable). γ ∈ K, ũ ∈ K*, γ ⊥ ũ is then Coulomb's law itself:
u_n ≥ 0, γ_n u_n = 0, and a sliding contact's friction is μ γ_n against the slip, so a sliding
contact keeps u_n = 0 instead of separating at μ|u_t| (the relaxed cone, ``corrected`` false).
Every solver takes μ|u_t| from the velocities of the current iterate (Jacobi and Gauss–Seidel at
each update, APGD at each evaluation of ũ: :func:`contact_velocities`): the shift and the impulses
converge together to the fixed point.
"""

from __future__ import annotations

import math

import numpy as np

from ..api import (
    FLAG_COINCIDENT,
    FLAG_NONFINITE,
    FLAG_OVERLAP,
    exact_accumulator,
    exact_add,
    exact_add_many,
    exact_bins,
    exact_partials,
    njit,
    surface_velocity,
    wall_contact,
)


@njit(inline="always")
def project_cone(gn, tx, ty, tz, mu):
    """Euclidean projection of (γ_n, γ_t) onto the cone K = {γ_n ≥ 0, |γ_t| ≤ μ γ_n}: on the surface
    γ_n = (γ_n + μ|γ_t|)/(μ² + 1), the origin when μ|γ_t| ≤ −γ_n (:func:`project_cone_weighted`
    with ρ = 1)."""
    return project_cone_weighted(gn, tx, ty, tz, mu, mu)


@njit(inline="always")
def project_cone_weighted(gn, tx, ty, tz, mu, murho):
    """Projection of (γ_n, γ_t) onto K in the metric diag(1, ρ, ρ) (``murho`` = μρ): the closest
    point of K when a tangential change counts ρ times a normal one. ρ = B_n/B_t of a
    contact's Delassus block makes the block-scaled sweep γ ← Π(γ − ω B u) a fixed-point iteration
    of the contact problem (the metric is B⁻¹'s). ρ = 1 (``murho`` = μ): :func:`project_cone`, bit
    for bit. On the surface γ_n = (γ_n + μρ|γ_t|)/(1 + μ²ρ); the origin when μρ|γ_t| ≤ −γ_n."""
    t = math.sqrt(tx * tx + ty * ty + tz * tz)
    if mu <= 0.0:
        return max(gn, 0.0), 0.0, 0.0, 0.0
    if t <= mu * gn:
        return gn, tx, ty, tz
    if murho * t <= -gn:
        return 0.0, 0.0, 0.0, 0.0
    gn2 = (murho * t + gn) / (mu * murho + 1.0)
    s = mu * gn2 / t
    return gn2, tx * s, ty * s, tz * s


@njit(inline="always")
def clamp_norm(x, y, z, bound):
    """(x, y, z) scaled to length ``bound`` if longer (bound ≥ 0)."""
    t = math.sqrt(x * x + y * y + z * z)
    if t <= bound:
        return x, y, z
    if bound <= 0.0:
        return 0.0, 0.0, 0.0
    s = bound / t
    return x * s, y * s, z * s


@njit(inline="always")
def clamp_abs(x, bound):
    """x clamped to [−bound, bound]."""
    if x > bound:
        return bound
    if x < -bound:
        return -bound
    return x


@njit
def project_cone_array(g, mu, croll):
    """Project each row of ``g`` (n, 8) onto its cone, then clamp its rolling and spinning impulses
    to the bounds of the projected γ_n (tests, APGD)."""
    out = g.copy()
    for c in range(g.shape[0]):
        out[c, 0], out[c, 1], out[c, 2], out[c, 3] = project_cone(g[c, 0], g[c, 1], g[c, 2], g[c, 3], mu[c])
        if croll[c, 2] > 0.0:
            out[c, 4], out[c, 5], out[c, 6] = clamp_norm(g[c, 4], g[c, 5], g[c, 6], croll[c, 0] * out[c, 0])
            out[c, 7] = clamp_abs(g[c, 7], croll[c, 1] * out[c, 0])
        else:
            for k in range(4, g.shape[1]):
                out[c, k] = 0.0
    return out


@njit(inline="always")
def _contact_envelope(envelope, env_base, env_factor, s1, s2):
    """A contact's envelope: min(``envelope``, max(``env_base``, ``env_factor`` × max(s1, s2))),
    s1, s2 its bodies' speed bounds; ``envelope`` itself when ``env_factor`` is 0."""
    if env_factor > 0.0:
        return min(envelope, max(env_base, env_factor * max(s1, s2)))
    return envelope


@njit
def count_pair_contacts(pi, pj, x, r, inv_m, envelope):
    n = 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        if inv_m[i] == 0.0 and inv_m[j] == 0.0:
            continue
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        lim = r[i] + r[j] + envelope
        if dx * dx + dy * dy + dz * dz <= lim * lim:
            n += 1
    return n


@njit
def entering_pairs(pi, pj, hist, x, r, inv_m, envelope, spd, env_base, env_factor, tk):
    """The listed pairs that enter this step's problem (gap below their envelope, one of the two
    free), as in :func:`assemble_pairs`: returns (m, flags), their list indices in ``tk[:m]`` (in
    list order; ``len(tk)`` ≥ the pairs listed). The history of the others is zeroed (a row
    already +0.0 bit for bit is not rewritten); coincident centres are flagged and left out. No
    branch on whether a pair enters: it is unpredictable where a tenth of the listed pairs do."""
    flags = 0
    hsize = hist.shape[1]
    hbits = hist.view(np.int64)
    m = 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        lim = r[i] + r[j] + _contact_envelope(envelope, env_base, env_factor, spd[i], spd[j])
        enters = (not (d2 > lim * lim)) & ((inv_m[i] != 0.0) | (inv_m[j] != 0.0))
        bits = 0
        for q in range(hsize):
            bits |= hbits[k, q]
        if bits != 0 and not enters:  # rare: a contact of the last step has left the problem
            for q in range(hsize):
                hist[k, q] = 0.0
        coincident = enters & (d2 == 0.0)
        flags |= FLAG_COINCIDENT if coincident else 0
        tk[m] = k
        m += enters & (not coincident)
    return m, flags


@njit
def assemble_pairs(
    pi, pj, hist, x, v, r, inv_m, inv_i, mat, coef, h, envelope, v_recovery, slack, v_bounce, max_overlap,
    cb, cn, ca, cvw, cbias, cmu, cscale, croll, gam, csrc, spd, env_base, env_factor, tk,
):  # fmt: skip
    """Fill rows [0, n_pair_contacts) from the pair list; zero the history of pairs out of reach.
    ``v`` holds the velocities at the start of the step (restitution's v_n⁻), ``coef[a, b]`` the
    pair's (μ, e, μ_r, μ_s), ``v_bounce`` the restitution threshold [m/s]; ``tk`` is work space
    (at least as long as the pair list).

    A pair enters when its gap is below its own envelope, min(``envelope``, max(``env_base``,
    ``env_factor`` × max(spd_i, spd_j))), ``spd`` a bound on each body's speed during the step
    (``env_factor`` = 0: every pair at ``envelope``). The pairs are tested first
    (:func:`entering_pairs`), then the rows of those that enter are filled, in list order.

    Returns (number of contacts, flags)."""
    m, flags = entering_pairs(pi, pj, hist, x, r, inv_m, envelope, spd, env_base, env_factor, tk)
    for c in range(m):
        k = tk[c]
        i = pi[k]
        j = pj[k]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        nx = dx / dist
        ny = dy / dist
        nz = dz / dist
        phi = dist - r[i] - r[j]
        if -phi > max_overlap * min(r[i], r[j]):
            flags |= FLAG_OVERLAP
        vn0 = (v[j, 0] - v[i, 0]) * nx + (v[j, 1] - v[i, 1]) * ny + (v[j, 2] - v[i, 2]) * nz
        co = coef[mat[i], mat[j]]
        _fill(c, i, j, nx, ny, nz, r[i], r[j], 0.0, phi, h, v_recovery, slack, co, vn0, v_bounce,
              inv_m[i], inv_m[j], inv_i[i], inv_i[j], hist[k], cb, cn, ca, cbias, cmu, cscale, croll,
              gam)  # fmt: skip
        for q in range(6):
            cvw[c, q] = 0.0
        csrc[c, 0] = -1
        csrc[c, 1] = k
    return m, flags


@njit(inline="always")
def _fill(c, i, j, nx, ny, nz, ai, aj, rstar, phi, h, v_recovery, slack, co, vn0, v_bounce, imi, imj, iii,
          iij, hrow, cb, cn, ca, cbias, cmu, cscale, croll, gam):  # fmt: skip
    """One contact row. ``rstar`` > 0: the effective radius of the rolling rows (a wall's contact);
    0: a_i a_j/(a_i + a_j) (a pair's). ``co`` = (μ, e, μ_r, μ_s)."""
    cb[c, 0] = i
    cb[c, 1] = j
    cn[c, 0] = nx
    cn[c, 1] = ny
    cn[c, 2] = nz
    ca[c, 0] = ai
    ca[c, 1] = aj
    b = phi / h
    if phi < 0.0 and slack > 0.0:  # an initial overlap still allowed: held, not pushed apart
        b = min(phi + slack, 0.0) / h
    if v_recovery > 0.0 and b < -v_recovery:
        b = -v_recovery
    e = co[1]
    # Newton's impact law: approaching faster than the threshold and closing within the step
    if e > 0.0 and vn0 < -v_bounce and b + vn0 < 0.0:
        b = min(b, e * vn0)
    cbias[c] = b
    mu = co[0]
    cmu[c] = mu
    trace = 3.0 * (imi + imj) + 2.0 * (ai * ai * iii + aj * aj * iij)
    cscale[c] = 3.0 / trace
    # warm start: last step's impulse, tangential part turned onto the current tangent plane
    tx = hrow[1]
    ty = hrow[2]
    tz = hrow[3]
    tn = tx * nx + ty * ny + tz * nz
    g0, g1, g2, g3 = project_cone(hrow[0], tx - tn * nx, ty - tn * ny, tz - tn * nz, mu)
    gam[c, 0] = g0
    gam[c, 1] = g1
    gam[c, 2] = g2
    gam[c, 3] = g3
    mu_r = co[2]
    mu_s = co[3]
    isum = iii + iij
    if (mu_r > 0.0 or mu_s > 0.0) and isum > 0.0:
        if rstar <= 0.0:
            rstar = ai * aj / (ai + aj)
        croll[c, 0] = mu_r
        croll[c, 1] = mu_s
        croll[c, 2] = rstar
        croll[c, 3] = 1.0 / (rstar * rstar * isum)
        # warm start: rolling part turned onto the tangent plane, both clamped to the bounds
        rx = hrow[4]
        ry = hrow[5]
        rz = hrow[6]
        rn = rx * nx + ry * ny + rz * nz
        gam[c, 4], gam[c, 5], gam[c, 6] = clamp_norm(rx - rn * nx, ry - rn * ny, rz - rn * nz, mu_r * g0)
        gam[c, 7] = clamp_abs(hrow[7], mu_s * g0)
    else:
        croll[c, 0] = 0.0
        croll[c, 1] = 0.0
        croll[c, 2] = 0.0
        croll[c, 3] = 0.0
        for k in range(4, gam.shape[1]):  # rows of 8 (some pair of the scene rolls) or of 4
            gam[c, k] = 0.0


@njit
def assemble_walls(
    kinds, params, vel, omega, centre, wmat, cstart, cand, whist, x, v, r, inv_m, inv_i, mat, coef, h,
    envelope, v_recovery, slack, v_bounce, max_overlap, start, cb, cn, ca, cvw, cbias, cmu, cscale, croll,
    gam, csrc, cpt, wbody, wbinv, spd, env_base, env_factor,
):  # fmt: skip
    """Append wall contacts from row ``start``; zero the history of candidates out of reach.

    The wall geometry kernel returns n from the sphere into the wall; the contact normal here points
    from the wall (body i) to the particle (body j), i.e. −n. ``cpt`` receives the contact point
    relative to the wall's reference point (for the reported torque). A row of a wall that is a free
    rigid body (``wbody[k]`` ≥ 0, the body's index in the velocity arrays ``v``, ``wbinv[k]`` its
    inverse mass) makes that body the contact's partner i (translation only: no lever), so its
    velocity is solved with the grains'. The rolling rows' effective radius is the grain's radius
    (DEM-P's R* of a wall contact). The envelope is per contact as in :func:`assemble_pairs`, with
    the speed of the wall's surface at the contact point for the wall's. Returns (end row, flags)."""
    flags = 0
    c = start
    for k in range(kinds.shape[0]):
        kind = kinds[k]
        p = params[k]
        for q in range(cstart[k], cstart[k + 1]):
            i = cand[q]
            if i < 0:  # set aside this step (mesh walls: one contact per grain)
                for s in range(whist.shape[1]):
                    whist[q, s] = 0.0
                continue
            gap, nx, ny, nz, px, py, pz = wall_contact(kind, p, x[i, 0], x[i, 1], x[i, 2], r[i])
            body = wbody[k]
            out = gap > envelope or (inv_m[i] == 0.0 and body < 0)
            if not out:
                # lever of the wall's load: its closest point relative to the reference point
                vwx, vwy, vwz, qx, qy, qz = surface_velocity(kind, p, vel, omega, centre, k, px, py, pz)
                if env_factor > 0.0:
                    sw = spd[body] if body >= 0 else math.sqrt(vwx * vwx + vwy * vwy + vwz * vwz)
                    out = gap > _contact_envelope(envelope, env_base, env_factor, spd[i], sw)
            if out:
                for s in range(whist.shape[1]):
                    whist[q, s] = 0.0
                continue
            if -gap > max_overlap * r[i]:
                flags |= FLAG_OVERLAP
            co = coef[mat[i], wmat[k]]
            if body >= 0:  # the body's velocity is an unknown of the problem
                vn0 = -((v[i, 0] - v[body, 0]) * nx + (v[i, 1] - v[body, 1]) * ny
                        + (v[i, 2] - v[body, 2]) * nz)
                _fill(c, body, i, -nx, -ny, -nz, 0.0, r[i], r[i], gap, h, v_recovery, slack, co, vn0,
                      v_bounce, wbinv[k], inv_m[i], 0.0, inv_i[i], whist[q], cb, cn, ca, cbias, cmu, cscale,
                      croll, gam)  # fmt: skip
                for s in range(6):
                    cvw[c, s] = 0.0
            else:
                vn0 = -((v[i, 0] - vwx) * nx + (v[i, 1] - vwy) * ny + (v[i, 2] - vwz) * nz)
                _fill(c, -1, i, -nx, -ny, -nz, 0.0, r[i], r[i], gap, h, v_recovery, slack, co, vn0, v_bounce,
                      0.0, inv_m[i], 0.0, inv_i[i], whist[q], cb, cn, ca, cbias, cmu, cscale, croll,
                      gam)  # fmt: skip
                cvw[c, 0] = vwx
                cvw[c, 1] = vwy
                cvw[c, 2] = vwz
                cvw[c, 3] = omega[k, 0]
                cvw[c, 4] = omega[k, 1]
                cvw[c, 5] = omega[k, 2]
            csrc[c, 0] = k
            csrc[c, 1] = i
            csrc[c, 2] = q
            cpt[c, 0] = qx
            cpt[c, 1] = qy
            cpt[c, 2] = qz
            c += 1
    return c, flags


@njit
def missed_pairs(pi, pj, x, v, r, inv_m, h, envelope, spd, env_base, env_factor):
    """Pairs that were not in the problem (gap above their envelope at the start of the step, as in
    :func:`assemble_pairs`) but overlap at the end of it (x + h v, v the solved velocities): the
    contacts a per-contact envelope missed. Returns their number (counted without branches)."""
    missed = 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        lim = r[i] + r[j] + _contact_envelope(envelope, env_base, env_factor, spd[i], spd[j])
        out = not (dx * dx + dy * dy + dz * dz <= lim * lim)  # not in the problem
        ex = dx + h * (v[j, 0] - v[i, 0])
        ey = dy + h * (v[j, 1] - v[i, 1])
        ez = dz + h * (v[j, 2] - v[i, 2])
        rs = r[i] + r[j]
        free = (inv_m[i] != 0.0) | (inv_m[j] != 0.0)
        missed += free & out & (ex * ex + ey * ey + ez * ez < rs * rs)
    return missed


@njit
def swept_missed_pairs(pi, pj, x, v, r, inv_m, h, envelope):
    """Pairs outside a fixed envelope at the start of the step whose spheres come closer than touching
    at any time during it, along the solved straight paths x + t h v (0 ≤ t ≤ 1): overlapping at the
    end, or passed through each other (tunnelling). Returns their number."""
    missed = 0
    for k in range(pi.shape[0]):
        i = pi[k]
        j = pj[k]
        if inv_m[i] == 0.0 and inv_m[j] == 0.0:
            continue
        dx = x[j, 0] - x[i, 0]
        dy = x[j, 1] - x[i, 1]
        dz = x[j, 2] - x[i, 2]
        rs = r[i] + r[j]
        lim = rs + envelope
        if dx * dx + dy * dy + dz * dz <= lim * lim:
            continue  # in the problem
        sx = h * (v[j, 0] - v[i, 0])
        sy = h * (v[j, 1] - v[i, 1])
        sz = h * (v[j, 2] - v[i, 2])
        ss = sx * sx + sy * sy + sz * sz
        t = 0.0
        if ss > 0.0:
            t = min(1.0, max(0.0, -(dx * sx + dy * sy + dz * sz) / ss))
        ex = dx + t * sx
        ey = dy + t * sy
        ez = dz + t * sz
        if ex * ex + ey * ey + ez * ez < rs * rs:
            missed += 1
    return missed


@njit
def missed_walls(kinds, params_start, params_end, vel, omega, centre, cstart, cand, x, v, r, inv_m, h,
                 envelope, wbody, spd, env_base, env_factor):  # fmt: skip
    """Wall candidates that were not in the problem at the start of the step (as in
    :func:`assemble_walls`) but overlap the wall where it is at the end of it: the wall contacts a
    per-contact envelope missed. Returns their number."""
    missed = 0
    for k in range(kinds.shape[0]):
        kind = kinds[k]
        body = wbody[k]
        for q in range(cstart[k], cstart[k + 1]):
            i = cand[q]
            if i < 0 or (inv_m[i] == 0.0 and body < 0):
                continue
            p = params_start[k]
            gap, nx, ny, nz, px, py, pz = wall_contact(kind, p, x[i, 0], x[i, 1], x[i, 2], r[i])
            if gap <= envelope:
                vwx, vwy, vwz, qx, qy, qz = surface_velocity(kind, p, vel, omega, centre, k, px, py, pz)
                sw = spd[body] if body >= 0 else math.sqrt(vwx * vwx + vwy * vwy + vwz * vwz)
                if gap <= _contact_envelope(envelope, env_base, env_factor, spd[i], sw):
                    continue  # in the problem
            if body >= 0:
                continue  # a free body's end position is not known here
            gap2 = wall_contact(kind, params_end[k], x[i, 0] + h * v[i, 0], x[i, 1] + h * v[i, 1],
                                x[i, 2] + h * v[i, 2], r[i])[0]  # fmt: skip
            if gap2 < 0.0:
                missed += 1
    return missed


@njit
def speed_bounds(v, n, dv):
    """|v_i| + ``dv`` for bodies [0, n): a bound on each body's speed during the step."""
    out = np.empty(n)
    for i in range(n):
        out[i] = math.sqrt(v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]) + dv
    return out


@njit(inline="always")
def _accumulate_impulse(i, j, nx, ny, nz, ai, aj, rs, g0, g1, g2, g3, g4, g5, g6, g7, P, L):
    """P, L += one contact's impulse G = γ_n n + γ_t (on j, −G on i) and its moments, and the
    rolling and spinning moment R*(ρ + σ n) when R* > 0 (see :func:`_accumulate_row`)."""
    gx = g0 * nx + g1
    gy = g0 * ny + g2
    gz = g0 * nz + g3
    # n × G; a_i × (−G) = −a_i (n × G), (−a_j n) × G = −a_j (n × G)
    cx = ny * gz - nz * gy
    cy = nz * gx - nx * gz
    cz = nx * gy - ny * gx
    if rs > 0.0:  # rolling and spinning: a pure moment R*(ρ + σ n) on j
        mx = rs * (g4 + g7 * nx)
        my = rs * (g5 + g7 * ny)
        mz = rs * (g6 + g7 * nz)
    else:
        mx = 0.0
        my = 0.0
        mz = 0.0
    P[j, 0] += gx
    P[j, 1] += gy
    P[j, 2] += gz
    L[j, 0] -= aj * cx - mx
    L[j, 1] -= aj * cy - my
    L[j, 2] -= aj * cz - mz
    if i >= 0:
        P[i, 0] -= gx
        P[i, 1] -= gy
        P[i, 2] -= gz
        L[i, 0] -= ai * cx + mx
        L[i, 1] -= ai * cy + my
        L[i, 2] -= ai * cz + mz


@njit(inline="always")
def _accumulate_row(c, cb, cn, ca, croll, gam, P, L):
    """P, L += contact c's impulse and its moments on its two bodies.

    Every array is read before the first branch and only scalars are branched on: an array whose
    last use in an inlined helper sits inside a branch keeps numba's reference counting (atomic
    increments and decrements, calls into its runtime) inside the caller's loop, which made this
    loop five times slower. The arithmetic is unchanged (the same bits)."""
    # the rolling impulses (columns 4-7 of rows of 8; rows of 4 have none, and these read columns
    # 0-3, unused: rs = 0 on every row of a scene without rolling friction)
    o = gam.shape[1] - 4
    _accumulate_impulse(
        cb[c, 0], cb[c, 1], cn[c, 0], cn[c, 1], cn[c, 2], ca[c, 0], ca[c, 1], croll[c, 2],
        gam[c, 0], gam[c, 1], gam[c, 2], gam[c, 3], gam[c, o], gam[c, o + 1], gam[c, o + 2], gam[c, o + 3],
        P, L,
    )  # fmt: skip


@njit
def accumulate(cb, cn, ca, croll, gam, nc, P, L):
    """P, L ← Σ impulses and their moments per body, contacts in row order (P, L zeroed first)."""
    P[:] = 0.0
    L[:] = 0.0
    for c in range(nc):
        _accumulate_row(c, cb, cn, ca, croll, gam, P, L)


@njit(inline="always")
def _lock(v, w, dof, i):
    """Zero the locked velocity components of body i (``dof`` bits: v_c at c, ω_c at 3 + c)."""
    lock = dof[i]
    if lock != 0:
        for d in range(3):
            if (lock >> d) & 1:
                v[i, d] = 0.0
            if (lock >> (d + 3)) & 1:
                w[i, d] = 0.0


@njit
def velocities(v, w, v_free, w_free, P, L, inv_m, inv_i, dof, n):
    """v = v_free + P/m, ω = ω_free + L/I for bodies [0, n); locked components stay zero."""
    for i in range(n):
        for d in range(3):
            v[i, d] = v_free[i, d] + inv_m[i] * P[i, d]
            w[i, d] = w_free[i, d] + inv_i[i] * L[i, d]
        _lock(v, w, dof, i)


@njit(inline="always")
def _contact_velocity(c, cb, cn, ca, cvw, cbias, v, w):
    # arrays read before any branch (see _accumulate_row); a wall row (i < 0) reads body 0's values
    # and uses the wall's
    i = cb[c, 0]
    j = cb[c, 1]
    ii = i if i >= 0 else 0
    nx = cn[c, 0]
    ny = cn[c, 1]
    nz = cn[c, 2]
    aj = ca[c, 1]
    ai = ca[c, 0]
    bias = cbias[c]
    vj0 = v[j, 0]
    vj1 = v[j, 1]
    vj2 = v[j, 2]
    wj0 = w[j, 0]
    wj1 = w[j, 1]
    wj2 = w[j, 2]
    vi0 = v[ii, 0]
    vi1 = v[ii, 1]
    vi2 = v[ii, 2]
    wi0 = w[ii, 0]
    wi1 = w[ii, 1]
    wi2 = w[ii, 2]
    cw0 = cvw[c, 0]
    cw1 = cvw[c, 1]
    cw2 = cvw[c, 2]
    # v_j + ω_j × (−a_j n)
    rx = vj0 - aj * (wj1 * nz - wj2 * ny)
    ry = vj1 - aj * (wj2 * nx - wj0 * nz)
    rz = vj2 - aj * (wj0 * ny - wj1 * nx)
    if i >= 0:
        rx -= vi0 + ai * (wi1 * nz - wi2 * ny)
        ry -= vi1 + ai * (wi2 * nx - wi0 * nz)
        rz -= vi2 + ai * (wi0 * ny - wi1 * nx)
    else:
        rx -= cw0
        ry -= cw1
        rz -= cw2
    vn = rx * nx + ry * ny + rz * nz
    return vn + bias, rx - vn * nx, ry - vn * ny, rz - vn * nz


@njit(inline="always")
def _rolling_velocity(c, cb, cn, cvw, croll, w):
    """R* × the relative angular velocity ω_j − ω_i (a wall: − Ω_w): its tangential part u_r and its
    normal part u_s [m/s]. (Arrays read before any branch, as in :func:`_contact_velocity`.)"""
    i = cb[c, 0]
    j = cb[c, 1]
    ii = i if i >= 0 else 0
    nx = cn[c, 0]
    ny = cn[c, 1]
    nz = cn[c, 2]
    wj0 = w[j, 0]
    wj1 = w[j, 1]
    wj2 = w[j, 2]
    wi0 = w[ii, 0]
    wi1 = w[ii, 1]
    wi2 = w[ii, 2]
    cw3 = cvw[c, 3]
    cw4 = cvw[c, 4]
    cw5 = cvw[c, 5]
    rs = croll[c, 2]
    if i >= 0:
        ox = wj0 - wi0
        oy = wj1 - wi1
        oz = wj2 - wi2
    else:
        ox = wj0 - cw3
        oy = wj1 - cw4
        oz = wj2 - cw5
    on = ox * nx + oy * ny + oz * nz
    return rs * (ox - on * nx), rs * (oy - on * ny), rs * (oz - on * nz), rs * on


@njit(inline="always")
def _residual(g0, g1, g2, g3, u0, u1, u2, u3, b, mu):
    """|γ − Π(γ − B u)| / B: the projected-gradient residual [m/s], and the projected γ_n."""
    p0, p1, p2, p3 = project_cone(g0 - b * u0, g1 - b * u1, g2 - b * u2, g3 - b * u3, mu)
    d0 = g0 - p0
    d1 = g1 - p1
    d2 = g2 - p2
    d3 = g3 - p3
    return math.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3) / b, p0


@njit(inline="always")
def _roll_residual(r0, r1, r2, r3, u4, u5, u6, u7, bn, br, mu_r, mu_s):
    """The rolling rows' residual [m/s]: |ρ − clamp(ρ − B_r u_r)| and |σ − clamp(σ − B_r u_s)| over
    B_r, with the bounds of the projected normal impulse ``bn``; the larger of the two."""
    p4, p5, p6 = clamp_norm(r0 - br * u4, r1 - br * u5, r2 - br * u6, mu_r * bn)
    p7 = clamp_abs(r3 - br * u7, mu_s * bn)
    d4 = r0 - p4
    d5 = r1 - p5
    d6 = r2 - p6
    return max(math.sqrt(d4 * d4 + d5 * d5 + d6 * d6), abs(r3 - p7)) / br


@njit(inline="always")
def _update_roll(c, cb, cn, cvw, croll, gam, w, omega_relax, bn, bn_new):
    """ρ_c, σ_c ← clamp(· − ω B_r u) to the bounds of the new normal impulse ``bn_new`` (Chrono's
    sequential projection: the sliding cone first, then the rolling and spinning bounds). Returns the
    residual of the old values (bounds of ``bn``, the fully projected γ_n) and their changes."""
    u4, u5, u6, u7 = _rolling_velocity(c, cb, cn, cvw, croll, w)
    br = croll[c, 3]
    mu_r = croll[c, 0]
    mu_s = croll[c, 1]
    r0 = gam[c, 4]
    r1 = gam[c, 5]
    r2 = gam[c, 6]
    r3 = gam[c, 7]
    rc = _roll_residual(r0, r1, r2, r3, u4, u5, u6, u7, bn, br, mu_r, mu_s)
    s = omega_relax * br
    n4, n5, n6 = clamp_norm(r0 - s * u4, r1 - s * u5, r2 - s * u6, mu_r * bn_new)
    n7 = clamp_abs(r3 - s * u7, mu_s * bn_new)
    gam[c, 4] = n4
    gam[c, 5] = n5
    gam[c, 6] = n6
    gam[c, 7] = n7
    return rc, n4 - r0, n5 - r1, n6 - r2, n7 - r3


@njit(inline="always")
def _update(c, cb, cn, ca, cvw, cbias, cmu, cscale, blk, gam, v, w, omega_relax, corrected, want_res=True):
    """γ_c ← Π_K(γ_c − ω B_c u_c) from the current velocities (ũ_c when ``corrected``); returns the
    residual of the old γ_c, the fully projected γ_n (the rolling rows' bound in the residual) and
    the old and new impulses. Without ``want_res`` the residual is not formed (0, and γ_n for the
    bound). ``blk[:, c]`` = (B_n, B_t, μρ) of the update (:func:`block_columns`; (B, B, μ) for the
    trace scaling); the residual always uses B = ``cscale[c]``."""
    u0, u1, u2, u3 = _contact_velocity(c, cb, cn, ca, cvw, cbias, v, w)
    b = cscale[c]
    mu = cmu[c]
    if corrected:
        u0 += mu * math.sqrt(u1 * u1 + u2 * u2 + u3 * u3)
    g0 = gam[c, 0]
    g1 = gam[c, 1]
    g2 = gam[c, 2]
    g3 = gam[c, 3]
    if want_res:
        rc, p0 = _residual(g0, g1, g2, g3, u0, u1, u2, u3, b, mu)
    else:
        rc = 0.0
        p0 = g0
    sn = omega_relax * blk[0, c]
    st = omega_relax * blk[1, c]
    n0, n1, n2, n3 = project_cone_weighted(g0 - sn * u0, g1 - st * u1, g2 - st * u2, g3 - st * u3, mu,
                                           blk[2, c])  # fmt: skip
    gam[c, 0] = n0
    gam[c, 1] = n1
    gam[c, 2] = n2
    gam[c, 3] = n3
    return rc, p0, g0, g1, g2, g3, n0, n1, n2, n3


# ---------------------------------------------------------------------------------------------
# Projected Jacobi in three passes. Every contact is updated from the same velocities, so the sweep
# splits into a gather (u of every contact from its two bodies), a projection that touches each
# contact's own data only, and a scatter of the new impulses onto the bodies. The middle pass runs
# on columns (``U``, ``G``: one row per impulse component, one column per contact) and without
# branches, so LLVM vectorizes it (4 contacts per instruction on AVX2): it was a third of the fused
# sweep's time, almost all of it in square roots and divisions. The arithmetic is the fused sweep's,
# operation for operation (the same bits; tests/test_dem_c_kernels.py). The residual a checked sweep
# forms decides only when the sweep stops: it is formed with fewer divisions and square roots (its
# square, from 1/B, and the cone projection with one division), equal to the fused sweep's within
# rounding, not bit for bit.


@njit(inline="always")
def _cone_select(gn, tx, ty, tz, mu, murho):
    """:func:`project_cone_weighted` computed on every path and selected: the same values bit for
    bit (t = 0 gives s = inf or nan, never selected), but no branch, so a loop over it vectorizes."""
    t = math.sqrt(tx * tx + ty * ty + tz * tz)
    gn2 = (murho * t + gn) / (mu * murho + 1.0)
    return _cone_pick(gn, tx, ty, tz, mu, murho, t, gn2, mu * gn2 / t)


@njit(inline="always")
def _cone_pick(gn, tx, ty, tz, mu, murho, t, gn2, s):
    """The projection onto the cone chosen among its three cases without branches: (γ_n, γ_t)
    inside, the origin, or (gn2, s γ_t) on the surface (``t`` = |γ_t|; gn2 and s are not used
    unless that case is chosen, so t = 0's inf or nan never shows)."""
    inside = t <= mu * gn
    zero = murho * t <= -gn
    o0 = gn if inside else (0.0 if zero else gn2)
    o1 = tx if inside else (0.0 if zero else tx * s)
    o2 = ty if inside else (0.0 if zero else ty * s)
    o3 = tz if inside else (0.0 if zero else tz * s)
    if mu <= 0.0:
        o0 = max(gn, 0.0)
        o1 = 0.0
        o2 = 0.0
        o3 = 0.0
    return o0, o1, o2, o3


@njit(inline="always")
def _cone_select_residual(gn, tx, ty, tz, mu):
    """:func:`_cone_select` with one division instead of two (q = 1 / ((μ² + 1) t) gives both the
    projected γ_n and the scale of γ_t): the same projection within rounding, for residuals only
    (a Jacobi sweep's impulses use :func:`_cone_select`, bit for bit the fused sweep's)."""
    t = math.sqrt(tx * tx + ty * ty + tz * tz)
    a = mu * t + gn
    q = 1.0 / ((mu * mu + 1.0) * t)
    return _cone_pick(gn, tx, ty, tz, mu, mu, t, a * t * q, mu * a * q)


@njit(inline="always")
def _clamp_norm_select(x, y, z, bound):
    """:func:`clamp_norm` without branches (the same values)."""
    t = math.sqrt(x * x + y * y + z * z)
    s = bound / t
    keep = t <= bound
    zero = bound <= 0.0
    ox = x if keep else (0.0 if zero else x * s)
    oy = y if keep else (0.0 if zero else y * s)
    oz = z if keep else (0.0 if zero else z * s)
    return ox, oy, oz


@njit
def jacobi_gather(cb, cn, ca, cvw, cbias, croll, v, w, nc, U):
    """Jacobi pass 1: u = Dᵀv + b of every contact into column c of ``U`` (rows u_n, u_t; with 8
    rows also the rolling rows' u_r, u_s, zero where R* = 0)."""
    roll = U.shape[0] == 8
    for c in range(nc):
        u0, u1, u2, u3 = _contact_velocity(c, cb, cn, ca, cvw, cbias, v, w)
        U[0, c] = u0
        U[1, c] = u1
        U[2, c] = u2
        U[3, c] = u3
        if roll:
            U[4, c], U[5, c], U[6, c], U[7, c] = _rolling_velocity(c, cb, cn, cvw, croll, w)


@njit(inline="always")
def _project_values(u0, u1, u2, u3, g0, g1, g2, g3, b, ib, mu, bn, bt, murho, omega_relax, corrected,
                    want_res):  # fmt: skip
    """One column of :func:`jacobi_project` on scalars: the new (γ_n, γ_t), the **square** of the
    residual of the old (|γ − Π(γ − B u)|² (1/B)², 0 without ``want_res``; ``ib`` = 1/B) and its
    fully projected γ_n (the old γ_n without). The update steps by (``bn``, ``bt``) and projects with
    ``murho`` (:func:`project_cone_weighted`); the residual uses ``b``. Scalars only: an inlined
    helper that takes arrays kept numba's reference counting in the loop, which stopped LLVM from
    vectorizing it."""
    if corrected:
        u0 += mu * math.sqrt(u1 * u1 + u2 * u2 + u3 * u3)
    rc = 0.0
    p0 = g0
    if want_res:
        p0, p1, p2, p3 = _cone_select_residual(g0 - b * u0, g1 - b * u1, g2 - b * u2, g3 - b * u3, mu)
        d0 = g0 - p0
        d1 = g1 - p1
        d2 = g2 - p2
        d3 = g3 - p3
        rc = (d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3) * (ib * ib)
    sn = omega_relax * bn
    st = omega_relax * bt
    n0, n1, n2, n3 = _cone_select(g0 - sn * u0, g1 - st * u1, g2 - st * u2, g3 - st * u3, mu, murho)
    return n0, n1, n2, n3, rc, p0


@njit
def jacobi_columns(cscale, croll, nc, roll):
    """What :func:`jacobi_project` reads besides the impulses, formed once per solve: 1/B of every
    contact (``IB``) and, with ``roll``, the rolling rows' (μ_r, μ_s, R*, B_r, 1/B_r) in columns
    (``CR``; empty without). 1/B_r is not used where R* = 0."""
    IB = np.empty(nc)
    for c in range(nc):
        IB[c] = 1.0 / cscale[c]
    CR = np.empty((5, nc if roll else 0))
    if roll:
        for c in range(nc):
            for k in range(4):
                CR[k, c] = croll[c, k]
            br = croll[c, 3]
            CR[4, c] = 1.0 / br if br != 0.0 else 0.0
    return IB, CR


@njit
def block_columns(cb, ca, cmu, cscale, inv_m, inv_i, nc, block):
    """The update's scaling of every contact in columns, (B_n, B_t, μρ) (:func:`jacobi_project`,
    :func:`gauss_seidel_sweep`). ``block``: the inverses of the diagonal of the contact's Delassus
    block, which for spheres is diagonal in the contact frame: D_n = m_i⁻¹ + m_j⁻¹ normally and
    D_t = D_n + a_i² I_i⁻¹ + a_j² I_j⁻¹ tangentially (the levers turn the bodies), so B_n = 1/D_n,
    B_t = 1/D_t and ρ = B_n/B_t = D_t/D_n; the projection then works in B⁻¹'s metric
    (:func:`project_cone_weighted`). Otherwise the trace scaling: B = ``cscale`` = 3/tr(D) on every
    row, ρ = 1."""
    BLK = np.empty((3, nc))
    if not block:
        for c in range(nc):
            BLK[0, c] = cscale[c]
            BLK[1, c] = cscale[c]
            BLK[2, c] = cmu[c]
        return BLK
    for c in range(nc):
        i = cb[c, 0]
        j = cb[c, 1]
        ai = ca[c, 0]
        aj = ca[c, 1]
        mi = inv_m[i] if i >= 0 else 0.0
        ii = inv_i[i] if i >= 0 else 0.0
        dn = mi + inv_m[j]
        dt = dn + ai * ai * ii + aj * aj * inv_i[j]
        BLK[0, c] = 1.0 / dn
        BLK[1, c] = 1.0 / dt
        BLK[2, c] = cmu[c] * (dt / dn)
    return BLK


@njit
def jacobi_project(U, G, cmu, cscale, IB, BLK, CR, nc, omega_relax, corrected, want_res, RES):
    """Jacobi pass 2: γ_c ← Π_K(γ_c − ω B_c u_c) for every column (ũ when ``corrected``), then the
    rolling rows clamped to the bounds of the new γ_n (Chrono's order), as :func:`_update` and
    :func:`_update_roll`. With ``want_res``, ``RES[c]`` = the **square** of the residual of the old
    impulses (the residual is the square root of their maximum, :func:`max_nonneg`; equal to
    :func:`_update`'s within rounding). ``IB``: 1/B of every contact. ``U`` is overwritten. ``CR``:
    the rows' ``croll`` in columns, and 1/B_r in a fifth row (read only with rolling rows, G of 8
    rows). ``BLK``: the update's (B_n, B_t, μρ) in columns (:func:`block_columns`). (One loop per
    case, its flags constant, so that each vectorizes.)"""
    u0a, u1a, u2a, u3a = U[0], U[1], U[2], U[3]
    g0a, g1a, g2a, g3a = G[0], G[1], G[2], G[3]
    bna, bta, mra = BLK[0], BLK[1], BLK[2]
    o = omega_relax
    if not want_res:
        if corrected:
            for c in range(nc):
                g0a[c], g1a[c], g2a[c], g3a[c], _r, _p = _project_values(
                    u0a[c], u1a[c], u2a[c], u3a[c], g0a[c], g1a[c], g2a[c], g3a[c], cscale[c], IB[c], cmu[c],
                    bna[c], bta[c], mra[c], o, True, False,
                )  # fmt: skip
        else:
            for c in range(nc):
                g0a[c], g1a[c], g2a[c], g3a[c], _r, _p = _project_values(
                    u0a[c], u1a[c], u2a[c], u3a[c], g0a[c], g1a[c], g2a[c], g3a[c], cscale[c], IB[c], cmu[c],
                    bna[c], bta[c], mra[c], o, False, False,
                )  # fmt: skip
    elif corrected:
        for c in range(nc):
            g0a[c], g1a[c], g2a[c], g3a[c], RES[c], u0a[c] = _project_values(
                u0a[c], u1a[c], u2a[c], u3a[c], g0a[c], g1a[c], g2a[c], g3a[c], cscale[c], IB[c], cmu[c],
                bna[c], bta[c], mra[c], o, True, True,
            )  # fmt: skip
    else:
        for c in range(nc):
            g0a[c], g1a[c], g2a[c], g3a[c], RES[c], u0a[c] = _project_values(
                u0a[c], u1a[c], u2a[c], u3a[c], g0a[c], g1a[c], g2a[c], g3a[c], cscale[c], IB[c], cmu[c],
                bna[c], bta[c], mra[c], o, False, True,
            )  # fmt: skip
    if G.shape[0] == 8:
        _jacobi_project_roll(U, G, CR, nc, omega_relax, want_res, RES)


@njit(inline="always")
def _clamp_abs_select(x, bound):
    """:func:`clamp_abs` as selects (the same values)."""
    return bound if x > bound else (-bound if x < -bound else x)


@njit(inline="always")
def _roll_values(r0, r1, r2, r3, u4, u5, u6, u7, bn, bn_new, br, ibr, mu_r, mu_s, rs, omega_relax, want_res,
                 rc):
    """One contact's rolling rows in :func:`jacobi_project`, on scalars and without branches: the
    new (ρ, σ) (unchanged where R* = 0; the arithmetic of :func:`_update_roll`) and the squared
    residual ``rc`` raised to the square of the rolling rows' (:func:`_roll_residual`'s within
    rounding; ``ibr`` = 1/B_r)."""
    s = omega_relax * br
    n4, n5, n6 = _clamp_norm_select(r0 - s * u4, r1 - s * u5, r2 - s * u6, mu_r * bn_new)
    n7 = _clamp_abs_select(r3 - s * u7, mu_s * bn_new)
    on = rs > 0.0
    if want_res:
        p4, p5, p6 = _clamp_norm_select(r0 - br * u4, r1 - br * u5, r2 - br * u6, mu_r * bn)
        p7 = _clamp_abs_select(r3 - br * u7, mu_s * bn)
        d4 = r0 - p4
        d5 = r1 - p5
        d6 = r2 - p6
        d7 = r3 - p7
        rr = max(d4 * d4 + d5 * d5 + d6 * d6, d7 * d7) * (ibr * ibr)
        rc = rr if (on & ((rr > rc) | (rr != rr))) else rc
    return (n4 if on else r0), (n5 if on else r1), (n6 if on else r2), (n7 if on else r3), rc


@njit
def _jacobi_project_roll(U, G, CR, nc, omega_relax, want_res, RES):
    """The rolling rows of :func:`jacobi_project` (after the sliding cone: the bounds are the new
    γ_n, in ``G[0]``, and for the residual the fully projected old one, left in ``U[0]`` by a
    checked sweep). ``CR``: the contacts' (μ_r, μ_s, R*, B_r, 1/B_r) in columns. Branch-free, one
    loop per case: vectorized."""
    bn_, bnew_, u4_, u5_, u6_, u7_ = U[0], G[0], U[4], U[5], U[6], U[7]
    r0_, r1_, r2_, r3_ = G[4], G[5], G[6], G[7]
    mr_, ms_, rs_, br_, ibr_ = CR[0], CR[1], CR[2], CR[3], CR[4]
    o = omega_relax
    if want_res:
        for c in range(nc):
            r0_[c], r1_[c], r2_[c], r3_[c], RES[c] = _roll_values(
                r0_[c], r1_[c], r2_[c], r3_[c], u4_[c], u5_[c], u6_[c], u7_[c], bn_[c], bnew_[c], br_[c],
                ibr_[c], mr_[c], ms_[c], rs_[c], o, True, RES[c],
            )  # fmt: skip
    else:
        for c in range(nc):
            r0_[c], r1_[c], r2_[c], r3_[c], _rc = _roll_values(
                r0_[c], r1_[c], r2_[c], r3_[c], u4_[c], u5_[c], u6_[c], u7_[c], bn_[c], bnew_[c], br_[c],
                ibr_[c], mr_[c], ms_[c], rs_[c], o, False, 0.0,
            )  # fmt: skip


@njit
def max_nonneg(x, n):
    """max of x[:n], values ≥ 0 or nan (nan if any is): the largest bit pattern with the sign
    cleared, an integer maximum that vectorizes (a float one does not without fastmath)."""
    bits = x[:n].view(np.int64)
    m = 0
    for c in range(n):
        m = max(m, bits[c] & 0x7FFFFFFFFFFFFFFF)
    out = np.empty(1, np.int64)
    out[0] = m
    return out.view(np.float64)[0]


@njit
def accumulate_columns(cb, cn, ca, croll, G, nc, P, L):
    """Jacobi pass 3: :func:`accumulate` of impulses held in columns (``G``: 4 or 8 rows).

    A contact whose impulses are all zero (±0.0) is skipped: its terms are ±0.0, and adding ±0.0
    to a sum that started at +0.0 never changes it (such a sum is never −0.0: x + y = −0.0 only for
    x = y = −0.0 in round-to-nearest), so the bits are :func:`accumulate`'s. About half the rows of
    the hopper's problems are zero (pairs within the envelope that do not touch)."""
    P[:] = 0.0
    L[:] = 0.0
    o = G.shape[0] - 4  # rows of 4: the rolling impulses read rows 0-3, unused (R* = 0)
    for c in range(nc):
        if G[0, c] == 0.0 and G[1, c] == 0.0 and G[2, c] == 0.0 and G[3, c] == 0.0:
            if o == 0 or (G[4, c] == 0.0 and G[5, c] == 0.0 and G[6, c] == 0.0 and G[7, c] == 0.0):
                continue
        _accumulate_impulse(
            cb[c, 0], cb[c, 1], cn[c, 0], cn[c, 1], cn[c, 2], ca[c, 0], ca[c, 1], croll[c, 2],
            G[0, c], G[1, c], G[2, c], G[3, c], G[o, c], G[o + 1, c], G[o + 2, c], G[o + 3, c], P, L,
        )  # fmt: skip


@njit
def jacobi_solve(cb, cn, ca, cvw, cbias, croll, cmu, cscale, IB, BLK, CR, G, U, RES, P, L, v, w, v_free,
                 w_free, inv_m, inv_i, dof, n, nc, omega_relax, corrected, check_every, max_iterations,
                 tolerance):  # fmt: skip
    """The Jacobi sweeps of a step in one call, for a run whose velocities need no forwarding (one
    rank, no periodic images, no rigid bodies): the loop of ``Stepper._jacobi`` (gather, project,
    scatter, velocities; the residual of the impulses before sweeps 1, k + 1, …), the same kernels
    in the same order, without returning to Python between sweeps (~10 µs a sweep). Returns
    (sweeps, residual of the last checked sweep or inf)."""
    it = 0
    res = math.inf
    while it < max_iterations:
        check = it % check_every == 0
        jacobi_gather(cb, cn, ca, cvw, cbias, croll, v, w, nc, U)
        jacobi_project(U, G, cmu, cscale, IB, BLK, CR, nc, omega_relax, corrected, check, RES)
        accumulate_columns(cb, cn, ca, croll, G, nc, P, L)
        it += 1
        velocities(v, w, v_free, w_free, P, L, inv_m, inv_i, dof, n)
        if check:
            res = math.sqrt(max_nonneg(RES, nc))
            if res <= tolerance:
                break
    return it, res


@njit
def gauss_seidel_sweep(
    cb, cn, ca, cvw, cbias, cmu, cscale, blk, croll, gam, v, w, inv_m, inv_i, dof, nc, omega_relax,
    corrected=True,
):  # fmt: skip
    """One projected Gauss–Seidel sweep in row order, velocities updated after each contact
    (``corrected`` and ``blk`` as in :func:`_update`). Returns the largest residual met during the
    sweep."""
    res = 0.0
    for c in range(nc):
        rc, p0, g0, g1, g2, g3, n0, n1, n2, n3 = _update(
            c, cb, cn, ca, cvw, cbias, cmu, cscale, blk, gam, v, w, omega_relax, corrected
        )
        d4 = d5 = d6 = d7 = 0.0
        if croll[c, 2] > 0.0:
            rr, d4, d5, d6, d7 = _update_roll(c, cb, cn, cvw, croll, gam, w, omega_relax, p0, n0)
            if rr > rc or rr != rr:
                rc = rr
        if rc > res or rc != rc:
            res = rc
        # apply the change at once
        nx = cn[c, 0]
        ny = cn[c, 1]
        nz = cn[c, 2]
        dn = n0 - g0
        gx = dn * nx + (n1 - g1)
        gy = dn * ny + (n2 - g2)
        gz = dn * nz + (n3 - g3)
        cx = ny * gz - nz * gy
        cy = nz * gx - nx * gz
        cz = nx * gy - ny * gx
        rs = croll[c, 2]
        mx = rs * (d4 + d7 * nx)
        my = rs * (d5 + d7 * ny)
        mz = rs * (d6 + d7 * nz)
        i = cb[c, 0]
        j = cb[c, 1]
        aj = ca[c, 1]
        v[j, 0] += inv_m[j] * gx
        v[j, 1] += inv_m[j] * gy
        v[j, 2] += inv_m[j] * gz
        w[j, 0] -= inv_i[j] * (aj * cx - mx)
        w[j, 1] -= inv_i[j] * (aj * cy - my)
        w[j, 2] -= inv_i[j] * (aj * cz - mz)
        _lock(v, w, dof, j)
        if i >= 0:
            ai = ca[c, 0]
            v[i, 0] -= inv_m[i] * gx
            v[i, 1] -= inv_m[i] * gy
            v[i, 2] -= inv_m[i] * gz
            w[i, 0] -= inv_i[i] * (ai * cx + mx)
            w[i, 1] -= inv_i[i] * (ai * cy + my)
            w[i, 2] -= inv_i[i] * (ai * cz + mz)
            _lock(v, w, dof, i)
    return res


@njit
def body_impulse_partials(cb, cn, gam, nc, body):
    """Exact partials (as :func:`pdem.parallel.exact.dot_partials`) of the three components of
    Σ (γ_n n + γ_t) over this rank's contacts with the rigid body ``body`` (rows whose first index is
    ``body``), and their plain sums of non-finite terms: the impulse the body's contacts give the
    grains, −(the impulse on the body)."""
    ax, bx, ix = exact_accumulator()
    ay, by, iy = exact_accumulator()
    az, bz, iz = exact_accumulator()
    spx = 0.0
    spy = 0.0
    spz = 0.0
    for c in range(nc):
        if cb[c, 0] != body:
            continue
        spx += exact_add(ax, bx, ix, gam[c, 0] * cn[c, 0] + gam[c, 1])
        spy += exact_add(ay, by, iy, gam[c, 0] * cn[c, 1] + gam[c, 2])
        spz += exact_add(az, bz, iz, gam[c, 0] * cn[c, 2] + gam[c, 3])
    return exact_partials(ax), spx, exact_partials(ay), spy, exact_partials(az), spz


@njit
def wall_load_partials(G, cn, wrows, wk, nwalls):
    """Exact partials of every wall's load Σ (γ_n n + γ_t) over the rows ``wrows`` (``wk[q]``: the
    wall of row ``wrows[q]``), from the impulses in columns ``G`` (G[k, c]): row 3 k + d of the first
    result holds component d of wall k's sum as exact doubles, their number in the row's last entry;
    the second the plain sums of its non-finite terms (APGD's ``load_tolerance``)."""
    nr = 3 * nwalls
    acc, buf, bits = exact_accumulator()
    parts = np.zeros((nr, acc.shape[0] + 1))  # no more digits than the accumulator has, and the count
    special = np.zeros(nr)
    for r in range(nr):
        k = r // 3
        d = r % 3
        acc[:] = 0
        for q in range(wrows.shape[0]):
            if wk[q] == k:
                c = wrows[q]
                special[r] += exact_add(acc, buf, bits, G[0, c] * cn[c, d] + G[1 + d, c])
        digits = exact_partials(acc)
        parts[r, : digits.shape[0]] = digits
        parts[r, -1] = digits.shape[0]
    return parts, special


@njit
def contact_velocities_raw(cb, cn, ca, cvw, cbias, croll, cmu, v, w, nc, uraw, u, corrected):
    """u = Dᵀ v + b for every contact into ``uraw`` and, with ``corrected``, ũ (u_n + μ_c |u_t|) into
    ``u``, in one pass (``u`` may be ``uraw``: then it ends as ũ). Rows of 8 or of 4 (no rolling)."""
    width = uraw.shape[1]
    for c in range(nc):
        u0, u1, u2, u3 = _contact_velocity(c, cb, cn, ca, cvw, cbias, v, w)
        uraw[c, 0] = u0
        uraw[c, 1] = u1
        uraw[c, 2] = u2
        uraw[c, 3] = u3
        if croll[c, 2] > 0.0:
            uraw[c, 4], uraw[c, 5], uraw[c, 6], uraw[c, 7] = _rolling_velocity(c, cb, cn, cvw, croll, w)
        else:
            for k in range(4, width):
                uraw[c, k] = 0.0
        if corrected:
            u[c, 0] = u0 + cmu[c] * math.sqrt(u1 * u1 + u2 * u2 + u3 * u3)
            for k in range(1, width):
                u[c, k] = uraw[c, k]


# ---------------------------------------------------------------- APGD on columns
# APGD's iterates, like Jacobi's, are held in columns: array[k, c] is component k of contact c
# (``G``: 4 rows, or 8 with rolling rows), so that each pass streams through whole rows and the
# elementwise ones vectorize (the same arithmetic per contact as the row layout it replaced, bit
# for bit at commit 6cc2c53, tests/test_dem_c_kernels.py). The corrected cone's ũ differs from u in its
# normal row only: it is kept as u in columns (``U``) plus the corrected normal row (``UN``, ``U[0]``
# itself for the relaxed cone).


@njit
def apgd_gather(cb, cn, ca, cvw, cbias, croll, cmu, v, w, nc, U, UN, corrected, GN, Y, GY, GYN, D1, trial):
    """u = Dᵀv + b of every contact into the columns of ``U`` (as :func:`jacobi_gather`; with 8
    rows, 0.0 in the rolling rows of a contact without rolling friction) and, with ``corrected``,
    ũ_n = u_n + μ_c |u_t| into ``UN``. ``U`` holds u(γ) for γ = ``GN``.

    In the same pass, while the contact's velocities are at hand (one pass less over the columns:
    APGD's passes are bound by memory traffic, not arithmetic), with ``trial`` the first dot
    product of a line-search trial, (γ − y)·(ũ(γ) − ũ(y)), into ``D1[c]`` (ũ(y): ``GY`` with normal
    row ``GYN``; formed in double in component order, rolling rows only where the contact has them,
    as :func:`apgd_project_step` forms the other two). (The residual is a pass of its own,
    :func:`apgd_residual`: formed here, its branches cost twice the gather.)"""
    roll = U.shape[0] == 8
    for c in range(nc):
        u0, u1, u2, u3 = _contact_velocity(c, cb, cn, ca, cvw, cbias, v, w)
        U[0, c] = u0
        U[1, c] = u1
        U[2, c] = u2
        U[3, c] = u3
        un = u0
        if corrected:
            un = u0 + cmu[c] * math.sqrt(u1 * u1 + u2 * u2 + u3 * u3)
            UN[c] = un
        rolling = roll and croll[c, 2] > 0.0
        if roll:
            if rolling:
                U[4, c], U[5, c], U[6, c], U[7, c] = _rolling_velocity(c, cb, cn, cvw, croll, w)
            else:
                U[4, c] = 0.0
                U[5, c] = 0.0
                U[6, c] = 0.0
                U[7, c] = 0.0
        if trial:
            d1 = 0.0
            d1 += (GN[0, c] - Y[0, c]) * (un - GYN[c])
            d1 += (GN[1, c] - Y[1, c]) * (u1 - GY[1, c])
            d1 += (GN[2, c] - Y[2, c]) * (u2 - GY[2, c])
            d1 += (GN[3, c] - Y[3, c]) * (u3 - GY[3, c])
            if rolling:
                for k in range(4, 8):
                    d1 += (GN[k, c] - Y[k, c]) * (U[k, c] - GY[k, c])
            D1[c] = d1


@njit
def apgd_residual(G, U, UN, cmu, cscale, croll, nc, RES):
    """max over contacts of |γ − Π(γ − B ũ)| / B and the rolling rows' residual, on columns (ũ's
    normal row from ``UN``; ``_residual`` and ``_roll_residual`` per contact). Rows of 4 take a loop
    without branches (``_cone_select`` gives ``project_cone``'s bits) that writes each contact's
    residual into ``RES``, then its maximum (NaN if any is NaN)."""
    if G.shape[0] == 4:
        for c in range(nc):
            b = cscale[c]
            g0 = G[0, c]
            g1 = G[1, c]
            g2 = G[2, c]
            g3 = G[3, c]
            p0, p1, p2, p3 = _cone_select(
                g0 - b * UN[c], g1 - b * U[1, c], g2 - b * U[2, c], g3 - b * U[3, c], cmu[c], cmu[c]
            )
            d0 = g0 - p0
            d1 = g1 - p1
            d2 = g2 - p2
            d3 = g3 - p3
            RES[c] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2 + d3 * d3) / b
        return max_nonneg(RES, nc)
    res = 0.0
    for c in range(nc):
        rc, p0 = _residual(G[0, c], G[1, c], G[2, c], G[3, c], UN[c], U[1, c], U[2, c], U[3, c], cscale[c],
                           cmu[c])  # fmt: skip
        if croll[c, 2] > 0.0:
            rr = _roll_residual(G[4, c], G[5, c], G[6, c], G[7, c], U[4, c], U[5, c], U[6, c], U[7, c], p0,
                                croll[c, 3], croll[c, 0], croll[c, 1])  # fmt: skip
            if rr > rc or rr != rr:
                rc = rr
        if rc > res or rc != rc:
            res = rc
    return res


@njit
def apgd_project_step(Y, GY, GYN, GK, t, mu, croll, nc, OUT, D2, D3, trial, BLK, scaled):
    """OUT = Π(Y − t ũ(Y)) contact by contact (APGD's projected gradient step; ũ's normal row from
    ``GYN``, its others from ``GY``): each cone first, then the rolling rows clamped to the bounds of
    the new γ_n (:func:`project_cone_array`'s order). Rows of 4 take a loop without branches
    (:func:`_cone_select`, the same values).

    With ``trial``, in the same pass, two of the trial's dot products per contact (formed in double
    in component order, the rolling rows only where the contact has them): |γ − y|² into ``D2`` and
    ũ(y)·(γ − γ_k) into ``D3`` (γ_k: ``GK``).

    ``scaled``: the step preconditioned by the contacts' blocks (``BLK`` = (B_n, B_t, μρ) in columns,
    :func:`block_columns`; the rolling rows by B_r): OUT = Π_M(Y − t B ũ(Y)) in the metric
    M = B⁻¹ (:func:`project_cone_weighted`), and |γ − y|² measured in M. This is APGD on the
    variables B^-½ γ, whose cones are the contacts' scaled cones."""
    if scaled:
        _apgd_project_step_scaled(Y, GY, GYN, GK, t, mu, croll, nc, OUT, D2, D3, trial, BLK)
        return
    if OUT.shape[0] == 4:
        for c in range(nc):
            yn = GYN[c]
            o0, o1, o2, o3 = _cone_select(
                Y[0, c] - t * yn, Y[1, c] - t * GY[1, c], Y[2, c] - t * GY[2, c], Y[3, c] - t * GY[3, c],
                mu[c], mu[c],
            )  # fmt: skip
            OUT[0, c] = o0
            OUT[1, c] = o1
            OUT[2, c] = o2
            OUT[3, c] = o3
            if trial:
                s0 = o0 - Y[0, c]
                s1 = o1 - Y[1, c]
                s2 = o2 - Y[2, c]
                s3 = o3 - Y[3, c]
                d2 = 0.0
                d2 += s0 * s0
                d2 += s1 * s1
                d2 += s2 * s2
                d2 += s3 * s3
                d3 = 0.0
                d3 += yn * (o0 - GK[0, c])
                d3 += GY[1, c] * (o1 - GK[1, c])
                d3 += GY[2, c] * (o2 - GK[2, c])
                d3 += GY[3, c] * (o3 - GK[3, c])
                D2[c] = d2
                D3[c] = d3
        return
    for c in range(nc):
        yn = GYN[c]
        n0, n1, n2, n3 = project_cone(
            Y[0, c] - t * yn, Y[1, c] - t * GY[1, c], Y[2, c] - t * GY[2, c], Y[3, c] - t * GY[3, c], mu[c]
        )
        OUT[0, c] = n0
        OUT[1, c] = n1
        OUT[2, c] = n2
        OUT[3, c] = n3
        rolling = croll[c, 2] > 0.0
        _apgd_roll_step(Y, GY, OUT, c, t, croll, n0, rolling)
        if trial:
            s = n0 - Y[0, c]
            d2 = 0.0 + s * s
            d3 = 0.0 + yn * (n0 - GK[0, c])
            for k in range(1, 8 if rolling else 4):
                s = OUT[k, c] - Y[k, c]
                d2 += s * s
                d3 += GY[k, c] * (OUT[k, c] - GK[k, c])
            D2[c] = d2
            D3[c] = d3


@njit(inline="always")
def _apgd_roll_step(Y, GY, OUT, c, tr, croll, n0, rolling):
    """The rolling rows of APGD's projected step for contact ``c``: ρ, σ − ``tr`` ũ clamped to the
    bounds of the new γ_n ``n0`` (zero where the contact has none)."""
    if rolling:
        r4 = Y[4, c] - tr * GY[4, c]
        r5 = Y[5, c] - tr * GY[5, c]
        r6 = Y[6, c] - tr * GY[6, c]
        OUT[4, c], OUT[5, c], OUT[6, c] = clamp_norm(r4, r5, r6, croll[c, 0] * n0)
        OUT[7, c] = clamp_abs(Y[7, c] - tr * GY[7, c], croll[c, 1] * n0)
    else:
        OUT[4, c] = 0.0
        OUT[5, c] = 0.0
        OUT[6, c] = 0.0
        OUT[7, c] = 0.0


@njit
def _apgd_project_step_scaled(Y, GY, GYN, GK, t, mu, croll, nc, OUT, D2, D3, trial, BLK):
    """:func:`apgd_project_step` with ``scaled``."""
    width = OUT.shape[0]
    for c in range(nc):
        yn = GYN[c]
        bn = BLK[0, c]
        bt = BLK[1, c]
        tn = t * bn
        tt = t * bt
        n0, n1, n2, n3 = _cone_select(
            Y[0, c] - tn * yn, Y[1, c] - tt * GY[1, c], Y[2, c] - tt * GY[2, c], Y[3, c] - tt * GY[3, c],
            mu[c], BLK[2, c],
        )  # fmt: skip
        OUT[0, c] = n0
        OUT[1, c] = n1
        OUT[2, c] = n2
        OUT[3, c] = n3
        rolling = width == 8 and croll[c, 2] > 0.0
        if width == 8:
            _apgd_roll_step(Y, GY, OUT, c, t * croll[c, 3], croll, n0, rolling)
        if trial:
            s0 = n0 - Y[0, c]
            s1 = n1 - Y[1, c]
            s2 = n2 - Y[2, c]
            s3 = n3 - Y[3, c]
            d2 = s0 * s0 / bn + (s1 * s1 + s2 * s2 + s3 * s3) / bt
            d3 = 0.0 + yn * (n0 - GK[0, c])
            d3 += GY[1, c] * (n1 - GK[1, c])
            d3 += GY[2, c] * (n2 - GK[2, c])
            d3 += GY[3, c] * (n3 - GK[3, c])
            if rolling:
                sr = 0.0
                for k in range(4, 8):
                    s = OUT[k, c] - Y[k, c]
                    sr += s * s
                    d3 += GY[k, c] * (OUT[k, c] - GK[k, c])
                d2 += sr / croll[c, 3]
            D2[c] = d2
            D3[c] = d3


_TRIAL_BLOCK = 500  # terms gathered per exact_add_many call when only some rows count


@njit
def apgd_trial_sums(D1, D2, D3, rows, all_rows, nc):
    """Exact partials (as :func:`pdem.parallel.exact.dot_partials`) of the sums over ``rows`` (every
    contact with ``all_rows``) of a line-search trial's three per-contact dot products: D1 from
    :func:`apgd_gather`, D2 and D3 from :func:`apgd_project_step`. Each is formed in double per
    contact; the sums are exact (:func:`pdem.parallel.exact.exact_add_many`, a bin per exponent), so
    they do not depend on how the contacts are split over ranks."""
    a1 = exact_accumulator()[0]  # exact_add_many needs only the digits, not the scratch
    a2 = exact_accumulator()[0]
    a3 = exact_accumulator()[0]
    bins = exact_bins()
    sp1 = 0.0
    sp2 = 0.0
    sp3 = 0.0
    nr = nc if all_rows else rows.shape[0]
    B = np.empty((3, _TRIAL_BLOCK))
    for q0 in range(0, nr, _TRIAL_BLOCK):
        m = min(_TRIAL_BLOCK, nr - q0)
        if all_rows:
            sp1 += exact_add_many(a1, bins, D1[q0 : q0 + m], m)
            sp2 += exact_add_many(a2, bins, D2[q0 : q0 + m], m)
            sp3 += exact_add_many(a3, bins, D3[q0 : q0 + m], m)
        else:
            for q in range(m):
                c = rows[q0 + q]
                B[0, q] = D1[c]
                B[1, q] = D2[c]
                B[2, q] = D3[c]
            sp1 += exact_add_many(a1, bins, B[0], m)
            sp2 += exact_add_many(a2, bins, B[1], m)
            sp3 += exact_add_many(a3, bins, B[2], m)
    return exact_partials(a1), sp1, exact_partials(a2), sp2, exact_partials(a3), sp3


@njit
def apgd_extrapolate(GN, GK, beta, nc, OUT):
    """OUT = γ + β (γ − γ_k) on columns (APGD's momentum step)."""
    for k in range(GN.shape[0]):
        a = GN[k]
        b = GK[k]
        o = OUT[k]
        for c in range(nc):
            o[c] = a[c] + beta * (a[c] - b[c])


@njit
def apgd_extrapolate_velocities(UN, UK, beta, cmu, nc, GY, GYN, corrected):
    """GY = u + β (u − u_k) (u is affine in γ: the velocities of the extrapolated impulses) and,
    with ``corrected``, GYN its ũ_n (u_n + μ|u_t|, as :func:`apgd_gather` forms it)."""
    apgd_extrapolate(UN, UK, beta, nc, GY)
    if corrected:
        a0, a1, a2, a3 = GY[0], GY[1], GY[2], GY[3]
        for c in range(nc):
            GYN[c] = a0[c] + cmu[c] * math.sqrt(a1[c] * a1[c] + a2[c] * a2[c] + a3[c] * a3[c])


@njit
def store_history(gam, csrc, nc, n_pair, hist, whist):
    """Keep each contact's impulses for the next step's warm start (the history keeps 8 per contact;
    rows of 4, without rolling, store zeros for the rest)."""
    hs = hist.shape[1]
    gs = min(hs, gam.shape[1])
    for c in range(nc):
        k = csrc[c, 1]
        if c < n_pair:
            for q in range(gs):
                hist[k, q] = gam[c, q]
            for q in range(gs, hs):
                hist[k, q] = 0.0
        else:
            row = csrc[c, 2]
            for q in range(gs):
                whist[row, q] = gam[c, q]
            for q in range(gs, hs):
                whist[row, q] = 0.0


@njit
def contact_forces(gam, cn, cpt, croll, csrc, nc, n_pair, inv_h, fpair, out_idx, out_val, counts, cstart):
    """Report contact forces: ``fpair[k]`` = force on the higher-id particle of pair k; per wall the
    force on the wall (−G/h) and its torque about the wall's reference point, with the rolling and
    spinning moment on the wall (the DEM-P layout)."""
    fpair[:] = 0.0
    counts[:] = 0
    for c in range(nc):
        gx = (gam[c, 0] * cn[c, 0] + gam[c, 1]) * inv_h
        gy = (gam[c, 0] * cn[c, 1] + gam[c, 2]) * inv_h
        gz = (gam[c, 0] * cn[c, 2] + gam[c, 3]) * inv_h
        if c < n_pair:
            k = csrc[c, 1]
            fpair[k, 0] = gx
            fpair[k, 1] = gy
            fpair[k, 2] = gz
        else:
            if gam[c, 0] == 0.0 and gam[c, 1] == 0.0 and gam[c, 2] == 0.0 and gam[c, 3] == 0.0:
                continue
            wk = csrc[c, 0]
            row = cstart[wk] + counts[wk]
            counts[wk] += 1
            out_idx[row] = csrc[c, 1]
            fx = -gx
            fy = -gy
            fz = -gz
            qx = cpt[c, 0]
            qy = cpt[c, 1]
            qz = cpt[c, 2]
            out_val[row, 0] = fx
            out_val[row, 1] = fy
            out_val[row, 2] = fz
            out_val[row, 3] = qy * fz - qz * fy
            out_val[row, 4] = qz * fx - qx * fz
            out_val[row, 5] = qx * fy - qy * fx
            rs = croll[c, 2]
            if rs > 0.0:  # the moment −R*(ρ + σ n)/h on the wall
                rs *= inv_h
                out_val[row, 3] -= rs * (gam[c, 4] + gam[c, 7] * cn[c, 0])
                out_val[row, 4] -= rs * (gam[c, 5] + gam[c, 7] * cn[c, 1])
                out_val[row, 5] -= rs * (gam[c, 6] + gam[c, 7] * cn[c, 2])


@njit
def free_velocities(v, w, motion, dof, gx, gy, gz, h, n, v_free, w_free):
    """v_free = v + h g for free particles (others keep their velocity); ω_free = ω; locked
    components zero."""
    for i in range(n):
        if motion[i] == 0:
            v_free[i, 0] = v[i, 0] + h * gx
            v_free[i, 1] = v[i, 1] + h * gy
            v_free[i, 2] = v[i, 2] + h * gz
        else:
            v_free[i, 0] = v[i, 0]
            v_free[i, 1] = v[i, 1]
            v_free[i, 2] = v[i, 2]
        w_free[i, 0] = w[i, 0]
        w_free[i, 1] = w[i, 1]
        w_free[i, 2] = w[i, 2]
        if motion[i] == 0:
            _lock(v_free, w_free, dof, i)


@njit
def add_external_impulses(v_free, w_free, f, t, inv_m, inv_i, motion, dof, h, n):
    """v_free += h f/m, ω_free += h τ/I for free particles (external forces of boundaries)."""
    for i in range(n):
        if motion[i] == 0:
            for d in range(3):
                v_free[i, d] += h * f[i, d] * inv_m[i]
                w_free[i, d] += h * t[i, d] * inv_i[i]
            _lock(v_free, w_free, dof, i)


@njit
def finish_step(x, v, w, f, t, P, L, mass, motion, gx, gy, gz, inv_h, h, n, snap):
    """x += h v⁺ (free and prescribed); report f = P/h + m g and τ = L/h. Returns a flag word.

    ``snap[c]`` > 0 rounds the displacement along a periodic axis c to the position grid (as the
    DEM-P integrator does), so that images shifted by the period stay exact."""
    flags = 0
    for i in range(n):
        mo = motion[i]
        if mo == 0 or mo == 2:
            for c in range(3):
                d = h * v[i, c]
                if snap[c] != 0.0:
                    d = (d + snap[c]) - snap[c]
                x[i, c] += d
        f[i, 0] = P[i, 0] * inv_h
        f[i, 1] = P[i, 1] * inv_h
        f[i, 2] = P[i, 2] * inv_h
        if mo == 0:
            f[i, 0] += mass[i] * gx
            f[i, 1] += mass[i] * gy
            f[i, 2] += mass[i] * gz
        t[i, 0] = L[i, 0] * inv_h
        t[i, 1] = L[i, 1] * inv_h
        t[i, 2] = L[i, 2] * inv_h
        for d in range(3):
            if not (math.isfinite(x[i, d]) and math.isfinite(v[i, d]) and math.isfinite(w[i, d])):
                flags |= FLAG_NONFINITE
    return flags
