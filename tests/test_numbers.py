"""Numbers at the edges of float64 and float32 (issue 33, "Numbers"): every backend gives the same answer
or the same named error.

* A direction is normalised without overflow or underflow: (1.4e154, 0, 0) and (1e-170, 0, 0) hit what
  (1, 0, 0) hits.
* Coordinates beyond ``COORDINATE_LIMIT`` of the frame kernels work in are refused alike everywhere
  (a triangle at +-1e30 m was hit by the reference and missed by Warp and OpenCL).
* Zero rigs score to an empty array everywhere (Warp's CPU device raised a RuntimeError).
* Grid parameters give a ValueError, never a bare OverflowError (voxel size 5e-324).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.backends.base import COORDINATE_LIMIT
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.ops import MeshGroups
from place3d_kernels.vehicle import VehicleBody

TRI = p3k.Mesh([[5.0, -1.0, -1.0], [5.0, 1.0, -1.0], [5.0, 0.0, 1.0]], [[0, 1, 2]])
GRID = p3k.Grid(lower=(0, 0, 0), upper=(5, 5, 1), voxel_size=1.0)
LIDAR = p3k.LidarModel(elevations=[0.0], azimuths=np.radians([0, 90, 180, 270]), max_range=100.0)


@pytest.mark.parametrize("scale", [1.4e154, 1e300, 1.7e308, 1e-170, 1e-300])
def test_huge_and_tiny_directions_hit_as_their_unit_direction(backend, scale):
    # squares of 1.4e154 overflow to inf and those of 1e-170 underflow to 0: the old code reported a miss
    # (with a RuntimeWarning) for the first and a "zero-length direction" error for the second
    o = np.zeros((3, 3))
    unit = np.array([[1.0, 0, 0], [0.6, 0.0, 0.8], [0.96, 0.28, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # no overflow, underflow or division warnings either
        want = p3k.raycast(TRI, o, unit, backend=backend)
        got = p3k.raycast(TRI, o, unit * scale, backend=backend)
    np.testing.assert_array_equal(got.face, want.face)
    assert got.face[0] == 0 and got.t[0] == 5.0
    np.testing.assert_allclose(got.t, want.t, rtol=1e-12)
    # the smallest double: its direction is (1, 0, 0) exactly
    np.testing.assert_array_equal(p3k.raycast(TRI, o[:1], [[5e-324, 0.0, 0.0]], backend=backend).t, [5.0])


@pytest.mark.parametrize("scale", [1.4e154, 1e-170])
def test_huge_and_tiny_directions_traverse_as_their_unit_direction(backend, scale):
    o = np.array([[0.5, 0.5, 0.5], [0.25, 0.5, 0.5]])
    unit = np.array([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        want = p3k.traverse(GRID, o, unit, 4.0, backend=backend)
        got = p3k.traverse(GRID, o, unit * scale, 4.0, backend=backend)
    np.testing.assert_array_equal(got.offsets, want.offsets)
    np.testing.assert_array_equal(got.voxels, want.voxels)
    assert len(want.ray(0)) == 5


def test_coordinate_limit_is_documented_and_float32_can_resolve_it():
    # float32's spacing at the limit stays below the smallest voxel the package tests (1 cm)
    assert np.spacing(np.float32(COORDINATE_LIMIT)) < 0.01
    assert "COORDINATE_LIMIT" in p3k.raycast.__doc__ and "COORDINATE_LIMIT" in p3k.Grid.__doc__


def test_a_triangle_at_1e30_is_refused_on_every_backend(backend):
    # spanning +-1e30: the reference hit it at t = 1, Warp and OpenCL missed it
    huge = p3k.Mesh([[-1e30, -1e30, -1.0], [1e30, -1e30, -1.0], [0.0, 1e30, -1.0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="COORDINATE_LIMIT") as e:
        p3k.raycast(huge, [[0.0, 0.0, 0.0]], [[0.0, 0.0, -1.0]], backend=backend)
    assert "1e+30" in str(e.value)
    # a small triangle 1e30 m away, seen from the origin: t = 1e30 for the reference, a miss elsewhere
    far = p3k.Mesh([[1e30, -1.0, -1.0], [1e30, 1.0, -1.0], [1e30, 0.0, 1.0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="ray 1 starts at .*COORDINATE_LIMIT"):
        p3k.raycast(far, [[1e30, 0.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0]] * 2, backend=backend)
    # float32 rays take the device's checked path where there is one: the same error
    with pytest.raises(ValueError, match="ray 0 starts at .*COORDINATE_LIMIT"):
        p3k.raycast(TRI, np.array([[-2e5, 0, 0], [0, 0, 0]], np.float32), np.array([[1, 0, 0]] * 2, np.float32),
                    backend=backend)


def test_far_world_coordinates_are_fine_when_rays_are_near_the_scene(backend):
    # the shift is subtracted in float64, so only distances from the mesh's centre are limited
    x = 1e12
    far = p3k.Mesh([[x + 5.0, -1.0, -1.0], [x + 5.0, 1.0, -1.0], [x + 5.0, 0.0, 1.0]], [[0, 1, 2]])
    h = p3k.raycast(far, [[x, 0.0, 0.0], [x, 0.0, 0.0]], [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], backend=backend)
    np.testing.assert_array_equal(h.face, [0, -1])
    assert h.t[0] == 5.0


def test_rays_far_from_a_grid_are_refused_on_every_backend(backend):
    for fn in (p3k.traverse, p3k.coverage):
        with pytest.raises(ValueError, match="ray 0 starts at .*grid's lower corner.*COORDINATE_LIMIT"):
            fn(GRID, [[-1e30, 0.5, 0.5]], [[1.0, 0.0, 0.0]], np.inf, backend=backend)
    # just inside the limit: accepted, and the ray enters the grid
    got = p3k.traverse(GRID, [[-0.9 * COORDINATE_LIMIT, 0.5, 0.5]], [[1.0, 0.0, 0.0]], np.inf, backend=backend)
    np.testing.assert_array_equal(got.voxels, [0, 5, 10, 15, 20])


def test_mesh_groups_leave_far_rays_to_raycast(backend):
    if not MeshGroups.supported(backend):
        pytest.skip(f"{backend} has no grouped casts")
    groups = MeshGroups([TRI, TRI], backend=backend)
    o = np.array([[0.0, 0, 0], [-2e5, 0, 0]])
    d = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    assert groups.cast(o, d, 1e9, 1) is None
    assert groups.cast(o[:1].repeat(2, 0), d, 1e9, 1).face.tolist() == [0, 0]


@pytest.mark.parametrize("case", ["sog", "none", "mesh", "evidence", "min_range", "body"])
def test_msog_batch_of_zero_rigs_is_empty_everywhere(backend, case):
    probs = np.zeros(GRID.shape + (22,))
    probs[..., 0] = 1.0
    psog = p3k.PSOG.from_probabilities(GRID, probs)
    lidar = LIDAR
    kw = {}
    if case in ("sog", "none", "mesh"):
        kw["occlusion"] = case
        kw["mesh"] = p3k.Mesh([[4.5, 0, 0], [4.5, 5, 0], [4.5, 2.5, 1]], [[0, 1, 2]])
    elif case == "evidence":
        kw["normalisation"] = "evidence"
    elif case == "min_range":
        lidar = p3k.LidarModel(elevations=[0.0], azimuths=np.radians([0, 90]), max_range=100.0, min_range=0.5)
    else:
        kw["body"] = VehicleBody.from_boxes(np.array([[[0.1, 0.1, 0.0], [0.4, 0.4, 0.3]]]))
    got = p3k.msog_batch(psog, lidar, np.zeros((0, 1, 6)), backend=backend, **kw)
    assert isinstance(got, np.ndarray) and got.dtype == np.float64 and got.shape == (0,)


def test_backends_score_zero_candidates(backend):
    b = get_backend(backend)
    h = b.prepare_grid(GRID.spec, np.ones(GRID.n_voxels, dtype=np.int64), None)
    for sums, counts in (b.score_placements(h, LIDAR.elevations, LIDAR.azimuths, 10.0, np.zeros((0, 1, 6))),
                         b.score_rays(h, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(1, np.int64))):
        assert np.asarray(sums).shape == (0,) and np.asarray(counts).shape == (0,)


@pytest.mark.parametrize("lower, upper, vs, match", [
    ((0, 0, 0), (1, 1, 1), 5e-324, "voxels along one axis"),
    ((0, 0, 0), (1, 1, 1), 1e-300, "voxels along one axis"),
    ((0, 0, 0), (1, 1, 1), np.inf, "voxel_size"),
    ((0, 0, 0), (1, 1, 1), "0.2 m", "voxel_size"),
    ((0, 0, 0), (1, 1, 1), None, "voxel_size"),
    ((-1e308, 0, 0), (1e308, 1, 1), 1.0, "extent"),
    ((0, 0, 0), (2e5, 1, 1), 10.0, "extent"),
])
def test_grid_parameters_give_named_errors(lower, upper, vs, match):
    with pytest.raises(ValueError, match=match):
        p3k.Grid(lower, upper, vs)


def test_grid_shapes_are_unchanged():
    assert p3k.DEFAULT_GRID.shape == (800, 800, 50)                     # 0.1 m since issue 34, item 2
    assert p3k.Grid(p3k.DEFAULT_GRID.lower, p3k.DEFAULT_GRID.upper, 0.2).shape == (400, 400, 25)   # the old one
    assert p3k.Grid((0, 0, 0), (1, 1, 1), 0.1).shape == (10, 10, 10)
    assert p3k.Grid((1e6, -1e6, 0), (1e6 + 2, -1e6 + 2, 1), 0.5).shape == (4, 4, 2)


@pytest.mark.parametrize("scale, length", [(1e200, r"1e\+200"), (1e-200, "1e-200")])
def test_direction_tables_name_the_true_length_of_a_huge_or_tiny_row(scale, length):
    from place3d_kernels.rig_metrics import direction_table

    table = np.array([[1.0, 0.0, 0.0], [0.0, 0.6 * scale, 0.8 * scale]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=f"row 1 has length {length} "):
            direction_table(table)
