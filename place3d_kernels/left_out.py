"""Leave-one-out grids of a pooled P-SOG, patched from the full pool instead of rebuilt.

A jackknife scores rigs on n P-SOGs, each the pool with one record (a subset or a drive) left out. Built
from scratch, each is a dense (M, K) table of counts and probabilities (some 100 MB on the default grid),
its entropies and its stop mask, which made most of a warm optimise's jackknife. Yet a
voxel the left-out record never saw keeps its counts; only the number of subsets T changes. So the
weights and stop mask of every voxel are computed once per T (the "base"), and for each left-out record
only the rows of the voxels it touched are recomputed (``LeftOutRows``, once per record for both tasks)
and written over the base.

Where they are written (``prepared_grids``): on backends that write grids in place (``Backend.writes_grids``:
reference, OpenCL) one working grid per T stays on the device and each record's rows, with the previous
record's rows restored, are all that moves (``patched_in_place``); on Warp's CUDA devices every record's
rows are computed there in one batch (``device_fields``) and a copy of a base on the device is patched per
grid (``patched_on_backend``); elsewhere a dense host copy is patched and uploaded whole
(``patched_on_host``). Sets kept between jackknifes (``HANDLES``) are made of copies. The fields of a row
(``left_out_tables``) come from per-T tables of entropy terms.

The ``evidence`` and ``uncertain`` normalisations (docs/metric-normalisation.md) count covered voxels with
0/1 weights (``metrics.indicator_weights``); their indicator is patched the same way, in a second grid
with the same stop mask, and scored beside the weights.

Exact: a voxel's weight is a function of its own count row and T alone (``PSOG.weights`` reduces each
row on its own), and ``left_out_fields`` mirrors ``PooledPSOG.psog``, ``PSOG.detection``, ``PSOG.weights``
and ``PSOG.stop_mask`` step for step; tests/test_left_out.py checks every left-out grid of the default
town against ``pooled.psog(m).for_task(task)`` bit for bit, for both tasks, and the scores of every path
against ``msog_batch`` on the rebuilt pools.
"""

from __future__ import annotations

import numpy as np

from place3d_kernels.backends.base import ENTROPY_SCALE
from place3d_kernels.classes import VEHICLE
from place3d_kernels.left_out_memo import HANDLES, KEEP_LEFT_OUT, PreparedLeftOut
from place3d_kernels.left_out_tables import (FieldTables, device_row_fields, device_tables, fields_of, indicator_rows,
                                             left_out_fields)
from place3d_kernels.profiling import section
from place3d_kernels.threads import block_map, thread_map, threads_for

__all__ = ["LeftOutRows", "LeftOutGrids", "left_out_fields", "FieldTables", "PreparedLeftOut", "HANDLES",
           "index_tables_used",
           "KEEP_LEFT_OUT", "fused_path", "prepared_grids", "patched_on_host", "patched_on_backend", "patched_in_place",
           "device_fields"]


