"""DEM-C: the cone-complementarity method for rigid grains (see :mod:`pdem.complementarity.method`)."""

from .method import Complementarity, ComplementarityParams

__all__ = ["Complementarity", "ComplementarityParams"]
