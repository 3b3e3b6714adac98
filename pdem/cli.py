"""The ``pdem`` command.

    pdem DECK [--set KEY=VALUE ...] [--steps N] [--output DIR] [--overwrite] [--quiet]
    pdem check DECK [--set KEY=VALUE ...] [--deck-only]
    pdem advise DECK [--set KEY=VALUE ...] [--apply OUT.toml] [--overwrite] [--json] [--no-probe]
    pdem resume CHECKPOINT [--set KEY=VALUE ...] [--steps N] [--output DIR] [--overwrite] [--quiet]
    pdem plugins
    pdem schema [--output FILE] [--overwrite]
    pdem study SPEC [--jobs N] [--ranks N] [--output DIR] [--retry-failed] [--series NAME] [--report-only]
               [--dry-run]

Exit codes: 0 success, 2 invalid input (deck, plugin, parameters, existing output directory, an
output path that is not or cannot become a directory, a ``run.decomposition`` that does not match
the rank count, a time step above the stability limit, overlapping grains, a bad packing file, a
checkpoint that is missing or not pdem's, a change a resume does not allow), 3 numerical failure
(instability, lost particles, a stage reaching its ``max_time``), 1 anything else. User errors
print one message, no traceback. With ``mpirun -n N``, every rank fails together.

Everything the command line alone can refuse (``--steps``, the output path, the decomposition) is
refused before the run is built; what needs the scene (time step, overlaps, packing files) is
refused before anything is written; a run that still fails before its first step removes what it
created. So a refused run leaves nothing behind, and the corrected one needs no ``--overwrite``.

``pdem resume`` needs only the checkpoint: the run's resolved deck is stored in it. By default it
continues the run's own output directory (series, XDMF and PVD indexes go on from the checkpoint's
step; what a previous run wrote after it is dropped), so ParaView opens one time series.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from . import __version__
from .errors import InputError, PdemError

__all__ = ["main"]

# a DEM-C run whose first step pushed its initial overlaps apart faster than this [m/s] is warned about
INITIAL_RECOVERY_WARNING = 0.01
SUBCOMMANDS = ("check", "advise", "resume", "plugins", "schema", "study")


def _run_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pdem",
        description="Run a pdem deck (TOML). Other commands (each has --help): "
        "pdem check DECK (validate without running) | "
        "pdem resume CHECKPOINT [--set KEY=VALUE] (continue a run in its own output directory) | "
        "pdem advise DECK (step margins, sample size, the cheaper method, --set changes) | "
        "pdem study SPEC (a grid of runs: error against wall time, stability maps) | "
        "pdem plugins (installed laws, boundaries, writers, sources) | "
        "pdem schema (the decks' JSON Schema). "
        "Exit codes: 0 ok, 2 invalid input, 3 numerical failure, 1 other.",
    )
    p.add_argument("deck", type=Path, help="the deck file (TOML); see docs/deck.md")
    _common(p)
    p.add_argument("--version", action="version", version=f"pdem {__version__}")
    return p


def _common(p: argparse.ArgumentParser, resume: bool = False) -> None:
    p.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=(
            "change a key of the checkpoint's deck, value in TOML syntax; allowed: end conditions, dt and "
            "output of the current stage and of later ones (stages.discharge.end.max_time=12), stages "
            "added at the end (stages.2.name=more), output.*, run.dt, run.force_dt, run.stiffness_limit, "
            "run.max_overlap, run.max_particles, run.balance_threshold, run.decomposition, a "
            "boundary's stage keys for stages not yet run (boundaries.cell.off_stages=[\"more\"]), "
            "DEM-C's solver settings (contact.max_iterations, "
            "contact.tolerance, ...); anything else (materials, particles, boundaries, "
            "...) is refused with the key named; repeatable"
            if resume
            else "override a deck key, value in TOML syntax (e.g. run.dt=1e-5, "
            'contact.law="hertz_mindlin", stages.fill.end.time=0.2); repeatable'
        ),
    )
    p.add_argument(
        "--steps",
        type=_step_count,
        default=None,
        metavar="N",
        help=(
            "stop at step N of the run (counted from its start, so more than the checkpoint's step), "
            "writing final output and a checkpoint"
            if resume
            else "stop after N steps in total (N >= 0), writing final output and a checkpoint; "
            "--steps 0 builds the scene, writes its initial state and a checkpoint to resume from, "
            "and stops"
        ),
    )
    p.add_argument(
        "--output",
        type=Path,
        default=None,
        metavar="DIR",
        help=(
            "write the continued run to DIR instead (a separate copy: its series start with the rows up "
            "to the checkpoint, its snapshots are those after it); default: continue the run's own "
            "output directory"
            if resume
            else "output directory (default: the deck's output.directory)"
        ),
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace an existing --output DIR" if resume else "replace an existing output directory",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def _step_count(text: str) -> int:
    """``--steps``: a whole number >= 0 (argparse turns the error into usage + exit code 2).

    0 is meaningful: the scene is built (sources inserted), its initial state written with a
    checkpoint, and the run stops there, to be inspected or resumed."""
    try:
        value = int(text.strip(), 10)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a whole number of steps (0 or more), got {text!r}; e.g. --steps 5000"
        ) from None
    if value < 0:
        raise argparse.ArgumentTypeError(
            f"the number of steps cannot be negative, got {value}; give 0 or more (--steps 0 only "
            "builds the scene and writes its initial state), or leave --steps out to run every stage"
        )
    return value


def _comm():
    from .parallel.comm import default_comm

    return default_comm()


def _check_before_run(resolved, out: Path, what: str, comm) -> None:
    """Refuse, on every rank together, what the run would only discover after creating its output:
    an output path that cannot be a directory, and a ``run.decomposition`` whose product is not the
    number of ranks (a serial run would ignore it silently, an MPI run fail after starting)."""
    dims = resolved.deck.run.decomposition
    ranks = comm.size
    if dims is not None and math.prod(dims) != ranks:
        shown = "[" + ", ".join(str(d) for d in dims) + "]"
        n = math.prod(dims)
        raise InputError(
            f"run.decomposition = {shown} asks for {' × '.join(str(d) for d in dims)} = "
            f"{n} subdomain{'s' if n != 1 else ''}, one per MPI rank, but this run has {ranks} "
            f"rank{'s' if ranks != 1 else ''}; start it with mpiexec -n {n}, give three "
            f"numbers whose product is {ranks}, or remove run.decomposition to let pdem choose the grid"
        )
    from .io.paths import output_dir_problem

    problem = output_dir_problem(out, what) if comm.rank == 0 else None
    problem = comm.bcast(problem, root=0)
    if problem:
        raise InputError(problem)


def _print_summary(summary: dict, out: Path) -> None:
    if _rank() != 0:
        return
    print(
        f"pdem: {summary['steps']} steps, t = {summary['time']:.6g} s, {summary['particles']} particles, "
        f"{summary['wall_time_s']:.1f} s wall time; output in {out}"
    )
    for name, res in summary.get("results", {}).items():
        items = ", ".join(  # per-item lists (a probe's per-sensor times) are in summary.json only
            f"{k} = {v:.6g}" for k, v in res.items() if isinstance(v, int | float) and not isinstance(v, bool)
        )
        print(f"pdem: {name}: {items}")
    bound = summary.get("stiffness_bound")
    if bound and bound.get("checks_exceeded"):
        print(
            f"pdem: warning: dt = {summary['dt']:.4g} s exceeded the step the contact network bore "
            f"(smallest {bound['dt_min']:.4g} s, at step {bound['at_step']}) at {bound['checks_exceeded']} "
            f"of "
            f"{bound['checks']} checks, by up to {bound['dt_over_bound']:.3g}x; the bound is conservative, "
            "but results past it can drift: compare with a run at dt below it"
        )
    solver = summary.get("solver")
    if solver:
        loads = solver.get("load_stopped_steps")
        if not solver["unconverged_steps"]:
            note = "; every step converged" + (" (on its residual or on the walls' loads)" if loads else "")
        elif solver.get("stage_settings"):  # [stages.contact]: the caps differ by stage
            note = (
                f"; {solver['unconverged_steps']} step(s) hit their stage's max_iterations before reaching "
                f"its tolerance (the last stage's: {solver['max_iterations']}, {solver['tolerance']:g} m/s; "
                f"largest residual {solver['max_residual']:.3g} m/s; see solver_<stage>.csv)"
            )
        else:
            note = (
                f"; {solver['unconverged_steps']} step(s) hit max_iterations = {solver['max_iterations']} "
                f"before reaching tolerance = {solver['tolerance']:g} m/s (largest residual "
                f"{solver['max_residual']:.3g} m/s; see solver_<stage>.csv)"
            )
        if loads:
            note += (
                f"; {loads} step(s) stopped when the walls' loads had settled within load_tolerance = "
                f"{solver['load_tolerance']:g}, before the residual reached the tolerance"
            )
        print(
            f"pdem: DEM-C ({solver['solver']}): {solver['mean_iterations']:.1f} iterations per step "
            "on average" + note
        )
        if solver.get("mass_scaled_steps"):
            print(
                f"pdem: DEM-C scaled the masses of grains under stiff boundary loads in "
                f"{solver['mass_scaled_steps']} step(s), by up to {solver['max_mass_ratio']:.3g}x "
                "(load_mass_scaling; docs/dem_c.md, Stiff boundary loads)"
            )
        thrown = solver.get("initial_recovery_speed", 0.0)
        if thrown >= INITIAL_RECOVERY_WARNING:
            print(
                f"pdem: warning: the packing the run started from overlapped by up to "
                f"{solver['initial_overlap']:.3g} m (a soft-grain preparation leaves such overlaps), and "
                f"the first DEM-C step pushed it apart at {thrown:.3g} m/s, more at the top of a deep "
                "bed, where the contacts below add up: that can throw grains and loosen the packing. "
                f"Raise contact.complementarity.recovery_steps (now {solver.get('recovery_steps', 1)}) "
                "or set contact.complementarity.recovery_speed (e.g. 1e-3 m/s) to remove overlaps gently "
                "(docs/dem_c.md, Initial overlaps)"
            )
        missed, short = solver.get("missed_contact_steps", 0), solver.get("envelope_short_steps", 0)
        if missed or short:
            print(
                f"pdem: warning: the contact envelope ({solver['envelope']:.3g} m) was shorter than the "
                f"fastest grain's travel in {short} step(s), and grains overlapped or passed through "
                f"contacts it had left out after {missed} step(s): grains may tunnel. Leave "
                "contact.complementarity.envelope out (the per-contact rule), raise it, or take a "
                "smaller step"
            )
    if not summary.get("completed", True):
        print(f"pdem: stopped early (--steps); resume with: pdem resume {out / 'checkpoints' / 'latest.h5'}")
    elif "resumed_from_step" in summary and summary.get("steps_run", 1) == 0:
        print(
            "pdem: the checkpoint is at the end of the last stage: nothing left to run. To go on, add a "
            "stage, e.g. pdem resume CHECKPOINT --set stages.N.name=more --set stages.N.end.time=0.1 "
            "(N = the number of stages)"
        )


def cmd_run(args: argparse.Namespace) -> int:
    from .deck import load_deck
    from .runner import Runner

    resolved = load_deck(args.deck, args.sets)
    comm = _comm()
    if args.output is not None:
        out, what = args.output, "--output"
    else:
        directory = resolved.deck.output.directory
        out, what = Path(directory), f"output.directory = '{directory}'"
    _check_before_run(resolved, out, what, comm)
    runner = Runner(
        resolved,
        output=out,
        overwrite=args.overwrite,
        max_steps=args.steps,
        comm=comm,
        progress=None if args.quiet else sys.stderr,
        overrides=tuple(args.sets),
    )
    summary = runner.run()
    _print_summary(summary, runner.out)
    return 0


def cmd_check(argv: list[str]) -> int:
    from .deck import load_deck
    from .runner import Runner

    p = argparse.ArgumentParser(
        prog="pdem check",
        description="Validate a deck without running it: the deck itself (every problem at once), then "
        "the scene of its first stage (the particles are made, the time step is checked against the "
        "contact law's stability estimate for every stage, initial overlaps between grains and with "
        "walls, packing files of later stages are read). Nothing is written.",
    )
    p.add_argument("deck", type=Path)
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument(
        "--deck-only",
        action="store_true",
        help="validate the deck only, without making the first stage's particles (fast; a pluviated "
        "packing, for one, is settled by the scene check)",
    )
    args = p.parse_args(argv)
    resolved = load_deck(args.deck, args.sets)
    deck = resolved.deck
    from .parallel.agree import launched_comm

    comm = launched_comm()  # under mpiexec the ranks share the scene's work (a pour), as in a run
    if comm is None:  # serial: MPI is not started for a check
        from .parallel.comm import SerialComm

        comm = SerialComm()
    # progress lines on stderr while a long scene is made (a pour): only after some seconds
    scene = (
        ""
        if args.deck_only
        else "; " + Runner(resolved, comm=comm, progress=sys.stderr, dry=True).check_scene()
    )
    nb = len(resolved.boundaries)
    if comm.rank != 0:
        return 0
    print(
        f"{args.deck}: valid ({len(deck.stages)} stage(s): {', '.join(s.name for s in deck.stages)}; "
        f"law {deck.contact.law}; {nb} boundar{'y' if nb == 1 else 'ies'}{scene})"
    )
    return 0


def cmd_advise(argv: list[str]) -> int:
    from .advise import advise, apply, dumps_json

    p = argparse.ArgumentParser(
        prog="pdem advise",
        description="Advise on a deck: step margins (Rayleigh and Hertz collision times at the scene's "
        "speeds), the overlap at the scene's stresses, the inertial number of the loading, the sample size "
        "against published minimums, which method is likely faster, and the --set changes that run it "
        "faster with its measured quantity unchanged (docs/advise.md). Runs at most a short probe of the "
        "first stage (about 10 s); writes nothing unless --apply.",
    )
    p.add_argument("deck", type=Path)
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--apply", type=Path, default=None, metavar="OUT.toml", help="write the adjusted deck")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT.toml")
    p.add_argument("--json", action="store_true", help="print the advice as JSON")
    p.add_argument("--no-probe", action="store_true", help="estimate from the deck only (no particles made)")
    args = p.parse_args(argv)
    out = args.apply
    if out is not None and (out.exists() or out.is_symlink()) and not args.overwrite:  # before the probe
        raise InputError(
            f"--apply {out} already exists; pass --overwrite to replace it, or choose another file"
        )
    advice = advise(args.deck, tuple(args.sets), probe=not args.no_probe)
    print(dumps_json(advice) if args.json else advice.report())
    if args.apply is not None:
        out = apply(advice, args.apply, overwrite=args.overwrite)
        print(
            f"pdem advise: wrote {out} ({len(advice.changes)} change(s)); check it with: pdem check {out}",
            file=sys.stderr if args.json else sys.stdout,
        )
    return 0


RESUME_DESCRIPTION = """\
Continue a run from one of its checkpoints, bitwise-identically to an uninterrupted run.

