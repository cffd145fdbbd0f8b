"""P-SOGs made from counts: probabilities made on first read, weights and stop masks from the count tables,
the plain pool summed record by record, and ``backends.base.unique_ints``: every value the same as before."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from place3d_kernels.classes import N_CLASSES
from place3d_kernels.grid import Grid
from place3d_kernels.left_out_tables import FieldTables
from place3d_kernels.backends.base import unique_ints
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.sog import PSOG

GRID = Grid((0.0, 0.0, 0.0), (4.0, 4.0, 2.0), 0.25)     # 16 x 16 x 8 voxels


def _random_counts(T, M, seed):
    """(voxels, counts (M, K) int32) whose rows sum to T: a few classes per voxel, as real P-SOGs have."""
    rng = np.random.default_rng(seed)
    vox = np.sort(rng.choice(GRID.n_voxels, M, replace=False)).astype(np.int64)
    c = np.zeros((M, N_CLASSES), dtype=np.int64)
    for i in range(M):
        cls = rng.choice(np.arange(1, N_CLASSES), rng.integers(1, 4), replace=False)
        left = T
        for k in cls:
            n = int(rng.integers(0, left + 1))
            c[i, k], left = n, left - n
        c[i, 0] = left
    c[rng.random(M) < 0.1, 0] = 0        # some voxels occupied in every subset
    c[:, 0] = T - c[:, 1:].sum(axis=1)
    keep = c[:, 1:].sum(axis=1) > 0
    return vox[keep], c[keep].astype(np.int32)


@pytest.mark.parametrize("T", [7, 40, FieldTables.MAX_T + 3])     # the last: left_out_fields, not the tables
def test_fields_from_counts_equal_those_from_probabilities(T):
    vox, c = _random_counts(T, 300, seed=T)
    lazy = PSOG.from_counts(GRID, vox, c, T)
    eager = PSOG(GRID, vox, c / float(T), n_subsets=T)          # no counts: the probabilities' path
    assert lazy._probs is None                                  # not made by the constructor
    for task in ("seg", "det"):
        a, b = lazy.for_task(task), eager.for_task(task)
        assert a._probs is None
        assert np.array_equal(a.weights, b.weights) and a.weights.dtype == b.weights.dtype
        assert np.array_equal(a.stop_mask, b.stop_mask) and a.stop_mask.dtype == b.stop_mask.dtype
        assert a.weights.any()
        assert np.array_equal(a.probs, b.probs)                 # made when read, the same bits
        assert np.array_equal(a.entropy, b.entropy)


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("stop_first", [False, True])
def test_fields_from_counts_in_blocks_on_threads(monkeypatch, threads, stop_first):
    """Weights and stop flags made from count rows in one pass of small blocks, side by side on threads
    (``threads.block_map``), whichever is read first: the probabilities' values, bit for bit."""
    import place3d_kernels.sog as sog_mod
    import place3d_kernels.threads as threads_mod

    monkeypatch.setattr(threads_mod, "threads_for", lambda entries: threads)
    monkeypatch.setattr(sog_mod, "ENTROPY_BLOCK", 37)               # many blocks, a short last one
    vox, c = _random_counts(40, 1000, seed=5)
    eager = PSOG(GRID, vox, c / 40.0, n_subsets=40)
    for task in ("seg", "det"):
        a, b = PSOG.from_counts(GRID, vox, c, 40).for_task(task), eager.for_task(task)
        if stop_first:
            assert a.stop_rows.tobytes() == b.stop_rows.tobytes()
        assert a.weight_rows.dtype == b.weight_rows.dtype and a.weight_rows.tobytes() == b.weight_rows.tobytes()
        assert a.stop_rows.dtype == b.stop_rows.dtype and a.stop_rows.tobytes() == b.stop_rows.tobytes()


@pytest.mark.parametrize("threads", [1, 2, 5])
@pytest.mark.parametrize("n", [0, 1, 9, 10, 11, 1001])
def test_block_map_calls_every_block_once(monkeypatch, threads, n):
    import place3d_kernels.threads as threads_mod

    monkeypatch.setattr(threads_mod, "threads_for", lambda entries: threads)
    seen = []
    threads_mod.block_map(lambda a, b: seen.append((a, b)), n, 10)
    assert sorted(seen) == [(a, min(a + 10, n)) for a in range(0, n, 10)]


def test_a_pickled_lazy_detection_variant_keeps_its_values():
    vox, c = _random_counts(12, 200, seed=3)
    det = PSOG.from_counts(GRID, vox, c, 12).detection()
    assert det._probs is None
    again = pickle.loads(pickle.dumps(det))         # before its probabilities were read: they travel made
    assert "probs_of" not in again._cache and again._probs is not None
    assert np.array_equal(again.weights, det.weights) and np.array_equal(again.probs, det.probs)


def test_counts_without_n_subsets_or_of_the_wrong_shape_are_refused():
    vox, c = _random_counts(5, 20, seed=4)
    with pytest.raises(ValueError, match="counts and n_subsets"):
        PSOG(GRID, vox, None, counts=c)
    with pytest.raises(ValueError, match="counts must be"):
        PSOG(GRID, vox, None, n_subsets=5, counts=c[:, :3])


def _records(seed, D=4, repeats=False):
    rng = np.random.default_rng(seed)
    out = []
    for d in range(D):
        T = int(rng.integers(3, 9))
        vox, c = _random_counts(T, 150, seed=seed * 10 + d)
        v, k = np.nonzero(c[:, 1:])
        r = DriveRecord(f"d{d}", T, vox[v], (k + 1).astype(np.int16), c[v, k + 1].astype(np.int32))
        if repeats:       # the first (voxel, class) entry twice: both counted
            r = DriveRecord(r.label, 2 * T, np.r_[r.voxels[:1], r.voxels], np.r_[r.classes[:1], r.classes],
                            np.r_[r.counts[:1], r.counts])
        out.append(r)
    return out


