"""Checkpoints: HDF5 files holding :meth:`pdem.Simulation.state_dict`, the resolved deck and the run's
position (stage, steps and time into the stage), written atomically.

A checkpoint is first written to ``<name>.tmp`` in the same directory, flushed and closed, then
renamed over the final name (``os.replace`` is atomic on POSIX), so a crash while writing never
destroys the previous checkpoint. ``latest.h5`` always names the most recent complete one.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from ..errors import CheckpointError

__all__ = ["write_checkpoint", "read_checkpoint", "CHECKPOINT_FORMAT"]

CHECKPOINT_FORMAT = 1


def write_checkpoint(path: Path, state: dict[str, object], meta: dict[str, object]) -> Path:
    """Write ``state`` (arrays by slash-separated key) and ``meta`` (strings / numbers) atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with h5py.File(tmp, "w") as fh:
            fh.attrs["pdem_checkpoint_format"] = CHECKPOINT_FORMAT
            for key, val in meta.items():
                fh.attrs[key] = val
            for key, val in state.items():
                fh.create_dataset(key, data=np.asarray(val))
            fh.flush()
        os.replace(tmp, path)
        latest = path.with_name("latest.h5")
        ltmp = path.with_name("latest.h5.tmp")
        if ltmp.exists() or ltmp.is_symlink():
            ltmp.unlink()
        os.symlink(path.name, ltmp)
        os.replace(ltmp, latest)
    except OSError as exc:
        raise CheckpointError(
            f"cannot write checkpoint {path}: {exc}; check disk space and permissions"
        ) from exc
    return path


def read_checkpoint(path: Path) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Read a checkpoint back: (state arrays by key, metadata attributes)."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(
            f"checkpoint {path} does not exist; give a checkpoint file written by pdem "
            "(e.g. OUTPUT/checkpoints/latest.h5)"
        )
    try:
        with h5py.File(path, "r") as fh:
            fmt = fh.attrs.get("pdem_checkpoint_format")
            if fmt != CHECKPOINT_FORMAT:
                raise CheckpointError(
                    f"{path} is not a pdem checkpoint of format {CHECKPOINT_FORMAT} (found {fmt!r})"
                )
            meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in fh.attrs.items()}
            state: dict[str, np.ndarray] = {}

            def visit(name, obj):
                if isinstance(obj, h5py.Dataset):
                    state[name] = obj[()]

            fh.visititems(visit)
    except OSError as exc:
        raise CheckpointError(f"cannot read checkpoint {path}: {exc}") from exc
    return state, meta
