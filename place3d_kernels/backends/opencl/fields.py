"""The OpenCL backend's left-out fields on the device (``left_out.cl``): the jackknife's left-out rows and a
P-SOG's weight and stop rows made from count rows where they are scored, as Warp makes them on CUDA
(``WarpScoring.left_out_fields``), bit for bit the host's ``left_out_tables.FieldTables``. The rows stay on the
device (``CLRows``) and ``OpenCLScoring.write_voxels`` writes them into a working grid there. A mixin of
``OpenCLBackend`` (host.py), whose plumbing (``_in``, ``_out``, ``_launch``, ...) it uses.

On an H200's opencl:nvidia the jackknife of ``reproduce --routes 8`` had spent 4.74 s making these rows on the
host and 1.31 s sending them, against Warp's 0.56 and 0.10 s (one profiled run each, drives cached;
bench/results/ab-2026-11-30-s31/README.md, section 4); made here, 0.51-0.56 and 0.73-0.75 s against 4.59-4.69 and
1.19-1.31 s (two profiled pairs, drives cached), and the whole command 24.2 -> 17.4 s (3 runs each, alternated;
bench/results/ab-2026-11-30-s32/README.md, sections 1 and 7)."""

from __future__ import annotations

import numpy as np
import pyopencl as cl

from place3d_kernels.backends.base import resident_copy

__all__ = ["CLRows", "OpenCLFields"]

_MF = cl.mem_flags


class CLRows:
    """``n`` values of ``dtype`` on the device, from element ``offset`` of ``buffer`` (which holds ``size``):
    a batch of rows or a record's part of it, sliced like an array (``left_out.device_fields``). ``take(index)``
    picks rows by a host index instead (the base's rows put back over a working grid), ``positive()`` reads each
    weight as 1 where it is above 0, else 0 (the "uncertain" indicator); ``numpy()`` reads the values back."""

    def __init__(self, backend, buffer: cl.Buffer, dtype, size: int, n: int | None = None, offset: int = 0,
                 index: np.ndarray | None = None, positive: bool = False):
        self.backend, self.buffer, self.dtype, self.size = backend, buffer, np.dtype(dtype), int(size)
        self.offset = int(offset)
        self.index = index
        self.n = int(len(index) if index is not None else (self.size - self.offset if n is None else n))
        self.is_positive = bool(positive)

    @property
    def shape(self) -> tuple[int]:
        return (self.n,)

    def __len__(self) -> int:
        return self.n

    def _with(self, **kw) -> "CLRows":
        args = dict(n=self.n, offset=self.offset, index=self.index, positive=self.is_positive)
        args.update(kw)
        return CLRows(self.backend, self.buffer, self.dtype, self.size, **args)

    def __getitem__(self, item) -> "CLRows":
        if not isinstance(item, slice) or self.index is not None:
            raise TypeError("CLRows takes a slice of unpicked rows only; use take() for an index")
        a, b, step = item.indices(self.n)
        if step != 1:
            raise ValueError("CLRows slices take a step of 1")
        return self._with(n=max(b - a, 0), offset=self.offset + a)

    def take(self, index) -> "CLRows":
        """The rows at ``index`` (host integers into these rows; the same array object for a grid's weights
        and stop flags, which ``write_voxels`` picks by one upload)."""
        if self.index is not None:
            raise TypeError("CLRows.take on rows already picked")
        index = np.asarray(index)
        if len(index) and (int(index.min()) < 0 or int(index.max()) >= self.n):
            raise IndexError(f"row index out of range [0, {self.n})")
        return self._with(index=index)

    def positive(self) -> "CLRows":
        return self._with(positive=True)

    def numpy(self) -> np.ndarray:
        b = self.backend
        if self.index is None:
            out = np.empty(self.n, dtype=self.dtype)
            if self.n:
                cl.enqueue_copy(b.queue, out, self.buffer, src_offset=self.offset * self.dtype.itemsize)
        else:
            whole = np.empty(self.size, dtype=self.dtype)
            if self.size:
                cl.enqueue_copy(b.queue, whole, self.buffer)
            out = whole[self.offset + np.asarray(self.index, dtype=np.int64)]
        return (out > 0).astype(self.dtype) if self.is_positive else out


