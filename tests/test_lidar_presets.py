"""LiDAR presets against their data sheets, CARLA import/export, directions(), rosette scan, bad input."""

from __future__ import annotations

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.base import sensor_directions
from place3d_kernels.lidar import CARLA_LIDAR_DEFAULTS, LidarModel, lidar_rays, list_presets, rays_from_directions
from place3d_kernels.scan_patterns import RosettePattern

# name: (channels, lowest elevation deg, highest elevation deg, rays per frame, horizontal FOV deg, source).
# Rays per frame = channels x points per channel per frame from the data sheet's point rate at 10 Hz.
DATA_SHEETS = {
    # Velodyne VLP-16 data sheet: 16 ch, +-15 deg, ~300,000 pts/s -> 30,000 per 10 Hz frame.
    "vlp16": (16, -15.0, 15.0, 30_000, 360.0, "Velodyne VLP-16 data sheet"),
    # Velodyne VLP-32C data sheet: 32 ch, -25..+15 deg, ~600,000 pts/s -> 60,000 per frame.
    "vlp32c": (32, -25.0, 15.0, 60_000, 360.0, "Velodyne VLP-32C data sheet"),
    # Velodyne HDL-32E data sheet: 32 ch, -30.67..+10.67 deg, ~695,000 pts/s -> 32 x 2172 per frame.
    "hdl32e": (32, -30.67, 10.67, 32 * 2172, 360.0, "Velodyne HDL-32E data sheet"),
    # Velodyne HDL-64E S2 data sheet (KITTI): 64 ch, -24.8..+2.0 deg, ~1.333 M pts/s -> 64 x 2083 per frame.
    "hdl64e": (64, -24.8, 2.0, 64 * 2083, 360.0, "Velodyne HDL-64E S2 data sheet"),
    # Ouster: real units' metadata (ouster-sdk tests/metadata/), 1024 columns x 10 Hz. OS-1-64 sn
    # 991913000010 is a gen-1 unit (33.2 deg data sheet); OS-1-128 sn 992119000444 a 45 deg one.
    "os1-64": (64, -16.679, 16.729, 64 * 1024, 360.0, "2_1_2_os1-991913000010-64.json"),
    "os1-128": (128, -21.44, 21.51, 128 * 1024, 360.0, "2_2_os-992119000444-128.json"),
    # Hesai Pandar64 user manual: 64 ch, -25..+15 deg, 1,152,000 pts/s -> 115,200 per 10 Hz frame.
    "pandar64": (64, -25.0, 15.0, 115_200, 360.0, "Hesai Pandar64 user manual"),
    # Hesai AT128P user manual: 128 ch, 25.4 deg vertical, 120 deg horizontal, 1,536,000 pts/s at 10 Hz.
    "at128": (128, -12.5, 12.9, 153_600, 120.0, "Hesai AT128P user manual"),
}
# Calibration tables differ from the data sheet's rounded extremes by up to this much (HDL-64E unit: 0.09 deg).
EXTREME_TOL_DEG = 0.15


@pytest.mark.parametrize("name", sorted(DATA_SHEETS))
def test_preset_matches_data_sheet(name):
    ch, lo, hi, rays, hfov, _ = DATA_SHEETS[name]
    m = LidarModel.load(name)
    e = np.degrees(m.channel_elevations)
    assert m.n_channels == ch
    assert abs(e.min() - lo) <= EXTREME_TOL_DEG and abs(e.max() - hi) <= EXTREME_TOL_DEG, (e.min(), e.max())
    assert m.n_rays == rays
    assert m.directions().shape == (rays, 3)
    assert m.horizontal_fov_deg == hfov
    az = np.degrees(m.base_azimuths)
    if hfov < 360:
        assert az.min() > -hfov / 2 and az.max() < hfov / 2
    assert 0 <= m.min_range < m.max_range
    assert m.source


