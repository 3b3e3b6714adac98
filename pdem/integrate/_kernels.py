"""Velocity-Verlet kernels for spheres (translation and rotation), LAMMPS ``nve/sphere`` order.

initial: v += (dt/2) f/m, ω += (dt/2) τ/I, x += dt v   (free particles)
         x += dt v                                      (prescribed particles; v set from outside)
         (along periodic axes dt v is rounded to the position grid of pdem.domain)
final:   v += (dt/2) f/m, ω += (dt/2) τ/I              (free particles)
Fixed particles never move. Body forces are added to ``f`` before ``final``.
"""

from __future__ import annotations

import math

from .._jit import njit

FLAG_NONFINITE = 2


@njit
def initial_integrate(x, v, w, f, t, inv_m, inv_i, motion, dof, dt, n, snap):
    """``snap[c]`` > 0 rounds the displacement along axis c to the periodic position grid:
    (d + C) − C with C = 1.5·2⁵²·q is d rounded to a multiple of q (see :mod:`pdem.domain`);
    0 leaves the axis alone. ``dof`` bits lock velocity components (bit c: v_c, bit 3 + c: ω_c):
    a locked component is not kicked (it stays zero).

    The lock test is made once per particle, outside the component loops: a per-component test
    through an inlined helper made this kernel 8× slower (1.37 against 0.17 ms for 20k particles)."""
    h = 0.5 * dt
    for i in range(n):
        mo = motion[i]
        if mo == 0:
            lock = dof[i]
            if lock == 0:
                for c in range(3):
                    v[i, c] += h * f[i, c] * inv_m[i]
                    w[i, c] += h * t[i, c] * inv_i[i]
            else:
                for c in range(3):
                    if (lock >> c) & 1 == 0:
                        v[i, c] += h * f[i, c] * inv_m[i]
                    if (lock >> (c + 3)) & 1 == 0:
                        w[i, c] += h * t[i, c] * inv_i[i]
            for c in range(3):
                d = dt * v[i, c]
                if snap[c] != 0.0:
                    d = (d + snap[c]) - snap[c]
                x[i, c] += d
        elif mo == 2:
            for c in range(3):
                d = dt * v[i, c]
                if snap[c] != 0.0:
                    d = (d + snap[c]) - snap[c]
                x[i, c] += d


@njit
def add_body_force_and_final_integrate(v, w, f, t, mass, inv_m, inv_i, motion, dof, gx, gy, gz, dt, n):
    """f += m g for free particles, then the second half kick (locked components skipped); returns a
    flag word."""
    h = 0.5 * dt
    flags = 0
    for i in range(n):
        if motion[i] == 0:
            f[i, 0] += mass[i] * gx
            f[i, 1] += mass[i] * gy
            f[i, 2] += mass[i] * gz
            lock = dof[i]
            if lock == 0:
                for c in range(3):
                    v[i, c] += h * f[i, c] * inv_m[i]
                    w[i, c] += h * t[i, c] * inv_i[i]
            else:
                for c in range(3):
                    if (lock >> c) & 1 == 0:
                        v[i, c] += h * f[i, c] * inv_m[i]
                    if (lock >> (c + 3)) & 1 == 0:
                        w[i, c] += h * t[i, c] * inv_i[i]
            s = 0.0
            for c in range(3):
                s += v[i, c] + w[i, c]
            if not math.isfinite(s):
                flags |= FLAG_NONFINITE
    return flags


@njit
def add_body_forces(f, mass, motion, gx, gy, gz, n):
    """f += m g for free particles."""
    for i in range(n):
        if motion[i] == 0:
            f[i, 0] += mass[i] * gx
            f[i, 1] += mass[i] * gy
            f[i, 2] += mass[i] * gz


@njit
def zero_forces(f, t, n):
    for i in range(n):
        for c in range(3):
            f[i, c] = 0.0
            t[i, c] = 0.0
