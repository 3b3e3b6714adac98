"""Checkpoints written per rank (format 3): every rank writes its own particles and their contact
history, a small manifest joins them, and any number of ranks reads them back.

A run on more than one rank writes

* ``checkpoints/step_<step>.parts-<token>/rank_<k>.h5``, one part per rank: the rank's particles
  (ordered by id), the history of every pair with one of them (a pair across two ranks is in both
  parts, identically) and their wall-contact history; with its own checksums (format 2's rules);
* ``checkpoints/step_<step>.h5``, the manifest: what every rank holds alike (walls' poses and
  motions, time, step, dt, the live bound, the solver's counters, the periodic box), the run's
  position and resolved deck as in format 2, the list of parts with each part's particle count and
  the SHA-256 of its checksums, and the writing run's decomposition (ranks, grid, cut planes).

No rank ever holds another rank's particles: a checkpoint of 10⁸ grains needs no more memory on
rank 0 than on any other.

**Atomic as a whole.** The parts go to a directory named with a fresh token, which no manifest names
yet; when every part is written (a collective check), rank 0 writes the manifest to ``*.tmp`` and
renames it over ``step_<step>.h5`` (atomic), then repoints ``latest.h5``, and only then removes other
part directories of the same step. A kill at any moment leaves ``latest.h5`` naming a complete
checkpoint (the previous one, until the rename); the orphaned part directory of a killed write is
removed by the next run that continues the folder (:func:`stray_parts`).

**Reading** (:func:`read_parts`, through :func:`pdem.io.checkpoint.read_checkpoint`): serially every
part is read and the whole state assembled, equal to format 2's (tools and tests compare them). On m
ranks, rank r reads parts r, r + m, …, checks their checksums and structure, and gets a
:class:`CheckpointShare`; the problems of all ranks are joined so that every rank raises the same
error. :meth:`pdem.Simulation.load_state` then places each particle on its owner
(:func:`pdem.parallel.exchange.scatter`): with the writer's rank count and grid, on the writer's
cut planes (nothing moves), else on planes at the particles' quantiles.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
from pathlib import Path

import h5py
import numpy as np

from ..errors import CheckpointError
from .checkpoint import (
    CHECKSUMS_ATTR,
    PARTED_FORMAT,
    READ_ERRORS,
    _quote,
    checksum_problems,
    point_latest,
    read_hdf5,
    structure_problems,
    write_hdf5,
)
from .state import CheckpointShare

__all__ = ["CheckpointShare", "write_parted", "read_parts", "is_part_key", "stray_parts", "checkpoint_parts"]

#: manifest attribute: the parts and the writer's decomposition (JSON)
PARTS_ATTR = "pdem_parts"
#: part attribute: which part of which checkpoint it is (JSON)
PART_ATTR = "pdem_part"
_PARTS_DIR = re.compile(r"(step_\d+)\.parts-[0-9a-f]{8}")
#: what writing a part or the manifest may raise (h5py: OSError, and ValueError/TypeError/RuntimeError
#: for data it cannot store)
WRITE_ERRORS = (OSError, ValueError, TypeError, RuntimeError)


def is_part_key(key: str) -> bool:
    """Does the state entry ``key`` belong to a rank's part (per particle or per contact), rather than
    to the manifest (the same on every rank)?"""
    if key.startswith(("particles/", "pairs/")):
        return True
    parts = key.split("/")
    return len(parts) == 3 and parts[0] == "walls" and parts[2] in ("rows", "ids", "hist")


def parts_dir_of(manifest: Path, meta: dict) -> Path | None:
    """The part directory a manifest names (None when its attribute is not readable)."""
    try:
        name = json.loads(meta[PARTS_ATTR])["dir"]
    except (KeyError, TypeError, ValueError):
        return None
    if not isinstance(name, str) or not _PARTS_DIR.fullmatch(name):
        return None
    return Path(manifest).with_name(name)


def _agree(comm, error: str | None) -> str | None:
    """The first rank's error, on every rank (collective)."""
    if comm.size == 1:
        return error
    errors = comm.allgather(error)
    return next((e for e in errors if e is not None), None)


