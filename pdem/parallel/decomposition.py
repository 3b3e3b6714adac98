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
    """Subdomains of a Cartesian communicator over the box [lo, hi).

    ``owner(x)`` gives the rank owning each position; ``sub_lo``/``sub_hi`` bound this rank's
    subdomain (±inf on the outer faces); ``neighbours[d] = (lower, upper)`` ranks along axis d
    (``None`` at an outer face).
    """

    def __init__(self, comm, lo, hi, dims=None) -> None:
        from mpi4py import MPI

        lo = np.asarray(lo, dtype=float)
        hi = np.asarray(hi, dtype=float)
        extent = np.maximum(hi - lo, 1e-12)
        self.dims = tuple(int(d) for d in (dims or choose_dims(comm.size, extent)))
        if int(np.prod(self.dims)) != comm.size:
            raise InputError(f"decomposition {self.dims} does not match {comm.size} ranks")
        self.comm = comm.Create_cart(list(self.dims), periods=[False, False, False], reorder=False)
        self.rank = self.comm.Get_rank()
        self.coords = tuple(self.comm.Get_coords(self.rank))
        self.lo, self.hi = lo, lo + extent
        self.cuts = [np.linspace(self.lo[d], self.hi[d], self.dims[d] + 1) for d in range(3)]
        self.sub_lo = np.array(
            [-np.inf if self.coords[d] == 0 else self.cuts[d][self.coords[d]] for d in range(3)]
        )
        self.sub_hi = np.array(
            [
                np.inf if self.coords[d] == self.dims[d] - 1 else self.cuts[d][self.coords[d] + 1]
                for d in range(3)
            ]
        )
        self.neighbours = []
        for d in range(3):
            lower, upper = self.comm.Shift(d, 1)
            self.neighbours.append(
                (None if lower == MPI.PROC_NULL else lower, None if upper == MPI.PROC_NULL else upper)
            )

    def cell_coords(self, x: np.ndarray) -> np.ndarray:
        """Subdomain coordinates (n, 3) of positions ``x``."""
        x = np.atleast_2d(x)
        out = np.empty((x.shape[0], 3), dtype=np.int64)
        for d in range(3):
            out[:, d] = np.searchsorted(self.cuts[d][1:-1], x[:, d], side="right")
        return out

    def owner(self, x: np.ndarray) -> np.ndarray:
        c = self.cell_coords(x)
        return (c[:, 0] * self.dims[1] + c[:, 1]) * self.dims[2] + c[:, 2]

    def owned_mask(self, x: np.ndarray) -> np.ndarray:
        c = self.cell_coords(x)
        return np.all(c == np.asarray(self.coords), axis=1)

    def check_ghost_width(self, width: float) -> None:
        """Ghosts travel one subdomain per swap: interior subdomains must be at least that wide."""
        for d in range(3):
            if self.dims[d] > 2:
                w = (self.hi[d] - self.lo[d]) / self.dims[d]
                if w < width:
                    raise InputError(
                        f"{self.dims[d]} subdomains along axis {'xyz'[d]} are {w:.3g} m wide, "
                        "narrower than the "
                        f"ghost width {width:.3g} m (2 r_max + skin); run on fewer ranks"
                    )
