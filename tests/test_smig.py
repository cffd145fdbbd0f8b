"""S-MIG: Bernoulli occupancy from boxes, hand-computed scores on a tiny grid, scene boxes."""

from __future__ import annotations

import math

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.scene.base import Actor, Scene
from place3d_kernels.scene.primitives import boxes as box_mesh
from place3d_kernels.mesh import Mesh
from place3d_kernels.smig import BernoulliGrid, binary_entropy, scene_boxes, smig, smig_batch

GRID = p3k.Grid(lower=(0, 0, 0), upper=(4, 1, 1), voxel_size=1.0)   # 4 voxels along x
RAY = p3k.LidarModel.uniform(1, (0.0, 0.0), 1, max_range=10.0)       # one ray along +x


def H(p):
    return 0.0 if p in (0.0, 1.0) else -p * math.log(p) - (1 - p) * math.log(1 - p)


def test_binary_entropy():
    assert np.allclose(binary_entropy([0.0, 0.5, 0.25, 1.0]), [0.0, math.log(2), H(0.25), 0.0])


def test_bernoulli_from_boxes_hand_computed():
    # frame 0: a box over voxels 1 and 2 (centres x = 1.5, 2.5); frame 1: a rotated box over voxel 1 only
    f0 = np.array([[2.0, 0.5, 0.5, 2.0, 0.8, 0.8, 0.0]])
    f1 = np.array([[1.5, 0.5, 0.5, 0.6, 0.6, 0.6, math.pi / 2]])
    bg = BernoulliGrid.from_boxes([f0, f1], GRID)
    assert np.allclose(bg.dense().ravel(), [0.0, 1.0, 0.5, 0.0])
    assert bg.total_entropy == pytest.approx(math.log(2), abs=1e-9)
    # a box outside the grid or empty frames add nothing but still count as frames
    bg3 = BernoulliGrid.from_boxes([f0, np.zeros((0, 7)), np.array([[50, 0, 0, 1, 1, 1, 0.0]])], GRID)
    assert np.allclose(bg3.dense().ravel(), [0.0, 1 / 3, 1 / 3, 0.0])
    with pytest.raises(ValueError, match=r"frame 0: boxes must have shape \(n, 7\)"):
        BernoulliGrid.from_boxes([np.zeros((2, 6))], GRID)


def test_smig_hand_computed(backend):  # conftest runs this once per available backend
    bg = BernoulliGrid.from_probabilities(GRID, np.array([0.0, 0.5, 0.25, 1.0]).reshape(4, 1, 1))
    pose = np.array([[0.5, 0.5, 0.5, 0.0, 0.0, 0.0]])  # in voxel 0, the ray crosses all four
    total = math.log(2) + H(0.25)
    assert bg.total_entropy == pytest.approx(total, abs=1e-9)
    assert smig(bg, RAY, pose, backend=backend) == pytest.approx(total, abs=1e-9)
    assert smig(bg, RAY, pose, reduce="mean", backend=backend) == pytest.approx(total / 4, abs=1e-9)
    assert smig(bg, RAY, pose, reduce="remaining", backend=backend) == pytest.approx(0.0, abs=1e-9)
    # "sog" occlusion: the ray stops after voxel 1 (p = 0.5 >= 0.5), which counts
    assert smig(bg, RAY, pose, occlusion="sog", backend=backend) == pytest.approx(math.log(2), abs=1e-9)
    assert smig(bg, RAY, pose, occlusion="sog", reduce="mean", backend=backend) == pytest.approx(math.log(2) / 2)
    assert smig(bg, RAY, pose, occlusion="sog", reduce="remaining", backend=backend) == pytest.approx(H(0.25))
    # a batch of rigs in one call: from voxel 2 the ray covers voxels 2, 3 only; a short ray covers voxel 0
    short = p3k.LidarModel.uniform(1, (0.0, 0.0), 1, max_range=0.3)
    got = smig_batch(bg, RAY, np.array([pose, [[2.5, 0.5, 0.5, 0, 0, 0]], [[0.5, 0.5, 0.5, 0, 0, math.pi]]]),
                     backend=backend)
    assert np.allclose(got, [total, H(0.25), 0.0], atol=1e-9)
    assert smig(bg, short, pose, backend=backend) == pytest.approx(0.0)
    # mesh occlusion: a wall at x = 2.2 stops the ray inside voxel 2
    v, f = box_mesh([(2.25, 0.5, 0.5)], [(0.1, 5.0, 5.0)])
    wall = Mesh(v, f, np.full(len(f), 11))
    assert smig(bg, RAY, pose, occlusion="mesh", mesh=wall, backend=backend) == pytest.approx(total, abs=1e-9)
    v, f = box_mesh([(1.25, 0.5, 0.5)], [(0.1, 5.0, 5.0)])
    wall = Mesh(v, f, np.full(len(f), 11))
    assert smig(bg, RAY, pose, occlusion="mesh", mesh=wall, backend=backend) == pytest.approx(math.log(2), abs=1e-9)


