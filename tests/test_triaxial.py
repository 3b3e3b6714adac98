"""The triaxial cell: a flexible membrane (the outermost grain of each (θ, z) cell loaded with σ₃ ×
its patch area), platens servo-controlled to σ₃ then driven at a constant strain rate.

Independent references: the outermost grain of each cell by brute force; the grains' own average
stress from their contacts (Love–Weber) against the boundary stresses; top against bottom platen
load (no gravity: they must carry the same force); the free bulging of the specimen."""

from __future__ import annotations

import math

import numpy as np
import pytest

import pdem
from pdem.boundaries.triaxial import TriaxialCell, TriaxialParams
from pdem.sources import CylinderRegion, Uniform, pluviate

R0 = 3.5e-3
SIGMA3 = 20e3
MAT = dict(density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3, friction=0.3)


@pytest.fixture(scope="module")
def packing():
    mat = pdem.Material("glass", **MAT)
    x, r = pluviate(CylinderRegion((0, 0, 0), R0, 0.03), Uniform(0.45e-3, 0.55e-3), 300, mat, seed=5)
    return x, r


def _cell(packing, law="hertz_mindlin", rate=2.0):
    x, r = packing
    sim = pdem.Simulation(law=law)
    sim.add_material("glass", **MAT)
    sim.add_particles(x, r)
    top = float((x[:, 2] + r).max())
    cell = TriaxialCell("cell", TriaxialParams(
        type="triaxial", material="glass", base_center=(0, 0, 0), radius=R0, height=top + 1e-5,
        sigma3=SIGMA3, strain_rate=rate, consolidation_stage="consolidate", shear_stage="shear"))  # fmt: skip
    sim.add_boundary(cell)
    sim.dt = 2e-6 if law == "hertz_mindlin" else 1e-4
    return sim, cell


def test_membrane_loads_the_outermost_grain_of_each_cell(packing):
    sim, cell = _cell(packing)
    sim.set_stage("consolidate")
    sim.prepare()
    sim.compute_forces()  # contacts + the membrane (apply_forces)
    f, _lever, rhat = cell._applied
    x, r = packing
    # brute force: the grain of largest ρ + r in every occupied cell
    nz, nt, filled = cell._cells
    h = cell.height()
    rho = np.hypot(x[:, 0], x[:, 1])
    kt = np.minimum(((np.arctan2(x[:, 1], x[:, 0]) + math.pi) / (2 * math.pi) * nt).astype(int), nt - 1)
    kz = np.clip((x[:, 2] / h * nz).astype(int), 0, nz - 1)
    cells = kz * nt + kt
    best = {}
    for i in np.lexsort((np.arange(len(x)), -(rho + r))):
        best.setdefault(int(cells[i]), i)
    assert len(best) == filled == len(f)
    loaded = np.flatnonzero(np.any(sim.particles.f[: len(x)] != 0.0, axis=1))  # no contacts yet? use forces
    expected = sorted(best.values())
    # every winner got a force −σ3 R Δθ Δz ρ̂ (horizontal, inward), and nobody else did
    got = np.array(sorted(np.flatnonzero(np.isin(np.arange(len(x)), expected))))
    assert np.array_equal(got, expected)
    assert np.all(f[:, 2] == 0.0)
    assert np.all(np.einsum("ij,ij->i", f, rhat) < 0)
    dth, dz = 2 * math.pi / nt, h / nz
    total = -np.einsum("ij,ij->i", f, rhat).sum()
    radii = np.array([rho[i] + r[i] for i in expected])
    assert total == pytest.approx(SIGMA3 * radii.sum() * dth * dz, rel=1e-12)
    assert loaded.size >= len(expected)


def test_membrane_band_shares_each_cells_load(packing):
    """With ``membrane_band`` the grains near a cell's outermost share its load (weights linear in
    their distance below it, brute force here): the total load is the same as with the outermost
    grain alone, more grains carry it, and each cell's shares sum to its patch load."""
    x, r = packing
    totals = {}
    for band in (0.0, 0.5):
        sim, cell = _cell(packing)
        cell.params = cell.params.model_copy(update={"membrane_band": band})
        sim.set_stage("consolidate")
        sim.prepare()
        sim.compute_forces()
        f, _lever, rhat = cell._applied
        totals[band] = (-np.einsum("ij,ij->i", f, rhat).sum(), len(f))
    nz, nt, filled = cell._cells
    assert totals[0.5][0] == pytest.approx(totals[0.0][0], rel=1e-12)
    assert totals[0.5][1] > totals[0.0][1] == filled
    # brute force of the weights: cell by cell, from the grains' own positions
    h, size = cell.height(), cell._size
    rho = np.hypot(x[:, 0], x[:, 1])
    val = rho + r
    kt = np.minimum(((np.arctan2(x[:, 1], x[:, 0]) + math.pi) / (2 * math.pi) * nt).astype(int), nt - 1)
    kz = np.clip((x[:, 2] / h * nz).astype(int), 0, nz - 1)
    cells = kz * nt + kt
    band = 0.5 * 0.5 * size
    expected = 0.0
    for c in np.unique(cells):
        v = val[cells == c]
        wt = (v[v > v.max() - band] - (v.max() - band)) / band
        assert wt.max() == pytest.approx(1.0)
        expected += SIGMA3 * v.max() * (2 * math.pi / nt) * (h / nz) * (wt / wt.sum()).sum()
    assert totals[0.5][0] == pytest.approx(expected, rel=1e-12)


