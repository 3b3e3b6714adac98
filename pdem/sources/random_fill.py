"""Random sequential addition (RSA) of non-overlapping spheres in a region.

Radii are drawn from a size distribution, sorted largest first, and each sphere is tried at
uniform random centres (uniform over the set of centres that keep it fully inside the region)
until it overlaps no sphere already placed: ``|x_i - x_j| >= r_i + r_j + gap``. Overlap tests use
a cell grid of edge ``2 r_max + gap`` in a numba kernel, so tens of thousands of spheres take a
fraction of a second. Random sequential addition of equal spheres jams near a volume fraction of
0.38; denser packings need pluviation or settling under gravity.

The candidate centres come from ``numpy.random.default_rng(seed)`` in one stream (radii first,
then uniforms in batches), so the result is bitwise reproducible. The returned arrays are sorted
spatially (cells of edge ``2 r_max`` by z, then y, then x).

A fill of more than :data:`BLOCK_SPHERES` spheres is made in blocks (:class:`BlockPlan`): boxes
of about that many spheres, each filled from its own stream with spheres that do not cross its
faces, so that any block can be made alone — an MPI run makes only the blocks over each rank's
subdomain, and no rank holds the whole fill. The blocks' faces leave thin looser layers.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from pdem._jit import njit
from pdem.errors import GeometryError, InputError

from .progress import report
from .regions import Region, spatial_order
from .sizes import SizeDistribution

__all__ = ["random_fill", "fill_plan", "BlockPlan", "BLOCK_SPHERES"]

#: upper bound on the number of cells of the overlap grid (the cell edge grows beyond it)
_MAX_CELLS = 1 << 22

#: a fill of more spheres than this is made in blocks of about this many (:class:`BlockPlan`)
BLOCK_SPHERES = 100_000

#: a block's edge is at least this many largest diameters
BLOCK_MIN_DIAMETERS = 10


@njit
def _rsa_kernel(kind, params, radii, gap, u, pos, count, fails, max_attempts, head, nxt, glo, cell, dims):
    """Place spheres ``count..`` using candidate uniforms ``u`` (m,3); returns (count, fails, used).

    ``kind`` 0: box, params = (lo, hi); kind 1: cylinder, params = (cx, cy, z0, R, h); kind 2: the
    part of a cylinder in a box (a block of a cylinder's fill), params = (lo, hi, cx, cy, R), the
    box inside the cylinder's height (candidates outside the cylinder are drawn again; they count
    as failures only after ``1000 * max_attempts`` in a row).
    Stops when all spheres are placed, when ``fails`` reaches ``max_attempts`` consecutive
    rejections for one sphere, or when ``u`` is used up.
    """
    n = radii.shape[0]
    m = u.shape[0]
    k = 0
    nx = dims[0]
    ny = dims[1]
    nz = dims[2]
    two_pi = 2.0 * math.pi
    outside = 0
    while count < n and k < m:
        r = radii[count]
        if kind == 0:
            x = params[0] + r + u[k, 0] * (params[3] - params[0] - 2.0 * r)
            y = params[1] + r + u[k, 1] * (params[4] - params[1] - 2.0 * r)
            z = params[2] + r + u[k, 2] * (params[5] - params[2] - 2.0 * r)
        elif kind == 1:
            rho = (params[3] - r) * math.sqrt(u[k, 0])
            th = two_pi * u[k, 1]
            x = params[0] + rho * math.cos(th)
            y = params[1] + rho * math.sin(th)
            z = params[2] + r + u[k, 2] * (params[4] - 2.0 * r)
        else:  # a block of a cylinder: uniform in the block, kept inside the cylinder
            x = params[0] + r + u[k, 0] * (params[3] - params[0] - 2.0 * r)
            y = params[1] + r + u[k, 1] * (params[4] - params[1] - 2.0 * r)
            z = params[2] + r + u[k, 2] * (params[5] - params[2] - 2.0 * r)
            dx = x - params[6]
            dy = y - params[7]
            if dx * dx + dy * dy > (params[8] - r) * (params[8] - r):
                k += 1
                outside += 1
                if outside >= 1000 * max_attempts:
                    fails = max_attempts
                    break
                continue
        k += 1
        outside = 0
        ix = int((x - glo[0]) / cell)
        iy = int((y - glo[1]) / cell)
        iz = int((z - glo[2]) / cell)
        ix = min(max(ix, 0), nx - 1)
        iy = min(max(iy, 0), ny - 1)
        iz = min(max(iz, 0), nz - 1)
        ok = True
        for cz in range(max(iz - 1, 0), min(iz + 2, nz)):
            if not ok:
                break
            for cy in range(max(iy - 1, 0), min(iy + 2, ny)):
                if not ok:
                    break
                for cx in range(max(ix - 1, 0), min(ix + 2, nx)):
                    j = head[(cz * ny + cy) * nx + cx]
                    while j >= 0:
                        dx = x - pos[j, 0]
                        dy = y - pos[j, 1]
                        dz = z - pos[j, 2]
                        lim = r + radii[j] + gap
                        if dx * dx + dy * dy + dz * dz < lim * lim:
                            ok = False
                            break
                        j = nxt[j]
                    if not ok:
                        break
        if ok:
            pos[count, 0] = x
            pos[count, 1] = y
            pos[count, 2] = z
            c = (iz * ny + iy) * nx + ix
            nxt[count] = head[c]
            head[c] = count
            count += 1
            fails = 0
        else:
            fails += 1
            if fails >= max_attempts:
                break
    return count, fails, k


def _draw_radii(
    sizes: SizeDistribution, rng: np.random.Generator, n: int | None, target_volume: float | None
) -> NDArray[np.float64]:
    """Radii for the fill: ``n`` of them, or as many as reach ``target_volume`` (m³)."""
    if n is not None:
        return np.asarray(sizes.sample(rng, n), dtype=np.float64)
    assert target_volume is not None
    chunk = max(16, int(math.ceil(1.05 * target_volume / sizes.mean_volume())) + 16)
    parts: list[NDArray[np.float64]] = []
    total = 0.0
    while total < target_volume:
        part = np.asarray(sizes.sample(rng, chunk), dtype=np.float64)
        parts.append(part)
        total += float(np.sum(4.0 / 3.0 * math.pi * part**3))
    radii = np.concatenate(parts)
    cum = np.cumsum(4.0 / 3.0 * math.pi * radii**3)
    # the smallest prefix whose volume reaches the target, or one fewer if that is closer
    k = int(np.searchsorted(cum, target_volume, side="left")) + 1
    if k > 1 and abs(cum[k - 2] - target_volume) < abs(cum[k - 1] - target_volume):
        k -= 1
    return radii[:k]


def random_fill(
    region: Region,
    sizes: SizeDistribution,
    *,
    n: int | None = None,
    volume_fraction: float | None = None,
    seed: int | np.random.Generator = 0,
    max_attempts: int = 100_000,
    gap: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Fill ``region`` with non-overlapping spheres by random sequential addition.

    Parameters
    ----------
    region:
        A :class:`~pdem.sources.regions.BoxRegion` or :class:`~pdem.sources.regions.CylinderRegion`.
    sizes:
        Size distribution (:mod:`pdem.sources.sizes`) the radii are drawn from.
    n, volume_fraction:
        Exactly one: the number of spheres, or the target solid volume fraction (spheres are
        drawn until their total volume is closest to ``volume_fraction * region.volume``).
    seed:
        Integer seed of ``numpy.random.default_rng`` (or a Generator, which is advanced).
    max_attempts:
        Consecutive rejected trial positions allowed for one sphere before giving up.
    gap:
        Extra clearance (m) between sphere surfaces, ``>= 0``.

    Returns
    -------
    positions (n,3), radii (n,) float64, sorted spatially (block by block for a fill of more
    than :data:`BLOCK_SPHERES` spheres, see :class:`BlockPlan`).

    Raises
    ------
    GeometryError
        If a sphere is larger than the region, or the target cannot be reached within
        ``max_attempts`` (the message gives how many spheres were placed and the volume
        fraction achieved).
    """
    plan = fill_plan(region, sizes, n=n, volume_fraction=volume_fraction, seed=seed,
                     max_attempts=max_attempts, gap=gap)  # fmt: skip
    if plan.single:
        return plan.fill_single()
    xs, rs = [], []
    for _, _, x, r in plan.blocks():
        xs.append(x)
        rs.append(r)
    return np.ascontiguousarray(np.concatenate(xs)), np.ascontiguousarray(np.concatenate(rs))


