"""The issue-17 speed paths give what the slow paths gave: each fast path is checked against the code it
replaced (written out here), or against its own invalidation rule."""

from __future__ import annotations

import json

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.backends import registry
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.scene import keymemo
from place3d_kernels.sog import entropy
from place3d_kernels.spec import SceneSpec


def _entropy_dense(p):
    # the formula entropy() used before it took logs of the non-zero entries only
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(p > 0, -p * np.log(np.where(p > 0, p, 1.0)), 0.0).sum(axis=-1)


def test_entropy_equals_the_dense_formula_bit_for_bit():
    rng = np.random.default_rng(3)
    c = rng.integers(0, 4, (5000, 22)) * (rng.random((5000, 22)) < 0.15)
    c[:, 0] += 1
    c[:7] = 0
    c[:7, 0] = 10                           # single-class voxels: entropy -0.0 in both
    p = c / c.sum(axis=1, keepdims=True)
    a, b = entropy(p), _entropy_dense(p)
    assert np.array_equal(a, b) and np.array_equal(np.signbit(a), np.signbit(b))


def _records(rng, n=6, grid_voxels=4000, k=22):
    out = []
    for i in range(n):
        vox = np.sort(rng.choice(grid_voxels, 300, replace=False)).astype(np.int64)
        cls = rng.integers(1, k, 300).astype(np.int64)
        order = np.lexsort((cls, vox))
        out.append(DriveRecord(f"r{i}", 4, vox[order], cls[order].astype(np.int16),
                               rng.integers(1, 4, 300).astype(np.int32)))
    return out


def _counts_from_scratch(pool, m):
    # PooledPSOG.counts before the leave-one-out path: every record weighted and summed from scratch
    cls_, inv, counts, owner, uvox, vinv = pool._prepare()
    w = counts * np.asarray(m, np.int64)[owner]
    summed = np.rint(np.bincount(inv, weights=w.astype(np.float64), minlength=len(cls_))).astype(np.int64)
    out = np.zeros((len(uvox), pool.n_classes), np.int64)
    out[vinv, cls_] = summed
    occ = out[:, 1:].sum(axis=1)
    keep = occ > 0
    out, vox = out[keep], uvox[keep]
    T = int((np.array([r.n_subsets for r in pool.records]) * np.asarray(m, np.int64)).sum())
    out[:, 0] = T - occ[keep]
    return vox, out, T


def test_leave_one_out_counts_equal_counts_from_scratch():
    rng = np.random.default_rng(5)
    grid = p3k.Grid((0, 0, 0), (4, 10, 10), 1.0)
    pool = PooledPSOG(grid, _records(rng))
    n = len(pool)
    weights = [np.where(np.arange(n) == i, 0, 1) for i in range(n)]            # the jackknife's
    weights += [np.where(np.arange(n) == 2, 3, 1), rng.integers(0, 3, n)]     # one heavier; a bootstrap draw
    for m in weights:
        got, want = pool.counts(m), _counts_from_scratch(pool, m)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]) and got[2] == want[2]


