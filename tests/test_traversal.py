"""Voxel traversal and coverage: hand-built cases, adversarial rays, and agreement with the reference."""

from __future__ import annotations

import numpy as np
import pytest
from checks import assert_visits_close

import place3d_kernels as p3k

G = p3k.Grid(lower=(0, 0, 0), upper=(4, 4, 4), voxel_size=1.0)


def flat(grid, *ijk):
    return [int(grid.flat(np.array(c))) for c in ijk]


def visits(grid, o, d, t_end, backend, stop=None):
    tr = p3k.traverse(grid, np.atleast_2d(o), np.atleast_2d(d), t_end, backend=backend, stop=stop)
    return [tr.ray(i).tolist() for i in range(len(tr))]


# ------------------------------------------------------------------------------ hand-built cases
def test_axis_parallel_each_axis(backend):
    for axis in range(3):
        o = np.array([0.5, 1.5, 2.5])
        for sign in (1.0, -1.0):
            d = np.zeros(3)
            d[axis] = sign
            got = visits(G, o, d, 100.0, backend)[0]
            cells = []
            start = int(np.floor(o[axis]))
            rng_ = range(start, 4) if sign > 0 else range(start, -1, -1)
            for c in rng_:
                ijk = np.floor(o).astype(int)
                ijk[axis] = c
                cells.append(ijk)
            assert got == flat(G, *cells), (axis, sign)


def test_negative_zero_components(backend):
    o = np.array([[0.5, 0.5, 0.5], [3.5, 0.5, 0.5]])
    d = np.array([[1.0, -0.0, 0.0], [-1.0, -0.0, -0.0]])
    got = visits(G, o, d, 10.0, backend)
    assert got[0] == flat(G, (0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0))
    assert got[1] == flat(G, (3, 0, 0), (2, 0, 0), (1, 0, 0), (0, 0, 0))


def test_origin_on_face_moves_into_the_voxel_ahead(backend):
    # origin on the plane x = 2 moving -x: the first voxel is i = 1, never i = 2
    got = visits(G, [2.0, 0.5, 0.5], [-1.0, 0.1, 0.0], 10.0, backend)[0]
    assert got[0] == flat(G, (1, 0, 0))[0]
    got = visits(G, [2.0, 0.5, 0.5], [1.0, 0.1, 0.0], 10.0, backend)[0]
    assert got[0] == flat(G, (2, 0, 0))[0]


def test_origin_on_edge_and_corner(backend):
    got = visits(G, [2.0, 2.0, 0.5], [-1.0, -1.0, 0.0], 10.0, backend)[0]
    assert got == flat(G, (1, 1, 0), (0, 0, 0))
    got = visits(G, [1.0, 1.0, 1.0], [1.0, 1.0, 1.0], 100.0, backend)[0]
    assert got == flat(G, (1, 1, 1), (2, 2, 2), (3, 3, 3))


def test_ray_starting_outside_enters(backend):
    got = visits(G, [-5.0, 0.5, 0.5], [1.0, 0.0, 0.0], 6.5, backend)[0]
    assert got == flat(G, (0, 0, 0), (1, 0, 0))
    # misses the grid entirely / points away from it
    assert visits(G, [-5.0, 0.5, 0.5], [-1.0, 0.0, 0.0], 100.0, backend)[0] == []
    assert visits(G, [-5.0, 5.5, 0.5], [1.0, 0.0, 0.0], 100.0, backend)[0] == []


def test_t_end_zero_visits_nothing(backend):
    assert visits(G, [0.5, 0.5, 0.5], [1.0, 0.0, 0.0], 0.0, backend)[0] == []


def test_segment_end_inside_voxel(backend):
    assert visits(G, [0.5, 0.5, 0.5], [1.0, 0.0, 0.0], 1.2, backend)[0] == flat(G, (0, 0, 0), (1, 0, 0))


def test_stop_mask_ends_after_first_occupied(backend):
    stop = np.zeros(G.n_voxels, dtype=np.uint8)
    stop[flat(G, (2, 0, 0))] = 1
    got = visits(G, [0.5, 0.5, 0.5], [1.0, 0.0, 0.0], 100.0, backend, stop=stop)[0]
    assert got == flat(G, (0, 0, 0), (1, 0, 0), (2, 0, 0))


