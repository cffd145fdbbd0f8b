"""CARLA's frame and this package's: the one statement of the convention, and the conversions every
caller uses (placement files, ``LidarModel.from_carla`` / ``to_carla``, ``io.read_carla_ply``).

CARLA (Unreal Engine 4; https://carla.readthedocs.io/en/latest/coordinates/) is left-handed: x forward,
y RIGHT, z up, metres and degrees. ``carla.Rotation(pitch, yaw, roll)`` turns pitch about Y, yaw about Z
and roll about X; LibCarla's ``Rotation::RotateVector`` (LibCarla/source/carla/geom/Rotation.h) applies
"Rz(yaw) Ry(pitch) Rx(roll) = first x, then y, then z" as the matrix (c = cos, s = sin; p, y, r)

    Rc = [[cp cy,  cy sp sr - sy cr,  -cy sp cr - sy sr],
          [cp sy,  sy sp sr + cy cr,  -sy sp cr + cy sr],
          [sp,     -cp sr,             cp cr           ]]

This package is right-handed: x forward, y LEFT, z up, metres and radians, R = Rz(yaw) Ry(pitch) Rx(roll)
with the usual right-handed matrices (``backends.base.rotation_matrices``). With the mirror
M = diag(1, -1, 1), which takes a CARLA vector to this package's (and back),

    M Rc(pitch, yaw, roll) M = R(roll, -pitch, -yaw)

(multiply it out; ``tests/test_carla_frame.py`` checks it against a transcription of ``RotateVector``).
So a sensor CARLA places at Transform(Location(x, y, z), Rotation(pitch, yaw, roll)) is this package's
pose (x, -y, z, roll, -pitch, -yaw): **flip y, pitch and yaw; keep roll.** carla-ros-bridge's
``carla_rotation_to_RPY`` (carla_common/transforms.py) does the same for ROS's x-forward / y-left frame.
Physically: a positive CARLA roll lowers the vehicle's right side (Rc sends +y to (0, cr, -sr)); a
positive roll here raises the left side (R sends +y to (0, cr, sr)); the two are the same motion.

Points CARLA's LiDARs return are in the sensor's CARLA frame; here they are ``points @ M`` (y negated).
CARLA's ray-cast LiDAR (``RayCastSemanticLidar.cpp``) fires channel i at the elevation
``upper_fov - i (upper_fov - lower_fov) / (channels - 1)`` (one channel: ``upper_fov``) and, over a tick
of 1 / rotation_frequency from its initial angle 0, at the horizontal angles
``h_k = -horizontal_fov / 2 + k horizontal_fov / n`` (degrees, clockwise seen from above; n = round(points
per second / (channels x rotation frequency))); a laser at (elevation v, angle h) points along
Rc(v, h, 0) x = (cos v cos h, cos v sin h, sin v) in the sensor's frame, i.e. along this package's
azimuth -h and elevation v.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIRROR", "pose_from_carla", "pose_to_carla", "points_from_carla", "points_to_carla",
           "carla_channel_elevations_deg", "carla_horizontal_angles_deg", "azimuths_from_carla"]

#: The mirror between CARLA's frame (y right) and this package's (y left); its own inverse.
MIRROR = np.diag([1.0, -1.0, 1.0])

_UNITS = ("deg", "rad")


def _to_rad(values, unit: str) -> np.ndarray:
    if unit not in _UNITS:
        raise ValueError(f"angle unit must be 'deg' (CARLA's) or 'rad', got {unit!r}")
    v = np.asarray(values, dtype=np.float64)
    return np.radians(v) if unit == "deg" else v


def pose_from_carla(x: float, y: float, z: float, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0,
                    unit: str = "deg") -> np.ndarray:
    """This package's pose (x, y, z, roll, pitch, yaw) in metres and radians of a CARLA sensor transform
    (location in metres, ``carla.Rotation`` angles in ``unit``, degrees as CARLA takes them):
    (x, -y, z, roll, -pitch, -yaw)."""
    r, p, w = _to_rad([roll, pitch, yaw], unit)
    return np.array([float(x), -float(y), float(z), r, -p, -w], dtype=np.float64) + 0.0  # + 0.0: no -0.0


def pose_to_carla(pose, unit: str = "deg") -> dict:
    """CARLA ``Transform`` fields (x, y, z in metres; roll, pitch, yaw in ``unit``) of this package's pose
    (x, y, z, roll, pitch, yaw) in metres and radians; the inverse of ``pose_from_carla``."""
    if unit not in _UNITS:
        raise ValueError(f"angle unit must be 'deg' (CARLA's) or 'rad', got {unit!r}")
    x, y, z, r, p, w = (float(v) for v in np.asarray(pose, dtype=np.float64).reshape(6))
    ang = np.degrees([r, -p, -w]) if unit == "deg" else np.array([r, -p, -w])
    return {"x": x, "y": -y + 0.0, "z": z, "roll": float(ang[0]) + 0.0, "pitch": float(ang[1]) + 0.0,
            "yaw": float(ang[2]) + 0.0}


def points_from_carla(points) -> np.ndarray:
    """(N, 3) float64 points in this package's frame (y left) from points in CARLA's frame (y right)."""
    p = np.array(points, dtype=np.float64).reshape(-1, 3)
    p[:, 1] = -p[:, 1]
    return p + 0.0


#: The mirror is its own inverse.
points_to_carla = points_from_carla


def carla_channel_elevations_deg(channels: int, lower_fov: float, upper_fov: float) -> np.ndarray:
    """(channels,) elevations in degrees in CARLA's firing order (upper_fov first; a single channel fires
    at upper_fov), as ``ARayCastSemanticLidar::CreateLasers``."""
    if channels < 1:
        raise ValueError(f"channels must be >= 1, got {channels}")
    step = 0.0 if channels == 1 else (upper_fov - lower_fov) / (channels - 1)
    return float(upper_fov) - np.arange(channels) * step


def carla_horizontal_angles_deg(steps: int, horizontal_fov: float) -> np.ndarray:
    """(steps,) horizontal angles in degrees (CARLA's frame, clockwise seen from above) of one tick of
    1 / rotation_frequency from CARLA's initial angle 0: -fov / 2 + k fov / steps."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    return -horizontal_fov / 2 + np.arange(steps) * (horizontal_fov / steps)


def azimuths_from_carla(horizontal_angles_deg) -> np.ndarray:
    """This package's azimuths (radians, counter-clockwise) of CARLA horizontal angles (degrees, clockwise)."""
    return -np.radians(np.asarray(horizontal_angles_deg, dtype=np.float64)) + 0.0
