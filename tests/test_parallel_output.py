"""Per-rank output (``output.parallel = "per_rank"``): rank pieces joined by an XDMF / PVTU index.

The MPI tests run one small deck on 2 ranks twice, gathered and per rank, and check that the pieces
put together are the gathered output bit for bit, that the indexes reference what exists, and (if
ParaView's ``pvpython`` is on PATH) that ParaView opens each index as one dataset per time step.
"""

from __future__ import annotations

import json
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
from test_io import METADATA, TIMES, check_xdmf, make_frame, same_bits

from pdem.deck import validate_deck
from pdem.errors import DeckError, OutputError
from pdem.io import HDF5Writer, VTKWriter, Writer
from pdem.parallel.comm import SerialComm

ROOT = Path(__file__).resolve().parents[1]
MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
PVPYTHON = shutil.which("pvpython")
try:
    from vtkmodules.vtkIOXML import vtkXMLPUnstructuredGridReader  # noqa: F401

    HAVE_VTK = True
except ImportError:
    HAVE_VTK = False


# ---------------------------------------------------------------------------------------------
# writers on one rank (SerialComm): layout, claims, plugin contract
# ---------------------------------------------------------------------------------------------


def test_per_rank_writers_on_one_rank(tmp_path):
    frames = [make_frame(i) for i in range(3)]
    empty = make_frame(2, n=0)
    with (
        HDF5Writer(tmp_path / "h5", metadata=METADATA, comm=SerialComm()) as h,
        VTKWriter(tmp_path / "vtk", comm=SerialComm()) as v,
    ):
        assert h.per_rank and v.per_rank
        for fr in [*frames, empty]:
            h.write(fr)
            v.write(fr)
    assert not (tmp_path / "h5" / "particles.h5").exists()
    with h5py.File(tmp_path / "h5" / "particles.r0000.h5", "r") as f:
        assert {k: f.attrs[k] for k in f.attrs} == {**METADATA, "rank": 0, "n_ranks": 1}
        for i, fr in enumerate(frames):
            g = f[f"frames/{i:06d}"]
            assert g.attrs["time"] == fr.time and g.attrs["step"] == fr.step and g.attrs["stage"] == fr.stage
            for name, a in fr.particles.items():
                assert same_bits(g[name][()], a), name
        assert f["frames/000003/x"].shape == (0, 3)  # an empty piece is written
    series = check_xdmf(tmp_path / "h5" / "particles.xdmf")
    assert [t for t, _ in series] == TIMES  # but frames without particles stay out of the index
    for (_, grids), fr in zip(series, frames, strict=True):
        assert [g["name"] for g in grids] == ["r0000"]
        assert same_bits(grids[0]["points"], fr.particles["x"])
    root = ET.parse(tmp_path / "vtk" / "particles.pvd").getroot()
    files = [ds.attrib["file"] for ds in root.iter("DataSet")]
    assert files == [f"particles/particles_{i:06d}.pvtu" for i in range(4)]
    assert _pvtu_sources(tmp_path / "vtk" / files[3])[0].is_file()  # an empty piece
    if HAVE_VTK:  # (meshio cannot read an empty .vtu)
        assert _read_pvtu(tmp_path / "vtk" / files[3])[0].shape == (0, 3)
    for i, fr in enumerate(frames):
        sources = _pvtu_sources(tmp_path / "vtk" / files[i])
        assert [s.relative_to(tmp_path / "vtk" / "particles").as_posix() for s in sources] == [
            f"r0000/particles_{i:06d}.vtu"
        ]
        m = meshio.read(sources[0])
        assert same_bits(m.points, fr.particles["x"]) and same_bits(m.point_data["id"], fr.particles["id"])
    assert (tmp_path / "vtk" / "walls.pvd").is_file()


def test_per_rank_claims_and_refusals(tmp_path, monkeypatch):
    frame = make_frame(0)
    d = tmp_path / "out"
    with HDF5Writer(d, comm=SerialComm()) as w:
        w.write(frame)
    # a stale piece of an earlier run (e.g. on more ranks) is refused, in either mode
    (d / "particles.r0007.h5").write_bytes(b"stale")
    for comm in (None, SerialComm()):
        with pytest.raises(OutputError, match=r"particles.r0007.h5.*overwrite=True"):
            HDF5Writer(d, comm=comm)
    with HDF5Writer(d, overwrite=True) as w:  # gathered, asked to overwrite: the pieces go
        w.write(frame)
    assert sorted(p.name for p in d.iterdir()) == ["particles.h5", "particles.xdmf", "walls.h5", "walls.xdmf"]
    v = tmp_path / "vtk"
    with VTKWriter(v, comm=SerialComm()) as w:
        w.write(frame)
    with pytest.raises(OutputError, match=r"particles_000000.pvtu|r0000"):
        VTKWriter(v)
    with VTKWriter(v, overwrite=True) as w:
        w.write(frame)
    assert not list((v / "particles").glob("*.pvtu")) and not list((v / "particles" / "r0000").iterdir())

    class Gathering(Writer):
        name = "gathering"

        def _write(self, frame, particles, walls):
            pass

    with pytest.raises(OutputError, match="cannot write per-rank"):
        Gathering(tmp_path / "g", comm=SerialComm())


