"""VTK XML output: one ``.vtu`` per frame plus ``.pvd`` collections that ParaView opens as a series.

Files written in the output directory
-------------------------------------
``particles/particles_NNNNNN.vtu``
    points = particle centres ``x`` [m], one ``vertex`` cell per particle, point data = the other
    particle fields (``id``, ``v``, ``w``, ``f``, ``t``, ``r``, ``mass``, ``material``,
    ``contacts``; dtypes and values exactly as in the frame; binary, zlib-compressed). The radius
    ``r`` is always included when the frame has it: in ParaView apply *Glyph* (Sphere), *Scale Array*
    = ``r``, *Scale Factor* = 2 (the glyph sphere has radius 0.5).
``walls/walls_NNNNNN.vtu``
    all wall meshes of the frame (:func:`pdem.io.wall_mesh.wall_triangles`) merged into one grid of
    triangles; cell data ``wall_index`` (int32, the wall's position in the frame), ``kind`` (int32),
    ``force`` (3) [N] and ``torque`` (3) [N m] (the load of the wall, repeated on each of its
    triangles so ParaView can colour walls by it). Written only when the frame has at least one
    triangle.
``particles.pvd``, ``walls.pvd``
    VTK collections listing every frame (``timestep`` = frame time, written with ``repr``),
    rewritten atomically after every frame. Each ``walls.pvd`` entry also carries the wall names in
    ``wall_index`` order in a ``walls`` attribute (``;``-separated), which ParaView ignores.
``metadata.json``
    the writer's ``metadata`` as a JSON object.

Per-rank output (``comm=``, deck ``output.parallel = "per_rank"``)
-------------------------------------------------------------------
``particles/rRRRR/particles_NNNNNN.vtu`` (``RRRR`` = rank)
    each rank's piece of frame ``NNNNNN``: the particles it owns, ordered by id, laid out like the
    gathered ``.vtu`` (written by every rank for every frame, even with no particles).
``particles/particles_NNNNNN.pvtu``
    the frame's index, written by rank 0 only: a ``PUnstructuredGrid`` listing every rank's piece
    (in rank order) with the point data arrays' names, types and components.
``particles.pvd``
    lists the ``.pvtu`` files, so ParaView opens one dataset per time step.
``walls/…``, ``walls.pvd``, ``metadata.json``
    written by rank 0 as in gathered output.

Continuing (``append_after=(step, time)``, used by ``pdem resume``): the entries of both ``.pvd`` files
after ``step`` (by their ``step`` attribute, which ParaView ignores, or by time for files written
before it existed) are dropped with their ``.vtu``/``.pvtu`` files, and new frames are appended with
the following frame numbers.

Every ``.vtu`` is written to a temporary file and moved into place, so a run killed at any point
leaves only complete files, all listed in the ``.pvd`` files. In per-rank output, rank 0 writes the
``.pvtu`` (atomically) only after every rank has written its piece, then the ``.pvd``.
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import meshio
import numpy as np

from ..errors import OutputError
from .base import Piece, Writer, atomic_write_text, make_temp_file, piece_name, write_metadata_json
from .frame import Frame, WallState
from .journal import discard
from .wall_mesh import wall_triangles

__all__ = ["VTKWriter", "write_vtu"]


def write_vtu(path: Path, mesh: meshio.Mesh) -> None:
    """Write ``mesh`` as binary VTU to ``path`` atomically (temp file in the same dir + os.replace)."""
    path = Path(path)
    fd, tmp = make_temp_file(path, suffix=".vtu")  # meshio picks the format by the suffix
    os.close(fd)
    try:
        meshio.write(tmp, mesh, file_format="vtu", binary=True, compression="zlib")
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


class VTKWriter(Writer):
    """Particles and walls as ``.vtu`` files per frame with ``.pvd`` collections (see module doc).

    Parameters
    ----------
    directory : output directory (created if missing).
    fields : particle fields to write (``None``: all present in each frame; ``id``, ``x`` and ``r``
        are always written when present).
    metadata : strings written to ``metadata.json``.
    overwrite : replace existing ``particles.pvd``, ``walls.pvd``, ``metadata.json`` and
        ``particles/particles_*.vtu``, ``particles/particles_*.pvtu``,
        ``particles/r*/particles_*.vtu``, ``walls/walls_*.vtu`` instead of raising
        :class:`~pdem.errors.OutputError` (other files are left alone).
    resolution : segments around the axis of revolved walls and cylinders in the wall meshes.
    comm : write per-rank pieces joined by ``.pvtu`` files (collective; see the module doc).
    append_after : ``(step, time)``: continue the files in ``directory`` (see the module doc).
    """

    name: ClassVar[str] = "vtk"
    supports_per_rank: ClassVar[bool] = True
    supports_append: ClassVar[bool] = True

    def __init__(
        self,
        directory: Path | str,
        *,
        fields: Sequence[str] | None = None,
        metadata: dict[str, str] | None = None,
        overwrite: bool = False,
        resolution: int = 48,
        comm=None,
        append_after: tuple[int, float] | None = None,
    ) -> None:
        super().__init__(
            directory,
            fields=fields,
            metadata=metadata,
            overwrite=overwrite,
            comm=comm,
            append_after=append_after,
        )
        self.resolution = int(resolution)
        self.particles_dir = self.directory / "particles"
        self.walls_dir = self.directory / "walls"
        self.particles_pvd = self.directory / "particles.pvd"
        self.walls_pvd = self.directory / "walls.pvd"
        self.metadata_path = self.directory / "metadata.json"
        #: the directory of this rank's pieces in per-rank output
        self.piece_dir = self.particles_dir / piece_name(self.rank)
        self._particle_entries: list[dict[str, str]] = []
        self._wall_entries: list[dict[str, str]] = []
        if self.append_after is not None:
            n_frames, last_step, pentries, wentries = self._collective(self._continue, root_only=True)[0]
            self.n_frames, self.last_step = n_frames, last_step
            if self.rank == 0:
                self._particle_entries, self._wall_entries = pentries, wentries
        else:
            self._collective(self._set_up, root_only=True)
        if self.per_rank:
            self._collective(self._make_piece_dir)

    def _set_up(self) -> None:
        """Claim the files of either layout (so no stale piece lingers), make the directories."""
        old = [self.particles_pvd, self.walls_pvd, self.metadata_path]
        old += sorted(self.particles_dir.glob("particles_*.vtu"))
        old += sorted(self.particles_dir.glob("particles_*.pvtu"))
        old += sorted(self.particles_dir.glob("r*/particles_*.vtu"))
        old += sorted(self.walls_dir.glob("walls_*.vtu"))
        self._claim(old)
        try:
            self.particles_dir.mkdir(exist_ok=True)
            self.walls_dir.mkdir(exist_ok=True)
            write_metadata_json(self.metadata_path, self.metadata)
        except OSError as exc:
            raise OutputError(
                f"VTKWriter: cannot set up the output in '{self.directory}' ({exc}); check that "
                f"'particles' and 'walls' there are directories (or absent), the permissions and free space"
            ) from exc

    def _continue(self) -> tuple[int, int | None, list[dict[str, str]], list[dict[str, str]]]:
        """Rank 0, appending: keep the .pvd entries up to the checkpoint, delete the files of later
        frames; ``(frame count, last kept step, particle entries, wall entries)``."""
        kept_p = [
            e
            for e in _read_pvd(self.particles_pvd)
            if self._keeps(_int(e.get("step")), _float(e.get("timestep")))
        ]
        numbers = [n for n in (_frame_number(e.get("file", "")) for e in kept_p) if n is not None]
        n_frames = max(numbers) + 1 if numbers else 0
        kept_w = [e for e in _read_pvd(self.walls_pvd) if (_frame_number(e.get("file", "")) or 0) < n_frames]
        stale = [p for p in self.particles_dir.glob("particles_*.vtu")]
        stale += list(self.particles_dir.glob("particles_*.pvtu"))
        stale += list(self.particles_dir.glob("r*/particles_*.vtu"))
        stale += list(self.walls_dir.glob("walls_*.vtu"))
        for path in stale:
            number = _frame_number(path.name)
            if number is not None and number >= n_frames:
                discard(self.directory, path)  # held while a resume is undecided
        try:
            self.particles_dir.mkdir(exist_ok=True)
            self.walls_dir.mkdir(exist_ok=True)
            write_metadata_json(self.metadata_path, self.metadata)
            atomic_write_text(self.particles_pvd, _pvd_text(kept_p))
            atomic_write_text(self.walls_pvd, _pvd_text(kept_w))
        except OSError as exc:
            raise OutputError(f"VTKWriter: cannot continue the output in '{self.directory}': {exc}") from exc
        last_step = _int(kept_p[-1].get("step")) if kept_p else None
        if kept_p and last_step is None:  # written before entries carried the step: only the time is known
            last_step = (
                self.append_after[0] if _float(kept_p[-1].get("timestep")) == self.append_after[1] else None
            )
        return n_frames, last_step, kept_p, kept_w

    def _make_piece_dir(self) -> None:
        try:
            self.piece_dir.mkdir(exist_ok=True)
        except OSError as exc:
            raise OutputError(
                f"VTKWriter: cannot create '{self.piece_dir}' for rank {self.rank}'s pieces ({exc}); "
                f"check that it is a directory (or absent) and the permissions"
            ) from exc

    def _write(self, frame: Frame, particles: dict[str, np.ndarray], walls: list[WallState]) -> None:
        key = f"{self.n_frames:06d}"
        wall_mesh = self._wall_mesh(frame, walls)  # first: a bad wall must not leave half a frame
        pfile = self.particles_dir / f"particles_{key}.vtu"
        write_vtu(pfile, _particle_mesh(particles))
        self._finish_frame(frame, key, pfile, walls, wall_mesh)

    def _write_piece(self, frame: Frame, particles: dict[str, np.ndarray]) -> None:
        write_vtu(self.piece_dir / f"particles_{self.n_frames:06d}.vtu", _particle_mesh(particles))

    def _write_index(self, frame: Frame, pieces: list[Piece], walls: list[WallState]) -> None:
        key = f"{self.n_frames:06d}"
        wall_mesh = self._wall_mesh(frame, walls)
        pfile = self.particles_dir / f"particles_{key}.pvtu"
        sources = [f"{piece.name}/particles_{key}.vtu" for piece in pieces]
        layout = [(k, shape[1:], dt) for k, (shape, dt) in pieces[0].fields.items()]
        for piece in pieces[1:]:  # one .pvtu declares the arrays of every piece
            if [(k, shape[1:], dt) for k, (shape, dt) in piece.fields.items()] != layout:
                raise OutputError(
                    f"VTKWriter frame {self.n_frames}: rank {piece.rank}'s particle fields "
                    f"{piece.fields} differ from rank 0's {pieces[0].fields} in names, components or "
                    f"dtypes; every rank must write the same fields"
                )
        atomic_write_text(pfile, _pvtu_text(pieces[0].fields, sources))
        self._finish_frame(frame, key, pfile, walls, wall_mesh)

    def _finish_frame(
        self, frame: Frame, key: str, pfile: Path, walls: list[WallState], wall_mesh: meshio.Mesh | None
    ) -> None:
        """Write the walls' file, then add the frame to both .pvd files (particles are on disk)."""
        time = repr(float(frame.time))
        particle_entry = {
            "timestep": time,
            "group": "",
            "part": "0",
            "file": f"{self.particles_dir.name}/{pfile.name}",
            "step": str(int(frame.step)),
        }
        wall_entry = None
        if wall_mesh is not None:
            wfile = self.walls_dir / f"walls_{key}.vtu"
            write_vtu(wfile, wall_mesh)
            wall_entry = {
                "timestep": time,
                "group": "",
                "part": "0",
                "file": f"{self.walls_dir.name}/{wfile.name}",
                "walls": ";".join(w.name for w in walls),
                "step": str(int(frame.step)),
            }
        self._particle_entries.append(particle_entry)
        if wall_entry is not None:
            self._wall_entries.append(wall_entry)
        atomic_write_text(self.particles_pvd, _pvd_text(self._particle_entries))
        atomic_write_text(self.walls_pvd, _pvd_text(self._wall_entries))

    def _wall_mesh(self, frame: Frame, walls: list[WallState]) -> meshio.Mesh | None:
        """All walls of the frame merged into one triangle mesh with per-cell wall data (None: empty)."""
        pts_all: list[np.ndarray] = []
        tri_all: list[np.ndarray] = []
        cdata: dict[str, list[np.ndarray]] = {"wall_index": [], "kind": [], "force": [], "torque": []}
        offset = 0
        for i, w in enumerate(walls):
            pts, tri = wall_triangles(w.kind, w.params, frame.bounds, self.resolution)
            k = tri.shape[0]
            if k == 0:
                continue
            pts_all.append(pts)
            tri_all.append(tri + offset)
            offset += pts.shape[0]
            cdata["wall_index"].append(np.full(k, i, dtype=np.int32))
            cdata["kind"].append(np.full(k, int(w.kind), dtype=np.int32))
            cdata["force"].append(np.tile(np.asarray(w.force, dtype=np.float64), (k, 1)))
            cdata["torque"].append(np.tile(np.asarray(w.torque, dtype=np.float64), (k, 1)))
        if not tri_all:
            return None
        return meshio.Mesh(
            np.concatenate(pts_all),
            [("triangle", np.concatenate(tri_all))],
            cell_data={name: [np.concatenate(parts)] for name, parts in cdata.items()},
        )


