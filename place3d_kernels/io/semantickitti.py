"""SemanticKITTI sequences: reading (with label remapping), writing simulated frames, and P-SOGs built from a
sequence folder.

A sequence folder holds ``velodyne/NNNNNN.bin`` (float32 x, y, z, intensity per point, in the sensor
frame), ``labels/NNNNNN.label`` (uint32 per point; the class in the low 16 bits, the instance in the high
16) and ``poses.txt`` (one 3x4 row-major sensor-to-world matrix per frame, KITTI odometry style). The
writer stores Place3D class ids; ``place3d simulate`` also writes ``sequence.json`` (sensor, mount, label
scheme, condition, provenance), which the readers use, so its sequences read back with no options.

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
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from place3d_kernels.classes import CLASS_ID, N_CLASSES
from place3d_kernels.pointcloud import PointCloud
from place3d_kernels.pose import invert, pose_from_matrix, pose_matrix, transform_points

__all__ = ["SEMANTICKITTI_TO_PLACE3D", "remap_semantickitti", "read_semantickitti", "read_poses", "read_sequence",
           "psog_from_semantickitti", "write_semantickitti_sequence", "write_frame", "write_frame_bin",
           "frame_paths", "sensor_matrix", "pose_row", "atomic_write", "SEQUENCE_META", "prepare_sequence_folder",
           "read_sequence_metadata", "write_sequence_metadata", "sequence_spec"]

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
            ``write_semantickitti_sequence`` writes them; the low 16 bits are kept).
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


#: metadata file of a sequence written by ``place3d simulate`` (a manifest: spec + sha256 + provenance)
SEQUENCE_META = "sequence.json"
_DEFAULT_MOUNT = (0.0, 0.0, 2.5, 0.0, 0.0, 0.0)


def read_sequence_metadata(folder) -> dict | None:
    """The spec stored in ``<folder>/sequence.json`` (sensor, mount, labels, condition, scene), or None."""
    from place3d_kernels.manifest import read_manifest

    m = read_manifest(Path(folder) / SEQUENCE_META)
    return None if m is None else m.get("spec")


def sequence_spec(scene: dict, lidar, condition: dict | None = None, mount=_DEFAULT_MOUNT) -> dict:
    """What a simulated sequence depends on (its ``sequence.json`` spec): scene, sensor (name, elevations,
    azimuth count, range), mount, label scheme ("place3d"), condition. The backend is provenance only:
    the backends agree bit for bit."""
    return {"scene": dict(scene), "sensor": {"name": lidar.name, "elevations": np.asarray(lidar.elevations).tolist(),
                                             "azimuths": int(np.asarray(lidar.azimuths).size),
                                             "max_range": float(lidar.max_range)},
            "mount": [float(v) for v in mount], "labels": "place3d", "condition": condition}


def write_sequence_metadata(folder, spec: dict) -> Path:
    """Write ``<folder>/sequence.json``: ``spec`` (sensor, mount, label scheme, condition, ...) with its
    sha256 and the provenance block (version, command line, time)."""
    from place3d_kernels.manifest import write_manifest

    return write_manifest(Path(folder) / SEQUENCE_META, spec)


def prepare_sequence_folder(folder, spec: dict, overwrite: bool = False) -> Path:
    """Make ``folder`` ready for a sequence made with ``spec``, before any frame is simulated.

    A folder made with other settings (its ``sequence.json`` differs), or holding frames without a
    ``sequence.json``, is refused with ``ValueError`` naming the field, unless ``overwrite`` (which
    deletes ``velodyne/``, ``labels/``, ``poses.txt`` and ``sequence.json`` first).
    """
    import shutil

    from place3d_kernels.manifest import verify_manifest

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"output {folder} is a file; give a folder")
    if overwrite:
        for name in ("velodyne", "labels"):
            if (folder / name).is_dir():
                shutil.rmtree(folder / name)
        for name in ("poses.txt", SEQUENCE_META):
            (folder / name).unlink(missing_ok=True)
        return folder
    has_frames = (folder / "velodyne").is_dir() and any((folder / "velodyne").iterdir())
    if not verify_manifest(folder / SEQUENCE_META, spec, "sequence") and has_frames:
        raise ValueError(f"{folder} holds frames without {SEQUENCE_META} (settings unknown); use --overwrite "
                         f"to replace them or choose a fresh folder")
    return folder


def read_sequence(folder, labels: str | None = None, mount=None, frames=None, strict: bool = True):
    """Frames (``PointCloud``: world points, Place3D labels, intensity, ego pose) of a SemanticKITTI folder.

    ``velodyne/NNNNNN.bin`` + ``labels/NNNNNN.label`` + ``poses.txt`` (sensor-to-world 3x4 rows).
    ``mount`` is the sensor pose in the ego frame; the ego pose is sensor @ inverse(mount), so the ego
    frame has z = 0 on the ground. ``labels`` and ``mount`` default to the folder's ``sequence.json``
    (written by ``place3d simulate``: Place3D ids, its mount) and otherwise to SemanticKITTI ids and
    2.5 m up.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such sequence folder")
    meta = read_sequence_metadata(folder) or {}
    if labels is None:
        labels = meta.get("labels", "semantickitti")
    if mount is None:
        mount = meta.get("mount") or _DEFAULT_MOUNT
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
        out.append(PointCloud(world, lab, inten, T[:3, 3].copy(), ego_pose=ego))
    return out


