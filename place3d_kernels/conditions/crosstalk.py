"""Crosstalk (Robo3D): spurious returns from other LiDARs, REFERENCE.md section 6.

With ratio p: ``int(p N)`` points, chosen without replacement, get ``N(0, 3^2)`` (metres) added to each
coordinate. They are marked in ``scattered`` (their return no longer comes from the surface); labels and
intensities are kept (Robo3D relabels them "ignored": use ``labels[cloud.scattered] = 0`` for that).
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.conditions._common import check_cloud, check_range, kernels, rng, scattered
from place3d_kernels.pointcloud import PointCloud

__all__ = ["crosstalk", "SEVERITIES"]

#: Robo3D levels; the paper uses 0.07 ("moderate").
SEVERITIES = {"light": {"ratio": 0.03}, "moderate": {"ratio": 0.07}, "heavy": {"ratio": 0.12}}


def crosstalk(cloud: PointCloud, ratio: float = 0.07, seed=0, backend=None, *, noise_std: float = 3.0) -> PointCloud:
    """Move a random ``int(ratio N)`` of the points by Gaussian noise (Robo3D crosstalk).

    Args:
        cloud: the frame.
        ratio: fraction of points hit, in [0, 1]; the paper uses 0.07.
        seed: int or numpy Generator; draws the points, then their noise.
        backend: backend name or instance (None: current default).
        noise_std: standard deviation of the noise per coordinate (m).

    Returns:
        A new PointCloud of the same length; the moved points are marked in ``scattered``.
    """
    cloud = check_cloud(cloud, "crosstalk")
    ratio = check_range("ratio", ratio, lo=0.0, hi=1.0)
    n = len(cloud)
    k = int(ratio * n)
    if k == 0:
        return cloud.copy()
    g = rng(seed, 0)
    index = g.choice(n, k, replace=False)
    noise = g.normal(0.0, noise_std, (k, 3))
    disp = kernels(backend).crosstalk_points(n, index, noise)
    hit = np.zeros(n, dtype=bool)
    hit[index] = True
    return cloud.copy(points=cloud.points + np.asarray(disp, dtype=np.float64), scattered=scattered(cloud) | hit)
