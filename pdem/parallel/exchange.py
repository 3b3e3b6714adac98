"""Particle migration and ghost exchange between neighbouring subdomains (x, then y, then z).

* :func:`migrate` (at neighbour-list rebuilds): particles whose centres left this subdomain move to
  the neighbour, one axis after the other, so a particle crossing an edge or a corner arrives in
  three hops. Each carries its fields, its per-wall contact history and the history rows of every
  pair it belongs to (keyed by id pair), so the receiving rank continues its contacts exactly.
* :func:`borders` (after migration): copies of particles within the ghost width of a face are sent
  to the neighbour behind it; ghosts received along x are forwarded along y and z, which covers edges
  and corners. The send lists are kept.
* :func:`forward` (every step without a rebuild): the same lists carry the ghosts' current x, v, ω
  (or v, ω only, between DEM-C's solver sweeps), with buffers and the message plan set up once per
  list (:class:`_ForwardPlan`; the requests are posted at every call).

Contacts between an owned particle and a ghost are computed on both ranks, identically, and each
rank applies the result to its own particle only ("newton off" across ranks).

Periodic boundaries go through the same three functions: a ghost sent across the periodic boundary
(down from the first subdomain along a periodic axis, or up from the last) is shifted by ±L on the
way (exactly: positions sit on the grid of :mod:`pdem.domain`). When an axis is not split, the rank
is its own neighbour and the "message" is a local copy; this is also how a serial periodic run makes
its images. Migration does not wrap: the simulation wraps owned positions into the box first (an
exact operation), and particles then travel to their owner through the interior or across the
periodic boundary, whichever is shorter.
"""

from __future__ import annotations

import numpy as np

from ._kernels import pack_vw, pack_xvw, unpack_vw, unpack_xvw

__all__ = ["migrate", "scatter", "borders", "forward", "forward_values"]

# Which fields travel is the particle store's registry (pdem.state.particles.Field: migrate, ghost);
# contact history travels with the particles through the contact store (rows keyed by ids).


def _sendrecv(dec, obj, dest, source, tag):
    """Exchange with neighbours (``None``: no neighbour); to oneself it is a local hand-over."""
    if dest is not None and dest == source == dec.rank:
        return obj
    from mpi4py import MPI

    return dec.comm.sendrecv(
        obj,
        dest=MPI.PROC_NULL if dest is None else dest,
        sendtag=tag,
        source=MPI.PROC_NULL if source is None else source,
        recvtag=tag,
    )


def migrate(sim) -> None:
    """Move owned particles that left this subdomain to their new owners (collective).

    One pass moves a particle by one subdomain along each axis; passes repeat until every particle is
    home (after a rebalance cut planes can move by several subdomains)."""
    from .comm import any_rank

    dec = sim.decomposition
    p = sim.particles
    p.n_ghost = 0
    while True:
        _migrate_pass(sim)
        n = p.n_owned
        if not any_rank(dec.comm, not bool(np.all(dec.owned_mask(p.x[:n])))):
            return


