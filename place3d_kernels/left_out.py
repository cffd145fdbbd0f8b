"""Leave-one-out grids of a pooled P-SOG, patched from the full pool instead of rebuilt.

A jackknife scores rigs on n P-SOGs, each the pool with one record (a subset or a drive) left out. Built
from scratch, each is a dense (M, K) table of counts and probabilities (some 100 MB on the default grid),
its entropies and its stop mask, which made most of a warm optimise's jackknife. Yet a
voxel the left-out record never saw keeps its counts; only the number of subsets T changes. So the
weights and stop mask of every voxel are computed once per T (the "base"), and for each left-out record
only the rows of the voxels it touched are recomputed and written over the base (in one working copy,
the previous record's rows restored first).

Exact: a voxel's weight is a function of its own count row and T alone (``PSOG.weights`` reduces each
row on its own), and ``left_out_fields`` mirrors ``PooledPSOG.psog``, ``PSOG.detection``, ``PSOG.weights``
and ``PSOG.stop_mask`` step for step; tests/test_left_out.py checks every left-out grid of the default
town against ``pooled.psog(m).for_task(task)`` bit for bit, for both tasks.

A resident process (``place3d serve``) runs the same jackknife again and again on the same records: the
left-out grids depend on the records, the task and the occlusion, never on the rigs scored. ``HANDLES``
keeps their prepared backend grids between calls (see ``PreparedLeftOut``) and remembers that the
scene's P-SOG passed ``PooledPSOG.plain_psog``'s identity check, so a warm jackknife on a known
pool patches, uploads and compares nothing: it only launches the scoring.
"""

from __future__ import annotations

import json
import threading
import weakref
from collections import OrderedDict
from concurrent.futures import Future
from typing import Callable, Iterable

import numpy as np

from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.classes import VEHICLE
from place3d_kernels.profiling import section
from place3d_kernels.sog import entropy

__all__ = ["LeftOutGrids", "left_out_fields", "PreparedLeftOut", "HANDLES", "KEEP_LEFT_OUT", "fused_path",
           "prepared_grids", "patched_on_host", "patched_on_backend"]


def left_out_fields(counts: np.ndarray, T: int, task: str) -> tuple[np.ndarray, np.ndarray]:
    """(weights (R,) int64, stop (R,) bool) of count rows ``counts`` (R, K) (column 0 = empty) pooled over T
    subsets, for ``task`` ("seg" or "det"): the values ``PSOG.weights`` and ``PSOG.stop_mask`` give those
    voxels in ``pooled.psog(m).for_task(task)``."""
    p = counts / float(T)                                     # PooledPSOG.psog
    if task == "det":                                         # PSOG.detection
        veh = p[:, VEHICLE] if p.shape[1] > VEHICLE else np.zeros(len(p))
        other = 1.0 - p[:, 0] - veh
        p = np.stack([p[:, 0], veh, np.clip(other, 0.0, 1.0)], axis=1)
    elif task != "seg":
        raise ValueError(f"task must be 'seg' or 'det', got {task!r}")
    w = np.rint(entropy(p) * ENTROPY_SCALE).astype(np.int64)  # PSOG.weights
    stop = (1.0 - p[:, 0]) >= 0.5 - 1e-12                     # PSOG.stop_mask
    return w, stop


