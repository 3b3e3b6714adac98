"""pdem — granular dynamics with penalty (DEM-P) and complementarity (DEM-C) contact.

SI units throughout. Start with :class:`pdem.Simulation`; see README.md and ARCHITECTURE.md.
"""

from __future__ import annotations

from . import errors
from .errors import (
    DeckError,
    GeometryError,
    InputError,
    InstabilityError,
    NumericalError,
    PdemError,
    PluginError,
)
from .geometry import shapes
from .materials import Material
from .simulation import Simulation

__version__ = "0.1.0"

__all__ = [
    "Simulation",
    "Material",
    "errors",
    "shapes",
    "PdemError",
    "InputError",
    "DeckError",
    "PluginError",
    "GeometryError",
    "NumericalError",
    "InstabilityError",
    "__version__",
]
