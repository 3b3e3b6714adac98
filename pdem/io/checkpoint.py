"""Checkpoints: HDF5 files holding :meth:`pdem.Simulation.state_dict`, the resolved deck and the run's
position (stage, steps and time into the stage), written atomically and checked when read back.

A checkpoint is first written to ``<name>.tmp`` in the same directory, flushed and closed, then
renamed over the final name (``os.replace`` is atomic on POSIX), so a crash while writing never
destroys the previous checkpoint. ``latest.h5`` always names the most recent complete one.

**Integrity (format 2).** The root attribute ``pdem_checksums`` (JSON) lists every dataset written,
each with its dtype, shape and SHA-256 (over its name, dtype, shape and bytes: :func:`dataset_digest`),
and the SHA-256 of every other root attribute (the stored deck, the stage position, the boundaries'
state, the format number: :func:`attribute_digest`). The list is also the set of datasets that must be
there: a dataset missing, added, reshaped or changed by a single bit, or an attribute edited, deleted
or added, is refused.

:func:`read_checkpoint` refuses a damaged checkpoint with :class:`BadCheckpointError` (exit code 2)
before its caller changes any file: the message names the checkpoint, each dataset or attribute at
fault and what is wrong with it, and suggests the newest earlier checkpoint of the same folder. Besides
the checksums it checks the structure, which a checksum cannot vouch for when the writer itself was
given a bad state (:func:`structure_problems`): every dataset the resume needs is present, the
per-particle datasets have one length and the right widths, the scalars are in range (``scalars/step``
a whole number >= 0, ``scalars/time`` finite and >= 0, ``scalars/dt`` finite and > 0), particle ids are
unique, and the state agrees with the stored deck where that is cheap to know (the deck parses as TOML,
``stage_index`` is within its stages, material indices within its materials, the boundaries' saved
state names its boundaries). The full validation of the stored deck (plugins, parameters) is
:func:`pdem.deck.resume.resume_deck`'s, also before any file changes.

**Format 1** files (written before the checksums existed) are still read, validated structurally
only: a flipped bit that leaves a plausible value cannot be detected in them.

**Format 3** is a checkpoint written per rank by a run on several ranks: a manifest (this module's
rules) and one part per rank, each with its own checksums, listed in the manifest with the SHA-256 of
its checksums (:mod:`pdem.io.parted`). Read whole, it is format 2's state.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import tomllib
from pathlib import Path

import h5py
import numpy as np

from ..errors import CheckpointError, InputError

__all__ = [
    "write_checkpoint",
    "read_checkpoint",
    "structure_problems",
    "dataset_digest",
    "attribute_digest",
    "CHECKPOINT_FORMAT",
    "PARTED_FORMAT",
    "READABLE_FORMATS",
    "BadCheckpointError",
]

CHECKPOINT_FORMAT = 2
#: a checkpoint written per rank: a manifest and one part per rank (:mod:`pdem.io.parted`)
PARTED_FORMAT = 3
#: formats :func:`read_checkpoint` reads (1: no checksums, checked structurally only)
READABLE_FORMATS = (1, 2, 3)
FORMAT_ATTR = "pdem_checkpoint_format"
CHECKSUMS_ATTR = "pdem_checksums"

#: per-particle datasets a resume needs in every format: name → (width: 0 scalar, 3 vector; dtype kind)
PARTICLE_DATASETS = {
    "id": (0, "i"),
    "x": (3, "f"),
    "v": (3, "f"),
    "w": (3, "f"),
    "f": (3, "f"),
    "t": (3, "f"),
    "r": (0, "f"),
    "mass": (0, "f"),
    "inv_m": (0, "f"),
    "inv_i": (0, "f"),
    "mat": (0, "i"),
    "motion": (0, "i"),
}
#: registered later than format 1: required from format 2 on (a format-1 file without them gets defaults)
PARTICLE_DATASETS_2 = {"group": (0, "i"), "dof": (0, "i")}
#: other datasets every checkpoint holds
STATE_DATASETS = ("pairs/keys", "pairs/hist", "scalars/step", "scalars/time", "scalars/dt", "scalars/next_id")
#: per-wall datasets: name → shape (None: (rows,) or (rows, width), checked together)
WALL_DATASETS = {"offset": (3,), "velocity": (3,), "omega": (3,), "rotation": (3, 3), "size_rate": (),
                 "active": (), "sizes": None, "rows": None, "ids": None, "hist": None}  # fmt: skip
WALL_REQUIRED = ("offset", "velocity", "active", "hist")
#: root attributes the runner writes (Runner._checkpoint); the first ones exist in every format-1 file
META_REQUIRED_1 = ("deck", "stage_index", "stage_start_time", "stage_start_step")
META_REQUIRED_2 = META_REQUIRED_1 + (
    "stage_started",
    "stage_name",
    "boundaries",
    "frame_bounds",
    "overrides",
    "deck_path",
    "output",
    "pdem_version",
)
#: motion codes a checkpoint may hold (removed particles are left out of it)
MOTIONS = (0, 1, 2)
#: at most this many problems are listed in one message
MAX_LISTED = 6


class BadCheckpointError(CheckpointError, InputError):
    """The file given as a checkpoint is missing, unreadable, damaged or not a pdem checkpoint: invalid
    input (exit code 2), unlike a checkpoint that cannot be written."""

    exit_code = 2


# ------------------------------------------------------------------------------------ checksums
def dataset_digest(name: str, value: object) -> str:
    """SHA-256 (hex) of a dataset: its name, dtype, shape and bytes (C order)."""
    a = np.ascontiguousarray(np.asarray(value))
    h = hashlib.sha256(json.dumps([name, a.dtype.str, list(a.shape)]).encode())
    h.update(b"\0")
    if a.dtype.hasobject:  # (h5py reads variable-length strings as objects)
        h.update(json.dumps(_canonical(a)).encode())
    else:
        h.update(a.reshape(-1).view(np.uint8) if a.size else b"")
    return h.hexdigest()


def _canonical(value: object) -> object:
    """An attribute value as JSON-able data that keeps its type (``1`` and ``1.0`` differ)."""
    if isinstance(value, bytes):
        return ["bytes", value.hex()]
    if isinstance(value, str):
        return ["str", value]
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            return ["array", value.dtype.str, list(value.shape), [_canonical(v) for v in value.reshape(-1)]]
        return ["array", value.dtype.str, list(value.shape), value.reshape(-1).tolist()]
    if isinstance(value, np.generic):
        return [value.dtype.str, value.item()]
    return [type(value).__name__, value]


def attribute_digest(name: str, value: object) -> str:
    """SHA-256 (hex) of a root attribute: its name, type and value."""
    text = json.dumps([name, _canonical(value)], allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


# ------------------------------------------------------------------------------------ writing
def write_hdf5(path: Path, state: dict[str, object], attrs: dict[str, object], fmt: int) -> str:
    """Write ``state`` as datasets and ``attrs`` as root attributes of a new file ``path``, with the
    format number and the checksums of every dataset and attribute; returns the checksums' text."""
    with h5py.File(path, "w") as fh:
        fh.attrs[FORMAT_ATTR] = fmt
        for key, val in attrs.items():
            fh.attrs[key] = val
        datasets = {}
        for key, val in state.items():
            arr = np.asarray(val)
            ds = fh.create_dataset(key, data=arr)
            back = arr  # the digest of what a reader gets back: the same array, unless HDF5 converts it
            if arr.dtype.hasobject or arr.dtype.str != ds.dtype.str or arr.shape != ds.shape:
                back = np.asarray(ds[()])
            datasets[key] = {
                "dtype": back.dtype.str,
                "shape": list(back.shape),
                "sha256": dataset_digest(key, back),
            }
        attributes = {k: attribute_digest(k, v) for k, v in fh.attrs.items()}
        text = json.dumps({"datasets": datasets, "attributes": attributes})
        fh.attrs[CHECKSUMS_ATTR] = text
        fh.flush()
    return text


