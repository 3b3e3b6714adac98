"""Every rank of an MPI job must run the same pdem command on the same input file.

``mpiexec -n 1 pdem a.toml : -n 1 pdem b.toml`` (an MPMD launch), or ranks of several nodes that see
different copies of a deck, would otherwise run one scene built from two decks, or wait forever for
each other in collectives that only some of them make. :func:`check_same_command` compares, in one
``allgather`` before anything else is done, a SHA-256 of each rank's argument list and one of its
input file (the deck; the checkpoint of ``pdem resume``; the spec of ``pdem study``), and raises the
same :class:`~pdem.errors.InputError` on every rank when they differ.

A file of at most :data:`WHOLE_FILE` bytes is hashed whole; a larger one (a checkpoint) by its size
and :data:`SAMPLES` evenly spaced samples of :data:`SAMPLE` bytes, the first and last included, so the
check stays under ~20 ms.

:func:`launched_comm` tells whether the process was started by an MPI launcher with more than one
rank, from the launcher's environment, so that a serial command does not start MPI for the check.
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
import sys

from ..errors import InputError

__all__ = ["check_same_command", "fingerprint", "input_file", "launched_comm"]

#: environment variables in which MPI launchers give the number of ranks (MPICH's and Intel MPI's
#: Hydra, Slurm's PMI-2, Open MPI, MVAPICH)
SIZE_VARIABLES = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MV2_COMM_WORLD_SIZE")
#: set by PMIx launchers (srun --mpi=pmix, prrte), which announce no size: MPI is started to ask
PMIX_VARIABLE = "PMIX_RANK"
WHOLE_FILE = 4 << 20
SAMPLES = 16
SAMPLE = 256 << 10
#: the pdem options followed by a value (any command); ``--output`` and ``--apply`` name outputs
VALUE_OPTIONS = ("--set", "--steps", "--output", "--apply", "--jobs", "--ranks", "--series")
FLAG_OPTIONS = (
    "--overwrite", "--quiet", "--version", "--help", "--deck-only", "--json", "--no-probe",
    "--retry-failed", "--report-only", "--dry-run",
)  # fmt: skip
FILE_KINDS = {"resume": "checkpoint file", "study": "study spec", "plugins": None, "schema": None}
SHOWN = 160  # characters of a rank's arguments quoted in the message


def launched_comm():
    """``MPI.COMM_WORLD`` if this process is one of several MPI ranks, else None (a serial run: MPI is
    not started unless the launcher's environment asks for it or it was started already)."""
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is not None and mpi.Is_initialized() and not mpi.Is_finalized():
        return mpi.COMM_WORLD if mpi.COMM_WORLD.Get_size() > 1 else None
    sizes = []
    for name in SIZE_VARIABLES:
        try:
            sizes.append(int(os.environ.get(name, "")))
        except ValueError:
            pass
    if not (any(s > 1 for s in sizes) or (not sizes and PMIX_VARIABLE in os.environ)):
        return None
    from .comm import default_comm

    comm = default_comm()
    return comm if comm.size > 1 else None


def input_file(argv: list[str]) -> tuple[str | None, str | None]:
    """(kind, path) of the input file of pdem's command line ``argv``: its first positional argument
    after the subcommand (the deck, ``pdem resume``'s checkpoint, ``pdem study``'s spec); (None,
    None) for a command without one. Options taking a value (an unambiguous prefix too, as argparse
    reads them) skip it."""
    kind = "deck file"
    rest = list(argv)
    if rest and rest[0] in ("check", "advise", "resume", "plugins", "schema", "study"):
        kind = FILE_KINDS.get(rest[0], "deck file")
        rest = rest[1:]
        if kind is None:
            return None, None
    skip = False
    for token in rest:
        if skip:
            skip = False
            continue
        if token == "--":
            continue
        if token.startswith("-") and len(token) > 1:
            name = token.split("=", 1)[0]
            if "=" not in token and token.startswith("--"):
                takes = any(o.startswith(name) for o in VALUE_OPTIONS)
                skip = takes and not any(o.startswith(name) for o in FLAG_OPTIONS)
            continue
        return kind, token
    return None, None


def _file_digest(path: str) -> str:
    """SHA-256 of the file (whole, or its size and samples when larger than :data:`WHOLE_FILE`), or
    why it cannot be read: a rank must reach the comparison whatever happens."""
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            h = hashlib.sha256()
            if size <= WHOLE_FILE:
                h.update(fh.read())
            else:
                h.update(f"{size} bytes, sampled:".encode())
                for k in range(SAMPLES):
                    fh.seek((size - SAMPLE) * k // (SAMPLES - 1))
                    h.update(fh.read(SAMPLE))
            return f"{size} bytes, sha256 {h.hexdigest()}"
    except FileNotFoundError:
        return "missing"
    except IsADirectoryError:
        return "a directory"
    except OSError as exc:
        return f"unreadable ({exc.strerror or type(exc).__name__})"


def fingerprint(argv: list[str]) -> dict[str, str | None]:
    """What the ranks compare: SHA-256 of the argument list, the input file's kind, path and digest,
    and the arguments as a (shortened) shell line for messages."""
    kind, path = input_file(argv)
    line = shlex.join(argv)
    digest = _file_digest(path) if path is not None else None
    return {
        "arguments": hashlib.sha256(json.dumps(argv).encode()).hexdigest(),
        "shown": line if len(line) <= SHOWN else line[: SHOWN - 1] + "…",
        "kind": kind,
        "path": path,
        "file": digest,
        "file_shown": digest[:-52] + "…" if digest and " sha256 " in digest else digest,
    }


def _ranks(ranks: list[int]) -> str:
    """``rank 3`` / ``ranks 0-2, 5``."""
    spans: list[list[int]] = []
    for r in ranks:
        if spans and r == spans[-1][1] + 1:
            spans[-1][1] = r
        else:
            spans.append([r, r])
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)
    return f"rank{'s' if len(ranks) > 1 else ''} {text}"


def _groups(prints: list[dict], key: str) -> list[tuple[list[int], dict]]:
    out: dict[str | None, tuple[list[int], dict]] = {}
    for rank, fp in enumerate(prints):
        out.setdefault(fp[key], ([], fp))[0].append(rank)
    return list(out.values())


def _listed(groups: list[tuple[list[int], dict]], show) -> str:
    parts = [f"{_ranks(ranks)}: {show(fp)}" for ranks, fp in groups[:4]]
    if len(groups) > 4:
        parts.append(f"and {len(groups) - 4} other variants")
    return "; ".join(parts)


def check_same_command(comm, argv: list[str]) -> None:
    """Raise the same :class:`InputError` on every rank unless every rank of ``comm`` was given the
    same arguments and the same input file (one collective ``allgather``: every rank must call it,
    first thing)."""
    prints = comm.allgather(fingerprint(argv))
    size = len(prints)
    groups = _groups(prints, "arguments")
    if len(groups) > 1:
        raise InputError(
            f"the {size} MPI ranks were not given the same pdem arguments "
            f"({_listed(groups, lambda fp: repr(fp['shown']))}); every rank must run the same command "
            f"on the same deck: launch them all with one command, e.g. mpiexec -n {size} pdem "
            f"{prints[0]['shown']}, not an MPMD launch (':') with different arguments"
        )
    groups = _groups(prints, "file")
    if len(groups) > 1:
        kind, path = prints[0]["kind"], prints[0]["path"]
        raise InputError(
            f"the {size} MPI ranks were given the same arguments, but the {kind} {path!r} differs "
            f"between them ({_listed(groups, lambda fp: fp['file_shown'])}); every rank must read the same "
            f"{kind}: keep it on a file system every node shares (or copy the same file to each node), "
            "and launch every rank with one command from the same directory"
        )
