"""The contact network as VTK lines, one file per snapshot (deck ``[output] contacts = true``).

Files written in the output directory
-------------------------------------
``contacts/contacts_NNNNNN.vtu``
    one ``line`` cell per touching pair, from the centre of particle ``id_i`` to that of ``id_j``
    (``id_i < id_j``; across a periodic face to the nearest image of ``j``, so the line is as long
    as the contact is); cell data ``id_i``, ``id_j`` (int64), ``force`` (3) [N] (on ``j``; on
    ``i`` its negative), ``normal_force`` [N] (positive = repulsive), ``overlap`` [m]; the points
    carry no data. NNNNNN counts the network's own snapshots. ParaView: colour the lines by
    ``normal_force``, or apply *Tube* with the radius scaled by it (force chains).
``contacts.pvd``
    the collection of those files, one ``DataSet`` per snapshot (``timestep`` = time, with a
    ``step`` attribute ParaView ignores), rewritten atomically after each.

Snapshots are taken with the particle snapshots (the same steps and times). Continuing a run
(``append_after=(step, time)``): entries after ``step`` are dropped with their files and new
snapshots follow, as in :mod:`pdem.io.vtk`.
"""

from __future__ import annotations

from pathlib import Path

import meshio
import numpy as np

from ..errors import OutputError
from .base import atomic_write_text
from .journal import discard
from .vtk import _frame_number, _int, _pvd_text, _read_pvd, write_vtu

__all__ = ["ContactNetworkWriter", "contact_lines"]


def contact_lines(contacts: dict[str, np.ndarray], particles: dict[str, np.ndarray], box=None) -> meshio.Mesh:
    """The line mesh of a contact list (``Simulation.contacts()``) given the particles ordered by id
    (``Simulation.get_particles()``); ``box``: the periodic box (``Simulation.box``) or None."""
    ids = np.asarray(particles["id"])
    x = np.asarray(particles["x"], dtype=np.float64)
    i = np.searchsorted(ids, contacts["id_i"])
    j = np.searchsorted(ids, contacts["id_j"])
    k = len(i)
    if k and (np.any(i >= len(ids)) or np.any(ids[np.minimum(i, len(ids) - 1)] != contacts["id_i"])):
        raise OutputError("contact network: a contact names a particle that is not in the snapshot")
    d = x[j] - x[i]
    if box is not None:
        d = box.minimum_image(d)
    points = np.empty((2 * k, 3))
    points[0::2] = x[i]
    points[1::2] = x[i] + d
    cells = [("line", np.arange(2 * k, dtype=np.int64).reshape(k, 2))]
    data = {
        "id_i": np.asarray(contacts["id_i"], dtype=np.int64),
        "id_j": np.asarray(contacts["id_j"], dtype=np.int64),
        "force": np.asarray(contacts["force"], dtype=np.float64).reshape(k, 3),
        "normal_force": np.asarray(contacts["normal_force"], dtype=np.float64),
        "overlap": np.asarray(contacts["overlap"], dtype=np.float64),
    }
    return meshio.Mesh(points, cells, cell_data={name: [a] for name, a in data.items()})


class ContactNetworkWriter:
    """Writes :func:`contact_lines` meshes and ``contacts.pvd`` in ``directory`` (rank 0 only).

    ``append_after``: ``(step, time)`` to continue an existing network (see the module doc);
    otherwise existing network files are refused unless ``overwrite``.
    """

    def __init__(
        self, directory: Path | str, *, overwrite: bool = False, append_after: tuple[int, float] | None = None
    ) -> None:
        self.directory = Path(directory)
        self.folder = self.directory / "contacts"
        self.pvd = self.directory / "contacts.pvd"
        self.n_frames = 0
        self.last_step: int | None = None
        self._entries: list[dict[str, str]] = []
        files = sorted(self.folder.glob("contacts_*.vtu")) + ([self.pvd] if self.pvd.exists() else [])
        if append_after is not None:
            step, time = append_after
            for e in _read_pvd(self.pvd):
                s, t = _int(e.get("step")), e.get("timestep")
                if (s <= step) if s is not None else (t is not None and float(t) <= time):
                    self._entries.append(e)
            numbers = [n for n in (_frame_number(e.get("file", "")) for e in self._entries) if n is not None]
            self.n_frames = max(numbers) + 1 if numbers else 0
            self.last_step = _int(self._entries[-1].get("step")) if self._entries else None
            for path in files:
                n = _frame_number(path.name)
                if n is not None and n >= self.n_frames:
                    discard(self.directory, path)  # held while a resume is undecided
        elif files and not overwrite:
            raise OutputError(
                f"contact network files already exist in '{self.directory}' ({files[0].name}, …); choose "
                "an empty output directory or pass --overwrite"
            )
        else:
            for path in files:
                path.unlink()
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.pvd, _pvd_text(self._entries))
        except OSError as exc:
            raise OutputError(f"contact network: cannot write in '{self.directory}': {exc}") from exc

    def write(self, mesh: meshio.Mesh, time: float, step: int) -> None:
        """Add one snapshot of the network (its file, then the collection)."""
        name = f"contacts_{self.n_frames:06d}.vtu"
        try:
            write_vtu(self.folder / name, mesh)
            self._entries.append(
                {
                    "timestep": repr(float(time)),
                    "group": "",
                    "part": "0",
                    "file": f"contacts/{name}",
                    "step": str(step),
                }
            )
            atomic_write_text(self.pvd, _pvd_text(self._entries))
        except OSError as exc:
            raise OutputError(
                f"contact network: writing snapshot {self.n_frames} (step {step}) failed: {exc}; check free "
                "disk space and permissions"
            ) from exc
        self.n_frames += 1
        self.last_step = int(step)

    def close(self) -> None:
        """Nothing is held open; for symmetry with the writers."""
