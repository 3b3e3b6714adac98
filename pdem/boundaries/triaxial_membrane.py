"""Kernels of the triaxial cell's smooth membrane (see ``TriaxialCell._smooth_membrane``).

Every per-cell sum is made order-independent, so that the result is bitwise the same on any number
of ranks without sorting: maxima are exact, and the sum of a cell's weights e ∈ (e^-cut, 1] is
accumulated in fixed point (integers of 2^-52), which is exact in any order. A grain's load is
summed over its nine cells in a fixed order relative to its own cell.
"""

from __future__ import annotations

import math

import numpy as np

from pdem.api import njit

FIXED = float(2**52)  # fixed-point scale of the weights (e ≤ 1: a cell of < 2^11 terms fits int64)
STEEP = 4.0  # fall-off of a cap beyond its flat top, × a sphere's: a cell two away is ≥ 2 r lower

_DZ = np.array([-1, -1, -1, 0, 0, 0, 1, 1, 1], dtype=np.int64)
_DT = np.array([-1, 0, 1, -1, 0, 1, -1, 0, 1], dtype=np.int64)


@njit
def cells_of(theta, zrel, nz, nt, dth, dz):
    """The (z, θ) cell of each grain: the nearest row (rows at z = k dz, k = 0 … nz − 1, the first
    and last on the platens) and the θ sector."""
    n = theta.size
    kz = np.empty(n, np.int64)
    kt = np.empty(n, np.int64)
    for i in range(n):
        t = int((theta[i] + math.pi) / dth)
        kt[i] = min(max(t, 0), nt - 1)
        z = int(zrel[i] / dz + 0.5) if zrel[i] > 0.0 else 0
        kz[i] = min(max(z, 0), nz - 1)
    return kz, kt


@njit
def binned_max(s, kz, kt, nt, ncell):
    """Largest outer radius s per cell (−inf where empty)."""
    mb = np.full(ncell, -np.inf)
    for i in range(s.size):
        c = kz[i] * nt + kt[i]
        if s[i] > mb[c]:
            mb[c] = s[i]
    return mb


@njit
def neighbourhood_min(mb, nz, nt):
    """Smallest of each cell's 3 × 3 neighbourhood (periodic in θ, clamped in z)."""
    low = np.empty(nz * nt)
    for a in range(nz):
        for t in range(nt):
            m = np.inf
            for k in range(9):
                zz = min(max(a + _DZ[k], 0), nz - 1)
                tt = (t + _DT[k]) % nt
                v = mb[zz * nt + tt]
                if v < m:
                    m = v
            low[a * nt + t] = m
    return low


@njit
def caps(theta, zrel, rho, r, kz, kt, low, depth, nz, nt, dth, dz):
    """The cap of every grain near the surface at the centres of its cell and the eight around: at a
    lateral offset (arc ρΔθ, Δz), q = s − (max(0, |arc| − r)² + max(0, |Δz| − dz)²)/(2r) (−inf for a
    grain deeper than ``low`` − ``depth`` − 2r, or a cell beyond the end rows), with the cell, Δθ,
    and the penalty's slopes ∂/∂arc and ∂/∂Δz; and the largest q per cell."""
    n = theta.size
    q = np.full((n, 9), -np.inf)
    cell = np.zeros((n, 9), np.int64)
    dtheta = np.zeros((n, 9))
    ga = np.zeros((n, 9))
    gw = np.zeros((n, 9))
    M = np.full(nz * nt, -np.inf)
    for i in range(n):
        s = rho[i] + r[i]
        if s <= low[kz[i] * nt + kt[i]] - depth - 2.0 * r[i]:
            continue
        for k in range(9):
            cz = kz[i] + _DZ[k]
            if cz < 0 or cz >= nz:
                continue
            ct = (kt[i] + _DT[k]) % nt
            c = cz * nt + ct
            d = theta[i] - ((ct + 0.5) * dth - math.pi)
            d = (d + math.pi) % (2.0 * math.pi) - math.pi
            a = rho[i] * d
            w = zrel[i] - cz * dz
            # flat top: |arc| ≤ r around, |Δz| ≤ dz along the axis (the membrane bridges a grain
            # radius around and a row spacing along); a sphere's fall-off beyond
            oa = abs(a) - r[i]
            ow = abs(w) - dz
            v = s
            if oa > 0.0:
                v -= STEEP * oa * oa / (2.0 * r[i])
                ga[i, k] = math.copysign(STEEP * oa / r[i], a)
            if ow > 0.0:
                v -= STEEP * ow * ow / (2.0 * r[i])
                gw[i, k] = math.copysign(STEEP * ow / r[i], w)
            q[i, k] = v
            cell[i, k] = c
            dtheta[i, k] = d
            if v > M[c]:
                M[c] = v
    return q, cell, dtheta, ga, gw, M


