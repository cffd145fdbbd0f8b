"""Warp kernels of the dense-rig lane-utilisation study (``gpu_dense_variants.py``, issue 17, goal 3).

Nsight Compute found the shipped CUDA score kernel (``score_kernel_gpu``: one thread per ray, per-brick
memory traffic) with only about 16 of 32 lanes of a warp active: the rays of a warp have very different
lengths (some stop at the first occupied voxel next to the car, others cross 100 m of free space), and a
warp runs until its longest ray ends. Two exact remedies, and both together:

* **ray order** (``tiled_kernel``): a pure permutation of the thread index, so that the 32 lanes of a
  warp walk a ``tile_c`` x ``32 / tile_c`` (channel x azimuth) tile of one LiDAR instead of 32
  consecutive azimuths of one channel; neighbouring beams have similar lengths and walk nearby voxels.
  ``tile_c = 1`` is the shipped order.
* **persistent threads with ray refill** (``persistent_kernel``): "while-while" traversal with
  replacement of finished rays (Aila & Laine, "Understanding the Efficiency of Ray Traversal on GPUs",
  HPG 2009, sections 3-4): a launch of about as many threads as the GPU holds at once; each loops, and a
  lane whose ray has ended takes the next ray (from a global atomic counter, ``chunk`` rays at a time,
  or with a fixed stride) instead of idling until the warp's longest ray is done. Ray indices go
  through the same tile permutation, so ``tile_c = 4`` combines both.

The per-ray work is the shipped ``score_ray_brick``'s (frozen copy in ``gpu_score_variants_kernels.py``):
a brick's masks and bitset snapshot read when the ray enters it, one ``atomic_or`` per brick left, the
first ray to set a voxel's bit adds its weight. Sums are int64 and a voxel's bit is set once whatever
the order, so every variant returns the shipped kernel's sums and (from the bitset) counts, bit for bit.
"""

from __future__ import annotations

import warp as wp

from gpu_score_variants_kernels import brick_bit, brick_word, flush_brick, walk32_begin, walk32_next

# as the shipped module: forward only, no fused multiply-add (FMA contraction flips voxel-boundary ties)
OPTS = {"enable_backward": False, "fuse_fp": False}


@wp.func
def tiled_ray(r: wp.int32, n: wp.int32, n_az: wp.int32, tile_c: wp.int32):
    """Map ray number ``r`` to (rig, sensor direction index): 32 consecutive numbers are one
    ``tile_c`` x ``32 / tile_c`` (channel x azimuth) tile; tiles run along azimuth, then channel. A
    bijection on [0, rigs * n) when the channel count divides by ``tile_c`` and the azimuth count by
    ``32 / tile_c`` (the runner checks)."""
    rig = r / n
    j = r - rig * n
    tile_a = 32 / tile_c
    t = j / 32
    lane = j - t * 32
    tiles_a = n_az / tile_a
    tc = t / tiles_a
    c = tc * tile_c + lane / tile_a
    a = (t - tc * tiles_a) * tile_a + lane % tile_a
    return rig, c * n_az + a


@wp.func
def walk_ray_brick(
    rig: wp.int32, sd: wp.int32,
    sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d), pos: wp.array(dtype=wp.vec3d),
    n_lidars: wp.int32, t_max: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32, masks64: wp.array(dtype=wp.uint64),
    weights: wp.array(dtype=wp.int64), words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
    sums: wp.array(dtype=wp.int64),
):
    # score_ray_brick's body (gpu_score_variants_kernels.py) for the ray of (rig, sd), given explicitly
    cand = rig / n_lidars
    o = pos[rig]
    d = rot[rig] * sensor_dirs[sd]
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
    base = wp.int64(cand) * words_per_candidate
    my_sum = wp.int64(0)
    cur = wp.int64(-1)
    seen = wp.uint32(0)
    pending = wp.uint32(0)
    stop_w = wp.uint32(0)
    nz_w = wp.uint32(0)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        word = brick_word(w, bny, bnz)
        if word != cur:
            if pending != wp.uint32(0):
                my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            cur = word
            pending = wp.uint32(0)
            m = masks64[word]
            stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
            nz_w = wp.uint32(m >> wp.uint64(32))
            seen = bits[base + word]
        bit = brick_bit(w)
        if (seen & bit) == wp.uint32(0):
            seen = seen | bit
            pending = pending | bit
        if (stop_w & bit) != wp.uint32(0):
            break
        w = walk32_next(w, o, d, s, sf, nx, ny, nz)
    if pending != wp.uint32(0):
        my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


