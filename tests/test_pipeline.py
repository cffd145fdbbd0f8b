"""End to end on the embedded town: simulate -> P-SOG -> M-SOG, the CLI, caching, and backend agreement."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.classes import CLASS_ID

GRID = p3k.Grid(lower=(-20.05, -20.05, -0.45), upper=(19.95, 19.95, 4.55), voxel_size=0.4)


@pytest.fixture(scope="module")
def small_town():
    return p3k.scene.town(seed=1, n_frames=8)


@pytest.fixture(scope="module")
def frames(small_town):
    lidar = p3k.LidarModel.uniform(32, (-30, 10), 360, max_range=60.0, name="test32")
    return p3k.simulate(small_town, lidar, backend="warp:cpu")


def test_simulated_frames_are_labelled_and_on_surfaces(frames, small_town):
    assert len(frames) == 8
    f = frames[0]
    assert len(f.points) > 5000
    assert np.all(f.labels > 0), "every return comes from a labelled face"
    seen = set(np.concatenate([fr.labels for fr in frames]).tolist())
    for name in ("road", "sidewalk", "building", "vehicle"):
        assert CLASS_ID[name] in seen, f"no {name} returns"
    assert np.all((f.intensity >= 0) & (f.intensity <= 1))
    ranges = np.linalg.norm(f.points - f.origins, axis=1)
    assert ranges.max() <= 60.0 + 1e-3
    # re-casting toward each point hits at its range: points lie on the first surface
    idx = np.random.default_rng(0).choice(len(f.points), 300, replace=False)
    d = f.points[idx] - f.sweep_origin
    hits = p3k.raycast(small_town.mesh(0), np.broadcast_to(f.sweep_origin, d.shape), d, 100.0, backend="warp:cpu")
    np.testing.assert_allclose(hits.t, ranges[idx], atol=2e-3)


def test_psog_and_msog_agree_across_backends(frames, device_backend):
    a = p3k.PSOG.from_frames(frames, GRID, frames_per_subset=2, backend="reference")
    b = p3k.PSOG.from_frames(frames, GRID, frames_per_subset=2, backend=device_backend)
    np.testing.assert_array_equal(a.voxels, b.voxels)
    np.testing.assert_array_equal(a.probs, b.probs)
    assert a.n_subsets == 4 and 0 < len(a.voxels) < GRID.n_voxels
    lidar = p3k.LidarModel.load("place3d_16ch").subsample(2, 5)
    for name in ("center", "pyramid", "ours-seg"):
        pl = p3k.Placement.load(name)
        for task in ("seg", "det"):
            r = p3k.msog(a, lidar, pl, task=task, backend="reference")
            w = p3k.msog(a, lidar, pl, task=task, backend=device_backend)
            assert r < 0
            assert abs(r - w) <= 1e-9, (name, task, r, w)


def test_scene_psog_is_cached_on_disk(small_town, tmp_path):
    lidar = p3k.LidarModel.uniform(16, (-30, 10), 180, max_range=40.0, name="cache16")
    p1 = p3k.scene_psog(small_town, GRID, lidar, frames_per_subset=4, cache=tmp_path)
    files = list(tmp_path.glob("psog-*.npz"))
    assert len(files) == 1
    mtime = files[0].stat().st_mtime_ns
    p2 = p3k.scene_psog(small_town, GRID, lidar, frames_per_subset=4, cache=tmp_path)
    assert files[0].stat().st_mtime_ns == mtime
    np.testing.assert_array_equal(p1.probs, p2.probs)
    p3 = p3k.scene_psog(small_town, GRID, lidar, frames_per_subset=2, cache=tmp_path)
    assert len(list(tmp_path.glob("psog-*.npz"))) == 2 and p3.n_subsets == 4


def _cli(*args, env_cache):
    import os

    env = dict(os.environ, PLACE3D_CACHE=str(env_cache))
    return subprocess.run([sys.executable, "-m", "place3d_app.cli", *args], capture_output=True, text=True,
                          env=env, timeout=600)


def test_cli_evaluate_writes_json(tmp_path):
    out = tmp_path / "eval.json"
    # 12 frames: T = 3 subsets, the fewest an interval needs (tests/test_few_subsets.py)
    r = _cli("evaluate", "center", "pyramid", "ours-seg", "--frames", "12", "--voxel-size", "0.4", "--quiet", "--routes", "1",
             "--backend", "warp:cpu", "--output", str(out), env_cache=tmp_path / "c")
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    assert set(data) >= {"rows", "backend", "grid", "seconds"}
    # the bootstrap (on by default) adds per row its intervals and pairwise orders (tests/test_intervals.py)
    assert [set(row) for row in data["rows"]] == [{"placement", "msog_seg", "msog_det", "ci", "pairwise"}] * 3
    assert all(set(row["ci"]) == {"seg", "det"} for row in data["rows"])
    seg = [row["msog_seg"] for row in data["rows"]]
    assert seg == sorted(seg, reverse=True) and all(s < 0 for s in seg)
    assert data["backend"] == "warp:cpu"
    assert "pyramid" in r.stdout and "M-SOG" in r.stdout


def test_cli_backends_and_errors(tmp_path):
    r = _cli("backends", env_cache=tmp_path)
    assert r.returncode == 0 and "reference" in r.stdout and "warp:cpu" in r.stdout
    r = _cli("evaluate", "--backend", "nope", "--quiet", env_cache=tmp_path)
    assert r.returncode == 2 and "Available here" in r.stderr
    r = _cli("evaluate", "not-a-placement", "--quiet", env_cache=tmp_path)
    assert r.returncode == 2 and "shipped names" in r.stderr


def test_conditions_plug_into_the_psog(small_town, tmp_path):
    from place3d_kernels.pipeline import FrameCondition

    lidar = p3k.LidarModel.uniform(16, (-30, 10), 180, max_range=40.0, name="cond16")
    clean = p3k.scene_psog(small_town, GRID, lidar, frames_per_subset=4, cache=tmp_path)
    fog = FrameCondition("fog", seed=1, alpha=0.06)
    foggy = p3k.scene_psog(small_town, GRID, lidar, frames_per_subset=4, cache=tmp_path, condition=fog)
    again = p3k.scene_psog(small_town, GRID, lidar, frames_per_subset=4, cache=False,
                           condition=FrameCondition("fog", seed=1, alpha=0.06))
    assert len(list(tmp_path.glob("psog-*.npz"))) == 2          # the condition is part of the cache key
    np.testing.assert_array_equal(foggy.probs, again.probs)     # per-frame seeds: deterministic
    assert not np.array_equal(clean.voxels, foggy.voxels)
    with pytest.raises(ValueError, match="unknown condition"):
        FrameCondition("hail")
