"""Output writers: wall meshes (areas), HDF5 + XDMF, VTK + PVD, CSV series; round trips are bitwise.

If ParaView's ``pvpython`` is on PATH, the XDMF and PVD files are also opened in ParaView and the
number of points and time steps checked; otherwise that test is skipped.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest

from pdem.errors import OutputError
from pdem.geometry._kernels import KIND_CYLINDER, KIND_PLANE, KIND_RECTANGLE, KIND_REVOLVED, N_PARAMS
from pdem.geometry.shapes import Annulus, Cylinder, CylinderTube, Disk, Frustum, Plane, Rectangle
from pdem.io import (
    PARTICLE_FIELDS,
    Frame,
    HDF5Writer,
    SeriesWriter,
    VTKWriter,
    WallState,
    mesh_area,
    read_series,
    wall_triangles,
)

BOX = (np.array([0.0, 0.0, 0.0]), np.array([1.0, 2.0, 3.0]))
N_PART = 300
TIMES = [0.0, 0.1 + 0.2, 2.0 / 3.0]  # awkward floats: the time values must round-trip exactly
METADATA = {"deck": 'title = "test"\n[run]\ndt = 1e-5\n', "pdem_version": "0.1.0"}


# ---------------------------------------------------------------------------------------------
# wall meshes
# ---------------------------------------------------------------------------------------------


def _area(shape, bounds=BOX, resolution=48) -> float:
    pts, tri = wall_triangles(shape.kind, shape.params(), bounds, resolution)
    assert pts.dtype == np.float64 and pts.ndim == 2 and pts.shape[1] == 3
    assert tri.dtype == np.int64 and tri.ndim == 2 and tri.shape[1] == 3
    assert np.all(np.isfinite(pts))
    if tri.size:
        assert tri.min() >= 0 and tri.max() < pts.shape[0]
    return mesh_area(pts, tri)


@pytest.mark.parametrize(
    ("shape", "exact"),
    [
        (Rectangle((0.1, 0.2, 0.3), (0, 1, 1), (1, 0, 0), (0.2, 0.7)), 4 * 0.2 * 0.7),
        (Disk((0, 0, 0), (1, 2, 3), 0.4), math.pi * 0.4**2),
        (Annulus((0, 0, 1), (0, 0, 1), 0.1, 0.3), math.pi * (0.3**2 - 0.1**2)),
        (CylinderTube((0, 0, 0), (1, 1, 0), 0.25, 1.5), 2 * math.pi * 0.25 * 1.5),
        (Frustum((0, 0, 0), (0, 0, 1), 0.0, 0.3, 0.4), math.pi * 0.3 * math.hypot(0.3, 0.4)),
        (Frustum((0, 0, 0), (0, 0, -1), 0.3, 0.0, 0.4), math.pi * 0.3 * math.hypot(0.3, 0.4)),
        (Frustum((1, 1, 1), (0, 1, 0), 0.05, 0.4, 0.5), math.pi * 0.45 * math.hypot(0.35, 0.5)),
    ],
    ids=["rectangle", "disk", "annulus", "tube", "cone", "cone_apex_at_end", "frustum"],
)
def test_finite_wall_areas(shape, exact):
    assert _area(shape) == pytest.approx(exact, rel=0.01)


def test_revolved_resolution_converges():
    disk = Disk((0, 0, 0), (0, 0, 1), 1.0)
    err = [abs(_area(disk, resolution=k) - math.pi) for k in (12, 48, 192)]
    assert err[0] > err[1] > err[2] and err[1] / math.pi < 0.003


@pytest.mark.parametrize(
    ("point", "normal", "exact"),
    [
        ((0.5, 0.5, 1.2), (0, 0, 1), 2.0),  # horizontal section: 1 x 2
        ((0.5, 0.5, 0.0), (0, 0, 1), 2.0),  # on the bottom face of the box
        ((0.5, 0.5, 3.0), (0, 0, -1), 2.0),  # on the top face, facing down
        ((1.0, 0.5, 0.5), (-1, 0, 0), 6.0),  # on the x-max face
        ((0.5, 1.0, 1.5), (1, 1, 0), math.sqrt(2) * 3.0),  # diagonal: width sqrt(2), height 3
    ],
)
def test_plane_patch_area(point, normal, exact):
    shape = Plane(point, normal)
    pts, tri = wall_triangles(shape.kind, shape.params(), BOX)
    assert mesh_area(pts, tri) == pytest.approx(exact, rel=1e-12)
    n = shape.normal
    d = (pts - shape.point) @ n
    assert np.allclose(d, 0.0, atol=1e-12)  # the patch lies in the plane
    assert np.all(pts >= BOX[0] - 1e-12) and np.all(pts <= BOX[1] + 1e-12)  # ... and inside the box
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    assert np.all(np.cross(b - a, c - a) @ n > 0)  # triangles face the particle side


def test_plane_patch_hexagon_and_misses():
    cube = (np.zeros(3), np.ones(3))
    hexagon = Plane((0.5, 0.5, 0.5), (1, 1, 1))  # regular hexagon of side sqrt(2)/2
    pts, tri = wall_triangles(hexagon.kind, hexagon.params(), cube)
    assert pts.shape[0] == 6
    assert mesh_area(pts, tri) == pytest.approx(3 * math.sqrt(3) / 4, rel=1e-12)
    triangle = Plane((1, 0, 0), (1, 1, 1))  # cuts off a corner: equilateral triangle of side sqrt(2)
    assert _area(triangle, cube) == pytest.approx(math.sqrt(3) / 2, rel=1e-12)
    for miss in (Plane((0, 0, 5), (0, 0, 1)), Plane((0, 0, 0), (1, 1, 1))):  # outside / touches a corner
        pts, tri = wall_triangles(miss.kind, miss.params(), cube)
        assert pts.shape == (0, 3) and tri.shape == (0, 3)


def test_infinite_cylinder_clipped_to_bounds():
    cyl = Cylinder((0.5, 1.0, 0.0), (0, 0, 1), 0.3)
    assert _area(cyl) == pytest.approx(2 * math.pi * 0.3 * 3.0, rel=0.01)  # the box is 3 m tall
    pts, _ = wall_triangles(cyl.kind, cyl.params(), BOX)
    assert pts[:, 2].min() == pytest.approx(0.0) and pts[:, 2].max() == pytest.approx(3.0)


def test_wall_triangles_errors():
    plane = Plane((0, 0, 0), (0, 0, 1))
    infinite = (np.full(3, -np.inf), np.full(3, np.inf))
    with pytest.raises(OutputError, match="bounds"):
        wall_triangles(KIND_PLANE, plane.params(), infinite)
    with pytest.raises(OutputError, match="bounds"):
        wall_triangles(KIND_CYLINDER, Cylinder((0, 0, 0), (0, 0, 1), 1.0).params(), (np.ones(3), np.zeros(3)))
    # finite walls do not need bounds
    rect = Rectangle((0, 0, 0), (0, 0, 1), (1, 0, 0), (1, 1))
    assert wall_triangles(KIND_RECTANGLE, rect.params(), infinite)[1].shape == (2, 3)
    assert wall_triangles(KIND_REVOLVED, Disk((0, 0, 0), (0, 0, 1), 1).params(), infinite)[1].shape == (48, 3)
    with pytest.raises(OutputError, match="unknown wall kind 7"):
        wall_triangles(7, np.zeros(N_PARAMS), BOX)
    with pytest.raises(OutputError, match="resolution"):
        wall_triangles(KIND_REVOLVED, Disk((0, 0, 0), (0, 0, 1), 1).params(), BOX, resolution=2)
    with pytest.raises(OutputError, match="16 finite floats"):
        wall_triangles(KIND_PLANE, np.zeros(5), BOX)


# ---------------------------------------------------------------------------------------------
# a scene of 3 frames
# ---------------------------------------------------------------------------------------------

SHAPES = {
    "floor": Plane((0.0, 0.0, 0.0), (0, 0, 1)),
    "hopper": Frustum((0.5, 1.0, 1.0), (0, 0, 1), 0.05, 0.45, 1.0),
    "gate plate": Rectangle((0.5, 1.0, 0.9), (0, 0, 1), (1, 0, 0), (0.1, 0.2)),  # name needs escaping
}


def make_frame(i: int, n: int = N_PART) -> Frame:
    rng = np.random.default_rng(100 + i)
    particles = {
        "id": np.arange(1000, 1000 + n, dtype=np.int64),
        "x": rng.random((n, 3)) * BOX[1],
        "v": rng.normal(size=(n, 3)),
        "w": rng.normal(size=(n, 3)),
        "f": rng.normal(size=(n, 3)),
        "t": rng.normal(size=(n, 3)),
        "r": rng.uniform(0.005, 0.01, n),
        "mass": rng.uniform(1e-3, 2e-3, n),
        "material": rng.integers(0, 3, n).astype(np.int32),
        "contacts": rng.integers(0, 8, n).astype(np.int32),
    }
    walls = [
        WallState(name, s.kind, s.params((0.0, 0.0, 0.05 * i)), rng.normal(size=3), rng.normal(size=3))
        for name, s in SHAPES.items()
    ]
    return Frame(TIMES[i], 1000 * i, "fill" if i < 2 else "settle", particles, walls, BOX)


@pytest.fixture(scope="module")
def frames() -> list[Frame]:
    return [make_frame(i) for i in range(3)]


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Same dtype, shape and bytes (bitwise identity, -0.0 and NaN payloads included)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.ascontiguousarray(a).tobytes() == b.tobytes()


# ---------------------------------------------------------------------------------------------
# an XDMF checker
# ---------------------------------------------------------------------------------------------

_XDMF_TYPES = {
    ("Float", "8"): np.float64,
    ("Float", "4"): np.float32,
    ("Int", "8"): np.int64,
    ("Int", "4"): np.int32,
    ("UInt", "4"): np.uint32,
    ("UInt", "8"): np.uint64,
    ("Char", "1"): np.int8,
    ("UChar", "1"): np.uint8,
}


def _data_item(item: ET.Element, base: Path) -> np.ndarray:
    """Resolve one DataItem: its shape must match Dimensions and its dtype NumberType/Precision."""
    dims = tuple(int(d) for d in item.attrib["Dimensions"].split())
    dtype = _XDMF_TYPES[(item.attrib.get("NumberType", "Float"), item.attrib.get("Precision", "4"))]
    fmt = item.attrib.get("Format", "XML")
    text = (item.text or "").strip()
    if fmt == "HDF":
        fname, _, path = text.partition(":")
        h5 = base / fname
        assert h5.is_file(), f"XDMF references missing file {h5}"
        with h5py.File(h5, "r") as f:
            assert path in f, f"XDMF references missing dataset {fname}:{path}"
            data = f[path][()]
        assert data.shape == dims, f"{fname}:{path} has shape {data.shape}, XDMF says {dims}"
        assert data.dtype == dtype, f"{fname}:{path} has dtype {data.dtype}, XDMF says {dtype}"
        return data
    assert fmt == "XML", f"unexpected DataItem format {fmt}"
    values = np.array([float(v) for v in text.split()], dtype=dtype)
    assert values.size == math.prod(dims)
    return values.reshape(dims)


def _uniform_grid(grid: ET.Element, base: Path) -> dict:
    topo = grid.find("Topology")
    geo = grid.find("Geometry")
    assert topo is not None and geo is not None
    assert geo.attrib["GeometryType"] == "XYZ"
    points = _data_item(geo.find("DataItem"), base)
    npts = points.shape[0]
    assert points.shape == (npts, 3)
    n_el = int(topo.attrib["NumberOfElements"])
    cells = _data_item(topo.find("DataItem"), base)
    kind = topo.attrib["TopologyType"]
    if kind == "Polyvertex":
        assert topo.attrib["NodesPerElement"] == "1" and cells.shape == (n_el,) and n_el == npts
        assert same_bits(cells, np.arange(npts, dtype=np.int64))
    else:
        assert kind == "Triangle" and topo.attrib["NodesPerElement"] == "3" and cells.shape == (n_el, 3)
        assert cells.min() >= 0 and cells.max() < npts
    attrs = {}
    for att in grid.findall("Attribute"):
        data = _data_item(att.find("DataItem"), base)
        center, atype = att.attrib["Center"], att.attrib["AttributeType"]
        rows = {"Node": npts, "Cell": n_el, "Grid": 1}[center]
        assert data.shape[0] == rows, f"attribute {att.attrib['Name']}: {data.shape[0]} rows, expected {rows}"
        assert (atype == "Vector") == (data.ndim == 2 and data.shape[1] == 3)
        assert atype in ("Vector", "Scalar") and (atype == "Vector" or data.ndim == 1)
        attrs[att.attrib["Name"]] = data
    return {"name": grid.attrib.get("Name"), "points": points, "cells": cells, "attributes": attrs}


def check_xdmf(path: Path) -> list[tuple[float, list[dict]]]:
    """Parse an XDMF time series; check every reference; return [(time, [uniform grids])]."""
    root = ET.parse(path).getroot()
    assert root.tag == "Xdmf" and root.attrib["Version"] == "3.0"
    series = root.find("Domain").findall("Grid")
    assert len(series) == 1
    series = series[0]
    assert series.attrib["GridType"] == "Collection" and series.attrib["CollectionType"] == "Temporal"
    out = []
    for grid in series.findall("Grid"):
        time = float(grid.find("Time").attrib["Value"])
        if grid.attrib["GridType"] == "Uniform":
            out.append((time, [_uniform_grid(grid, path.parent)]))
        else:
            assert grid.attrib["GridType"] == "Collection" and grid.attrib["CollectionType"] == "Spatial"
            out.append((time, [_uniform_grid(g, path.parent) for g in grid.findall("Grid")]))
    return out


# ---------------------------------------------------------------------------------------------
# HDF5 + XDMF
# ---------------------------------------------------------------------------------------------


def _check_hdf5_output(d: Path, frames: list[Frame]) -> None:
    with h5py.File(d / "particles.h5", "r") as f:
        assert {k: f.attrs[k] for k in f.attrs} == METADATA
        assert sorted(f["frames"]) == [f"{i:06d}" for i in range(len(frames))]
        for i, fr in enumerate(frames):
            g = f[f"frames/{i:06d}"]
            assert g.attrs["time"] == fr.time and g.attrs["step"] == fr.step and g.attrs["stage"] == fr.stage
            assert sorted(g) == sorted(fr.particles)
            for name, a in fr.particles.items():
                assert same_bits(g[name][()], a), name
    with h5py.File(d / "walls.h5", "r") as f:
        assert {k: f.attrs[k] for k in f.attrs} == METADATA
        for i, fr in enumerate(frames):
            g = f[f"frames/{i:06d}"]
            assert g.attrs["time"] == fr.time and g.attrs["step"] == fr.step
            assert sorted(g) == sorted(["floor", "hopper", "gate_plate"])
            for k, w in enumerate(fr.walls):
                wg = g[w.name.replace(" ", "_")]
                pts, tri = wall_triangles(w.kind, w.params, fr.bounds)
                assert same_bits(wg["points"][()], pts) and same_bits(wg["cells"][()], tri)
                assert wg.attrs["name"] == w.name and wg.attrs["index"] == k and wg.attrs["kind"] == w.kind
                assert same_bits(wg.attrs["force"], w.force) and same_bits(wg.attrs["torque"], w.torque)
                assert same_bits(wg.attrs["params"], w.params)
    parts = check_xdmf(d / "particles.xdmf")
    assert [t for t, _ in parts] == [fr.time for fr in frames]  # exact round trip of the times
    for (_, (grid,)), fr in zip(parts, frames, strict=True):
        assert same_bits(grid["points"], fr.particles["x"])
        assert sorted(grid["attributes"]) == sorted(k for k in fr.particles if k != "x")
        for k, a in grid["attributes"].items():
            assert same_bits(a, fr.particles[k])
    walls = check_xdmf(d / "walls.xdmf")
    assert [t for t, _ in walls] == [fr.time for fr in frames]
    for (_, grids), fr in zip(walls, frames, strict=True):
        assert [g["name"] for g in grids] == ["floor", "hopper", "gate_plate"]
        for g, w in zip(grids, fr.walls, strict=True):
            assert same_bits(g["attributes"]["force"], np.asarray(w.force)[None, :])
            assert same_bits(g["attributes"]["torque"], np.asarray(w.torque)[None, :])


def test_hdf5_roundtrip(tmp_path, frames):
    d = tmp_path / "out"
    with HDF5Writer(d, metadata=METADATA) as w:
        for fr in frames:
            w.write(fr)
            _check_hdf5_output(d, frames[: w.n_frames])  # readable after every frame
    assert w.closed
    w.close()  # idempotent
    with pytest.raises(OutputError, match="closed"):
        w.write(frames[0])
    _check_hdf5_output(d, frames)
    assert not [p.name for p in d.iterdir() if p.name.endswith(".tmp")]  # no temp files left behind


def test_hdf5_file_held_open_elsewhere(tmp_path, frames):
    with HDF5Writer(tmp_path, metadata=METADATA) as w:
        w.write(frames[0])
        with h5py.File(tmp_path / "particles.h5", "r"):  # e.g. an analysis script still reading it
            with pytest.raises(OutputError, match="particles.h5' to append frame 1"):
                w.write(frames[1])
        w.write(frames[1])  # retried once the file is free
    _check_hdf5_output(tmp_path, frames[:2])


def test_hdf5_field_selection(tmp_path, frames):
    with HDF5Writer(tmp_path, fields=["v", "contacts"]) as w:
        w.write(frames[0])
    with h5py.File(tmp_path / "particles.h5", "r") as f:
        assert sorted(f["frames/000000"]) == ["contacts", "id", "r", "v", "x"]  # id, x, r always
    (grid,) = check_xdmf(tmp_path / "particles.xdmf")[0][1]
    assert sorted(grid["attributes"]) == ["contacts", "id", "r", "v"]
    with pytest.raises(OutputError, match="valid fields: id, x, v, w, f, t, r, mass, material, contacts"):
        HDF5Writer(tmp_path / "b", fields=["v", "velocity"])
    w = HDF5Writer(tmp_path / "c", fields=["v"])
    fr = make_frame(0)
    del fr.particles["v"]
    with pytest.raises(OutputError, match="'v' not in the frame"):
        w.write(fr)


def test_empty_and_bad_frames(tmp_path):
    empty = make_frame(0, n=0)
    with HDF5Writer(tmp_path / "h", metadata=METADATA) as w, VTKWriter(tmp_path / "v") as v:
        for fr in (empty, make_frame(1)):
            w.write(fr)
            v.write(fr)
        bad = make_frame(2)
        bad.particles["r"] = bad.particles["r"][:-1]
        with pytest.raises(OutputError, match="'r' has shape"):
            w.write(bad)
        twins = make_frame(2)
        twins.walls[1].name = "gate/plate"  # same file-safe name as 'gate plate'
        with pytest.raises(OutputError, match="same output name 'gate_plate'"):
            w.write(twins)
    with h5py.File(tmp_path / "h" / "particles.h5", "r") as f:
        assert sorted(f["frames"]) == ["000000", "000001"] and f["frames/000000/x"].shape == (0, 3)
    # ParaView's XDMF reader fails on empty grids: frames without particles are left out of the XDMF
    assert [t for t, _ in check_xdmf(tmp_path / "h" / "particles.xdmf")] == [TIMES[1]]
    assert len(check_xdmf(tmp_path / "h" / "walls.xdmf")) == 2
    # meshio cannot read empty meshes back (ParaView can): check the VTU header instead
    piece = ET.parse(tmp_path / "v" / "particles" / "particles_000000.vtu").getroot().find(".//Piece")
    assert piece.attrib["NumberOfPoints"] == "0" and piece.attrib["NumberOfCells"] == "0"
    assert meshio.read(tmp_path / "v" / "particles" / "particles_000001.vtu").points.shape == (N_PART, 3)


def test_writers_refuse_to_overwrite(tmp_path, frames):
    for cls, victim in ((HDF5Writer, "particles.h5"), (VTKWriter, "particles.pvd")):
        d = tmp_path / cls.name
        with cls(d) as w:
            w.write(frames[0])
            w.write(frames[1])
        with pytest.raises(OutputError, match=f"{victim}.*overwrite=True"):
            cls(d)
        with cls(d, overwrite=True, metadata=METADATA) as w:
            w.write(frames[2])
    with h5py.File(tmp_path / "hdf5" / "particles.h5", "r") as f:
        assert list(f["frames"]) == ["000000"] and f["frames/000000"].attrs["time"] == TIMES[2]
    assert sorted(p.name for p in (tmp_path / "vtk" / "particles").iterdir()) == ["particles_000000.vtu"]
    assert json.loads((tmp_path / "vtk" / "metadata.json").read_text()) == METADATA
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="not a directory"):
        HDF5Writer(tmp_path / "file")
    with pytest.raises(OutputError, match="metadata"):
        VTKWriter(tmp_path / "m", metadata={"n": 3})


_KILLED_RUN = """
import os, signal, sys
sys.path.insert(0, {tests!r})
from test_io import make_frame
from pdem.io import HDF5Writer, VTKWriter
h = HDF5Writer({d!r} + "/h5", metadata={meta!r})
v = VTKWriter({d!r} + "/vtk", metadata={meta!r})
for i in range(2):
    h.write(make_frame(i))
    v.write(make_frame(i))