def _deck(parallel: object, formats: list[str]) -> dict:
    return {
        "run": {"dt": 1e-6},
        "materials": {"glass": {"density": 2500.0, "youngs_modulus": 5e7, "poisson_ratio": 0.3}},
        "stages": [{"name": "s", "end": {"steps": 10}}],
        "output": {"parallel": parallel, "formats": formats},
    }


def test_deck_parallel_key(monkeypatch):
    assert validate_deck(_deck("per_rank", ["hdf5", "vtk"])).deck.output.parallel == "per_rank"
    out = validate_deck({k: v for k, v in _deck("auto", ["hdf5"]).items() if k != "output"}).deck.output
    assert out.parallel == "auto"
    assert out.parallel_mode(10**7, 1) == "gather" and out.parallel_mode(64, 4) == "per_rank"
    assert out.parallel_mode(10**6, 2) == "per_rank"
    with pytest.raises(DeckError, match=r"output.parallel: must be one of .*did you mean 'per_rank'"):
        validate_deck(_deck("per-rank", ["hdf5"]))

    class Gathering(Writer):
        name = "gathering"

    import pdem.plugins

    real = pdem.plugins.load
    monkeypatch.setattr(
        pdem.plugins, "load", lambda g, n: Gathering if (g, n) == ("writers", "gathering") else real(g, n)
    )
    writers = ["hdf5", "vtk", "gathering"]
    with pytest.raises(DeckError, match=r"output.formats.*writer 'gathering' cannot write per-rank"):
        validate_deck(_deck("per_rank", ["hdf5", "gathering"]), writers=writers)
    for mode in ("auto", "gather"):  # auto gathers frames for such writers
        validate_deck(_deck(mode, ["hdf5", "gathering"]), writers=writers)


# ---------------------------------------------------------------------------------------------
# a deck on 2 ranks, gathered and per rank
# ---------------------------------------------------------------------------------------------

DECK = """\
title = "per-rank output"
[run]
gravity = [0.0, 0.0, -9.81]
dt = 2e-6
seed = 3
[contact]
law = "hertz_mindlin"
[materials.glass]
density = 2500.0
youngs_modulus = 5e7
poisson_ratio = 0.3
restitution = 0.5
friction = 0.5
[[particles]]
source = "random_fill"
material = "glass"
region = { type = "box", lo = [0.0, 0.0, 0.0], hi = [0.01, 0.01, 0.006] }
sizes = { type = "uniform", r_min = 0.45e-3, r_max = 0.55e-3 }
n = 300
velocity = [0.0, 0.0, -1.0]
[boundaries.box]
type = "box"
material = "glass"
lo = [0.0, 0.0, 0.0]
hi = [0.01, 0.01, 0.02]
[[stages]]
name = "drop"
[stages.end]
steps = 400
[[stages]]
name = "rest"
[stages.end]
steps = 400
[output]
formats = ["hdf5", "vtk"]
every_steps = 200
series_every_steps = 100
"""
N = 300
N_FRAMES = 5
RANKS = 2


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """The deck on 2 ranks: gathered and per_rank (the default on more than one rank)."""
    if MPIEXEC is None:
        pytest.skip("mpiexec not found (pip install mpich)")
    d = tmp_path_factory.mktemp("parallel_output")
    deck = d / "deck.toml"
    deck.write_text(DECK)
    out = {}
    for mode, sets in (("gather", ["--set", 'output.parallel="gather"']), ("per_rank", [])):
        cmd = [MPIEXEC, "-n", str(RANKS), sys.executable, "-m", "pdem.cli", str(deck)]
        cmd += ["--output", str(d / mode), "--quiet", *sets]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=d)
        assert proc.returncode == 0, proc.stderr[-3000:]
        out[mode] = d / mode
    return out