@pytest.mark.parametrize("rank", [True, False])           # a row per grid voxel, or sorted voxels searched
@pytest.mark.parametrize("repeats", [False, True])
def test_plain_pool_summed_record_by_record_equals_the_resampling_sums(repeats, rank, monkeypatch):
    monkeypatch.setattr("place3d_kernels.pooled.RANK_VOXELS", GRID.n_voxels if rank else GRID.n_voxels - 1)
    recs = _records(5, repeats=repeats)
    pool = PooledPSOG(GRID, recs)
    plain = pool.counts()                                         # _sum_plain
    ones = PooledPSOG(GRID, recs).counts(np.ones(len(recs)))      # the (voxel, class) union's path
    for a, b in zip(plain, ones):
        assert np.array_equal(a, b)
    assert plain[1].dtype == np.int32 and plain[0].dtype == np.int64
    assert (pool._rank is not None) == rank
    for r in recs:                                                # each entry's row, as a search finds it
        assert np.array_equal(pool.rows_of(r.voxels), np.searchsorted(plain[0], r.voxels))


def test_unique_ints_equals_numpy_unique():
    rng = np.random.default_rng(0)
    for a in (rng.integers(0, 1000, 5000), rng.integers(-5, 5, 7), np.array([3]), np.zeros(0, np.int64),
              np.arange(10)[::-1]):
        u = unique_ints(a)
        assert np.array_equal(u, np.unique(a)) and u.dtype == np.unique(a).dtype


def _warp_backends():
    import place3d_kernels as p3k

    return [b for b in p3k.available_backends() if b.startswith("warp:")]


@pytest.mark.parametrize("name", _warp_backends())
@pytest.mark.parametrize("task", ["seg", "det"])
def test_a_grid_from_device_made_rows_is_the_hosts(task, name, monkeypatch):
    # where the backend computes fields (Warp on CUDA; Warp's CPU device told so) a P-SOG from counts makes
    # its handle from rows computed there, not from weight_rows: the same grid
    from place3d_kernels.backends.registry import get_backend

    b = get_backend(name)
    vox, c = _random_counts(40, 400, seed=11)
    want = PSOG.from_counts(GRID, vox, c, 40).for_task(task)
    want.weight_rows, want.stop_rows        # noqa: B018 - the host's rows made first: its handle is made from them
    host = want.handle(b, "sog")
    assert ("device rows", b) not in want._cache
    monkeypatch.setattr(type(b), "fields_on_device", property(lambda self: True))
    got = PSOG.from_counts(GRID, vox, c, 40).for_task(task)
    h = got.handle(b, "sog")
    assert "weight rows" not in got._cache and ("device rows", b) in got._cache
    assert h.weights.numpy().tobytes() == host.weights.numpy().tobytes()
    assert h.masks.numpy().tobytes() == host.masks.numpy().tobytes()
    w, s = got._cache[("device rows", b)]
    assert w.numpy().tobytes() == want.weight_rows.tobytes()
    assert s.numpy().tobytes() == want.stop_rows.astype(np.uint8).tobytes()


@pytest.mark.parametrize("degenerate", [False, True, "last row only"])
@pytest.mark.parametrize("block", [8192, 7])
def test_check_entropy_from_counts_agrees_with_the_weights(degenerate, block, monkeypatch):
    # the counts are read block by block (``ENTROPY_BLOCK`` rows): one block, and 42 blocks of 7 rows with the
    # only row that has entropy in the last, short one
    from place3d_kernels import sog
    from place3d_kernels.pipeline import check_entropy

    monkeypatch.setattr(sog, "ENTROPY_BLOCK", block)
    vox, c = _random_counts(9, 300, seed=2)
    if degenerate:                              # every voxel a single class in every subset
        c = np.zeros_like(c)
        c[np.arange(len(c)), 1 + np.arange(len(c)) % (N_CLASSES - 1)] = 9
    if degenerate == "last row only":
        c[-1] = 0
        c[-1, 1:3] = (4, 5)
        degenerate = False
    lazy = PSOG.from_counts(GRID, vox, c, 9)
    eager = PSOG(GRID, vox, c / 9.0, n_subsets=9)
    assert bool(eager.weight_rows.any()) is (not degenerate)
    if degenerate:
        with pytest.raises(ValueError, match="no entropy"):
            check_entropy(lazy)
    else:
        assert check_entropy(lazy) is lazy
    assert "weight rows" not in lazy._cache          # decided from the counts


@pytest.mark.parametrize("T", [7, 40, FieldTables.MAX_T + 3])
def test_stop_flags_alone_from_the_empty_counts(T):
    """A P-SOG's stop flags read first come from its rows' empty counts alone, without the weights (the plot's
    coverage mask on a backend that computes fields on its device reads only these): the probabilities' flags,
    bit for bit, and the weights made later are theirs too."""
    vox, c = _random_counts(T, 500, seed=T + 1)
    eager = PSOG(GRID, vox, c / float(T), n_subsets=T)
    for task in ("seg", "det"):
        a, b = PSOG.from_counts(GRID, vox, c, T).for_task(task), eager.for_task(task)
        assert a.stop_rows.dtype == b.stop_rows.dtype and a.stop_rows.tobytes() == b.stop_rows.tobytes()
        assert "weight rows" not in a._cache and a._probs is None
        assert a.stop_rows.any() and not a.stop_rows.all()
        assert a.weight_rows.tobytes() == b.weight_rows.tobytes()
        assert a.stop_mask.tobytes() == b.stop_mask.tobytes()
