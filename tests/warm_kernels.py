"""Compiles pdem's numba kernels into the on-disk cache before the tests start.

On an empty cache every test process (and every rank a test launches) would otherwise compile the
kernels it meets first, several at once on the same few cores. ``tests/conftest.py`` runs this script
once per session: ``dem_p`` and ``dem_c`` side by side (each compiles its method's kernels through a few
short deck runs; ``dem_p`` ends with DEM-C's APGD and Gauss-Seidel, so that both parts take about as
long), then ``mpi`` on two ranks for the exchange paths. Each part takes ~1-3 s once the cache
is warm. Run by hand: ``python tests/warm_kernels.py dem_p|dem_c|mpi OUTPUT_DIR`` (the folder for the
short runs' output, the same on every rank; a temporary folder when left out).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from decks import SHORT_HOPPER_SETS, TINY_LATTICE, TRIAXIAL_SMALL_PACKED  # noqa: E402

DEM_C = ["--set", 'contact.law="complementarity"']


def _sets(pairs: list[str]) -> list[str]:
    return [a for s in pairs for a in ("--set", s)]


def _runs(kind: str, tiny: Path) -> list[list[str]]:
    triaxial = [str(HERE / "data" / "triaxial_small.toml"), *TRIAXIAL_SMALL_PACKED]
    hopper = [str(ROOT / "inputs" / "hopper.toml"), *_sets(SHORT_HOPPER_SETS)]
    periodic = [str(ROOT / "inputs" / "examples" / "periodic_column_collapse.toml")]
    def solver(name: str) -> list[str]:
        return [str(tiny), *DEM_C, "--set", f'contact.complementarity.solver="{name}"']

    # the two parts run side by side and take about as long: DEM-P's kernels take about half of
    # DEM-C's, so the dem_p part also compiles the APGD and Gauss-Seidel solvers once the shared
    # DEM-C kernels are in the cache (the dem_c part's first run writes them within ~30 s)
    if kind == "dem_p":
        return [[str(tiny)], triaxial, hopper, periodic, solver("apgd"), solver("gauss_seidel")]
    if kind == "dem_c":
        return [solver("jacobi"), [*triaxial, *DEM_C, "--set", "run.dt=1e-4"], [*hopper, *DEM_C]]
    if kind == "mpi":
        return [[str(tiny)], [str(tiny), *DEM_C], [*triaxial], periodic]
    raise SystemExit(f"warm_kernels.py: unknown part {kind!r}; use dem_p, dem_c or mpi")


def main(kind: str, out: Path) -> int:
    from pdem.cli import main as pdem

    tiny = out / "tiny.toml"
    if not tiny.exists():  # conftest.py writes it before the ranks start
        tiny.write_text(TINY_LATTICE)
    for i, args in enumerate(_runs(kind, tiny)):
        code = pdem([*args, "--steps", "3", "--quiet", "--overwrite", "--output", str(out / f"{kind}{i}")])
        if code != 0:
            print(f"warm_kernels.py {kind}: pdem {' '.join(args)} exited with {code}", file=sys.stderr)
            return code
    return 0


if __name__ == "__main__":
    part = sys.argv[1] if len(sys.argv) > 1 else "dem_p"
    if len(sys.argv) > 2:
        raise SystemExit(main(part, Path(sys.argv[2])))
    with tempfile.TemporaryDirectory(prefix="pdem-warm-") as tmp:
        raise SystemExit(main(part, Path(tmp)))
