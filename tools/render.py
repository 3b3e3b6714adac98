#!/usr/bin/env python
"""Render one snapshot of a pdem output directory to a PNG, off-screen, with pyvista.

    python tools/render.py OUTPUT_DIR [--frame K] [--field speed] [--out PNG] [--size 1200x900] [--clip-y]

Reads ``particles.h5`` (or the per-rank pieces ``particles.r*.h5`` of ``output.parallel =
"per_rank"``, joined and ordered by id) and ``walls.h5`` (written with ``formats = ["hdf5"]``) and
draws frame ``K`` (Python indexing over the stored frames: ``0`` the first, ``-1`` the last, the
default):

* particles as spheres of their true radii (a unit sphere glyph scaled by ``r``), smooth-shaded and
  coloured by ``--field``: any particle dataset of the frame (``v``, ``w``, ``f``, ``t``, ``r``,
  ``mass``, ``contacts``, ``material``, ``id``, …; vectors by their magnitude) or ``speed`` = |v|;
  ``material`` is drawn with one colour per material, labelled with the deck's material names;
* the walls of the same frame as semi-transparent grey surfaces with their rims and creases drawn
  as thin dark lines, so that they show the geometry without hiding the grains;
* a scalar bar with units, the time, stage and step in the title;
* the camera looks at the whole scene (grains and walls) from an isometric direction, "up" being
  against gravity (read from ``deck.resolved.toml``; +z if absent). ``--clip-y`` keeps only what lies
  at y >= 0 (particle centres, wall surfaces) and looks from -y, slightly from above, to see the
  section through the middle of a hopper or silo.

The default output is ``OUTPUT_DIR/render_<field>_<frame>.png``. Importable:
``render_frame(output_dir, frame=-1, field="speed", path=None, size=(1200, 900), clip_y=False)``.

Off-screen rendering (no display, as on CI)
-------------------------------------------
No X server is needed. The ``vtk`` wheels from PyPI (>= 9.4; pyvista pulls them in) choose the
OpenGL window at run time: X (GLX) when a display is there, otherwise EGL, otherwise OSMesa. EGL
with Mesa's software rasteriser (llvmpipe) works head-less on any machine; on Debian/Ubuntu it
takes the packages ``libegl1`` and ``libgl1-mesa-dri`` (``libosmesa6`` provides the OSMesa
fallback). Without a display this script sets ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``
(when ``libEGL`` is found; else ``vtkOSOpenGLRenderWindow`` when ``libOSMesa`` is) before VTK opens
a window, which skips VTK's failed attempt at X and its warning; a value already set in the
environment wins. ``xvfb`` is not used. Python packages: ``pyvista`` (the ``render`` extra).
:func:`offscreen_works` checks the whole chain in a child process (a broken OpenGL set-up can
crash the process rather than raise).
"""

from __future__ import annotations

import argparse
import ctypes.util
import os
import re
import subprocess
import sys
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

__all__ = ["render_frame", "read_frame", "field_values", "offscreen_works", "configure_offscreen", "main"]

# field -> (label, unit, factor applied to the SI values for display, number format)
_FIELDS: dict[str, tuple[str, str, float, str]] = {
    "speed": ("speed", "m/s", 1.0, "%.3g"),
    "v": ("|v|", "m/s", 1.0, "%.3g"),
    "w": ("|ω|", "rad/s", 1.0, "%.3g"),
    "f": ("|f|", "N", 1.0, "%.2e"),
    "t": ("|torque|", "N m", 1.0, "%.2e"),
    "r": ("radius", "mm", 1e3, "%.3g"),
    "mass": ("mass", "mg", 1e6, "%.3g"),
    "contacts": ("contacts", "count", 1.0, "%.0f"),
    "id": ("id", "", 1.0, "%.0f"),
    "x": ("|x|", "m", 1.0, "%.3g"),
}

_WALL_COLOR = "#9aa4ae"
_EDGE_COLOR = "#3b4650"


