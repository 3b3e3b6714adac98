#!/usr/bin/env python3
"""Pictures and profiles of a run's continuum fields (``[output.continuum.<name>]``).

    python tools/field_pictures.py OUT GRID [--frame -1] [--quantity shear_rate ...] [--output PNG]
    python tools/field_pictures.py OUT GRID --profile z --quantity velocity.x [--at 0.0]

Draws the section y = const (the grid's middle y-plane, or ``--at``) of one frame, one panel per
quantity, x across and z up; or, with ``--profile AXIS``, prints and plots one quantity along x or z
averaged over the other two axes (over the cells where the solid fraction exceeds ``--min-solid``).
On a cylindrical grid (``type = "cylinder"``) the section is the r–z plane, the mean over θ (or the
θ-plane nearest ``--at`` degrees), the profiles run along r or z, and vectors and tensors have
(r, θ, z) components: ``velocity.r``, ``stress.rr``, ``stress.tt`` (θθ), ``strain_rate.rz``.

Quantities: any scalar field (``density``, ``solid_fraction``, ``coordination``, …), a component
``velocity.x`` / ``stress.zz`` / ``strain_rate.xz`` / ``fabric.zz``, or a derived one:
``speed`` (|V|), ``pressure`` (tr σ / 3), ``deviator`` (√(3/2) |σ'|, σ' the deviatoric stress),
``shear_rate`` (√(2 D':D'), D' the deviatoric strain rate: the equivalent shear rate), ``dilation_rate``
(tr D: the volumetric strain rate, positive when the material expands).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pdem.fields import CylindricalGrid  # noqa: E402
from pdem.io.continuum import read_continuum  # noqa: E402

_AXES = {"x": 0, "y": 1, "z": 2}
_CYL_AXES = {"r": 0, "t": 1, "z": 2}
_LABELS = {
    "shear_rate": "equivalent shear rate √(2 D':D') [1/s]",
    "dilation_rate": "volumetric strain rate tr D [1/s]",
    "speed": "speed |V| [m/s]",
    "pressure": "pressure tr σ / 3 [Pa]",
    "deviator": "deviator √(3/2) |σ'| [Pa]",
    "solid_fraction": "solid fraction [-]",
    "coordination": "coordination number [-]",
    "density": "density [kg/m³]",
}


def quantity(frame: dict, name: str) -> np.ndarray:
    """The scalar field ``name`` of a frame (see the module doc), shape (nx, ny, nz)."""
    if name in frame and np.ndim(frame[name]) == 3:
        return frame[name]
    if "." in name:
        base, comp = name.split(".", 1)
        arr = _need(frame, base)
        cyl = _cylinder(frame)
        if cyl is not None and set(comp) & {"r", "t"}:  # (r, θ, z) components
            arr = cyl.cylindrical(arr)
        axes = _AXES | (_CYL_AXES if cyl is not None else {})
        if not set(comp) <= set(axes):
            raise SystemExit(f"{name}: components are {', '.join(axes)} on this grid")
        idx = [axes[c] for c in comp]
        if arr.ndim == 4 and len(idx) == 1:
            return arr[..., idx[0]]
        if arr.ndim == 5 and len(idx) == 2:
            return arr[..., idx[0], idx[1]]
        raise SystemExit(
            f"{name}: give one component of a vector (velocity.x) or two of a tensor (stress.zz)"
        )
    eye = np.eye(3)
    if name == "speed":
        return np.linalg.norm(_need(frame, "velocity"), axis=-1)
    if name in ("pressure", "deviator"):
        s = _need(frame, "stress")
        p = np.trace(s, axis1=-2, axis2=-1) / 3.0
        if name == "pressure":
            return p
        dev = s - p[..., None, None] * eye
        return np.sqrt(1.5 * np.sum(dev * dev, axis=(-2, -1)))
    if name in ("shear_rate", "dilation_rate"):
        d = _need(frame, "strain_rate")
        tr = np.trace(d, axis1=-2, axis2=-1)
        if name == "dilation_rate":
            return tr
        dev = d - (tr / 3.0)[..., None, None] * eye
        return np.sqrt(2.0 * np.sum(dev * dev, axis=(-2, -1)))
    raise SystemExit(f"unknown quantity {name!r}; see tools/field_pictures.py --help")


def _need(frame: dict, name: str) -> np.ndarray:
    if name not in frame:
        have = sorted(k for k, v in frame.items() if isinstance(v, np.ndarray) and k != "points")
        raise SystemExit(f"the grid was not written with {name!r} (it has {', '.join(have)}); add it to "
                         "[output.continuum.<name>] quantities")  # fmt: skip
    return frame[name]


def _cylinder(frame: dict) -> CylindricalGrid | None:
    where = frame.get("where")
    return where if isinstance(where, CylindricalGrid) else None


def _coords(frame: dict) -> np.ndarray:
    """The nodes' coordinates (…, 3): x, y, z, or on a cylindrical grid r, θ, z."""
    cyl = _cylinder(frame)
    if cyl is None:
        return frame["points"]
    r, t, z = np.meshgrid(*cyl.axes(), indexing="ij")
    return np.stack([r, t, z], axis=-1)


