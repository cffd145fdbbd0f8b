"""Per-rig datasets: merged multi-LiDAR semantic point clouds per frame, in the ego frame, as SemanticKITTI
sequences.

A *rig* is a ``Placement`` (L poses in the ego frame) of one ``LidarModel``. A *drive* is one route seed
on one scene (``pooled.Drive``: 'town' or 'opendrive:...', seed, frames); the seed picks the route and the
generated roadside content and traffic (for the embedded town, the whole town). Each LiDAR of the rig is
simulated along the drive (``simulate.simulate`` with the LiDAR's pose as mount) and its returns are moved
into the ego frame of the frame and merged: the paper's setting (Li et al., NeurIPS 2024, Sec. 4: the
point clouds of the L LiDARs merged in the ego frame).

Layout (``place3d_kernels.io.semantickitti``), one sequence folder per (rig, drive)::

    <root>/<rig>/sequences/<scene>-r<seed>/velodyne/NNNNNN.bin    float32 x, y, z, intensity (ego frame)
                                          /labels/NNNNNN.label    uint32 Place3D class (low 16 bits)
                                          /poses.txt              ego-to-world 3x4 rows
                                          /sequence.json          manifest: the spec below, written last

The "sensor" of these sequences is the ego frame itself, so ``sequence.json`` says ``mount`` = zeros and
``labels`` = "place3d", and ``io.read_sequence`` reads them back as world frames with no options. A
sequence whose manifest matches its spec is finished and skipped (resume); a folder made with other
settings is refused (``ValueError`` naming the field) unless ``overwrite``.

Splits (``Splits``): training drives are ``towns`` x ``train_routes``; test drives are ``towns`` x
``test_routes`` (route seeds disjoint from the training ones); held-out drives are ``heldout_towns`` x
``test_routes`` (towns never trained on). Disjoint seeds are not disjoint streets on a fixed road network
(a CARLA map): ``route_overlap`` says what share of the test frames lie near a training frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from place3d_kernels.pooled import Drive

__all__ = ["Rig", "Splits", "scene_name", "sequence_folder", "sequence_spec", "simulate_rig", "write_drive",
           "build_datasets", "read_frames", "route_overlap", "EGO_MOUNT"]

#: the merged clouds are stored in the ego frame: the sequences' "sensor" is the ego frame itself
EGO_MOUNT = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Rig:
    """A rig: ``name``, its (L, 6) ego-frame poses (a tuple of tuples) and the LiDAR model's name."""

    name: str
    poses: tuple
    lidar: str = "place3d_16ch"

    @classmethod
    def load(cls, placement: str, lidar: str = "place3d_16ch") -> "Rig":
        """From a shipped placement name (``pyramid``) or a placement TOML path (an optimiser's winner)."""
        from place3d_kernels.placement import Placement

        p = Placement.load(placement)
        name = p.name or Path(placement).stem
        if Path(placement).suffix == ".toml":
            name = Path(placement).stem     # file names are what a user passed; two winners may share a name
        return cls(name, tuple(tuple(float(v) for v in row) for row in p.poses), lidar)

    @property
    def pose_array(self) -> np.ndarray:
        return np.asarray(self.poses, dtype=np.float64)

    def to_dict(self) -> dict:
        return {"name": self.name, "poses": [list(r) for r in self.poses], "lidar": self.lidar}


def scene_name(town: str) -> str:
    """A scene string for ``Drive``: 'town', 'opendrive:...' as given, a shipped CARLA map by name
    ('Town01' -> 'opendrive:Town01'), or an .xodr path."""
    from place3d_kernels.data import CARLA_TOWNS

    if town == "town" or town.startswith("opendrive:"):
        return town
    if town in CARLA_TOWNS:
        return f"opendrive:{town}"
    if town.endswith(".xodr"):
        if not Path(town).is_file():
            raise FileNotFoundError(f"OpenDRIVE file {town} not found")
        return f"opendrive:{Path(town).resolve()}"
    raise ValueError(f"unknown town {town!r}: use 'town' (the embedded one), a CARLA map ({', '.join(CARLA_TOWNS)}) "
                     f"or an .xodr path")


def _town_label(scene: str) -> str:
    return scene if scene == "town" else Path(scene.split(":", 1)[1]).stem


