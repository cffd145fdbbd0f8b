"""Point-cloud formats: SemanticKITTI sequences with label remapping, CARLA semantic-LiDAR PLY, and P-SOGs
built from a SemanticKITTI-layout folder.

SemanticKITTI label ids -> Place3D classes (``SEMANTICKITTI_TO_PLACE3D``; the low 16 bits of each
``.label`` value are the class, the high 16 bits the instance and are dropped):

==========================================  =====================================================
SemanticKITTI                               Place3D
==========================================  =====================================================
0 unlabeled, 1 outlier                      0 unlabeled
10 car, 13 bus, 16 on-rails, 18 truck,      10 vehicle
20 other-vehicle
11 bicycle, 15 motorcycle, 31 bicyclist,    10 vehicle (CARLA spawns a two-wheeler and its rider as
32 motorcyclist                             one vehicle actor; the Place3D classes have no rider)
30 person                                   4 pedestrian
40 road, 44 parking                         7 road (Place3D has no parking class)
48 sidewalk                                 8 sidewalk
49 other-ground                             13 ground
50 building                                 1 building
51 fence                                    2 fence
52 other-structure                          18 static
60 lane-marking                             6 road line
70 vegetation, 71 trunk                     9 vegetation
72 terrain                                  21 terrain
80 pole                                     5 pole
81 traffic-sign                             12 traffic sign
99 other-object                             3 other
252 moving-car, 253 moving-bicyclist,       10 vehicle
255 moving-motorcyclist, 256 moving-on-
rails, 257 moving-bus, 258 moving-truck,
259 moving-other-vehicle
254 moving-person                           4 pedestrian
==========================================  =====================================================

Label ids outside the table raise ValueError (``strict=True``, default) or become 0.

CARLA semantic LiDAR (``sensor.lidar.ray_cast_semantic``; ``save_to_disk`` writes PLY with float x, y, z,
CosAngle and uint ObjIdx, ObjTag per point). ``tags="legacy"`` (CARLA <= 0.9.13, the version family
Place3D used): tags 0..12 are the Place3D ids, 13 (sky) -> 0, 14..22 -> 13..21. ``tags="cityscapes"``
(CARLA >= 0.9.14, Cityscapes order): remapped by ``CARLA_CITYSCAPES_TO_PLACE3D``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from place3d_kernels.classes import CLASS_ID, N_CLASSES
from place3d_kernels.pose import invert, pose_from_matrix, pose_matrix, transform_points

__all__ = ["SEMANTICKITTI_TO_PLACE3D", "CARLA_LEGACY_TO_PLACE3D", "CARLA_CITYSCAPES_TO_PLACE3D", "remap_semantickitti",
           "read_semantickitti", "read_carla_ply", "CarlaCloud", "read_poses", "read_sequence",
           "psog_from_semantickitti"]

C = CLASS_ID
SEMANTICKITTI_TO_PLACE3D: dict[int, int] = {
    0: 0, 1: 0,
    10: C["vehicle"], 11: C["vehicle"], 13: C["vehicle"], 15: C["vehicle"], 16: C["vehicle"], 18: C["vehicle"],
    20: C["vehicle"], 30: C["pedestrian"], 31: C["vehicle"], 32: C["vehicle"],
    40: C["road"], 44: C["road"], 48: C["sidewalk"], 49: C["ground"],
    50: C["building"], 51: C["fence"], 52: C["static"], 60: C["road line"],
    70: C["vegetation"], 71: C["vegetation"], 72: C["terrain"], 80: C["pole"], 81: C["traffic sign"],
    99: C["other"],
    252: C["vehicle"], 253: C["vehicle"], 254: C["pedestrian"], 255: C["vehicle"], 256: C["vehicle"],
    257: C["vehicle"], 258: C["vehicle"], 259: C["vehicle"],
}
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

_SK_LUT = np.full(260, -1, np.int32)
for _k, _v in SEMANTICKITTI_TO_PLACE3D.items():
    _SK_LUT[_k] = _v


def remap_semantickitti(raw, strict: bool = True, where: str = "") -> np.ndarray:
    """Place3D classes (int32) from raw SemanticKITTI ``.label`` values (instance bits dropped)."""
    sem = (np.asarray(raw).astype(np.uint32) & 0xFFFF).astype(np.int64)
    out = np.full(sem.shape, -1, np.int32)
    ok = sem < len(_SK_LUT)
    out[ok] = _SK_LUT[sem[ok]]
    bad = out < 0
    if bad.any():
        if strict:
            ids = sorted(set(sem[bad].tolist()))[:10]
            raise ValueError(f"{where}SemanticKITTI label ids {ids} are not in the table "
                             f"(SEMANTICKITTI_TO_PLACE3D); pass strict=False to map them to 0")
        out[bad] = 0
    return out


def read_semantickitti(path_bin, path_label=None, labels: str = "semantickitti", strict: bool = True):
    """One frame: (N, 3) float32 points (sensor frame), (N,) float32 intensity, (N,) int32 Place3D labels.

    Args:
        labels: "semantickitti" (remap SemanticKITTI ids) or "place3d" (ids already Place3D classes, as
            ``place3d_kernels.io.write_semantickitti_sequence`` writes them; the low 16 bits are kept).
    Returns labels None when ``path_label`` is None.
    """
    if labels not in ("semantickitti", "place3d"):
        raise ValueError(f"labels must be 'semantickitti' or 'place3d', got {labels!r}")
    path_bin = Path(path_bin)
    if not path_bin.is_file():
        raise ValueError(f"{path_bin}: no such point file")
    raw = np.fromfile(path_bin, dtype=np.uint8)
    if raw.size % 16:
        raise ValueError(f"{path_bin}: size {raw.size} bytes is not a whole number of 16-byte (x, y, z, i) float32 rows")
    pts = raw.view(np.float32).reshape(-1, 4)
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path_bin}: holds non-finite values")
    lab = None
    if path_label is not None:
        path_label = Path(path_label)
        if not path_label.is_file():
            raise ValueError(f"{path_label}: no such label file")
        rawl = np.fromfile(path_label, dtype=np.uint8)
        if rawl.size % 4:
            raise ValueError(f"{path_label}: size {rawl.size} bytes is not a whole number of uint32 labels")
        rawl = rawl.view(np.uint32)
        if len(rawl) != len(pts):
            raise ValueError(f"{path_label}: {len(rawl)} labels for {len(pts)} points in {path_bin}")
        if labels == "semantickitti":
            lab = remap_semantickitti(rawl, strict, f"{path_label}: ")
        else:
            lab = (rawl & 0xFFFF).astype(np.int32)
            if lab.size and lab.max() >= N_CLASSES:
                raise ValueError(f"{path_label}: Place3D class ids must be < {N_CLASSES}, got {int(lab.max())} "
                                 f"(SemanticKITTI ids? pass labels='semantickitti')")
    return pts[:, :3], pts[:, 3], lab


class CarlaCloud(NamedTuple):
    points: np.ndarray      # (N, 3) float64, sensor frame
    labels: np.ndarray      # (N,) int32 Place3D classes
    cos_angle: np.ndarray   # (N,) float32
    object_id: np.ndarray   # (N,) uint32 (ObjIdx)
    tag: np.ndarray         # (N,) uint32 raw CARLA tag (ObjTag)


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_carla_ply(path, tags: str = "legacy") -> CarlaCloud:
    """Read a CARLA semantic-LiDAR PLY (ascii or binary) into points, Place3D labels and raw fields."""
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
    pts = np.stack([col["x"], col["y"], col["z"]], 1).astype(np.float64)
    tag = np.asarray(col["ObjTag"]).astype(np.int64)
    lut = CARLA_LEGACY_TO_PLACE3D if tags == "legacy" else CARLA_CITYSCAPES_TO_PLACE3D
    if tag.size and (tag.min() < 0 or tag.max() >= len(lut)):
        raise ValueError(f"{path}: ObjTag {int(tag.max())} outside the {tags} CARLA tag table (0..{len(lut) - 1})")
    lab = lut[tag] if tag.size else np.zeros(0, np.int32)
    cos = np.asarray(col.get("CosAngle", np.zeros(n)), np.float32)
    obj = np.asarray(col.get("ObjIdx", np.zeros(n)), np.float64).astype(np.uint32)
    return CarlaCloud(pts, lab.astype(np.int32), cos, obj, tag.astype(np.uint32))


def read_poses(path) -> np.ndarray:
    """(T, 4, 4) sensor-to-world matrices from a KITTI odometry ``poses.txt`` (12 numbers a row)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such poses file")
    rows = []
    for i, line in enumerate(path.read_text().splitlines()):
        if not line.strip():
            continue
        w = line.split()
        if len(w) != 12:
            raise ValueError(f"{path}: line {i + 1} has {len(w)} numbers, expected 12 (a 3x4 row-major matrix)")
        try:
            v = np.array([float(x) for x in w])
        except ValueError:
            raise ValueError(f"{path}: line {i + 1} holds a non-number") from None
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{path}: line {i + 1} holds a non-finite number")
        T = np.eye(4)
        T[:3] = v.reshape(3, 4)
        rows.append(T)
    if not rows:
        raise ValueError(f"{path}: no poses")
    return np.stack(rows)




