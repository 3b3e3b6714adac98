"""Continuum fields written by a run (deck ``[output.continuum.<name>]``): the files, their values
against :mod:`pdem.fields` computed on the same state, bitwise identity on 1 and 2 ranks and across
a resume, the index ParaView opens, and the deck's errors."""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ET
from pathlib import Path

import h5py
import numpy as np
import pytest
from decks import settling_bed

from pdem.deck import validate_deck
from pdem.errors import DeckError
from pdem.io.continuum import QUANTITIES, read_continuum
from pdem.io.paths import named_as_pdem

MPIEXEC = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
PVPYTHON = shutil.which("pvpython")
XVFB = shutil.which("xvfb-run")

DECK = settling_bed(
    0.03,
    600,
    textwrap.dedent("""
    every_steps = 200
    checkpoint_every_steps = 200
    [output.continuum.bed]
    lo = [0.0, 0.0, 0.0]
    hi = [0.02, 0.02, 0.03]
    counts = [7, 6, 9]
    average_every_steps = 50
    [output.continuum.coarse]
    lo = [-0.002, 0.0, 0.0]
    hi = [0.022, 0.02, 0.03]
    counts = [3, 2, 4]
    kernel = "lucy"
    width = 0.003
    quantities = ["density", "stress", "velocity"]
    every_steps = 100
    [output.continuum.instant]
    lo = [0.0, 0.0, 0.0]
    hi = [0.02, 0.02, 0.03]
    counts = [7, 6, 9]
    quantities = ["density", "velocity"]
    every_steps = 50
    [output.continuum.moving]
    lo = [0.0, 0.0, 0.0]
    hi = [0.02, 0.02, 0.03]
    counts = [7, 6, 9]
    quantities = ["velocity"]
    average_every_steps = 50
    [output.continuum.cell]
    type = "cylinder"
    base_center = [0.01, 0.01, 0.0]
    radius = 0.009
    inner_radius = 0.001
    height = 0.03
    counts = [5, 8, 6]
    quantities = ["density", "velocity", "stress"]
    every_steps = 100
    [output.continuum.probe]
    type = "points"
    points = [[0.01, 0.01, 0.001], [0.01, 0.01, 0.003], [0.005, 0.012, 0.005], [0.0, 0.0, 0.0],
              [0.019, 0.002, 0.007]]
    quantities = ["density", "velocity", "stress"]
    average_every_steps = 50
    """),
)


