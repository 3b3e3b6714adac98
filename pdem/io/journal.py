"""A resume into a run's own output directory as a transaction: what it replaces is held, not deleted.

``pdem resume`` continues the run's own directory as one time series, so what the previous run wrote
after the checkpoint (later checkpoints, series rows, snapshots) belongs to a future that the resume
replaces. Before anything is changed, :meth:`Journal.begin` records the directory as it is: the list
of its files, copies of the small files that are rewritten in place (series CSVs, XDMF and PVD
indexes, ``summary.json``, the resolved deck), the frame groups of every HDF5 file. What the resume
then drops is *held*, never deleted: later checkpoints and per-frame files are moved into the
journal folder (:func:`discard`), HDF5 frame groups are moved to the file's ``/replaced`` group
(:func:`discard_frame`).

- :meth:`Journal.commit` (the resume ended: every stage run, ``--steps``, a stage's ``max_time``):
  what was held is deleted and the journal removed.
- :meth:`Journal.rollback` (the resume failed or was refused): the directory is put back as it was
  before the resume, byte for byte for every file but the HDF5 ones, whose frames are put back
  (their values unchanged): what the failed resume wrote is removed, what it held is restored.

A journal left by a killed resume (``.pdem-journal/`` in the output directory, found by the next
run that takes the directory's lock) is settled before that run touches anything: rolled back when
the new run resumes from at or before the killed resume's checkpoint (the killed attempt is
replaced anyway, the previous future comes back until the new attempt succeeds), committed when it
resumes from a later checkpoint (one the killed attempt wrote: its output is the history being
continued) or when the directory is overwritten.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import h5py

__all__ = ["Journal", "JOURNAL_DIR", "discard", "discard_frame", "settle_stale"]

#: the journal's folder in an output directory
JOURNAL_DIR = ".pdem-journal"
_STATE = "journal.json"
#: entries never recorded nor touched by a rollback (the lock is held by the process running)
_SKIP = {JOURNAL_DIR, ".pdem-lock"}
#: files rewritten in place and small enough to copy whole (everything else is appended, or held)
_COPIED_SUFFIXES = {".csv", ".xdmf", ".pvd", ".json", ".toml", ".txt"}


def _active(directory: Path) -> Path | None:
    path = Path(directory) / JOURNAL_DIR
    return path if (path / _STATE).is_file() else None


def discard(directory: Path, path: Path) -> None:
    """Drop ``path`` (a file, or a folder such as a per-rank checkpoint's parts, in ``directory``'s
    tree): held in the open journal, else deleted."""
    journal = _active(directory)
    path = Path(path)
    folder = path.is_dir() and not path.is_symlink()
    if journal is None:
        if folder:
            shutil.rmtree(path)
        else:
            path.unlink()
        return
    rel = os.path.relpath(path, directory)
    target = journal / "held" / rel
    target.parent.mkdir(parents=True, exist_ok=True)
    if folder and target.exists():
        shutil.rmtree(target)
    os.replace(path, target)


def discard_frame(directory: Path, frames: h5py.Group, key: str) -> None:
    """Drop frame group ``key`` of an HDF5 file's ``/frames``: moved to ``/replaced`` while a journal
    is open in ``directory``, else deleted."""
    if _active(directory) is None:
        del frames[key]
        return
    f = frames.file
    held = f.require_group("replaced")
    if key in held:
        del held[key]
    f.move(f"{frames.name}/{key}", f"/replaced/{key}")


def _files(directory: Path) -> list[str]:
    """Relative paths of every file and symbolic link in ``directory``'s tree (the journal aside)."""
    out = []
    for root, dirs, files in os.walk(directory):
        rel_root = os.path.relpath(root, directory)
        if rel_root == ".":
            dirs[:] = [d for d in dirs if d not in _SKIP]
        for name in files + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            rel = os.path.normpath(os.path.join(rel_root, name))
            if rel not in _SKIP:
                out.append(rel)
    return sorted(out)


