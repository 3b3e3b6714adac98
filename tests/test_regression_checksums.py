"""Engine refactors keep results bitwise identical: five reduced reference scenes (the hopper with
DEM-P, with DEM-C Jacobi and with DEM-C APGD, the periodic column collapse, the benchmark column) are
fingerprinted and compared with the fingerprints stored in tests/data/regression_checksums.json by
tools/regression_checksums.py.

Fingerprints are stored per platform (CPU, numpy's SIMD level, numpy and numba versions): the same code
gives other bits on another CPU (found when the same commit's fingerprints differed on an AMD EPYC
without AVX-512 from those stored on the earlier CI machines). On a platform with an entry, every
scene must match it exactly. On a platform without one, a scene passes if it matches the same scene of
any recorded platform, and is skipped otherwise, with the command that records the platform: run it
on the previous commit first, so that the entry is the unchanged engine's.

A change that must alter results (a different summation order, a new physical term) regenerates this
platform's entry with ``python tools/regression_checksums.py --write tests/data/regression_checksums.json``
(and drops the entries it cannot regenerate) and says why in its commit."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
STORED = json.loads((ROOT / "tests" / "data" / "regression_checksums.json").read_text())
SCENES = sorted({name for entry in STORED.values() for name in entry})


def _tool():
    path = ROOT / "tools" / "regression_checksums.py"
    spec = importlib.util.spec_from_file_location("regression_checksums", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("scene", SCENES)
def test_scene_bitwise_identical_to_stored(scene):
    tool = _tool()
    sig = tool.platform_signature()
    got = tool.scenes()[scene]()
    if sig in STORED and scene in STORED[sig]:
        assert got == STORED[sig][scene], f"scene {scene} on {sig}"
        return
    if any(entry.get(scene) == got for entry in STORED.values()):
        return
    pytest.skip(
        f"no fingerprint of {scene} recorded for this platform ({sig}) and none recorded elsewhere matches; "
        "record it with: python tools/regression_checksums.py --write tests/data/regression_checksums.json "
        "(on the previous commit, to store the unchanged engine's)"
    )
