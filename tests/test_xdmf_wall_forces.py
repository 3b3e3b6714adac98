"""The HDF5 + XDMF walls carry the load as the VTK walls do: cell attributes ``wall_index``,
``kind``, ``force``, ``torque`` on every wall's triangles, equal (bitwise) to the VTK walls' cell
data and to ``Wall.force`` / ``Wall.torque`` at the frame."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest

import pdem
from pdem.api import Frame, RigidBody, WallState, safe_key, shapes
from pdem.io.hdf5 import HDF5Writer
from pdem.io.vtk import VTKWriter

R = 0.5e-3


def _frame(sim: pdem.Simulation, stage: str = "drop") -> Frame:
    """The snapshot a run writes (walls as the runner passes them, scene box around everything)."""
    p = sim.get_particles()
    walls = [
        WallState(w.name, int(w.kinds[0]), (w.rows if w.n_rows > 1 else w.params).copy(), w.force, w.torque)
        for w in sim.walls.values()
        if w.active
    ]
    lo, hi = p["x"].min(axis=0) - 2 * R, p["x"].max(axis=0) + 2 * R
    for w in sim.walls.values():
        wlo, whi = w.bounding_box()
        lo = np.minimum(lo, np.where(np.isfinite(wlo), wlo, lo))
        hi = np.maximum(hi, np.where(np.isfinite(whi), whi, hi))
    particles = {"id": p["id"], "x": p["x"], "v": p["v"], "r": p["r"]}
    return Frame(sim.time, sim.step_count, stage, particles, walls, (lo, hi))


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Grains thrown sideways onto a floor inside a tube (so both carry a load, with a torque about
    their reference points), a free ball resting on nothing; written by both writers."""
    d = tmp_path_factory.mktemp("walls")
    sim = pdem.Simulation(law="hertz_mindlin")
    sim.add_material("glass", density=2500.0, youngs_modulus=5e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.5)  # fmt: skip
    sim.gravity = (4.0, 0.0, -9.81)
    g = np.arange(4) * 2.2 * R - 3.3 * R
    x, y, z = np.meshgrid(g, g, 1.2 * R + np.arange(3) * 2.2 * R, indexing="ij")
    xyz = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    sim.add_particles(xyz, R, material="glass", velocities=np.tile([0.15, 0.05, -0.1], (len(xyz), 1)))
    sim.add_wall(shapes.Plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), name="floor")
    sim.add_wall(shapes.CylinderTube((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 5.5 * R, 8 * R), name="side wall")
    sim.add_wall(shapes.Sphere((0.0, 0.0, 30 * R), 2 * R), name="ball",
                 motion=RigidBody(mass=1e-4, fixed_translation="xyz"))  # fmt: skip
    sim.dt = 2e-6
    frames, loads = [], []
    with HDF5Writer(d / "h5") as h, VTKWriter(d / "vtk") as v:
        for _ in range(4):
            fr = _frame(sim)
            h.write(fr)
            v.write(fr)
            frames.append(fr)
            loads.append({w.name: (w.force.copy(), w.torque.copy()) for w in sim.walls.values()})
            sim.run(steps=1500)
    return d, frames, loads


def _xdmf_walls(path: Path) -> list[dict[str, dict[tuple[str, str], np.ndarray]]]:
    """Per frame: {grid name: {(attribute name, centre): values}} (HDF references read)."""
    series = ET.parse(path).getroot().find("Domain").find("Grid")
    out = []
    for frame in series.findall("Grid"):
        grids = {}
        for grid in frame.findall("Grid"):
            n_cells = int(grid.find("Topology").attrib["NumberOfElements"])
            attrs = {}
            for att in grid.findall("Attribute"):
                item = att.find("DataItem")
                dims = tuple(int(s) for s in item.attrib["Dimensions"].split())
                if item.attrib["Format"] == "HDF":
                    fname, dset = item.text.strip().split(":", 1)
                    with h5py.File(path.parent / fname, "r") as f:
                        a = f[dset][()]
                else:
                    a = np.array([float(s) for s in item.text.split()]).reshape(dims)
                assert a.shape == dims, (att.attrib, a.shape, dims)
                key = (att.attrib["Name"], att.attrib["Center"])
                assert key not in attrs, f"attribute {key} twice in grid {grid.attrib['Name']}"
                if att.attrib["Center"] == "Cell":
                    assert a.shape[0] == n_cells
                    assert att.attrib["AttributeType"] == ("Vector" if a.ndim == 2 else "Scalar")
                attrs[key] = a
            grids[grid.attrib["Name"]] = attrs
        out.append(grids)
    return out


def test_xdmf_wall_cell_attributes_equal_vtk_and_wall_loads(run):
    d, frames, loads = run
    xdmf = _xdmf_walls(d / "h5" / "walls.xdmf")
    assert len(xdmf) == len(frames)
    loaded = set()
    for k, (fr, grids, load) in enumerate(zip(frames, xdmf, loads, strict=True)):
        vtu = meshio.read(d / "vtk" / "walls" / f"walls_{k:06d}.vtu")
        cells = {name: vtu.cell_data[name][0] for name in ("wall_index", "kind", "force", "torque")}
        assert sorted(grids) == sorted(safe_key(w.name) for w in fr.walls)
        for i, w in enumerate(fr.walls):
            attrs = grids[safe_key(w.name)]
            mine = cells["wall_index"] == i
            assert mine.any()
            for name in ("wall_index", "kind", "force", "torque"):
                a = attrs[(name, "Cell")]
                assert a.dtype == cells[name].dtype, name
                assert np.array_equal(a, cells[name][mine]), (k, w.name, name)  # bitwise: no NaN here
            force, torque = load[w.name]
            assert np.array_equal(attrs[("force", "Cell")], np.tile(force, (mine.sum(), 1)))
            assert np.array_equal(attrs[("torque", "Cell")], np.tile(torque, (mine.sum(), 1)))
            # the grid-centred load (field data) is still there, with the same values
            assert np.array_equal(attrs[("force", "Grid")], force[None, :])
            assert np.array_equal(attrs[("torque", "Grid")], torque[None, :])
            if np.any(force != 0.0):
                loaded.add(w.name)
    assert loaded == {"floor", "side wall"}, "the floor and the tube should carry a load in some frame"


def test_walls_h5_cell_data(run):
    d, frames, _ = run
    with h5py.File(d / "h5" / "walls.h5", "r") as f:
        for k, fr in enumerate(frames):
            for i, w in enumerate(fr.walls):
                wg = f[f"frames/{k:06d}/{safe_key(w.name)}"]
                n = wg["cells"].shape[0]
                cd = wg["cell_data"]
                assert sorted(cd) == ["force", "kind", "torque", "wall_index"]
                assert cd["wall_index"].dtype == np.int32 and np.all(cd["wall_index"][()] == i)
                assert cd["kind"].dtype == np.int32 and np.all(cd["kind"][()] == w.kind)
                assert np.array_equal(cd["force"][()], np.tile(np.asarray(w.force), (n, 1)))
                assert np.array_equal(cd["torque"][()], np.tile(np.asarray(w.torque), (n, 1)))


def test_continued_output_rebuilds_the_same_walls_xdmf(run, tmp_path):
    """Continuing (``pdem resume``) rebuilds walls.xdmf from walls.h5: the same text; files written
    before walls carried cell data continue with the grid-centred load only."""
    import shutil

    d, frames, _ = run
    copy = tmp_path / "h5"
    shutil.copytree(d / "h5", copy)
    original = (copy / "walls.xdmf").read_text()
    last = frames[-1]
    HDF5Writer(copy, append_after=(last.step, last.time)).close()
    assert (copy / "walls.xdmf").read_text() == original
    with h5py.File(copy / "walls.h5", "a") as f:  # as written before cell data existed
        for key in f["frames"]:
            for wname in f["frames"][key]:
                del f["frames"][key][wname]["cell_data"]
    HDF5Writer(copy, append_after=(last.step, last.time)).close()
    for grids in _xdmf_walls(copy / "walls.xdmf"):
        for attrs in grids.values():
            assert sorted(attrs) == [("force", "Grid"), ("torque", "Grid")]
