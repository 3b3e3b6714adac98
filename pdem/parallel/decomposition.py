"""Spatial domain decomposition: a Cartesian grid of subdomains, one per rank.

The grid spans the global bounds of the scene (particles and finite walls) when the simulation is
prepared; cut planes are uniform in each direction. The outermost subdomains extend to infinity in
non-periodic directions, so a particle can never be outside every subdomain. The grid shape is
chosen to minimise the total area of the cut planes (communication volume), unless given.
"""

from __future__ import annotations

import itertools

import numpy as np

from ..errors import InputError

__all__ = ["Decomposition", "choose_dims"]


def choose_dims(size: int, extent: np.ndarray) -> tuple[int, int, int]:
    """(nx, ny, nz) with nx·ny·nz = size minimising the cut area (ties: split x, then y, then z)."""
    best = None
    for nx, ny in itertools.product(range(1, size + 1), repeat=2):
        if size % (nx * ny):
            continue
        nz = size // (nx * ny)
        area = (
            (nx - 1) * extent[1] * extent[2]
            + (ny - 1) * extent[0] * extent[2]
            + (nz - 1) * extent[0] * extent[1]
        )
        key = (area, -nx, -ny)
        if best is None or key < best[0]:
            best = (key, (nx, ny, nz))
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

    def __init__(self, comm, x_all: np.ndarray, dims=None, min_width: float = 0.0) -> None:
        from mpi4py import MPI

        x_all = np.atleast_2d(np.asarray(x_all, dtype=float))
        if x_all.shape[0]:
            extent = np.maximum(x_all.max(axis=0) - x_all.min(axis=0), 1e-12)
        else:
            extent = np.ones(3)
        self.dims = tuple(int(d) for d in (dims or choose_dims(comm.size, extent)))
        if int(np.prod(self.dims)) != comm.size:
            raise InputError(f"decomposition {self.dims} does not match {comm.size} ranks")
        self.comm = comm.Create_cart(list(self.dims), periods=[False, False, False], reorder=False)
        self.rank = self.comm.Get_rank()
        self.coords = tuple(self.comm.Get_coords(self.rank))
        self.min_width = min_width
        self.neighbours = []
        for d in range(3):
            lower, upper = self.comm.Shift(d, 1)
            self.neighbours.append(
                (None if lower == MPI.PROC_NULL else lower, None if upper == MPI.PROC_NULL else upper)
            )
        self.set_cuts([self._quantile_cuts(np.sort(x_all[:, d]), d) for d in range(3)])
        self.n_rebalances = 0

    def _quantile_cuts(self, sorted_x: np.ndarray, d: int) -> np.ndarray:
        k = self.dims[d]
        if k == 1 or sorted_x.size == 0:
            return np.zeros(0)
        idx = (np.arange(1, k) * sorted_x.size) // k
        return self._spread(sorted_x[idx].astype(float))

    def _spread(self, cuts: np.ndarray) -> np.ndarray:
        """Keep interior subdomains at least ``min_width`` wide (ghosts move one subdomain per swap)."""
        cuts = np.array(cuts, dtype=float)
        for i in range(1, cuts.size):
            cuts[i] = max(cuts[i], cuts[i - 1] + self.min_width)
        return cuts

    def set_cuts(self, cuts: list[np.ndarray]) -> None:
        self.cuts = [np.asarray(c, dtype=float) for c in cuts]
        self.sub_lo = np.array(
            [-np.inf if self.coords[d] == 0 else self.cuts[d][self.coords[d] - 1] for d in range(3)]
        )
        self.sub_hi = np.array(
            [np.inf if self.coords[d] == self.dims[d] - 1 else self.cuts[d][self.coords[d]] for d in range(3)]
        )

    def cell_coords(self, x: np.ndarray) -> np.ndarray:
        """Subdomain coordinates (n, 3) of positions ``x``."""
        x = np.atleast_2d(x)
        out = np.empty((x.shape[0], 3), dtype=np.int64)
        for d in range(3):
            out[:, d] = np.searchsorted(self.cuts[d], x[:, d], side="right")
        return out

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
            new.append(self._spread(edges[np.searchsorted(cum, targets) + 1]))
        self.set_cuts(new)
        self.n_rebalances += 1

    def widen(self, min_width: float) -> None:
        """Raise the minimum subdomain width (a wider ghost layer) and push the cut planes apart where
        needed; particles move to their new owners at the next migration (collective decision: every
        rank calls it with the same width)."""
        self.min_width = max(self.min_width, min_width)
        self.set_cuts([self._spread(c) for c in self.cuts])

    def check_ghost_width(self, width: float) -> None:
        """Interior subdomains must be at least one ghost width wide."""
        for d in range(3):
            widths = np.diff(self.cuts[d])
            if widths.size and widths.min() < width * (1 - 1e-12):
                raise InputError(
                    f"{self.dims[d]} subdomains along axis {'xyz'[d]}: an interior one is "
                    f"{widths.min():.3g} m wide, narrower than the ghost width {width:.3g} m "
                    "(2 r_max + skin); run on fewer ranks"
                )
