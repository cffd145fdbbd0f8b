"""Pooled P-SOGs: one P-SOG from many drives (routes x scenes), the way the paper built its own.

The paper builds its P-SOG from the training scenes of a dataset over four CARLA towns (Li et al.,
NeurIPS 2024, Sec. 4 "P-SOG Synthesis": Towns 1, 3, 4, 6 with six ego routes each), not from one
40-frame drive. A pooled P-SOG sums each voxel's per-class subset counts over every subset of every
drive, so ``p(v = c) = count(v, c) / T_total`` with ``T_total`` the number of subsets of all drives.

Each drive goes through ``pipeline.scene_psog`` (cached on disk per drive by its inputs), so adding a
route reuses the P-SOGs of the others; only its sparse per-class counts are kept (a ``DriveRecord``,
a few MB at 0.2 m), so memory grows with the number of occupied voxels, never with frames. Keeping the
records separate makes resampling cheap: a bootstrap over drives (``uncertainty.py``) re-weights the
records and sums again, without simulating anything.

    >>> from place3d_kernels.pooled import Drive, build_pooled
    >>> drives = [Drive("opendrive:Town01.xodr", seed=s) for s in range(4)]
    >>> pooled = build_pooled(drives)                 # or executor=get_executor("ray")
    >>> psog = pooled.psog()                          # a PSOG like any other (counts included)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from place3d_kernels.classes import N_CLASSES
from place3d_kernels.grid import Grid, roi_grid
from place3d_kernels.pool_memo import keep_pool, kept_pool, pool_files_key
from place3d_kernels.backends.base import unique_ints
from place3d_kernels.sog import PSOG
from place3d_kernels.threads import thread_map, threads_for, usable_cores

__all__ = ["Drive", "PoolSettings", "DriveRecord", "PooledPSOG", "build_pooled", "drive_record",
           "subset_records", "backend_name", "parse_route_seeds", "pool_specs", "cached_records", "scene_groups",
           "DEFAULT_ROUTES"]

#: Routes per scene of the commands' default pooled P-SOG: the smallest count at which the order of the
#: paper's placements no longer moved when the routes were doubled (bench/route_convergence.py; the
#: measurement is in docs/guide.md, "How many routes").
DEFAULT_ROUTES = 4

#: Grids up to this many voxels pool through a flag and a row per grid voxel (``PooledPSOG.counts``, 1 + 4 bytes
#: a voxel: 160 MB on the default 0.1 m grid); larger ones sort and binary-search the records' voxels instead.
RANK_VOXELS = 2**26


@dataclass(frozen=True)
class Drive:
    """One ego route on one scene: ``scene`` is 'town' or 'opendrive:PATH'; ``seed`` picks the route
    (and the generated roadside content and traffic); ``frames`` its length."""

    scene: str = "town"
    seed: int = 0
    frames: int = 40

    def spec(self):
        from place3d_kernels.spec import SceneSpec

        return SceneSpec(self.scene, int(self.seed), int(self.frames))

    def build(self):
        """The ``Scene`` (rebuilt deterministically from the three fields)."""
        return self.spec().build()

    @property
    def label(self) -> str:
        return self.spec().label


@dataclass(frozen=True)
class PoolSettings:
    """Everything besides the drive that decides a per-drive P-SOG (the inputs of ``scene_psog``).

    Args:
        voxel_size: ROI voxel edge in metres (None: ``DEFAULT_GRID``'s 0.1 m).
        lidar: the collection LiDAR (name or TOML path) that records the drives.
        frames_per_subset: k frames merged per SOG (None: ``pipeline.DEFAULT_FRAMES_PER_SUBSET``).
        backend: backend name (None: ``$PLACE3D_BACKEND`` or auto, resolved once in the driver).
        cache: P-SOG cache folder (None: ``sog.cache_dir()``); False disables the cache.
        roi: the ROI box: None (``DEFAULT_GRID``'s 80 x 80 x 5 m), 3 sizes or 6 corners in metres
            (``grid.roi_bounds``). It is part of the grid, so of every per-drive P-SOG's cache key.
    """

    voxel_size: float | None = None
    lidar: str = "collection_64ch"
    frames_per_subset: int | None = None
    backend: str | None = None
    cache: Any = None
    roi: tuple | None = None

    def __post_init__(self):
        if self.roi is not None:
            object.__setattr__(self, "roi", tuple(float(x) for x in self.roi))

    @property
    def grid(self) -> Grid:
        return roi_grid(self.roi, self.voxel_size)

    @property
    def k(self) -> int:
        from place3d_kernels.pipeline import DEFAULT_FRAMES_PER_SUBSET

        return int(self.frames_per_subset or DEFAULT_FRAMES_PER_SUBSET)

    def to_dict(self) -> dict:
        return {"voxel_size": self.grid.voxel_size, "roi": None if self.roi is None else list(self.roi),
                "collection_lidar": self.lidar, "frames_per_subset": self.k, "backend": self.backend}


@dataclass
class DriveRecord:
    """The sparse per-class subset counts of one drive (or one subset): what pooling sums.

    Attributes:
        label: which drive (``Drive.label``, or ``label#subset`` for a single subset).
        n_subsets: T of this drive.
        voxels: (E,) int64 flat voxel index of each entry (ascending, a voxel repeats per class).
        classes: (E,) int16 class (1..K-1; "empty" is implied: T minus the occupied counts).
        counts: (E,) int32 number of subsets in which the voxel had that class (> 0).
    """

    label: str
    n_subsets: int
    voxels: np.ndarray
    classes: np.ndarray
    counts: np.ndarray

    @classmethod
    def from_psog(cls, psog: PSOG, label: str) -> "DriveRecord":
        """From a P-SOG built by ``PSOG.from_frames`` (it carries integer counts)."""
        occupied = psog.occupied                     # a P-SOG read from the cache: its entries as stored, and
        if occupied is None and (psog.counts is None or psog.n_subsets is None):    # no dense counts made
            raise ValueError(f"{label}: the P-SOG has no subset counts (built from probabilities?); pooling "
                             f"needs a P-SOG from PSOG.from_frames / scene_psog")
        if occupied is not None:
            at, cnt = occupied
            v, k = np.divmod(at.astype(np.int64), len(psog.channels) - 1)
            return cls(label, int(psog.n_subsets), psog.voxels[v], (k + 1).astype(np.int16), cnt.astype(np.int32))
        c = np.asarray(psog.counts)[:, 1:]
        v, k = np.nonzero(c)                                  # row-major: voxels stay ascending
        return cls(label, int(psog.n_subsets), psog.voxels[v].astype(np.int64), (k + 1).astype(np.int16),
                   c[v, k].astype(np.int32))

    @classmethod
    def merge(cls, parts: Sequence["DriveRecord"], n_classes: int = N_CLASSES) -> "DriveRecord":
        """One drive's record from records of disjoint sets of its subsets (``PSOGSpec.build_part``): the
        entries of equal (voxel, class) summed, T the parts' T summed, the label the first part's. The counts
        are integer sums, so they are the record of the drive built whole, to the bit."""
        if not parts:
            raise ValueError("DriveRecord.merge needs at least one part")
        if len(parts) == 1:
            return parts[0]
        key = np.concatenate([r.voxels * n_classes + r.classes for r in parts])
        counts = np.concatenate([r.counts for r in parts])
        # each part's keys ascend (voxel, then class): a stable sort merges the runs
        order = np.argsort(key, kind="stable")
        key, counts = key[order], counts[order]
        starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]])) if len(key) else np.zeros(0, np.int64)
        summed = np.add.reduceat(counts, starts).astype(np.int32) if len(key) else counts
        key = key[starts]
        return cls(parts[0].label, int(sum(r.n_subsets for r in parts)), key // n_classes,
                   (key % n_classes).astype(np.int16), summed)

    @property
    def nbytes(self) -> int:
        return int(self.voxels.nbytes + self.classes.nbytes + self.counts.nbytes)


class PooledPSOG:
    """Per-drive records over one grid and their pooled P-SOG.

    Args:
        grid: the ROI grid shared by every record.
        records: ``DriveRecord`` list (more can be ``add``-ed).
        n_classes: K channels (channel 0 = empty).
    """

    def __init__(self, grid: Grid, records: Sequence[DriveRecord] = (), n_classes: int = N_CLASSES):
        self.grid = grid
        self.n_classes = int(n_classes)
        self.records: list[DriveRecord] = []
        self._union = self._plain = self._spans = self._plain_counts = self._rank = None
        self._plain_psog = None      # a P-SOG known to be exactly the plain pool (``known_plain``)
        #: what other modules derive from these records and keep with the pool (``left_out.LeftOutRows.shared``);
        #: emptied when a record is added
        self.derived: dict = {}
        #: kept between commands (``pool_memo.keep_pool``): records can no longer be added
        self.shared = False
        for r in records:
            self.add(r)

    def add(self, record: DriveRecord) -> None:
        if self.shared:
            raise ValueError("this pool is kept between commands (pool_memo) and shared; extend a copy: "
                             "PooledPSOG(pool.grid, pool.records)")
        if record.classes.size and int(record.classes.max()) >= self.n_classes:
            raise ValueError(f"{record.label}: class {int(record.classes.max())} outside the {self.n_classes} channels")
        self.records.append(record)
        self._union = self._plain = self._spans = self._plain_counts = self._plain_psog = self._rank = None
        self.derived = {}

    @property
    def labels(self) -> list[str]:
        return [r.label for r in self.records]

    @property
    def n_subsets(self) -> int:
        """T_total over all records."""
        return int(sum(r.n_subsets for r in self.records))

    def __len__(self) -> int:
        return len(self.records)

    def __repr__(self) -> str:
        mb = sum(r.nbytes for r in self.records) / 2**20
        return (f"PooledPSOG({len(self)} drives, T={self.n_subsets}, grid {self.grid.shape} @ "
                f"{self.grid.voxel_size} m, {mb:.1f} MB of counts)")

    def subset(self, indices) -> "PooledPSOG":
        """The pool of the chosen records only (same grid)."""
        return PooledPSOG(self.grid, [self.records[i] for i in indices], self.n_classes)

    # ------------------------------------------------------------------ pooling
    def _prepare(self):
        """Union of (voxel, class) keys over the records, computed once per record set."""
        if self._union is None:
            if not self.records:
                raise ValueError("PooledPSOG has no drives; add DriveRecords or use build_pooled(drives)")
            K = self.n_classes
            keys = np.concatenate([r.voxels * K + r.classes for r in self.records])
            counts = np.concatenate([r.counts for r in self.records]).astype(np.int64)
            owner = np.concatenate([np.full(len(r.voxels), i, np.int64) for i, r in enumerate(self.records)])
            ukeys, inv = np.unique(keys, return_inverse=True)
            uvox, vinv = np.unique(ukeys // K, return_inverse=True)
            self._union = (ukeys % K, inv, counts, owner, uvox, vinv)
        return self._union

    def _plain_sums(self) -> np.ndarray:
        """Per (voxel, class) key: the counts summed over every record taken once (memoised)."""
        if self._plain is None:
            cls_, inv, counts, _, _, _ = self._prepare()
            self._plain = np.rint(np.bincount(inv, weights=counts.astype(np.float64),
                                              minlength=len(cls_))).astype(np.int64)
            self._spans = np.concatenate([[0], np.cumsum([len(r.voxels) for r in self.records])])
        return self._plain

    def counts(self, multiplicity=None) -> tuple[np.ndarray, np.ndarray, int]:
        """Pooled integer counts.

        Args:
            multiplicity: (D,) non-negative integers, how many times each record enters the pool
                (a bootstrap resample); None = each once.

        Returns:
            voxels (M,) int64 ascending, counts (M, K) int32 (int64 if T_total reaches 2**31; column 0 = empty),
            T_total; voxels never
            occupied in the weighted pool are left out, as ``PSOG.from_frames`` leaves them out. For
            ``multiplicity=None`` the same read-only arrays on every call.
        """
        if multiplicity is None and self._plain_counts is None and self._plain_psog is not None:
            # the pool's own P-SOG (known_plain): its voxels and counts are these sums, without summing
            ps = self._plain_psog
            vox, out = ps.voxels.copy(), ps.counts.astype(_count_dtype(ps.n_subsets))
            vox.setflags(write=False)
            out.setflags(write=False)
            self._plain_counts = (vox, out, int(ps.n_subsets))
        if multiplicity is None and self._plain_counts is not None:
            return self._plain_counts
        if multiplicity is None and self._union is None:
            return self._sum_plain()
        cls_, inv, counts, owner, uvox, vinv = self._prepare()
        D = len(self.records)
        T_each = np.array([r.n_subsets for r in self.records], dtype=np.int64)
        if multiplicity is None:
            m = np.ones(D, dtype=np.int64)
        else:
            m = np.asarray(multiplicity)
            if m.shape != (D,) or np.any(m < 0) or not np.all(m == np.round(m)):
                raise ValueError(f"multiplicity must be {D} non-negative integers (one per drive), got {m!r}")
            m = m.astype(np.int64)
        T = int((T_each * m).sum())
        if T <= 0:
            raise ValueError("the weighted pool has no subsets (all multiplicities zero)")
        changed = np.flatnonzero(m != 1)
        if len(changed) <= max(1, D // 4):
            # few records weighted other than once (a jackknife leaves one out): the sums of the plain
            # pool, corrected record by record; integers, so the same sums as summing from scratch
            summed = self._plain_sums().copy()
            for j in changed:
                a, b = self._spans[j], self._spans[j + 1]      # record j's entries are contiguous
                summed += (m[j] - 1) * np.bincount(inv[a:b], weights=counts[a:b].astype(np.float64),
                                                   minlength=len(cls_)).round().astype(np.int64)
        else:
            w = counts * m[owner]
            # integer sums: bincount with float weights is exact below 2**53, far above any subset count
            summed = np.rint(np.bincount(inv, weights=w.astype(np.float64), minlength=len(cls_))).astype(np.int64)
        out = np.zeros((len(uvox), self.n_classes), dtype=_count_dtype(T))
        out[vinv, cls_] = summed
        occ = _occupied(out)
        keep = occ > 0
        if keep.all():              # every voxel still occupied (the plain pool, a jackknife): no row copy
            vox = uvox.copy()
        else:
            # rows by index: the rows a boolean mask selects, without its slow 2-D path
            rows = np.flatnonzero(keep)
            out, vox, occ = out.take(rows, axis=0), uvox[rows], occ[rows]
        out[:, 0] = T - occ
        if multiplicity is None:
            # every record once is asked for several times per interval (the point, each task's left-out
            # grids): kept, read-only, so no caller can change what the next one reads
            vox.setflags(write=False)
            out.setflags(write=False)
            self._plain_counts = (vox, out, T)
        return vox, out, T

    def _sum_plain(self) -> tuple[np.ndarray, np.ndarray, int]:
        """``counts()`` of the plain pool (every record once) summed record by record into the rows of the
        union of their voxels, without the (voxel, class) union that resampling needs (``_prepare``, a sort of
        every entry): the same integer sums, so the same arrays."""
        if not self.records:
            raise ValueError("PooledPSOG has no drives; add DriveRecords or use build_pooled(drives)")
        n = self.grid.n_voxels
        rank = None
        if n <= RANK_VOXELS:
            # a flag per grid voxel and each stored voxel's row by position: no sort of every record's voxels
            # and no binary search per entry (the pool of 32 drives at 0.1 m: some 18 M entries)
            seen = np.zeros(n, dtype=bool)
            t = threads_for(sum(len(r.voxels) for r in self.records))

            def mark(j: int) -> None:       # thread j marks every t-th record (each write stores the same True)
                for r in self.records[j::t]:
                    seen[r.voxels] = True

            thread_map(mark, range(t), t)
            vox = np.flatnonzero(seen)
            del seen
            rank = np.empty(n, dtype=np.int64 if len(vox) >= 2**31 else np.int32)   # read at stored voxels only
            rank[vox] = np.arange(len(vox), dtype=rank.dtype)
        else:
            vox = unique_ints(np.concatenate([r.voxels for r in self.records]))
        out = np.zeros((len(vox), self.n_classes), dtype=_count_dtype(self.n_subsets))
        _add_records(out, vox, rank, self.records)
        occ = _occupied(out)
        rows = np.flatnonzero(occ > 0)
        if len(rows) < len(vox):                    # entries of count 0 only: not stored, as counts() leaves them
            out, vox, occ = out.take(rows, axis=0), vox[rows], occ[rows]
            rank = None
        T = self.n_subsets
        out[:, 0] = T - occ
        vox.setflags(write=False)
        out.setflags(write=False)
        self._plain_counts = (vox, out, T)
        self._rank = rank
        return self._plain_counts

    def rows_of(self, voxels: np.ndarray) -> np.ndarray:
        """The row of each of ``voxels`` (voxels the plain pool stores) in ``counts()``'s arrays: by the rank
        array ``counts()`` kept where the grid allows (``RANK_VOXELS``), else by binary search."""
        vox = self.counts()[0]
        rank = getattr(self, "_rank", None)
        return np.searchsorted(vox, voxels) if rank is None else rank[voxels].astype(np.intp, copy=False)

    def known_plain(self, psog: PSOG) -> None:
        """Take ``psog`` as exactly this pool's P-SOG (every record once: the same voxels, counts, T and
        float64 probabilities), as ``left_out.HANDLES`` knows it for records it has seen pooled: ``counts()``
        then reads its arrays instead of summing the records. Only for a P-SOG known so (not checked here)."""
        self._plain_psog = psog

    def plain_psog(self, reference: PSOG | None = None) -> PSOG:
        """``psog()`` (every record once), or ``reference`` itself when it is exactly that P-SOG: the same
        grid, voxels, counts, T and float64 probabilities (checked here). The scene's own P-SOG is, for
        records of its drive; reusing it reuses its weights and the grids already on the device. A reference
        given to ``known_plain`` is returned unchecked."""
        if reference is not None and reference is self._plain_psog:
            return reference                    # known to be exactly this pool's P-SOG (``known_plain``)
        vox, c, T = self.counts()
        if (reference is not None and reference.n_subsets == T and reference.counts is not None
                and reference.grid.to_dict() == self.grid.to_dict() and len(reference.channels) == self.n_classes
                and np.array_equal(reference.voxels, vox) and np.array_equal(reference.counts, c)
                and reference.probs_are_counts()):      # its counts are c and its T is T: probs == c / T
            return reference
        return PSOG.from_counts(self.grid, vox, c, T)

    def kept_psog(self) -> PSOG:
        """``psog()``, made on the first call and kept with the pool (as ``known_plain``'s): a pool kept between
        commands (``pool_memo``) keeps its P-SOG, and what that P-SOG derives on first use (weights, stop mask,
        each backend's prepared grids), with it."""
        if self._plain_psog is None:
            self._plain_psog = self.psog()
        return self._plain_psog

    def psog(self, multiplicity=None) -> PSOG:
        """The pooled P-SOG: ``p(v = c) = count / T_total`` (see ``counts`` for ``multiplicity``).

        With one record this is that drive's P-SOG exactly (same voxels, counts and float64 probs).
        """
        vox, c, T = self.counts(multiplicity)
        return PSOG.from_counts(self.grid, vox, c, T)


def _add_records(out: np.ndarray, vox: np.ndarray, rank, records) -> None:
    """Add every record's counts into ``out`` ((len(vox), K) counts, one row per voxel of ``vox``, ascending;
    ``rank``: each grid voxel's row, or None to find rows by binary search).

    A record's entries are in voxel order, so a block of rows is a slice of every record: on several threads
    (``threads_for``) the rows are cut into one block per thread and each thread adds its block's slices (the
    blocks never share a row). Integer sums, so the same table as record after record on one thread."""
    n = threads_for(sum(len(r.voxels) for r in records))
    K = out.shape[1]
    flat = out.reshape(-1)
    cuts = vox[np.linspace(0, len(vox), n + 1).astype(np.int64)[1:-1]]      # first voxel of each later block
    # where each block starts and ends in each record
    ends = [np.concatenate([[0], np.searchsorted(r.voxels, cuts), [len(r.voxels)]]) for r in records]

    def block(j: int) -> None:
        for r, at in zip(records, ends):
            a, b = int(at[j]), int(at[j + 1])
            v, c = r.voxels[a:b], r.classes[a:b].astype(np.intp)
            rows = np.searchsorted(vox, v) if rank is None else rank[v]
            key = rows.astype(np.intp) * K + c
            if np.all(key[1:] > key[:-1]):         # each (voxel, class) once, as from_psog makes them: no repeats
                flat[key] += r.counts[a:b]
            else:
                np.add.at(flat, key, r.counts[a:b])

    thread_map(block, range(n), n)


def _occupied(counts: np.ndarray) -> np.ndarray:
    """Each row's occupied subsets, ``counts[:, 1:].sum(axis=1)``, summed in the counts' own integer type: a
    row's occupied counts add up to at most T (each subset gives a voxel one class), and ``_count_dtype`` holds
    T. ``einsum`` sums the strided rows some three times faster than ``sum`` (which widens int32 to int64):
    0.11 against 0.30 s for the 7 M rows of the 32-drive pool on the dev VM."""
    return np.einsum("ij->i", counts[:, 1:])


def _count_dtype(T: int):
    """The pooled counts' integer type: int32 (half the memory of int64, and the type a P-SOG keeps) while every
    count, at most T, fits."""
    return np.int32 if int(T) < 2**31 else np.int64


# ====================================================================== building
def drive_record(drive: Drive, settings: PoolSettings = PoolSettings(), save_in_background: bool = False,
                 scene=None) -> DriveRecord:
    """The record of one drive: its P-SOG from ``scene_psog`` (on-disk cache per drive), sparsified.
    ``save_in_background``: a newly built P-SOG is written to the cache on a thread (``scene_psog``); the
    caller waits for it with ``pipeline.wait_for_saves``. ``scene``: the drive's scene when the caller built it
    already (``drive.build()``)."""
    from place3d_kernels.pipeline import scene_psog

    cache = True if settings.cache is None else settings.cache
    ps = scene_psog(drive.build() if scene is None else scene, grid=settings.grid, lidar=settings.lidar,
                    frames_per_subset=settings.k,
                    backend=settings.backend, cache=cache, save_in_background=save_in_background)
    return DriveRecord.from_psog(ps, drive.label)


def backend_name(backend) -> str:
    """A backend name every task resolves alike: None / 'auto' resolve here, names pass through."""
    if backend is not None and not isinstance(backend, str):
        return backend.name
    if backend in (None, "auto"):
        from place3d_kernels.backends.registry import get_backend

        return get_backend(backend).name
    return backend


def _record_task(t) -> DriveRecord:
    drive, settings = t
    return drive_record(drive, settings)


def _records_task(t) -> list[DriveRecord]:
    # a worker's drives: every scene first (Python on the CPU), while the worker's backend starts on its own thread
    # (executors._start_worker): sixteen workers starting CUDA on one GPU at once took 2.3-2.8 s each on an H200
    # host against 0.5 s for one (2026-11-29), longer than a big town's first scene, and the drive's simulation
    # waited for it. Then each P-SOG, compressed into the cache on a thread (zlib lets the next drive's work run
    # meanwhile); the task returns once every file is written, so the cache is whole when the pool is, unless
    # this process waits for its saves when it ends (``pipeline.saves_outlive_tasks``: the application's worker
    # processes; then the last file's 0.2-0.3 s leave the task; tests/test_executors.py)
    # A drive whose P-SOG is in the cache is read from it, its scene built only where its key is not remembered
    # (``SceneSpec.for_cache``): a warm reproduce --routes 8 built all 32 scenes for nothing (pool 19.0 [18.3-19.2]
    # of 69.6 [65.2-71.4] s on the 2-core dev VM, 3 runs; 3.5 s after).
    from place3d_kernels.pipeline import end_task_saves
    from place3d_kernels.profiling import section
    from place3d_kernels.scene.keymemo import SceneRef

    drives, settings = t
    try:
        with section("drives: cache look-up and scenes"):
            looked = [_cached_record(d, settings) for d in drives]        # (record or None, scene or SceneRef)
            missing = [j for j, (rec, _) in enumerate(looked) if rec is None]
            # the scenes of every miss first; one built to learn its cache key is not built again
            scenes = []
            for j in missing:
                sc = looked[j][1]
                scenes.append(drives[j].build() if sc is None or isinstance(sc, SceneRef) else sc)
        out = [rec for rec, _ in looked]
        del looked
        for j in missing:                   # each scene let go once its record is made
            out[j] = drive_record(drives[j], settings, save_in_background=True, scene=scenes.pop(0))
        return out
    finally:
        end_task_saves()


def _cached_record(drive: Drive, settings: PoolSettings) -> tuple[DriveRecord | None, Any]:
    """(the drive's record from the P-SOG cache, or None on a miss; what the cache was asked with: a
    ``SceneRef`` when the scene's key is remembered, else the built ``Scene``, or None without a cache)."""
    if settings.cache is not None and not settings.cache:
        return None, None
    from place3d_kernels.pipeline import cached_psog
    from place3d_kernels.sog import cache_folder

    folder = cache_folder(settings.cache)
    scene = drive.spec().for_cache(folder)
    ps = cached_psog(scene, grid=settings.grid, lidar=settings.lidar, frames_per_subset=settings.k, cache=folder)
    return (None if ps is None else DriveRecord.from_psog(ps, drive.label)), scene


def scene_groups(drives: Sequence[Drive], workers: int) -> list[list[int]]:
    """The drives' indices as tasks for ``workers`` worker processes: two routes of one town a task (one
    route each when there are no more drives than workers), town after town, in drive order within a town.

    A worker makes a town's roads and ground once per process (``opendrive._town_base``, about 0.6 s a
    town on the dev VM), so a second route of the same town in the same task costs only its own scene.
    Tasks no larger than two drives leave the executor free to balance the towns' unequal drives among
    the workers (Town01's drives are the cheapest); a task never mixes towns."""
    n = max(1, int(workers))
    size = max(1, min(2, -(-len(drives) // n)))
    by_scene: dict = {}
    for i, d in enumerate(drives):
        by_scene.setdefault(d.scene, []).append(i)
    out = []
    for idx in by_scene.values():
        out += [idx[a:a + size] for a in range(0, len(idx), size)]
    return out


def build_pooled(drives: Sequence[Drive], settings: PoolSettings = PoolSettings(), executor=None,
                 progress: bool = False) -> PooledPSOG:
    """Pool the P-SOGs of ``drives`` (records come back in drive order).

    An executor with ``workers`` (the process executor) gets tasks of two routes of one town
    (``scene_groups``); any other gets one task per drive.

    Args:
        drives: the drives (routes x scenes).
        settings: grid, collection LiDAR, k, backend, cache (``PoolSettings``).
        executor: an object with ``map(fn, tasks)`` (the application's executors: local processes, Ray);
            None, or one whose ``kind`` is ``"local"``, runs the drives here one after the other, so at most
            one drive's frames are in memory at a time.
        progress: print one line per drive to stderr (local executor; others: one line for all drives).
    """
    drives = list(drives)
    if not drives:
        raise ValueError("build_pooled needs at least one Drive")
    # resolve the backend and the cache folder in the driver so every task agrees (see PSOGSpec.resolved)
    from place3d_kernels.sog import cache_dir

    settings = PoolSettings(settings.voxel_size, settings.lidar, settings.k, backend_name(settings.backend),
                            str(cache_dir()) if settings.cache is None else settings.cache, settings.roi)
    pooled = PooledPSOG(settings.grid)
    if executor is None or getattr(executor, "kind", None) == "local":
        import sys
        import time

        for i, d in enumerate(drives):
            t0 = time.perf_counter()
            pooled.add(drive_record(d, settings))
            if executor is not None:
                executor.submitted += 1
            if progress:
                print(f"  drive {i + 1}/{len(drives)} {d.label}: {time.perf_counter() - t0:.1f} s",
                      file=sys.stderr)
        return pooled
    import time

    from place3d_kernels import profiling

    t0 = time.perf_counter()
    workers = getattr(executor, "workers", None)
    if workers:
        # worker processes of this machine: a task is two routes of one town, so the town's roads are made once
        groups = scene_groups(drives, workers)
        # under --profile each task's steps join the table (profiling.task)
        fn = profiling.task("drive worker task", _records_task)
        got = [profiling.untraced(r) for r in executor.map(fn, [([drives[i] for i in g], settings) for g in groups])]
        records: list = [None] * len(drives)
        for g, recs in zip(groups, got):
            for i, rec in zip(g, recs):
                records[i] = rec
    else:
        records = executor.map(_record_task, [(d, settings) for d in drives])
    for rec in records:                     # in drive order, whoever built them
        pooled.add(rec)
    if progress:
        import sys

        print(f"  {len(drives)} drives on the {getattr(executor, 'kind', 'given')} executor"
              + (f" ({workers} workers)" if workers else "") + f": {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return pooled


def subset_records(drive: Drive, settings: PoolSettings = PoolSettings()) -> list[DriveRecord]:
    """One record per subset of k frames of a drive (T = 1 each), for a bootstrap over subsets.

    Their sum equals the drive's P-SOG counts: each subset is voted exactly as ``PSOG.from_frames``
    votes it (merged in the ego frame of its middle frame). Simulates the drive's frames (not cached).
    """
    from place3d_kernels.simulate import simulate

    frames = simulate(drive.build(), settings.lidar, backend=settings.backend)
    k = settings.k
    n_sub = max(1, len(frames) // k)
    groups = [frames[i * k:(i + 1) * k] for i in range(n_sub)] if len(frames) >= k else [frames]
    out = []
    for j, g in enumerate(groups):
        ps = PSOG.from_frames(g, settings.grid, len(g), backend=settings.backend)
        out.append(DriveRecord.from_psog(ps, f"{drive.label}#{j}"))
    return out


# ====================================================================== routes from specs
def parse_route_seeds(text) -> list[int]:
    """Route seeds from ``"100-107"``, ``"1,2,5"`` or ``"0-3,10"`` (ranges inclusive; order kept, no repeats).

    Raises:
        ValueError: anything else (a descending range, a repeated seed, a non-integer, nothing).
    """
    seeds: list[int] = []
    for part in str(text).split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part[1:]:                          # a range; a leading '-' is a negative seed
                i = part.index("-", 1)
                lo, hi = int(part[:i]), int(part[i + 1:])
                if hi < lo:
                    raise ValueError
                seeds.extend(range(lo, hi + 1))
            else:
                seeds.append(int(part))
        except ValueError:
            raise ValueError(f"route seeds {text!r}: give integers and ranges such as 100-107 or 1,2,5 "
                             f"(a range runs low-high)") from None
    if not seeds:
        raise ValueError(f"route seeds {text!r}: no seeds")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"route seeds {text!r}: seed {next(x for x in seeds if seeds.count(x) > 1)} is repeated; "
                         f"a pool counts each route once")
    return seeds


def pool_specs(specs, backend=None, cache=True, progress: bool = False, known: dict | None = None,
               read: dict | None = None, files_key=None) -> PooledPSOG:
    """The pooled P-SOG of several ``spec.PSOGSpec`` (one per drive: scene x route seed, each with the run's
    condition, vehicle and collection LiDAR), each built or read from the on-disk cache by ``spec.build``, or
    taken from ``known`` ({spec: DriveRecord}: records already made, e.g. by the worker that built the drive)
    or ``read`` (records ``cached_records`` read already). The cached drives among the rest are read first,
    side by side (``cached_records``); only the others are built, one after the other, on ``backend``. Where
    the process keeps pools (``pool_memo.keep_pools``: ``place3d serve``), a pool of these very cache files
    kept by an earlier call is returned as it is (shared: nothing may be added to it), and a pool whose every
    drive was read from its file is kept. ``files_key``: the files' ``pool_memo.pool_files_key`` taken before
    ``read`` was read (default: taken here, before the reads).

    ``build_pooled`` pools ``Drive``s (scene, seed, frames); this pools full specs, so a command's adverse
    condition and vehicle body apply to every drive. Records come back in spec order, labelled by the
    scene's label (``Town06-s3-f40``).
    """
    import sys
    import time

    specs = list(specs)
    if not specs:
        raise ValueError("pool_specs needs at least one P-SOG spec")
    grids = {s.grid.grid().to_dict().__repr__() for s in specs}
    if len(grids) != 1:
        raise ValueError("pooled drives must share one ROI grid")
    known, read = dict(known or {}), dict(read or {})
    # a pool kept from an earlier command on these very files (pool_memo.keep_pools: place3d serve)
    key = None if known else files_key if files_key is not None else pool_files_key(specs, cache)
    pooled = kept_pool(key)
    if pooled is not None:
        if progress:
            for i, s in enumerate(specs):
                print(f"  drive {i + 1}/{len(specs)} {s.scene.label}: pooled by an earlier command", file=sys.stderr)
        return pooled
    read.update(cached_records([s for s in specs if s not in known and s not in read], cache))
    pooled = PooledPSOG(specs[0].grid.grid())
    for i, s in enumerate(specs):
        t0 = time.perf_counter()
        rec = known.get(s, read.get(s))
        pooled.add(rec if rec is not None else DriveRecord.from_psog(s.build(backend=backend, cache=cache), s.scene.label))
        if progress:
            # a record a worker made was timed with the workers (the caller's line), one read from the cache
            # with the others read beside it: not "0.0 s" here
            took = ("built by a worker" if s in known else "read from the cache" if s in read
                    else f"{time.perf_counter() - t0:.1f} s")
            print(f"  drive {i + 1}/{len(specs)} {s.scene.label}: {took}", file=sys.stderr)
    if key is not None and all(s in read for s in specs) and pool_files_key(specs, cache) == key:
        keep_pool(key, pooled)          # every drive read from the files the key names, none rewritten meanwhile
    return pooled


def cached_records(specs, cache=True) -> dict:
    """{spec: DriveRecord} of the ``spec.PSOGSpec``s whose P-SOG the on-disk cache holds, read side by side on
    threads (one a spec, at most the usable cores): reading a file, checking its hash and inflating it leave
    the interpreter lock free, and the four drives of the default pool took 0.71 s one after the other on the
    H200 host (2026-11-30). Needs no backend: a command reads its drives while its backend is probed.

    Only specs whose cache file is known without building the scene (``PSOGSpec.cache_file``: the scene's
    key remembered) and exists are read here; the others, and a file that fails its check (``build`` then
    reports and rebuilds it), are left out."""
    if not cache:
        return {}
    specs = [s for s in dict.fromkeys(specs) if (f := s.cache_file(cache)) is not None and f.exists()]

    def read(s):
        ps = s.cached(cache, warn=False)        # a file that fails its check: build reads it again, says so once
        return None if ps is None else DriveRecord.from_psog(ps, s.scene.label)

    got = thread_map(read, specs, min(len(specs), usable_cores()))
    return {s: r for s, r in zip(specs, got) if r is not None}
