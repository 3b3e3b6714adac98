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
from .random_fill import fill_plan
from .regions import BoxRegion, CylinderRegion
from .sizes import SizeDistribution

__all__ = ["pluviate", "pour", "PouredBed"]


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
    return pour(
        container, sizes, n, material, seed=seed, fill_fraction=fill_fraction, gravity=gravity, dt=dt,
        rest_speed=rest_speed, max_time=max_time, check_every=check_every, progress=progress, comm=comm,
    ).whole()  # fmt: skip


def pour(
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
) -> PouredBed:
    """:func:`pluviate`'s pour, its packing left with the ranks that poured it (each holds its own
    spheres; no rank holds them all): a :class:`PouredBed`. Collective under MPI."""
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
    plan = fill_plan(column, sizes, n=n, seed=seed)
    sim = Simulation(comm=comm)
    sim.add_material(material)
    if sim.comm.size > 1:  # each rank keeps the fill's spheres over its own space (made by blocks)
        sim.place_decomposition(plan.survey().sample)
        dec = sim.decomposition
        x, r, index, total = plan.part(dec.sub_lo, dec.sub_hi)
        sim.add_particle_part(x, r, index, total)
        if plan.single:
            r = plan.fill_single()[1]
    else:
        x, r = plan.fill_single() if plan.single else plan.part(np.full(3, -np.inf), np.full(3, np.inf))[:2]
        sim.add_particles(x, r)
    if plan.single:  # (as it always was: the mean of the whole fill's radii)
        d_mean = 2.0 * float(np.mean(r))
    else:  # an exact sum over the ranks' own spheres: the same on any rank count
        d_mean = 2.0 * sim.exact_sum(sim.particles.r[: sim.particles.n_owned]) / n
    del x, r, plan
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
    return PouredBed(sim, 2.0 * sizes.r_max)


class PouredBed:
    """A settled pour, each rank holding the spheres it owned at the end, numbered in the order of
    :func:`~pdem.sources.spatial_order` (cells of edge ``cell`` from the centres' minimum; ties by
    the pour's ids) of the whole packing, without ever holding it whole: the cells' z-layers are
    shared out over the ranks by their counts (one ``alltoall``), each rank orders its layers, and
    the layers' counts give every sphere its place. ``positions``, ``radii``, ``index`` (increasing),
    ``count``. :meth:`survey`, :meth:`part` and :meth:`whole` are collective."""

    def __init__(self, sim, cell: float) -> None:
        from ..parallel.comm import all_max, all_min, all_sum_int_array

        comm = self.comm = sim.comm
        own = sim.own_particles()
        x, r, ids = own["x"], own["r"], own["id"]
        self.count = int(all_sum_int_array(comm, np.array([r.shape[0]], dtype=np.int64))[0])
        origin = np.array([all_min(comm, float(x[:, d].min()) if r.shape[0] else math.inf) for d in range(3)])
        cells = np.floor((x - origin) / cell).astype(np.int64)
        layers = int(all_max(comm, float(cells[:, 2].max()) if r.shape[0] else -1.0)) + 1
        counts = all_sum_int_array(comm, np.bincount(cells[:, 2], minlength=layers).astype(np.int64))
        first = np.cumsum(counts) - counts  # the first place of each layer in the whole order
        owner = np.minimum(first * comm.size // max(self.count, 1), comm.size - 1)  # contiguous, balanced
        if comm.size > 1:
            dest = owner[cells[:, 2]]
            got = comm.alltoall([(x[dest == k], r[dest == k], ids[dest == k], cells[dest == k])
                                 for k in range(comm.size)])  # fmt: skip
            x, r, ids, cells = (np.concatenate([g[i] for g in got]) for i in range(4))
            x, cells = x.reshape(-1, 3), cells.reshape(-1, 3)
        order = np.lexsort((ids, x[:, 0], x[:, 1], x[:, 2], cells[:, 0], cells[:, 1], cells[:, 2]))
        self.positions, self.radii = np.ascontiguousarray(x[order]), np.ascontiguousarray(r[order])
        start = int(first[cells[order[0], 2]]) if order.shape[0] else 0
        self.index = start + np.arange(order.shape[0], dtype=np.int64)

    def survey(self):
        """The :class:`pdem.sources.api.Survey` of the packing: count, exact bounds, largest radius
        and every stride-th sphere (the stride a power of two, as :class:`~pdem.sources.api.Sampler`
        keeps them), the same on every rank."""
        from ..parallel.comm import all_max, all_min
        from .api import SURVEY_SAMPLE, Survey

        comm, x = self.comm, self.positions
        has = x.shape[0] > 0
        lo = np.array([all_min(comm, float(x[:, d].min()) if has else math.inf) for d in range(3)])
        hi = np.array([all_max(comm, float(x[:, d].max()) if has else -math.inf) for d in range(3)])
        r_max = all_max(comm, float(self.radii.max()) if has else 0.0)
        stride = 1
        while -(-self.count // stride) > SURVEY_SAMPLE:
            stride *= 2
        take = self.index % stride == 0
        parts = comm.allgather((self.index[take], x[take]))
        index = np.concatenate([p[0] for p in parts])
        sample = np.concatenate([p[1] for p in parts]).reshape(-1, 3)[np.argsort(index)]
        return Survey(self.count, lo, hi, float(r_max), sample)

    def part(self, lo, hi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(positions, radii, index)`` of the spheres centred in this rank's box ``[lo, hi]`` (each
        rank gives its own box; one ``allgather`` of the boxes, one ``alltoall`` of the spheres)."""
        comm = self.comm
        boxes = comm.allgather((np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)))
        x, r, index = self.positions, self.radii, self.index
        if comm.size == 1:
            keep = np.all((x >= boxes[0][0]) & (x <= boxes[0][1]), axis=1)
            return x[keep], r[keep], index[keep]
        send = []
        for a, b in boxes:
            keep = np.all((x >= a) & (x <= b), axis=1)
            send.append((x[keep], r[keep], index[keep]))
        got = comm.alltoall(send)
        x, r, index = (np.concatenate([g[i] for g in got]) for i in range(3))
        order = np.argsort(index, kind="stable")
        return x.reshape(-1, 3)[order], r[order], index[order].astype(np.int64)

    def whole(self) -> tuple[np.ndarray, np.ndarray]:
        """The whole packing on every rank (positions, radii), in its order (gathers: for serial use
        and small pours)."""
        parts = self.comm.allgather((self.index, self.positions, self.radii))
        index = np.concatenate([p[0] for p in parts])
        order = np.argsort(index)
        x = np.concatenate([p[1] for p in parts]).reshape(-1, 3)[order]
        return np.ascontiguousarray(x), np.ascontiguousarray(np.concatenate([p[2] for p in parts])[order])


def _settling_detail(t: float, v_rms: float, v_rest: float, max_time: float, wall: float) -> str:
    """The progress line of a settling pour: it ends when the RMS speed falls below the rest speed,
    which cannot be foreseen, or gives up at ``max_time``, whose wall time can."""
    text = f"t = {t:.3g} s simulated, RMS speed {v_rms:.3g} m/s (at rest below {v_rest:.3g} m/s)"
    if t > 0 and wall > 0 and max_time > t:
        text += f"; gives up at max_time = {max_time:g} s, at most {(max_time - t) * wall / t:.0f} s from now"
    return text
