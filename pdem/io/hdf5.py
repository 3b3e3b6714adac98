"""HDF5 output with XDMF sidecars that ParaView opens as one time series per file.

Files written in the output directory
-------------------------------------
``particles.h5``
    root attributes: the writer's ``metadata`` (strings);
    ``/frames/NNNNNN`` (frame counter, 6 digits): one dataset per particle field (``id``, ``x``,
    ``v``, …, dtype and values exactly as in the frame); attributes ``time`` [s], ``step``,
    ``stage``; ``/vertex_index/<n>`` = arange(n) (int64), the explicit Polyvertex connectivity the
    XDMF grids of frames with n particles share (ParaView's Xdmf3 readers make no cells without it).
``walls.h5``
    root attributes: ``metadata``; ``/frames/NNNNNN`` with attributes ``time``, ``step``,
    ``stage`` and one group per wall (named after the wall, characters outside
    ``[A-Za-z0-9_.-]`` replaced by ``_``) holding datasets ``points`` (m, 3) float64 [m] and
    ``cells`` (k, 3) int64 (triangles, from :func:`pdem.io.wall_mesh.wall_triangles`) and
    attributes ``name``, ``index`` (order in the frame), ``kind``, ``kind_name``, ``params`` (16,),
    ``force`` (3,) [N], ``torque`` (3,) [N m]; and a group ``cell_data`` with one row per triangle,
    the cell data of the VTK walls (:mod:`pdem.io.vtk`): ``wall_index`` (k,) int32 (= ``index``),
    ``kind`` (k,) int32, ``force`` (k, 3) float64 [N] and ``torque`` (k, 3) float64 [N m] (the
    wall's load repeated on each of its triangles). Frames written before ``cell_data`` existed
    lack it; they still read and continue.
``particles.xdmf``, ``walls.xdmf``
    XDMF 3 sidecars: a ``Temporal`` collection with one grid per frame (``<Time Value>`` = frame
    time, written with ``repr`` so it round-trips exactly; ``step`` and ``stage`` as grid
    ``Information``; the metadata as domain ``Information``). Particles: a ``Uniform`` grid with
    ``Polyvertex`` topology (``NumberOfElements`` = n, one node each, connectivity
    ``/vertex_index/<n>``), ``XYZ`` geometry = ``x`` and every other field as a node ``Attribute``
    (``Vector`` for (n, 3), ``Scalar`` for (n,)). Frames without particles are left out of
    ``particles.xdmf`` (ParaView's XDMF reader fails on empty grids); they stay in ``particles.h5``.
    Walls: per frame a ``Spatial`` collection of one ``Uniform`` grid per wall (ParaView shows one
    block per wall, named after it) with ``Triangle`` topology and the attributes the VTK walls
    carry: cell-centred ``wall_index`` and ``kind`` (``Scalar``) and ``force`` [N] and ``torque``
    [N m] (``Vector``), referencing ``cell_data`` (cell data in ParaView: colour the walls by
    ``force``); and, as before, the wall's force and torque as grid-centred ``Vector`` attributes
    of the same names with inline values (field data in ParaView). Walls whose
    mesh is empty (a plane missing the scene box) are left out of the XDMF (they stay in
    ``walls.h5``), and so are frames without any wall triangle.

Per-rank output (``comm=``, deck ``output.parallel = "per_rank"``)
-------------------------------------------------------------------
``particles.rRRRR.h5`` (``RRRR`` = rank, 4 digits or more) instead of ``particles.h5``
    one file per rank, laid out exactly like ``particles.h5`` but holding the particles that rank
    owns at each frame (ordered by id; concatenating the pieces of a frame and ordering by id gives
    the gathered frame, bitwise). Root attributes: ``metadata`` plus ``rank`` and ``n_ranks``.
    Every rank writes a group for every frame, even with no particles.
``particles.xdmf``
    the index, written by rank 0 only: each frame of the ``Temporal`` collection is a ``Spatial``
    collection (``Time``, ``step`` and ``stage`` on it) of one ``Uniform`` grid per rank piece,
    named ``rRRRR``, referencing that rank's file, with the same topology, geometry and attributes
    as the gathered grid. ParaView opens it as one dataset per time step (a multiblock of the
    pieces). Pieces without particles are left out, and so are frames without any particle.
``walls.h5``, ``walls.xdmf``
    written by rank 0 as in gathered output.

Continuing (``append_after=(step, time)``, used by ``pdem resume``): the existing files are opened,
frames after ``step`` are deleted from every particle file (gathered and per-rank pieces, of any
earlier rank count) and from ``walls.h5``, both XDMF files are rebuilt from the frames kept, and new
frames are appended with the following frame numbers, so ``particles.xdmf`` lists every time once,
in order, whichever layout or rank count wrote each frame.

Robustness: every :meth:`HDF5Writer.write` opens each HDF5 file, appends the frame, flushes and
closes it; then rewrites both XDMF files atomically (temp file + ``os.replace``). A run killed
between frames leaves files that read back with everything written so far. In per-rank output,
rank 0 rewrites the index only after every rank has closed its piece of the frame.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any, ClassVar

import h5py
import numpy as np

from ..api import KIND_NAMES
from ..errors import OutputError
from .base import Piece, Writer, atomic_write_text, piece_name, safe_key
from .frame import PARTICLE_FIELDS, Frame, WallState
from .journal import discard_frame
from .wall_mesh import wall_triangles

__all__ = ["HDF5Writer", "WALL_CELL_DATA", "wall_cell_data", "xdmf_number_type"]

# HDF5 1.8 file format: readable by every HDF5 >= 1.8 (ParaView's included) and allows attributes
# larger than 64 kB (a long deck in the metadata).
_LIBVER = ("v108", "v108")

_XDMF_HEADER = '<?xml version="1.0" encoding="utf-8"?>\n<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>\n'


def xdmf_number_type(dtype: np.dtype) -> tuple[str, str]:
    """XDMF ``(NumberType, Precision)`` of a NumPy dtype (float, signed or unsigned integer)."""
    dt = np.dtype(dtype)
    size = str(dt.itemsize)
    if dt.kind == "f":
        return "Float", size
    if dt.kind == "i":
        return ("Char" if dt.itemsize == 1 else "Int"), size
    if dt.kind == "u":
        return ("UChar" if dt.itemsize == 1 else "UInt"), size
    raise OutputError(f"no XDMF number type for dtype {dt}; write float or integer arrays")


def _hdf_item(parent: ET.Element, h5name: str, path: str, shape: Sequence[int], dtype: np.dtype) -> None:
    number, precision = xdmf_number_type(dtype)
    item = ET.SubElement(
        parent,
        "DataItem",
        Dimensions=" ".join(str(int(d)) for d in shape),
        NumberType=number,
        Precision=precision,
        Format="HDF",
    )
    item.text = f"{h5name}:{path}"


def _xml_vector_attribute(parent: ET.Element, name: str, values: np.ndarray) -> None:
    att = ET.SubElement(parent, "Attribute", Name=name, AttributeType="Vector", Center="Grid")
    item = ET.SubElement(att, "DataItem", Dimensions="1 3", NumberType="Float", Precision="8", Format="XML")
    item.text = " ".join(repr(float(v)) for v in values)


#: the per-triangle arrays of a wall (the VTK walls' cell data), in the order they are written
WALL_CELL_DATA = ("wall_index", "kind", "force", "torque")


def wall_cell_data(index: int, wall: WallState, n_cells: int) -> dict[str, np.ndarray]:
    """The cell data of wall number ``index`` of a frame drawn with ``n_cells`` triangles, as the VTK
    walls carry it: ``wall_index``, ``kind`` (int32) and the load ``force``, ``torque`` (float64,
    repeated on every triangle)."""
    return {
        "wall_index": np.full(n_cells, index, dtype=np.int32),
        "kind": np.full(n_cells, int(wall.kind), dtype=np.int32),
        "force": np.tile(np.asarray(wall.force, dtype=np.float64), (n_cells, 1)),
        "torque": np.tile(np.asarray(wall.torque, dtype=np.float64), (n_cells, 1)),
    }


def _wall_uniform_grid(
    coll: ET.Element,
    h5: str,
    key: str,
    wname: str,
    cells: tuple[tuple[int, ...], np.dtype],
    points: tuple[tuple[int, ...], np.dtype],
    force: np.ndarray,
    torque: np.ndarray,
    cell_data: dict[str, tuple[tuple[int, ...], np.dtype]],
) -> None:
    """Append one wall's Uniform grid to the frame's collection ``coll``: triangles, points, the cell
    attributes found in ``cell_data`` (name: shape, dtype of ``/frames/<key>/<wname>/cell_data/<name>``)
    and the grid-centred ``force``, ``torque``."""
    base = f"/frames/{key}/{wname}"
    grid = ET.SubElement(coll, "Grid", Name=wname, GridType="Uniform")
    topo = ET.SubElement(
        grid, "Topology", TopologyType="Triangle", NumberOfElements=str(cells[0][0]), NodesPerElement="3"
    )
    _hdf_item(topo, h5, f"{base}/cells", *cells)
    geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
    _hdf_item(geo, h5, f"{base}/points", *points)
    for name in WALL_CELL_DATA:
        if name not in cell_data:
            continue
        shape, dtype = cell_data[name]
        kind = "Vector" if len(shape) == 2 else "Scalar"
        att = ET.SubElement(grid, "Attribute", Name=name, AttributeType=kind, Center="Cell")
        _hdf_item(att, h5, f"{base}/cell_data/{name}", shape, dtype)
    _xml_vector_attribute(grid, "force", force)
    _xml_vector_attribute(grid, "torque", torque)


class HDF5Writer(Writer):
    """Particles and walls to ``particles.h5`` / ``walls.h5`` with XDMF sidecars (see module doc).

    Parameters
    ----------
    directory : output directory (created if missing).
    fields : particle fields to write (``None``: all present in each frame; ``id``, ``x`` and ``r``
        are always written when present).
    metadata : strings stored as root attributes of both HDF5 files (and as ``Information`` in the
        XDMF domain).
    overwrite : replace existing ``particles.h5``, ``particles.r*.h5``, ``walls.h5``,
        ``particles.xdmf``, ``walls.xdmf`` instead of raising :class:`~pdem.errors.OutputError`.
    resolution : segments around the axis of revolved walls and cylinders in the wall meshes.
    comm : write per-rank files joined by ``particles.xdmf`` (collective; see the module doc).
    append_after : ``(step, time)``: continue the files in ``directory`` (see the module doc).
    """

    name: ClassVar[str] = "hdf5"
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
        #: the particle file this process writes: particles.h5, or its rank's piece
        self.particles_path = self.piece_path(self.rank) if self.per_rank else self.directory / "particles.h5"
        self.walls_path = self.directory / "walls.h5"
        self.particles_xdmf = self.directory / "particles.xdmf"
        self.walls_xdmf = self.directory / "walls.xdmf"
        # serialised once per frame: rewriting the XDMF costs one string join, not a re-serialisation
        self._particle_grids: list[str] = []
        self._wall_grids: list[str] = []
        extra = {"rank": self.rank, "n_ranks": self.n_ranks} if self.per_rank else {}
        if self.append_after is not None:
            n_frames, last_step, pgrids, wgrids = self._collective(self._continue, root_only=True)[0]
            self.n_frames, self.last_step = n_frames, last_step
            if self.rank == 0:
                self._particle_grids, self._wall_grids = pgrids, wgrids
            self._collective(lambda: self._create(self.particles_path, extra, missing_only=True))
            if self.rank == 0:
                self._create(self.walls_path, {}, missing_only=True)
            return
        # rank 0 claims every file of either layout, so no stale piece of an earlier run lingers
        old = [self.directory / "particles.h5", self.walls_path, self.particles_xdmf, self.walls_xdmf]
        self._collective(
            lambda: self._claim(old + sorted(self.directory.glob("particles.r*.h5"))), root_only=True
        )
        self._collective(lambda: self._create(self.particles_path, extra))
        if self.rank == 0:
            self._create(self.walls_path, {})

    def piece_path(self, rank: int) -> Path:
        """Rank ``rank``'s particle file in per-rank output: ``particles.rRRRR.h5``."""
        return self.directory / f"particles.{piece_name(rank)}.h5"

    def _create(self, path: Path, extra: dict[str, int], missing_only: bool = False) -> None:
        if missing_only and path.exists():
            return
        try:
            with h5py.File(path, "w-", libver=_LIBVER) as f:
                for k, v in self.metadata.items():
                    f.attrs[k] = v
                for k, i in extra.items():
                    f.attrs[k] = np.int64(i)
                f.create_group("frames")
        except OSError as exc:
            raise OutputError(
                f"HDF5Writer: cannot create '{path}': {exc}; check the directory permissions and free space"
            ) from exc

    # ------------------------------------------------------------------ continuing
    def _open_existing(self, path: Path) -> h5py.File:
        try:
            return h5py.File(path, "a", libver=_LIBVER)
        except OSError as exc:
            raise OutputError(
                f"HDF5Writer: cannot continue the output in '{self.directory}': '{path.name}' cannot be "
                f"opened ({exc}); it may be held open by another program or damaged by a kill during a "
                f"write. Resume into a new directory instead (pdem resume ... --output DIR)"
            ) from exc

    def _continue(self) -> tuple[int, int | None, list[str], list[str]]:
        """Rank 0, appending: drop the frames after the checkpoint from every file, rebuild the XDMF
        grids of the frames kept; ``(frame count, last kept step, particle grids, wall grids)``."""
        files: list[tuple[int | None, Path]] = []
        if (self.directory / "particles.h5").exists():
            files.append((None, self.directory / "particles.h5"))
        for path in sorted(self.directory.glob("particles.r*.h5")):
            m = re.fullmatch(r"particles\.r(\d+)\.h5", path.name)
            if m:
                files.append((int(m.group(1)), path))
        # frame number -> header (time, step, stage) and its particle pieces (rank, file, shapes)
        headers: dict[int, Any] = {}
        pieces: dict[int, list[tuple[int | None, str, dict]]] = {}
        for rank, path in files:
            with self._open_existing(path) as f:
                for key, g in self._kept_frames(f, headers):
                    if "x" not in g:
                        continue
                    shapes = {k: (g[k].shape, g[k].dtype) for k in _field_order(list(g.keys()))}
                    pieces.setdefault(int(key), []).append((rank, path.name, shapes))
                f.flush()
        walls: dict[int, list[tuple[str, tuple, np.dtype, tuple, np.dtype, Any, Any, dict]]] = {}
        if self.walls_path.exists():
            with self._open_existing(self.walls_path) as f:
                for key, g in self._kept_frames(f, headers):
                    rows = []
                    for wname in g:
                        wg = g[wname]
                        if "points" not in wg or "cells" not in wg:
                            continue
                        rows.append(
                            (
                                int(wg.attrs.get("index", 0)),
                                wname,
                                wg["cells"].shape,
                                wg["cells"].dtype,
                                wg["points"].shape,
                                wg["points"].dtype,
                                np.asarray(wg.attrs.get("force", np.zeros(3)), dtype=np.float64),
                                np.asarray(wg.attrs.get("torque", np.zeros(3)), dtype=np.float64),
                                _cell_data_layout(wg),
                            )
                        )
                    walls[int(key)] = [r[1:] for r in sorted(rows, key=lambda r: r[0])]
                f.flush()
        pgrids: list[str] = []
        wgrids: list[str] = []
        for number in sorted(headers):
            key = f"{number:06d}"
            hdr = headers[number]
            parts = pieces.get(number, [])
            gathered = [p for p in parts if p[0] is None]
            if gathered:
                _, h5name, shapes = gathered[0]
                if shapes["x"][0][0] > 0:
                    pgrids.append(_serialise(self._particle_grid(f"frame_{key}", h5name, key, shapes, hdr)))
            elif parts:
                coll = ET.Element(
                    "Grid", Name=f"frame_{key}", GridType="Collection", CollectionType="Spatial"
                )
                self._grid_header(coll, hdr)
                for rank, h5name, shapes in sorted(parts, key=lambda p: p[0]):
                    if shapes["x"][0][0] > 0:
                        coll.append(self._particle_grid(piece_name(rank), h5name, key, shapes))
                if any(shapes["x"][0][0] > 0 for _, _, shapes in parts):
                    pgrids.append(_serialise(coll))
            grid = self._wall_grid_from_file(key, hdr, walls.get(number, []))
            if grid is not None:
                wgrids.append(_serialise(grid))
        n_frames = max(headers) + 1 if headers else 0
        last_step = int(headers[max(headers)].step) if headers else None
        if headers:
            atomic_write_text(self.particles_xdmf, self._xdmf_text("particles", pgrids))
            atomic_write_text(self.walls_xdmf, self._xdmf_text("walls", wgrids))
        else:  # nothing kept: no index referring to dropped frames
            for path in (self.particles_xdmf, self.walls_xdmf):
                if path.exists():
                    path.unlink()
        return n_frames, last_step, pgrids, wgrids

    def _kept_frames(self, f: h5py.File, headers: dict[int, Any]):
        """Delete the frames after the checkpoint from ``f``; yield ``(key, group)`` of the others
        and record their headers."""
        frames = f.get("frames")
        if frames is None:
            return
        for key in sorted(frames, key=lambda k: int(k) if k.isdigit() else -1):
            if not key.isdigit():
                continue
            g = frames[key]
            step = g.attrs.get("step")
            time = g.attrs.get("time")
            step = int(step) if step is not None else None
            time = float(time) if time is not None else None
            if not self._keeps(step, time):
                discard_frame(self.directory, frames, key)  # held while a resume is undecided
                continue
            stage = g.attrs.get("stage", "")
            stage = stage.decode() if isinstance(stage, bytes) else str(stage)
            headers.setdefault(int(key), SimpleNamespace(time=time or 0.0, step=step or 0, stage=stage))
            yield key, g

    def _wall_grid_from_file(self, key: str, hdr: Any, walls: list) -> ET.Element | None:
        h5 = self.walls_path.name
        coll = ET.Element("Grid", Name=f"frame_{key}", GridType="Collection", CollectionType="Spatial")
        self._grid_header(coll, hdr)
        drawn = 0
        for wname, cshape, cdtype, pshape, pdtype, force, torque, cell_data in walls:
            if cshape[0] == 0:
                continue
            _wall_uniform_grid(
                coll, h5, key, wname, (cshape, cdtype), (pshape, pdtype), force, torque, cell_data
            )
            drawn += 1
        return coll if drawn else None

    # ------------------------------------------------------------------ writing
    def _write(self, frame: Frame, particles: dict[str, np.ndarray], walls: list[WallState]) -> None:
        key = f"{self.n_frames:06d}"
        meshes = [wall_triangles(w.kind, w.params, frame.bounds, self.resolution) for w in walls]
        self._write_particles(frame, key, particles)
        self._write_walls(frame, key, walls, meshes)
        if particles["x"].shape[0] > 0:  # ParaView's XDMF (2) reader fails on empty grids
            grid = self._particle_grid(
                f"frame_{key}", self.particles_path.name, key, _shapes(particles), frame
            )
            self._particle_grids.append(_serialise(grid))
        self._finish_frame(frame, key, walls, meshes)

    def _write_piece(self, frame: Frame, particles: dict[str, np.ndarray]) -> None:
        self._write_particles(frame, f"{self.n_frames:06d}", particles)

    def _write_index(self, frame: Frame, pieces: list[Piece], walls: list[WallState]) -> None:
        key = f"{self.n_frames:06d}"
        meshes = [wall_triangles(w.kind, w.params, frame.bounds, self.resolution) for w in walls]
        self._write_walls(frame, key, walls, meshes)
        coll = ET.Element("Grid", Name=f"frame_{key}", GridType="Collection", CollectionType="Spatial")
        self._grid_header(coll, frame)
        for piece in pieces:
            if piece.n > 0:  # ParaView's XDMF (2) reader fails on empty grids
                shapes = {k: (shape, np.dtype(dt)) for k, (shape, dt) in piece.fields.items()}
                coll.append(self._particle_grid(piece.name, self.piece_path(piece.rank).name, key, shapes))
        if any(piece.n > 0 for piece in pieces):
            self._particle_grids.append(_serialise(coll))
        self._finish_frame(frame, key, walls, meshes)

    def _finish_frame(
        self, frame: Frame, key: str, walls: list[WallState], meshes: list[tuple[np.ndarray, np.ndarray]]
    ) -> None:
        """Add the frame's wall grid, then rewrite both XDMF files (particles are on disk by now)."""
        wall_grid = self._wall_grid(frame, key, walls, meshes)
        if wall_grid is not None:
            self._wall_grids.append(_serialise(wall_grid))
        atomic_write_text(self.particles_xdmf, self._xdmf_text("particles", self._particle_grids))
        atomic_write_text(self.walls_xdmf, self._xdmf_text("walls", self._wall_grids))

    def _open(self, path: Path) -> h5py.File:
        """Open ``path`` for appending; a failure (locked, missing, disk) is an OutputError naming it."""
        try:
            return h5py.File(path, "a", libver=_LIBVER)
        except OSError as exc:
            hint = (
                "another program holds it open (HDF5 locks files: close it there, or have readers set "
                "HDF5_USE_FILE_LOCKING=FALSE)"
                if "lock" in str(exc)
                else "check that it still exists, the permissions and the free disk space"
            )
            raise OutputError(
                f"HDF5Writer: cannot open '{path}' to append frame {self.n_frames}: {exc}; {hint}"
            ) from exc

    @staticmethod
    def _frame_group(f: h5py.File, key: str, frame: Frame) -> h5py.Group:
        frames = f.require_group("frames")
        if key in frames:  # left over by a write that failed half-way: replace it
            del frames[key]
        g = frames.create_group(key)
        g.attrs["time"] = np.float64(frame.time)
        g.attrs["step"] = np.int64(frame.step)
        g.attrs["stage"] = str(frame.stage)
        return g

    def _write_particles(self, frame: Frame, key: str, particles: dict[str, np.ndarray]) -> None:
        with self._open(self.particles_path) as f:
            g = self._frame_group(f, key, frame)
            for name, a in particles.items():
                g.create_dataset(name, data=a)
            n = particles["x"].shape[0]
            vi = f.require_group("vertex_index")
            if str(n) not in vi:
                vi.create_dataset(str(n), data=np.arange(n, dtype=np.int64))
            f.flush()

    def _write_walls(
        self, frame: Frame, key: str, walls: list[WallState], meshes: list[tuple[np.ndarray, np.ndarray]]
    ) -> None:
        with self._open(self.walls_path) as f:
            g = self._frame_group(f, key, frame)
            for i, (w, (pts, tri)) in enumerate(zip(walls, meshes, strict=True)):
                wg = g.create_group(safe_key(w.name))
                wg.create_dataset("points", data=pts)
                wg.create_dataset("cells", data=tri)
                wg.attrs["name"] = w.name
                wg.attrs["index"] = np.int64(i)
                wg.attrs["kind"] = np.int64(w.kind)
                wg.attrs["kind_name"] = KIND_NAMES.get(int(w.kind), "unknown")
                wg.attrs["params"] = np.asarray(w.params, dtype=np.float64)
                wg.attrs["force"] = np.asarray(w.force, dtype=np.float64)
                wg.attrs["torque"] = np.asarray(w.torque, dtype=np.float64)
                cg = wg.create_group("cell_data")
                for name, a in wall_cell_data(i, w, tri.shape[0]).items():
                    cg.create_dataset(name, data=a)
            f.flush()

    # ------------------------------------------------------------------ XDMF
    @staticmethod
    def _grid_header(grid: ET.Element, frame: Frame) -> None:
        ET.SubElement(grid, "Time", Value=repr(float(frame.time)))
        ET.SubElement(grid, "Information", Name="step", Value=str(int(frame.step)))
        ET.SubElement(grid, "Information", Name="stage", Value=str(frame.stage))

    @classmethod
    def _particle_grid(
        cls,
        name: str,
        h5: str,
        key: str,
        fields: dict[str, tuple[tuple[int, ...], np.dtype]],
        frame: Frame | None = None,
    ) -> ET.Element:
        """The Uniform grid of frame ``key``'s particles in file ``h5`` (``fields``: shape, dtype);
        with the frame's time, step and stage if ``frame`` is given."""
        base = f"/frames/{key}"
        shape_x, dtype_x = fields["x"]
        n = shape_x[0]
        grid = ET.Element("Grid", Name=name, GridType="Uniform")
        if frame is not None:
            cls._grid_header(grid, frame)
        topo = ET.SubElement(
            grid, "Topology", TopologyType="Polyvertex", NumberOfElements=str(n), NodesPerElement="1"
        )
        _hdf_item(topo, h5, f"/vertex_index/{n}", (n,), np.dtype(np.int64))
        geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
        _hdf_item(geo, h5, f"{base}/x", shape_x, dtype_x)
        for field, (shape, dtype) in fields.items():
            if field == "x":
                continue
            kind = "Vector" if len(shape) == 2 else "Scalar"
            att = ET.SubElement(grid, "Attribute", Name=field, AttributeType=kind, Center="Node")
            _hdf_item(att, h5, f"{base}/{field}", shape, dtype)
        return grid

    def _wall_grid(
        self, frame: Frame, key: str, walls: list[WallState], meshes: list[tuple[np.ndarray, np.ndarray]]
    ) -> ET.Element | None:
        h5 = self.walls_path.name
        coll = ET.Element("Grid", Name=f"frame_{key}", GridType="Collection", CollectionType="Spatial")
        self._grid_header(coll, frame)
        drawn = 0
        for i, (w, (pts, tri)) in enumerate(zip(walls, meshes, strict=True)):
            if tri.shape[0] == 0:
                continue
            cell_data = {k: (a.shape, a.dtype) for k, a in wall_cell_data(i, w, tri.shape[0]).items()}
            _wall_uniform_grid(
                coll, h5, key, safe_key(w.name), (tri.shape, tri.dtype), (pts.shape, pts.dtype),
                np.asarray(w.force, dtype=np.float64), np.asarray(w.torque, dtype=np.float64), cell_data,
            )  # fmt: skip
            drawn += 1
        return coll if drawn else None

    def _xdmf_text(self, name: str, grids: list[str]) -> str:
        """The whole XDMF document: metadata, then a Temporal collection of the serialised ``grids``."""
        info = "".join(
            f"    {ET.tostring(ET.Element('Information', Name=k, Value=v), encoding='unicode')}\n"
            for k, v in self.metadata.items()
        )
        series = ET.tostring(
            ET.Element("Grid", Name=name, GridType="Collection", CollectionType="Temporal"),
            encoding="unicode",
        )
        return (
            f'{_XDMF_HEADER}<Xdmf Version="3.0">\n  <Domain>\n{info}    {series[:-3]}>\n'
            + "".join(grids)
            + "    </Grid>\n  </Domain>\n</Xdmf>\n"
        )


def _field_order(names: list[str]) -> list[str]:
    """Dataset names in the order frames write them: known particle fields first, then the others."""
    return [k for k in PARTICLE_FIELDS if k in names] + sorted(k for k in names if k not in PARTICLE_FIELDS)


def _cell_data_layout(wg: h5py.Group) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of each ``cell_data`` array of a wall group in ``walls.h5`` (none: written
    before walls carried cell data)."""
    cg = wg.get("cell_data")
    if not isinstance(cg, h5py.Group):
        return {}
    return {k: (cg[k].shape, cg[k].dtype) for k in WALL_CELL_DATA if isinstance(cg.get(k), h5py.Dataset)}


def _shapes(particles: dict[str, np.ndarray]) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    return {k: (a.shape, a.dtype) for k, a in particles.items()}


def _serialise(grid: ET.Element) -> str:
    """One frame's grid as indented XML text (nesting level of the Temporal collection's children)."""
    ET.indent(grid, space="  ", level=3)
    return "      " + ET.tostring(grid, encoding="unicode").rstrip() + "\n"
