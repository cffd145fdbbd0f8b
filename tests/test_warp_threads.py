"""Warp's CPU device runs a launch on one thread, so the Warp backend splits its ray kernels over a thread
pool (score kernel: whole candidates per thread). Split and unsplit launches must give the same bits."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k

warp_backend = pytest.importorskip("place3d_kernels.backends.warp")


@pytest.fixture(scope="module")
def pair():
    one = warp_backend.WarpBackend("cpu")
    one.threads = 1
    many = warp_backend.WarpBackend("cpu")
    many.threads = 3          # more threads than this machine may have cores: chunks still interleave
    return one, many


@pytest.fixture(scope="module")
def rays():
    lidar = p3k.LidarModel.uniform(16, (-25, 15), 512, max_range=100.0)
    return p3k.lidar_rays(lidar, p3k.Placement.load("pyramid"))      # 32,768 rays: many chunks


def test_split_traversal_and_coverage_equal_unsplit(pair, rays):
    one, many = pair
    o, d = rays
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.2)     # the old default, as these counts
    a = p3k.traverse(grid, o, d, 100.0, backend=one)
    b = p3k.traverse(grid, o, d, 100.0, backend=many)
    assert len(a.voxels) > 1_000_000
    assert np.array_equal(a.offsets, b.offsets) and np.array_equal(a.voxels, b.voxels)
    ma = p3k.coverage(grid, o, d, 100.0, backend=one)
    mb = p3k.coverage(grid, o, d, 100.0, backend=many)
    assert ma.sum() > 100_000 and np.array_equal(ma, mb)
    assert np.array_equal(np.flatnonzero(ma), np.unique(a.voxels))


def test_split_raycast_equals_unsplit(pair, rays):
    one, many = pair
    o, d = rays
    mesh = p3k.scene.town(seed=0).static
    a = p3k.raycast(mesh, o, d, 100.0, backend=one)
    b = p3k.raycast(mesh, o, d, 100.0, backend=many)
    assert np.isfinite(a.t).mean() > 0.5
    assert np.array_equal(a.t, b.t) and np.array_equal(a.face, b.face)


def test_split_population_scores_equal_unsplit(pair):
    one, many = pair
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.4)
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend=one)
    lidar = p3k.LidarModel.load("place3d_16ch")
    rng = np.random.default_rng(3)
    pop = np.repeat(p3k.Placement.load("pyramid").poses[None], 5, axis=0)
    pop[..., :3] += rng.uniform(-0.3, 0.3, pop[..., :3].shape)
    a = p3k.msog_batch(psog, lidar, pop, backend=one)
    b = p3k.msog_batch(psog, lidar, pop, backend=many)
    assert np.all(np.isfinite(a)) and len(set(a.tolist())) > 1
    assert np.array_equal(a, b)
    assert np.array_equal(a, p3k.msog_batch(psog, lidar, pop, backend="reference"))


@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_split_single_rig_equals_unsplit(pair, occlusion, monkeypatch):
    # one rig's rays over the threads (per-thread bitsets OR-ed, sum from the union) against one launch
    from place3d_kernels.backends.warp import scoring

    monkeypatch.setattr(scoring, "SPLIT_SINGLE_RIG", True)
    one, many = pair
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.4)
    psog = p3k.scene_psog(p3k.scene.town(seed=0), grid=grid, backend=one)
    lidar = p3k.LidarModel.load("place3d_16ch")
    scores = {}
    for name in ("pyramid", "line", "center"):
        rig = p3k.Placement.load(name).poses[None]
        a = p3k.msog_batch(psog, lidar, rig, occlusion=occlusion, backend=one)
        b = p3k.msog_batch(psog, lidar, rig, occlusion=occlusion, backend=many)
        assert np.array_equal(a, b), name
        assert np.array_equal(a, p3k.msog_batch(psog, lidar, rig, occlusion=occlusion, backend="reference")), name
        scores[name] = float(a[0])
    assert len(set(scores.values())) == 3 and all(np.isfinite(list(scores.values())))



def test_split_single_rig_path_runs_and_matches_one_launch(pair, monkeypatch):
    # sums and covered-voxel counts straight from score_placements: split path vs the one launch
    _, many = pair
    calls = []
    split = many._score_one_rig_split
    monkeypatch.setattr(many, "_score_one_rig_split", lambda *a: calls.append(1) or split(*a))
    grid = p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.4)
    rng = np.random.default_rng(5)
    weights = np.where(rng.random(grid.n_voxels) < 0.3, rng.integers(1, 1 << 32, grid.n_voxels), 0)
    stop = (rng.random(grid.n_voxels) < 0.002).astype(np.uint8)
    handle = many.prepare_grid(grid.spec, weights, stop)
    lidar = p3k.LidarModel.load("place3d_16ch")
    poses = p3k.Placement.load("pyramid").poses[None]
    args = (handle, lidar.elevations, lidar.azimuths, 60.0, poses)
    from place3d_kernels.backends.warp import scoring

    monkeypatch.setattr(scoring, "SPLIT_SINGLE_RIG", True)
    s1, c1 = many.score_placements(*args)
    assert calls, "the single-rig split path did not run"
    monkeypatch.setattr(scoring, "SPLIT_SINGLE_RIG", False)
    n = len(calls)
    s2, c2 = many.score_placements(*args)
    assert len(calls) == n
    assert c1[0] > 1000 and s1[0] > 0
    assert np.array_equal(s1, s2) and np.array_equal(c1, c2)


@pytest.mark.parametrize("value", ["0", "-2", "two"])
def test_thread_count_variable_rejects_bad_values(monkeypatch, value):
    monkeypatch.setenv("PLACE3D_WARP_CPU_THREADS", value)
    with pytest.raises(ValueError, match="PLACE3D_WARP_CPU_THREADS"):
        warp_backend.cpu_threads()


def test_thread_count_variable_is_used(monkeypatch):
    monkeypatch.setenv("PLACE3D_WARP_CPU_THREADS", "5")
    assert warp_backend.cpu_threads() == 5
    monkeypatch.delenv("PLACE3D_WARP_CPU_THREADS")
    assert warp_backend.cpu_threads() >= 1


def test_single_rig_split_rule(monkeypatch):
    """By default a single rig is split only when it is large and a core is idle beside this process."""
    from place3d_kernels.backends.warp import scoring

    monkeypatch.setattr(scoring, "SPLIT_SINGLE_RIG", None)
    monkeypatch.setattr(scoring.os, "getloadavg", lambda: (0.6, 0.6, 0.6))
    assert scoring._split_pays(262144, 2) and not scoring._split_pays(16000, 2) and not scoring._split_pays(262144, 1)
    monkeypatch.setattr(scoring.os, "getloadavg", lambda: (1.9, 1.9, 1.9))      # another job on the other core
    assert not scoring._split_pays(262144, 2)
    monkeypatch.setattr(scoring, "SPLIT_SINGLE_RIG", True)
    assert scoring._split_pays(16000, 2)
