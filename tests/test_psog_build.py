"""The cold P-SOG build's faster data paths give the arrays the earlier code gave, bit for bit.

The earlier code is kept here, frozen, as the oracle: ``PSOG.from_frames`` pooled its subset votes with
``np.unique`` and ``np.add.at`` on a 2-D index, the subset records were ``DriveRecord.from_psog`` of a
one-subset ``PSOG.from_frames`` each, and the cold aggregate returned ``PooledPSOG(grid, recs).psog()``.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.classes import N_CLASSES
from place3d_kernels.grid import Grid
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.pose import invert, pose_matrix, transform_points
from place3d_kernels.sog import PSOG, pool_votes
from place3d_kernels.spec import PSOGSpec, SceneSpec

GRID = Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), 0.4)


def _old_from_frames(frames, grid, k, backend):
    """``PSOG.from_frames`` as it was before the votes were pooled on dense voxel ranks."""
    b = p3k.get_backend(backend)
    n_sub = max(1, len(frames) // k)
    groups = [frames[i * k:(i + 1) * k] for i in range(n_sub)] if len(frames) >= k else [frames]
    all_vox, all_lab = [], []
    for g in groups:
        to_ref = invert(pose_matrix(g[len(g) // 2].ego_pose))
        pts = np.concatenate([transform_points(to_ref, f.points) for f in g])
        lab = np.concatenate([np.asarray(f.labels, dtype=np.int32) for f in g])
        vox, win = b.vote(b.voxel_keys(grid.spec, grid.to_local(pts)), lab, N_CLASSES)
        all_vox.append(np.asarray(vox, np.int64))
        all_lab.append(np.asarray(win, np.int64))
    uniq, inv = np.unique(np.concatenate(all_vox), return_inverse=True)
    counts = np.zeros((len(uniq), N_CLASSES), dtype=np.int32)
    np.add.at(counts, (inv, np.concatenate(all_lab)), 1)
    counts[:, 0] = len(groups) - counts[:, 1:].sum(axis=1)
    return PSOG(grid, uniq, counts / float(len(groups)), n_subsets=len(groups), counts=counts)


def _old_records(frames, grid, k, backend, label):
    n_sub = max(1, len(frames) // k)
    groups = [frames[i * k:(i + 1) * k] for i in range(n_sub)] if len(frames) >= k else [frames]
    return [DriveRecord.from_psog(_old_from_frames(g, grid, len(g), backend), f"{label}#{j}")
            for j, g in enumerate(groups)]


def _same_psog(a: PSOG, b: PSOG) -> None:
    assert a.voxels.dtype == b.voxels.dtype and np.array_equal(a.voxels, b.voxels)
    assert a.probs.dtype == b.probs.dtype and a.probs.tobytes() == b.probs.tobytes()
    assert a.counts.dtype == b.counts.dtype and np.array_equal(a.counts, b.counts)
    assert a.n_subsets == b.n_subsets and a.channels == b.channels


@pytest.fixture(scope="module")
def town_frames():
    sim = sys.modules["place3d_kernels.simulate"]        # the package exports a function of that name
    return sim.simulate(SceneSpec("town", 3, 10).build())      # the default backend: same frames, faster


@pytest.mark.parametrize("k", [1, 3, 4, 20])
def test_from_frames_matches_earlier_pooling(town_frames, k, backend):
    for grid in (GRID, Grid((-20.0, -20.0, -2.0), (20.0, 20.0, 4.0), 0.1)):
        _same_psog(PSOG.from_frames(town_frames, grid, k, backend=backend),
                   _old_from_frames(town_frames, grid, k, backend))


def test_records_and_aggregate_match_earlier(town_frames, backend, tmp_path, monkeypatch):
    from place3d_kernels import subset_records as sr

    spec = PSOGSpec(SceneSpec("town", 3, 10), grid=0.4, frames_per_subset=3, cache=str(tmp_path))
    grid = spec.grid.grid()
    label = spec.scene.label
    new = sr.frame_subset_records(town_frames, grid, 3, backend, label)
    old = _old_records(town_frames, grid, 3, backend, label)
    assert len(new) == len(old) == 3
    for a, b in zip(new, old):
        assert (a.label, a.n_subsets) == (b.label, b.n_subsets)
        for x, y in ((a.voxels, b.voxels), (a.classes, b.classes), (a.counts, b.counts)):
            assert x.dtype == y.dtype and np.array_equal(x, y)
    built = sr.records_aggregator(spec)(town_frames, backend)
    _same_psog(built, PooledPSOG(grid, old).psog())
    _same_psog(built, _old_from_frames(town_frames, grid, 3, backend))
    sim = sys.modules["place3d_kernels.simulate"]
    monkeypatch.setattr(sim, "simulate", lambda *a, **k: pytest.fail("the records were not found on disk"))
    read = sr.spec_subset_records(spec)
    assert [(r.label, r.voxels.tolist(), r.classes.tolist()) for r in read] == \
        [(r.label, r.voxels.tolist(), r.classes.tolist()) for r in old]


def test_pool_votes_sparse_path_and_bad_classes():
    votes = [(np.array([5, 9, 2**40]), np.array([1, 2, 3])), (np.array([9, 2**40]), np.array([2, 1]))]
    vox, counts = pool_votes(votes, n_voxels=2**41)                    # too many voxels for dense ranks
    assert vox.tolist() == [5, 9, 2**40]
    assert counts[:, :4].tolist() == [[1, 1, 0, 0], [0, 0, 2, 0], [0, 1, 0, 1]]
    with pytest.raises(ValueError, match="classes in"):
        pool_votes([(np.array([1]), np.array([N_CLASSES]))], n_voxels=10)
    with pytest.raises(ValueError, match="voxels must lie in"):
        pool_votes([(np.array([1, 10]), np.array([1, 1]))], n_voxels=10)


def test_saved_psog_loads_identically(town_frames, tmp_path):
    import json

    ps = PSOG.from_frames(town_frames, GRID, 3, backend="reference")
    loaded = PSOG.load(ps.save(tmp_path / "p.npz"))
    _same_psog(loaded, ps)
    # the counts are stored as their occupied entries (column 0 is T minus the rest)
    with np.load(tmp_path / "p.npz") as z:
        meta = str(z["meta"])
        assert sorted(z.files) == ["meta", "occupied_counts", "occupied_index", "voxels"]
        assert len(z["occupied_counts"]) == np.count_nonzero(ps.counts[:, 1:]) > 0
    assert json.loads(meta)["n_subsets"] == ps.n_subsets
    # a file with the dense table, as np.savez_compressed wrote before, reads as the same P-SOG
    np.savez_compressed(tmp_path / "old.npz", voxels=ps.voxels, counts=ps.counts, meta=meta)
    _same_psog(PSOG.load(tmp_path / "old.npz"), ps)
    # counts whose column 0 is not T minus the rest keep the dense table
    other = ps.counts.copy()
    other[0, 0] += 1
    kept = PSOG(GRID, ps.voxels, ps.probs, n_subsets=ps.n_subsets, counts=other)
    with np.load(kept.save(tmp_path / "kept.npz")) as z:
        assert "counts" in z.files and z["counts"].tobytes() == other.tobytes()
    # a P-SOG whose probs are not counts / T keeps them in the file
    odd = PSOG(GRID, ps.voxels, ps.probs * 0.5 + 0.5 * np.eye(ps.probs.shape[1])[0], n_subsets=ps.n_subsets,
               counts=ps.counts)
    _same_psog(PSOG.load(odd.save(tmp_path / "odd.npz")), odd)


def test_scene_dynamic_is_the_concatenation_of_moved_actors():
    from place3d_kernels.mesh import Mesh
    from place3d_kernels.pose import pose_matrix

    scene = SceneSpec("town", 3, 10).build()
    assert scene.actors
    for f in (0, 7):
        parts = []
        for a in scene.actors:               # the earlier Scene.dynamic: one validated Mesh per actor
            T = pose_matrix(a.poses[f])
            parts.append(Mesh(a.mesh.vertices @ T[:3, :3].T + T[:3, 3], a.mesh.faces, a.mesh.labels))
        old, new = Mesh.concatenate(parts), scene.dynamic(f)
        for x, y in ((old.vertices, new.vertices), (old.faces, new.faces), (old.labels, new.labels),
                     (old.valid_faces, new.valid_faces), (old.shift, new.shift)):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()


def test_simulate_frame_matches_earlier_masks():
    # the gathers do not depend on the backend: the default one (the reference's BVH of the town takes 40 s)
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.ops import raycast
    from place3d_kernels.classes import REFLECTIVITY
    from place3d_kernels.pose import pose_from_matrix

    def intensity(mesh, face, d, labels):                   # simulate._intensity, frozen
        cos = np.abs(np.einsum("ij,ij->i", mesh.normals[face], d))
        return (REFLECTIVITY[np.clip(labels, 0, len(REFLECTIVITY) - 1)] * cos).astype(np.float32)

    sim = sys.modules["place3d_kernels.simulate"]
    scene = SceneSpec("town", 3, 10).build()
    lidar = LidarModel.load("collection_64ch")
    lidar = LidarModel(lidar.elevations[::4], lidar.azimuths[::16], lidar.max_range, "coarse")
    b = p3k.get_backend(None)
    pose = pose_from_matrix(pose_matrix(scene.ego_poses[4]) @ pose_matrix(sim.DEFAULT_MOUNT))
    dyn = scene.dynamic(4)
    for dynamic in (dyn, None):
        pts, lab, inten, origin = sim.simulate_frame(scene.static, dynamic, lidar, pose, b)
        # the earlier gathers: boolean masks, the intensity per source mesh
        o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, pose[None])
        h = raycast(scene.static, o, d, lidar.max_range, backend=b)
        t, face, lb, src = h.t, h.face, h.label, np.zeros(len(o), dtype=bool)
        if dynamic is not None:
            dh = raycast(dynamic, o, d, lidar.max_range, backend=b)
            src = dh.t < t
            t, face, lb = np.where(src, dh.t, t), np.where(src, dh.face, face), np.where(src, dh.label, lb)
        hit = np.isfinite(t)
        want = np.empty(int(hit.sum()), dtype=np.float32)
        s_hit, d_hit = src[hit], ~src[hit]
        want[d_hit] = intensity(scene.static, face[hit][d_hit], d[hit][d_hit], lb[hit][d_hit])
        if s_hit.any():
            want[s_hit] = intensity(dynamic, face[hit][s_hit], d[hit][s_hit], lb[hit][s_hit])
        assert pts.tobytes() == (o[hit] + t[hit, None] * d[hit]).tobytes()
        assert np.array_equal(lab, lb[hit].astype(np.int32)) and inten.tobytes() == want.tobytes()
        assert dynamic is None or s_hit.any()


def test_plain_psog_needs_probs_that_are_counts_over_T(town_frames, tmp_path):
    from place3d_kernels import subset_records as sr

    recs = sr.frame_subset_records(town_frames, GRID, 3, None, "d")
    pooled = PooledPSOG(GRID, recs)
    ref = pooled.psog()
    assert ref.probs_are_counts() and pooled.plain_psog(ref) is ref
    loaded = PSOG.load(ref.save(tmp_path / "r.npz"))       # probs not stored: derived from the counts
    assert loaded.probs_are_counts() and pooled.plain_psog(loaded) is loaded
    probs = ref.probs.copy()
    probs[7, 0] = np.nextafter(probs[7, 0], 2.0)          # one ulp off counts / T
    off = PSOG(GRID, ref.voxels, probs, n_subsets=ref.n_subsets, counts=ref.counts)
    assert not off.probs_are_counts()
    rebuilt = pooled.plain_psog(off)
    assert rebuilt is not off and rebuilt.probs.tobytes() == ref.probs.tobytes()
    kept = PSOG.load(off.save(tmp_path / "off.npz"))       # probs stored, read back as they were
    assert kept.probs.tobytes() == probs.tobytes() and not kept.probs_are_counts()


@pytest.mark.parametrize("block", [1, 7, 1 << 20])
def test_left_out_base_in_blocks(town_frames, monkeypatch, block):
    from place3d_kernels import left_out
    from place3d_kernels import subset_records as sr

    monkeypatch.setattr(left_out, "BASE_BLOCK", block)
    recs = sr.frame_subset_records(town_frames[:6], GRID, 2, None, "d")
    pooled = PooledPSOG(GRID, recs)
    for task in ("seg", "det"):
        grids = left_out.LeftOutGrids(pooled, task)
        for i in (0, 2, 1):
            w, stop = grids.fields(i)
            m = np.ones(len(recs), dtype=np.int64)
            m[i] = 0
            want = pooled.psog(m).for_task(task)
            assert w.tobytes() == want.weights.tobytes() and stop.tobytes() == want.stop_mask.tobytes()


def _old_fillet_points(corners, radii, step=0.25):
    """``scene.paths.fillet``'s points as they were built row by row before."""
    import math

    P = np.asarray(corners, float)
    radii = np.broadcast_to(np.asarray(radii, float), (len(P),))
    pts = [P[0]]
    for i in range(1, len(P) - 1):
        u, w = P[i] - P[i - 1], P[i + 1] - P[i]
        lu, lw = np.linalg.norm(u), np.linalg.norm(w)
        u, w = u / lu, w / lw
        cross = u[0] * w[1] - u[1] * w[0]
        theta = math.acos(float(np.clip(u @ w, -1.0, 1.0)))
        if theta < 1e-6:
            pts.append(P[i])
            continue
        t = min(radii[i] * math.tan(theta / 2), 0.49 * lu, 0.49 * lw)
        r = t / math.tan(theta / 2)
        A = P[i] - u * t
        sgn = 1.0 if cross > 0 else -1.0
        centre = A + sgn * r * np.array([-u[1], u[0]])
        a0 = math.atan2(A[1] - centre[1], A[0] - centre[0])
        k = max(2, int(math.ceil(r * theta / step)))
        a = a0 + sgn * theta * np.linspace(0, 1, k + 1)
        pts.extend(np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)], 1))
    pts.append(P[-1])
    pts = np.array(pts)
    out = [pts[0]]
    for a, b in zip(pts[:-1], pts[1:]):
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        out.extend(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
    return np.array(out)


def test_fillet_points_match_earlier_rows(rng):
    from place3d_kernels.scene.paths import Path as CurvePath, fillet

    for n in (2, 3, 6):
        corners = np.cumsum(rng.uniform(-40, 40, size=(n, 2)), axis=0)
        if n == 6:                      # a straight corner (no fillet): corners 0, 1, 2 on one line
            corners[2] = corners[1] + 2 * (corners[1] - corners[0])
        radii = rng.uniform(0, 15, size=n)
        want = CurvePath(_old_fillet_points(corners, radii))
        got = fillet(corners, radii)
        assert got.points.tobytes() == want.points.tobytes() and got.yaw.tobytes() == want.yaw.tobytes()
    for laps in (1, 3):                 # a walker's laps: each corner met again is filleted once (paths._arcs)
        ring = np.array([(0, 0), (70.5, 0), (70.5, 71.2), (0, 71.2)]) + rng.uniform(-2, 2, 2)
        corners = np.concatenate([ring] * laps + [ring[:1]])
        want = CurvePath(_old_fillet_points(corners, 1.0, 0.2))
        got = fillet(corners, 1.0, 0.2)
        assert got.points.tobytes() == want.points.tobytes() and got.s.tobytes() == want.s.tobytes()


def test_entropy_in_blocks_is_the_whole_array_entropy(town_frames, monkeypatch):
    from place3d_kernels import sog

    probs = PSOG.from_frames(town_frames, GRID, 2, backend="reference").probs
    monkeypatch.setattr(sog, "ENTROPY_BLOCK", len(probs))
    whole = sog.entropy(probs)                              # the whole array at once, as before
    for block in (1, 5, 4096):
        monkeypatch.setattr(sog, "ENTROPY_BLOCK", block)
        assert sog.entropy(probs).tobytes() == whole.tobytes()
        head = probs[:100].reshape(50, 2, probs.shape[1])  # more axes: blocks along the first
        assert sog.entropy(head).tobytes() == whole[:100].reshape(50, 2).tobytes()


def test_actors_are_built_while_the_backend_is_probed(monkeypatch):
    # place3d_app.prefetch.backend_after_actors: while a backend probe runs on a thread, the actors' meshes
    # of the first frames are built and handed to scene_psog on the scene, which builds only the rest
    import threading
    from concurrent.futures import Future

    from place3d_app.prefetch import backend_after_actors
    from place3d_kernels.pipeline import scene_psog

    sim = sys.modules["place3d_kernels.simulate"]
    spec = PSOGSpec(SceneSpec("town", 3, 8))
    scene = spec.scene.build()                 # memoised: the scene backend_after_actors builds on
    direct = scene_psog(scene, GRID, frames_per_subset=2, backend=None, cache=False)
    seen = {}
    real = sim.simulate

    def spy(*a, dynamic=None, **k):
        seen["prebuilt"] = sorted(dynamic)
        return real(*a, dynamic=dynamic, **k)

    monkeypatch.setattr(sys.modules["place3d_kernels.pipeline"], "simulate", spy)
    probe = Future()
    calls = []
    real_dynamic = type(scene).dynamic

    def dynamic(self, f):                    # the probe ends while the third frame's actors are built
        calls.append(f)
        if len(calls) == 3:
            threading.Timer(0.0, probe.set_result, (p3k.get_backend(None),)).start()
            threading.Event().wait(0.2)
        return real_dynamic(self, f)

    monkeypatch.setattr(type(scene), "dynamic", dynamic)
    b = backend_after_actors(spec, probe)
    assert b is p3k.get_backend(None)
    late = scene_psog(scene, GRID, frames_per_subset=2, backend=b, cache=False)
    assert seen["prebuilt"] == [0, 1, 2] and sorted(calls) == list(range(8))   # each frame's actors once
    _same_psog(late, direct)


def test_a_cached_psog_is_found_without_a_backend(tmp_path):
    spec = PSOGSpec(SceneSpec("town", 3, 8), grid=0.8, frames_per_subset=2, cache=str(tmp_path))
    assert spec.cached(cache=str(tmp_path)) is None               # nothing there yet
    built = spec.build(cache=str(tmp_path))
    found = spec.cached(cache=str(tmp_path))
    assert found is not None
    _same_psog(found, built)


def test_cold_records_find_their_psog_without_pooling_again(town_frames, tmp_path, monkeypatch):
    import os

    from place3d_kernels import left_out
    from place3d_kernels import subset_records as sr

    handles = left_out.PreparedLeftOut()                 # this test's own memo (the aggregator reads HANDLES)
    monkeypatch.setattr(left_out, "HANDLES", handles)
    spec = PSOGSpec(SceneSpec("town", 3, 10), grid=0.4, frames_per_subset=3, cache=str(tmp_path))
    built = sr.records_aggregator(spec)(town_frames, None)
    recs, key = sr.keyed_subset_records(spec)
    assert key is not None
    fresh = PooledPSOG(spec.grid.grid(), recs)
    want = fresh.counts()
    pooled = PooledPSOG(spec.grid.grid(), recs)
    monkeypatch.setattr(pooled, "plain_psog", lambda ref=None: pytest.fail("pooled and compared again"))
    assert handles.plain_psog(pooled, built, key) is built
    got = pooled.counts()
    for a, b in zip(got[:2], want[:2]):
        assert a.dtype == b.dtype and np.array_equal(a, b) and not a.flags.writeable
    assert got[2] == want[2]
    # the file rewritten (a new identity): checked as before, and still the pool
    path = sr.subset_records_path(spec)[0]
    os.replace(path, path.with_name("moved.npz"))
    os.replace(path.with_name("moved.npz"), path)
    os.utime(path, ns=(1, 1))
    recs2, key2 = sr.keyed_subset_records(spec)
    assert key2 is not None and key2 != key
    checked = []
    again = PooledPSOG(spec.grid.grid(), recs2)
    real = again.plain_psog
    monkeypatch.setattr(again, "plain_psog", lambda ref=None: checked.append(1) or real(ref))
    assert handles.plain_psog(again, built, key2) is built and checked == [1]
