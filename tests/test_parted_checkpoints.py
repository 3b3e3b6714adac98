"""Checkpoints written per rank: a manifest and one part per rank, read back on any rank count.

A run on more than one rank writes each rank's particles and contacts to its own part; no rank
gathers the others'. The tests check that such a checkpoint, read whole, is the serial run's state
bit for bit; that it resumes bitwise on more and on fewer ranks; that a damaged, missing or swapped
part is refused; that a kill -9 at any point of a checkpoint write leaves the previous checkpoint
usable (and the next resume removes the killed write's parts); and that a resumed 2-rank run never
holds every particle on one rank.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from decks import TINY_LATTICE

from pdem.io.checkpoint import BadCheckpointError, read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
from determinism import compare  # noqa: E402

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
pytestmark = pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")

# 64 grains above a floor, 40 steps, a checkpoint every 10
DECK = TINY_LATTICE.replace("steps = 20\n", "steps = 40\n")
SETS = ["--set", "output.checkpoint_every_steps=10"]


def pdem(cwd: Path, ranks: int, *args, ok: bool = True, script: str | None = None):
    head = [sys.executable, "-c", script] if script else [sys.executable, "-m", "pdem.cli"]
    cmd = ([MPIEXEC, "-n", str(ranks)] if ranks > 1 else []) + head + [str(a) for a in args] + ["--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=cwd)
    if ok:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """A serial run and a 2-rank run of the deck, side by side."""
    tmp = tmp_path_factory.mktemp("parted")
    (tmp / "deck.toml").write_text(DECK)
    pdem(tmp, 1, "deck.toml", "--output", "serial", *SETS)
    pdem(tmp, 2, "deck.toml", "--output", "two", *SETS)
    return tmp


def checkpoints(run: Path) -> Path:
    return run / "checkpoints"


def parts_of(manifest: Path) -> Path:
    with h5py.File(manifest, "r") as fh:
        return manifest.with_name(json.loads(fh.attrs["pdem_parts"])["dir"])


def test_two_ranks_write_one_part_each_and_read_whole_it_is_the_serial_state(runs):
    ck = checkpoints(runs / "two")
    for step in (10, 20, 30, 40):
        manifest = ck / f"step_{step:010d}.h5"
        parts = parts_of(manifest)
        assert sorted(p.name for p in parts.iterdir()) == ["rank_00000.h5", "rank_00001.h5"]
        with h5py.File(manifest, "r") as fh:  # the manifest holds no particle
            assert "particles" not in fh and "pairs" not in fh
            table = json.loads(fh.attrs["pdem_parts"])
        assert table["particles"] == 64 and table["layout"]["ranks"] == 2
        counts = []
        for part in sorted(parts.iterdir()):
            with h5py.File(part, "r") as fh:
                counts.append(fh["particles/id"].shape[0])
        assert sum(counts) == 64 and 0 < min(counts)  # each rank wrote its own grains only
        serial, _ = read_checkpoint(checkpoints(runs / "serial") / f"step_{step:010d}.h5")
        whole, _ = read_checkpoint(manifest)
        assert sorted(whole) == sorted(serial)
        assert compare(serial, whole) is None
    assert not list(ck.glob("*.tmp"))


@pytest.mark.parametrize("ranks", [pytest.param(3, marks=pytest.mark.integration), 1])
def test_a_per_rank_checkpoint_resumes_bitwise_on_other_rank_counts(runs, tmp_path, ranks):
    """2 → 3 and 2 → 1 ranks, and (3 → 1) the 3-rank resume's own checkpoints read back serially."""
    source = runs / "two"
    pdem(tmp_path, ranks, "resume", source / "checkpoints" / "step_0000000020.h5", "--output", "again")
    serial, _ = read_checkpoint(checkpoints(runs / "serial") / "latest.h5")
    again, _ = read_checkpoint(checkpoints(tmp_path / "again") / "latest.h5")
    assert int(again["scalars/step"]) == 40
    assert compare(serial, again) is None
    if ranks == 3:  # three parts, resumed serially
        assert len(list(parts_of(checkpoints(tmp_path / "again") / "step_0000000030.h5").iterdir())) == 3
        pdem(tmp_path, 1, "resume", "again/checkpoints/step_0000000030.h5", "--output", "three_to_one")
        back, _ = read_checkpoint(checkpoints(tmp_path / "three_to_one") / "latest.h5")
        assert compare(serial, back) is None


def _damaged_copy(runs: Path, tmp_path: Path) -> tuple[Path, Path]:
    run = tmp_path / "two"
    shutil.copytree(runs / "two", run, symlinks=True)
    manifest = checkpoints(run) / "step_0000000030.h5"
    return manifest, parts_of(manifest)