# ------------------------------------------------------------------------------------ writing
def write_parted(path: Path, share: dict, meta: dict, comm) -> Path:
    """Write a per-rank checkpoint whose manifest is ``path`` (collective; see the module doc).
    ``share`` is this rank's :meth:`pdem.Simulation.state_dict` with ``local=True``."""
    path = Path(path)
    stem = path.name[: -len(".h5")] if path.name.endswith(".h5") else path.name
    token = comm.bcast(secrets.token_hex(4) if comm.rank == 0 else None, root=0) if comm.size > 1 else (
        secrets.token_hex(4)
    )
    parts = path.with_name(f"{stem}.parts-{token}")
    error = None
    if comm.rank == 0:
        try:
            parts.mkdir()
        except OSError as exc:
            error = f"cannot create {parts}: {exc}"
    error = _agree(comm, error)
    if error is None:
        name = f"rank_{comm.rank:05d}.h5"
        mine = {k: v for k, v in share.items() if is_part_key(k)}
        label = json.dumps({"index": comm.rank, "of": comm.size, "checkpoint": path.name})
        try:
            text = write_hdf5(parts / name, mine, {PART_ATTR: label}, PARTED_FORMAT)
            entry = {
                "file": name,
                "particles": int(np.asarray(share["particles/id"]).shape[0]),
                "sha256": hashlib.sha256(text.encode()).hexdigest(),
            }
        except WRITE_ERRORS as exc:  # (on one rank only: every rank learns it below, none hangs)
            entry, error = None, f"cannot write {parts / name}: {exc}"
        entries = comm.allgather((entry, error)) if comm.size > 1 else [(entry, error)]
        error = next((e for _, e in entries if e is not None), None)
    if error is None and comm.rank == 0:
        layout = getattr(share, "layout", None)
        manifest = {
            "dir": parts.name,
            "parts": [e for e, _ in entries],
            "particles": sum(e["particles"] for e, _ in entries),
            "layout": layout,
        }
        common = {k: v for k, v in share.items() if not is_part_key(k)}
        tmp = path.with_name(path.name + ".tmp")
        try:
            write_hdf5(tmp, common, {**meta, PARTS_ATTR: json.dumps(manifest)}, PARTED_FORMAT)
            os.replace(tmp, path)  # from here on the checkpoint exists, whole
            point_latest(path)
        except WRITE_ERRORS as exc:
            error = f"cannot write {path}: {exc}"
        else:
            for other in path.parent.glob(f"{stem}.parts-*"):  # an older write of the same step
                if other != parts and _PARTS_DIR.fullmatch(other.name):
                    shutil.rmtree(other, ignore_errors=True)
    if error is None and comm.size > 1:
        error = comm.bcast(error, root=0)
    if error is not None:
        if comm.rank == 0:
            shutil.rmtree(parts, ignore_errors=True)
        raise CheckpointError(f"cannot write checkpoint {path}: {error}; check disk space and permissions")
    return path


def checkpoint_parts(manifest: Path) -> Path | None:
    """The part directory of a per-rank checkpoint's manifest (None: not one, or not readable)."""
    try:
        with h5py.File(manifest, "r") as fh:
            text = fh.attrs.get(PARTS_ATTR)
    except READ_ERRORS:
        return None
    return parts_dir_of(manifest, {PARTS_ATTR: text.decode() if isinstance(text, bytes) else text})


