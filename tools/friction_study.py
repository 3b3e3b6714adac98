#!/usr/bin/env python
"""Run a triaxial or direct shear deck at several stresses and fit the Mohr–Coulomb envelope.

    python tools/friction_study.py triaxial     [DECK] [--stress 5e4 1e5 2e5]            [options]
    python tools/friction_study.py direct_shear [DECK] [--stress 3100 6400 12500 24200]  [options]

    options: --ranks N (mpiexec -n N; default 1) --out DIR --set KEY=VALUE ... --dry-run
             --constant-stiffness MATERIAL

Each run is ``pdem DECK --set boundaries.NAME.KEY=S`` (``sigma3`` of the deck's ``triaxial``
boundary, or ``normal_stress`` of its ``shear_box``) plus the extra ``--set``s, into
``OUT/<stress>``, one after the other. A finished run whose record (``study_run.json``, as
``pdem study`` writes it) shows the same overrides is kept and skipped (the study can be stopped
and started again; a run made by hand into that folder is made again); a failed run stops the
study with its exit code.
``--constant-stiffness MATERIAL`` scales that material's Young's modulus with the stress (E × S /
S_deck): soft grains are characterised by κ = (E/p)^(2/3) (overlaps ~ d/κ), and at a fixed E a
friction angle can fall as the stress rises only because κ falls (docs/experiments/triaxial.md); at
a constant κ every run has the same relative overlaps. Then ``tools/mohr_coulomb.py`` fits and
plots all runs into ``OUT/mohr_coulomb.{json,csv,png}``.
The decks default to ``inputs/triaxial.toml`` and ``inputs/direct_shear.toml`` (full size: tens of
minutes per run on 2 cores; the results are in docs/experiments/).
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import mohr_coulomb  # noqa: E402

from pdem.study import command, launch  # noqa: E402

TESTS = {
    # test: (boundary type, stress key, default deck, default stresses [Pa])
    "triaxial": ("triaxial", "sigma3", "inputs/triaxial.toml", [5e4, 1e5, 2e5]),
    "direct_shear": ("shear_box", "normal_stress", "inputs/direct_shear.toml",
                     [3100.0, 6400.0, 12500.0, 24200.0]),
}


def boundary_of(deck: Path, kind: str) -> str:
    """The name of the deck's boundary of type ``kind``."""
    data = tomllib.loads(deck.read_text())
    tables = data.get("boundaries", {}).items()
    names = [n for n, b in tables if isinstance(b, dict) and b.get("type") == kind]
    if len(names) != 1:
        raise SystemExit(f"{deck}: expected one boundary of type '{kind}', found {names or 'none'}")
    return names[0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("test", choices=sorted(TESTS))
    ap.add_argument("deck", nargs="?", type=Path, default=None)
    ap.add_argument("--stress", type=float, nargs="+", default=None, help="stresses [Pa]")
    ap.add_argument("--ranks", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="default out/<test>_study")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    ap.add_argument("--constant-stiffness", metavar="MATERIAL", default=None,
                    help="scale this material's Young's modulus with the stress (constant κ)")  # fmt: skip
    args = ap.parse_args(argv)
    kind, key, default_deck, default_stress = TESTS[args.test]
    deck = args.deck or ROOT / default_deck
    out = args.out or Path("out") / f"{args.test}_study"
    name = boundary_of(deck, kind)
    outputs = []
    stresses = args.stress or default_stress
    data = tomllib.loads(deck.read_text())
    for k, s in enumerate(stresses):
        run_dir = out / f"{s:g}"
        outputs.append(run_dir)
        sets = [f"boundaries.{name}.{key}={s!r}"]
        if args.constant_stiffness:
            mat = data.get("materials", {}).get(args.constant_stiffness)
            if not isinstance(mat, dict) or "youngs_modulus" not in mat:
                raise SystemExit(f"{deck}: no materials.{args.constant_stiffness}.youngs_modulus to scale")
            ref = float(data["boundaries"][name][key])
            modulus = float(mat["youngs_modulus"]) * s / ref
            sets.append(f"materials.{args.constant_stiffness}.youngs_modulus={modulus!r}")
        cmd = command(deck, run_dir, [*sets, *args.overrides], args.ranks)
        if args.dry_run:
            print(" ".join(cmd))
            continue
        tag = f"[{k + 1}/{len(stresses)}] {s:g} Pa:"
        code = _run(deck, run_dir, [*sets, *args.overrides], args.ranks, tag)
        if code != 0:
            return code
    if args.dry_run:
        return 0
    return mohr_coulomb.main([*map(str, outputs), "--out", str(out / "mohr_coulomb")])


def _run(deck: Path, run_dir: Path, sets: list[str], ranks: int, tag: str) -> int:
    """One run through ``pdem.study.launch``: kept when its record shows the same overrides."""
    record, ran = launch(deck, run_dir, sets, ranks=ranks)
    what = f"{record.process_wall_s:.0f} s" if ran else "done before, kept"
    print(f"{tag} {run_dir}: {record.status} ({what})", file=sys.stderr)
    if record.status != "ok":
        print(record.stderr_tail, file=sys.stderr)
    return 0 if record.status == "ok" else (record.exit_code or 1)


if __name__ == "__main__":
    raise SystemExit(main())
