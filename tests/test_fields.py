"""Coarse-grained fields (``pdem.fields``) against independent references.

The references never call the fields' code: brute-force sums over ``sim.contacts()``,
``sim.wall_contacts()`` and ``sim.get_particles()`` (virial, mass, momentum, contact counts, fabric),
closed forms (a Gaussian's second moment, a linear velocity field), the weight of a settled column
(∫ ρ g dz), NumPy quadrature of the line integrals, ``math.fsum``, and the fields of one rank
against those of several. Grid integrals use the midpoint rule on cell-centred nodes: for a
Gaussian cut off at 9 widths and nodes at most w/1.5 apart its error is below e^{−2π²·1.5²} ≈ 10⁻¹⁹
of the integral (the field is smooth and periodic, or vanishes beyond the nodes), so sum rules
hold to round-off there; with the default kernels they hold to the quadrature error only.
"""

from __future__ import annotations

import math
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import pdem
from pdem.errors import InputError
from pdem.fields import CoarseGraining, GaussianKernel, Grid, LucyKernel, TimeAverage, coarse_grain
from pdem.fields import _kernels as fk
from pdem.geometry.shapes import Plane

RHO = 2500.0
G = 9.81
#: as tests/test_mpi.py finds it: the virtualenv's (the mpich wheel's), else the PATH's
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")


def _material(sim: pdem.Simulation, restitution: float = 0.3, friction: float = 0.5) -> None:
    sim.add_material("glass", density=RHO, youngs_modulus=5e7, poisson_ratio=0.3, restitution=restitution,
                     friction=friction)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# building blocks: the correctly rounded sum and the line integrals
# ---------------------------------------------------------------------------------------------