def section(frame: dict, name: str, at: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, z, values (nz, nx)) of the plane y = ``at`` (nearest grid plane; default the middle one);
    on a cylindrical grid (r, z, values (nz, nr)), the mean over θ or, with ``at`` [degrees], the
    θ-plane nearest it."""
    cyl = _cylinder(frame)
    if cyl is not None:
        r, t, z = cyl.axes()
        v = quantity(frame, name)
        if at is None:
            return r, z, v.mean(axis=1).T
        j = int(np.argmin(np.abs(np.angle(np.exp(1j * (t - np.radians(at)))))))
        return r, z, v[:, j, :].T
    pts = frame["points"]
    ys = pts[0, :, 0, 1]
    j = len(ys) // 2 if at is None else int(np.argmin(np.abs(ys - at)))
    return pts[:, 0, 0, 0], pts[0, 0, :, 2], quantity(frame, name)[:, j, :].T


def mean_frame(frames: list[dict]) -> dict:
    """The mean of several frames' arrays, each weighted by its number of samples (the points and
    the first frame's header kept)."""
    out = dict(frames[0])
    weights = np.array([f["samples"] for f in frames], dtype=float)
    for k, v in frames[0].items():
        if isinstance(v, np.ndarray) and k != "points":
            out[k] = np.average([f[k] for f in frames], axis=0, weights=weights)
    out["samples"] = sum(f["samples"] for f in frames)
    return out


def band(coord: np.ndarray, values: np.ndarray, ends: float) -> tuple[float, float, float]:
    """A shear band's 10 %, 50 % and 90 % heights: where the profile ``values`` (rising with ``coord``)
    crosses those fractions of the way from its mean within ``ends`` of the first finite coordinate to
    its mean within ``ends`` of the last (linear interpolation between nodes)."""
    ok = np.isfinite(values)
    c, v = coord[ok], values[ok]
    lo = v[c <= c[0] + ends].mean()
    hi = v[c >= c[-1] - ends].mean()
    n = (v - lo) / (hi - lo)

    def cross(level: float) -> float:
        k = int(np.flatnonzero(n >= level)[0])
        return float(c[k - 1] + (level - n[k - 1]) / (n[k] - n[k - 1]) * (c[k] - c[k - 1]))

    return cross(0.1), cross(0.5), cross(0.9)


