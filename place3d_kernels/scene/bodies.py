"""Low-poly labelled bodies shared by the scene builders: vehicles, pedestrians and unit templates."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from place3d_kernels.classes import CLASS_ID
from place3d_kernels.mesh import Mesh
from place3d_kernels.scene.primitives import MeshBuilder, boxes, icosphere, prism

__all__ = ["vehicle_mesh", "vehicle_body", "Body", "pedestrian_mesh", "template", "EGO_LENGTH", "EGO_WIDTH"]

VEHICLE, PEDESTRIAN = CLASS_ID["vehicle"], CLASS_ID["pedestrian"]

#: footprint of the ego vehicle (not part of the scene), metres
EGO_LENGTH, EGO_WIDTH = 4.6, 2.0

_TEMPLATES: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def template(name: str):
    """A cached unit solid (vertices, faces): "ico0"/"ico1" icospheres, "prismN" an N-sided unit prism.

    Raises:
        KeyError: any other name.
    """
    if name not in _TEMPLATES:
        if name == "ico1":
            _TEMPLATES[name] = icosphere(1)
        elif name == "ico0":
            _TEMPLATES[name] = icosphere(0)
        elif name.startswith("prism"):
            n = int(name[5:])
            _TEMPLATES[name] = prism(n, 1.0, 0.0, 1.0, phase=math.pi / n)
        else:
            raise KeyError(name)
    return _TEMPLATES[name]


_WHEEL_PARTS: dict = {}


def _wheel_parts(r, w, n):
    """The unit 6-sided prism scaled and turned into a wheel of radius r and width w (its x, -z and y + r
    columns) and the faces of ``n`` such wheels, made once per (r, w, n) (a town's vehicles have four radii);
    read-only."""
    key = (float(r), float(w), int(n))
    parts = _WHEEL_PARTS.get(key)
    if parts is None:
        v_unit, f_unit = template("prism6")
        v = v_unit.copy()
        v[:, :2] *= r
        v[:, 2] = (v[:, 2] - 0.5) * w
        faces = (np.asarray(f_unit)[None] + len(v) * np.arange(n)[:, None, None]).reshape(-1, 3)
        parts = (v[None, :, 0], -v[None, :, 2], v[None, :, 1] + r, faces)
        for a in parts:
            a.flags.writeable = False
        _WHEEL_PARTS[key] = parts
    return parts


def _wheels(xs, ys, r, w):
    """Wheels at (xs[i], ys[i]): the unit 6-sided prism (axis z) turned to axis y, radius r, width w, centred
    (x, y, r), as one part: their vertices wheel after wheel and each wheel's faces offset to its vertices
    (what adding them one by one to a ``MeshBuilder`` concatenates, element for element; the faces shared)."""
    # rotation about x by +90 deg: (x, y, z) -> (x, -z, y)
    xs, ys = np.asarray(xs, float)[:, None], np.asarray(ys, float)[:, None]
    vx, vy, vz, faces = _wheel_parts(r, w, len(xs))
    out = np.stack([vx + xs, vy + ys, np.broadcast_to(vz, (len(xs), vz.shape[1]))], 2)
    return out.reshape(-1, 3), faces


class Body(NamedTuple):
    """A solid's arrays as a ``MeshBuilder`` makes them, not checked as a ``Mesh``: what a builder copies
    into a larger mesh (parked cars are thousands of these a town; a ``Mesh`` each would check every one)."""

    vertices: np.ndarray
    faces: np.ndarray
    labels: np.ndarray

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3): the lowest and highest vertex coordinates, as ``Mesh.bounds``."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])


def vehicle_mesh(rng: np.random.Generator, kind: str | None = None) -> tuple[Mesh, str]:
    """A low-poly vehicle in its own frame (x forward, z up, origin on the ground under its centre)."""
    body, kind = vehicle_body(rng, kind)
    return Mesh(*body), kind


def vehicle_body(rng: np.random.Generator, kind: str | None = None) -> tuple[Body, str]:
    """``vehicle_mesh``'s vehicle as a ``Body`` (the same draws from ``rng``, the same arrays)."""
    if kind is None:
        kind = rng.choice(["car", "car", "car", "car", "car", "car", "van", "van", "truck", "bus"])
    boxes_at: list = []      # (centre, size) of the body's boxes, as MeshBuilder.add_box keeps them
    if kind == "car":
        L, W, H = rng.uniform(4.0, 4.9), rng.uniform(1.75, 1.95), rng.uniform(1.4, 1.6)
        _box(boxes_at, 0, 0, 0.3, L, W, 0.65)
        cab = L * rng.uniform(0.45, 0.55)
        _box(boxes_at, -0.05 * L, 0, 0.95, cab, W - 0.14, H - 0.95)
        r, ax = 0.32, L / 2 - 0.8
    elif kind == "van":
        L, W, H = rng.uniform(4.8, 5.6), 2.0, rng.uniform(1.9, 2.4)
        _box(boxes_at, 0, 0, 0.35, L, W, 0.9)
        _box(boxes_at, -0.1, 0, 1.25, L - 0.8, W - 0.06, H - 1.25)
        r, ax = 0.35, L / 2 - 0.85
    elif kind == "truck":
        L, W, H = rng.uniform(6.5, 8.0), 2.3, rng.uniform(2.8, 3.4)
        _box(boxes_at, L / 2 - 1.0, 0, 0.45, 2.0, W, 2.1)            # cab
        _box(boxes_at, -0.9, 0, 0.6, L - 2.2, W, H - 0.6)            # cargo box
        r, ax = 0.45, L / 2 - 1.1
    elif kind == "bus":
        L, W, H = rng.uniform(10.0, 12.0), 2.5, rng.uniform(2.9, 3.2)
        _box(boxes_at, 0, 0, 0.35, L, W, H - 0.35)
        r, ax = 0.5, L / 2 - 2.2
    else:
        raise ValueError(f"unknown vehicle kind {kind!r}; use car, van, truck or bus")
    y = W / 2 - 0.12
    # MeshBuilder's arrays of the wheels added as a part, then the boxes, without its bookkeeping
    v, f = _wheels((-ax, -ax, ax, ax), (-y, y, -y, y), r, 0.24)
    c, sz = zip(*boxes_at)
    bv, bf = boxes(np.array(c), np.array(sz), np.zeros(len(c), int))
    labels = np.full(len(f) + len(bf), VEHICLE, dtype=np.int32)
    return Body(np.concatenate([v, bv]), np.concatenate([f, bf + len(v)]), labels), str(kind)


def _box(boxes_at: list, cx, cy, z0, sx, sy, sz) -> None:
    # MeshBuilder.add_box's centre and size of an unturned box standing on z0
    boxes_at.append(((cx, cy, z0 + sz / 2), (sx, sy, sz)))


def pedestrian_mesh(rng: np.random.Generator) -> Mesh:
    """A low-poly pedestrian (label 4), origin on the ground between the feet, facing +x."""
    h = rng.uniform(1.55, 1.92)
    b = MeshBuilder()
    for sy in (-0.09, 0.09):
        b.add_box(0, sy, 0, 0.14, 0.14, 0.47 * h, 0, PEDESTRIAN)                 # legs
    b.add_box(0, 0, 0.47 * h, 0.22, 0.38, 0.35 * h, 0, PEDESTRIAN)              # torso
    for sy in (-0.245, 0.245):
        b.add_box(0, sy, 0.48 * h, 0.1, 0.09, 0.33 * h, 0, PEDESTRIAN)          # arms
    hv, hf = template("ico0")
    b.add_moved(hv, hf, PEDESTRIAN, 0, 0, 0.9 * h, scale=0.075 * h)        # head
    return b.build()
