"""The MPI layer's own pieces: pdem's MPICH defaults (pdem.parallel.MPICH_DEFAULTS) are in the
environment before MPI starts, and a value the user gave wins; all_max and all_min over ranks
(exact, NaN from any rank on every rank)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")

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


EXTREMES = textwrap.dedent(
    """
    import json, math, sys
    import pdem
    from mpi4py import MPI
    from pdem.parallel.comm import all_max, all_min
    comm = MPI.COMM_WORLD
    r = comm.rank
    cases = {
        "plain": [0.5, -2.0, 3.25, 1e-300][r],
        "ties": 7.0,
        "signed": [-1.5, -0.0, -7.0, -1e300][r],
        "inf": [1.0, math.inf, -math.inf, 2.0][r],
        "nan_on_last": math.nan if r == comm.size - 1 else float(r),
        "nan_on_first": math.nan if r == 0 else float(r),
        "int": [3, 9, -4, 0][r],
    }
    out = {k: [repr(all_max(comm, v)), repr(all_min(comm, v))] for k, v in cases.items()}
    with open(f"{sys.argv[1]}/rank{r}.json", "w") as fh:
        json.dump(out, fh)
    """
)


@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
@pytest.mark.parametrize("ranks", [2, 3, 4])
def test_all_max_and_all_min_over_ranks(tmp_path, ranks):
    script = tmp_path / "extremes.py"
    script.write_text(EXTREMES)
    cmd = [MPIEXEC, "-n", str(ranks), sys.executable, str(script), str(tmp_path)]
    subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True)
    lines = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(ranks)]
    assert len(lines) == ranks and all(line == lines[0] for line in lines)  # every rank alike
    got = lines[0]
    values = {
        "plain": [0.5, -2.0, 3.25, 1e-300], "ties": [7.0] * 4, "signed": [-1.5, -0.0, -7.0, -1e300],
        "inf": [1.0, float("inf"), float("-inf"), 2.0], "int": [3, 9, -4, 0],
    }
    for key, vals in values.items():
        assert got[key] == [repr(float(max(vals[:ranks]))), repr(float(min(vals[:ranks])))], key
    assert got["nan_on_last"] == ["nan", "nan"] and got["nan_on_first"] == ["nan", "nan"]
