"""Typed errors of pdem.

Every user-facing failure is one of these. Each message says what happened, where (key path,
particle id, wall name…) and what to do about it. The CLI maps them to exit codes:
0 success, 2 invalid input (:class:`InputError` and subclasses), 3 numerical failure
(:class:`NumericalError`), 1 anything else.
"""

from __future__ import annotations

__all__ = [
    "PdemError",
    "InputError",
    "DeckError",
    "PluginError",
    "GeometryError",
    "NumericalError",
    "InstabilityError",
    "LostParticleError",
    "CheckpointError",
    "OutputError",
]


class PdemError(Exception):
    """Base class of every error pdem raises on purpose."""

    exit_code = 1


class InputError(PdemError, ValueError):
    """Invalid input: a bad parameter, a malformed deck, an impossible setup."""

    exit_code = 2


class DeckError(InputError):
    """A deck failed validation; the message lists every problem with its key path."""


class PluginError(InputError):
    """A plugin is unknown, failed to import, or does not honour its contract."""


class GeometryError(InputError):
    """Particles or walls that cannot be placed as asked (overlaps, outside the domain, …)."""


class NumericalError(PdemError, ArithmeticError):
    """The numerics failed during a run (instability, non-finite values, lost particles)."""

    exit_code = 3


class InstabilityError(NumericalError):
    """The explicit integration became unstable (overlap runaway, non-finite state)."""


class LostParticleError(NumericalError):
    """A particle left the domain or was lost between ranks."""


class CheckpointError(PdemError):
    """A checkpoint cannot be written or read back."""


class OutputError(PdemError):
    """An output cannot be written (existing directory without --overwrite, disk full, …)."""
