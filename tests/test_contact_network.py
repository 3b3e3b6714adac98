"""The contact network dump (`[output] contacts = true`): one VTK file of lines per snapshot, for
force chains in ParaView; continued by a resume like the other output."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest
from test_cli_hostile import TINY

from pdem.cli import main

vtk = pytest.importorskip("vtk")  # what ParaView reads .vtu files with (the render extra installs it)


def read_lines(path) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(points, line connectivity, cell data) of a contact file, read by VTK itself."""
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkXMLUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    assert reader.GetErrorCode() == 0
    grid = reader.GetOutput()
    n = grid.GetNumberOfCells()
    assert all(grid.GetCellType(c) == vtk.VTK_LINE for c in range(n))
    points = vtk_to_numpy(grid.GetPoints().GetData()) if grid.GetNumberOfPoints() else np.zeros((0, 3))
    lines = np.array([[grid.GetCell(c).GetPointId(0), grid.GetCell(c).GetPointId(1)] for c in range(n)])
    data = grid.GetCellData()
    arrays = {data.GetArrayName(k): vtk_to_numpy(data.GetArray(k)) for k in range(data.GetNumberOfArrays())}
    return points, lines.reshape(n, 2), arrays


def pvd(path) -> list[dict]:
    return [d.attrib for d in ET.parse(path).getroot().iter("DataSet")]


def test_contact_network_snapshots(tmp_path, capsys):
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY)
    out = tmp_path / "out"
    assert main([str(deck), "--output", str(out), "--quiet", "--set", "output.contacts=true"]) == 0
    entries = pvd(out / "contacts.pvd")
    assert [int(e["step"]) for e in entries] == [0, 10, 20]  # with the particle snapshots
    with h5py.File(out / "particles.h5", "r") as fh:
        for k, e in enumerate(entries):
            points, lines, data = read_lines(out / e["file"])
            frame = fh["frames"][f"{k:06d}"]
            # each contact once, its ends at the two particles' centres
            assert len(lines) == int(frame["contacts"][()].sum()) // 2
            if len(lines):
                ids, x = frame["id"][()], frame["x"][()]
                i, j = np.searchsorted(ids, data["id_i"]), np.searchsorted(ids, data["id_j"])
                assert np.array_equal(points[lines[:, 0]], x[i])
                assert np.array_equal(points[lines[:, 1]], x[j])
                assert np.all(data["id_i"] < data["id_j"]) and np.all(data["normal_force"] > 0)
                assert data["force"].shape == (len(lines), 3)
    assert len(read_lines(out / entries[-1]["file"])[1]) > 0


def test_contact_network_continued_by_resume(tmp_path, capsys):
    deck = tmp_path / "deck.toml"
    deck.write_text(TINY.replace("steps = 20\n", "steps = 40\n"))
    sets = ["--set", "output.contacts=true"]
    assert main([str(deck), "--output", str(tmp_path / "full"), "--quiet", *sets]) == 0
    assert main([str(deck), "--output", str(tmp_path / "run"), "--quiet", "--steps", "30", *sets]) == 0
    # resume from step 30: the network goes on in the same collection
    assert main(["resume", str(tmp_path / "run" / "checkpoints" / "latest.h5"), "--quiet"]) == 0
    a, b = pvd(tmp_path / "full" / "contacts.pvd"), pvd(tmp_path / "run" / "contacts.pvd")
    assert b == a  # each snapshot once (30, where the run stopped, is on the cadence too)
    assert [e["step"] for e in b] == ["0", "10", "20", "30", "40"]
    last_a = read_lines(tmp_path / "full" / a[-1]["file"])[2]
    last_b = read_lines(tmp_path / "run" / b[-1]["file"])[2]
    assert np.array_equal(last_a["force"], last_b["force"])
    files = sorted(p.name for p in (tmp_path / "run" / "contacts").iterdir())
    assert files == [f"contacts_{k:06d}.vtu" for k in range(5)]


def test_a_contact_across_a_periodic_face_is_drawn_short():
    """Particles 0 and 1 touch across the x faces of a periodic box: the line goes from 0 to the
    nearest image of 1, not across the box."""
    from pdem.domain import PeriodicBox
    from pdem.io.contacts import contact_lines

    box = PeriodicBox((0.0, 0.0, 0.0), (0.01, 0.01, 0.01), "x")
    particles = {"id": np.array([0, 1]), "x": np.array([[0.0004, 0.005, 0.005], [0.0096, 0.005, 0.005]])}
    contacts = {
        "id_i": np.array([0]),
        "id_j": np.array([1]),
        "force": np.array([[-1.0, 0.0, 0.0]]),
        "normal_force": np.array([1.0]),
        "overlap": np.array([2e-4]),
    }
    mesh = contact_lines(contacts, particles, box)
    assert np.allclose(mesh.points, [[0.0004, 0.005, 0.005], [-0.0004, 0.005, 0.005]])
    assert mesh.cells_dict["line"].tolist() == [[0, 1]]