def _run(tmp_path: Path, name: str, args: list[str], ranks: int = 1) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "pdem", *args]
    if ranks > 1:
        cmd = [MPIEXEC, "-n", str(ranks), *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    return proc


def _deck(tmp_path: Path) -> Path:
    deck = tmp_path / "bed.toml"
    deck.write_text(DECK)
    return deck


def _same(a: list[dict], b: list[dict]) -> None:
    assert [f["step"] for f in a] == [f["step"] for f in b]
    for fa, fb in zip(a, b, strict=True):
        assert fa.keys() == fb.keys()
        for k, v in fa.items():
            if isinstance(v, np.ndarray):
                assert v.tobytes() == fb[k].tobytes(), (k, fa["step"])
            elif k == "where":  # a Grid or CylindricalGrid
                assert repr(v) == repr(fb[k])
            else:
                assert v == fb[k], k


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("continuum")
    deck = _deck(tmp)
    proc = _run(tmp, "one", [str(deck), "--output", str(tmp / "one")])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return tmp, tmp / "one"


def test_files_and_frames(serial_run):
    _, out = serial_run
    assert {p.name for p in out.glob("continuum_*")} == {
        "continuum_bed.h5", "continuum_bed.xdmf", "continuum_coarse.h5", "continuum_coarse.xdmf",
        "continuum_instant.h5", "continuum_instant.xdmf", "continuum_moving.h5", "continuum_moving.xdmf",
        "continuum_cell.h5", "continuum_cell.xdmf", "continuum_probe.h5", "continuum_probe.xdmf",
    }  # fmt: skip
    assert all(named_as_pdem(p.name) for p in out.glob("continuum_*"))  # --overwrite may remove them
    bed = read_continuum(out, "bed")
    # with the snapshots (every 200 steps), each the mean of the samples every 50 steps since the last
    assert [f["step"] for f in bed] == [0, 200, 400, 600]
    assert [f["samples"] for f in bed] == [1, 4, 4, 4]
    assert set(bed[-1]) >= set(QUANTITIES)
    assert bed[-1]["density"].shape == (7, 6, 9) and bed[-1]["stress"].shape == (7, 6, 9, 3, 3)
    coarse = read_continuum(out, "coarse")
    assert [f["step"] for f in coarse] == [0, 100, 200, 300, 400, 500, 600]
    head = {"time", "since", "step", "stage", "samples", "points", "where"}
    assert set(coarse[0]) == head | {"density", "stress", "velocity"}
    # each averaged frame's first sample: 50 steps after the previous frame
    assert [f["since"] for f in bed] == pytest.approx([0.0, 0.001, 0.005, 0.009])
    with h5py.File(out / "continuum_coarse.h5", "r") as f:
        assert f.attrs["kernel"] == "lucy" and f.attrs["width"] == 0.003
        batches = list(f["batches"].values())  # frames stacked per write: written before each checkpoint
        assert sum(len(g.attrs["numbers"]) for g in batches) == 7
        for g in batches:  # (and every 2 s of wall time): no batch spans a checkpoint (every 200 steps)
            assert len({max(int(step) - 1, 0) // 200 for step in g.attrs["table"][:, 2]}) == 1
        assert all(g["stress"].shape[1:] == (4, 2, 3, 9) for g in batches)  # ParaView's order: x fastest
    with h5py.File(out / "continuum_bed.h5", "r") as f:  # default width: the mean diameter
        assert 0.0009 < f.attrs["width"] < 0.0011


def test_an_averaged_frame_is_the_mean_of_its_samples_and_its_velocity_mass_weighted(serial_run):
    """A frame averaged over samples every 50 steps holds the mean of the instantaneous fields at
    those steps (read from a grid written at each of them), and as its velocity the mean momentum
    over the mean density (a node nearly empty in some samples is not pulled towards their velocity),
    which differs from the plain mean of the samples' velocities where the bed falls."""
    _, out = serial_run
    bed = read_continuum(out, "bed")
    instant = {f["step"]: f for f in read_continuum(out, "instant")}
    for frame in bed[1:]:
        steps = [frame["step"] - 150, frame["step"] - 100, frame["step"] - 50, frame["step"]]
        rho = [instant[s]["density"] for s in steps]
        total = rho[0].copy()
        for r in rho[1:]:
            total += r
        assert np.array_equal(frame["density"], total / 4)  # the same sums, in the same order
        mom = sum(r[..., None] * instant[s]["velocity"] for r, s in zip(rho, steps, strict=True))
        held = total > 0
        expect = np.where(held[..., None], mom / np.where(held, total, 1.0)[..., None], 0.0)
        assert np.allclose(frame["velocity"], expect, rtol=1e-12, atol=1e-15)
        plain = np.mean([instant[s]["velocity"] for s in steps], axis=0)  # what a plain mean gives
        moving = np.abs(expect[..., 2]) > 1e-3
        assert moving.any() and not np.allclose(frame["velocity"][moving], plain[moving], rtol=1e-3)
    # a grid asking for the velocity alone averages it the same way, to the bit
    only = read_continuum(out, "moving")
    assert set(only[-1]) == {"time", "since", "step", "stage", "samples", "points", "where", "velocity"}
    for a, b in zip(only, bed, strict=True):
        assert a["velocity"].tobytes() == b["velocity"].tobytes()


def test_written_fields_are_those_of_the_state(serial_run, tmp_path):
    """The fields a frame holds are pdem.fields' on the state of the same step, bit for bit (the
    instant grids: a box's, a cylinder's). The state is the step-400 checkpoint run on to step 600,
    which is the run's bit for bit, forces included: a checkpoint of step 600 reloaded would give
    the same positions and velocities, but its first forces see the whole-step velocities in the
    normal damping where the run's saw the half-step ones (velocity Verlet)."""
    from pdem.deck import load_deck
    from pdem.fields import CoarseGraining, Grid, LucyKernel
    from pdem.io.checkpoint import read_checkpoint
    from pdem.runner import Runner

    tmp, out = serial_run
    sim = Runner(load_deck(tmp / "bed.toml"), progress=None, dry=True).build()
    sim.load_state(read_checkpoint(out / "checkpoints" / "step_0000000400.h5")[0])
    from pdem.fields import CylindricalGrid, GaussianKernel

    width = float(h5py.File(out / "continuum_cell.h5", "r").attrs["width"])
    pts = np.array([[0.01, 0.01, 0.001], [0.01, 0.01, 0.003], [0.005, 0.012, 0.005], [0.0, 0.0, 0.0],
                    [0.019, 0.002, 0.007]])  # fmt: skip
    at_points = CoarseGraining(GaussianKernel(width), pts, quantities=["density", "stress", "momentum"])
    samples = []
    for _ in range(4):  # the probe's last frame: the mean of the samples at steps 450, 500, 550, 600
        sim.run(steps=50)
        samples.append(at_points(sim))
    grid = Grid((-0.002, 0.0, 0.0), (0.022, 0.02, 0.03), (3, 2, 4))
    f = CoarseGraining(LucyKernel(0.003), grid)(sim)
    last = read_continuum(out, "coarse")[-1]
    for q in ("density", "stress", "velocity"):
        assert getattr(f, q).tobytes() == last[q].tobytes(), q
    # the cylinder's and the point list's: the same as pdem.fields on those nodes
    cyl = CylindricalGrid((0.01, 0.01, 0.0), 0.009, 0.03, (5, 8, 6), inner_radius=0.001)
    cell = read_continuum(out, "cell")[-1]
    assert isinstance(cell["where"], CylindricalGrid) and cell["density"].shape == (5, 8, 6)
    assert cell["points"].tobytes() == cyl.points().reshape(5, 8, 6, 3).tobytes()
    f = CoarseGraining(GaussianKernel(width), cyl, quantities=["density", "stress", "velocity"])(sim)
    for q in ("density", "stress", "velocity"):
        assert getattr(f, q).tobytes() == cell[q].tobytes(), q
    probe = read_continuum(out, "probe")
    assert [fr["samples"] for fr in probe] == [1, 4, 4, 4]
    last = probe[-1]
    assert last["points"].tobytes() == pts.tobytes() and last["stress"].shape == (5, 3, 3)
    for q in ("density", "stress"):
        total = getattr(samples[0], q).copy()
        for f in samples[1:]:
            total += getattr(f, q)
        assert (total / 4).tobytes() == last[q].tobytes(), q
    rho = sum(f.density for f in samples)
    mom = sum(f.momentum for f in samples)
    np.testing.assert_allclose(last["velocity"], mom / rho[:, None], rtol=1e-12, atol=1e-15)
    assert np.all(last["density"] > 0.0) and np.any(last["stress"] != 0.0)


@pytest.mark.skipif(MPIEXEC is None, reason="mpiexec not found (pip install mpich)")
def test_two_ranks_and_a_resume_write_the_same_bits(serial_run):
    """The same deck on 2 ranks (per-rank slabs joined by the index), and a serial run resumed on 2
    ranks from its step-200 checkpoint into its own directory: every frame of both grids is the
    serial run's, bit for bit, the averaged frames included."""
    tmp, one = serial_run
    two = tmp / "two"
    proc = _run(tmp, "two", [str(tmp / "bed.toml"), "--output", str(two)], ranks=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (two / "continuum_bed.r0001.h5").is_file() and not (two / "continuum_bed.h5").exists()
    resumed = tmp / "resumed"
    shutil.copytree(one, resumed)
    proc = _run(tmp, "resume", ["resume", str(resumed / "checkpoints" / "step_0000000200.h5")], ranks=2)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for name in ("bed", "coarse", "cell", "probe"):
        ref = read_continuum(one, name)
        _same(ref, read_continuum(two, name))
        _same(ref, read_continuum(resumed, name))
    index = ET.parse(two / "continuum_bed.xdmf").getroot()
    frames = index.findall("./Domain/Grid/Grid")
    assert len(frames) == 4 and all(len(fr.findall("Grid")) == 2 for fr in frames)
    dims = [g.find("Topology").get("Dimensions") for g in frames[-1].findall("Grid")]
    assert dims == ["9 6 4", "9 6 4"]  # of the 7 x-planes: 0–2 and the next slab's first, then 3–6
    origins = [float(g.find("Geometry/DataItem").text.split()[2]) for g in frames[-1].findall("Grid")]
    assert origins == pytest.approx([0.02 / 14, 0.02 / 14 + 3 * 0.02 / 7], rel=1e-12)  # x of each slab
    index = ET.parse(resumed / "continuum_bed.xdmf").getroot()
    assert [len(fr.findall("Grid")) for fr in index.findall("./Domain/Grid/Grid")] == [1, 1, 2, 2]


#: pvpython: the last frame of the index argv[1], as ``d``, its times as ``times``
_PV_OPEN = textwrap.dedent(
    """
    import sys
    import numpy as np
    from paraview.simple import XDMFReader, servermanager
    from vtk.util.numpy_support import vtk_to_numpy
    r = XDMFReader(FileNames=[sys.argv[1]])
    r.UpdatePipelineInformation()
    times = list(r.TimestepValues)
    r.UpdatePipeline(times[-1])
    d = servermanager.Fetch(r)
    """
)
_PV_SCRIPT = _PV_OPEN + textwrap.dedent(
    """
    b = d.GetBlock(0)
    s = vtk_to_numpy(b.GetPointData().GetArray("stress"))
    print(len(times), d.GetNumberOfBlocks(), *b.GetDimensions(), *b.GetOrigin(), *b.GetSpacing())
    nx, ny, nz = b.GetDimensions()
    print(*[repr(float(v)) for v in s[2 + nx * (3 + ny * 4)]])
    """
)


@pytest.mark.skipif(PVPYTHON is None, reason="ParaView's pvpython is not installed")
def test_paraview_opens_the_index(serial_run, tmp_path):
    """ParaView's XDMF reader gives the grid's nodes where pdem puts them and the stress tensor at a
    node as read_continuum has it."""
    _, out = serial_run
    script = tmp_path / "pv.py"
    script.write_text(_PV_SCRIPT)
    cmd = [PVPYTHON, str(script), str(out / "continuum_bed.xdmf")]
    if XVFB:
        cmd = [XVFB, "-a", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    head = [float(v) for v in lines[-2].split()]
    assert head[:5] == [4, 1, 7, 6, 9]
    np.testing.assert_allclose(head[5:8], [0.02 / 14, 0.02 / 12, 0.03 / 18], rtol=1e-12)
    np.testing.assert_allclose(head[8:11], [0.02 / 7, 0.02 / 6, 0.03 / 9], rtol=1e-12)
    last = read_continuum(out, "bed")[-1]
    assert [float(v) for v in lines[-1].split()] == last["stress"][2, 3, 4].ravel().tolist()


_PV_NODES = _PV_OPEN + textwrap.dedent(
    """
    pts, rho, kinds = [], [], []
    for k in range(d.GetNumberOfBlocks()):
        b = d.GetBlock(k)
        kinds.append(b.GetClassName())
        pts.append(vtk_to_numpy(b.GetPoints().GetData()))
        rho.append(vtk_to_numpy(b.GetPointData().GetArray("density")))
    np.savez(sys.argv[2], points=np.concatenate(pts), density=np.concatenate(rho), times=np.array(times))
    print(*kinds)
    """
)


@pytest.mark.skipif(PVPYTHON is None or MPIEXEC is None, reason="pvpython or mpiexec is not installed")
@pytest.mark.parametrize(
    "name, kind", [("cell", "vtkStructuredGrid"), ("probe", "vtkPolyData|vtkUnstructuredGrid")]
)
def test_paraview_opens_a_cylinder_and_a_point_list(serial_run, tmp_path, name, kind):
    """The 2-rank run's cylindrical grid (two slabs of r-planes, each a structured grid whose θ ring
    is closed) and point list (two runs of points) in ParaView: every node where pdem puts it, with
    the density read_continuum gives there, and every node of pdem's shown."""
    tmp, _ = serial_run
    two = tmp / "two"
    if not two.is_dir():
        proc = _run(tmp, "two", [str(tmp / "bed.toml"), "--output", str(two)], ranks=2)
        assert proc.returncode == 0, proc.stderr[-3000:]
    script = tmp_path / "pv.py"
    script.write_text(_PV_NODES)
    got = tmp_path / "nodes.npz"
    cmd = [PVPYTHON, str(script), str(two / f"continuum_{name}.xdmf"), str(got)]
    if XVFB:
        cmd = [XVFB, "-a", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    kinds = proc.stdout.strip().splitlines()[-1].split()
    assert len(kinds) == 2 and all(k in kind.split("|") for k in kinds), kinds
    seen = np.load(got)
    last = read_continuum(two, name)[-1]
    assert len(seen["times"]) == len(read_continuum(two, name))
    nodes = zip(last["points"].reshape(-1, 3), last["density"].ravel(), strict=True)
    ours = {p.tobytes(): v for p, v in nodes}
    assert len(ours) == last["density"].size
    for p, v in zip(seen["points"], seen["density"], strict=True):
        assert p.tobytes() in ours and ours[p.tobytes()] == v
    assert {p.tobytes() for p in seen["points"]} == set(ours)
    if name == "cell":  # 5 r-planes in slabs of 2 (+1 shared) and 3, 8 θ columns + 1 closing the ring
        assert len(seen["points"]) == (3 + 3) * 9 * 6


@pytest.mark.parametrize(
    "table, key, words",
    [
        ({"lo": [0, 0, 0], "hi": [1, 1, 0], "counts": [2, 2, 2]}, "hi", "must exceed lo"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2, 2]}, "counts", "three positive integers"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2, 0, 2]}, "counts", "three positive integers"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2000, 2000, 2]}, "counts", "more than the"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2, 2, 2], "quantities": ["pressure"]},
         "quantities", "pressure"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2, 2, 2], "width": -1.0}, "width", "> 0"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2, 2, 2], "kernel": "tophat"}, "kernel", "gaussian"),
        ({"lo": [0, 0, 0], "hi": [1, 1, 1], "counts": [2, 2, 2], "spacing": 0.1}, "spacing", "unknown"),
        ({"lo": [0, 0, 0], "hi": [0.1, 0.1, 0.1], "counts": [2, 2, 2], "width": 0.5}, "width", "10 times"),
        ({"type": "cylinder", "base_center": [0, 0, 0], "height": 0.1, "counts": [2, 4, 2]}, "radius",
         "needs radius"),
        ({"type": "cylinder", "base_center": [0, 0, 0], "radius": 0.1, "height": 0.1, "counts": [2, 4, 2],
          "inner_radius": 0.1}, "inner_radius", "below radius"),
        ({"type": "cylinder", "base_center": [0, 0, 0], "radius": 0.1, "height": 0.1, "counts": [2, 4, 2],
          "lo": [0, 0, 0]}, "lo", "not a key of a cylinder grid"),
        ({"type": "cylinder", "base_center": [0, 0, 0], "radius": 0.01, "height": 0.01, "counts": [2, 4, 2],
          "width": 0.5}, "width", "10 times"),
        ({"type": "points", "points": []}, "points", "empty"),
        ({"type": "points", "points": [[0, 0]]}, "points.0", "exactly 3 items"),
        ({"type": "points", "points": [[0, 0, 0]], "counts": [1, 1, 1]}, "counts",
         "not a key of a points grid"),
        ({"type": "sphere", "points": [[0, 0, 0]]}, "type", "cylinder"),
        ({"lo": [0, 0, 0], "counts": [2, 2, 2]}, "hi", "needs hi"),
    ],
)  # fmt: skip
def test_deck_errors_name_the_key(table, key, words):
    import tomllib

    data = tomllib.loads(DECK)
    data["output"]["continuum"] = {"g": table}
    with pytest.raises(DeckError) as err:
        validate_deck(data)
    text = str(err.value)
    assert f"output.continuum.g.{key}" in text and words in text, text


