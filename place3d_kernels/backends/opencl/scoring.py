"""The OpenCL backend's M-SOG scores: the prepared grids (``CLGrid``), their in-place writes, and
``score_placements`` / ``score_rays`` over them (``grid.cl``, ``walk_lanes.cl``, ``score_gpu.cl``,
``score_rays.cl``). A mixin of ``OpenCLBackend`` (host.py), whose plumbing (``_in``, ``_out``, ``_launch``,
...) it uses."""

from __future__ import annotations

import numpy as np
import pyopencl as cl

from place3d_kernels.backends.base import GridSpec, dense_rows, check_voxel_rows
from place3d_kernels.backends.bricks import brick_masks, brick_shape, flat_shape
from place3d_kernels.backends.opencl import _runtime as rt
from place3d_kernels.backends.opencl.fields import CLRows

__all__ = ["CLGrid", "OpenCLScoring"]

_MF = cl.mem_flags
#: candidates per score launch are chunked so that their visited-voxel bitsets stay below this
_BITSET_BYTES = 256 * 2**20


def _bit_words(ctx, mask: np.ndarray) -> cl.Buffer:
    """A read-only buffer of ``mask`` (n,) bool as bits: bit b of uint32 word q is element 32 q + b."""
    b = np.packbits(mask, bitorder="little")
    b = np.concatenate([b, np.zeros(-len(b) % 4 or (4 if len(b) == 0 else 0), np.uint8)]).view("<u4")
    return cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(b))


