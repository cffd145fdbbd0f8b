"""Semantic LiDAR simulation: frames of labelled returns along a scene's ego route."""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.classes import REFLECTIVITY
from place3d_kernels.lidar import LidarModel
from place3d_kernels.mesh import Mesh
from place3d_kernels.ops import raycast
from place3d_kernels.pointcloud import PointCloud
from place3d_kernels.pose import pose_from_matrix, pose_matrix

__all__ = ["simulate_frame", "simulate", "DEFAULT_MOUNT"]

#: Pose of the collection LiDAR in the ego frame (roof centre, 2.5 m above ground).
DEFAULT_MOUNT = np.array([0.0, 0.0, 2.5, 0.0, 0.0, 0.0])


def _intensity(mesh: Mesh, face: np.ndarray, d: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Lambertian return: class reflectivity times |cos(incidence)|."""
    cos = np.abs(np.einsum("ij,ij->i", mesh.normals[face], d))
    return (REFLECTIVITY[np.clip(labels, 0, len(REFLECTIVITY) - 1)] * cos).astype(np.float32)


def simulate_frame(static: Mesh, dynamic: Mesh | None, lidar: LidarModel, sensor_pose_world: np.ndarray,
                   backend=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cast one LiDAR sweep into a static mesh (+ optional dynamic mesh); keep the closest hits.

    Returns:
        points (N, 3) world, labels (N,), intensity (N,), origin (3,) of the sweep.
    """
    b = get_backend(backend)
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, np.asarray(sensor_pose_world)[None])
    hits = raycast(static, o, d, lidar.max_range, backend=b)
    t, face, lab, src = hits.t, hits.face, hits.label, np.zeros(len(o), dtype=bool)
    if dynamic is not None:
        dh = raycast(dynamic, o, d, lidar.max_range, backend=b)
        closer = dh.t < t
        t = np.where(closer, dh.t, t)
        face = np.where(closer, dh.face, face)
        lab = np.where(closer, dh.label, lab)
        src = closer
    hit = np.isfinite(t)
    pts = o[hit] + t[hit, None] * d[hit]
    inten = np.empty(int(hit.sum()), dtype=np.float32)
    s_hit, d_hit = src[hit], ~src[hit]
    if d_hit.any():
        inten[d_hit] = _intensity(static, face[hit][d_hit], d[hit][d_hit], lab[hit][d_hit])
    if s_hit.any():
        inten[s_hit] = _intensity(dynamic, face[hit][s_hit], d[hit][s_hit], lab[hit][s_hit])
    return pts, lab[hit].astype(np.int32), inten, o[0]


def simulate(scene, lidar: LidarModel | str = "collection_64ch", mount=DEFAULT_MOUNT, frames=None,
             backend=None, progress: bool = False) -> list[PointCloud]:
    """Semantic LiDAR frames along the scene's ego route (world points, ego pose, sensor origin per return).

    Args:
        scene: a ``Scene``.
        lidar: the sensor model (default: the dense collection LiDAR used to build P-SOGs).
        mount: (6,) pose of the sensor in the ego frame.
        frames: indices of the frames to simulate (default: all).
        backend: backend name or instance.
        progress: show a progress bar.
    """
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    idx = range(scene.n_frames) if frames is None else frames
    mount_T = pose_matrix(np.asarray(mount, dtype=np.float64))
    it = idx
    if progress:
        from tqdm import tqdm

        it = tqdm(list(idx), desc="simulate", unit="frame", leave=False)
    out = []
    for f in it:
        ego_T = pose_matrix(scene.ego_poses[f])
        T = ego_T @ mount_T
        sensor_pose = pose_from_matrix(T)
        pts, lab, inten, origin = simulate_frame(scene.static, scene.dynamic(f), lidar, sensor_pose, backend)
        out.append(PointCloud(pts, lab, inten, origin, ego_pose=scene.ego_poses[f].copy()))
    return out