def read_sequence(folder, labels: str = "semantickitti", mount=(0.0, 0.0, 2.5, 0.0, 0.0, 0.0), frames=None,
                  strict: bool = True):
    """Frames (world points, Place3D labels, ego pose) of a SemanticKITTI-layout folder.

    ``velodyne/NNNNNN.bin`` + ``labels/NNNNNN.label`` + ``poses.txt`` (sensor-to-world 3x4 rows).
    ``mount`` is the sensor pose in the ego frame (default: 2.5 m up, as ``simulate`` mounts it); the ego
    pose is sensor @ inverse(mount), so the ego frame has z = 0 on the ground.
    """
    from place3d_kernels.sog import Frame

    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such sequence folder")
    vel = folder / "velodyne"
    if not vel.is_dir():
        raise ValueError(f"{folder}: no velodyne/ folder")
    bins = sorted(p for p in vel.glob("*.bin") if re.fullmatch(r"\d+", p.stem))
    if not bins:
        raise ValueError(f"{vel}: no NNNNNN.bin frames")
    poses = read_poses(folder / "poses.txt")
    if len(poses) < len(bins):
        raise ValueError(f"{folder / 'poses.txt'}: {len(poses)} poses for {len(bins)} frames")
    mount_inv = invert(pose_matrix(np.asarray(mount, np.float64)))
    idx = range(len(bins)) if frames is None else frames
    out = []
    for i in idx:
        b = bins[i]
        lab_path = folder / "labels" / f"{b.stem}.label"
        if not lab_path.is_file():
            raise ValueError(f"{lab_path}: missing label file for {b}")
        pts, inten, lab = read_semantickitti(b, lab_path, labels=labels, strict=strict)
        T = poses[int(b.stem)] if int(b.stem) < len(poses) else poses[i]
        world = transform_points(T, pts.astype(np.float64))
        ego = pose_from_matrix(T @ mount_inv)
        out.append(Frame(world, lab, ego, inten, T[:3, 3].copy()))
    return out


def psog_from_semantickitti(folder, grid, frames_per_subset: int = 5, labels: str = "semantickitti",
                            mount=(0.0, 0.0, 2.5, 0.0, 0.0, 0.0), frames=None, backend=None, strict: bool = True):
    """A P-SOG from a SemanticKITTI-layout sequence (see :func:`read_sequence` and ``PSOG.from_frames``)."""
    from place3d_kernels.sog import PSOG

    fr = read_sequence(folder, labels=labels, mount=mount, frames=frames, strict=strict)
    return PSOG.from_frames(fr, grid, frames_per_subset=frames_per_subset, backend=backend)
