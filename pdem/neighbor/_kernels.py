"""Cell-grid + Verlet-list kernels (arrays in, arrays out; problems reported, never raised).

The pair list holds each pair once, as local indices (i, j) with id[i] < id[j], sorted by
(id[i], id[j]). A pair is listed when the centre distance is below r_i + r_j + skin and at least one
of the two particles is owned (local index < n_owned); ghosts follow the owned particles.
"""

from __future__ import annotations

import math

import numpy as np

from .._jit import njit


@njit
def bin_particles(x, n, lo, inv_cell, dims):
    """Counting sort of particles 0..n-1 into cells: returns (cell_start, cell_items)."""
    ncell = dims[0] * dims[1] * dims[2]
    cell_of = np.empty(n, dtype=np.int64)
    counts = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        cx = min(max(int((x[i, 0] - lo[0]) * inv_cell), 0), dims[0] - 1)
        cy = min(max(int((x[i, 1] - lo[1]) * inv_cell), 0), dims[1] - 1)
        cz = min(max(int((x[i, 2] - lo[2]) * inv_cell), 0), dims[2] - 1)
        c = (cz * dims[1] + cy) * dims[0] + cx
        cell_of[i] = c
        counts[c + 1] += 1
    for c in range(ncell):
        counts[c + 1] += counts[c]
    fill = counts[:-1].copy()
    items = np.empty(n, dtype=np.int64)
    for i in range(n):
        c = cell_of[i]
        items[fill[c]] = i
        fill[c] += 1
    return counts, items


@njit
def bounds(x, n):
    """(lo, hi): the componentwise minimum and maximum of x[:n] (n ≥ 1), NaN where a component has
    a NaN, as ``x[:n].min(axis=0)`` and ``max(axis=0)`` give them (~80 µs a call on 4,000 rows,
    against a few µs here; each rebuild asked four times)."""
    lo = x[0, :3].copy()
    hi = x[0, :3].copy()
    for i in range(1, n):
        for k in range(3):
            v = x[i, k]  # a NaN, once taken, stays (comparisons with it are false)
            if lo[k] == lo[k] and (v < lo[k] or v != v):
                lo[k] = v
            if hi[k] == hi[k] and (v > hi[k] or v != v):
                hi[k] = v
    return lo, hi


@njit
def id_order(ids, n):
    """The rows ``0..n-1`` sorted by ``ids`` (distinct integers): a radix sort by 11-bit digits of
    ``id - min``, as many passes as its largest value needs (2 below 4 million). ``np.argsort``
    took 1.1 ms on 18,000 ids in random order (0.19 ms sorted), this 0.1 ms either way."""
    order = np.arange(n)
    if n < 2:
        return order
    lo = ids[0]
    hi = ids[0]
    for q in range(n):
        lo = min(lo, ids[q])
        hi = max(hi, ids[q])
    span = hi - lo
    src = order
    dst = np.empty(n, dtype=np.int64)
    count = np.empty(2049, dtype=np.int64)
    shift = 0
    while True:  # least significant digit first; each pass is stable
        count[:] = 0
        for q in range(n):
            count[((ids[src[q]] - lo) >> shift & 2047) + 1] += 1
        for c in range(2048):
            count[c + 1] += count[c]
        for q in range(n):
            row = src[q]
            d = (ids[row] - lo) >> shift & 2047
            dst[count[d]] = row
            count[d] += 1
        src, dst = dst, src
        shift += 11
        if span >> shift == 0:
            return src