def make_tiled(maxreg=None):
    """One thread per ray, ray order permuted by ``tiled_ray`` (launch dim: all rays)."""
    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def tiled_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                     pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                     nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                     masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                     words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                     sums: wp.array(dtype=wp.int64), n_az: wp.int32, tile_c: wp.int32):
        rig, sd = tiled_ray(wp.tid(), sensor_dirs.shape[0], n_az, tile_c)
        walk_ray_brick(rig, sd, sensor_dirs, rot, pos, n_lidars, t_max, s, nx, ny, nz, bny, bnz, masks64,
                       weights, words_per_candidate, bits, sums)
    return tiled_kernel


def make_persistent(maxreg=None):
    """Persistent threads with ray refill (launch dim: ``n_threads``). ``mode`` 0: thread t walks rays
    t, t + T, t + 2T, ... (T = ``n_threads``, no atomics); ``mode`` 1: a lane whose ray has ended takes
    the next ``chunk`` ray numbers from ``counter[0]`` (zeroed before each launch) once its previous
    chunk is used up. A walk takes at most nx + ny + nz steps, so the shipped loop's bound never binds
    and the refill loop needs none."""
    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def persistent_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                          pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                          nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                          masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                          words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                          sums: wp.array(dtype=wp.int64), n_az: wp.int32, tile_c: wp.int32,
                          n_rays: wp.int32, n_threads: wp.int32, mode: wp.int32, chunk: wp.int32,
                          counter: wp.array(dtype=wp.int32)):
        tid = wp.tid()
        n = sensor_dirs.shape[0]
        sf = wp.float32(s)
        # the ray in hand: its walk and score_ray_brick's per-ray state
        o = wp.vec3d()
        d = wp.vec3d()
        w = walk32_begin(o, d, wp.float64(-1.0), s, sf, nx, ny, nz)     # t_end < 0: an empty walk (alive 0)
        cand = wp.int32(0)
        base = wp.int64(0)
        my_sum = wp.int64(0)
        cur = wp.int64(-1)
        seen = wp.uint32(0)
        pending = wp.uint32(0)
        stop_w = wp.uint32(0)
        nz_w = wp.uint32(0)
        nxt = tid          # next ray number to take, and the end of the chunk in hand (mode 1)
        end = tid
        while True:
            if w.alive == 0:
                # the ray in hand is done (or none was taken yet): settle it, take the next
                if pending != wp.uint32(0):
                    my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
                    pending = wp.uint32(0)
                if my_sum > wp.int64(0):
                    wp.atomic_add(sums, cand, my_sum)
                    my_sum = wp.int64(0)
                r = nxt
                if mode == 0:
                    nxt = nxt + n_threads
                else:
                    if nxt >= end:
                        r = wp.atomic_add(counter, 0, chunk)
                        end = r + chunk
                    nxt = r + 1
                if r >= n_rays:
                    break
                rig, sd = tiled_ray(r, n, n_az, tile_c)
                cand = rig / n_lidars
                base = wp.int64(cand) * words_per_candidate
                o = pos[rig]
                d = rot[rig] * sensor_dirs[sd]
                w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
                cur = wp.int64(-1)
            if w.alive != 0:
                # one step of score_ray_brick's loop
                word = brick_word(w, bny, bnz)
                if word != cur:
                    if pending != wp.uint32(0):
                        my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
                    cur = word
                    pending = wp.uint32(0)
                    m = masks64[word]
                    stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
                    nz_w = wp.uint32(m >> wp.uint64(32))
                    seen = bits[base + word]
                bit = brick_bit(w)
                if (seen & bit) == wp.uint32(0):
                    seen = seen | bit
                    pending = pending | bit
                if (stop_w & bit) != wp.uint32(0):
                    w.alive = 0            # occlusion: the ray ends after this voxel
                else:
                    w = walk32_next(w, o, d, s, sf, nx, ny, nz)
    return persistent_kernel
