"""Triaxial cell: a cylindrical specimen between two platens, confined by a flexible membrane.

**Membrane** (why this design): the confining pressure σ₃ acts on the grains of the lateral surface,
found anew every step as the outermost grain (largest ρ + r about the specimen axis) of each cell of
an (θ, z) grid over the current specimen height; ties go to the lower id. The surface radius of cell
(k, m) is R = ρ + r of its grain, and the force on that grain,

    F = −σ₃ · R Δθ Δz · ρ̂,

is σ₃ × the area of the surface patch it represents, along the inward radial direction. (Tilting the
normal by the bulge's slope ∂R/∂z, estimated from neighbouring cells, was tried: at the grain scale
the slopes are noise, and their end terms do not cancel — it loaded the bottom platen 38 % more than
the top one with no gravity. On a real specimen the membrane's axial pull goes to the platens; here
the lateral pressure is horizontal, and the measured platen loads then agree with each other and with
the grains' own stress within 0.2 %.) Nothing holds the
grains radially but these forces, so the specimen is free to bulge. It needs no membrane elements
and no bonds (the bonded-ball membrane of Qu et al. 2019 is stiffer to set up and adds its own
elasticity); it works with both methods (DEM-C takes the forces into the free velocity) and, since
the outermost grain is a global maximum (exact under any reduction) and forces act on owned grains,
it gives bitwise identical results on any number of ranks. Its limits: a grain smaller than the
cells can slip between the loaded ones (cells of about one grain diameter, the default, avoid it),
and the enclosed volume is that of the cells' radii (the specimen volume to within a grain's
roughness).

**Platens**: horizontal planes; the bottom one is fixed. The top one is servo-controlled to σ₃
during consolidation (a velocity servo for soft grains; for rigid grains, ``control = "force"``, a
free plate under the load σ₃ A, solved with the grains by DEM-C), then driven down at a constant
axial strain rate during shearing (v = ε̇ H₀).

**Preparation**: an optional rigid mould (a cylinder wall of the specimen's radius) is active in the
stages listed in ``mould_stages`` (e.g. while grains are poured and settle), while the top platen is
servoed down to a small seating stress; the membrane takes over in ``consolidation_stage`` (its
pressure rising over ``ramp_time``) and ``shear_stage``.

Measured every series row: ``sigma1`` (top platen force / current cross-section V/H), ``sigma3``
(realised: total radial membrane force / lateral area), ``eps_a`` (axial strain from the start of
shearing, compression positive), ``eps_v`` (volumetric strain, from the membrane's enclosed volume),
``q`` = σ₁ − σ₃, ``p`` = (σ₁ + 2σ₃)/3, ``height``, ``radius`` (mean of the cells), and the average
stress of the grains from their contacts (Love–Weber, ``lw_szz``, ``lw_srr``): σ = (1/V) Σ_c l_c ⊗ f_c
over pair contacts (branch vectors), platen contacts and membrane forces (levers from the grain
centres), an independent check of the boundary stresses. Lengths in m, stresses in Pa.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from ..parallel.comm import all_max
from . import shapes
from .api import Boundary, BoundaryParams, Vec3
from .walls import Controlled, RigidBody

__all__ = ["TriaxialCell", "TriaxialParams"]


class TriaxialParams(BoundaryParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "triaxial"``."""

    material: str = Field(description="material of the platens (and of the mould)")
    base_center: Vec3 = Field(description="centre of the bottom platen [m]; the axis is +z")
    radius: float = Field(gt=0, description="initial specimen radius (the mould's) [m]")
    height: float = Field(gt=0, description="initial specimen height (the top platen's start) [m]")
    sigma3: float = Field(gt=0, description="confining pressure σ₃ [Pa]")
    strain_rate: float = Field(gt=0, description="axial strain rate during shearing [1/s]")
    consolidation_stage: str = Field(description="stage in which the specimen is consolidated to σ₃")
    shear_stage: str = Field(description="stage in which it is sheared at constant axial strain rate")
    mould_stages: list[str] = Field(
        default_factory=list, description="stages with the rigid mould in place"
    )
    cell_size: float | None = Field(
        default=None, gt=0,
        description="membrane cell size [m] along z and around; default one mean diameter",
    )
    membrane_band: float = Field(
        0.0, ge=0,
        description="share of a cell's membrane load [fraction of half the cell size, i.e. of the mean "
        "radius by default]: 0 loads the "
        "outermost grain only; b > 0 shares it among the grains whose outer surface lies within b r "
        "of the outermost, weighted linearly from 0 at the band's inner edge to 1 at the outermost, "
        "so that the load moves continuously from grain to grain",
    )
    control: str = Field(
        "auto", pattern="^(auto|velocity|force)$",
        description="top platen while seating and consolidating: 'velocity' servo (soft grains), "
        "'force' (a free plate under the seating stress, then σ₃ A, solved with the grains; rigid "
        "grains, on which a velocity servo reads impulses and overloads them); 'auto': by the contact law",
    )
    max_speed: float = Field(0.05, gt=0, description="largest platen speed of the velocity servo [m/s]")
    seating_stress: float | None = Field(
        default=None, ge=0,
        description="during the mould stages the top platen is servoed down onto the specimen to this "
        "axial stress [Pa] (seating); default 0.05 sigma3",
    )
    ramp_time: float = Field(
        0.0, ge=0,
        description="the membrane pressure rises linearly from 0 to sigma3 over this time at the start of "
        "consolidation [s] (0: at once)",
    )

    @model_validator(mode="after")
    def _stages(self):
        if self.consolidation_stage == self.shear_stage:
            raise ValueError("consolidation_stage and shear_stage must be different stages")
        return self


