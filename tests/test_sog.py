"""P-SOG from hand-built frames: voting, ties, unlabeled points, subsets, entropy, detection variant."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.classes import CLASS_ID

G = p3k.Grid(lower=(0, 0, 0), upper=(4, 4, 2), voxel_size=1.0)
ROAD, CAR, BLD, TREE = CLASS_ID["road"], CLASS_ID["vehicle"], CLASS_ID["building"], CLASS_ID["vegetation"]
ORIGIN = np.zeros(6)


def frame(points, labels, pose=ORIGIN):
    return p3k.PointCloud(np.asarray(points, float), np.asarray(labels), ego_pose=np.asarray(pose, float))


def _vote_by_hand(keys, labels):
    """Each voxel's label with the most points, ties to the lowest; keys < 0 and label 0 do not vote."""
    from collections import Counter, defaultdict

    per = defaultdict(Counter)
    for k, lab in zip(keys.tolist(), labels.tolist()):
        if k >= 0 and lab > 0:
            per[k][lab] += 1
    vox = sorted(per)
    return vox, [min(per[v], key=lambda lab: (-per[v][lab], lab)) for v in vox]


def test_vote_matches_a_count_by_hand(backend, rng):
    # every backend's vote (the reference's and OpenCL's host sort, base.host_vote, and the device kernels)
    # against a per-voxel count in plain Python, many ties among few labels
    keys = rng.integers(-3, 600, 5000)
    labels = rng.integers(0, 5, 5000)
    vox, lab = p3k.get_backend(backend).vote(keys, labels, 22)
    want_vox, want_lab = _vote_by_hand(keys, labels)
    assert vox.tolist() == want_vox and lab.tolist() == want_lab


def test_vote_majority_ties_and_unlabeled(backend):
    pts = [[0.5, 0.5, 0.5]] * 5 + [[1.5, 0.5, 0.5]] * 4 + [[2.5, 0.5, 0.5]] * 3 + [[9, 9, 9]]
    labels = [ROAD, ROAD, CAR, CAR, CAR,          # voxel A: car wins 3-2
              BLD, TREE, TREE, BLD,               # voxel B: 2-2 tie -> lowest id (building = 1)
              0, 0, 0,                            # voxel C: only unlabeled points -> stays empty
              ROAD]                               # outside the grid: ignored
    psog = p3k.PSOG.from_frames([frame(pts, labels)], G, frames_per_subset=1, backend=backend)
    dense = psog.dense()
    assert psog.n_subsets == 1
    assert dense[0, 0, 0, CAR] == 1.0
    assert dense[1, 0, 0, BLD] == 1.0
    assert dense[2, 0, 0, 0] == 1.0            # empty
    assert len(psog.voxels) == 2
    np.testing.assert_allclose(dense.sum(axis=-1), 1.0)


def test_subsets_give_frequencies(backend):
    # 4 frames, k = 2 -> T = 2 subsets; voxel (0,0,0): road in subset 1, car in subset 2
    f = [frame([[0.5, 0.5, 0.5]], [ROAD]), frame([[0.5, 0.5, 0.5]], [ROAD]),
         frame([[0.5, 0.5, 0.5]], [CAR]), frame([[3.5, 3.5, 1.5]], [BLD])]
    psog = p3k.PSOG.from_frames(f, G, frames_per_subset=2, backend=backend)
    d = psog.dense()
    assert psog.n_subsets == 2
    np.testing.assert_allclose(d[0, 0, 0, [0, ROAD, CAR]], [0.0, 0.5, 0.5])
    np.testing.assert_allclose(d[3, 3, 1, [0, BLD]], [0.5, 0.5])
    np.testing.assert_allclose(psog.entropy[0, 0, 0], np.log(2), rtol=1e-6)
    np.testing.assert_allclose(psog.entropy[3, 3, 1], np.log(2), rtol=1e-6)
    assert psog.entropy[1, 1, 1] == 0.0