def test_covered_voxels_equal_the_unique_traversal():
    # the 0.2 m box (the old default: its P-SOG may be cached already); the check needs no particular grid
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.2)
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid, backend="warp:cpu")
    lidar = p3k.LidarModel.load("place3d_16ch")
    poses = p3k.Placement.load("pyramid").poses
    b = p3k.get_backend("warp:cpu")
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, poses)
    for occlusion, stop in (("sog", psog.stop_mask), ("none", None)):
        want = np.unique(p3k.traverse(psog.grid, o, d, lidar.max_range, backend=b, stop=stop).voxels)
        got = p3k.covered_voxels(psog, lidar, poses, occlusion=occlusion, backend=b)
        assert np.array_equal(got, want)
        # the mask coverage.png reads: True exactly there; its columns and count are the indices'
        from place3d_app.commands.optimize import coverage_view, entropy_view
        from place3d_kernels.metrics import coverage_mask

        mask = coverage_mask(psog, lidar, poses, occlusion=occlusion, backend=b)
        assert mask.shape == (grid.n_voxels,) and np.array_equal(np.flatnonzero(mask), want)
        column, columns, n, extent = coverage_view(psog, mask)
        assert n == len(want) and np.array_equal(np.flatnonzero(columns), np.unique(want // grid.shape[2]))
        # with the panel's entropy view made already (optimize keeps it during the search): the same view
        kept = entropy_view(psog)
        again = coverage_view(psog, mask, kept)
        assert again[0] is kept[0] and np.array_equal(again[0], column) and again[3] == extent
        assert np.array_equal(again[1], columns) and again[2] == n


def test_scene_keys_are_remembered_and_a_new_identity_builds_again(tmp_path, monkeypatch):
    spec = SceneSpec("town", seed=0, frames=8)
    first = spec.for_cache(tmp_path)                     # not remembered yet: the scene itself
    assert isinstance(first, p3k.scene.Scene)
    again = spec.for_cache(tmp_path)                     # now a reference with the same name and key
    assert isinstance(again, keymemo.SceneRef) and (again.name, again.key) == (first.name, first.key)
    assert [json.loads(f.read_text()) for f in (tmp_path / "scene-keys").iterdir()] == \
        [{"name": first.name, "key": first.key}]
    # another spec, or a changed builder source, is another identity: built again, never the old key
    assert isinstance(SceneSpec("town", seed=1, frames=8).for_cache(tmp_path), p3k.scene.Scene)
    keymemo._sources_digest.cache_clear()
    monkeypatch.setattr(keymemo, "_sources_digest", lambda: "a changed builder")
    assert isinstance(spec.for_cache(tmp_path), p3k.scene.Scene)
    # a mesh scene is its file: always built, never remembered
    assert keymemo.identity({"name": "mesh:x.obj"}, "mesh", None) is None


def test_a_cached_psog_is_read_without_building_the_scene(tmp_path, monkeypatch):
    from place3d_kernels.spec import PSOGSpec

    spec = PSOGSpec(SceneSpec("town", seed=0, frames=8), backend="warp:cpu", grid=0.8, cache=str(tmp_path))
    built = spec.build(cache=str(tmp_path))
    spec.scene.for_cache(tmp_path)                       # the first build remembered the key already

    def refuse(*a, **k):
        raise AssertionError("the scene was built although its P-SOG is cached")

    monkeypatch.setattr("place3d_kernels.spec._build_scene", refuse)
    again = spec.build(cache=str(tmp_path))
    assert np.array_equal(again.voxels, built.voxels) and np.array_equal(again.probs, built.probs)


def test_auto_does_not_import_warp_without_a_cuda_driver(monkeypatch):
    monkeypatch.setattr(registry, "_cuda_driver_loadable", lambda: False)
    probed = []
    real = registry._probe_cached

    def spy(fam):
        probed.append(fam)
        return real(fam)

    monkeypatch.setattr(registry, "_probe_cached", spy)
    name = registry._auto()
    if name == "opencl:pocl" or name.startswith("opencl:"):
        assert "warp" not in probed
    else:                                                # no OpenCL here: Warp's CPU device or the reference
        assert name in ("warp:cpu", "reference")


@pytest.mark.parametrize("fails_at", [3, 6])
def test_a_run_that_raises_keeps_its_last_completed_generation(tmp_path, fails_at):
    from place3d_kernels.optimize import SearchSpace, optimize
    from place3d_kernels.optimize.checkpoint import load_checkpoint

    space = SearchSpace(n_lidars=1)
    calls = {"n": 0}

    def objective(X):
        calls["n"] += 1
        if calls["n"] == fails_at:
            raise RuntimeError("device lost")
        return -np.sum((X - 0.1) ** 2, axis=1)

    ckpt = tmp_path / "run.ckpt"
    with pytest.raises(RuntimeError, match="device lost"):
        optimize(objective, space, checkpoint=ckpt, max_evals=400, seed=1, progress=False)
    # every objective call but the failing one completed a generation; all of them are on disk although
    # checkpoints are written at most once a second
    assert load_checkpoint(ckpt)["generation"] == fails_at - 1


def test_jackknife_with_left_out_psogs_built_on_threads_equals_one_thread(monkeypatch):
    from place3d_kernels import uncertainty as U

    rng = np.random.default_rng(9)
    grid = p3k.Grid((-5, -5, -1), (5, 5, 3), 0.5)
    recs = _records(rng, n=5, grid_voxels=grid.n_voxels)
    lidar = p3k.LidarModel.uniform(8, (-20, 10), 32, max_range=20.0)
    rigs = {"a": [[0.0, 0.0, 1.0, 0, 0, 0]], "b": [[1.0, -0.5, 1.5, 0, 0, 0.3]]}
    runs = []
    for threads, cpus in ((1, 1), (3, 8)):
        monkeypatch.setattr(U, "LEFT_OUT_THREADS", threads)
        monkeypatch.setattr(U.os, "cpu_count", lambda cpus=cpus: cpus)
        runs.append(U.jackknife_records(recs, grid, lidar, rigs, tasks=("seg", "det"), backend="reference"))
    for t in ("seg", "det"):
        assert np.array_equal(runs[0][t].samples, runs[1][t].samples)
        assert np.isfinite(runs[0][t].samples).all() and np.ptp(runs[0][t].samples) > 0   # the units differ


@pytest.mark.parametrize("processes", [False, True])
def test_plot_worker_draws_the_optimise_outputs_and_reports_errors(tmp_path, processes):
    from place3d_kernels.optimize import SearchSpace
    from place3d_kernels.optimize.plots import PlotWorker

    history = [{"evaluations": 10 * (i + 1), "best": -0.05 + 0.001 * i, "gen_best": -0.05 + 0.001 * i,
                "gen_mean": -0.06, "sigma": 0.3 / (i + 1)} for i in range(5)]
    best = p3k.Placement.load("pyramid")
    view = (np.random.default_rng(0).random((20, 20)), np.eye(20, dtype=bool), 20, (-4.0, 4.0, -4.0, 4.0), "pyramid")
    worker = PlotWorker(processes=processes)
    try:
        paths = worker.submit(history, best, SearchSpace(n_lidars=4), view, tmp_path).result(timeout=120)
        assert sorted(p.rsplit("/", 1)[1] for p in paths) == ["convergence.png", "coverage.png", "rig.png"]
        assert all((tmp_path / n).stat().st_size > 1000 for n in ("convergence.png", "coverage.png", "rig.png"))
        with pytest.raises(Exception):
            worker.submit(history, best, None, view[:2], tmp_path / "bad").result(timeout=120)
    finally:
        worker.close()


def test_plot_worker_falls_back_to_a_thread(tmp_path, monkeypatch):
    """A worker process that died (or could not start, as for a program read from standard input) does not
    fail the command: the figures are drawn on a thread instead."""
    import os
    import signal
    import sys
    import time

    from place3d_kernels.optimize import SearchSpace, plots

    monkeypatch.setattr(sys.modules["__main__"], "__file__", "<stdin>", raising=False)
    assert not plots._spawn_can_start()
    w = plots.PlotWorker()
    w.close()
    assert w.processes is False                                    # on any machine: no process could start
    monkeypatch.undo()
    history = [{"evaluations": 10 * (i + 1), "best": -0.05 + 0.001 * i, "sigma": 0.3} for i in range(4)]
    view = (np.random.default_rng(0).random((8, 8)), np.eye(8, dtype=bool), 8, (-4.0, 4.0, -4.0, 4.0), "pyramid")
    worker = plots.PlotWorker(processes=True)
    try:
        worker.pool.submit(time.sleep, 0).result(timeout=120)          # the processes are up
        for pid in list(worker.pool._processes):
            os.kill(pid, signal.SIGKILL)
        time.sleep(1.0)
        paths = worker.submit(history, p3k.Placement.load("pyramid"), SearchSpace(n_lidars=4), view,
                              tmp_path).result(timeout=120)
        assert worker.processes is False
        assert sorted(p.rsplit("/", 1)[1] for p in paths) == ["convergence.png", "coverage.png", "rig.png"]
    finally:
        worker.close()


@pytest.mark.parametrize("per", [64, 1024, 4096])
def test_bit_count_equals_numpy_whatever_the_words_per_thread(per):
    """count_bits_kernel gives each candidate's set bits for any words per thread, including a last chunk
    cut short and a chunk larger than the bitset (the CPU path uses 1024 for large bitsets)."""
    wp = pytest.importorskip("warp")
    from place3d_kernels.backends.warp import kernels as k

    rng = np.random.default_rng(per)
    P, words = 3, 5003
    host = rng.integers(0, 2**32, P * words, dtype=np.uint64).astype(np.uint32)
    host[words:2 * words] = 0                       # a candidate with nothing covered
    counts = wp.zeros(P, dtype=wp.int64, device="cpu")
    chunks = -(-words // per)
    bits = wp.array(host, dtype=wp.uint32, device="cpu")
    wp.launch(k.count_bits_kernel, dim=P * chunks, device="cpu",
              inputs=[bits, words, chunks, per, wp.zeros(1, dtype=wp.uint64, device="cpu"), 0, counts])
    want = np.bitwise_count(host.reshape(P, words)).sum(axis=1)
    np.testing.assert_array_equal(counts.numpy(), want)
    # masked: the bits under the high halves of one uint64 per word (another grid's nonzero-weight bits)
    masks = rng.integers(0, 2**63, words, dtype=np.uint64)
    masked = wp.zeros(P, dtype=wp.int64, device="cpu")
    wp.launch(k.count_bits_kernel, dim=P * chunks, device="cpu",
              inputs=[bits, words, chunks, per, wp.array(masks, dtype=wp.uint64, device="cpu"), 1, masked])
    high = (masks >> np.uint64(32)).astype(np.uint32)
    np.testing.assert_array_equal(masked.numpy(), np.bitwise_count(host.reshape(P, words) & high).sum(axis=1))
    assert k.count_words_per_thread(2**24) == 1024 and k.count_words_per_thread(2**24 - 1) == k.COUNT_WORDS


@pytest.mark.parametrize("words", [1, 5003, 70_001])
def test_cuda_clearing_count_with_a_mask_equals_numpy(words):
    """CUDA's one pass after a score launch (``count_clear_kernel`` with masks, the ``uncertain`` / ``evidence``
    denominators): every set bit and the masked ones per candidate, as NumPy counts them, and the bitsets
    zero afterwards; as the masked count_bits pass and count_clear gave them. Skipped without a CUDA device."""
    wp = pytest.importorskip("warp")
    from place3d_kernels.backends.registry import get_backend

    try:
        b = get_backend("warp:cuda:0")
    except Exception as e:  # noqa: BLE001 - no CUDA device here
        pytest.skip(f"no CUDA device: {e}")
    rng = np.random.default_rng(words)
    P = 4
    host = rng.integers(0, 2**32, P * words, dtype=np.uint64).astype(np.uint32)
    host[rng.random(P * words) < 0.7] = 0                 # most words untouched, as a rig's walk leaves them
    host[words:2 * words] = 0                            # a candidate with nothing covered
    masks = rng.integers(0, 2**63, words, dtype=np.uint64)
    high = (masks >> np.uint64(32)).astype(np.uint32)
    results = []
    for fused in (True, False):
        bits = wp.array(host, dtype=wp.uint32, device=b.device)
        m = wp.array(masks, dtype=wp.uint64, device=b.device)
        counts, masked = (wp.zeros(P, dtype=wp.int64, device=b.device) for _ in range(2))
        if fused:
            b._count_bits(bits, P, words, counts, masked, m)
        else:
            b._count_words(bits, P, words, masked, m)
            b._count_bits(bits, P, words, counts)
        assert not bits.numpy().any()
        results.append((counts.numpy(), masked.numpy()))
    np.testing.assert_array_equal(results[0][0], np.bitwise_count(host.reshape(P, words)).sum(axis=1))
    np.testing.assert_array_equal(results[0][1], np.bitwise_count(host.reshape(P, words) & high).sum(axis=1))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
