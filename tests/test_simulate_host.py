"""The cold build's host paths give what the earlier code gave, bit for bit: ``simulate_frame``'s gathers by
``ndarray.take`` and its one intensity pass over static and actor returns (points, labels, intensities), and
``pool_votes``'s counts by one increment per subset or ``np.bincount`` (instead of ``np.add.at``).

The earlier code is kept here, frozen, as the oracle."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.classes import REFLECTIVITY
from place3d_kernels.lidar import LidarModel
from place3d_kernels.ops import raycast
from place3d_kernels.pose import pose_from_matrix, pose_matrix
from place3d_kernels.simulate import DEFAULT_MOUNT, body_hits, simulate_frame

SIM = sys.modules["place3d_kernels.simulate"]


def _old_intensity(mesh, face, d, labels):
    cos = np.abs(np.einsum("ij,ij->i", mesh.normals[face], d))
    return (REFLECTIVITY[np.clip(labels, 0, len(REFLECTIVITY) - 1)] * cos).astype(np.float32)


def _old_simulate_frame(static, dynamic, lidar, sensor_pose_world, backend=None, body_t=None):
    """``simulate_frame`` as it was before the gathers by ``take`` (commit dcdba97)."""
    b = get_backend(backend)
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, np.asarray(sensor_pose_world)[None])
    hits = raycast(static, o, d, lidar.max_range, backend=b)
    t, face, lab, src = hits.t, hits.face, hits.label, np.zeros(len(o), dtype=bool)
    if dynamic is not None:
        dh = raycast(dynamic, o, d, lidar.max_range, backend=b)
        closer = dh.t < t
        t = np.where(closer, dh.t, t)
        face = np.where(closer, dh.face, face)
        lab = np.where(closer, dh.label, lab)
        src = closer
    hit = np.isfinite(t)
    if body_t is not None:
        hit &= t < np.asarray(body_t, dtype=np.float64)
    at = np.flatnonzero(hit)
    d_hit, face_hit, lab_hit = d[at], face[at], lab[at]
    pts = o[at] + t[at, None] * d_hit
    if dynamic is None:
        inten = _old_intensity(static, face_hit, d_hit, lab_hit)
    else:
        inten = np.empty(len(at), dtype=np.float32)
        s_hit = src[at]
        s_at, d_at = np.flatnonzero(s_hit), np.flatnonzero(~s_hit)
        if len(d_at):
            inten[d_at] = _old_intensity(static, face_hit[d_at], d_hit[d_at], lab_hit[d_at])
        if len(s_at):
            inten[s_at] = _old_intensity(dynamic, face_hit[s_at], d_hit[s_at], lab_hit[s_at])
    return pts, lab_hit.astype(np.int32), inten, o[0]


@pytest.fixture(scope="module")
def town():
    from place3d_kernels import scene as scenes

    return scenes.town(seed=2, n_frames=6)


def _same(a, b):
    for x, y in zip(a, b):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@pytest.mark.parametrize("with_actors", [True, False])
@pytest.mark.parametrize("with_body", [False, True])
def test_frames_equal_the_earlier_code(town, with_actors, with_body):
    lidar = LidarModel.load("collection_64ch")
    b = get_backend(None)
    body_t = None
    if with_body:
        from place3d_kernels.blindspot import vehicle_from_arg

        body_t = body_hits(vehicle_from_arg("car"), lidar, DEFAULT_MOUNT, b)
    mount_T = pose_matrix(DEFAULT_MOUNT)
    n_actor_returns = 0
    for f in range(town.n_frames):
        pose = pose_from_matrix(pose_matrix(town.ego_poses[f]) @ mount_T)
        dyn = town.dynamic(f) if with_actors else None
        new = simulate_frame(town.static, dyn, lidar, pose, b, body_t)
        old = _old_simulate_frame(town.static, dyn, lidar, pose, b, body_t)
        _same(new, old)
        if dyn is not None:
            hits = raycast(dyn, *b.lidar_rays(lidar.elevations, lidar.azimuths, pose[None]), lidar.max_range, backend=b)
            n_actor_returns += int(np.isfinite(hits.t).sum())
    if with_actors:
        assert n_actor_returns > 0        # the actor branch of the intensity was exercised


def test_intensity_of_normals():
    n = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    d = np.array([[0.0, 0.6, -0.8], [0.0, 1.0, 0.0]])
    got = SIM._intensity(n, d, np.array([7, 99]))
    want = (REFLECTIVITY[[7, len(REFLECTIVITY) - 1]] * np.array([0.8, 0.0])).astype(np.float32)
    assert got.tobytes() == want.tobytes()


def _old_pool_votes(votes, n_voxels, n_classes):
    """``sog.pool_votes`` as it was before its counts were taken with ``np.bincount`` (np.unique + np.add.at)."""
    vox = np.concatenate([v for v, _ in votes])
    lab = np.concatenate([w for _, w in votes])
    uniq, inv = np.unique(vox, return_inverse=True)
    counts = np.zeros((len(uniq), n_classes), dtype=np.int32)
    np.add.at(counts.reshape(-1), inv * n_classes + lab, 1)
    counts[:, 0] = len(votes) - counts[:, 1:].sum(axis=1)
    return uniq.astype(np.int64), counts


@pytest.mark.parametrize("repeat", [False, True])             # subsets of distinct ascending voxels, or not
@pytest.mark.parametrize("n_voxels", [5000, 2**40])          # the grid-sized flags, and the np.unique path
def test_pool_votes_equal_the_earlier_counts(n_voxels, repeat):
    from place3d_kernels.classes import N_CLASSES
    from place3d_kernels.sog import pool_votes

    rng = np.random.default_rng(7)
    votes = []
    for _ in range(6):
        v = np.unique(rng.integers(0, min(n_voxels, 5000), 1500)) * (n_voxels // 5000)
        votes.append((v.astype(np.int64), rng.integers(1, N_CLASSES, len(v)).astype(np.int64)))
    votes.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))     # a subset with no votes
    if repeat:      # one subset votes a voxel twice, out of order: each vote still counts (the bincount path)
        v, w = votes[0]
        votes[0] = (np.r_[v, v[3]], np.r_[w, w[3]])
    got, want = pool_votes(votes, n_voxels), _old_pool_votes(votes, n_voxels, N_CLASSES)
    for x, y in zip(got, want):
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y)
    if not repeat:
        assert got[1].sum() == len(votes) * len(got[0])       # each voxel: T entries in all


def _per_frame(scene, lidar, frames, b, body_t=None):
    """``simulate``'s frames one sweep per call (``simulate_frame``), as ``simulate`` made them before it
    cast several sweeps per call."""
    mount_T = pose_matrix(DEFAULT_MOUNT)
    out = []
    for f in frames:
        pose = pose_from_matrix(pose_matrix(scene.ego_poses[f]) @ mount_T)
        out.append(simulate_frame(scene.static, scene.dynamic(f), lidar, pose, b, body_t))
    return out


def _same_frames(got, want, scene, frames):
    assert len(got) == len(want) == len(frames)
    for pc, (pts, lab, inten, origin), f in zip(got, want, frames):
        _same((pc.points, pc.labels, pc.intensity, pc.sweep_origin, pc.ego_pose),
              (pts, lab, inten, origin, scene.ego_poses[f]))


@pytest.mark.parametrize("sweeps_per_call", [1, 2, 4, 100])
def test_sweeps_cast_together_equal_one_sweep_per_call(town, monkeypatch, sweeps_per_call):
    # batches of 1, 2 (with a remainder of 1 from 5 frames), 4 and all sweeps; frames out of order
    from place3d_kernels.simulate import simulate

    lidar = LidarModel.load("collection_64ch")
    b = get_backend(None)
    monkeypatch.setattr(SIM, "SWEEP_BATCH_RAYS", sweeps_per_call * 64 * 1024)
    # each frame's actors in a tree of their own, as _per_frame casts them (tests/test_raycast_groups.py holds
    # a grouped tree to the same hits)
    monkeypatch.setenv(SIM.ACTOR_GROUPS_ENV, "0")
    frames = [4, 0, 1, 3, 2]
    _same_frames(simulate(town, lidar, frames=frames, backend=b), _per_frame(town, lidar, frames, b), town, frames)


def test_sweeps_cast_together_on_every_backend(monkeypatch):
    # every available backend, the reference included, on a small sensor and scene (the reference is brute force)
    from place3d_kernels import available_backends
    from place3d_kernels import scene as scenes
    from place3d_kernels.simulate import simulate

    small = scenes.town(seed=1, n_frames=3)
    lidar = LidarModel.uniform(4, (-20, 5), 48, max_range=60.0)
    monkeypatch.setattr(SIM, "SWEEP_BATCH_RAYS", 2 * 4 * 48)
    monkeypatch.setenv(SIM.ACTOR_GROUPS_ENV, "0")       # as above
    for name in available_backends():
        b = get_backend(name)
        _same_frames(simulate(small, lidar, backend=b), _per_frame(small, lidar, range(3), b), small, range(3))


def test_frames_without_intensities_are_the_same_returns(town):
    """simulate(intensity=False), what a P-SOG without a condition asks for: the same points, labels and
    origins bit for bit, intensities zero; a P-SOG built from either is the same."""
    from place3d_kernels.grid import DEFAULT_GRID, Grid
    from place3d_kernels.simulate import simulate
    from place3d_kernels.sog import PSOG

    lidar = LidarModel.load("collection_64ch")
    b = get_backend(None)
    full = simulate(town, lidar, backend=b)
    bare = simulate(town, lidar, backend=b, intensity=False)
    assert len(full) == len(bare) == town.n_frames
    for x, y in zip(full, bare):
        assert x.points.tobytes() == y.points.tobytes() and x.labels.tobytes() == y.labels.tobytes()
        assert x.origins.tobytes() == y.origins.tobytes() and x.sweep_origin.tobytes() == y.sweep_origin.tobytes()
        assert y.intensity.dtype == np.float32 and not y.intensity.any() and x.intensity.any()
    grid = Grid(DEFAULT_GRID.lower, DEFAULT_GRID.upper, 0.2)      # the old default's 0.2 m: 8x fewer voxels
    a, c = PSOG.from_frames(full, grid, 3, backend=b), PSOG.from_frames(bare, grid, 3, backend=b)
    assert a.voxels.tobytes() == c.voxels.tobytes() and a.probs.tobytes() == c.probs.tobytes()


@pytest.mark.parametrize("batch", [2, 100])
def test_returns_made_on_the_device_are_the_hosts(town, monkeypatch, batch):
    """simulate(intensity=False) on a backend that makes the returns on its device (``device_returns``, Warp):
    every frame's points, labels, intensities (zeros), origins and ego pose as the host pass makes them, with
    the sweeps in batches of 2 (a remainder of 1, the actors' groups taken from an offset) and all at once;
    frames out of order."""
    from place3d_kernels import available_backends
    from place3d_kernels.simulate import device_returns, simulate

    names = [n for n in available_backends() if hasattr(get_backend(n), "sweep_returns")]
    if not names:
        pytest.skip("no backend here makes returns on its device")
    lidar = LidarModel.load("collection_64ch")
    monkeypatch.setattr(SIM, "SWEEP_BATCH_RAYS", batch * 64 * 1024)
    frames = [5, 0, 1, 3, 2]
    for name in names:
        b = get_backend(name)
        monkeypatch.setenv(SIM.DEVICE_RETURNS_ENV, "0")
        host = simulate(town, lidar, frames=frames, backend=b, intensity=False)
        monkeypatch.setenv(SIM.DEVICE_RETURNS_ENV, "1")
        made = []
        real = SIM.device_returns

        def counted(*a, **k):
            out = real(*a, **k)
            made.append(out is not None)
            return out

        monkeypatch.setattr(SIM, "device_returns", counted)
        dev = simulate(town, lidar, frames=frames, backend=b, intensity=False)
        monkeypatch.setattr(SIM, "device_returns", real)
        # one call a batch, each giving the batch's returns (None would have sent it to the host pass)
        assert made == [True] * -(-len(frames) // batch), name
        assert len(dev) == len(host)
        for x, y in zip(host, dev):
            _same((x.points, x.labels, x.intensity, x.origins, x.sweep_origin, x.ego_pose),
                  (y.points, y.labels, y.intensity, y.origins, y.sweep_origin, y.ego_pose))
    # a backend without the device pass: None, and simulate keeps the host pass
    assert device_returns(town.static, None, lidar, np.zeros((1, 6)), backend="reference") is None
