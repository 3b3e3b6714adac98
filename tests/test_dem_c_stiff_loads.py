"""DEM-C under stiff boundary loads: mass scaling (``contact.complementarity.load_mass_scaling``).

A boundary load F(x) enters DEM-C's free velocity explicitly (v += h F/m), which is stable only
while h² k/m < 4 for a load of stiffness k; the triaxial membrane's surface grains reach ~20 at the
automatic step. A boundary declares k (``Simulation.add_load_stiffness``) and the step gives the
grain the mass max(m, h² k). References: the closed form of semi-implicit Euler on a spring (at
h² k/m_eff = 1 the motion repeats every 6 steps exactly), statics (a floor carries the weight and
the load whatever the mass), and the run without scaling, which must blow up (so the tests can
fail)."""

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
from pdem.api import Boundary, BoundaryParams, InputError
from pdem.geometry import shapes

R = 1e-3
RHO = 2500.0
MASS = RHO * 4.0 / 3.0 * math.pi * R**3
H = 1e-3
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")


class Spring(Boundary):
    """Each particle of group 1 is pulled to its anchor by F = f0 − k (x − anchor), and the load's
    stiffness is declared as ``declared`` (default k)."""

    def __init__(self, anchors, k, f0=(0.0, 0.0, 0.0), declared=None):
        super().__init__("spring", BoundaryParams(type="spring"))
        self.anchors = np.asarray(anchors, dtype=float)
        self.k = k
        self.f0 = np.asarray(f0, dtype=float)
        self.declared = k if declared is None else declared

    def apply_forces(self, sim):
        p = sim.particles
        n = p.n_owned
        rows = np.flatnonzero(p.group[:n] == 1)
        p.f[rows] += self.f0 - self.k * (p.x[rows] - self.anchors[p.id[rows]])
        sim.add_load_stiffness(rows, np.full(rows.size, self.declared))


def _sim(scaling=True, gravity=(0.0, 0.0, 0.0)):
    sim = pdem.Simulation(law="complementarity", solver="apgd", tolerance=1e-12, max_iterations=300,
                          load_mass_scaling=scaling)  # fmt: skip
    sim.add_material("glass", density=RHO, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.3)  # fmt: skip
    sim.gravity = gravity
    sim.dt = H
    return sim


def test_a_stiff_spring_load_is_stable_with_the_scaled_mass():
    """h² k/m = 10 (unstable for semi-implicit Euler): scaled to m_eff = h² k, the grain oscillates
    with the closed-form period of 6 steps (eigenvalues e^{±iπ/3}) at its initial amplitude; with
    the true mass the amplitude grows by orders of magnitude."""
    k = 10.0 * MASS / H**2
    d = 1e-4
    out = {}
    for scaling in (True, False):
        sim = _sim(scaling)
        sim.add_particles([[d, 0.0, 0.0]], R, group=1)
        sim.add_boundary(Spring([[0.0, 0.0, 0.0]], k))
        xs = [sim.particles.x[0, 0]]
        for _ in range(60):
            sim.step()
            xs.append(sim.particles.x[0, 0])
        out[scaling] = (np.array(xs), sim)
    xs, sim = out[True]
    np.testing.assert_allclose(xs[6::6], d, rtol=1e-9)
    assert np.abs(xs).max() <= 1.0000001 * d
    assert sim.integrator.summary()["max_mass_ratio"] == pytest.approx(10.0, rel=1e-12)
    assert sim.integrator.summary()["mass_scaled_steps"] == 60
    assert np.abs(out[False][0]).max() > 1e3 * d  # the true mass: unstable


def test_a_soft_load_leaves_the_masses_exact():
    """h² k ≤ m: nothing is scaled, and the run is bitwise the run without scaling."""
    k = 0.5 * MASS / H**2
    runs = []
    for scaling in (True, False):
        sim = _sim(scaling)
        sim.add_particles([[1e-4, 0.0, 0.0], [0.0, 3 * R, 0.0]], R, group=1)
        sim.add_boundary(Spring([[0.0, 0.0, 0.0], [0.0, 2.5 * R, 0.0]], k))
        sim.run(steps=40)
        runs.append(sim.particles.x[:2].copy())
        assert sim.integrator.summary()["mass_scaled_steps"] == 0
    assert np.array_equal(runs[0], runs[1])


@pytest.mark.parametrize("scaling", [True, False])
def test_the_floor_carries_weight_and_load_whatever_the_mass(scaling):
    """A sphere resting on a floor under gravity and a constant load f0, declared 50 × stiffer than
    the step bears: the floor carries m g + |f0| in every step, with and without scaling (an impulse
    balances h F whatever the grain's mass), and the grain stays put."""
    f0 = 20.0 * MASS * 9.81
    sim = _sim(scaling, gravity=(0.0, 0.0, -9.81))
    sim.add_particles([[0.0, 0.0, R]], R, group=1)
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), material="glass", name="floor")
    sim.add_boundary(Spring([[0.0, 0.0, R]], 0.0, f0=(0.0, 0.0, -f0), declared=50.0 * MASS / H**2))
    for _ in range(5):
        sim.step()
        assert sim.walls["floor"].force[2] == pytest.approx(-(MASS * 9.81 + f0), rel=1e-9)
    assert abs(sim.particles.x[0, 2] - R) < 1e-9 * R
    assert sim.integrator.summary()["mass_scaled_steps"] == (5 if scaling else 0)


