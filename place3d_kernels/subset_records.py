"""Per-subset records of a drive: the sparse counts each subset of k frames votes, kept on disk.

Intervals over a drive (the jackknife and the bootstrap of ``place3d_kernels.uncertainty``) pool these
records with one left out or resampled. They are cached beside the P-SOG under a key of the P-SOG's
inputs (``subset_records_path``), written either when a command builds the P-SOG on a cache miss
(``records_aggregator``, handed to ``PSOGSpec.build`` by the commands: the P-SOG is then pooled from them,
the same P-SOG as ``PSOG.from_frames``) or, for a P-SOG cached before that, by simulating the drive once
more (``spec_subset_records``).
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Callable

import numpy as np

from place3d_kernels.atomic import file_identity


__all__ = ["frame_subset_records", "votes_records", "subset_records_path", "spec_subset_records", "records_aggregator",
           "keyed_subset_records"]


def frame_subset_records(frames, grid, k: int, backend=None, label: str = "drive") -> list:
    """One ``DriveRecord`` per subset of ``k`` consecutive frames, voted as ``PSOG.from_frames`` votes
    them (the same grouping as ``pooled.subset_records``), so the records sum to the drive's P-SOG."""
    from place3d_kernels.sog import subset_votes

    return votes_records(subset_votes(list(frames), grid, k, backend=backend), label)


def votes_records(votes, label: str = "drive") -> list:
    """One ``DriveRecord`` (T = 1) per subset SOG of ``sog.subset_votes``, named ``label#j``.

    The record ``DriveRecord.from_psog`` gives for ``PSOG.from_frames`` of that subset alone, without
    building it: a one-subset P-SOG counts 1 for the winning class of each voxel, so its record is the
    voxels with a voting class (ascending, as the vote returns them), those classes and counts of 1.
    """
    from place3d_kernels.pooled import DriveRecord

    recs = []
    for j, (vox, win) in enumerate(votes):
        vox, win = _ascending(vox, win)
        occ = win > 0                      # class 0 (no vote) is "empty", never a record entry
        recs.append(DriveRecord(f"{label}#{j}", 1, vox[occ].astype(np.int64), win[occ].astype(np.int16),
                                np.ones(int(occ.sum()), dtype=np.int32)))
    return recs


def _ascending(vox, win):
    """A subset's votes in ascending voxel order (``Backend.vote`` returns them so; this keeps a backend
    that does not from giving records out of order), or ``ValueError`` for a voxel voted twice."""
    vox, win = np.asarray(vox, np.int64), np.asarray(win, np.int64)
    if len(vox) < 2 or bool((vox[1:] > vox[:-1]).all()):
        return vox, win
    order = np.argsort(vox, kind="stable")
    vox, win = vox[order], win[order]
    if bool((vox[1:] == vox[:-1]).any()):
        raise ValueError("Backend.vote returned a voxel twice; it must return each voted voxel once")
    return vox, win


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
    from place3d_kernels.manifest import cache_warning, verified_bytes
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
            # inputs and the sha256 of the bytes, both from the manifest beside the file (manifest.py)
            data = verified_bytes(path, path.with_suffix(".json"), inputs, "subset-record cache")
            z = np.load(io.BytesIO(data), allow_pickle=False)
            cut = np.cumsum(z["sizes"])[:-1]
            return [DriveRecord(str(lab), int(t), v, c, n) for lab, t, v, c, n in
                    zip(z["labels"], z["n_subsets"], np.split(z["voxels"], cut), np.split(z["classes"], cut),
                        np.split(z["counts"], cut))]
        except Exception as e:  # noqa: BLE001 - a broken or stale cache file is rebuilt, not fatal
            cache_warning(path, e)
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


def keyed_subset_records(spec, backend=None, cache: bool = True) -> tuple[list, tuple | None]:
    """``spec_subset_records`` and, when the records are exactly the cache file's content, that file's
    identity (``atomic.file_identity``): the key under which a process may keep what it derives from
    them (``left_out.PreparedLeftOut``). None when the records were simulated or rewritten meanwhile (the
    identity changed during the read), or nothing is cached (``cache=False``, semantickitti)."""
    path = subset_records_path(spec)[0] if cache else None
    before = None if path is None else file_identity(path)
    recs = spec_subset_records(spec, backend, cache)
    if before is None or file_identity(path) != before:
        return recs, None
    return recs, before


def _write_records(path: Path, inputs: dict, recs) -> None:
    """Write the records and their manifest (inputs and content sha256); a cache that cannot be written (a
    full disk, a read-only folder) is a one-line warning: the next command simulates them again."""
    import logging

    from place3d_kernels.atomic import atomic_write
    from place3d_kernels.manifest import content_hash, write_manifest

    buf = io.BytesIO()
    np.savez(buf, labels=np.array([r.label for r in recs]), n_subsets=np.array([r.n_subsets for r in recs]),
             sizes=np.array([len(r.voxels) for r in recs]), voxels=np.concatenate([r.voxels for r in recs]),
             classes=np.concatenate([r.classes for r in recs]), counts=np.concatenate([r.counts for r in recs]))
    data = buf.getvalue()
    try:
        atomic_write(path, data)
        write_manifest(path.with_suffix(".json"), inputs, content_hash(data))
    except OSError as e:
        logging.getLogger(__name__).warning("subset-record cache %s not written: %s", path, e)


def records_aggregator(spec) -> Callable:
    """``(frames, backend) -> PSOG`` for ``scene_psog(aggregate=...)``: votes each subset of the frames once
    into per-subset records, writes them to the subset-record cache of ``spec`` (where
    ``spec_subset_records`` finds them) and returns their pool, which is the P-SOG ``PSOG.from_frames``
    gives: the same voxels, counts and float64 probabilities (tests/test_interval_memo.py checks it)."""
    from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET

    def aggregate(frames, backend):
        from place3d_kernels.sog import PSOG, subset_votes, vote_entries

        from place3d_kernels.left_out import HANDLES

        grid = spec.grid.grid()
        votes = subset_votes(frames, grid, spec.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET, backend)
        recs = votes_records(votes, spec.scene.label)
        path, inputs = subset_records_path(spec)
        if path is not None:
            _write_records(path, inputs, recs)
        # the pool of the records (PooledPSOG(grid, recs).psog()) counted straight from their entries: the
        # same voxels (those with a voting class), counts and float64 probabilities (counts / T)
        voxels, occupied = vote_entries([(r.voxels, r.classes.astype(np.int64)) for r in recs], grid.n_voxels)
        psog = PSOG(grid, voxels, None, n_subsets=len(recs), occupied=occupied)
        if path is not None:
            # the intervals read these records back (keyed_subset_records: this file's identity while it is
            # not rewritten) and find this P-SOG their pool without pooling and comparing them again
            HANDLES.remember_plain(file_identity(path), psog)
        return psog

    return aggregate
