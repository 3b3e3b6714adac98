"""Particle sources: regions, size distributions, lattices, random fills and packing files.

Every source returns plain arrays, ``positions`` (n,3) and ``radii`` (n,) float64, in a
deterministic, spatially coherent order (particle ids are assigned in that order).

A deck's ``[[particles]] source = "NAME"`` names a plugin of entry-point group ``pdem.sources``: the
contract is :mod:`pdem.sources.api`, pdem's own sources (built on the functions here) are
:mod:`pdem.sources.builtin`.
"""

from .files import read_spheres, write_spheres_text
from .lattice import fcc, hcp, hex2d, simple_cubic
from .pluviation import pluviate
from .random_fill import random_fill
from .regions import BoxRegion, CylinderRegion, Region, spatial_order
from .sizes import Normal, Single, SizeDistribution, Table, Uniform

__all__ = [
    "Region",
    "BoxRegion",
    "CylinderRegion",
    "spatial_order",
    "SizeDistribution",
    "Single",
    "Uniform",
    "Normal",
    "Table",
    "simple_cubic",
    "fcc",
    "hcp",
    "hex2d",
    "random_fill",
    "pluviate",
    "read_spheres",
    "write_spheres_text",
]
