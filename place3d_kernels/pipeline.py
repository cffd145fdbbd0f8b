"""The end-to-end path: scene -> semantic frames -> P-SOG, cached on disk by its inputs."""

from __future__ import annotations

import logging
from concurrent.futures import Future    # the background saves only
from pathlib import Path

import numpy as np

from place3d_kernels.grid import DEFAULT_GRID, Grid
from place3d_kernels.lidar import LidarModel
from place3d_kernels.manifest import cache_warning, verified_bytes, write_manifest
from place3d_kernels.profiling import section
from place3d_kernels.scene.keymemo import SceneRef
from place3d_kernels.simulate import DEFAULT_MOUNT, check_frames, simulate
from place3d_kernels.sog import PSOG, cache_folder, cache_key, subset_groups

__all__ = ["scene_psog", "part_psog", "drive_subsets", "save_psog", "cached_psog", "cache_file", "FrameCondition",
           "DEFAULT_FRAMES_PER_SUBSET", "check_entropy", "wait_for_saves", "saves_outlive_tasks", "end_task_saves"]

log = logging.getLogger(__name__)

#: Frames merged into one SOG: 40 frames -> T = 10 subsets, each spanning 2 s of driving.
DEFAULT_FRAMES_PER_SUBSET = 4


def scene_psog(scene, grid: Grid = DEFAULT_GRID, lidar: LidarModel | str = "collection_64ch",
               frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET, mount=DEFAULT_MOUNT, backend=None,
               cache: bool | str | Path = True, progress: bool = False, condition=None, body=None,
               aggregate=None, save_in_background: bool = False) -> PSOG:
    """The P-SOG of a scene: simulate its frames with the collection LiDAR, vote, aggregate.

    The result is cached on disk (``$PLACE3D_CACHE`` or ~/.cache/place3d) under a key made of every
    input (scene identity, grid, sensor, mount, subset size, condition), so a second call skips the
    simulation. The inputs themselves are stored beside it (``psog-...json``, a manifest) and checked on
    load; a cache whose manifest differs is rebuilt. ``cache=False`` disables it; a path chooses the folder.

    Args:
        scene: the ``Scene``, or a ``SceneRef`` (its name and key; built here only on a cache miss).
        condition: optional ``FrameCondition`` (or any callable ``(frame, index) -> frame`` with a ``key``
            attribute for the cache) applied to each simulated frame before voting.
        backend: backend name or instance (used only when the P-SOG is not in the cache; an application
            that probes its backend meanwhile asks ``cached_psog`` first).
        body: optional ``VehicleBody`` (ego frame) that blocks the collection LiDAR's rays (see
            ``simulate``); its name and content hash enter the cache key and the manifest. None (default) is
            the paper's setting, and its cache key is the one used before bodies existed.
        aggregate: optional ``(frames, backend) -> PSOG`` used on a cache miss instead of
            ``PSOG.from_frames`` (it must give the same P-SOG; ``PSOGSpec.build`` passes one that keeps the
            per-subset records of the same frames for the intervals, so they are not simulated again).
        save_in_background: write a newly built P-SOG to the cache on a thread of its own and return at
            once (``wait_for_saves`` waits for it; the interpreter does at exit). Compressing it (zlib, which
            lets other threads run) then overlaps what the caller does next, e.g. the search of
            ``place3d optimize``. The file is the one a direct save writes.
    """
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    entry = _cache_entry(scene, grid, lidar, frames_per_subset, mount, cache, condition, body)
    if entry is not None:
        found = _load_cached(*entry)
        if found is not None:
            return found
    frames = _frames(_built(scene), lidar, mount, backend, progress, condition, body)
    with section("P-SOG build: aggregate"):
        if aggregate is not None:
            psog = aggregate(frames, backend)
        else:
            psog = PSOG.from_frames(frames, grid, frames_per_subset, backend=backend, progress=progress)
    if entry is not None:
        path, manifest, inputs = entry
        with section("P-SOG build: save"):
            if save_in_background:
                _saves.append(_saver().submit(_save, psog, path, manifest, inputs))
            else:
                _save(psog, path, manifest, inputs)
    return psog


def part_psog(scene, subsets: range, grid: Grid = DEFAULT_GRID, lidar: LidarModel | str = "collection_64ch",
              frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET, mount=DEFAULT_MOUNT, backend=None, condition=None,
              body=None, progress: bool = False) -> PSOG:
    """The P-SOG of some subsets of a drive: the subsets ``subsets`` (a range of indices into the T subsets
    ``scene_psog`` votes, ``sog.subset_groups``) simulated and voted alone, with T = ``len(subsets)``; never
    cached. Parts that cover ``range(drive_subsets(...))`` once, merged (``pooled.DriveRecord.merge``), give
    the integer counts ``scene_psog`` builds from all the frames: each subset's frames, reference pose and
    vote are the same, and the counts are sums over subsets. Drives split so are built by several processes
    at once (``place3d_app``'s cold commands); ``save_psog`` then writes the merged drive to the cache.

    Args: as ``scene_psog``'s, and ``subsets``: ``range(a, b)`` with 0 <= a < b <= T.
    """
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    scene = _built(scene)
    groups = subset_groups(list(range(scene.n_frames)), frames_per_subset)
    if not isinstance(subsets, range) or subsets.step != 1 or not 0 <= subsets.start < subsets.stop <= len(groups):
        raise ValueError(f"subsets must be range(a, b) with 0 <= a < b <= {len(groups)} (the drive's subsets), "
                         f"got {subsets!r}")
    frames = [i for g in groups[subsets.start:subsets.stop] for i in g]
    frames = _frames(scene, lidar, mount, backend, progress, condition, body, frames)
    with section("P-SOG build: aggregate"):
        return PSOG.from_frames(frames, grid, frames_per_subset, backend=backend, progress=progress)


