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
    ``force`` (3,) [N], ``torque`` (3,) [N m].
``particles.xdmf``, ``walls.xdmf``
    XDMF 3 sidecars: a ``Temporal`` collection with one grid per frame (``<Time Value>`` = frame
    time, written with ``repr`` so it round-trips exactly; ``step`` and ``stage`` as grid
    ``Information``; the metadata as domain ``Information``). Particles: a ``Uniform`` grid with
    ``Polyvertex`` topology (``NumberOfElements`` = n, one node each, connectivity
    ``/vertex_index/<n>``), ``XYZ`` geometry = ``x`` and every other field as a node ``Attribute``
    (``Vector`` for (n, 3), ``Scalar`` for (n,)). Frames without particles are left out of
    ``particles.xdmf`` (ParaView's XDMF reader fails on empty grids); they stay in ``particles.h5``.
    Walls: per frame a ``Spatial`` collection of one ``Uniform`` grid per wall (ParaView shows one
    block per wall, named after it) with ``Triangle`` topology; the wall's force and torque are
    grid-centred ``Vector`` attributes with inline values (field data in ParaView). Walls whose
    mesh is empty (a plane missing the scene box) are left out of the XDMF (they stay in
    ``walls.h5``), and so are frames without any wall triangle.

Robustness: every :meth:`HDF5Writer.write` opens each HDF5 file, appends the frame, flushes and
closes it; then rewrites both XDMF files atomically (temp file + ``os.replace``). A run killed
between frames leaves files that read back with everything written so far.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import h5py
import numpy as np

from ..boundaries._geometry import KIND_NAMES
from ..errors import OutputError
from .base import Writer, atomic_write_text, safe_key
from .frame import Frame, WallState
from .wall_mesh import wall_triangles

__all__ = ["HDF5Writer", "xdmf_number_type"]

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


class HDF5Writer(Writer):
    """Particles and walls to ``particles.h5`` / ``walls.h5`` with XDMF sidecars (see module doc).

    Parameters
    ----------
    directory : output directory (created if missing).
    fields : particle fields to write (``None``: all present in each frame; ``id``, ``x`` and ``r``
        are always written when present).
    metadata : strings stored as root attributes of both HDF5 files (and as ``Information`` in the
        XDMF domain).
    overwrite : replace existing ``particles.h5``, ``walls.h5``, ``particles.xdmf``, ``walls.xdmf``
        instead of raising :class:`~pdem.errors.OutputError`.
    resolution : segments around the axis of revolved walls and cylinders in the wall meshes.
    """

    name: ClassVar[str] = "hdf5"

    def __init__(
        self,
        directory: Path | str,
        *,
        fields: Sequence[str] | None = None,
        metadata: dict[str, str] | None = None,
        overwrite: bool = False,
        resolution: int = 48,
    ) -> None:
        super().__init__(directory, fields=fields, metadata=metadata, overwrite=overwrite)
        self.resolution = int(resolution)
        self.particles_path = self.directory / "particles.h5"
        self.walls_path = self.directory / "walls.h5"
        self.particles_xdmf = self.directory / "particles.xdmf"
        self.walls_xdmf = self.directory / "walls.xdmf"
        self._claim([self.particles_path, self.walls_path, self.particles_xdmf, self.walls_xdmf])
        # serialised once per frame: rewriting the XDMF costs one string join, not a re-serialisation
        self._particle_grids: list[str] = []
        self._wall_grids: list[str] = []
        for path in (self.particles_path, self.walls_path):
            try:
                with h5py.File(path, "w-", libver=_LIBVER) as f:
                    for k, v in self.metadata.items():
                        f.attrs[k] = v
                    f.create_group("frames")
            except OSError as exc:
                raise OutputError(
                    f"HDF5Writer: cannot create '{path}': {exc}; "
                    f"check the directory permissions and free space"
                ) from exc

    # ------------------------------------------------------------------ writing
    def _write(self, frame: Frame, particles: dict[str, np.ndarray], walls: list[WallState]) -> None:
        key = f"{self.n_frames:06d}"
        meshes = [wall_triangles(w.kind, w.params, frame.bounds, self.resolution) for w in walls]
        self._write_particles(frame, key, particles)
        self._write_walls(frame, key, walls, meshes)
        if particles["x"].shape[0] > 0:  # ParaView's XDMF (2) reader fails on empty grids
            self._particle_grids.append(_serialise(self._particle_grid(frame, key, particles)))
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
            f.flush()

    # ------------------------------------------------------------------ XDMF
    @staticmethod
    def _grid_header(grid: ET.Element, frame: Frame) -> None:
        ET.SubElement(grid, "Time", Value=repr(float(frame.time)))
        ET.SubElement(grid, "Information", Name="step", Value=str(int(frame.step)))
        ET.SubElement(grid, "Information", Name="stage", Value=str(frame.stage))

    def _particle_grid(self, frame: Frame, key: str, particles: dict[str, np.ndarray]) -> ET.Element:
        h5 = self.particles_path.name
        base = f"/frames/{key}"
        n = particles["x"].shape[0]
        grid = ET.Element("Grid", Name=f"frame_{key}", GridType="Uniform")
        self._grid_header(grid, frame)
        topo = ET.SubElement(
            grid, "Topology", TopologyType="Polyvertex", NumberOfElements=str(n), NodesPerElement="1"
        )
        _hdf_item(topo, h5, f"/vertex_index/{n}", (n,), np.dtype(np.int64))
        geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
        _hdf_item(geo, h5, f"{base}/x", particles["x"].shape, particles["x"].dtype)
        for name, a in particles.items():
            if name == "x":
                continue
            kind = "Vector" if a.ndim == 2 else "Scalar"
            att = ET.SubElement(grid, "Attribute", Name=name, AttributeType=kind, Center="Node")
            _hdf_item(att, h5, f"{base}/{name}", a.shape, a.dtype)
        return grid

    def _wall_grid(
        self, frame: Frame, key: str, walls: list[WallState], meshes: list[tuple[np.ndarray, np.ndarray]]
    ) -> ET.Element | None:
        h5 = self.walls_path.name
        coll = ET.Element("Grid", Name=f"frame_{key}", GridType="Collection", CollectionType="Spatial")
        self._grid_header(coll, frame)
        drawn = 0
        for w, (pts, tri) in zip(walls, meshes, strict=True):
            if tri.shape[0] == 0:
                continue
            base = f"/frames/{key}/{safe_key(w.name)}"
            grid = ET.SubElement(coll, "Grid", Name=safe_key(w.name), GridType="Uniform")
            topo = ET.SubElement(
                grid,
                "Topology",
                TopologyType="Triangle",
                NumberOfElements=str(tri.shape[0]),
                NodesPerElement="3",
            )
            _hdf_item(topo, h5, f"{base}/cells", tri.shape, tri.dtype)
            geo = ET.SubElement(grid, "Geometry", GeometryType="XYZ")
            _hdf_item(geo, h5, f"{base}/points", pts.shape, pts.dtype)
            _xml_vector_attribute(grid, "force", np.asarray(w.force, dtype=np.float64))
            _xml_vector_attribute(grid, "torque", np.asarray(w.torque, dtype=np.float64))
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


def _serialise(grid: ET.Element) -> str:
    """One frame's grid as indented XML text (nesting level of the Temporal collection's children)."""
    ET.indent(grid, space="  ", level=3)
    return "      " + ET.tostring(grid, encoding="unicode").rstrip() + "\n"
