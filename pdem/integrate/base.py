"""The integrator contract: one time step of a method, on top of the simulation's public API.

A contact law chooses its integrator (``ContactLaw.make_integrator``): penalty laws get
:class:`~pdem.integrate.verlet.VelocityVerlet`, the complementarity method its own stepper
(:mod:`pdem.complementarity.method`). An integrator is built once, at the first preparation, and
uses only public members of :class:`~pdem.Simulation`:

* ``sim.particles`` (fields, owned rows ``[0, n_owned)`` then ghosts), ``sim.contact_store``
  (pairs, wall candidates, keyed history, wall loads: :mod:`pdem.contact.store`),
  ``sim.coefficients`` (the law's mixed rows), ``sim.dt``, ``sim.g``, ``sim.position_snap``;
* ``sim.advance_walls(dt)``, ``sim.update_neighbours(before_rebuild)``, ``sim.forward_ghosts(positions)``,
  ``sim.compute_forces()`` (contacts + boundary forces), ``sim.external_forces()`` (boundary forces
  only), ``sim.record_wall_loads()``, ``sim.add_work_time(s)``, ``sim.finish_step(flags)``
  (time, step counter, collective error check; under ``Simulation.step(defer_check=True)`` on
  several ranks the check rides on the next step's ``update_neighbours``, so an integrator calls
  that once per step, before any other collective that needs a checked state).

``step`` must end with ``sim.finish_step(flags)``. The boundaries' ``before_step``/``after_step``
hooks run around it (``Simulation.step``); ``apply_forces`` hooks run inside ``compute_forces`` /
``external_forces``.
"""

from __future__ import annotations

from typing import Any, ClassVar

__all__ = ["Integrator"]


class Integrator:
    """Base class of time integrators (see the module docstring)."""

    name = "integrator"
    #: a step whose check is deferred (``Simulation.step(defer_check=True)``) is checked by the next
    #: step's rebuild test, after that step's drift (velocity Verlet): the overlap quoted is the
    #: one found then
    drifts_before_check: ClassVar[bool] = True

    def __init__(self, sim: Any) -> None:
        self.sim = sim

    def prepare(self) -> None:
        """Called after every preparation (the neighbour list is fresh): e.g. the forces that start
        the first step."""

    def step(self) -> None:
        raise NotImplementedError

    def state(self) -> dict[str, Any]:
        """Arrays a checkpoint keeps (keys ``solver/…``)."""
        return {}

    def restore(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state` returned."""

    def stats(self) -> dict[str, float]:
        """Per-step solver statistics (``Simulation.solver_stats``); none for explicit methods."""
        return {}

    def summary(self) -> dict[str, Any] | None:
        """Statistics of the run for summary.json (None: nothing to report)."""
        return None