def _migrate_pass(sim) -> None:
    dec = sim.decomposition
    p = sim.particles
    for d in range(3):
        lower, upper = dec.neighbours[d]
        if dec.dims[d] == 1:  # one subdomain along d: everything is home along this axis
            continue
        n = p.n_owned
        target = dec.axis_coords(p.x[:n, d], d)
        mine = dec.coords[d]
        if dec.periodic[d]:  # the shorter way round (positions are already wrapped into the box)
            k = dec.dims[d]
            ahead = (target - mine) % k
            go_up = (ahead >= 1) & (ahead <= k // 2)
            go_down = ahead > k // 2
        else:
            go_down = target < mine
            go_up = target > mine
        down = _pack(sim, np.flatnonzero(go_down))
        up = _pack(sim, np.flatnonzero(go_up))
        _remove(sim, go_down | go_up)
        from_up = _sendrecv(dec, down, lower, upper, 0)
        from_down = _sendrecv(dec, up, upper, lower, 1)
        for parcel in (from_down, from_up):
            if parcel is not None and len(parcel["id"]):
                _unpack(sim, parcel)


def scatter(sim, saved: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Send every owned particle to the rank that owns its position, in one all-to-all (collective):
    the start of a run from a checkpoint read back in shares, whose particles sit on the ranks that
    read them, anywhere in space. Each carries its fields, the history rows of its pairs and wall
    contacts, and its saved force and torque (``saved``: ``id``, ``f``, ``t`` of the owned rows, in
    storage order); returns the saved forces of the particles now owned, ordered by id.

    No rank receives more than its own particles and their rows, so no rank ever holds all of them;
    the received history is then held as a restored checkpoint's
    (:meth:`pdem.contact.store.ContactStore.adopt_received`)."""
    dec = sim.decomposition
    p = sim.particles
    store = sim.contact_store
    n = p.n_owned
    if not np.array_equal(saved.get("id", np.zeros(0, np.int64)), p.id[:n]):
        raise RuntimeError("scatter: the saved forces are not in storage order")
    dest = dec.owner(p.x[:n]) if n else np.zeros(0, dtype=np.int64)
    names = p.names(migrate=True)
    saved = {k: np.asarray(saved.get(k, np.zeros((0, 3)))).reshape(-1, 3) for k in ("f", "t")}  # (none read)
    parcels = []
    for r in range(dec.comm.size):
        idx = np.flatnonzero(dest == r)
        parcel = _pack(sim, idx)
        parcel["saved_f"] = saved["f"][idx]
        parcel["saved_t"] = saved["t"][idx]
        parcels.append(parcel)
    received = dec.comm.alltoall(parcels) if dec.comm.size > 1 else parcels
    del parcels
    p.n_owned = 0
    store.clear_rows()
    for parcel in received:
        p.append_owned({k: v for k, v in parcel.items() if k in names})
        store.merge(parcel)
    store.adopt_received()
    ids = p.id[: p.n_owned].copy()
    order = np.argsort(ids, kind="stable")
    forces = [np.concatenate([q[k] for q in received]).reshape(-1, 3) for k in ("saved_f", "saved_t")]
    return {"id": ids[order], "f": forces[0][order], "t": forces[1][order]}


def _pack(sim, idx: np.ndarray) -> dict:
    p = sim.particles
    out = p.take(idx, p.names(migrate=True))
    out.update(sim.contact_store.rows_of(out["id"]))
    return out


def _remove(sim, mask: np.ndarray) -> None:
    """Drop the owned rows in ``mask`` (already packed): the staying rows past the first n − k
    fill the leavers' rows, which end up behind the owned ones. Only those rows move (a stable
    compaction had reordered every field of every particle, ~0.7 ms on 10,000 particles at each
    migration with departures). Storage order never changes results; DEM-P re-sorts it in space
    when its pairs drift apart, DEM-C sorts it by id
    (:meth:`pdem.neighbor.list.NeighbourList.order_storage`)."""
    p = sim.particles
    n = p.n_owned
    k = int(mask.sum())
    if k == 0:
        return
    keep = n - k
    holes = np.flatnonzero(mask[:keep])
    movers = keep + np.flatnonzero(~mask[keep:n])
    p.swap_rows(holes, movers)
    p.n_owned = keep


def _unpack(sim, parcel: dict) -> None:
    p = sim.particles
    p.append_owned({k: v for k, v in parcel.items() if k in p.fields})
    sim.contact_store.merge(parcel)


def borders(sim, width: float) -> None:
    """Receive ghost copies of the particles within ``width`` of this subdomain (collective).

    Each swap is recorded as ``[send_idx, dest, source, start, end, axis, shift]``: the ghosts it
    delivers occupy ``[start, end)``, and ``shift`` (±L or 0) is added to the sent coordinate along
    ``axis`` (a ghost crossing the periodic boundary)."""
    dec = sim.decomposition
    p = sim.particles
    ghost_fields = p.names(ghost=True)
    swaps = []
    for d in range(3):
        lower, upper = dec.neighbours[d]
        if lower is None and upper is None:
            continue
        n = p.n  # owned + ghosts of previous axes: forwarding covers edges and corners
        x = p.x[:n, d]
        to_lower = np.flatnonzero(x < dec.sub_lo[d] + width) if lower is not None else np.zeros(0, np.int64)
        to_upper = np.flatnonzero(x >= dec.sub_hi[d] - width) if upper is not None else np.zeros(0, np.int64)
        recv = []
        for tag, (send_idx, dest, source, shift) in enumerate(
            ((to_lower, lower, upper, dec.shift_down[d]), (to_upper, upper, lower, dec.shift_up[d]))
        ):
            parcel = None
            if dest is not None:
                parcel = p.take(send_idx, ghost_fields)
                if shift != 0.0:
                    parcel["x"][:, d] += shift  # exact on the periodic position grid
            got = _sendrecv(dec, parcel, dest, source, tag)
            recv.append(got)
            swaps.append([send_idx, dest, source, 0, 0, d, shift])
        for got, swap in zip(recv, swaps[-2:], strict=True):
            start = p.n
            if got is not None and len(got["id"]):
                p.append_ghosts(got)
            swap[3], swap[4] = start, p.n
    dec.swaps = swaps


class _ForwardPlan:
    """The messages of :func:`forward` for one set of swaps (they change only at rebuilds): per axis,
    the local copies, and the receives and sends with their partners, tags and buffers. Building
    them anew at every call cost several µs of Python per forward; DEM-C forwards at every solver
    sweep."""

    def __init__(self, dec, width: int) -> None:
        self.swaps = dec.swaps  # identity: a new list at every borders()
        self.axes = []
        for a in range(0, len(dec.swaps), 2):
            local, sends, recvs = [], [], []
            for tag, (send_idx, dest, source, start, end, d, shift) in enumerate(dec.swaps[a : a + 2]):
                if dest is not None and dest == source == dec.rank:  # our own images
                    if end > start:
                        local.append((send_idx, d, shift, np.empty((end - start, width)), start))
                    continue
                if source is not None and end > start:
                    recvs.append((np.empty((end - start, width)), start, source, tag))
                # the receiver posts a receive only for a non-empty swap (its count was set by borders)
                if dest is not None and send_idx.shape[0] > 0:
                    sends.append((send_idx, d, shift, np.empty((send_idx.shape[0], width)), dest, tag))
            self.axes.append((local, sends, recvs))


def _forward_plan(dec, width: int) -> _ForwardPlan:
    plans = getattr(dec, "_forward_plans", None)
    if plans is None:
        plans = dec._forward_plans = {}
    plan = plans.get(width)
    if plan is None or plan.swaps is not dec.swaps:
        plan = plans[width] = _ForwardPlan(dec, width)
    return plan


def forward(sim, positions: bool = True) -> None:
    """Send the ghosts' current positions, velocities and spins along the recorded swaps (without
    ``positions``: velocities and spins only, for callers that have not moved any particle since
    the last forward, e.g. DEM-C's solver sweeps).

    The two swaps of an axis read only data from before that axis, so they run concurrently
    (non-blocking receives and sends, then one wait): a sequential exchange in alternating
    directions cost a rendezvous round trip per swap (~200 µs per step on 2 ranks, against ~20 µs
    now). Buffers hold (k, 9) floats ((k, 6) without positions) and are kept with the swaps
    (:class:`_ForwardPlan`); swaps with no partner cost nothing; a swap with oneself (an unsplit
    periodic axis) is a local copy. Messages are tagged by swap direction, because along a periodic
    axis split in two both swaps have the same partner."""
    dec = sim.decomposition
    comm = dec.comm
    p = sim.particles
    x, v, w = p.x, p.v, p.w
    for local, sends, recvs in _forward_plan(dec, 9 if positions else 6).axes:
        for send_idx, d, shift, buf, start in local:
            if positions:
                pack_xvw(x, v, w, send_idx, d, shift, buf)
                unpack_xvw(buf, start, x, v, w)
            else:
                pack_vw(v, w, send_idx, buf)
                unpack_vw(buf, start, v, w)
        if not (sends or recvs):
            continue
        requests = [comm.Irecv(buf, source=source, tag=tag) for buf, _start, source, tag in recvs]
        for send_idx, d, shift, buf, dest, tag in sends:
            if positions:
                pack_xvw(x, v, w, send_idx, d, shift, buf)
            else:
                pack_vw(v, w, send_idx, buf)
            requests.append(comm.Isend(buf, dest=dest, tag=tag))
        from mpi4py import MPI

        MPI.Request.Waitall(requests)
        for buf, start, _source, _tag in recvs:
            if positions:
                unpack_xvw(buf, start, x, v, w)
            else:
                unpack_vw(buf, start, v, w)


def forward_values(sim, values: np.ndarray) -> None:
    """Send the owners' entries of a per-particle array (``values[i]`` for particle row i, owned and
    ghosts; floats) to their ghost copies along the recorded swaps, as :func:`forward` does for x,
    v, ω (no periodic shift: the values are not positions). Collective; a serial run without
    periodic images has no ghosts and does nothing."""
    dec = sim.decomposition
    if dec is None:
        return
    comm = dec.comm
    swaps = dec.swaps
    for a in range(0, len(swaps), 2):
        requests = []
        received = []
        for tag, (send_idx, dest, source, start, end, _d, _shift) in enumerate(swaps[a : a + 2]):
            if dest is not None and dest == source == dec.rank:  # our own images
                if end > start:
                    values[start:end] = values[send_idx]
                continue
            if source is not None and end > start:
                buf = np.empty(end - start)
                requests.append(comm.Irecv(buf, source=source, tag=tag))
                received.append((buf, start, end))
        for tag, (send_idx, dest, source, _start, _end, _d, _shift) in enumerate(swaps[a : a + 2]):
            if dest is not None and dest == source == dec.rank:
                continue
            if dest is not None and send_idx.shape[0] > 0:
                buf = np.ascontiguousarray(values[send_idx], dtype=float)
                requests.append(comm.Isend(buf, dest=dest, tag=tag))
                received.append((buf, -1, -1))
        if requests:
            from mpi4py import MPI

            MPI.Request.Waitall(requests)
        for buf, start, end in received:
            if start >= 0:
                values[start:end] = buf
