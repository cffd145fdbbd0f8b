"""LiDAR beam patterns and ray generation."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from place3d_kernels._toml import read_toml, require, resolve_config

__all__ = ["LidarModel", "lidar_rays"]


@dataclass(frozen=True, eq=False)
class LidarModel:
    """A spinning LiDAR: channel elevations, azimuth steps and maximum range.

    Attributes:
        elevations: (C,) radians, one per channel.
        azimuths: (A,) radians, one per azimuth step.
        max_range: metres.
        name: label.
    """

    elevations: np.ndarray
    azimuths: np.ndarray
    max_range: float
    name: str = ""

    def __post_init__(self) -> None:
        e = np.asarray(self.elevations, dtype=np.float64).reshape(-1)
        a = np.asarray(self.azimuths, dtype=np.float64).reshape(-1)
        if len(e) == 0 or len(a) == 0:
            raise ValueError("LidarModel needs at least one channel and one azimuth step")
        if not (np.all(np.isfinite(e)) and np.all(np.abs(e) <= np.pi / 2)):
            raise ValueError(f"LidarModel elevations must be finite and within +-90 deg, got {np.degrees(e)}")
        if not np.all(np.isfinite(a)):
            raise ValueError("LidarModel azimuths must be finite")
        if not (np.isfinite(self.max_range) and self.max_range > 0):
            raise ValueError(f"LidarModel max_range must be positive, got {self.max_range!r}")
        object.__setattr__(self, "elevations", e)
        object.__setattr__(self, "azimuths", a)
        object.__setattr__(self, "max_range", float(self.max_range))

    @classmethod
    def uniform(cls, channels: int, fov_deg=(-24.8, 2.0), azimuth_steps: int = 250,
                horizontal_fov_deg: float = 360.0, max_range: float = 100.0, name: str = "") -> "LidarModel":
        """Channels spread uniformly over the vertical FOV; azimuth steps evenly over the horizontal FOV."""
        if channels < 1 or azimuth_steps < 1:
            raise ValueError(f"channels and azimuth_steps must be >= 1, got {channels}, {azimuth_steps}")
        lo, hi = fov_deg
        if not lo <= hi:
            raise ValueError(f"vertical FOV lower bound must not exceed the upper, got {fov_deg}")
        e = np.radians(np.linspace(lo, hi, channels)) if channels > 1 else np.radians([0.5 * (lo + hi)])
        h = np.radians(horizontal_fov_deg)
        if horizontal_fov_deg >= 360.0:
            a = np.arange(azimuth_steps) * (2 * np.pi / azimuth_steps)
        else:
            a = -h / 2 + (np.arange(azimuth_steps) + 0.5) * (h / azimuth_steps)
        return cls(e, a, max_range, name)

    @classmethod
    def load(cls, path_or_name) -> "LidarModel":
        """Read a LiDAR TOML (path or shipped name such as ``"place3d_16ch"``)."""
        path = resolve_config(path_or_name, "lidars")
        d = read_toml(path)
        name = str(d.get("name", path.stem))
        max_range = float(require(d, "max_range_m", path))
        steps = int(require(d, "azimuth_steps", path, int))
        hfov = float(d.get("horizontal_fov_deg", 360.0))
        if "elevations_deg" in d:
            e = d["elevations_deg"]
            if not isinstance(e, list) or not e:
                raise ValueError(f"{path}: elevations_deg must be a non-empty list of degrees")
            base = cls.uniform(1, (0, 0), steps, hfov, max_range, name)
            return cls(np.radians(np.asarray(e, dtype=float)), base.azimuths, max_range, name)
        channels = int(require(d, "channels", path, int))
        fov = d.get("vertical_fov_deg")
        if not (isinstance(fov, list) and len(fov) == 2):
            raise ValueError(f"{path}: vertical_fov_deg must be [lower, upper] in degrees (or give elevations_deg)")
        return cls.uniform(channels, tuple(float(x) for x in fov), steps, hfov, max_range, name)

    @property
    def n_channels(self) -> int:
        return len(self.elevations)

    @property
    def n_rays(self) -> int:
        return len(self.elevations) * len(self.azimuths)

    def subsample(self, channel_step: int = 1, azimuth_step: int = 1) -> "LidarModel":
        return LidarModel(self.elevations[::channel_step], self.azimuths[::azimuth_step], self.max_range,
                          f"{self.name}/c{channel_step}a{azimuth_step}")


def lidar_rays(lidar: LidarModel, placement, backend=None) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions of every ray of a rig, ordered (LiDAR, channel, azimuth).

    Args:
        lidar: the beam pattern shared by all LiDARs of the rig.
        placement: a ``Placement`` or an (L, 6) pose array.
        backend: name or Backend; default the current one.
    """
    from place3d_kernels.backends.registry import resolve

    poses = placement.poses if hasattr(placement, "poses") else np.asarray(placement, dtype=np.float64)
    b = resolve(backend)
    o, d = b.lidar_rays(lidar.elevations, lidar.azimuths, np.asarray(poses, dtype=np.float64).reshape(-1, 6))
    return np.asarray(o, dtype=np.float64), np.asarray(d, dtype=np.float64)
