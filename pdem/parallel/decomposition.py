"""Spatial domain decomposition: a Cartesian grid of subdomains, one per rank.

Cut planes sit at particle-count quantiles when the simulation is first prepared (or, when it had
no particles then, when the first ones are added: an empty first stage). The outermost
subdomains extend to infinity in non-periodic directions, so a particle can never be outside every
subdomain; along a periodic axis they end at the box faces, and the first and last subdomains are
neighbours across the periodic boundary (the same rank when the axis is not split: a rank is then its
own neighbour, and its ghosts along that axis are its own particles' images). The grid shape is
chosen to minimise the total area of the cut planes (communication volume), unless given.

A serial periodic run uses the same object with one subdomain (no MPI calls: every neighbour is
the rank itself).
"""

from __future__ import annotations

import hashlib
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
        x_all = np.atleast_2d(np.asarray(x_all, dtype=float)).reshape(-1, 3)
        self.box = box
        self.periodic = tuple(bool(p) for p in box.periodic) if box is not None else (False, False, False)
        self.min_width = min_width
        self._world = comm
        self._given_dims = dims
        #: False while no particle exists on any rank (a first stage without grains): the cut planes
        #: are then provisional, and the first particles added (:meth:`owned_mask`) place them, and
        #: choose the grid, as if they had been there from the start
        self.placed = comm.size == 1 or x_all.shape[0] > 0
        self._just_placed = False  # placed since the last imbalance(): the work measured before is moot
        self._grid(self._choose_dims(x_all))
        if self.placed:
            self.set_cuts([self._quantile_cuts(np.sort(x_all[:, d]), d) for d in range(3)])
        else:
            self.set_cuts([self._even_cuts(d) for d in range(3)])
        self.n_rebalances = 0

    @classmethod
    def from_shares(
        cls, comm, x: np.ndarray, layout: dict | None = None, dims=None, min_width: float = 0.0, box=None
    ) -> Decomposition:
        """Subdomains for particles spread over the ranks in any way (collective): a per-rank
        checkpoint read back, each rank holding the parts it read. The grid follows the particles'
        global extent; the cut planes are the writing run's (``layout``: ranks, dims, cuts) when it
        ran on as many ranks with the same grid, else the particle-count quantiles (histograms summed
        over the ranks, as :meth:`rebalance`). No rank sees another's positions; results never depend
        on where the cuts are."""
        from mpi4py import MPI

        x = np.asarray(x, dtype=float).reshape(-1, 3)
        lo = np.full(3, np.inf) if not len(x) else x.min(axis=0)
        hi = np.full(3, -np.inf) if not len(x) else x.max(axis=0)
        lo = np.array([comm.allreduce(float(v), op=MPI.MIN) for v in lo])
        hi = np.array([comm.allreduce(float(v), op=MPI.MAX) for v in hi])
        corners = np.array([lo, hi]) if np.all(np.isfinite(lo)) else np.zeros((0, 3))
        self = cls(comm, corners, dims=dims, min_width=min_width, box=box)
        if not self.placed:
            return self
        same = (
            isinstance(layout, dict)
            and layout.get("ranks") == comm.size
            and tuple(layout.get("dims") or ()) == self.dims
            and all(len(c) == k - 1 for c, k in zip(layout.get("cuts") or [], self.dims, strict=False))
        )
        if same:
            self.set_cuts([self._spread(np.asarray(c, dtype=float), d) for d, c in enumerate(layout["cuts"])])
        else:
            self.rebalance(x)
            self.n_rebalances = 0
        self._just_placed = True  # the first rebuild keeps these planes (the work measured is moot)
        return self

    def layout(self) -> dict:
        """Ranks, grid and cut planes (JSON-able: kept with per-rank checkpoints)."""
        cuts = [c.tolist() for c in self.cuts]
        return {"ranks": int(np.prod(self.dims)), "dims": list(self.dims), "cuts": cuts}

    def _choose_dims(self, x_all: np.ndarray) -> tuple[int, ...]:
        """The grid: the one given, else the one with the least cut area over the particles' extent."""
        if x_all.shape[0]:
            extent = np.maximum(x_all.max(axis=0) - x_all.min(axis=0), 1e-12)
        else:
            extent = np.ones(3)
        if self.box is not None:
            extent = np.where(self.box.periodic, self.box.length, extent)
        dims = self._given_dims or choose_dims(self._world.size, extent, self.periodic, self.min_width)
        return tuple(int(d) for d in dims)

    def _grid(self, dims: tuple[int, ...]) -> None:
        """The Cartesian communicator of ``dims`` (collective on several ranks), this rank's place in
        it and its neighbours."""
        comm = self._world
        self.dims = dims
        if len(self.dims) != 3 or int(np.prod(self.dims)) != comm.size:
            raise InputError(f"decomposition {self.dims} does not match {comm.size} ranks")
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
                    self.shift_down[d] = self.box.length[d]
                if self.coords[d] == self.dims[d] - 1:
                    self.shift_up[d] = -self.box.length[d]
        self.swaps: list = []  # ghost swaps recorded by parallel.exchange.borders, replayed by forward

    def _quantile_cuts(self, sorted_x: np.ndarray, d: int) -> np.ndarray:
        k = self.dims[d]
        if k == 1:
            return np.zeros(0)
        if sorted_x.size == 0:
            return self._even_cuts(d)
        idx = (np.arange(1, k) * sorted_x.size) // k
        return self._spread(sorted_x[idx].astype(float), d)

    def _even_cuts(self, d: int) -> np.ndarray:
        """The ``dims[d] − 1`` cut planes along ``d`` with no particle to place them: evenly over the
        box along a periodic axis, else ``min_width`` apart from 0."""
        k = self.dims[d]
        if self.periodic[d]:
            lo, hi = self.box.lo[d], self.box.hi[d]
            return self._spread(lo + (hi - lo) * np.arange(1, k) / k, d)
        return self._spread(np.zeros(k - 1), d)

    def _place(self, x: np.ndarray) -> None:
        """Place the provisional cut planes at the first particles (collective: every caller of
        :meth:`owned_mask` is; nothing happens while no rank has a particle).

        ``Simulation.add_particles`` gives every rank the same new particles: their quantiles are then
        computed locally, as at a first preparation; should the ranks hold different ones, the
        quantiles are those of all of them. Either way every rank computes the same planes."""
        digest = hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest() if x.shape[0] else ""
        seen = self._world.allgather((int(x.shape[0]), digest))
        if not any(n for n, _ in seen):
            return
        if len(set(seen)) > 1:
            x = np.concatenate(self._world.allgather(x))
        dims = self._choose_dims(x)
        if dims != self.dims:
            self._grid(dims)
        self.placed = True
        self._just_placed = True
        self.set_cuts([self._quantile_cuts(np.sort(x[:, d]), d) for d in range(3)])

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
        """Which of positions ``x`` this rank owns. While the cut planes are provisional (no particle
        yet) it places them at ``x`` first, collectively (see :meth:`_place`)."""
        if not self.placed:
            self._place(np.atleast_2d(np.asarray(x, dtype=float)).reshape(-1, 3))
        c = self.cell_coords(x)
        return np.all(c == np.asarray(self.coords), axis=1)

    def imbalance(self, work: float) -> float:
        """max / mean of a per-rank work estimate (1 = perfect; collective).

        1 at the first call after the provisional cut planes were placed (every rank alike): the work
        measured until then, without particles, says nothing about the planes just placed at the
        particle quantiles (a first preparation does not rebalance either)."""
        if self._just_placed:
            self._just_placed = False
            return 1.0
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
            self._check_periodic_room()

    def _check_periodic_room(self) -> None:
        """Along a split periodic axis the subdomains fill the box: when it has no room for ``dims[d]``
        of them ``min_width`` wide (the ghost width grew: larger grains added, a wider skin or
        envelope), refuse rather than miss the ghosts two subdomains away."""
        for d in range(3):
            if not (self.periodic[d] and self.dims[d] > 1):
                continue
            lo, hi = self.box.lo[d], self.box.hi[d]
            widths = np.diff(np.concatenate([[lo], self.cuts[d], [hi]]))
            if widths.min() < self.min_width - 1e-9 * (hi - lo):
                raise InputError(
                    f"{self.dims[d]} subdomains along the periodic axis {'xyz'[d]} do not fit in the "
                    f"{hi - lo:.4g} m box at the ghost width {self.min_width:.3g} m (2 r_max + skin) each; "
                    "run on fewer ranks, or give run.decomposition without splitting that axis"
                )

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
