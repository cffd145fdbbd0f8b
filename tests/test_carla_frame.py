"""CARLA's conventions (issue 34): CARLA's rotation written from its documentation, and every conversion
(placement files, LidarModel.from_carla / to_carla, read_carla_ply, the single-channel LiDAR) checked to
give CARLA's rays, mirrored by diag(1, -1, 1).

The CARLA side is written here from CARLA's own sources, independently of place3d_kernels.carla_frame:
- rotation: carla.Rotation(pitch, yaw, roll) in degrees, in Unreal's left-handed frame (x forward,
  y right, z up); yaw about Z turns x toward +y (clockwise seen from above), pitch about Y raises the
  nose, roll about X is clockwise seen from behind (lowers the right side), applied yaw, then pitch
  about the new Y, then roll about the new X (carla.readthedocs.io "Coordinates and transformations",
  Unreal's MakeRotationFromYawPitchRollDegrees). LibCarla's Rotation::RotateVector writes the product out;
  both forms are below and must agree.
- ray-cast LiDAR (Unreal/CarlaUE4/Plugins/Carla/Source/Carla/Sensor/RayCastSemanticLidar.cpp):
  CreateLasers fires channel i at upper_fov - i (upper - lower) / (channels - 1), one channel at
  upper_fov; SimulateLidar fires round(pps dt / channels) times per laser at horizontal angles
  fmod(current + k step, hfov) - hfov / 2; ShootLaser points along the forward vector of
  ComposeRotators(FRotator(vertical, horizontal, 0), sensor rotation), i.e. sensor rotation applied
  after the laser's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import place3d_kernels as p3k
from place3d_kernels import carla_frame as cf
from place3d_kernels import placement_sources as ps
from place3d_kernels.backends.base import rotation_matrices
from place3d_kernels.io.carla import read_carla_ply
from place3d_kernels.lidar import LidarModel, lidar_rays
from place3d_kernels.placement import CARLA_PUBLIC_PLACEMENTS, PAPER_PLACEMENTS, Placement

M = np.diag([1.0, -1.0, 1.0])


# ------------------------------------------------------------------ CARLA, written from its documentation
def carla_rotate_vector_matrix(pitch, yaw, roll):
    """LibCarla Rotation::RotateVector (Rotation.h), transcribed: degrees in, CARLA-frame matrix out."""
    cp, sp = math.cos(math.radians(pitch)), math.sin(math.radians(pitch))
    cy, sy = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    cr, sr = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    return np.array([[cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr],
                     [cp * sy, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr],
                     [sp, -cp * sr, cp * cr]])


def carla_rotation_from_axes(pitch, yaw, roll):
    """The documented semantics, composed: yaw (x toward +y), then pitch (nose up), then roll (right side down)."""
    p, y, r = (math.radians(a) for a in (pitch, yaw, roll))
    yaw_m = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    # columns are the images of x, y, z: pitch sends x to (cp, 0, sp); roll sends y to (0, cr, -sr)
    pitch_m = np.array([[math.cos(p), 0, -math.sin(p)], [0, 1, 0], [math.sin(p), 0, math.cos(p)]])
    roll_m = np.array([[1, 0, 0], [0, math.cos(r), math.sin(r)], [0, -math.sin(r), math.cos(r)]])
    return yaw_m @ pitch_m @ roll_m


def carla_lidar_rays(attrs: dict, transforms) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions (CARLA frame, the vehicle's) of one tick of CARLA's ray-cast LiDAR at each
    sensor transform ((x, y, z), (pitch, yaw, roll)), with dt = 1 / rotation_frequency from angle 0.
    Ordered (sensor, channel, shot), as CARLA fires them."""
    ch, lo, hi = int(attrs["channels"]), float(attrs["lower_fov"]), float(attrs["upper_fov"])
    pps, freq, hfov = float(attrs["points_per_second"]), float(attrs["rotation_frequency"]), float(attrs["horizontal_fov"])
    dt = 1.0 / freq
    shots = int(math.floor(pps * dt / ch + 0.5))                 # FMath::RoundHalfFromZero, positive
    delta = 0.0 if ch == 1 else (hi - lo) / (ch - 1)
    current, tick = 0.0, freq * hfov * dt
    step = tick / shots
    origins, dirs = [], []
    for loc, (pitch, yaw, roll) in transforms:
        body = carla_rotate_vector_matrix(pitch, yaw, roll)
        for i in range(ch):
            vert = hi - i * delta
            for k in range(shots):
                horiz = math.fmod(current + step * k, hfov) - hfov / 2
                laser = carla_rotate_vector_matrix(vert, horiz, 0.0) @ np.array([1.0, 0.0, 0.0])
                dirs.append(body @ laser)
                origins.append(np.asarray(loc, dtype=float))
    return np.array(origins), np.array(dirs)