def test_subset_merged_in_middle_frame_ego_frame(backend):
    # the same world point seen from two ego poses; the subset uses frame index 1 (the middle of 3)
    world = [[10.5, 0.5, 0.5]]
    poses = [np.array([9.0, 0, 0, 0, 0, 0]), np.array([10.0, 0, 0, 0, 0, 0]), np.array([11.0, 0, 0, 0, 0, 0])]
    frames = [frame(world, [ROAD], p) for p in poses]
    psog = p3k.PSOG.from_frames(frames, G, frames_per_subset=3, backend=backend)
    assert psog.voxels.tolist() == [int(G.flat(np.array([0, 0, 0])))]
    # a yawed ego pose rotates the world into the ego frame
    yawed = frame([[0.0, 2.5, 0.5]], [CAR], [0, 0, 0, 0, 0, np.pi / 2])   # ahead of a car facing +y
    psog = p3k.PSOG.from_frames([yawed], G, frames_per_subset=1, backend=backend)
    assert psog.voxels.tolist() == [int(G.flat(np.array([2, 0, 0])))]


def test_detection_variant_merges_classes():
    probs = np.zeros(G.shape + (22,))
    probs[..., 0] = 1.0
    probs[0, 0, 0] = 0
    probs[0, 0, 0, [0, CAR, ROAD, BLD]] = [0.25, 0.25, 0.25, 0.25]
    psog = p3k.PSOG.from_probabilities(G, probs)
    det = psog.detection()
    assert det.channels == ("empty", "vehicle", "other")
    np.testing.assert_allclose(det.dense()[0, 0, 0], [0.25, 0.25, 0.5])
    np.testing.assert_allclose(psog.entropy[0, 0, 0], np.log(4), rtol=1e-6)
    h = -(0.25 * np.log(0.25) * 2 + 0.5 * np.log(0.5))
    np.testing.assert_allclose(det.entropy[0, 0, 0], h, rtol=1e-6)


def test_entropy_edge_probabilities():
    p = np.array([[1.0, 0, 0], [0.5, 0.5, 0], [1 - 1e-30, 1e-30, 0]])
    h = p3k.sog.entropy(p)
    assert h[0] == 0.0 and np.isfinite(h).all()
    np.testing.assert_allclose(h[1], np.log(2))
    assert 0 <= h[2] < 1e-27


def test_from_probabilities_validates():
    with pytest.raises(ValueError, match="sum to 1"):
        p3k.PSOG.from_probabilities(G, np.full(G.shape + (3,), 0.5))
    with pytest.raises(ValueError, match="shape"):
        p3k.PSOG.from_probabilities(G, np.ones((2, 2, 2, 3)))


def test_save_load_roundtrip(tmp_path):
    f = [frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5]], [ROAD, CAR])]
    psog = p3k.PSOG.from_frames(f, G, frames_per_subset=1, backend="reference")
    back = p3k.PSOG.load(psog.save(tmp_path / "p.npz"))
    np.testing.assert_array_equal(back.voxels, psog.voxels)
    np.testing.assert_array_equal(back.probs, psog.probs)
    assert back.grid == psog.grid and back.n_subsets == 1
    with np.load(tmp_path / "p.npz") as z:
        assert "probs" not in z.files            # from frames: counts / T, derived on load to the same bits


def test_npz_members_are_read_as_numpy_reads_them(tmp_path):
    # the P-SOG reader inflates each member in one call (sog._npz_arrays); it must give np.load's arrays: a saved
    # P-SOG's members, and an empty, a 0-d text, a Fortran-ordered and a small-int member; object arrays refused
    import io
    import json

    from place3d_kernels.sog import _npz_arrays

    f = [frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5]], [ROAD, CAR]), frame([[0.5, 0.5, 0.5]], [CAR])]
    path = p3k.PSOG.from_frames(f, G, frames_per_subset=1, backend="reference").save(tmp_path / "p.npz")
    buf = io.BytesIO()
    np.savez_compressed(buf, empty=np.zeros(0), meta=json.dumps({"a": 1}), fortran=np.asfortranarray(
        np.arange(12.0).reshape(3, 4)), small=np.arange(5, dtype=np.int8), rows=np.zeros((0, 3), np.int64))
    for data in (path.read_bytes(), buf.getvalue()):
        got = _npz_arrays(data)
        with np.load(io.BytesIO(data), allow_pickle=False) as want:
            assert sorted(got) == sorted(want.files)
            for k in want.files:
                assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape, k
                assert np.array_equal(got[k], want[k]) and got[k].flags.writeable, k
    buf = io.BytesIO()
    np.savez(buf, objects=np.array([1, "a"], dtype=object))
    with pytest.raises(ValueError, match="object arrays"):
        _npz_arrays(buf.getvalue())