def test_fsum_exact_is_math_fsum_bit_for_bit():
    """The numba port of ``math.fsum`` gives its bits on sums built to cancel and to sit on
    rounding ties (the half-even fix across partials)."""
    rng = np.random.default_rng(3)
    cases = [np.array([1e-16, 1.0, 1e16]), np.array([1e100, 1.0, -1e100, 1e-100]), np.array([0.1] * 10)]
    for _ in range(300):
        n = int(rng.integers(1, 40))
        x = rng.standard_normal(n) * np.exp2(rng.integers(-60, 60, n).astype(float))
        cases.append(np.concatenate([x, -x[: n // 2] * (1 + 2.0**-52), rng.standard_normal(3)]))
        tie = np.array([1.0, 2.0**-53, 2.0**-106 * rng.choice([-1.0, 1.0])])
        cases.append(rng.permutation(tie))
    for x in cases:
        assert fk.fsum_exact(x, len(x)) == math.fsum(x), x


def _chord_quadrature(kernel, d: np.ndarray, b: np.ndarray) -> float:
    """∫₀¹ φ(d − s b) ds by Gauss–Legendre on the part of [0, 1] inside the cut-off sphere (the roots
    of |d − s b|² = c²), split at the foot of the point on the line."""
    c = kernel.radius
    bb, db, dd = b @ b, d @ b, d @ d
    disc = db * db - bb * (dd - c * c)
    if disc <= 0:
        return 0.0
    lo, hi = max((db - math.sqrt(disc)) / bb, 0.0), min((db + math.sqrt(disc)) / bb, 1.0)
    if hi <= lo:
        return 0.0
    xg, wg = np.polynomial.legendre.leggauss(60)
    total = 0.0
    foot = min(max(db / bb, lo), hi)
    for a, e in ((lo, foot), (foot, hi)):
        if e > a:
            s = 0.5 * (a + e) + 0.5 * (e - a) * xg
            pts = d[None, :] - s[:, None] * b[None, :]
            total += 0.5 * (e - a) * float(wg @ kernel(np.linalg.norm(pts, axis=1)))
    return total


@pytest.mark.parametrize("kernel", [GaussianKernel(0.7, cutoff=3.0), GaussianKernel(0.5, cutoff=6.0),
                                    LucyKernel(1.3)])  # fmt: skip
def test_line_integrals_are_the_quadrature_of_the_kernel(kernel):
    """The closed forms of ∫₀¹ φ(d − s b) ds (erf/erfc; Lucy's polynomial with its asinh term) are
    the Gauss–Legendre quadrature of the kernel along the chord, to 1e-12 of the kernel's peak;
    a segment through the centre (h = 0) and one of zero length included."""
    rng = np.random.default_rng(7)
    d = rng.uniform(-1.5, 1.5, (400, 3))
    b = rng.uniform(-1.2, 1.2, (400, 3))
    d[0], b[0] = np.array([0.3, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])  # through the centre
    d[1], b[1] = np.array([0.2, 0.1, -0.3]), np.zeros(3)  # a point
    got = fk.line_integrals(kernel.kind, kernel.norm, kernel.width, kernel.radius, d, b)
    ref = [_chord_quadrature(kernel, d[k], b[k]) if k != 1 else float(kernel(np.linalg.norm(d[1])))
           for k in range(len(d))]  # fmt: skip
    assert np.count_nonzero(got) > 100
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * kernel.norm)


def test_kernels_integrate_to_one():
    """Radial quadrature of each kernel over its ball gives 1 (the normalisation after the cut)."""
    for kernel in (GaussianKernel(0.3), GaussianKernel(0.3, cutoff=1.5), LucyKernel(0.8)):
        xg, wg = np.polynomial.legendre.leggauss(200)
        r = 0.5 * kernel.radius * (xg + 1.0)
        total = 0.5 * kernel.radius * float(wg @ (4 * math.pi * r**2 * kernel(r)))
        assert total == pytest.approx(1.0, rel=1e-13)


# ---------------------------------------------------------------------------------------------
# 1-2: sum rules on a compressed packing (periodic in x and y, walls in z)
# ---------------------------------------------------------------------------------------------

R = 0.5e-3
_A = 2 * R / 1.01 * math.sqrt(2.0)  # FCC cube edge: nearest neighbours overlap by 1 % of d


def _packing() -> tuple[pdem.Simulation, float, tuple[float, float]]:
    """An FCC packing of 32 grains compressed isotropically (overlaps of ~1 % of d), periodic in x
    and y (period 2 cube edges), between a floor and a lid that press on it; 20 steps of DEM-P
    develop tangential forces (friction) and velocities."""
    rng = np.random.default_rng(11)
    idx = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    idx = idx[idx.sum(axis=1) % 2 == 0]
    x = (idx + 0.5) * (_A / 2) + rng.uniform(-0.02, 0.02, idx.shape) * R
    sim = pdem.Simulation()
    _material(sim)
    sim.add_particles(x, R * (1.0 + rng.uniform(-0.005, 0.005, len(x))))
    period = 2 * _A
    sim.set_periodic((0.0, 0.0, -0.01), (period, period, 0.02), "xy")
    zlo, zhi = float(x[:, 2].min()) - 0.99 * R, float(x[:, 2].max()) + 0.99 * R
    sim.add_wall(Plane((0, 0, zlo), (0, 0, 1)), name="floor")
    sim.add_wall(Plane((0, 0, zhi), (0, 0, -1)), name="lid")
    sim.dt = 2e-6
    sim.run(steps=20)
    return sim, period, (zlo, zhi)


@pytest.fixture(scope="module")
def packing():
    sim, period, walls = _packing()
    p = sim.get_particles()
    c = sim.contacts()
    w = sim.wall_contacts()
    return sim, period, walls, p, c, w


def _brute_force(period, walls, p, c, w) -> dict[str, np.ndarray]:
    """The integrals over space of the fields' densities, from the grains and contacts."""
    x = p["x"]
    b = x[c["id_j"]] - x[c["id_i"]]
    b[:, :2] -= np.round(b[:, :2] / period) * period  # the nearest image
    n_pair = b / np.linalg.norm(b, axis=1)[:, None]
    xw = x[w["id"]]
    zlo, zhi = walls
    normal = np.where((w["wall"] == 0)[:, None], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0])
    gap = np.where(w["wall"] == 0, xw[:, 2] - zlo, zhi - xw[:, 2])  # centre to plane
    delta = p["r"][w["id"]] - gap
    lever = (p["r"][w["id"]] - 0.5 * delta)[:, None] * normal
    virial = np.einsum("ka,kb->ab", c["force"], b) + np.einsum("ka,kb->ab", w["force"], lever)
    fabric = 2 * np.einsum("ka,kb->ab", n_pair, n_pair) + np.einsum("ka,kb->ab", normal, normal)
    return {
        "contact_stress": virial,
        "density": p["mass"].sum(),
        "solid_fraction": (4 / 3 * math.pi * p["r"] ** 3).sum(),
        "number_density": float(len(x)),
        "momentum": (p["mass"][:, None] * p["v"]).sum(axis=0),
        "contact_density": float(2 * len(c["id_i"]) + len(w["id"])),
        "fabric_density": fabric,
        "wall_force_density": -w["force"].sum(axis=0),
    }


def _grid_integrals(f, grid: Grid) -> dict[str, np.ndarray]:
    dv = grid.cell_volume
    fab = f.fabric * f.number_density[..., None, None]  # Σ n n φ
    names = ("contact_stress", "density", "solid_fraction", "number_density", "momentum", "contact_density",
             "wall_force_density")  # fmt: skip
    out = {k: getattr(f, k).sum(axis=(0, 1, 2)) * dv for k in names}
    out["fabric_density"] = fab.sum(axis=(0, 1, 2)) * dv
    return out


def test_packing_has_what_the_sum_rules_need(packing):
    sim, period, walls, p, c, w = packing
    assert len(c["id_i"]) >= 150 and len(w["id"]) >= 12
    x = p["x"]
    b = x[c["id_j"]] - x[c["id_i"]]
    assert np.any(np.abs(b[:, :2]) > period / 2), "no contact across a periodic face"
    tangential = c["force"] - c["normal_force"][:, None] * b / np.linalg.norm(b, axis=1)[:, None]
    assert np.abs(tangential).max() > 1e-3 * np.abs(c["normal_force"]).max()


def test_box_integral_of_the_contact_stress_is_the_virial(packing):
    """1. ∫ σᶜ dV over one period in x, y and all z = Σ_pairs f ⊗ b + Σ_walls F ⊗ l (the virial
    (1/V) Σ f ⊗ b times V, walls included), every component, to 1e-10 of the largest — with a
    Gaussian cut at 9 widths on a grid of w/1.6; compression positive (the trace is positive).
    2. ∫ ρ dV = the grains' mass to 1e-12; and alike ∫ solid fraction = Σ V_i, ∫ n = N,
    ∫ p = Σ m v, ∫ contact density = 2 N_pairs + N_walls, ∫ Σ n n φ = Σ_ends n ⊗ n, ∫ t = −Σ F_wall."""
    sim, period, walls, p, c, w = packing
    kernel = GaussianKernel(0.45e-3, cutoff=9.0)
    h = period / 10
    zlo, zhi = walls
    nz = int(math.ceil((zhi - zlo + 2 * kernel.radius + 2 * R) / h))
    z0 = 0.5 * (zlo + zhi) - 0.5 * nz * h
    grid = Grid((0.0, 0.0, z0), (period, period, z0 + nz * h), (10, 10, nz))
    assert kernel.width / h > 1.5
    f = coarse_grain(sim, kernel, grid)
    got = _grid_integrals(f, grid)
    ref = _brute_force(period, walls, p, c, w)
    sig = ref["contact_stress"]
    assert np.trace(sig) > 0 and np.abs(sig - sig.T).max() > 1e-9 * np.abs(sig).max()  # not symmetric
    np.testing.assert_allclose(got["contact_stress"], sig, rtol=0, atol=1e-10 * np.abs(sig).max())
    assert got["density"] == pytest.approx(ref["density"], rel=1e-12)
    for key in ("solid_fraction", "number_density", "contact_density"):
        assert got[key] == pytest.approx(ref[key], rel=1e-12), key
    for key in ("momentum", "fabric_density", "wall_force_density"):
        scale = np.abs(ref[key]).max()
        np.testing.assert_allclose(got[key], ref[key], rtol=0, atol=1e-11 * scale, err_msg=key)


@pytest.mark.parametrize("kernel,rel", [(GaussianKernel(0.45e-3), 3e-3), (LucyKernel(1.5e-3), 1e-4)])
def test_sum_rules_with_the_default_kernels_hold_to_the_quadrature_error(packing, kernel, rel):
    """The same sum rules with the default Gaussian (cut at 3 w: a jump of 1.1 % of its peak, which
    the midpoint rule resolves to O(h)) and Lucy's kernel (C² at the cut-off): within the grid
    quadrature's error, which is what these bounds allow."""
    sim, period, walls, p, c, w = packing
    h = period / 10
    zlo, zhi = walls
    nz = int(math.ceil((zhi - zlo + 2 * kernel.radius + 2 * R) / h))
    z0 = 0.5 * (zlo + zhi) - 0.5 * nz * h
    grid = Grid((0.0, 0.0, z0), (period, period, z0 + nz * h), (10, 10, nz))
    got = _grid_integrals(coarse_grain(sim, kernel, grid), grid)
    ref = _brute_force(period, walls, p, c, w)
    sig = ref["contact_stress"]
    np.testing.assert_allclose(got["contact_stress"], sig, rtol=0, atol=rel * np.abs(sig).max())
    assert got["density"] == pytest.approx(ref["density"], rel=rel)


# ---------------------------------------------------------------------------------------------
# 3: a settled column: σ_zz(z) = g ∫_z ρ dz
# ---------------------------------------------------------------------------------------------


def test_settled_column_stress_is_the_weight_above():
    """Three columns of 10 grains (radii 0.5, 0.4, 0.45 mm), periodic in x and y, on a floor, damped
    to rest by DEM-P (e = 0.1, 50 ms). The laterally averaged σ_zz(z) (kinetic + contact) equals the
    weight of the material above, g ∫_z^∞ ρ̄ dz (trapezoid of the CG density on the 0.05 mm z grid),
    within 2 % wherever z is a kernel radius and a millimetre from the floor and the lowest top; and
    it is positive (compression)."""
    radii = np.array([0.5e-3, 0.4e-3, 0.45e-3])
    nlay, sx, ly = 10, 1.2e-3, 2.4e-3
    sim = pdem.Simulation()
    _material(sim, restitution=0.1)
    x = np.array([[(c + 0.5) * sx, 0.5 * ly, rc * (1 + 2 * k)] for c, rc in enumerate(radii)
                  for k in range(nlay)])  # fmt: skip
    sim.add_particles(x, np.repeat(radii, nlay))
    sim.set_periodic((0, 0, -0.01), (3 * sx, ly, 0.1), "xy")
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0, 0, -G)
    sim.run(until=0.05)
    p = sim.get_particles()
    assert sum(sim.kinetic_energy()) < 1e-9 * p["mass"].min() * G * radii.min()
    top = min(p["x"][p["r"] == rc, 2].max() for rc in radii)
    hz = 0.05e-3
    for kernel in (GaussianKernel(0.5e-3), LucyKernel(1.75e-3)):
        below = math.ceil(kernel.radius / hz) + 2  # nodes below the floor: the floor's force density
        nz = int(round((p["x"][:, 2].max() + kernel.radius + 1e-3) / hz)) + below
        grid = Grid((0, 0, -below * hz), (3 * sx, ly, (nz - below) * hz), (9, 6, nz))
        f = coarse_grain(sim, kernel, grid)
        szz = f.stress[..., 2, 2].mean(axis=(0, 1))
        rho = f.density.mean(axis=(0, 1))
        above = np.concatenate([np.cumsum((0.5 * (rho[1:] + rho[:-1]) * hz)[::-1])[::-1], [0.0]])
        z = grid.axes()[2]
        sel = (z > kernel.radius + 1e-3) & (z < top - kernel.radius - 1e-3)
        assert sel.sum() > 30
        assert np.all(szz[sel] > 0)
        np.testing.assert_allclose(szz[sel], G * above[sel], rtol=0.02)
        # the floor carries the whole weight (the bound: the quadrature of the default kernels)
        floor = f.wall_force_density[..., 2].sum() * grid.cell_volume
        assert floor == pytest.approx(p["mass"].sum() * G, rel=1e-3)


# ---------------------------------------------------------------------------------------------
# 4: velocity, strain rate and kinetic stress of prescribed velocity fields
# ---------------------------------------------------------------------------------------------


def _lattice(velocity) -> tuple[pdem.Simulation, np.ndarray]:
    """A simple cubic lattice (spacing 1 mm, 2 × 2 × 36, radius 0.4 mm: no contacts), periodic in x
    and y; ``velocity(x)`` gives each grain's velocity."""
    a = 1e-3
    idx = np.stack(np.meshgrid(np.arange(2), np.arange(2), np.arange(36), indexing="ij"), -1).reshape(-1, 3)
    x = (idx + 0.5) * a
    sim = pdem.Simulation()
    _material(sim)
    sim.add_particles(x, 0.4e-3, velocities=velocity(x))
    sim.set_periodic((0, 0, -0.01), (2 * a, 2 * a, 0.05), "xy")
    sim.dt = 1e-6
    return sim, x


def test_linear_shear_gives_the_velocity_strain_rate_and_kinetic_stress_exactly():
    """v = V0 + (γ̇ z, β z, 0) on a lattice: with a Gaussian of width 1.5 lattice spacings cut at 9
    widths (lattice sums equal the integrals up to e^{−2π²·1.5²} ≈ 10⁻¹⁹), at points a kernel radius
    from the lattice's ends the CG velocity is V0 + (γ̇ z, β z, 0) to 1e-12, the velocity gradient
    has ∂_z V_x = γ̇, ∂_z V_y = β and zeros to 1e-9 γ̇, the strain rate is its symmetric part, and the
    kinetic stress is the closed form ρ w² (γ̇², γ̇β, β²) in xx, xy, yy (the Gaussian's second
    moment; compression positive) and zero elsewhere."""
    v0, gd, beta = np.array([0.3, -0.2, 0.1]), 40.0, -25.0

    def vel(x):
        return v0 + np.stack([gd * x[:, 2], beta * x[:, 2], 0 * x[:, 2]], axis=1)

    sim, _ = _lattice(vel)
    kernel = GaussianKernel(1.5e-3, cutoff=9.0)
    rng = np.random.default_rng(2)
    pts = np.column_stack([rng.uniform(0, 2e-3, 20), rng.uniform(0, 2e-3, 20), rng.uniform(14e-3, 22e-3, 20)])
    f = coarse_grain(sim, kernel, pts)
    expect = v0 + np.stack([gd * pts[:, 2], beta * pts[:, 2], 0 * pts[:, 2]], axis=1)
    np.testing.assert_allclose(f.velocity, expect, rtol=0, atol=1e-12 * np.abs(expect).max())
    grad = np.zeros((3, 3))
    grad[0, 2], grad[1, 2] = gd, beta
    np.testing.assert_allclose(f.velocity_gradient, np.broadcast_to(grad, (20, 3, 3)), rtol=0, atol=1e-9 * gd)
    np.testing.assert_allclose(f.strain_rate, np.broadcast_to(0.5 * (grad + grad.T), (20, 3, 3)), rtol=0,
                               atol=1e-9 * gd)  # fmt: skip
    w2 = kernel.width**2
    sk = np.zeros((20, 3, 3))
    sk[:, 0, 0] = f.density * w2 * gd * gd
    sk[:, 0, 1] = sk[:, 1, 0] = f.density * w2 * gd * beta
    sk[:, 1, 1] = f.density * w2 * beta * beta
    np.testing.assert_allclose(f.kinetic_stress, sk, rtol=0, atol=1e-9 * sk.max())
    assert np.all(f.kinetic_stress[:, 0, 0] > 0)
    # the lattice's density: one grain mass per cubic millimetre
    mass = RHO * 4 / 3 * math.pi * 0.4e-3**3
    np.testing.assert_allclose(f.density, mass / 1e-9, rtol=1e-12)


def test_shear_between_moving_walls_gives_the_grains_velocity_profile():
    """Simple shear of a dense periodic layer (periodic in x and y) between two walls moving at ±U
    along x: after a start-up, the CG velocity profile V_x(z) (a Lucy kernel, averaged over the grid's
    x–y nodes and over snapshots) equals the grains' own profile — their mean v_x in slabs one grain
    diameter thick, over the same snapshots — within 2 % of U wherever the layer is, 1.5 diameters
    from the walls; and the profile is a shear (V_x rises by more than U across the layer)."""
    from pdem.geometry.walls import ConstantVelocity

    r, a, (nx, ny, nz) = 0.5e-3, 1.02e-3, (6, 6, 12)
    L, H, U = nx * a, ny * a, 0.05
    top = nz * a
    rng = np.random.default_rng(7)
    idx = np.stack(np.meshgrid(*[np.arange(k) for k in (nx, ny, nz)], indexing="ij"), -1).reshape(-1, 3)
    x = (idx + 0.5) * a + rng.uniform(-0.005, 0.005, idx.shape) * a
    v = np.zeros_like(x)
    v[:, 0] = U * (2.0 * x[:, 2] / top - 1.0)  # start from the linear profile
    sim = pdem.Simulation()
    _material(sim, restitution=0.5, friction=0.5)
    sim.add_particles(x, r, velocities=v)
    sim.set_periodic((0.0, 0.0, -0.01), (L, H, 0.05), "xy")
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="bottom", motion=ConstantVelocity((-U, 0.0, 0.0)))
    sim.add_wall(Plane((0, 0, top), (0, 0, -1)), name="top", motion=ConstantVelocity((U, 0.0, 0.0)))
    sim.dt = 5e-6
    sim.run(steps=4000)
    zs = (np.arange(nz) + 0.5) * a
    grid = Grid((0.0, 0.0, 0.0), (L, H, top), (4, 4, nz))
    cg = CoarseGraining(LucyKernel(2 * r), grid, quantities=["velocity", "density"])
    field, grains = np.zeros(nz), np.zeros(nz)
    for _ in range(10):
        sim.run(steps=200)
        f = cg(sim)
        field += f.velocity[..., 0].mean(axis=(0, 1)) / 10
        p = sim.get_particles()
        slab = np.clip((p["x"][:, 2] // a).astype(int), 0, nz - 1)
        grains += np.bincount(slab, p["v"][:, 0], nz) / np.bincount(slab, minlength=nz) / 10
    inner = (zs > 1.5 * 2 * r) & (zs < top - 1.5 * 2 * r)
    assert grains[inner][-1] - grains[inner][0] > U, grains  # a shear flow, not a plug
    np.testing.assert_allclose(field[inner], grains[inner], rtol=0, atol=0.02 * U)


@pytest.mark.parametrize("kernel", [GaussianKernel(0.6e-3), LucyKernel(2e-3)])
def test_uniform_velocity_is_exact_everywhere_with_any_kernel(kernel):
    """v = V0 for every grain: wherever the density is positive (the lattice's ends included) the
    CG velocity is V0 to round-off, and the strain rate and kinetic stress vanish to round-off
    (relative to |V0|/w and ρ |V0|²)."""
    v0 = np.array([0.25, -0.5, 0.125])
    sim, _ = _lattice(lambda x: np.broadcast_to(v0, x.shape).copy())
    grid = Grid((-1e-3, -1e-3, -3e-3), (3e-3, 3e-3, 39e-3), (5, 5, 60))
    f = coarse_grain(sim, kernel, grid)
    on = f.density > 1e-6 * f.density.max()
    assert on.sum() > 1000 and (~on).sum() > 0
    np.testing.assert_allclose(f.velocity[on], np.broadcast_to(v0, (on.sum(), 3)), rtol=0, atol=1e-14)
    assert np.abs(f.velocity_gradient[on]).max() < 1e-11 * np.abs(v0).max() / kernel.radius
    assert np.abs(f.kinetic_stress[on]).max() < 1e-12 * f.density.max() * (v0 @ v0)
    assert np.all(f.velocity[~on & (f.density == 0)] == 0)


# ---------------------------------------------------------------------------------------------
# API: errors, time averages
# ---------------------------------------------------------------------------------------------


def test_user_errors_are_typed_and_name_the_value():
    with pytest.raises(InputError, match="width"):
        GaussianKernel(-1.0)
    with pytest.raises(InputError, match="cutoff"):
        GaussianKernel(1.0, cutoff=float("nan"))
    with pytest.raises(InputError, match="cutoff = 0.5"):
        GaussianKernel(1.0, cutoff=0.5)
    with pytest.raises(InputError, match="radius"):
        LucyKernel("big")
    with pytest.raises(InputError, match="counts"):
        Grid((0, 0, 0), (1, 1, 1), (4, 0, 4))
    with pytest.raises(InputError, match="hi"):
        Grid((0, 0, 0), (1, -1, 1), (4, 4, 4))
    with pytest.raises(InputError, match="lo"):
        Grid((0, 0), (1, 1, 1), (4, 4, 4))
    with pytest.raises(InputError, match=r"\(m, 3\)"):
        CoarseGraining(LucyKernel(1.0), np.zeros((4, 2)))
    with pytest.raises(InputError, match="kernel"):
        CoarseGraining(1.0, np.zeros((4, 3)))
    with pytest.raises(InputError, match="quantities = .*pressure"):
        CoarseGraining(LucyKernel(1.0), np.zeros((4, 3)), quantities=["density", "pressure"])
    with pytest.raises(InputError, match="quantities"):
        CoarseGraining(LucyKernel(1.0), np.zeros((4, 3)), quantities=[])
    sim, _ = _lattice(lambda x: np.zeros_like(x))
    with pytest.raises(InputError, match="root"):
        coarse_grain(sim, LucyKernel(1e-3), np.zeros((1, 3)), root=3)
    with pytest.raises(InputError, match="periodic images"):  # 10⁶ images of each grain in a 2 mm box
        coarse_grain(sim, GaussianKernel(1e-3, cutoff=1000.0), np.zeros((1, 3)))
    with pytest.raises(InputError, match="no snapshot"):
        TimeAverage(LucyKernel(1e-3), np.zeros((1, 3))).mean()


def test_time_average_is_the_mean_of_the_snapshots():
    sim, _ = _lattice(lambda x: np.column_stack([np.sin(x[:, 2] * 300), 0 * x[:, 0], 0 * x[:, 0]]))
    pts = np.array([[1e-3, 1e-3, 10e-3], [0.5e-3, 1.5e-3, 20.3e-3]])
    avg = TimeAverage(LucyKernel(2e-3), pts)
    snaps = []
    for _ in range(3):
        snaps.append(avg.add(sim))
        sim.run(steps=200)
    mean = avg.mean()
    assert mean.step == 3 and mean.time == pytest.approx(0.5 * (snaps[0].time + snaps[-1].time))
    for name in ("density", "velocity", "kinetic_stress", "strain_rate"):
        ref = sum(getattr(s, name) for s in snaps) / 3
        np.testing.assert_allclose(getattr(mean, name), ref, rtol=1e-15, atol=0)
    assert not np.array_equal(snaps[0].velocity, snaps[-1].velocity)


# ---------------------------------------------------------------------------------------------
# 5: bitwise the same fields on any rank count
# ---------------------------------------------------------------------------------------------

_MPI_SCRIPT = textwrap.dedent(
    """
    import hashlib, sys
    import numpy as np
    import pdem
    from pdem.fields import (CoarseGraining, CylindricalGrid, GaussianKernel, Grid, LucyKernel, TimeAverage,
                             coarse_grain)
    from pdem.geometry.shapes import Plane
    from pdem.parallel.comm import default_comm

    comm = default_comm()
    for law, steps in zip(sys.argv[1::2], map(int, sys.argv[2::2])):
        sim = pdem.Simulation(comm=comm, law=law)
        sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                         friction=0.4)
        r, a, n = 0.5e-3, 0.99e-3, (7, 7, 5)  # a simple cubic lattice, neighbours overlapping by 1 % of d
        rng = np.random.default_rng(4)
        idx = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), axis=-1).reshape(-1, 3)
        x = (idx + 0.5) * a + rng.uniform(-0.01, 0.01, idx.shape) * a
        x[:, 2] -= 0.015 * a
        sim.add_particles(x, r, velocities=rng.normal(0.0, 0.02, x.shape))
        sim.set_periodic((0.0, 0.0, -0.01), (n[0] * a, n[1] * a, 0.05), "xy")
        sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
        sim.add_wall(Plane((0, 0, n[2] * a - 0.03 * a), (0, 0, -1)), name="lid")
        sim.gravity = (0.0, 0.0, -9.81)
        sim.dt = 5e-6 if law == "hertz_mindlin" else 2e-5
        sim.run(steps=steps)
        h = hashlib.sha256()
        grid = Grid((-0.001, -0.001, -0.001), (0.008, 0.008, 0.006), (9, 9, 7))
        pts = np.random.default_rng(5).uniform((-0.002, -0.002, -0.001), (0.01, 0.01, 0.006), (40, 3))
        cyl = CylindricalGrid((0.0035, 0.0035, -0.001), 0.005, 0.007, (5, 12, 7), inner_radius=0.0005)
        kernels = ((GaussianKernel(0.5e-3), grid), (LucyKernel(1.5e-3), grid), (GaussianKernel(0.4e-3), pts),
                   (GaussianKernel(0.5e-3), cyl))
        for kern, where in kernels:
            for name, arr in coarse_grain(sim, kern, where).arrays().items():
                h.update(name.encode())
                h.update(np.ascontiguousarray(arr).tobytes())
        avg = TimeAverage(LucyKernel(1.2e-3), grid)
        for _ in range(2):
            avg.add(sim)
            sim.run(steps=3)
        for arr in avg.mean().arrays().values():
            h.update(np.ascontiguousarray(arr).tobytes())
        for kern, where in kernels:  # each rank's block (a slab of the grid) is the whole's, bit for bit
            cg = CoarseGraining(kern, where)
            whole = cg(sim).arrays()
            plane = 9 * 7 if where is grid else 12 * 7 if where is cyl else 1
            for overlap in (True, False):
                part, first = cg.block(sim, overlap=overlap)
                for name, arr in part.arrays().items():
                    n = arr.shape[0] * plane
                    ref = whole[name].reshape(-1, *whole[name].shape[len(cg.shape):])[first : first + n]
                    assert arr.reshape(ref.shape).tobytes() == ref.tobytes(), (name, overlap)
                counts = comm.allgather(part.density.size)
                if not overlap:
                    assert sum(counts) == whole["density"].size, counts
        whole = coarse_grain(sim, LucyKernel(1.5e-3), grid).arrays()
        for some in (["density"], ["velocity", "fabric"], ["stress"], ["strain_rate"], ["wall_force_density"],
                     ["kinetic_stress", "coordination"]):  # fmt: skip
            part = coarse_grain(sim, LucyKernel(1.5e-3), grid, quantities=some).arrays()
            assert set(part) == {"points", *some}, part.keys()
            for q in some:  # fewer passes and columns, the same bits
                assert part[q].tobytes() == whole[q].tobytes(), q
        f0 = coarse_grain(sim, LucyKernel(1.5e-3), grid, root=0)
        nc, nw = sim.count_contacts(), len(sim.wall_contacts()["id"])
        p = sim.get_particles()
        if comm.rank == 0:
            h.update(f0.stress.tobytes())
            print(law, h.hexdigest(), hashlib.sha256(p["x"].tobytes()).hexdigest(), nc, nw)
        else:
            assert f0 is None
    """
)

#: (law, steps) of each scene: DEM-P, and DEM-C, whose ghosts' positions the fields forward first
_LAWS = ["hertz_mindlin", "100", "complementarity", "20"]


def _fields_hashes(tmp_path, ranks: int) -> list[list[str]]:
    script = tmp_path / "fields.py"
    script.write_text(_MPI_SCRIPT)
    proc = subprocess.run([MPIEXEC, "-n", str(ranks), sys.executable, str(script), *_LAWS],
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return [line.split() for line in proc.stdout.splitlines()]


@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
@pytest.mark.parametrize("ranks", [2, pytest.param(3, marks=pytest.mark.integration),
                                   pytest.param(4, marks=pytest.mark.integration)])  # fmt: skip
def test_fields_are_bitwise_the_same_on_any_rank_count(tmp_path, ranks):
    """A packing in contact with two walls, periodic in x and y, run with DEM-P and with DEM-C on 1
    and on K ranks: every field (two kernels on a grid, arbitrary points, a cylindrical grid, a time
    average, a root-only result, each rank's block) has the same bytes; the contact and wall-contact
    counts show what was summed (pairs across the periodic faces and the ranks' cuts, wall
    contacts)."""
    one = _fields_hashes(tmp_path, 1)
    many = _fields_hashes(tmp_path, ranks)
    assert [row[0] for row in one] == ["hertz_mindlin", "complementarity"], one
    for a, b in zip(one, many, strict=True):
        assert int(a[3]) > 300 and int(a[4]) > 30, a
        assert a[2] == b[2], f"{a[0]}: the simulation itself differs between rank counts"
        assert a == b


# ---------------------------------------------------------------------------------------------
# cylindrical grids
# ---------------------------------------------------------------------------------------------


def test_cylindrical_grid_nodes_volumes_and_components():
    """The nodes of a CylindricalGrid are at the cells' centres in r, θ and z about its axis; its node
    volumes add up to the ring's volume (the midpoint rule is exact for r dr); and a vector and a
    tensor built from e_r, e_θ, e_z come back as their (r, θ, z) components."""
    from pdem.fields import CylindricalGrid, cylindrical_components

    g = CylindricalGrid((0.1, -0.2, 0.05), 0.03, 0.08, (4, 12, 5), inner_radius=0.01)
    assert g.shape == (4, 12, 5)
    p = g.points().reshape(4, 12, 5, 3)
    r = np.hypot(p[..., 0] - 0.1, p[..., 1] + 0.2)
    np.testing.assert_allclose(r[:, 0, 0], 0.01 + (np.arange(4) + 0.5) * 0.005, rtol=1e-12)
    np.testing.assert_allclose(p[0, 0, :, 2], 0.05 + (np.arange(5) + 0.5) * 0.016, rtol=1e-12)
    theta = np.mod(np.arctan2(p[0, :, 0, 1] + 0.2, p[0, :, 0, 0] - 0.1), 2 * np.pi)
    np.testing.assert_allclose(theta, (np.arange(12) + 0.5) * np.pi / 6, rtol=1e-12)
    assert g.node_volumes().sum() == pytest.approx(np.pi * (0.03**2 - 0.01**2) * 0.08, rel=1e-12)
    t = np.arctan2(p[..., 1] + 0.2, p[..., 0] - 0.1)
    er = np.stack([np.cos(t), np.sin(t), 0 * t], -1)
    et = np.stack([-np.sin(t), np.cos(t), 0 * t], -1)
    ez = np.broadcast_to([0.0, 0.0, 1.0], er.shape)
    v = 2.0 * er - 3.0 * et + 0.5 * ez
    np.testing.assert_allclose(g.cylindrical(v), np.broadcast_to([2.0, -3.0, 0.5], v.shape), atol=1e-12)
    dyad = lambda a, b: a[..., :, None] * b[..., None, :]  # noqa: E731
    tensor = 5.0 * dyad(er, er) + 7.0 * dyad(et, et) + 11.0 * dyad(ez, ez)
    tensor += 2.0 * (dyad(er, ez) + dyad(ez, er))
    local = cylindrical_components(tensor, p, (0.1, -0.2))
    expect = np.broadcast_to([[5, 0, 2], [0, 7, 0], [2, 0, 11]], tensor.shape)
    np.testing.assert_allclose(local, expect, atol=1e-12)
    with pytest.raises(InputError, match="inner_radius"):
        CylindricalGrid((0, 0, 0), 0.01, 0.1, (2, 4, 2), inner_radius=0.01)
    with pytest.raises(InputError, match="counts"):
        CylindricalGrid((0, 0, 0), 0.01, 0.1, (2, 0, 2))
    with pytest.raises(InputError, match="vectors"):
        g.cylindrical(np.zeros((4, 12, 5, 2)))


def test_fields_on_a_cylindrical_grid_are_those_at_its_nodes(packing):
    """A CylindricalGrid's fields are, bit for bit, those at its nodes given as a list of points,
    shaped (nr, nθ, nz, …); their (r, θ, z) components keep the stress's trace."""
    from pdem.fields import CylindricalGrid

    sim, period, (zlo, zhi), *_ = packing
    g = CylindricalGrid((0.5 * period, 0.5 * period, zlo), 0.45 * period, zhi - zlo, (3, 8, 4))
    kern = GaussianKernel(0.5e-3)
    f = coarse_grain(sim, kern, g)
    h = coarse_grain(sim, kern, g.points())
    assert f.stress.shape == (3, 8, 4, 3, 3) and h.stress.shape == (96, 3, 3)
    for q in ("density", "stress", "velocity", "fabric"):
        assert getattr(f, q).tobytes() == getattr(h, q).tobytes(), q
    local = g.cylindrical(f.stress)
    trace = np.trace(f.stress, axis1=-2, axis2=-1)
    np.testing.assert_allclose(np.trace(local, axis1=-2, axis2=-1), trace, rtol=1e-12)


def test_a_grid_spanning_huge_distances_gives_fields_not_an_overflow():
    """Grid corners 1e100 m apart (the deck's largest magnitude) with a millimetre kernel: the
    points' cells are counted in floats, so the fields come out (zero far from the grain, its
    density at its node) instead of an integer overflow."""
    sim = pdem.Simulation()
    _material(sim)
    sim.add_particles([[0.0, 0.0, 0.0]], 0.5e-3)
    grid = Grid((-1e100, -1e-3, -1e-3), (1e100, 1e-3, 1e-3), (3, 1, 1))
    points = np.array([[0.0, 0.0, 0.0], [1e100, 0.0, 0.0], [-1e100, 0.0, 0.0]])
    f = coarse_grain(sim, GaussianKernel(1e-3), points)
    g = coarse_grain(sim, GaussianKernel(1e-3), grid)
    assert f.density[0] > 0.0 and f.density[1] == f.density[2] == 0.0
    assert g.density[1, 0, 0] == f.density[0] and g.density[0, 0, 0] == 0.0