# ------------------------------------------------------------------ the rotation
def test_carla_rotation_from_its_documentation_and_the_mirror():
    rng = np.random.default_rng(34)
    for pitch, yaw, roll in [(0, 0, 30), (20, 0, 0), (0, 45, 0), *rng.uniform(-180, 180, (20, 3))]:
        rc = carla_rotate_vector_matrix(pitch, yaw, roll)
        np.testing.assert_allclose(rc, carla_rotation_from_axes(pitch, yaw, roll), atol=1e-14)
        # this package's pose of a CARLA rotation: M Rc M, for every conversion that places a sensor
        pose = cf.pose_from_carla(0.0, 0.0, 0.0, roll=roll, pitch=pitch, yaw=yaw)
        np.testing.assert_allclose(rotation_matrices(pose[None])[0], M @ rc @ M, atol=1e-14)
        # carla-ros-bridge carla_rotation_to_RPY: roll, -pitch, -yaw (radians)
        np.testing.assert_allclose(pose[3:], np.radians([roll, -pitch, -yaw]), atol=1e-15)
        back = cf.pose_to_carla(pose)
        np.testing.assert_allclose([back["pitch"], back["yaw"], back["roll"]], [pitch, yaw, roll], atol=1e-12)
    # a positive CARLA roll lowers the right side (+y in CARLA); here that side is -y, and it goes down too
    right_c = carla_rotate_vector_matrix(0, 0, 10) @ [0, 1, 0]
    assert right_c[2] < 0
    right_here = rotation_matrices(cf.pose_from_carla(0, 0, 0, roll=10)[None])[0] @ [0, -1, 0]
    np.testing.assert_allclose(right_here, M @ right_c, atol=1e-15)


def test_pose_round_trip_and_locations():
    pose = cf.pose_from_carla(0.4, -0.6, 2.2, roll=-0.3, pitch=0.1, yaw=0.2, unit="rad")
    np.testing.assert_array_equal(pose, [0.4, 0.6, 2.2, -0.3, -0.1, -0.2])
    back = cf.pose_to_carla(pose, unit="rad")
    assert back == {"x": 0.4, "y": -0.6, "z": 2.2, "roll": -0.3, "pitch": 0.1, "yaw": 0.2}
    with pytest.raises(ValueError, match="angle unit"):
        cf.pose_from_carla(0, 0, 0, unit="grad")
    np.testing.assert_array_equal(cf.points_to_carla(cf.points_from_carla([[1.0, 2.0, 3.0]])), [[1.0, 2.0, 3.0]])


# ------------------------------------------------------------------ placements
@pytest.mark.parametrize("name", PAPER_PLACEMENTS)
def test_placement_rays_tilt_as_carla_would(name, backend):
    """Every paper placement, rolled ones included: the package's rays of the shipped file are CARLA's rays
    of the paper's row (sensor at Location(x, y, z), Rotation(roll = the table's roll as CARLA degrees of
    the package's radians)), mirrored; on every backend."""
    attrs = {"channels": 4, "lower_fov": -24.8, "upper_fov": 2.0, "points_per_second": 4 * 20 * 36,
             "rotation_frequency": 20.0, "horizontal_fov": 360.0, "range": 100.0}
    transforms = [((x, y, z), (0.0, 0.0, math.degrees(r))) for x, y, z, r in ps.PAPER_TABLE[name]]
    o_c, d_c = carla_lidar_rays(attrs, transforms)
    o, d = lidar_rays(LidarModel.from_carla(attrs), Placement.load(name), backend=backend)
    np.testing.assert_allclose(o, o_c @ M, atol=1e-12)
    np.testing.assert_allclose(d, d_c @ M, atol=1e-12)


