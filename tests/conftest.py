"""Shared pytest configuration: two opt-in tiers beside the default suite.

- ``--integration`` adds the integration runs (marker ``integration``): each takes 5 s or more on
  2 cores — whole decks, bitwise identity on 3-4 ranks (more ranks than such a machine has cores),
  resumes across rank counts, kills. The default suite keeps a short version of each MPI identity
  scene on 1 and 2 ranks; CI (.ci/run) runs both.
- ``--runslow`` adds the full experiments (marker ``slow``).

The MPI tests run 3-4 ranks on 2-core machines. MPICH's ranks busy-poll while they wait, so an
oversubscribed rank waits for a descheduled one at every exchange; letting idle ranks sleep a
microsecond (MPIR_CVAR_CH4_PROGRESS_THROTTLE) made a 4-rank DEM-C hopper run 1.4-1.6x faster on
such a machine. It changes timing only, never results. The launched processes inherit it.

Most tests launch pdem in fresh processes. Where Python is told not to write bytecode
(``PYTHONDONTWRITEBYTECODE``, common in containers), each of them compiled pdem's sources again:
the session compiles them once (``compileall``) and every process reads the bytecode.

The ``run_pdem`` fixture runs pdem's command line in-process (``pdem.cli.main``) and returns its exit
code and what it printed to stdout and stderr; ``run_pdem_guarded`` does the same within a 180 s
time limit and fails the test if a RuntimeWarning is issued.
"""

from __future__ import annotations

import os
import signal
import warnings
from collections.abc import Callable, Iterable
from typing import NamedTuple

import pytest

os.environ.setdefault("MPIR_CVAR_CH4_PROGRESS_THROTTLE", "1")


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run tests marked slow (full experiments, large scenes)")
    parser.addoption("--integration", action="store_true", default=False,
                     help="also run tests marked integration (runs of 5 s or more: whole decks, 3-4 ranks)")


def pytest_collection_modifyitems(config, items):
    tiers = {"slow": "--runslow", "integration": "--integration"}
    skips = {marker: pytest.mark.skip(reason=f"{marker}: run with {option}")
             for marker, option in tiers.items() if not config.getoption(option)}
    for item in items:
        for marker, skip in skips.items():
            if marker in item.keywords:
                item.add_marker(skip)


class PdemResult(NamedTuple):
    """What an in-process pdem command returned and printed; unpacks as ``code, out, err``."""

    code: int
    out: str
    err: str


