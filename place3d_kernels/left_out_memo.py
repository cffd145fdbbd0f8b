"""The prepared left-out grids a process keeps between jackknifes on the same records (``HANDLES``).

A resident process (``place3d serve``) runs the same jackknife again and again on the same records: the
left-out grids depend on the records, the task, the occlusion and the normalisation, never on the rigs
scored. ``HANDLES`` keeps their prepared backend grids between calls (see ``PreparedLeftOut``) and
remembers that the scene's P-SOG passed ``PooledPSOG.plain_psog``'s identity check, so a warm jackknife on
a known pool patches, uploads and compares nothing: it only launches the scoring. ``left_out`` makes the
grids and re-exports these names.
"""

from __future__ import annotations

import json
import threading
import weakref
from collections import OrderedDict
from concurrent.futures import Future
from typing import Callable, Iterable

from place3d_kernels.grid import DENSE_BYTES_PER_VOXEL

__all__ = ["PreparedLeftOut", "HANDLES", "KEEP_LEFT_OUT", "KEEP_SET_BYTES"]


#: Sets of prepared left-out grids (one set: the n grids of one pool, task, occlusion and backend) that
#: ``HANDLES`` keeps; 2 holds both tasks of one pool. One grid is its int64 weights plus masks
#: (``grid.DENSE_BYTES_PER_VOXEL``): 36 MB on a 0.2 m grid, 290 MB on the default 0.1 m one.
KEEP_LEFT_OUT = 2
#: Largest set kept, in bytes of device (or, on a CPU backend, host) memory: a set of 10 subsets on a 0.2 m
#: grid (360 MB) is kept, one on the default 0.1 m grid (2.9 GB) is not, and its jackknife patches one working
#: grid per task in place instead (``left_out.prepared_grids``), which needs no copies.
KEEP_SET_BYTES = 2**30


class PreparedLeftOut:
    """A bounded memo of the prepared backend grids of left-out P-SOGs, most recently used kept.

    A key names everything a left-out grid is made of, so an entry is never served for other data:

    - ``pool_key``, the records' content identity, given by the caller: for records read from the
      subset-record cache, the file's resolved path, device, inode, size and modification time in ns
      (``atomic.file_identity``), taken before and after the read. A rewritten file
      (``os.replace``: a new inode) or a touched one gets another key. Callers without such an identity
      pass None and nothing is kept.
    - the grid (its bounds and voxel size), the task, the occlusion mode (the stop mask or none) and the
      normalisation (its indicator grids beside the weights);
    - the backend instance itself, not its name: two instances of one name may hold different contexts,
      and a handle is only valid on the one that prepared it (as ``PSOG.handle`` keys its grids).

    Handles are opaque and read-only to their users (a kept set is made of copies, never of one working grid
    rewritten per record), so one set serves any number of jackknifes. The memo lives as long as the process: a
    one-shot command frees it at exit, ``place3d serve`` keeps it between commands. Thread-safe; ``keep(0)`` or
    ``clear()`` frees every handle.
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

    @staticmethod
    def fits(grid, n: int) -> bool:
        """Whether a set of ``n`` left-out grids of ``grid`` is small enough to keep (``KEEP_SET_BYTES``);
        callers pass no pool key for one that is not."""
        return DENSE_BYTES_PER_VOXEL * int(grid.n_voxels) * int(n) <= KEEP_SET_BYTES

    def will_keep(self, pool_key) -> bool:
        """Whether ``get`` keeps (or serves kept) grids for ``pool_key``: else it hands back ``prepare()`` as it
        is, whose handles may then be one working grid rewritten per record (``left_out.prepared_grids``)."""
        return pool_key is not None and self._keep > 0

    def get(self, pool_key, grid, task: str, occlusion: str, backend, prepare: Callable[[], Iterable],
            normalisation: str = "paper") -> Iterable:
        """The prepared left-out grids (one item per record, in record order: ``left_out.prepared_grids``) of
        this pool, task, occlusion, normalisation and backend: the kept list; or ``prepare()``'s handles,
        collected into a list and kept when ``pool_key`` is not None (and ``keep`` > 0), else ``prepare()``
        itself, returned as it is (an iterator that prepares each grid when asked keeps one grid in memory at a
        time).

        A call that finds another thread preparing the same set (``place3d_app.prefetch.prepare_in_background``)
        waits for its list; should that preparation fail, this call prepares the set itself."""
        if not self.will_keep(pool_key):
            return prepare()
        key = (pool_key, _grid_key(grid), task, occlusion, normalisation, backend)
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


#: The process's memo of prepared left-out grids (``uncertainty.jackknife_records`` uses it, as ``left_out.HANDLES``).
HANDLES = PreparedLeftOut()


def _grid_key(grid) -> str:
    return json.dumps(grid.to_dict(), sort_keys=True)
