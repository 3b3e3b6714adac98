"""DEM-C: rigid grains, non-penetration and Coulomb friction as a cone complementarity problem.

Physics reference §3 (Anitescu–Tasora; Chrono NSC). Selected in a deck with
``[contact] law = "complementarity"`` (or ``--set contact.law=complementarity``); registered through
pdem's own entry point like any contact law. One time step h:

1. rebuild the neighbour list if particles moved more than half the skin (as DEM-P), else forward
   the ghosts' state;
2. contacts: every listed pair and wall candidate with gap φ ≤ ``envelope``, normal n, bias
   b = φ/h (or max(φ/h, −``recovery_speed``); the overlaps the run starts from are removed over
   ``recovery_steps`` steps: :meth:`Stepper.recovery_slack`), warm-started from the previous step's
   impulses of the same id pair (of the same wall and particle); restitution: a contact approaching at
   v_n⁻ < −``restitution_threshold`` (start-of-step velocities) and closing within the step
   (b + v_n⁻ < 0) gets b = min(b, e v_n⁻), so it leaves at ≥ e|v_n⁻| (Newton's impact law, as
   Chrono NSC); rolling and spinning friction add, per contact, a rolling impulse (tangent) and a
   spinning impulse (about n), bounded by μ_r R* γ_n and μ_s R* γ_n (DEM-P's torque bound
   μ_r R* F_n) and clamped after the friction cone's projection (Tasora & Anitescu 2013, Chrono);
3. walls advance (their velocity over the step enters the constraints: moving and servo walls);
4. v_free = v + h g; solve the CCP for the impulses γ ∈ K (friction cones), u = Dᵀv⁺ + b,
   −u ∈ K°, γ ⊥ u, with the chosen solver; with ``cone = "corrected"`` (default) u_n is replaced by
   u_n + μ|u_t| (b_n raised by the slip speed of the current iterate, a fixed point), which makes
   the problem Coulomb's law: sliding contacts stay closed;
5. v⁺ = v_free + M⁻¹ D γ, ω likewise; x⁺ = x + h v⁺ (semi-implicit Euler).

Reported forces are impulses / h (particles: contact force + weight; walls: the DEM-P layout, force
on the wall and torque about its reference point), so loads, measurements and output are the same
for both methods.

Solvers (``solver``):

* ``"jacobi"``: projected Jacobi, γ ← Π_K(γ − ω B u), B = 3/trace(N_cc). Under MPI every rank
  updates the contacts of its owned particles (cross-rank contacts on both ranks, identically) and
  forwards its ghosts' velocities once per iteration; the stopping test uses a max (exact), so the
  results are bitwise identical on any rank count.
* ``"apgd"``: accelerated projected gradient descent with adaptive step and restart (Mazhar et al.
  2015). Under MPI every rank iterates its contacts (cross-rank ones on both ranks, identically)
  and forwards its ghosts' velocities after every evaluation of ũ; the dot products and norms that
  steer it are exact global sums, each contact counted once (by the owner of its lower-id grain),
  and its decisions are taken alike on every rank: bitwise identical on any rank count
  (:meth:`Stepper._apgd`).
* ``"gauss_seidel"``: projected Gauss–Seidel / SOR in contact order (pairs by id, then walls);
  serial.

The residual of a step is max_c |γ_c − Π_K(γ_c − B_c u_c)| / B_c [m/s] (with the corrected u_n when
``cone = "corrected"``: then it measures Coulomb's law); iterations stop when it is below
``tolerance`` or at ``max_iterations``, and for APGD with ``load_tolerance`` also when the walls' loads
have settled (:meth:`_ApgdSolve.loads_settled`). Each step's iteration count and residual are recorded
(:meth:`Stepper.drain_records`, through which the deck runner drains them into
``solver_<stage>.csv``; undrained, only the last ``Stepper.log_keep`` are kept); steps that hit the
cap unconverged are counted.

Known behaviours (documented in docs/dem_c.md and measured by tools/dem_c_study.py): collisions
slower than the restitution threshold are perfectly inelastic, with ``cone = "relaxed"`` sliding contacts
separate at a normal speed μ|u_t| (the cone relaxation of Coulomb's law: a sliding sphere hops),
Jacobi needs iterations growing with the number of grains a load must cross, and information moves
at most one contact per iteration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from ..api import ContactLaw, InputError, Integrator, LawParams, ListNeeds, MaterialTable
from ..parallel.comm import all_max, any_rank
from ..parallel.exact import dot_partials_columns, exact_reduce
from . import _kernels as ck

__all__ = ["Complementarity", "ComplementarityParams", "Stepper"]


class ComplementarityParams(LawParams):
    """Parameters of :class:`Complementarity` (DEM-C)."""

    #: solver settings a resume may change (e.g. a tighter solve from a checkpoint)
    resumable: ClassVar[frozenset[str]] = frozenset(
        {"solver", "tolerance", "max_iterations", "check_every", "apgd_start", "relaxation", "scaling",
         "load_mass_scaling", "load_tolerance"}
    )  # fmt: skip

    solver: Literal["jacobi", "apgd", "gauss_seidel"] = Field(
        "jacobi",
        description="CCP solver: 'jacobi' or 'apgd' (both MPI, bitwise identical on any rank count), "
        "'gauss_seidel' (serial)",
    )
    cone: Literal["corrected", "relaxed"] = Field(
        "corrected",
        description="friction law solved: 'corrected' (default) is Coulomb's law: each contact's "
        "normal right-hand side is raised by μ|u_t| (its slip speed, from the current iterate) and "
        "iterated to a fixed point, so a sliding contact stays closed "
        "(u_n = 0); 'relaxed' is the convex Anitescu–Tasora cone problem, in which a sliding contact "
        "separates at u_n = μ|u_t| (a sphere sliding at 5 m/s on a floor with μ = 0.5 leaves it at "
        "1.3 m/s): pdem's behaviour before this option, kept for comparison",
    )
    tolerance: float = Field(
        1e-5, gt=0, description="stop when the projected-gradient residual (a velocity) is below this [m/s]"
    )
    max_iterations: int = Field(200, gt=0, description="iteration cap per step")
    apgd_start: Literal["cold", "warm"] = Field(
        "cold",
        description="where APGD starts each step: 'cold' from zero impulses (default; in flowing scenes "
        "a warm start did not help), 'warm' from the previous step's impulses, contact by contact "
        "(as Jacobi and Gauss–Seidel always do), for quasi-static scenes whose impulses change little "
        "from step to step",
    )
    relaxation: float = Field(
        0.3, gt=0, le=1.0, description="relaxation ω of Jacobi and Gauss–Seidel updates (0 < ω ≤ 1)"
    )
    scaling: Literal["trace", "block"] = Field(
        "block",
        description="how the solvers scale each contact's update: 'block' (default) by the inverse "
        "of the contact's diagonal Delassus block D, normal and tangential rows apart (for spheres D "
        "is diagonal in the contact frame: its tangential entry holds the levers' rotation), with the "
        "cone projection in D's metric so that the fixed point is the same contact problem (APGD: "
        "the same block as its preconditioner); 'trace' steps every row of Jacobi and Gauss–Seidel "
        "by 3/tr(D), which moves the normal impulse 2.7× less per sweep (3/tr(D) = 0.37/D_n between "
        "solid spheres), and runs APGD unpreconditioned (pdem's solvers before this option). The "
        "residual and the stopping rule are the same for both",
    )
    check_every: int = Field(
        1,
        ge=1,
        le=1000,
        description="Jacobi and APGD: measure the residual (and test convergence) on every k-th "
        "iteration only, the first included (APGD: and the last, at the cap); the others skip the "
        "second cone projection per contact and, for Jacobi under MPI, the global maximum. A solve may "
        "then run up to k − 1 iterations past convergence. Jacobi's steps at the cap run the same "
        "sweeps; APGD returns its best checked iterate, so its results change. 1 (default): every "
        "iteration",
    )
    load_tolerance: float | None = Field(
        default=None,
        gt=0,
        lt=1,
        description="APGD only: also stop a solve when the loads on the walls (each wall's summed "
        "contact force, the quantity a boundary measures) have settled: measured every 10 iterations "
        "(on checked ones), the largest change of a wall's load over 10 iterations is at most this "
        "fraction of the largest wall load twice in a row. The grains' residual may then still be above "
        "``tolerance``; such steps are counted as ``load_stopped_steps``, not as unconverged. "
        "Default: off (stop on the residual or the cap only)",
    )
    load_mass_scaling: bool = Field(
        True,
        description="grains whose boundary loads are stiff (a membrane's: Simulation.add_load_stiffness, "
        "k [N/m]) get the mass max(m, h² k) in the step's solve, so that the explicit load stays stable "
        "(h² k/m ≤ 1) at DEM-C's large steps; their static loads and contact forces are unchanged, their "
        "motion slower (mass scaling, docs/dem_c.md 'Stiff boundary loads'). false: the true masses "
        "(surface grains of the triaxial membrane then run away at the automatic step)",
    )
    envelope: float | None = Field(
        default=None,
        ge=0,
        description="collision envelope [m]: contacts enter the problem when their gap is below it; "
        "default: automatic, at every step the larger of 0.1 of the smallest radius and 2.5 × the "
        "fastest grain's travel per step (a fixed envelope narrower than the travel lets grains overlap)",
    )
    recovery_speed: float | None = Field(
        default=None,
        gt=0,
        description="cap on the speed [m/s] at which penetration is removed (b = max(φ/h, −v)); "
        "default: no cap",
    )
    recovery_steps: int = Field(
        50,
        ge=1,
        le=100000,
        description="the overlaps of the packing the run starts from (a bed poured with soft grains) "
        "are removed over this many steps: the overlap allowed falls from their deepest φ₀ to zero, a "
        "contact within the allowance is held and a deeper one pushed out to it, so the deepest parts "
        "at φ₀ / (recovery_steps h) and the bed starts at rest instead of being thrown apart (summary."
        "json: solver.initial_overlap, initial_recovery_speed). 1: removed within the first step",
    )
    envelope_rule: Literal["contact", "global"] = Field(
        "contact",
        description="automatic envelope: 'contact' (default) gives each contact its own, 2.5 × the "
        "step × the larger speed bound of its two bodies (|v| + |g| h; a wall: its surface's speed), at "
        "least 0.1 r_min, so grains in free fall do not widen every contact's envelope; 'global' gives "
        "every contact the one for the fastest body (pdem's rule before this option). Both only "
        "apply when envelope is not given",
    )
    max_travel: float = Field(
        0.2,
        gt=0,
        description="automatic step: a grain at reference_speed travels this fraction of the smallest "
        "radius per step (used when [run] dt is not given)",
    )
    reference_speed: float = Field(1.0, gt=0, description="speed [m/s] of the automatic step rule")
    restitution_threshold: float = Field(
        0.1,
        ge=0,
        description="restitution applies to contacts approaching faster than this [m/s] at the start "
        "of the step (and closing within it): their normal velocity after the step is at least "
        "e × the approach speed, e the pair's material restitution (Newton's impact law); slower "
        "contacts, among them the persistent contacts of packings, are perfectly inelastic. "
        "Default 0.1 m/s: above the velocity noise of unconverged solves in dense packings, below "
        "the impact speed of a grain falling half a millimetre",
    )


class Complementarity(ContactLaw):
    """DEM-C (see module docstring). Coefficient row: ``[μ, e, μ_r, μ_s]`` per material pair."""

    name = "complementarity"
    kind = "complementarity"
    # sweeps in id order, a fixed skin, the collision envelope in the list's reach
    list_needs = ListNeeds(order="id", auto_skin=False, envelope=True)
    rigid = True
    history_size = 8  # last step's impulses (γ_n, γ_t, ρ, σ) for the warm start
    n_coef = 4
    Params = ComplementarityParams

    def instability_advice(self, sim) -> str:
        return (
            f"complementarity solver '{self.params.solver}' with max_iterations = "
            f"{self.params.max_iterations}: the contact problem was not solved well enough; reduce dt, "
            "raise contact.complementarity.max_iterations or lower contact.complementarity.tolerance, "
            "or check the initial overlaps and prescribed velocities"
        )

    def pair_coefficients(self, materials: MaterialTable, a: int, b: int) -> np.ndarray:
        keys = ("friction", "restitution", "rolling_friction", "spinning_friction")
        return np.array([materials.mixed(a, b, k) for k in keys])

    def critical_dt(self, materials, radii, mat_index, masses) -> float:
        """Rigid contact has no stiffness limit: the step is bounded only by accuracy."""
        return math.inf

    def suggested_dt(self, materials, radii, mat_index, masses) -> float:
        if len(radii) == 0:
            return math.inf
        p = self.params
        return p.max_travel * float(np.min(radii)) / p.reference_speed

    def envelope(self, radii) -> float:
        if self.params.envelope is not None:
            return float(self.params.envelope)
        return 0.1 * float(np.min(radii)) if len(radii) else 0.0

    def make_integrator(self, sim) -> Stepper:
        if self.params.solver == "gauss_seidel" and sim.comm.size > 1:
            raise InputError(
                "contact.solver = 'gauss_seidel' runs on one rank only (it sweeps the contacts in one "
                "sequence across the whole packing, so its results would depend on the partition); use "
                "solver = 'jacobi' or 'apgd' under MPI (both bitwise identical on any rank count), or "
                "run serially"
            )
        return Stepper(sim, self)


@dataclass(eq=False)
class _StepProblem:
    """What one DEM-C step carries from phase to phase (:meth:`Stepper.step`): the step's sizes, the
    envelope rule, the free velocities, the impulse accumulators and the solve's outcome."""

    h: float  # the step [s]
    env: float  # this step's envelope (the bound of the per-contact ones) [m]
    v_rec: float  # recovery speed cap (0: none) [m/s]
    slack: float  # initial overlap still allowed at the step's end (0: none) [m]
    v_th: float  # restitution threshold [m/s]
    n_tot: int  # particle rows (owned, then ghosts)
    n_own: int  # owned particle rows
    nb: int  # free rigid-body walls (rows after the particles')
    npairs: int  # listed pairs
    walls: bool  # any wall
    nw: int  # wall candidates
    w_params: np.ndarray | None = None  # the walls' geometry at the start of the step
    external: Any = False  # boundary forces were applied (sim.external_forces)
    scaled: np.ndarray | None = None  # owned rows whose masses are scaled (_scale_masses)
    per_contact: bool = False  # the per-contact envelope rule
    gh: float = 0.0  # |g| h [m/s]
    spd: np.ndarray | None = None  # speed bounds of the bodies (per-contact rule), else empty
    env_base: float = 0.0  # the per-contact envelope's floor (or the global envelope) [m]
    env_factor: float = 0.0  # its factor on the speed bound (2.5 h; 0 without the per-contact rule)
    v_start: np.ndarray | None = None  # start-of-step velocities (per-contact rule: a re-solve's start)
    w_start: np.ndarray | None = None
    n_pair: int = 0  # contact rows of pairs
    nc: int = 0  # contact rows (pairs, then walls)
    flags: Any = 0  # the kernels' flags (sim.finish_step)
    v_free: np.ndarray | None = None  # free velocities (bodies' rows included)
    w_free: np.ndarray | None = None
    f_ext: np.ndarray | None = None  # the boundary forces and torques (added back to the reported)
    t_ext: np.ndarray | None = None
    P: np.ndarray | None = None  # accumulated impulses per body
    L: np.ndarray | None = None  # accumulated angular impulses per body
    it: int = 0  # solver iterations (re-solves included)
    res: float = 0.0  # the final residual [m/s]