os.kill(os.getpid(), signal.SIGKILL)  # no close(), no interpreter shutdown
"""


def test_killed_run_leaves_readable_files(tmp_path):
    script = _KILLED_RUN.format(tests=str(Path(__file__).parent), d=str(tmp_path), meta=METADATA)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    frames = [make_frame(0), make_frame(1)]
    _check_hdf5_output(tmp_path / "h5", frames)
    _check_vtk_output(tmp_path / "vtk", frames)


# ---------------------------------------------------------------------------------------------
# VTK + PVD
# ---------------------------------------------------------------------------------------------


def _pvd(path: Path) -> list[dict[str, str]]:
    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.attrib["type"] == "Collection"
    entries = [ds.attrib for ds in root.find("Collection").findall("DataSet")]
    for e in entries:
        assert (path.parent / e["file"]).is_file()
    return entries


def _check_vtk_output(d: Path, frames: list[Frame]) -> None:
    assert json.loads((d / "metadata.json").read_text()) == METADATA
    parts = _pvd(d / "particles.pvd")
    walls = _pvd(d / "walls.pvd")
    assert [float(e["timestep"]) for e in parts] == [fr.time for fr in frames]
    assert [float(e["timestep"]) for e in walls] == [fr.time for fr in frames]
    for e, ew, fr in zip(parts, walls, frames, strict=True):
        m = meshio.read(d / e["file"])
        assert same_bits(m.points, fr.particles["x"])
        assert sorted(m.point_data) == sorted(k for k in fr.particles if k != "x")
        for k, a in m.point_data.items():
            assert same_bits(a, fr.particles[k]), k
        (block,) = m.cells
        assert block.type == "vertex" and same_bits(block.data[:, 0], np.arange(N_PART, dtype=np.int64))
        mw = meshio.read(d / ew["file"])
        assert ew["walls"] == ";".join(w.name for w in fr.walls)
        meshes = [wall_triangles(w.kind, w.params, fr.bounds) for w in fr.walls]
        assert same_bits(mw.points, np.concatenate([p for p, _ in meshes]))
        (tri,) = mw.cells
        offsets = np.cumsum([0] + [p.shape[0] for p, _ in meshes[:-1]])
        assert tri.type == "triangle"
        expected = np.concatenate([t + o for (_, t), o in zip(meshes, offsets, strict=True)])
        assert same_bits(tri.data, expected)
        counts = [t.shape[0] for _, t in meshes]
        index = np.repeat(np.arange(len(meshes), dtype=np.int32), counts)
        assert same_bits(mw.cell_data["wall_index"][0], index)
        force = np.repeat(np.array([w.force for w in fr.walls]), counts, axis=0)
        assert same_bits(mw.cell_data["force"][0], force)
        torque = np.repeat(np.array([w.torque for w in fr.walls]), counts, axis=0)
        assert same_bits(mw.cell_data["torque"][0], torque)


def test_vtk_roundtrip(tmp_path, frames):
    with VTKWriter(tmp_path, metadata=METADATA) as w:
        for fr in frames:
            w.write(fr)
            _check_vtk_output(tmp_path, frames[: w.n_frames])
    _check_vtk_output(tmp_path, frames)
    leftovers = [p for p in tmp_path.rglob("*") if p.name.startswith(".")]
    assert not leftovers


def test_writer_entry_points():
    from pdem import plugins

    assert HDF5Writer.name == "hdf5" and VTKWriter.name == "vtk"
    installed = plugins.available("writers")
    for cls in (HDF5Writer, VTKWriter):
        if cls.name in installed:
            assert plugins.load("writers", cls.name) is cls


# ---------------------------------------------------------------------------------------------
# CSV series
# ---------------------------------------------------------------------------------------------


def test_series_roundtrip(tmp_path):
    path = tmp_path / "sub" / "loads.csv"
    rows = [
        {"time": 0.1 + 0.2, "step": 10, "fz": -1 / 3, "stage": "fill"},
        {"time": 1e-300, "step": 20, "fz": np.float64(2.5e17), "stage": "settle, then discharge"},
        {"time": np.float32(0.1), "step": np.int64(2**40), "stage": 'quoted "x"'},  # fz missing
    ]
    with SeriesWriter(path, ["time", "step", "fz", "stage"]) as s:
        for row in rows:
            s.append(row)
            assert len(path.read_text().splitlines()) == s.n_rows + 1  # flushed every row
        with pytest.raises(OutputError, match="unknown column.*'fy'.*time, step, fz, stage"):
            s.append({"fy": 1.0})
    data = read_series(path)
    assert list(data) == ["time", "step", "fz", "stage"]
    assert same_bits(data["time"], np.array([0.1 + 0.2, 1e-300, float(np.float32(0.1))]))
    assert same_bits(data["step"], np.array([10, 20, 2**40], dtype=np.int64))
    assert same_bits(data["fz"][:2], np.array([-1 / 3, 2.5e17])) and math.isnan(data["fz"][2])
    assert data["stage"].tolist() == [r["stage"] for r in rows]
    with pytest.raises(OutputError, match="already exists"):
        SeriesWriter(path, ["time"])
    with SeriesWriter(path, ["time"], overwrite=True) as s:
        s.append({"time": 1.0})
    assert same_bits(read_series(path)["time"], np.array([1.0]))
    with pytest.raises(OutputError, match="duplicate"):
        SeriesWriter(tmp_path / "d.csv", ["a", "a"])
    with pytest.raises(OutputError, match="closed"):
        s.append({"time": 2.0})


# ---------------------------------------------------------------------------------------------
# ParaView (optional)
# ---------------------------------------------------------------------------------------------

_PV_SCRIPT = textwrap.dedent(
    """
    import json, sys
    from paraview import simple as pv

    def probe(reader):
        times = [float(t) for t in reader.TimestepValues]
        points, cells = [], []
        for t in times:
            reader.UpdatePipeline(t)
            info = reader.GetDataInformation()
            points.append(info.GetNumberOfPoints())
            cells.append(info.GetNumberOfCells())
        return {"times": times, "points": points, "cells": cells,
                "point_arrays": sorted(a.Name for a in reader.PointData)}

    d = sys.argv[1]
    out = {
        "xdmf2": probe(pv.XDMFReader(FileNames=[d + "/h5/particles.xdmf"])),
        "xdmf3": probe(pv.Xdmf3ReaderS(FileName=d + "/h5/particles.xdmf")),
        "walls_xdmf2": probe(pv.XDMFReader(FileNames=[d + "/h5/walls.xdmf"])),
        "walls_xdmf3": probe(pv.Xdmf3ReaderS(FileName=d + "/h5/walls.xdmf")),
        "pvd": probe(pv.PVDReader(FileName=d + "/vtk/particles.pvd")),
        "walls_pvd": probe(pv.PVDReader(FileName=d + "/vtk/walls.pvd")),
    }
    print("RESULT " + json.dumps(out))
    """
)


@pytest.mark.skipif(
    shutil.which("pvpython") is None,
    reason="pvpython (ParaView's Python) is not on PATH; install ParaView (Debian: apt-get install paraview "
    "python3-paraview) to check that ParaView opens the XDMF and PVD series",
)
def test_paraview_opens_series(tmp_path, frames):
    with HDF5Writer(tmp_path / "h5") as h, VTKWriter(tmp_path / "vtk") as v:
        for fr in frames:
            h.write(fr)
            v.write(fr)
    script = tmp_path / "probe.py"
    script.write_text(_PV_SCRIPT)
    env = {**os.environ, "PYTHONPATH": ""}  # keep the venv's numpy away from ParaView's Python
    proc = subprocess.run(
        ["pvpython", "--force-offscreen-rendering", str(script), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=180,
        env=env,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, f"pvpython failed:\n{proc.stdout}\n{proc.stderr}"
    res = json.loads(lines[-1][len("RESULT ") :])
    n_tri = sum(wall_triangles(w.kind, w.params, frames[0].bounds)[1].shape[0] for w in frames[0].walls)
    fields = sorted(k for k in frames[0].particles if k != "x")  # every field the frames hold
    assert set(fields) < set(PARTICLE_FIELDS)
    for key in ("xdmf2", "xdmf3", "pvd"):
        assert res[key]["times"] == TIMES, key
        assert res[key]["points"] == [N_PART] * 3, key
        assert res[key]["cells"] == [N_PART] * 3, key  # one vertex cell per particle: renderable
        assert res[key]["point_arrays"] == fields, key
    for key in ("walls_xdmf2", "walls_xdmf3", "walls_pvd"):
        assert res[key]["times"] == TIMES, key
        assert res[key]["cells"] == [n_tri] * 3, key