def profile(
    frame: dict, name: str, axis: str, min_solid: float = 0.0, within: tuple[float, float] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(coordinate, mean of ``name`` over the other two axes) along ``axis``, the mean taken over the
    cells whose solid fraction exceeds ``min_solid`` (NaN where none does) and, with ``within``
    (lo, hi), whose x (for a z profile) or z (for an x profile) lies in that range."""
    axes = _CYL_AXES if _cylinder(frame) is not None else _AXES
    if axis not in axes or axis in "yt":
        allowed = " or ".join(k for k in axes if k not in "yt")
        raise SystemExit(f"--profile {axis}: give {allowed} on this grid")
    a = axes[axis]
    coords = _coords(frame)
    values = quantity(frame, name)
    keep = _need(frame, "solid_fraction") > min_solid if min_solid > 0 else np.ones(values.shape, bool)
    if within is not None:
        across = coords[..., 0 if axis == "z" else 2]
        keep = keep & (across >= within[0]) & (across <= within[1])
    other = tuple(k for k in range(3) if k != a)
    total = np.sum(np.where(keep, values, 0.0), axis=other)
    count = np.sum(keep, axis=other)
    coord = coords[..., a].mean(axis=other)
    with np.errstate(invalid="ignore", divide="ignore"):
        return coord, np.where(count > 0, total / np.maximum(count, 1), np.nan)


def flux(frame: dict, z: float, grain_density: float | None = None) -> list[tuple[float, float]]:
    """``[(z_k, W_k)]``: the mass flux down through the node planes nearest below and above ``z`` of
    a section (ny = 1) taken as axisymmetric about x = 0, W = -∫ ρ V_z 2π r dr over r = |x| (the
    trapezoid rule on the nodes, the two sides of the axis averaged; a side without a mirror node
    is used alone); on a cylindrical grid W = -Σ ρ V_z r Δr Δθ over the plane's nodes."""
    pts = frame["points"]
    if "density" in frame:
        rho = frame["density"]
    elif grain_density is not None and "solid_fraction" in frame:
        rho = grain_density * frame["solid_fraction"]
    else:
        raise SystemExit("--flux needs the grid's density, or its solid_fraction and --grain-density")
    vz = _need(frame, "velocity")[..., 2]
    cyl = _cylinder(frame)
    if cyl is not None:  # W = -Σ ρ V_z r Δr Δθ over a z-plane: the midpoint rule in r and θ
        zs = cyl.axes()[2]
        below, above = np.flatnonzero(zs <= z), np.flatnonzero(zs >= z)
        planes = sorted({int(k) for k in (*below[-1:], *above[:1])})
        area = cyl.node_volumes()[..., 0] / cyl.spacing[2]  # r Δr Δθ
        return [(float(zs[k]), float(-np.sum(rho[..., k] * vz[..., k] * area))) for k in planes]
    rho, vz = rho[:, 0, :], vz[:, 0, :]
    x, zs = pts[:, 0, 0, 0], pts[0, 0, :, 2]
    below = np.flatnonzero(zs <= z)
    above = np.flatnonzero(zs >= z)
    planes = sorted({int(k) for k in (*below[-1:], *above[:1])})
    out = []
    right = x >= 0.0
    r = x[right]
    for k in planes:
        f = rho[:, k] * vz[:, k]
        mirror = np.interp(r, -x[::-1], f[::-1], left=np.nan, right=np.nan)  # f at -r
        prof = np.where(np.isnan(mirror), f[right], 0.5 * (f[right] + np.nan_to_num(mirror)))
        out.append((float(zs[k]), float(-np.trapezoid(prof * 2.0 * np.pi * r, r))))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="the run's output directory")
    ap.add_argument("grid", help="the grid's name ([output.continuum.<name>])")
    ap.add_argument("--frame", type=int, default=-1, help="frame index (default the last)")
    ap.add_argument("--step", type=int, help="the frame at this step instead of --frame")
    ap.add_argument("--quantity", "-q", action="append", help="quantities to draw (default shear_rate)")
    ap.add_argument("--at", type=float, help="y of the section [m] (default the middle y-plane); on a "
                    "cylindrical grid θ [degrees] (default the mean over θ)")
    ap.add_argument("--profile", choices=["x", "r", "z"],
                    help="print and plot a profile along this axis (r: a cylindrical grid's)")
    ap.add_argument("--min-solid", type=float, default=0.0, help="profiles: only cells denser than this")
    ap.add_argument("--within", type=float, nargs=2, metavar=("LO", "HI"),
                    help="profiles: only cells whose other coordinate (x for a z profile) lies in LO–HI [m]")
    ap.add_argument("--stage", help="average the frames of this stage (with --last)")
    ap.add_argument("--last", type=int, help="average the last N frames (of --stage, if given)")
    ap.add_argument("--times", type=float, nargs=2, metavar=("T0", "T1"),
                    help="average the frames with T0 < time <= T1 [s] (of --stage, if given)")
    ap.add_argument("--band", type=float, metavar="ENDS",
                    help="profiles: print the 10/50/90 %% heights between the means within ENDS [m] "
                    "of the ends")
    ap.add_argument("--flux", type=float, metavar="Z",
                    help="print the mass flux down through the plane z = Z, the section taken as "
                    "axisymmetric about x = 0: -∫ rho V_z 2 pi r dr on the node planes nearest below and "
                    "above Z (both sides of the axis averaged)")
    ap.add_argument("--grain-density", type=float,
                    help="with --flux, for a grid without density: rho = solid_fraction × this [kg/m³]")
    ap.add_argument("--log", action="store_true", help="colour scale logarithmic")
    ap.add_argument("--clip", type=float, default=100.0,
                    help="sections: colour scale up to this percentile of the values (default 100)")
    ap.add_argument("--title", help="figure title")
    ap.add_argument("--output", "-o", dest="png", type=Path, help="the PNG (default OUT/fields_<grid>.png)")
    args = ap.parse_args(argv)
    frames = read_continuum(args.run, args.grid)
    if args.step is not None:
        match = [f for f in frames if f["step"] == args.step]
        if not match:
            raise SystemExit(f"no frame at step {args.step}; steps: {[f['step'] for f in frames]}")
        frame = match[0]
    elif args.last or args.stage or args.times:
        chosen = [f for f in frames if args.stage is None or f["stage"] == args.stage]
        if args.times:
            chosen = [f for f in chosen if args.times[0] < f["time"] <= args.times[1]]
        chosen = chosen[-args.last:] if args.last else chosen
        if not chosen:
            stages = sorted({f["stage"] for f in frames})
            raise SystemExit(f"no frame of stage {args.stage!r}; stages: {stages}")
        frame = mean_frame(chosen)
        frame["window"] = (chosen[0]["since"], chosen[-1]["time"], len(chosen))
        print(f"# the mean of {len(chosen)} frames, steps {chosen[0]['step']}–{chosen[-1]['step']}")
    else:
        frame = frames[args.frame]
    names = args.quantity or ["shear_rate"]
    if args.flux is not None:
        for z, value in flux(frame, args.flux, args.grain_density):
            print(f"mass flux through z = {z:.6g} m: {value:.6g} kg/s")
        if not args.quantity:
            return 0

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    head = f"t = {frame['time']:.4g} s, step {frame['step']} ({frame['stage']}), {frame['samples']} sample(s)"
    if "window" in frame:  # a mean of frames: the time it covers
        t0, t1, k = frame["window"]
        head = f"mean of {k} frames, t = {t0:.4g}–{t1:.4g} s ({frame['stage']}), {frame['samples']} samples"
    if args.profile:
        fig, ax = plt.subplots(figsize=(4.5, 4.0))
        for name in names:
            c, v = profile(frame, name, args.profile, args.min_solid, args.within)
            print(f"# {name} along {args.profile}: {head}")
            for ci, vi in zip(c, v, strict=True):
                print(f"{ci:.6g} {vi:.6g}")
            if args.band:
                b10, b50, b90 = band(c, v, args.band)
                print(f"# band: 10 % at {b10:.5g}, 50 % at {b50:.5g}, 90 % at {b90:.5g} m; "
                      f"10–90 % width {b90 - b10:.4g} m")  # fmt: skip
            if args.profile == "z":
                ax.plot(v, c, ".-", label=name)
            else:
                ax.plot(c, v, ".-", label=name)
        ax.set_xlabel("value" if args.profile == "z" else f"{args.profile} [m]")
        ax.set_ylabel(f"{args.profile} [m]" if args.profile == "z" else "value")
        ax.legend(fontsize=8)
    else:
        fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names) + 0.6, 5.0), squeeze=False)
        for ax, name in zip(axes[0], names, strict=True):
            x, z, v = section(frame, name, args.at)
            pos = v[np.isfinite(v) & (v > 0)]
            finite = v[np.isfinite(v)]
            top = float(np.percentile(finite, args.clip)) if finite.size else None
            norm = None
            if args.log and pos.size:
                norm = LogNorm(vmin=max(pos.min(), top * 1e-3), vmax=top)
            kw = {} if norm is not None else {"vmax": top}
            im = ax.pcolormesh(x, z, v, shading="nearest", cmap="viridis", norm=norm, **kw)
            ax.set_aspect("equal")
            ax.set_xlabel("r [m]" if _cylinder(frame) is not None else "x [m]")
            ax.set_ylabel("z [m]")
            fig.colorbar(im, ax=ax, shrink=0.8, label=_LABELS.get(name, name))
    fig.suptitle(args.title or head, fontsize=9)
    fig.tight_layout()
    out = args.png or args.run / f"fields_{args.grid}.png"
    fig.savefig(out, dpi=130)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
