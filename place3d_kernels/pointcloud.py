"""One frame of labelled LiDAR returns: what the simulator produces, conditions transform, P-SOGs vote on
and the SemanticKITTI writer stores. One type end to end, so no frame is converted on the way."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

__all__ = ["PointCloud"]


def _opt(a, fn):
    return None if a is None else fn(a)


@dataclass
class PointCloud:
    """Labelled returns of one frame.

    Attributes:
        points: (N, 3) float64 positions (frame given by the producer: world for simulated frames).
        labels: (N,) int32 Place3D classes.
        intensity: (N,) float32 return intensity in [0, 1] (None: zeros).
        origins: (N, 3) float64 sensor origin of each return, or None (ranges then measured from 0). A (3,)
            or (1, 3) origin is broadcast to every return.
        ego_pose: (6,) ego pose (x, y, z, roll, pitch, yaw) in the world when the frame was taken, or None
            (a bare cloud, e.g. for the conditions alone). P-SOGs and the writer need it.
        scattered: (N,) bool, True where a condition replaced the surface return (fog); None if unset.
        sweep_origin: (3,) float64 where the sweep was cast from (world). Defaults to the first origin;
            kept when a condition drops every return, so the frame still knows its sensor position.
    """

    points: np.ndarray
    labels: np.ndarray
    intensity: np.ndarray | None = None
    origins: np.ndarray | None = None
    ego_pose: np.ndarray | None = None
    scattered: np.ndarray | None = field(default=None)
    sweep_origin: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.points = np.asarray(self.points, dtype=np.float64).reshape(-1, 3)
        n = len(self.points)
        self.labels = np.asarray(self.labels, dtype=np.int32).reshape(-1)
        if self.intensity is None:
            self.intensity = np.zeros(n, np.float32)
        self.intensity = np.asarray(self.intensity, dtype=np.float32).reshape(-1)
        if self.labels.shape != (n,) or self.intensity.shape != (n,):
            raise ValueError(f"PointCloud needs one label and one intensity per point ({n}); got "
                             f"{self.labels.shape} and {self.intensity.shape}")
        if self.origins is not None:
            o = np.asarray(self.origins, dtype=np.float64)
            if o.shape == (1, 3):
                o = o[0]
            if o.shape == (3,):
                if self.sweep_origin is None:
                    self.sweep_origin = o.copy()
                o = np.broadcast_to(o, (n, 3)).copy()
            if o.shape != (n, 3):
                raise ValueError(f"PointCloud origins must be (3,) or ({n}, 3), got {o.shape}")
            self.origins = o
            if self.sweep_origin is None and n:
                self.sweep_origin = o[0].copy()
        if self.sweep_origin is not None:
            self.sweep_origin = np.asarray(self.sweep_origin, dtype=np.float64).reshape(3)
        if self.ego_pose is not None:
            self.ego_pose = np.asarray(self.ego_pose, dtype=np.float64).reshape(6)
        if self.scattered is not None:
            self.scattered = np.asarray(self.scattered, dtype=bool).reshape(-1)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def ranges(self) -> np.ndarray:
        o = 0.0 if self.origins is None else self.origins
        return np.linalg.norm(self.points - o, axis=1)

    def subset(self, mask: np.ndarray) -> "PointCloud":
        """The returns selected by ``mask`` (pose and sweep origin kept)."""
        m = np.asarray(mask)
        return PointCloud(self.points[m], self.labels[m], self.intensity[m], _opt(self.origins, lambda a: a[m]),
                          _opt(self.ego_pose, np.copy), _opt(self.scattered, lambda a: a[m]),
                          _opt(self.sweep_origin, np.copy))

    def copy(self, **changes) -> "PointCloud":
        """A deep copy, with ``changes`` (field=value) applied."""
        base = PointCloud(self.points.copy(), self.labels.copy(), self.intensity.copy(), _opt(self.origins, np.copy),
                          _opt(self.ego_pose, np.copy), _opt(self.scattered, np.copy),
                          _opt(self.sweep_origin, np.copy))
        return replace(base, **changes) if changes else base
