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

Every ``.vtu`` is written to a temporary file and moved into place, so a run killed at any point
leaves only complete files, all listed in the ``.pvd`` files.
"""

from __future__ import annotations

import os
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path
from typing import ClassVar

import meshio
import numpy as np

from ..errors import OutputError
from .base import Writer, atomic_write_text, write_metadata_json
from .frame import Frame, WallState
from .wall_mesh import wall_triangles

__all__ = ["VTKWriter", "write_vtu"]


def write_vtu(path: Path, mesh: meshio.Mesh) -> None:
    """Write ``mesh`` as binary VTU to ``path`` atomically (temp file in the same dir + os.replace)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".vtu")
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
        ``particles/particles_*.vtu``, ``walls/walls_*.vtu`` instead of raising
        :class:`~pdem.errors.OutputError` (other files are left alone).
    resolution : segments around the axis of revolved walls and cylinders in the wall meshes.
    """

    name: ClassVar[str] = "vtk"

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
        self.particles_dir = self.directory / "particles"
        self.walls_dir = self.directory / "walls"
        self.particles_pvd = self.directory / "particles.pvd"
        self.walls_pvd = self.directory / "walls.pvd"
        self.metadata_path = self.directory / "metadata.json"
        old = [self.particles_pvd, self.walls_pvd, self.metadata_path]
        old += sorted(self.particles_dir.glob("particles_*.vtu")) + sorted(self.walls_dir.glob("walls_*.vtu"))
        self._claim(old)
        self._particle_entries: list[dict[str, str]] = []
        self._wall_entries: list[dict[str, str]] = []
        try:
            self.particles_dir.mkdir(exist_ok=True)
            self.walls_dir.mkdir(exist_ok=True)
            write_metadata_json(self.metadata_path, self.metadata)
        except OSError as exc:
            raise OutputError(
                f"VTKWriter: cannot set up the output in '{self.directory}' ({exc}); check that "
                f"'particles' and 'walls' there are directories (or absent), the permissions and free space"
            ) from exc

    def _write(self, frame: Frame, particles: dict[str, np.ndarray], walls: list[WallState]) -> None:
        key = f"{self.n_frames:06d}"
        time = repr(float(frame.time))
        wall_mesh = self._wall_mesh(frame, walls)  # first: a bad wall must not leave half a frame
        x = particles["x"]
        n = x.shape[0]
        point_data = {k: a for k, a in particles.items() if k != "x"}
        cells = [("vertex", np.arange(n, dtype=np.int64).reshape(-1, 1))]
        pfile = self.particles_dir / f"particles_{key}.vtu"
        write_vtu(pfile, meshio.Mesh(x, cells, point_data=point_data))
        particle_entry = {
            "timestep": time,
            "group": "",
            "part": "0",
            "file": f"{self.particles_dir.name}/{pfile.name}",
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


def _pvd_text(entries: list[dict[str, str]]) -> str:
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for e in entries:
        ET.SubElement(coll, "DataSet", e)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"
