"""The Warp backend's M-SOG scores: the prepared grids (``_WarpGrid``, and ``_WarpGridBase`` for grids patched
on the device), their device-side patches and left-out fields, and ``score_placements`` / ``score_rays`` over
them (kernels.py on the CPU, score_gpu.py on CUDA, score_rays.py, left_out_kernels.py). A mixin of ``WarpCore``
(host.py), whose plumbing (``device``, ``k``, ``score_gpu``, ``threads``, ``_run_chunks``, ``_launch_groups``,
``_vec3d``, ...) it uses."""

from __future__ import annotations

import os

import numpy as np
import warp as wp

from place3d_kernels.backends.base import check_voxel_rows, resident_copy, rotation_matrices
from place3d_kernels.backends.bricks import brick_masks, brick_shape, brick_word_bits, flat_shape
from place3d_kernels.backends.warp.cpu_split import CHUNKS_PER_THREAD, MIN_CHUNK

__all__ = ["WarpScoring", "SPLIT_SINGLE_RIG", "SPLIT_MIN_RAYS"]

# Split a single rig on the CPU over the threads (per-thread bitsets, OR-ed; _score_one_rig_split)? Exact
# either way. It pays only for large rigs on cores that are really idle: the split work costs somewhat more
# (near-sensor voxels marked once per thread) plus the union's sum on the host. On an idle machine a large rig
# scored markedly faster split and a small one no faster; under other load it was slower at every size
# (bench/README.md, "What the studies found", M-SOG walk on the CPU). So None (the default) splits rigs of
# SPLIT_MIN_RAYS or more when the 1-minute load average leaves a core idle beside this process; True / False
# force it (tests force it on to check it stays exact).
SPLIT_SINGLE_RIG: bool | None = None
SPLIT_MIN_RAYS = 65536


def _split_pays(rays: int, threads: int) -> bool:
    if SPLIT_SINGLE_RIG is not None:
        return SPLIT_SINGLE_RIG
    if rays < SPLIT_MIN_RAYS or threads < 2:
        return False
    try:
        return os.getloadavg()[0] <= threads - 1.0     # this process counts one; another core must be free
    except OSError:  # pragma: no cover - no load average on this platform
        return False


