"""Poses (x, y, z, roll, pitch, yaw) and rotations R = Rz(yaw) Ry(pitch) Rx(roll)."""

from __future__ import annotations

import numpy as np

__all__ = ["rotation", "pose_matrix", "pose_from_matrix", "invert", "transform_points"]


def rotation(roll, pitch, yaw) -> np.ndarray:
    """Rotation matrices (..., 3, 3) for broadcastable angles in radians."""
    r, p, y = np.broadcast_arrays(np.asarray(roll, float), np.asarray(pitch, float), np.asarray(yaw, float))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R = np.empty(r.shape + (3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def pose_matrix(pose) -> np.ndarray:
    """4x4 homogeneous matrix (..., 4, 4) of poses (..., 6)."""
    p = np.asarray(pose, dtype=np.float64)
    T = np.zeros(p.shape[:-1] + (4, 4))
    T[..., :3, :3] = rotation(p[..., 3], p[..., 4], p[..., 5])
    T[..., :3, 3] = p[..., :3]
    T[..., 3, 3] = 1.0
    return T


def pose_from_matrix(T: np.ndarray) -> np.ndarray:
    """(x, y, z, roll, pitch, yaw) of a 4x4 transform (inverse of ``pose_matrix``)."""
    R = T[:3, :3]
    pitch = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return np.array([T[0, 3], T[1, 3], T[2, 3], roll, pitch, yaw])


def invert(T: np.ndarray) -> np.ndarray:
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Ti = np.zeros_like(T)
    Ti[..., :3, :3] = np.swapaxes(R, -1, -2)
    Ti[..., :3, 3] = -np.einsum("...ji,...j->...i", R, t)
    Ti[..., 3, 3] = 1.0
    return Ti


def transform_points(T: np.ndarray, points: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Apply one 4x4 transform to (N, 3) points in float64 (into ``out``, a C-contiguous (N, 3) float64 array,
    when given: the same product and sum, the same bits)."""
    p = np.asarray(points, dtype=np.float64)
    if out is None:
        return p @ T[:3, :3].T + T[:3, 3]
    np.matmul(p, T[:3, :3].T, out=out)
    out += T[:3, 3]
    return out