Only the checkpoint is needed: the run's resolved deck is stored in it (the deck file may have moved
or changed). By default the run goes on in its own output directory, as one time series: the series
CSVs continue from the checkpoint's step, the XDMF and PVD indexes go on with the next frames, and
what a previous run wrote after the checkpoint (rows, snapshots, later checkpoints) is dropped;
nothing up to the checkpoint is rewritten. --output DIR writes the continuation elsewhere instead.

--set changes how the run goes on, e.g. a stage that reached its max_time:
  pdem resume out/hopper/checkpoints/latest.h5 --set stages.discharge.end.max_time=12
or an extra stage after the last one:
  pdem resume out/hopper/checkpoints/latest.h5 --set stages.2.name=rest --set stages.2.end.time=0.5
Keys that describe the scene the checkpoint holds (materials, particles, boundaries, contact law,
gravity, ...) cannot change; the error names them."""


def _run_directory(checkpoint: Path, meta: dict) -> Path:
    """The output directory of the run that wrote ``checkpoint``: the directory holding its
    ``checkpoints/`` folder (so a moved output is found), else the one recorded in it."""
    real = Path(checkpoint).resolve()
    if real.parent.name == "checkpoints":
        return real.parent.parent
    return Path(str(meta.get("output") or real.parent))


def cmd_resume(argv: list[str]) -> int:
    import os

    from .deck.resume import ResumePoint, resume_deck
    from .io.checkpoint import read_checkpoint
    from .runner import Runner

    p = argparse.ArgumentParser(
        prog="pdem resume",
        description=RESUME_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("checkpoint", type=Path, help="a checkpoint, e.g. OUTPUT/checkpoints/latest.h5")
    _common(p, resume=True)
    args = p.parse_args(argv)
    comm = _comm()
    state, meta = read_checkpoint(args.checkpoint, comm=comm)  # on several ranks: each its share
    point = ResumePoint.from_checkpoint(state, meta)
    if args.steps is not None and args.steps <= point.step:
        raise InputError(
            f"--steps {args.steps}: the checkpoint is at step {point.step} already, and --steps counts "
            f"steps from the start of the run; give more than {point.step} (e.g. --steps "
            f"{point.step + 1000}), or leave --steps out to run every stage"
        )
    _, resolved = resume_deck(meta, tuple(args.sets), point, args.checkpoint)
    source = _run_directory(args.checkpoint, meta)
    series_from = None
    if args.output is None or (
        os.path.lexists(args.output) and os.path.realpath(args.output) == os.path.realpath(source)
    ):
        out, what, append = source, "the run's own output directory, continued by pdem resume", True
    else:
        out, what, append = args.output, "--output", False
        series_from = source if source.is_dir() else None
    _check_before_run(resolved, out, what, comm)
    overrides = tuple(json.loads(meta.get("overrides", "[]"))) + tuple(args.sets)
    runner = Runner(
        resolved,
        output=out,
        overwrite=args.overwrite,
        max_steps=args.steps,
        comm=comm,
        progress=None if args.quiet else sys.stderr,
        resume=(state, meta),
        overrides=overrides,
        append=append,
        series_from=series_from,
    )
    summary = runner.run()
    _print_summary(summary, runner.out)
    return 0


def cmd_plugins(argv: list[str]) -> int:
    from .plugins import GROUPS, available

    argparse.ArgumentParser(prog="pdem plugins", description="List installed plugins.").parse_args(argv)
    for group in GROUPS:
        print(f"{GROUPS[group]}:")
        for name, info in sorted(available(group).items()):
            print(f"  {name:16s} {info.value}  (from {info.distribution})")
    return 0


def cmd_schema(argv: list[str]) -> int:
    from .deck import deck_json_schema

    p = argparse.ArgumentParser(prog="pdem schema", description="Print the JSON Schema of decks.")
    p.add_argument(
        "--output", type=Path, default=None, metavar="FILE", help="write it to FILE instead of stdout"
    )
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    args = p.parse_args(argv)
    out = args.output
    if out is not None:  # refuse before the (slow) schema is built
        if out.is_dir():
            raise InputError(
                f"--output {out} is a directory; give a file name, e.g. --output {out / 'deck.schema.json'}"
            )
        if (out.exists() or out.is_symlink()) and not args.overwrite:
            raise InputError(
                f"--output {out} already exists; pass --overwrite to replace it, or choose another file"
            )
    text = json.dumps(deck_json_schema(), indent=2) + "\n"
    if out is None:
        sys.stdout.write(text)
        return 0
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise InputError(
            f"cannot write the schema to --output {out}: {exc.strerror or exc}; check that its directory "
            "exists and is writable, or choose another file"
        ) from exc
    return 0


def cmd_study(argv: list[str]) -> int:
    """``pdem study SPEC``: run a grid of one deck's overrides (resumable) and chart the results."""
    p = argparse.ArgumentParser(
        prog="pdem study",
        description="Run one deck over a grid of --set overrides as separate processes (resumable: "
        "finished runs are kept), then write study.csv, charts (error against wall time with each "
        "method's Pareto front, error against each knob, the stability map) and reading.md in "
        "OUTPUT/report. The spec format: docs/study.md.",
    )
    p.add_argument("spec", type=Path, help="the study spec (TOML)")
    p.add_argument("--jobs", type=int, default=None, metavar="N", help="runs at a time (default: spec's)")
    p.add_argument("--ranks", type=int, default=None, metavar="N", help="MPI ranks per run (default: spec's)")
    p.add_argument("--output", type=Path, default=None, metavar="DIR", help="study directory")
    p.add_argument("--retry-failed", action="store_true", help="run again the runs that did not end ok")
    p.add_argument("--series", action="append", default=None, metavar="NAME",
                   help="run only this series' runs (repeatable); the report still covers every run there is")
    p.add_argument("--report-only", action="store_true", help="run nothing; tabulate and chart what is there")
    p.add_argument("--dry-run", action="store_true", help="list the runs and their commands; run nothing")
    args = p.parse_args(argv)
    from .study import Study
    from .study.launch import command

    study = Study.from_file(args.spec, jobs=args.jobs, ranks=args.ranks, output=args.output)
    selected = study.select(args.series)  # (an unknown series: InputError, exit 2)
    if args.dry_run:
        for plan in selected:
            cmd = command(study.spec.deck, plan.directory, plan.set_args(), study.spec.ranks)
            print(f"{plan.name} [{plan.method}]: {' '.join(cmd)}")
        return 0
    import signal

    def _terminate(signum, frame):  # a terminated study stops its runs (they are redone on rerun)
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _terminate)
    if not args.report_only:
        study.run(retry_failed=args.retry_failed, series=args.series)
    paths = study.report()
    print(f"pdem study: {len(study.plans)} runs; table {paths['table']}; reading {paths['reading']}")
    print(paths["reading"].read_text())
    return 0