@dataclass(frozen=True)
class Splits:
    """Which drives train and which test. Route seeds of training and test must not meet; held-out towns
    must not be training towns."""

    towns: tuple
    train_routes: tuple
    test_routes: tuple
    frames: int
    heldout_towns: tuple = ()

    def __post_init__(self):
        both = set(self.train_routes) & set(self.test_routes)
        if both:
            raise ValueError(f"training and test routes must be disjoint; both have seeds {sorted(both)}")
        shared = {scene_name(t) for t in self.towns} & {scene_name(t) for t in self.heldout_towns}
        if shared:
            raise ValueError(f"held-out towns must not be training towns: {sorted(shared)}")
        if not self.towns or not self.train_routes or not self.test_routes:
            raise ValueError("give at least one town, one training route and one test route")
        if self.frames < 1:
            raise ValueError(f"frames must be >= 1, got {self.frames}")

    def drives(self, split: str) -> list[Drive]:
        """'train', 'test' or 'heldout' drives, town by town, route by route."""
        towns, routes = {"train": (self.towns, self.train_routes), "test": (self.towns, self.test_routes),
                         "heldout": (self.heldout_towns, self.test_routes)}[split]
        return [Drive(scene_name(t), int(r), int(self.frames)) for t in towns for r in routes]

    def all_drives(self) -> list[Drive]:
        return self.drives("train") + self.drives("test") + self.drives("heldout")

    def to_dict(self) -> dict:
        return {"towns": [scene_name(t) for t in self.towns], "heldout_towns": [scene_name(t) for t in self.heldout_towns],
                "train_routes": [int(r) for r in self.train_routes], "test_routes": [int(r) for r in self.test_routes],
                "frames": int(self.frames)}


def sequence_folder(root, rig: Rig, drive: Drive) -> Path:
    return Path(root) / rig.name / "sequences" / f"{_town_label(drive.scene)}-r{drive.seed}"


def sequence_spec(rig: Rig, drive: Drive) -> dict:
    """What a sequence depends on (its ``sequence.json`` spec). The backend is provenance only: the
    backends agree bit for bit on ray casts."""
    return {"scene": drive.spec().to_dict(), "rig": rig.to_dict(), "frame": "ego", "mount": list(EGO_MOUNT),
            "labels": "place3d", "merged": "multi-lidar"}