# ------------------------------------------------------------------------------------ off-screen
def configure_offscreen() -> None:
    """Select a head-less OpenGL window for VTK when there is no display (see the module doc)."""
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    if "VTK_DEFAULT_OPENGL_WINDOW" in os.environ:
        return
    if ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    elif ctypes.util.find_library("OSMesa"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkOSOpenGLRenderWindow"


_PROBE = """
import sys
sys.path.insert(0, {here!r})
import render
render.configure_offscreen()
import pyvista as pv
p = pv.Plotter(off_screen=True, window_size=(64, 48))
p.add_mesh(pv.Sphere(), color="red")
img = p.screenshot(return_img=True)
p.close()
assert img.shape[:2] == (48, 64) and len({{tuple(c) for c in img.reshape(-1, img.shape[-1])}}) > 1
print("ok")
"""


def offscreen_works(timeout: float = 60.0) -> tuple[bool, str]:
    """Whether pyvista can render off-screen here: ``(True, "")`` or ``(False, reason)``.

    Runs a tiny render in a child process, since a missing OpenGL library may abort the process.
    """
    try:
        import pyvista  # noqa: F401
    except ImportError as exc:
        return False, f"pyvista is not installed ({exc}); pip install pyvista (pdem[render])"
    code = _PROBE.format(here=str(Path(__file__).resolve().parent))
    try:
        proc = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout, check=False
        )
    except subprocess.TimeoutExpired:
        return False, f"off-screen test render did not finish within {timeout:.0f} s"
    if proc.returncode == 0 and proc.stdout.strip().endswith("ok"):
        return True, ""
    text = re.sub(r"\x1b\[[0-9;]*m", "", proc.stderr or proc.stdout).strip()
    tail = " | ".join(dict.fromkeys(text.splitlines()[-3:]))
    return False, (
        f"off-screen rendering failed (exit code {proc.returncode}): {tail}; install EGL + Mesa "
        f"(Debian: apt-get install libegl1 libgl1-mesa-dri) or OSMesa (libosmesa6)"
    )


# ------------------------------------------------------------------------------------ reading
@dataclass
class Snapshot:
    """One frame of an output directory."""

    index: int
    key: str
    time: float
    step: int
    stage: str
    particles: dict[str, np.ndarray]
    walls: list[tuple[str, np.ndarray, np.ndarray]] = field(default_factory=list)  # name, points, cells


def _deck(output_dir: Path) -> dict:
    path = output_dir / "deck.resolved.toml"
    try:
        return tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError):
        return {}


def particle_files(output_dir: Path) -> list[Path]:
    """``particles.h5``, or the per-rank pieces ``particles.rRRRR.h5`` in rank order."""
    ppath = output_dir / "particles.h5"
    if ppath.is_file():
        return [ppath]
    pieces = [q for q in output_dir.glob("particles.r*.h5") if re.fullmatch(r"particles\.r\d+\.h5", q.name)]
    pieces.sort(key=lambda q: int(q.name.split(".")[1][1:]))
    if not pieces:
        raise FileNotFoundError(
            f"{ppath} not found (nor per-rank pieces particles.r*.h5): render needs the HDF5 output of "
            f"a run (output.formats = ['hdf5'])"
        )
    return pieces


def read_frame(output_dir: Path | str, frame: int = -1) -> Snapshot:
    """Particles and walls of frame ``frame`` (Python index over the stored frames); per-rank
    pieces are joined and ordered by id."""
    output_dir = Path(output_dir)
    paths = particle_files(output_dir)
    ppath = paths[0]
    with h5py.File(ppath, "r", locking=False) as f:
        keys = sorted(f["frames"]) if "frames" in f else []
    if len(paths) > 1:  # a frame is complete when every rank has written its piece
        for q in paths[1:]:
            with h5py.File(q, "r", locking=False) as f:
                keys = [k for k in keys if "frames" in f and k in f["frames"]]
    if not keys:
        raise ValueError(f"{ppath} holds no frames yet")
    try:
        key = keys[frame]
    except IndexError:
        raise ValueError(
            f"frame {frame} does not exist: {ppath} holds {len(keys)} frames (0 … {len(keys) - 1}, "
            f"or -1 … -{len(keys)} from the end)"
        ) from None
    pieces: list[dict[str, np.ndarray]] = []
    for q in paths:
        with h5py.File(q, "r", locking=False) as f:
            g = f["frames"][key]
            attrs = dict(g.attrs)
            pieces.append({name: np.asarray(ds[()]) for name, ds in g.items()})
    particles = {k: np.concatenate([piece[k] for piece in pieces]) for k in pieces[0]}
    if len(pieces) > 1:
        order = np.argsort(particles["id"], kind="stable")
        particles = {k: v[order] for k, v in particles.items()}
    snap = Snapshot(
        index=keys.index(key),
        key=key,
        time=float(attrs.get("time", np.nan)),
        step=int(attrs.get("step", -1)),
        stage=str(attrs.get("stage", "")),
        particles=particles,
    )
    wpath = output_dir / "walls.h5"
    if wpath.is_file():
        with h5py.File(wpath, "r", locking=False) as f:
            frames = f.get("frames")
            if frames is not None and len(frames):
                wkey = key if key in frames else _nearest_key(frames, snap.time)
                for name, wg in frames[wkey].items():
                    if not isinstance(wg, h5py.Group) or "points" not in wg:
                        continue
                    pts, cells = np.asarray(wg["points"][()]), np.asarray(wg["cells"][()])
                    if cells.shape[0]:
                        snap.walls.append((str(wg.attrs.get("name", name)), pts, cells))
    return snap