class Journal:
    """The transaction of one resume into ``directory`` (see the module doc); rank 0 only."""

    def __init__(self, directory: Path) -> None:
        self.directory = Path(directory)
        self.path = self.directory / JOURNAL_DIR

    # ------------------------------------------------------------------ opening
    def begin(self, step: int) -> None:
        """Record the directory before a resume from ``step`` changes it."""
        if self.path.exists():
            shutil.rmtree(self.path)
        (self.path / "copies").mkdir(parents=True)
        files = _files(self.directory)
        h5: dict[str, list[str]] = {}
        for rel in files:
            src = self.directory / rel
            if src.is_symlink():
                continue
            if src.suffix in _COPIED_SUFFIXES:
                dst = self.path / "copies" / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dst)
            elif src.suffix == ".h5" and not rel.startswith("checkpoints" + os.sep):
                try:
                    with h5py.File(src, "r") as f:
                        h5[rel] = sorted(f["frames"]) if "frames" in f else []
                except OSError:
                    continue  # not a frame file pdem can continue; the writer will say so
        links = {r: os.readlink(self.directory / r) for r in files if (self.directory / r).is_symlink()}
        state = {"step": int(step), "files": files, "h5_frames": h5, "links": links}
        tmp = self.path / (_STATE + ".tmp")
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self.path / _STATE)  # the journal exists from here on

    def _state(self) -> dict:
        return json.loads((self.path / _STATE).read_text())

    @property
    def step(self) -> int:
        return int(self._state()["step"])

    @property
    def open(self) -> bool:
        return (self.path / _STATE).is_file()

    @property
    def replaced_anything(self) -> bool:
        """Did the resume hold anything back or cut anything short (a future it replaces)? A file
        it only appended to (series rows after the checkpoint's) still starts with its copy."""
        held = self.path / "held"
        if held.is_dir() and any(held.rglob("*")):
            return True
        copies = self.path / "copies"
        for src in (p for p in copies.rglob("*") if p.is_file()):
            if src.suffix != ".csv":
                continue  # indexes and the deck are rewritten whole; the frames they list are held
            now = self.directory / src.relative_to(copies)
            old = src.read_bytes()
            try:
                with open(now, "rb") as fh:
                    if fh.read(len(old)) != old:
                        return True
            except OSError:
                return True
        for rel in self._state()["h5_frames"]:
            path = self.directory / rel
            try:
                with h5py.File(path, "r") as f:
                    if "replaced" in f and len(f["replaced"]):
                        return True
            except OSError:
                continue
        return False

    # ------------------------------------------------------------------ closing
    def commit(self) -> None:
        """The resume's output stands: delete what it held, remove the journal."""
        if not self.open:
            return
        state = self._state()
        for rel in state["h5_frames"]:
            path = self.directory / rel
            try:
                with h5py.File(path, "a") as f:
                    if "replaced" in f:
                        del f["replaced"]
            except OSError:
                continue
        (self.path / _STATE).unlink()
        shutil.rmtree(self.path, ignore_errors=True)

    def rollback(self) -> None:
        """Put the directory back as :meth:`begin` found it (see the module doc)."""
        if not self.open:
            return
        state = self._state()
        before = set(state["files"])
        # 1. what the resume created: removed (new checkpoints, frames, series of stages it reached)
        for rel in _files(self.directory):
            if rel not in before:
                path = self.directory / rel
                try:
                    path.unlink()
                except OSError:
                    pass
        for root, dirs, _ in os.walk(self.directory, topdown=False):  # folders it created, if empty
            for d in dirs:
                p = Path(root) / d
                rel = os.path.relpath(p, self.directory)
                if rel.split(os.sep)[0] in _SKIP or p.is_symlink():
                    continue
                if not any(r == rel or r.startswith(rel + os.sep) for r in before):
                    shutil.rmtree(p, ignore_errors=True)
        # 2. what it held: back in place
        held = self.path / "held"
        if held.is_dir():
            for src in sorted(p for p in held.rglob("*") if p.is_file() or p.is_symlink()):
                rel = os.path.relpath(src, held)
                dst = self.directory / rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
        for rel, target in state["links"].items():
            dst = self.directory / rel
            if dst.is_symlink() and os.readlink(dst) == target:
                continue
            tmp = dst.with_name(dst.name + ".restore")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(target, tmp)
            os.replace(tmp, dst)
        # 3. HDF5 frame files: the resume's frames out, the held ones back
        for rel, keys in state["h5_frames"].items():
            path = self.directory / rel
            try:
                with h5py.File(path, "a") as f:
                    frames = f.require_group("frames")
                    for key in list(frames):
                        if key not in keys:
                            del frames[key]
                    if "replaced" in f:
                        for key in list(f["replaced"]):
                            if key in frames:
                                del frames[key]
                            f.move(f"/replaced/{key}", f"{frames.name}/{key}")
                        del f["replaced"]
            except OSError:
                continue
        # 4. files rewritten in place: their copies back
        copies = self.path / "copies"
        for src in sorted(p for p in copies.rglob("*") if p.is_file()):
            rel = os.path.relpath(src, copies)
            dst = self.directory / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
        (self.path / _STATE).unlink()
        shutil.rmtree(self.path, ignore_errors=True)


def settle_stale(directory: Path, resume_step: int | None) -> str | None:
    """A journal left by a killed resume in ``directory``: rolled back if the run about to start
    resumes from at or before its step, else committed (see the module doc); what was done, or None.
    Call with the directory's lock held."""
    journal = Journal(directory)
    if not journal.open:
        if journal.path.exists():  # a journal killed while it was being begun: nothing was changed yet
            shutil.rmtree(journal.path, ignore_errors=True)
        return None
    step = journal.step
    if resume_step is not None and resume_step <= step:
        journal.rollback()
        return f"an interrupted resume from step {step} was undone"
    journal.commit()
    return f"the output of an interrupted resume from step {step} was kept"