def fill_plan(
    region: Region,
    sizes: SizeDistribution,
    *,
    n: int | None = None,
    volume_fraction: float | None = None,
    seed: int | np.random.Generator = 0,
    max_attempts: int = 100_000,
    gap: float = 0.0,
) -> BlockPlan:
    """The :class:`BlockPlan` of ``random_fill`` with these arguments, checked as it checks them."""
    if not isinstance(region, Region):
        raise InputError(
            f"random_fill: region = {region!r} is not a pdem region; pass a BoxRegion or CylinderRegion"
        )
    if not isinstance(sizes, SizeDistribution):
        raise InputError(
            f"random_fill: sizes = {sizes!r} is not a size distribution; pass e.g. Single(radius) "
            "or Uniform(r_min, r_max) from pdem.sources.sizes"
        )
    if (n is None) == (volume_fraction is None):
        raise InputError(
            f"random_fill: give exactly one of n (= {n!r}) and volume_fraction (= {volume_fraction!r})"
        )
    if n is not None and (isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0):
        raise InputError(f"random_fill: n = {n!r} must be an integer >= 0 (number of spheres)")
    if volume_fraction is not None:
        vf = float(volume_fraction)
        if not (0.0 < vf < 1.0) or not math.isfinite(vf):
            raise InputError(
                f"random_fill: volume_fraction = {volume_fraction!r} must lie in (0, 1); random "
                "sequential addition reaches at most about 0.38 for equal spheres"
            )
    if isinstance(max_attempts, bool) or not isinstance(max_attempts, (int, np.integer)) or max_attempts < 1:
        raise InputError(f"random_fill: max_attempts = {max_attempts!r} must be an integer >= 1")
    g = float(gap)
    if not math.isfinite(g) or g < 0.0:
        raise InputError(f"random_fill: gap = {gap!r} must be a finite clearance >= 0 (metres)")
    if sizes.r_max > region.max_sphere_radius():
        raise GeometryError(
            f"random_fill: spheres up to radius {sizes.r_max!r} do not fit in {region!r} (largest "
            f"radius that fits: {region.max_sphere_radius()!r}); use a larger region or smaller spheres"
        )

    return BlockPlan(region, sizes, n=None if n is None else int(n), volume_fraction=volume_fraction,
                     seed=seed, gap=g, max_attempts=int(max_attempts))  # fmt: skip


