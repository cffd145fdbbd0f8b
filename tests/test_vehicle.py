"""The ego vehicle body: presets, loading, inside tests, and rays it blocks (M-SOG on a body)."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels import rig_metrics as rm
from place3d_kernels.vehicle import PRESETS, VehicleBody

REF = p3k.get_backend("reference")
GRID = p3k.Grid(lower=(-10, -10, -1), upper=(10, 10, 5), voxel_size=0.25)
# elevations avoid 0 (a horizontal ray would graze the plate's top plane)
LIDAR = p3k.LidarModel(np.radians(np.linspace(-31.0, 9.0, 9)), np.linspace(0, 2 * np.pi, 72, endpoint=False) + 0.01,
                       max_range=12.0)
POSE = np.array([0.1, 0.05, 2.0, 0.0, 0.0, 0.0])
PLATE_TOP, PLATE_HALF = 1.6, (3.1, 2.7)


@pytest.fixture(scope="module")
def psog():
    rng = np.random.default_rng(7)
    n = GRID.n_voxels
    vox = np.sort(rng.choice(n, n // 5, replace=False))
    probs = rng.dirichlet(np.r_[6.0, np.full(21, 0.2)], len(vox))
    return p3k.PSOG(GRID, vox, probs)


def plate() -> VehicleBody:
    hx, hy = PLATE_HALF
    return VehicleBody.from_boxes([[[-hx, -hy, 1.5], [hx, hy, PLATE_TOP]]], "plate")


def test_presets_dimensions_and_inside():
    for name, p in PRESETS.items():
        body = VehicleBody.preset(name)
        lo, hi = body.bounds
        assert hi[0] - lo[0] == pytest.approx(p.length) and hi[1] - lo[1] == pytest.approx(p.width)
        assert hi[2] == pytest.approx(p.height) and lo[2] == pytest.approx(p.clearance)
        assert body.contains([[0, 0, p.height - 0.05], [0, 0, 0.5 * (p.clearance + p.shoulder)]]).all()
        assert not body.contains([[0, 0, p.height + 0.01], [p.length, 0, 1.0], [0, 0, p.clearance / 2]]).any()
    assert VehicleBody.preset("car").key != VehicleBody.preset("suv").key
    assert VehicleBody.preset("car").key == VehicleBody.preset("car").key
    with pytest.raises(ValueError, match="unknown vehicle preset 'bus'"):
        VehicleBody.preset("bus")
    with pytest.raises(ValueError, match="width must be a positive"):
        VehicleBody.box(4.0, 0.0, 1.5)


def test_load_mesh_file(tmp_path):
    import trimesh

    path = tmp_path / "van.obj"
    trimesh.creation.box(extents=(5.0, 2.0, 2.4), transform=trimesh.transformations.translation_matrix(
        [0, 0, 1.2])).export(path)
    body = VehicleBody.load(path)
    assert body.name == "van" and body.mesh.n_faces == 12
    assert body.contains([[0, 0, 1.0]]).all() and not body.contains([[0, 0, 2.6], [3, 0, 1]]).any()
    with pytest.raises(FileNotFoundError, match="nope.glb"):
        VehicleBody.load(tmp_path / "nope.glb")


def _analytic_t_end(o, d):
    # rays going down hit the plate's top face where |x| <= hx and |y| <= hy; nothing else is hit
    t = np.full(len(o), LIDAR.max_range)
    down = d[:, 2] < 0
    th = (PLATE_TOP - o[down, 2]) / d[down, 2]
    p = o[down] + th[:, None] * d[down]
    hit = (np.abs(p[:, 0]) <= PLATE_HALF[0]) & (np.abs(p[:, 1]) <= PLATE_HALF[1]) & (th < LIDAR.max_range)
    t[np.flatnonzero(down)[hit]] = th[hit]
    return t


@pytest.mark.parametrize("occlusion", ["none", "sog"])
def test_plate_below_rig_hides_exactly_what_geometry_says(backend, psog, occlusion):
    body = plate()
    got = rm.msog_with_body_batch(psog, LIDAR, POSE[None], body, occlusion=occlusion, backend=backend)
    free = rm.msog_with_body_batch(psog, LIDAR, POSE[None], None, occlusion=occlusion, backend=backend)
    # expected: the reference traversal of the rays clipped at the plate's analytic hit distance
    o, d = rm.rig_rays(rm.direction_table(LIDAR)[0], POSE[None])
    te = _analytic_t_end(o, d)
    assert 0 < np.sum(te < LIDAR.max_range) < len(te)
    stop = psog.stop_mask if occlusion == "sog" else None
    _, vox = REF.traverse(GRID.spec, GRID.to_local(o), d, te, stop)
    u = np.unique(vox)
    assert got.counts[0] == len(u)
    assert got.sums[0] == psog.weights[u].sum(dtype=np.int64)
    assert got.counts[0] < free.counts[0]
    assert got.feasible.all() and got.reasons == [""]
    # bit-identical across backends
    ref = rm.msog_with_body_batch(psog, LIDAR, POSE[None], body, occlusion=occlusion, backend="reference")
    assert got.sums[0] == ref.sums[0] and got.counts[0] == ref.counts[0] and got.msog[0] == ref.msog[0]


def test_no_body_equals_msog_batch(backend, psog):
    poses = np.stack([p3k.Placement.load(n).poses for n in ("center", "pyramid", "ours-seg")])
    want = p3k.msog_batch(psog, LIDAR, poses, occlusion="sog", backend=backend)
    got = rm.msog_with_body(psog, LIDAR, poses, None, occlusion="sog", backend=backend)
    np.testing.assert_array_equal(got, want)
    # a bare direction table with a range gives the same
    table = rm.direction_table(LIDAR)[0]
    np.testing.assert_array_equal(rm.msog_with_body(psog, table, poses, None, backend=backend, max_range=12.0), want)


def test_lidar_inside_body_is_infeasible(psog):
    body = VehicleBody.preset("car")
    rigs = np.array([[[0.0, 0.0, 1.7, 0, 0, 0], [0.5, 0.0, 1.2, 0, 0, 0]],     # second LiDAR inside the cabin
                     [[0.0, 0.0, 1.7, 0, 0, 0], [0.5, 0.3, 1.6, 0, 0, 0]]])
    with pytest.raises(ValueError, match=r"LiDAR 1 at \[0.5, 0.0, 1.2\] lies inside .* 'car'"):
        rm.msog_with_body(psog, LIDAR, rigs, body, backend="reference")
    r = rm.msog_with_body_batch(psog, LIDAR, rigs, body, backend="reference")
    assert r.feasible.tolist() == [False, True] and np.isnan(r.msog[0]) and np.isfinite(r.msog[1])
    assert "LiDAR 1" in r.reasons[0] and r.reasons[1] == "" and r.counts[0] == 0
    with pytest.raises(ValueError, match="max_range"):
        rm.msog_with_body(psog, rm.direction_table(LIDAR)[0], rigs[1], body)


@pytest.mark.parametrize("ext", ["glb", "gltf"])
def test_load_gltf_body_turns_y_up_to_z_up(tmp_path, ext):
    # CesiumMilkTruck.glb (Y-up) lay on its side half under the ground; here a Y-up box truck made by trimesh
    import trimesh

    box = trimesh.creation.box(extents=(6.0, 2.5, 2.0),
                               transform=trimesh.transformations.translation_matrix([0.0, 1.25, 0.0]))
    path = tmp_path / f"truck.{ext}"
    box.export(path)
    body = VehicleBody.load(path)
    np.testing.assert_allclose(body.bounds, [[-3.0, -1.0, 0.0], [3.0, 1.0, 2.5]], atol=1e-12)
    assert body.contains([[0.0, 0.0, 2.0]]).all() and not body.contains([[0.0, 0.0, -0.5]]).any()
    np.testing.assert_allclose(VehicleBody.load(path, up="z").bounds, [[-3.0, 0.0, -1.0], [3.0, 2.5, 1.0]],
                               atol=1e-12)
