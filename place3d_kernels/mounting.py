"""Mounting surfaces: where on a vehicle body a LiDAR may sit, and which way it may look.

A ``MountSurface`` maps parameters ``(u, v, w)`` in [0, 1]^3 to an ego-frame position on (just outside)
the body: ``u`` and ``v`` run along a patch of the body's surface, ``w`` lifts the sensor off it from
``standoff`` to ``standoff + lift`` metres along the patch's outward normal. Each surface also carries the
orientations allowed there (roll, pitch, yaw ranges in radians, and a nominal look direction): a bumper
unit looks forward (rear bumper: backward) within +-yaw range, a fender unit sideways, a roof unit
anywhere in yaw. The optimiser (``place3d_kernels.optimize.rig_search``) moves sensors in these
coordinates, so they slide along the car rather than through it.

Surfaces come from the body's boxes (parametric presets: a lower body and a cabin) or, for a loaded mesh,
from its bounding box with the cabin taken as the whole body. The paper's search box above the roof
(x, y in [-0.6, 0.6] m, z in [2.2, 2.8] m, Place3D Sec. 4.1) stays available as the surface
``roof-box`` (there ``u, v, w`` span x, y, z and the orientation is free in roll as in the paper).

Standoffs: ``STANDOFF_M`` (5 cm) puts the optical centre just outside a bumper or fender face, as a
flush-mounted unit's window is; on the roof the centre sits ``ROOF_STANDOFF_M`` (10 cm) above it,
about half the height of a spinning unit's housing (VLP-16: 71.7 mm tall, OS1: 73 mm, mounted on a
bracket). These are illustrative defaults; pass ``standoff=`` to change them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from place3d_kernels.vehicle import VehicleBody

__all__ = ["MountSurface", "SURFACE_NAMES", "surfaces_for", "STANDOFF_M", "ROOF_STANDOFF_M"]

STANDOFF_M = 0.05
ROOF_STANDOFF_M = 0.10
_LIFT_M = 0.20                 # how far w = 1 lifts a unit beyond its standoff (a bracket or riser)
_YAW_RANGE = 0.6               # +-rad about the nominal look direction for bumper / fender units
_PITCH_RANGE = 0.3             # +-rad of pitch everywhere
SURFACE_NAMES = ("roof", "front-bumper", "rear-bumper", "left-fender", "right-fender", "left-a-pillar",
                 "right-a-pillar", "roof-box")


@dataclass(frozen=True)
class MountSurface:
    """A parametrised mounting patch on a body.

    Attributes:
        name: surface name (one of ``SURFACE_NAMES``).
        origin: (3,) ego-frame corner of the patch at u = v = 0.
        du, dv: (3,) patch edge vectors (u and v run along them).
        normal: (3,) outward unit normal; positions are ``origin + u du + v dv + (standoff + w lift) normal``.
        standoff: metres off the surface at w = 0.
        lift: extra metres at w = 1.
        orientation: ``{"roll"|"pitch"|"yaw": (lo, hi)}`` allowed ranges in radians.
        nominal: ``{"roll"|"pitch"|"yaw": value}`` used when an angle is not optimised.
    """

    name: str
    origin: np.ndarray
    du: np.ndarray
    dv: np.ndarray
    normal: np.ndarray
    standoff: float
    lift: float
    orientation: dict = field(default_factory=dict)
    nominal: dict = field(default_factory=dict)

    def position(self, u, v, w=0.0) -> np.ndarray:
        """(..., 3) ego-frame positions of parameters in [0, 1] (values outside are clipped)."""
        u, v, w = (np.clip(np.asarray(a, dtype=np.float64), 0.0, 1.0)[..., None] for a in (u, v, w))
        return self.origin + u * self.du + v * self.dv + (self.standoff + w * self.lift) * self.normal

    def angle(self, key: str, s) -> np.ndarray:
        """Angle ``key`` at fraction ``s`` in [0, 1] of its allowed range (clipped)."""
        lo, hi = self.orientation[key]
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
        return (1.0 - s) * lo + s * hi            # exact at both ends of the range

    def nominal_fraction(self, key: str) -> float:
        """Where the nominal angle lies in its range, as a fraction (0.5 when the range is empty)."""
        lo, hi = self.orientation[key]
        return 0.5 if hi <= lo else float((self.nominal[key] - lo) / (hi - lo))

    def corners(self) -> np.ndarray:
        """(8, 3) positions at the corners of the parameter cube (u, v, w in {0, 1})."""
        c = np.array([[u, v, w] for u in (0, 1) for v in (0, 1) for w in (0, 1)], dtype=np.float64)
        return self.position(c[:, 0], c[:, 1], c[:, 2])

    def to_dict(self) -> dict:
        return {"name": self.name, "origin_m": np.round(self.origin, 4).tolist(),
                "du_m": np.round(self.du, 4).tolist(), "dv_m": np.round(self.dv, 4).tolist(),
                "normal": np.round(self.normal, 4).tolist(), "standoff_m": self.standoff, "lift_m": self.lift,
                "orientation_rad": {k: list(v) for k, v in self.orientation.items()},
                "nominal_rad": dict(self.nominal)}


def _orient(yaw0: float, yaw_range: float, roll=(0.0, 0.0)) -> tuple[dict, dict]:
    return ({"roll": roll, "pitch": (-_PITCH_RANGE, _PITCH_RANGE), "yaw": (yaw0 - yaw_range, yaw0 + yaw_range)},
            {"roll": 0.0, "pitch": 0.0, "yaw": yaw0})


def _body_boxes(body: VehicleBody) -> tuple[np.ndarray, np.ndarray]:
    """(lower box, cabin box) of a body: the two preset boxes, or the bounds twice for a loaded mesh."""
    if body.boxes is not None and len(body.boxes) >= 2:
        order = np.argsort(body.boxes[:, 1, 2])          # by top height: lower body first, cabin last
        return body.boxes[order[0]], body.boxes[order[-1]]
    b = np.asarray(body.bounds, dtype=np.float64)
    return b, b


def surfaces_for(body: VehicleBody | None, names=SURFACE_NAMES, standoff: float | None = None) -> dict:
    """``{name: MountSurface}`` for the requested surface names on a body.

    Args:
        body: the vehicle (``None`` allows only ``roof-box``).
        names: surface names (see ``SURFACE_NAMES``).
        standoff: overrides the default standoffs (metres, > 0).

    Raises:
        ValueError: an unknown or empty name list, a body surface without a body, a bad standoff.
    """
    names = list(names)
    if not names:
        raise ValueError(f"the surface list is empty; choose from {list(SURFACE_NAMES)}")
    bad = [n for n in names if n not in SURFACE_NAMES]
    if bad:
        raise ValueError(f"unknown mounting surface(s) {bad}; choose from {list(SURFACE_NAMES)}")
    if standoff is not None and not (np.isfinite(standoff) and standoff > 0):
        raise ValueError(f"standoff must be a positive number of metres, got {standoff!r}")
    if body is None and any(n != "roof-box" for n in names):
        raise ValueError(f"surfaces {[n for n in names if n != 'roof-box']} need a vehicle body (--vehicle car, "
                         f"suv, van, truck or a mesh); without one only 'roof-box' exists")
    out = {}
    for n in names:
        out[n] = _surface(n, body, standoff)
    return out


def _surface(name: str, body: VehicleBody | None, standoff: float | None) -> MountSurface:
    A = np.asarray
    ex, ey, ez = A([1.0, 0, 0]), A([0, 1.0, 0]), A([0, 0, 1.0])
    s = STANDOFF_M if standoff is None else float(standoff)
    if name == "roof-box":
        # the paper's box (DEFAULT_BOUNDS of optimize.space): u, v, w span x, y, z; no standoff
        orient = {"roll": (-0.3, 0.3), "pitch": (-_PITCH_RANGE, _PITCH_RANGE), "yaw": (-np.pi, np.pi)}
        return MountSurface(name, A([-0.6, -0.6, 2.2]), 1.2 * ex, 1.2 * ey, ez, 0.0, 0.6, orient,
                            {"roll": 0.0, "pitch": 0.0, "yaw": 0.0})
    lower, cabin = _body_boxes(body)
    (lx0, ly0, lz0), (lx1, ly1, lz1) = lower
    (cx0, cy0, _), (cx1, cy1, cz1) = cabin
    inset = 0.1                                    # keep units 10 cm in from an edge
    if name == "roof":
        o, _ = _orient(0.0, np.pi)
        return MountSurface(name, A([cx0 + inset, cy0 + inset, cz1]), (cx1 - cx0 - 2 * inset) * ex,
                            (cy1 - cy0 - 2 * inset) * ey, ez, ROOF_STANDOFF_M if standoff is None else s, _LIFT_M,
                            o, {"roll": 0.0, "pitch": 0.0, "yaw": 0.0})
    zb0 = lz0 + 0.15 * (lz1 - lz0)                  # bumper band: lower 15 %..85 % of the lower body
    zb1 = lz0 + 0.85 * (lz1 - lz0)
    if name in ("front-bumper", "rear-bumper"):
        front = name == "front-bumper"
        x = lx1 if front else lx0
        o, nom = _orient(0.0 if front else np.pi, _YAW_RANGE)
        return MountSurface(name, A([x, ly0 + inset, zb0]), (ly1 - ly0 - 2 * inset) * ey, (zb1 - zb0) * ez,
                            ex if front else -ex, s, _LIFT_M, o, nom)
    if name in ("left-fender", "right-fender"):
        left = name == "left-fender"
        y = ly1 if left else ly0
        # front fender: from the front of the cabin to 10 cm behind the bumper corner
        x0, x1 = max(cx1 - 0.3, lx0), lx1 - inset
        o, nom = _orient(np.pi / 2 if left else -np.pi / 2, _YAW_RANGE)
        return MountSurface(name, A([x0, y, zb0]), (x1 - x0) * ex, (zb1 - zb0) * ez, ey if left else -ey, s,
                            _LIFT_M, o, nom)
    # A-pillars: a strip on the cabin side at its front edge, from 30 cm above the shoulder to the roof (u) and 20 cm
    # back (v); the unit stands off the side (normal +-y) and looks diagonally forward (nominal yaw +-45 deg)
    left = name == "left-a-pillar"
    y = cy1 if left else cy0
    n = ey if left else -ey
    z0 = lz1 + 0.3                # above the belt line, so a lifted unit clears the lower body too
    o, nom = _orient(np.pi / 4 if left else -np.pi / 4, _YAW_RANGE)
    return MountSurface(name, A([cx1, y, z0]), (cz1 - 0.05 - z0) * ez, -0.2 * ex, n, s, _LIFT_M, o, nom)
