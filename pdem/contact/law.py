"""The contact-law contract.

A **penalty law** (DEM-P) is a class deriving from :class:`ContactLaw`, registered under the entry
point group ``pdem.contact_laws`` (the entry-point name is the value written in a deck). It
declares, as class data:

* ``name`` and ``kind`` (``"penalty"``; a method with its own time step, like complementarity,
  returns its :class:`~pdem.integrate.base.Integrator` from ``make_integrator``);
* ``history_size`` — floats of history per contact (0 for memoryless laws);
* ``list_needs`` — what the method needs of the neighbour list (:class:`ListNeeds`: the storage or
  the id order, an automatic skin, a collision envelope); the default suits a penalty law;
* ``rigid`` — rigid grains (False for penalty laws): contact forces are the method's impulses over
  the step, which may act at a zero gap, and servo boundaries control force rather than velocity;
* ``hertz_from_materials(params)`` (class method) — True when, with these parameters, the normal
  force is Hertz's from the materials' E and ν (default False): ``pdem advise``'s overlap and
  stiffness rules then apply to the scene;
* ``Params`` — a pydantic model of its parameters (validated before anything runs);
* ``pair_kernel`` / ``wall_kernel`` — the generic loops of :mod:`pdem.contact._kernels`
  specialised with the law's ``@njit`` force function.

The specialisation is two small module-level wrappers in the law's own module, so that numba
caches them with the law inlined (numba cannot cache a function that receives another jitted
function as an argument across processes, but it can cache one that calls it as a global)::

    @njit(inline="always")
    def my_force(delta, nx, ny, nz, vx, vy, vz, wx, wy, wz, r_eff, m_eff, i_eff, coef, mi, mj, hist, k, dt):
        # coefficients coef[mi, mj, :], history hist[k, :]
        ...
        return fx, fy, fz, mx, my, mz

    @njit
    def my_pair_kernel(pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair, dt, max_overlap):
        return pair_forces(my_force, pi, pj, hist, x, v, w, r, inv_m, inv_i, mat, coef, f, t, fpair,
                           dt, max_overlap)

    @njit
    def my_wall_kernel(kinds, params, vel, omega, centre, wmat, cstart, cand, hist, x, v, w, r, inv_m,
                       inv_i, mat, coef, f, t, dt, max_overlap, out_idx, out_val, counts):
        return wall_forces(my_force, kinds, params, vel, omega, centre, wmat, cstart, cand, hist, x, v,
                           w, r, inv_m, inv_i, mat, coef, f, t, dt, max_overlap, out_idx, out_val, counts)

(explicit argument lists: with ``*args`` numba falls back to an uncacheable first-class function).

A law never writes a neighbour loop: the generic loops own neighbour iteration, canonical
orientation (lower id first), accumulation order and flags. Each law also ships a plain-Python
twin of its force function (``force_numpy``), used by contract tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict, ValidationError

from ..errors import InputError
from ..materials import MaterialTable

__all__ = ["ContactLaw", "LawParams", "ListNeeds"]


@dataclass(frozen=True)
class ListNeeds:
    """What a contact method needs of the neighbour list (:mod:`pdem.neighbor.list`), as data.

    ``order``: ``"storage"`` — the storage is sorted by cells in space and the pair loop may follow
    it (sums stay in partner-id order per grain); ``"id"`` — storage and pair loops in id order (a
    method whose sweeps run in id order). ``auto_skin``: with no skin given, the skin may follow the
    fastest grain at every rebuild. ``envelope``: the method has a collision envelope
    (``law.envelope(radii)``) that the list reaches beyond touching plus skin."""

    order: str = "storage"
    auto_skin: bool = True
    envelope: bool = False


class LawParams(BaseModel):
    """Base of every law's parameter model: unknown keys are errors. ``resumable``: the keys that
    only steer the numerics (a solver's cap or tolerance), which ``pdem resume --set`` may change;
    every other key describes the scene and is fixed for the run."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    resumable: ClassVar[frozenset[str]] = frozenset()


class ContactLaw:
    """Base class of penalty contact laws. See the module docstring for the contract."""

    name: ClassVar[str] = "abstract"
    kind: ClassVar[str] = "penalty"
    history_size: ClassVar[int] = 0
    list_needs: ClassVar[ListNeeds] = ListNeeds()
    rigid: ClassVar[bool] = False
    n_coef: ClassVar[int] = 1
    Params: ClassVar[type[LawParams]] = LawParams
    pair_kernel: ClassVar[Any] = None
    wall_kernel: ClassVar[Any] = None

    @classmethod
    def hertz_from_materials(cls, params: LawParams) -> bool:
        """Whether the normal force is Hertz's from the materials' E and ν with these parameters
        (``pdem advise``'s overlap and stiffness rules assume it). Default: False."""
        return False

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        # numba dispatchers are descriptors: stored on a class they would bind like methods
        for attr in ("pair_kernel", "wall_kernel"):
            val = cls.__dict__.get(attr)
            if val is not None and not isinstance(val, staticmethod):
                setattr(cls, attr, staticmethod(val))

    def __init__(self, **params: Any) -> None:
        try:
            self.params = self.Params(**params)
        except ValidationError as exc:
            lines = []
            for err in exc.errors():
                loc = ".".join(str(p) for p in err["loc"])
                lines.append(f"law '{self.name}' parameter '{loc}': {err['msg']} (got {err.get('input')!r})")
            raise InputError("\n".join(lines)) from None

    def coefficients(self, materials: MaterialTable) -> np.ndarray:
        """Return the pre-mixed coefficient table, shape (M, M, n_coef), for all material pairs."""
        m = len(materials)
        table = np.zeros((m, m, self.n_coef), dtype=np.float64)
        for a in range(m):
            for b in range(m):
                table[a, b] = self.pair_coefficients(materials, a, b)
        return table

    def pair_coefficients(self, materials: MaterialTable, a: int, b: int) -> np.ndarray:
        raise NotImplementedError

    def instability_advice(self, sim: Any) -> str | None:
        """Optional: for a method that solves for its contacts, what to change when a step left
        overlaps or non-finite values (the solver's settings); None (penalty laws): pdem's own
        diagnosis of the overlap (static or dynamic) is given instead."""
        return None

    def critical_dt(
        self, materials: MaterialTable, radii: np.ndarray, mat_index: np.ndarray, masses: np.ndarray
    ) -> float:
        """Largest time step [s] the law considers stable for these particles."""
        raise NotImplementedError

    def contact_stiffness(
        self,
        coef: np.ndarray,
        mi: np.ndarray,
        mj: np.ndarray,
        r_eff: np.ndarray,
        m_eff: np.ndarray,
        overlap: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Optional, penalty laws: the linearised contacts, for the live step bound
        (:mod:`pdem.contact.stability`). Arrays per touching contact: the coefficient table from
        :meth:`coefficients`, the two material indices, R* [m], m* [kg] and the overlap δ > 0 [m].
        Returns (S_n = dF_n/dδ [N/m], k_t the tangential spring [N/m], 0 where the contact carries
        no tangential force, e.g. μ = 0). A law that does not implement it gets no live bound; its
        runs are unaffected."""
        raise NotImplementedError

    def contact_damping(
        self,
        coef: np.ndarray,
        mi: np.ndarray,
        mj: np.ndarray,
        r_eff: np.ndarray,
        m_eff: np.ndarray,
        overlap: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Optional, penalty laws: the contacts' dashpots, with the arguments of
        :meth:`contact_stiffness`. Returns (c_n = −dF_n/dv_n [N s/m] ≥ 0, the normal dashpot at
        these overlaps; c_t the tangential one, 0 where the contact carries no tangential force).
        Velocity servos (:func:`pdem.contact.stability.servo_gain`) need it: a wall moved at v feels
        c_n v at once, which with a large gain makes the servo chatter. A law that does not implement
        it is taken as undamped there."""
        raise NotImplementedError

    def contact_slip(
        self,
        coef: np.ndarray,
        mi: np.ndarray,
        mj: np.ndarray,
        r_eff: np.ndarray,
        m_eff: np.ndarray,
        overlap: np.ndarray,
        vn: np.ndarray,
        hist: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Optional, penalty laws with a Coulomb cap: which touching contacts slide now, for the live
        step bound (:mod:`pdem.contact.stability`). Arguments of :meth:`contact_stiffness` plus the
        relative normal velocity ``vn`` (the kernel's: (v_j − v_i)·n, negative while approaching) and
        each contact's history row ``hist`` (the law's own layout). Returns (the unit direction of
        the tangential force's spring, shape (k, 3), zero rows for contacts that stick; the slope
        dF_t/dδ of a sliding contact's force, μ S_n for a Coulomb cap μ F_n), or ``None`` (the
        default): every contact counted as sticking, which keeps the bound conservative. A sliding
        contact has no stiffness along its slip, only across it (the cap turns with the spring)."""
        return None

    def slip_slope_ratio(self, coef: np.ndarray) -> float:
        """Optional, with :meth:`contact_slip`: an upper bound of slope / S_n over every material pair
        (the friction coefficient μ for a Coulomb cap). The live bound asks :meth:`contact_slip` only
        about the contacts whose bound sliding could change (those of grains with locked axes, and
        those whose tangential mode does not dominate a coupling this large); ``inf`` (the
        default): about every contact."""
        return math.inf

    def suggested_dt(
        self, materials: MaterialTable, radii: np.ndarray, mat_index: np.ndarray, masses: np.ndarray
    ) -> float:
        """Time step [s] used when the user gives none (a fraction of :meth:`critical_dt`)."""
        return 0.2 * self.critical_dt(materials, radii, mat_index, masses)

    def make_integrator(self, sim: Any):
        """The time integrator of this law's method: velocity Verlet for penalty laws. A method with
        its own step (DEM-C) returns its own :class:`pdem.integrate.base.Integrator`."""
        from ..integrate.verlet import VelocityVerlet

        return VelocityVerlet(sim)

    def describe(self) -> str:
        return f"{self.name}({self.params.model_dump()})"