class Stepper(Integrator):
    """The DEM-C time step for one :class:`~pdem.Simulation` (holds the solver's work arrays). It uses
    the simulation's public integrator API only (:mod:`pdem.integrate.base`)."""

    name = "complementarity"
    drifts_before_check = False  # its deferred check comes before any drift of the next step
    #: records kept while nobody drains them (:meth:`drain_records`): the last this many steps'
    log_keep: int = 10_000

    @property
    def p(self) -> ComplementarityParams:
        """The law's parameters now (a stage may change its solver settings: ``[stages.contact]``)."""
        return self.law.params

    def __init__(self, sim, law: Complementarity) -> None:
        super().__init__(sim)
        self.law = law
        self.n_unconverged = 0
        self.n_stalls = 0  # APGD solves stopped by a line search that could not accept a step
        self.n_load_stops = 0  # APGD solves stopped because the walls' loads settled (load_tolerance)
        self.load_stopped = False  # the last solve did
        self.n_resolves = 0  # steps solved again because the per-contact envelope missed a contact
        # steps after which a contact left out by a fixed or global envelope overlapped (reported,
        # not solved again: that envelope is the user's choice)
        self.n_missed_steps = 0
        self.n_short_steps = 0  # steps whose fastest grain could close more than a fixed envelope
        # mass scaling of grains under stiff boundary loads (load_mass_scaling): steps that scaled,
        # the largest m_eff / m of the run and of the last step (global maxima)
        self.n_scaled_steps = 0
        self.max_mass_ratio = 1.0
        self.last_mass_ratio = 1.0
        # the deepest grain-pair overlap of the packing the run starts from (e.g. left by a soft-grain
        # preparation): the first step removes it at overlap / h, or at recovery_speed if capped
        self.initial_overlap = 0.0
        self.n_steps = 0
        self.total_iterations = 0
        self.max_residual = 0.0
        self.last_iterations = 0
        self.last_residual = 0.0
        self.last_contacts = 0  # the last step's contact rows (this rank's)
        # the steps' records (step, iterations, residual, contacts) not yet drained: see drain_records
        self.log: list[tuple[int, int, float, int]] = []
        self._drained = False  # drain_records has been called: keep every record until the next call
        self._cap = 0
        self._base_envelope = sim.envelope_base  # 0.1 r_min or the deck's value
        self._bodies: list = []
        self._apgd_work = np.empty(0)  # APGD's work arrays (see _apgd)
        # serial Jacobi sweeps in one kernel call (False: the Python loop, which forwards ghosts; tests)
        self.fused_sweeps = True
        self.corrected = self.p.cone == "corrected"

    def prepare(self) -> None:
        """The reported forces before the first step: weights only (plus boundary forces)."""
        sim = self.sim
        sim.external_forces()
        sim.add_body_forces()

    # ------------------------------------------------------------------ work arrays
    # a nominal cost model of a step [s] (kernel costs of docs/dem_c.md; only ratios between ranks matter)
    _ROW_ITERATION_S = 1.0e-7  # a contact row per solver iteration (the APGD iteration's ~100 ns)
    _BODY_ITERATION_S = 2.0e-8  # a body per iteration: accumulation, velocities, ghost forwarding
    _LISTED_S = 3.0e-8  # a listed pair or wall candidate per step: assembly, envelope, history

    def _modelled_work(self, nc: int, iterations: int, bodies: int, listed: int) -> float:
        """This rank's solver work in the step [s, nominal], for the load balancer (deterministic)."""
        return (
            iterations * (nc * self._ROW_ITERATION_S + bodies * self._BODY_ITERATION_S)
            + listed * self._LISTED_S
        )

    def _row_width(self) -> int:
        """Impulses per contact row: 8 (γ_n, γ_t, ρ, σ) when some material pair has rolling or
        spinning friction, else 4 (γ_n, γ_t). Without rolling rows the last four columns would be
        zeros read and written by every kernel (APGD's projected step: 18.6 against 11.9 ns per row;
        on the hopper no difference above the noise, the other kernels being compute-bound). The same
        for every rank (the materials are global), and the arithmetic of the first four columns is
        the same either way (the same bits)."""
        coef = self.sim.coefficients
        return 8 if coef.size and bool(np.any(coef[..., 2:4] > 0.0)) else 4

    def _reserve(self, nc: int) -> None:
        width = self._row_width()
        if nc <= self._cap and self._cap > 0 and self.gam.shape[1] == width:
            return
        cap = max(int(nc * 1.3) + 64, 256, self._cap)
        self.cb = np.empty((cap, 2), dtype=np.int64)
        self.cn = np.empty((cap, 3))
        self.ca = np.empty((cap, 2))
        self.cvw = np.empty((cap, 6))
        self.cbias = np.empty(cap)
        self.cmu = np.empty(cap)
        self.cscale = np.empty(cap)
        self.croll = np.empty((cap, 4))
        self.gam = np.empty((cap, width))
        self.csrc = np.empty((cap, 3), dtype=np.int64)
        self.cpt = np.zeros((cap, 3))
        self._cap = cap

    # ------------------------------------------------------------------ one step
    def step(self) -> None:
        """One time step h (the module docstring's 1–5), in phases that share a :class:`_StepProblem`:

        1. :meth:`_update_list`: this step's envelope, the neighbour list's reach, the list (rebuilt,
           or its ghosts forwarded);
        2. :meth:`_setup_bodies`: the free rigid-body walls' rows, after the grains';
        3. :meth:`_begin_problem`: contact rows reserved, the walls' start-of-step geometry, walls
           advanced, boundary forces and mass scaling, the envelope rule;
        4. :meth:`_assemble`: the contact rows (normals, biases, warm start); the run's first step
           also measures the initial overlap;
        5. :meth:`_predict`: the free velocities v + h g (+ h f_ext / m);
        6. :meth:`_solve_step`: the CCP (:meth:`_solve`), solved again when the per-contact envelope
           missed a contact (:meth:`_resolve_missed`), else the missed contacts counted
           (:meth:`_count_missed`);
        7. :meth:`_advance`: history, reported forces, x⁺ = x + h v⁺, rigid bodies;
        8. :meth:`_record_step`: the modelled work, the counters and the step's record; then
           ``sim.finish_step``."""
        sim = self.sim
        self._update_list()
        if self.n_steps == 0:
            cs = sim.contact_store
            p = sim.particles
            self.initial_overlap = all_max(sim.comm, _deepest_overlap(p.x, p.r, cs.pi, cs.pj))
        self._setup_bodies()
        sp = self._begin_problem()
        sp.n_pair, sp.nc, sp.flags = self._assemble(sp, sp.spd)
        self._predict(sp)
        self._solve_step(sp)
        self._advance(sp)
        self._record_step(sp)
        sim.finish_step(sp.flags)

    def _update_list(self) -> None:
        """This step's envelope, a function of the state alone (not of when the list was built), so
        results do not depend on rebuild timing, checkpoints or the partition; the list's reach
        widened to it if needed, and the neighbour list updated (rebuilt with a reach narrowed to the
        grains' speed, or its ghosts forwarded)."""
        sim = self.sim
        need = self._needed_envelope()
        sim.envelope = need
        if need > sim.list_envelope:
            sim.set_list_reach(1.25 * need)

        def narrow() -> None:
            # at a rebuild the list's reach follows the grains' speed down again (fewer pairs), with
            # room for the envelope to grow by a quarter before it forces a rebuild, and the skin
            # for the grains' travel. Neither when the fastest grain travels more than half the skin
            # per step (need = 2.5 × its travel): the skin then makes the next step rebuild anyway,
            # so the list is built without skin (the next step rebuilds, as it would have) and holds
            # just the pairs within this step's envelope. The DEM-C hopper's discharge rebuilds at
            # every step; its list held half again as many pairs for nothing
            fast = 0.8 * need > sim.skin
            sim.set_list_reach(
                max((1.0 if fast else 1.25) * need, self._base_envelope), force=False,
                skin=0.0 if fast else sim.skin,
            )  # fmt: skip

        sim.update_neighbours(before_rebuild=narrow)

    def _setup_bodies(self) -> None:
        """The step's bodies: ``self.V, W, IM, II, DOF`` are the particles' arrays, or, when walls are
        free rigid bodies (solved with the grains), padded copies with the bodies' rows after the
        particles'."""
        p = self.sim.particles
        bodies = self._bodies = self._free_bodies()
        nb = len(bodies)
        if nb:  # rigid-body walls are solved with the grains, in rows after them
            p.reserve(p.n + nb)
            n = p.n
            self.V, self.W = p.padded("v", nb), p.padded("w", nb)
            self.IM, self.II, self.DOF = p.padded("inv_m", nb), p.padded("inv_i", nb), p.padded("dof", nb)
            for j, (_k, wall) in enumerate(bodies):
                self.V[n + j] = wall.motion.velocity_now
                self.W[n + j] = 0.0
                self.IM[n + j] = 1.0 / wall.motion.mass
                self.II[n + j] = 0.0
                self.DOF[n + j] = wall.motion.dof_bits
        else:
            self.V, self.W, self.IM, self.II, self.DOF = p.v, p.w, p.inv_m, p.inv_i, p.dof

    def _begin_problem(self) -> _StepProblem:
        """Everything the contact rows are assembled from: the rows reserved, the walls' geometry at
        the start of the step, then the walls advanced (their velocity over the step enters the
        constraints), the boundary forces (and the mass scaling they may call for) and the envelope
        rule's speed bounds."""
        sim = self.sim
        p = sim.particles
        h = sim.dt
        cs = sim.contact_store
        nb = len(self._bodies)
        env = sim.envelope
        n_tot = p.n
        walls = bool(cs.walls)
        sp = _StepProblem(
            h=h, env=env, v_rec=self.recovery_cap(), slack=self.recovery_slack(),
            v_th=self.p.restitution_threshold, n_tot=n_tot,
            n_own=p.n_owned, nb=nb, npairs=cs.pi.shape[0], walls=walls,
            nw=int(cs.cstart[-1]) if walls else 0,
        )  # fmt: skip
        self._reserve(sp.npairs + sp.nw)
        if walls and cs.walls_changed:
            cs.pack_walls()
        # geometry at the start of the step (walls where they are now) ...
        sp.w_params = cs.params.copy() if walls else None
        # ... with the velocity the walls move at during the step
        sim.advance_walls(h)
        # external (boundary) forces: impulses h f_ext enter the free velocity; the reported force
        # below adds them back. Taken before the rows are assembled: a boundary that declares its
        # loads' stiffness makes the step scale those grains' masses (_scale_masses), which the
        # rows' effective masses read
        sp.external = sim.external_forces()
        sp.scaled = self._scale_masses(h, sp.external)
        # self.V: the velocities at the start of the step (restitution's pre-impact velocities)
        sp.per_contact = self.p.envelope is None and self.p.envelope_rule == "contact"
        sp.gh = float(np.linalg.norm(sim.g)) * h
        if sp.per_contact:
            sp.spd = ck.speed_bounds(self.V, n_tot + nb, sp.gh)
            sp.env_base, sp.env_factor = self._base_envelope, 2.5 * h
            sp.v_start, sp.w_start = self.V.copy(), self.W.copy()
        else:
            sp.spd, sp.env_base, sp.env_factor = np.zeros(0), env, 0.0
        if walls:
            cs.filter_meshes(p.x, p.r, p.inv_m, env)
        return sp

    def _assemble(self, sp: _StepProblem, spd: np.ndarray) -> tuple[int, int, int]:
        """The contact rows: listed pairs, then wall contacts, within their envelopes (speed bounds
        ``spd``). Returns (pair rows, all rows, the kernels' flags)."""
        sim = self.sim
        p = sim.particles
        cs = sim.contact_store
        h, env, v_rec, slack, v_th = sp.h, sp.env, sp.v_rec, sp.slack, sp.v_th
        n_pair, flags = ck.assemble_pairs(
            cs.pi, cs.pj, cs.hist, p.x, self.V, p.r, self.IM, p.inv_i, p.mat, sim.coefficients, h, env,
            v_rec, slack, v_th, sim.max_overlap, self.cb, self.cn, self.ca, self.cvw, self.cbias, self.cmu,
            self.cscale, self.croll, self.gam, self.csrc, spd, sp.env_base, sp.env_factor, self._pair_work(),
        )  # fmt: skip
        nc = n_pair
        if sp.walls:
            nc, wflags = ck.assemble_walls(
                cs.kinds, sp.w_params, cs.vel, cs.omega, cs.centre, cs.wmat, cs.cstart, cs.cand_step,
                cs.wall_hist, p.x, self.V, p.r, self.IM, p.inv_i, p.mat, sim.coefficients, h, env, v_rec,
                slack, v_th, sim.max_overlap, n_pair, self.cb, self.cn, self.ca, self.cvw, self.cbias,
                self.cmu, self.cscale, self.croll, self.gam, self.csrc, self.cpt, *self._body_rows(sp.n_tot),
                spd, sp.env_base, sp.env_factor,
            )  # fmt: skip
            flags |= wflags
        return n_pair, nc, flags

    def _predict(self, sp: _StepProblem) -> None:
        """The free velocities v_free = v + h g (a scaled grain's gain from its true weight; the rigid
        bodies' from their loads) plus the boundary forces' impulses, and the impulse accumulators."""
        sim = self.sim
        p = sim.particles
        h, n_tot, n_own = sp.h, sp.n_tot, sp.n_own
        g = sim.g
        v_free = sp.v_free = np.empty((n_tot + sp.nb, 3))
        w_free = sp.w_free = np.zeros((n_tot + sp.nb, 3))
        for j, (_k, wall) in enumerate(self._bodies):
            v_free[n_tot + j] = wall.motion.free_velocity(h)
        ck.free_velocities(p.v, p.w, p.motion, p.dof, g[0], g[1], g[2], h, n_own, v_free, w_free)
        scaled = sp.scaled
        if scaled is not None:  # a heavier grain gains m g h / m_eff from its (true) weight
            ratio = (p.mass[scaled] * self.IM[scaled])[:, None]
            v_free[scaled] = p.v[scaled] + (v_free[scaled] - p.v[scaled]) * ratio
        if sp.external:
            ck.add_external_impulses(v_free, w_free, p.f, p.t, self.IM, p.inv_i, p.motion, p.dof, h, n_own)
            sp.f_ext, sp.t_ext = p.f[:n_own].copy(), p.t[:n_own].copy()
        sp.P = np.empty((n_tot + sp.nb, 3))
        sp.L = np.empty((n_tot + sp.nb, 3))

    def _solve_step(self, sp: _StepProblem) -> None:
        """The CCP with the chosen solver; then the envelope's check: with the per-contact rule a
        contact it missed makes the step solve again (:meth:`_resolve_missed`), with a fixed or
        global envelope the missed contacts are counted (:meth:`_count_missed`). Every solver ends
        with the velocities (and P, L) of its final impulses, accumulated in contact order
        (deterministic)."""
        sp.it, sp.res = self._solve(sp.nc, sp.v_free, sp.w_free, sp.P, sp.L)
        if sp.per_contact and math.isfinite(sp.res):
            self._resolve_missed(sp)
        elif math.isfinite(sp.res):
            self._count_missed(sp)

    def _resolve_missed(self, sp: _StepProblem) -> None:
        """A grain pushed during the step by its neighbours' impulses can close a gap its own start
        speed did not cover: if any pair or wall contact outside the problem overlaps at the end of
        the step, solve again with every body's speed bound raised to its solved speed, and if that
        misses one too, with the global envelope (the first rule's). One collective decision per
        attempt."""
        sim = self.sim
        p = sim.particles
        cs = sim.contact_store
        h, env, n_tot, nb = sp.h, sp.env, sp.n_tot, sp.nb
        spd = sp.spd
        wb = self._body_rows(n_tot)[0] if sp.walls else np.zeros(0, dtype=np.int64)
        for attempt in range(2):
            missed = ck.missed_pairs(cs.pi, cs.pj, p.x, self.V, p.r, p.inv_m, h, env, spd, sp.env_base,
                                     sp.env_factor)  # fmt: skip
            if sp.walls:
                missed += ck.missed_walls(
                    cs.kinds, sp.w_params, cs.params, cs.vel, cs.omega, cs.centre, cs.cstart, cs.cand_step,
                    p.x, self.V, p.r, p.inv_m, h, env, wb, spd, sp.env_base, sp.env_factor,
                )  # fmt: skip
            if not any_rank(sim.comm, missed > 0):
                break
            self.n_resolves += 1
            if attempt == 0:
                spd = np.maximum(spd, ck.speed_bounds(self.V, n_tot + nb, sp.gh))
            else:
                spd = np.full_like(spd, np.inf)  # every contact at the global envelope
            self.V[:] = sp.v_start  # the start-of-step velocities (restitution reads them)
            self.W[:] = sp.w_start
            sp.n_pair, sp.nc, flags2 = self._assemble(sp, spd)
            sp.flags |= flags2
            it2, sp.res = self._solve(sp.nc, sp.v_free, sp.w_free, sp.P, sp.L)
            sp.it += it2

    def _count_missed(self, sp: _StepProblem) -> None:
        """A fixed or global envelope: the contacts it left out that overlap at the end of the step
        (grains too fast for it: tunnelling) are counted, one collective decision per step; and the
        envelope against the largest closing distance of the step, 2 h max|v⁺| (pairs the neighbour
        list never held can pass through each other unseen when it is larger)."""
        sim = self.sim
        p = sim.particles
        cs = sim.contact_store
        h, env, n_tot, nb = sp.h, sp.env, sp.n_tot, sp.nb
        wb = self._body_rows(n_tot)[0] if sp.walls else np.zeros(0, dtype=np.int64)
        zero = np.zeros(n_tot + nb)
        missed = ck.swept_missed_pairs(cs.pi, cs.pj, p.x, self.V, p.r, p.inv_m, h, env)
        if sp.walls:
            missed += ck.missed_walls(
                cs.kinds, sp.w_params, cs.params, cs.vel, cs.omega, cs.centre, cs.cstart, cs.cand_step,
                p.x, self.V, p.r, p.inv_m, h, env, wb, zero, env, 0.0,
            )  # fmt: skip
        if any_rank(sim.comm, missed > 0):
            self.n_missed_steps += 1
        fastest = float(np.max(ck.speed_bounds(self.V, n_tot + nb, 0.0))) if n_tot + nb else 0.0
        if 2.0 * h * all_max(sim.comm, fastest) > env:
            self.n_short_steps += 1

    def _advance(self, sp: _StepProblem) -> None:
        """Apply the solved impulses: the warm-start history, the reported forces (impulses / h; the
        walls' loads), v⁺ and x⁺ = x + h v⁺ of the grains (boundary forces added back to the reported
        ones), and the rigid bodies moved by semi-implicit Euler, as the grains."""
        sim = self.sim
        p = sim.particles
        cs = sim.contact_store
        h, nc, n_pair, n_own, n_tot = sp.h, sp.nc, sp.n_pair, sp.n_own, sp.n_tot
        g = sim.g
        ck.store_history(self.gam, self.csrc, nc, n_pair, cs.hist, cs.wall_hist)
        if cs.force.shape[0] != sp.npairs:
            cs.force = np.zeros((sp.npairs, 3))
        ck.contact_forces(
            self.gam, self.cn, self.cpt, self.croll, self.csrc, nc, n_pair, 1.0 / h, cs.force, cs.out_idx,
            cs.out_val, cs.counts, cs.cstart,
        )  # fmt: skip
        sim.record_wall_loads()
        sp.flags |= ck.finish_step(
            p.x, p.v, p.w, p.f, p.t, sp.P, sp.L, p.mass, p.motion, g[0], g[1], g[2], 1.0 / h, h, n_own,
            sim.position_snap,
        )  # fmt: skip
        if sp.external:
            p.f[:n_own] += sp.f_ext
            p.t[:n_own] += sp.t_ext
        for j, (k, wall) in enumerate(self._bodies):  # semi-implicit Euler, as the grains
            wall.motion.finish(wall, self.V[n_tot + j].copy(), h)
            cs.update_wall(k)  # the next step's contacts start from where the body is now
        if sim.decomposition is not None:  # ghosts (other ranks' grains, periodic images) where their
            # owners now are: what is read between steps (branch vectors, snapshots) is then the same
            # on any rank count; the next step's list update forwards or rebuilds from the same bits
            sim.forward_ghosts()

    def _record_step(self, sp: _StepProblem) -> None:
        """The step's bookkeeping: the load balancer's measure of this rank's work, the solver's
        counters and the step's record (:meth:`drain_records`)."""
        # the load balancer's measure of this rank's work: modelled, not timed. The step's time includes
        # the waits in its collectives (every iteration has one or two), where the emptier rank waits
        # for the busier, so both look equally busy and the cut planes never move: the 2-rank DEM-C
        # hopper stayed at a work imbalance (max/mean) of 1.8-2.0 through 653 rebalances
        sim = self.sim
        it, res, nc = sp.it, sp.res, sp.nc
        sim.add_work_time(self._modelled_work(nc, it, sp.n_tot + sp.nb, sp.npairs + sp.nw))
        if self.load_stopped:
            self.n_load_stops += 1
        elif not res <= self.p.tolerance:
            self.n_unconverged += 1
        self.load_stopped = False
        self.last_iterations = it
        self.last_residual = res
        self.last_contacts = nc
        self.n_steps += 1
        self.total_iterations += it
        self.max_residual = max(self.max_residual, res)
        self._record((sim.step_count + 1, it, res, nc))  # contacts: this rank's

    # ------------------------------------------------------------------ the steps' records
    def _record(self, record: tuple[int, int, float, int]) -> None:
        """Keep a step's record: every one while a reader drains them (:meth:`drain_records` has been
        called), else the last ``log_keep`` (the list is trimmed in blocks, so it never holds more
        than 5/4 of them)."""
        log = self.log
        log.append(record)
        if not self._drained and len(log) > self.log_keep + self.log_keep // 4:
            del log[: len(log) - self.log_keep]

    def drain_records(self) -> list[tuple[int, int, float, int]]:
        """The steps' records (step, iterations, residual, this rank's contacts) since the last drain,
        oldest first, handed over and forgotten. The first call makes the stepper keep every record
        from then on until the next call (a reader that drains, as the deck runner does at every
        series row, bounds the log by its cadence); before it, only the last ``log_keep``
        records are kept (``Simulation.run`` for a million steps does not grow the log)."""
        self._drained = True
        records, self.log = self.log, []
        return records

    @property
    def wants_load_stiffness(self) -> bool:
        """Boundaries' load stiffness is used (Simulation.load_stiffness_wanted)."""
        return bool(self.p.load_mass_scaling)

    def _scale_masses(self, h: float, external: bool) -> np.ndarray | None:
        """Mass scaling for stiff boundary loads (``load_mass_scaling``). A load F_i(x) that a
        boundary declares with stiffness k_i (:meth:`Simulation.add_load_stiffness`) enters the free
        velocity explicitly, v += h F/m, which is stable only while h² k/m stays below ~4; a grain
        on a softening load (negative k) drifts off by a factor exp(h sqrt(|k|/m)) a step. The
        triaxial membrane's surface grains reach h² k/m ≈ 20 at DEM-C's automatic step (docs/dem_c.md).
        Such a grain gets the mass m_eff = max(m, h² k) for the whole step (its free velocity, its
        rows' effective masses, its velocity update): h² k/m_eff ≤ 1. Loads held by contacts are
        unchanged (an impulse balances h F whatever the mass), only the grain's own acceleration is
        slower. Grains with h² k ≤ m keep their masses exactly.

        Returns the owned rows scaled (``self.IM`` then holds the scaled inverse masses, ghosts' from
        their owners), or ``None``. Collective: one maximum per step with boundary forces."""
        self.last_mass_ratio = 1.0
        if not external or not self.p.load_mass_scaling:
            return None
        sim = self.sim
        p = sim.particles
        k = sim.load_stiffness
        rows = np.zeros(0, dtype=np.int64)
        hk = np.zeros(0)
        if k is not None:
            hk_all = h * h * k
            rows = np.flatnonzero((hk_all > p.mass[: k.shape[0]]) & (p.inv_m[: k.shape[0]] > 0.0))
            hk = hk_all[rows]
        local = float(np.max(hk * p.inv_m[rows])) if rows.size else 1.0
        ratio = all_max(sim.comm, local)
        if ratio <= 1.0:
            return None
        im = np.array(self.IM, copy=True)  # owned, ghosts and free rigid bodies
        im[rows] = 1.0 / hk
        from ..parallel.exchange import forward_values

        forward_values(sim, im)  # ghost copies take their owners' masses (the same on any rank count)
        self.IM = im
        self.last_mass_ratio = ratio
        self.max_mass_ratio = max(self.max_mass_ratio, ratio)
        self.n_scaled_steps += 1
        return rows

    def _solve(self, nc, v_free, w_free, P, L) -> tuple[int, float]:
        solver = self.p.solver
        if solver == "jacobi":
            return self._jacobi(nc, v_free, w_free, P, L)
        if solver == "gauss_seidel":
            return self._gauss_seidel(nc, v_free, w_free, P, L)
        return self._apgd(nc, v_free, w_free, P, L)

    # ------------------------------------------------------------------ rigid-body walls
    def _free_bodies(self) -> list:
        """Active walls that are free rigid bodies (``RigidBody``): solved with the grains."""
        out = []
        for k, wall in enumerate(self.sim.contact_store.walls):
            if wall.active and getattr(wall.motion, "moved_by_load", False):
                wall.motion.implicit = True  # moved after the solve, not by advance_walls
                out.append((k, wall))
            elif getattr(wall.motion, "implicit", False):
                wall.motion.implicit = False  # off (or held): advance_walls moves it, as under DEM-P
        return out

    def _body_rows(self, n_tot: int) -> tuple[np.ndarray, np.ndarray]:
        """Per wall row: the index of its body in the velocity arrays (−1: an immovable wall) and
        the body's inverse mass."""
        cs = self.sim.contact_store
        nr = cs.kinds.shape[0]
        wbody = np.full(nr, -1, dtype=np.int64)
        wbinv = np.zeros(nr)
        for j, (k, wall) in enumerate(self._bodies):
            wbody[cs.wall_rows[k] : cs.wall_rows[k + 1]] = n_tot + j
            wbinv[cs.wall_rows[k] : cs.wall_rows[k + 1]] = 1.0 / wall.motion.mass
        return wbody, wbinv

    def _body_velocities(self, nc: int, v_free: np.ndarray, gam: np.ndarray) -> None:
        """v = v_free + P/M for every body, P the exact sum of its contacts' impulses ``gam`` over all
        ranks (each contact of a body is held by the rank that owns the grain), so the body moves
        alike on every rank and partition."""
        sim = self.sim
        n_tot = sim.particles.n
        for j, (_k, wall) in enumerate(self._bodies):
            px, sx, py, sy, pz, sz = ck.body_impulse_partials(self.cb, self.cn, gam, nc, n_tot + j)
            # the impulse on the grains, correctly rounded (the body's is its negative)
            g = exact_reduce(sim.comm, [(px, sx), (py, sy), (pz, sz)])[0]
            P = -np.array(g)
            v = v_free[n_tot + j] + P / wall.motion.mass
            self.V[n_tot + j] = v * wall.motion.free_axes

    def recovery_cap(self) -> float:
        """The cap on the speed at which penetration is removed (0: none): ``recovery_speed``."""
        cap = self.p.recovery_speed
        return cap if cap is not None and math.isfinite(cap) else 0.0

    def recovery_slack(self) -> float:
        """The initial overlap still allowed at the end of this step (0: none): φ₀ (1 − (k + 1)/
        ``recovery_steps``) at the run's k-th step (from 0), φ₀ the deepest pair overlap of the
        packing it starts from (measured at its first step), so the deepest contact parts at
        φ₀ / (``recovery_steps`` h) and no contact deeper than the allowance is kept (penetration
        from an unconverged solve included). A function of the checkpointed state (step count, φ₀)
        alone."""
        if self.initial_overlap <= 0.0:
            return 0.0
        return self.initial_overlap * max(0.0, 1.0 - (self.n_steps + 1) / self.p.recovery_steps)

    def _needed_envelope(self) -> float:
        """Automatic envelope: every pair that can close its gap within the step must be in the
        problem, so 2.5 × the fastest body's travel per step (at least 0.1 r_min): the bound of the
        per-contact envelopes (``envelope_rule = "contact"``), or every contact's (``"global"``),
        and the neighbour list's reach. The speed is a global max, so every rank decides alike; with
        the per-contact rule it includes |g| h and the walls' translation speeds."""
        sim = self.sim
        if self.p.envelope is not None:
            return float(self.p.envelope)
        p = sim.particles
        n = p.n_owned
        vmax = math.sqrt(float(np.max(np.einsum("ij,ij->i", p.v[:n], p.v[:n])))) if n else 0.0
        if self.p.envelope_rule == "contact":
            vmax += float(np.linalg.norm(sim.g)) * sim.dt
            cs = sim.contact_store
            if cs.vel.shape[0]:
                vmax = max(vmax, float(np.max(np.linalg.norm(cs.vel[:, :3], axis=1))))
        return max(2.5 * all_max(sim.comm, vmax) * sim.dt, self._base_envelope)

    def state(self) -> dict[str, np.ndarray]:
        """Counters for checkpoints (the envelope follows the state: :meth:`_needed_envelope`)."""
        return {
            "solver/counters": np.array(
                [
                    self.n_steps,
                    self.n_unconverged,
                    self.total_iterations,
                    self.n_stalls,
                    self.n_resolves,
                    self.n_missed_steps,
                    self.n_short_steps,
                    self.n_scaled_steps,
                    self.n_load_stops,
                ]
            ),
            "solver/max_mass_ratio": np.array(self.max_mass_ratio),
            "solver/max_residual": np.array(self.max_residual),
            "solver/initial_overlap": np.array(self.initial_overlap),
        }

    def restore(self, state: dict) -> None:
        if "solver/counters" in state:
            counters = [int(c) for c in state["solver/counters"]]
            self.n_steps, self.n_unconverged, self.total_iterations = counters[:3]
            self.n_stalls = counters[3] if len(counters) > 3 else 0  # older checkpoints: none
            self.n_resolves = counters[4] if len(counters) > 4 else 0
            self.n_missed_steps = counters[5] if len(counters) > 5 else 0
            self.n_short_steps = counters[6] if len(counters) > 6 else 0
            self.n_scaled_steps = counters[7] if len(counters) > 7 else 0
            self.n_load_stops = counters[8] if len(counters) > 8 else 0
            self.max_mass_ratio = float(state.get("solver/max_mass_ratio", 1.0))
            self.max_residual = float(state["solver/max_residual"])
            self.initial_overlap = float(state.get("solver/initial_overlap", 0.0))  # older checkpoints: 0

    def stats(self) -> dict[str, float]:
        """The last step's iterations and residual, and the run's counters (public statistics)."""
        return {
            "iterations": float(self.last_iterations),
            "residual": float(self.last_residual),
            "steps": float(self.n_steps),
            "unconverged_steps": float(self.n_unconverged),
            "load_stopped_steps": float(self.n_load_stops),
            "mean_iterations": self.total_iterations / max(self.n_steps, 1),
            "max_residual": float(self.max_residual),
        }

    def summary(self) -> dict[str, object]:
        """Solver statistics of this run (summary.json)."""
        p = self.p
        return {
            "method": "complementarity",
            "solver": p.solver,
            "cone": p.cone,
            "restitution_threshold": p.restitution_threshold,
            "tolerance": p.tolerance,
            "max_iterations": p.max_iterations,
            "relaxation": p.relaxation,
            "envelope": self.sim.envelope,
            "steps": self.n_steps,
            "unconverged_steps": self.n_unconverged,
            "mean_iterations": self.total_iterations / max(self.n_steps, 1),
            "max_residual": self.max_residual,
            "line_search_stalls": self.n_stalls,
            "load_tolerance": p.load_tolerance,
            "load_stopped_steps": self.n_load_stops,
            "envelope_resolves": self.n_resolves,
            "missed_contact_steps": self.n_missed_steps,
            "envelope_short_steps": self.n_short_steps,
            "load_mass_scaling": p.load_mass_scaling,
            "mass_scaled_steps": self.n_scaled_steps,
            "max_mass_ratio": self.max_mass_ratio,
            "recovery_speed": p.recovery_speed,
            "recovery_steps": p.recovery_steps,
            "initial_overlap": self.initial_overlap,
            # how fast the first step pushed the deepest initial overlap apart
            "initial_recovery_speed": self._initial_recovery_speed(),
        }

    def _initial_recovery_speed(self) -> float:
        """The speed at which the run's first step pushed its deepest initial overlap apart:
        φ₀ / (``recovery_steps`` h), or the cap if lower (0 before the first step)."""
        if not self.n_steps:
            return 0.0
        gradual = self.initial_overlap / (self.p.recovery_steps * self.sim.dt)
        return min(gradual, self.recovery_cap() or math.inf)

    # ------------------------------------------------------------------ solvers
    def _sync_velocities(self, nc, v_free, w_free, P, L, gam=None) -> None:
        """Velocities from the impulses ``gam`` (default: the contacts' own, ``self.gam``)."""
        gam = self.gam if gam is None else gam
        ck.accumulate(self.cb, self.cn, self.ca, self.croll, gam, nc, P, L)
        self._apply_impulses(nc, v_free, w_free, P, L, gam)

    def _apply_impulses(self, nc, v_free, w_free, P, L, gam=None) -> None:
        """v, ω of every body from the accumulated impulses P, L (and the rigid bodies' from ``gam``,
        default ``self.gam``); ghosts' forwarded."""
        sim = self.sim
        p = sim.particles
        ck.velocities(p.v, p.w, v_free, w_free, P, L, self.IM, p.inv_i, p.dof, p.n_owned)
        if self._bodies:
            self._body_velocities(nc, v_free, self.gam if gam is None else gam)
        sim.forward_ghosts(positions=False)  # no particle moves within the step's solve

    def _jacobi(self, nc, v_free, w_free, P, L) -> tuple[int, float]:
        """Projected Jacobi: each sweep gathers every contact's velocity, projects all impulses at
        once (on columns: ``G`` holds γ transposed, vectorized) and scatters them onto the bodies."""
        sim = self.sim
        pr = self.p
        self._sync_velocities(nc, v_free, w_free, P, L)
        width = self.gam.shape[1]
        G = np.ascontiguousarray(self.gam[:nc].T)
        # 1/B of every row, and the rolling rows' coefficients in columns (read only by rows of 8)
        IB, CR = ck.jacobi_columns(self.cscale, self.croll, nc, width == 8)
        BLK = self._block_columns(nc)
        U = np.empty((width, nc))
        RES = np.empty(nc)
        it = 0
        k = pr.check_every
        res = math.inf
        if sim.decomposition is None and not self._bodies and self.fused_sweeps:
            # nothing to forward between sweeps: the whole loop below in one kernel call, same bits
            p = sim.particles
            it, res = ck.jacobi_solve(
                self.cb, self.cn, self.ca, self.cvw, self.cbias, self.croll, self.cmu, self.cscale, IB, BLK,
                CR, G, U, RES, P, L, p.v, p.w, v_free, w_free, self.IM, p.inv_i, p.dof, p.n_owned, nc,
                pr.relaxation, self.corrected, k, pr.max_iterations, pr.tolerance,
            )  # fmt: skip
        while it < pr.max_iterations and not res <= pr.tolerance:  # (after the fused call: done)
            check = it % k == 0  # sweeps 1, k + 1, 2k + 1, …: residual of the impulses before them
            ck.jacobi_gather(
                self.cb, self.cn, self.ca, self.cvw, self.cbias, self.croll, self.V, self.W, nc, U
            )
            ck.jacobi_project(
                U, G, self.cmu, self.cscale, IB, BLK, CR, nc, pr.relaxation, self.corrected, check, RES
            )  # fmt: skip
            ck.accumulate_columns(self.cb, self.cn, self.ca, self.croll, G, nc, P, L)
            it += 1
            self._apply_impulses(nc, v_free, w_free, P, L, G.T)
            if check:
                res = math.sqrt(all_max(sim.comm, ck.max_nonneg(RES, nc)))  # RES: squared residuals
                if res <= pr.tolerance:
                    break
        self.gam[:nc] = G.T
        if res > pr.tolerance:
            # the residual above is that of the impulses before the last sweep: measure the final one
            res = self._residual(nc, G, U, RES)
        return it, res

    def _pair_work(self) -> np.ndarray:
        """Work space of the pair assembly: one index per listed pair (kept between steps, grown
        with the list)."""
        n = self.sim.contact_store.pi.shape[0]
        work = getattr(self, "_tk", None)
        if work is None or work.shape[0] < n:
            work = self._tk = np.empty(int(n * 1.25) + 64, dtype=np.int64)
        return work

    def _residual(self, nc, G=None, U=None, UN=None) -> float:
        """The global residual of the current impulses and velocities: of Coulomb's law (ũ) for the
        corrected cone, of the relaxed cone problem (u) otherwise. On columns (the column gather and
        the branch-free residual pass): ``G`` the impulses in columns (default: ``self.gam``'s),
        ``U`` (width, nc) and ``UN`` (nc) work space, overwritten."""
        width = self.gam.shape[1]
        if G is None:
            G = np.ascontiguousarray(self.gam[:nc].T)
        U = np.empty((width, nc)) if U is None else U
        UN = np.empty(nc) if UN is None else UN  # ũ_n of every contact
        none = np.empty((width, 0))
        ck.apgd_gather(
            self.cb, self.cn, self.ca, self.cvw, self.cbias, self.croll, self.cmu, self.V, self.W, nc, U, UN,
            self.corrected, G, none, none, UN, UN, False,
        )  # fmt: skip
        own = ck.apgd_residual(
            G, U, UN if self.corrected else U[0], self.cmu, self.cscale, self.croll, nc, np.empty(nc)
        )
        return all_max(self.sim.comm, own)

    def _block_columns(self, nc: int) -> np.ndarray:
        """The update's (B_n, B_t, μρ) of every contact (:func:`ck.block_columns`, ``scaling``)."""
        return ck.block_columns(
            self.cb, self.ca, self.cmu, self.cscale, self.IM, self.II, nc, self.p.scaling == "block"
        )

    def _gauss_seidel(self, nc, v_free, w_free, P, L) -> tuple[int, float]:
        pr = self.p
        self._sync_velocities(nc, v_free, w_free, P, L)
        BLK = self._block_columns(nc)
        res = 0.0
        it = 0
        while it < pr.max_iterations:
            res = ck.gauss_seidel_sweep(
                self.cb, self.cn, self.ca, self.cvw, self.cbias, self.cmu, self.cscale, BLK, self.croll,
                self.gam, self.V, self.W, self.IM, self.II, self.DOF, nc, pr.relaxation, self.corrected,
            )  # fmt: skip
            it += 1
            if res <= pr.tolerance:
                break
        self._sync_velocities(nc, v_free, w_free, P, L)
        return it, self._residual(nc)

    def _counted_rows(self, nc: int) -> np.ndarray:
        """The contact rows this rank counts in APGD's global sums, so that every contact is counted
        exactly once over all ranks: a pair by the rank that owns its lower-id particle (pair rows
        are (i, j) with id_i < id_j, so: i owned here), a wall contact by the rank that owns its grain
        (j). A cross-rank pair is a row on both ranks (computed identically), counted on one; a pair
        with a periodic image of an owned particle likewise."""
        p = self.sim.particles
        cb = self.cb[:nc]
        i, j = cb[:, 0], cb[:, 1]
        pair = (i >= 0) & (i < p.n)  # −1: a fixed wall; ≥ n: a rigid-body wall (after the particles)
        return np.flatnonzero(np.where(pair, i < p.n_owned, j < p.n_owned)).astype(np.int64)

    def jacobi_bound(self, active: bool = True, iterations: int = 200) -> float:
        """λ_max of B N on the last step's contact problem, by power iteration: Jacobi's sweep
        γ ← Π_K(γ − ω B (N γ + r)) is a contraction on a set of contacts that stay in contact only
        while ω λ_max < 2, so 2/λ_max bounds ``relaxation`` there. ``active``: the contacts whose
        solved γ_n > 0 (those that carry load; the others are projected to zero and leave the
        iteration), else every row of the problem. N = D M⁻¹ Dᵀ (rolling rows included), B the
        rows' scaling (``scaling``: 3/trace of the contact's block, or the block's own inverse on the
        normal and tangential rows; B_r for rolling rows).

        A diagnostic, for choosing ``relaxation`` on a scene (docs/dem_c.md, *The hopper at each
        method's best settings*): call it on every rank after a step. Partition-independent up to
        rounding (exact global sums, each contact counted once); the state is left as it was."""
        sim = self.sim
        p = sim.particles
        comm = sim.comm
        nc = int(self.last_contacts)
        width = self.gam.shape[1]
        mask = (self.gam[:nc, 0] > 0.0) if active else np.ones(nc, dtype=bool)
        B = np.zeros((width, nc))
        blk = self._block_columns(nc)
        B[0] = np.where(mask, blk[0], 0.0)
        B[1:4] = np.where(mask, blk[1], 0.0)
        if width == 8:
            B[4:] = np.where(mask, self.croll[:nc, 3], 0.0)  # 0: a row without rolling friction
        IB = np.divide(1.0, B, out=np.zeros_like(B), where=B > 0.0)
        rows = self._counted_rows(nc)
        all_rows = rows.shape[0] == nc

        def dot(a, b):
            return dot_partials_columns(a, b, rows, all_rows)

        n_all = p.n + len(self._bodies)
        saved = [a.copy() for a in (p.v, p.w, self.V, self.W)]
        zero = np.zeros((n_all, 3))
        cvw = np.zeros_like(self.cvw)  # walls at rest, no bias: the linear part N γ alone
        cbias = np.zeros_like(self.cbias)
        P, L = np.empty((n_all, 3)), np.empty((n_all, 3))
        U = np.empty((width, nc))
        G = np.where(B > 0.0, 1.0, 0.0)  # the same start on every rank: partition-independent
        (gg,), _ = exact_reduce(comm, [dot(G, G * IB)])
        lam = 0.0
        if gg > 0.0:
            G /= math.sqrt(gg)
            for _ in range(iterations):
                P[:] = 0.0
                L[:] = 0.0
                ck.accumulate_columns(self.cb, self.cn, self.ca, self.croll, G, nc, P, L)
                self._apply_impulses(nc, zero, zero, P, L, np.ascontiguousarray(G.T))
                ck.jacobi_gather(self.cb, self.cn, self.ca, cvw, cbias, self.croll, self.V, self.W, nc, U)
                U *= B > 0.0
                # Rayleigh quotient of B^½ N B^½ at h = B^-½ γ (γ normalised: γ·B⁻¹γ = 1)
                (lam, uu), _ = exact_reduce(comm, [dot(G, U), dot(U, U * B)])
                if not uu > 0.0:
                    break
                G = U * B / math.sqrt(uu)
        for a, s in zip((p.v, p.w, self.V, self.W), saved, strict=True):
            a[:] = s
        return float(lam)

    MAX_TRIALS = 60  # line-search doublings of the Lipschitz estimate per APGD iteration

    def _apgd(self, nc, v_free, w_free, P, L) -> tuple[int, float]:
        """Accelerated projected gradient descent with adaptive step size and restart (Mazhar et al.,
        ACM TOG 34(3), 2015, Algorithm 1), on f(γ) = ½ γᵀNγ + rᵀγ over the cones, ∇f = u(γ).

        Corrected cone: the same iteration on the corrected velocities ũ(γ) = u(γ) + μ|u_t(γ)| e_n
        (the shift of the current iterate, as Jacobi and Gauss–Seidel use it). ũ is not the gradient
        of a function, so the step's acceptance test is written without f: for the quadratic f,
        f(γ) ≤ f(y) + ∇f(y)·(γ − y) + L/2 |γ − y|² is (γ − y)·(u(γ) − u(y)) ≤ L |γ − y|², and that
        local Lipschitz test is applied to ũ. (It also avoids the cancellation of f's large terms.
        Holding the shift fixed through whole APGD solves and refreshing it between them, a fixed
        point of convex problems, needed 10–40 times the iterations on a sheared packing.)

        Partition independence (MPI): every per-contact operation (projection, extrapolation,
        ũ from the bodies' velocities) is elementwise, and a cross-rank contact's row holds the same
        numbers on both ranks (as in Jacobi: impulses accumulated per body in contact-row order,
        ghosts' velocities forwarded after every evaluation of ũ). The scalars that steer the
        iteration (dot products and norms, hence the step size, line search and restart; the
        residual) are global: exact sums over :meth:`_counted_rows` (each contact once) and an
        exact max, gathered in one collective per line-search trial, so every rank takes the same
        decisions and the results are bitwise identical on any number of ranks. The serial run
        takes the same path (its sums are exact too).

        Phases (:class:`_ApgdSolve`): :meth:`~_ApgdSolve.start` (the first iterate and the step
        size from a Lipschitz estimate), then per iteration :meth:`~_ApgdSolve.line_search` (the
        projected step, halved until accepted, or a stall), :meth:`~_ApgdSolve.stop` (the residual
        on checked iterations, the best iterate, the stopping test) and :meth:`~_ApgdSolve.next_point`
        (restart or Nesterov extrapolation). The solve returns its best checked iterate."""
        pr = self.p
        if not any_rank(self.sim.comm, nc > 0):
            self._sync_velocities(nc, v_free, w_free, P, L)
            return 0, 0.0
        solve = _ApgdSolve(self, nc, v_free, w_free, P, L)
        solve.start(warm=pr.apgd_start == "warm")
        if pr.load_tolerance is not None:
            solve.watch_loads(pr.load_tolerance)
        it = 0
        while it < pr.max_iterations:
            it += 1
            # the residual on every k-th iteration (the first included) and at the cap
            check = (it - 1) % pr.check_every == 0 or it == pr.max_iterations
            trial = solve.line_search(check)
            if trial is None:  # stalled: stop this solve, keeping its best iterate
                self.n_stalls += 1
                break
            if solve.stop(trial, check, pr.tolerance, it):
                break
            solve.next_point(trial)
        self.gam[:nc] = solve.best.T
        self._sync_velocities(nc, v_free, w_free, P, L)
        self.load_stopped = solve.load_stopped
        return it, solve.best_res


