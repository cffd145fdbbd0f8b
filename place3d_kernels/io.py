"""Writing LiDAR frames in the SemanticKITTI layout (readers: ``place3d_kernels.io_formats``).

A sequence folder holds ``velodyne/NNNNNN.bin`` (float32 x, y, z, intensity per point, in the sensor
frame), ``labels/NNNNNN.label`` (uint32 per point; here the Place3D class id in the low 16 bits) and
``poses.txt`` (one 3x4 row-major sensor-to-world matrix per frame, KITTI odometry style).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from place3d_kernels.pose import invert, pose_matrix, transform_points

__all__ = ["write_semantickitti_sequence", "write_frame", "write_frame_bin", "frame_paths", "sensor_matrix",
           "pose_row", "atomic_write"]


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (readers never see half a file)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_frame_bin(path_bin, path_label, points_sensor, intensity, labels) -> None:
    xyz = np.asarray(points_sensor, dtype=np.float32).reshape(-1, 3)
    arr = np.concatenate([xyz, np.asarray(intensity, np.float32).reshape(-1, 1)], axis=1)
    atomic_write(Path(path_bin), arr.astype(np.float32).tobytes())
    atomic_write(Path(path_label), np.asarray(labels, dtype=np.uint32).tobytes())


def frame_paths(folder, index: int) -> tuple[Path, Path]:
    """``velodyne/NNNNNN.bin`` and ``labels/NNNNNN.label`` of one frame of a sequence folder."""
    folder = Path(folder)
    return folder / "velodyne" / f"{index:06d}.bin", folder / "labels" / f"{index:06d}.label"


def sensor_matrix(frame) -> np.ndarray:
    """Sensor-to-world 4x4 matrix of a simulated frame: the ego rotation, the sweep's origin."""
    sensor = pose_matrix(frame.ego_pose)
    if frame.origins is not None:
        sensor[:3, 3] = np.asarray(frame.origins, dtype=np.float64).reshape(-1, 3)[0]
    return sensor


def pose_row(sensor: np.ndarray) -> str:
    """One line of ``poses.txt`` (3x4 row-major, KITTI odometry style)."""
    return " ".join(f"{v:.9g}" for v in sensor[:3].reshape(-1))


def write_frame(folder, index: int, frame) -> np.ndarray:
    """Write one frame (points in the sensor frame) atomically; returns its sensor-to-world matrix."""
    sensor = sensor_matrix(frame)
    local = transform_points(invert(sensor), frame.points)
    inten = frame.intensity if frame.intensity is not None else np.zeros(len(local), np.float32)
    write_frame_bin(*frame_paths(folder, index), local, inten, frame.labels)
    return sensor


def write_semantickitti_sequence(frames, folder) -> Path:
    """Write simulated frames (``Frame`` objects with world points and a sensor origin) as a sequence.

    Reading back: ``place3d_kernels.io_formats.read_semantickitti`` / ``read_sequence``.
    """
    folder = Path(folder)
    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(parents=True, exist_ok=True)
    rows = [pose_row(write_frame(folder, i, f)) for i, f in enumerate(frames)]
    atomic_write(folder / "poses.txt", ("\n".join(rows) + "\n").encode())
    return folder
