"""The ``pdem`` command.

    pdem DECK [--set KEY=VALUE ...] [--steps N] [--output DIR] [--overwrite] [--quiet]
    pdem check DECK [--set KEY=VALUE ...]
    pdem resume CHECKPOINT [--steps N] [--output DIR] [--overwrite] [--quiet]
    pdem plugins
    pdem schema [--output FILE] [--overwrite]

Exit codes: 0 success, 2 invalid input (deck, plugin, parameters, existing output directory, an
output path that is not or cannot become a directory, a ``run.decomposition`` that does not match
the rank count), 3 numerical failure (instability, lost particles), 1 anything else. User errors
print one message, no traceback. With ``mpirun -n N``, every rank fails together.

Everything the command line alone can refuse (``--steps``, the output path, the decomposition) is
refused before the run is built, so a refused run leaves nothing behind.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import stat
import sys
from pathlib import Path

from . import __version__
from .errors import CheckpointError, InputError, PdemError

__all__ = ["main"]

SUBCOMMANDS = ("check", "resume", "plugins", "schema")


def _run_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pdem",
        description="Run a pdem deck (TOML). Other commands: pdem check DECK | pdem resume CHECKPOINT | "
        "pdem plugins | pdem schema. Exit codes: 0 ok, 2 invalid input, 3 numerical failure, 1 other.",
    )
    p.add_argument("deck", type=Path, help="the deck file (TOML); see docs/deck.md")
    _common(p, sets=True)
    p.add_argument("--version", action="version", version=f"pdem {__version__}")
    return p


def _common(p: argparse.ArgumentParser, sets: bool) -> None:
    if sets:
        p.add_argument(
            "--set",
            dest="sets",
            action="append",
            default=[],
            metavar="KEY=VALUE",
            help="override a deck key, value in TOML syntax (e.g. run.dt=1e-5, "
            'contact.law="hertz_mindlin", stages.fill.end.time=0.2); repeatable',
        )
    p.add_argument(
        "--steps",
        type=_step_count,
        default=None,
        metavar="N",
        help="stop after N steps in total (N >= 0), writing final output and a checkpoint; "
        "--steps 0 builds the scene, writes its initial state and a checkpoint to resume from, "
        "and stops",
    )
    p.add_argument(
        "--output",
        type=Path,
        default=None,
        metavar="DIR",
        help="output directory (default: the deck's output.directory)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
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


def _describe(mode: int) -> str:
    if stat.S_ISREG(mode):
        return "a regular file"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISFIFO(mode):
        return "a named pipe"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a directory"


def _output_dir_problem(out: Path, what: str) -> str | None:
    """Why ``out`` cannot be (or become) a run's output directory, or None.

    ``what`` says where the path came from (``--output``, ``output.directory = …``), for the message.
    Only looks, creates nothing: an existing directory (empty or not) is fine here, the Runner applies
    the --overwrite rule to it.
    """
    remedy = "choose a directory path with --output DIR"
    try:
        st = os.stat(out)
    except (FileNotFoundError, NotADirectoryError):  # missing, or under a file: see the ancestors
        st = None
    except OSError as exc:  # a loop of links, a name too long, …
        return f"output path {out} ({what}) cannot be used: {exc.strerror}; {remedy}"
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            if not os.access(out, os.W_OK | os.X_OK):
                return f"output directory {out} ({what}) is not writable; fix its permissions or {remedy}"
            return None
        return (
            f"output path {out} ({what}) exists and is {_describe(st.st_mode)}, not a directory; "
            f"pdem writes a directory of files and never replaces a file (not even with --overwrite): "
            f"{remedy}"
        )
    if out.is_symlink():
        return f"output path {out} ({what}) is a symbolic link to a missing target; {remedy}"
    # a new directory: its nearest existing ancestor must be a writable directory
    parent = Path(os.path.abspath(out)).parent
    while True:
        try:
            pst = os.stat(parent)
        except (FileNotFoundError, NotADirectoryError):
            pst = None
        except OSError as exc:
            return f"output directory {out} ({what}) cannot be created: {parent}: {exc.strerror}; {remedy}"
        if pst is not None or parent.parent == parent:
            break
        parent = parent.parent
    if pst is None or not stat.S_ISDIR(pst.st_mode):
        kind = _describe(pst.st_mode) if pst is not None else "missing"
        return (
            f"output directory {out} ({what}) cannot be created: {parent} is {kind}, not a "
            f"directory; {remedy}"
        )
    if not os.access(parent, os.W_OK | os.X_OK):
        return (
            f"output directory {out} ({what}) cannot be created: no permission to write in {parent}; {remedy}"
        )
    return None


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
    problem = _output_dir_problem(out, what) if comm.rank == 0 else None
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
        items = ", ".join(f"{k} = {v:.6g}" for k, v in res.items())
        print(f"pdem: {name}: {items}")
    solver = summary.get("solver")
    if solver:
        note = (
            f"; {solver['unconverged_steps']} step(s) hit max_iterations = {solver['max_iterations']} "
            f"before reaching tolerance = {solver['tolerance']:g} m/s (largest residual "
            f"{solver['max_residual']:.3g} m/s; see solver_<stage>.csv)"
            if solver["unconverged_steps"]
            else "; every step converged"
        )
        print(
            f"pdem: DEM-C ({solver['solver']}): {solver['mean_iterations']:.1f} iterations per step "
            "on average" + note
        )
    if not summary.get("completed", True):
        print(f"pdem: stopped early (--steps); resume with: pdem resume {out / 'checkpoints' / 'latest.h5'}")


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

    p = argparse.ArgumentParser(prog="pdem check", description="Validate a deck without running it.")
    p.add_argument("deck", type=Path)
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    resolved = load_deck(args.deck, args.sets)
    deck = resolved.deck
    nb = len(resolved.boundaries)
    print(
        f"{args.deck}: valid ({len(deck.stages)} stage(s): {', '.join(s.name for s in deck.stages)}; "
        f"law {deck.contact.law}; {nb} boundar{'y' if nb == 1 else 'ies'})"
    )
    return 0


def cmd_resume(argv: list[str]) -> int:
    from .deck import load_deck
    from .io.checkpoint import read_checkpoint
    from .runner import Runner

    p = argparse.ArgumentParser(
        prog="pdem resume", description="Continue a run from a checkpoint, bitwise-identically."
    )
    p.add_argument("checkpoint", type=Path, help="e.g. OUTPUT/checkpoints/latest.h5")
    _common(p, sets=False)
    args = p.parse_args(argv)
    state, meta = read_checkpoint(args.checkpoint)
    deck_path = Path(meta["deck_path"])
    overrides = json.loads(meta.get("overrides", "[]"))
    if not deck_path.exists():
        raise CheckpointError(
            f"the deck {deck_path} the checkpoint was written from no longer exists; restore it to resume"
        )
    resolved = load_deck(deck_path, overrides)
    if resolved.resolved_toml() != meta["deck"]:
        raise CheckpointError(
            f"the deck {deck_path} changed since the checkpoint was written; resume needs "
            "the same deck (compare with deck.resolved.toml in the run's output)"
        )
    if args.output is not None:
        out, what = args.output, "--output"
    else:
        out = Path(str(meta["output"]) + f"-resumed-{int(state['scalars/step'])}")
        what = "the default for resume: the checkpoint's output directory + '-resumed-STEP'"
    comm = _comm()
    _check_before_run(resolved, out, what, comm)
    runner = Runner(
        resolved,
        output=out,
        overwrite=args.overwrite,
        max_steps=args.steps,
        comm=comm,
        progress=None if args.quiet else sys.stderr,
        resume=(state, meta),
        overrides=tuple(overrides),
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


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] in SUBCOMMANDS:
            return {"check": cmd_check, "resume": cmd_resume, "plugins": cmd_plugins, "schema": cmd_schema}[
                argv[0]
            ](argv[1:])
        return cmd_run(_run_parser().parse_args(argv))
    except PdemError as exc:
        return _fail(exc.exit_code, f"pdem: error: {exc}")
    except KeyboardInterrupt:
        return _fail(1, "pdem: interrupted")
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
