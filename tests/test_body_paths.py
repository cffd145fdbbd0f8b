"""The ego vehicle body in every kernel path: simulation (and so the P-SOG and its cache key), S-MIG, and the
CLI's --vehicle (issue 16 item 2). M-SOG on a body is covered by tests/test_vehicle.py."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.mesh import Mesh
from place3d_kernels.pose import pose_from_matrix, pose_matrix
from place3d_kernels.simulate import DEFAULT_MOUNT
from place3d_kernels.smig import BernoulliGrid, smig, smig_batch
from place3d_kernels.vehicle import VehicleBody

SIM_BACKEND = "warp:cpu"
# steep channels so that the car's roof and hood block some rays of a mount 1 m above the roof
STEEP = p3k.LidarModel.uniform(12, (-70, 10), 60, max_range=40.0, name="steep12")
GRID = p3k.Grid(lower=(-20.05, -20.05, -0.45), upper=(19.95, 19.95, 4.55), voxel_size=0.4)


@pytest.fixture(scope="module")
def town():
    return p3k.scene.town(seed=1, n_frames=4)


def _posed(mesh: Mesh, T: np.ndarray) -> Mesh:
    v = np.c_[mesh.vertices, np.ones(len(mesh.vertices))] @ T.T
    return Mesh(v[:, :3], mesh.faces, mesh.labels)


def test_simulate_drops_exactly_the_returns_blocked_by_the_body(town):
    car = VehicleBody.preset("car")
    b = p3k.get_backend(SIM_BACKEND)
    free = p3k.simulate(town, STEEP, frames=[0, 3], backend=b)
    got = p3k.simulate(town, STEEP, frames=[0, 3], backend=b, body=car)
    dropped = 0
    for f, fr, fb in zip([0, 3], free, got):
        ego = pose_matrix(town.ego_poses[f])
        o, d = b.lidar_rays(STEEP.elevations, STEEP.azimuths, pose_from_matrix(ego @ pose_matrix(DEFAULT_MOUNT))[None])
        # independently: the body posed in the world at this frame, cast with the world rays
        t_scene = p3k.raycast(town.mesh(f), o, d, STEEP.max_range, backend=b).t
        t_body = p3k.raycast(_posed(car.mesh, ego), o, d, STEEP.max_range, backend=b).t
        seen = np.isfinite(t_scene)
        assert len(fr.points) == seen.sum()
        keep = seen & (t_scene < t_body)
        assert len(fb.points) == keep.sum()
        np.testing.assert_allclose(fb.points, o[keep] + t_scene[keep, None] * d[keep], atol=1e-6)
        # the kept returns are the no-body returns minus the blocked ones, labels included
        np.testing.assert_array_equal(fb.labels, fr.labels[keep[seen]])
        np.testing.assert_array_equal(fb.points, fr.points[keep[seen]])
        dropped += int(seen.sum() - keep.sum())
    assert dropped > 50, "the test must exercise blocked rays"
    with pytest.raises(ValueError, match="inside .*'car'"):
        p3k.simulate(town, STEEP, mount=[0, 0, 1.0, 0, 0, 0], frames=[0], backend=b, body=car)


def test_psog_cache_key_and_manifest_carry_the_body(town, tmp_path):
    van = VehicleBody.preset("van")    # roof 3 cm under the default mount: blocks every downward ray near it
    lidar = p3k.LidarModel.uniform(16, (-30, 10), 90, max_range=40.0, name="cache16")
    a = p3k.scene_psog(town, GRID, lidar, frames_per_subset=2, backend=SIM_BACKEND, cache=tmp_path)
    b = p3k.scene_psog(town, GRID, lidar, frames_per_subset=2, backend=SIM_BACKEND, cache=tmp_path, body=van)
    files = sorted(tmp_path.glob("psog-*.npz"))
    assert len(files) == 2, "a body must give its own cache file"
    manifests = [json.loads(p.with_suffix(".json").read_text()) for p in files]
    bodies = [json.dumps(m) for m in manifests if '"body"' in json.dumps(m)]
    assert len(bodies) == 1 and van.key in bodies[0] and '"van"' in bodies[0]
    assert a.voxels.size != b.voxels.size or not np.array_equal(a.probs, b.probs)
    # the body-less key is the one from before bodies existed: no "body" input
    assert sum('"body"' in json.dumps(m) for m in manifests) == 1
    c = p3k.scene_psog(town, GRID, lidar, frames_per_subset=2, backend=SIM_BACKEND, cache=tmp_path, body=van)
    np.testing.assert_array_equal(b.probs, c.probs)
    assert len(list(tmp_path.glob("psog-*.npz"))) == 2


def test_spec_vehicle_round_trip_and_none():
    from place3d_kernels.spec import PSOGSpec, SceneSpec

    s = PSOGSpec(SceneSpec("town", 0, 8), vehicle="car")
    assert PSOGSpec.from_dict(s.to_dict()) == s and s.vehicle_body().name == "car"
    assert PSOGSpec(SceneSpec("town", 0, 8), vehicle="none") == PSOGSpec(SceneSpec("town", 0, 8))
    assert PSOGSpec(SceneSpec("town", 0, 8)).vehicle_body() is None
    with pytest.raises(ValueError, match="unknown vehicle 'bus'"):
        PSOGSpec(SceneSpec("town", 0, 8), vehicle="bus").vehicle_body()


# ------------------------------------------------------------------------------------------- S-MIG
SGRID = p3k.Grid(lower=(-10, -10, -1), upper=(10, 10, 5), voxel_size=0.25)
# elevations avoid 0 (a horizontal ray would graze the plate's top plane)
SLIDAR = p3k.LidarModel(np.radians(np.linspace(-31.0, 9.0, 9)), np.linspace(0, 2 * np.pi, 72, endpoint=False) + 0.01,
                        max_range=12.0)
POSE = np.array([0.1, 0.05, 2.0, 0.0, 0.0, 0.0])
PLATE = VehicleBody.from_boxes([[[-3.1, -2.7, 1.5], [3.1, 2.7, 1.6]]], "plate")


@pytest.fixture(scope="module")
def bgrid():
    rng = np.random.default_rng(3)
    p = np.zeros(SGRID.n_voxels)
    idx = rng.choice(SGRID.n_voxels, SGRID.n_voxels // 6, replace=False)
    p[idx] = rng.choice([0.25, 0.5, 0.75, 1.0], len(idx))
    return BernoulliGrid.from_probabilities(SGRID, p.reshape(SGRID.shape))


@pytest.mark.parametrize("occlusion", ["none", "sog"])
def test_smig_with_plate_equals_smig_of_clipped_rays(backend, bgrid, occlusion):
    ref = p3k.get_backend("reference")
    # independently: the reference rays of the rig, cut at the plate's analytic top face, traversed
    o, d = ref.lidar_rays(SLIDAR.elevations, SLIDAR.azimuths, POSE[None])
    t = np.full(len(o), SLIDAR.max_range)
    down = d[:, 2] < 0
    th = (1.6 - o[down, 2]) / d[down, 2]
    p = o[down] + th[:, None] * d[down]
    hit = (np.abs(p[:, 0]) <= 3.1) & (np.abs(p[:, 1]) <= 2.7) & (th < SLIDAR.max_range)
    t[np.flatnonzero(down)[hit]] = th[hit]
    assert 0 < np.sum(t < SLIDAR.max_range) < len(t)
    stop = bgrid.psog.stop_mask if occlusion == "sog" else None
    _, vox = ref.traverse(SGRID.spec, SGRID.to_local(o), d, t, stop)
    u = np.unique(vox)
    want = bgrid.psog.weights[u].sum(dtype=np.int64) / ENTROPY_SCALE
    got = smig(bgrid, SLIDAR, POSE[None], occlusion=occlusion, backend=backend, body=PLATE)
    assert got == want
    free = smig(bgrid, SLIDAR, POSE[None], occlusion=occlusion, backend=backend)
    assert got < free
    # the mean and remaining reductions follow from the same sums
    mean = smig(bgrid, SLIDAR, POSE[None], occlusion=occlusion, reduce="mean", backend=backend, body=PLATE)
    assert mean == want / len(u)
    # bit-identical to the reference backend, in a batch too
    poses = np.stack([POSE[None], POSE[None] + [[0.5, 0, 0.3, 0, 0, 0.2]]])
    np.testing.assert_array_equal(smig_batch(bgrid, SLIDAR, poses, occlusion, backend=backend, body=PLATE),
                                  smig_batch(bgrid, SLIDAR, poses, occlusion, backend="reference", body=PLATE))


def test_smig_lidar_inside_body_raises(bgrid):
    with pytest.raises(ValueError, match="rig 0: LiDAR 0 .* inside .*'plate'"):
        smig(bgrid, SLIDAR, [[0.0, 0.0, 1.55, 0, 0, 0]], backend="reference", body=PLATE)


# ------------------------------------------------------------------------------------------- CLI
def _cli(*args, cache):
    env = dict(os.environ, PLACE3D_CACHE=str(cache))
    return subprocess.run([sys.executable, "-m", "place3d_app.cli", *args], capture_output=True, text=True,
                          env=env, timeout=600)


def test_cli_evaluate_vehicle_car_differs_from_none(tmp_path):
    rows = {}
    for v in ("none", "car"):
        out = tmp_path / f"{v}.json"
        r = _cli("evaluate", "center", "line", "--frames", "8", "--voxel-size", "0.4", "--quiet", "--routes", "1", "--interval",
                 "none", "--backend", "warp:cpu", "--vehicle", v, "--output", str(out), cache=tmp_path / "c")
        assert r.returncode == 0, r.stderr
        data = json.loads(out.read_text())
        rows[v] = {row["placement"]: row for row in data["rows"]}
        assert data["psog"]["vehicle"] == (None if v == "none" else "car")
        assert (data["vehicle"] is None) == (v == "none")
        assert f"vehicle {v}" in r.stdout
    assert rows["car"].keys() == rows["none"].keys()
    assert all(rows["car"][n]["msog_seg"] != rows["none"][n]["msog_seg"] for n in rows["car"])
    assert len(list((tmp_path / "c").glob("psog-*.npz"))) == 2
    r = _cli("evaluate", "center", "--quiet", "--vehicle", "bus", cache=tmp_path / "c")
    assert r.returncode != 0 and "unknown vehicle 'bus'" in r.stderr


def test_cli_simulate_vehicle_records_the_body_and_drops_returns(tmp_path):
    counts = {}
    for v in ("none", "van"):
        out = tmp_path / v
        r = _cli("simulate", "--frames", "2", "--quiet", "--backend", "warp:cpu", "--vehicle", v, "--output", str(out),
                 cache=tmp_path / "c")
        assert r.returncode == 0, r.stderr
        meta = json.loads(next(out.rglob("sequence.json")).read_text())
        spec = meta.get("spec", meta)
        assert (spec.get("vehicle") or {}).get("name") == (None if v == "none" else "van"), list(spec)
        counts[v] = sum(p.stat().st_size for p in out.rglob("*.bin"))
    assert 0 < counts["van"] < counts["none"]