def psog_from_semantickitti(folder, grid, frames_per_subset: int = 5, labels: str | None = None,
                            mount=None, frames=None, backend=None, strict: bool = True):
    """A P-SOG from a SemanticKITTI-layout sequence (see :func:`read_sequence` and ``PSOG.from_frames``;
    ``labels`` / ``mount`` default to the folder's ``sequence.json``)."""
    from place3d_kernels.sog import PSOG

    fr = read_sequence(folder, labels=labels, mount=mount, frames=frames, strict=strict)
    return PSOG.from_frames(fr, grid, frames_per_subset=frames_per_subset, backend=backend)


# ------------------------------------------------------------------------------ writing
def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename (``place3d_kernels.atomic``: readers
    never see half a file; a full disk leaves no temporary file and raises a one-line ``WriteError``)."""
    from place3d_kernels.atomic import atomic_write as write

    write(path, data)


def write_frame_bin(path_bin, path_label, points_sensor, intensity, labels) -> None:
    xyz = np.asarray(points_sensor, dtype=np.float32).reshape(-1, 3)
    arr = np.concatenate([xyz, np.asarray(intensity, np.float32).reshape(-1, 1)], axis=1)
    atomic_write(Path(path_bin), arr.astype(np.float32).tobytes())
    atomic_write(Path(path_label), np.asarray(labels, dtype=np.uint32).tobytes())


def frame_paths(folder, index: int) -> tuple[Path, Path]:
    """``velodyne/NNNNNN.bin`` and ``labels/NNNNNN.label`` of one frame of a sequence folder."""
    folder = Path(folder)
    return folder / "velodyne" / f"{index:06d}.bin", folder / "labels" / f"{index:06d}.label"


def sensor_matrix(frame) -> np.ndarray:
    """Sensor-to-world 4x4 matrix of a simulated frame: the ego rotation, the sweep's origin."""
    sensor = pose_matrix(frame.ego_pose)
    if frame.sweep_origin is not None:
        sensor[:3, 3] = frame.sweep_origin
    return sensor


def pose_row(sensor: np.ndarray) -> str:
    """One line of ``poses.txt`` (3x4 row-major, KITTI odometry style)."""
    return " ".join(f"{v:.9g}" for v in sensor[:3].reshape(-1))


def write_frame(folder, index: int, frame) -> np.ndarray:
    """Write one frame (points in the sensor frame) atomically; returns its sensor-to-world matrix."""
    sensor = sensor_matrix(frame)
    local = transform_points(invert(sensor), frame.points)
    inten = frame.intensity if frame.intensity is not None else np.zeros(len(local), np.float32)
    write_frame_bin(*frame_paths(folder, index), local, inten, frame.labels)
    return sensor


def write_semantickitti_sequence(frames, folder) -> Path:
    """Write simulated frames (``PointCloud`` frames with world points, ego pose and sensor origin) as a sequence.

    Reading back: ``read_semantickitti`` / ``read_sequence``.
    """
    folder = Path(folder)
    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(parents=True, exist_ok=True)
    rows = [pose_row(write_frame(folder, i, f)) for i, f in enumerate(frames)]
    # frames of an earlier, longer run beyond the new ones would otherwise sit beside a shorter poses.txt
    for sub, ext in (("velodyne", ".bin"), ("labels", ".label")):
        for p in (folder / sub).glob(f"*{ext}"):
            if re.fullmatch(r"\d+", p.stem) and int(p.stem) >= len(rows):
                p.unlink()
    atomic_write(folder / "poses.txt", ("\n".join(rows) + "\n").encode())
    return folder
