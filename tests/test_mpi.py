"""MPI: identical results on any rank count, and no hang when one rank fails.

These launch ``mpiexec`` (the ``mpich`` wheel provides it) with several ranks, oversubscribed on a
2-core machine."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from decks import HOPPER_PLAIN_DEM_C

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
pytestmark = pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")

# counts what crossed ranks, in every launched rank (a sitecustomize.py put first on PYTHONPATH): per
# rank, the neighbour-list rebuilds, the particles that arrived from another rank at a rebuild, and
# the rebuilds whose pair list held a pair with a ghost
_CROSSING_HOOK = textwrap.dedent(
    """
    import atexit, json, os
    from pdem.neighbor import list as _nl
    _st = {"size": 1, "rank": 0, "rebuilds": 0, "arrivals": 0, "ghost_pair_rebuilds": 0}
    _rebuild = _nl.NeighbourList.rebuild
    def rebuild(self):
        p = self.sim.particles
        before = set(p.id[: p.n_owned].tolist())
        _rebuild(self)
        n = p.n_owned
        if _st["rebuilds"]:
            _st["arrivals"] += sum(1 for i in p.id[:n].tolist() if i not in before)
        cs = self.sim.contact_store
        _st["ghost_pair_rebuilds"] += bool(((cs.pi >= n) | (cs.pj >= n)).any())
        _st["rebuilds"] += 1
        _st["size"], _st["rank"] = self.sim.comm.size, self.sim.comm.rank
    _nl.NeighbourList.rebuild = rebuild
    @atexit.register
    def _dump():
        if _st["rebuilds"]:
            name = f"{_st['size']}_{_st['rank']}_{os.getpid()}.json"
            with open(os.path.join(os.environ["PDEM_TEST_CROSSING"], name), "w") as f:
                json.dump(_st, f)
    """
)


def _run_counting_crossings(cmd, tmp_path):
    """Run ``cmd`` (tools/determinism.py) with the crossing counter; its process and the counts,
    summed over the ranks of each rank count (a 4-rank count run twice, 4 and 4:2x2x1, sums both)."""
    hook, counts = tmp_path / "hook", tmp_path / "crossings"
    hook.mkdir()
    counts.mkdir()
    (hook / "sitecustomize.py").write_text(_CROSSING_HOOK)
    path = os.pathsep.join(filter(None, [str(hook), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path, "PDEM_TEST_CROSSING": str(counts)}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=env)
    print(proc.stdout, proc.stderr)
    per_size: dict[int, dict[str, int]] = {}
    for f in counts.glob("*.json"):
        st = json.loads(f.read_text())
        tot = per_size.setdefault(
            st["size"], {"ranks": 0, "rebuilds": 0, "arrivals": 0, "ghost_pair_rebuilds": 0}
        )
        tot["ranks"] += 1
        tot["rebuilds"] = max(tot["rebuilds"], st["rebuilds"])
        tot["arrivals"] += st["arrivals"]
        tot["ghost_pair_rebuilds"] = max(tot["ghost_pair_rebuilds"], st["ghost_pair_rebuilds"])
    print(per_size)
    return proc, per_size


def _assert_crossed(per_size, sizes, min_rebuilds=5):
    """On every multi-rank count: several rebuilds, particles that changed rank, and ghost pairs at
    half the rebuilds or more (of the rank that had them most often)."""
    for k in sizes:
        c = per_size[k]
        assert c["rebuilds"] >= min_rebuilds, (k, c)
        assert c["arrivals"] > 0, (k, c)
        assert c["ghost_pair_rebuilds"] >= c["rebuilds"] // 2, (k, c)


# a short hopper: 300 beads, a short fill, then the plug opens and beads leave through the outflow
HOPPER_SETS = [
    "particles.0.n=300",
    "particles.0.region.height=0.008",
    "stages.fill.end.time=0.03",
    "stages.fill.end.kinetic_energy_below=1e-12",
    "output.every_time=0.05",
    "boundaries.hopper.outflow_depth=0.004",
]
# the DEM-P runs take 0.35 of the Rayleigh time (the live bound of this small hopper is ~0.46):
# determinism does not need the default's accuracy, and 5,000 steps then reach mid-discharge
HOPPER_DT = ["run.dt_fraction=0.35"]
# the determinism tests' fill: the beads start low in the cone (inside its walls) already falling, so
# they pile on the plug within a 0.01 s fill and, with the outflow 1 mm under the orifice, leave
# through it from the first 0.015 s of the discharge
LOW_FILL = [
    "particles.0.region.base_center=[0.0, 0.0, 0.006]",
    "particles.0.region.radius=0.009",
    "particles.0.region.height=0.014",
    "particles.0.velocity=[0.0, 0.0, -0.5]",
    "stages.fill.end.time=0.01",
    "boundaries.hopper.outflow_depth=0.001",
]


@pytest.mark.integration
def test_hopper_identical_on_1_2_3_ranks(tmp_path):
    """tools/determinism.py: the hopper (grains crossing subdomains, leaving through the sink). 2 and
    3 ranks split it in slabs (3: an interior subdomain with two neighbours); 4 ranks took the same
    paths and are left out."""
    cmd = [
        sys.executable,
        str(ROOT / "tools" / "determinism.py"),
        str(ROOT / "inputs" / "hopper.toml"),
        "--ranks",
        "1",
        "2",
        "3",
        "--steps",
        "1200",
        "--keep",
        str(tmp_path),
    ]
    for s in HOPPER_SETS + HOPPER_DT + LOW_FILL:
        cmd += ["--set", s]
    proc, crossed = _run_counting_crossings(cmd, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("bitwise identical") == 2
    _assert_crossed(crossed, (2, 3))
    # the scene really flowed out: fewer beads than inserted
    last = [ln for ln in proc.stdout.splitlines() if ln.startswith("1 rank")][0]
    assert int(last.split(":")[1].split()[0]) < 300


# DEM-C hopper scenes: restitution and rolling and spinning friction on every contact, so that the
# bounce test and the rolling rows of cross-rank contacts are exercised. Each solver iteration
# exchanges ghost velocities, and with 3-4 ranks oversubscribed on 2 cores every exchange waits for
# a descheduled rank: the tests cap the iterations (15-20, most steps reach the cap, so each rank
# count runs the same number of sweeps through every path) to keep the exchanges few
DEM_C_SETS = HOPPER_SETS + HOPPER_PLAIN_DEM_C + [
    "contact.law=complementarity",
    "materials.glass.restitution=0.6",
    "materials.glass.rolling_friction=0.1",
    "materials.glass.spinning_friction=0.05",
    "materials.steel.rolling_friction=0.1",
    "materials.steel.spinning_friction=0.05",
]


def _dem_c_hopper(ranks, steps, tmp_path, sets=()):
    """tools/determinism.py on the DEM-C hopper: its output, after checking that every rank count
    matched the first bit for bit and that the hopper is mid-discharge."""
    cmd = [sys.executable, str(ROOT / "tools" / "determinism.py"), str(ROOT / "inputs" / "hopper.toml"),
           "--ranks", *map(str, ranks), "--steps", str(steps), "--keep", str(tmp_path)]  # fmt: skip
    for s in [*DEM_C_SETS, *LOW_FILL, *sets]:
        cmd += ["--set", s]
    proc, crossed = _run_counting_crossings(cmd, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("bitwise identical") == len(ranks) - 1
    _assert_crossed(crossed, [k for k in ranks if k > 1])
    left = int([ln for ln in proc.stdout.splitlines() if ln.startswith("1 rank")][0].split(":")[1].split()[0])
    assert 0 < left < 300  # mid-discharge: grains are flowing through the orifice
    for k in ranks:  # real solves: most discharge steps iterate to the cap
        log = np.genfromtxt(tmp_path / f"ranks{k}" / "solver_discharge.csv", delimiter=",", names=True)
        assert np.median(log["iterations"]) > 10, (k, log["iterations"])
    return proc


@pytest.mark.integration
def test_dem_c_jacobi_identical_on_1_2_3_ranks(tmp_path):
    """DEM-C with the distributed projected Jacobi solver: the same hopper, mid-discharge, is
    bitwise identical on 1, 2 and 3 ranks (one ghost-velocity exchange per iteration; 4 ranks took
    the same paths as 3), with restitution and rolling friction on (with them off the kernels take a
    subset of the same path: the regression checksum with restitution off is the stored one of
    before)."""
    _dem_c_hopper((1, 2, 3), 160, tmp_path, ["contact.complementarity.max_iterations=20"])


@pytest.mark.integration
def test_dem_c_apgd_identical_on_1_2_3_ranks(tmp_path):
    """DEM-C with APGD under MPI: the same hopper, mid-discharge, is bitwise identical on 1, 2 and
    3 ranks, and so is every step's iteration count (solver_<stage>.csv): the global sums that
    steer APGD (step size, line search, restart, stop) are exact and count each cross-rank contact
    once."""
    _dem_c_hopper(
        (1, 2, 3),
        160,
        tmp_path,
        ["contact.complementarity.solver=apgd", "contact.complementarity.max_iterations=15"],
    )
    for stage in ("fill", "discharge"):
        logs = [
            np.genfromtxt(tmp_path / f"ranks{k}" / f"solver_{stage}.csv", delimiter=",", names=True)
            for k in (1, 2, 3)
        ]
        for log in logs[1:]:
            assert np.array_equal(log["iterations"], logs[0]["iterations"]), stage
            assert np.array_equal(log["residual"], logs[0]["residual"]), stage
    assert logs[0]["iterations"].max() > 10  # the discharge's solves are real APGD solves
    # the load balancer weighs DEM-C ranks by modelled work: timed, the waits in the solver's
    # collectives made both ranks look equally busy and the grains settling on one rank stayed there
    # (work imbalance max/mean 1.7-2.0 on 2 ranks during the fill of this scene)
    for k in (2, 3):
        for stage in ("fill", "discharge"):
            series = np.genfromtxt(tmp_path / f"ranks{k}" / f"series_{stage}.csv", delimiter=",", names=True)
            assert series["imbalance_work"].max() < 1.35, (k, stage, series["imbalance_work"])


# the periodic column collapse: as many steps as tests/test_periodic.py shows to be enough for beads to
# cross both periodic faces and touch images across them
PERIODIC_DECK = ROOT / "inputs" / "examples" / "periodic_column_collapse.toml"
PERIODIC_STEPS = 1000
# the determinism test's run: 250 steps, about 20 rebuilds with beads changing rank (it asserts both)
PERIODIC_DETERMINISM_STEPS = 250


@pytest.mark.parametrize(
    "rank_counts", [("1", "2"), pytest.param(("1", "3", "4:2x2x1"), marks=pytest.mark.integration)]
)
def test_periodic_column_collapse_identical_across_ranks(tmp_path, rank_counts):
    """tools/determinism.py: periodic x and y; the default grids split x (2 and 3 subdomains, the
    periodic face between two ranks, or the same rank on both sides when split in two; 4 slabs took
    the same paths as 3), and a 2x2x1 grid splits y as well (edges and corners forwarded across both
    periodic faces). The default suite runs 1 and 2 ranks, the integration tier 1, 3 and 2x2x1."""
    cmd = [
        sys.executable,
        str(ROOT / "tools" / "determinism.py"),
        str(PERIODIC_DECK),
        "--ranks",
        *rank_counts,
        "--steps",
        str(PERIODIC_DETERMINISM_STEPS),
        "--keep",
        str(tmp_path),
    ]
    proc, crossed = _run_counting_crossings(cmd, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.count("bitwise identical") == len(rank_counts) - 1
    assert f"400 particles at step {PERIODIC_DETERMINISM_STEPS}" in proc.stdout
    _assert_crossed(crossed, [int(k.split(":")[0]) for k in rank_counts[1:]])


_FAIL = textwrap.dedent(
    """
    import sys
    from mpi4py import MPI
    import pdem.runner as runner
    from pdem.errors import NumericalError
    from pdem.cli import main

    original = runner.Runner._run_stage

    def failing(self, *args, **kwargs):
        if MPI.COMM_WORLD.Get_rank() == 1:
            raise NumericalError("injected failure on rank 1")
        return original(self, *args, **kwargs)

    runner.Runner._run_stage = failing
    sys.exit(main(sys.argv[1:]))
    """
)


def test_failure_on_one_rank_ends_every_rank(tmp_path):
    script = tmp_path / "fail.py"
    script.write_text(_FAIL)
    deck = ROOT / "inputs" / "hopper.toml"
    cmd = [
        MPIEXEC,
        "-n",
        "3",
        sys.executable,
        str(script),
        str(deck),
        "--output",
        str(tmp_path / "out"),
        "--quiet",
    ]
    for s in HOPPER_SETS:
        cmd += ["--set", s]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    elapsed = time.perf_counter() - t0
    assert "injected failure on rank 1" in proc.stderr
    assert proc.returncode == 3, (proc.returncode, proc.stderr[-2000:])
    assert elapsed < 120, f"the job took {elapsed:.0f} s to end"


@pytest.mark.integration
def test_checkpoint_written_on_2_ranks_resumes_on_3(tmp_path):
    """n -> m resume: 2 ranks to step 2500, checkpoint, 3 ranks to 5000 (mid-discharge)
    == 1 rank to 5000, bitwise."""
    sys.path.insert(0, str(ROOT / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    def pdem(ranks, *args):
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, "-m", "pdem.cli", *map(str, args), "--quiet"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]

    sets = [a for s in HOPPER_SETS + HOPPER_DT for a in ("--set", s)]
    deck = ROOT / "inputs" / "hopper.toml"
    pdem(1, deck, "--steps", 5000, "--output", "full", *sets)
    pdem(2, deck, "--steps", 2500, "--output", "part", *sets)
    pdem(3, "resume", "part/checkpoints/latest.h5", "--steps", 5000, "--output", "resumed")
    full, _ = read_checkpoint(tmp_path / "full" / "checkpoints" / "latest.h5")
    resumed, _ = read_checkpoint(tmp_path / "resumed" / "checkpoints" / "latest.h5")
    assert int(full["scalars/step"]) == int(resumed["scalars/step"]) == 5000
    assert compare(full, resumed) is None


@pytest.mark.integration
def test_periodic_checkpoint_written_on_2_ranks_resumes_on_3(tmp_path):
    """n -> m resume across periodic faces: 2 ranks to step 500, 3 ranks on to 1000 == 1 rank to 1000."""
    sys.path.insert(0, str(ROOT / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    def pdem(ranks, *args):
        cmd = [MPIEXEC, "-n", str(ranks), sys.executable, "-m", "pdem.cli", *map(str, args), "--quiet"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-2000:]

    pdem(1, PERIODIC_DECK, "--steps", PERIODIC_STEPS, "--output", "full")
    pdem(2, PERIODIC_DECK, "--steps", PERIODIC_STEPS // 2, "--output", "part")
    pdem(3, "resume", "part/checkpoints/latest.h5", "--steps", PERIODIC_STEPS, "--output", "resumed")
    full, _ = read_checkpoint(tmp_path / "full" / "checkpoints" / "latest.h5")
    half, _ = read_checkpoint(tmp_path / "part" / "checkpoints" / "latest.h5")
    resumed, _ = read_checkpoint(tmp_path / "resumed" / "checkpoints" / "latest.h5")
    assert int(full["scalars/step"]) == int(resumed["scalars/step"]) == PERIODIC_STEPS
    assert compare(full, resumed) is None
    # the checkpoint holds contacts across a periodic face
    ids, x, keys = half["particles/id"], half["particles/x"], half["pairs/keys"]
    raw = x[np.searchsorted(ids, keys & 0xFFFFFFFF)] - x[np.searchsorted(ids, keys >> 32)]
    period = half["domain/hi"] - half["domain/lo"]
    assert np.any(np.abs(raw[:, :2]) > 0.5 * period[:2])


_RESOLVE_SCRIPT = textwrap.dedent(
    """
    import hashlib, sys
    import numpy as np, pdem
    from pdem.parallel.comm import default_comm
    R = 1e-3
    comm = default_comm()
    sim = pdem.Simulation(law="complementarity", solver=sys.argv[1], tolerance=1e-10, max_iterations=300,
                          comm=comm)
    sim.add_material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.0,
                     friction=0.3)
    xs, vs = [], []
    for row in range(6):  # strikers touching a resting sphere that sits 0.2 r from a third
        for g in range(5):
            x0, y = g * 12 * R, row * 2.5 * R
            xs += [[x0, y, 0], [x0 + 2.0 * R, y, 0], [x0 + 4.2 * R, y, 0]]
            vs += [[3.0, 0.1 * row, 0], [0, 0, 0], [0, 0, 0]]
    sim.add_particles(xs, R, material="glass", velocities=vs)
    sim.dt = 2e-4
    sim.max_overlap = 10.0
    sim.run(steps=20)
    p = sim.get_particles()
    o = np.argsort(p["id"])
    h = hashlib.sha256(p["x"][o].tobytes() + p["v"][o].tobytes()).hexdigest()
    if comm.rank == 0:
        print(h, sim.integrator.n_resolves)
    """
)


@pytest.mark.integration
@pytest.mark.parametrize("solver", ["jacobi", "apgd"])
def test_dem_c_envelope_second_solve_identical_on_1_2_3_ranks(tmp_path, solver):
    """Steps solved a second time because the per-contact envelope left out a contact that an impulse
    closed (docs/dem_c.md): the decision is collective, so the run stays bitwise identical on 1, 2 and
    3 ranks, and the second solve really happens."""
    script = tmp_path / "resolve.py"
    script.write_text(_RESOLVE_SCRIPT)
    out = {}
    for n in (1, 2, 3):
        proc = subprocess.run([MPIEXEC, "-n", str(n), sys.executable, str(script), solver],
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        out[n] = proc.stdout.split()
    assert int(out[1][1]) >= 1
    assert out[1] == out[2] == out[3]


_ADD_SCRIPT = textwrap.dedent(
    """
    import hashlib
    import numpy as np, pdem
    from pdem.geometry.shapes import Plane
    from pdem.parallel.comm import default_comm
    comm = default_comm()
    rng = np.random.default_rng(2)
    sim = pdem.Simulation(comm=comm)
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.4)
    g = np.stack(np.meshgrid(np.arange(8), np.arange(3), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    sim.add_particles(g * 2.1e-3 + [1e-3, 1e-3, 1e-3], 1e-3)
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)))
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 2e-5
    sim.run(steps=300)
    # a second preparation: a falling layer added over the bed; the automatic skin goes on
    sim.add_particles(g[:24] * 2.1e-3 + [1e-3, 1e-3, 0.012], 1e-3, velocities=rng.normal(0, 0.3, (24, 3)))
    sim.run(steps=600)
    p = sim.get_particles()
    h = hashlib.sha256(p["x"].tobytes() + p["v"].tobytes()).hexdigest()
    if comm.rank == 0:
        print(h)
    """
)


@pytest.mark.integration
def test_particles_added_after_a_run_identical_on_1_2_3_ranks(tmp_path):
    """Grains added after a run (a second preparation, which chooses the automatic skin again and
    fits it to the subdomains): the same bits on 1, 2 and 3 ranks."""
    script = tmp_path / "add.py"
    script.write_text(_ADD_SCRIPT)
    out = {}
    for n in (1, 2, 3):
        proc = subprocess.run([MPIEXEC, "-n", str(n), sys.executable, str(script)],
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        out[n] = proc.stdout.split()
    assert out[1][0] == out[2][0] == out[3][0]


_UNSTABLE_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np, pdem
    from pdem.geometry.shapes import Plane
    from pdem.errors import InstabilityError
    from pdem.parallel.comm import default_comm
    comm = default_comm()
    steps, every = int(sys.argv[1]), int(sys.argv[2])
    sim = pdem.Simulation(comm=comm)
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.4)
    g = np.stack(np.meshgrid(np.arange(8), np.arange(3), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    sim.add_particles(g * 2.1e-3 + [1e-3, 1e-3, 1e-3], 1e-3)
    # a projectile at 50 m/s, a radius a step: its first contact overlaps past max_overlap
    sim.add_particles(np.array([[8.35e-3, 3.1e-3, 0.06]]), 1e-3, velocities=np.array([[0.0, 0.0, -50.0]]))
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)))
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 2e-5
    seen = []
    try:
        sim.run(steps=steps, callback=lambda s: seen.append(s.step_count), every=every)
        line = f"{comm.rank} ran {sim.step_count}"
    except InstabilityError as exc:
        at = str(exc).split("at step ")[1].split()[0]
        drift = "drift" in str(exc)
        line = f"{comm.rank} raised {at} {sim.step_count} {len(seen)} {seen[-1] if seen else -1} {drift}"
    lines = comm.allgather(line)  # every rank is here (an error is raised on all ranks alike)
    if comm.rank == 0:
        print("\\n".join(lines))
    """
)