class LeftOutRows:
    """The plain pool's count rows and, per left-out record, the rows it touched with its counts taken out:
    the part of a left-out grid both tasks share, computed once per record (the last one is kept, as a
    jackknife asks for record i's grid of every task before record i + 1's)."""

    def __init__(self, pooled):
        self.pooled = pooled
        self.n_voxels = pooled.grid.n_voxels
        self.voxels, self.counts, self.T = pooled.counts()    # the plain pool: every record once
        self._last = None
        self._batch = None

    @classmethod
    def shared(cls, pooled) -> "LeftOutRows":
        """One ``LeftOutRows`` per pool, kept with it (``PooledPSOG.derived``) until a record is added, so
        jackknifes of the same records share the records' index and entry tables (``batch``)."""
        got = pooled.derived.get(cls)           # emptied when a record is added
        if got is None:
            got = pooled.derived[cls] = cls(pooled)
        return got

    def of(self, i: int) -> tuple[int, np.ndarray, np.ndarray]:
        """(T, rows of the plain pool record ``i`` touched (sorted), their count rows (R, K) without it)."""
        if self._last is not None and self._last[0] == i:
            return self._last[1]
        T, rows, first, cls, cnt = self.index(i)
        sub = self.counts[rows]
        sub[np.cumsum(first) - 1, cls] -= cnt                 # one entry per (voxel, class): no repeats
        sub[:, 0] = T - sub[:, 1:].sum(axis=1)
        self._last = (i, (T, rows, sub))
        return T, rows, sub

    def batch(self) -> tuple[list, list, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What ``device_fields`` sends for every record at once, made once for both tasks: (each record's
        (T, flat voxel ids of the rows it touched), the sorted distinct T, and the entry tables of
        ``Backend.left_out_fields``: rows (R,) int64, estart (R + 1,) int32, classes and counts (E,) int32, row_t
        (R,) int32), read-only from here, so a backend may keep its device copies while they live
        (``WarpScoring._resident``). Each record's own index arrays are let go once concatenated."""
        if self._batch is None:
            n = len(self.pooled)
            # each record's index is its own NumPy work over its entries: side by side on threads for a large pool
            idx = thread_map(self.index, range(n), threads_for(sum(len(r.voxels) for r in self.pooled.records)))
            Ts = sorted({t for t, *_ in idx})
            R = np.array([len(r) for _, r, *_ in idx], dtype=np.int64)
            E = np.array([len(c) for *_, c in idx], dtype=np.int64)
            e_off = np.concatenate([[0], np.cumsum(E)])
            estart = np.concatenate([np.flatnonzero(f) + e_off[k] for k, (_, _, f, _, _) in enumerate(idx)]
                                    + [e_off[-1:]]).astype(np.int32)
            row_t = np.repeat(np.array([Ts.index(t) for t, *_ in idx], dtype=np.int32), R)
            rows = np.concatenate([r for _, r, *_ in idx]).astype(np.int64, copy=False)
            ecls = np.concatenate([c for *_, c, _ in idx]).astype(np.int32, copy=False)
            ecnt = np.concatenate([c for *_, c in idx]).astype(np.int32, copy=False)
            # per record only its T and its rows' voxel ids (what each task's grids are patched at), gathered once
            ids = [(t, self.voxels[r]) for t, r, *_ in idx]
            del idx
            for a in (rows, estart, ecls, ecnt, row_t, *(v for _, v in ids)):
                a.setflags(write=False)
            self._batch = (ids, Ts, rows, estart, ecls, ecnt, row_t)
        return self._batch

    def index(self, i: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where record ``i``'s entries fall: (T without it, the rows it touched (sorted), and its entries in
        row order: a flag where each row's first entry is, their classes and counts)."""
        r = self.pooled.records[i]
        T = self.T - int(r.n_subsets)
        if T <= 0:
            raise ValueError(f"leaving record {i} out leaves no subsets (T = {T})")
        at = self.pooled.rows_of(r.voxels)                    # each entry's row in the plain pool
        cls, cnt = r.classes.astype(np.intp), r.counts
        if np.any(at[1:] < at[:-1]):                          # a record's voxels ascend; else sort them so
            order = np.argsort(at, kind="stable")
            at, cls, cnt = at[order], cls[order], cnt[order]
        first = np.r_[True, at[1:] != at[:-1]] if len(at) else np.zeros(0, dtype=bool)
        return T, at[first], first, cls, cnt


class LeftOutGrids:
    """The weights and stop masks (and an indicator, for a normalisation other than the paper's) of a
    pool's leave-one-out P-SOGs for one task, one record left out at a time.

    Args:
        pooled: the ``PooledPSOG``.
        task: "seg" or "det".
        indicator: None, "evidence" or "uncertain" (``indicator_rows``).
        rows: a ``LeftOutRows`` of ``pooled`` to share with the other task's grids (None: one of its own).
    """

    def __init__(self, pooled, task: str, indicator: str | None = None, rows: LeftOutRows | None = None):
        self.pooled, self.task, self.indicator = pooled, task, indicator
        self.source = rows if rows is not None else LeftOutRows(pooled)
        self.n_voxels = self.source.n_voxels
        self.voxels, self.counts, self.T = self.source.voxels, self.source.counts, self.source.T
        self._base: dict = {}
        self._tables: dict = {}     # (T, task) -> FieldTables
        self._work: dict = {}       # T -> (weights, stop, rows last written): the base, patched in place

    def _base_fields(self, T: int):
        """(weights (M,) int64, stop (M,) bool, indicator (M,) int64 or None) of the plain pool's count rows
        taken over T subsets: right for every voxel a left-out record did not touch (the others are
        overwritten).

        Computed in blocks of rows: each row's fields depend on that row alone, and blocks that stay in
        the cache spare the passes over fresh (M, K) temporaries (some 40 MB each on the default grid)."""
        if T not in self._base:
            M = len(self.voxels)
            w, s = np.empty(M, dtype=np.int64), np.empty(M, dtype=bool)
            ind = None if self.indicator is None else np.empty(M, dtype=np.int64)
            fields = fields_of(T, self.task, self._tables)

            def block(a: int, b: int) -> None:
                c = self.counts[a:b].copy()
                c[:, 0] = T - c[:, 1:].sum(axis=1)
                # rows some record with this T touched can hold more than T subsets here (its own included);
                # every left-out grid overwrites them, but the tables take counts in [0, T] only
                np.clip(c, 0, T, out=c)
                w[a:b], s[a:b] = fields(c)
                if ind is not None:
                    ind[a:b] = indicator_rows(self.indicator, c, T, w[a:b])

            block_map(block, M, BASE_BLOCK, self.counts.shape[1])
            self._base[T] = (w, s, ind)
        return self._base[T]

    def rows(self, i: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """What leaving record ``i`` out changes: (T, rows of the plain pool it touched (sorted), their flat
        voxel indices, weights int64 and stop bool over T subsets, indicator int64 or None). Every other
        voxel keeps the base's fields for that T (``dense_base``); a voxel no longer occupied gets weight 0
        and no stop."""
        T, rows, sub = self.source.of(i)
        R = len(rows)
        w, s = np.empty(R, dtype=np.int64), np.empty(R, dtype=bool)
        ind = None if self.indicator is None else np.empty(R, dtype=np.int64)
        fields = fields_of(T, self.task, self._tables)

        def block(a: int, b: int) -> None:      # blocks: the temporaries stay in the cache
            w[a:b], s[a:b] = fields(sub[a:b])
            if ind is not None:
                ind[a:b] = indicator_rows(self.indicator, sub[a:b], T, w[a:b])

        block_map(block, R, BASE_BLOCK, sub.shape[1])
        return T, rows, self.voxels[rows], w, s, ind

    def dense_base(self, T: int) -> tuple[np.ndarray, np.ndarray]:
        """(weights (n_voxels,) int64, stop (n_voxels,) uint8): the plain pool's fields over T subsets on the
        whole grid (zero where no record saw anything), a new pair each call."""
        wb, sb, _ = self._base_fields(T)
        return self._dense(wb), self._dense(sb, np.uint8)

    def _dense(self, values: np.ndarray, dtype=np.int64) -> np.ndarray:
        d = np.zeros(self.n_voxels, dtype=dtype)
        d[self.voxels] = values
        return d

    def fields(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(weights (n_voxels,) int64, stop (n_voxels,) uint8) of the pool without record ``i``.

        The arrays are reused: they hold record ``i``'s grid until the next call (copy them to keep one).
        """
        return self.dense(i)[:2]

    def dense(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """``fields(i)`` and the dense indicator (None without one), reused alike."""
        T, rows, at, w, s, ind = self.rows(i)
        if T not in self._work:
            # one dense copy of the base per T, patched and restored from the base's rows
            wb, sb, ib = self._base_fields(T)
            self._work[T] = (self._dense(wb), self._dense(sb, np.uint8), None if ib is None else self._dense(ib),
                             None)
        wd, sd, idn, last = self._work[T]
        if last is not None:                                  # undo the previous record's rows
            wb, sb, ib = self._base_fields(T)
            back = self.voxels[last]
            wd[back], sd[back] = wb[last], sb[last]
            if idn is not None:
                idn[back] = ib[last]
        wd[at], sd[at] = w, s
        if idn is not None:
            idn[at] = ind
        self._work[T] = (wd, sd, idn, rows)
        return wd, sd, idn

    def changes(self, i: int, last: np.ndarray | None, mark: np.ndarray):
        """(T, voxels, weights, stop, indicator or None) to write over a grid that holds the base for T with
        the rows ``last`` of the previous record written (None: the base as it is) so that it holds record
        ``i``'s left-out grid: record ``i``'s rows, and the base's values back on the rows of ``last`` it did
        not touch. Also returns its rows (the next call's ``last``). ``mark``: (M,) bool scratch, all False
        (and left so)."""
        T, rows, at, w, s, ind = self.rows(i)
        if last is None or not len(last):
            return (T, at, w, s, ind), rows
        back = _untouched(last, rows, mark)
        wb, sb, ib = self._base_fields(T)
        out = (T, np.concatenate([self.voxels[back], at]), np.concatenate([wb[back], w]),
               np.concatenate([sb[back], s]), None if ind is None else np.concatenate([ib[back], ind]))
        return out, rows


def _untouched(last: np.ndarray, rows: np.ndarray, mark: np.ndarray) -> np.ndarray:
    """The rows of ``last`` not among ``rows`` (in ``last``'s order): those a working grid must get back from its
    base when it goes from one record's left-out grid to the next. ``mark``: (M,) bool scratch, all False (and
    left so)."""
    mark[rows] = True
    back = last[~mark[last]]
    mark[rows] = False
    return back


def fused_path(lidar, occlusion: str, normalisation: str = "paper", body=None) -> bool:
    """Whether ``uncertainty.jackknife_records`` scores these settings on patched left-out grids (the path
    of ``metrics.msog_on_handles``: any normalisation, no ego body, a grid LiDAR from range 0, occlusion by
    the SOG or none) rather than on whole left-out P-SOGs."""
    from place3d_kernels.metrics import NORMALISATIONS

    return (normalisation in NORMALISATIONS and body is None and lidar.is_grid and lidar.min_range == 0
            and occlusion in ("sog", "none"))


def _indicator(normalisation: str) -> str | None:
    from place3d_kernels.metrics import check_normalisation

    return None if check_normalisation(normalisation) == "paper" else normalisation


def prepared_grids(pooled, task: str, occlusion: str, backend, normalisation: str = "paper", reuse: bool = False,
                   rows: LeftOutRows | None = None):
    """Each left-out grid of ``pooled`` (one record left out at a time, in record order) for ``task``,
    prepared on ``backend`` (the stop mask only with ``occlusion="sog"``), made one at a time as the
    iterator is advanced. An item is the handle ``prepare_grid`` gives for the dense arrays
    (tests/test_left_out.py); for the ``evidence`` and ``uncertain`` normalisations, a pair (that handle,
    the handle of the indicator's 0/1 weights with the same stop mask).

    ``reuse=True`` lets an item be valid only until the next one is asked for: where the backend writes
    grids in place (``Backend.writes_grids``) every item is then one working grid per T, rewritten
    (``patched_in_place``). Otherwise each item is a grid of its own: patched on the device where the
    backend patches copies (``Backend.patches_grids``: Warp on CUDA), else on the host. ``rows``: a
    ``LeftOutRows`` shared with the other task's grids."""
    kind = _indicator(normalisation)
    if reuse and backend.writes_grids:
        make = patched_in_place
    else:
        make = patched_on_backend if backend.patches_grids else patched_on_host
    yield from make(pooled, task, occlusion, backend, kind, rows)


def patched_on_host(pooled, task: str, occlusion: str, backend, indicator: str | None = None, rows=None):
    """``prepared_grids`` by one dense host copy per T, patched with each record's rows
    (``LeftOutGrids.dense``) and uploaded whole with ``prepare_grid``."""
    grids = LeftOutGrids(pooled, task, indicator, rows)
    for i in range(len(pooled)):
        with section("jackknife: left-out grid"):
            w, stop, ind = grids.dense(i)
        with section("jackknife: grid upload"):
            stop = stop if occlusion == "sog" else None
            h = backend.prepare_grid(pooled.grid.spec, w, stop)
            if ind is not None:
                h = (h, backend.prepare_indicator(pooled.grid.spec, ind, stop))
        yield h


def patched_on_backend(pooled, task: str, occlusion: str, backend, indicator: str | None = None, rows=None):
    """``prepared_grids`` by the backend: the base of each T sent once (``grid_base``), each left-out grid
    the base with the record's rows written over a copy of it there (``patched_grid``): per grid, no dense
    host copy, no host brick masks and no upload of the whole grid. Where the backend computes fields
    (``fields_on_device``: Warp on CUDA), every record's rows are made there in one batch first
    (``device_fields``; with the "uncertain" indicator, which is their weights above 0, not "evidence")."""
    grids = LeftOutGrids(pooled, task, indicator, rows)
    sog = occlusion == "sog"
    bases = {}
    batch = None
    # the rows' fields on the device where the backend computes them; the "uncertain" indicator is then its
    # weights above 0 (left_out_tables.indicator_rows), read back from the device rows ("evidence" needs the
    # counts: the host's rows)
    if _fields_here(grids, backend, indicator):
        with section("jackknife: left-out grid"):
            batch = device_fields(pooled, task, backend, grids.source)
    for i in range(len(pooled)):
        with section("jackknife: left-out grid"):
            if batch is not None:
                T, at, w, stop = batch[i]
                ind = None if indicator is None else _positive(w)
            else:
                T, _, at, w, stop, ind = grids.rows(i)
        with section("jackknife: grid upload"):
            if T not in bases and batch is not None:
                # _base_fields(T) made where the left-out rows were (no host pass over the pool's M rows): the
                # same bits, each count clipped into [0, T] as there (tests/test_left_out.py)
                wb, sb = device_row_fields(grids.counts, T, task, backend)
                sv = sb if sog else None
                bases[T] = [backend.grid_base_from_rows(pooled.grid.spec, grids.voxels, wb, sv)]
                if indicator is not None:          # host rows: the weights and the stop flags read back
                    bases[T].append(backend.grid_base_from_rows(pooled.grid.spec, grids.voxels, _positive(wb),
                                                                None if sv is None else _host(sv)))
            elif T not in bases:
                # from the pool's M voxels: the backend fills its dense copy (no dense host array)
                wb, sb, ib = grids._base_fields(T)
                sv = sb if sog else None
                bases[T] = [backend.grid_base_from_rows(pooled.grid.spec, grids.voxels, wb, sv)]
                if ib is not None:
                    bases[T].append(backend.grid_base_from_rows(pooled.grid.spec, grids.voxels, ib, sv))
            h = backend.patched_grid(bases[T][0], at, w, stop if sog else None)
            if ind is not None:                    # its rows on the host, the stop flags too (a device batch's)
                h = (h, backend.patched_grid(bases[T][1], at, ind, _host(stop) if sog else None))
        yield h


def _host(a) -> np.ndarray:
    """``a`` as a NumPy array: a device array (``device_fields``' rows: Warp) read back, a host array as it is."""
    return a.numpy() if hasattr(a, "numpy") else np.asarray(a)


def _positive(w) -> np.ndarray:
    """(R,) int64 0/1: the "uncertain" indicator of rows whose weights are ``w`` (host or device rows, ``_host``):
    ``left_out_tables.indicator_rows``, which reads the weights alone for that kind."""
    return indicator_rows("uncertain", None, 0, _host(w))


def device_fields(pooled, task: str, backend, rows: LeftOutRows | None = None):
    """Every record's left-out rows computed on the backend in one batch (``Backend.left_out_fields``, Warp
    on CUDA): per record (T, its rows' flat voxel indices (host), weights and stop flags (device arrays,
    slices of the batch)). Only the index work (where each record's entries fall) stays on the host."""
    src = rows if rows is not None else LeftOutRows(pooled)
    ids, Ts, all_rows, estart, ecls, ecnt, row_t = src.batch()
    term, stop_t, other = device_tables(Ts, task)
    w, s = backend.left_out_fields(src.counts, all_rows, estart, ecls, ecnt, row_t, np.array(Ts), term, stop_t, other,
                                   task == "det", VEHICLE, float(ENTROPY_SCALE))
    r_off = [0, *np.cumsum([len(v) for _, v in ids]).tolist()]
    return [(t, v, w[r_off[k]:r_off[k + 1]], s[r_off[k]:r_off[k + 1]]) for k, (t, v) in enumerate(ids)]


def patched_in_place(pooled, task: str, occlusion: str, backend, indicator: str | None = None, rows=None):
    """``prepared_grids`` with ``reuse``, on a backend that writes grids in place: per T one working grid
    (``Backend.working_grid``, filled from the base's M voxels on the device), and per record only its rows
    and the previous record's rows it did not touch written (``Backend.write_voxels``). Where the backend
    computes fields (``left_out_on_device``: OpenCL devices with doubles) the rows are made and kept there
    (``_written_from_device_rows``). An item is valid until the next is asked for."""
    grids = LeftOutGrids(pooled, task, indicator, rows)
    if _fields_here(grids, backend, indicator):
        yield from _written_from_device_rows(grids, pooled, task, occlusion, backend, indicator)
        return
    sog = occlusion == "sog"
    spec = pooled.grid.spec
    work = {}                     # T -> [handle, indicator handle or None, rows last written]
    mark = np.zeros(len(grids.voxels), dtype=bool)
    for i in range(len(pooled)):
        with section("jackknife: left-out grid"):
            T = grids.source.of(i)[0]
            last = work[T][2] if T in work else None
            (T, at, w, stop, ind), written = grids.changes(i, last, mark)
        with section("jackknife: grid upload"):
            if T not in work:
                wb, sb, ib = grids._base_fields(T)
                sv = sb if sog else None
                work[T] = [backend.working_grid(spec, grids.voxels, wb, sv),
                           None if ib is None else backend.working_grid(spec, grids.voxels, ib, sv), None]
            h, hi, _ = work[T]
            backend.write_voxels(h, at, w, stop if sog else None)
            if hi is not None:
                backend.write_voxels(hi, at, ind, stop if sog else None)
            work[T][2] = written
        yield h if hi is None else (h, hi)


def _fields_here(grids: "LeftOutGrids", backend, indicator: str | None) -> bool:
    """Whether the left-out rows are made on the backend (``_rows_on_device``), the tables allow T and every
    count fits an int32."""
    return (_rows_on_device(backend, indicator)
            and grids.T <= FieldTables.MAX_T and (len(grids.counts) == 0 or int(grids.counts.max()) < 2**31))


def _rows_on_device(backend, indicator: str | None) -> bool:
    # the backend makes left-out rows (``left_out_on_device``) and the indicator is none or "uncertain" (their
    # weights above 0; "evidence" needs the counts: the host's rows)
    return indicator in (None, "uncertain") and getattr(backend, "left_out_on_device", False)


def index_tables_used(lidar, occlusion: str, normalisation: str, backend, body=None) -> bool:
    """Whether a jackknife with these settings makes its left-out grids from the pool's index tables
    (``LeftOutRows.batch``): the fused path (``fused_path``) with the rows made on ``backend`` (``_fields_here``;
    the pool's own conditions, T and the count range, are checked there)."""
    return fused_path(lidar, occlusion, normalisation, body) and _rows_on_device(backend, _indicator(normalisation))


def _written_from_device_rows(grids: "LeftOutGrids", pooled, task: str, occlusion: str, backend,
                              indicator: str | None):
    """``patched_in_place`` with every row made on the backend (OpenCL devices with doubles): each record's
    left-out rows in one batch (``device_fields``) and each T's base rows (``device_row_fields``) stay on the
    device; per record the previous record's rows it does not touch are put back from the base's and its own
    written (the indicator from the same rows, read as weight > 0), so nothing but voxel ids and row indexes is
    sent."""
    sog = occlusion == "sog"
    spec = pooled.grid.spec
    with section("jackknife: left-out grid"):
        batch = device_fields(pooled, task, backend, grids.source)
        _, _, all_rows, *_ = grids.source.batch()
        r_off = np.concatenate([[0], np.cumsum([len(v) for _, v, _, _ in batch])])
    work = {}                     # T -> [handle, indicator handle or None, base weights, base stop, rows last written]
    mark = np.zeros(len(grids.voxels), dtype=bool)
    for i, (T, at, w, stop) in enumerate(batch):
        rows_i = all_rows[r_off[i]:r_off[i + 1]]
        with section("jackknife: grid upload"):
            if T not in work:
                wb, sb = device_row_fields(grids.counts, T, task, backend)
                sv = sb if sog else None
                work[T] = [backend.working_grid(spec, grids.voxels, wb, sv),
                           None if indicator is None else backend.working_grid(spec, grids.voxels, wb.positive(), sv),
                           wb, sb, None]
            h, hi, wb, sb, last = work[T]
            if last is not None:                  # the previous record's other rows back to the base's
                back = _untouched(last, rows_i, mark)
                bw, bs = wb.take(back), sb.take(back) if sog else None
                backend.write_voxels(h, grids.voxels[back], bw, bs)
                if hi is not None:
                    backend.write_voxels(hi, grids.voxels[back], bw.positive(), bs)
            backend.write_voxels(h, at, w, stop if sog else None)
            if hi is not None:
                backend.write_voxels(hi, at, w.positive(), stop if sog else None)
            work[T][4] = rows_i
        yield h if hi is None else (h, hi)


#: Rows of the plain pool's counts per block when the base fields are computed (``LeftOutGrids``): 8192
#: rows of 22 float64 channels are 1.4 MB, so a block's temporaries stay in the cache.
BASE_BLOCK = 8192
