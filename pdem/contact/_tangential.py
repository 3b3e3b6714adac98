"""Kernel helpers that contact laws share (inlined into each law's force function).

:func:`tangential_spring` is the tangential spring with multi-step history and a Coulomb cap used by
the Hertz–Mindlin law and by the example linear-spring plugin; a law plugin can call it too
(``from pdem.contact._tangential import tangential_spring``).
"""

from __future__ import annotations

import math

from .._jit import njit

__all__ = ["tangential_spring"]


@njit(inline="always")
def tangential_spring(hist, k, nx, ny, nz, vtx, vty, vtz, k_t, c_t, fcap, dt):
    """Tangential force on j and the updated spring ξ = ``hist[k, 0:3]`` (global frame).

    ξ is rotated onto the tangent plane normal to n keeping its length, then ξ += v_t dt and
    F_t = −k_t ξ − c_t v_t. If |F_t| > ``fcap`` (μ max(F_n, 0)), F_t is scaled to the cap and the spring
    follows the slider with ξ = −F_t/k_t: the spring alone carries the Coulomb force (storing the
    damping too, ξ = −(F_t + c_t v_t)/k_t, reverses friction early in damped contacts because k_t
    grows faster than c_t; see pdem.laws.hertz_mindlin). Returns (F_tx, F_ty, F_tz).
    """
    sx = hist[k, 0]
    sy = hist[k, 1]
    sz = hist[k, 2]
    old2 = sx * sx + sy * sy + sz * sz
    if old2 > 0.0:
        sn = sx * nx + sy * ny + sz * nz
        sx -= sn * nx
        sy -= sn * ny
        sz -= sn * nz
        new2 = sx * sx + sy * sy + sz * sz
        if new2 > 0.0:
            scale = math.sqrt(old2 / new2)
            sx *= scale
            sy *= scale
            sz *= scale
    sx += vtx * dt
    sy += vty * dt
    sz += vtz * dt
    ftx = -k_t * sx - c_t * vtx
    fty = -k_t * sy - c_t * vty
    ftz = -k_t * sz - c_t * vtz
    ft2 = ftx * ftx + fty * fty + ftz * ftz
    if ft2 > fcap * fcap:
        scale = fcap / math.sqrt(ft2)
        ftx *= scale
        fty *= scale
        ftz *= scale
        sx = -ftx / k_t
        sy = -fty / k_t
        sz = -ftz / k_t
    hist[k, 0] = sx
    hist[k, 1] = sy
    hist[k, 2] = sz
    return ftx, fty, ftz
