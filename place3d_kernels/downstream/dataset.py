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
                                          /labels/NNNNNN.label    uint32: Place3D class (low 16 bits),
                                                                  instance id (high 16 bits)
                                          /poses.txt              ego-to-world 3x4 rows
                                          /sequence.json          manifest: the spec below, written last

The "sensor" of these sequences is the ego frame itself, so ``sequence.json`` says ``mount`` = zeros and
``labels`` = "place3d", and ``io.read_sequence`` reads them back as world frames with no options. A
sequence whose manifest matches its spec is finished and skipped (resume); a folder made with other
settings is refused (``ValueError`` naming the field) unless ``overwrite``.

Instance ids (``instance_tables``) follow the SemanticKITTI ``.label`` layout (Behley et al., ICCV 2019,
and its development kit, semantic-kitti-api: ``label & 0xFFFF`` is the class, ``label >> 16`` the
instance), so readers that keep the low 16 bits (``io.read_semantickitti``) see the same classes as before.
They come from the ray cast itself: ``simulate(hit_faces=True)`` says which triangle of which mesh each
return hit, and a table per mesh maps triangles to objects. Actor k of ``scene.actors`` (moving vehicles
and pedestrians) is instance k + 1. Parked cars are part of the static mesh: parked car j of an OpenDRIVE
scene (its builder records the boxes, ``scene.meta["static_boxes"]``) is instance len(actors) + 1 + j, its
triangles the vehicle triangles of the static mesh whose centroid lies in its box. The embedded town's
builder records no boxes; its parked cars are found in the mesh: vehicle triangles that share a vertex form
a part (a box, a wheel), and parts whose bounds touch form one car (``_touching_parts``; parked cars stand
0.8 m or more apart, and on Town01 this grouping gives exactly the recorded boxes' cars, see the tests).
Every other return is instance 0 (no object). Ids are per drive, the same for every rig and every frame of
it, so one object can be followed across rigs.

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
           "build_datasets", "read_frames", "route_overlap", "instance_tables", "pack_labels", "unpack_labels",
           "EGO_MOUNT", "INSTANCE_SHIFT", "INSTANCES"]

#: the merged clouds are stored in the ego frame: the sequences' "sensor" is the ego frame itself
EGO_MOUNT = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

#: SemanticKITTI ``.label``: class in the low 16 bits, instance id in the high 16 (Behley et al., ICCV 2019)
INSTANCE_SHIFT = 16

#: how the instance ids of a sequence were assigned (``sequence.json``); see the module docstring
INSTANCES = "actors-then-parked-cars-v1"

#: slack of the parked-car boxes and of touching parts (metres): the boxes are the cars' own bounds and the
#: parts of one car touch, so only rounding needs room
_SLACK = 1e-3


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
            "labels": "place3d", "merged": "multi-lidar", "instances": INSTANCES}


def pack_labels(labels, instances) -> np.ndarray:
    """uint32 ``.label`` values: class in the low 16 bits, instance id in the high 16."""
    lab = np.asarray(labels, dtype=np.int64)
    inst = np.asarray(instances, dtype=np.int64)
    for name, a in (("classes", lab), ("instance ids", inst)):
        if a.size and (a.min() < 0 or a.max() >= 1 << INSTANCE_SHIFT):
            raise ValueError(f"{name} must lie in [0, 65535] to fit 16 bits, got {a.min()}..{a.max()}")
    return ((inst << INSTANCE_SHIFT) | lab).astype(np.uint32)


def unpack_labels(raw) -> tuple[np.ndarray, np.ndarray]:
    """(classes, instance ids) as int64 from uint32 ``.label`` values."""
    raw = np.asarray(raw, dtype=np.uint32)
    return (raw & 0xFFFF).astype(np.int64), (raw >> INSTANCE_SHIFT).astype(np.int64)


def instance_tables(scene) -> tuple[np.ndarray, np.ndarray]:
    """Instance id per triangle: ((F_static,) int32 for the static mesh, (F_actors,) int32 for the actors'
    mesh of any frame, ``scene.dynamic(f)``: actors concatenated in order, so their triangle counts do not
    change between frames). See the module docstring for the numbering."""
    from place3d_kernels.classes import VEHICLE

    n_act = len(scene.actors)
    actors = (np.repeat(np.arange(1, n_act + 1), [a.mesh.n_faces for a in scene.actors]).astype(np.int32)
              if n_act else np.zeros(0, np.int32))
    static = np.zeros(scene.static.n_faces, np.int32)
    boxes = np.asarray(scene.meta.get("static_boxes", ()) if isinstance(scene.meta, dict) else (),
                       np.float64).reshape(-1, 7)
    cars = np.flatnonzero(scene.static.labels == VEHICLE)
    if len(boxes) and len(cars):
        v, f = scene.static.vertices, scene.static.faces[cars]
        centre = (v[f[:, 0]] + v[f[:, 1]] + v[f[:, 2]]) / 3.0
        for j, (x, y, z, length, width, height, yaw) in enumerate(boxes):
            dx, dy, dz = centre[:, 0] - x, centre[:, 1] - y, centre[:, 2] - z
            u = np.cos(yaw) * dx + np.sin(yaw) * dy
            w = -np.sin(yaw) * dx + np.cos(yaw) * dy
            inside = ((np.abs(u) <= length / 2 + _SLACK) & (np.abs(w) <= width / 2 + _SLACK)
                      & (np.abs(dz) <= height / 2 + _SLACK))
            # boxes of parked cars do not overlap (each takes its cells of the roadside raster); a triangle
            # keeps the first box it lies in all the same
            take = inside & (static[cars] == 0)
            static[cars[take]] = n_act + 1 + j
    rest = cars[static[cars] == 0]
    if len(rest):
        static[rest] = n_act + len(boxes) + 1 + _touching_parts(scene.static, rest)
    if static.size and static.max() >= 1 << INSTANCE_SHIFT:
        raise ValueError(f"{n_act} actors and {static.max() - n_act} parked cars do not fit 16-bit instance ids")
    return static, actors