def test_deck_refuses_a_name_that_cannot_name_a_file():
    import tomllib

    data = tomllib.loads(DECK)
    data["output"]["continuum"] = {"a/b": data["output"]["continuum"]["bed"]}
    with pytest.raises(DeckError, match="continuum grid name"):
        validate_deck(data)


def test_a_resume_inside_a_batch_keeps_its_earlier_frames(tmp_path):
    """Frames written together (one batch) across the step a resume continues from: the resumed
    writer keeps the batch's frames up to that step, drops the later ones, and appends after them;
    the index lists every kept and new frame once, in order."""
    import pdem
    from pdem.deck.schema import ContinuumSpec
    from pdem.io.continuum import ContinuumWriter
    from pdem.parallel.comm import SerialComm

    sim = pdem.Simulation()
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.4)  # fmt: skip
    rng = np.random.default_rng(1)
    x = (np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * 2.5e-3
    sim.add_particles(x, 0.4e-3, velocities=rng.normal(0, 0.1, x.shape))
    sim.dt = 1e-5
    spec = ContinuumSpec(lo=[0, 0, 0], hi=[0.01, 0.01, 0.01], counts=[3, 2, 2], width=0.002,
                         quantities=["density", "velocity"])  # fmt: skip
    w = ContinuumWriter(tmp_path, "g", spec, comm=SerialComm())
    w.flush_seconds = float("inf")  # everything in one batch, written at close
    for _ in range(5):
        sim.run(steps=100)
        w.write(sim, "run")
    w.close()
    first = read_continuum(tmp_path, "g")
    assert [f["step"] for f in first] == [100, 200, 300, 400, 500]
    w = ContinuumWriter(tmp_path, "g", spec, comm=SerialComm(), append_after=(300, first[2]["time"]))
    assert w.last_step == 300 and w.frame_count == 3
    sim.run(steps=100)
    w.write(sim, "again")
    w.close()
    frames = read_continuum(tmp_path, "g")
    assert [f["step"] for f in frames] == [100, 200, 300, 600]  # (this simulation was not rewound)
    assert [f["stage"] for f in frames] == ["run", "run", "run", "again"]
    for a, b in zip(first[:3], frames[:3], strict=True):
        assert a["velocity"].tobytes() == b["velocity"].tobytes()
    index = ET.parse(tmp_path / "continuum_g.xdmf").getroot()
    grids = index.findall("./Domain/Grid/Grid")
    steps = [int(g.find("Information[@Name='step']").get("Value")) for g in grids]
    assert steps == [100, 200, 300, 600]


def test_field_pictures_tool_draws_and_profiles(serial_run, tmp_path, capsys):
    """tools/field_pictures.py on a run: a section of derived quantities, a profile along z with its
    band heights (between the bottom and top means), and a clear error for a quantity not written."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import field_pictures

    _, out = serial_run
    png = tmp_path / "s.png"
    args = ["-q", "shear_rate", "-q", "pressure", "-q", "velocity.z", "--stage", "settle", "--last", "2"]
    assert field_pictures.main([str(out), "bed", *args, "--clip", "99", "-o", str(png)]) == 0
    assert png.stat().st_size > 1000
    assert field_pictures.main([str(out), "bed", "--profile", "z", "-q", "solid_fraction", "--band", "0.004",
                                "-o", str(tmp_path / "p.png")]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert "the mean of 2 frames, steps 400–600" in text and "# band: 10 % at" in text
    frame = read_continuum(out, "bed")[-1]
    z, phi = field_pictures.profile(frame, "solid_fraction", "z")
    np.testing.assert_allclose(phi, frame["solid_fraction"].mean(axis=(0, 1)))
    with pytest.raises(SystemExit, match="fabric"):
        field_pictures.main([str(out), "coarse", "-q", "fabric.zz", "-o", str(tmp_path / "x.png")])


def test_field_pictures_on_a_cylindrical_grid(serial_run, tmp_path, capsys):
    """tools/field_pictures.py on the cylinder: the r–z section is the mean over θ, a θ-plane with
    --at, (r, θ, z) components of the stress, and a profile along r; x is refused there."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import field_pictures

    _, out = serial_run
    frame = read_continuum(out, "cell")[-1]
    r, z, v = field_pictures.section(frame, "stress.rr", None)
    local = frame["where"].cylindrical(frame["stress"])
    np.testing.assert_allclose(v, local[..., 0, 0].mean(axis=1).T)
    assert r.shape == (5,) and z.shape == (6,)
    _, _, v = field_pictures.section(frame, "stress.tt", 100.0)  # θ-plane 2 of 8: 112.5°
    np.testing.assert_allclose(v, local[:, 2, :, 1, 1].T)
    assert np.array_equal(field_pictures.quantity(frame, "stress.zz"), frame["stress"][..., 2, 2])
    png = tmp_path / "c.png"
    assert field_pictures.main([str(out), "cell", "-q", "stress.rr", "-q", "pressure", "-o", str(png)]) == 0
    assert png.stat().st_size > 1000
    assert field_pictures.main([str(out), "cell", "--profile", "r", "-q", "density", "-o", str(png)]) == 0
    assert "# density along r" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="give r or z"):
        field_pictures.main([str(out), "cell", "--profile", "x", "-q", "density", "-o", str(png)])