def simulate_rig(scene, rig: Rig, backend=None, frames=None) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per frame of ``scene``: (N, 3) float32 ego-frame points, (N,) int32 labels, (N,) float32 intensity
    of every LiDAR of ``rig`` merged (LiDAR by LiDAR, in the rig's order)."""
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.pose import invert, pose_matrix, transform_points
    from place3d_kernels.simulate import simulate

    lidar = LidarModel.load(rig.lidar)
    idx = list(range(scene.n_frames) if frames is None else frames)
    per_lidar = [simulate(scene, lidar, mount=pose, frames=idx, backend=backend) for pose in rig.pose_array]
    out = []
    for j, f in enumerate(idx):
        to_ego = invert(pose_matrix(scene.ego_poses[f]))
        pts = np.concatenate([transform_points(to_ego, fr[j].points) for fr in per_lidar]).astype(np.float32)
        lab = np.concatenate([fr[j].labels for fr in per_lidar]).astype(np.int32)
        inten = np.concatenate([fr[j].intensity for fr in per_lidar]).astype(np.float32)
        out.append((pts, lab, inten))
    return out


def _write_sequence(folder: Path, scene, frames) -> None:
    from place3d_kernels.io.semantickitti import atomic_write, frame_paths, pose_row, write_frame_bin
    from place3d_kernels.pose import pose_matrix

    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(parents=True, exist_ok=True)
    rows = []
    for i, (pts, lab, inten) in enumerate(frames):
        write_frame_bin(*frame_paths(folder, i), pts, inten, lab)
        rows.append(pose_row(pose_matrix(scene.ego_poses[i])))
    atomic_write(folder / "poses.txt", ("\n".join(rows) + "\n").encode())


def write_drive(root, rigs, drive: Drive, backend=None, overwrite: bool = False) -> dict:
    """Write the sequences of ``drive`` for every rig still missing it; the scene is built once (and only
    if some rig needs it). Returns {"written": [rig names], "skipped": [...], "seconds": float}."""
    from place3d_kernels.manifest import verify_manifest, write_manifest
    from place3d_kernels.io.semantickitti import SEQUENCE_META

    todo, skipped = [], []
    for rig in rigs:
        folder = sequence_folder(root, rig, drive)
        spec = sequence_spec(rig, drive)
        if overwrite and folder.is_dir():
            import shutil

            shutil.rmtree(folder)
        # a finished sequence has its manifest (written last); one made with other settings raises here
        if verify_manifest(folder / SEQUENCE_META, spec, "dataset sequence"):
            skipped.append(rig.name)
        else:
            todo.append((rig, folder, spec))
    t0 = time.perf_counter()
    if todo:
        scene = drive.build()
        for rig, folder, spec in todo:
            _write_sequence(folder, scene, simulate_rig(scene, rig, backend))
            write_manifest(folder / SEQUENCE_META, spec)
    return {"written": [r.name for r, _, _ in todo], "skipped": skipped, "seconds": time.perf_counter() - t0}


def _drive_task(t):
    """One drive in a worker: its sequences for every rig, then (``settings`` given) its P-SOG record from
    the scene still in memory."""
    root, rigs, drive, backend, overwrite, settings = t
    res = write_drive(root, rigs, drive, backend, overwrite)
    record = None
    if settings is not None:
        from place3d_kernels.pooled import drive_record

        t0 = time.perf_counter()
        record = drive_record(drive, settings)
        res["psog_seconds"] = time.perf_counter() - t0
    return res, record


def build_datasets(root, rigs, splits: Splits, backend=None, overwrite: bool = False, progress: bool = False,
                   psog=None, workers: int = 0) -> tuple[dict, list]:
    """Every (rig, drive) sequence of ``splits``, drive by drive (a scene is built once for all rigs).

    Args:
        psog: optional ``pooled.PoolSettings``: the training drives' P-SOG records are built too, each right
            after its drive's sequences, from the scene still in memory (``pooled.drive_record``; cached on
            disk by its inputs).
        workers: drives run in this many spawned processes at once (0: here, one after the other). Scene
            building and the simulation's per-frame host work are single-threaded Python, so on a GPU host
            processes overlap them; each process opens its own device context.
    Returns: ({"written", "skipped", "seconds", "psog_seconds"} totals, the training drives' records in drive
        order, empty without ``psog``).
    """
    drives = splits.all_drives()
    train = {d.label for d in splits.drives("train")}
    tasks = [(str(root), list(rigs), d, backend, overwrite, psog if psog is not None and d.label in train else None)
             for d in drives]
    if workers and workers > 0:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(min(workers, len(tasks)), mp_context=mp.get_context("spawn"))
        results = pool.map(_drive_task, tasks)
    else:
        pool = None
        results = map(_drive_task, tasks)
    if progress:
        from tqdm import tqdm

        results = tqdm(results, total=len(tasks), desc="datasets", unit="drive", leave=False)
    tot = {"written": 0, "skipped": 0, "seconds": 0.0, "psog_seconds": 0.0}
    records = []
    try:
        for r, rec in results:
            tot["written"] += len(r["written"])
            tot["skipped"] += len(r["skipped"])
            tot["seconds"] += r["seconds"]
            tot["psog_seconds"] += r.get("psog_seconds", 0.0)
            if rec is not None:
                records.append(rec)
    finally:
        if pool is not None:
            pool.shutdown()
    return tot, records


def read_frames(root, rig: Rig, drives) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Per drive, its frames as (N, 3) float32 ego-frame points and (N,) int64 labels."""
    from place3d_kernels.io.semantickitti import frame_paths, read_semantickitti

    out = []
    for d in drives:
        folder = sequence_folder(root, rig, d)
        frames = []
        for i in range(d.frames):
            pts, _, lab = read_semantickitti(*frame_paths(folder, i), labels="place3d")
            frames.append((np.ascontiguousarray(pts, np.float32), lab.astype(np.int64)))
        out.append(frames)
    return out


def route_overlap(root, rig: Rig, train, test, radius: float = 10.0) -> float:
    """Share of the ``test`` drives' frames whose ego position lies within ``radius`` metres of a frame of a
    ``train`` drive on the same scene (0: the test routes drive streets the training never saw)."""
    from scipy.spatial import cKDTree

    from place3d_kernels.io.semantickitti import read_poses

    def xy(d):
        return read_poses(sequence_folder(root, rig, d) / "poses.txt")[:, :2, 3]

    near = total = 0
    for d in test:
        same = [t for t in train if t.scene == d.scene]
        pts = xy(d)
        total += len(pts)
        if same:
            tree = cKDTree(np.concatenate([xy(t) for t in same]))
            near += int(np.sum(tree.query(pts, k=1)[0] <= radius))
    return near / total if total else float("nan")