def _gathered_frames(d: Path) -> list[tuple[dict, dict[str, np.ndarray]]]:
    with h5py.File(d / "particles.h5", "r") as f:
        return [
            (dict(g.attrs), {k: g[k][()] for k in g}) for g in (f["frames"][k] for k in sorted(f["frames"]))
        ]


def test_summary_records_the_mode(runs):
    for mode, d in runs.items():
        assert json.loads((d / "summary.json").read_text())["output_parallel"] == mode
    assert not (runs["gather"] / "particles.r0000.h5").exists()
    assert not (runs["per_rank"] / "particles.h5").exists()


def test_hdf5_pieces_are_the_gathered_frames(runs):
    """(a) every rank's piece, concatenated and ordered by id, is the gathered frame, bitwise."""
    gathered = _gathered_frames(runs["gather"])
    assert len(gathered) == N_FRAMES
    files = [h5py.File(runs["per_rank"] / f"particles.r{r:04d}.h5", "r") for r in range(RANKS)]
    try:
        assert sorted(p.name for p in runs["per_rank"].glob("particles.r*.h5")) == [
            f"particles.r{r:04d}.h5" for r in range(RANKS)
        ]
        for r, f in enumerate(files):
            assert f.attrs["rank"] == r and f.attrs["n_ranks"] == RANKS and "deck" in f.attrs
            assert sorted(f["frames"]) == [f"{i:06d}" for i in range(N_FRAMES)]
        split = False
        for i, (attrs, data) in enumerate(gathered):
            pieces = [f["frames"][f"{i:06d}"] for f in files]
            for g in pieces:
                assert dict(g.attrs) == attrs
                assert sorted(g) == sorted(data)
                assert np.all(np.diff(g["id"][()]) > 0), "a piece must be ordered by id"
            split |= all(len(g["id"]) > 0 for g in pieces)
            ids = np.concatenate([g["id"][()] for g in pieces])
            order = np.argsort(ids, kind="stable")
            for name, a in data.items():
                joined = np.concatenate([g[name][()] for g in pieces])[order]
                assert same_bits(joined, a), (i, name)
        assert split, "the deck should put particles on both ranks"
        assert data["contacts"].sum() > 0, "the deck should have contacts (also across ranks)"
    finally:
        for f in files:
            f.close()
    # walls are written once, by rank 0, as in gathered output
    with (
        h5py.File(runs["gather"] / "walls.h5", "r") as fg,
        h5py.File(runs["per_rank"] / "walls.h5", "r") as fp,
    ):
        names: list[str] = []
        fg.visit(names.append)
        for name in names:
            if isinstance(fg[name], h5py.Dataset):
                assert same_bits(fp[name][()], fg[name][()]), name


def test_xdmf_index(runs):
    """(b) the XDMF parses, references existing datasets of the right shape, and is the gathered data."""
    gathered = _gathered_frames(runs["gather"])
    series = check_xdmf(runs["per_rank"] / "particles.xdmf")  # checks every reference, shape, dtype
    assert [t for t, _ in series] == [a["time"] for a, _ in gathered]
    root = ET.parse(runs["per_rank"] / "particles.xdmf").getroot()
    frames = root.find("Domain").find("Grid").findall("Grid")
    for frame_grid, (_, grids), (_, data) in zip(frames, series, gathered, strict=True):
        assert frame_grid.attrib["GridType"] == "Collection"
        assert frame_grid.attrib["CollectionType"] == "Spatial"
        for piece in frame_grid.findall("Grid"):
            for item in piece.iter("DataItem"):
                assert item.text.startswith(f"particles.{piece.attrib['Name']}.h5:")
        assert 1 <= len(grids) <= RANKS
        assert sum(g["points"].shape[0] for g in grids) == N
        ids = np.concatenate([g["attributes"]["id"] for g in grids])
        order = np.argsort(ids, kind="stable")
        assert same_bits(np.concatenate([g["points"] for g in grids])[order], data["x"])
        for name in data:
            if name != "x":
                joined = np.concatenate([g["attributes"][name] for g in grids])[order]
                assert same_bits(joined, data[name]), name


def _pvtu_sources(path: Path) -> list[Path]:
    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.attrib["type"] == "PUnstructuredGrid"
    sources = [path.parent / p.attrib["Source"] for p in root.iter("Piece")]
    for s in sources:
        assert s.is_file(), f"{path} references missing {s}"
    return sources


