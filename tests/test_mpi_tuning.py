"""pdem's MPICH defaults (pdem.parallel.MPICH_DEFAULTS) are in the environment before MPI starts,
and a value the user gave wins."""

from __future__ import annotations

import os
import subprocess
import sys

VAR = "MPIR_CVAR_CH4_IPC_CMA_P2P_THRESHOLD"
PROBE = f"import os, pdem; from mpi4py import MPI; print(os.environ.get({VAR!r}), MPI.Is_initialized())"


def _probe(env_value: str | None) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != VAR}
    if env_value is not None:
        env[VAR] = env_value
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    return out.stdout.split()


def test_pdem_sets_its_mpich_default_before_mpi_starts():
    from pdem.parallel import MPICH_DEFAULTS

    assert _probe(None) == [MPICH_DEFAULTS[VAR], "True"]
    assert int(MPICH_DEFAULTS[VAR]) >= 1 << 20  # ghost forwards (10–100 KiB) go through shared memory


def test_a_value_in_the_environment_wins():
    assert _probe("8192") == ["8192", "True"]