class LeftOutGrids:
    """The dense weights and stop masks of a pool's leave-one-out P-SOGs, one record left out at a time.

    Args:
        pooled: the ``PooledPSOG``.
        task: "seg" or "det".
    """

    def __init__(self, pooled, task: str):
        self.pooled, self.task = pooled, task
        self.n_voxels = pooled.grid.n_voxels
        self.voxels, self.counts, self.T = pooled.counts()    # the plain pool: every record once
        self._base: dict = {}
        self._work: dict = {}       # T -> (weights, stop, rows last written): the base, patched in place

    def _base_fields(self, T: int):
        """(weights (M,) int64, stop (M,) bool) of the plain pool's count rows taken over T subsets: right
        for every voxel a left-out record did not touch (the others are overwritten).

        Computed in blocks of rows: each row's fields depend on that row alone, and blocks that stay in
        the cache spare the passes over fresh (M, K) temporaries (some 40 MB each on the default grid)."""
        if T not in self._base:
            M = len(self.voxels)
            w, s = np.empty(M, dtype=np.int64), np.empty(M, dtype=bool)
            for a in range(0, M, BASE_BLOCK):
                c = self.counts[a:a + BASE_BLOCK].copy()
                c[:, 0] = T - c[:, 1:].sum(axis=1)
                w[a:a + BASE_BLOCK], s[a:a + BASE_BLOCK] = left_out_fields(c, T, self.task)
            self._base[T] = (w, s)
        return self._base[T]

    def rows(self, i: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What leaving record ``i`` out changes: (T, rows of the plain pool it touched (sorted), their flat
        voxel indices, weights int64 and stop bool over T subsets). Every other voxel keeps the base's
        fields for that T (``dense_base``); a voxel no longer occupied gets weight 0 and no stop."""
        r = self.pooled.records[i]
        T = self.T - int(r.n_subsets)
        if T <= 0:
            raise ValueError(f"leaving record {i} out leaves no subsets (T = {T})")
        at = np.searchsorted(self.voxels, r.voxels)            # each entry's row in the plain pool
        rows, pos = np.unique(at, return_inverse=True)
        sub = self.counts[rows].copy()
        sub[pos, r.classes.astype(np.intp)] -= r.counts       # one entry per (voxel, class): no repeats
        sub[:, 0] = T - sub[:, 1:].sum(axis=1)
        w, s = left_out_fields(sub, T, self.task)
        return T, rows, self.voxels[rows], w, s

    def dense_base(self, T: int) -> tuple[np.ndarray, np.ndarray]:
        """(weights (n_voxels,) int64, stop (n_voxels,) uint8): the plain pool's fields over T subsets on the
        whole grid (zero where no record saw anything), a new pair each call."""
        wb, sb = self._base_fields(T)
        wd = np.zeros(self.n_voxels, dtype=np.int64)
        sd = np.zeros(self.n_voxels, dtype=np.uint8)
        wd[self.voxels], sd[self.voxels] = wb, sb
        return wd, sd

    def fields(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(weights (n_voxels,) int64, stop (n_voxels,) uint8) of the pool without record ``i``.

        The arrays are reused: they hold record ``i``'s grid until the next call (copy them to keep one).
        """
        T, rows, at, w, s = self.rows(i)
        if T not in self._work:
            # one dense copy of the base per T, patched and restored from the base's rows
            self._work[T] = (*self.dense_base(T), None)
        wd, sd, last = self._work[T]
        if last is not None:                                  # undo the previous record's rows
            wb, sb = self._base_fields(T)
            back = self.voxels[last]
            wd[back], sd[back] = wb[last], sb[last]
        wd[at], sd[at] = w, s
        self._work[T] = (wd, sd, rows)
        return wd, sd


def fused_path(lidar, occlusion: str, normalisation: str = "paper", body=None) -> bool:
    """Whether ``uncertainty.jackknife_records`` scores these settings on patched left-out grids (the path
    of ``metrics.msog_on_handle``: paper normalisation, no ego body, a grid LiDAR from range 0, occlusion
    by the SOG or none) rather than on whole left-out P-SOGs."""
    return (normalisation == "paper" and body is None and lidar.is_grid and lidar.min_range == 0
            and occlusion in ("sog", "none"))


def prepared_grids(pooled, task: str, occlusion: str, backend):
    """Each left-out grid of ``pooled`` (one record left out at a time, in record order) for ``task``,
    prepared on ``backend`` (the stop mask only with ``occlusion="sog"``), made one at a time as the
    iterator is advanced: by ``patched_on_backend`` where the backend patches grids itself
    (``Backend.patches_grids``: Warp on CUDA), else by ``patched_on_host``. Both give the handle
    ``prepare_grid`` gives for the dense arrays (tests/test_left_out.py)."""
    make = patched_on_backend if backend.patches_grids else patched_on_host
    yield from make(pooled, task, occlusion, backend)


def patched_on_host(pooled, task: str, occlusion: str, backend):
    """``prepared_grids`` by one dense host copy per T, patched with each record's rows
    (``LeftOutGrids.fields``) and uploaded whole with ``prepare_grid``."""
    grids = LeftOutGrids(pooled, task)
    for i in range(len(pooled)):
        with section("jackknife: left-out grid"):
            w, stop = grids.fields(i)
        with section("jackknife: grid upload"):
            h = backend.prepare_grid(pooled.grid.spec, w, stop if occlusion == "sog" else None)
        yield h


def patched_on_backend(pooled, task: str, occlusion: str, backend):
    """``prepared_grids`` by the backend: the base of each T sent once (``grid_base``), each left-out grid
    the base with the record's rows written over a copy of it there (``patched_grid``): per grid, no dense
    host copy, no host brick masks and no upload of the whole grid."""
    grids = LeftOutGrids(pooled, task)
    sog = occlusion == "sog"
    bases = {}
    for i in range(len(pooled)):
        with section("jackknife: left-out grid"):
            T, _, at, w, stop = grids.rows(i)
        with section("jackknife: grid upload"):
            if T not in bases:
                wd, sd = grids.dense_base(T)
                bases[T] = backend.grid_base(pooled.grid.spec, wd, sd if sog else None)
            h = backend.patched_grid(bases[T], at, w, stop if sog else None)
        yield h


#: Rows of the plain pool's counts per block when the base fields are computed (``LeftOutGrids``): 8192
#: rows of 22 float64 channels are 1.4 MB, so a block's temporaries stay in the cache.
BASE_BLOCK = 8192


#: Sets of prepared left-out grids (one set: the n grids of one pool, task, occlusion and backend) that
#: ``HANDLES`` keeps; 2 holds both tasks of one pool. One grid is its int64 weights plus masks, about
#: 40 MB on the default 0.2 m grid, so a set of 10 subsets is about 400 MB of device (or, on a CPU
#: backend, host) memory.
KEEP_LEFT_OUT = 2


class PreparedLeftOut:
    """A bounded memo of the prepared backend grids of left-out P-SOGs, most recently used kept.

    A key names everything a left-out grid is made of, so an entry is never served for other data:

    - ``pool_key``, the records' content identity, given by the caller: for records read from the
      subset-record cache, the file's resolved path, device, inode, size and modification time in ns
      (``subset_records.records_file_identity``), taken before and after the read. A rewritten file
      (``os.replace``: a new inode) or a touched one gets another key. Callers without such an identity
      pass None and nothing is kept.
    - the grid (its bounds and voxel size), the task and the occlusion mode (the stop mask or none);
    - the backend instance itself, not its name: two instances of one name may hold different contexts,
      and a handle is only valid on the one that prepared it (as ``PSOG.handle`` keys its grids).

    Handles are opaque and read-only to their users (``Backend.prepare_grid`` copies its inputs), so one
    set serves any number of jackknifes. The memo lives as long as the process: a one-shot command frees
    it at exit, ``place3d serve`` keeps it between commands. Thread-safe; ``keep(0)`` or ``clear()``
    frees every handle.
    """

    def __init__(self, keep: int = KEEP_LEFT_OUT):
        self._sets: OrderedDict = OrderedDict()
        self._pending: dict = {}    # key -> Future of the list a caller is preparing now (another waits for it)
        # (pool_key, grid) -> weak reference to the P-SOG that passed PooledPSOG.plain_psog's check for that
        # pool; a P-SOG that dies is never matched again (its weak reference then returns None)
        self._verified: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._keep = 0
        self.keep(keep)

    def keep(self, n: int) -> None:
        """Keep at most ``n`` sets (0: none, and nothing kept now)."""
        if n < 0:
            raise ValueError(f"keep needs n >= 0 sets of left-out grids, got {n}")
        with self._lock:
            self._keep = int(n)
            self._trim()

    def _trim(self) -> None:
        for d in (self._sets, self._verified):
            while len(d) > self._keep:
                d.popitem(last=False)

    def clear(self) -> None:
        """Forget every set (their device memory is freed with the last reference) and every check."""
        with self._lock:
            self._sets.clear()
            self._verified.clear()

    def __len__(self) -> int:
        return len(self._sets)

    @property
    def keeps(self) -> bool:
        """Whether any set is kept (``keep`` > 0)."""
        return self._keep > 0

    def get(self, pool_key, grid, task: str, occlusion: str, backend, prepare: Callable[[], Iterable]) -> Iterable:
        """The prepared left-out grids (one handle per record, in record order) of this pool, task,
        occlusion and backend: the kept list; or ``prepare()``'s handles, collected into a list and kept
        when ``pool_key`` is not None (and ``keep`` > 0), else ``prepare()`` itself, returned as it is (an
        iterator that prepares each grid when asked keeps one grid in memory at a time).

        A call that finds another thread preparing the same set (``place3d_app.prefetch.prepare_in_background``)
        waits for its list; should that preparation fail, this call prepares the set itself."""
        if pool_key is None or not self._keep:
            return prepare()
        key = (pool_key, _grid_key(grid), task, occlusion, backend)
        while True:
            with self._lock:
                handles = self._sets.get(key)
                if handles is not None:
                    self._sets.move_to_end(key)
                    return handles
                other = self._pending.get(key)
                if other is None:
                    mine = self._pending[key] = Future()
                    break
            try:
                return other.result()
            except BaseException:  # noqa: BLE001 - that caller's failure: prepare here (and meet it here)
                with self._lock:
                    if self._pending.get(key) is other:
                        del self._pending[key]
        try:
            handles = list(prepare())
        except BaseException as e:
            with self._lock:
                del self._pending[key]
            mine.set_exception(e)
            raise
        with self._lock:
            self._sets[key] = handles
            self._trim()
            del self._pending[key]
        mine.set_result(handles)
        return handles

    def remember_plain(self, pool_key, psog) -> None:
        """Remember ``psog`` as exactly the plain pool of the records ``pool_key`` names, without the check of
        ``plain_psog``: for a P-SOG pooled from those very records (``subset_records.records_aggregator``
        writes the records of a cold build and pools its P-SOG from them). None keeps nothing."""
        if pool_key is None or not self._keep:
            return
        key = (pool_key, _grid_key(psog.grid))
        with self._lock:
            self._verified[key] = weakref.ref(psog)
            self._verified.move_to_end(key)
            self._trim()

    def plain_psog(self, pooled, reference=None, pool_key=None):
        """``pooled.plain_psog(reference)``, without its check when ``reference`` already passed it for the
        pool ``pool_key`` names (None: always checked).

        The check compares the pool's summed counts, voxels and probabilities with the reference's (a sum
        over every record and three full-array comparisons); its answer depends only on the records and on
        the reference's arrays, which nothing writes to after a P-SOG is made. So the same P-SOG object on
        the same records passes again, and the point estimate reuses its weights and device grids at once.
        """
        if pool_key is None or reference is None or not self._keep:
            return pooled.plain_psog(reference)
        key = (pool_key, _grid_key(pooled.grid))
        with self._lock:
            ref = self._verified.get(key)
            if ref is not None and ref() is reference:
                self._verified.move_to_end(key)
                pooled.known_plain(reference)      # its counts, should the left-out grids ask for them
                return reference
        full = pooled.plain_psog(reference)
        if full is reference:
            with self._lock:
                self._verified[key] = weakref.ref(reference)
                self._trim()
        return full


#: The process's memo of prepared left-out grids (``uncertainty.jackknife_records`` uses it).
HANDLES = PreparedLeftOut()


def _grid_key(grid) -> str:
    return json.dumps(grid.to_dict(), sort_keys=True)
