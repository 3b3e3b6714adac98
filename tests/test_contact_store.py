"""ContactStore's history by key through migrations: received rows are set aside and carried at the
next rebuild, with this rank's own rows winning where both hold a key (as when they were merged)."""

from __future__ import annotations

import numpy as np

from pdem.contact.store import ContactStore


def _key(a: int, b: int) -> int:
    return (a << 32) | b


def _store(keys, hist):
    cs = ContactStore(2)
    keys = np.array(keys, dtype=np.int64)
    n = keys.size
    cs.set_pairs(np.zeros(n, np.int64), np.zeros(n, np.int64), keys)
    cs.hist[:] = np.asarray(hist, dtype=float).reshape(-1, 2)
    return cs


def _parcel(pair_keys, pair_hist, wall_keys=(), wall_hist=()):
    return {
        "pair_keys": np.array(pair_keys, dtype=np.int64),
        "pair_hist": np.asarray(pair_hist, dtype=float).reshape(-1, 2),
        "wall_keys": np.array(wall_keys, dtype=np.int64),
        "wall_hist": np.asarray(wall_hist, dtype=float).reshape(-1, 2),
    }


def test_received_rows_are_carried_at_the_next_rebuild_own_rows_win():
    cs = _store([_key(1, 2), _key(2, 5)], [[1, 1], [2, 2]])
    # two migration passes: a row this rank holds (another value: its own wins), new rows, and the
    # same new row twice (the first received wins)
    cs.merge(_parcel([_key(2, 5), _key(3, 4)], [[9, 9], [3, 3]]))
    cs.merge(_parcel([_key(3, 4), _key(4, 7)], [[8, 8], [4, 4]]))
    assert cs.keys.size == 2  # nothing merged into the list itself
    new = np.array([_key(1, 2), _key(2, 5), _key(3, 4), _key(4, 7), _key(6, 7)], dtype=np.int64)
    cs.set_pairs(np.zeros(5, np.int64), np.zeros(5, np.int64), new)
    assert cs.hist.tolist() == [[1, 1], [2, 2], [3, 3], [4, 4], [0, 0]]
    # consumed: the next rebuild carries only the list's own rows
    cs.hist[3] = 0.0
    cs.set_pairs(np.zeros(5, np.int64), np.zeros(5, np.int64), new)
    assert cs.hist.tolist() == [[1, 1], [2, 2], [3, 3], [0, 0], [0, 0]]


def test_rows_received_in_one_pass_go_on_with_their_particle():
    """A particle received in one migration pass and sent on in the next takes the rows it
    brought, not yet carried into the list."""
    cs = _store([_key(1, 2)], [[1, 1]])
    cs.merge(_parcel([_key(3, 4), _key(5, 6)], [[3, 3], [5, 5]], [_key(0, 4), _key(0, 6)], [[7, 7], [6, 6]]))
    out = cs.rows_of(np.array([4, 1], dtype=np.int64))
    assert sorted(out["pair_keys"].tolist()) == [_key(1, 2), _key(3, 4)]
    assert out["wall_keys"].tolist() == [_key(0, 4)]
    assert out["wall_hist"].tolist() == [[7, 7]]


def test_keys_with_ids_is_isin_on_the_key_halves():
    """The migration's row selection (pdem.neighbor._kernels.keys_with_ids) against np.flatnonzero
    of np.isin on the low id, and on either id: random keys and id sets, ids at 0, near 2³¹ and at
    the range ends, empty sets and lists."""
    from pdem.neighbor import _kernels as nk

    rng = np.random.default_rng(5)
    for n_ids, span in [(0, 10), (1, 10), (3, 50), (40, 2000), (7, 2**31 - 1)]:
        lo_ids = rng.integers(0, span, 3000)
        hi_ids = lo_ids + rng.integers(1, 50, 3000)
        hi_ids = np.minimum(hi_ids, 2**31 - 1)
        keys = (lo_ids.astype(np.int64) << 32) | hi_ids
        ids = rng.choice(np.concatenate([lo_ids[:20], hi_ids[:20], [0, span - 1]]), n_ids).astype(np.int64)
        for high in (True, False):
            want = np.isin(keys & 0xFFFFFFFF, ids)
            if high:
                want |= np.isin(keys >> 32, ids)
            got = nk.keys_with_ids(keys, np.sort(ids), high)
            assert got.dtype == np.int64 and np.array_equal(got, np.flatnonzero(want)), (n_ids, span, high)
    assert nk.keys_with_ids(np.zeros(0, np.int64), np.array([3], np.int64), True).shape == (0,)
