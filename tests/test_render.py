"""tools/render.py and tools/plot_series.py on a tiny run: PNGs of the requested size, not blank.

The render test needs pyvista and a working off-screen OpenGL (EGL or OSMesa through the vtk wheel,
see tools/render.py); it is skipped, with the reason, where either is missing.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from pdem.cli import main as pdem_main

TOOLS = Path(__file__).resolve().parents[1] / "tools"

DECK = """\
title = "render test: spheres falling in a box"
[run]
gravity = [0.0, 0.0, -9.81]
dt = 2e-6
seed = 5
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
region = { type = "box", lo = [0.0, 0.0, 0.0], hi = [0.01, 0.01, 0.008] }
sizes = { type = "uniform", r_min = 0.4e-3, r_max = 0.6e-3 }
n = 200
velocity = [0.0, 0.0, -0.3]
[boundaries.box]
type = "box"
material = "glass"
lo = [0.0, 0.0, 0.0]
hi = [0.01, 0.01, 0.012]
open_faces = ["zhi"]
[[stages]]
name = "drop"
[stages.end]
steps = 60
[[stages]]
name = "settle"
[stages.end]
steps = 40
[output]
formats = ["hdf5"]
every_steps = 50
series_every_steps = 10
"""


def _tool(name: str):
    spec = importlib.util.spec_from_file_location(f"pdem_tools_{name}", TOOLS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("render")
    deck = tmp / "deck.toml"
    deck.write_text(DECK)
    out = tmp / "out"
    assert pdem_main([str(deck), "--output", str(out), "--quiet"]) == 0
    assert (out / "particles.h5").is_file() and (out / "walls.h5").is_file()
    return out


def _check_png(path: Path, size: tuple[int, int] | None = None) -> None:
    import matplotlib.image as mpimg

    assert path.is_file() and path.stat().st_size > 1000, f"{path} missing or nearly empty"
    img = mpimg.imread(path)
    if size is not None:
        assert img.shape[1] == size[0] and img.shape[0] == size[1], f"{path}: {img.shape} is not {size}"
    rgb = img[..., :3].reshape(-1, 3)
    assert len(np.unique(rgb, axis=0)) > 10, f"{path} is (nearly) one colour"


@pytest.mark.integration
def test_plot_series_and_discharge(run_dir, tmp_path):
    ps = _tool("plot_series")
    path = ps.plot_series(run_dir, tmp_path / "series.png")
    assert path == tmp_path / "series.png"
    _check_png(path)
    # no discharge column in this run
    assert ps.plot_discharge(run_dir, tmp_path / "discharge.png") is None
    assert not (tmp_path / "discharge.png").exists()
    # the CLI writes the default file into the output directory
    assert ps.main([str(run_dir)]) == 0
    _check_png(run_dir / "series.png")


def test_plot_discharge_with_fit(run_dir, tmp_path):
    """A synthetic discharge column and flow rate: the discharge figure is drawn with W."""
    import json
    import shutil

    ps = _tool("plot_series")
    out = tmp_path / "hop"
    out.mkdir()
    shutil.copy(run_dir / "deck.resolved.toml", out)
    t = np.linspace(0.0, 1.0, 51).tolist()
    m = [max(0.03 * (ti - 0.2), 0.0) for ti in t]
    lines = ["time,step,ke_trans,ke_rot,hopper.discharged_mass"]
    lines += [
        f"{ti!r},{i},{1e-4 + ti * 1e-5!r},0.0,{mi!r}" for i, (ti, mi) in enumerate(zip(t, m, strict=True))
    ]
    (out / "series_drop.csv").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps({"results": {"hopper": {"flow_rate": 0.03}}}))
    path = ps.plot_discharge(out)
    assert path == out / "discharge.png"
    _check_png(path)


def test_displacement_matches_grains_by_id():
    render = _tool("render")
    ref = {"id": np.array([5, 1, 3]), "x": np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])}
    now = {"id": np.array([3, 5, 7]), "x": np.array([[2.0, 0, 3], [0.0, 4, 0], [9.0, 9, 9]])}
    d = render.displacement(now, ref)
    assert d[:2].tolist() == [3.0, 4.0] and np.isnan(d[2])


def test_render_png(run_dir, tmp_path):
    render = _tool("render")
    ok, reason = render.offscreen_works()
    if not ok:
        pytest.skip(f"no off-screen rendering here: {reason}")
    size = (320, 240)
    path = render.render_frame(run_dir, frame=-1, field="speed", path=tmp_path / "speed.png", size=size)
    _check_png(path, size)
    path = render.render_frame(
        run_dir, frame=0, field="material", path=tmp_path / "mat.png", size=(200, 160), clip_y=True
    )
    _check_png(path, (200, 160))
    # the CLI, with its default file name
    assert render.main([str(run_dir), "--field", "contacts", "--size", "240x180"]) == 0
    pngs = sorted(run_dir.glob("render_contacts_*.png"))
    assert pngs, "the CLI wrote no render_contacts_<frame>.png"
    _check_png(pngs[-1], (240, 180))
    # displacement since the stage's first frame (by id), and from a chosen frame
    path = render.render_frame(run_dir, frame=-1, field="displacement", path=tmp_path / "d.png", size=size)
    _check_png(path, size)
    args = [str(run_dir), "--field", "displacement", "--reference", "0", "--size", "240x180"]
    assert render.main(args) == 0
    # a field that does not exist is a clear error
    with pytest.raises(KeyError, match="speed"):
        render.render_frame(run_dir, field="nonexistent", path=tmp_path / "x.png", size=size)
