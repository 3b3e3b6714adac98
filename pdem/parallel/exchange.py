"""Particle migration and ghost exchange between neighbouring subdomains (x, then y, then z).

* :func:`migrate` (at neighbour-list rebuilds): particles whose centres left this subdomain move to
  the neighbour, one axis after the other, so a particle crossing an edge or a corner arrives in
  three hops. Each carries its fields, its per-wall contact history and the history rows of every
  pair it belongs to (keyed by id pair), so the receiving rank continues its contacts exactly.
* :func:`borders` (after migration): copies of particles within the ghost width of a face are sent
  to the neighbour behind it; ghosts received along x are forwarded along y and z, which covers edges
  and corners. The send lists are kept.
* :func:`forward` (every other step): the same lists carry the ghosts' current x, v, ω.

Contacts between an owned particle and a ghost are computed on both ranks, identically, and each
rank applies the result to its own particle only ("newton off" across ranks).
"""

from __future__ import annotations

import numpy as np

__all__ = ["migrate", "borders", "forward"]

_FIELDS = ("id", "x", "v", "w", "f", "t", "r", "mass", "inv_m", "inv_i", "mat", "motion", "x_build")
_GHOST_FIELDS = ("id", "x", "v", "w", "r", "mass", "inv_m", "inv_i", "mat", "motion")


def _sendrecv(comm, obj, dest, source):
    from mpi4py import MPI

    return comm.sendrecv(
        obj, dest=MPI.PROC_NULL if dest is None else dest, source=MPI.PROC_NULL if source is None else source
    )


def migrate(sim) -> None:
    """Move owned particles that left this subdomain to their new owners (collective).

    One pass moves a particle by one subdomain along each axis; passes repeat until every particle is
    home (after a rebalance cut planes can move by several subdomains)."""
    from .comm import any_rank

    dec = sim._decomp
    p = sim.particles
    p.n_ghost = 0
    while True:
        _migrate_pass(sim)
        n = p.n_owned
        if not any_rank(dec.comm, not bool(np.all(dec.owned_mask(p.x[:n])))):
            return


def _migrate_pass(sim) -> None:
    dec = sim._decomp
    p = sim.particles
    for d in range(3):
        lower, upper = dec.neighbours[d]
        n = p.n_owned
        x = p.x[:n, d]
        go_down = x < dec.sub_lo[d] if lower is not None else np.zeros(n, bool)
        go_up = x >= dec.sub_hi[d] if upper is not None else np.zeros(n, bool)
        down = _pack(sim, np.flatnonzero(go_down))
        up = _pack(sim, np.flatnonzero(go_up))
        _remove(sim, go_down | go_up)
        if lower is None and upper is None:
            continue
        from_up = _sendrecv(dec.comm, down, lower, upper)
        from_down = _sendrecv(dec.comm, up, upper, lower)
        for parcel in (from_down, from_up):
            if parcel is not None and len(parcel["id"]):
                _unpack(sim, parcel)


def _pack(sim, idx: np.ndarray) -> dict:
    p = sim.particles
    out = {k: getattr(p, k)[idx].copy() for k in _FIELDS}
    out["wall_hist"] = sim._wall_hist[:, idx, :].copy() if len(sim._wall_list) else None
    keys = sim._pair_keys
    if len(idx) and keys.size:
        ids = out["id"]
        rows = np.isin(keys >> 32, ids) | np.isin(keys & 0xFFFFFFFF, ids)
        out["pair_keys"] = keys[rows].copy()
        out["pair_hist"] = sim._pair_hist[rows].copy()
    else:
        out["pair_keys"] = np.zeros(0, dtype=np.int64)
        out["pair_hist"] = np.zeros((0, sim._pair_hist.shape[1]))
    return out


def _remove(sim, mask: np.ndarray) -> None:
    p = sim.particles
    n = p.n_owned
    k = int(mask.sum())
    if k == 0:
        return
    sim._permute_storage(np.concatenate([np.flatnonzero(~mask), np.flatnonzero(mask)]))
    if len(sim._wall_list):
        sim._wall_hist[:, n - k : n, :] = 0.0
    p.n_owned = n - k


