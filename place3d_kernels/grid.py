"""The region of interest (ROI) and its voxel grid."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from place3d_kernels.backends.base import COORDINATE_LIMIT, GridSpec

__all__ = ["Grid", "DEFAULT_GRID", "MAX_VOXELS", "FACE_OFFSET", "DENSE_BYTES_PER_VOXEL", "roi_bounds", "roi_grid",
           "check_roi", "check_inside"]

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


#: The default ROI: 80 m x 80 m x 5 m around the ego vehicle, 0.1 m voxels (800 x 800 x 50, 32 M voxels;
#: why 0.1 m: docs/assumptions.md, section 1). It is offset by half a voxel so that LiDAR positions on the
#: paper's 0.1 m grid never sit on a voxel face, and so that the ground plane z = 0 lies inside a voxel
#: layer rather than on its boundary.
DEFAULT_GRID = Grid(lower=(-40.05, -40.05, -0.45), upper=(39.95, 39.95, 4.55), voxel_size=0.1)


# ---------------------------------------------------------------------------------------- user ROIs
#: Every face of an ROI grid lies at ``FACE_OFFSET + n * voxel_size`` (metres, n an integer) on each axis:
#: DEFAULT_GRID's anchor. At 0.2 m this is a quarter voxel and at 0.1 m half a voxel off every multiple of
#: 0.1 m, so LiDARs on the paper's 0.1 m grid and the ground (z = 0) never sit on a face; at 0.05 m the
#: faces fall on those multiples (docs/assumptions.md, section 1).
FACE_OFFSET = -0.05
#: How far below the ground the sizes form of an ROI reaches (down to a face): DEFAULT_GRID's z = -0.45 m,
#: room for road points below the ego's ground plane on a slope.
BELOW_GROUND = 0.45
#: Bytes each voxel costs in the dense fields a scoring run prepares per grid (an int64 fixed-point entropy
#: weight and a uint8 stop mask, ``PSOG.weights_fixed`` / ``stop_mask``), on the host and again on a device.
DENSE_BYTES_PER_VOXEL = 9

_SNAP = 1e-6        # a bound within a millionth of a voxel of a face is on it (0.2 * 200 is 40.000000000000004)


def _face_below(x: float, v: float) -> float:
    return round(FACE_OFFSET + v * math.floor((x - FACE_OFFSET) / v + _SNAP), 9)


def _face_above(x: float, v: float) -> float:
    return round(FACE_OFFSET + v * math.ceil((x - FACE_OFFSET) / v - _SNAP), 9)


def roi_bounds(roi, voxel_size: float | None = None) -> tuple[tuple, tuple]:
    """(lower, upper) corners of the ROI box ``roi`` asks for, on faces at ``FACE_OFFSET + n * voxel_size``.

    Args:
        roi: None (DEFAULT_GRID's box, kept as it is at every voxel size); 3 sizes (LX, LY, LZ) in metres:
            x and y centred on the ego origin (the ground below the vehicle centre) less FACE_OFFSET, each
            half rounded up to whole voxels, and z from BELOW_GROUND under the ground (down to a face) up by
            LZ; or 6 corners (X0, Y0, Z0, X1, Y1, Z1) in the ego frame (x forward, y left, z up), each moved
            outward to the next face.
        voxel_size: the voxel edge (None: DEFAULT_GRID's 0.1 m).

    ``roi_bounds((80, 80, 5), 0.1)`` is DEFAULT_GRID's box, so ``--roi 80 80 5`` is the default.
    """
    v = DEFAULT_GRID.voxel_size if voxel_size is None else float(voxel_size)
    if roi is None:
        return DEFAULT_GRID.lower, DEFAULT_GRID.upper
    r = _roi_numbers(roi)
    if len(r) == 3:
        halves = [v * math.ceil(s / 2.0 / v - _SNAP) for s in r[:2]]
        lower = [round(FACE_OFFSET - h, 9) for h in halves]
        upper = [round(FACE_OFFSET + h, 9) for h in halves]
        z0 = _face_below(-BELOW_GROUND, v)
        return (lower[0], lower[1], z0), (upper[0], upper[1], round(z0 + v * math.ceil(r[2] / v - _SNAP), 9))
    return (tuple(_face_below(x, v) for x in r[:3]), tuple(_face_above(x, v) for x in r[3:]))


def roi_grid(roi=None, voxel_size: float | None = None, max_voxels: int = MAX_VOXELS) -> Grid:
    """The ``Grid`` of ``roi_bounds(roi, voxel_size)``; DEFAULT_GRID itself when both are None, and
    DEFAULT_GRID's box at ``voxel_size`` when ``roi`` is None (as before ROIs could be chosen)."""
    if roi is None and voxel_size is None:
        return DEFAULT_GRID
    lower, upper = roi_bounds(roi, voxel_size)
    return Grid(lower, upper, DEFAULT_GRID.voxel_size if voxel_size is None else float(voxel_size),
                max_voxels=max_voxels)


def _roi_numbers(roi) -> tuple:
    """``roi`` as 3 positive sizes or 6 corners (lower below upper), or ``ValueError`` naming --roi."""
    try:
        r = tuple(float(x) for x in roi)
    except (TypeError, ValueError):
        raise ValueError(f"--roi takes numbers (metres), got {roi!r}") from None
    if len(r) not in (3, 6):
        raise ValueError(f"--roi takes 3 sizes LX LY LZ or 6 corners X0 Y0 Z0 X1 Y1 Z1 (metres), got {len(r)} "
                         f"numbers {list(r)}")
    if not all(math.isfinite(x) for x in r):
        raise ValueError(f"--roi numbers must be finite, got {list(r)}")
    if len(r) == 3 and not all(x > 0 for x in r):
        raise ValueError(f"--roi sizes LX LY LZ must be > 0 metres, got {list(r)}")
    if len(r) == 6 and not all(hi > lo for lo, hi in zip(r[:3], r[3:])):
        raise ValueError(f"--roi corners X0 Y0 Z0 X1 Y1 Z1 need X1 > X0, Y1 > Y0 and Z1 > Z0, got {list(r)}")
    return r


def check_roi(roi, voxel_size: float | None = None, max_voxels: int = MAX_VOXELS) -> Grid:
    """The grid of ``--roi`` / ``--voxel-size``, or ``ValueError`` naming the options: a malformed ROI, or a
    box of more voxels than ``max_voxels`` (with its memory and a voxel size or box that fits)."""
    v = DEFAULT_GRID.voxel_size if voxel_size is None else float(voxel_size)
    if roi is not None:
        _roi_numbers(roi)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"--voxel-size must be > 0 metres, got {voxel_size}")
    n, extent = _voxel_count(roi, v)
    if n > max_voxels or max(extent) > COORDINATE_LIMIT:
        fits = math.ceil(v * (n / max_voxels) ** (1.0 / 3.0) * 100) / 100
        while _voxel_count(roi, fits)[0] > max_voxels:      # whole voxels per axis round the count up
            fits = round(fits + 0.01, 2)
        raise ValueError(
            f"--roi {_roi_text(roi)} at --voxel-size {v:g} m is a {' x '.join(f'{e:g}' for e in extent)} m box of "
            f"{n:.3g} voxels (about {n * DENSE_BYTES_PER_VOXEL / 2**30:.3g} GiB of dense fields per grid, on the "
            f"host and again on the device), above the limit of {max_voxels:,}: use a smaller --roi or a "
            f"--voxel-size of at least {fits:g} m")
    return roi_grid(roi, voxel_size, max_voxels=max_voxels)


def _voxel_count(roi, v: float) -> tuple[float, list]:
    """(voxels, extent in metres) of the box ``roi_bounds(roi, v)``, the count a float so that absurd sizes
    cannot overflow it."""
    lower, upper = roi_bounds(roi, v)
    extent = [u - lo for lo, u in zip(lower, upper)]
    per_axis = [e / v for e in extent]          # whole voxels already (roi_bounds), up to rounding
    return math.prod(float(round(q)) if q < 2.0**53 else q for q in per_axis), extent


def _roi_text(roi) -> str:
    return "(default 80 80 5)" if roi is None else " ".join(f"{float(x):g}" for x in roi)


def check_inside(grid: Grid, points, what: str) -> None:
    """``ValueError`` naming --roi when a point of ``points`` ((..., 3) metres, ego frame: LiDAR mounts) lies
    outside ``grid``: rays from outside the ROI start in no voxel, so the rig would be scored on part of its
    view."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = ~grid.contains(p)
    if out.any():
        q = p[int(np.argmax(out))]
        box = ", ".join(f"{a} [{lo:g}, {hi:g}]" for a, lo, hi in zip("xyz", grid.lower, grid.upper))
        raise ValueError(f"--roi: the ROI ({box} m) does not contain {what} at "
                         f"({q[0]:g}, {q[1]:g}, {q[2]:g}) m; choose a box around the rig's mount points")
