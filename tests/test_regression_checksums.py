"""Engine refactors keep results bitwise identical: five reduced reference scenes (the hopper with
DEM-P, with DEM-C Jacobi and with DEM-C APGD, the periodic column collapse, the benchmark column) are
fingerprinted and compared with the fingerprints stored in tests/data/regression_checksums.json,
which were made by tools/regression_checksums.py on the main branch before the engine-seams refactor
(the APGD scene: when APGD's sums became exact for MPI).

A change that must alter results (a different summation order, a new physical term) regenerates the
file with ``python tools/regression_checksums.py --write tests/data/regression_checksums.json`` and
says why in its commit. Fingerprints assume the same floating-point behaviour of numpy/numba/libm;
fastmath is off in pdem, so only a change of those libraries' rounding would move them."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STORED = json.loads((ROOT / "tests" / "data" / "regression_checksums.json").read_text())


def _tool():
    path = ROOT / "tools" / "regression_checksums.py"
    spec = importlib.util.spec_from_file_location("regression_checksums", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("scene", sorted(STORED))
def test_scene_bitwise_identical_to_stored(scene):
    assert _tool().scenes()[scene]() == STORED[scene]