def test_tiny_voxels_on_long_rays(device_backend, rng):
    grid = p3k.Grid(lower=(0, 0, 0), upper=(200, 0.5, 0.5), voxel_size=0.01)
    n = 6
    o = np.column_stack([np.full(n, 0.003), rng.uniform(0.1, 0.4, n), rng.uniform(0.1, 0.4, n)])
    d = np.column_stack([np.ones(n), rng.uniform(-1e-3, 1e-3, n), rng.uniform(-1e-3, 1e-3, n)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = p3k.traverse(grid, o, d, 200.0, backend=device_backend)
    want = p3k.traverse(grid, o, d, 200.0, backend="reference")
    for i in range(n):
        assert len(want.ray(i)) > 19_000
        assert_visits_close(grid, o[i], d[i], 200.0, got.ray(i), want.ray(i))


def test_grid_far_from_origin(backend, rng):
    off = np.array([1e5, -1e5, 50.0])
    grid = p3k.Grid(lower=off, upper=off + [20, 20, 5], voxel_size=0.1)
    o = off + rng.uniform([0, 0, 0], [20, 20, 5], (200, 3))
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = p3k.traverse(grid, o, d, 30.0, backend=backend)
    want = p3k.traverse(grid, o, d, 30.0, backend="reference")
    for i in range(200):
        assert_visits_close(grid, o[i], d[i], 30.0, got.ray(i), want.ray(i))


# ------------------------------------------------------------------------------ random + adversarial
def _adversarial_rays(grid, rng, n=400):
    s = grid.voxel_size
    shape = np.asarray(grid.shape)
    lo = np.asarray(grid.lower)
    parts = []
    # origins exactly on voxel faces, edges and corners (integer multiples of s)
    ijk = rng.integers(0, shape + 1, (n, 3)).astype(float)
    jitter = rng.uniform(0, 1, (n, 3)) * (rng.uniform(size=(n, 3)) < 0.4)
    parts.append(lo + (ijk + jitter) * s)
    d = rng.normal(size=(n, 3))
    # axis-parallel and planar directions with exact zeros and negative zeros
    zero = rng.uniform(size=(n, 3)) < 0.3
    d[zero] = np.where(rng.uniform(size=zero.sum()) < 0.5, 0.0, -0.0)
    d[np.all(d == 0, axis=1)] = [1.0, 0.0, 0.0]
    # diagonal directions through edges and corners
    diag = rng.uniform(size=n) < 0.2
    d[diag] = rng.choice([-1.0, 1.0], (diag.sum(), 3))
    # rays from outside the grid
    outside = rng.uniform(size=n) < 0.25
    parts[0][outside] = lo - 3 * s + rng.uniform(0, 1, (outside.sum(), 3)) * (shape + 6) * s
    return parts[0], d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("voxel", [0.2, 1.0, 0.05])
def test_traverse_matches_reference(device_backend, rng, voxel):
    grid = p3k.Grid(lower=(-3.2, -1.0, 0.4), upper=(3.2, 2.2, 2.0), voxel_size=voxel)
    o, d = _adversarial_rays(grid, rng)
    t_end = rng.choice([0.0, 0.3, 2.0, 50.0, np.inf], len(o))
    got = p3k.traverse(grid, o, d, t_end, backend=device_backend)
    want = p3k.traverse(grid, o, d, t_end, backend="reference")
    assert np.all(np.isfinite(got.voxels.astype(float)))
    te = np.minimum(t_end, 1e3)
    # origins on (or within float rounding of) a voxel plane may start on either side of it
    frac = grid.to_local(o) / grid.voxel_size
    clean = np.all(np.abs(frac - np.round(frac)) > 1e-4, axis=1)
    assert clean.sum() > 50
    for i in range(len(o)):
        g, w = got.ray(i), want.ray(i)
        assert_visits_close(grid, o[i], d[i], te[i], g, w)
        if clean[i]:
            np.testing.assert_array_equal(g, w, err_msg=f"ray {i}: {o[i]} {d[i]} t_end {t_end[i]}")


def test_random_rays_identical_to_reference(device_backend, rng):
    grid = p3k.Grid(lower=(-10, -10, -1), upper=(10, 10, 3), voxel_size=0.2)
    o = rng.uniform([-9, -9, 0], [9, 9, 2.5], (3000, 3))
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = p3k.traverse(grid, o, d, 40.0, backend=device_backend)
    want = p3k.traverse(grid, o, d, 40.0, backend="reference")
    np.testing.assert_array_equal(got.offsets, want.offsets)
    np.testing.assert_array_equal(got.voxels, want.voxels)
    stop = (rng.uniform(size=grid.n_voxels) < 0.01).astype(np.uint8)
    np.testing.assert_array_equal(p3k.coverage(grid, o, d, 40.0, backend=device_backend, stop=stop),
                                  p3k.coverage(grid, o, d, 40.0, backend="reference", stop=stop))


def test_coverage_is_union_of_traversal(backend, rng):
    grid = p3k.Grid(lower=(0, 0, 0), upper=(3, 3, 3), voxel_size=0.25)
    o = rng.uniform(0, 3, (300, 3))
    d = rng.normal(size=(300, 3))
    tr = p3k.traverse(grid, o, d, 2.0, backend=backend)
    mask = p3k.coverage(grid, o, d, 2.0, backend=backend)
    want = np.zeros(grid.n_voxels, bool)
    want[tr.voxels] = True
    np.testing.assert_array_equal(mask.reshape(-1), want)
    assert mask.shape == grid.shape


def test_no_duplicates_and_contiguous_steps(backend, rng):
    grid = p3k.Grid(lower=(0, 0, 0), upper=(5, 5, 5), voxel_size=0.5)
    o = rng.uniform(0, 5, (500, 3))
    d = rng.normal(size=(500, 3))
    tr = p3k.traverse(grid, o, d, 20.0, backend=backend)
    for i in range(len(tr)):
        v = tr.ray(i)
        assert len(np.unique(v)) == len(v)
        ijk = grid.unflat(v)
        # consecutive voxels share a face, an edge or a corner: each index moves by at most one
        assert np.all(np.abs(np.diff(ijk, axis=0)) <= 1)
