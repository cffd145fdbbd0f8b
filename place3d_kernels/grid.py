"""The region of interest (ROI) and its voxel grid."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from place3d_kernels.backends.base import COORDINATE_LIMIT, GridSpec

__all__ = ["Grid", "DEFAULT_GRID", "MAX_VOXELS"]

#: Grids above this many voxels are refused before anything is allocated (about 1.6 GB of float32
#: entropy plus masks). Raise it per call with ``Grid(..., max_voxels=...)``.
MAX_VOXELS = 400_000_000


@dataclass(frozen=True)
class Grid:
    """An axis-aligned box split into cubic voxels.

    Args:
        lower: (x, y, z) lower corner in metres.
        upper: (x, y, z) upper corner in metres; rounded up to whole voxels.
        voxel_size: edge length in metres (finite, > 0).
        max_voxels: refuse grids larger than this (memory guard).

    Raises:
        ValueError: a corner or the voxel size is not finite, the voxel size is not > 0, upper does not
            exceed lower, an extent exceeds ``COORDINATE_LIMIT`` (1e5 m: float32 backends cannot resolve
            grid-local coordinates farther out; ``backends/base.py``), or the grid would have more than
            ``max_voxels`` voxels (checked before any count becomes an integer, so even 5e-324 m voxels
            give this error).

    The flat index of voxel (i, j, k) is ``(i * ny + j) * nz + k``.
    """

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]
    voxel_size: float
    max_voxels: int = field(default=MAX_VOXELS, compare=False)

    def __post_init__(self) -> None:
        lower = tuple(float(v) for v in np.asarray(self.lower, dtype=np.float64).reshape(-1))
        upper = tuple(float(v) for v in np.asarray(self.upper, dtype=np.float64).reshape(-1))
        if len(lower) != 3 or len(upper) != 3:
            raise ValueError(f"Grid lower/upper must have 3 components, got {self.lower!r} / {self.upper!r}")
        try:
            vs = float(self.voxel_size)
        except (TypeError, ValueError):
            vs = math.nan
        if not math.isfinite(vs) or vs <= 0:
            raise ValueError(f"Grid voxel_size must be a positive finite number of metres, got {self.voxel_size!r}")
        if not all(math.isfinite(v) for v in lower + upper):
            raise ValueError(f"Grid corners must be finite, got lower={lower} upper={upper}")
        if any(u <= lo for lo, u in zip(lower, upper)):
            raise ValueError(f"Grid upper corner must exceed lower on every axis, got lower={lower} upper={upper}")
        extent = [u - lo for lo, u in zip(lower, upper)]
        if not all(e <= COORDINATE_LIMIT for e in extent):     # inf (corners at +-1e308) fails this too
            raise ValueError(f"Grid extent {extent} m exceeds {COORDINATE_LIMIT:g} m on an axis: grid-local "
                             f"coordinates that far cannot be placed to a voxel by float32 backends "
                             f"(backends/base.py COORDINATE_LIMIT); use a smaller ROI")
        # voxels per axis as a float first: a tiny voxel_size (5e-324) makes it inf or too large for an int
        per_axis = [e / vs for e in extent]
        if not all(q <= self.max_voxels for q in per_axis):
            raise ValueError(
                f"Grid voxel_size {vs!r} m gives {max(per_axis):.3g} voxels along one axis of the {extent} m "
                f"box, above the limit of {self.max_voxels:,} voxels: use a larger voxel_size or a smaller ROI, "
                f"or pass max_voxels=")
        shape = tuple(int(math.ceil(q - 1e-9)) for q in per_axis)
        n = shape[0] * shape[1] * shape[2]
        if n > self.max_voxels:
            gib = n * 4 / 2**30
            raise ValueError(
                f"Grid of shape {shape} has {n:,} voxels (about {gib:.1f} GiB per float32 field), above the "
                f"limit of {self.max_voxels:,}: use a larger voxel_size or a smaller ROI, or pass max_voxels=")
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", tuple(lo + s * vs for lo, s in zip(lower, shape)))
        object.__setattr__(self, "voxel_size", vs)

    # ----------------------------------------------------------------- derived
    @property
    def shape(self) -> tuple[int, int, int]:
        vs = self.voxel_size
        return tuple(int(round((u - lo) / vs)) for lo, u in zip(self.lower, self.upper))

    @property
    def n_voxels(self) -> int:
        nx, ny, nz = self.shape
        return nx * ny * nz

    @property
    def spec(self) -> GridSpec:
        """What kernels see: grid-local coordinates."""
        return GridSpec(self.voxel_size, self.shape)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """Subtract the lower corner in float64 (before anything becomes float32 on a device)."""
        return np.asarray(points, dtype=np.float64) - np.asarray(self.lower, dtype=np.float64)

    def contains(self, points: np.ndarray) -> np.ndarray:
        p = np.asarray(points, dtype=np.float64)
        return np.all((p >= self.lower) & (p < self.upper), axis=-1)

    def index(self, points: np.ndarray) -> np.ndarray:
        """Integer (i, j, k) of each point (float64 floor); no bounds check."""
        return np.floor(self.to_local(points) / self.voxel_size).astype(np.int64)

    def flat(self, ijk: np.ndarray) -> np.ndarray:
        ijk = np.asarray(ijk, dtype=np.int64)
        _, ny, nz = self.shape
        return (ijk[..., 0] * ny + ijk[..., 1]) * nz + ijk[..., 2]

    def unflat(self, flat: np.ndarray) -> np.ndarray:
        return np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), self.shape), axis=-1)

    def centers(self, flat: np.ndarray) -> np.ndarray:
        return np.asarray(self.lower) + (self.unflat(flat) + 0.5) * self.voxel_size

    def to_dict(self) -> dict:
        return {"lower": list(self.lower), "upper": list(self.upper), "voxel_size": self.voxel_size,
                "shape": list(self.shape)}

    @classmethod
    def from_dict(cls, d: dict) -> "Grid":
        return cls(tuple(d["lower"]), tuple(d["upper"]), float(d["voxel_size"]))


#: The default ROI: 80 m x 80 m x 5 m around the ego vehicle, 0.2 m voxels (4.0 M voxels). It is offset
#: by a quarter voxel so that LiDAR positions on the paper's 0.1 m grid never sit on a voxel face, and so
#: that the ground plane z = 0 lies inside a voxel layer rather than on its boundary.
DEFAULT_GRID = Grid(lower=(-40.05, -40.05, -0.45), upper=(39.95, 39.95, 4.55), voxel_size=0.2)