class CLGrid:
    """Handle of a prepared grid: fixed-point weights and the stop mask on the device."""

    def __init__(self, backend: "OpenCLScoring", spec: GridSpec, weights: np.ndarray, stop: np.ndarray | None):
        self.spec = spec
        ctx = backend.ctx
        w = np.ascontiguousarray(weights, dtype=np.int64).reshape(-1)
        if w.shape != (spec.n_voxels,):
            raise ValueError(f"weights must have one int64 per voxel ({spec.n_voxels}), got shape {w.shape}")
        self.weights = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=w)
        nonzero = w != 0
        self.binary = False    # every weight 0 or 1 (prepare_indicator): its sums are counts of bits
        self.use_stop = stop is not None
        # each score strategy reads one form of the occlusion mask: bytes (private) or bricked bit pairs
        # of (occlusion, nonzero weight) for the atomic strategy (score_rays_csr reads them, and flat_masks makes
        # score_rays_flat's from them); only that form is uploaded
        self.stop = self.masks = None
        if backend.score_strategy == "private":
            self.stop = backend._stop_buffer(stop, spec, keep=True)
            # score_reduce's nonzero-weight bits: bit b of word q for voxel 32 q + b (little-endian words)
            self.nonzero = _bit_words(ctx, nonzero)
            # score_walk_lanes reads the stop mask as bits in the same layout
            self.stop_bits = _bit_words(ctx, np.asarray(stop).reshape(-1) != 0) if self.use_stop else backend._dummy
        else:
            sm = None if stop is None else np.asarray(stop).reshape(-1) != 0
            if sm is not None and sm.shape != (spec.n_voxels,):
                raise ValueError(f"stop mask must have one uint8 per voxel ({spec.n_voxels}), got shape {sm.shape}")
            m = brick_masks(spec.shape, nonzero, sm)
            self.masks = cl.Buffer(ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR, hostbuf=m)
        self.flat = None      # score_rays_flat's masks (bricks.flat_brick_masks), made from masks on first use
        self.writable = False  # read-only buffers: write_voxels takes working grids only

    @classmethod
    def working(cls, backend: "OpenCLScoring", spec: GridSpec, use_stop: bool) -> "CLGrid":
        """A grid of zero weights and no stop, its buffers writable (``OpenCLBackend.working_grid``), in the
        form of the backend's score strategy; filled on the device, nothing uploaded."""
        self = cls.__new__(cls)
        self.spec, self.use_stop, self.writable, self.binary = spec, bool(use_stop), True, False
        n = spec.n_voxels
        words = max((n + 31) // 32, 1)
        zeros = backend._zeroed
        self.weights = zeros(n * 8)
        self.stop = self.masks = self.flat = None
        if backend.score_strategy == "private":
            self.nonzero = zeros(words * 4)
            self.stop = zeros(n) if use_stop else backend._dummy
            self.stop_bits = zeros(words * 4) if use_stop else backend._dummy
        else:
            bx, by, bz = brick_shape(spec.shape)
            self.masks = zeros(2 * bx * by * bz * 4)
        return self


class OpenCLScoring:
    """``Backend``'s grid and score methods on OpenCL (see the module docstring)."""

    def prepare_grid(self, grid, weights, stop):
        return CLGrid(self, grid, weights, stop)

    def prepare_indicator(self, grid, weights, stop):
        # its sums are counted from bits (score_reduce's popcount, the masked count_bits): the caller's 0/1 promise
        h = CLGrid(self, grid, weights, stop)
        h.binary = True
        return h

    writes_grids = True

    def working_grid(self, grid, voxels, weights, stop):
        h = CLGrid.working(self, grid, stop is not None)
        self.write_voxels(h, voxels, weights, stop)
        return h

    def indicator_from_rows(self, grid, voxels, weights, stop):
        # the dense arrays and prepare_indicator, not a working grid: with a working-grid indicator beside it, the
        # default optimize's search scored about 10 % slower on PoCL (dev VM, five pairs of runs, 4-11 s of
        # 44-62 s; one call alone showed no difference, the cause was not found); GPUs not measured
        w, s = dense_rows(grid, voxels, weights, stop)
        return self.prepare_indicator(grid, w, s)

    def write_voxels(self, handle, voxels, weights, stop):
        if not isinstance(handle, CLGrid) or not handle.writable:
            raise TypeError(f"write_voxels needs a handle from {self.name}.working_grid, got {type(handle).__name__}")
        spec = handle.spec
        if isinstance(weights, CLRows):         # rows on the device (left_out_fields): read there, not sent
            ids, row_args = self._device_row_args(voxels, weights, stop, spec.n_voxels, handle.use_stop)
        else:
            ids, w, s = check_voxel_rows(voxels, weights, stop, spec.n_voxels, handle.use_stop)
            row_args = (self._in(w), self._in(s), np.int64(len(ids)), np.int64(0), np.int64(0), self._dummy,
                        np.int32(0))
        n = len(ids)
        if n:
            rows = (self._in(ids), *row_args, handle.weights)
            if self.score_strategy == "private":
                self._launch("patch_private", n, *rows, handle.nonzero, np.int32(handle.use_stop), handle.stop,
                             handle.stop_bits)
                handle.masks = None                  # score_rays derives them again from the new buffers
            else:
                _, by, bz = brick_shape(spec.shape)
                self._launch("patch_bricked", n, *rows, handle.masks, np.int32(handle.use_stop),
                             *(np.int32(v) for v in (spec.shape[1], spec.shape[2], by, bz)))
                if handle.flat is not None:          # the score kernel's bricks, made again from the pairs
                    self._fill_flat(handle)
        self.queue.finish()         # the rows' host memory (_in uses it in place on CPUs) is free after this

    def _device_row_args(self, voxels, weights: CLRows, stop, n_voxels: int, use_stop: bool):
        """(flat voxel ids, the patch kernels' row arguments) for rows on the device, checked as
        ``check_voxel_rows`` checks host rows: one weight and stop value per voxel, both picked by one index."""
        ids = np.ascontiguousarray(voxels, dtype=np.int64).reshape(-1)
        if use_stop and stop is None:
            raise ValueError("a grid with a stop mask needs a stop value per written voxel")
        s = stop if use_stop else None
        if s is not None and not isinstance(s, CLRows):
            raise TypeError(f"weights on the device need their stop flags there too, got {type(s).__name__}")
        if len(weights) != len(ids) or (s is not None and len(s) != len(ids)):
            raise ValueError(f"writing {len(ids)} voxels needs one weight and one stop value per voxel, got "
                             f"{len(weights)} and {len(ids) if s is None else len(s)}")
        if s is not None and s.index is not weights.index:
            raise ValueError("device weights and stop flags must be picked by the same index")
        if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= n_voxels):
            raise ValueError(f"voxel indices must lie in [0, {n_voxels}), got [{int(ids.min())}, {int(ids.max())}]")
        flags = (1 if weights.index is not None else 0) | (2 if weights.is_positive else 0)
        gather = self._dummy if weights.index is None else self._in(np.asarray(weights.index, dtype=np.int64))
        return ids, (weights.buffer, self._dummy if s is None else s.buffer, np.int64(len(ids)),
                     np.int64(weights.offset), np.int64(0 if s is None else s.offset), gather, np.int32(flags))

    def _zeroed(self, nbytes: int) -> cl.Buffer:
        buf = self._out(nbytes)
        cl.enqueue_fill_buffer(self.queue, buf, np.uint8(0), 0, buf.size)
        return buf

    def score_placements(self, handle, elevations, azimuths, t_max, poses):
        return self.score_placements_many([handle], elevations, azimuths, t_max, poses)[0]

    def score_placements_many(self, handles, elevations, azimuths, t_max, poses):
        """``Backend.score_placements_many``: with the private strategy the rays are walked once (on the first
        handle's stop mask) and each grid's weights reduced over the same bitsets; the atomic strategy sums
        weights during its walk, so it walks once per grid, except for grids of 0/1 weights (indicators,
        ``prepare_indicator``), whose sums it counts from the first grid's bitsets against their nonzero bits."""
        handles = list(handles)
        for handle in handles:
            if not isinstance(handle, CLGrid):
                raise TypeError(f"score_placements needs the handle from {self.name}.prepare_grid, "
                                f"got {type(handle).__name__}")
        if len(handles) < 2:
            return [self._score_placements(h, elevations, azimuths, t_max, poses) for h in handles]
        if self.score_strategy == "private":
            return self._score_private(handles, elevations, azimuths, t_max, poses)
        first = handles[0]
        extra = [h for h in handles[1:] if h.binary and h.spec.shape == first.spec.shape]
        got = dict(zip(map(id, [first] + extra), self._score_placements(first, elevations, azimuths, t_max, poses,
                                                                        extra, many=True)))
        return [got[id(h)] if id(h) in got else self._score_placements(h, elevations, azimuths, t_max, poses)
                for h in handles]

    def _score_inputs(self, poses, elevations, azimuths):
        """(P, L, rig pose rows, direction table buffer, rays per LiDAR) of a score call."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[2] != 6:
            raise ValueError(f"poses must have shape (P, L, 6), got {poses.shape}")
        P, L = poses.shape[:2]
        rig = self._rig_poses(poses.reshape(-1, 6))
        local, sdir_b = self._directions.get(elevations, azimuths)      # host table and its kept buffer
        return P, L, rig, sdir_b, len(local)

    def _score_private(self, handles, elevations, azimuths, t_max, poses):
        """The private strategy: per chunk of candidates the rays walked once, on the first handle's stop mask
        (the caller's promise: every handle has the same), then each handle's weights summed over the bits."""
        P, L, rig, sdir_b, CA = self._score_inputs(poses, elevations, azimuths)
        out = [(np.zeros(P, dtype=np.int64), np.zeros(P, dtype=np.int64)) for _ in handles]
        n_rays = L * CA
        if P == 0 or n_rays == 0:
            return out
        handle = handles[0]
        spec = handle.spec
        if any(h.spec.shape != spec.shape for h in handles):
            raise ValueError("score_placements_many needs grids of one shape")
        words = (spec.n_voxels + 31) // 32
        ga = self._grid_args(spec, handle.stop, handle.use_stop)
        # few threads: a private bitset per work-item, no atomics, then an OR-reduction per candidate
        G = int(max(1, min(64, -(-4 * self.device.max_compute_units // P),
                           _BITSET_BYTES // max(words * 4, 1))))
        chunk = int(max(1, min(P, _BITSET_BYTES // max(words * 4 * G, 1))))
        per = 4096
        n_chunks = (words + per - 1) // per
        # rays in vector lanes (walk_lanes.cl), where voxel indices fit its 32 bits
        walk = "score_walk_lanes" if self.walk_lanes and spec.n_voxels < 2**31 else "score_walk"
        bits = self._out(chunk * G * words * 4)
        ps, pc = self._out(chunk * n_chunks * 8), self._out(chunk * n_chunks * 8)
        for p0 in range(0, P, chunk):
            pn = min(chunk, P - p0)
            cl.enqueue_fill_buffer(self.queue, bits, np.uint32(0), 0, pn * G * words * 4)
            rig_b = self._in(rig[p0 * L:(p0 + pn) * L])
            # the lane walk takes the stop mask as bits (walk_lanes.cl), score_walk as bytes
            grid_args = (*ga[:4], handle.stop_bits, ga[5]) if walk == "score_walk_lanes" else ga
            self._launch(walk, (G, pn), rig_b, sdir_b, np.int32(L), np.int32(CA), self.real(t_max),
                         *grid_args, bits, np.int64(words), np.int32(G))
            for h, (sums, counts) in zip(handles, out):
                self._launch("score_reduce", (n_chunks, pn), bits, np.int64(words), np.int32(G), np.int32(per),
                             np.int32(n_chunks), h.weights, h.nonzero, np.int32(h.binary), np.int64(spec.n_voxels),
                             ps, pc)
                sums[p0:p0 + pn] = self._read(ps, np.int64, pn * n_chunks).reshape(pn, -1).sum(1, dtype=np.int64)
                counts[p0:p0 + pn] = self._read(pc, np.int64, pn * n_chunks).reshape(pn, -1).sum(1, dtype=np.int64)
        return out

    def _score_placements(self, handle, elevations, azimuths, t_max, poses, extra=(), many: bool = False):
        """(sums, counts) of ``handle``; with ``many``, [(sums, counts)] of ``handle`` and then of each 0/1 grid
        of ``extra`` (atomic strategy: counted from ``handle``'s bitsets, its counts ``handle``'s)."""
        if self.score_strategy == "private":
            got = self._score_private([handle, *extra], elevations, azimuths, t_max, poses)
            return got if many else got[0]
        P, L, rig, sdir_b, CA = self._score_inputs(poses, elevations, azimuths)
        sums = np.zeros(P, dtype=np.int64)
        counts = np.zeros(P, dtype=np.int64)
        marked = [np.zeros(P, dtype=np.int64) for _ in extra]
        n_rays = L * CA
        if P == 0 or n_rays == 0:
            return [(sums, counts)] + [(m, counts.copy()) for m in marked] if many else (sums, counts)
        spec = handle.spec
        per = self.rays_per_item
        items = (n_rays + per - 1) // per
        flat, (fx, fy, fz) = self._flat_masks(handle), flat_shape(spec.shape)
        words = fx * fy * fz
        if words >= 2**31:
            raise ValueError(f"grid of shape {spec.shape} needs {words:,} bitset words per candidate; the OpenCL "
                             f"score kernel indexes fewer than 2**31 (a coarser voxel size or a smaller grid)")
        chunk = int(max(1, min(P, _BITSET_BYTES // max(words * 4, 1))))
        bits = self._out(chunk * words * 4)
        per_count = 256
        n_chunks = (words + per_count - 1) // per_count
        gpu = self.score_kernel == "gpu" and n_rays < 2**31
        ps = self._out(chunk * (1 if gpu else items) * 8)
        pc = self._out(chunk * n_chunks * 8)
        grid_args = (self.real(t_max), self.real(spec.voxel_size), *(np.int32(v) for v in spec.shape),
                     np.int32(fx), np.int32(fy), flat, handle.weights, bits, np.int64(words))
        for p0 in range(0, P, chunk):
            pn = min(chunk, P - p0)
            cl.enqueue_fill_buffer(self.queue, bits, np.uint32(0), 0, pn * words * 4)
            rig_b = self._in(rig[p0 * L:(p0 + pn) * L])
            if gpu:
                cl.enqueue_fill_buffer(self.queue, ps, np.int64(0), 0, pn * 8)
                G = int(self.score_group_size)
                k = self._score_gpu_kernel()
                with self._lock:
                    k(self.queue, (-(-n_rays // G) * G, pn), (G, 1), rig_b, sdir_b, np.int32(L), np.int32(CA),
                      *grid_args, np.int32(n_rays), ps)
            else:
                self._launch("score_rays_flat", (items, pn), rig_b, sdir_b, np.int32(L), np.int32(CA), *grid_args,
                             np.int32(per), np.int32(items), ps)
            self._launch("count_bits", (n_chunks, pn), bits, np.int64(words), np.int32(per_count),
                         np.int32(n_chunks), self._dummy, np.int32(0), pc)
            part = self._read(ps, np.int64, pn * (1 if gpu else items))
            sums[p0:p0 + pn] = part.reshape(pn, -1).sum(axis=1, dtype=np.int64)
            counts[p0:p0 + pn] = self._read(pc, np.int64, pn * n_chunks).reshape(pn, -1).sum(axis=1, dtype=np.int64)
            for h, m in zip(extra, marked):         # an indicator's covered voxels of weight 1, from these bits
                self._launch("count_bits", (n_chunks, pn), bits, np.int64(words), np.int32(per_count),
                             np.int32(n_chunks), self._flat_masks(h), np.int32(1), pc)
                m[p0:p0 + pn] = self._read(pc, np.int64, pn * n_chunks).reshape(pn, -1).sum(axis=1, dtype=np.int64)
        return [(sums, counts)] + [(m, counts.copy()) for m in marked] if many else (sums, counts)

    #: work-group size of score_gpu.cl's kernel. On an H100 groups of 64 and 128 were equally fast, 256 slower, and
    #: NVIDIA register caps from 40 to 80 changed nothing (bench/README.md, "What the studies found", dense rig)
    score_group_size: int = 128

    def _score_gpu_kernel(self) -> cl.Kernel:
        """score_gpu.cl's kernel, built once per work-group size."""
        opts = self._options() + (f"-DSCORE_GROUP={int(self.score_group_size)}",)
        key = "score_rays_gpu" + " ".join(opts)
        k = self._kernels.get(key)
        if k is None:
            k = self._kernels[key] = rt.build_program(self.ctx, ("common.cl", "grid.cl", "score_gpu.cl"),
                                                      opts).score_rays_gpu
        return k

    def _flat_masks(self, handle):
        """score_rays_flat's masks for a grid (atomic strategy), made once on the device from its brick pairs."""
        if handle.flat is None:
            fx, fy, fz = flat_shape(handle.spec.shape)
            handle.flat = cl.Buffer(self.ctx, _MF.READ_WRITE, size=max(fx * fy * fz, 1) * 8)
            self._fill_flat(handle)
        return handle.flat

    def _fill_flat(self, handle) -> None:
        spec = handle.spec
        bx, by, bz = brick_shape(spec.shape)
        fx, fy, fz = flat_shape(spec.shape)
        n = fx * fy * fz
        self._launch("flat_masks", n, handle.masks, np.int32(bx), np.int32(by), np.int32(bz), np.int32(fx),
                     np.int32(fy), np.int64(n), handle.flat)

    def score_rays(self, handle, origins, directions, t_end, ray_offsets):
        """``Backend.score_rays``: ``score_rays.cl`` over all rays (one work-item per ray, atomic bricked
        bitsets per candidate), then ``count_bits``; partial sums are added per candidate on the host."""
        from place3d_kernels.backends.base import check_ray_batch

        if not isinstance(handle, CLGrid):
            raise TypeError(f"score_rays needs the handle from {self.name}.prepare_grid, got {type(handle).__name__}")
        o64, d64, te64, off = check_ray_batch(origins, directions, t_end, ray_offsets)
        P, n = len(off) - 1, len(o64)
        sums = np.zeros(P, dtype=np.int64)
        counts = np.zeros(P, dtype=np.int64)
        if P == 0 or n == 0:
            return sums, counts
        spec = handle.spec
        if handle.masks is None:
            # grids prepared for the private strategy hold the byte stop mask only; the bricked masks are
            # derived once from the device copies and kept on the handle (score_placements never reads them)
            w = self._read(handle.weights, np.int64, spec.n_voxels)
            sm = self._read(handle.stop, np.uint8, spec.n_voxels) != 0 if handle.use_stop else None
            handle.masks = cl.Buffer(self.ctx, _MF.READ_ONLY | _MF.COPY_HOST_PTR,
                                     hostbuf=brick_masks(spec.shape, w != 0, sm))
        if "score_rays_csr" not in self._kernels:
            prg = rt.build_program(self.ctx, ("common.cl", "grid.cl", "score_rays.cl"), self._options())
            self._kernels["score_rays_csr"] = prg.score_rays_csr
        o, d, te = self._rays(o64, d64, te64)
        cand = np.repeat(np.arange(P, dtype=np.int32), np.diff(off))
        bx, by, bz = brick_shape(spec.shape)
        words = bx * by * bz
        per_count = 256
        n_chunks = (words + per_count - 1) // per_count
        # candidates in chunks whose bitsets stay below _BITSET_BYTES (whole candidates per chunk)
        chunk = int(max(1, min(P, _BITSET_BYTES // max(words * 4, 1))))
        bits = self._out(chunk * words * 4)
        pc = self._out(chunk * n_chunks * 8)
        for p0 in range(0, P, chunk):
            pn = min(chunk, P - p0)
            a, b = int(off[p0]), int(off[p0 + pn])
            cl.enqueue_fill_buffer(self.queue, bits, np.uint32(0), 0, pn * words * 4)
            if b > a:
                part, pb = self._host_out(np.int64, b - a)
                # named: CPU buffers use the NumPy memory in place, which must outlive the kernel
                cand_p = cand[a:b] - np.int32(p0)
                bufs = [self._in(o[a:b]), self._in(d[a:b]), self._in(te[a:b]), self._in(cand_p)]
                self._launch("score_rays_csr", b - a, *bufs, self.real(spec.voxel_size),
                             *(np.int32(v) for v in spec.shape), np.int32(by), np.int32(bz), handle.masks,
                             handle.weights, bits, np.int64(words), pb, np.int32(b - a))
                part = self._fetch(part, pb)
                cs = np.concatenate([[0], np.cumsum(part, dtype=np.int64)])
                sums[p0:p0 + pn] = cs[off[p0 + 1:p0 + pn + 1] - a] - cs[off[p0:p0 + pn] - a]
            self._launch("count_bits", (n_chunks, pn), bits, np.int64(words), np.int32(per_count),
                         np.int32(n_chunks), self._dummy, np.int32(0), pc)
            counts[p0:p0 + pn] = self._read(pc, np.int64, pn * n_chunks).reshape(pn, -1).sum(axis=1, dtype=np.int64)
        return sums, counts
