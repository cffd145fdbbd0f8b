"""Entropy edge values and deterministic fixed-point reductions (docs/architecture.md, Kernel contract: reductions)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import place3d_kernels as p3k
from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.grid import MAX_VOXELS
from place3d_kernels.metrics import _score, msog_batch
from place3d_kernels.sog import PSOG, entropy

SETTINGS = dict(deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), print_blob=True)
K = 22
EDGE = [0.0, 1.0, 1e-30, 1e-300, 5e-324, 1.0 - 1e-16, 0.5]


# ------------------------------------------------------------------------------ entropy
@settings(max_examples=200, **SETTINGS)
@given(st.lists(st.sampled_from(EDGE) | st.floats(0.0, 1.0), min_size=1, max_size=K))
def test_entropy_edge_probabilities(raw):
    p = np.zeros(K)
    p[: len(raw)] = raw
    if p.sum() == 0:
        p[0] = 1.0
    p = p / p.sum()
    h = entropy(p)
    assert np.isfinite(h) and h >= 0 and h <= math.log(K) + 1e-12
    # the entropy of a one-hot distribution is exactly 0, with 1e-30 mass still tiny and >= 0
    assert entropy(np.eye(K)[3]) == 0.0
    tiny = np.eye(K)[0] * (1 - 1e-30)
    tiny[5] = 1e-30
    assert 0.0 <= entropy(tiny) < 1e-27


def test_psog_from_edge_probabilities():
    grid = p3k.Grid(lower=(1e6, -1e6, 0), upper=(1e6 + 2, -1e6 + 2, 1), voxel_size=0.5)
    rng = np.random.default_rng(0)
    probs = np.zeros(grid.shape + (K,))
    flat = probs.reshape(-1, K)
    n = len(flat)
    flat[:, 0] = 1.0                                     # empty
    flat[1] = np.eye(K)[7]                               # certain class 7
    flat[2] = np.full(K, 1 / K)                          # maximal entropy
    flat[3] = np.eye(K)[0] * (1 - 21e-30) + np.r_[0, np.full(21, 1e-30)]   # 1e-30 masses
    flat[4] = np.r_[0.5, 0.5, np.zeros(20)]
    flat[5, :] = 0
    flat[5, [0, 3]] = [5e-324, 1.0]                      # subnormal
    flat[6:] = rng.dirichlet(np.full(K, 0.05), n - 6)    # many near-zero probabilities
    psog = PSOG.from_probabilities(grid, probs)
    h = psog.entropy
    assert h.dtype == np.float32 and np.all(np.isfinite(h)) and np.all(h >= 0)
    assert np.all(h <= np.float32(math.log(K)) * (1 + 1e-6))
    w = psog.weights
    assert w.dtype == np.int64 and np.all(w >= 0)
    assert w[1] == 0 and w[5] == 0
    assert w[2] == int(np.rint(math.log(K) * ENTROPY_SCALE))
    assert np.all(psog.occupancy >= 0) and np.all(psog.occupancy <= 1)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1e-30])
def test_psog_rejects_non_finite_probabilities(bad):
    grid = p3k.Grid(lower=(0, 0, 0), upper=(1, 1, 1), voxel_size=0.5)
    probs = np.zeros(grid.shape + (K,))
    probs[..., 0] = 1.0
    probs[0, 0, 0, 1] = bad
    with pytest.raises(ValueError):
        PSOG.from_probabilities(grid, probs)


# ------------------------------------------------------------------------------ fixed-point sums
def test_fixed_point_overflow_bound():
    """int64 fixed-point sums cannot overflow: 1e8 voxels (and the Grid's 4e8 cap) of maximal entropy."""
    w_max = int(np.rint(math.log(K) * ENTROPY_SCALE))
    assert w_max * 10**8 < 2**63 - 1
    assert w_max * MAX_VOXELS < 2**63 - 1
    # the float64 division in _score stays within rounding of the exact mean
    s = np.int64(w_max) * np.int64(10**8)
    assert abs(float(s) / ENTROPY_SCALE / 1e8 - math.log(K)) < 1e-9
    # a grid of 1e8 voxels is accepted (the guard is 4e8) without allocating anything per voxel
    g = p3k.Grid(lower=(0, 0, 0), upper=(1000, 1000, 100), voxel_size=1.0)
    assert g.n_voxels == 10**8


def test_int64_sum_is_order_independent_over_1e8_weights():
    """Summing 1e8 fixed-point weights in any order/chunking gives one exact int64 (what the kernels do);
    done in 1e7 chunks to keep memory at 80 MB."""
    w_max = int(np.rint(math.log(K) * ENTROPY_SCALE))
    rng = np.random.default_rng(3)
    chunk = rng.integers(0, w_max + 1, 10**7, dtype=np.int64)
    fwd = np.int64(0)
    for _ in range(10):
        fwd += chunk.sum(dtype=np.int64)
    rev = np.int64(0)
    for _ in range(10):
        rev += chunk[::-1].reshape(1000, -1).sum(axis=0, dtype=np.int64).sum(dtype=np.int64)
    exact = 10 * sum(int(x) for x in np.add.reduceat(chunk, np.arange(0, 10**7, 10**5)))
    assert int(fwd) == int(rev) == exact < 2**63


def _psog_and_rigs(seed):
    grid = p3k.Grid(lower=(-20.05, -20.05, -0.45), upper=(19.95, 19.95, 4.55), voxel_size=0.2)
    rng = np.random.default_rng(seed)
    n = grid.n_voxels
    probs = np.zeros((n, K))
    probs[:, 0] = 1.0
    occ = rng.choice(n, n // 20, replace=False)
    probs[occ] = rng.dirichlet(np.full(K, 0.3), len(occ))
    psog = PSOG.from_probabilities(grid, probs.reshape(grid.shape + (K,)))
    lidar = p3k.LidarModel.uniform(8, (-25, 10), 90, max_range=40.0)
    P, L = 3, 2
    poses = np.zeros((P, L, 6))
    poses[..., :2] = rng.uniform(-1.5, 1.5, (P, L, 2))
    poses[..., 2] = rng.uniform(1.3, 2.3, (P, L))
    poses[..., 3:] = rng.uniform(-0.2, 0.2, (P, L, 3))
    poses[..., 5] = rng.uniform(-np.pi, np.pi, (P, L))
    return psog, lidar, poses


@pytest.mark.parametrize("occlusion", ["none", "sog"])
@pytest.mark.parametrize("seed", [0, 1])
def test_msog_sums_identical_across_backends_and_runs(device_backend, occlusion, seed):
    psog, lidar, poses = _psog_and_rigs(seed)
    b = p3k.get_backend(device_backend)
    local = poses.copy()
    local[..., :3] = psog.grid.to_local(poses[..., :3])
    h = psog.handle(b, occlusion)
    runs = [b.score_placements(h, lidar.elevations, lidar.azimuths, lidar.max_range, local) for _ in range(3)]
    for s, c in runs[1:]:
        np.testing.assert_array_equal(s, runs[0][0])
        np.testing.assert_array_equal(c, runs[0][1])
    ref = p3k.get_backend("reference")
    s_ref, c_ref = ref.score_placements(psog.handle(ref, occlusion), lidar.elevations, lidar.azimuths,
                                        lidar.max_range, local)
    assert runs[0][0].dtype == np.int64
    np.testing.assert_array_equal(runs[0][1], c_ref)
    np.testing.assert_array_equal(runs[0][0], s_ref)
    # the public score, bit for bit
    a = msog_batch(psog, lidar, poses, occlusion=occlusion, backend=device_backend)
    r = _score(s_ref, c_ref)
    assert np.all(np.isfinite(a)) and np.all(a <= 0)
    np.testing.assert_array_equal(a, r)
    # the batch sum equals the union of the backend's own coverage, summed exactly
    for p in range(len(poses)):
        o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, poses[p])
        stop = psog.stop_mask if occlusion == "sog" else None
        cov = p3k.coverage(psog.grid, o, d, lidar.max_range, backend=b, stop=stop).reshape(-1)
        assert int(psog.weights[cov].sum(dtype=np.int64)) == int(runs[0][0][p])
        assert int(cov.sum()) == int(runs[0][1][p])


def test_score_placements_maximal_weights_exact(backend):
    """Every voxel at maximal entropy: the sum is exactly count * w_max (no float accumulation)."""
    grid = p3k.Grid(lower=(-10.05, -10.05, -0.45), upper=(9.95, 9.95, 3.55), voxel_size=0.1)
    w_max = int(np.rint(math.log(K) * ENTROPY_SCALE))
    b = p3k.get_backend(backend)
    h = b.prepare_grid(grid.spec, np.full(grid.n_voxels, w_max, dtype=np.int64), None)
    lidar = p3k.LidarModel.uniform(8, (-20, 5), 90, max_range=30.0)
    poses = np.array([[[10.0, 10.0, 2.0, 0, 0, 0], [11.0, 9.0, 2.2, 0.1, 0.0, 1.0]]])
    s, c = b.score_placements(h, lidar.elevations, lidar.azimuths, lidar.max_range, poses)
    assert c[0] > 0 and int(s[0]) == int(c[0]) * w_max
