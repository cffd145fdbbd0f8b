"""Reading and writing LiDAR frames in the SemanticKITTI layout.

A sequence folder holds ``velodyne/NNNNNN.bin`` (float32 x, y, z, intensity per point, in the sensor
frame), ``labels/NNNNNN.label`` (uint32 per point; here the Place3D class id in the low 16 bits) and
``poses.txt`` (one 3x4 row-major sensor-to-world matrix per frame, KITTI odometry style).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from place3d_kernels.pose import invert, pose_matrix, transform_points

__all__ = ["write_semantickitti_sequence", "read_semantickitti", "write_frame_bin"]


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_frame_bin(path_bin, path_label, points_sensor, intensity, labels) -> None:
    xyz = np.asarray(points_sensor, dtype=np.float32).reshape(-1, 3)
    arr = np.concatenate([xyz, np.asarray(intensity, np.float32).reshape(-1, 1)], axis=1)
    _atomic_write(Path(path_bin), arr.astype(np.float32).tobytes())
    _atomic_write(Path(path_label), np.asarray(labels, dtype=np.uint32).tobytes())


def write_semantickitti_sequence(frames, folder) -> Path:
    """Write simulated frames (``Frame`` objects with world points and a sensor origin) as a sequence."""
    folder = Path(folder)
    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(parents=True, exist_ok=True)
    rows = []
    for i, f in enumerate(frames):
        ego = pose_matrix(f.ego_pose)
        sensor = ego.copy()
        if f.origins is not None:
            sensor[:3, 3] = np.asarray(f.origins, dtype=np.float64).reshape(-1, 3)[0]
        local = transform_points(invert(sensor), f.points)
        inten = f.intensity if f.intensity is not None else np.zeros(len(local), np.float32)
        write_frame_bin(folder / "velodyne" / f"{i:06d}.bin", folder / "labels" / f"{i:06d}.label",
                        local, inten, f.labels)
        rows.append(" ".join(f"{v:.9g}" for v in sensor[:3].reshape(-1)))
    _atomic_write(folder / "poses.txt", ("\n".join(rows) + "\n").encode())
    return folder


def read_semantickitti(path_bin, path_label=None):
    """Read one frame: (N, 3) float32 points, (N,) float32 intensity, (N,) uint32 labels or None."""
    path_bin = Path(path_bin)
    raw = np.fromfile(path_bin, dtype=np.float32)
    if raw.size % 4:
        raise ValueError(f"{path_bin}: size {raw.size * 4} bytes is not a whole number of (x, y, z, i) float32 rows")
    pts = raw.reshape(-1, 4)
    labels = None
    if path_label is not None:
        labels = np.fromfile(path_label, dtype=np.uint32)
        if len(labels) != len(pts):
            raise ValueError(f"{path_label}: {len(labels)} labels for {len(pts)} points in {path_bin}")
    return pts[:, :3], pts[:, 3], labels
