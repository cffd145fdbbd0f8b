"""Leave-one-out grids of a pooled P-SOG, patched from the full pool instead of rebuilt.

A jackknife scores rigs on n P-SOGs, each the pool with one record (a subset or a drive) left out. Built
from scratch, each is a dense (M, K) table of counts and probabilities (some 100 MB on the default grid),
its entropies and its stop mask: 50 ms on the dev VM and most of a warm optimise's jackknife. Yet a
voxel the left-out record never saw keeps its counts; only the number of subsets T changes. So the
weights and stop mask of every voxel are computed once per T (the "base"), and for each left-out record
only the rows of the voxels it touched are recomputed and written over the base (in one working copy,
the previous record's rows restored first).

Exact: a voxel's weight is a function of its own count row and T alone (``PSOG.weights`` reduces each
row on its own), and ``left_out_fields`` mirrors ``PooledPSOG.psog``, ``PSOG.detection``, ``PSOG.weights``
and ``PSOG.stop_mask`` step for step; tests/test_left_out.py checks every left-out grid of the default
town against ``pooled.psog(m).for_task(task)`` bit for bit, for both tasks.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.classes import VEHICLE
from place3d_kernels.sog import entropy

__all__ = ["LeftOutGrids", "left_out_fields"]


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
        self._work: dict = {}       # T -> (weights, stop, voxels last written): the base, patched in place

    def __len__(self) -> int:
        return len(self.pooled.records)

    def _base_fields(self, T: int):
        """Dense (weights, stop) of the plain pool's count rows taken over T subsets: right for every voxel
        a left-out record did not touch (the others are overwritten)."""
        if T not in self._base:
            c = self.counts.copy()
            c[:, 0] = T - c[:, 1:].sum(axis=1)
            w, s = left_out_fields(c, T, self.task)
            wd = np.zeros(self.n_voxels, dtype=np.int64)
            sd = np.zeros(self.n_voxels, dtype=np.uint8)
            wd[self.voxels], sd[self.voxels] = w, s
            self._base[T] = (wd, sd)
        return self._base[T]

    def fields(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(weights (n_voxels,) int64, stop (n_voxels,) uint8) of the pool without record ``i``.

        The arrays are reused: they hold record ``i``'s grid until the next call (copy them to keep one).
        """
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
        wb, sb = self._base_fields(T)
        if T not in self._work:
            self._work[T] = (wb.copy(), sb.copy(), None)
        wd, sd, last = self._work[T]
        if last is not None:                                  # undo the previous record's rows
            wd[last], sd[last] = wb[last], sb[last]
        at = self.voxels[rows]
        wd[at], sd[at] = w, s                                 # a voxel no longer occupied: weight 0, no stop
        self._work[T] = (wd, sd, at)
        return wd, sd