def _same_command_on_every_rank(argv: list[str]) -> None:
    """Under MPI, before anything else (parsing included: a rank refused by argparse would leave the
    others waiting): every rank must have been given the same arguments and the same deck, checkpoint
    or spec, else every rank raises the same InputError (exit 2). A serial run does not start MPI
    for it (:mod:`pdem.parallel.agree`)."""
    from .parallel.agree import check_same_command, launched_comm

    comm = launched_comm()
    if comm is not None:
        check_same_command(comm, argv)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        _same_command_on_every_rank(argv)
        if argv and argv[0] in SUBCOMMANDS:
            return {
                "check": cmd_check,
                "advise": cmd_advise,
                "resume": cmd_resume,
                "plugins": cmd_plugins,
                "schema": cmd_schema,
                "study": cmd_study,
            }[argv[0]](argv[1:])
        return cmd_run(_run_parser().parse_args(argv))
    except PdemError as exc:
        return _fail(exc.exit_code, f"pdem: error: {exc}")
    except KeyboardInterrupt:
        return _fail(1, "pdem: interrupted")
    except BrokenPipeError:  # the reader of stdout went away (pdem plugins | head): not an error
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 0
    except Exception as exc:  # a bug: keep the traceback, but never leave other ranks hanging
        if _world_size() > 1:
            import traceback

            traceback.print_exc()
            return _fail(1, f"pdem: internal error: {type(exc).__name__}: {exc}")
        raise


