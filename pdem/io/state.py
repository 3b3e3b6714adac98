"""A simulation's checkpoint state: what :meth:`pdem.Simulation.state_dict` returns and
:meth:`pdem.Simulation.load_state` restores.

The state is a flat dict of arrays keyed by path (the datasets of a checkpoint file,
:mod:`pdem.io.checkpoint`): ``particles/<field>`` (every field registered with ``checkpoint``,
ordered by id; forces included: velocity Verlet starts a step from them), ``pairs/keys`` and
``pairs/hist`` (contact history keyed by id pairs), ``walls/<name>/…`` (per-wall history by row
and particle id, pose, velocity, sizes, motion state), ``scalars/…`` (time, step, dt, next id),
``stiffness/…`` (the live step bound's record), the integrator's ``solver/…`` entries and the
periodic box's ``domain/…``. It is independent of the storage order and (with MPI) of the number
of ranks: a run resumed from it continues bitwise-identically.

This module reads and writes the simulation's state through its public members; the simulation
keeps its own set-up bookkeeping (the next id, the integrator's saved counters, the preparation
that follows a restore) in :meth:`~pdem.Simulation.load_state`.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import CheckpointError
from ..geometry.walls import Controlled
from ..neighbor import _kernels as nk
from ..parallel.comm import gather_by_id
from ..state.particles import REMOVED

__all__ = ["simulation_state", "restore_simulation", "restore_forces", "CheckpointShare"]


class CheckpointShare(dict):
    """A rank's share of a checkpoint's state: its particles and their contacts only (the keys of
    :meth:`pdem.Simulation.state_dict`), plus ``layout``: the writing run's decomposition
    (``{"ranks", "dims", "cuts"}``) or None. Written by per-rank checkpoints, restored by
    :meth:`pdem.Simulation.load_state`, which places every particle on its owner."""

    layout: dict | None = None


def _history(saved, hsize: int) -> np.ndarray:
    """A checkpoint's contact history as (rows, hsize). A 2-D history narrower than the law's (a
    DEM-C checkpoint written before rolling friction: 4 columns of 8) is padded with zeros."""
    h = np.asarray(saved, dtype=np.float64)
    if h.ndim == 2 and h.shape[1] < hsize:
        return np.concatenate([h, np.zeros((h.shape[0], hsize - h.shape[1]))], axis=1)
    return h.reshape(-1, hsize)


def simulation_state(sim, local: bool = False) -> dict[str, object]:
    """The checkpoint state of ``sim`` (module docstring), prepared and checked first (collective).
    ``local``: this rank's share only (:class:`CheckpointShare`): its particles, the
    history of every pair with one of them and their wall-contact history; no particle data moves
    between ranks."""
    sim.prepare()
    sim.check_deferred()  # a checkpoint holds only a checked state
    p = sim.particles
    n = p.n_owned
    live = p.motion[:n] != REMOVED
    names = p.names(checkpoint=True)
    mine = {k: getattr(p, k)[:n][live].copy() for k in names}
    if sim.box is not None:  # wrapped (exact: the trajectory does not depend on it)
        sim.box.wrap(mine["x"])
    if local:
        order = np.argsort(mine["id"], kind="stable")
        g = {k: v[order] for k, v in mine.items()}
    else:
        g = gather_by_id(sim.comm, mine)
    out: dict[str, object] = {f"particles/{k}": g[k] for k in names}
    store = sim.contact_store
    wall_list = store.walls
    live = np.any(store.hist != 0.0, axis=1)
    keys, hist = store.keys[live], store.hist[live]
    if store.walls_changed:
        store.pack_walls()
    walls = [store.wall_history_of(k) for k in range(len(wall_list))]
    if local:  # the rows of this rank's particles (a pair across ranks is in both shares)
        ids = g["id"]
        keep = nk.keys_with_ids(keys, ids, True)
        keys, hist = keys[keep], hist[keep]
        walls = [(r[m], i[m], h[m]) for r, i, h in walls for m in [np.isin(i, ids)]]
    elif sim.comm.size > 1:
        parts = sim.comm.allgather((keys, hist, walls))
        keys = np.concatenate([q[0] for q in parts])
        hist = np.concatenate([q[1] for q in parts]).reshape(-1, store.history_size)
        walls = [
            (np.concatenate([q[2][k][0] for q in parts]),
             np.concatenate([q[2][k][1] for q in parts]),
             np.concatenate([q[2][k][2] for q in parts]).reshape(-1, store.history_size))
            for k in range(len(wall_list))
        ]  # fmt: skip
    # a pair across ranks is held by both, and a pair across the periodic boundary twice (by each
    # end's image), identically: keep one
    keys, first = np.unique(keys, return_index=True)
    hist = hist[first]
    out["pairs/keys"] = keys.copy()
    out["pairs/hist"] = hist.copy()
    for k, wall in enumerate(wall_list):
        key = f"walls/{wall.name}/"
        rows, ids, whist = walls[k]
        order = np.lexsort((ids, rows))
        out[key + "rows"] = rows[order].copy()
        out[key + "ids"] = ids[order].copy()
        out[key + "hist"] = whist[order].copy()
        out[key + "offset"] = wall.offset.copy()
        out[key + "velocity"] = wall.velocity.copy()
        out[key + "omega"] = wall.omega.copy()
        out[key + "size_rate"] = np.array(wall.size_rate)
        out[key + "rotation"] = wall.rotation.copy()
        names = sorted(wall.sizes)
        out[key + "sizes"] = np.array([wall.sizes[nm] for nm in names], float)
        out[key + "active"] = np.array(wall.active)
        for name, value in wall.motion.state().items():
            out[key + "motion/" + name] = np.asarray(value)
    out["scalars/time"] = np.array(sim.time)
    out["scalars/step"] = np.array(sim.step_count)
    out["scalars/dt"] = np.array(sim.dt)
    out["scalars/next_id"] = np.array(sim.next_id)
    for name, value in sim.stiffness.items():
        if math.isfinite(value):  # (min_dt is +inf until a bound is measured, always with DEM-C: a
            # checkpoint leaves it out, a resume starts from +inf again, and no file holds a
            # non-finite number that a failure scan would take for a blown-up state)
            out[f"stiffness/{name}"] = np.array(value)
    out.update(sim.integrator.state())  # e.g. DEM-C solver counters
    if sim.box is not None:
        out.update(sim.box.state())
    if local:
        share = CheckpointShare(out)
        share.layout = sim.decomposition_layout()
        return share
    return out


def _check_compatible(sim, state: dict[str, object]) -> None:
    """The state fits ``sim``: no particles yet, the same walls and the same periodic box."""
    if sim.particles.n_owned:
        raise CheckpointError(
            "load_state needs a simulation without particles (built from the deck "
            "without running its particle sources)"
        )
    names = set(sim.walls)
    saved = {k.split("/")[1] for k in state if k.startswith("walls/")}
    if names != saved:
        raise CheckpointError(
            f"the checkpoint's walls {sorted(saved)} differ from the deck's "
            f"{sorted(names)}; resume with the deck the checkpoint was written from"
        )
    saved = {k: np.asarray(state[k]) for k in ("domain/periodic", "domain/lo", "domain/hi") if k in state}
    mine = sim.box.state() if sim.box is not None else {}
    if saved.keys() != mine.keys() or not all(np.array_equal(saved[k], mine[k]) for k in saved):

        def show(b):
            if not b:
                return "none"
            return ", ".join(f"{k.split('/')[1]} {b[k].tolist()}" for k in sorted(b))

        raise CheckpointError(
            f"the checkpoint's periodic box ({show(saved)}) differs from this simulation's "
            f"({show(mine)}); resume with the deck (or set_periodic call) it was written with"
        )


def restore_simulation(sim, state: dict[str, object]) -> dict[str, np.ndarray]:
    """Put ``state`` into ``sim`` (built with the same materials, law, walls and periodic box but no
    particles): the particles, the contact and wall histories, the walls' poses and motions, time,
    step, dt and the live bound's record. Returns the saved particle arrays (ordered by id) for
    :func:`restore_forces`, once the simulation is prepared."""
    _check_compatible(sim, state)
    share = isinstance(state, CheckpointShare) and sim.comm.size > 1
    p = sim.particles
    g = {
        k: np.asarray(state[f"particles/{k}"])
        for k in p.names(checkpoint=True)
        if f"particles/{k}" in state  # fields registered after the checkpoint was written: defaults
    }
    p.append_owned({k: v for k, v in g.items() if k not in ("f", "t")})
    store = sim.contact_store
    hsize = store.history_size
    store.keys = np.asarray(state["pairs/keys"], dtype=np.int64)
    store.hist = _history(state.get("pairs/hist", np.zeros(0)), hsize)
    store.pi = store.pj = np.zeros(0, dtype=np.int64)
    store.key_order = None
    store.force = np.zeros((0, 3))
    store.pair_capacity = max(8 * len(g["id"]), 64)
    for k, wall in enumerate(store.walls):
        key = f"walls/{wall.name}/"
        empty = share and key + "hist" not in state  # a rank that read no part
        whist = _history(np.zeros(0) if empty else state[key + "hist"], hsize)
        ids = np.asarray(state[key + "ids"]) if key + "ids" in state else g["id"]  # dense before 0.2
        rows = np.asarray(state[key + "rows"]) if key + "rows" in state else np.zeros(len(ids), np.int64)
        store.set_wall_history(k, rows, ids, whist)
        if key + "rotation" in state:
            wall.rotation = np.array(state[key + "rotation"], dtype=float).reshape(3, 3)
            names = sorted(wall.sizes)
            sizes = (float(v) for v in np.atleast_1d(state[key + "sizes"]))
            wall.sizes.update(zip(names, sizes, strict=True))
            wall.omega = np.array(state[key + "omega"], dtype=float)
            wall.size_rate = float(state[key + "size_rate"])
        wall.set_offset(np.array(state[key + "offset"], dtype=float))
        wall.velocity = np.array(state[key + "velocity"], dtype=float)
        wall.active = bool(state[key + "active"])
        prefix = key + "motion/"
        wall.motion.restore({k2[len(prefix):]: v for k2, v in state.items() if k2.startswith(prefix)})
        if key + "motion_velocity" in state and isinstance(wall.motion, Controlled):  # before 0.2
            wall.motion.velocity = np.array(state[key + "motion_velocity"], dtype=float)
    if not share:  # (a share's rows are held once they are on their ranks: exchange.scatter)
        store.hold_restored()  # for every rebuild until the first step ends (DEM-C's wide lists)
    sim.time = float(state["scalars/time"])
    sim.step_count = int(state["scalars/step"])
    sim.dt = float(state["scalars/dt"])
    bound = {k[len("stiffness/") :]: v for k, v in state.items() if k.startswith("stiffness/")}
    sim.stiffness_monitor.restore(bound)  # (none in checkpoints before the live bound: afresh)
    return g


def restore_forces(particles, saved: dict[str, np.ndarray]) -> None:
    """The forces that start the next step are the saved ones, not a re-evaluation: copy them from
    the arrays :func:`restore_simulation` returned into the owned particles, by id."""
    p = particles
    rows = np.searchsorted(saved["id"], p.id[: p.n_owned])
    if rows.size and (rows.max() >= saved["id"].shape[0] or np.any(saved["id"][rows] != p.id[: p.n_owned])):
        raise CheckpointError("the restored particles' saved forces are not on their ranks (internal error)")
    p.f[: p.n_owned] = saved["f"][rows]
    p.t[: p.n_owned] = saved["t"][rows]
