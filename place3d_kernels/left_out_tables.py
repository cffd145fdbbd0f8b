"""The fields of left-out count rows: a voxel's fixed-point entropy weight, its stop flag and the 0/1
indicator of a normalisation, from its count row over T subsets (``left_out`` uses them; tests/test_left_out.py
checks them against the rebuilt pools, bit for bit).

``left_out_fields`` mirrors ``PooledPSOG.psog``, ``PSOG.detection``, ``PSOG.weights`` and ``PSOG.stop_mask``
step for step; ``FieldTables`` gives the same values by table look-ups, the host's tables also serving the
device batch (``left_out.device_fields``).
"""

from __future__ import annotations

import functools

import numpy as np

from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.classes import VEHICLE
from place3d_kernels.entropy import entropy

__all__ = ["left_out_fields", "FieldTables", "fields_of", "indicator_rows"]


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


class FieldTables:
    """``left_out_fields`` for count rows over T subsets by table look-ups: every probability is c / T for an
    integer c in [0, T], so each entropy term -p ln p (and, for "det", the "other" channel's term, a function
    of the empty and vehicle counts) is computed once per value, by the same NumPy expressions on the same
    float64 values, and gathered per row; the rows' terms are then summed as ``sog.entropy`` sums them (one
    (R, K) array along its last axis). Bit for bit the same fields (tests/test_left_out.py), without a log
    per entry."""

    #: beyond this T the det table ((T + 1)^2 float64) grows large: ``left_out_fields`` is used instead
    MAX_T = 2048

    def __init__(self, T: int, task: str):
        if task not in ("seg", "det"):
            raise ValueError(f"task must be 'seg' or 'det', got {task!r}")
        self.T, self.task = int(T), task
        v = np.arange(self.T + 1) / float(self.T)             # c / T as PooledPSOG.psog divides
        self.term = _terms(v)
        self.stop = (1.0 - v) >= 0.5 - 1e-12                  # PSOG.stop_mask of p(empty) = c / T
        if task == "det":                                     # PSOG.detection's "other", per (empty, vehicle)
            self.other = _terms(np.clip(1.0 - v[:, None] - v[None, :], 0.0, 1.0))

    def __call__(self, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c0 = counts[:, 0]
        if self.task == "seg":
            terms = self.term[counts]
        else:
            veh = counts[:, VEHICLE] if counts.shape[1] > VEHICLE else np.zeros(len(counts), dtype=np.intp)
            terms = np.stack([self.term[c0], self.term[veh], self.other[c0, veh]], axis=1)
        w = np.rint(terms.sum(axis=-1) * ENTROPY_SCALE).astype(np.int64)
        return w, self.stop[c0]


def device_tables(Ts, task: str):
    """``Backend.left_out_fields``' tables for the subset counts ``Ts``: (term (n, T+1), stop (n, T+1) uint8,
    other (n, T+1, T+1) for det, else a (1, 1, 1) dummy), row j for ``Ts[j]``, zero-padded to the largest T."""
    tables = [FieldTables(t, task) for t in Ts]
    n = max(Ts) + 1
    term, stop_t = np.zeros((len(Ts), n)), np.zeros((len(Ts), n), dtype=np.uint8)
    other = np.zeros((len(Ts), n, n) if task == "det" else (1, 1, 1))
    for j, tb in enumerate(tables):
        term[j, :tb.T + 1], stop_t[j, :tb.T + 1] = tb.term, tb.stop
        if task == "det":
            other[j, :tb.T + 1, :tb.T + 1] = tb.other
    return term, stop_t, other


def device_row_fields(counts: np.ndarray, T: int, task: str, backend):
    """``FieldTables(T, task)(counts)`` (each count clipped into [0, T] first, the empty count T minus the
    occupied ones) made on a backend with ``fields_on_device`` (``Backend.left_out_fields`` with no entries
    taken out): two device arrays, (M,) int64 weights and (M,) uint8 stop flags. ``counts``: (M, K) integer,
    every value below 2**31; T at most ``FieldTables.MAX_T``."""
    M = len(counts)
    term, stop_t, other = device_tables([T], task)
    rows, estart, row_t = _whole_rows(M)
    return backend.left_out_fields(counts, rows, estart, np.zeros(1, dtype=np.int32), np.zeros(1, dtype=np.int32),
                                   row_t, np.array([T]), term, stop_t, other, task == "det", VEHICLE,
                                   float(ENTROPY_SCALE))


@functools.lru_cache(maxsize=1)
def _whole_rows(M: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``device_row_fields``' entry tables for M rows with nothing taken out: (rows 0..M-1 int64, estart zeros
    (M + 1) int32, row_t zeros (M) int32), read-only and kept for the next call (the point grid and the bases
    of both tasks ask for the same M), so a backend may keep its device copies while they live."""
    out = (np.arange(M, dtype=np.int64), np.zeros(M + 1, dtype=np.int32), np.zeros(M, dtype=np.int32))
    for a in out:
        a.setflags(write=False)
    return out


def _terms(v: np.ndarray) -> np.ndarray:
    # sog._entropy_rows' terms: -p ln p where p > 0, else 0
    out = np.zeros(v.shape, dtype=np.float64)
    nz = v > 0
    p = v[nz]
    out[nz] = -p * np.log(p)
    return out


def fields_of(T: int, task: str, cache: dict | None = None):
    """A callable giving ``left_out_fields(counts, T, task)``: ``FieldTables`` where T allows (kept in
    ``cache`` by (T, task)), else ``left_out_fields`` itself."""
    if T > FieldTables.MAX_T:
        return lambda counts: left_out_fields(counts, T, task)
    if cache is None:
        return FieldTables(T, task)
    if (T, task) not in cache:
        cache[T, task] = FieldTables(T, task)
    return cache[T, task]


def indicator_rows(kind: str | None, counts: np.ndarray, T: int, w: np.ndarray) -> np.ndarray | None:
    """``metrics.indicator_weights(psog, kind)`` of count rows ``counts`` over T subsets whose weights are
    ``w``: 1 where the voxel is stored in the P-SOG, i.e. occupied in some subset (``"evidence"``), or where
    its weight is above 0 (``"uncertain"``); None for no indicator (the paper's normalisation)."""
    if kind is None:
        return None
    if kind == "evidence":
        return (counts[:, 0] < T).astype(np.int64)          # PooledPSOG.counts keeps the occupied rows
    if kind == "uncertain":
        return (w > 0).astype(np.int64)
    raise ValueError(f"indicator must be 'evidence' or 'uncertain', got {kind!r}")