def test_bad_stiffness_declarations_are_errors():
    sim = _sim()
    sim.add_particles([[0.0, 0.0, 0.0]], R, group=1)
    sim.prepare()
    with pytest.raises(InputError, match="owned"):
        sim.add_load_stiffness([5], [1.0])
    with pytest.raises(InputError, match="finite"):
        sim.add_load_stiffness([0], [-1.0])
    with pytest.raises(InputError, match="rows"):
        sim.add_load_stiffness([0], [1.0, 2.0])


@pytest.mark.integration
def test_membrane_grains_are_scaled_at_the_dem_c_step_and_the_run_stays_bounded(small_packing):
    """The triaxial membrane (300 poured beads, σ3 = 20 kPa at once) at DEM-C's automatic step for
    these grains, h = 1e-4 s: the membrane declares its stiffness (h² k/m ≈ 10 on its stiffest
    grains), the step scales them, and 400 steps of consolidation run and settle, every grain below
    1 m/s in the last 200; with the true masses the first steps throw the surface grains into the
    platens and the run stops on an overlap (or, if it goes on, runs 10× faster)."""
    from pdem.boundaries.triaxial import TriaxialCell, TriaxialParams
    from pdem.errors import InstabilityError
    x, r = small_packing()
    speeds = {}
    for scaling in (True, False):
        # APGD unpreconditioned (scaling = "trace"): preconditioned by the contacts' blocks, the run
        # with the true masses stayed bounded here too (0.067 against 0.046 m/s in the last 200 steps)
        sim = pdem.Simulation(law="complementarity", solver="apgd", max_iterations=80, tolerance=1e-6,
                              apgd_start="warm", recovery_speed=1e-3, load_mass_scaling=scaling,
                              scaling="trace")  # fmt: skip
        sim.add_material("glass", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3,
                         friction=0.3)  # fmt: skip
        sim.add_particles(x, r)
        top = float((x[:, 2] + r).max())
        sim.add_boundary(TriaxialCell("cell", TriaxialParams(
            type="triaxial", material="glass", base_center=(0, 0, 0), radius=3.5e-3, height=top + 1e-5,
            sigma3=2e4, strain_rate=2.0, consolidation_stage="c", shear_stage="s")))  # fmt: skip
        sim.dt = 1e-4
        sim.set_stage("c")
        late = 0.0
        try:
            for step in range(400):
                sim.step()
                v = np.linalg.norm(sim.particles.v[: sim.particles.n_owned], axis=1)
                if step >= 200:
                    late = max(late, float(v.max()))
        except InstabilityError:
            late = math.inf
        speeds[scaling] = late
        if scaling:
            s = sim.integrator.summary()
            assert s["mass_scaled_steps"] == 400 and s["max_mass_ratio"] > 5.0
            assert np.median(v) < 5e-3  # settling (0.001 r a step)
    # (a surface grain out of contact oscillates in the membrane's potential at ~0.3 m/s: the
    # membrane is conservative and undamped, as with DEM-P)
    assert speeds[True] < 1.0
    assert speeds[False] > 10 * speeds[True]


MPI_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    from mpi4py import MPI
    import pdem
    from pdem.boundaries.triaxial import TriaxialCell, TriaxialParams

    pack, out = sys.argv[1], sys.argv[2]
    comm = MPI.COMM_WORLD
    d = np.load(pack)
    sim = pdem.Simulation(comm=comm, law="complementarity", solver="apgd", max_iterations=60,
                          tolerance=1e-7, apgd_start="warm", recovery_speed=1e-3)
    sim.add_material("glass", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.3)
    sim.add_particles(d["x"], d["r"])
    top = float((d["x"][:, 2] + d["r"]).max())
    sim.add_boundary(TriaxialCell("cell", TriaxialParams(
        type="triaxial", material="glass", base_center=(0, 0, 0), radius=3.5e-3, height=top + 1e-5,
        sigma3=2e4, strain_rate=2.0, consolidation_stage="c", shear_stage="s")))
    sim.dt = 1e-4
    sim.set_stage("c")
    sim.run(steps=40)
    sim.set_stage("s")
    sim.run(steps=20)
    p = sim.get_particles()
    s = sim.integrator.summary()
    if comm.rank == 0:
        np.savez(out, x=p["x"], v=p["v"], f=p["f"],
                 scaled=np.array([s["mass_scaled_steps"], s["max_mass_ratio"]]))
    """
)


@pytest.mark.integration
@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
def test_scaled_masses_are_bitwise_identical_on_1_2_3_ranks(tmp_path, small_packing):
    """Ghost copies take their owners' scaled masses (forwarded every scaled step): a DEM-C
    triaxial consolidation and shear with scaled membrane grains is bitwise the same on 1–3 ranks."""
    x, r = small_packing()
    pack = tmp_path / "pack.npz"
    np.savez(pack, x=x, r=r)
    script = tmp_path / "scaled.py"
    script.write_text(MPI_SCRIPT)
    res = {}
    for ranks in (1, 2, 3):
        out = tmp_path / f"s{ranks}.npz"
        proc = subprocess.run([MPIEXEC, "-n", str(ranks), sys.executable, str(script), str(pack), str(out)],
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        res[ranks] = dict(np.load(out))
    assert res[1]["scaled"][0] == 60 and res[1]["scaled"][1] > 3.0
    for ranks in (2, 3):
        for key in res[1]:
            assert np.array_equal(res[1][key], res[ranks][key]), (ranks, key)
