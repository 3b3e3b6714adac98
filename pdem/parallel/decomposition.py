"""Spatial domain decomposition: a Cartesian grid of subdomains, one per rank.

Cut planes sit at particle-count quantiles when the simulation is first prepared. The outermost
subdomains extend to infinity in non-periodic directions, so a particle can never be outside every
subdomain; along a periodic axis they end at the box faces, and the first and last subdomains are
neighbours across the periodic boundary (the same rank when the axis is not split: a rank is then its
own neighbour, and its ghosts along that axis are its own particles' images). The grid shape is
chosen to minimise the total area of the cut planes (communication volume), unless given.

A serial periodic run uses the same object with one subdomain (no MPI calls: every neighbour is
the rank itself).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from ..errors import InputError

__all__ = ["Decomposition", "choose_dims"]


def choose_dims(
    size: int, extent: np.ndarray, periodic=(False, False, False), min_width: float = 0.0
) -> tuple[int, int, int]:
    """(nx, ny, nz) with nx·ny·nz = size minimising the cut area (ties: split x, then y, then z).

    A periodic axis split in k > 1 has k cut planes (its faces become one); it may be split only
    into subdomains at least ``min_width`` wide (its ``extent`` is the box length)."""
    best = None
    for nx, ny in itertools.product(range(1, size + 1), repeat=2):
        if size % (nx * ny):
            continue
        nz = size // (nx * ny)
        dims = (nx, ny, nz)
        if any(periodic[d] and dims[d] > 1 and extent[d] / dims[d] < min_width for d in range(3)):
            continue
        planes = [dims[d] if (periodic[d] and dims[d] > 1) else dims[d] - 1 for d in range(3)]
        area = (
            planes[0] * extent[1] * extent[2]
            + planes[1] * extent[0] * extent[2]
            + planes[2] * extent[0] * extent[1]
        )
        key = (area, -nx, -ny)
        if best is None or key < best[0]:
            best = (key, dims)
    if best is None:
        raise InputError(
            f"{size} ranks cannot split the periodic box into subdomains at least {min_width:.3g} m wide "
            "(the ghost width 2 r_max + skin); run on fewer ranks"
        )
    return best[1]


class Decomposition:
    """Subdomains of a Cartesian communicator.

    Cut planes sit at particle-count quantiles along each axis (``cuts[d]`` holds the ``dims[d] − 1``
    interior planes), so every rank starts with a similar share; :meth:`rebalance` moves them when the
    particles have moved. The outer subdomains extend to infinity. Results never depend on where the
    cuts are: every sum is ordered by particle ids.

    ``owner(x)`` gives the rank owning each position; ``sub_lo``/``sub_hi`` bound this rank's
    subdomain; ``neighbours[d] = (lower, upper)`` ranks along axis d (``None`` at an outer face).
    """

    def __init__(self, comm, x_all: np.ndarray, dims=None, min_width: float = 0.0, box=None) -> None:
        self.swaps: list = []  # ghost swaps recorded by parallel.exchange.borders, replayed by forward
        x_all = np.atleast_2d(np.asarray(x_all, dtype=float))
        self.box = box
        self.periodic = tuple(bool(p) for p in box.periodic) if box is not None else (False, False, False)
        if x_all.shape[0]:
            extent = np.maximum(x_all.max(axis=0) - x_all.min(axis=0), 1e-12)
        else:
            extent = np.ones(3)
        if box is not None:
            extent = np.where(box.periodic, box.length, extent)
        self.dims = tuple(int(d) for d in (dims or choose_dims(comm.size, extent, self.periodic, min_width)))
        if len(self.dims) != 3 or int(np.prod(self.dims)) != comm.size:
            raise InputError(f"decomposition {self.dims} does not match {comm.size} ranks")
        self.min_width = min_width
        self.neighbours = []
        if comm.size == 1:  # serial (periodic): no MPI; along a periodic axis the rank is its own neighbour
            self.comm = comm
            self.rank = 0
            self.coords = (0, 0, 0)
            for d in range(3):
                self.neighbours.append((0, 0) if self.periodic[d] else (None, None))
        else:
            from mpi4py import MPI

            self.comm = comm.Create_cart(list(self.dims), periods=list(self.periodic), reorder=False)
            self.rank = self.comm.Get_rank()
            self.coords = tuple(self.comm.Get_coords(self.rank))
            for d in range(3):
                lower, upper = self.comm.Shift(d, 1)
                self.neighbours.append(
                    (None if lower == MPI.PROC_NULL else lower, None if upper == MPI.PROC_NULL else upper)
                )
        # a ghost sent down across the periodic boundary appears at x + L, one sent up at x − L
        self.shift_down = np.zeros(3)
        self.shift_up = np.zeros(3)
        for d in range(3):
            if self.periodic[d]:
                if self.coords[d] == 0:
                    self.shift_down[d] = box.length[d]
                if self.coords[d] == self.dims[d] - 1:
                    self.shift_up[d] = -box.length[d]
        self.set_cuts([self._quantile_cuts(np.sort(x_all[:, d]), d) for d in range(3)])
        self.n_rebalances = 0

    def _quantile_cuts(self, sorted_x: np.ndarray, d: int) -> np.ndarray:
        k = self.dims[d]
        if k == 1 or sorted_x.size == 0:
            return np.zeros(0)
        idx = (np.arange(1, k) * sorted_x.size) // k
        return self._spread(sorted_x[idx].astype(float), d)

    def _spread(self, cuts: np.ndarray, d: int | None = None) -> np.ndarray:
        """Keep subdomains at least ``min_width`` wide (ghosts move one subdomain per swap): the interior
        ones, and along a periodic axis ``d`` the outer ones too (they end at the box faces)."""
        cuts = np.array(cuts, dtype=float)
        w = self.min_width
        if d is not None and self.periodic[d] and cuts.size:
            lo, hi = self.box.lo[d], self.box.hi[d]
            cuts[0] = max(cuts[0], lo + w)
            for i in range(1, cuts.size):
                cuts[i] = max(cuts[i], cuts[i - 1] + w)
            cuts[-1] = min(cuts[-1], hi - w)
            for i in range(cuts.size - 2, -1, -1):
                cuts[i] = min(cuts[i], cuts[i + 1] - w)
            return cuts
        for i in range(1, cuts.size):
            cuts[i] = max(cuts[i], cuts[i - 1] + w)
        return cuts

    def set_cuts(self, cuts: list[np.ndarray]) -> None:
        self.cuts = [np.asarray(c, dtype=float) for c in cuts]
        # outer faces: infinity, or the box face along a periodic axis
        outer_lo = self.box.lo if self.box is not None else np.full(3, -np.inf)
        outer_hi = self.box.hi if self.box is not None else np.full(3, np.inf)
        self.sub_lo = np.array(
            [outer_lo[d] if self.coords[d] == 0 else self.cuts[d][self.coords[d] - 1] for d in range(3)]
        )
        self.sub_hi = np.array(
            [
                outer_hi[d] if self.coords[d] == self.dims[d] - 1 else self.cuts[d][self.coords[d]]
                for d in range(3)
            ]
        )

    def cell_coords(self, x: np.ndarray) -> np.ndarray:
        """Subdomain coordinates (n, 3) of positions ``x``."""
        x = np.atleast_2d(x)
        out = np.empty((x.shape[0], 3), dtype=np.int64)
        for d in range(3):
            out[:, d] = np.searchsorted(self.cuts[d], x[:, d], side="right")
        return out

    def axis_coords(self, xd: np.ndarray, d: int) -> np.ndarray:
        """Subdomain coordinate along axis ``d`` of coordinates ``xd``."""
        return np.searchsorted(self.cuts[d], xd, side="right")

    def owner(self, x: np.ndarray) -> np.ndarray:
        c = self.cell_coords(x)
        return (c[:, 0] * self.dims[1] + c[:, 1]) * self.dims[2] + c[:, 2]

    def owned_mask(self, x: np.ndarray) -> np.ndarray:
        c = self.cell_coords(x)
        return np.all(c == np.asarray(self.coords), axis=1)

    def imbalance(self, work: float) -> float:
        """max / mean of a per-rank work estimate (1 = perfect; collective)."""
        loads = self.comm.allgather(float(work))
        mean = sum(loads) / len(loads)
        return max(loads) / mean if mean > 0 else 1.0

    def rebalance(self, x_owned: np.ndarray, weights: np.ndarray | None = None, bins: int = 4096) -> None:
        """Move the cut planes to the work quantiles of all ranks' particles (collective).

        ``weights`` (integers ≥ 1, default 1) estimate each particle's cost. Each axis uses a weighted
        histogram of ``bins`` bins over the global range, summed over ranks in integers (exact), so
        every rank computes the same cuts.
        """
        from mpi4py import MPI

        new = []
        for d in range(3):
            if self.dims[d] == 1:
                new.append(np.zeros(0))
                continue
            xd = x_owned[:, d]
            lo = self.comm.allreduce(float(xd.min()) if xd.size else np.inf, op=MPI.MIN)
            hi = self.comm.allreduce(float(xd.max()) if xd.size else -np.inf, op=MPI.MAX)
            if not hi > lo:
                new.append(self.cuts[d])
                continue
            counts = np.histogram(xd, bins=bins, range=(lo, hi), weights=weights)[0].astype(np.int64)
            total = np.zeros_like(counts)
            self.comm.Allreduce(counts, total, op=MPI.SUM)
            cum = np.cumsum(total)
            edges = np.linspace(lo, hi, bins + 1)
            targets = np.arange(1, self.dims[d]) * cum[-1] / self.dims[d]
            new.append(self._spread(edges[np.searchsorted(cum, targets) + 1], d))
        self.set_cuts(new)
        self.n_rebalances += 1

    def widen(self, min_width: float) -> None:
        """Raise the minimum subdomain width (a wider ghost layer) and push the cut planes apart where
        needed; particles move to their new owners at the next migration (collective decision: every
        rank calls it with the same width)."""
        self.min_width = max(self.min_width, min_width)
        self.set_cuts([self._spread(c, d) for d, c in enumerate(self.cuts)])
        if self.box is not None:
            self.box.check_width(min_width)

    def narrowest(self) -> float:
        """The width of the narrowest subdomain that must hold a ghost layer (interior ones, and
        along a split periodic axis all); ``inf`` when no axis is split."""
        out = math.inf
        for d in range(3):
            edges = self.cuts[d]
            if self.periodic[d] and self.dims[d] > 1:
                edges = np.concatenate([[self.box.lo[d]], edges, [self.box.hi[d]]])
            widths = np.diff(edges)
            if widths.size:
                out = min(out, float(widths.min()))
        return out

    def check_ghost_width(self, width: float) -> None:
        """Interior subdomains (and, along a split periodic axis, all) must be at least one ghost width
        wide."""
        for d in range(3):
            edges = self.cuts[d]
            if self.periodic[d] and self.dims[d] > 1:
                edges = np.concatenate([[self.box.lo[d]], edges, [self.box.hi[d]]])
            widths = np.diff(edges)
            if widths.size and widths.min() < width * (1 - 1e-12):
                raise InputError(
                    f"{self.dims[d]} subdomains along axis {'xyz'[d]}: an interior one is "
                    f"{widths.min():.3g} m wide, narrower than the ghost width {width:.3g} m "
                    "(2 r_max + skin); run on fewer ranks"
                )