def _nearest_key(frames: h5py.Group, time: float) -> str:
    keys = sorted(frames)
    times = np.array([float(frames[k].attrs.get("time", np.nan)) for k in keys])
    return keys[int(np.nanargmin(np.abs(times - time)))]


def field_values(particles: dict[str, np.ndarray], name: str) -> tuple[np.ndarray, str, str]:
    """Per-particle values of ``name`` for colouring (magnitude of vectors, display units),
    its label and the number format of the colour bar."""
    if name == "speed":
        if "v" not in particles:
            raise KeyError("field 'speed' needs the velocity 'v' in the output (output.fields)")
        raw = particles["v"]
    elif name in particles:
        raw = particles[name]
    else:
        known = ", ".join(["speed", *sorted(particles)])
        raise KeyError(f"no particle field '{name}' in this frame; choose one of: {known}")
    a = np.asarray(raw, dtype=np.float64)
    if a.ndim == 2:
        a = np.linalg.norm(a, axis=1)
    label, unit, factor, fmt = _FIELDS.get(name, (name, "", 1.0, "%.3g"))
    title = f"{label} [{unit}]" if unit else label
    return a * factor, title, fmt


# ------------------------------------------------------------------------------------ rendering
def displacement(particles: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> np.ndarray:
    """|x − x_ref| of each grain of ``particles`` (matched by id; nan for grains not in the reference)."""
    if "id" not in particles or "id" not in reference or "x" not in reference:
        raise KeyError("field 'displacement' needs 'x' and 'id' in the output (output.fields)")
    ids, rid = np.asarray(particles["id"]), np.asarray(reference["id"])
    order = np.argsort(rid, kind="stable")
    k = np.clip(np.searchsorted(rid, ids, sorter=order), 0, max(len(rid) - 1, 0))
    out = np.full(len(ids), np.nan)
    if len(rid):
        j = order[k]
        found = rid[j] == ids
        x, x_ref = np.asarray(particles["x"], dtype=np.float64), np.asarray(reference["x"], dtype=np.float64)
        out[found] = np.linalg.norm(x[found] - x_ref[j[found]], axis=1)
    return out


def _stage_start(output_dir: Path, snap: Snapshot) -> int:
    """Index of the stored frame at the start of ``snap``'s stage: the frame nearest the first row of
    ``series_<stage>.csv`` (the stage's first state may be stored as the previous stage's last
    frame), else the stage's first frame."""
    with h5py.File(particle_files(output_dir)[0], "r", locking=False) as f:
        keys = sorted(f["frames"])
        times = np.array([float(f["frames"][k].attrs.get("time", np.nan)) for k in keys])
        stages = [str(f["frames"][k].attrs.get("stage", "")) for k in keys]
    series = output_dir / f"series_{snap.stage}.csv"
    if series.is_file():
        from pdem.io.series import read_series

        t = read_series(series).get("time")
        if t is not None and len(t):
            return int(np.nanargmin(np.abs(times - float(t[0]))))
    return stages.index(snap.stage) if snap.stage in stages else 0


def _up_vector(deck: dict) -> np.ndarray:
    g = np.asarray(deck.get("run", {}).get("gravity", (0.0, 0.0, -9.81)), dtype=np.float64)
    n = float(np.linalg.norm(g))
    return -g / n if n > 0 else np.array([0.0, 0.0, 1.0])


def _view_direction(up: np.ndarray, azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector from the focal point towards the camera: ``azimuth`` from -y about ``up``
    (positive turns towards +x), ``elevation`` above the horizontal plane."""
    h = np.array([0.0, -1.0, 0.0])
    h = h - (h @ up) * up
    if np.linalg.norm(h) < 1e-6:
        h = np.array([-1.0, 0.0, 0.0]) - up[0] * up
    h /= np.linalg.norm(h)
    s = np.cross(up, h)
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    d = np.cos(el) * (np.cos(az) * h - np.sin(az) * s) + np.sin(el) * up
    return d / np.linalg.norm(d)


def _sphere_resolution(n: int) -> int:
    return 20 if n <= 3000 else 14 if n <= 30000 else 8


def render_frame(
    output_dir: Path | str,
    frame: int = -1,
    field: str = "speed",
    path: Path | str | None = None,
    size: tuple[int, int] = (1200, 900),
    clip_y: bool = False,
    log_scale: bool = False,
    reference: int | None = None,
) -> Path:
    """Render frame ``frame`` of ``output_dir`` coloured by ``field`` to a PNG; returns its path.

    ``field = "displacement"``: each grain's displacement since frame ``reference`` (default: the
    first frame of the rendered frame's stage, e.g. since the start of the shear), matched by id.

    ``log_scale``: logarithmic colour scale over three decades below the maximum (values below
    are drawn in the lowest colour); useful for speeds in a hopper, slow inside, fast below.
    """
    configure_offscreen()
    import pyvista as pv

    output_dir = Path(output_dir)
    snap = read_frame(output_dir, frame)
    deck = _deck(output_dir)
    width, height = (int(size[0]), int(size[1]))
    if path is None:
        path = output_dir / f"render_{field}_{snap.index:06d}.png"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    p = snap.particles
    x = np.asarray(p.get("x", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    r = np.asarray(p.get("r", np.zeros(len(x))), dtype=np.float64)
    if field == "displacement":
        ref = read_frame(output_dir, _stage_start(output_dir, snap) if reference is None else reference)
        values = 1e3 * displacement(p, ref.particles)
        # (the reference time goes in the header: in the bar's title it ran off the picture)
        bar_title, fmt = "displacement [mm]", "%.3g"
        what = f"displacement since t = {ref.time:.4g} s"
    else:
        values, bar_title, fmt = field_values(p, field) if len(x) else (np.zeros(0), field, "%.3g")
        what = "material" if field == "material" else bar_title.split(" [")[0]
    keep = x[:, 1] >= 0.0 if clip_y else np.ones(len(x), dtype=bool)

    pv.OFF_SCREEN = True
    scale = height / 900.0
    plotter = pv.Plotter(off_screen=True, window_size=(width, height))
    try:
        plotter.set_background("white")
        plotter.enable_depth_peeling(number_of_peels=8)
        bounds_pts = [x[keep] + r[keep, None], x[keep] - r[keep, None]]

        if keep.any():
            cloud = pv.PolyData(x[keep])
            cloud["radius"] = r[keep]
            cloud["value"] = values[keep]
            res = _sphere_resolution(int(keep.sum()))
            ball = pv.Sphere(radius=1.0, theta_resolution=res, phi_resolution=res)
            spheres = cloud.glyph(geom=ball, scale="radius", orient=False, factor=1.0)
            bar = dict(
                title=bar_title + "\n",
                vertical=True,
                position_x=0.87,
                position_y=0.18,
                width=0.05,
                height=0.64,
                title_font_size=max(10, int(20 * scale)),
                label_font_size=max(9, int(17 * scale)),
                color="black",
                fmt=fmt,
                n_labels=5,
            )
            kwargs: dict = dict(
                scalars="value",
                smooth_shading=True,
                specular=0.35,
                specular_power=20.0,
                ambient=0.15,
                diffuse=0.85,
                scalar_bar_args=bar,
            )
            if field == "material":
                names = list(deck.get("materials", {}))
                ids = np.unique(values[keep]).astype(int)
                labels = {float(i): (names[i] if 0 <= i < len(names) else str(i)) for i in ids}
                lo, hi = (min(ids), max(ids)) if len(ids) else (0, 1)
                kwargs.update(
                    cmap="tab10",
                    clim=(lo - 0.5, hi + 0.5),
                    n_colors=hi - lo + 1,
                    annotations=labels,
                )
                bar.update(n_labels=0, title="material\n")
            else:
                vmin, vmax = float(np.min(values[keep])), float(np.max(values[keep]))
                if field in ("speed", "v", "w", "f", "t", "contacts"):
                    vmin = 0.0
                if not vmax > vmin:
                    vmax = vmin + (abs(vmin) * 1e-3 or 1.0)
                if log_scale and vmax > 0:
                    vmin = max(vmin, vmax * 1e-3)
                    cloud["value"] = np.clip(values[keep], vmin, None)
                    spheres = cloud.glyph(geom=ball, scale="radius", orient=False, factor=1.0)
                    kwargs.update(log_scale=True)
                    bar.update(fmt="%.2g", n_labels=4)
                    bar.update(title=bar_title + ", log\n")
                kwargs.update(cmap="viridis", clim=(vmin, vmax))
            plotter.add_mesh(spheres, **kwargs)

        for _name, pts, cells in snap.walls:
            faces = np.hstack([np.full((cells.shape[0], 1), 3, dtype=np.int64), cells]).ravel()
            mesh = pv.PolyData(np.asarray(pts, dtype=np.float64), faces)
            if clip_y:
                mesh = mesh.clip(normal=(0.0, -1.0, 0.0), origin=(0.0, 0.0, 0.0), invert=True)
                if mesh.n_points == 0:
                    continue
            bounds_pts.append(np.asarray(mesh.points))
            plotter.add_mesh(
                mesh,
                color=_WALL_COLOR,
                opacity=0.35 if clip_y else 0.22,
                smooth_shading=False,
                ambient=0.3,
                specular=0.1,
                show_scalar_bar=False,
            )
            edges = mesh.extract_feature_edges(
                feature_angle=40.0, boundary_edges=True, feature_edges=True, manifold_edges=False
            )
            if edges.n_points:
                plotter.add_mesh(edges, color=_EDGE_COLOR, line_width=max(1.0, 1.5 * scale), opacity=0.8)

        # camera: isometric, or from -y slightly from above for the section
        allpts = np.concatenate([b for b in bounds_pts if len(b)] or [np.zeros((1, 3))])
        lo, hi = allpts.min(axis=0), allpts.max(axis=0)
        focal = 0.5 * (lo + hi)
        up = _up_vector(deck)
        d = _view_direction(up, 0.0, 12.0) if clip_y else _view_direction(up, 40.0, 28.0)
        radius = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
        plotter.camera_position = [tuple(focal + 4.0 * radius * d), tuple(focal), tuple(up)]
        plotter.reset_camera(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
        plotter.camera.zoom(0.98)

        title = deck.get("title", "")
        head = (  # two lines: one line ran off pictures of narrow scenes
            f"{what}   t = {snap.time:.4g} s\n(stage '{snap.stage}', step {snap.step}, "
            f"{len(x)} particles{', y >= 0' if clip_y else ''})"
        )
        plotter.add_text(head, position="upper_edge", font_size=max(8, int(13 * scale)), color="black")
        if title:
            plotter.add_text(title, position="lower_left", font_size=max(7, int(11 * scale)), color="#444444")
        plotter.enable_anti_aliasing("ssaa")
        plotter.screenshot(str(path), window_size=(width, height))
    finally:
        plotter.close()
    return path


# ------------------------------------------------------------------------------------ CLI
def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"size must be WIDTHxHEIGHT in pixels, e.g. 1200x900, got {text!r}"
        ) from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"size {text!r} is too small (at least 16x16)")
    return w, h


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Render one snapshot of a pdem output directory to PNG.")
    ap.add_argument("output_dir", type=Path, help="pdem output directory (with particles.h5, walls.h5)")
    ap.add_argument("--frame", type=int, default=-1, help="frame index (0 first, -1 last; default -1)")
    ap.add_argument(
        "--field", default="speed",
        help="colour field: speed (|v|), displacement, v, w, f, r, contacts, material…"
    )
    ap.add_argument(
        "--out", type=Path, default=None, help="PNG to write (default OUTPUT_DIR/render_<field>_<frame>.png)"
    )
    ap.add_argument(
        "--size", type=_size, default=(1200, 900), help="image size WIDTHxHEIGHT (default 1200x900)"
    )
    ap.add_argument("--clip-y", action="store_true", help="keep y >= 0 only and look from -y (see inside)")
    ap.add_argument(
        "--reference", type=int, default=None,
        help="with --field displacement: the frame displacements are measured from (default: the first "
        "frame of the rendered frame's stage)",
    )  # fmt: skip
    ap.add_argument(
        "--log", action="store_true", help="logarithmic colour scale (3 decades below the maximum)"
    )
    args = ap.parse_args(argv)
    try:
        out = render_frame(
            args.output_dir, args.frame, args.field, args.out, args.size, args.clip_y, args.log,
            reference=args.reference,
        )  # fmt: skip
    except (FileNotFoundError, ValueError, KeyError) as exc:
        msg = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        print(f"render: {msg}", file=sys.stderr)
        return 2
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