def test_line_roll_tilt_directions():
    """The sign made physical. line-roll gives both outer LiDARs (CARLA y = -0.6, i.e. left, and +0.6) a
    roll of -0.3; in CARLA a negative roll turns the sensor anticlockwise seen from behind: its left side
    goes down, its right side up. So LiDAR 1's leftward beam points down and LiDAR 4's rightward beam up
    (before issue 34 the files negated roll and had it the other way round)."""
    pl = Placement.load("line-roll")
    R = rotation_matrices(pl.poses)
    assert pl.poses[0, 1] > 0 > pl.poses[3, 1]           # y left: LiDAR 1 (CARLA y -0.6) is on the left
    assert (R[0] @ [0, 1, 0])[2] < 0                     # LiDAR 1's leftward beam points down
    assert (R[3] @ [0, -1, 0])[2] > 0                    # LiDAR 4's rightward beam points up
    for Ri, (x, y, z, r) in zip(R, ps.PAPER_TABLE["line-roll"]):
        np.testing.assert_allclose(Ri, M @ carla_rotate_vector_matrix(0, 0, math.degrees(r)) @ M, atol=1e-14)
    # CARLA itself: roll -0.3 rad lowers the left side (-y in CARLA)
    assert (carla_rotate_vector_matrix(0, 0, math.degrees(-0.3)) @ [0, -1, 0])[2] < 0


def test_shipped_placement_files_are_the_derivation():
    for name in PAPER_PLACEMENTS:
        assert Placement.load(name) == ps.paper_placement(name), name
    for name in ps.CARLA_PUBLIC:
        got = Placement.load(f"{ps.PUBLIC_PREFIX}/{name}")
        assert got == ps.public_placement(name) and got.name == f"carla_public/{name}"
    assert set(PAPER_PLACEMENTS) == set(ps.PAPER_TABLE)
    assert set(CARLA_PUBLIC_PLACEMENTS) <= set(Placement.shipped_names())


def test_shipped_placement_files_match_the_generator_text(tmp_path):
    from place3d_kernels._toml import config_dir

    for p in ps.write_all(tmp_path):
        rel = p.relative_to(tmp_path)
        assert (config_dir("placements") / rel).read_text() == p.read_text(), rel


def test_public_placements_load_by_name_and_differ_from_the_paper():
    c = Placement.load("carla_public/center")
    np.testing.assert_array_equal(c.poses[:, 2], [1.8, 2.0, 2.2, 2.4])       # the paper's table: 2.2..2.8
    assert not np.array_equal(c.poses, Placement.load("center").poses)
    t = Placement.load("carla_public/trapezoid").poses
    np.testing.assert_array_equal(t[:, :2], [[-0.6, -0.6], [-0.6, 0.6], [0.2, -0.4], [0.2, 0.4]])
    with pytest.raises(FileNotFoundError, match="carla_public/center"):
        Placement.load("carla_public/no-such-rig")


