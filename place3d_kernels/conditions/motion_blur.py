"""Motion blur (Robo3D): a global offset plus per-point jitter, REFERENCE.md section 6.

With level sigma: one offset ``N(0, sigma^2)`` per axis for the whole frame, then per point
``x, y += clip(N(0, (0.1 sigma)^2), -3 sigma, 3 sigma)`` and ``z += clip(N(0, (0.05 sigma)^2), -3 sigma, 3 sigma)``.
Labels and intensities are kept; no point is added or removed.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.conditions._common import check_cloud, check_range, kernels, rng
from place3d_kernels.pointcloud import PointCloud

__all__ = ["motion_blur", "SEVERITIES"]

#: Robo3D levels; the paper uses 0.30 ("moderate").
SEVERITIES = {"light": {"sigma": 0.20}, "moderate": {"sigma": 0.30}, "heavy": {"sigma": 0.40}}


def motion_blur(cloud: PointCloud, sigma: float = 0.30, seed=0, backend=None) -> PointCloud:
    """Jitter a frame as a moving sensor would (Robo3D motion blur).

    Args:
        cloud: the frame.
        sigma: jitter level (m); the paper uses 0.30.
        seed: int or numpy Generator; draws the global offset, then the per-point normals.
        backend: backend name or instance (None: current default).

    Returns:
        A new PointCloud with displaced points (origins unchanged).
    """
    cloud = check_cloud(cloud, "motion_blur")
    sigma = check_range("sigma", sigma, lo=0.0)
    if sigma == 0.0 or len(cloud) == 0:
        return cloud.copy()
    g = rng(seed, 0)
    offset = g.normal(0.0, sigma, 3)
    normals = g.standard_normal((len(cloud), 3))
    disp = kernels(backend).motion_blur_points(normals, offset, sigma)
    return cloud.copy(points=cloud.points + np.asarray(disp, dtype=np.float64))
