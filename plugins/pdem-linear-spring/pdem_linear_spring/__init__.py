"""pdem-linear-spring: a linear spring–dashpot contact law for pdem.

Registered as ``linear_spring`` in the entry-point group ``pdem.contact_laws`` (see pyproject.toml),
so a deck selects it with ``[contact] law = "linear_spring"`` and ``kn = …``. The law lives in
:mod:`pdem_linear_spring.law`; docs/plugins.md in pdem walks through how it is built.
"""

from .law import (
    LinearSpring,
    LinearSpringParams,
    contact_duration,
    force_numpy,
    linear_spring_force,
    stable_dt,
)

__all__ = [
    "LinearSpring",
    "LinearSpringParams",
    "linear_spring_force",
    "force_numpy",
    "stable_dt",
    "contact_duration",
]
__version__ = "0.1.0"