def test_a_loaded_psog_makes_its_dense_counts_only_when_asked(tmp_path):
    # pooling reads a drive's occupied entries as stored (DriveRecord.from_psog); the dense (M, K) table took
    # most of a cache read and is made on first use of ``counts``, the same table as before the save
    import pickle

    from place3d_kernels.pooled import DriveRecord

    f = [frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5], [2.5, 0.5, 0.5]], [ROAD, CAR, CAR]),
         frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5]], [ROAD, ROAD])]
    psog = p3k.PSOG.from_frames(f, G, frames_per_subset=1, backend="reference")
    back = p3k.PSOG.load(psog.save(tmp_path / "p.npz"))
    rec, want = DriveRecord.from_psog(back, "d"), DriveRecord.from_psog(psog, "d")
    assert back._counts is None                              # the record came from the stored entries
    for name in ("voxels", "classes", "counts"):
        a, b = getattr(rec, name), getattr(want, name)
        assert a.dtype == b.dtype and np.array_equal(a, b)
    again = pickle.loads(pickle.dumps(back))                 # a served client's copy keeps the entries
    for q in (back, again):
        assert q.counts.dtype == psog.counts.dtype and np.array_equal(q.counts, psog.counts)
    np.testing.assert_array_equal(back.probs, psog.probs)
    with pytest.raises(ValueError, match="not both"):
        p3k.PSOG(G, psog.voxels, None, psog.channels, 2, psog.counts, occupied=back.occupied)


def test_save_load_keeps_probs_that_are_not_counts_over_t(tmp_path):
    rng = np.random.default_rng(2)
    p = rng.random(G.shape + (3,))
    p /= p.sum(axis=-1, keepdims=True)
    psog = p3k.PSOG.from_probabilities(G, p)                 # no counts: probs are stored
    back = p3k.PSOG.load(psog.save(tmp_path / "p.npz"))
    np.testing.assert_array_equal(back.probs, psog.probs)
    f = [frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5]], [ROAD, CAR])]
    counted = p3k.PSOG.from_frames(f, G, frames_per_subset=1, backend="reference")
    odd = p3k.PSOG(G, counted.voxels, counted.probs * 0.5 + 0.25, counted.channels, 1, counted.counts)
    back = p3k.PSOG.load(odd.save(tmp_path / "q.npz"))      # counts present but probs not counts / T
    np.testing.assert_array_equal(back.probs, odd.probs)


def test_psog_identical_across_backends(device_backend, rng):
    n = 20000
    frames = [frame(rng.uniform([-1, -1, -0.5], [5, 5, 2.5], (n, 3)), rng.integers(0, 22, n),
                    [rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), 0, 0, 0, rng.uniform(-0.2, 0.2)])
              for _ in range(6)]
    grid = p3k.Grid(lower=(0, 0, 0), upper=(4, 4, 2), voxel_size=0.25)
    a = p3k.PSOG.from_frames(frames, grid, frames_per_subset=2, backend="reference")
    b = p3k.PSOG.from_frames(frames, grid, frames_per_subset=2, backend=device_backend)
    np.testing.assert_array_equal(a.voxels, b.voxels)
    np.testing.assert_array_equal(a.probs, b.probs)


def _counts_by_hand(votes, n_classes):
    """Every subset's votes counted one by one (np.unique + np.add.at): the dense (M, K) counts, column 0 the
    subsets in which the voxel was empty (T minus the others)."""
    vox = np.concatenate([np.asarray(v, np.int64) for v, _ in votes])
    lab = np.concatenate([np.asarray(w, np.int64) for _, w in votes])
    uniq, inv = np.unique(vox, return_inverse=True)
    counts = np.zeros((len(uniq), n_classes), dtype=np.int32)
    np.add.at(counts.reshape(-1), inv * n_classes + lab, 1)
    counts[:, 0] = len(votes) - counts[:, 1:].sum(axis=1)
    return uniq, counts


