"""MPI ranks agree on what they run.

A first stage without grains runs on any rank count (the cut planes are placed when the first grains
are added, as if they had been there from the start) and gives the serial run's bits. Ranks launched
with different arguments or decks (an MPMD launch, ``mpiexec -n 1 pdem a.toml : -n 1 pdem b.toml``)
all exit 2 at once with a message naming the ranks and what differs, instead of running a mixed scene
or waiting for each other forever. Every launch has a timeout, so a hang fails the test.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from test_cli_hostile import TINY

from pdem.parallel.agree import check_same_command, fingerprint, input_file, launched_comm

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
needs_mpi = pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
PDEM = [sys.executable, "-m", "pdem.cli"]
TIMEOUT = 120

# TINY with a first stage that has no grains: the lattice is inserted at the start of "drop"
EMPTY_FIRST = TINY.replace('[[stages]]\nname = "drop"', '[[stages]]\nname = "wait"\n[stages.end]\nsteps = 3\n'
                           '[[stages]]\nname = "drop"').replace(
    'source = "lattice"', 'source = "lattice"\nstage = "drop"'
)  # fmt: skip


def _launch(*blocks: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``mpiexec`` with one block per ``:``-separated group of ranks (``[-n, k, ..., args]``)."""
    cmd = [MPIEXEC]
    for k, block in enumerate(blocks):
        cmd += ([":"] if k else []) + [str(a) for a in block]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT, cwd=cwd)


def test_the_empty_first_stage_deck_is_what_it_says():
    assert EMPTY_FIRST.count("[[stages]]") == 2 and 'stage = "drop"' in EMPTY_FIRST


