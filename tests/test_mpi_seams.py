"""The engine seams under MPI: a scene with a shrinking cylinder, a mesh floor, a rigid ball dropped
on the grains, a boundary force inside the step and a registered per-particle field is bitwise
identical on 1, 2 and 3 ranks, with DEM-P and with DEM-C (Jacobi, trace-scaled, and APGD; the ball is
solved with the grains, its impulses summed exactly across ranks every iteration)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from decks import TRIAXIAL_SMALL_PACKED

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
pytestmark = pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")

SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    from mpi4py import MPI
    import pdem
    from pdem.api import Boundary, BoundaryParams, Resize, RigidBody, shapes

    method, steps, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    law = "complementarity" if method == "apgd" else method
    comm = MPI.COMM_WORLD
    R = 1e-3

    class Push(Boundary):
        def apply_forces(self, sim):
            p = sim.particles
            n = p.n_owned
            sel = p.group[:n] == 1
            p.f[:n][sel] += (2e-5, 0.0, 0.0)

    sim = pdem.Simulation(comm=comm, law=law)
    if method == "complementarity":  # the trace-scaled Jacobi sweep (tests/test_mpi.py runs block)
        sim.set_law(law, scaling="trace")
    elif method == "apgd":  # APGD preconditioned by the contacts' Delassus blocks (the default)
        sim.set_law(law, solver="apgd", max_iterations=40)
    sim.add_material("glass", density=2500, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.3)
    sim.gravity = (0, 0, -9.81)
    sim.register_field("tag", "float64", output=True)
    k = np.arange(6 * 6 * 4)
    x = np.stack([(k % 6 - 2.5) * 2.2 * R, (k // 6 % 6 - 2.5) * 2.2 * R, 1.1 * R + (k // 36) * 2.2 * R], 1)
    rng = np.random.default_rng(4)
    x += rng.uniform(-0.05 * R, 0.05 * R, x.shape)
    sim.add_particles(x, R, group=(k % 5 == 0).astype(int), tag=k * 0.5)
    floor = shapes.TriangleMesh([[-9e-3, -9e-3, 0], [9e-3, -9e-3, 0], [9e-3, 9e-3, 0], [-9e-3, 9e-3, 0]],
                                [[0, 1, 2], [0, 2, 3]])
    sim.add_wall(floor, name="floor")
    cell = shapes.Cylinder((0, 0, 0), (0, 0, 1), 9.0 * R)
    sim.add_wall(cell, name="cell", motion=Resize({"radius": -0.05}))
    ball = RigidBody(mass=2e-4, gravity=(0, 0, -9.81), velocity=(0, 0, -0.2), fixed_translation="xy")
    sim.add_wall(shapes.Sphere((0, 0, 0.0121), 3 * R), name="ball", motion=ball)
    sim.add_boundary(Push("push", BoundaryParams(type="push")))
    sim.dt = 2e-6 if law == "hertz_mindlin" else 1e-4
    sim.run(steps=steps)
    p = sim.get_particles()
    w = sim.walls["ball"]
    state = (w.offset.copy(), w.velocity.copy(), w.force, sim.walls["floor"].facet_loads())
    if comm.rank == 0:
        np.savez(out, x=p["x"], v=p["v"], w=p["w"], f=p["f"], tag=p["tag"], id=p["id"],
                 ball_offset=state[0], ball_velocity=state[1], ball_force=state[2], facets=state[3])
    """
)


# the default suite runs each scene on 1 and 2 ranks, the integration tier on 1 and 3 (3 ranks
# oversubscribe a 2-core machine: most of these tests' time is starting processes and waiting for them)
@pytest.mark.parametrize(
    "law, steps, rank_counts",
    [
        ("hertz_mindlin", 3000, (1, 2)),
        ("complementarity", 90, (1, 2)),
        ("apgd", 90, (1, 2)),
        pytest.param("hertz_mindlin", 3000, (1, 3), marks=pytest.mark.integration),
        pytest.param("complementarity", 90, (1, 3), marks=pytest.mark.integration),
    ],
)
def test_seams_identical_across_ranks(tmp_path, law, steps, rank_counts):
    script = tmp_path / "scene.py"
    script.write_text(SCRIPT)
    results = {}
    for ranks in rank_counts:
        out = tmp_path / f"r{ranks}.npz"
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, str(script), law, str(steps), str(out)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        results[ranks] = dict(np.load(out))
    ref = results[1]
    t = steps * (2e-6 if law == "hertz_mindlin" else 1e-4)
    assert ref["ball_velocity"][2] > -0.2 - 9.81 * t + 0.03  # the grains slowed the ball down
    assert np.abs(ref["facets"][:, 2]).min() > 0.0  # both facets of the mesh floor carry grains
    assert np.array_equal(ref["tag"], ref["id"] * 0.5)
    for ranks in rank_counts[1:]:
        for key in ref:
            assert np.array_equal(ref[key], results[ranks][key]), (ranks, key)