@pytest.fixture
def run_pdem(capsys) -> Callable[..., PdemResult]:
    """``run_pdem(args, *, time_limit=None, forbid_runtime_warnings=False)`` runs
    ``pdem.cli.main([str(a) for a in args])`` and returns its exit code with the stdout and stderr
    captured since they were last read. ``time_limit`` (seconds) raises TimeoutError in a command
    that runs longer (SIGALRM: main thread only); ``forbid_runtime_warnings`` records warnings and
    fails the test if any RuntimeWarning (numpy's overflow, invalid value...) was issued."""
    import pdem.cli

    def run(
        args: Iterable, *, time_limit: float | None = None, forbid_runtime_warnings: bool = False
    ) -> PdemResult:
        def _alarm(signum, frame):
            raise TimeoutError(f"pdem did not finish within {time_limit:g} s")

        argv = [str(a) for a in args]
        old = None
        if time_limit is not None:
            old = signal.signal(signal.SIGALRM, _alarm)
            signal.setitimer(signal.ITIMER_REAL, time_limit)
        try:
            with warnings.catch_warnings(record=forbid_runtime_warnings) as caught:
                if forbid_runtime_warnings:
                    warnings.simplefilter("always")
                code = pdem.cli.main(argv)
        finally:
            if time_limit is not None:
                signal.setitimer(signal.ITIMER_REAL, 0)
                signal.signal(signal.SIGALRM, old)
        out, err = capsys.readouterr()
        if forbid_runtime_warnings:
            runtime = [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
            assert not runtime, f"numpy/runtime warnings reached the user: {runtime}"
        return PdemResult(code, out, err)

    return run


@pytest.fixture
def run_pdem_guarded(run_pdem) -> Callable[..., PdemResult]:
    """``run_pdem`` within a 180 s time limit, failing the test if a RuntimeWarning is issued."""

    def run(args: Iterable) -> PdemResult:
        # the limit catches a hang; it leaves room for a first kernel compilation on a loaded machine
        return run_pdem(args, time_limit=180, forbid_runtime_warnings=True)

    return run


@pytest.fixture(scope="session")
def small_packing() -> Callable[[], tuple]:
    """``small_packing()`` gives (positions, radii) of the 300 beads poured into the small triaxial
    cell's mould (tests/data/make_triaxial_small_packing.py), a fresh copy at each call."""
    from pathlib import Path

    from pdem.sources.files import read_spheres

    d = read_spheres(Path(__file__).with_name("data") / "triaxial_small_packing.txt")

    def copy() -> tuple:
        return d["positions"].copy(), d["radii"].copy()

    return copy


def pytest_configure(config):
    """Once per session (in the controlling process when the tests run in parallel): compile the
    kernels into the numba cache before any test runs, unless this cache was warmed already or
    ``PDEM_TEST_WARM=0`` (tests/warm_kernels.py)."""
    if hasattr(config, "workerinput") or os.environ.get("PDEM_TEST_WARM") == "0":
        return
    if config.getoption("collectonly", False) or config.getoption("help", False):
        return
    _compile_sources()
    _warm_kernels()


def _compile_sources() -> None:
    """Bytecode for pdem and tools/, written once: the launched processes then skip compiling
    them (about half a second each where bytecode is not written on import)."""
    import compileall
    from pathlib import Path

    import pdem

    root = Path(__file__).resolve().parents[1]
    for folder in (Path(pdem.__file__).parent, root / "tools"):
        if folder.is_dir():
            compileall.compile_dir(str(folder), quiet=2, workers=1)


def _warm_kernels() -> None:
    import shutil
    import subprocess
    import sys
    import tempfile
    import time
    from pathlib import Path

    from pdem import _jit

    marker = Path(_jit.cache_dir) / "warmed-by-tests"
    if marker.exists():
        return
    here = Path(__file__).resolve().parent
    script = str(here / "warm_kernels.py")
    t0 = time.perf_counter()
    print("\ncompiling pdem's kernels into the numba cache (once per kernel version)...", flush=True)
    with tempfile.TemporaryDirectory(prefix="pdem-warm-") as tmp:
        sys.path.insert(0, str(here))
        from decks import TINY_LATTICE

        (Path(tmp) / "tiny.toml").write_text(TINY_LATTICE)
        pipes = dict(stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

        def wait(p: subprocess.Popen) -> tuple[subprocess.Popen, str]:
            try:  # a hang here would stop the whole session before its first test
                return p, p.communicate(timeout=900)[0]
            except subprocess.TimeoutExpired:
                p.kill()
                return p, p.communicate()[0] + "\n(stopped after 900 s)"

        serial = [subprocess.Popen([sys.executable, script, part, tmp], **pipes)
                  for part in ("dem_p", "dem_c")]
        outs = [wait(p) for p in serial]
        mpiexec = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
        if mpiexec:
            ranks = [mpiexec, "-n", "2", sys.executable, script, "mpi", tmp]
            outs.append(wait(subprocess.Popen(ranks, **pipes)))
    failed = [out for p, out in outs if p.returncode != 0]
    if failed:  # the tests then compile what they need themselves, and show what went wrong
        print("warming the kernel cache failed:\n" + "\n".join(o[-2000:] for o in failed), flush=True)
        return
    marker.write_text(f"{time.perf_counter() - t0:.0f} s\n")
    print(f"kernels compiled in {time.perf_counter() - t0:.0f} s", flush=True)