def test_vote_entries_are_the_entries_of_the_votes_counts(rng):
    # PSOG.from_frames keeps its counts as the occupied entries a cache file stores, counted by one sort of the
    # votes (sog.vote_entries), and pool_votes makes its dense table from them: the entries, dtypes and P-SOG
    # of the votes counted by hand; votes whose voxels repeat within a subset, a class-0 vote (its voxel kept)
    # and an empty subset included
    from place3d_kernels.classes import N_CLASSES
    from place3d_kernels.sog import _counts_members, pool_votes, vote_entries

    K, n = N_CLASSES, 5000
    votes = [(np.sort(rng.choice(n, 300, replace=False)), rng.integers(1, K, 300)) for _ in range(6)]
    votes.append((rng.integers(0, n, 200), rng.integers(1, K, 200)))               # repeats, not ascending
    votes.append((np.array([7, 4999], np.int64), np.array([0, 3], np.int64)))      # a class-0 vote
    votes.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))
    voxels, counts = _counts_by_hand(votes, K)
    got_voxels, (at, cnt) = vote_entries(votes, n, K)
    dense_voxels, dense = pool_votes(votes, n, K)
    assert np.array_equal(dense_voxels, voxels) and dense.dtype == counts.dtype and np.array_equal(dense, counts)
    want = _counts_members(counts, len(votes))
    assert got_voxels.dtype == voxels.dtype and np.array_equal(got_voxels, voxels)
    assert at.dtype == want["occupied_index"].dtype and np.array_equal(at, want["occupied_index"])
    assert cnt.dtype == want["occupied_counts"].dtype and np.array_equal(cnt, want["occupied_counts"])
    g = p3k.Grid(lower=(0, 0, 0), upper=(50, 10, 10), voxel_size=1.0)
    made = p3k.PSOG(g, got_voxels, None, n_subsets=len(votes), occupied=(at, cnt))
    assert made.counts.dtype == counts.dtype and np.array_equal(made.counts, counts)
    for bad, match in (([(np.array([n]), np.array([1]))], "voxels must lie"),
                       ([(np.array([1]), np.array([K]))], "classes in")):
        with pytest.raises(ValueError, match=match):
            pool_votes(bad, n, K)
        with pytest.raises(ValueError, match=match):
            vote_entries(bad, n, K)


def test_a_psog_from_frames_saves_the_members_of_its_dense_counts(tmp_path):
    # save writes a P-SOG's occupied entries as made (no dense table in between): the members a P-SOG with the
    # same counts given densely writes, byte for byte
    import zipfile

    f = [frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5], [2.5, 0.5, 0.5]], [ROAD, CAR, CAR]),
         frame([[0.5, 0.5, 0.5], [1.5, 2.5, 1.5]], [ROAD, ROAD]), frame([[3.5, 3.5, 1.5]], [TREE])]
    made = p3k.PSOG.from_frames(f, G, frames_per_subset=1, backend="reference")
    assert made.occupied is not None and made._counts is None
    dense = p3k.PSOG.from_counts(G, made.voxels, made.counts, made.n_subsets)
    a, b = zipfile.ZipFile(made.save(tmp_path / "a.npz")), zipfile.ZipFile(dense.save(tmp_path / "b.npz"))
    assert a.namelist() == b.namelist() and "occupied_index.npy" in a.namelist()
    for name in a.namelist():
        assert a.read(name) == b.read(name), name


def test_transform_points_into_a_buffer_gives_the_same_bits(rng):
    from place3d_kernels.pose import pose_matrix, transform_points

    T = pose_matrix(np.array([3.1, -2.7, 0.4, 0.03, -0.02, 1.3]))
    p = rng.normal(scale=40.0, size=(1001, 3))
    buf = np.full((1500, 3), np.nan)
    got = transform_points(T, p, out=buf[200:1201])
    assert np.shares_memory(got, buf)
    assert np.array_equal(got.view(np.uint64), transform_points(T, p).view(np.uint64))
    assert np.isnan(buf[:200]).all() and np.isnan(buf[1201:]).all()
