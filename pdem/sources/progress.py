"""Progress of a long source (a pour, a large random fill), for the runner's progress lines.

A source's ``generate`` may take minutes (``pluviate`` settles thousands of spheres with pdem
itself). It calls :func:`report` as often as convenient (it is cheap, and a no-op outside a run);
the runner (:mod:`pdem.runner`) turns the latest report into a progress line on rank 0 at most
every few seconds, with a fraction done and an ETA where the source gives a fraction.

Reports go to the receiver installed with :func:`reporting` in the current context (a
:class:`contextvars.ContextVar`), so library calls (``pdem.sources.pluviate`` from a script) print
nothing.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

__all__ = ["report", "reporting"]

#: receives ``(phase, fraction, detail)``; None: nobody listens
_receiver: ContextVar[Callable[[str, float | None, str], None] | None] = ContextVar(
    "pdem_source_progress", default=None
)


def report(phase: str, fraction: float | None = None, detail: str = "") -> None:
    """How far a long source is: ``phase`` names what it does now (e.g. ``"settling"``; the ETA is
    measured within one phase), ``fraction`` in [0, 1] how much of that phase is done (None: not
    known), ``detail`` a few words with numbers (e.g. the simulated time and speed of a pour)."""
    receiver = _receiver.get()
    if receiver is not None:
        receiver(phase, fraction, detail)


@contextmanager
def reporting(receiver: Callable[[str, float | None, str], None] | None) -> Iterator[None]:
    """Send the :func:`report` calls made inside the block to ``receiver`` (None: to nobody)."""
    token = _receiver.set(receiver)
    try:
        yield
    finally:
        _receiver.reset(token)