def test_preset_azimuth_offsets_from_tables():
    # VLP-32C: VeloView table staggers beams by +-1.4 and +-4.2 deg; HDL-64E unit: -8.0..+10.0 deg.
    off = np.degrees(LidarModel.load("vlp32c").azimuth_offsets)
    assert sorted(set(np.round(off, 3))) == [-4.2, -1.4, 1.4, 4.2]
    off = np.degrees(LidarModel.load("hdl64e").azimuth_offsets)
    assert off.min() == pytest.approx(-10.0, abs=1e-3) and off.max() == pytest.approx(8.0, abs=1e-3) or \
        off.min() == pytest.approx(-8.0, abs=1e-3) and off.max() == pytest.approx(10.0, abs=1e-3)
    assert not LidarModel.load("vlp32c").is_grid and LidarModel.load("vlp16").is_grid


def test_ouster_presets_carry_the_metadata_tables():
    """beam_altitude_angles and minus beam_azimuth_angles of the cited files (first and last four beams
    here; the TOMLs hold all): ouster-sdk's make_xyz_lut points a beam at encoder angle - azimuth angle."""
    m = LidarModel.load("os1-128")
    e, off = np.degrees(m.channel_elevations), np.degrees(m.azimuth_offsets)
    np.testing.assert_allclose(e[:4], [21.51, 21.18, 20.87, 20.57], atol=1e-12)
    np.testing.assert_allclose(e[-1], -21.44, atol=1e-12)
    np.testing.assert_allclose(off[:4], [-4.26, -1.44, 1.39, 4.22], atol=1e-12)
    m = LidarModel.load("os1-64")
    np.testing.assert_allclose(np.degrees(m.channel_elevations[:2]), [16.729, 16.118], atol=1e-12)
    np.testing.assert_allclose(np.degrees(m.azimuth_offsets[:4]), [-3.073, -0.904, 1.261, 3.384], atol=1e-12)
    for name in ("os1-64", "os1-128"):
        m = LidarModel.load(name)
        assert not m.is_grid and "ouster-sdk tests/metadata/" in m.source and m.n_rays == m.n_channels * 1024