def point_latest(path: Path) -> None:
    """Make ``latest.h5`` beside ``path`` name it (atomically)."""
    latest = path.with_name("latest.h5")
    ltmp = path.with_name("latest.h5.tmp")
    if ltmp.exists() or ltmp.is_symlink():
        ltmp.unlink()
    os.symlink(path.name, ltmp)
    os.replace(ltmp, latest)


def write_checkpoint(path: Path, state: dict[str, object], meta: dict[str, object]) -> Path:
    """Write ``state`` (arrays by slash-separated key) and ``meta`` (strings / numbers) atomically,
    with the checksums of every dataset and attribute (see the module doc)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        write_hdf5(tmp, state, meta, CHECKPOINT_FORMAT)
        os.replace(tmp, path)
        point_latest(path)
    except OSError as exc:
        raise CheckpointError(
            f"cannot write checkpoint {path}: {exc}; check disk space and permissions"
        ) from exc
    return path


# ------------------------------------------------------------------------------------ reading
def _quote(value: object, limit: int = 200) -> str:
    """``repr`` of a value found in a file, at most ``limit`` characters."""
    text = repr(value.tolist() if isinstance(value, np.ndarray | np.generic) else value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _step_of(name: str) -> int | None:
    m = re.fullmatch(r"step_(\d+)\.h5", name)
    return int(m.group(1)) if m else None


def _remedy(path: Path) -> str:
    """Where to go on from: the newest earlier checkpoint in the same folder, else a fresh run."""
    real = path.resolve()
    own = _step_of(real.name)
    others = []
    try:
        for cand in real.parent.glob("step_*.h5"):
            step = _step_of(cand.name)
            if step is not None and cand.resolve() != real and (own is None or step < own):
                others.append((step, cand))
    except OSError:
        pass
    if not others:
        return (
            f"no earlier checkpoint (step_*.h5) is in {real.parent}; rerun the deck from the start "
            "(its resolved deck is deck.resolved.toml in the run's output directory)"
        )
    step, best = max(others)
    shown = path.parent / best.name if path.parent.resolve() == real.parent else best
    return (
        f"resume from an earlier checkpoint of the same run instead, e.g. pdem resume {shown} "
        f"(step {step}; {len(others)} earlier checkpoint(s) in {path.parent})"
    )


def _name(path: Path) -> str:
    """``path``, and the file it points to when it is a link (``latest.h5``)."""
    if path.is_symlink():
        return f"{path} (→ {path.resolve().name})"
    return str(path)


def _bad(path: Path, problems: list[str]) -> BadCheckpointError:
    listed = problems[:MAX_LISTED]
    more = len(problems) - len(listed)
    head = f"checkpoint {_name(path)} is damaged or was changed after pdem wrote it"
    text = "; ".join(listed) + (f"; and {more} more problem(s)" if more > 0 else "")
    return BadCheckpointError(f"{head}: {text}; {_remedy(path)}")


def read_hdf5(path: Path) -> tuple[dict[str, object], dict[str, np.ndarray]]:
    """Every root attribute and every dataset of an HDF5 file, unchecked (h5py's errors pass)."""
    state: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as fh:
        raw = dict(fh.attrs.items())

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                state[name] = obj[()]

        fh.visititems(visit)
    return raw, state


#: what h5py raises for a damaged or foreign file
READ_ERRORS = (OSError, RuntimeError, KeyError, ValueError, TypeError)


def read_checkpoint(path: Path, comm=None) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Read a checkpoint back: (state arrays by key, metadata attributes), after checking it (see the
    module doc); raises :class:`BadCheckpointError` naming every problem found.

    A checkpoint written per rank (format 3, :mod:`pdem.io.parted`) is read whole without ``comm`` or
    on one rank; on several ranks (collective) each rank reads and checks only its share of the parts
    and gets a :class:`pdem.io.parted.CheckpointShare`, and every rank raises the same error when any
    share is damaged."""
    from ..textutil import file_problem, quote

    path = Path(path)
    problem = file_problem(path)  # from stat alone: a FIFO or /dev/zero is never read
    if problem is not None:
        if path.is_dir():
            example = path / "checkpoints" / "latest.h5" if (path / "checkpoints").is_dir() else None
            raise BadCheckpointError(
                f"checkpoint {quote(str(path))} is a directory; give a checkpoint file written by pdem, "
                f"e.g. {example or 'OUTPUT/checkpoints/latest.h5'}"
            )
        raise BadCheckpointError(
            f"checkpoint {quote(str(path))} {problem}; give a checkpoint file written by pdem "
            "(e.g. OUTPUT/checkpoints/latest.h5)"
        )
    try:
        raw, state = read_hdf5(path)
    except READ_ERRORS as exc:
        raise BadCheckpointError(
            f"cannot read checkpoint {_name(path)}: {_quote(str(exc))}; it is damaged (truncated?) or not "
            f"a checkpoint written by pdem; {_remedy(path)}"
        ) from exc
    fmt = raw.get(FORMAT_ATTR)
    readable = isinstance(fmt, int | np.integer) and int(fmt) in READABLE_FORMATS
    if isinstance(fmt, bool | np.bool_) or not readable:
        raise BadCheckpointError(
            f"{path} is not a pdem checkpoint: its attribute '{FORMAT_ATTR}' is {_quote(fmt)}, "
            f"pdem reads formats {', '.join(map(str, READABLE_FORMATS))}; give a checkpoint file "
            "written by pdem (OUTPUT/checkpoints/step_*.h5)"
        )
    fmt = int(fmt)
    meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in raw.items() if k != CHECKSUMS_ATTR}
    if not any(k in meta for k in META_REQUIRED_1) and CHECKSUMS_ATTR not in raw:
        missing = [f"attribute '{k}'" for k in META_REQUIRED_1]
        raise BadCheckpointError(
            f"checkpoint {path} lacks {', '.join(missing)}; it was not written by the pdem command "
            "(Simulation.state_dict files cannot be resumed with pdem resume); give a checkpoint of a "
            "pdem run (OUTPUT/checkpoints/step_*.h5)"
        )
    if fmt == PARTED_FORMAT:
        from .parted import read_parts

        problems = checksum_problems(raw, state)
        if problems:  # the manifest itself (the same file, the same verdict on every rank)
            raise _bad(path, problems)
        state, problems = read_parts(path, meta, state, comm)  # collective: the same list everywhere
        if problems:
            raise _bad(path, problems)
        return state, meta
    problems = structure_problems(state, meta, fmt)
    if fmt >= 2 or CHECKSUMS_ATTR in raw:  # (also a format-2 file whose format number was changed)
        problems += [p for p in checksum_problems(raw, state) if p not in problems]
    if problems:
        raise _bad(path, problems)
    return state, meta


def checksum_problems(raw: dict[str, object], state: dict[str, np.ndarray]) -> list[str]:
    """What does not match the checksums the writer stored (see the module doc)."""
    text = raw.get(CHECKSUMS_ATTR)
    if text is None:
        return [f"attribute '{CHECKSUMS_ATTR}' (the checksums) is missing"]
    try:
        table = json.loads(text.decode() if isinstance(text, bytes) else str(text))
        datasets, attributes = table["datasets"], table["attributes"]
        if not isinstance(datasets, dict) or not isinstance(attributes, dict):
            raise TypeError("not tables")
    except (ValueError, TypeError, KeyError):
        return [f"attribute '{CHECKSUMS_ATTR}' (the checksums) is not readable: {_quote(text)}"]
    out = []
    for key, entry in datasets.items():
        if key not in state:
            out.append(f"dataset '{key}' is missing")
            continue
        a = np.asarray(state[key])
        try:
            shape, dtype, digest = tuple(entry["shape"]), entry["dtype"], entry["sha256"]
        except (TypeError, KeyError):
            out.append(f"the checksum entry of dataset '{key}' is not readable: {_quote(entry)}")
            continue
        if a.shape != shape:
            out.append(f"dataset '{key}' has shape {a.shape}, it was written with shape {shape}")
        elif a.dtype.str != dtype:
            out.append(f"dataset '{key}' has dtype {a.dtype.str}, it was written with {dtype}")
        elif dataset_digest(key, a) != digest:
            out.append(f"dataset '{key}' does not match its SHA-256 checksum (its values were changed)")
    for key in sorted(set(state) - set(datasets)):
        out.append(f"dataset '{key}' was not written by pdem (it has no checksum)")
    for key, digest in attributes.items():
        if key not in raw:
            out.append(f"attribute '{key}' is missing")
        elif attribute_digest(key, raw[key]) != digest:
            out.append(f"attribute '{key}' does not match its SHA-256 checksum (it was changed)")
    for key in sorted(set(raw) - set(attributes) - {CHECKSUMS_ATTR}):
        out.append(f"attribute '{key}' was not written by pdem (it has no checksum)")
    return out


# ------------------------------------------------------------------------------------ structure
def _whole(value: object) -> int | None:
    """``value`` as an int when it is a whole number (integer dtype, or an integral finite float)."""
    a = np.asarray(value)
    if a.shape != () or a.dtype.kind not in "iuf":
        return None
    v = a.item()
    if isinstance(v, float):
        return int(v) if math.isfinite(v) and v.is_integer() else None
    return int(v)


def _real(value: object) -> float | None:
    a = np.asarray(value)
    if a.shape != () or a.dtype.kind not in "iuf":
        return None
    return float(a.item())


def structure_problems(state: dict[str, np.ndarray], meta: dict[str, object], fmt: int = 2) -> list[str]:
    """Every structural problem of a checkpoint's ``state`` and ``meta`` (see the module doc): a list
    of messages naming the dataset or attribute, the value found and what it should be."""
    out: list[str] = []
    for key in META_REQUIRED_2 if fmt >= 2 else META_REQUIRED_1:
        if key not in meta:
            out.append(f"attribute '{key}' is missing")
    for key in STATE_DATASETS:
        if key not in state:
            out.append(f"dataset '{key}' is missing")
    deck = _deck_problems(meta, out)
    _particle_problems(state, fmt, deck, out)
    _pair_and_wall_problems(state, out)
    _scalar_problems(state, meta, deck, out)
    return out


def _deck_problems(meta: dict[str, object], out: list[str]) -> dict | None:
    text = meta.get("deck")
    if text is None:
        return None
    if not isinstance(text, str) or not text.strip():
        out.append(f"attribute 'deck' = {_quote(text)} is not the text of a deck")
        return None
    try:
        deck = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        out.append(f"attribute 'deck' is not valid TOML ({exc}): {_quote(text)}")
        return None
    stages = deck.get("stages")
    if not isinstance(stages, list) or not stages or not all(isinstance(s, dict) for s in stages):
        out.append(f"attribute 'deck' holds no [[stages]] (stages = {_quote(stages)})")
        return None
    materials = deck.get("materials")
    if not isinstance(materials, dict) or not materials:
        out.append(f"attribute 'deck' holds no [materials] (materials = {_quote(materials)})")
        return None
    return deck


def _particle_problems(state: dict, fmt: int, deck: dict | None, out: list[str]) -> None:
    required = dict(PARTICLE_DATASETS)
    if fmt >= 2:
        required.update(PARTICLE_DATASETS_2)
    for name in required:
        if f"particles/{name}" not in state:
            out.append(f"dataset 'particles/{name}' is missing")
    if "particles/id" not in state:
        return
    ids = np.asarray(state["particles/id"])
    if ids.ndim != 1 or ids.dtype.kind not in "iu":
        out.append(
            f"dataset 'particles/id' has shape {ids.shape} and dtype {ids.dtype}: expected (n,) integers"
        )
        return
    n = ids.shape[0]
    good: dict[str, np.ndarray] = {}
    for key in sorted(k for k in state if k.startswith("particles/")):
        name = key.split("/", 1)[1]
        a = np.asarray(state[key])
        width, kind = {**PARTICLE_DATASETS, **PARTICLE_DATASETS_2}.get(name, (None, None))
        if width is None:  # a plugin's field: one row per particle, a scalar or a 3-vector
            if a.ndim not in (1, 2) or a.shape[0] != n or (a.ndim == 2 and a.shape[1] != 3):
                out.append(
                    f"dataset '{key}' has shape {a.shape}; the checkpoint holds {n} particles "
                    f"(particles/id), so it should be ({n},) or ({n}, 3)"
                )
            continue
        want = (n, 3) if width else (n,)
        if a.shape != want:
            out.append(
                f"dataset '{key}' has shape {a.shape}, expected {want}: the checkpoint holds {n} particles "
                "(particles/id)" + (", each with a 3-vector" if width else "")
            )
            continue
        if (kind == "f" and a.dtype.kind != "f") or (kind == "i" and a.dtype.kind not in "iu"):
            out.append(
                f"dataset '{key}' has dtype {a.dtype}, expected {'floats' if kind == 'f' else 'integers'}"
            )
            continue
        good[name] = a
        if kind == "f" and not np.all(np.isfinite(a)):
            k = int(np.flatnonzero(~np.isfinite(a).reshape(n, -1).all(axis=1))[0])
            out.append(f"dataset '{key}' holds a non-finite value (particle id {ids[k]}: {_quote(a[k])})")
            good.pop(name)
    d = np.diff(ids)
    if n and (ids[0] < 0 or np.any(d <= 0)):
        if ids[0] < 0 or np.any(ids < 0):
            out.append(f"dataset 'particles/id' holds a negative id ({int(ids.min())})")
        uniq, counts = np.unique(ids, return_counts=True)
        if np.any(counts > 1):
            out.append(
                f"dataset 'particles/id' holds id {int(uniq[counts > 1][0])} {int(counts.max())} times "
                f"({int(np.count_nonzero(counts > 1))} duplicated id(s)): ids are unique"
            )
        elif np.any(d <= 0):
            out.append(
                "dataset 'particles/id' is not in increasing order (a checkpoint stores particles by id)"
            )
    for name, op, bound, what in (
        ("r", np.greater, 0.0, "> 0"),
        ("mass", np.greater, 0.0, "> 0"),
        ("inv_m", np.greater_equal, 0.0, ">= 0"),
        ("inv_i", np.greater_equal, 0.0, ">= 0"),
    ):
        if name in good and not np.all(op(good[name], bound)):
            k = int(np.flatnonzero(~op(good[name], bound))[0])
            out.append(
                f"dataset 'particles/{name}' = {_quote(good[name][k])} for particle id {ids[k]}: "
                f"must be {what}"
            )
    if "motion" in good and not np.all(np.isin(good["motion"], MOTIONS)):
        k = int(np.flatnonzero(~np.isin(good["motion"], MOTIONS))[0])
        out.append(
            f"dataset 'particles/motion' = {_quote(good['motion'][k])} for particle id {ids[k]}: "
            f"expected one of {list(MOTIONS)} (free, fixed, prescribed)"
        )
    if "mat" in good and deck is not None and n:
        count = len(deck["materials"])
        lo, hi = int(good["mat"].min()), int(good["mat"].max())
        if lo < 0 or hi >= count:
            bad = lo if lo < 0 else hi
            out.append(
                f"dataset 'particles/mat' holds material index {bad}, but the stored deck (attribute "
                f"'deck') has {count} material(s) ({', '.join(map(str, deck['materials']))}): indices "
                f"0..{count - 1}"
            )
    if "scalars/next_id" in state and n:
        next_id = _whole(state["scalars/next_id"])
        if next_id is not None and int(ids.max()) >= next_id:
            out.append(
                f"dataset 'scalars/next_id' = {next_id} is not above the largest particle id "
                f"{int(ids.max())}: new particles would reuse ids"
            )


def _pair_and_wall_problems(state: dict, out: list[str]) -> None:
    keys = np.asarray(state["pairs/keys"]) if "pairs/keys" in state else None
    hist = np.asarray(state["pairs/hist"]) if "pairs/hist" in state else None
    if keys is not None and (keys.ndim != 1 or keys.dtype.kind not in "iu"):
        out.append(
            f"dataset 'pairs/keys' has shape {keys.shape} and dtype {keys.dtype}: expected (m,) integers"
        )
        keys = None
    if hist is not None and hist.ndim != 2:
        out.append(f"dataset 'pairs/hist' has shape {hist.shape}: expected (pairs, history size)")
        hist = None
    if keys is not None and hist is not None and keys.shape[0] != hist.shape[0]:
        out.append(
            f"dataset 'pairs/hist' has {hist.shape[0]} rows but 'pairs/keys' {keys.shape[0]}: "
            "one row per pair"
        )
    if keys is not None and keys.size > 1 and np.any(np.diff(keys) <= 0):
        out.append(
            "dataset 'pairs/keys' is not strictly increasing (each contact pair is stored once, sorted)"
        )
    if hist is not None and hist.dtype.kind == "f" and not np.all(np.isfinite(hist)):
        out.append("dataset 'pairs/hist' holds a non-finite value")
    walls = sorted({k.split("/")[1] for k in state if k.startswith("walls/") and k.count("/") >= 2})
    for wall in walls:
        pre = f"walls/{wall}/"
        for name in WALL_REQUIRED:
            if pre + name not in state:
                out.append(f"dataset '{pre}{name}' is missing")
        if pre + "rotation" in state:
            for name in ("sizes", "omega", "size_rate"):
                if pre + name not in state:
                    out.append(f"dataset '{pre}{name}' is missing (it goes with '{pre}rotation')")
        rows = None
        for name, shape in WALL_DATASETS.items():
            if pre + name not in state:
                continue
            a = np.asarray(state[pre + name])
            if shape is not None and a.shape != shape:
                out.append(f"dataset '{pre}{name}' has shape {a.shape}, expected {shape}")
                continue
            if shape is None and name != "sizes":
                if (name == "hist") != (a.ndim == 2) or a.ndim not in (1, 2):
                    out.append(
                        f"dataset '{pre}{name}' has shape {a.shape}, expected "
                        + ("(rows, history size)" if name == "hist" else "(rows,)")
                    )
                    continue
                if rows is not None and a.shape[0] != rows[1]:
                    out.append(
                        f"dataset '{pre}{name}' has {a.shape[0]} rows but '{pre}{rows[0]}' has {rows[1]}: "
                        "one row per wall contact"
                    )
                rows = rows or (name, a.shape[0])
            if name == "sizes" and a.ndim != 1:
                out.append(f"dataset '{pre}{name}' has shape {a.shape}, expected (k,)")
            elif a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                out.append(f"dataset '{pre}{name}' holds a non-finite value: {_quote(a)}")
    for key in ("domain/lo", "domain/hi", "domain/periodic"):
        if key in state and np.asarray(state[key]).shape != (3,):
            out.append(f"dataset '{key}' has shape {np.asarray(state[key]).shape}, expected (3,)")
    for key in sorted(k for k in state if k.startswith("stiffness/")):
        if _real(state[key]) is None or not math.isfinite(_real(state[key])):
            out.append(f"dataset '{key}' = {_quote(state[key])}: expected a finite number")


def _scalar_problems(state: dict, meta: dict, deck: dict | None, out: list[str]) -> None:
    step = time = None
    if "scalars/step" in state:
        step = _whole(state["scalars/step"])
        if step is None or step < 0:
            step = None
            out.append(
                f"dataset 'scalars/step' = {_quote(state['scalars/step'])}: a step count is a whole "
                "number >= 0"
            )
    if "scalars/time" in state:
        time = _real(state["scalars/time"])
        if time is None or not math.isfinite(time) or time < 0:
            time = None
            out.append(f"dataset 'scalars/time' = {_quote(state['scalars/time'])}: a time is finite and >= 0")
    if "scalars/dt" in state:
        dt = _real(state["scalars/dt"])
        if dt is None or not math.isfinite(dt) or dt <= 0:
            out.append(f"dataset 'scalars/dt' = {_quote(state['scalars/dt'])}: a time step is finite and > 0")
    if "scalars/next_id" in state:
        nid = _whole(state["scalars/next_id"])
        if nid is None or nid < 0:
            out.append(
                f"dataset 'scalars/next_id' = {_quote(state['scalars/next_id'])}: expected a whole "
                "number >= 0"
            )
    # ---- the run's position, against the stored deck
    stages = deck["stages"] if deck is not None else None
    index = None
    if "stage_index" in meta:
        index = _whole(meta["stage_index"])
        if index is None or index < 0:
            out.append(
                f"attribute 'stage_index' = {_quote(meta['stage_index'])}: expected a whole number >= 0"
            )
            index = None
        elif stages is not None and index > len(stages):
            out.append(
                f"attribute 'stage_index' = {index}, but the stored deck (attribute 'deck') has "
                f"{len(stages)} stage(s): expected 0..{len(stages)}"
            )
            index = None
    started = 1
    if "stage_started" in meta:
        started = _whole(meta["stage_started"])
        if started not in (0, 1):
            out.append(f"attribute 'stage_started' = {_quote(meta['stage_started'])}: expected 0 or 1")
        elif stages is not None and index == len(stages) and started:
            out.append(
                f"attribute 'stage_started' = 1 with 'stage_index' = {index}, past the stored deck's "
                "last stage "
                "(a finished run's checkpoint has stage_started = 0)"
            )
    if "stage_name" in meta and stages is not None and index is not None:
        want = stages[index].get("name", "") if index < len(stages) else ""
        if meta["stage_name"] != want:
            out.append(
                f"attribute 'stage_name' = {_quote(meta['stage_name'])}, but stage {index} of the "
                "stored deck "
                f"is {_quote(want)}"
            )
    if "stage_start_step" in meta:
        first = _whole(meta["stage_start_step"])
        if first is None or first < 0 or (step is not None and first > step):
            out.append(
                f"attribute 'stage_start_step' = {_quote(meta['stage_start_step'])}: expected a whole number "
                f"from 0 to the checkpoint's step ({step if step is not None else 'scalars/step'})"
            )
    if "stage_start_time" in meta:
        t0 = _real(meta["stage_start_time"])
        if t0 is None or not math.isfinite(t0) or t0 < 0 or (time is not None and t0 > time):
            out.append(
                f"attribute 'stage_start_time' = {_quote(meta['stage_start_time'])}: expected a finite time "
                f"from 0 to the checkpoint's time ({time if time is not None else 'scalars/time'})"
            )
    # ---- JSON attributes the runner reads back
    if "boundaries" in meta:
        saved = _json(meta, "boundaries", dict, out)
        if saved is not None and deck is not None:
            names = deck.get("boundaries") if isinstance(deck.get("boundaries"), dict) else {}
            if set(saved) != set(names):
                out.append(
                    f"attribute 'boundaries' holds the state of {sorted(saved)}, but the stored deck's "
                    f"boundaries are {sorted(names)}"
                )
    if "overrides" in meta:
        sets = _json(meta, "overrides", list, out)
        if sets is not None and not all(isinstance(s, str) for s in sets):
            out.append(
                f"attribute 'overrides' = {_quote(meta['overrides'])}: expected a list of KEY=VALUE texts"
            )
    if meta.get("frame_bounds"):
        bounds = _json(meta, "frame_bounds", list, out)
        try:
            ok = bounds is None or np.asarray(bounds, dtype=float).shape == (2, 3)
        except (TypeError, ValueError):
            ok = False
        if not ok:
            out.append(
                f"attribute 'frame_bounds' = {_quote(meta['frame_bounds'])}: expected [[3 lo], [3 hi]]"
            )
    for key in ("deck_path", "output", "stage_name", "pdem_version"):
        if key in meta and not isinstance(meta[key], str):
            out.append(f"attribute '{key}' = {_quote(meta[key])}: expected a text")


def _json(meta: dict, key: str, kind: type, out: list[str]) -> object:
    try:
        value = json.loads(meta[key]) if isinstance(meta[key], str) else None
    except ValueError:
        value = None
    if not isinstance(value, kind):
        out.append(f"attribute '{key}' = {_quote(meta[key])}: expected a JSON {kind.__name__}")
        return None
    return value
