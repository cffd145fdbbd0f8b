"""Backends keep the last few sensor-direction tables uploaded (``DirectionCache``): one table per LiDAR
model, rebuilt when the model changes (even when the caller edits its arrays in place), and the scores of
a search that reuses them equal the reference's."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.backends.base import DirectionCache, GridSpec, sensor_directions


def test_a_table_is_built_once_per_model_and_the_oldest_is_dropped():
    built = []

    def upload(sd):
        built.append(sd)
        return ("device", sd)

    cache = DirectionCache(upload, size=2)
    e, a = np.radians([-10.0, 0.0, 5.0]), np.linspace(0, 2 * np.pi, 8, endpoint=False)
    first = cache.get(e, a)
    assert cache.get(e.copy(), a.copy()) is first           # equal values: the same entry
    assert len(built) == 1
    np.testing.assert_array_equal(first[1], sensor_directions(e, a))
    e[1] = 0.25                                              # the caller edits its array in place
    edited = cache.get(e, a)
    assert len(built) == 2 and edited is not first
    np.testing.assert_array_equal(edited[1], sensor_directions(e, a))
    cache.get(e[:2], a)                                      # a third model: the oldest (first) goes
    assert len(built) == 3
    e[1] = 0.0
    assert cache.get(e, a) is not first                      # rebuilt
    assert len(built) == 4


@pytest.mark.parametrize("name", [b for b in p3k.available_backends() if b != "reference"])
def test_scores_with_a_reused_table_equal_the_reference(name):
    """Two LiDAR models scored alternately on one backend (each call finds the other's table cached)."""
    from place3d_kernels.backends.registry import get_backend

    rng = np.random.default_rng(3)
    spec = GridSpec(0.4, (40, 40, 10))
    weights = (rng.integers(1, 2**32, spec.shape) * (rng.random(spec.shape) < 0.2)).astype(np.int64)
    stop = (rng.random(spec.shape) < 0.02).astype(np.uint8)
    models = [(np.radians(np.linspace(-15, 10, 8)), np.linspace(0, 2 * np.pi, 90, endpoint=False)),
              (np.radians(np.linspace(-25, 5, 5)), np.linspace(0, 2 * np.pi, 64, endpoint=False))]
    poses = np.zeros((3, 2, 6))
    poses[..., :3] = rng.uniform(4, 12, (3, 2, 3)) * [1, 1, 0.25]     # grid-local, inside
    poses[..., 3:] = rng.uniform(-0.3, 0.3, (3, 2, 3))
    ref, b = get_backend("reference"), get_backend(name)
    weights, stop = weights.reshape(-1), stop.reshape(-1)      # flat voxel order, as prepare_grid takes them
    hr, hb = ref.prepare_grid(spec, weights, stop), b.prepare_grid(spec, weights, stop)
    for _ in range(2):
        for e, a in models:
            want = ref.score_placements(hr, e, a, 12.0, poses)
            assert np.all(np.asarray(want[0]) > 0) and np.all(np.asarray(want[1]) > 0)    # rays cover weights
            got = b.score_placements(hb, e, a, 12.0, poses)
            for w, g in zip(want, got):
                np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_a_kept_bitset_comes_back_zeroed_and_is_not_shared():
    """The CUDA score path keeps its bitset buffer between calls (WarpBackend._take_bits/_give_bits; the
    logic is device-independent, exercised here on Warp's CPU device): a buffer taken again is zeroed
    over the words asked for, except the leading words it was given back as clean (the CUDA bit count
    zeroes what it counts), a larger request gets a larger buffer, and a buffer that is out (another
    thread scoring) is not handed out twice."""
    pytest.importorskip("warp")
    from place3d_kernels.backends.registry import get_backend

    if "warp:cpu" not in p3k.available_backends():
        pytest.skip("no Warp CPU backend")
    b = get_backend("warp:cpu")
    first, clean = b._take_bits(100)
    assert clean == 0 and not first.numpy()[:100].any()
    first.fill_(7)
    other, _ = b._take_bits(50)                   # the first is out: a buffer of its own
    assert other.ptr != first.ptr
    b._give_bits(first, 0)
    b._give_bits(other, 50)                       # smaller: the kept one stays the larger
    again, clean = b._take_bits(60)
    assert again.ptr == first.ptr and clean == 0
    assert not again.numpy()[:60].any() and (again.numpy()[60:] == 7).all()
    again.numpy()[0] = 5                          # (a word it will be told is clean: not zeroed again)
    b._give_bits(again, 60)
    more, clean = b._take_bits(80)
    assert more.ptr == first.ptr and clean == 60
    got = more.numpy()
    assert got[0] == 5 and not got[1:80].any() and (got[80:] == 7).all()
    b._give_bits(more, 0)
    bigger, clean = b._take_bits(200)
    assert bigger.shape[0] >= 200 and clean == 0 and not bigger.numpy()[:200].any()
    b._give_bits(bigger, 200)
    assert b._take_bits(10) == (bigger, 200)


@pytest.mark.parametrize("threads", [1, 7, 64, 5003, 9000])
def test_the_cuda_bit_count_counts_and_leaves_the_bitsets_zero(threads):
    """score_gpu.count_clear_kernel (run here on Warp's CPU device) gives each candidate's set bits, for any
    threads per candidate (a last word not on a thread's stride, more threads than words), and leaves every
    word zero; with masks, in the same pass, the set bits under the masks' high halves (the ``uncertain`` /
    ``evidence`` denominators); count_threads_per_candidate keeps 64 words a thread for small bitsets and about
    2^18 threads for large ones."""
    wp = pytest.importorskip("warp")
    from place3d_kernels.backends.warp import score_gpu as g

    rng = np.random.default_rng(threads)
    P, words = 3, 5003
    host = rng.integers(0, 2**32, P * words, dtype=np.uint64).astype(np.uint32)
    host[words:2 * words] = 0                     # a candidate with nothing covered
    host[2 * words:2 * words + 100] = 0           # and zero words among set ones
    masks = rng.integers(0, 2**63, words, dtype=np.uint64)
    high = (masks >> np.uint64(32)).astype(np.uint32)
    for with_masks in (0, 1):
        bits = wp.array(host, dtype=wp.uint32, device="cpu")
        counts, masked = (wp.zeros(P, dtype=wp.int64, device="cpu") for _ in range(2))
        m = wp.array(masks if with_masks else masks[:1], dtype=wp.uint64, device="cpu")
        wp.launch(g.count_clear_kernel, dim=P * threads, device="cpu",
                  inputs=[bits, words, threads, m, with_masks, counts, masked])
        np.testing.assert_array_equal(counts.numpy(), np.bitwise_count(host.reshape(P, words)).sum(axis=1))
        want = np.bitwise_count(host.reshape(P, words) & high).sum(axis=1) if with_masks else np.zeros(P)
        np.testing.assert_array_equal(masked.numpy(), want)
        assert not bits.numpy().any()
    assert g.count_threads_per_candidate(6400, 22) == 100
    assert g.count_threads_per_candidate(2**23, 16) == 2**14
