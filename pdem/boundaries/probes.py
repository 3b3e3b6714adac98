"""Probes on chosen grains: ``type = "sensors"`` records their motion and contact forces, ``type =
"impulse"`` gives them a velocity when a stage starts (experiments.md §1, the shock wave).

**Choosing grains** (both plugins; the sensors are numbered in this order, ``s0``, ``s1``, …):

* ``ids``: grain ids (a source's grains are numbered in the order it makes them, after those of
  the tables before it; a ``hex2d`` lattice is row by row: id = first + row × n_cols + col);
* ``positions``: for each point, the grain whose centre is nearest (ties: the lowest id);
* ``line = {start, step, count}``: the points start + k step, k = 0 … count − 1, chosen like
  ``positions`` (e.g. every 10 spacings along a bed's surface).

Points are resolved once, when the boundary first becomes active (all particles of the stage
exist by then), over every rank: each rank offers its nearest owned grain per point and the lexicographic
minimum of (distance², id) wins, so the choice does not depend on the partition. Two points that pick
the same grain, an id that no grain has, a grain removed from the run are errors naming the key.

**Sensors** sample every ``every`` steps (``sim.step_count`` a multiple of it), after the step:
velocity ``vx, vy, vz`` [m/s] and ``speed``; ``f`` [N], the magnitude of the total force on the
grain (contacts with grains and walls, boundary forces, weight); ``fc`` [N], the largest normal
force among the grain's contacts with other grains (0 without one; the contact force a chain or a
force chain carries). Under MPI the owner of a grain fills its values and the others add zeros
(an ``allreduce`` of one small array per sample, x + 0 being exact): every rank holds the same
bits, on any number of ranks. Between samples a sensor costs nothing.

Each sample is a row of ``<name>.<stage>.csv`` (columns ``step``, ``time``, then ``s<k>.vx`` …
``s<k>.fc`` for every sensor; ``records = false`` turns the file off, ``quantities`` picks the
columns: a wide row costs ~1 µs a cell to write). Online, per sensor:

* **arrival**: the first time the speed exceeds ``threshold`` [m/s], linearly interpolated between
  the two samples around the crossing (and with ``force_threshold`` [N], the same for ``fc``);
* **peak**: the time of the largest speed (and of the largest ``fc``), refined by the parabola
  through the peak sample and its two neighbours (equally spaced samples), with the peak values.

``summary.json`` (``results.<name>``): per sensor, in order, ``ids``, ``positions`` (the grains'
centres when chosen), ``distance`` (from the first sensor's grain), ``arrival_time``,
``peak_time``, ``peak_speed``, ``peak_force``, ``force_peak_time`` (and ``force_arrival_time``),
null where there was none; and wave speeds: ``speed_arrival``, ``speed_peak``, ``speed_force_peak``,
the inverse slopes of least-squares lines of those times against ``distance`` over the sensors that
have one (at least two at distinct distances; null when the times do not grow, a front that crossed
every sensor within one sample, as DEM-C's does). Measured every series row: ``arrived_count`` (sensors
whose arrival was seen), ``front_distance`` (the largest distance of those) and ``max_speed``.
The online state is kept in checkpoints, so a resumed run reports the same arrival and peak times.

**Impulse**: when the first stage in which it is active starts, each chosen grain's velocity is set
to ``velocity`` [m/s] (and its spin to ``angular_velocity`` [rad/s] when given), locked components
(``fixed_translation``) staying zero; once per run (kept in checkpoints). A fixed grain cannot be
kicked (an error).

Deck::

    [boundaries.kick]
    type = "impulse"
    positions = [[0.05, 0.0, 0.0866]]       # the top-centre grain of a hex2d bed
    velocity = [0.0, 0.0, -5.0]

    [boundaries.surface]
    type = "sensors"
    line = { start = [0.05, 0.0, 0.0866], step = [0.02, 0.0, 0.0], count = 6 }
    threshold = 0.01                        # m/s
    every = 1

Both use only the public plugin API (:mod:`pdem.api`).
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from pdem.api import FIXED, REMOVED, Boundary, BoundaryParams, InputError, Loading, SceneFacts, Vec3

__all__ = ["Sensors", "SensorsParams", "Impulse", "ImpulseParams", "LineSpec", "GrainSelectionParams"]


class LineSpec(BaseModel):
    """Points ``start + k step``, k = 0 … count − 1 [m]."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    start: Vec3 = Field(description="first point [m]")
    step: Vec3 = Field(description="distance from one point to the next [m]")
    count: int = Field(ge=1, le=100_000, description="number of points")


