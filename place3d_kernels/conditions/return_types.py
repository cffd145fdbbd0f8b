"""What ``lidar_returns`` gives per ray (``Returns``) and its return kinds, shared by the analytic model
(``returns``) and the Mitsuba one (``mitsuba_returns``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Returns", "NONE", "SURFACE", "FOG"]

NONE, SURFACE, FOG = 0, 1, 2


@dataclass
class Returns:
    """One entry per ray.

    Attributes:
        range: metres along the ray (inf: no return).
        intensity: return intensity (0: no return).
        hard_power: surface return power / (C_A P0) (0 on a miss or a dropped return).
        fog_power: peak fog backscatter power / (C_A P0) (0 without fog).
        kind: 0 no return, 1 surface, 2 fog.
        label: class of the surface hit (-1 on a miss).
    """

    range: np.ndarray
    intensity: np.ndarray
    hard_power: np.ndarray
    fog_power: np.ndarray
    kind: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return len(self.range)