@pytest.mark.integration
@pytest.mark.parametrize("steps,every", [(200, 1), (200, 7), (200, 500)])
def test_instability_raised_at_the_same_step_on_1_2_3_ranks(tmp_path, steps, every):
    """A step's stability check is deferred to the next step's list test on several ranks
    (Simulation.step(defer_check=True), which run() uses between callbacks): the error names the
    same step on every rank count, every rank raises it, and no callback sees the failed step."""
    script = tmp_path / "unstable.py"
    script.write_text(_UNSTABLE_SCRIPT)
    found, drifts = {}, {}
    for n in (1, 2, 3):
        proc = subprocess.run([MPIEXEC, "-n", str(n), sys.executable, str(script), str(steps), str(every)],
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        lines = sorted(proc.stdout.split("\n")[:-1])
        assert len(lines) == n and all(ln.split()[1] == "raised" for ln in lines), proc.stdout
        found[n] = {tuple(ln.split()[2:6]) for ln in lines}
        assert len(found[n]) == 1, found  # every rank raised the same error at the same point
        drifts[n] = {ln.split()[6] for ln in lines}
    at, count, calls, last = (int(v) for v in next(iter(found[1])))
    assert found[2] == found[3] == found[1]
    # a deferred check (several ranks, no callback at the failed step) says that the overlap it
    # quotes was found after the next step's drift
    deferred = at % every != 0
    assert drifts == {1: {"False"}, 2: {str(deferred)}, 3: {str(deferred)}}, (at, every, drifts)
    assert 20 < at < steps and count == at
    assert calls == (at - 1) // every and last < at  # the failed step was never handed to a callback


@pytest.mark.integration
def test_instability_on_the_last_step_is_raised_by_run(tmp_path):
    """A run that ends on the failed step still raises (run() checks what it deferred)."""
    script = tmp_path / "unstable.py"
    script.write_text(_UNSTABLE_SCRIPT)
    proc = subprocess.run([MPIEXEC, "-n", "1", sys.executable, str(script), "200", "500"],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    at = int(proc.stdout.split()[2])
    proc = subprocess.run([MPIEXEC, "-n", "2", sys.executable, str(script), str(at), "500"],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.split("\n")[:-1]
    assert len(lines) == 2 and all(ln.split()[1:3] == ["raised", str(at)] for ln in lines), proc.stdout
    assert all(ln.split()[6] == "False" for ln in lines)  # run()'s own last check: nothing drifted


@pytest.mark.integration
def test_jacobi_bound_tool_agrees_on_1_and_2_ranks(tmp_path):
    """tools/jacobi_bound.py on the short DEM-C hopper (rolling friction on): the loaded contacts'
    count and λ_max of B N at each measure are the same on 2 ranks as serially (exact global sums,
    each cross-rank contact counted once)."""
    sets = [*HOPPER_SETS, *HOPPER_PLAIN_DEM_C, "contact.law=complementarity",
            "materials.glass.rolling_friction=0.1", "materials.steel.rolling_friction=0.1"]  # fmt: skip
    tables = {}
    for n in (1, 2):
        cmd = [MPIEXEC, "-n", str(n), sys.executable, str(ROOT / "tools" / "jacobi_bound.py"),
               "--every", "100", "--csv", str(tmp_path / f"b{n}.csv"), str(ROOT / "inputs" / "hopper.toml"),
               "--steps", "400", "--output", str(tmp_path / f"o{n}"), "--quiet"]  # fmt: skip
        for s in sets:
            cmd += ["--set", s]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
        tables[n] = np.loadtxt(tmp_path / f"b{n}.csv", delimiter=",", skiprows=1)
    assert tables[1].shape == (4, 7)
    assert tables[1][-1, 2] > 50  # loaded contacts at the last measure: a pile has formed
    assert np.array_equal(tables[1][:, :3], tables[2][:, :3])
    assert np.allclose(tables[2][:, 3:], tables[1][:, 3:], rtol=1e-9, atol=0.0)


_POUR_SCRIPT = textwrap.dedent(
    """
    import hashlib, sys
    from pdem.materials import Material
    from pdem.parallel.comm import default_comm
    from pdem.sources import pluviate
    from pdem.sources.regions import BoxRegion, CylinderRegion
    from pdem.sources.sizes import Uniform
    comm = default_comm()
    mat = Material("g", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.1, friction=0.3)
    sizes = Uniform(0.9e-3, 1.1e-3)
    if sys.argv[1] == "blocks":  # a fill of several blocks (of about 300 spheres) to pour from
        import pdem.sources.random_fill
        sys.modules["pdem.sources.random_fill"].BLOCK_SPHERES = 300
        sizes = Uniform(0.45e-3, 0.55e-3)
    if sys.argv[1] == "cylinder":
        container = CylinderRegion((0.001, -0.002, 0.0), 0.008, 0.05)
    else:
        container = BoxRegion((0.0, 0.0, 0.0), (0.012, 0.009, 0.05))
    x, r = pluviate(container, sizes, int(sys.argv[2]), mat, seed=3, comm=comm)
    line = hashlib.sha256(x.tobytes() + r.tobytes()).hexdigest() + f" {len(r)}"
    lines = comm.allgather(line)
    if comm.rank == 0:
        print("\\n".join(lines))
    """
)


@pytest.mark.parametrize(
    "container,n,ranks",
    [("cylinder", 300, 2), pytest.param("box", 400, 3, marks=pytest.mark.integration),
     pytest.param("blocks", 1500, 2, marks=pytest.mark.integration)],
)  # fmt: skip
def test_pour_shared_over_ranks_is_the_serial_pour(tmp_path, container, n, ranks):
    """A pour (``source = "pluviate"``) runs as one MPI simulation over the run's ranks: every rank
    gets the whole packing, bitwise the packing of the serial pour (the same script on one rank);
    also when its loose fill is made in blocks, each rank making its own."""
    script = tmp_path / "pour.py"
    script.write_text(_POUR_SCRIPT)
    out = {}
    for k in (1, ranks):
        proc = subprocess.run([MPIEXEC, "-n", str(k), sys.executable, str(script), container, str(n)],
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        out[k] = proc.stdout.split("\n")[:k]
    assert len(set(out[ranks])) == 1, out  # every rank holds the same packing
    assert out[ranks][0] == out[1][0] and out[1][0].endswith(f" {n}")


_OWN_CONTACTS_SCRIPT = textwrap.dedent(
    """
    import numpy as np, pdem
    from pdem.geometry.shapes import Plane
    from pdem.parallel.comm import default_comm
    from pdem.sources import random_fill
    from pdem.sources.regions import BoxRegion
    from pdem.sources.sizes import Uniform
    comm = default_comm()
    sim = pdem.Simulation(comm=comm)
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.3,
                     friction=0.4)
    x, r = random_fill(BoxRegion((0, 0, 0), (0.012, 0.012, 0.008)), Uniform(0.45e-3, 0.55e-3), n=700, seed=5)
    sim.add_particles(x, r)
    sim.set_periodic((0.0, 0.0, -0.01), (0.012, 0.012, 0.05), "xy")
    sim.add_wall(Plane((0, 0, 0), (0, 0, 1)), name="floor")
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 5e-6
    sim.run(steps=4000)
    full, walls = sim.contacts(), sim.wall_contacts()
    own = comm.allgather(sim.own_contacts())
    mine = {k: np.concatenate([o[k] for o in own]) for k in own[0]}
    order = np.lexsort((mine["id_j"], mine["id_i"]))
    mine = {k: v[order] for k, v in mine.items()}
    ok = all(np.array_equal(mine[k], full[k]) for k in full)
    p = sim.get_particles()
    branch = p["x"][mine["id_j"]] - p["x"][mine["id_i"]]
    branch -= np.round(branch / 0.012) * 0.012 * np.array([1, 1, 0])  # the nearest periodic image
    ok &= bool(np.allclose(mine["branch"], branch, rtol=0, atol=1e-12))
    ok &= sim.count_contacts() == len(full["id_i"]) > 200
    ow = comm.allgather(sim.own_wall_contacts())
    ow = {k: np.concatenate([o[k] for o in ow]) for k in ow[0]}
    o2 = np.lexsort((ow["id"], ow["row"], ow["wall"]))
    ok &= all(np.array_equal(ow[k][o2], walls[k]) for k in walls) and len(walls["id"]) > 20
    ok &= bool(np.array_equal(ow["r"][o2], p["r"][walls["id"]]))
    terms = np.einsum("ka,kb->kab", sim.own_contacts()["branch"], sim.own_contacts()["force"]).reshape(-1, 9)
    sums = sim.exact_column_sums(terms)
    if comm.rank == 0:
        print(ok, sums.tobytes().hex(), len(full["id_i"]))
    """
)


@pytest.mark.parametrize("ranks", [2, pytest.param(3, marks=pytest.mark.integration)])
def test_own_contacts_are_a_partition_of_the_contacts(tmp_path, ranks):
    """Each rank's ``own_contacts`` (and ``own_wall_contacts``), together, are ``contacts()`` (and
    ``wall_contacts()``) exactly, with every pair once, including pairs across rank boundaries and
    across the periodic faces; the branch vectors are the nearest images'; ``count_contacts`` is
    their number; a stress sum over the shares with ``exact_column_sums`` is bitwise the serial one."""
    script = tmp_path / "own.py"
    script.write_text(_OWN_CONTACTS_SCRIPT)
    out = {}
    for k in (1, ranks):
        proc = subprocess.run([MPIEXEC, "-n", str(k), sys.executable, str(script)],
                              capture_output=True, text=True, timeout=600)  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-2000:]
        out[k] = proc.stdout.split()
        assert out[k][0] == "True", out[k]
    assert out[1] == out[ranks]
