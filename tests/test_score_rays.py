"""Backend.score_rays (explicit rays, CSR per candidate): equal to score_placements on the paper rigs,
to the reference on heterogeneous candidates, and to traverse where rays end early."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.backends.base import GridSpec

REF = p3k.get_backend("reference")
# grid-local: the ego sits at (10, 10, 2) of a 20 m x 20 m x 8 m box of 0.25 m voxels
SPEC = GridSpec(0.25, (80, 80, 32))
EGO = np.array([10.0, 10.0, 2.0])
EL = np.radians(np.linspace(-25.0, 5.0, 5))
AZ = np.linspace(0.0, 2 * np.pi, 36, endpoint=False) + 0.013
T_MAX = 14.0


def _grid(rng):
    w = rng.integers(0, 2**40, SPEC.n_voxels)
    w[rng.uniform(size=SPEC.n_voxels) < 0.5] = 0            # free space carries no weight
    stop = (rng.uniform(size=SPEC.n_voxels) < 0.004).astype(np.uint8)
    return w, stop


def _paper_poses():
    poses = np.stack([pl.poses for pl in p3k.Placement.all_paper().values()])   # (11, 4, 6)
    local = poses.copy()
    local[..., :3] = poses[..., :3] + EGO - np.array([0.0, 0.0, 2.0])
    return local


@pytest.mark.parametrize("occluded", [False, True])
def test_equals_score_placements_on_paper_rigs(backend, rng, occluded):
    b = p3k.get_backend(backend)
    w, stop = _grid(rng)
    h = b.prepare_grid(SPEC, w, stop if occluded else None)
    poses = _paper_poses()
    want = b.score_placements(h, EL, AZ, T_MAX, poses)
    o, d = b.lidar_rays(EL, AZ, poses.reshape(-1, 6))
    per = poses.shape[1] * len(EL) * len(AZ)
    off = np.arange(len(poses) + 1, dtype=np.int64) * per
    got = b.score_rays(h, o, d, np.full(len(o), T_MAX), off)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert np.all(got[1] > 0) and got[0].dtype == np.int64 and got[1].dtype == np.int64


def _hetero_batch(rng):
    # candidates with 1, 3, 0, 2 LiDARs of two beam patterns; one empty candidate; per-ray lengths
    rigs = [1, 3, 0, 2]
    el2, az2 = np.radians([-15.0, -2.0, 3.0]), np.linspace(0.1, 6.0, 23)
    os_, ds, off = [], [], [0]
    for k, n in enumerate(rigs):
        for li in range(n):
            pose = np.r_[EGO + rng.uniform(-1, 1, 3), rng.uniform(-0.3, 0.3, 3)]
            o, d = REF.lidar_rays(*((EL, AZ) if (k + li) % 2 else (el2, az2)), pose)
            os_.append(o)
            ds.append(d)
        off.append(sum(len(x) for x in os_))
    o, d = np.concatenate(os_), np.concatenate(ds)
    t_end = rng.uniform(0.0, T_MAX, len(o))
    return o, d, t_end, np.array(off, dtype=np.int64)


def test_heterogeneous_candidates_equal_reference(backend, rng):
    b = p3k.get_backend(backend)
    w, stop = _grid(rng)
    o, d, t_end, off = _hetero_batch(rng)
    for s in (None, stop):
        got = b.score_rays(b.prepare_grid(SPEC, w, s), o, d, t_end, off)
        want = REF.score_rays(REF.prepare_grid(SPEC, w, s), o, d, t_end, off)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        assert got[0][2] == 0 and got[1][2] == 0                      # the empty candidate
        assert np.all(got[1][[0, 1, 3]] > 0)
    # no candidates, and candidates without rays
    h = b.prepare_grid(SPEC, w, stop)
    s0, c0 = b.score_rays(h, np.empty((0, 3)), np.empty((0, 3)), np.empty(0), np.zeros(1, np.int64))
    assert s0.shape == (0,) and c0.shape == (0,)
    s2, c2 = b.score_rays(h, np.empty((0, 3)), np.empty((0, 3)), np.empty(0), np.zeros(3, np.int64))
    assert s2.tolist() == [0, 0] and c2.tolist() == [0, 0]


def test_short_t_end_counts_as_traverse_says(backend, rng):
    b = p3k.get_backend(backend)
    w, stop = _grid(rng)
    h = b.prepare_grid(SPEC, w, stop)
    o, d = REF.lidar_rays(EL, AZ, np.r_[EGO, 0.0, 0.0, 0.0])
    full = np.full(len(o), T_MAX)
    short = full.copy()
    short[::3] = rng.uniform(0.3, 4.0, len(short[::3]))            # a third of the rays end early
    off = np.array([0, len(o), 2 * len(o)], dtype=np.int64)
    sums, counts = b.score_rays(h, np.r_[o, o], np.r_[d, d], np.r_[full, short], off)
    for p, te in enumerate((full, short)):
        _, vox = REF.traverse(SPEC, o, d, te, stop)
        u = np.unique(vox)
        assert counts[p] == len(u)
        assert sums[p] == w[u].sum(dtype=np.int64)
    assert counts[1] < counts[0]


def test_bad_offsets_are_rejected(backend):
    b = p3k.get_backend(backend)
    h = b.prepare_grid(SPEC, np.zeros(SPEC.n_voxels, np.int64), None)
    o = np.zeros((4, 3)) + 1.0
    d = np.tile([1.0, 0.0, 0.0], (4, 1))
    with pytest.raises(ValueError, match="ray_offsets"):
        b.score_rays(h, o, d, np.ones(4), np.array([0, 3], np.int64))
    with pytest.raises(ValueError, match="ray_offsets"):
        b.score_rays(h, o, d, np.ones(4), np.array([0, 3, 2, 4], np.int64))


@pytest.mark.parametrize("strategy", ["private", "atomic"])
def test_opencl_both_grid_layouts(strategy, rng):
    # grids prepared for either score strategy (byte stop mask or bricked masks) serve score_rays alike
    if "opencl:pocl" not in p3k.available_backends():
        pytest.skip("OpenCL (PoCL) is not available here")
    from place3d_kernels.backends.opencl.host import OpenCLBackend

    b = OpenCLBackend("pocl", score_strategy=strategy)
    w, stop = _grid(rng)
    o, d, t_end, off = _hetero_batch(rng)
    for s in (None, stop):
        got = b.score_rays(b.prepare_grid(SPEC, w, s), o, d, t_end, off)
        want = REF.score_rays(REF.prepare_grid(SPEC, w, s), o, d, t_end, off)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