def drive_subsets(n_frames: int, frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET) -> int:
    """T, the subsets ``scene_psog`` votes for a drive of ``n_frames`` frames (``sog.subset_groups``)."""
    return len(subset_groups(list(range(int(n_frames))), frames_per_subset))


def save_psog(psog: PSOG, scene, grid: Grid = DEFAULT_GRID, lidar: LidarModel | str = "collection_64ch",
              frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET, mount=DEFAULT_MOUNT, cache: bool | str | Path = True,
              condition=None, body=None) -> Path | None:
    """Write ``psog`` (a whole drive's, e.g. merged from ``part_psog`` parts) to the cache entry ``scene_psog``
    reads for these inputs, with its manifest, as ``scene_psog`` writes it; returns the file (None without a
    cache). ``scene``: the ``Scene`` or its ``SceneRef`` (only its name and key are read)."""
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    entry = _cache_entry(scene, grid, lidar, frames_per_subset, mount, cache, condition, body)
    if entry is None:
        return None
    _save(psog, *entry)
    return entry[0]


def _built(scene):
    if isinstance(scene, SceneRef):
        with section("P-SOG build: scene"):
            scene = scene.build()    # known by its key only (PSOGSpec.build): the geometry is needed now
    return scene


def _frames(scene, lidar, mount, backend, progress, condition, body, frames=None) -> list:
    """The scene's simulated frames (all, or the indices ``frames``), each through ``condition`` if any."""
    at = list(range(scene.n_frames)) if frames is None else list(frames)
    check_frames(len(at), lidar, "frames")      # every frame is held before the vote
    # actor meshes made ahead by whoever built the scene (the application's forked build), else none yet
    dynamic = scene.take_prebuilt()
    with section("P-SOG build: simulate"):
        # intensities only for a condition (fog, wet ground, snow read them); the vote needs labels alone
        out = simulate(scene, lidar, mount=mount, frames=frames, backend=backend, progress=progress, body=body,
                       dynamic=dynamic, intensity=condition is not None)
    if condition is not None:
        out = [condition(f, i) for i, f in zip(at, out)]      # a frame's index in the drive, part or whole
    return out


def cached_psog(scene, grid: Grid = DEFAULT_GRID, lidar: LidarModel | str = "collection_64ch",
                frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET, mount=DEFAULT_MOUNT,
                cache: bool | str | Path = True, condition=None, body=None, warn: bool = True) -> PSOG | None:
    """The P-SOG ``scene_psog`` would read from the cache for these inputs, or None (no backend needed).
    ``warn=False``: a file that fails its check is not reported here (a caller that builds it next, through
    ``scene_psog``, reads it again and reports it once)."""
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    entry = _cache_entry(scene, grid, lidar, frames_per_subset, mount, cache, condition, body)
    return None if entry is None else _load_cached(*entry, warn=warn)


def cache_file(scene, grid: Grid = DEFAULT_GRID, lidar: LidarModel | str = "collection_64ch",
               frames_per_subset: int = DEFAULT_FRAMES_PER_SUBSET, mount=DEFAULT_MOUNT,
               cache: bool | str | Path = True, condition=None, body=None) -> Path | None:
    """The file ``scene_psog`` caches these inputs' P-SOG in (``scene``: a ``Scene`` or a ``SceneRef``), or
    None without a cache; it need not exist, and is not read or verified here."""
    if isinstance(lidar, str):
        lidar = LidarModel.load(lidar)
    entry = _cache_entry(scene, grid, lidar, frames_per_subset, mount, cache, condition, body)
    return None if entry is None else entry[0]


def _cache_entry(scene, grid, lidar, frames_per_subset, mount, cache, condition, body):
    """(file, manifest, inputs) of the P-SOG cache entry for these inputs, or None without a cache."""
    if not cache:
        return None
    folder = cache_folder(cache)
    inputs = dict(scene=scene.key, grid=grid.to_dict(), lidar=[lidar.name, lidar.elevations.tolist(),
                  lidar.azimuths.size, lidar.max_range], mount=np.asarray(mount).tolist(),
                  k=frames_per_subset, condition=getattr(condition, "key", None))
    if body is not None:
        # only with a body, so the no-body (paper) key and the caches already on disk stay valid
        inputs["body"] = {"name": body.name, "key": body.key}
    path = folder / f"psog-{scene.name}-{cache_key(**inputs)}.npz"
    return path, path.with_suffix(".json"), inputs


