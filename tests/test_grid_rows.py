"""``Backend.grid_from_rows`` and ``grid_base_from_rows``: a grid made from its stored voxels' rows is the grid
``prepare_grid`` (``grid_base``) makes from the dense arrays, on every backend (Warp on CUDA fills it on the
device), and a P-SOG's handle, now made that way, scores as before."""

from __future__ import annotations

import numpy as np
import pytest

from place3d_kernels.backends.base import GridSpec
from place3d_kernels.backends.registry import get_backend

SPEC = GridSpec(voxel_size=0.5, shape=(9, 6, 5))       # partial bricks on every axis


def _rows(seed, k):
    rng = np.random.default_rng(seed)
    n = SPEC.n_voxels
    ids = np.sort(rng.choice(n, k, replace=False)).astype(np.int64)
    w = np.where(rng.random(k) < 0.7, rng.integers(1, 10**6, k), 0).astype(np.int64)
    return ids, w, rng.random(k) < 0.3


def _dense(ids, w, s):
    dw = np.zeros(SPEC.n_voxels, dtype=np.int64)
    dw[ids] = w
    if s is None:
        return dw, None
    ds = np.zeros(SPEC.n_voxels, dtype=np.uint8)
    ds[ids] = s
    return dw, ds


def _score(b, h):
    # rigs inside the grid, rays of a small LiDAR
    el = np.radians([-30.0, -10.0, 0.0, 12.0])
    az = np.radians(np.arange(0.0, 360.0, 20.0))
    poses = np.array([[[1.3, 1.1, 1.2, 0, 0, 0]], [[3.2, 2.0, 0.7, 0.1, -0.2, 0.5]], [[0.4, 2.6, 2.1, 0, 0.3, 2.0]]])
    return b.score_placements(h, el, az, 6.0, poses)


@pytest.mark.parametrize("stop", [True, False])
@pytest.mark.parametrize("k", [0, 1, 60, SPEC.n_voxels])
def test_grid_from_rows_scores_as_the_dense_grid(backend, k, stop):
    b = get_backend(backend)
    ids, w, s = _rows(k, k)
    s = s if stop else None
    got = _score(b, b.grid_from_rows(SPEC, ids, w, s))
    want = _score(b, b.prepare_grid(SPEC, *_dense(ids, w, s)))
    assert all(np.array_equal(g, x) for g, x in zip(got, want))
    if k == SPEC.n_voxels:
        assert got[0].any()                     # the grid has weights the rigs reach


def _warp_backends():
    import place3d_kernels as p3k

    return [n for n in p3k.available_backends() if n.startswith("warp:")]


@pytest.mark.parametrize("name", _warp_backends())
def test_warp_grids_from_rows_hold_the_dense_arrays(name):
    b = get_backend(name)
    ids, w, s = _rows(7, 80)
    dw, ds = _dense(ids, w, s)
    h, want = b.grid_from_rows(SPEC, ids, w, s), b.prepare_grid(SPEC, dw, ds)
    assert h.weights.numpy().tobytes() == want.weights.numpy().tobytes()
    assert h.masks.numpy().tobytes() == want.masks.numpy().tobytes()
    assert (h.flat is None) == (want.flat is None)
    assert h.flat is None or h.flat.numpy().tobytes() == want.flat.numpy().tobytes()
    base, ref = b.grid_base_from_rows(SPEC, ids, w, s), b.grid_base(SPEC, dw, ds)
    assert base.weights.numpy().tobytes() == ref.weights.numpy().tobytes()
    assert base.stop.numpy().tobytes() == ref.stop.numpy().tobytes()
    assert b.grid_base_from_rows(SPEC, ids, w, None).stop is None


def test_rows_outside_the_grid_or_of_another_length_are_refused(backend):
    b = get_backend(backend)
    with pytest.raises(ValueError, match="voxel indices must lie"):
        b.grid_from_rows(SPEC, np.array([SPEC.n_voxels]), np.array([1]), None)
    with pytest.raises(ValueError, match="one weight and one stop value"):
        b.grid_from_rows(SPEC, np.array([1, 2]), np.array([1]), np.array([True, False]))
