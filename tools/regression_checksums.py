#!/usr/bin/env python
"""Bitwise fingerprints of reduced reference scenes, to hold engine refactors to identical results.

    python tools/regression_checksums.py                 # print the fingerprints of this checkout
    python tools/regression_checksums.py --write FILE    # store them (tests/data/regression_checksums.json)

Scenes (each small enough for CI):

* ``hopper_dem_p``: inputs/hopper.toml shortened (300 beads, the plug opens at 0.03 s), 3,000 steps;
* ``hopper_dem_c``: the same with ``contact.law = "complementarity"`` (Jacobi capped at 100 at the
  automatic step, trace-scaled: the default until the block scaling became it; the deck's own
  DEM-C settings are replaced by these, HOPPER_PLAIN_DEM_C), 700 steps;
* ``hopper_dem_c_apgd``: the same with ``contact.solver = "apgd"`` (added with APGD under MPI, whose
  exact global sums changed serial APGD's rounding; stored from that branch, not from main before
  the refactor);
* ``hopper_dem_c_block``: ``hopper_dem_c`` with the block-scaled Jacobi (the default since it was
  added); ``hopper_dem_c_apgd`` likewise pins APGD unpreconditioned (``scaling = "trace"``) and
  ``hopper_dem_c_apgd_block`` runs the default, block-preconditioned APGD;
* ``periodic_column``: inputs/examples/periodic_column_collapse.toml, 1,000 steps;
* ``bench_column``: the benchmark scene of tools/bench_vs_lammps.py (five planes, dt = 2 µs,
  skin 0.1 mm) on a jittered lattice column of 1,500 spheres, 600 steps, through the Python API.

A fingerprint is the SHA-256 of the final particle state ordered by id (id, x, v, w, f, t) and of
the pair history keyed by id pair, as raw bytes: equal fingerprints mean bitwise-equal states.
Fingerprints are stored per platform (:func:`platform_signature`: CPU, numpy's SIMD level, numpy and
numba versions): the same code gives other bits on another CPU (numpy's reductions in set-up code
sum in an order that follows its SIMD dispatch), so each platform has its own entry.
tests/test_regression_checksums.py compares a checkout with the stored values, which were made on
the main branch before the engine-seams refactor (stored at commit f0d80e7).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HOPPER_SETS = [
    "particles.0.n=300",
    "particles.0.region.height=0.008",
    "stages.fill.end.time=0.03",
    "stages.fill.end.kinetic_energy_below=1e-12",
    "output.every_time=0.05",
    "boundaries.hopper.outflow_depth=0.004",
]
# the hopper deck's DEM-C tables as the DEM-C scenes were stored with (Jacobi capped at 100 at the
# automatic step, one solver for both stages), before the deck carried its tuned settings; the
# scenes' own keys go on top of them
HOPPER_PLAIN_DEM_C = [
    'contact.complementarity={solver="jacobi", tolerance=1.0e-4, max_iterations=100}',
    "stages.discharge.contact={}",
]
HOPPER_DEM_C = HOPPER_SETS + HOPPER_PLAIN_DEM_C + ["contact.law=complementarity"]
PARTICLE_FIELDS = ("id", "x", "v", "w", "f", "t")


def fingerprint(particles: dict[str, np.ndarray], pair_keys: np.ndarray, pair_hist: np.ndarray) -> str:
    """SHA-256 of the particle fields (ordered by id) and the pair history (ordered by key)."""
    order = np.argsort(particles["id"], kind="stable")
    h = hashlib.sha256()
    for name in PARTICLE_FIELDS:
        h.update(np.ascontiguousarray(np.asarray(particles[name])[order], dtype=None).tobytes())
    korder = np.argsort(pair_keys, kind="stable")
    h.update(np.ascontiguousarray(pair_keys[korder], dtype=np.int64).tobytes())
    h.update(np.ascontiguousarray(pair_hist[korder], dtype=np.float64).tobytes())
    return h.hexdigest()


def _deck_run(deck: Path, steps: int, sets: list[str]) -> str:
    from pdem.cli import main
    from pdem.io.checkpoint import read_checkpoint

    with tempfile.TemporaryDirectory(prefix="pdem-fingerprint-") as tmp:
        out = Path(tmp) / "out"
        args = [str(deck), "--steps", str(steps), "--output", str(out), "--quiet"]
        for s in sets:
            args += ["--set", s]
        code = main(args)
        if code != 0:
            raise RuntimeError(f"{deck.name} failed with exit code {code}")
        state, _ = read_checkpoint(out / "checkpoints" / "latest.h5")
    parts = {k: np.asarray(state[f"particles/{k}"]) for k in PARTICLE_FIELDS}
    return fingerprint(parts, np.asarray(state["pairs/keys"]), np.asarray(state["pairs/hist"]))


def bench_column(n: int = 1500, steps: int = 600) -> str:
    """The benchmark scene (tools/bench_vs_lammps.py) on a jittered lattice column."""
    import pdem
    from pdem.geometry.shapes import Plane

    rng = np.random.default_rng(7)
    d = 1.1e-3
    nx = ny = 18
    nz = int(np.ceil(n / (nx * ny)))
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    x = (g[:n] + 0.5) * d + rng.uniform(-0.04e-3, 0.04e-3, (n, 3))
    r = rng.uniform(0.45e-3, 0.5e-3, n)
    sim = pdem.Simulation()
    sim.add_material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.5)
    sim.add_particles(x, r)
    for name, point, normal in [("floor", (0, 0, 0), (0, 0, 1)), ("x0", (0, 0, 0), (1, 0, 0)),
                                ("x1", (0.08, 0, 0), (-1, 0, 0)), ("y0", (0, 0, 0), (0, 1, 0)),
                                ("y1", (0, 0.0198, 0), (0, -1, 0))]:
        sim.add_wall(Plane(point, normal), name=name)
    sim.gravity = (0.0, 0.0, -9.81)
    sim.dt = 2e-6
    sim.skin = 1e-4
    sim.run(steps=steps)
    p = sim.get_particles()
    c = sim.state_dict()
    return fingerprint(p, np.asarray(c["pairs/keys"]), np.asarray(c["pairs/hist"]))


def scenes() -> dict[str, object]:
    hopper = ROOT / "inputs" / "hopper.toml"
    periodic = ROOT / "inputs" / "examples" / "periodic_column_collapse.toml"
    return {
        "hopper_dem_p": lambda: _deck_run(hopper, 3000, HOPPER_SETS),
        "hopper_dem_c": lambda: _deck_run(
            hopper,
            700,
            HOPPER_DEM_C + ['contact.complementarity.scaling="trace"'],
        ),
        "hopper_dem_c_block": lambda: _deck_run(
            hopper,
            700,
            HOPPER_DEM_C + ['contact.complementarity.scaling="block"'],
        ),
        "hopper_dem_c_apgd": lambda: _deck_run(
            hopper,
            700,
            HOPPER_DEM_C
            + ["contact.complementarity.solver=apgd",
               'contact.complementarity.scaling="trace"'],
        ),
        "hopper_dem_c_apgd_block": lambda: _deck_run(
            hopper,
            700,
            HOPPER_DEM_C + ["contact.complementarity.solver=apgd"],
        ),
        "periodic_column": lambda: _deck_run(periodic, 1000, []),
        "bench_column": bench_column,
    }


def platform_signature() -> str:
    """What the fingerprints depend on besides pdem's code: the CPU (vendor, model, the SIMD level
    numpy dispatches to: its reductions' summation order follows it) and the numpy and numba versions.
    Bitwise results are reproducible on one platform, not across them."""
    import numba

    vendor = model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "vendor_id":
                vendor = value.strip()
            elif key.strip() == "model name":
                model = value.strip()
            if vendor != "unknown" and model != "unknown":
                break
    except OSError:
        pass
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as feats
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_features__ as feats
    simd = "AVX512F" if feats.get("AVX512F") else "AVX2" if feats.get("AVX2") else "SSE"
    return f"{vendor} {model} {simd}; numpy {np.__version__}; numba {numba.__version__}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--write",
        type=Path,
        default=None,
        help="store the fingerprints under this platform's signature in this JSON file (other platforms' "
        "entries are kept)",
    )
    ap.add_argument("--only", nargs="*", default=None, help="scene names (default: all)")
    args = ap.parse_args(argv)
    sig = platform_signature()
    print(f"platform: {sig}", flush=True)
    out = {}
    for name, fn in scenes().items():
        if args.only and name not in args.only:
            continue
        out[name] = fn()
        print(f"{name}: {out[name]}", flush=True)
    if args.write:
        stored = json.loads(args.write.read_text()) if args.write.is_file() else {}
        stored.setdefault(sig, {}).update(out)
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(json.dumps(stored, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
