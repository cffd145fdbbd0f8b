"""Leave-one-out grids patched from the full pool (place3d_kernels/left_out.py) are the grids of the
left-out P-SOGs built from scratch, bit for bit, and the jackknife scores on them are msog_batch's."""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.left_out import LeftOutGrids
from place3d_kernels.lidar import LidarModel
from place3d_kernels.metrics import msog_batch, msog_on_grid
from place3d_kernels.placement import Placement
from place3d_kernels.pooled import DriveRecord, PooledPSOG
from place3d_kernels.spec import PSOGSpec, RoiSpec, SceneSpec
from place3d_kernels.subset_records import spec_subset_records
from place3d_kernels.uncertainty import jackknife_records


def _spec(seed=0, frames=16):
    return PSOGSpec(SceneSpec("town", seed, frames), "warp:cpu", RoiSpec(0.8)).resolved()


@pytest.fixture(scope="module")
def subsets():
    return PooledPSOG(_spec().grid.grid(), spec_subset_records(_spec()))


@pytest.fixture(scope="module")
def drives():
    # three drives of 4, 4 and 2 subsets: leaving one out gives T' = 6 or 8, two different bases
    recs = [DriveRecord.from_psog(_spec(s, f).build(), f"d{s}") for s, f in ((0, 16), (1, 16), (2, 8))]
    return PooledPSOG(_spec().grid.grid(), recs)


@pytest.mark.parametrize("task", ["seg", "det"])
@pytest.mark.parametrize("pool", ["subsets", "drives"])
def test_every_left_out_grid_is_the_rebuilt_one(request, pool, task):
    pooled = request.getfixturevalue(pool)
    grids = LeftOutGrids(pooled, task)
    n = len(pooled)
    assert n >= 3
    for i in [*range(n), 0, n - 1, 1]:                  # again and out of order: the working copy is restored
        m = np.ones(n, dtype=np.int64)
        m[i] = 0
        want = pooled.psog(m).for_task(task)
        w, stop = grids.fields(i)
        assert w.dtype == want.weights.dtype and np.array_equal(w, want.weights), f"weights, record {i}"
        assert stop.dtype == want.stop_mask.dtype and np.array_equal(stop, want.stop_mask), f"stop, record {i}"
    if pool == "drives":
        assert len(grids._base) == 2                      # T' = 6 and 8


@pytest.mark.parametrize("occlusion", ["sog", "none"])
def test_jackknife_scores_are_msog_batch_on_the_rebuilt_pools(subsets, occlusion):
    lidar = LidarModel.load("place3d_16ch")
    rigs = {n: Placement.load(n).poses for n in ("center", "line", "pyramid")}
    got = jackknife_records(subsets.records, subsets.grid, lidar, rigs, ("seg", "det"), occlusion, "warp:cpu")
    n = len(subsets)
    poses = np.stack(list(rigs.values()))
    for t in ("seg", "det"):
        assert got[t].point.tobytes() == msog_batch(subsets.psog(), lidar, poses, occlusion, t, "warp:cpu").tobytes()
        for i in range(n):
            m = np.ones(n, dtype=np.int64)
            m[i] = 0
            want = msog_batch(subsets.psog(m), lidar, poses, occlusion, t, "warp:cpu")
            assert got[t].samples[i].tobytes() == want.tobytes(), (t, i)


def test_msog_on_grid_checks_its_inputs(subsets):
    lidar = LidarModel.load("place3d_16ch")
    ps = subsets.psog()
    far = Placement.load("center").poses.copy()
    far[0, 0] = 1e4
    with pytest.raises(ValueError, match="outside the grid"):
        msog_on_grid(ps.grid, ps.weights, ps.stop_mask, lidar, far, "warp:cpu")
    with pytest.raises(ValueError, match="minimum range"):
        msog_on_grid(ps.grid, ps.weights, ps.stop_mask,
                     LidarModel(lidar.elevations, lidar.azimuths, lidar.max_range, min_range=1.0),
                     Placement.load("center").poses, "warp:cpu")


def test_the_scene_psog_serves_as_the_point_when_it_is_the_pool(subsets):
    """The jackknife's point estimate reuses the scene's P-SOG (its weights and device grids) only when it
    is exactly the records' pool; another P-SOG is ignored, and the intervals are the same either way."""
    scene = _spec().build()
    assert subsets.plain_psog(scene) is scene
    other = _spec(1).build()
    rebuilt = subsets.plain_psog(other)
    assert rebuilt is not other
    assert np.array_equal(rebuilt.voxels, scene.voxels) and rebuilt.probs.tobytes() == scene.probs.tobytes()
    lidar = LidarModel.load("place3d_16ch")
    rigs = {n: Placement.load(n).poses for n in ("center", "pyramid")}
    plain = jackknife_records(subsets.records, subsets.grid, lidar, rigs, ("seg",), "sog", "warp:cpu")["seg"]
    for ref in (scene, other):
        got = jackknife_records(subsets.records, subsets.grid, lidar, rigs, ("seg",), "sog", "warp:cpu",
                                reference=ref)["seg"]
        assert got.point.tobytes() == plain.point.tobytes() and got.samples.tobytes() == plain.samples.tobytes()
