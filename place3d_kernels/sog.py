"""Probabilistic semantic occupancy grids (P-SOG) and their entropy (Place3D, Sec. 3.2).

A SOG gives each voxel one label per subset of frames (majority vote of its points; "empty" if none).
The P-SOG holds, per voxel, the fraction of the T subsets in which it had each label. Only voxels that
were occupied in at least one subset are stored; every other voxel is empty with probability 1.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from place3d_kernels.atomic import file_identity
from place3d_kernels.backends.registry import get_backend
from place3d_kernels.backends.base import ENTROPY_SCALE, cache_dir, cache_folder
from place3d_kernels.classes import CLASSES, N_CLASSES, VEHICLE
from place3d_kernels.entropy import ENTROPY_BLOCK, entropy
from place3d_kernels.grid import Grid
from place3d_kernels.kept import Kept
from place3d_kernels.pointcloud import PointCloud
from place3d_kernels.pose import invert, pose_matrix, transform_points
from place3d_kernels.profiling import section
from place3d_kernels.threads import block_map

__all__ = ["PSOG", "entropy", "cache_dir", "cache_folder", "cache_key", "keep_loaded", "subset_groups", "subset_votes",
           "pool_votes", "vote_entries"]

_FORMAT = 5  # bump when the on-disk layout or the build changes (2: float64 voxel binning; 3: ray-mesh
             # distances from the reference formula on every backend, so P-SOGs agree across backends;
             # 4: subset counts stored as their occupied entries, ``save``; 5: float64 decides which
             # triangle a ray hits, the reference's face on every backend)


#: P-SOGs read by ``PSOG.load``, kept by file identity while ``keep_loaded(n)`` allows (``place3d serve``)
_LOADED = Kept("P-SOGs")


def keep_loaded(n: int) -> None:
    """Keep the last ``n`` P-SOGs read by ``PSOG.load`` in memory (0, the default, keeps none).

    A resident process (``place3d serve``) turns this on, so a command on a cached P-SOG skips reading and
    decompressing the file (a visible part of a warm command on a large P-SOG) and keeps what the P-SOG
    derives on first use: its entropy, weights, stop mask and each backend's prepared grid (a device upload).
    An entry is keyed by the file's resolved path, device, inode, size and modification time (ns), so a file
    that was rewritten (``PSOG.save`` replaces it: a new inode) is read again. Nothing in the package writes
    into a P-SOG's arrays after it is made, so sharing one between commands gives the same results.
    """
    _LOADED.keep(n)


def subset_groups(frames: list, k: int) -> list[list]:
    """Consecutive subsets of ``k`` frames (trailing frames that do not fill one are dropped; all frames
    form one subset when there are fewer than ``k``): the grouping of ``PSOG.from_frames``."""
    if int(k) < 1:
        raise ValueError(f"frames_per_subset must be >= 1, got {k}")
    k = int(k)
    if not frames:
        raise ValueError("PSOG.from_frames needs at least one frame")
    n_sub = max(1, len(frames) // k)
    return [frames[i * k:(i + 1) * k] for i in range(n_sub)] if len(frames) >= k else [list(frames)]


def subset_votes(frames: list[PointCloud], grid: Grid, frames_per_subset: int, backend=None,
                 progress: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """The SOG of each subset of ``frames_per_subset`` frames (``subset_groups``): its frames merged in the
    ego frame of its middle frame and voxelised with a majority vote (``Backend.vote``: ties -> lowest
    class, unlabeled points do not vote).

    Returns:
        one (voxels (M,) int64 ascending, winning class (M,) int64) pair per subset.
    """
    groups = subset_groups(frames, frames_per_subset)
    b = get_backend(backend)
    it = groups
    if progress:
        from tqdm import tqdm

        it = tqdm(groups, desc="P-SOG subsets", unit="subset", leave=False)
    votes = []
    # one buffer of points and one of labels for every subset (the largest's size): a fresh array per frame, per
    # merge and per shift to the grid's corner was new memory each time, faulted in page by page, in every
    # worker process that builds a drive
    size = max(sum(len(f.points) for f in g) for g in groups)
    pts_buf, lab_buf = np.empty((size, 3)), np.empty(size, dtype=np.int32)
    lower = np.asarray(grid.lower, dtype=np.float64)
    for g in it:
        ref = g[len(g) // 2]
        to_ref = invert(pose_matrix(ref.ego_pose))
        n = sum(len(f.points) for f in g)
        pts, lab = pts_buf[:n], lab_buf[:n]
        at = 0
        with section("P-SOG vote: frames moved"):
            for f in g:
                m = len(f.points)
                # transform_points' arithmetic (one product, then the shift), written into the buffer, and then
                # Grid.to_local's subtraction: the same float64 roundings in the same order
                transform_points(to_ref, f.points, out=pts[at:at + m])
                lab[at:at + m] = f.labels
                at += m
            np.subtract(pts, lower, out=pts)
        with section("P-SOG vote: keys and vote"):
            vox, win = b.vote(b.voxel_keys(grid.spec, pts), lab, N_CLASSES)
        votes.append((np.asarray(vox, np.int64), np.asarray(win, np.int64)))
    return votes


def pool_votes(votes: list[tuple[np.ndarray, np.ndarray]], n_voxels: int,
               n_classes: int = N_CLASSES) -> tuple[np.ndarray, np.ndarray]:
    """Per-voxel label counts over the T = ``len(votes)`` subset SOGs of ``subset_votes``; ``n_voxels``: the
    grid's voxel count (every voted voxel lies below it).

    Returns:
        voxels (M,) int64 ascending (every voxel voted in some subset), counts (M, n_classes) int32 with
        column 0 = the subsets in which the voxel was empty (T minus its other columns).

    Raises:
        ValueError: a class outside [0, n_classes) or a voxel outside [0, n_voxels).
    """
    # the dense table of vote_entries' occupied entries (the one count of the votes; PSOG.from_frames keeps
    # the entries alone)
    voxels, (at, cnt) = vote_entries(votes, n_voxels, n_classes)
    return voxels, _dense_counts(at, cnt, len(voxels), n_classes, len(votes))


def vote_entries(votes: list[tuple[np.ndarray, np.ndarray]], n_voxels: int,
                 n_classes: int = N_CLASSES) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Per-voxel label counts over the T = ``len(votes)`` subset SOGs of ``subset_votes`` as the occupied entries a
    cache file stores (``_counts_members``), counted by one sort of every (voxel, class) vote, without the dense
    (M, K) table (``pool_votes`` makes it from these): ``PSOG(grid, voxels, None, n_subsets=len(votes),
    occupied=entries)`` is the P-SOG of ``PSOG.from_counts(grid, *pool_votes(...))``, the same counts to the bit,
    and its file the same bytes.

    Returns:
        voxels (M,) int64 ascending (every voxel voted in some subset), and (flat indices into ``counts[:, 1:]``,
        row-major, int64 as ``_counts_members`` gives them; their counts, int32).

    Raises:
        ValueError: a class outside [0, n_classes) or a voxel outside [0, n_voxels).
    """
    vox = np.concatenate([np.asarray(v, np.int64) for v, _ in votes]) if votes else np.zeros(0, np.int64)
    lab = np.concatenate([np.asarray(w, np.int64) for _, w in votes]) if votes else np.zeros(0, np.int64)
    if len(lab) and (lab.min() < 0 or lab.max() >= n_classes):
        raise ValueError(f"votes must be classes in [0, {n_classes}), got range [{lab.min()}, {lab.max()}]")
    if len(vox) and (vox.min() < 0 or vox.max() >= n_voxels):
        raise ValueError(f"voted voxels must lie in [0, {n_voxels}), got range [{vox.min()}, {vox.max()}]")
    key = vox * n_classes + lab
    key.sort()
    first = np.empty(len(key), dtype=bool)              # the first of each run of equal (voxel, class) votes
    first[:1] = True
    np.not_equal(key[1:], key[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    count = np.diff(np.append(starts, len(key))).astype(np.int32)
    key = key[starts]
    voxel, cls = np.divmod(key, n_classes)
    new = np.empty(len(voxel), dtype=bool)              # the first entry of each voxel
    new[:1] = True
    np.not_equal(voxel[1:], voxel[:-1], out=new[1:])
    voxels = voxel[new]
    row = np.cumsum(new) - 1
    # class 0 (empty) is T minus the others in every row: not an occupied entry (no vote gives it; one that did
    # still adds its voxel)
    keep = cls > 0
    return voxels, (row[keep] * (n_classes - 1) + cls[keep] - 1, count[keep])


class PSOG:
    """A P-SOG over a grid.

    Attributes:
        grid: the ROI grid (ego frame).
        voxels: (M,) int64 ascending flat indices of the stored (ever occupied) voxels.
        probs: (M, K) float64 class probabilities of those voxels; channel 0 = empty.
        channels: names of the K channels.
        n_subsets: T, the number of SOGs aggregated (None when built from probabilities).
        counts: (M, K) integer subset counts, or None (built from probabilities).

    ``probs=None`` with ``counts`` and ``n_subsets`` makes ``probs`` ``counts / T``, computed on first use:
    a P-SOG made from counts (a pooled one, one read from the cache) then derives its weights and stop mask
    from the integer counts by table look-ups (``left_out_tables.FieldTables``, the same bits as from the
    probabilities) and never builds the (M, K) float64 array unless something reads it. ``probs`` may also
    be a callable giving them, called on first use (``detection``'s variant of such a P-SOG).

    ``occupied`` (instead of ``counts``): the counts as a cache file stores them (``_counts_members``: flat indices
    into ``counts[:, 1:]`` of the nonzero entries, and those entries), made into the dense ``counts`` on first
    use. A drive read from the cache for pooling needs only these entries (``pooled.DriveRecord.from_psog``).
    """

    def __init__(self, grid: Grid, voxels: np.ndarray, probs, channels=None, n_subsets=None,
                 counts: np.ndarray | None = None, occupied: tuple | None = None):
        self.grid = grid
        self.voxels = np.asarray(voxels, dtype=np.int64)
        self.channels = tuple(channels) if channels is not None else ("empty",) + CLASSES[1:]
        self.n_subsets = n_subsets
        self._counts = counts
        self._cache: dict = {}
        shape = (len(self.voxels), len(self.channels))
        if occupied is not None:
            if counts is not None or not n_subsets:
                raise ValueError("PSOG takes counts or their occupied entries (with n_subsets >= 1), not both")
            self._cache["occupied"] = (np.asarray(occupied[0]), np.asarray(occupied[1]))
        if probs is None:
            if (counts is None and occupied is None) or not n_subsets:
                raise ValueError("PSOG needs probs, or integer counts and n_subsets >= 1 to derive them")
            if occupied is None and np.shape(counts) != shape:
                raise ValueError(f"PSOG counts must be (M={shape[0]}, K={shape[1]}), got {np.shape(counts)}")
            self._probs = None
            self._cache["probs_from_counts"] = True
        elif callable(probs):
            self._probs = None
            self._cache["probs_of"] = probs
        else:
            self._probs = np.asarray(probs, dtype=np.float64)
            if self._probs.shape != shape:
                raise ValueError(f"PSOG probs must be (M={shape[0]}, K={shape[1]}), got {self._probs.shape}")
        # (rows, T, task): integer count rows whose table fields (``_count_fields``) are this P-SOG's weights and stop
        # mask, row for row; set where the probabilities are known to be counts / T (``_count_source``)
        self._rows_of = None
        self.sha256: str | None = None      # of the file last written by ``save``

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        if "probs_of" in self._cache:               # a closure does not pickle: its probabilities do
            state["_probs"] = self.probs
            state["_cache"] = {k: v for k, v in self._cache.items() if k != "probs_of"}
        return state

    @property
    def occupied(self) -> tuple | None:
        """The ``occupied`` entries the P-SOG was made with (a cache file's: flat indices into ``counts[:, 1:]``
        and their counts), or None."""
        return self._cache.get("occupied")

    @property
    def counts(self) -> np.ndarray | None:
        """(M, K) integer subset counts, or None (built from probabilities); from the occupied entries a cache
        file stores, made on first use (two threads may both make them: the same values)."""
        if self._counts is None and "occupied" in self._cache:
            self._counts = _dense_counts(*self._cache["occupied"], len(self.voxels), len(self.channels),
                                         self.n_subsets)
        return self._counts

    @property
    def probs(self) -> np.ndarray:
        """(M, K) float64 class probabilities (``counts / T`` on first use where made from counts)."""
        if self._probs is None:
            # two threads may both make them (a background preparation and the command): the same values
            make = self._cache.get("probs_of")             # a variant derived from another P-SOG's probs
            self._probs = make() if make is not None else self.counts / float(self.n_subsets)
        return self._probs

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_probabilities(cls, grid: Grid, probs: np.ndarray, channels=None) -> "PSOG":
        """From a dense (nx, ny, nz, K) array: channel 0 = empty, channel c = class c."""
        p = np.asarray(probs, dtype=np.float64)
        if p.ndim != 4 or p.shape[:3] != grid.shape:
            raise ValueError(f"probs must have shape {grid.shape} + (K,), got {p.shape}")
        if not np.all(np.isfinite(p)) or p.min() < 0:
            raise ValueError("probs must be finite and non-negative")
        s = p.sum(axis=-1)
        if np.max(np.abs(s - 1.0)) > 1e-6:
            i = np.unravel_index(int(np.argmax(np.abs(s - 1.0))), s.shape)
            raise ValueError(f"probs must sum to 1 over the last axis; voxel {tuple(int(v) for v in i)} sums to {s[i]}")
        flat = p.reshape(-1, p.shape[-1])
        keep = np.flatnonzero(flat[:, 0] < 1.0)
        if channels is None and p.shape[-1] != len(CLASSES):
            channels = ("empty",) + tuple(f"class {c}" for c in range(1, p.shape[-1]))
        return cls(grid, keep, flat[keep], channels)

    @classmethod
    def from_frames(cls, frames: list[PointCloud], grid: Grid, frames_per_subset: int = 5, backend=None,
                    progress: bool = False) -> "PSOG":
        """Build from labelled frames (docs/architecture.md, "P-SOG").

        Consecutive subsets of ``frames_per_subset`` frames are merged in the ego frame of their middle
        frame, voxelised with a majority vote (ties -> lowest class, unlabeled points do not vote), and
        the per-voxel label frequencies over the T subsets form the P-SOG. Trailing frames that do not
        fill a subset are dropped (all frames form one subset when there are fewer than k).
        """
        votes = subset_votes(frames, grid, frames_per_subset, backend=backend, progress=progress)
        voxels, occupied = vote_entries(votes, grid.n_voxels)
        return cls(grid, voxels, None, n_subsets=len(votes), occupied=occupied)

    @classmethod
    def from_counts(cls, grid: Grid, voxels: np.ndarray, counts: np.ndarray, n_subsets: int) -> "PSOG":
        """From integer subset counts (M, K) of ``voxels`` over T = ``n_subsets`` subsets (column 0 =
        empty; each row sums to T): ``probs = counts / T``, the way ``from_frames`` and
        ``PooledPSOG.psog`` make them. ``counts`` is kept as int32."""
        c = np.asarray(counts)
        T = int(n_subsets)
        if c.ndim != 2 or not np.issubdtype(c.dtype, np.integer) or T < 1:
            raise ValueError(f"counts must be an (M, K) integer array over n_subsets >= 1 subsets, got "
                             f"{c.dtype} {c.shape} over {n_subsets}")
        # probs are counts / T to the bit, derived on first use (save then skips its check)
        return cls(grid, voxels, None, n_subsets=T, counts=c.astype(np.int32, copy=False))

    # ------------------------------------------------------------------ variants
    def detection(self) -> "PSOG":
        """Detection variant: channels (empty, vehicle, other occupied)."""
        if len(self.channels) == 3:
            return self
        if "det" not in self._cache:
            def probs():
                p = self.probs
                veh = p[:, VEHICLE] if p.shape[1] > VEHICLE else np.zeros(len(p))
                other = 1.0 - p[:, 0] - veh
                return np.stack([p[:, 0], veh, np.clip(other, 0.0, 1.0)], axis=1)

            src = self._count_source("det")
            # from counts: its fields come from the same count rows by the det tables, and its probabilities
            # are made only if read
            det = PSOG(self.grid, self.voxels, probs() if src is None else probs, ("empty", "vehicle", "other"),
                       self.n_subsets)
            det._rows_of = src
            self._cache["det"] = det
        return self._cache["det"]

    def _count_source(self, task: str):
        """(count rows, T, task) when this P-SOG's probabilities are its counts / T (known, never checked
        here), else None: the rows ``_count_fields`` turns into the ``task`` variant's weights and stop mask."""
        if self._rows_of is not None:
            return self._rows_of if task == self._rows_of[2] else None
        if self.counts is None or not self._cache.get("probs_from_counts") or len(self.channels) != N_CLASSES:
            return None
        return self.counts, int(self.n_subsets), task

    def _count_fields(self) -> bool:
        """Make the weights (int64) and stop flags (bool) of the stored voxels from their count rows
        (``_count_source``) in one pass, in blocks of ``ENTROPY_BLOCK`` rows on threads (``threads.block_map``),
        into the "weight rows" and "stop rows" caches; False without count rows."""
        src = self._count_source("seg" if len(self.channels) == N_CLASSES else "det")
        if src is None:
            return False
        from place3d_kernels.left_out_tables import fields_of

        rows, T, task = src
        f = fields_of(T, task)
        w, s = np.empty(len(rows), dtype=np.int64), np.empty(len(rows), dtype=bool)

        def block(a: int, b: int) -> None:
            w[a:b], s[a:b] = f(rows[a:b])

        block_map(block, len(rows), ENTROPY_BLOCK, rows.shape[1])
        self._cache["weight rows"] = w
        self._cache.setdefault("stop rows", s)      # the same bits as stop_rows made alone, if it was read first
        return True

    def for_task(self, task: str) -> "PSOG":
        if task == "seg":
            return self
        if task == "det":
            return self.detection()
        raise ValueError(f"task must be 'seg' or 'det', got {task!r}")

    # ------------------------------------------------------------------ derived fields
    @property
    def entropy(self) -> np.ndarray:
        """(nx, ny, nz) float32 voxel entropy (nats)."""
        if "entropy" not in self._cache:
            h = np.zeros(self.grid.n_voxels, dtype=np.float32)
            h[self.voxels] = entropy(self.probs)
            self._cache["entropy"] = h.reshape(self.grid.shape)
        return self._cache["entropy"]

    @property
    def weight_rows(self) -> np.ndarray:
        """(M,) int64: ``weights`` at the stored voxels (every other voxel's weight is 0)."""
        if "weight rows" not in self._cache and not self._count_fields():
            self._cache["weight rows"] = np.rint(entropy(self.probs) * ENTROPY_SCALE).astype(np.int64)
        return self._cache["weight rows"]

    @property
    def stop_rows(self) -> np.ndarray:
        """(M,) bool: ``stop_mask`` at the stored voxels (every other voxel is empty and stops no ray)."""
        if "stop rows" not in self._cache:
            src = self._count_source("seg" if len(self.channels) == N_CLASSES else "det")
            # p(empty) = c / T from the count rows' empty column, as ``probs`` and the field tables divide: the
            # flags alone, without the weights ``_count_fields`` makes with them (a backend that computes
            # fields has the weights on its device: the plot's coverage mask was the only host reader, and
            # the weights were most of its time)
            p0 = self.probs[:, 0] if src is None else np.asarray(src[0])[:, 0] / float(src[1])
            self._cache["stop rows"] = (1.0 - p0) >= 0.5 - 1e-12
        return self._cache["stop rows"]

    def has_entropy(self) -> bool:
        """Whether some stored voxel has a weight > 0 (``weight_rows.any()``). From the count rows where the
        weights were not made (a backend computing fields makes them on the device): a row has entropy exactly
        when no class holds all T subsets, and its weight round(H * 2**32) is then > 0, since
        H >= (ln T + 1) / T - O(1/T^2) > 2**-33 for every T below 2**31."""
        src = None if "weight rows" in self._cache else self._count_source("seg")
        if src is None:
            return bool(self.weight_rows.any())
        rows, T, _ = src
        rows = np.asarray(rows)
        # in ``ENTROPY_BLOCK`` rows, stopping at the first block with a row below T: a P-SOG has such rows all over
        # (the whole scan of the default pooled P-SOG's 1.4 M rows took 0.05 s of a warm command on the dev VM)
        return any(bool((rows[a:a + ENTROPY_BLOCK].max(axis=1) < T).any())
                   for a in range(0, len(rows), ENTROPY_BLOCK))

    @property
    def weights(self) -> np.ndarray:
        """(n_voxels,) int64 fixed-point entropy, round(H * 2**32): what kernels sum exactly."""
        if "weights" not in self._cache:
            w = np.zeros(self.grid.n_voxels, dtype=np.int64)
            w[self.voxels] = self.weight_rows
            self._cache["weights"] = w
        return self._cache["weights"]

    @property
    def occupancy(self) -> np.ndarray:
        """(nx, ny, nz) float32 probability that a voxel is occupied (1 - p_empty)."""
        occ = np.zeros(self.grid.n_voxels, dtype=np.float32)
        occ[self.voxels] = 1.0 - self.probs[:, 0]
        return occ.reshape(self.grid.shape)

    @property
    def stop_mask(self) -> np.ndarray:
        """(n_voxels,) uint8: 1 where the voxel is occupied with probability >= 0.5 (stops rays)."""
        if "stop" not in self._cache:
            m = np.zeros(self.grid.n_voxels, dtype=np.uint8)
            m[self.voxels] = self.stop_rows
            self._cache["stop"] = m
        return self._cache["stop"]

    def dense(self) -> np.ndarray:
        """(nx, ny, nz, K) float32 probabilities (memory: n_voxels * K * 4 bytes)."""
        out = np.zeros((self.grid.n_voxels, len(self.channels)), dtype=np.float32)
        out[:, 0] = 1.0
        out[self.voxels] = self.probs
        return out.reshape(self.grid.shape + (len(self.channels),))

    def handle(self, backend, occlusion: str):
        """Backend grid handle (weights + stop mask uploaded once) for one occlusion mode: made from the
        stored voxels' rows (``Backend.grid_from_rows``), so no dense host array is needed where the backend
        fills the grid itself."""
        key = ("handle", backend, occlusion)   # the object: same-named instances may differ in context
        if key not in self._cache:
            rows = self._device_rows(backend)
            w, s = rows if rows is not None else (self.weight_rows, self.stop_rows)
            self._cache[key] = backend.grid_from_rows(self.grid.spec, self.voxels, w, s if occlusion == "sog" else None)
        return self._cache[key]

    def _device_rows(self, backend):
        """(weights, stop) of the stored voxels as device arrays, made on ``backend`` from the count rows
        (``left_out_tables.device_row_fields``: the bits ``weight_rows`` and ``stop_rows`` hold), where the
        backend computes fields (``fields_on_device``: Warp on CUDA, OpenCL GPUs with doubles), the P-SOG has
        count rows, T is at most ``FieldTables.MAX_T`` and the host's rows were not made already; else None."""
        if not getattr(backend, "fields_on_device", False) or "weight rows" in self._cache:
            return None
        src = self._count_source("seg" if len(self.channels) == N_CLASSES else "det")
        from place3d_kernels.left_out_tables import FieldTables, device_row_fields

        if src is None or src[1] > FieldTables.MAX_T or np.asarray(src[0]).dtype.itemsize > 4:
            return None
        key = ("device rows", backend)
        if key not in self._cache:
            self._cache[key] = device_row_fields(src[0], src[1], src[2], backend)
        return self._cache[key]

    # ------------------------------------------------------------------ persistence
    def save(self, path) -> Path:
        """Write the P-SOG to ``path`` atomically (``atomic.atomic_write``); ``self.sha256`` is then the
        sha256 of the bytes written, which the cache's manifest records (``pipeline.scene_psog``)."""
        from place3d_kernels.atomic import atomic_write
        from place3d_kernels.manifest import content_hash

        arrays = dict(voxels=self.voxels, meta=json.dumps({"grid": self.grid.to_dict(), "channels": list(self.channels),
                                                           "n_subsets": self.n_subsets, "format": _FORMAT}))
        occupied = self.occupied
        # the entries the P-SOG was made with are its counts' _counts_members (a file's, or vote_entries'):
        # written as they are, without the dense table
        arrays.update(_counts_members(self.counts, self.n_subsets) if occupied is None else
                      {"occupied_index": occupied[0], "occupied_counts": occupied[1]})
        # probs left out when they are counts / T to the bit (P-SOGs from frames): a third of the bytes to
        # decompress on every cached load, a visible part of a warm optimise (more beside other work)
        if not self.probs_are_counts():
            arrays["probs"] = self.probs
        data = _npz_bytes(arrays)
        # processes that build the same cached P-SOG at once (tests, Ray workers) each write a temporary
        # file of their own, and the last rename wins with identical content
        atomic_write(path, data)
        self.sha256 = content_hash(data)
        return Path(path)

    def probs_are_counts(self) -> bool:
        """Whether ``probs`` is ``counts / n_subsets`` to the bit (P-SOGs from frames or subset records, and
        loaded from their files); known without a look at the arrays where the P-SOG was made so, else
        checked (and remembered: a P-SOG's arrays do not change after it is made)."""
        if "probs_from_counts" not in self._cache:
            self._cache["probs_from_counts"] = (
                self.counts is not None and bool(self.n_subsets) and self.counts.shape == self.probs.shape
                and np.array_equal(self.probs, self.counts / float(self.n_subsets)))
        return self._cache["probs_from_counts"]

    @classmethod
    def load(cls, path, check=None) -> "PSOG":
        """The P-SOG saved at ``path`` (by ``save``); the one already in memory if ``keep_loaded`` allows.

        ``check``: optional ``check() -> bytes``, the file's bytes once verified (``manifest.verified_bytes``),
        called whenever the file is read (not for a P-SOG kept in memory: it was checked when read, and a
        rewritten file has another identity)."""
        if not _LOADED.keeps:
            return cls._read(path, check)
        key = file_identity(path)            # None (absent): the read raises what it raises without keep_loaded
        psog = _LOADED.get(key)
        if psog is None:
            psog = cls._read(path, check)
            _LOADED.put(key, psog)
        return psog

    @classmethod
    def _read(cls, path, check=None) -> "PSOG":
        z = _npz_arrays(Path(path).read_bytes() if check is None else check())
        meta = json.loads(str(z["meta"]))
        voxels, T = z["voxels"], meta["n_subsets"]
        occupied, counts = None, None
        if "occupied_index" in z:                   # _counts_members' sparse layout: dense counts on first use
            occupied = (z["occupied_index"], z["occupied_counts"])
        elif z["counts"].size:
            counts = z["counts"]
        # files without probs stored them as counts / T (save checked that this gives the same bits): the
        # P-SOG derives them from the counts when read
        probs = z.get("probs")
        return cls(Grid.from_dict(meta["grid"]), voxels, probs, meta["channels"], T, counts, occupied=occupied)

    def __repr__(self) -> str:
        return (f"PSOG(grid {self.grid.shape} @ {self.grid.voxel_size} m, {len(self.voxels):,} occupied voxels, "
                f"T={self.n_subsets}, {len(self.channels)} channels)")


#: zlib level per member of a saved P-SOG (others: zlib's default, 6, as ``np.savez_compressed`` uses).
#: The ascending voxel ids and occupied-entry indices compress at level 1 to within a few percent of level
#: 6's size in a fraction of its time, and inflate as fast; so do the occupied entries' counts (small
#: integers). A dense counts table (P-SOGs not made from frames) keeps level 6, which halves its size.
_ZLIB_LEVEL = {"voxels": 1, "occupied_index": 1, "occupied_counts": 1}


def _counts_members(counts, T) -> dict:
    """The subset counts as saved: where column 0 (empty) is T minus the others, as in every P-SOG made from
    frames or records, only the occupied entries (``occupied_index``, row-major flat indices into
    ``counts[:, 1:]``, and ``occupied_counts``): a voxel has one or two of its classes, so these are a small
    share of the dense (M, K) int32 table that each save deflated and each load inflated whole. Otherwise
    the dense table (``counts``; empty where there are none)."""
    if counts is None:
        return {"counts": np.zeros(0)}
    c = np.asarray(counts)
    if c.ndim == 2 and c.shape[1] > 1 and T and np.array_equal(c[:, 0], int(T) - c[:, 1:].sum(axis=1)):
        occ = c[:, 1:]
        v, k = np.nonzero(occ)                              # row-major, on the view (no copy of the table)
        at = v.astype(np.int32 if occ.size < 2**31 else np.int64) * (c.shape[1] - 1) + k
        return {"occupied_index": at, "occupied_counts": occ[v, k].astype(np.int32)}
    return {"counts": c}


def _dense_counts(index, values, M: int, K: int, T: int) -> np.ndarray:
    """(M, K) int32 counts from ``_counts_members``' occupied entries: column 0 = T minus the others."""
    occ = np.zeros(M * (K - 1), dtype=np.int32)
    occ[index] = values
    occ = occ.reshape(M, K - 1)
    c = np.empty((M, K), dtype=np.int32)
    c[:, 1:] = occ
    c[:, 0] = int(T) - occ.sum(axis=1)
    return c


def _npz_bytes(arrays: dict) -> bytes:
    """The bytes ``np.savez_compressed(f, **arrays)`` would write, with the zlib level of ``_ZLIB_LEVEL`` per
    member: the same .npz layout (one deflated ``NAME.npy`` per array), so ``np.load`` gives the same arrays."""
    import io
    import zipfile

    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, value in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(value), allow_pickle=False)
            zf.writestr(f"{name}.npy", buf.getvalue(), compresslevel=_ZLIB_LEVEL.get(name, 6))
    return out.getvalue()


def _npz_arrays(data: bytes) -> dict:
    """The arrays of an .npz file's bytes, as ``np.load`` gives them (writable, same dtypes and shapes; no pickled
    objects), each member inflated in one call. ``np.load`` reads a member in 256 KB pieces, each its own zlib
    call that lets go of the interpreter lock and takes it back: beside a thread busy in Python (a command's
    backend probe importing Warp while its drives are read) every piece waits for the lock, and four default
    drives read side by side took 0.83-0.88 s on the dev VM against 0.21-0.29 s so (0.10-0.12 s alone either
    way; bench/results/ab-2026-11-30-s34/README.md)."""
    import io
    import zipfile

    from numpy.lib import format as npy

    out = {}
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        for name in zf.namelist():
            raw = zf.read(name)                         # inflated whole, its CRC checked
            f = io.BytesIO(raw)
            major, _ = npy.read_magic(f)
            shape, fortran, dtype = (npy.read_array_header_1_0 if major == 1 else npy.read_array_header_2_0)(f)
            if dtype.hasobject:
                raise ValueError(f"{name}: object arrays are not read (allow_pickle=False)")
            flat = np.frombuffer(raw, dtype=dtype, count=int(np.prod(shape, dtype=np.int64)), offset=f.tell())
            out[name.removesuffix(".npy")] = (flat.reshape(shape[::-1]).T if fortran else flat.reshape(shape)).copy()
    return out


def cache_key(**inputs) -> str:
    """Stable hash of JSON-able inputs, for on-disk caches."""
    blob = json.dumps({"format": _FORMAT, **inputs}, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:20]
