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

The DEM-C stepper (:class:`~pdem.complementarity.method.Stepper`) uses, besides those:

* ``sim.comm`` (its collectives: global maxima, exact sums), ``sim.decomposition`` (None serially),
  ``sim.step_count`` (its records), ``sim.max_overlap`` (the assembly's overlap flag);
* the envelope: ``sim.envelope`` (this step's, written by the stepper), ``sim.envelope_base`` (the
  law's ``envelope``: 0.1 r_min or the deck's), ``sim.list_envelope`` and ``sim.skin`` (the
  neighbour list's reach), ``sim.set_list_reach(envelope, force, skin)``;
* ``sim.add_body_forces()`` (the reported forces before the first step: weights),
  ``sim.load_stiffness`` (the boundary loads' stiffness of the step, for its mass scaling; declared by
  boundaries only while ``wants_load_stiffness``), ``pdem.parallel.exchange.forward_values(sim, a)``
  (ghost rows of a per-particle array from their owners);
* walls through ``sim.contact_store`` (packed rows, meshes, wall history and loads,
  ``update_wall(k)``) and free rigid bodies through their motion (``moved_by_load``, ``implicit``,
  ``velocity_now``, ``mass``, ``dof_bits``, ``free_axes``, ``free_velocity(h)``, ``finish(wall, v, h)``).

The other side of the contract, what the simulation and the deck runner call on an integrator:

* ``Simulation._prepare``: built by ``law.make_integrator(sim)`` once, then :meth:`Integrator.restore`
  (the checkpoint's ``solver/…`` arrays, or ``{}``) and :meth:`Integrator.prepare` after every
  preparation;
* ``Simulation.step``: :meth:`Integrator.step`; the rebuild test that carries a deferred check
  reads :attr:`Integrator.drifts_before_check` (how its error is worded);
* ``Simulation.load_stiffness_wanted``: :attr:`Integrator.wants_load_stiffness`;
* ``Simulation.state_dict`` (checkpoints): :meth:`Integrator.state`;
* ``Simulation.solver_stats``: :meth:`Integrator.stats`;
* the deck runner: :meth:`Integrator.stats` and :meth:`Integrator.drain_records` at every series row
  (solver columns, ``solver_<stage>.csv``; none when ``stats()`` is empty) and
  :meth:`Integrator.summary` for summary.json.
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
    #: the boundaries' load stiffness is wanted (``Simulation.add_load_stiffness``; DEM-C's mass
    #: scaling): read through ``Simulation.load_stiffness_wanted``
    wants_load_stiffness: bool = False

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

    def drain_records(self) -> list[tuple]:
        """Per-step records since the last call, oldest first, handed over and forgotten (the deck
        runner writes them to ``solver_<stage>.csv`` at every series row); none for explicit methods.
        DEM-C: (step, iterations, residual, this rank's contact rows). An integrator that keeps such
        records bounds them while nobody calls this (the stepper: its last ``log_keep``)."""
        return []