class _ApgdSolve:
    """One APGD solve of a step (:meth:`Stepper._apgd`, which documents the method): its work arrays,
    its global sums and its phases. The iterates live in columns (array[k, c]: component k of
    contact c), as Jacobi's, so that the passes stream (``ck.apgd_*``)."""

    #: iterations between two measurements of the walls' loads (load_tolerance)
    LOAD_WINDOW = 10

    def __init__(self, st: Stepper, nc: int, v_free, w_free, P, L) -> None:
        self.st = st
        self.nc = nc
        self.v_free, self.w_free, self.P, self.L = v_free, w_free, P, L
        self.comm = st.sim.comm
        self.corrected = st.corrected
        self.cmu = st.cmu[:nc]
        self.cscale = st.cscale[:nc]
        self.croll = st.croll[:nc]
        self.rows = st._counted_rows(nc)
        # scaling = "block": APGD on B^-½ γ (the contacts' Delassus blocks as a preconditioner):
        # steps t B ũ, projections and |γ − y|² in B⁻¹'s metric (ck.apgd_project_step)
        self.scaled = st.p.scaling == "block"
        self.blk = st._block_columns(nc) if self.scaled else np.empty((3, 0))
        # serially, or no contact held by two ranks: every row counts
        self.all_rows = self.rows.shape[0] == nc
        # Work arrays are reused through the solve and across steps (views of one block): allocating
        # them per iteration cost as much as the iteration's kernels on a 10,000-contact scene (page
        # faults of fresh memory).
        width = self.width = st.gam.shape[1]
        # (a flat buffer reshaped: every array C-contiguous, which lets numba vectorize the passes)
        if st._apgd_work.shape[0] < (9 * width + 6) * nc:
            st._apgd_work = np.empty(int(1.25 * (9 * width + 6) * nc))
        buf = st._apgd_work
        work = buf[: 9 * width * nc].reshape(9, width, nc)
        self.Y, self.GY, self.GK, self.UK, self.GN, self.UN, self.BEST, self.G0, self.GH = work
        self.GYN_c, self.UNN_c = buf[9 * width * nc : (9 * width + 2) * nc].reshape(2, nc)
        # the trial's three dot products per contact, and the contacts' residuals
        self.D = buf[(9 * width + 2) * nc : (9 * width + 6) * nc].reshape(4, nc)
        self.no_trial = np.empty((width, 0))
        # load_tolerance (watch_loads): off until asked for
        self.load_tol: float | None = None
        self.prev_loads: np.ndarray | None = None
        self.load_passes = 0
        self.load_it = -self.LOAD_WINDOW  # the iteration of the last load measurement
        self.load_stopped = False

    # ------------------------------------------------------------------ the solve's operations
    def reduce(self, pairs, maxima=()):
        """Global exact Σ a·b for each (a, b) (columns) and global max of each local value."""
        rows, all_rows = self.rows, self.all_rows
        return exact_reduce(self.comm, [dot_partials_columns(a, b, rows, all_rows) for a, b in pairs], maxima)

    def row_scales(self) -> np.ndarray:
        """B of every row in columns (width, nc): B_n, B_t (×3) and the rolling rows' B_r (1 where a
        contact has none: its rows are zero)."""
        width, nc = self.width, self.nc
        S = np.empty((width, nc))
        S[0] = self.blk[0]
        S[1:4] = self.blk[1]
        if width == 8:
            br = self.croll[:, 3]
            S[4:] = np.where(br > 0.0, br, 1.0)
        return S

    def normal(self, u: np.ndarray, un: np.ndarray) -> np.ndarray:
        """The normal row of ũ: the corrected one, or u's own for the relaxed cone."""
        return un if self.corrected else u[0]

    def grad(self, gv: np.ndarray, u: np.ndarray, un: np.ndarray, trial: bool = False) -> None:
        """u(γ) into ``u`` (and ũ_n into ``un`` for the corrected cone), from γ = ``gv``; with
        ``trial`` also the trial's first dot products (against y)."""
        st = self.st
        nc = self.nc
        ck.accumulate_columns(st.cb, st.cn, st.ca, st.croll, gv, nc, self.P, self.L)
        st._apply_impulses(nc, self.v_free, self.w_free, self.P, self.L, gv.T)
        no_trial = self.no_trial
        ck.apgd_gather(
            st.cb, st.cn, st.ca, st.cvw, st.cbias, st.croll, self.cmu, st.V, st.W, nc, u, un,
            self.corrected, gv, self.Y if trial else no_trial, self.GY if trial else no_trial, self.GYN_c,
            self.D[0], trial,
        )  # fmt: skip

    @staticmethod
    def objective(s_nu: float, s_r: float) -> float:
        """f = ½ γ·(Nγ) + r·γ with Nγ = u − r, from the global sums γ·(u − r) and r·γ."""
        return 0.5 * s_nu + s_r

    # ------------------------------------------------------------------ phases
    def start(self, warm: bool) -> None:
        """The first iterate γ0 (zero impulses, or the last step's with ``warm``), projected onto the
        cones, y = γ_k = γ0 and u(y); the relaxed cone's r = u(0); the step size 1/L from a
        Lipschitz estimate |ũ(γ0) − ũ(γ̂)| / |γ0 − γ̂| with γ̂ a perturbed start (3/min B when that
        is not positive)."""
        st, nc, width = self.st, self.nc, self.width
        cmu, cscale, croll = self.cmu, self.cscale, self.croll
        G0, GH, GY, UN, GYN_c, UNN_c = self.G0, self.GH, self.GY, self.UN, self.GYN_c, self.UNN_c
        # a cold start: from the last step's impulses (the Jacobi warm start) APGD took 23.8 instead
        # of 22.8 iterations per step on the 300-bead hopper scene, and the 4,000-bead hopper's fill
        # (h = 1e-3 s) no longer settled below its kinetic-energy threshold by 0.3 s
        start = st.gam[:nc].copy() if warm else np.zeros((nc, width))
        # u(0) = r (the relaxed cone's f), kept for the solve
        self.r_vec = None
        if not self.corrected:
            G0[:] = 0.0
            self.grad(G0, UN, UNN_c)
            self.r_vec = UN.copy()
        g0 = ck.project_cone_array(start, cmu, croll)
        # step from a Lipschitz estimate: |N(γ0 − γ̂)| / |γ0 − γ̂| with γ̂ a perturbed start
        e_n = np.zeros(width)
        e_n[0] = 1.0
        ghat = ck.project_cone_array(g0 + 1e-3 * (1.0 / cscale)[:, None] * e_n, cmu, croll)
        G0[:] = g0.T
        GH[:] = ghat.T
        d = G0 - GH
        S = self.row_scales() if self.scaled else None
        self.inv_s = 1.0 / S if self.scaled else None
        nd = math.sqrt(self.reduce([(d, d * self.inv_s if self.scaled else d)])[0][0])  # (in B⁻¹'s metric)
        self.grad(G0, GY, GYN_c)  # ũ and u at the first y = γ0
        self.gyn = self.normal(GY, GYN_c)
        if nd > 0.0:
            self.grad(GH, UN, UNN_c)
            du = GY - UN
            du[0] = self.gyn - self.normal(UN, UNN_c)
            lip = math.sqrt(self.reduce([(du, du * S if self.scaled else du)])[0][0]) / nd
        else:
            lip = 0.0
        if not (lip > 0.0):
            # the largest diagonal block's trace: of N_cc, or of B N_cc = I (3) when scaled
            local = (3.0 if self.scaled else float(np.max(3.0 / cscale))) if nc else -math.inf
            lip = self.reduce([], [local])[1][0]
        self.lip = lip
        self.t = 1.0 / lip
        self.gam_k = self.GK
        self.gam_k[:] = G0
        self.u_k = self.UK
        self.u_k[:] = GY  # u(γ_k)
        self.y = self.Y
        self.y[:] = G0
        self.theta = 1.0
        self.best = self.BEST
        self.best[:] = G0
        self.g_new, self.u_new = self.GN, self.UN
        self.best_res = math.inf

    def line_search(self, check: bool) -> tuple | None:
        """One iteration's step: γ = Π_K(y − t ũ(y)) and ũ(γ), accepted when the local Lipschitz
        test holds (the relaxed cone: f's sufficient decrease), else L doubled and tried again.
        ``check``: the trial's residual is measured too. One collective per trial: the acceptance
        test's sums, the restart test's and the residual (the last two used only if the trial is
        accepted). Returns the accepted trial's global (sums, maxima), or None when the search
        stalls (non-finite sums, or more than ``MAX_TRIALS`` doublings)."""
        nc, comm = self.nc, self.comm
        cmu, cscale, croll = self.cmu, self.cscale, self.croll
        corrected = self.corrected
        y, GY, D, UNN_c, r_vec = self.y, self.GY, self.D, self.UNN_c, self.r_vec
        g_new, u_new, gam_k = self.g_new, self.u_new, self.gam_k
        if corrected:
            fy = 0.0
        else:
            s = self.reduce([(y, GY - r_vec), (r_vec, y)])[0]
            fy = self.objective(s[0], s[1])
        trials = 0
        while True:
            # Π(y − t ∇), with the corrected cone's trial sums |γ − y|² and ũ(y)·(γ − γ_k)
            ck.apgd_project_step(
                y, GY, self.gyn, gam_k, self.t, cmu, croll, nc, g_new, D[1], D[2], corrected, self.blk,
                self.scaled,
            )  # fmt: skip
            self.grad(g_new, u_new, UNN_c, corrected)  # and (γ − y)·(ũ(γ) − ũ(y))
            res_args = (g_new, u_new, self.normal(u_new, UNN_c), cmu, cscale, croll, nc, D[3])
            local_res = ck.apgd_residual(*res_args) if check else math.inf
            if corrected:
                p1, e1, p2, e2, p3, e3 = ck.apgd_trial_sums(D[0], D[1], D[2], self.rows, self.all_rows, nc)
                s, m = exact_reduce(comm, [(p1, e1), (p2, e2), (p3, e3)], [local_res])
                accept = s[0] <= self.lip * s[1]
            else:
                step = g_new - y
                restart_terms = (GY, g_new - gam_k)
                s, m = self.reduce(
                    [(g_new, u_new - r_vec), (r_vec, g_new), (GY, step),
                     (step, step * self.inv_s if self.scaled else step), restart_terms],
                    [local_res],
                )
                accept = self.objective(s[0], s[1]) <= fy + s[2] + 0.5 * self.lip * s[3]
            if accept:
                return s, m
            trials += 1
            if not (math.isfinite(s[0]) and math.isfinite(s[1])) or trials > self.st.MAX_TRIALS:
                # non-finite sums never pass the test, and a step 2^60 times below the estimate
                # makes no progress: stop this solve (keeping its best iterate) instead of looping
                return None
            self.lip *= 2.0
            self.t = 1.0 / self.lip

    def stop(self, trial: tuple, check: bool, tolerance: float, it: int) -> bool:
        """On a checked iteration (``it``): the accepted iterate's residual, kept as the best iterate
        when it is the lowest so far; True when it is below ``tolerance``, or when the walls' loads
        have settled (:meth:`loads_settled`, with ``load_tolerance``)."""
        if not check:
            return False
        res = trial[1][0]
        if res < self.best_res:
            self.best_res = res
            self.best[:] = self.g_new
        if res <= tolerance:
            return True
        if self.load_tol is not None and it - self.load_it >= self.LOAD_WINDOW and self.loads_settled(it):
            # the loads belong to this iterate: return it, whatever its residual
            self.best_res = res
            self.best[:] = self.g_new
            self.load_stopped = True
            return True
        return False

    def watch_loads(self, tol: float) -> None:
        """Also stop when the walls' loads have settled (``load_tolerance``): the counted rows of
        each wall's contacts, for the exact per-wall sums of :meth:`loads_settled`."""
        st = self.st
        rows = self.rows
        i = st.cb[rows, 0]
        wrows = rows[(i < 0) | (i >= st.sim.particles.n)]  # −1: a fixed wall; ≥ n: a rigid body
        self.wrows, self.wk = wrows, st.csrc[wrows, 0]
        self.nwalls = len(st.sim.contact_store.walls)
        self.load_tol = tol

    def loads_settled(self, it: int) -> bool:
        """The walls' loads of the current iterate ``it`` (each wall's summed contact impulse, an
        exact global sum per wall and component, so every rank decides alike), measured on checked
        iterations at least :attr:`LOAD_WINDOW` apart: True on the second measurement in a row whose
        largest change of a wall's load since the last one is at most ``load_tol`` × the largest wall
        load. (The window is in iterations, not checks, so that the test means the same at any
        ``check_every``.)"""
        self.load_it = it
        parts, special = ck.wall_load_partials(self.g_new, self.st.cn, self.wrows, self.wk, self.nwalls)
        sums = [(parts[r, : int(parts[r, -1])], special[r]) for r in range(parts.shape[0])]
        loads = np.array(exact_reduce(self.comm, sums)[0]).reshape(-1, 3)
        prev, self.prev_loads = self.prev_loads, loads
        if prev is None:
            return False
        scale = math.sqrt(float(np.max((loads * loads).sum(axis=1), initial=0.0)))
        change = math.sqrt(float(np.max(((loads - prev) ** 2).sum(axis=1), initial=0.0)))
        self.load_passes = self.load_passes + 1 if 0.0 < scale and change <= self.load_tol * scale else 0
        return self.load_passes >= 2

    def next_point(self, trial: tuple) -> None:
        """The next y: a restart (y = γ, θ = 1) when ũ(y)·(γ − γ_k) > 0, else Nesterov's
        extrapolation y = γ + β (γ − γ_k); L decays by 0.9; γ_k ← γ."""
        s = trial[0]
        theta = self.theta
        theta_new = 0.5 * (-theta * theta + theta * math.sqrt(theta * theta + 4.0))
        beta = theta * (1.0 - theta) / (theta * theta + theta_new)
        g_new, u_new = self.g_new, self.u_new
        if s[-1] > 0.0:  # restart
            self.y[:] = g_new
            self.GY[:] = u_new
            if self.corrected:
                self.GYN_c[:] = self.UNN_c
            theta_new = 1.0
        else:
            # y = γ + β (γ − γ_k), and u(y) = u(γ) + β (u(γ) − u(γ_k)) without solving for the
            # bodies' velocities again (u is affine in γ; elementwise, so the same on every rank):
            # one evaluation of ũ per iteration instead of two
            ck.apgd_extrapolate(g_new, self.gam_k, beta, self.nc, self.y)
            ck.apgd_extrapolate_velocities(u_new, self.u_k, beta, self.cmu, self.nc, self.GY, self.GYN_c,
                                           self.corrected)  # fmt: skip
        self.lip *= 0.9
        self.t = 1.0 / self.lip
        # γ_k ← γ, u(γ_k) ← u(γ); the old γ_k's arrays take the next trial
        self.gam_k, self.g_new = g_new, self.gam_k
        self.u_k, self.u_new = u_new, self.u_k
        self.theta = theta_new


def _deepest_overlap(x: np.ndarray, r: np.ndarray, pi: np.ndarray, pj: np.ndarray) -> float:
    """The largest overlap r_i + r_j − |x_i − x_j| of the listed pairs (0 when none overlaps)."""
    if pi.size == 0:
        return 0.0
    gap = np.linalg.norm(x[pi] - x[pj], axis=1) - r[pi] - r[pj]
    return float(max(0.0, -gap.min()))