def stray_parts(directory: Path) -> list[Path]:
    """Part directories in a checkpoint folder that no manifest names (a write a kill interrupted)."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    named = set()
    for manifest in directory.glob("step_*.h5"):
        if not manifest.is_symlink() and manifest.is_file():
            d = checkpoint_parts(manifest)
            if d is not None:
                named.add(d.name)
    return sorted(p for p in directory.iterdir() if _PARTS_DIR.fullmatch(p.name) and p.name not in named)


# ------------------------------------------------------------------------------------ reading
def _merge(states: list[dict]) -> dict[str, np.ndarray]:
    """Join parts: particles ordered by id, pairs each once in key order, wall rows by (row, id)."""
    out: dict[str, np.ndarray] = {}
    keys = sorted({k for s in states for k in s})
    for key in keys:
        arrays = [np.asarray(s[key]) for s in states if key in s]
        out[key] = np.concatenate(arrays) if len(arrays) > 1 else arrays[0]
    if "particles/id" in out:
        order = np.argsort(out["particles/id"], kind="stable")
        for key in keys:
            if key.startswith("particles/"):
                out[key] = out[key][order]
    if "pairs/keys" in out:
        pk, first = np.unique(out["pairs/keys"], return_index=True)
        out["pairs/keys"] = pk
        if "pairs/hist" in out:
            out["pairs/hist"] = out["pairs/hist"][first]
    for key in keys:
        if key.startswith("walls/") and key.endswith("/rows"):
            pre = key[: -len("rows")]
            if pre + "ids" in out:
                order = np.lexsort((out[pre + "ids"], out[key]))
                for name in ("rows", "ids", "hist"):
                    if pre + name in out:
                        out[pre + name] = out[pre + name][order]
    return out


def read_parts(path: Path, meta: dict, common: dict, comm=None) -> tuple[dict, list[str]]:
    """The state of the per-rank checkpoint whose manifest is ``path`` (its attributes ``meta``, its
    datasets ``common``, checked already): (state, problems). Without ``comm`` or on one rank, every
    part joined; on several ranks (collective), this rank's share (:class:`CheckpointShare`), with
    the problems of every rank's share."""
    size = 1 if comm is None else comm.size
    rank = 0 if comm is None else comm.rank
    problems: list[str] = []
    try:
        table = json.loads(meta[PARTS_ATTR])
        entries, dirname, total = table["parts"], table["dir"], int(table["particles"])
        layout = table.get("layout")
        if not isinstance(entries, list) or not entries or not _PARTS_DIR.fullmatch(str(dirname)):
            raise ValueError("no parts")
    except (KeyError, TypeError, ValueError):
        shown = _quote(meta.get(PARTS_ATTR))
        return {}, [f"attribute '{PARTS_ATTR}' (the list of parts) is not readable: {shown}"]
    base = Path(path).resolve().parent / dirname
    states = []
    for k in range(rank, len(entries), size):
        entry = entries[k]
        name = entry.get("file") if isinstance(entry, dict) else None
        if not isinstance(name, str) or "/" in name or name.startswith("."):
            problems.append(f"part {k} of attribute '{PARTS_ATTR}' is not readable: {_quote(entry)}")
            continue
        file = base / name
        where = f"part {dirname}/{name}"
        if not file.is_file():
            problems.append(f"{where} is missing")
            continue
        try:
            raw, part = read_hdf5(file)
        except READ_ERRORS as exc:
            problems.append(f"{where} cannot be read: {_quote(str(exc))}")
            continue
        text = raw.get(CHECKSUMS_ATTR)
        text = text.decode() if isinstance(text, bytes) else text
        if not isinstance(text, str) or hashlib.sha256(text.encode()).hexdigest() != entry.get("sha256"):
            problems.append(f"{where} is not the part the manifest lists (its checksums differ)")
            continue
        problems += [f"{where}: {p}" for p in checksum_problems(raw, part)]
        n = np.asarray(part.get("particles/id", np.zeros(0))).shape[0]
        if n != entry.get("particles"):
            listed = _quote(entry.get("particles"))
            problems.append(f"{where} holds {n} particles, the manifest lists {listed}")
        states.append(part)
    if states:
        state = _merge(states)
        state.update(common)
        problems += structure_problems(state, meta, 2) if not problems else []
    else:  # more ranks than parts: this rank starts without particles
        state = {"particles/id": np.zeros(0, np.int64), "pairs/keys": np.zeros(0, np.int64), **common}
    if size > 1:
        held = int(np.asarray(state.get("particles/id", np.zeros(0))).shape[0])
        counts = comm.allgather((held, problems))
        problems = [p for _, ps in counts for p in ps]
        problems = list(dict.fromkeys(problems))
        if not problems and sum(h for h, _ in counts) != total:
            problems.append(
                f"the parts hold {sum(h for h, _ in counts)} particles, the manifest lists {total}"
            )
        share = CheckpointShare(state)
        share.layout = layout if isinstance(layout, dict) else None
        return share, problems
    if not problems:
        held = int(np.asarray(state["particles/id"]).shape[0])
        if held != total:
            problems.append(f"the parts hold {held} particles, the manifest lists {total}")
    return state, problems