@njit
def build_pairs(x, r, ids, n_owned, n, skin, lo, inv_cell, dims, capacity):
    """Verlet pair list sorted by (lower id, higher id).

    Returns (pi, pj, count). If ``count > capacity`` the arrays (of ``capacity`` entries) hold nothing
    usable and the caller must retry with a capacity of at least ``count``.
    """
    cell_start, cell_items = bin_particles(x, n, lo, inv_cell, dims)
    # positions, radii and ids copied in cell order: the neighbour cells' particles are then read
    # from contiguous memory instead of scattered rows (the storage need not follow space; the
    # scattered reads made a build ~1.2 µs per particle on the hopper). The same candidates in the
    # same order: the same list, bit for bit
    xs = np.empty((n, 3))
    rs = np.empty(n)
    ids_s = np.empty(n, dtype=np.int64)
    own_s = np.empty(n, dtype=np.bool_)
    for s in range(n):
        j = cell_items[s]
        xs[s, 0] = x[j, 0]
        xs[s, 1] = x[j, 1]
        xs[s, 2] = x[j, 2]
        rs[s] = r[j]
        ids_s[s] = ids[j]
        own_s[s] = j < n_owned
    # particles visited in cell order (consecutive ones scan overlapping cells, which stay in cache;
    # a visit in id order read the cells of a random place at each particle when ids are scattered in
    # space: 9.0 against 6.2 ms a build on the 18k column read from a file in random row order). Each
    # particle's partners go to its own segment of ``seg``; the list is then written in id order
    start = np.empty(n, dtype=np.int64)
    size = np.empty(n, dtype=np.int64)
    seg = np.empty(capacity, dtype=np.int64)
    # room for every particle of 27 cells: no growth inside the loop (an array re-bound there made
    # numba count references at every candidate, ~45 % of a build)
    most = 1
    for c in range(cell_start.shape[0] - 1):
        most = max(most, cell_start[c + 1] - cell_start[c])
    cand = np.empty(27 * most, dtype=np.int64)
    cand_id = np.empty(27 * most, dtype=np.int64)
    count = 0
    for q in range(n):
        i = cell_items[q]
        idi = ids_s[q]
        xi0 = xs[q, 0]
        xi1 = xs[q, 1]
        xi2 = xs[q, 2]
        ri = rs[q]
        ghost_i = not own_s[q]
        cx = min(max(int((xi0 - lo[0]) * inv_cell), 0), dims[0] - 1)
        cy = min(max(int((xi1 - lo[1]) * inv_cell), 0), dims[1] - 1)
        cz = min(max(int((xi2 - lo[2]) * inv_cell), 0), dims[2] - 1)
        nc = 0
        ex0 = max(cx - 1, 0)
        ex1 = min(cx + 1, dims[0] - 1)
        for ez in range(max(cz - 1, 0), min(cz + 2, dims[2])):
            for ey in range(max(cy - 1, 0), min(cy + 2, dims[1])):
                # a row's three cells are consecutive, and so are their particles (in cell order):
                # one loop over them instead of three short ones (their exits were mispredicted)
                row = (ez * dims[1] + ey) * dims[0]
                for s in range(cell_start[row + ex0], cell_start[row + ex1 + 1]):
                    idj = ids_s[s]
                    if idj <= idi or (ghost_i and not own_s[s]):
                        continue
                    dx = xs[s, 0] - xi0
                    dy = xs[s, 1] - xi1
                    dz = xs[s, 2] - xi2
                    cut = ri + rs[s] + skin
                    if dx * dx + dy * dy + dz * dz < cut * cut:
                        j = cell_items[s]
                        # insertion by id keeps the candidates sorted
                        p = nc
                        while p > 0 and cand_id[p - 1] > idj:
                            cand_id[p] = cand_id[p - 1]
                            cand[p] = cand[p - 1]
                            p -= 1
                        cand_id[p] = idj
                        cand[p] = j
                        nc += 1
        start[i] = count
        size[i] = nc
        for s in range(nc):
            if count < capacity:
                seg[count] = cand[s]
            count += 1
    pi = np.empty(capacity, dtype=np.int64)
    pj = np.empty(capacity, dtype=np.int64)
    if count > capacity:
        return pi, pj, count
    order = id_order(ids, n)
    k = 0
    for q in range(n):
        i = order[q]
        a = start[i]
        for e in range(size[i]):
            pi[k] = i
            pj[k] = seg[a + e]
            k += 1
    return pi, pj, count