def _touching_parts(mesh, faces) -> np.ndarray:
    """Object index (0, 1, ...) of each triangle ``faces`` of ``mesh``: triangles sharing a vertex form a
    part, parts whose bounding boxes touch (within ``_SLACK``) form an object; objects are numbered in the
    order of their first triangle."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    f = mesh.faces[faces]
    n = len(f)
    verts, inv = np.unique(f.ravel(), return_inverse=True)
    size = n + len(verts)
    graph = coo_matrix((np.ones(3 * n), (np.repeat(np.arange(n), 3), n + inv.ravel())), shape=(size, size))
    part = connected_components(graph, directed=False)[1][:n]
    part = np.unique(part, return_inverse=True)[1].ravel()
    n_parts = int(part.max()) + 1
    corners = mesh.vertices[f]
    lo = np.full((n_parts, 3), np.inf)
    hi = np.full((n_parts, 3), -np.inf)
    np.minimum.at(lo, part, corners.min(axis=1))
    np.maximum.at(hi, part, corners.max(axis=1))
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    pairs = cKDTree(centre).query_pairs(2 * float(np.linalg.norm(half, axis=1).max()) + _SLACK, output_type="ndarray")
    a, b = pairs[:, 0], pairs[:, 1]
    touch = np.all((lo[a] <= hi[b] + _SLACK) & (lo[b] <= hi[a] + _SLACK), axis=1)
    links = coo_matrix((np.ones(int(touch.sum())), (a[touch], b[touch])), shape=(n_parts, n_parts))
    obj = connected_components(links, directed=False)[1][part]
    # number objects by their first triangle, so the ids do not depend on scipy's labelling
    first = np.full(obj.max() + 1, n)
    np.minimum.at(first, obj, np.arange(n))
    return np.argsort(np.argsort(first))[obj].astype(np.int32)


def simulate_rig(scene, rig: Rig, backend=None, frames=None, instances: bool = False) -> list[tuple]:
    """Per frame of ``scene``: (N, 3) float32 ego-frame points, (N,) int32 labels, (N,) float32 intensity
    of every LiDAR of ``rig`` merged (LiDAR by LiDAR, in the rig's order); with ``instances`` a fourth item,
    (N,) int32 instance ids (``instance_tables``) from the triangle each return hit."""
    from place3d_kernels.lidar import LidarModel
    from place3d_kernels.pose import invert, pose_matrix, transform_points
    from place3d_kernels.simulate import simulate

    lidar = LidarModel.load(rig.lidar)
    idx = list(range(scene.n_frames) if frames is None else frames)
    per_lidar, per_faces = [], []
    for pose in rig.pose_array:
        res = simulate(scene, lidar, mount=pose, frames=idx, backend=backend, hit_faces=instances)
        per_lidar.append(res[0] if instances else res)
        per_faces.append(res[1] if instances else None)
    tables = instance_tables(scene) if instances else None
    out = []
    for j, f in enumerate(idx):
        to_ego = invert(pose_matrix(scene.ego_poses[f]))
        pts = np.concatenate([transform_points(to_ego, fr[j].points) for fr in per_lidar]).astype(np.float32)
        lab = np.concatenate([fr[j].labels for fr in per_lidar]).astype(np.int32)
        inten = np.concatenate([fr[j].intensity for fr in per_lidar]).astype(np.float32)
        if instances:
            static, actors = tables
            inst = []
            for on_actor, face in (fa[j] for fa in per_faces):
                ids = static[np.where(on_actor, 0, face)]
                if on_actor.any():
                    ids = np.where(on_actor, actors[np.where(on_actor, face, 0)], ids)
                inst.append(ids)
            out.append((pts, lab, inten, np.concatenate(inst).astype(np.int32)))
        else:
            out.append((pts, lab, inten))
    return out


def _write_sequence(folder: Path, scene, frames) -> None:
    from place3d_kernels.io.semantickitti import atomic_write, frame_paths, pose_row, write_frame_bin
    from place3d_kernels.pose import pose_matrix

    (folder / "velodyne").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(parents=True, exist_ok=True)
    rows = []
    for i, (pts, lab, inten, inst) in enumerate(frames):
        write_frame_bin(*frame_paths(folder, i), pts, inten, pack_labels(lab, inst))
        rows.append(pose_row(pose_matrix(scene.ego_poses[i])))
    atomic_write(folder / "poses.txt", ("\n".join(rows) + "\n").encode())


def write_drive(root, rigs, drive: Drive, backend=None, overwrite: bool = False) -> dict:
    """Write the sequences of ``drive`` for every rig still missing it; the scene is built once (and only
    if some rig needs it). Returns {"written": [rig names], "skipped": [...], "seconds": float}."""
    from place3d_kernels.manifest import write_manifest

    todo, skipped = [], []
    for rig in rigs:
        folder = sequence_folder(root, rig, drive)
        spec = sequence_spec(rig, drive)
        if overwrite and folder.is_dir():
            import shutil

            shutil.rmtree(folder)
        if _finished(folder, spec):
            skipped.append(rig.name)
        else:
            todo.append((rig, folder, spec))
    t0 = time.perf_counter()
    if todo:
        from place3d_kernels.io.semantickitti import SEQUENCE_META

        scene = drive.build()
        for rig, folder, spec in todo:
            _write_sequence(folder, scene, simulate_rig(scene, rig, backend, instances=True))
            write_manifest(folder / SEQUENCE_META, spec)
    return {"written": [r.name for r, _, _ in todo], "skipped": skipped, "seconds": time.perf_counter() - t0}


def _finished(folder: Path, spec: dict) -> bool:
    """Whether the sequence in ``folder`` is finished for ``spec`` (its manifest, written last, matches). One
    made before instance ids were written (the same spec without "instances") is not: it is written again,
    with the same points and classes. One made with other settings raises ``ValueError`` naming the field."""
    from place3d_kernels.io.semantickitti import SEQUENCE_META
    from place3d_kernels.manifest import plain, read_manifest, verify_manifest

    m = read_manifest(folder / SEQUENCE_META)
    if m is not None and "instances" not in (m.get("spec") or {}):
        if m.get("spec") == plain({k: v for k, v in spec.items() if k != "instances"}):
            return False
    return verify_manifest(folder / SEQUENCE_META, spec, "dataset sequence")


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
                   psog=None, workers: int = 0, executor=None) -> tuple[dict, list]:
    """Every (rig, drive) sequence of ``splits``, drive by drive (a scene is built once for all rigs).

    One task per drive writes that drive's sequence for every rig still missing it (and its P-SOG record):
    the scene, the costly part to build, is made once per drive and serves every rig. A task depends only
    on its arguments and writes only its own drive's folders, so wherever it runs it writes the same bytes.

    Args:
        psog: optional ``pooled.PoolSettings``: the training drives' P-SOG records are built too, each right
            after its drive's sequences, from the scene still in memory (``pooled.drive_record``; cached on
            disk by its inputs).
        workers: drives run in this many spawned processes at once (0: here, one after the other). Scene
            building and the simulation's per-frame host work are single-threaded Python, so on a GPU host
            processes overlap them; each process opens its own device context.
        executor: instead of ``workers``, anything with ``map(fn, tasks) -> results in task order``, e.g.
            ``place3d_app.executors.RayExecutor`` (tasks on a Ray cluster; ``root`` and the P-SOG cache
            must then be on storage every node sees).
    Returns: ({"written", "skipped", "seconds", "psog_seconds"} totals, the training drives' records in drive
        order, empty without ``psog``).
    """
    drives = splits.all_drives()
    train = {d.label for d in splits.drives("train")}
    tasks = [(str(root), list(rigs), d, backend, overwrite, psog if psog is not None and d.label in train else None)
             for d in drives]
    if executor is not None and workers:
        raise ValueError("give workers or an executor, not both")
    pool = None
    if executor is not None:
        results = executor.map(_drive_task, tasks)
        progress = False                      # the results come back together
    elif workers and workers > 0:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        pool = ProcessPoolExecutor(min(workers, len(tasks)), mp_context=mp.get_context("spawn"))
        results = pool.map(_drive_task, tasks)
    else:
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


def read_frames(root, rig: Rig, drives, instances: bool = False) -> list[list[tuple]]:
    """Per drive, its frames as (N, 3) float32 ego-frame points and (N,) int64 labels (and, with
    ``instances``, (N,) int64 instance ids: the high 16 bits of the ``.label`` values)."""
    from place3d_kernels.io.semantickitti import frame_paths, read_semantickitti

    out = []
    for d in drives:
        folder = sequence_folder(root, rig, d)
        frames = []
        for i in range(d.frames):
            pts, _, lab = read_semantickitti(*frame_paths(folder, i), labels="place3d")
            fr = (np.ascontiguousarray(pts, np.float32), lab.astype(np.int64))
            if instances:
                fr += (unpack_labels(np.fromfile(frame_paths(folder, i)[1], dtype=np.uint32))[1],)
            frames.append(fr)
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
