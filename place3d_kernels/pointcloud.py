"""One frame of labelled LiDAR returns."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["PointCloud"]


@dataclass
class PointCloud:
    """Labelled returns of one frame.

    Attributes:
        points: (N, 3) float64 positions (frame given by the producer: world for simulated frames).
        labels: (N,) int32 Place3D classes.
        intensity: (N,) float32 return intensity in [0, 1].
        origins: (N, 3) float64 sensor origin of each return, or None (ranges then measured from 0).
        scattered: (N,) bool, True where a condition replaced the surface return (fog); None if unset.
    """

    points: np.ndarray
    labels: np.ndarray
    intensity: np.ndarray
    origins: np.ndarray | None = None
    scattered: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        n = len(self.points)
        self.labels = np.asarray(self.labels, dtype=np.int32).reshape(-1)
        self.intensity = np.asarray(self.intensity, dtype=np.float32).reshape(-1)
        if self.labels.shape != (n,) or self.intensity.shape != (n,):
            raise ValueError(f"PointCloud needs one label and one intensity per point ({n}); got "
                             f"{self.labels.shape} and {self.intensity.shape}")
        if self.origins is not None:
            o = np.asarray(self.origins, dtype=np.float64)
            if o.shape == (3,):
                o = np.broadcast_to(o, (n, 3)).copy()
            if o.shape != (n, 3):
                raise ValueError(f"PointCloud origins must be (3,) or ({n}, 3), got {o.shape}")
            self.origins = o
        if self.scattered is not None:
            self.scattered = np.asarray(self.scattered, dtype=bool).reshape(-1)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def ranges(self) -> np.ndarray:
        o = 0.0 if self.origins is None else self.origins
        return np.linalg.norm(self.points - o, axis=1)

    def subset(self, mask: np.ndarray) -> "PointCloud":
        m = np.asarray(mask)
        return PointCloud(self.points[m], self.labels[m], self.intensity[m],
                          None if self.origins is None else self.origins[m],
                          None if self.scattered is None else self.scattered[m])

    def copy(self, **changes) -> "PointCloud":
        base = PointCloud(self.points.copy(), self.labels.copy(), self.intensity.copy(),
                          None if self.origins is None else self.origins.copy(),
                          None if self.scattered is None else self.scattered.copy())
        return replace(base, **changes) if changes else base