def _place(kind, params, radii, lo, hi, gap, rng, max_attempts, where, volume, want, phase=None):
    """Random sequential addition of ``radii`` (largest first) in the region ``(kind, params)``
    whose bounds are ``[lo, hi]``; positions in the order of ``radii``."""
    n_tot = radii.shape[0]
    pos = np.zeros((n_tot, 3), dtype=np.float64)
    if n_tot == 0:
        return pos
    r_max = float(radii[0])
    cell = 2.0 * r_max + gap
    ext = hi - lo
    while np.prod(np.maximum(np.ceil(ext / cell), 1.0)) > _MAX_CELLS:
        cell *= 1.25
    dims = np.maximum(np.ceil(ext / cell), 1.0).astype(np.int64)
    head = np.full(int(np.prod(dims)), -1, dtype=np.int64)
    nxt = np.full(n_tot, -1, dtype=np.int64)
    count = 0
    fails = 0
    while count < n_tot:
        batch = int(min(max(4096, 4 * (n_tot - count)), 1 << 20))
        u = rng.random((batch, 3))
        count, fails, _ = _rsa_kernel(
            kind, params, radii, gap, u, pos, count, fails, int(max_attempts), head, nxt, lo, cell, dims
        )
        if phase is not None:
            report(phase, count / n_tot, f"{count} of {n_tot} placed")
        if fails >= max_attempts:
            placed_vol = float(np.sum(4.0 / 3.0 * math.pi * radii[:count] ** 3))
            raise GeometryError(
                f"random_fill: placed only {count} of {n_tot} spheres in {where} (volume fraction "
                f"{placed_vol / volume:.4f} of the {want / volume:.4f} asked) before "
                f"{max_attempts} consecutive attempts failed for sphere {count} (radius "
                f"{float(radii[count])!r}). Use a larger region or a lower volume fraction (random "
                "sequential addition jams near 0.38 for equal spheres), or place loosely and "
                "settle / pluviate the particles under gravity"
            )
    return pos


def _sorted_radii(radii: NDArray[np.float64]) -> NDArray[np.float64]:
    """Largest first; the stable sort keeps the draw order among equal radii (deterministic)."""
    return np.ascontiguousarray(radii[np.argsort(-radii, kind="stable")])