def test_field_pictures_flux_through_a_plane_of_an_axisymmetric_jet():
    """--flux on a synthetic section: a jet of density 1,500 kg/m³ falling at 0.3 m/s within
    r < 6 mm (linear to zero over the next node) carries ρ v π R² to the trapezoid rule's error;
    without density it takes solid_fraction × --grain-density, and says what it needs otherwise."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
    import field_pictures

    x = np.linspace(-0.03, 0.03, 401)
    z = np.array([-0.001, 0.0005, 0.002])
    pts = np.zeros((x.size, 1, z.size, 3))
    pts[..., 0] = x[:, None, None]
    pts[..., 2] = z[None, None, :]
    inside = (np.abs(x) < 0.006)[:, None, None]
    vel = np.zeros((x.size, 1, z.size, 3))
    vel[..., 2] = np.where(inside, -0.3, 0.0)
    frame = {"points": pts, "velocity": vel, "solid_fraction": np.where(inside, 0.6, 0.0) + 0 * pts[..., 0]}
    got = field_pictures.flux(frame, 0.0, grain_density=2500.0)
    assert [round(zk, 6) for zk, _ in got] == [-0.001, 0.0005]
    exact = 1500.0 * 0.3 * np.pi * 0.006**2
    for _, w in got:
        assert w == pytest.approx(exact, rel=0.03)
    with pytest.raises(SystemExit, match="density"):
        field_pictures.flux(frame, 0.0)
    # the same jet on a cylindrical grid whose ring edge falls on the jet's: exact (midpoint rule)
    from pdem.fields import CylindricalGrid

    cyl = CylindricalGrid((0.0, 0.0, -0.0015), 0.012, 0.003, (8, 6, 2))
    r = cyl.axes()[0]
    shape = (8, 6, 2)
    vel = np.zeros((*shape, 3))
    vel[..., 2] = np.where(r < 0.006, -0.3, 0.0)[:, None, None]
    frame = {"points": cyl.points().reshape(*shape, 3), "where": cyl, "velocity": vel,
             "density": np.full(shape, 1500.0)}  # fmt: skip
    got = field_pictures.flux(frame, 0.0)
    assert [round(zk, 6) for zk, _ in got] == [-0.00075, 0.00075]
    for _, w in got:
        assert w == pytest.approx(exact, rel=1e-12)


def test_default_width_waits_for_grains(tmp_path):
    """Without a width the kernel is one mean grain diameter: before any grain exists (a later
    stage's source) no frame is written, and the first frame after the grains arrive takes it."""
    import pdem
    from pdem.deck.schema import ContinuumSpec
    from pdem.io.continuum import ContinuumWriter
    from pdem.parallel.comm import SerialComm

    sim = pdem.Simulation()
    sim.add_material("glass", density=2500.0, youngs_modulus=1e7, poisson_ratio=0.3, restitution=0.5,
                     friction=0.4)  # fmt: skip
    sim.dt = 1e-5
    spec = ContinuumSpec(lo=[0, 0, 0], hi=[0.01, 0.01, 0.01], counts=[2, 2, 2], average_every_steps=5)
    w = ContinuumWriter(tmp_path, "g", spec, comm=SerialComm())
    w.sample(sim)
    w.write(sim, "empty")
    assert w.last_step is None and w.width is None
    x = (np.stack(np.meshgrid(*[np.arange(3)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * 3e-3
    sim.add_particles(x, np.linspace(0.4e-3, 0.6e-3, len(x)))
    sim.run(steps=10)
    w.write(sim, "full")
    w.close()
    frames = read_continuum(tmp_path, "g")
    assert [(f["step"], f["stage"], f["samples"]) for f in frames] == [(10, "full", 1)]
    assert w.width == pytest.approx(1e-3)