TRIAXIAL = textwrap.dedent(
    """
    import sys
    import numpy as np
    from mpi4py import MPI
    import pdem
    from pdem.boundaries.triaxial import TriaxialCell, TriaxialParams

    pack, out, consolidation, shear = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    max_speed = float(sys.argv[5]) if len(sys.argv) > 5 else 0.05
    comm = MPI.COMM_WORLD
    d = np.load(pack)
    sim = pdem.Simulation(comm=comm)
    sim.add_material("glass", density=2500, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.3)
    sim.add_particles(d["x"], d["r"])
    top = float((d["x"][:, 2] + d["r"]).max())
    cell = TriaxialCell("cell", TriaxialParams(
        type="triaxial", material="glass", base_center=(0, 0, 0), radius=3.5e-3, height=top + 1e-5,
        sigma3=2e4, strain_rate=2.0, consolidation_stage="c", shear_stage="s", max_speed=max_speed))
    sim.add_boundary(cell)
    sim.dt = 2e-6
    sim.set_stage("c")
    loops = []
    sim.run(steps=consolidation, callback=lambda s: loops.append(cell.loop_gain))
    sim.set_stage("s")
    sim.run(steps=shear)
    p = sim.get_particles()
    m = cell.measurements(sim)
    if comm.rank == 0:
        np.savez(out, x=p["x"], v=p["v"], f=p["f"], m=np.array([m[k] for k in sorted(m)]),
                 loop=np.array(loops))
    """
)


def _triaxial_on(tmp_path, ranks_list, packing, *args):
    x, r = packing
    pack = tmp_path / "pack.npz"
    np.savez(pack, x=x, r=r)
    script = tmp_path / "triaxial.py"
    script.write_text(TRIAXIAL)
    res = {}
    for ranks in ranks_list:
        out = tmp_path / f"t{ranks}.npz"
        proc = subprocess.run([MPIEXEC, "-n", str(ranks), sys.executable, str(script), str(pack), str(out),
                               *args], capture_output=True, text=True, timeout=600)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-3000:]
        res[ranks] = dict(np.load(out))
    for ranks in ranks_list[1:]:
        for key in res[1]:
            assert np.array_equal(res[1][key], res[ranks][key]), (ranks, key)
    return res[1]


@pytest.mark.parametrize(
    "rank_counts, consolidation, shear",
    [((1, 2), 500, 300), pytest.param((1, 2, 3), 1000, 800, marks=pytest.mark.integration)],
)
def test_triaxial_identical_across_ranks(tmp_path, small_packing, rank_counts, consolidation, shear):
    """The membrane's outermost grains are a global maximum and its forces act on owned grains, and
    the platen servo's gain is capped (max_speed = 1 m/s: its loop gain from the stiffness and
    dashpots of the platen's contacts, exact sums over ranks) in most steps: the triaxial test is
    bitwise identical on any number of ranks."""
    res = _triaxial_on(tmp_path, rank_counts, small_packing(), str(consolidation), str(shear), "1.0")
    assert np.count_nonzero(res["loop"] > 1.0) > 0.3 * consolidation  # the cap acted


@pytest.mark.integration
def test_triaxial_deck_identical_on_1_and_4_ranks(tmp_path):
    """The whole small triaxial deck through the CLI (its beads read from a file, a mould stage at
    its own friction, seating, consolidation with the pressure ramp, shear): the final checkpoint on
    4 ranks is bitwise the serial one."""
    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    deck = root / "tests" / "data" / "triaxial_small.toml"
    states = {}
    for ranks in (1, 4):
        out = tmp_path / f"r{ranks}"
        cmd = [sys.executable, "-m", "pdem", str(deck), "--output", str(out), "--quiet",
               *TRIAXIAL_SMALL_PACKED]  # fmt: skip
        if ranks > 1:
            cmd = [MPIEXEC, "-n", str(ranks), *cmd]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, proc.stderr[-3000:]
        states[ranks], _ = read_checkpoint(out / "checkpoints" / "latest.h5")
    assert int(states[1]["scalars/step"]) == 1600
    assert compare(states[1], states[4]) is None