@njit
def weights(q, cell, M, cut, b):
    """e = exp((q − M_c)/b) for the caps within ``cut`` of their cell's largest (0 otherwise), and
    the cells' sums of e in fixed point (exact in any order)."""
    n = q.shape[0]
    e = np.zeros((n, 9))
    zsum = np.zeros(M.size, np.int64)
    for i in range(n):
        for k in range(9):
            c = cell[i, k]
            if q[i, k] > M[c] - cut:
                v = math.exp((q[i, k] - M[c]) / b)
                e[i, k] = v
                zsum[c] += np.int64(v * FIXED + 0.5)
    return e, zsum


@njit
def loads(e, cell, dtheta, ga, gw, R, Z, r, dx, dy, rho, scale, wrow, nt, b, want_k):
    """Load of each grain, −σ₃ Δθ Σ_c w_c R_c ∂R_c/∂x (``scale`` = σ₃ Δθ, w the row's height, half
    a spacing for the rows on the platens), summed over its cells in a fixed order;
    ∂R_c/∂x = p g, g = ρ̂ − g_a (Δθ ρ̂ + θ̂) − g_w ẑ (the penalty's slopes), p = e / Z_c. Each cell's
    part acts where the grain's surface faces along g (lever r ĝ): also returned, per grain, the
    moment Σ lever ⊗ f (for the grains' average stress) and the radial virial Σ (ρ + lever)·f over
    the horizontal components (for the pressure the membrane exerts, −Σ/(2V)).

    Also a bound k_i on the stiffness of each grain's own load, |∂F_i/∂x_i| (the largest eigenvalue
    in magnitude): −∂F_i/∂x_i = Σ_c σ₃ Δθ w_c [∂R_c ⊗ ∂R_c + R_c ∂²R_c], and with the smooth maximum
    ∂²R_c = p(1 − p)/b g ⊗ g + p ∂g/∂x, whose slope terms change at STEEP/r on a cap's flanks and
    ρ̂ turns at 1/ρ, so k_i = Σ_c S_c [(1 − p)|g|²/b + p|g|²/R_c + STEEP/r (flanks) + |g|/ρ] with
    S_c = σ₃ Δθ w_c R_c p (the triangle inequality over the terms' norms). The 1/b term dominates:
    a narrow smoothing makes a stiff load (tests/test_triaxial.py compares k with finite
    differences). Computed only with ``want_k``."""
    n = e.shape[0]
    f = np.zeros((n, 3))
    kst = np.zeros(n)
    mom = np.zeros((n, 3, 3))
    vir = np.zeros(n)
    for i in range(n):
        rh = max(rho[i], 1e-300)
        ux, uy = dx[i] / rh, dy[i] / rh
        fx = fy = fz = 0.0
        for k in range(9):
            if e[i, k] == 0.0:
                continue
            c = cell[i, k]
            coef = -scale * wrow[c // nt] * R[c] * e[i, k] / Z[c]
            pk = e[i, k] / Z[c]
            kk = ga[i, k]
            radial = 1.0 - kk * dtheta[i, k]
            gx = radial * ux + kk * uy
            gy = radial * uy - kk * ux
            gz = -gw[i, k]
            if want_k:  # (a cell held up only by far caps can have R < 0: magnitudes)
                gg = gx * gx + gy * gy + gz * gz
                flanks = (1.0 if kk != 0.0 else 0.0) + (1.0 if gz != 0.0 else 0.0)
                kst[i] += abs(coef) * (
                    abs(1.0 - pk) * gg / b + pk * gg / max(abs(R[c]), r[i]) + flanks * STEEP / r[i]
                    + math.sqrt(gg) / rh
                )
            px, py, pz = coef * gx, coef * gy, coef * gz
            fx += px
            fy += py
            fz += pz
            gn = r[i] / math.sqrt(gx * gx + gy * gy + gz * gz)
            lx, ly, lz = gx * gn, gy * gn, gz * gn
            mom[i, 0, 0] += lx * px
            mom[i, 0, 1] += lx * py
            mom[i, 0, 2] += lx * pz
            mom[i, 1, 0] += ly * px
            mom[i, 1, 1] += ly * py
            mom[i, 1, 2] += ly * pz
            mom[i, 2, 0] += lz * px
            mom[i, 2, 1] += lz * py
            mom[i, 2, 2] += lz * pz
            vir[i] += (dx[i] + lx) * px + (dy[i] + ly) * py
        f[i, 0] = fx
        f[i, 1] = fy
        f[i, 2] = fz
    return f, mom, vir, kst