def test_a_changed_part_is_refused_naming_it(runs, tmp_path):
    manifest, parts = _damaged_copy(runs, tmp_path)
    with h5py.File(parts / "rank_00001.h5", "a") as fh:
        x = fh["particles/x"][()]
        x[3, 2] = np.nextafter(x[3, 2], 1.0)
        fh["particles/x"][...] = x
    with pytest.raises(BadCheckpointError) as exc:
        read_checkpoint(manifest)
    text = str(exc.value)
    assert "rank_00001.h5" in text and "particles/x" in text and "SHA-256" in text
    assert "step_0000000020.h5" in text  # the earlier checkpoint to go on from


def test_a_missing_part_is_refused(runs, tmp_path):
    manifest, parts = _damaged_copy(runs, tmp_path)
    (parts / "rank_00000.h5").unlink()
    with pytest.raises(BadCheckpointError, match="rank_00000.h5 is missing"):
        read_checkpoint(manifest)


def test_a_part_of_another_checkpoint_is_refused(runs, tmp_path):
    manifest, parts = _damaged_copy(runs, tmp_path)
    other = parts_of(checkpoints(tmp_path / "two") / "step_0000000020.h5")
    shutil.copy(other / "rank_00001.h5", parts / "rank_00001.h5")
    with pytest.raises(BadCheckpointError, match="not the part the manifest lists"):
        read_checkpoint(manifest)