def _rank() -> int:
    try:
        from mpi4py import MPI
    except ImportError:  # pragma: no cover
        return 0
    return MPI.COMM_WORLD.Get_rank() if MPI.Is_initialized() else 0


def _world_size() -> int:
    try:
        from mpi4py import MPI
    except ImportError:  # pragma: no cover
        return 1
    return MPI.COMM_WORLD.Get_size() if MPI.Is_initialized() else 1


def _fail(code: int, message: str) -> int:
    """Report and make every rank fail together.

    Serial: print and return the code. Under MPI, rank 0 prints and aborts the whole job with the
    code at once; other ranks wait a moment first, so that an error raised on every rank (the usual
    case: decisions are collective) is printed once, while an error raised on one rank only still
    ends the job within seconds instead of leaving the others waiting in a collective call.
    """
    if _world_size() == 1:
        print(message, file=sys.stderr)
        return code
    import time

    from mpi4py import MPI

    rank = MPI.COMM_WORLD.Get_rank()
    if rank != 0:
        time.sleep(2.0)
        message = f"[rank {rank}] {message}"
    print(message, file=sys.stderr, flush=True)
    # mpiexec relays each rank's stderr asynchronously: aborting at once can kill the job before the
    # message reaches the user, so give the forwarder a moment
    time.sleep(0.5)
    MPI.COMM_WORLD.Abort(code)
    return code  # pragma: no cover


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