class TriaxialCell(Boundary):
    """See the module docstring."""

    Params = TriaxialParams

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        self.phase = "off"
        self._stage_t0 = 0.0
        self.force_control = False  # set per stage by on_stage
        self._seated = False
        self._size = None
        self.h0 = self.v0 = None
        self._cells: tuple | None = None
        self._membrane_force = np.zeros(3)
        self._lateral_area = 0.0
        self._volume = math.nan
        self._radius = math.nan

    # ------------------------------------------------------------------ building, stages
    def build(self, sim: Any) -> None:
        p = self.params
        c = np.asarray(p.base_center, dtype=float)
        self.axis_xy = c[:2].copy()
        self.z0 = float(c[2])
        self.bottom = self.add_wall(sim, shapes.Plane(c, (0, 0, 1)), "bottom")
        self.motion = Controlled()
        top = shapes.Plane(c + (0, 0, p.height), (0, 0, -1))
        self.top = self.add_wall(sim, top, "top", motion=self.motion)
        mould = shapes.Cylinder(c, (0, 0, 1), p.radius)
        self.mould = self.add_wall(sim, mould, "mould") if p.mould_stages else None
        self._comm = sim.comm

    def on_stage(self, sim: Any, stage: str) -> None:
        p = self.params
        resumed = getattr(self, "_restored", None)
        self._restored = None
        if resumed is not None and resumed.get("stage") != stage:
            resumed = None  # the checkpoint was taken at the end of an earlier stage
        self._size = None
        stages = getattr(p, "stages", None)
        self.active = stages is None or stage in stages
        for wall in (self.bottom, self.top):
            sim.set_wall_active(wall.name, self.active)
        if self.mould is not None:
            sim.set_wall_active(self.mould.name, self.active and stage in p.mould_stages)
        if not self.active:
            self.phase = "off"
            return
        control = p.control
        if control == "auto":
            control = "force" if sim.law.kind == "complementarity" else "velocity"
        self.force_control = control == "force"
        self._seated = bool(resumed.get("seated", False)) if resumed is not None else False
        if stage == p.consolidation_stage:
            self.phase = "consolidate"
            if self.force_control:
                area = math.pi * p.radius**2
                body = RigidBody(mass=p.sigma3 * area / 10.0, force=(0.0, 0.0, -p.sigma3 * area),
                                 fixed_translation="xy")  # fmt: skip
                if resumed is not None and "body_velocity" in resumed:
                    body.restore({"velocity": np.array(resumed["body_velocity"]),
                                  "angular_velocity": np.zeros(3)})  # fmt: skip
                sim.set_wall_motion(self.top.name, body)
            else:
                self.motion = Controlled()
                sim.set_wall_motion(self.top.name, self.motion)
        elif stage == p.shear_stage:
            self.phase = "shear"
            self.motion = Controlled()
            sim.set_wall_motion(self.top.name, self.motion)
            self.h0 = None  # taken at the first step of shearing
        else:
            self.phase = "prepare"
            if self.force_control and self._seated:  # resumed after the plate came down
                self._seat_body(sim, resumed)
            else:
                self.motion = Controlled()
                sim.set_wall_motion(self.top.name, self.motion)
        self._stage_t0 = sim.time
        if resumed is not None:  # continue the stage where the checkpoint left it
            self._stage_t0 = resumed["stage_t0"]
            self.h0, self.v0 = resumed["h0"], resumed["v0"]
        self._stage = stage

    def _seat_body(self, sim: Any, resumed: dict | None = None) -> None:
        """Force control while seating: the top platen becomes a free plate (mass: its load / 10
        m/s²) pressed down by the seating stress over the mould's cross-section, at rest unless
        resumed."""
        load = self._seat_stress() * math.pi * self.params.radius**2
        body = RigidBody(mass=max(load, 1e-300) / 10.0, force=(0.0, 0.0, -load), fixed_translation="xy")
        if resumed is not None and "body_velocity" in resumed:
            body.restore({"velocity": np.array(resumed["body_velocity"]), "angular_velocity": np.zeros(3)})
        sim.set_wall_motion(self.top.name, body)

    def after_step(self, sim: Any) -> None:
        # force control while seating: the platen comes down at max_speed until the grains push it,
        # then it is a free plate under the seating load (from the next step on)
        if self.phase == "prepare" and self.force_control and not self._seated and self.mould is not None:
            if self.mould.active and float(self.top.force[2]) > 0.0:  # collective
                self._seated = True
                self._seat_body(sim)

    def state(self) -> dict[str, Any]:
        """What a resumed stage needs: the stage, its start time (pressure ramp), the height and
        volume at the start of shearing (strain references), a load-controlled plate's velocity."""
        out = {"stage": getattr(self, "_stage", None), "stage_t0": self._stage_t0, "h0": self.h0,
               "v0": self.v0, "seated": self._seated}  # fmt: skip
        if isinstance(self.top.motion, RigidBody):
            out["body_velocity"] = self.top.motion.velocity_now.tolist()
        return out

    def restore(self, state: dict[str, Any]) -> None:
        self._restored = dict(state) if state else None

    # ------------------------------------------------------------------ geometry
    def height(self) -> float:
        return float(self.top.reference_point[2] - self.bottom.reference_point[2])

    def _own(self, sim):
        p = sim.particles
        n = p.n_owned
        live = p.motion[:n] != 3  # not removed
        return p, n, live

    # ------------------------------------------------------------------ hooks
    def _area(self) -> float:
        """Current cross-section: the membrane's enclosed volume / height (the mould's before)."""
        vol = self._volume
        return vol / self.height() if vol == vol else math.pi * self.params.radius**2

    def _servo(self, target: float, area: float, scale: float) -> None:
        """Top platen velocity from the axial stress (grains push it up): proportional, with the
        gain max_speed / ``scale`` (full speed while nothing touches it)."""
        sigma1 = float(self.top.force[2]) / area
        vmax = self.params.max_speed
        v = float(np.clip(vmax / max(scale, 1e-300) * (target - sigma1), -vmax, vmax))
        self.motion.velocity = np.array([0.0, 0.0, -v])

    def before_step(self, sim: Any) -> None:
        # consolidation is isotropic: the platen's target follows the membrane's pressure ramp (a
        # platen driven to the full σ₃ at once overloads the few chains that first carry it)
        if self.phase == "consolidate" and isinstance(self.top.motion, RigidBody):
            self.top.motion.force = (0.0, 0.0, -self.pressure(sim) * self._area())
        elif self.phase == "prepare" and self.mould is not None and self.mould.active:
            seat = self._seat_stress()
            if not self.force_control:
                self._servo(seat, math.pi * self.params.radius**2, seat)
            elif not self._seated:  # force control: come down at full speed until the grains are met
                self.motion.velocity = np.array([0.0, 0.0, -self.params.max_speed])
        elif self.phase == "consolidate" and isinstance(self.top.motion, Controlled):
            self._servo(max(self.pressure(sim), self._seat_stress()), self._area(), self.params.sigma3)
        elif self.phase == "shear":
            if self.h0 is None:
                self.h0, self.v0 = self.height(), self._volume
            self.motion.velocity = np.array([0.0, 0.0, -self.params.strain_rate * self.h0])

    def apply_forces(self, sim: Any) -> None:
        if self.phase not in ("consolidate", "shear"):
            return
        self._membrane(sim, apply=True)

    def _membrane(self, sim: Any, apply: bool) -> tuple[float, float, float]:
        """Find the outermost grain of every (θ, z) cell (globally) and, with ``apply``, load it
        (owned grains). Returns the (volume, lateral area, mean radius) of the cells."""
        p, n, live = self._own(sim)
        x, r, ids = p.x[:n][live], p.r[:n][live], p.id[:n][live]
        rows = np.flatnonzero(live)
        h = self.height()
        size = self.params.cell_size
        if size is None:  # one mean diameter (exact sums: the same on any rank count), once a stage
            if self._size is None:
                self._size = 2.0 * sim.exact_sum(r) / max(sim.count(r.size), 1)
            size = self._size
        dx = x[:, 0] - self.axis_xy[0]
        dy = x[:, 1] - self.axis_xy[1]
        rho = np.hypot(dx, dy)
        # the grid is a function of the current state only (not of earlier evaluations): cells of
        # about one `size` around the outermost radius, an exact global max
        r_out = all_max(sim.comm, float(np.max(rho + r)) if r.size else 0.0)
        nz = max(int(round(h / size)), 1)
        nt = max(int(round(2 * math.pi * r_out / size)), 6)
        theta = np.arctan2(dy, dx)
        zrel = x[:, 2] - self.bottom.reference_point[2]
        kt = np.minimum(((theta + math.pi) / (2 * math.pi) * nt).astype(np.int64), nt - 1)
        kz = np.clip((zrel / h * nz).astype(np.int64), 0, nz - 1)
        cell = kz * nt + kt
        val = rho + r
        order = np.lexsort((ids, -val, cell))
        first = np.ones(order.size, dtype=bool)
        first[1:] = cell[order][1:] != cell[order][:-1]
        win = order[first]
        local = (cell[win], val[win], ids[win])
        if sim.comm.size > 1:  # the outermost grain of a cell may be on another rank: global max
            parts = sim.comm.allgather(local)
            cells = np.concatenate([q[0] for q in parts])
            vals = np.concatenate([q[1] for q in parts])
            wids = np.concatenate([q[2] for q in parts])
            o = np.lexsort((wids, -vals, cells))
            f1 = np.ones(o.size, dtype=bool)
            f1[1:] = cells[o][1:] != cells[o][:-1]
            gcell, gval, gid = cells[o][f1], vals[o][f1], wids[o][f1]
        else:
            gcell, gval, gid = local
            o = np.argsort(gcell, kind="stable")
            gcell, gval, gid = gcell[o], gval[o], gid[o]
        R = np.full(nz * nt, np.nan)
        R[gcell] = gval
        dz = h / nz
        dth = 2 * math.pi / nt
        filled = np.isfinite(R)
        geometry = (
            float(0.5 * np.sum(R[filled] ** 2) * dth * dz),  # enclosed volume
            float(np.sum(R[filled]) * dth * dz),  # lateral area
            float(np.mean(R[filled])) if filled.any() else math.nan,  # mean radius
        )
        if not apply:  # measuring: leave the state the dynamics read untouched
            return geometry
        self._volume, self._lateral_area, self._radius = geometry
        self._cells = (nz, nt, int(filled.sum()))
        band = self.params.membrane_band * 0.5 * size
        if band > 0.0:
            # the grains within `band` of their cell's outermost share its load, weighted linearly
            # (continuous in the positions); the weights of a cell are summed in id order over the
            # gathered candidates, so every rank gets the same sums on any rank count
            near = np.flatnonzero(val > R[cell] - band)
            wt = (val[near] - (R[cell[near]] - band)) / band
            cand = (cell[near], ids[near], wt)
            if sim.comm.size > 1:
                parts = sim.comm.allgather(cand)
                cc = np.concatenate([q[0] for q in parts])
                ci = np.concatenate([q[1] for q in parts])
                cw = np.concatenate([q[2] for q in parts])
            else:
                cc, ci, cw = cand
            o = np.lexsort((ci, cc))
            total = np.zeros(nz * nt)
            np.add.at(total, cc[o], cw[o])
            w = near
            share = wt / total[cell[w]]
        else:
            # the global winners this rank owns, loaded with σ3 × their patch along the inward normal
            owner = np.full(nz * nt, -1, dtype=np.int64)
            owner[gcell] = gid
            w = win[owner[cell[win]] == ids[win]]
            share = np.ones(w.size)
        k = cell[w]
        rhat = np.stack([dx[w], dy[w], np.zeros(w.size)], axis=1) / np.maximum(rho[w], 1e-300)[:, None]
        f = -self.pressure(sim) * (share * R[k] * dth * dz)[:, None] * rhat
        p.f[rows[w]] += f
        # kept for the measurements: the load and the lever r ρ̂ of each loaded grain, and the area
        self._applied = (f, r[w][:, None] * rhat, rhat)
        self._applied_area = self._lateral_area
        return geometry

    # ------------------------------------------------------------------ measuring
    def measurements(self, sim: Any) -> dict[str, float]:
        if self.phase in ("consolidate", "shear"):
            vol, _area, radius = self._membrane(sim, apply=False)
        else:
            vol, radius = self._volume, self._radius
        h = self.height()
        area = vol / h if vol == vol and h > 0 else math.pi * self.params.radius**2
        sigma1 = float(self.top.force[2]) / area
        # realised σ3: the membrane's radial load over its lateral area (exact sum over ranks)
        fr = self._radial_membrane_load(sim)
        area3 = getattr(self, "_applied_area", 0.0)
        sigma3 = fr / area3 if area3 > 0 else math.nan
        out = {
            "sigma1": sigma1,
            "sigma3": sigma3,
            "q": sigma1 - sigma3,
            "p": (sigma1 + 2 * sigma3) / 3,
            "height": h,
            "radius": radius,
            "volume": vol,
            "eps_a": (self.h0 - h) / self.h0 if self.h0 else 0.0,
            "eps_v": (self.v0 - vol) / self.v0 if self.v0 else 0.0,
        }
        out.update(self._love_weber(sim, vol))
        # inertial number of the loading, I = ε̇ d sqrt(ρ/p) (grain density from their mass and volume)
        if self.phase == "shear" and out["p"] > 0 and self._size:
            prt = sim.particles
            n = prt.n_owned
            rho = sim.exact_sum(prt.mass[:n]) / sim.exact_sum(4.0 / 3.0 * math.pi * prt.r[:n] ** 3)
            out["inertial"] = self.params.strain_rate * self._size * math.sqrt(rho / out["p"])
        return out

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, float]:
        """Peak deviator and where, final volumetric strain, servo accuracy of σ₃ and of σ₁ at the end
        of consolidation, agreement of the boundary and Love–Weber stresses during shearing."""
        key = lambda k: series.get(f"{self.name}.{k}")  # noqa: E731
        ea, q, s1, s3 = key("eps_a"), key("q"), key("sigma1"), key("sigma3")
        if ea is None or q is None or len(ea) < 3:
            return {}
        shear = ea > 0
        out: dict[str, float] = {}
        if shear.any():
            k = int(np.nanargmax(np.where(shear, q, -np.inf)))
            out["q_peak"] = float(q[k])
            out["eps_a_at_peak"] = float(ea[k])
            out["q_over_p_peak"] = float(q[k] / key("p")[k])
            out["eps_a_final"] = float(ea[shear][-1])
            out["eps_v_final"] = float(key("eps_v")[shear][-1])
            err3 = np.abs(s3[shear] / self.params.sigma3 - 1)
            out["sigma3_error_mean"] = float(np.nanmean(err3))
            out["sigma3_error_p95"] = float(np.nanpercentile(err3, 95))
            lz, lr = key("lw_szz"), key("lw_srr")
            if lz is not None:
                # the grains' own stress against the boundary's: the realised σ₁ and σ₃
                e1, e3 = np.abs(lz[shear] / s1[shear] - 1), np.abs(lr[shear] / s3[shear] - 1)
                out["lw_sigma1_error_mean"] = float(np.nanmean(e1))
                out["lw_sigma1_error_p95"] = float(np.nanpercentile(e1, 95))
                out["lw_sigma3_error_mean"] = float(np.nanmean(e3))
                out["lw_sigma3_error_p95"] = float(np.nanpercentile(e3, 95))
            inert = key("inertial")
            if inert is not None and np.isfinite(inert[shear]).any():
                out["inertial_number_max"] = float(np.nanmax(inert[shear]))
        before = ~shear & np.isfinite(s1)
        if before.any():
            out["sigma1_end_of_consolidation"] = float(s1[before][-1])
        return out

    def _seat_stress(self) -> float:
        seat = self.params.seating_stress
        return 0.05 * self.params.sigma3 if seat is None else seat

    def pressure(self, sim: Any) -> float:
        """The membrane pressure now: σ₃, ramped over ``ramp_time`` at the start of consolidation."""
        ramp = self.params.ramp_time
        if self.phase == "consolidate" and ramp > 0:
            return self.params.sigma3 * min(1.0, (sim.time - self._stage_t0) / ramp)
        return self.params.sigma3

    def _radial_membrane_load(self, sim) -> float:
        """Σ F·(−ρ̂) of the membrane forces applied at the last evaluation (exact over ranks)."""
        f, _lever, rhat = getattr(self, "_applied", (np.zeros((0, 3)), None, np.zeros((0, 3))))
        return sim.exact_sum(-np.einsum("ij,ij->i", f, rhat))

    def _love_weber(self, sim: Any, vol: float) -> dict[str, float]:
        """Average stress of the grains, compression positive: −(1/V) Σ lever ⊗ force over every
        force on every grain (pairs: −l ⊗ f with the branch vector; platens; membrane)."""
        if not (vol == vol and vol > 0):
            return {"lw_szz": math.nan, "lw_srr": math.nan}
        parts = sim.get_particles()  # collective
        ids, x, r = parts["id"], parts["x"], parts["r"]
        c = sim.contacts()  # collective, each contact once
        s = np.zeros((3, 3))
        if len(c["id_i"]):
            xi = x[np.searchsorted(ids, c["id_i"])]
            xj = x[np.searchsorted(ids, c["id_j"])]
            s -= np.einsum("ka,kb->ab", xj - xi, c["force"])  # Σ (x_i − x_j) ⊗ f_j
        wc = sim.wall_contacts()  # collective
        names = list(sim.walls)
        for wall, sign in ((self.bottom, -1.0), (self.top, 1.0)):
            sel = wc["wall"] == names.index(wall.name)
            if not sel.any():
                continue
            rr = r[np.searchsorted(ids, wc["id"][sel])] - 0.5 * wc["overlap"][sel]
            lever = np.zeros((rr.size, 3))
            lever[:, 2] = sign * rr
            s += np.einsum("ka,kb->ab", lever, -wc["force"][sel])
        f, lever, _ = getattr(self, "_applied", (np.zeros((0, 3)), np.zeros((0, 3)), None))
        # membrane forces act on owned grains: every rank's terms, summed exactly (any rank count)
        terms = np.einsum("ka,kb->kab", lever, f).reshape(-1, 9) if len(f) else np.zeros((0, 9))
        s += np.array([sim.exact_sum(terms[:, c]) for c in range(9)]).reshape(3, 3)
        sigma = -s / vol
        return {"lw_szz": float(sigma[2, 2]), "lw_srr": float(0.5 * (sigma[0, 0] + sigma[1, 1]))}
