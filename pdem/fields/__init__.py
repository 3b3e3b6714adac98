"""Coarse-grained continuum fields (density, velocity, stress, strain rate, fabric) of a simulation:
:mod:`pdem.fields.coarse`; documentation in ``docs/fields.md``."""

from .coarse import CoarseGraining, Fields, GaussianKernel, Grid, LucyKernel, TimeAverage, coarse_grain

__all__ = ["GaussianKernel", "LucyKernel", "Grid", "Fields", "CoarseGraining", "TimeAverage", "coarse_grain"]
