"""Shared plumbing of the condition models: backend choice, seeded streams, ray geometry."""

from __future__ import annotations

import warnings

import numpy as np

from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.conditions_base import ConditionKernels
from place3d_kernels.pointcloud import PointCloud

_warned: set[str] = set()


def kernels(backend=None) -> ConditionKernels:
    """The condition kernels of a backend; the reference ones (with one warning) if it has none."""
    b = get_backend(backend)
    if isinstance(b, ConditionKernels):
        return b
    name = getattr(b, "name", type(b).__name__)
    if name not in _warned:
        _warned.add(name)
        warnings.warn(f"backend {name!r} has no condition kernels (ConditionKernels mixin); the conditions "
                      f"run on the 'reference' backend instead", RuntimeWarning, stacklevel=3)
    return get_backend("reference")


def rng(seed, stream: int) -> np.random.Generator:
    """Independent PCG64 stream ``stream`` of a seed (an int, or a Generator whose next draws seed it).

    Separate streams keep, e.g., fog's noise draws the same whether or not alpha itself was drawn.
    """
    if isinstance(seed, np.random.Generator):
        seed = int(seed.integers(0, 2**63 - 1))
    if seed is None:
        seed = 0
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative int or a numpy Generator, got {seed!r}")
    return np.random.default_rng([int(seed), int(stream)])


def rays(cloud: PointCloud) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origins (N, 3), unit directions (N, 3), ranges (N,)) of a cloud's returns, float64.

    Points at their origin get a zero direction and range 0.
    """
    o = np.zeros((len(cloud), 3)) if cloud.origins is None else cloud.origins
    rel = cloud.points - o
    r = np.linalg.norm(rel, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(r[:, None] > 0, rel / r[:, None], 0.0)
    return o, u, r


def scattered(cloud: PointCloud) -> np.ndarray:
    return np.zeros(len(cloud), dtype=bool) if cloud.scattered is None else cloud.scattered.copy()


def check_cloud(cloud, fn: str) -> PointCloud:
    if not isinstance(cloud, PointCloud):
        raise TypeError(f"{fn} needs a place3d_kernels.PointCloud, got {type(cloud).__name__}; build one with "
                        f"p3k.PointCloud(points, labels, intensity, origins)")
    return cloud


def check_range(name: str, value, lo=None, hi=None, lo_open=False) -> float:
    v = float(value)
    if not np.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)) or (hi is not None and v > hi):
        bounds = f"{'(' if lo_open else '['}{lo if lo is not None else '-inf'}, {hi if hi is not None else 'inf'}]"
        raise ValueError(f"{name} must lie in {bounds}, got {value!r}")
    return v