def test_boundary_stresses_agree_with_the_grains_own_stress(packing):
    sim, cell = _cell(packing)
    sim.set_stage("consolidate")
    sim.run(until=0.015)
    m = cell.measurements(sim)
    top, bottom = sim.walls["cell.top"].force[2], -sim.walls["cell.bottom"].force[2]
    assert top == pytest.approx(bottom, rel=0.03)  # no gravity: the column carries one force
    assert m["sigma1"] == pytest.approx(SIGMA3, rel=0.1)  # the servo brings σ1 to σ3
    assert m["lw_szz"] == pytest.approx(m["sigma1"], rel=0.03)
    assert m["lw_srr"] == pytest.approx(m["sigma3"], rel=0.05)
    assert m["sigma3"] == pytest.approx(SIGMA3, rel=1e-9)  # the membrane's applied load / its area


def test_shearing_bulges_the_specimen_and_mobilises_friction(packing):
    sim, cell = _cell(packing)
    sim.set_stage("consolidate")
    sim.run(until=0.012)
    sim.set_stage("shear")
    sim.run(until=sim.time + 1e-4)
    r0 = cell.measurements(sim)["radius"]
    sim.run(until=sim.time + 0.04)  # ε_a ≈ 8 % at 2 /s
    m = cell.measurements(sim)
    assert m["eps_a"] == pytest.approx(0.08, abs=0.005)
    assert m["q"] > 0.2 * SIGMA3  # friction mobilised (μ = 0.3)
    assert m["radius"] > r0 * 1.005  # free to bulge: no rigid wall around it
    assert m["lw_szz"] == pytest.approx(m["sigma1"], rel=0.05)


@pytest.mark.slow  # ~45 s: APGD at its iteration cap every step
def test_dem_c_consolidates_under_load_control(packing):
    """Rigid grains: the top platen is a free plate under σ3 A (solved with the grains). The
    platen stress averages σ3, and the grains' own (Love–Weber) stress, from the impulses of every
    contact, agrees with the boundary's (rigid grains touch at a gap ≥ 0: a contact counted only
    when it overlapped left most of them out, and the grains' stress read ~20–65 % of it)."""
    sim, cell = _cell(packing, law="complementarity")
    sim.set_law("complementarity", solver="apgd")
    sim.set_stage("consolidate")
    sim.run(until=0.025)
    rows = []
    sim.run(until=0.04, callback=lambda s: rows.append(cell.measurements(s)), every=10)
    assert isinstance(sim.walls["cell.top"].motion, pdem.api.RigidBody)
    s1 = np.array([m["sigma1"] for m in rows])
    assert np.mean(s1) == pytest.approx(SIGMA3, rel=0.1)
    assert np.mean([m["lw_szz"] for m in rows]) == pytest.approx(np.mean(s1), rel=0.1)
    assert np.mean([m["lw_srr"] for m in rows]) == pytest.approx(SIGMA3, rel=0.1)


def test_dem_c_seats_the_platen_as_a_free_plate(packing):
    """Force control in the mould stage (DEM-C): the platen comes down at max_speed from above the
    grains, becomes a free plate at the first contact, and then carries the seating load (the
    grains stay un-overloaded: a velocity servo reading impulses drove them past 0.25 r)."""
    x, r = packing
    sim = pdem.Simulation(law="complementarity")
    sim.set_law("complementarity", solver="apgd", max_iterations=300)
    sim.add_material("glass", **MAT)
    sim.add_particles(x, r)
    top = float((x[:, 2] + r).max())
    seat = 2e3
    cell = TriaxialCell("cell", TriaxialParams(
        type="triaxial", material="glass", base_center=(0, 0, 0), radius=R0, height=top + 1e-3,
        sigma3=SIGMA3, strain_rate=2.0, max_speed=0.1, seating_stress=seat, mould_stages=["settle"],
        consolidation_stage="consolidate", shear_stage="shear"))  # fmt: skip
    sim.add_boundary(cell)
    sim.dt = 1e-4
    sim.set_stage("settle")
    sim.run(until=0.012)  # 1 mm at 0.1 m/s: touching
    assert isinstance(sim.walls["cell.top"].motion, pdem.api.RigidBody)
    assert cell.state()["seated"] is True
    s1 = []
    sim.run(until=0.03, callback=lambda s: s1.append(float(cell.top.force[2]) / (math.pi * R0**2)), every=5)
    assert np.mean(s1[len(s1) // 2 :]) == pytest.approx(seat, rel=0.15)


def test_resume_at_every_stage_is_bitwise(tmp_path):
    """Kill points in each stage (settle, consolidation with its pressure ramp, shear with its
    strain references): `pdem resume` continues bit for bit as the uninterrupted run."""
    import sys
    from pathlib import Path

    from pdem.cli import main
    from pdem.io.checkpoint import read_checkpoint

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "tools"))
    from determinism import compare

    deck = root / "tests" / "data" / "triaxial_small.toml"
    assert main([str(deck), "--output", str(tmp_path / "full"), "--quiet"]) == 0
    ref, _ = read_checkpoint(tmp_path / "full" / "checkpoints" / "latest.h5")
    for stop in (150, 600, 1300):  # settle, consolidate (ramp), shear
        out = tmp_path / f"stop{stop}"
        assert main([str(deck), "--output", str(out), "--quiet", "--steps", str(stop)]) == 0
        assert main(["resume", str(out / "checkpoints" / "latest.h5"), "--quiet"]) == 0
        got, _ = read_checkpoint(out / "checkpoints" / "latest.h5")
        assert int(got["scalars/step"]) == 1600
        assert compare(ref, got) is None, stop


def test_a_misspelt_mould_stage_is_a_deck_error(tmp_path):
    from pathlib import Path

    from pdem.cli import main

    text = (Path(__file__).resolve().parent / "data" / "triaxial_small.toml").read_text()
    deck = tmp_path / "deck.toml"
    deck.write_text(text.replace('mould_stages = ["settle"]', 'mould_stages = ["setle"]'))
    assert main(["check", str(deck), "--deck-only"]) == 2