def _read_pvtu(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], int]:
    """Points, point data and cell count of a .pvtu, through VTK's own reader when available."""
    if not HAVE_VTK:  # meshio reads the pieces (it has no .pvtu reader)
        meshes = [meshio.read(s) for s in _pvtu_sources(path)]
        points = np.concatenate([m.points for m in meshes])
        data = {k: np.concatenate([m.point_data[k] for m in meshes]) for k in meshes[0].point_data}
        return points, data, sum(len(c.data) for m in meshes for c in m.cells)
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPUnstructuredGridReader

    reader = vtkXMLPUnstructuredGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    pd = grid.GetPointData()
    data = {pd.GetArrayName(k): vtk_to_numpy(pd.GetArray(k)) for k in range(pd.GetNumberOfArrays())}
    return vtk_to_numpy(grid.GetPoints().GetData()), data, grid.GetNumberOfCells()


def test_pvtu_index(runs):
    """(c) each .pvtu reads back (VTK's reader) as the gathered .vtu: same points and data."""
    g_root = ET.parse(runs["gather"] / "particles.pvd").getroot()
    p_root = ET.parse(runs["per_rank"] / "particles.pvd").getroot()
    g_sets = [ds.attrib for ds in g_root.iter("DataSet")]
    p_sets = [ds.attrib for ds in p_root.iter("DataSet")]
    assert [e["timestep"] for e in p_sets] == [e["timestep"] for e in g_sets] and len(p_sets) == N_FRAMES
    for i, (eg, ep) in enumerate(zip(g_sets, p_sets, strict=True)):
        assert ep["file"] == f"particles/particles_{i:06d}.pvtu"
        pvtu = runs["per_rank"] / ep["file"]
        assert [s.parent.name for s in _pvtu_sources(pvtu)] == [f"r{r:04d}" for r in range(RANKS)]
        ref = meshio.read(runs["gather"] / eg["file"])
        points, data, n_cells = _read_pvtu(pvtu)
        assert points.shape == ref.points.shape == (N, 3) and n_cells == N
        assert sorted(data) == sorted(ref.point_data)
        order = np.argsort(data["id"], kind="stable")
        assert same_bits(points[order], ref.points)
        for name, a in ref.point_data.items():
            assert same_bits(data[name][order], a), name


def test_render_reads_per_rank_pieces(runs):
    """tools/render.py joins the pieces: the same snapshot as from the gathered particles.h5."""
    sys.path.insert(0, str(ROOT / "tools"))
    import render

    for k in (0, -1):
        a, b = render.read_frame(runs["gather"], k), render.read_frame(runs["per_rank"], k)
        assert (a.key, a.time, a.step, a.stage) == (b.key, b.time, b.step, b.stage)
        assert sorted(a.particles) == sorted(b.particles)
        for name in a.particles:
            assert same_bits(a.particles[name], b.particles[name]), name
        assert [w[0] for w in a.walls] == [w[0] for w in b.walls] and a.walls


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
    print("RESULT " + json.dumps({
        "xdmf2": probe(pv.XDMFReader(FileNames=[d + "/particles.xdmf"])),
        "xdmf3": probe(pv.Xdmf3ReaderS(FileName=d + "/particles.xdmf")),
        "pvd": probe(pv.PVDReader(FileName=d + "/particles.pvd")),
    }))
    """
)


@pytest.mark.skipif(
    PVPYTHON is None,
    reason="pvpython (ParaView's Python) is not on PATH; install ParaView (Debian: apt-get install paraview "
    "python3-paraview) to check that ParaView opens the per-rank XDMF and PVD series",
)
def test_paraview_opens_per_rank_output(runs, tmp_path):
    """(d) ParaView opens the XDMF and the PVD of the pieces as one dataset per time step."""
    script = tmp_path / "probe.py"
    script.write_text(_PV_SCRIPT)
    env = {**os.environ, "PYTHONPATH": ""}  # keep the venv's numpy away from ParaView's Python
    proc = subprocess.run(
        [PVPYTHON, "--force-offscreen-rendering", str(script), str(runs["per_rank"])],
        capture_output=True,
        text=True,
        timeout=180,
        env=env,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, f"pvpython failed:\n{proc.stdout}\n{proc.stderr}"
    res = json.loads(lines[-1][len("RESULT ") :])
    times = [a["time"] for a, _ in _gathered_frames(runs["gather"])]
    fields = sorted(k for k in _gathered_frames(runs["gather"])[0][1] if k != "x")
    for key in ("xdmf2", "xdmf3", "pvd"):
        assert res[key]["times"] == times, key
        assert res[key]["points"] == [N] * N_FRAMES, key
        assert res[key]["cells"] == [N] * N_FRAMES, key
        assert res[key]["point_arrays"] == fields, key