def _particle_mesh(particles: dict[str, np.ndarray]) -> meshio.Mesh:
    """Points = ``x``, one vertex cell per particle, the other fields as point data."""
    x = particles["x"]
    point_data = {k: a for k, a in particles.items() if k != "x"}
    cells = [("vertex", np.arange(x.shape[0], dtype=np.int64).reshape(-1, 1))]
    return meshio.Mesh(x, cells, point_data=point_data)


#: VTK XML type names of NumPy dtypes (what meshio writes in the pieces)
_VTK_TYPES = {
    np.dtype(t).str: name
    for t, name in [
        (np.int8, "Int8"),
        (np.uint8, "UInt8"),
        (np.int16, "Int16"),
        (np.uint16, "UInt16"),
        (np.int32, "Int32"),
        (np.uint32, "UInt32"),
        (np.int64, "Int64"),
        (np.uint64, "UInt64"),
        (np.float32, "Float32"),
        (np.float64, "Float64"),
    ]
}


def _vtk_type(dtype: str) -> str:
    try:
        return _VTK_TYPES[np.dtype(dtype).newbyteorder("<").str]
    except KeyError:
        raise OutputError(
            f"no VTK data type for dtype {np.dtype(dtype)}; write float or integer arrays"
        ) from None


def _pvtu_text(fields: dict[str, tuple[tuple[int, ...], str]], sources: list[str]) -> str:
    """A PUnstructuredGrid joining the ``.vtu`` pieces ``sources`` (paths relative to the file).

    ``fields`` (shape, dtype string) describes the pieces' arrays: ``x`` the points, the others the
    point data. The cell arrays are declared as meshio writes them (Int64).
    """
    root = ET.Element("VTKFile", type="PUnstructuredGrid", version="0.1", byte_order="LittleEndian")
    grid = ET.SubElement(root, "PUnstructuredGrid", GhostLevel="0")
    pdata = ET.SubElement(grid, "PPointData")
    for name, (shape, dtype) in fields.items():
        if name == "x":
            continue
        att = {"type": _vtk_type(dtype), "Name": name}
        if len(shape) == 2:
            att["NumberOfComponents"] = str(shape[1])
        ET.SubElement(pdata, "PDataArray", att)
    points = ET.SubElement(grid, "PPoints")
    ET.SubElement(points, "PDataArray", type=_vtk_type(fields["x"][1]), Name="Points", NumberOfComponents="3")
    pcells = ET.SubElement(grid, "PCells")
    for name in ("connectivity", "offsets", "types"):
        ET.SubElement(pcells, "PDataArray", type="Int64", Name=name)
    for src in sources:
        ET.SubElement(grid, "Piece", Source=src)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _read_pvd(path: Path) -> list[dict[str, str]]:
    """The ``DataSet`` entries of a ``.pvd`` file (none if it is missing)."""
    if not path.exists():
        return []
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise OutputError(
            f"VTKWriter: cannot continue '{path}': {exc}; resume into a new directory instead "
            f"(pdem resume ... --output DIR)"
        ) from exc
    return [dict(e.attrib) for e in root.iter("DataSet")]


def _frame_number(name: str) -> int | None:
    m = re.search(r"_(\d+)\.p?vtu$", name)
    return int(m.group(1)) if m else None


def _int(text: str | None) -> int | None:
    try:
        return int(text) if text is not None else None
    except ValueError:
        return None


def _float(text: str | None) -> float | None:
    try:
        return float(text) if text is not None else None
    except ValueError:
        return None


def _pvd_text(entries: list[dict[str, str]]) -> str:
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for e in entries:
        ET.SubElement(coll, "DataSet", e)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