class GrainSelectionParams(BoundaryParams):
    """Keys that choose grains: ``ids``, ``positions``, ``line`` (at least one; in that order)."""

    ids: list[int] | None = Field(default=None, description="grain ids (each ≥ 0)")
    positions: list[Vec3] | None = Field(
        default=None, description="points [m]: the grain whose centre is nearest to each (ties: lowest id)"
    )
    line: LineSpec | None = Field(
        default=None, description="points start + k step, k < count, chosen like positions"
    )

    @model_validator(mode="after")
    def _some_grains(self):
        if not (self.ids or self.positions or self.line):
            raise ValueError("choose grains with ids, positions or line (none given)")
        if self.ids is not None:
            bad = [i for i in self.ids if i < 0 or i >= 2**31]
            if bad:
                raise ValueError(f"ids: {bad[0]} is not a grain id (ids are integers from 0 to 2^31 - 1)")
            if len(set(self.ids)) != len(self.ids):
                dup = next(i for i in self.ids if self.ids.count(i) > 1)
                raise ValueError(f"ids: id {dup} is listed twice")
        return self


class SensorsParams(GrainSelectionParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "sensors"``."""

    every: int = Field(default=1, ge=1, description="steps between samples")
    threshold: float = Field(gt=0, allow_inf_nan=False, description="speed that marks the arrival [m/s]")
    force_threshold: float | None = Field(
        default=None, gt=0, allow_inf_nan=False, description="contact force fc that marks an arrival [N]"
    )
    records: bool = Field(default=True, description="write every sample to <name>.<stage>.csv")
    quantities: list[Literal["vx", "vy", "vz", "speed", "f", "fc"]] = Field(
        default=["vx", "vy", "vz", "speed", "f", "fc"],
        min_length=1,
        description="columns of <name>.<stage>.csv per sensor (arrival and peaks use speed and fc alike)",
    )


class ImpulseParams(GrainSelectionParams):
    """Keys of ``[boundaries.NAME]`` with ``type = "impulse"``."""

    velocity: Vec3 = Field(description="velocity given to each chosen grain [m/s]")
    angular_velocity: Vec3 | None = Field(default=None, description="spin given to each chosen grain [rad/s]")


# ------------------------------------------------------------------------------------- selection
def _points(params: GrainSelectionParams) -> tuple[np.ndarray, list[str]]:
    """The target points and, per point, the key that gave it (for messages)."""
    pts: list[tuple[float, float, float]] = []
    keys: list[str] = []
    for k, q in enumerate(params.positions or []):
        pts.append(tuple(q))
        keys.append(f"positions.{k}")
    if params.line is not None:
        s, d = np.asarray(params.line.start, float), np.asarray(params.line.step, float)
        for k in range(params.line.count):
            pts.append(tuple(s + k * d))
            keys.append(f"line (point {k})")
    return np.asarray(pts, dtype=float).reshape(-1, 3), keys


def select_grains(sim: Any, where: str, params: GrainSelectionParams) -> tuple[np.ndarray, np.ndarray]:
    """Ids and centres of the chosen grains, the same on every rank (collective); errors name
    ``where.<key>`` (``where`` = ``boundaries.NAME``)."""
    p = sim.particles
    n = p.n_owned
    live = p.motion[:n] != REMOVED
    own_id = p.id[:n][live]
    own_x = p.x[:n][live]
    ids: list[int] = [int(i) for i in params.ids or []]
    origin: list[str] = [f"ids.{k}" for k in range(len(ids))]
    if ids:
        want = np.asarray(ids, dtype=np.int64)
        found = np.isin(want, own_id).astype(np.int64)
        found = sim.comm.allreduce(found) if sim.comm.size > 1 else found
        if np.any(found == 0):
            k = int(np.flatnonzero(found == 0)[0])
            total = sim.count_particles()
            raise InputError(
                f"{where}.ids: no grain has id {ids[k]} (the run has {total} grains"
                + (f", ids 0 to {total - 1} unless some were removed)" if total else ")")
            )
    pts, keys = _points(params)
    for q, key in zip(pts, keys, strict=True):
        if own_id.size:
            d2 = np.sum((own_x - q) ** 2, axis=1)
            best = np.flatnonzero(d2 == d2.min())
            j = best[np.argmin(own_id[best])]
            cand = (float(d2[j]), int(own_id[j]))
        else:
            cand = (math.inf, -1)
        everyone = sim.comm.allgather(cand) if sim.comm.size > 1 else [cand]
        d2min, gid = min(everyone)
        if gid < 0:
            raise InputError(f"{where}.{key}: there are no grains to choose from")
        if gid in ids:
            other = origin[ids.index(gid)]
            raise InputError(
                f"{where}.{key}: the nearest grain to {q.tolist()} is grain {gid}, already chosen by "
                f"{other}; give points at least a grain apart"
            )
        ids.append(gid)
        origin.append(key)
    want = np.asarray(ids, dtype=np.int64)
    rows = _rows_of(p.id[:n], want)
    mine = rows >= 0
    local = (mine, p.x[rows[mine]] + 0.0)
    # before the first preparation every rank holds every particle: take the first rank's copy
    parts = sim.comm.allgather(local) if sim.comm.size > 1 else [local]
    centres = np.full((want.size, 3), np.nan)
    for has, x in parts:
        todo = has & np.isnan(centres[:, 0])
        centres[todo] = x[todo[has]]
    return want, centres


def _rows_of(own_ids: np.ndarray, want: np.ndarray) -> np.ndarray:
    """Storage row of each wanted id among ``own_ids`` (owned particles), −1 where not owned."""
    rows = np.full(want.size, -1, dtype=np.int64)
    if own_ids.size == 0 or want.size == 0:
        return rows
    order = np.argsort(own_ids, kind="stable")
    srt = own_ids[order]
    pos = np.searchsorted(srt, want)
    pos = np.minimum(pos, srt.size - 1)
    hit = srt[pos] == want
    rows[hit] = order[pos[hit]]
    return rows


# ------------------------------------------------------------------------------------- sensors
_COLUMNS = ("vx", "vy", "vz", "speed", "f", "fc")
_STATE_KEYS = (
    "arrival", "peak", "peak_t", "peak_prev", "peak_next", "peak_k",
    "f_arrival", "fpeak", "fpeak_t", "fpeak_prev", "fpeak_next", "fpeak_k",
    "last_speed", "last_fc",
)  # fmt: skip


def _parabola(t: float, a: float, b: float, c: float, dt: float) -> float:
    """Time of the vertex of the parabola through (t − dt, a), (t, b), (t + dt, c)."""
    den = a - 2.0 * b + c
    if not (math.isfinite(a) and math.isfinite(c)) or den >= 0.0:
        return t
    return t + 0.5 * (a - c) / den * dt


def _fit_speed(dist: np.ndarray, times: np.ndarray) -> float | None:
    ok = np.isfinite(times)
    if np.count_nonzero(ok) < 2 or np.ptp(dist[ok]) <= 0.0:
        return None
    slope = np.polyfit(dist[ok], times[ok], 1)[0]
    # times that do not grow beyond rounding: the front crossed every sensor within one sample
    if not slope * np.ptp(dist[ok]) > 1e-9 * np.max(np.abs(times[ok])):
        return None
    return float(1.0 / slope)


def _json(values: np.ndarray) -> list[float | None]:
    return [float(v) if math.isfinite(v) else None for v in np.asarray(values, float)]


class Sensors(Boundary):
    """See the module docstring."""

    Params = SensorsParams
    measurement_keys = ("arrived_count", "front_distance", "max_speed")

    @classmethod
    def loading(cls, name: str, params: BaseModel, facts: SceneFacts) -> list[Loading]:
        """It times a wave (whose speed the grains' stiffness sets)."""
        return [Loading(stages=tuple(facts.stages), wave=True)]

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        self.ids: np.ndarray | None = None
        self.centres: np.ndarray | None = None
        self._rows: np.ndarray | None = None
        self._rows_key: tuple | None = None
        self._pairs_key: tuple | None = None
        self._pairs: np.ndarray | None = None
        self._rows_buf: list[dict[str, float]] = []
        self._columns: list[str] | None = None
        self._last_t = math.nan
        self._k = -1  # index of the last sample
        self._dt_sample = math.nan
        self.st: dict[str, np.ndarray] = {}

    # ---------------------------------------------------------------- selection
    def on_stage(self, sim: Any, stage: str) -> None:
        super().on_stage(sim, stage)
        if self.active:
            self._resolve(sim)

    def _resolve(self, sim: Any) -> None:
        if self.ids is not None:
            return
        self.ids, self.centres = select_grains(sim, f"boundaries.{self.name}", self.params)
        s = self.ids.size
        nan = np.full(s, math.nan)
        self.st = {k: nan.copy() for k in _STATE_KEYS}
        for k in ("peak", "fpeak", "peak_k", "fpeak_k"):
            self.st[k] = np.full(s, -math.inf if k in ("peak", "fpeak") else -1.0)

    @property
    def distance(self) -> np.ndarray:
        return np.sqrt(np.sum((self.centres - self.centres[0]) ** 2, axis=1))

    def _owned_rows(self, sim: Any) -> np.ndarray:
        p = sim.particles
        n = p.n_owned
        key = (sim.n_rebuilds, n, p.n)
        rows = self._rows
        if rows is not None and key == self._rows_key:
            mine = rows >= 0
            if np.all(p.id[rows[mine]] == self.ids[mine]):  # storage unchanged since the last look
                return rows
        rows = _rows_of(p.id[:n], self.ids)
        mine = rows >= 0
        rows[mine] = np.where(p.motion[rows[mine]] == REMOVED, -1, rows[mine])
        self._rows, self._rows_key, self._pairs_key = rows, key, None
        return rows

    def _contact_force(self, sim: Any, rows: np.ndarray) -> np.ndarray:
        """Largest normal force among each owned sensor grain's grain contacts (0 if none)."""
        p = sim.particles
        cs = sim.contact_store
        fc = np.zeros(rows.size)
        mine = np.flatnonzero(rows >= 0)
        if mine.size == 0 or len(cs.pi) == 0:
            return fc
        key = (id(cs.pi), len(cs.pi), self._rows_key)
        if key != self._pairs_key:
            mark = np.full(p.n, -1, dtype=np.int64)
            mark[rows[mine]] = mine
            sel = np.flatnonzero((mark[cs.pi] >= 0) | (mark[cs.pj] >= 0))
            self._pairs, self._pairs_key, self._mark = sel, key, mark
        sel, mark = self._pairs, self._mark
        if sel.size == 0:
            return fc
        pi, pj = cs.pi[sel], cs.pj[sel]
        d = p.x[pj] - p.x[pi]
        dist = np.sqrt(np.sum(d * d, axis=1))
        fn = np.sum(cs.force[sel] * d, axis=1) / dist
        if not sim.law.rigid:  # a penalty force with a gap is stale (the pair parted)
            fn = np.where(p.r[pi] + p.r[pj] - dist > 0.0, fn, 0.0)
        for end in (mark[pi], mark[pj]):
            ok = end >= 0
            np.maximum.at(fc, end[ok], fn[ok])
        return fc

    # ---------------------------------------------------------------- sampling
    def after_step(self, sim: Any) -> None:
        if sim.step_count % self.params.every:
            return
        self._resolve(sim)
        p = sim.particles
        rows = self._owned_rows(sim)
        s = self.ids.size
        buf = np.zeros((s, 5))
        mine = rows >= 0
        r = rows[mine]
        buf[mine, 0:3] = p.v[r] + 0.0  # + 0.0: a −0.0 of the owner plus the others' 0.0 would differ
        f = p.f[r]
        buf[mine, 3] = np.sqrt(f[:, 0] * f[:, 0] + f[:, 1] * f[:, 1] + f[:, 2] * f[:, 2]) + 0.0
        buf[:, 4] = self._contact_force(sim, rows) + 0.0
        if sim.comm.size > 1:
            buf = sim.comm.allreduce(buf)
        v = buf[:, 0:3]
        speed = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
        self._update(sim.time, speed, buf[:, 4])
        if self.params.records:
            if self._columns is None:
                want = [c for c in _COLUMNS if c in self.params.quantities]
                self._columns = [f"s{k}.{c}" for k in range(s) for c in want]
                self._pick = [_COLUMNS.index(c) for c in want]
            vals = np.column_stack([v, speed, buf[:, 3:5]])[:, self._pick].ravel().tolist()
            row: dict[str, float] = {"step": int(sim.step_count), "time": sim.time}
            row.update(zip(self._columns, vals, strict=True))
            self._rows_buf.append(row)

    def _update(self, t: float, speed: np.ndarray, fc: np.ndarray) -> None:
        st, p = self.st, self.params
        self._k += 1
        k = self._k
        if math.isfinite(self._last_t):
            self._dt_sample = t - self._last_t
        t0 = self._last_t
        for val, thr, arr, last in ((speed, p.threshold, "arrival", "last_speed"),
                                    (fc, p.force_threshold, "f_arrival", "last_fc")):  # fmt: skip
            if thr is None:
                continue
            new = np.isnan(st[arr]) & (val > thr)
            for i in np.flatnonzero(new):
                a = st[last][i]
                if math.isfinite(a) and math.isfinite(t0) and val[i] > a:
                    st[arr][i] = t0 + (thr - a) / (val[i] - a) * (t - t0) if a <= thr else t0
                else:
                    st[arr][i] = t
        for val, pk, pt, prev, nxt, pk_k, last in (
            (speed, "peak", "peak_t", "peak_prev", "peak_next", "peak_k", "last_speed"),
            (fc, "fpeak", "fpeak_t", "fpeak_prev", "fpeak_next", "fpeak_k", "last_fc"),
        ):
            fill = st[pk_k] == k - 1
            st[nxt][fill] = val[fill]
            up = val > st[pk]
            st[pk][up] = val[up]
            st[pt][up] = t
            st[prev][up] = st[last][up]
            st[nxt][up] = math.nan
            st[pk_k][up] = k
            st[last][:] = val
        self._last_t = t

    def records(self, sim: Any) -> list[dict[str, float]]:
        rows, self._rows_buf = self._rows_buf, []
        return rows

    # ---------------------------------------------------------------- results
    def _refined(self, pk: str, pt: str, prev: str, nxt: str) -> np.ndarray:
        st, dt = self.st, self._dt_sample
        out = np.array(st[pt], float)
        for i in range(out.size):
            if math.isfinite(out[i]) and math.isfinite(dt):
                out[i] = _parabola(out[i], st[prev][i], st[pk][i], st[nxt][i], dt)
        return out

    def measurements(self, sim: Any) -> dict[str, float]:
        if self.ids is None:
            return {"arrived_count": 0.0, "front_distance": 0.0, "max_speed": 0.0}
        arrived = np.isfinite(self.st["arrival"])
        return {
            "arrived_count": float(np.count_nonzero(arrived)),
            "front_distance": float(self.distance[arrived].max()) if arrived.any() else 0.0,
            "max_speed": float(np.max(self.st["last_speed"])) if self._k >= 0 else 0.0,
        }

    def summary(self, series: dict[str, np.ndarray]) -> dict[str, Any]:
        if self.ids is None:
            return {}
        st = self.st
        dist = self.distance
        peak_t = self._refined("peak", "peak_t", "peak_prev", "peak_next")
        fpeak_t = self._refined("fpeak", "fpeak_t", "fpeak_prev", "fpeak_next")
        peak = np.where(np.isfinite(st["peak"]), st["peak"], math.nan)
        fpeak = np.where(np.isfinite(st["fpeak"]), st["fpeak"], math.nan)
        peak_t = np.where(peak > 0, peak_t, math.nan)
        fpeak_t = np.where(fpeak > 0, fpeak_t, math.nan)
        out: dict[str, Any] = {
            "ids": [int(i) for i in self.ids],
            "positions": [[float(c) for c in x] for x in self.centres],
            "distance": _json(dist),
            "arrival_time": _json(st["arrival"]),
            "peak_time": _json(peak_t),
            "peak_speed": _json(peak),
            "peak_force": _json(fpeak),
            "force_peak_time": _json(fpeak_t),
            "speed_arrival": _fit_speed(dist, st["arrival"]),
            "speed_peak": _fit_speed(dist, peak_t),
            "speed_force_peak": _fit_speed(dist, fpeak_t),
        }
        if self.params.force_threshold is not None:
            out["force_arrival_time"] = _json(st["f_arrival"])
            out["speed_force_arrival"] = _fit_speed(dist, st["f_arrival"])
        return out

    # ---------------------------------------------------------------- checkpoints
    def state(self) -> dict[str, Any]:
        if self.ids is None:
            return {}
        return {
            "ids": [int(i) for i in self.ids],
            "centres": self.centres.tolist(),
            "k": self._k,
            "last_t": None if not math.isfinite(self._last_t) else self._last_t,
            "dt_sample": None if not math.isfinite(self._dt_sample) else self._dt_sample,
            "st": {k: [None if not math.isfinite(x) else float(x) for x in v] for k, v in self.st.items()},
            "inf": {k: [bool(np.isinf(x)) for x in v] for k, v in self.st.items()},
        }

    def restore(self, state: dict[str, Any]) -> None:
        if not state:
            return
        self.ids = np.asarray(state["ids"], dtype=np.int64)
        self.centres = np.asarray(state["centres"], dtype=float).reshape(-1, 3)
        self._k = int(state["k"])
        self._last_t = math.nan if state["last_t"] is None else float(state["last_t"])
        self._dt_sample = math.nan if state["dt_sample"] is None else float(state["dt_sample"])
        self.st = {}
        for k, vals in state["st"].items():
            inf = state["inf"][k]
            self.st[k] = np.array(
                [(-math.inf if i else math.nan) if x is None else x for x, i in zip(vals, inf, strict=True)],
                dtype=float,
            )


# ------------------------------------------------------------------------------------- impulse
class Impulse(Boundary):
    """See the module docstring."""

    Params = ImpulseParams

    @classmethod
    def loading(cls, name: str, params: BaseModel, facts: SceneFacts) -> list[Loading]:
        """It strikes grains at ``velocity`` and launches a wave (whose speed the stiffness sets)."""
        speed = float(np.linalg.norm(np.asarray(params.velocity, dtype=float)))
        return [Loading(stages=tuple(facts.stages), speed=speed, speed_from=f"boundaries.{name}.velocity",
                        wave=True)]  # fmt: skip

    def __init__(self, name: str, params: BoundaryParams) -> None:
        super().__init__(name, params)
        self.applied = False
        self.ids: list[int] = []

    def on_stage(self, sim: Any, stage: str) -> None:
        super().on_stage(sim, stage)
        if self.active and not self.applied:
            self.kick(sim)

    def kick(self, sim: Any) -> None:
        """Set the chosen grains' velocities (collective)."""
        where = f"boundaries.{self.name}"
        ids, _ = select_grains(sim, where, self.params)
        p = sim.particles
        n = p.n_owned
        rows = _rows_of(p.id[:n], ids)
        r = rows[rows >= 0]
        fixed = int(np.count_nonzero(p.motion[r] == FIXED))
        if sim.count(fixed):
            raise InputError(
                f"{where}: a chosen grain is fixed (motion 'fixed'): it cannot be given a velocity"
            )
        vel = np.asarray(self.params.velocity, float)
        p.v[r] = vel
        if self.params.angular_velocity is not None:
            p.w[r] = np.asarray(self.params.angular_velocity, float)
        for c in range(3):  # locked components stay zero
            p.v[r[(p.dof[r] >> c) & 1 == 1], c] = 0.0
            p.w[r[(p.dof[r] >> (3 + c)) & 1 == 1], c] = 0.0
        self.ids = [int(i) for i in ids]
        self.applied = True

    def state(self) -> dict[str, Any]:
        return {"applied": self.applied, "ids": self.ids}

    def restore(self, state: dict[str, Any]) -> None:
        self.applied = bool(state.get("applied", False))
        self.ids = list(state.get("ids", []))
