"""Pluviation and settling: a dense random packing made the way a lab makes one.

Spheres are placed loosely (random sequential addition at ``fill_fraction``) in a tall column above
the container footprint, then rain down under gravity into a closed container (a box or an upright
cylinder with a floor) and are integrated with pdem itself until they are at rest. The result is a
settled packing whose density depends on friction and restitution, as in a real pour.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np

from ..errors import GeometryError
from ..materials import Material
from .progress import report
from .random_fill import random_fill
from .regions import BoxRegion, CylinderRegion, spatial_order
from .sizes import SizeDistribution

__all__ = ["pluviate"]


def pluviate(
    container: BoxRegion | CylinderRegion,
    sizes: SizeDistribution,
    n: int,
    material: Material,
    *,
    seed: int = 0,
    fill_fraction: float = 0.3,
    gravity: float = 9.81,
    dt: float | None = None,
    rest_speed: float | None = None,
    max_time: float = 2.0,
    check_every: int = 500,
    progress: Callable[[float, float], None] | None = None,
    comm=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Pour ``n`` spheres into ``container`` and let them settle; return (positions, radii).

    ``container`` gives the footprint and the floor (its lower z); its height is ignored, the pour
    column is as tall as needed. Settling ends when the root-mean-square speed of the spheres falls
    below ``rest_speed`` [m/s] (default 0.01 sqrt(g d_mean)), checked every ``check_every`` steps (the
    RMS, not the maximum: without rolling resistance a few surface spheres keep rolling for a long
    time), and not before the column's top could have reached the floor in free fall, sqrt(2 H / g)
    (the spheres start at rest: with a short step the first checks come before they have gathered
    speed); if that does not happen within ``max_time`` simulated seconds a :class:`GeometryError`
    is raised. ``progress(t, v_rms)`` is called at each check. Output is spatially ordered.
    Inside a run, the pour reports its progress (:mod:`pdem.sources.progress`).

    ``comm``: an MPI communicator (default: serial). The pour is then one MPI simulation, its space
    split over the ranks like a run's; every rank must call, and every rank gets the whole packing,
    bitwise the same as a serial pour's (the engine's results do not depend on the rank count, and
    the rest test sums the speeds exactly).
    """
    from ..geometry.shapes import Cylinder, Plane
    from ..simulation import Simulation

    if n <= 0:
        raise GeometryError(f"pluviate: n = {n} must be a positive number of spheres")
    if not 0.05 <= fill_fraction <= 0.35:
        raise GeometryError(f"pluviate: fill_fraction = {fill_fraction} must lie in [0.05, 0.35]")
    lo, hi = container.bounds
    footprint = (hi[0] - lo[0]) * (hi[1] - lo[1])
    if isinstance(container, CylinderRegion):
        footprint = math.pi * container.radius**2
    height = n * sizes.mean_volume() / fill_fraction / footprint + 2.0 * sizes.r_max
    if isinstance(container, CylinderRegion):
        column = CylinderRegion(container.base_center, container.radius, height)
    else:
        column = BoxRegion(lo, (hi[0], hi[1], lo[2] + height))
    t_fall = math.sqrt(2.0 * height / gravity) if gravity > 0 else 0.0  # the column's top reaches the floor
    if max_time < t_fall:
        raise GeometryError(
            f"pluviate: max_time = {max_time:.3g} s is shorter than the {height:.3g} m pour column's free "
            f"fall, {t_fall:.3g} s; raise max_time"
        )
    x, r = random_fill(column, sizes, n=n, seed=seed)

    sim = Simulation(comm=comm)
    sim.add_material(material)
    sim.add_particles(x, r)
    sim.add_wall(Plane(lo, (0, 0, 1)), name="floor")
    if isinstance(container, CylinderRegion):
        sim.add_wall(Cylinder(container.base_center, (0, 0, 1), container.radius, inside=True), name="side")
    else:
        for axis in (0, 1):
            normal = np.zeros(3)
            normal[axis] = 1.0
            sim.add_wall(Plane(lo, normal), name=f"side{axis}lo")
            sim.add_wall(Plane(hi, -normal), name=f"side{axis}hi")
    sim.gravity = (0.0, 0.0, -gravity)
    sim.dt = dt
    d_mean = 2.0 * float(np.mean(r))
    v_rest = rest_speed if rest_speed is not None else 0.01 * math.sqrt(gravity * d_mean)
    report("settling", None, f"{n} spheres falling from a {height:.3g} m column")
    wall0 = time.perf_counter()
    while True:
        sim.run(steps=check_every)
        v = sim.particles.v[: sim.particles.n_owned]
        v_rms = math.sqrt(sim.exact_sum(np.einsum("ij,ij->i", v, v)) / n)  # the same on every rank
        if progress is not None:
            progress(sim.time, v_rms)
        report(
            "settling", None, _settling_detail(sim.time, v_rms, v_rest, max_time, time.perf_counter() - wall0)
        )
        if v_rms < v_rest and sim.time >= t_fall:
            break
        if sim.time > max_time:
            raise GeometryError(
                f"pluviate: not at rest after {sim.time:.3g} s (RMS speed {v_rms:.3g} m/s > "
                f"{v_rest:.3g} m/s); raise max_time, lower restitution, or raise rest_speed"
            )
    p = sim.get_particles()
    order = spatial_order(p["x"], 2.0 * sizes.r_max)
    return p["x"][order], p["r"][order]


def _settling_detail(t: float, v_rms: float, v_rest: float, max_time: float, wall: float) -> str:
    """The progress line of a settling pour: it ends when the RMS speed falls below the rest speed,
    which cannot be foreseen, or gives up at ``max_time``, whose wall time can."""
    text = f"t = {t:.3g} s simulated, RMS speed {v_rms:.3g} m/s (at rest below {v_rest:.3g} m/s)"
    if t > 0 and wall > 0 and max_time > t:
        text += f"; gives up at max_time = {max_time:g} s, at most {(max_time - t) * wall / t:.0f} s from now"
    return text