@njit
def pair_keys(pi, pj, ids):
    """Key of each pair: id_lo · 2³² + id_hi (ids must be < 2³¹)."""
    k = np.empty(pi.shape[0], dtype=np.int64)
    for p in range(pi.shape[0]):
        k[p] = (ids[pi[p]] << 32) | ids[pj[p]]
    return k


@njit
def keys_with_ids(keys, ids, high):
    """Positions (ascending) of the ``keys`` (id_lo·2³² + id_hi) whose low id, or (``high``) either
    id, is one of ``ids`` (sorted ascending, ≥ 0): ``np.flatnonzero`` of ``np.isin`` on the halves,
    in one pass over the keys with a flag per id up to the largest of ``ids`` (a binary search per
    key when that is large). A migration sends a few particles' rows out of tens of thousands of
    keys: ``np.isin`` made two passes per id and took ~70 % of a migration's packing.

    No ``np.sort`` in here (the caller sorts): numba names its sort and argsort helpers alike, and
    a cached ``build_pairs`` (argsort) loaded into a process that had just compiled a sort here
    called the sort and listed ids as rows (tests/test_neighbor.py)."""
    out = np.empty(0, dtype=np.int64)
    if ids.shape[0] == 0 or keys.shape[0] == 0:
        return out
    top = ids[ids.shape[0] - 1]
    m = 0
    if top >= max(4 * keys.shape[0], 1 << 16):  # large ids: a binary search per key
        hit = np.zeros(keys.shape[0], dtype=np.bool_)
        for k in range(keys.shape[0]):
            b = keys[k] & 0xFFFFFFFF
            q = np.searchsorted(ids, b)
            h = q < ids.shape[0] and ids[q] == b
            if high and not h:
                a = keys[k] >> 32
                q = np.searchsorted(ids, a)
                h = q < ids.shape[0] and ids[q] == a
            hit[k] = h
            m += h
        out = np.empty(m, dtype=np.int64)
        m = 0
        for k in range(keys.shape[0]):
            if hit[k]:
                out[m] = k
                m += 1
        return out
    flag = np.zeros(top + 1, dtype=np.bool_)
    for a in range(ids.shape[0]):
        flag[ids[a]] = True
    for k in range(keys.shape[0]):  # count, then fill: no list growing
        b = keys[k] & 0xFFFFFFFF
        h = b <= top and flag[b]
        if high:
            a = keys[k] >> 32
            h |= a <= top and flag[a]
        m += h
    out = np.empty(m, dtype=np.int64)
    if m == 0:
        return out
    m = 0
    for k in range(keys.shape[0]):
        b = keys[k] & 0xFFFFFFFF
        h = b <= top and flag[b]
        if high:
            a = keys[k] >> 32
            h |= a <= top and flag[a]
        if h:
            out[m] = k
            m += 1
    return out


@njit
def carry_history(old_keys, old_hist, new_keys, new_hist, zero_others=True):
    """Copy history rows of keys present in both sorted key lists (a linear merge); zero the other
    rows of ``new_hist`` (with ``zero_others`` False, leave them as they are)."""
    a = 0
    na = old_keys.shape[0]
    h = new_hist.shape[1]
    for b in range(new_keys.shape[0]):
        key = new_keys[b]
        while a < na and old_keys[a] < key:
            a += 1
        if a < na and old_keys[a] == key:
            for c in range(h):
                new_hist[b, c] = old_hist[a, c]
        elif zero_others:
            for c in range(h):
                new_hist[b, c] = 0.0


@njit
def take_keyed(order, keys, hist):
    """``(keys[order], hist[order])``: a pair list's rows in another order, in one loop (NumPy's
    fancy indexing took 1.5-2.1 ms for 65,000 rows of keys and history, this ~0.3 ms)."""
    m = order.shape[0]
    h = hist.shape[1]
    k2 = np.empty(m, dtype=keys.dtype)
    h2 = np.empty((m, h), dtype=hist.dtype)
    for q in range(m):
        s = order[q]
        k2[q] = keys[s]
        for c in range(h):
            h2[q, c] = hist[s, c]
    return k2, h2


