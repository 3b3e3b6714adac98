"""Peer reference for tests/test_chung_ooi.py: Chung & Ooi (2011) test 4 with YADE's Hertz–Mindlin law.

Run with YADE (Debian package ``yade``), not with pdem's Python::

    yade -n -x tools/chung_ooi_yade.py tests/data/chung_ooi_test4_yade.csv [DT_FRACTION]

A sphere (aluminium oxide: E = 380 GPa, ν = 0.23, ρ = 4000 kg/m³, r = 2.5 mm) hits a plane wall
(the same material with E 1000 times larger, as in YADE's own Chung & Ooi scripts) at 3.9 m/s,
5°–85° from the normal, μ = 0.092, no initial spin. Contact law: ``Law2_ScGeom_MindlinPhys_Mindlin``
(Hertz normal force, incremental Mindlin tangential force with k_s = 8 G* a, Coulomb cap), normal
and shear damping ratios β_n = β_s from e = 0.98 (β = −ln e / sqrt(ln² e + π²)); time step
DT_FRACTION (default 0.01, as in YADE's scripts) of YADE's Rayleigh time step. Written as CSV, with
a header of comment lines saying how: incidence [deg], the
rebound normal speed v_n' [m/s], the tangential velocity v_t' [m/s] (along the incident tangential
direction), the spin ω' [rad/s] (positive in the sense friction drives it, so that the contact patch
moves at v_t' − r ω'), and the contact-patch rebound angle atan((v_t' − r ω')/v_n') [deg].
"""

import math
import sys

import yade.config
from yade import O, utils
from yade.wrapper import (
    Bo1_Sphere_Aabb,
    Bo1_Wall_Aabb,
    ForceResetter,
    FrictMat,
    Ig2_Wall_Sphere_ScGeom,
    InsertionSortCollider,
    InteractionLoop,
    Ip2_FrictMat_FrictMat_MindlinPhys,
    Law2_ScGeom_MindlinPhys_Mindlin,
    NewtonIntegrator,
)

R = 2.5e-3
SPEED = 3.9
MU = 0.092
E_REST = 0.98
ANGLES = [5, 10, 15, 20, 25, 30, 35, 40, 45, 50, 55, 60, 65, 70, 75, 80, 85]


OUT = sys.argv[1] if len(sys.argv) > 1 else "chung_ooi_test4_yade.csv"
DT_FRACTION = float(sys.argv[2]) if len(sys.argv) > 2 else 0.01


def impact(angle_deg):
    O.reset()
    sphere_mat = O.materials.append(
        FrictMat(young=3.8e11, poisson=0.23, density=4000, frictionAngle=math.atan(MU))
    )
    wall_mat = O.materials.append(
        FrictMat(young=3.8e14, poisson=0.23, density=4000, frictionAngle=math.atan(MU))
    )
    th = math.radians(angle_deg)
    gap = 1e-7
    s = O.bodies.append(utils.sphere((-R - gap, 0, 0), R, material=sphere_mat))
    O.bodies.append(utils.wall(0, axis=0, material=wall_mat))
    b = O.bodies[s]
    b.state.vel = (SPEED * math.cos(th), SPEED * math.sin(th), 0)
    beta = -math.log(E_REST) / math.sqrt(math.log(E_REST) ** 2 + math.pi**2)
    O.engines = [
        ForceResetter(),
        InsertionSortCollider([Bo1_Sphere_Aabb(), Bo1_Wall_Aabb()]),
        InteractionLoop(
            [Ig2_Wall_Sphere_ScGeom()],
            [Ip2_FrictMat_FrictMat_MindlinPhys(betan=beta, betas=beta)],
            [Law2_ScGeom_MindlinPhys_Mindlin(preventGranularRatcheting=False)],  # a no-op in 2023.02a
        ),
        NewtonIntegrator(gravity=(0, 0, 0), damping=0),
    ]
    O.dt = DT_FRACTION * utils.RayleighWaveTimeStep()
    touched = False
    for _ in range(10_000_000):
        O.step()
        if O.interactions.countReal() > 0:
            touched = True
        elif touched and b.state.pos[0] < -R - gap:
            break
    vn = -b.state.vel[0]
    vt = b.state.vel[1]
    w = -b.state.angVel[2]
    patch = math.degrees(math.atan((vt - R * w) / vn))
    return vn, vt, w, patch, O.dt


rows = [(a, *impact(a)) for a in ANGLES]
with open(OUT, "w") as out:
    out.write(
        f"# Chung & Ooi (2011) test 4 computed with YADE {yade.config.version} (Debian package yade),\n"
        f"# Law2_ScGeom_MindlinPhys_Mindlin, by: yade -n -x tools/chung_ooi_yade.py {OUT} {DT_FRACTION}\n"
        f"# sphere E = 380 GPa, nu = 0.23, rho = 4000 kg/m3, r = {R} m; wall E = 3.8e14 Pa, nu = 0.23;\n"
        f"# speed {SPEED} m/s, mu = {MU}, e = {E_REST} (betan = betas); dt = {rows[0][5]:.4g} s\n"
        "# (omega positive in the sense friction drives it; patch angle atan((vt - r omega)/vn))\n"
        "incidence_deg,vn_rebound,vt_rebound,omega_rebound,patch_rebound_angle_deg\n"
    )
    for a, vn, vt, w, patch, _ in rows:
        out.write(f"{a},{vn:.9g},{vt:.9g},{w:.9g},{patch:.9g}\n")
