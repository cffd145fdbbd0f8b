"""Indicator grids made from a P-SOG's stored rows (``Backend.indicator_from_rows``, ``indicators.indicator_handle``).

The denominators' 0/1 grids are made from the stored voxels' rows, as ``PSOG.handle`` makes the weights' grid,
instead of dense host arrays: on CUDA and OpenCL filled on the device. Declared binary, they are counted from
the first grid's walk in ``score_placements_many``. Every backend must give the sums the reference gives for
the dense grid, and ``indicator_handle`` the counts of ``indicator_weights``.
"""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.backends.base import GridSpec
from place3d_kernels.backends.reference import ReferenceBackend


def _backends():
    import place3d_kernels as p3k

    names = list(dict.fromkeys(["reference", *p3k.available_backends()]))
    return names + (["opencl:pocl/atomic"] if "opencl:pocl" in names else [])


def _get(name):
    from place3d_kernels.backends.registry import get_backend

    if name.endswith("/atomic"):          # the GPUs' score strategy (brick pairs, flat masks), on the CPU device
        from place3d_kernels.backends.opencl.host import OpenCLBackend

        return OpenCLBackend(name.split(":")[1].split("/")[0], score_strategy="atomic")
    return get_backend(name)


@pytest.mark.parametrize("name", _backends())
def test_indicator_from_rows_counts_what_the_dense_grid_sums(name, rng):
    spec = GridSpec(0.25, (23, 17, 9))
    n = spec.n_voxels
    voxels = np.sort(rng.choice(n, n // 3, replace=False))
    w_rows = np.where(rng.uniform(size=len(voxels)) < 0.7, rng.integers(1, 2**40, len(voxels)), 0)
    stop_rows = rng.uniform(size=len(voxels)) < 0.03
    ind_rows = (w_rows > 0).astype(np.int64)
    el = np.deg2rad([-30.0, -12.0, -3.0, 0.0, 5.0])
    az = np.deg2rad(np.arange(0.0, 360.0, 7.5))
    poses = np.array([[[2.0, 2.1, 1.0, 0, 0, 0.1]], [[3.3, 2.2, 1.2, 0.05, 0, -0.4]], [[1.1, 3.0, 0.6, 0, 0.1, 2.0]]])
    dense_ind, dense_stop = np.zeros(n, np.int64), np.zeros(n, np.uint8)
    dense_ind[voxels], dense_stop[voxels] = ind_rows, stop_rows
    ref = ReferenceBackend()
    want = ref.score_placements(ref.prepare_grid(spec, dense_ind, dense_stop), el, az, 20.0, poses)
    b = _get(name)
    first = b.grid_from_rows(spec, voxels, w_rows, stop_rows)
    ind = b.indicator_from_rows(spec, voxels, ind_rows, stop_rows)
    assert want[0].min() > 0 and not np.array_equal(want[0], want[1])    # some covered voxels have weight 0
    for got in (b.score_placements(ind, el, az, 20.0, poses), b.score_placements_many([first, ind], el, az, 20.0,
                                                                                      poses)[1]):
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


@pytest.mark.parametrize("kind", ["evidence", "uncertain"])
def test_indicator_handle_counts_the_indicator_weights(kind, device_backend):
    """``indicator_handle`` (rows) against ``prepare_indicator`` of ``indicator_weights`` (dense), on a pooled
    P-SOG of the embedded town: the same counts for the paper's rigs, with the stop mask and without (the device
    backends: the reference walks each ray in Python, and the first test holds them to it)."""
    from place3d_kernels.indicators import indicator_handle, indicator_weights
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.placement import Placement
    from place3d_kernels.pooled import Drive, PoolSettings, build_pooled

    from place3d_kernels.backends.registry import get_backend

    b = get_backend(device_backend)
    settings = PoolSettings(voxel_size=0.4, frames_per_subset=2, backend="warp:cpu", cache=False)
    p = build_pooled([Drive("town", seed=s, frames=4) for s in (100, 101)], settings).psog()
    lidar = LidarModel.load("place3d_16ch")
    poses = np.stack([Placement.load(n).poses for n in ("center", "line", "pyramid")])
    local = poses.copy()
    local[..., :3] = p.grid.to_local(poses[..., :3])
    for occlusion in ("sog", "none"):
        stop = p.stop_mask if occlusion == "sog" else None
        dense = b.prepare_indicator(p.grid.spec, indicator_weights(p, kind), stop)
        got = b.score_placements(indicator_handle(p, kind, b, occlusion), lidar.elevations, lidar.azimuths,
                                 lidar.max_range, local)
        want = b.score_placements(dense, lidar.elevations, lidar.azimuths, lidar.max_range, local)
        assert want[0].min() > 0
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