@pytest.mark.integration
@needs_mpi
def test_empty_first_stage_on_2_ranks_equals_the_serial_run(tmp_path):
    sys.path.insert(0, str(ROOT / "tools"))
    from determinism import compare

    from pdem.io.checkpoint import read_checkpoint

    deck = tmp_path / "deck.toml"
    deck.write_text(EMPTY_FIRST)
    state = {}
    for ranks in (1, 2):
        proc = _launch(["-n", ranks, *PDEM, deck, "--output", f"out{ranks}", "--quiet"], cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        state[ranks], _ = read_checkpoint(tmp_path / f"out{ranks}" / "checkpoints" / "latest.h5")
    assert len(state[1]["particles/id"]) == 64
    assert int(state[1]["scalars/step"]) == 23
    assert compare(state[1], state[2]) is None


_PLACE = textwrap.dedent(
    """
    import hashlib, json, sys
    import numpy as np, pdem
    from pdem.geometry.shapes import Plane
    from pdem.parallel.comm import default_comm

    comm = default_comm()
    g = np.stack(np.meshgrid(np.arange(3), np.arange(3), np.arange(12), indexing="ij"), -1).reshape(-1, 3)
    out = {}
    for empty_first in (False, True):
        sim = pdem.Simulation(comm=comm)
        sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3,
                         restitution=0.3, friction=0.4)
        sim.add_wall(Plane((0, 0, 0), (0, 0, 1)))
        sim.gravity = (0.0, 0.0, -9.81)
        sim.dt = 2e-5
        if empty_first:
            sim.run(steps=5)  # decomposed without a grain
        sim.add_particles(g * 2.1e-3 + [1e-3, 1e-3, 1e-3], 1e-3)
        sim.run(steps=100)
        d = sim.decomposition
        p = sim.get_particles()
        out[str(empty_first)] = {
            "dims": list(d.dims) if d else None,
            "cuts": [c.tolist() for c in d.cuts] if d else None,
            "owned": comm.allgather(int(sim.particles.n_owned)),
            "rebalances": d.n_rebalances if d else 0,
            "bits": hashlib.sha256(p["x"].tobytes() + p["v"].tobytes()).hexdigest(),
        }
    if comm.rank == 0:
        print(json.dumps(out))
    """
)


@pytest.mark.integration
@needs_mpi
def test_grains_of_a_later_stage_are_decomposed_as_if_there_from_the_start(tmp_path):
    """A column of 108 grains added after 5 steps without any: on 3 ranks the grid and cut planes
    are those of a run that had them at its first step (split along the column's height, a third of
    the grains each), and the trajectory is the serial one."""
    import json

    script = tmp_path / "place.py"
    script.write_text(_PLACE)
    found = {}
    for ranks in (1, 3):
        proc = _launch(["-n", ranks, sys.executable, script], cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        found[ranks] = json.loads(proc.stdout)
    at_start, later = found[3]["False"], found[3]["True"]
    assert at_start["dims"] == [1, 1, 3]
    assert later["dims"] == at_start["dims"] and later["cuts"] == at_start["cuts"]
    assert later["owned"] == at_start["owned"] and min(later["owned"]) >= 30, later
    assert later["rebalances"] == at_start["rebalances"]
    assert found[1]["True"]["bits"] == found[1]["False"]["bits"] == later["bits"] == at_start["bits"]


def _decks(tmp_path: Path) -> tuple[Path, Path]:
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.write_text(TINY)
    b.write_text(TINY.replace("hi = [0.004, 0.004, 0.004]", "hi = [0.004, 0.004, 0.002]"))  # 32 grains
    return a, b


@needs_mpi
def test_two_decks_in_an_mpmd_launch_exit_2_on_every_rank(tmp_path):
    a, b = _decks(tmp_path)
    proc = _launch(["-n", 1, *PDEM, a.name, "--output", "out"], ["-n", 2, *PDEM, b.name, "--output", "out"],
                   cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-3000:]
    err = proc.stderr
    assert "the 3 MPI ranks were not given the same pdem arguments" in err, err
    assert "rank 0: 'a.toml --output out'" in err and "ranks 1-2: 'b.toml --output out'" in err, err
    assert "launch them all with one command, e.g. mpiexec -n 3 pdem a.toml --output out" in err, err
    assert "Traceback" not in err and not (tmp_path / "out").exists()


@needs_mpi
def test_a_different_set_in_an_mpmd_launch_exits_2(tmp_path):
    a, _ = _decks(tmp_path)
    args = [*PDEM, a.name, "--output", "out", "--set"]
    proc = _launch(["-n", 1, *args, "run.seed=1"], ["-n", 1, *args, "run.seed=2"], cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    shown = "rank 0: 'a.toml --output out --set run.seed=1'; rank 1: 'a.toml --output out --set run.seed=2'"
    assert shown in proc.stderr, proc.stderr
    assert not (tmp_path / "out").exists()


@needs_mpi
def test_the_same_arguments_naming_different_decks_exit_2(tmp_path):
    """Two working directories whose deck.toml differ (nodes with their own copies): the arguments
    agree, the deck's bytes do not; a missing deck is named as such."""
    a, b = _decks(tmp_path)
    for name, deck in (("one", a), ("two", b), ("three", None)):
        (tmp_path / name).mkdir()
        if deck is not None:
            shutil.copy(deck, tmp_path / name / "deck.toml")
    args = [*PDEM, "deck.toml", "--output", str(tmp_path / "out")]
    proc = _launch(["-n", 1, "-wdir", tmp_path / "one", *args], ["-n", 1, "-wdir", tmp_path / "two", *args],
                   ["-n", 1, "-wdir", tmp_path / "three", *args], cwd=tmp_path)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-3000:]
    err = proc.stderr
    assert "given the same arguments, but the deck file 'deck.toml' differs between them" in err, err
    assert f"rank 0: {a.stat().st_size} bytes, sha256 " in err and "rank 2: missing" in err, err
    assert "every rank must read the same deck file" in err, err
    assert not (tmp_path / "out").exists()


@needs_mpi
def test_identical_commands_in_an_mpmd_launch_still_run(tmp_path):
    a, _ = _decks(tmp_path)
    args = [*PDEM, a.name, "--output", "out", "--quiet"]
    proc = _launch(["-n", 1, *args], ["-n", 1, *args], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "20 steps" in proc.stdout and "64 particles" in proc.stdout, proc.stdout


# ----------------------------------------------------------------------------- without MPI


def test_a_serial_command_does_not_start_mpi(tmp_path):
    """Outside a launcher no check is made and MPI is not started for it (pdem check never starts
    MPI)."""
    a, _ = _decks(tmp_path)
    code = (
        "import sys; from pdem.cli import main; rc = main(['check', sys.argv[1], '--deck-only']); "
        "print(rc, 'mpi4py.MPI' in sys.modules)"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PMI", "OMPI_", "MV2_", "PMIX"))}
    proc = subprocess.run([sys.executable, "-c", code, str(a)], capture_output=True, text=True, env=env,
                          timeout=TIMEOUT)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split()[-2:] == ["0", "False"], proc.stdout


def test_launched_comm_reads_the_launchers_environment(monkeypatch):
    for name in ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MV2_COMM_WORLD_SIZE", "PMIX_RANK"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.delitem(sys.modules, "mpi4py.MPI", raising=False)  # as if MPI were not started
    assert launched_comm() is None
    monkeypatch.setenv("PMI_SIZE", "1")
    monkeypatch.setenv("PMIX_RANK", "0")
    assert launched_comm() is None  # one rank: nothing to agree on, MPI not started
    assert "mpi4py.MPI" not in sys.modules


@pytest.mark.parametrize(
    "argv, found",
    [
        (["a.toml", "--steps", "5"], ("deck file", "a.toml")),
        (["--set", "x=1", "--ou", "o.toml", "--steps=3", "a.toml"], ("deck file", "a.toml")),
        (["--overwrite", "a.toml"], ("deck file", "a.toml")),
        (["check", "--set", "run.dt=1", "a.toml"], ("deck file", "a.toml")),
        (["advise", "--apply", "o.toml", "a.toml"], ("deck file", "a.toml")),
        (["resume", "out/checkpoints/latest.h5"], ("checkpoint file", "out/checkpoints/latest.h5")),
        (["study", "--jobs", "2", "s.toml"], ("study spec", "s.toml")),
        (["schema", "--output", "s.json"], (None, None)),
        (["plugins"], (None, None)),
        ([], (None, None)),
    ],
)
def test_the_input_file_of_a_command_line(argv, found):
    assert input_file(argv) == found


def test_fingerprint_of_a_large_file_is_quick_and_sees_a_change(tmp_path):
    """A checkpoint-sized file is hashed by samples (a change in a sample is seen), an unreadable one
    gets a fingerprint too (every rank reaches the comparison)."""
    import time

    big = tmp_path / "big.h5"
    data = bytearray(os.urandom(1 << 16)) * 1024  # 64 MiB
    big.write_bytes(data)
    t0 = time.perf_counter()
    first = fingerprint(["resume", str(big)])
    assert time.perf_counter() - t0 < 1.0
    data[-1] ^= 1
    big.write_bytes(data)
    second = fingerprint(["resume", str(big)])
    assert first["arguments"] == second["arguments"] and first["file"] != second["file"]
    assert first["file"].startswith(f"{len(data)} bytes, sha256 ")
    assert fingerprint(["resume", str(tmp_path / "none.h5")])["file"] == "missing"
    assert fingerprint([str(tmp_path)])["file"] == "a directory"


class _Comm:
    """allgather of the fingerprints of given command lines, one per rank."""

    def __init__(self, *argvs):
        self.argvs = argvs

    def allgather(self, mine):
        return [mine] + [fingerprint(a) for a in self.argvs[1:]]


def test_the_message_groups_ranks_and_quotes_at_most_a_line(tmp_path):
    from pdem.errors import InputError

    long = ["deck.toml"] + [f"--set=stages.drop.end.steps={k}" for k in range(30)]
    argvs = [long, long, ["b.toml"], long, ["b.toml"]]
    with pytest.raises(InputError) as exc:
        check_same_command(_Comm(*argvs), argvs[0])
    msg = str(exc.value)
    assert "the 5 MPI ranks were not given the same pdem arguments" in msg
    assert "ranks 0-1, 3: 'deck.toml --set=stages.drop.end.steps=0" in msg and "ranks 2, 4: 'b.toml'" in msg
    assert "…" in msg and len(msg) < 800
    check_same_command(_Comm(long, long), long)  # the same everywhere: nothing raised


# ------------------------------------------------------- the decomposition of no grain (no MPI)


class _Cart:
    """The Cartesian communicator of :class:`_World` (row-major ranks, as MPI's)."""

    def __init__(self, dims, periods, world):
        self.dims, self.periods, self.world, self.rank = dims, periods, world, world.rank

    def allgather(self, value):
        return self.world.allgather(value)

    def Get_rank(self):  # noqa: N802 (mpi4py naming)
        return self.rank

    def Get_coords(self, rank):  # noqa: N802
        import numpy as np

        return [int(c) for c in np.unravel_index(rank, self.dims)]

    def Shift(self, d, disp):  # noqa: N802
        import numpy as np
        from mpi4py import MPI

        coords = self.Get_coords(self.rank)
        out = []
        for step in (-disp, disp):
            c = list(coords)
            c[d] += step
            if self.periods[d]:
                c[d] %= self.dims[d]
            out.append(int(np.ravel_multi_index(c, self.dims)) if 0 <= c[d] < self.dims[d] else MPI.PROC_NULL)
        return tuple(out)


class _World:
    """Rank ``rank`` of ``size`` ranks that all hold the same data (as after add_particles)."""

    def __init__(self, size, rank):
        self.size, self.rank = size, rank
        self.gathers = 0

    def Create_cart(self, dims, periods, reorder):  # noqa: N802
        return _Cart(tuple(dims), tuple(periods), self)

    def allgather(self, value):
        self.gathers += 1
        return [value] * self.size


@pytest.mark.parametrize("rank", [0, 1, 2])
def test_a_decomposition_without_grains_is_placed_by_the_first_ones(rank):
    """With no particle the cut planes are provisional (there were none: an IndexError on every rank
    past the first); the first particles asked about place them at their quantiles and choose the
    grid for their extent, as a decomposition made with them would."""
    import numpy as np

    from pdem.parallel.decomposition import Decomposition

    x = np.stack([np.zeros(90), np.zeros(90), np.arange(90) * 1e-3], axis=1)  # a column along z
    world = _World(3, rank)
    empty = Decomposition(world, np.zeros((0, 3)), min_width=2e-3)
    assert not empty.placed and [c.size for c in empty.cuts] == [2, 0, 0]
    assert empty.owned_mask(np.zeros((0, 3))).size == 0 and not empty.placed  # still nothing to place
    mask = empty.owned_mask(x)
    ref = Decomposition(_World(3, rank), x, min_width=2e-3)
    assert empty.placed and empty.dims == ref.dims == (1, 1, 3)
    assert all(np.array_equal(a, b) for a, b in zip(empty.cuts, ref.cuts, strict=True))
    assert np.array_equal(mask, ref.owned_mask(x)) and mask.sum() == 30
    assert empty.imbalance(123.0) == 1.0  # the work measured without grains does not rebalance
    gathers = world.gathers
    assert empty.imbalance(123.0) == 1.0 and world.gathers == gathers + 1  # then it is measured again


def test_a_split_periodic_axis_without_room_for_wider_ghosts_is_refused():
    import numpy as np

    from pdem.domain import PeriodicBox
    from pdem.errors import InputError
    from pdem.parallel.decomposition import Decomposition

    box = PeriodicBox([0.0, 0.0, 0.0], [0.012, 1.0, 1.0], axes=("x",))
    dec = Decomposition(_World(3, 1), np.zeros((0, 3)), dims=(3, 1, 1), min_width=3e-3, box=box)
    assert np.allclose(dec.cuts[0], [0.004, 0.008])
    dec.widen(4e-3)  # 3 x 4 mm fit in 12 mm
    with pytest.raises(InputError, match="3 subdomains along the periodic axis x do not fit in the 0.012 m"):
        dec.widen(5e-3)  # the box itself is long enough (2 x 5 mm), three subdomains are not
