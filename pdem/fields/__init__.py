"""Coarse-grained continuum fields (density, velocity, stress, strain rate, fabric) of a simulation:
:mod:`pdem.fields.coarse`; documentation in ``docs/fields.md``."""

from .coarse import (
    CoarseGraining,
    CylindricalGrid,
    Fields,
    GaussianKernel,
    Grid,
    LucyKernel,
    TimeAverage,
    coarse_grain,
    cylindrical_components,
)

__all__ = [
    "GaussianKernel", "LucyKernel", "Grid", "CylindricalGrid", "cylindrical_components", "Fields",
    "CoarseGraining", "TimeAverage", "coarse_grain",
]  # fmt: skip