class _WarpGrid:
    def __init__(self, spec, weights, masks, flat=None):
        self.spec = spec
        self.weights = weights          # int64 fixed-point entropy, flat voxel order
        self.masks = masks              # per brick word w: [2w] occlusion bits, [2w + 1] nonzero-weight bits
                                        # (uint32 pairs; on CUDA the same bytes as one uint64 per brick)
        self.flat = flat                # CUDA: the score kernel's masks per 8 x 4 x 1 brick (bricks.flat_brick_masks)
        self.binary = False             # every weight 0 or 1 (prepare_indicator): its sums are counts of bits
        self.writable = False           # a CPU working grid (working_grid), which write_voxels changes
        self.has_stop = False           # a working grid's: whether it has a stop mask (occlusion bits)

    def nonzero_words(self, cuda: bool):
        """This grid's masks in the score bitsets' layout, one uint64 per word (nonzero-weight bits high):
        the flat bricks on CUDA, on the CPU the 4 x 4 x 2 brick pairs read as one uint64 each (an alias)."""
        if cuda:
            return self.flat
        return wp.array(ptr=self.masks.ptr, shape=(self.masks.shape[0] // 2,), dtype=wp.uint64,
                        device=self.masks.device)


class _WarpGridBase:
    def __init__(self, spec, weights, stop):
        self.spec = spec
        self.weights = weights          # int64, flat voxel order
        self.stop = stop                # uint8 per voxel, or None (no occlusion)


class WarpScoring:
    """``Backend``'s grid and score methods on Warp (see the module docstring)."""

    # ------------------------------------------------------------------ grids
    def prepare_grid(self, grid, weights, stop):
        w = wp.array(np.ascontiguousarray(weights, dtype=np.int64), dtype=wp.int64, device=self.device)
        masks = brick_masks(grid.shape, np.asarray(weights).reshape(-1) != 0,
                            None if stop is None else np.asarray(stop).reshape(-1) != 0)
        if self.device.is_cuda:   # each brick's pair as one little-endian uint64, and the score kernel's bricks
            pairs = wp.array(masks.view(np.uint64), dtype=wp.uint64, device=self.device)
            return _WarpGrid(grid, w, pairs, self._flat_masks(grid.shape, pairs))
        return _WarpGrid(grid, w, wp.array(masks, dtype=wp.uint32, device=self.device))

    def prepare_indicator(self, grid, weights, stop):
        # score_placements_many counts its covered voxels from the first grid's bits (the caller's 0/1 promise)
        h = self.prepare_grid(grid, weights, stop)
        h.binary = True
        return h

    def _flat_masks(self, shape, pairs):
        """The CUDA score kernel's masks (``bricks.flat_brick_masks``) from a grid's brick pairs, on the device."""
        bx, by, bz = brick_shape(shape)
        fx, fy, fz = flat_shape(shape)
        flat = wp.empty(fx * fy * fz, dtype=wp.uint64, device=self.device)
        # the score module's block size: another would compile the module again (score_gpu's note on block_dim)
        wp.launch(self.score_gpu.flat_masks_kernel, dim=fx * fy * fz, device=self.device,
                  inputs=[pairs, int(bx), int(by), int(bz), int(fx), int(fy), flat],
                  block_dim=self.score_gpu.SCORE_BLOCK_DIM)
        return flat

    @property
    def writes_grids(self) -> bool:
        """On the CPU device: one grid written in place (``working_grid``, ``write_voxels``) through the host's view
        of its arrays. The jackknife's left-out grids then cost the voxels that change instead of a dense host copy
        and ``prepare_grid``'s copy of it and its brick masks: default ``place3d evaluate``'s grid uploads
        took 0.6 s a grid on a 2-core VM (README, Speed). On CUDA the grids are patched on the device."""
        return not self.device.is_cuda

    def working_grid(self, grid, voxels, weights, stop):
        if self.device.is_cuda:
            raise NotImplementedError(f"{self.name} patches grids on the device (patched_grid); use prepare_grid")
        bx, by, bz = brick_shape(grid.shape)
        h = _WarpGrid(grid, wp.zeros(grid.n_voxels, dtype=wp.int64, device=self.device),
                      wp.zeros(2 * bx * by * bz, dtype=wp.uint32, device=self.device))
        h.writable, h.has_stop = True, stop is not None
        self.write_voxels(h, voxels, weights, stop)
        return h

    def write_voxels(self, handle, voxels, weights, stop):
        if not isinstance(handle, _WarpGrid) or not handle.writable:
            raise TypeError(f"write_voxels needs a handle from {self.name}.working_grid, got {type(handle).__name__}")
        ids, w, s = check_voxel_rows(voxels, weights, stop, handle.spec.n_voxels, handle.has_stop)
        if not len(ids):
            return
        handle.weights.numpy()[ids] = w           # the CPU device's arrays: host memory, viewed without a copy
        # each voxel's bit in its brick's pair of words (nonzero-weight word 2b + 1, occlusion word 2b): cleared,
        # then set where it holds
        word, bit = brick_word_bits(ids, handle.spec.shape)
        masks = handle.masks.numpy()
        for at, on in [(2 * word + 1, w != 0)] + ([(2 * word, s != 0)] if handle.has_stop else []):
            np.bitwise_and.at(masks, at, ~bit)
            np.bitwise_or.at(masks, at[on], bit[on])

    @property
    def patches_grids(self) -> bool:
        # on CUDA; on the CPU the host's patched copy and prepare_grid were faster than these kernels, which
        # run there too (measured on the default town's left-out grids)
        return self.device.is_cuda

    def grid_base(self, grid, weights, stop):
        w = wp.array(np.ascontiguousarray(weights, dtype=np.int64).reshape(-1), dtype=wp.int64, device=self.device)
        s = None
        if stop is not None:
            s = wp.array((np.asarray(stop).reshape(-1) != 0).view(np.uint8), dtype=wp.uint8, device=self.device)
        return _WarpGridBase(grid, w, s)

    def grid_from_rows(self, grid, voxels, weights, stop):
        if not self.device.is_cuda:             # the host's dense arrays (as prepare_grid's callers make them)
            return super().grid_from_rows(grid, voxels, *_on_host(weights, stop))
        # zeros on the device, the rows scattered there and the brick masks made by a kernel: patched_grid on a
        # zero base, so no dense host array and no upload of the whole grid
        ids, w_rows, s_rows = self._rows_here(voxels, weights, stop, grid.n_voxels)
        base = self._zero_base(grid, stop is not None)
        return self._patched(grid, base.weights, base.stop, ids, w_rows, None if stop is None else s_rows)

    def indicator_from_rows(self, grid, voxels, weights, stop):
        h = self.grid_from_rows(grid, voxels, weights, stop)     # on CUDA filled there, brick masks by a kernel
        h.binary = True
        return h

    def grid_base_from_rows(self, grid, voxels, weights, stop):
        if not self.device.is_cuda:
            return super().grid_base_from_rows(grid, voxels, *_on_host(weights, stop))
        base = self._zero_base(grid, stop is not None)
        ids, w_rows, s_rows = self._rows_here(voxels, weights, stop, grid.n_voxels)
        if len(ids):
            dev = self.device
            s_arg = base.stop if base.stop is not None else wp.zeros(1, dtype=wp.uint8, device=dev)
            wp.launch(self.k.scatter_rows_kernel, dim=len(ids), device=dev,
                      inputs=[wp.array(ids, dtype=wp.int64, device=dev), w_rows, s_rows, int(stop is not None),
                              base.weights, s_arg])
        return base

    def _rows_here(self, voxels, weights, stop, n_voxels: int):
        """(flat int64 voxel ids on the host, weights (R,) int64 and stop (R,) uint8 on this device) of a
        ``grid_from_rows`` call, checked as ``check_voxel_rows`` checks them. Weights and stop already on the
        device (``PSOG._device_rows``, ``left_out_tables.device_row_fields``) are used where they are."""
        dev = self.device
        if not isinstance(weights, wp.array):
            ids, w, s = check_voxel_rows(voxels, weights, stop, n_voxels, stop is not None)
            return ids, wp.array(w, dtype=wp.int64, device=dev), wp.array(s, dtype=wp.uint8, device=dev)
        ids = np.ascontiguousarray(voxels, dtype=np.int64).reshape(-1)
        if weights.shape != ids.shape or (stop is not None and stop.shape != ids.shape):
            raise ValueError(f"writing {len(ids)} voxels needs one weight and one stop value per voxel")
        if len(ids) and (int(ids.min()) < 0 or int(ids.max()) >= n_voxels):
            raise ValueError(f"voxel indices must lie in [0, {n_voxels}), got [{int(ids.min())}, {int(ids.max())}]")
        return ids, weights, stop if stop is not None else wp.zeros(len(ids), dtype=wp.uint8, device=dev)

    def _zero_base(self, grid, has_stop: bool) -> _WarpGridBase:
        dev = self.device
        return _WarpGridBase(grid, wp.zeros(grid.n_voxels, dtype=wp.int64, device=dev),
                             wp.zeros(grid.n_voxels, dtype=wp.uint8, device=dev) if has_stop else None)

    @property
    def fields_on_device(self) -> bool:
        """Whether the jackknife computes its left-out rows here in one batch (``left_out_fields``; on CUDA,
        where the host's rows were most of a left-out grid's time), and a P-SOG's grid its fields."""
        return self.device.is_cuda

    @property
    def left_out_on_device(self) -> bool:
        """The jackknife's switch (``left_out._fields_here``): as ``fields_on_device`` on Warp."""
        return self.fields_on_device

    def left_out_fields(self, counts, rows, estart, ecls, ecnt, row_t, Ts, term, stop_t, other, det, veh, scale):
        """Weights and stop flags of left-out count rows, one device batch (``left_out_kernels``): row r is
        ``counts[rows[r]]`` less the entries ``estart[r]:estart[r + 1]`` of ``(ecls, ecnt)``, over
        ``Ts[row_t[r]]`` subsets, its terms from the host's tables. Returns two device arrays, (R,) int64 and
        (R,) uint8, for ``patched_grid``."""
        from place3d_kernels.backends.warp import left_out_kernels

        dev = self.device
        R = len(rows)
        w = wp.empty(max(R, 1), dtype=wp.int64, device=dev)
        s = wp.empty(max(R, 1), dtype=wp.uint8, device=dev)
        if R:
            a = self._resident
            wp.launch(left_out_kernels.left_out_fields_kernel, dim=R, device=dev,
                      inputs=[a(counts, np.int32), a(rows, np.int64), a(estart, np.int32), a(ecls, np.int32),
                              a(ecnt, np.int32), a(row_t, np.int32), a(Ts, np.int32), a(term, np.float64),
                              a(stop_t, np.uint8), a(other, np.float64), int(det), int(veh), float(scale), w, s])
        return w[:R], s[:R]

    def _resident(self, x, dtype):
        """``x`` on the device as ``dtype``: a device array as it is, a read-only host array that owns its memory
        sent once while it lives (``base.resident_copy``), anything else sent on each call."""
        if isinstance(x, wp.array):
            return x
        return resident_copy(self.__dict__.setdefault("_resident_arrays", {}), x, dtype,
                             lambda a: wp.array(a, device=self.device))

    def patched_grid(self, base, voxels, weights, stop):
        # the base copied on the device, the changed voxels written over it, and the brick masks made from the
        # result by a kernel (the bits bricks.brick_masks gives the same arrays on the host)
        if base.stop is not None and stop is None:
            raise ValueError("patched_grid needs a stop value per voxel for a base with a stop mask")
        return self._patched(base.spec, wp.clone(base.weights), None if base.stop is None else wp.clone(base.stop),
                             voxels, weights, stop)

    def _patched(self, spec, w, s, voxels, weights, stop):
        # patched_grid on device arrays of its own (w, s), written in place
        nx, ny, nz = spec.shape
        has_stop = int(s is not None)
        s_arg = s if s is not None else wp.zeros(1, dtype=wp.uint8, device=self.device)
        ids = np.ascontiguousarray(voxels, dtype=np.int64).reshape(-1)
        if len(ids):
            # rows given on the device (left_out_fields: int64 weights, uint8 stop) are used where they are
            on_dev = isinstance(weights, wp.array)
            w_rows = weights if on_dev else np.ascontiguousarray(weights, dtype=np.int64).reshape(-1)
            if on_dev:
                s_rows = stop if s is not None else wp.zeros(len(ids), dtype=wp.uint8, device=self.device)
            else:
                s_rows = (np.zeros(len(ids), dtype=np.uint8) if s is None
                          else (np.asarray(stop).reshape(-1) != 0).view(np.uint8))
            if w_rows.shape != ids.shape or s_rows.shape != ids.shape:
                raise ValueError(f"patched_grid needs one weight and one stop value per voxel ({len(ids)}), got "
                                 f"{w_rows.shape[0]} and {s_rows.shape[0]}")
            if not on_dev:
                w_rows = wp.array(w_rows, dtype=wp.int64, device=self.device)
                s_rows = wp.array(s_rows, dtype=wp.uint8, device=self.device)
            wp.launch(self.k.scatter_rows_kernel, dim=len(ids), device=self.device,
                      inputs=[wp.array(ids, dtype=wp.int64, device=self.device), w_rows, s_rows, has_stop, w, s_arg])
        bx, by, bz = brick_shape(spec.shape)
        n_bricks = bx * by * bz
        args = [w, s_arg, has_stop, int(nx), int(ny), int(nz), int(by), int(bz)]
        if self.device.is_cuda:   # each brick's pair as one little-endian uint64, and the score kernel's bricks
            masks = wp.empty(n_bricks, dtype=wp.uint64, device=self.device)
            wp.launch(self.k.brick_masks64_kernel, dim=n_bricks, device=self.device, inputs=args + [masks])
            return _WarpGrid(spec, w, masks, self._flat_masks(spec.shape, masks))
        masks = wp.empty(2 * n_bricks, dtype=wp.uint32, device=self.device)
        wp.launch(self.k.brick_masks_pairs_kernel, dim=n_bricks, device=self.device, inputs=args + [masks])
        return _WarpGrid(spec, w, masks)

    # ------------------------------------------------------------------ scores
    def score_placements(self, handle, elevations, azimuths, t_max, poses):
        return self._score_walked(handle, (), elevations, azimuths, t_max, poses)[0]

    def score_placements_many(self, handles, elevations, azimuths, t_max, poses):
        """``Backend.score_placements_many``: the rays are walked once, on the first grid. A further grid of 0/1
        weights (an indicator, such as the denominators' grids of ``indicators.py``, made by ``prepare_indicator``)
        sums to its covered voxels with weight 1, which are counted from the same bitsets against its
        nonzero-weight bits; its counts are the first grid's (one stop mask: the caller's promise). Other grids
        are walked on their own; with such grids a single rig is not split over CPU threads."""
        handles = list(handles)
        poses = np.asarray(poses, dtype=np.float64)
        first = handles[0] if handles else None
        extra = [h for h in handles[1:] if getattr(h, "binary", False) and h.spec.shape == first.spec.shape]
        if not extra:
            return [self.score_placements(h, elevations, azimuths, t_max, poses) for h in handles]
        got = dict(zip(map(id, [first] + extra), self._score_walked(first, extra, elevations, azimuths, t_max, poses)))
        return [got[id(h)] if id(h) in got else self.score_placements(h, elevations, azimuths, t_max, poses)
                for h in handles]

    def _score_walked(self, handle, extra, elevations, azimuths, t_max, poses):
        """[(sums, counts)] of ``handle`` and then of each grid of ``extra`` (0/1 weights, the same stop mask),
        from one walk of the rays on ``handle``."""
        poses = np.asarray(poses, dtype=np.float64)
        if not np.all(np.isfinite(poses)):
            # metrics.msog_batch refuses them first; here because the CUDA kernel's loop has no step bound,
            # which a ray of NaN direction could need
            bad = np.argwhere(~np.isfinite(poses))[0].tolist()
            raise ValueError(f"poses must be finite; poses{bad} is {poses[tuple(bad)]}")
        P, L = poses.shape[:2]
        if P == 0:     # no candidates: empty scores, as on every backend (a Warp array has no empty slice)
            return [(np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))] * (1 + len(extra))
        flat = poses.reshape(-1, 6)
        sd, sd_a = self._directions.get(elevations, azimuths)     # host and device tables
        # CUDA's score kernel keeps its bitsets in flat bricks, the CPU's in 4 x 4 x 2 ones (bricks.py)
        words = int(np.prod((flat_shape if self.device.is_cuda else brick_shape)(handle.spec.shape)))
        n = P * words
        kept, clean = self._take_bits(n) if self.device.is_cuda else (None, 0)
        bits = wp.zeros(n, dtype=wp.uint32, device=self.device) if kept is None else kept[:n]
        done = False
        try:
            out = self._score_into(handle, bits, sd, sd_a, flat, P, L, t_max, words, extra)
            done = True
            return out
        finally:
            if kept is not None:   # the CUDA count zeroes the words it counts: [:n] is clean after a call
                self._give_bits(kept, max(clean, n) if done else 0)

    # CUDA: the bitsets of a score call are kept for the next one. Allocating them through Warp's memory pool
    # (hundreds of MB for a population of dense rigs) was a visible part of each call, as the pool hands freed
    # memory back at once, and zeroing them added to it; the bit count after the score kernel zeroes what it
    # counts (score_gpu.count_clear_kernel), so a kept buffer comes back clean (bench/README.md, "What the studies
    # found", dense-rig score kernel, API around the kernel). One buffer per backend, the largest recently needed,
    # with the number of leading words known to be zero; a call that finds it taken (another thread scoring)
    # allocates its own.
    def _take_bits(self, n: int):
        """A buffer of at least ``n`` words whose first ``n`` are zero (stream-ordered after the previous
        call's kernels, as a fresh array), and how many leading words were zero already."""
        with self._pool_lock:
            kept, self._bits = self._bits, None
        buf, clean = (None, 0) if kept is None else kept
        if buf is None or buf.shape[0] < n:
            buf, clean = wp.empty(n, dtype=wp.uint32, device=self.device), 0
        if clean < n:
            buf[clean:n].zero_()
        return buf, clean

    def _give_bits(self, buf, clean: int) -> None:
        with self._pool_lock:
            if self._bits is None or self._bits[0].shape[0] < buf.shape[0]:
                self._bits = (buf, clean)

    def _score_into(self, handle, bits, sd, sd_a, flat, P, L, t_max, words, extra=()):
        """score_placements on zeroed bitsets ``bits`` (P * words words): [(sums, counts)] of ``handle``, then
        of each 0/1 grid of ``extra`` (its sums the covered voxels it marks, its counts ``handle``'s)."""
        spec = handle.spec
        nx, ny, nz = spec.shape
        _, by, bz = brick_shape(spec.shape)
        # sums, counts, then each extra grid's sums: one download
        both = wp.zeros((2 + len(extra)) * P, dtype=wp.int64, device=self.device)
        sums, counts = both[:P], both[P:2 * P]
        rot = wp.array(rotation_matrices(flat), dtype=wp.mat33d, device=self.device)
        pos = self._vec3d(flat[:, :3])
        rays = L * len(sd)     # per candidate
        if self.device.is_cuda:
            g = self.score_gpu
            if words > g.MAX_WORDS:
                raise ValueError(f"grid of shape {spec.shape} needs {words:,} bitset words per candidate; the CUDA "
                                 f"score kernel indexes at most {g.MAX_WORDS:,} (a coarser voxel size or a "
                                 f"smaller grid)")
            fx, fy, _ = flat_shape(spec.shape)
            wp.launch(g.score_kernel_gpu, dim=P * rays, device=self.device,
                      inputs=[sd_a, rot, pos, int(L), float(t_max), float(spec.voxel_size), int(nx), int(ny),
                              int(nz), int(fx), int(fy), handle.flat, handle.weights, int(words), bits, sums],
                      block_dim=g.SCORE_BLOCK_DIM)
        elif not extra and P == 1 and self.threads > 1 and rays >= 2 * MIN_CHUNK and _split_pays(rays, self.threads):
            return [self._score_one_rig_split(handle, sd, rot, pos, L, t_max)]
        elif P == 1 or self.threads <= 1:
            # no block_dim on the CPU: the default keeps the kernels module's one compiled variant
            wp.launch(self.k.score_kernel, dim=P * rays, device=self.device,
                      inputs=[sd_a, rot, pos, int(L), float(t_max), float(spec.voxel_size), int(nx), int(ny),
                              int(nz), int(by), int(bz), handle.masks, handle.weights, int(words), bits, sums])
        else:
            # CPU threads take whole candidates: a candidate's bitset and sum are written by one thread only
            def cand_range(a, b):
                return [sd_a, rot[a * L:b * L], pos[a * L:b * L], int(L), float(t_max), float(spec.voxel_size),
                        int(nx), int(ny), int(nz), int(by), int(bz), handle.masks, handle.weights, int(words),
                        bits[a * words:b * words], sums[a:b]]

            self._launch_groups(self.k.score_kernel, P, rays, cand_range)
        if self.device.is_cuda and len(extra) == 1:
            # one pass counts every set bit and the 0/1 grid's, and zeroes the bitsets (count_clear_kernel with
            # masks: 0.540 -> 0.387 ms a call for 14 candidates on the 0.1 m grid, H200;
            # bench/results/ab-2026-12-01-s40/)
            self._count_bits(bits, P, words, counts, both[2 * P:3 * P], extra[0].nonzero_words(True))
        else:
            for e, h in enumerate(extra):          # before _count_bits, which zeroes the CUDA bitsets
                # its covered voxels of nonzero weight: the bits set where its masks have their nonzero bit
                self._count_words(bits, P, words, both[(2 + e) * P:(3 + e) * P], h.nonzero_words(self.device.is_cuda))
            self._count_bits(bits, P, words, counts)
        out = both.numpy()
        # each grid its own counts array (the same covered voxels), so no caller's change reaches another's
        return [(out[:P], out[P:2 * P])] + [(out[(2 + e) * P:(3 + e) * P], out[P:2 * P].copy())
                                            for e in range(len(extra))]

    def _count_bits(self, bits, P: int, words: int, counts, masked=None, masks=None) -> None:
        """counts[c] = set bits of candidate c's bitset (P candidates of ``words`` words each); on CUDA the
        bitsets are left zero, and with ``masks`` (CUDA only: ``nonzero_words(True)`` of a 0/1 grid)
        ``masked[c]`` gets the set bits that grid's nonzero weights keep, in the same pass."""
        if self.device.is_cuda:
            g = self.score_gpu
            if words > g.MAX_WORDS:
                raise ValueError(f"{words:,} bitset words per candidate; the CUDA bit count indexes at most "
                                 f"{g.MAX_WORDS:,} (a coarser voxel size or a smaller grid)")
            t = g.count_threads_per_candidate(words, P)
            with_masks = masks is not None
            wp.launch(g.count_clear_kernel, dim=P * t, device=self.device,
                      inputs=[bits, int(words), int(t), masks if with_masks else self._no_masks(), int(with_masks),
                              counts, masked if with_masks else counts], block_dim=g.SCORE_BLOCK_DIM)
            return
        if masks is not None:
            raise ValueError("a masked count in the clearing pass is CUDA's; on the CPU count_words counts it")
        self._count_words(bits, P, words, counts)

    def _count_words(self, bits, P: int, words: int, counts, masks=None) -> None:
        """count_bits_kernel over P candidates' bitsets, of every set bit or (``masks``) of the masked ones."""
        per = self.k.count_words_per_thread(P * words)
        chunks = -(-words // per)
        masked = masks is not None
        wp.launch(self.k.count_bits_kernel, dim=P * chunks, device=self.device,
                  inputs=[bits, int(words), int(chunks), int(per), masks if masked else self._no_masks(), int(masked),
                          counts])

    def _no_masks(self):
        """The one-word masks argument of an unmasked count (never read)."""
        if getattr(self, "_no_masks_array", None) is None:
            self._no_masks_array = wp.zeros(1, dtype=wp.uint64, device=self.device)
        return self._no_masks_array

    def _score_one_rig_split(self, handle, sd, rot, pos, L, t_max):
        """CPU: one rig's rays over the thread pool, exactly. Thread c walks the sensor directions
        ``sd[c::K]`` (interleaved, so every thread gets rays of every length) of all L LiDARs into a bitset
        of its own; the K bitsets are OR-ed afterwards and the rig's sum is the weights of the union's
        bits with entropy (integer sum: order-free), its count the union's set bits, as one launch gives."""
        spec = handle.spec
        nx, ny, nz = spec.shape
        bx, by, bz = brick_shape(spec.shape)
        words = bx * by * bz
        K = min(self.threads, len(sd) // MIN_CHUNK * L) or 1
        bits = wp.zeros(K * words, dtype=wp.uint32, device=self.device)
        sums = wp.zeros(K, dtype=wp.int64, device=self.device)     # per-thread first-setter sums: unused
        chunks = []
        for c in range(K):
            part = self._vec3d(sd[c::K])
            chunks.append((0, L * len(sd[c::K]), [part, rot, pos, int(L), float(t_max), float(spec.voxel_size),
                                                  int(nx), int(ny), int(nz), int(by), int(bz), handle.masks,
                                                  handle.weights, int(words), bits[c * words:(c + 1) * words],
                                                  sums[c:c + 1]]))
        self._run_chunks(self.k.score_kernel, chunks)
        union = np.bitwise_or.reduce(bits.numpy().reshape(K, words), axis=0)
        count = int(np.bitwise_count(union).sum(dtype=np.int64))
        ent = union & handle.masks.numpy()[1::2]          # bits of covered voxels with a nonzero weight
        wi = np.flatnonzero(ent)
        total = 0
        if len(wi):
            b = np.arange(32, dtype=np.uint32)
            word_i, bit = np.nonzero((ent[wi, None] >> b) & np.uint32(1))
            w = wi[word_i]
            bk, bj, bi = w % bz, (w // bz) % by, w // (bz * by)
            i, j, k = bi * 4 + (bit & 3), bj * 4 + ((bit >> 2) & 3), bk * 2 + (bit >> 4)
            total = int(handle.weights.numpy()[(i * ny + j) * nz + k].sum(dtype=np.int64))
        return np.array([total], dtype=np.int64), np.array([count], dtype=np.int64)

    # ------------------------------------------------------------------ explicit-ray scores
    def score_rays(self, handle, origins, directions, t_end, ray_offsets):
        """``Backend.score_rays``: the kernel of ``score_rays.py`` over all rays, each with its candidate."""
        from place3d_kernels.backends.base import check_ray_batch
        from place3d_kernels.backends.warp import score_rays as kr

        o, d, te, off = check_ray_batch(origins, directions, t_end, ray_offsets)
        P, n = len(off) - 1, len(o)
        spec = handle.spec
        nx, ny, nz = spec.shape
        bx, by, bz = brick_shape(spec.shape)
        words = bx * by * bz
        bits = wp.zeros(max(P * words, 1), dtype=wp.uint32, device=self.device)
        sums = wp.zeros(max(P, 1), dtype=wp.int64, device=self.device)
        counts = wp.zeros(max(P, 1), dtype=wp.int64, device=self.device)
        masks = handle.masks
        if masks.dtype == wp.uint64:   # CUDA grids keep each brick's pair as one uint64: alias as uint32 pairs
            masks = wp.array(ptr=masks.ptr, shape=(2 * masks.shape[0],), dtype=wp.uint32, device=self.device)
        cand = np.repeat(np.arange(P, dtype=np.int32), np.diff(off))
        oa, da, ta, ca = self._vec3d(o), self._vec3d(d), self._f64(te, n), wp.array(cand, dtype=wp.int32,
                                                                                      device=self.device)

        def rays(a, b):
            return [oa[a:b], da[a:b], ta[a:b], ca[a:b], float(spec.voxel_size), int(nx), int(ny), int(nz),
                    int(by), int(bz), masks, handle.weights, int(words), bits, sums]

        if n and (self.device.is_cuda or self.threads <= 1 or P == 1):
            wp.launch(kr.score_rays_kernel, dim=n, device=self.device, inputs=rays(0, n))
        elif n:
            # CPU threads take whole candidates (Warp's CPU atomics are plain read-modify-writes): cut the
            # candidate list into runs of about equal ray counts, at candidate boundaries
            k = min(P, self.threads * CHUNKS_PER_THREAD)
            cuts = np.unique(np.searchsorted(off, np.linspace(0, n, k + 1), side="left").clip(0, P))
            edges = np.unique(off[cuts])
            self._run_chunks(kr.score_rays_kernel, [(int(a), int(b), rays(int(a), int(b)))
                                                    for a, b in zip(edges[:-1], edges[1:]) if b > a])
        if P:
            self._count_bits(bits, P, words, counts)
        return sums.numpy()[:P], counts.numpy()[:P]



def _on_host(weights, stop):
    """(weights, stop) as host arrays, copied back where they are device arrays."""
    if isinstance(weights, wp.array):
        return weights.numpy(), None if stop is None else stop.numpy()
    return weights, stop
