"""Output for ParaView and post-processing: HDF5 + XDMF, VTK (.vtu + .pvd), CSV time series.

Writers take :class:`Frame` snapshots (:mod:`pdem.io.frame`) and are registered as entry points
of group ``pdem.writers`` (``hdf5`` → :class:`HDF5Writer`, ``vtk`` → :class:`VTKWriter`). Under MPI
a writer writes gathered frames on rank 0, or (``comm=``, deck ``output.parallel = "per_rank"``)
one piece per rank joined by an index rank 0 writes (:class:`Piece`, :mod:`pdem.io.base`).
"""

from .base import Piece, Writer
from .frame import PARTICLE_FIELDS, Frame, WallState
from .hdf5 import HDF5Writer
from .series import SeriesWriter, read_series
from .vtk import VTKWriter
from .wall_mesh import mesh_area, wall_triangles

__all__ = [
    "Frame",
    "WallState",
    "PARTICLE_FIELDS",
    "Writer",
    "Piece",
    "HDF5Writer",
    "VTKWriter",
    "SeriesWriter",
    "read_series",
    "wall_triangles",
    "mesh_area",
]
