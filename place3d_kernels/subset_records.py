"""Per-subset records of a drive: the sparse counts each subset of k frames votes, kept on disk.

Intervals over a drive (the jackknife and the bootstrap of ``place3d_kernels.uncertainty``) pool these
records with one left out or resampled. They are cached beside the P-SOG under a key of the P-SOG's
inputs (``subset_records_path``), written either when a command builds the P-SOG on a cache miss
(``records_aggregator``, handed to ``PSOGSpec.build`` by the commands: the P-SOG is then pooled from them,
the same P-SOG as ``PSOG.from_frames``) or, for a P-SOG cached before that, by simulating the drive once
more (``spec_subset_records``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import numpy as np

from place3d_kernels.pooled import PooledPSOG

__all__ = ["frame_subset_records", "subset_records_path", "spec_subset_records", "records_aggregator",
           "records_file_identity", "keyed_subset_records"]


def frame_subset_records(frames, grid, k: int, backend=None, label: str = "drive") -> list:
    """One ``DriveRecord`` per subset of ``k`` consecutive frames, voted as ``PSOG.from_frames`` votes
    them (the same grouping as ``pooled.subset_records``), so the records sum to the drive's P-SOG."""
    from place3d_kernels.pooled import DriveRecord
    from place3d_kernels.sog import PSOG

    frames = list(frames)
    n_sub = max(1, len(frames) // k)
    groups = [frames[i * k:(i + 1) * k] for i in range(n_sub)] if len(frames) >= k else [frames]
    return [DriveRecord.from_psog(PSOG.from_frames(g, grid, len(g), backend=backend), f"{label}#{j}")
            for j, g in enumerate(groups)]


def subset_records_path(spec):
    """(npz path, inputs) of the subset-record cache of a ``PSOGSpec`` (None for semantickitti: nothing
    is simulated, the frames are read again)."""
    from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET
    from place3d_kernels.simulate import DEFAULT_MOUNT
    from place3d_kernels.sog import cache_dir, cache_key
    from place3d_kernels.spec import resolve_lidar

    if spec.scene.kind == "semantickitti":
        return None, None
    lidar = resolve_lidar(spec.lidar)
    folder = Path(spec.cache) if spec.cache else cache_dir()
    scene = spec.scene.for_cache(folder)       # name and key; built only when not remembered
    # the inputs of scene_psog's cache key, plus what makes these files different from a P-SOG
    inputs = dict(kind="subset-records", scene=scene.key, grid=spec.grid.grid().to_dict(),
                  lidar=[lidar.name, lidar.elevations.tolist(), lidar.azimuths.size, lidar.max_range],
                  mount=np.asarray(DEFAULT_MOUNT if spec.mount is None else spec.mount).tolist(),
                  k=spec.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET,
                  condition=None if spec.condition is None else spec.condition.to_dict())
    body = spec.vehicle_body()
    if body is not None:
        # only with a body, so the no-body (paper) key and the files already on disk stay valid
        inputs["body"] = {"name": body.name, "key": body.key}
    return folder / f"subsets-{scene.name}-{cache_key(**inputs)}.npz", inputs


def spec_subset_records(spec, backend=None, cache: bool = True) -> list:
    """Per-subset ``DriveRecord``s of a ``PSOGSpec`` (its scene, condition, grid, collection LiDAR, k).

    Simulates the frames once and keeps the sparse records on disk beside the P-SOG cache (a few MB at
    0.2 m), so later bootstraps cost no simulation. ``cache=False`` rebuilds and writes nothing.
    """
    from place3d_kernels.manifest import verify_manifest
    from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET
    from place3d_kernels.pooled import DriveRecord
    from place3d_kernels.simulate import DEFAULT_MOUNT, simulate
    from place3d_kernels.spec import resolve_lidar

    b = spec.backend if backend is None else backend
    k = spec.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET
    grid = spec.grid.grid()
    path, inputs = subset_records_path(spec) if cache else (None, None)
    if path is not None and path.exists():
        try:
            if not verify_manifest(path.with_suffix(".json"), inputs, "subset-record cache", "it is rebuilt"):
                raise ValueError(f"{path}: no manifest")
            z = np.load(path)
            cut = np.cumsum(z["sizes"])[:-1]
            return [DriveRecord(str(lab), int(t), v, c, n) for lab, t, v, c, n in
                    zip(z["labels"], z["n_subsets"], np.split(z["voxels"], cut), np.split(z["classes"], cut),
                        np.split(z["counts"], cut))]
        except Exception:  # noqa: BLE001 - a broken or stale cache file is rebuilt, not fatal
            pass
    if spec.scene.kind == "semantickitti":
        from place3d_kernels.io.semantickitti import read_sequence

        frames = read_sequence(spec.scene.path)
    else:
        frames = simulate(spec.scene.build(), resolve_lidar(spec.lidar),
                          mount=DEFAULT_MOUNT if spec.mount is None else spec.mount, backend=b,
                          body=spec.vehicle_body())
        if spec.condition is not None:
            cond = spec.condition.condition(b)
            frames = [cond(f, i) for i, f in enumerate(frames)]
    recs = frame_subset_records(frames, grid, k, b, spec.scene.label)
    if path is not None:
        _write_records(path, inputs, recs)
    return recs


def records_file_identity(path) -> tuple | None:
    """(resolved path, device, inode, size, modification time in ns) of a file, or None if it is absent:
    the key ``sog.keep_loaded`` uses for P-SOG files. ``_write_records`` replaces a file (a new inode),
    so a rewritten record file never has the identity of the one it replaced."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (os.path.realpath(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def keyed_subset_records(spec, backend=None, cache: bool = True) -> tuple[list, tuple | None]:
    """``spec_subset_records`` and, when the records are exactly the cache file's content, that file's
    identity (``records_file_identity``): the key under which a process may keep what it derives from
    them (``left_out.PreparedLeftOut``). None when the records were simulated or rewritten meanwhile (the
    identity changed during the read), or nothing is cached (``cache=False``, semantickitti)."""
    path = subset_records_path(spec)[0] if cache else None
    before = None if path is None else records_file_identity(path)
    recs = spec_subset_records(spec, backend, cache)
    if before is None or records_file_identity(path) != before:
        return recs, None
    return recs, before


def _write_records(path: Path, inputs: dict, recs) -> None:
    from place3d_kernels.manifest import write_manifest

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, labels=np.array([r.label for r in recs]), n_subsets=np.array([r.n_subsets for r in recs]),
             sizes=np.array([len(r.voxels) for r in recs]), voxels=np.concatenate([r.voxels for r in recs]),
             classes=np.concatenate([r.classes for r in recs]), counts=np.concatenate([r.counts for r in recs]))
    os.replace(tmp, path)
    write_manifest(path.with_suffix(".json"), inputs)


def records_aggregator(spec) -> Callable:
    """``(frames, backend) -> PSOG`` for ``scene_psog(aggregate=...)``: votes each subset of the frames once
    into per-subset records, writes them to the subset-record cache of ``spec`` (where
    ``spec_subset_records`` finds them) and returns their pool, which is the P-SOG ``PSOG.from_frames``
    gives: the same voxels, counts and float64 probabilities (tests/test_interval_memo.py checks it)."""
    from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET

    def aggregate(frames, backend):
        grid = spec.grid.grid()
        recs = frame_subset_records(frames, grid, spec.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET, backend,
                                    spec.scene.label)
        path, inputs = subset_records_path(spec)
        if path is not None:
            _write_records(path, inputs, recs)
        return PooledPSOG(grid, recs).psog()

    return aggregate