def _unpack(sim, parcel: dict) -> None:
    p = sim.particles
    n0 = p.n_owned
    k = len(parcel["id"])
    p.append_owned(
        parcel["id"],
        parcel["x"],
        parcel["v"],
        parcel["w"],
        parcel["r"],
        parcel["mass"],
        parcel["inv_m"],
        parcel["inv_i"],
        parcel["mat"],
        parcel["motion"],
    )
    p.f[n0 : n0 + k] = parcel["f"]
    p.t[n0 : n0 + k] = parcel["t"]
    p.x_build[n0 : n0 + k] = parcel["x_build"]
    if len(sim._wall_list):
        sim._allocate_wall_history(p.n_owned, sim._pair_hist.shape[1])
        sim._wall_hist[:, n0 : n0 + k, :] = parcel["wall_hist"]
    if parcel["pair_keys"].size:
        keys = np.concatenate([sim._pair_keys, parcel["pair_keys"]])
        hist = np.concatenate([sim._pair_hist, parcel["pair_hist"]])
        order = np.argsort(keys, kind="stable")
        keys, hist = keys[order], hist[order]
        first = np.ones(keys.shape[0], dtype=bool)
        first[1:] = keys[1:] != keys[:-1]
        sim._pair_keys, sim._pair_hist = keys[first], hist[first]


def borders(sim, width: float) -> None:
    """Receive ghost copies of the particles within ``width`` of this subdomain (collective)."""
    dec = sim._decomp
    p = sim.particles
    swaps = []
    for d in range(3):
        lower, upper = dec.neighbours[d]
        n = p.n  # owned + ghosts of previous axes: forwarding covers edges and corners
        x = p.x[:n, d]
        to_lower = np.flatnonzero(x < dec.sub_lo[d] + width) if lower is not None else np.zeros(0, np.int64)
        to_upper = np.flatnonzero(x >= dec.sub_hi[d] - width) if upper is not None else np.zeros(0, np.int64)
        recv = []
        for send_idx, dest, source in ((to_lower, lower, upper), (to_upper, upper, lower)):
            parcel = {k: getattr(p, k)[send_idx].copy() for k in _GHOST_FIELDS} if dest is not None else None
            got = (
                _sendrecv(dec.comm, parcel, dest, source)
                if (dest is not None or source is not None)
                else None
            )
            recv.append(got)
            swaps.append([send_idx, dest, source, 0, 0])
        for got, swap in zip(recv, swaps[-2:], strict=True):
            start = p.n
            if got is not None and len(got["id"]):
                _append_ghosts(p, got)
            swap[3], swap[4] = start, p.n
    sim._swaps = swaps


def _append_ghosts(p, got: dict) -> None:
    n0 = p.n
    k = len(got["id"])
    p.reserve(n0 + k)
    p.n_ghost = p.n_ghost + k
    for name in _GHOST_FIELDS:
        getattr(p, name)[n0 : n0 + k] = got[name]
    p.f[n0 : n0 + k] = 0.0
    p.t[n0 : n0 + k] = 0.0


def forward(sim) -> None:
    """Send the ghosts' current positions, velocities and spins along the recorded swaps.

    The two swaps of an axis read only data from before that axis, so they run concurrently
    (non-blocking receives and sends, then one wait): a sequential exchange in alternating
    directions cost a rendezvous round trip per swap (~200 µs per step on 2 ranks, against ~20 µs
    now). Buffers hold (k, 9) floats; swaps with no partner cost nothing."""
    from mpi4py import MPI

    comm = sim._decomp.comm
    p = sim.particles
    x, v, w = p.x, p.v, p.w
    swaps = sim._swaps
    for a in range(0, len(swaps), 2):
        requests = []
        received = []
        for _send_idx, _dest, source, start, end in swaps[a : a + 2]:
            if source is not None and end > start:
                buf = np.empty((end - start, 9))
                requests.append(comm.Irecv(buf, source=source))
                received.append((buf, start, end))
        for send_idx, dest, _source, _start, _end in swaps[a : a + 2]:
            # the receiver posts a receive only for a non-empty swap (its count was set by borders)
            if dest is not None and send_idx.shape[0] > 0:
                buf = np.empty((send_idx.shape[0], 9))
                buf[:, 0:3] = x[send_idx]
                buf[:, 3:6] = v[send_idx]
                buf[:, 6:9] = w[send_idx]
                requests.append(comm.Isend(buf, dest=dest))
                received.append((buf, -1, -1))  # keep the send buffer alive until Waitall
        if requests:
            MPI.Request.Waitall(requests)
        for buf, start, end in received:
            if start >= 0:
                x[start:end] = buf[:, 0:3]
                v[start:end] = buf[:, 3:6]
                w[start:end] = buf[:, 6:9]
