"""CARLA semantic LiDAR (``sensor.lidar.ray_cast_semantic``; ``save_to_disk`` writes PLY with float x, y, z,
CosAngle and uint ObjIdx, ObjTag per point). ``tags="legacy"`` (CARLA <= 0.9.13, the version family
Place3D used): tags 0..12 are the Place3D ids, 13 (sky) -> 0, 14..22 -> 13..21. ``tags="cityscapes"``
(CARLA >= 0.9.14, Cityscapes order): remapped by ``CARLA_CITYSCAPES_TO_PLACE3D``.

CARLA writes points in the sensor's left-handed frame (x forward, y right, z up); ``read_carla_ply``
returns them in this package's sensor frame (y left): y negated (``place3d_kernels.carla_frame``).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from place3d_kernels.carla_frame import points_from_carla
from place3d_kernels.classes import CLASS_ID

__all__ = ["CARLA_LEGACY_TO_PLACE3D", "CARLA_CITYSCAPES_TO_PLACE3D", "read_carla_ply", "CarlaCloud"]

C = CLASS_ID
CARLA_LEGACY_TO_PLACE3D = np.array([t if t <= 12 else (0 if t == 13 else t - 1) for t in range(23)], np.int32)
#: CARLA >= 0.9.14 tags: 0 unlabeled, 1 roads, 2 sidewalks, 3 building, 4 wall, 5 fence, 6 pole, 7 traffic
#: light, 8 traffic sign, 9 vegetation, 10 terrain, 11 sky, 12 pedestrian, 13 rider, 14 car, 15 truck,
#: 16 bus, 17 train, 18 motorcycle, 19 bicycle, 20 static, 21 dynamic, 22 other, 23 water, 24 road line,
#: 25 ground, 26 bridge, 27 rail track, 28 guard rail
CARLA_CITYSCAPES_TO_PLACE3D = np.array([
    0, C["road"], C["sidewalk"], C["building"], C["wall"], C["fence"], C["pole"], C["traffic light"],
    C["traffic sign"], C["vegetation"], C["terrain"], 0, C["pedestrian"], C["pedestrian"], C["vehicle"],
    C["vehicle"], C["vehicle"], C["vehicle"], C["vehicle"], C["vehicle"], C["static"], C["dynamic"], C["other"],
    C["water"], C["road line"], C["ground"], C["bridge"], C["rail track"], C["guard rail"]], np.int32)


class CarlaCloud(NamedTuple):
    points: np.ndarray      # (N, 3) float64, this package's sensor frame (y left; CARLA's y negated)
    labels: np.ndarray      # (N,) int32 Place3D classes
    cos_angle: np.ndarray   # (N,) float32
    object_id: np.ndarray   # (N,) uint32 (ObjIdx)
    tag: np.ndarray         # (N,) uint32 raw CARLA tag (ObjTag)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_carla_ply(path, tags: str = "legacy") -> CarlaCloud:
    """Read a CARLA semantic-LiDAR PLY (ascii or binary) into points, Place3D labels and raw fields.

    Points come back in this package's sensor frame (x forward, y LEFT, z up): CARLA's y is negated
    (``carla_frame.points_from_carla``; ``carla_frame.points_to_carla`` gives CARLA's coordinates back).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such PLY file")
    if tags not in ("legacy", "cityscapes"):
        raise ValueError(f"tags must be 'legacy' (CARLA <= 0.9.13) or 'cityscapes' (>= 0.9.14), got {tags!r}")
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    nl = data.find(b"\n", end)
    header = data[:end].decode("ascii", "replace").splitlines()
    body = data[nl + 1:]
    fmt, n, props, in_vertex, seen_vertex = None, None, [], False, False
    for line in header:
        w = line.split()
        if not w:
            continue
        if w[0] == "format":
            fmt = w[1] if len(w) > 1 else None
        elif w[0] == "element":
            in_vertex = len(w) == 3 and w[1] == "vertex"
            if in_vertex:
                seen_vertex = True
                try:
                    n = int(w[2])
                except ValueError:
                    raise ValueError(f"{path}: bad vertex count {w[2]!r}") from None
            elif seen_vertex and n:
                pass  # later elements (none in CARLA files) are ignored
        elif w[0] == "property" and in_vertex:
            if len(w) != 3 or w[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unsupported vertex property line {line.strip()!r}")
            props.append((w[2], _PLY_TYPES[w[1]]))
    if n is None:
        raise ValueError(f"{path}: no 'element vertex' in the header")
    names = [p[0] for p in props]
    need = ("x", "y", "z", "ObjTag")
    missing = [k for k in need if k not in names]
    if missing:
        raise ValueError(f"{path}: vertex properties {missing} missing (have {names}); expected CARLA semantic "
                         "LiDAR fields x, y, z, CosAngle, ObjIdx, ObjTag")
    if fmt == "ascii":
        try:
            rows = np.loadtxt(body.decode("ascii").splitlines()[:n], dtype=np.float64, ndmin=2)
        except ValueError as e:
            raise ValueError(f"{path}: bad ASCII vertex data ({e})") from None
        if rows.shape != (n, len(props)) and not (n == 0):
            raise ValueError(f"{path}: expected {n} rows of {len(props)} values, got {rows.shape}")
        col = {k: rows[:, i] for i, k in enumerate(names)} if n else {k: np.zeros(0) for k in names}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        e = "<" if fmt == "binary_little_endian" else ">"
        dt = np.dtype([(k, e + t) for k, t in props])
        if len(body) < n * dt.itemsize:
            raise ValueError(f"{path}: truncated: {len(body)} bytes of vertex data for {n} x {dt.itemsize}")
        arr = np.frombuffer(body, dtype=dt, count=n)
        col = {k: arr[k] for k in names}
    else:
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    pts = points_from_carla(np.stack([col["x"], col["y"], col["z"]], 1))
    tag = np.asarray(col["ObjTag"]).astype(np.int64)
    lut = CARLA_LEGACY_TO_PLACE3D if tags == "legacy" else CARLA_CITYSCAPES_TO_PLACE3D
    if tag.size and (tag.min() < 0 or tag.max() >= len(lut)):
        raise ValueError(f"{path}: ObjTag {int(tag.max())} outside the {tags} CARLA tag table (0..{len(lut) - 1})")
    lab = lut[tag] if tag.size else np.zeros(0, np.int32)
    cos = np.asarray(col.get("CosAngle", np.zeros(n)), np.float32)
    obj = np.asarray(col.get("ObjIdx", np.zeros(n)), np.float64).astype(np.uint32)
    return CarlaCloud(pts, lab.astype(np.int32), cos, obj, tag.astype(np.uint32))
