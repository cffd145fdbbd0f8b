"""Scan patterns other than a spinning grid: the non-repetitive rosette of Risley-prism LiDARs.

Livox units (Mid-40, Avia, ...) steer one beam (or a few) through two wedge prisms that rotate in
opposite directions at incommensurate rates. To first order each thin prism deflects the beam by a
fixed angle in the direction it currently faces, so the deflection off the boresight is the sum of two
counter-rotating vectors,

    rho(t) = delta * (exp(i 2 pi f1 t) + exp(-i 2 pi f2 t)),   delta = half_fov / 2,

a rose curve that sweeps through the centre and out to the FOV edge. Because f1 / f2 is not a ratio
of small integers the trace never closes, so every frame lands on new directions and the covered
fraction of the FOV grows with integration time (Livox's "non-repetitive scanning").

Frame of the directions: x forward (boresight), y left, z up, matching the package's sensor frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RosettePattern"]


@dataclass(frozen=True)
class RosettePattern:
    """Non-repetitive rosette scan of a two-prism (Risley) LiDAR.

    Attributes:
        fov_deg: full cone angle of the circular FOV, degrees (the rose's outer edge is fov_deg / 2
            off the boresight).
        points_per_second: beam firings per second (all beams together).
        frame_time_s: integration time of one frame, seconds.
        prism_hz: (f1, f2) rotation rates of the two prisms in Hz, positive numbers; the second turns
            the other way.
    """

    fov_deg: float
    points_per_second: float
    frame_time_s: float
    prism_hz: tuple[float, float]

    def __post_init__(self) -> None:
        if not (np.isfinite(self.fov_deg) and 0 < self.fov_deg < 180):
            raise ValueError(f"rosette fov_deg must be in (0, 180), got {self.fov_deg!r}")
        if not (np.isfinite(self.points_per_second) and self.points_per_second > 0):
            raise ValueError(f"rosette points_per_second must be positive, got {self.points_per_second!r}")
        if not (np.isfinite(self.frame_time_s) and self.frame_time_s > 0):
            raise ValueError(f"rosette frame_time_s must be positive, got {self.frame_time_s!r}")
        f = tuple(float(x) for x in self.prism_hz)
        if len(f) != 2 or not all(np.isfinite(x) and x > 0 for x in f):
            raise ValueError(f"rosette prism_hz must be two positive rates in Hz, got {self.prism_hz!r}")
        object.__setattr__(self, "prism_hz", f)
        if self.n_rays < 1:
            raise ValueError(f"rosette gives no ray per frame: points_per_second * frame_time_s = "
                             f"{self.points_per_second * self.frame_time_s}; raise either")

    @property
    def n_rays(self) -> int:
        """Rays per frame: points_per_second * frame_time_s, rounded."""
        return int(round(self.points_per_second * self.frame_time_s))

    def deflection(self, frame: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Polar angle off the boresight and its direction in the y-z plane, radians, per ray of a frame.

        Args:
            frame: frame index; frame k covers times [k, k+1) * frame_time_s.
        """
        t = (int(frame) * self.n_rays + np.arange(self.n_rays, dtype=np.float64)) / float(self.points_per_second)
        delta = 0.5 * np.radians(0.5 * self.fov_deg)
        f1, f2 = self.prism_hz
        rho = delta * (np.exp(2j * np.pi * f1 * t) + np.exp(-2j * np.pi * f2 * t))
        return np.abs(rho), np.angle(rho)

    def directions(self, frame: int = 0) -> np.ndarray:
        """(R, 3) float64 unit directions of one frame, in firing order."""
        theta, phi = self.deflection(frame)
        s = np.sin(theta)
        return np.stack([np.cos(theta), s * np.cos(phi), s * np.sin(phi)], -1)
