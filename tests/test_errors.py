"""Bad input gets a clear ValueError naming the value and the fix, and leaves the inputs untouched."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k

G = p3k.Grid(lower=(0, 0, 0), upper=(2, 2, 2), voxel_size=0.5)


@pytest.mark.parametrize("bad, match", [
    ([np.nan, 0, 1], "non-finite direction"),
    ([np.inf, 0, 0], "non-finite direction"),
    ([0.0, 0.0, 0.0], "zero-length direction"),
])
def test_bad_directions(backend, bad, match):
    o = np.array([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    d = np.array([[1.0, 0, 0], bad], dtype=float)
    o0, d0 = o.copy(), d.copy()
    for fn in (p3k.traverse, p3k.coverage):
        with pytest.raises(ValueError, match=match) as e:
            fn(G, o, d, 1.0, backend=backend)
        assert "ray 1" in str(e.value)
    mesh = p3k.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match=match):
        p3k.raycast(mesh, o, d, 1.0, backend=backend)
    np.testing.assert_array_equal(o, o0)
    np.testing.assert_array_equal(d, d0)


def test_bad_origins_and_t_end(backend):
    with pytest.raises(ValueError, match="non-finite origin"):
        p3k.traverse(G, [[np.nan, 0, 0]], [[1, 0, 0]], 1.0, backend=backend)
    with pytest.raises(ValueError, match="must be >= 0"):
        p3k.traverse(G, [[0, 0, 0]], [[1, 0, 0]], -1.0, backend=backend)
    with pytest.raises(ValueError, match="one value per ray"):
        p3k.traverse(G, [[0, 0, 0], [1, 1, 1]], [[1, 0, 0], [0, 1, 0]], [1.0, 2.0, 3.0], backend=backend)


def test_empty_and_degenerate_meshes():
    with pytest.raises(ValueError, match="empty"):
        p3k.Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    with pytest.raises(ValueError, match="degenerate"):
        p3k.Mesh([[0, 0, 0], [1, 1, 1], [2, 2, 2]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="face indices"):
        p3k.Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]])
    with pytest.raises(ValueError, match="not finite"):
        p3k.Mesh([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])


@pytest.mark.parametrize("vs", [0.0, -0.1, np.nan])
def test_bad_voxel_size(vs):
    with pytest.raises(ValueError, match="voxel_size"):
        p3k.Grid((0, 0, 0), (1, 1, 1), vs)


def test_grid_too_large_is_refused_before_allocating():
    with pytest.raises(ValueError, match="voxels") as e:
        p3k.Grid((-500, -500, 0), (500, 500, 10), 0.01)
    assert "voxel_size" in str(e.value)


def test_inverted_grid():
    with pytest.raises(ValueError, match="exceed lower"):
        p3k.Grid((0, 0, 0), (1, -1, 1), 0.1)


def test_lidar_outside_grid():
    probs = np.zeros(G.shape + (22,))
    probs[..., 0] = 1
    psog = p3k.PSOG.from_probabilities(G, probs)
    lidar = p3k.LidarModel.uniform(2, (-5, 5), 8)
    with pytest.raises(ValueError, match="outside the grid"):
        p3k.msog(psog, lidar, p3k.Placement([[5.0, 0.5, 0.5, 0, 0, 0]]))
    with pytest.raises(ValueError, match="occlusion"):
        p3k.msog(psog, lidar, p3k.Placement([[0.5, 0.5, 0.5, 0, 0, 0]]), occlusion="bogus")
    with pytest.raises(ValueError, match="needs mesh"):
        p3k.msog(psog, lidar, p3k.Placement([[0.5, 0.5, 0.5, 0, 0, 0]]), occlusion="mesh")
    with pytest.raises(ValueError, match="task"):
        p3k.msog(psog, lidar, p3k.Placement([[0.5, 0.5, 0.5, 0, 0, 0]]), task="cls")


def test_non_finite_poses_are_refused_by_the_api_and_the_warp_backend():
    """msog_batch refuses NaN poses; the Warp backend's score_placements, whose CUDA loop has no step bound,
    refuses them too when called directly (nothing launched, the poses left as they were)."""
    probs = np.zeros(G.shape + (22,))
    probs[..., 0] = 1
    psog = p3k.PSOG.from_probabilities(G, probs)
    lidar = p3k.LidarModel.uniform(2, (-5, 5), 8)
    poses = np.array([[[0.5, 0.5, 0.5, 0.0, np.nan, 0.0]]])
    kept = poses.copy()
    with pytest.raises(ValueError, match="finite"):
        p3k.msog_batch(psog, lidar, poses)
    if "warp:cpu" not in p3k.available_backends():
        pytest.skip("Warp is not installed")
    b = p3k.get_backend("warp:cpu")
    handle = psog.handle(b, "sog")
    with pytest.raises(ValueError, match=r"poses must be finite; poses\[0, 0, 4\] is nan"):
        b.score_placements(handle, lidar.elevations, lidar.azimuths, lidar.max_range, poses)
    np.testing.assert_array_equal(poses, kept)


def test_unknown_backend_names_what_is_available():
    with pytest.raises(ValueError) as e:
        p3k.get_backend("vulkan")
    msg = str(e.value)
    assert "vulkan" in msg and "reference" in msg and "pip install" in msg
    with pytest.raises(ValueError):
        with p3k.use_backend("nope"):
            pass


def test_use_backend_scopes_the_default():
    with p3k.use_backend("reference") as b:
        assert p3k.get_backend() is b
        assert b.name == "reference"


def test_env_variable_sets_default(monkeypatch):
    monkeypatch.setenv("PLACE3D_BACKEND", "reference")
    assert p3k.get_backend().name == "reference"


def test_malformed_toml(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[lidar]\nx = 1\n")
    with pytest.raises(ValueError, match="malformed TOML") as e:
        p3k.Placement.load(bad)
    assert str(bad) in str(e.value)
    missing = tmp_path / "missing.toml"
    missing.write_text("[[lidar]]\nx = 0.1\ny = 0.2\n")
    with pytest.raises(ValueError, match="missing key 'z'"):
        p3k.Placement.load(missing)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text('name = "l"\nchannels = "sixteen"\nazimuth_steps = 10\nmax_range_m = 50\nvertical_fov_deg = [-10, 2]\n')
    with pytest.raises(ValueError, match="channels"):
        p3k.LidarModel.load(wrong)
    with pytest.raises(FileNotFoundError, match="shipped names"):
        p3k.Placement.load("no-such-placement")


def test_paper_placements_load_with_flipped_frame():
    pl = p3k.Placement.all_paper()
    assert len(pl) == 11
    # CARLA y-right -> project y-left: the paper's "line" LiDAR 1 at y = -0.6 sits at y = +0.6 here
    np.testing.assert_allclose(pl["line"].poses[0], [0, 0.6, 2.2, 0, 0, 0])
    np.testing.assert_allclose(pl["line-roll"].poses[0, 3], -0.3)    # roll kept (carla_frame)
    assert all(len(p) == 4 for p in pl.values())
    assert np.all(pl["2d-plane"].poses[:, 2] == 2.2)
    lidar = p3k.LidarModel.load("place3d_16ch")
    assert lidar.n_channels == 16 and len(lidar.azimuths) == 250 and lidar.max_range == 100
    np.testing.assert_allclose(np.degrees(lidar.elevations[[0, -1]]), [-24.8, 2.0])


def test_placement_roundtrip(tmp_path):
    p = p3k.Placement.load("ours-seg")
    back = p3k.Placement.load(p.save(tmp_path / "x.toml"))
    assert back == p and back.name == "ours-seg"