def test_ouster_rays_and_scores_identical_on_every_backend(backend):
    """Per-beam azimuth offsets: the rays are built once on the host (lidar_rays, rig_metrics) and every
    backend walks them to the same M-SOG as the reference."""
    grid = p3k.Grid(lower=(-8, -8, -1), upper=(8, 8, 4), voxel_size=0.25)
    rng = np.random.default_rng(5)
    vox = np.sort(rng.choice(grid.n_voxels, grid.n_voxels // 6, replace=False))
    psog = p3k.PSOG(grid, vox, rng.dirichlet(np.r_[5.0, np.full(21, 0.3)], len(vox)))
    rig = p3k.Placement.load("line-roll").poses
    for name in ("os1-128", "os1-64"):
        m = LidarModel.load(name).subsample(2, 16)
        o, d = lidar_rays(m, rig, backend=backend)
        o_ref, d_ref = lidar_rays(m, rig, backend="reference")
        assert np.array_equal(o, o_ref) and np.array_equal(d, d_ref)
        assert p3k.msog(psog, m, rig, backend=backend) == p3k.msog(psog, m, rig, backend="reference")


def test_authors_carla_16ch_presets():
    """ywyeli/Place3D carla_nus/hyperparams/4x16.toml: 16 channels, -25..+5 and -14..+2 deg, 14,400 points
    per channel per second at 20 Hz = 720 steps, 200 m; every shipped preset states its rate."""
    for name, lo, hi in (("place3d_16ch_carla", -25.0, 5.0), ("place3d_16ch_carla_narrow", -14.0, 2.0)):
        m = LidarModel.load(name)
        assert m.n_channels == 16 and len(m.azimuths) == 14_400 // 20 and m.max_range == 200.0
        np.testing.assert_allclose(np.degrees(m.elevations[[0, -1]]), [lo, hi])
        a = m.to_carla()
        assert a["rotation_frequency"] == 20.0 and a["points_per_second"] == 14_400 * 16
    from place3d_kernels._toml import config_dir, read_toml

    for path in sorted(config_dir("lidars").glob("*.toml")):
        d = read_toml(path)
        assert d.get("scan") == "rosette" or "rotation_frequency_hz" in d, f"{path.name}: no rotation_frequency_hz"


def test_at128_range_is_the_decoders():
    # tier4/nebula pandar_at128.hpp: PandarAT128::min_range = 1.0, max_range = 180.0 (decoder drops the rest)
    m = LidarModel.load("at128")
    assert (m.min_range, m.max_range) == (1.0, 180.0)


def test_rosette_preset():
    # Livox Mid-40 user manual: 38.4 deg circular FOV, 100,000 pts/s; 0.1 s frame -> 10,000 rays.
    m = LidarModel.load("mid40")
    assert m.pattern is not None and not m.is_grid
    assert m.n_rays == 10_000
    d = m.directions()
    off_axis = np.degrees(np.arccos(np.clip(d[:, 0], -1, 1)))
    assert off_axis.max() <= 19.2 + 1e-9 and off_axis.max() > 19.0


def test_rosette_covers_fov_and_does_not_repeat():
    m = LidarModel.load("mid40")
    half = np.radians(19.2)

    def covered(frames):
        # Measured 2026-11-24: 0.28 for one 0.1 s frame, 0.98 for ten. Fraction of 0.5-deg cells of the FOV disc (tangent-plane grid) hit by at least one ray.
        d = np.concatenate([m.directions(k) for k in frames])
        u, v = d[:, 1] / d[:, 0], d[:, 2] / d[:, 0]
        n = int(np.ceil(2 * np.tan(half) / np.tan(np.radians(0.5))))
        edges = np.linspace(-np.tan(half), np.tan(half), n + 1)
        hit = np.histogram2d(u, v, [edges, edges])[0] > 0
        c = 0.5 * (edges[:-1] + edges[1:])
        inside = (c[:, None] ** 2 + c[None, :] ** 2) <= np.tan(half) ** 2
        return hit[inside].mean()

    one, ten = covered([0]), covered(range(10))
    assert one > 0.2, one
    assert ten > 0.9, ten
    assert ten > one + 0.2          # coverage grows with integration time: the pattern does not repeat
    assert not np.allclose(m.directions(0), m.directions(1))


def test_existing_presets_rays_unchanged():
    # The paper's LiDAR and the collection LiDAR give exactly the rays of the original uniform formula.
    for name, ch, lo, hi, steps in (("place3d_16ch", 16, -24.8, 2.0, 250), ("collection_64ch", 64, -30.0, 10.0, 1024)):
        m = LidarModel.load(name)
        assert np.array_equal(m.elevations, np.radians(np.linspace(lo, hi, ch)))
        assert np.array_equal(m.azimuths, np.arange(steps) * (2 * np.pi / steps))
        assert m.is_grid and m.min_range == 0.0


@pytest.mark.parametrize("name", ["place3d_16ch", "collection_64ch", "vlp16", "hdl32e", "place3d_16ch_carla"])
def test_directions_equal_sensor_directions_bit_for_bit(name):
    m = LidarModel.load(name)
    assert m.is_grid
    assert np.array_equal(m.directions(), sensor_directions(m.elevations, m.azimuths))
    g = LidarModel.load("vlp32c").without_azimuth_offsets()
    assert np.array_equal(g.directions(), sensor_directions(g.elevations, g.azimuths))


def test_offsets_shift_each_channel_azimuth():
    e, a = np.radians([-10.0, 5.0]), np.radians([0.0, 90.0, 180.0])
    off = np.radians([2.0, -3.0])
    m = LidarModel(e, a, 50.0, azimuth_offsets=off)
    d = m.directions().reshape(2, 3, 3)
    az = np.arctan2(d[..., 1], d[..., 0])
    expect = np.angle(np.exp(1j * (a[None, :] + off[:, None])))
    assert np.allclose(az, expect, atol=1e-12)
    assert np.allclose(np.arcsin(d[..., 2]), e[:, None], atol=1e-12)


def test_lidar_rays_host_path_matches_reference_for_grid():
    rig = p3k.Placement.load("pyramid").poses
    m = LidarModel.load("vlp16")
    o_ref, d_ref = get_backend("reference").lidar_rays(m.elevations, m.azimuths, rig)
    o, d = rays_from_directions(m.directions(), rig)
    assert np.array_equal(o, o_ref) and np.array_equal(d, d_ref)
    o2, d2 = lidar_rays(m, rig, backend="reference")
    assert np.array_equal(o2, o_ref) and np.array_equal(d2, d_ref)


def test_lidar_rays_non_grid_on_host():
    rig = p3k.Placement.load("pyramid").poses
    for name in ("vlp32c", "mid40"):
        m = LidarModel.load(name)
        o, d = lidar_rays(m, rig, backend="reference")
        assert o.shape == d.shape == (len(rig) * m.n_rays, 3)
        assert np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
        assert np.array_equal(o[: m.n_rays], np.repeat(rig[:1, :3], m.n_rays, axis=0))


def test_non_grid_model_refuses_grid_kernels():
    m = LidarModel.load("vlp32c")
    with pytest.raises(NotImplementedError, match="issue 16"):
        m.azimuths
    with pytest.raises(NotImplementedError, match="rosette"):
        LidarModel.load("mid40").elevations


def test_carla_defaults_and_mapping():
    m = LidarModel.from_carla({})
    assert m.n_channels == CARLA_LIDAR_DEFAULTS["channels"] == 32 and m.max_range == 10.0
    assert len(m.azimuths) == round(56000 / (32 * 10))     # CARLA: points per laser per revolution
    assert np.degrees(m.elevations).min() == pytest.approx(-30) and np.degrees(m.elevations).max() == pytest.approx(10)


def test_carla_round_trip():
    attrs = {"channels": 64, "range": 100.0, "points_per_second": 1_280_000, "rotation_frequency": 20.0,
             "upper_fov": 10.0, "lower_fov": -30.0, "horizontal_fov": 360.0}
    m = LidarModel.from_carla(attrs)
    assert m.n_rays == 64 * 1000
    assert m.to_carla() == attrs
    m2 = LidarModel.from_carla({k: str(v) for k, v in attrs.items()})   # CARLA attributes are strings
    assert np.array_equal(m2.directions(), m.directions())
    back = LidarModel.from_carla(m.to_carla())
    assert np.array_equal(back.directions(), m.directions())
    limited = LidarModel.from_carla({"horizontal_fov": 120.0, "channels": 16})
    assert limited.to_carla()["horizontal_fov"] == 120.0
    assert LidarModel.from_carla(limited.to_carla()).n_rays == limited.n_rays


def test_carla_export_refuses_what_carla_cannot_express():
    for name in ("vlp32c", "mid40", "hdl32e"):
        with pytest.raises(ValueError, match="CARLA"):
            LidarModel.load(name).to_carla()


def test_bad_input(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('channels = 4\nelevations_deg = [0.0, 1.0, 2.0]\nazimuth_steps = 10\nmax_range_m = 50.0\n')
    with pytest.raises(ValueError, match=r"channels = 4.*lists 3"):
        LidarModel.load(p)
    with pytest.raises(FileNotFoundError, match="vlp16"):
        LidarModel.load("no_such_lidar")
    with pytest.raises(ValueError, match="2 channels"):
        LidarModel(np.zeros(2), np.zeros(3), 10.0, azimuth_offsets=np.zeros(3))
    with pytest.raises(ValueError, match="unknown CARLA lidar attributes"):
        LidarModel.from_carla({"chanels": 32})
    with pytest.raises(ValueError, match="prism_hz"):
        RosettePattern(38.4, 1e5, 0.1, (97.0, -1.0))


def test_list_presets_lists_every_shipped_preset():
    rows = {r["name"]: r for r in list_presets()}
    assert set(DATA_SHEETS) | {"mid40", "place3d_16ch", "collection_64ch", "place3d_16ch_carla",
                               "place3d_16ch_carla_narrow"} <= set(rows)
    assert rows["at128"]["hfov_deg"] == 120.0 and rows["mid40"]["scan"] == "rosette"
    assert all(r["source"] for r in rows.values())