def test_smig_errors():
    bg = BernoulliGrid.from_probabilities(GRID, np.full((4, 1, 1), 0.5))
    with pytest.raises(ValueError, match="reduce must be one of"):
        smig(bg, RAY, np.zeros(6) + 0.5, reduce="max")
    with pytest.raises(ValueError, match="outside the grid"):
        smig(bg, RAY, np.array([[9.0, 0.5, 0.5, 0, 0, 0]]))
    with pytest.raises(ValueError, match="occlusion must be one of"):
        smig(bg, RAY, np.array([[0.5, 0.5, 0.5, 0, 0, 0]]), occlusion="fog")
    with pytest.raises(ValueError, match=r"must lie in \[0, 1\]"):
        BernoulliGrid(GRID, [0], [1.5])


def test_scene_boxes_ego_frame():
    v, f = box_mesh([(0, 0, 0.75)], [(4.0, 2.0, 1.5)])
    car = Mesh(v, f, np.full(len(f), 10))
    ego = np.array([[10.0, 5.0, 0.0, 0, 0, math.pi / 2], [10.0, 6.0, 0.0, 0, 0, math.pi / 2]])
    act = np.array([[10.0, 15.0, 0.0, 0, 0, math.pi / 2], [11.0, 15.0, 0.0, 0, 0, 0.0]])
    sc = Scene(static=car, ego_poses=ego, actors=[Actor(car, act, "vehicle")],
               meta={"static_boxes": np.array([[7.0, 5.0, 0.75, 4.0, 2.0, 1.5, 0.0]])})
    b0 = scene_boxes(sc, 0)
    # the actor 10 m ahead of the ego (ego yaw 90 deg: world +y is ego +x), same heading
    assert np.allclose(b0[0], [10.0, 0.0, 0.75, 4.0, 2.0, 1.5, 0.0], atol=1e-9)
    # the parked car: world offset (-3, 0) from the ego, and world -x is ego +y, so 3 m to the left
    assert np.allclose(b0[1], [0.0, 3.0, 0.75, 4.0, 2.0, 1.5, -math.pi / 2], atol=1e-9)
    b1 = scene_boxes(sc, 1, kinds=("vehicle",))
    assert b1.shape == (1, 7) and np.allclose(b1[0], [9.0, -1.0, 0.75, 4.0, 2.0, 1.5, -math.pi / 2], atol=1e-9)
    grid = p3k.Grid(lower=(-20, -20, 0), upper=(20, 20, 4), voxel_size=1.0)
    bg = BernoulliGrid.from_scene(sc, grid)
    assert bg.n_frames == 2 and 0 < bg.p.min() and bg.p.max() == 1.0  # the parked car is there both frames


def test_opendrive_town_smig_objective():
    from place3d_kernels.data import opendrive_path

    path = opendrive_path("Town01")
    from place3d_kernels.scene.opendrive import from_opendrive

    sc = from_opendrive(path, seed=0, n_frames=8)
    grid = p3k.Grid(lower=(-40, -40, 0), upper=(40, 40, 4), voxel_size=0.5)
    bg = BernoulliGrid.from_scene(sc, grid)
    lidar = p3k.LidarModel.uniform(16, (-25, 5), 180, max_range=80)
    place = p3k.Placement.load("pyramid")
    rigs = np.stack([place.poses, place.poses + np.array([0.0, 0.0, 0.3, 0, 0, 0])])
    s = smig_batch(bg, lidar, rigs)
    assert s.shape == (2,) and np.all(np.isfinite(s)) and np.all(s >= 0) and np.all(s <= bg.total_entropy + 1e-9)