def _load_cached(path: Path, manifest: Path, inputs: dict, warn: bool = True) -> PSOG | None:
    if not path.exists():
        return None
    try:
        # the file name is a hash of the inputs; the manifest beside it holds the inputs themselves and the
        # sha256 of the file's bytes, so a stale, colliding, damaged or rewritten file (or one without a
        # manifest) is caught here instead of silently reused
        with section("P-SOG cache load"):
            return PSOG.load(path, check=lambda: verified_bytes(path, manifest, inputs, "P-SOG cache"))
    except Exception as e:  # noqa: BLE001 - a broken or mismatching cache file is rebuilt, not fatal
        if warn:
            cache_warning(path, e)
        return None


_saves: list[Future] = []
_saver_pool = None


def _saver():
    global _saver_pool
    if _saver_pool is None:
        from concurrent.futures import ThreadPoolExecutor

        # one thread: saves of one process land in the order they were asked for. Its threads are joined
        # when the interpreter exits (concurrent.futures does so), so a command's cache is complete then
        _saver_pool = ThreadPoolExecutor(1, thread_name_prefix="place3d-psog-save")
    return _saver_pool


def _save(psog: PSOG, path: Path, manifest: Path, inputs: dict) -> None:
    with section("P-SOG save (thread)"):
        try:
            psog.save(path)
            # after the file: a manifest never names a missing P-SOG; a kill between the two leaves a file
            # whose manifest is missing or records another hash, which the next load rebuilds
            write_manifest(manifest, inputs, psog.sha256)
        except OSError as e:
            # the cache only saves time: a full disk or a read-only folder costs the next command a rebuild
            log.warning("P-SOG cache %s not written: %s", path, e)


def wait_for_saves() -> None:
    """Wait until every P-SOG that ``scene_psog(save_in_background=True)`` is writing is on disk."""
    while _saves:
        _saves.pop(0).result()


_outlive = False


def saves_outlive_tasks(on: bool | None = None) -> bool:
    """Whether a task that builds P-SOGs for another process (``pooled``'s drive tasks) may return while their
    cache files are still being written on the saver thread; ``on`` sets it. Off by default: such a task waits
    for its saves, so the cache is whole when it returns. A process that itself waits for its saves before it
    ends turns it on (the application's worker processes: their normal exit joins the saver thread, and their
    SIGTERM handler waits for it), so the file's compression leaves the task's critical path."""
    global _outlive
    if on is not None:
        _outlive = bool(on)
    return _outlive


def end_task_saves() -> None:
    """What a drive task does with its background saves before it returns: waits for them, unless this process
    lets them outlive its tasks (``saves_outlive_tasks``)."""
    if not _outlive:
        wait_for_saves()


def check_entropy(psog: PSOG, frames_per_subset: int | None = None) -> PSOG:
    """``psog`` itself, or ``ValueError`` when no voxel has entropy (every stored voxel holds a single
    class in every subset, e.g. T < 2 subsets): M-SOG would be 0 for every rig."""
    if not psog.has_entropy():
        k = frames_per_subset or DEFAULT_FRAMES_PER_SUBSET
        raise ValueError(f"P-SOG has no entropy: T = {psog.n_subsets} subsets of k = {k} frames, every voxel a "
                         f"single class, so every rig would score 0; use at least {2 * k} frames (--frames, or a --route of "
                         f"that many poses for a mesh scene)")
    return psog


class FrameCondition:
    """An adverse condition applied to simulated frames (callable ``(PointCloud, index) -> PointCloud``).

    Each frame gets its own seed derived from the run seed and the frame's position in the drive, so
    results never depend on evaluation order. ``key`` identifies the condition for P-SOG caches.

    Args:
        name: condition name (``place3d_kernels.conditions.CONDITIONS``) or a condition TOML path.
        seed: run seed.
        backend: backend for the condition kernels.
        severity: "light" | "moderate" | "heavy" (default: the paper's setting).
        **params: condition parameters (override the severity's).
    """

    def __init__(self, name: str, seed: int = 0, backend=None, severity: str | None = None, **params):
        from place3d_kernels import conditions

        if name not in conditions.CONDITIONS and not Path(name).exists():
            raise ValueError(f"unknown condition {name!r}; choose one of {sorted(conditions.CONDITIONS)} "
                             f"or give a condition TOML file")
        self.name, self.seed, self.backend, self.severity, self.params = name, int(seed), backend, severity, params
        self.key = {"condition": name, "seed": self.seed, "severity": severity,
                    "params": {k: params[k] for k in sorted(params)}}
        self._count = 0

    def __call__(self, frame, index: int | None = None):
        from place3d_kernels import conditions

        i = self._count if index is None else index
        self._count += 1
        # the conditions return copies or subsets of the frame, so its ego pose and sweep origin travel on
        return conditions.apply(frame, self.name, seed=self.seed * 1_000_003 + i, backend=self.backend,
                                severity=self.severity, **self.params)
