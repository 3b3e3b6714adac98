"""Velocity Verlet for penalty laws (DEM-P), LAMMPS ``nve/sphere`` order (ARCHITECTURE.md)::

    initial_integrate   v += a dt/2; x += v dt; ω half step   (locked degrees of freedom skipped)
    move walls
    if anything moved more than the skin allows → rebuild (wrap, migrate, ghosts, pairs, history)
    else forward ghost positions and velocities
    forces              pairs (id-pair order) → walls (in order) → boundary forces → body forces
    final_integrate     v += a dt/2; ω
    check flags         collective
"""

from __future__ import annotations

import time

from . import _kernels as integ
from .base import Integrator

__all__ = ["VelocityVerlet"]


class VelocityVerlet(Integrator):
    name = "velocity_verlet"

    def prepare(self) -> None:
        """Forces for the first half kick. Like LAMMPS's setup, this evaluation must not advance the
        contact history (the next step does)."""
        sim = self.sim
        cs = sim.contact_store
        saved = cs.hist.copy(), cs.wall_hist.copy()
        sim.compute_forces()
        cs.hist[:] = saved[0]
        cs.wall_hist[:] = saved[1]
        sim.add_body_forces()

    def step(self) -> None:
        sim = self.sim
        p = sim.particles
        dt = sim.dt
        t0 = time.perf_counter()
        integ.initial_integrate(
            p.x, p.v, p.w, p.f, p.t, p.inv_m, p.inv_i, p.motion, p.dof, dt, p.n_owned, sim.position_snap
        )
        t1 = time.perf_counter()
        sim.advance_walls(dt)
        sim.update_neighbours()
        flags = sim.compute_forces()
        g = sim.g
        t2 = time.perf_counter()
        flags |= integ.add_body_force_and_final_integrate(
            p.v, p.w, p.f, p.t, p.mass, p.inv_m, p.inv_i, p.motion, p.dof, g[0], g[1], g[2], dt, p.n_owned
        )
        # the integration is per owned particle and waits for no other rank: the load balancer
        # weighs it with the contacts (a rank with more grains in free flight does more of it)
        sim.add_work_time(t1 - t0 + time.perf_counter() - t2)
        sim.finish_step(flags)