# ------------------------------------------------------------------ the LiDAR
@pytest.mark.parametrize("attrs", [
    {"channels": 1, "lower_fov": -30.0, "upper_fov": 10.0, "points_per_second": 3600, "rotation_frequency": 10.0},
    {"channels": 5, "lower_fov": -20.0, "upper_fov": 4.0, "points_per_second": 5 * 10 * 25, "rotation_frequency": 10.0},
    {"channels": 3, "lower_fov": -10.0, "upper_fov": 10.0, "points_per_second": 3 * 20 * 37, "rotation_frequency": 20.0,
     "horizontal_fov": 120.0},
])
def test_from_carla_casts_carlas_rays(attrs):
    """from_carla's rays are CARLA's mirrored, ray for ray: elevations (one channel at upper_fov), the
    horizontal angles of CARLA's first tick (odd step counts and a limited FOV included), at a rotated
    sensor."""
    transforms = [((0.3, -0.5, 2.1), (4.0, 25.0, -12.0))]
    o_c, d_c = carla_lidar_rays({**p3k.lidar.CARLA_LIDAR_DEFAULTS, **attrs}, transforms)
    (loc, (pitch, yaw, roll)), = transforms
    pose = cf.pose_from_carla(*loc, roll=roll, pitch=pitch, yaw=yaw)
    m = LidarModel.from_carla(attrs)
    o, d = lidar_rays(m, pose[None], backend="reference")
    np.testing.assert_allclose(o, o_c @ M, atol=1e-12)
    np.testing.assert_allclose(d, d_c @ M, atol=1e-12)


def test_single_channel_carla_lidar_fires_at_upper_fov():
    m = LidarModel.from_carla({"channels": 1, "lower_fov": -30.0, "upper_fov": 10.0})
    np.testing.assert_allclose(np.degrees(m.elevations), [10.0])              # not the middle (-10)
    a = m.to_carla()
    assert a["upper_fov"] == a["lower_fov"] == pytest.approx(10.0)
    assert np.array_equal(LidarModel.from_carla(a).directions(), m.directions())
    np.testing.assert_array_equal(cf.carla_channel_elevations_deg(4, -30.0, 9.0), [9.0, -4.0, -17.0, -30.0])


def test_to_carla_keeps_the_preset_rate():
    """place3d_16ch says 20 Hz (5,000 points per second per channel): its export must not fall back to 10 Hz."""
    a = LidarModel.load("place3d_16ch").to_carla()
    assert a["rotation_frequency"] == 20.0 and a["points_per_second"] == 16 * 5000
    rebuilt = LidarModel.from_carla(a)
    assert rebuilt.n_rays == 16 * 250
    np.testing.assert_allclose(np.sort(np.degrees(rebuilt.elevations)), np.linspace(-24.8, 2.0, 16), atol=1e-12)


# ------------------------------------------------------------------ points
def test_read_carla_ply_returns_y_left_points(tmp_path):
    """A CARLA point 5 m to the sensor's right (CARLA y = +5, laser at horizontal angle +90) comes back at
    y = -5, where this package's ray at azimuth -90 deg (the same laser, mirrored) ends."""
    o_c, d_c = carla_lidar_rays({"channels": 1, "lower_fov": 0.0, "upper_fov": 0.0, "points_per_second": 4,
                                 "rotation_frequency": 1.0, "horizontal_fov": 360.0}, [((0, 0, 0), (0, 0, 0))])
    k = int(np.argmax(d_c[:, 1]))                       # the shot to CARLA's right
    hit_c = 5.0 * d_c[k]
    head = ("ply\nformat ascii 1.0\nelement vertex 2\nproperty float32 x\nproperty float32 y\nproperty float32 z\n"
            "property float32 CosAngle\nproperty uint32 ObjIdx\nproperty uint32 ObjTag\nend_header\n")
    rows = [f"{hit_c[0]:.6f} {hit_c[1]:.6f} {hit_c[2]:.6f} 1.0 7 1\n", "2.0 -1.5 0.25 0.5 3 10\n"]
    (tmp_path / "f.ply").write_text(head + "".join(rows))
    c = read_carla_ply(tmp_path / "f.ply")
    np.testing.assert_allclose(c.points[0], [0.0, -5.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(c.points[1], [2.0, 1.5, 0.25])
    m = LidarModel.from_carla({"channels": 1, "lower_fov": 0.0, "upper_fov": 0.0, "points_per_second": 4,
                               "rotation_frequency": 1.0})
    _, d = lidar_rays(m, np.zeros((1, 6)), backend="reference")
    np.testing.assert_allclose(5.0 * d[k], c.points[0], atol=1e-6)