def test_a_damaged_part_is_refused_on_every_rank_before_anything_changes(runs, tmp_path):
    """Under MPI each rank checks only the parts it reads; the damage one rank finds stops all."""
    manifest, parts = _damaged_copy(runs, tmp_path)
    with h5py.File(parts / "rank_00001.h5", "a") as fh:
        fh["particles/w"][...] = fh["particles/w"][()] + 1.0
    before = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*"))
    proc = pdem(tmp_path, 2, "resume", manifest, ok=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "rank_00001.h5" in proc.stderr and "particles/w" in proc.stderr
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == before


# kill -9 inside a checkpoint write: at the third checkpoint (step 30), a rank kills itself
_KILL = textwrap.dedent(
    """
    import os, signal, sys
    from mpi4py import MPI
    import pdem.io.parted as parted
    from pdem.cli import main

    where = os.environ["PDEM_TEST_KILL"]
    rank = MPI.COMM_WORLD.rank
    count = {"part": 0, "manifest": 0, "latest": 0}
    write, latest = parted.write_hdf5, parted.point_latest

    def write_hdf5(path, state, attrs, fmt):
        kind = "manifest" if str(path).endswith(".tmp") else "part"
        out = write(path, state, attrs, fmt)
        count[kind] += 1
        if where == kind and count[kind] == 3 and rank == (1 if kind == "part" else 0):
            if kind == "part":  # half a file
                os.truncate(path, os.path.getsize(path) // 2)
            os.kill(os.getpid(), signal.SIGKILL)
        return out

    def point_latest(path):
        count["latest"] += 1
        if where == "latest" and count["latest"] == 3 and rank == 0:
            os.kill(os.getpid(), signal.SIGKILL)
        return latest(path)

    parted.write_hdf5, parted.point_latest = write_hdf5, point_latest
    sys.exit(main(sys.argv[1:]))
    """
)


@pytest.mark.parametrize(
    "where",
    [
        pytest.param("part", marks=pytest.mark.integration),
        "manifest",
        pytest.param("latest", marks=pytest.mark.integration),
    ],
)
def test_kill_9_during_a_checkpoint_write_leaves_the_previous_one_usable(runs, tmp_path, where, monkeypatch):
    monkeypatch.setenv("PDEM_TEST_KILL", where)
    (tmp_path / "deck.toml").write_text(DECK)
    proc = pdem(tmp_path, 2, "deck.toml", "--output", "run", *SETS, ok=False, script=_KILL)
    assert proc.returncode != 0
    ck = checkpoints(tmp_path / "run")
    state, _ = read_checkpoint(ck / "latest.h5")  # complete, checked
    assert int(state["scalars/step"]) == 20
    strays = {p.name for p in ck.iterdir() if ".parts-" in p.name} - {
        parts_of(m).name for m in ck.glob("step_*.h5") if not m.is_symlink()
    }
    assert bool(strays) == (where != "latest")  # the killed write's parts, named by no manifest
    if where == "latest":  # the manifest was in place: that checkpoint is whole too
        assert int(read_checkpoint(ck / "step_0000000030.h5")[0]["scalars/step"]) == 30
    pdem(tmp_path, 3, "resume", "run/checkpoints/step_0000000020.h5")
    serial, _ = read_checkpoint(checkpoints(runs / "serial") / "latest.h5")
    resumed, _ = read_checkpoint(ck / "latest.h5")
    assert compare(serial, resumed) is None
    named = {parts_of(m).name for m in ck.glob("step_*.h5") if not m.is_symlink()}
    assert {p.name for p in ck.iterdir() if ".parts-" in p.name} == named  # no stray parts left
    assert not list(ck.glob("*.tmp"))
    for m in ck.glob("step_*.h5"):
        read_checkpoint(m)


# a 2-rank resume from per-rank checkpoints: the largest particle storage any rank asks for
_LARGEST = textwrap.dedent(
    """
    import json, sys
    from mpi4py import MPI
    import pdem.io.state as state
    import pdem.parallel.comm as comm
    import pdem.simulation as simulation
    import pdem.state.particles as particles
    from pdem.cli import main

    largest = [0]
    reserve = particles.ParticleStore.reserve

    def reserve_counted(self, n):
        largest[0] = max(largest[0], int(n))
        return reserve(self, n)

    def refuse(*args, **kwargs):
        raise AssertionError("every particle gathered on one rank")

    particles.ParticleStore.reserve = reserve_counted
    state.gather_by_id = simulation.gather_by_id = comm.gather_by_id = refuse
    code = main(sys.argv[2:])
    with open(f"{sys.argv[1]}.{MPI.COMM_WORLD.rank}", "w") as fh:
        json.dump(largest[0], fh)
    sys.exit(code)
    """
)


def test_a_two_rank_run_never_holds_every_particle_on_one_rank(tmp_path):
    """512 grains from a lattice (a partitioned source: each rank makes its own) with per-rank
    snapshots and checkpoints: no rank's particle storage (owned + ghosts) ever reaches all 512 and
    nothing gathers particles by id, neither in a fresh 2-rank run nor in a 2-rank resume from its
    per-rank checkpoint. The count is seen to catch a gather: a run whose lattice is made whole on
    every rank (the source's partitioning switched off) reaches 512."""
    deck = DECK.replace("hi = [0.004, 0.004, 0.004]", "hi = [0.008, 0.008, 0.008]")
    (tmp_path / "deck.toml").write_text(deck)
    sets = [*SETS, "--set", "output.parallel='per_rank'"]
    pdem(tmp_path, 2, "fresh", "deck.toml", "--output", "run", "--steps", 20, *sets, script=_LARGEST)
    pdem(tmp_path, 2, "resumed", "resume", "run/checkpoints/latest.h5", script=_LARGEST)
    for label in ("fresh", "resumed"):
        sizes = [json.loads((tmp_path / f"{label}.{r}").read_text()) for r in (0, 1)]
        assert 0 < max(sizes) < 512, (label, sizes)
    whole = _LARGEST.replace("= refuse", "= comm.gather_by_id").replace(
        "from pdem.cli import main", "from pdem.cli import main\nimport pdem.sources.builtin as b\n"
        "b.LatticeSource.partitioned = False"
    )
    pdem(tmp_path, 2, "whole", "deck.toml", "--output", "whole", "--steps", 1, *sets, script=whole)
    sizes = [json.loads((tmp_path / f"whole.{r}").read_text()) for r in (0, 1)]
    assert min(sizes) >= 512, sizes


LATTICE_TABLE = """source = "lattice"
lattice = "sc"
material = "glass"
radius = 0.5e-3
region = { type = "box", lo = [0.0, 0.0, 0.0], hi = [0.004, 0.004, 0.004] }
"""
assert LATTICE_TABLE in TINY_LATTICE
FILE_TABLE = 'source = "file"\nmaterial = "glass"\npath = "packing.txt"\n'
FILE_DECK = TINY_LATTICE.replace(LATTICE_TABLE, FILE_TABLE).replace("steps = 20\n", "steps = 30\n")


@pytest.mark.parametrize("ranks", [2, pytest.param(3, marks=pytest.mark.integration)])
def test_a_packing_file_read_in_parts_runs_bitwise_as_serially(tmp_path, ranks):
    """A shuffled packing file (ids in space, the default): each rank reads the file in chunks and
    keeps its own spheres (no rank reserves storage for all 1,500); the run is bitwise the serial
    one, rows included."""
    from pdem.sources import random_fill, write_spheres_text
    from pdem.sources.regions import BoxRegion
    from pdem.sources.sizes import Uniform

    x, r = random_fill(BoxRegion((0, 0, 0), (0.016, 0.012, 0.02)), Uniform(0.4e-3, 0.6e-3), n=1500, seed=9)
    perm = np.random.default_rng(4).permutation(len(r))
    write_spheres_text(tmp_path / "packing.txt", x[perm], r[perm])
    (tmp_path / "deck.toml").write_text(FILE_DECK)
    pdem(tmp_path, 1, "deck.toml", "--output", "serial")
    pdem(tmp_path, ranks, "parts", "deck.toml", "--output", "parts", script=_LARGEST)
    sizes = [json.loads((tmp_path / f"parts.{k}").read_text()) for k in range(ranks)]
    assert 0 < max(sizes) < 1500, sizes
    serial, _ = read_checkpoint(checkpoints(tmp_path / "serial") / "latest.h5")
    parts, _ = read_checkpoint(checkpoints(tmp_path / "parts") / "latest.h5")
    assert compare(serial, parts) is None
    assert np.array_equal(serial["particles/row"], parts["particles/row"])


@pytest.mark.integration
def test_bitwise_identical_on_1_to_8_ranks_with_per_rank_checkpoints(tmp_path):
    """512 lattice grains falling on a floor, 40 steps: the final state, read from per-rank
    checkpoints of 2-8 ranks (oversubscribed on small machines), is bitwise the serial one."""
    deck = DECK.replace("hi = [0.004, 0.004, 0.004]", "hi = [0.008, 0.008, 0.008]")
    (tmp_path / "deck.toml").write_text(deck)
    pdem(tmp_path, 1, "deck.toml", "--output", "r1", *SETS)
    serial, _ = read_checkpoint(checkpoints(tmp_path / "r1") / "latest.h5")
    for ranks in range(2, 9):
        pdem(tmp_path, ranks, "deck.toml", "--output", f"r{ranks}", *SETS)
        state, _ = read_checkpoint(checkpoints(tmp_path / f"r{ranks}") / "latest.h5")
        assert compare(serial, state) is None, ranks
        assert len(list(parts_of(checkpoints(tmp_path / f"r{ranks}") / "latest.h5").iterdir())) == ranks


def _parts_without_gather(tmp_path: Path, deck: str, ranks: int, n: int, script: str = _LARGEST) -> None:
    """Run ``deck`` serially and on ``ranks`` ranks under ``script`` (the largest particle storage
    counted, gathers by id refused on several ranks): no rank reserves storage for all ``n`` grains,
    and the final state is bitwise the serial one."""
    (tmp_path / "deck.toml").write_text(deck)
    serial_script = script.replace("= refuse", "= comm.gather_by_id")  # (a serial run gathers trivially)
    pdem(tmp_path, 1, "serial", "deck.toml", "--output", "serial", script=serial_script)
    pdem(tmp_path, ranks, "parts", "deck.toml", "--output", "parts", script=script)
    sizes = [json.loads((tmp_path / f"parts.{k}").read_text()) for k in range(ranks)]
    assert 0 < max(sizes) < n, sizes
    serial, _ = read_checkpoint(checkpoints(tmp_path / "serial") / "latest.h5")
    parts, _ = read_checkpoint(checkpoints(tmp_path / "parts") / "latest.h5")
    assert serial["particles/id"].shape[0] == n
    assert compare(serial, parts) is None


FILL_TABLE = """source = "random_fill"
material = "glass"
region = { type = "box", lo = [0.0, 0.0, 0.0], hi = [0.03, 0.03, 0.02] }
sizes = { type = "uniform", r_min = 0.4e-3, r_max = 0.6e-3 }
n = 1500
"""
FILL_DECK = TINY_LATTICE.replace(LATTICE_TABLE, FILL_TABLE)


@pytest.mark.parametrize("ranks", [2, pytest.param(3, marks=pytest.mark.integration)])
def test_a_random_fill_made_in_blocks_runs_bitwise_as_serially(tmp_path, ranks):
    """1,500 spheres filled at random in blocks of about 300: each rank makes only the blocks over
    its subdomain (no rank reserves storage for all 1,500) and the run is bitwise the serial one."""
    blocks = _LARGEST.replace(
        "from pdem.cli import main",
        "from pdem.cli import main\nimport pdem.sources.random_fill\n"
        "sys.modules['pdem.sources.random_fill'].BLOCK_SPHERES = 300",
    )
    _parts_without_gather(tmp_path, FILL_DECK, ranks, 1500, blocks)


POUR_TABLE = """source = "pluviate"
material = "glass"
region = { type = "cylinder", base_center = [0.002, 0.002, 0.0], radius = 0.006, height = 0.02 }
sizes = { type = "uniform", r_min = 0.45e-3, r_max = 0.55e-3 }
n = 400
"""
POUR_DECK = TINY_LATTICE.replace(LATTICE_TABLE, POUR_TABLE)


@pytest.mark.parametrize("ranks", [2, pytest.param(3, marks=pytest.mark.integration)])
def test_a_pour_shared_over_ranks_never_gathers_and_runs_bitwise_as_serially(tmp_path, ranks):
    """400 beads poured (one MPI pour over the run's ranks): the settled packing stays spread over
    the ranks that poured it, each rank is handed the beads in its own subdomain (no rank reserves
    storage for all 400, nothing gathers by id), and the run is bitwise the serial one."""
    _parts_without_gather(tmp_path, POUR_DECK, ranks, 400)
