"""Kernel helpers that contact laws share (inlined into each law's force function).

:func:`tangential_spring` is the tangential spring with multi-step history and a Coulomb cap used by
the Hertz–Mindlin law and by the example linear-spring plugin; a law plugin can call it too
(``from pdem.contact._tangential import tangential_spring``).
"""

from __future__ import annotations

import math

from .._jit import njit

__all__ = ["tangential_spring", "tangential_spring_values", "tangential_mindlin_values"]


@njit(inline="always")
def tangential_spring(hist, k, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt):
    """Tangential force on j and the updated spring ξ = ``hist[k, 0:3]`` (global frame).

    ξ is rotated onto the tangent plane normal to n keeping its length, then ξ += v_t dt and
    F_t = −k_t ξ − c_t v_t. If |F_t| > ``fcap`` (μ max(F_n, 0)), F_t is scaled to the cap and the spring
    follows the slider with ξ = −F_t/k_t: the spring alone carries the Coulomb force (storing the
    damping too, ξ = −(F_t + c_t v_t)/k_t, reverses friction early in damped contacts because k_t
    grows faster than c_t; see pdem.laws.hertz_mindlin). Returns (F_tx, F_ty, F_tz).
    """
    ftx, fty, ftz, sx, sy, sz = tangential_spring_values(
        hist[k, 0], hist[k, 1], hist[k, 2], nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt
    )
    hist[k, 0] = sx
    hist[k, 1] = sy
    hist[k, 2] = sz
    return ftx, fty, ftz


@njit(inline="always")
def tangential_spring_values(sx, sy, sz, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt):
    """:func:`tangential_spring` on scalars: from the spring (sx, sy, sz) to (F_t, the new spring).

    Every path is computed and the right one selected, without branches, so that a loop over
    contacts held in columns vectorizes (DEM-P's Hertz–Mindlin pair loop); the values are those of
    the branching form, bit for bit (a zero-length spring or tangent gives inf or nan in a product
    that is never selected)."""
    ux, uy, uz = _onto_tangent_plane(sx, sy, sz, nx, ny, nz)
    ux += vtx * dt
    uy += vty * dt
    uz += vtz * dt
    ftx = -k_t * ux - c_t * vtx
    fty = -k_t * uy - c_t * vty
    ftz = -k_t * uz - c_t * vtz
    cap, gx, gy, gz, ox, oy, oz = _coulomb_cap(ftx, fty, ftz, fcap)
    ux = -gx / k_t if cap else ux
    uy = -gy / k_t if cap else uy
    uz = -gz / k_t if cap else uz
    return ox, oy, oz, ux, uy, uz


@njit(inline="always")
def tangential_mindlin_values(
    sx, sy, sz, a_old, a, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt, force, rescale
):
    """The Mindlin–Deresiewicz-type variants of :func:`tangential_spring_values`, on scalars.

    ``force`` False: the history (sx, sy, sz) is the spring ξ, as in :func:`tangential_spring_values`
    (F_t = −k_t ξ − c_t v_t). ``force`` True: it is the elastic tangential force F_e, updated
    incrementally, F_e += −k_t v_t dt (Di Renzo & Di Maio 2005, Thornton et al. 2013 eq. 18;
    LAMMPS ``mindlin/force``), and F_t = F_e − c_t v_t. ``rescale`` True: when the contact radius a
    shrinks below the previous step's ``a_old``, the history is first scaled by a/a_old (LAMMPS
    ``mindlin_rescale`` and ``mindlin_rescale/force``: with k_t ∝ a, F_e then follows
    k_t,new/k_t,old on unloading). Then, as in :func:`tangential_spring_values`: rotation onto the
    tangent plane keeping the length, the Coulomb cap ``fcap`` and, at the cap, the elastic part
    equal to the capped force (ξ = −F_t/k_t, or F_e = F_t). A new contact has zero history and
    ``a_old`` = 0 (no rescaling at its first step).

    Every path is computed and the right one selected, without branches (columns vectorize).
    Returns (F_t on j, the new history, a: the ``a_old`` of the next step)."""
    shrink = rescale & (a < a_old)
    f = a / a_old
    sx = sx * f if shrink else sx
    sy = sy * f if shrink else sy
    sz = sz * f if shrink else sz
    ux, uy, uz = _onto_tangent_plane(sx, sy, sz, nx, ny, nz)
    # the increment: of the spring (v_t dt) or of the elastic force (−k_t v_t dt)
    gain = -k_t * dt if force else dt
    ux += vtx * gain
    uy += vty * gain
    uz += vtz * gain
    ex = ux if force else -k_t * ux
    ey = uy if force else -k_t * uy
    ez = uz if force else -k_t * uz
    ftx = ex - c_t * vtx
    fty = ey - c_t * vty
    ftz = ez - c_t * vtz
    cap, gx, gy, gz, ox, oy, oz = _coulomb_cap(ftx, fty, ftz, fcap)
    # at the cap the elastic part carries the Coulomb force alone
    hx = gx if force else -gx / k_t
    hy = gy if force else -gy / k_t
    hz = gz if force else -gz / k_t
    ux = hx if cap else ux
    uy = hy if cap else uy
    uz = hz if cap else uz
    return ox, oy, oz, ux, uy, uz, a


@njit(inline="always")
def _onto_tangent_plane(sx, sy, sz, nx, ny, nz):
    """The history vector rotated onto the plane normal to n, keeping its length (branch-free: a
    zero vector or a zero projection keeps the vector as it is)."""
    old2 = sx * sx + sy * sy + sz * sz
    sn = sx * nx + sy * ny + sz * nz
    px = sx - sn * nx
    py = sy - sn * ny
    pz = sz - sn * nz
    new2 = px * px + py * py + pz * pz
    scale = math.sqrt(old2 / new2)
    turn = old2 > 0.0
    stretch = turn & (new2 > 0.0)
    ux = (px * scale if stretch else px) if turn else sx
    uy = (py * scale if stretch else py) if turn else sy
    uz = (pz * scale if stretch else pz) if turn else sz
    return ux, uy, uz


@njit(inline="always")
def _coulomb_cap(ftx, fty, ftz, fcap):
    """The trial force F against the cap ``fcap``: (capped?, F scaled to the cap, the force)."""
    ft2 = ftx * ftx + fty * fty + ftz * ftz
    cap = ft2 > fcap * fcap
    s = fcap / math.sqrt(ft2)
    gx = ftx * s
    gy = fty * s
    gz = ftz * s
    ox = gx if cap else ftx
    oy = gy if cap else fty
    oz = gz if cap else ftz
    return cap, gx, gy, gz, ox, oy, oz