class OpenCLFields:
    """``Backend.left_out_fields`` and ``fields_on_device`` on OpenCL (see the module docstring)."""

    @property
    def fields_on_device(self) -> bool:
        """Whether a P-SOG's grid makes its fields here from count rows (``PSOG.handle``): GPUs with doubles (the
        tables' terms are float64). A CPU device keeps the host's rows, which lie in its own memory: with PoCL
        making them on the 2-core dev VM (for the jackknife too) the warm default ``optimize`` took 50.4
        [49.8-51.6] against 47.8 [47.7-58.7] s (its held-out P-SOGs and diagnostics made the "uncertain"
        indicator's host rows beside the device's; 3 runs each, alternated; bench/results/ab-2026-11-30-s32/
        README.md, section 9)."""
        return self.fp64 and not self.is_cpu

    @property
    def left_out_on_device(self) -> bool:
        """Whether the jackknife makes its left-out rows here (``left_out._fields_here``): every device with
        doubles, CPUs too (see ``fields_on_device`` for a P-SOG's grid). With PoCL making them on the 2-core dev VM
        the warm ``reproduce --routes 8`` took 32.5 [31.6-33.0] against 37.6 [36.2-37.7] s, the default
        ``evaluate`` 4.06 against 4.62 s warm, the warm ``optimize`` no longer (3 runs or 5 pairs, alternated;
        bench/results/ab-2026-11-30-s33/README.md, section 8)."""
        return self.fp64

    def left_out_fields(self, counts, rows, estart, ecls, ecnt, row_t, Ts, term, stop_t, other, det, veh, scale):
        """Weights and stop flags of left-out count rows, one launch (``left_out.cl``): row r is
        ``counts[rows[r]]`` less the entries ``estart[r]:estart[r + 1]`` of ``(ecls, ecnt)``, over
        ``Ts[row_t[r]]`` subsets, its terms from the host's tables. Returns (R,) int64 and (R,) uint8 rows on the
        device (``CLRows``) for ``write_voxels``."""
        if not self.fp64:
            raise NotImplementedError(f"{self.name} has no doubles: left-out fields are made on the host")
        counts = np.asarray(counts)
        if counts.ndim != 2:
            raise ValueError(f"counts must be (M, K), got shape {counts.shape}")
        term = np.asarray(term)
        R = len(rows)
        w, s = self._out(max(R, 1) * 8), self._out(max(R, 1))
        if R:
            a = self._resident
            args = (a(counts, np.int32), np.int32(counts.shape[1]), a(rows, np.int64), a(estart, np.int32),
                    a(ecls, np.int32), a(ecnt, np.int32), a(row_t, np.int32), a(Ts, np.int32), a(term, np.float64),
                    a(stop_t, np.uint8), a(other, np.float64), np.int32(term.shape[1]), np.int32(bool(det)),
                    np.int32(veh), np.float64(scale), np.int64(R), w, s)
            self._launch("left_out_fields", R, *args)
            if self.is_cpu:     # the inputs' host memory (``_in`` uses it in place there) is held until this
                self.queue.finish()
            del args
        return CLRows(self, w, np.int64, R), CLRows(self, s, np.uint8, R)

    def _resident(self, x, dtype) -> cl.Buffer:
        """``x`` on the device as ``dtype``: on GPUs a read-only host array that owns its memory is sent once and
        its copy kept while it lives (``base.resident_copy``, as Warp's), anything else sent on each call; on CPUs
        the host memory itself (``_in``)."""
        if self.is_cpu:
            return self._in(np.ascontiguousarray(x, dtype=dtype))
        return resident_copy(self.__dict__.setdefault("_resident_buffers", {}), x, dtype, self._send_copy)

    def _send_copy(self, a: np.ndarray) -> cl.Buffer:
        if a.nbytes == 0:
            return self._dummy
        buf = cl.Buffer(self.ctx, _MF.READ_ONLY, size=a.nbytes)
        cl.enqueue_copy(self.queue, buf, a)
        return buf
