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

from ..errors import CheckpointError, InputError

__all__ = ["write_checkpoint", "read_checkpoint", "CHECKPOINT_FORMAT", "BadCheckpointError"]

CHECKPOINT_FORMAT = 1


class BadCheckpointError(CheckpointError, InputError):
    """The file given as a checkpoint is missing, unreadable or not a pdem checkpoint: invalid input
    (exit code 2), unlike a checkpoint that cannot be written."""

    exit_code = 2


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
    if not path.is_file():
        if path.is_dir():
            example = path / "checkpoints" / "latest.h5" if (path / "checkpoints").is_dir() else None
            raise BadCheckpointError(
                f"checkpoint {path} is a directory; give a checkpoint file written by pdem, e.g. "
                f"{example or 'OUTPUT/checkpoints/latest.h5'}"
            )
        raise BadCheckpointError(
            f"checkpoint {path} does not exist; give a checkpoint file written by pdem "
            "(e.g. OUTPUT/checkpoints/latest.h5)"
        )
    try:
        with h5py.File(path, "r") as fh:
            fmt = fh.attrs.get("pdem_checkpoint_format")
            if fmt != CHECKPOINT_FORMAT:
                raise BadCheckpointError(
                    f"{path} is not a pdem checkpoint of format {CHECKPOINT_FORMAT} (found {fmt!r})"
                )
            meta = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in fh.attrs.items()}
            state: dict[str, np.ndarray] = {}

            def visit(name, obj):
                if isinstance(obj, h5py.Dataset):
                    state[name] = obj[()]

            fh.visititems(visit)
    except OSError as exc:
        raise BadCheckpointError(
            f"cannot read checkpoint {path}: {exc}; is it a checkpoint written by pdem (not damaged)?"
        ) from exc
    missing = [k for k in ("deck", "stage_index", "stage_start_time", "stage_start_step") if k not in meta]
    missing += [k for k in ("scalars/step", "scalars/time", "scalars/dt") if k not in state]
    if missing:
        raise BadCheckpointError(
            f"checkpoint {path} lacks {', '.join(missing)}; it was not written by the pdem command "
            "(Simulation.state_dict files cannot be resumed with pdem resume)"
        )
    return state, meta
