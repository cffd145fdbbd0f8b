"""One frame of a town drive cast on every backend: the same hits, bit for bit, as the reference's.

Found on 2026-11-29 (docs/performance.md, "Exactness"): the collection LiDAR of the embedded town's seed-0
drive, frame 9, at the default mount, cast into the static mesh. When float32 decided which triangle a ray
hits, warp:cpu and opencl:pocl reported another face for 71 of its 62,874 hits, and the reference agreed with
neither everywhere: most were two faces meeting at the hit, and ray 13266 was a real miss (warp:cpu and the
reference hit a road-mark strip's 1.2 cm side face at 6.562099 m, opencl:pocl the strip's bottom face at
6.565764 m). P-SOGs built on different backends then differed in a few voxels. Now float32 trees only propose
triangles and the reference's float64 test decides (raycast.cl; warp/kernels.py, closest_hit).
"""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.lidar import LidarModel
from place3d_kernels.ops import raycast
from place3d_kernels.pose import pose_from_matrix, pose_matrix
from place3d_kernels.simulate import DEFAULT_MOUNT

_BACKENDS = [b for b in p3k.available_backends() if b != "reference"]

pytestmark = pytest.mark.skipif(len(_BACKENDS) < 2, reason="needs two backends besides the reference")


def test_the_town_frames_hits_are_the_references_on_every_backend():
    scene = p3k.scene.town(seed=0)
    lidar = LidarModel.load("collection_64ch")
    sensor = pose_from_matrix(pose_matrix(scene.ego_poses[9]) @ pose_matrix(np.asarray(DEFAULT_MOUNT, float)))
    o, d = p3k.get_backend("reference").lidar_rays(lidar.elevations, lidar.azimuths, np.asarray(sensor)[None])
    o, d = np.asarray(o), np.asarray(d)
    hits = {b: raycast(scene.static, o, d, lidar.max_range, backend=b) for b in _BACKENDS}
    first = hits[_BACKENDS[0]]
    assert first.hit.sum() > 60_000
    differ = set()
    for name, h in hits.items():
        same_t = (h.t == first.t) | (np.isinf(h.t) & np.isinf(first.t))
        differ |= set(np.flatnonzero((h.face != first.face) | ~same_t).tolist())
    # the reference is slow on the whole sweep: the rays that differ, the old difference's rays and a sample
    old = [13266, 2226, 10391, 33001, 47020]
    rays = np.union1d(np.union1d(np.array(sorted(differ), dtype=np.int64), old),
                      np.random.default_rng(9).choice(len(o), 300, replace=False))
    ref = raycast(scene.static, o[rays], d[rays], lidar.max_range, backend="reference")
    assert ref.hit[rays == 13266].all() and ref.t[rays == 13266] < 6.563
    for name, h in hits.items():
        assert np.array_equal(h.face[rays], ref.face), name
        assert np.array_equal(h.t[rays], ref.t), name
        assert np.array_equal(h.label[rays], ref.label), name
    assert not differ, f"{len(differ)} rays differ between {_BACKENDS}"