class BlockPlan:
    """How a random fill is made: whole (one block, the classic algorithm), or, when it would place
    more than :data:`BLOCK_SPHERES` spheres, in blocks filled independently.

    A block is a box of a regular grid over the region's bounds, its edges at least
    ``BLOCK_MIN_DIAMETERS`` largest diameters. Its spheres lie wholly inside it (and inside the
    region), so blocks cannot overlap one another and each is made from its own random stream,
    ``numpy.random.default_rng([seed, block])``; any block can be made alone, bitwise the same,
    which lets each MPI rank make only the blocks over its subdomain (and survey the others one at a
    time). With ``n`` the spheres are shared over the blocks in proportion to the volume their
    centres can reach (largest remainders); with ``volume_fraction`` each block fills that fraction
    of its part of the region. The fill's order is block by block (z, then y, then x), each block's
    spheres in spatial order. Cost of the blocks: no centre lies within a radius of a block's face,
    so each face carries a layer about a diameter thick that is looser than the bulk (it disappears
    once the grains move); a fill of one block has none.
    """

    def __init__(self, region, sizes, *, n, volume_fraction, seed, gap, max_attempts):
        self.region, self.sizes, self.n, self.gap = region, sizes, n, float(gap)
        self.volume_fraction = volume_fraction
        self.max_attempts = int(max_attempts)
        self.seed = seed
        lo, hi = region.bounds
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        estimate = n if n is not None else float(volume_fraction) * region.volume / sizes.mean_volume()
        self.single = estimate <= BLOCK_SPHERES
        if self.single:
            return
        if isinstance(seed, np.random.Generator):
            seed = int(seed.integers(0, 2**63 - 1))
        self.base_seed = int(seed)
        ext = self.hi - self.lo
        edge = (region.volume * BLOCK_SPHERES / estimate) ** (1.0 / 3.0)
        smallest = BLOCK_MIN_DIAMETERS * 2.0 * sizes.r_max
        self.m = np.maximum(np.minimum(np.ceil(ext / edge), np.floor(ext / smallest)), 1).astype(np.int64)
        self.edges = [np.linspace(self.lo[d], self.hi[d], int(self.m[d]) + 1) for d in range(3)]
        self.count = int(np.prod(self.m))
        if self.count == 1:  # (a region too small to cut into blocks that large)
            self.single = True
            return
        if n is not None:
            reach = np.array([self._volume(b, sizes.r_max) for b in range(self.count)])
            if not reach.sum() > 0.0:
                raise GeometryError(
                    f"random_fill: no block of {region!r} has room for a sphere of radius {sizes.r_max!r}"
                )
            share = n * reach / reach.sum()
            quota = np.floor(share).astype(np.int64)
            left = int(n - quota.sum())
            order = np.lexsort((np.arange(self.count), -(share - quota)))  # largest remainder, then index
            quota[order[:left]] += 1
            self.quota = quota

    # ------------------------------------------------------------------ geometry of the blocks
    def bounds(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` of block ``b`` (index (iz m_y + iy) m_x + ix)."""
        mx, my = int(self.m[0]), int(self.m[1])
        iz, rest = divmod(int(b), mx * my)
        iy, ix = divmod(rest, mx)
        idx = (ix, iy, iz)
        lo = np.array([self.edges[d][idx[d]] for d in range(3)])
        hi = np.array([self.edges[d][idx[d] + 1] for d in range(3)])
        return lo, hi

    def _volume(self, b: int, shrink: float) -> float:
        """Volume of the part of block ``b`` in the region, both shrunk by ``shrink`` (the room of
        centres of spheres of that radius); a cylinder's is a midpoint rule on a 128 × 128 grid."""
        lo, hi = self.bounds(b)
        lo, hi = lo + shrink, hi - shrink
        ext = hi - lo
        if np.any(ext <= 0.0):
            return 0.0
        kind, params = self.region._rsa_spec()
        if kind == 0:
            return float(np.prod(ext))
        cx, cy, rad = params[0], params[1], params[3] - shrink
        if rad <= 0.0:
            return 0.0
        k = 128
        xs = lo[0] + (np.arange(k) + 0.5) * ext[0] / k
        ys = lo[1] + (np.arange(k) + 0.5) * ext[1] / k
        inside = (xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2 <= rad * rad
        return float(inside.sum() / (k * k) * ext[0] * ext[1] * ext[2])

    def _spec(self, b: int):
        lo, hi = self.bounds(b)
        kind, params = self.region._rsa_spec()
        if kind == 0:
            return 0, np.concatenate([lo, hi]), lo, hi
        return 2, np.concatenate([lo, hi, [params[0], params[1], params[3]]]), lo, hi

    # ------------------------------------------------------------------ making the spheres
    def fill_single(self):
        """The whole fill as one block (the classic algorithm, one random stream); made once per plan
        (a Generator seed is advanced only then)."""
        if getattr(self, "_whole", None) is None:
            self._whole = self._fill_single()
        return self._whole

    def _fill_single(self):
        region = self.region
        rng = self.seed if isinstance(self.seed, np.random.Generator) else np.random.default_rng(self.seed)
        target = None if self.n is not None else float(self.volume_fraction) * region.volume
        radii = _sorted_radii(_draw_radii(self.sizes, rng, self.n, target))
        if radii.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros(0)
        kind, params = region._rsa_spec()
        want = target if target is not None else float(np.sum(4.0 / 3.0 * math.pi * radii**3))
        pos = _place(kind, params, radii, self.lo, self.hi, self.gap, rng, self.max_attempts, repr(region),
                     region.volume, want, phase="placing spheres (random sequential addition)")  # fmt: skip
        order = spatial_order(pos, 2.0 * float(radii[0]), origin=self.lo)
        return np.ascontiguousarray(pos[order]), np.ascontiguousarray(radii[order])

    def _radii(self, b: int):
        """Block ``b``'s random stream and radii (largest first)."""
        rng = np.random.default_rng([self.base_seed, int(b)])
        if self.n is not None:
            radii = _draw_radii(self.sizes, rng, int(self.quota[b]), None)
        else:
            target = float(self.volume_fraction) * self._volume(b, 0.0)
            radii = _draw_radii(self.sizes, rng, None, target) if target > 0.0 else np.zeros(0)
        return rng, _sorted_radii(radii)

    def counts(self) -> np.ndarray:
        """Spheres per block (draws the radii of every block when filling to a volume fraction)."""
        if self.n is not None:
            return self.quota.copy()
        if getattr(self, "_counts", None) is None:  # (drawn once per plan)
            self._counts = np.array([self._radii(b)[1].shape[0] for b in range(self.count)], dtype=np.int64)
        return self._counts.copy()

    def block(self, b: int):
        """Block ``b``'s spheres: positions and radii, in spatial order."""
        rng, radii = self._radii(b)
        if radii.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros(0)
        kind, params, lo, hi = self._spec(b)
        volume = max(self._volume(b, 0.0), 1e-300)
        want = float(np.sum(4.0 / 3.0 * math.pi * radii**3))
        where = f"block {b} ({lo.tolist()} to {hi.tolist()}) of {self.region!r}"
        pos = _place(kind, params, radii, lo, hi, self.gap, rng, self.max_attempts, where, volume, want)
        order = spatial_order(pos, 2.0 * float(radii[0]), origin=lo)
        return np.ascontiguousarray(pos[order]), np.ascontiguousarray(radii[order])

    def blocks(self, lo=None, hi=None):
        """``(block, first index, positions, radii)`` of every block, or of those that meet the box
        ``[lo, hi]``, in the fill's order, one at a time."""
        counts = self.counts()
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        total = int(counts.sum())
        done = 0
        for b in range(self.count):
            if lo is not None:
                blo, bhi = self.bounds(b)
                if np.any(bhi < lo) or np.any(blo > hi):
                    continue
            x, r = self.block(b)
            done += r.shape[0]
            report("placing spheres (random sequential addition, by blocks)", min(done / max(total, 1), 1.0),
                   f"block {b + 1} of {self.count}")  # fmt: skip
            yield b, int(start[b]), x, r

    def total(self) -> int:
        return int(self.counts().sum())

    def survey(self):
        """``(count, lo, hi, r_max, sample)`` of the fill, made one block at a time (a whole fill of one
        block is made at once), as :class:`pdem.sources.api.Survey` wants them."""
        from .api import Sampler

        sampler, r_max = Sampler(), 0.0
        for x, r in ([self.fill_single()] if self.single else (b[2:] for b in self.blocks())):
            sampler.add(x)
            if r.shape[0]:
                r_max = max(r_max, float(r.max()))
        return sampler.survey(r_max)

    def part(self, lo, hi):
        """``(positions, radii, index, total)`` of the spheres centred in the box ``[lo, hi]``, made from
        the blocks that meet it only (a fill of one block is made whole), ``index`` their places in
        the whole fill of ``total`` spheres."""
        lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        if self.single:
            x, r = self.fill_single()
            blocks, total = [(0, x, r)], r.shape[0]
        else:
            total = self.total()
            blocks = [(start, x, r) for _, start, x, r in self.blocks(lo, hi)]
        xs, rs, index = [], [], []
        for start, x, r in blocks:
            inside = np.flatnonzero(np.all((x >= lo) & (x <= hi), axis=1))
            xs.append(x[inside])
            rs.append(r[inside])
            index.append(start + inside)
        x = np.concatenate(xs).reshape(-1, 3) if xs else np.zeros((0, 3))
        r = np.concatenate(rs) if rs else np.zeros(0)
        index = np.concatenate(index).astype(np.int64) if index else np.zeros(0, np.int64)
        return x, r, index, total
