"""M-SOG against values worked by hand on a tiny grid, for every occlusion mode and both tasks."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.classes import CLASS_ID

ROAD, CAR, BLD = CLASS_ID["road"], CLASS_ID["vehicle"], CLASS_ID["building"]
# 5 x 5 x 1 grid of 1 m voxels; one LiDAR at the centre of voxel (2, 2, 0) with four horizontal rays
# along +x, +y, -x, -y
GRID = p3k.Grid(lower=(0, 0, 0), upper=(5, 5, 1), voxel_size=1.0)
LIDAR = p3k.LidarModel(elevations=[0.0], azimuths=np.radians([0, 90, 180, 270]), max_range=100.0)
RIG = p3k.Placement([[2.5, 2.5, 0.5, 0, 0, 0]])


def h(*p):
    p = np.asarray(p, float)
    p = p[p > 0]
    return float(-(p * np.log(p)).sum())


@pytest.fixture(scope="module")
def psog():
    probs = np.zeros(GRID.shape + (22,))
    probs[..., 0] = 1.0

    def put(ijk, channels, values):
        probs[ijk] = 0.0
        probs[ijk + (list(channels),)] = values

    put((3, 2, 0), [0, ROAD], [0.5, 0.5])          # H = ln 2, occupied 0.5 -> stops "sog" rays
    put((4, 2, 0), [CAR], [1.0])                   # H = 0
    put((2, 3, 0), [0, BLD], [0.25, 0.75])         # occupied 0.75 -> stops
    put((2, 4, 0), [0, CAR, ROAD], [0.5, 0.25, 0.25])
    put((1, 2, 0), [0, CAR], [0.9, 0.1])           # occupied 0.1: rays pass
    put((0, 0, 0), [ROAD], [1.0])                  # never covered
    return p3k.PSOG.from_probabilities(GRID, probs)


H32 = h(0.5, 0.5)
H23 = h(0.25, 0.75)
H24_SEG = h(0.5, 0.25, 0.25)
H24_DET = h(0.5, 0.25, 0.25)   # vehicle 0.25, other 0.25: same partition sizes
H12 = h(0.9, 0.1)


def test_sog_occlusion(backend, psog):
    # +x: (2,2) (3,2) stop | +y: (2,2) (2,3) stop | -x: (2,2) (1,2) (0,2) | -y: (2,2) (2,1) (2,0)
    want = -(H32 + H23 + H12) / 7
    assert p3k.msog(psog, LIDAR, RIG, occlusion="sog", backend=backend) == pytest.approx(want, abs=1e-9)


def test_no_occlusion(backend, psog):
    # every voxel of the cross: 9 voxels
    want = -(H32 + H23 + H24_SEG + H12) / 9
    assert p3k.msog(psog, LIDAR, RIG, occlusion="none", backend=backend) == pytest.approx(want, abs=1e-9)


def test_mesh_occlusion(backend, psog):
    # a wall across +x at x = 3.4 stops that ray inside voxel (3, 2): 8 voxels, (4, 2) not covered
    wall = p3k.Mesh([[3.4, 0, -1], [3.4, 5, -1], [3.4, 5, 2], [3.4, 0, 2]], [[0, 1, 2], [0, 2, 3]])
    want = -(H32 + H23 + H24_SEG + H12) / 8
    got = p3k.msog(psog, LIDAR, RIG, occlusion="mesh", mesh=wall, backend=backend)
    assert got == pytest.approx(want, abs=1e-9)


def test_detection_task(backend, psog):
    want = -(H32 + H23 + H24_DET + H12) / 9
    got = p3k.msog(psog, LIDAR, RIG, occlusion="none", task="det", backend=backend)
    assert got == pytest.approx(want, abs=1e-9)
    # building/road become "other": voxel (3,2) is still {empty .5, other .5}
    assert p3k.msog(psog, LIDAR, RIG, occlusion="sog", task="det", backend=backend) == pytest.approx(
        -(H32 + H23 + H12) / 7, abs=1e-9)


def test_batch_equals_single_and_is_bit_identical(device_backend, psog, rng):
    poses = np.zeros((6, 2, 6))
    poses[..., :3] = rng.uniform([0.2, 0.2, 0.2], [4.8, 4.8, 0.8], (6, 2, 3))
    poses[..., 5] = rng.uniform(-np.pi, np.pi, (6, 2))
    lidar = p3k.LidarModel.uniform(4, (-10, 10), 90, max_range=20.0)
    for occ in ("sog", "none"):
        for task in ("seg", "det"):
            a = p3k.msog_batch(psog, lidar, poses, occ, task, backend=device_backend)
            b = p3k.msog_batch(psog, lidar, poses, occ, task, backend="reference")
            np.testing.assert_array_equal(a, b)
            single = [p3k.msog(psog, lidar, p, occ, task, backend=device_backend) for p in poses]
            np.testing.assert_array_equal(a, single)
            for norm in ("evidence", "uncertain"):      # optimize scores its baselines in one batch
                a = p3k.msog_batch(psog, lidar, poses, occ, task, backend=device_backend, normalisation=norm)
                one = [p3k.msog_batch(psog, lidar, p[None], occ, task, backend=device_backend,
                                      normalisation=norm)[0] for p in poses]
                np.testing.assert_array_equal(a, one)


def test_covered_voxels_union_gives_msog(backend, psog):
    v = p3k.covered_voxels(psog, LIDAR, RIG.poses, occlusion="sog", backend=backend)
    assert len(v) == 7
    from place3d_kernels.metrics import msog_from_voxels

    assert msog_from_voxels(psog, v) == p3k.msog(psog, LIDAR, RIG, backend=backend)


def test_msog_is_never_positive_and_empty_grid_scores_zero(backend):
    probs = np.zeros(GRID.shape + (22,))
    probs[..., 0] = 1.0
    empty = p3k.PSOG.from_probabilities(GRID, probs)
    assert p3k.msog(empty, LIDAR, RIG, backend=backend) == 0.0


def test_rig_rays_and_scores_bit_identical_on_ties(device_backend):
    """Rays from voxel corners along 45-degree and 1:2 diagonals pass exactly through voxel edges and
    corners, where one ulp in a direction decides which side voxel a ray visits. Backends must build the
    rig's rays exactly as the reference does (R @ local, no renormalisation, no fused multiply-add) and
    then agree on every covered voxel."""
    grid = p3k.Grid(lower=(0, 0, 0), upper=(8, 8, 4), voxel_size=0.25)       # exact binary planes
    rng = np.random.default_rng(7)
    probs = rng.dirichlet(np.full(4, 0.3), grid.shape)
    full = np.zeros(grid.shape + (22,))
    full[..., [0, ROAD, CAR, BLD]] = probs
    psog = p3k.PSOG.from_probabilities(grid, full)
    az = np.radians(np.concatenate([np.arange(0, 360, 45), np.degrees(np.arctan2([1, 2, -1, 1], [2, 1, 2, -2]))]))
    el = np.radians([-45.0, -np.degrees(np.arctan(0.5)), -10.0, 0.0, 30.0])
    lidar = p3k.LidarModel(elevations=el, azimuths=az, max_range=30.0)
    poses = np.zeros((4, 3, 6))
    poses[..., :3] = rng.integers(4, 28, (4, 3, 3)) * 0.25 * np.array([1, 1, 0.5])
    poses[..., 5] = np.radians(rng.choice([0.0, 45.0, 90.0, -135.0], (4, 3)))
    ref = p3k.get_backend("reference")
    b = p3k.get_backend(device_backend)
    if getattr(b, "fp64", True):
        o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, poses[0])
        ro, rd = ref.lidar_rays(lidar.elevations, lidar.azimuths, poses[0])
        np.testing.assert_array_equal(np.asarray(d), rd)
        np.testing.assert_array_equal(np.asarray(o), ro)
    for occ in ("sog", "none"):
        np.testing.assert_array_equal(p3k.msog_batch(psog, lidar, poses, occ, backend=b),
                                      p3k.msog_batch(psog, lidar, poses, occ, backend=ref))