@njit
def take_pairs(order, pi, pj, keys, hist):
    """``pi[order], pj[order], keys[order], hist[order]`` and the inverse of ``order``, without NumPy's
    fancy indexing (:func:`take_keyed` for the keys and history)."""
    m = order.shape[0]
    pi2 = np.empty(m, dtype=pi.dtype)
    pj2 = np.empty(m, dtype=pj.dtype)
    inverse = np.empty(m, dtype=np.int64)
    for q in range(m):
        s = order[q]
        pi2[q] = pi[s]
        pj2[q] = pj[s]
        inverse[s] = q
    k2, h2 = take_keyed(order, keys, hist)
    return pi2, pj2, k2, h2, inverse


@njit
def max_displacement2(x, x_ref, n):
    """Largest squared displacement of particles 0..n-1 since ``x_ref``."""
    best = 0.0
    for i in range(n):
        dx = x[i, 0] - x_ref[i, 0]
        dy = x[i, 1] - x_ref[i, 1]
        dz = x[i, 2] - x_ref[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 > best or d2 != d2:
            best = d2 if d2 == d2 else math.inf
    return best


@njit
def brute_force_pairs(x, r, ids, n, skin):
    """All pairs within r_i + r_j + skin by an O(n²) loop (the oracle of the tests)."""
    out_i = []
    out_j = []
    for i in range(n):
        for j in range(n):
            if ids[j] <= ids[i]:
                continue
            d = x[j] - x[i]
            cut = r[i] + r[j] + skin
            if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < cut * cut:
                out_i.append(i)
                out_j.append(j)
    return np.array(out_i, dtype=np.int64), np.array(out_j, dtype=np.int64)


@njit
def schedule_pairs(pi, pj, n):
    """An order of the pair list (given sorted by id pair) that follows the storage instead of the
    ids, and in which every particle still meets its pairs in the list's order.

    Each particle's pairs form a chain in list order (its partners by increasing id). Give pair k
    the time T(k): the larger storage row of its two particles, or the time of the pair before it
    in either particle's chain if that is later (one pass in list order, where those come first).
    T never decreases along a chain, so the pairs sorted by (T, list position) keep every chain's
    order: a loop over them adds the same terms to every particle in the same order as a loop over
    the list, bit for bit. When the storage is sorted in space, the pairs of time t touch row t and
    rows close behind it, as a loop over the storage would. Returns ``order``: position s of the
    new list is pair ``order[s]`` of the old one.
    """
    m = pi.shape[0]
    last = np.zeros(n, dtype=np.int64)
    t = np.empty(m, dtype=np.int64)
    count = np.zeros(n + 1, dtype=np.int64)
    for k in range(m):
        a = pi[k]
        b = pj[k]
        tk = max(a, b, last[a], last[b])
        t[k] = tk
        last[a] = tk
        last[b] = tk
        count[tk + 1] += 1
    for q in range(n):
        count[q + 1] += count[q]
    order = np.empty(m, dtype=np.int64)
    for k in range(m):  # a stable counting sort by time
        order[count[t[k]]] = k
        count[t[k]] += 1
    return order


@njit
def row_jumps(pi):
    """Mean |pi[k] - pi[k-1]| over the list: how far a loop over it jumps through storage."""
    m = pi.shape[0]
    if m < 2:
        return 0.0
    s = 0.0
    for k in range(1, m):
        s += abs(pi[k] - pi[k - 1])
    return s / (m - 1)


@njit
def partner_spread(pi, pj):
    """Mean |pi[k] - pj[k]|: how far apart in storage the two particles of a pair lie."""
    m = pi.shape[0]
    if m == 0:
        return 0.0
    s = 0.0
    for k in range(m):
        s += abs(pi[k] - pj[k])
    return s / m
