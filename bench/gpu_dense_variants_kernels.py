"""Warp kernels of the dense-rig lane-utilisation study (``gpu_dense_variants.py``, issue 17, goal 3).

Nsight Compute found the shipped CUDA score kernel (``score_kernel_gpu``: one thread per ray, per-brick
memory traffic) with only about 16 of 32 lanes of a warp active. Two causes, and exact remedies for each:

Rays of different lengths (a warp runs until its longest ray ends):

* **ray order** (``make_tiled``): a pure permutation of the thread index, so that the 32 lanes of a
  warp walk a ``tile_c`` x ``32 / tile_c`` (channel x azimuth) tile of one LiDAR instead of 32
  consecutive azimuths of one channel. ``tile_c = 1`` is the shipped order.
* **persistent threads with ray refill** (``make_persistent``): "while-while" traversal with
  replacement of finished rays (Aila & Laine, "Understanding the Efficiency of Ray Traversal on GPUs",
  HPG 2009, sections 3-4): a launch of about as many threads as the GPU holds at once; each loops, and a
  lane whose ray has ended takes the next ray (from a global atomic counter, ``chunk`` rays at a time,
  or with a fixed stride; at once, or once ``batch`` lanes of its warp are done) instead of idling
  until the warp's longest ray is done. Ray numbers go through the same tile permutation.

Branches inside a step (lanes of a warp stepping along different axes, or some entering a new brick,
run the branch bodies one after another). The lane model ``gpu_dense_lanes.py`` counted, for the dense
rig at 0.05 m, 96 % of lanes kept busy by ray lengths in the shipped order but lanes on 2.5 different
axes per warp-step (39 % of lanes active in the axis branches) and 27 % active in the brick-entry branch:

* **branch-free step** (``walk32_next_sel``): the axis chosen by selects;
* **eager brick loads** (``walk_ray_brick_eager``): the masks and bitset word read on every step and
  kept only on entering a brick, so that only the flush stays a branch.

The per-ray work is the shipped ``score_ray_brick``'s (frozen copy in ``gpu_score_variants_kernels.py``):
a brick's masks and bitset snapshot read when the ray enters it, one ``atomic_or`` per brick left, the
first ray to set a voxel's bit adds its weight. Sums are int64 and a voxel's bit is set once whatever
the order, so every variant returns the shipped kernel's sums and (from the bitset) counts, bit for bit
(tests/test_dense_variants.py).
"""

from __future__ import annotations

import warp as wp

from gpu_score_variants_kernels import (Walk32, brick_bit, brick_word, flush_brick, walk32_begin, walk32_exact,
                                        walk32_next)

# as the shipped score_kernel_gpu: forward only, no fused multiply-add (FMA contraction flips voxel-boundary
# ties), compiled for 128-thread blocks (the runner launches every variant with BLOCK_DIM = 128)
OPTS = {"enable_backward": False, "fuse_fp": False, "block_dim": 128}


@wp.func_native("""
#if defined(__CUDA_ARCH__)
    unsigned int mask = __activemask();
    return __popc(__ballot_sync(mask, done != 0)) | (__popc(mask) << 8);
#else
    return (done != 0 ? 1 : 0) | (1 << 8);
#endif
""")
def warp_vote(done: wp.int32) -> wp.int32:
    """(lanes of this warp here whose ray is done) | (lanes here) << 8. On the CPU a thread is its own
    warp. Lanes that have left the loop are not counted."""
    ...


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
def walk32_next_sel(w: Walk32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32, nx: wp.int32,
                    ny: wp.int32, nz: wp.int32) -> Walk32:
    """walk32_next with the axis chosen by selects instead of three branches: lanes stepping along
    different axes run the same instructions (in walk32_next each takes its own branch, and the warp
    runs the three one after another). Same comparisons, same float32 expression for the new crossing
    (no FMA), same float64 fallback: the same voxels, bit for bit."""
    xa = w.tx < w.ty and w.tx < w.tz
    ya = (not xa) and w.ty < w.tz
    za = (not xa) and (not ya)
    tmin = wp.where(xa, w.tx, wp.where(ya, w.ty, w.tz))
    o1 = wp.where(xa, w.ty, w.tx)                 # the two other axes' crossings
    o2 = wp.where(za, w.ty, w.tz)
    lim = tmin + w.tol
    if w.exact != 0 or o1 <= lim or o2 <= lim or w.t1 <= lim:
        return walk32_exact(w, o, d, s, sf, nx, ny, nz)
    di = wp.where(xa, w.si, 0)
    dj = wp.where(ya, w.sj, 0)
    dk = wp.where(za, w.sk, 0)
    w.i = w.i + di
    w.j = w.j + dj
    w.k = w.k + dk
    w.ki = w.ki + di
    w.kj = w.kj + dj
    w.kk = w.kk + dk
    kk = wp.where(xa, w.ki, wp.where(ya, w.kj, w.kk))
    q = wp.where(xa, w.qx, wp.where(ya, w.qy, w.qz))
    v = wp.where(xa, w.vx, wp.where(ya, w.vy, w.vz))
    t = (wp.float32(kk) * sf - q) * v
    w.tx = wp.where(xa, t, w.tx)
    w.ty = wp.where(ya, t, w.ty)
    w.tz = wp.where(za, t, w.tz)
    out = w.i < 0 or w.i >= nx or w.j < 0 or w.j >= ny or w.k < 0 or w.k >= nz
    w.alive = wp.where(out, 0, w.alive)
    return w


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


@wp.func
def walk_ray_brick_sel(
    rig: wp.int32, sd: wp.int32,
    sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d), pos: wp.array(dtype=wp.vec3d),
    n_lidars: wp.int32, t_max: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32, masks64: wp.array(dtype=wp.uint64),
    weights: wp.array(dtype=wp.int64), words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
    sums: wp.array(dtype=wp.int64),
):
    # walk_ray_brick with the branch-free axis choice (walk32_next_sel)
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
        w = walk32_next_sel(w, o, d, s, sf, nx, ny, nz)
    if pending != wp.uint32(0):
        my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


@wp.func
def walk_ray_brick_eager(
    rig: wp.int32, sd: wp.int32,
    sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d), pos: wp.array(dtype=wp.vec3d),
    n_lidars: wp.int32, t_max: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32, masks64: wp.array(dtype=wp.uint64),
    weights: wp.array(dtype=wp.int64), words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
    sums: wp.array(dtype=wp.int64),
):
    # walk_ray_brick_sel with the brick's masks and bitset word loaded on every step (cache hits while
    # the ray stays in the brick) and kept only on entering a new one: the lane model found some 27 % of
    # a warp's lanes active in the shipped brick-entry branch. Only the flush stays a branch. The same
    # snapshot semantics (``seen`` is the word read on entry, plus the ray's own bits): the same sums.
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
    nz_w = wp.uint32(0)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        word = brick_word(w, bny, bnz)
        change = word != cur
        if change and pending != wp.uint32(0):
            my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        m = masks64[word]
        fresh = bits[base + word]
        stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
        nz_w = wp.uint32(m >> wp.uint64(32))
        seen = wp.where(change, fresh, seen)
        pending = wp.where(change, wp.uint32(0), pending)
        cur = word
        bit = brick_bit(w)
        pending = pending | (bit & ~seen)
        seen = seen | bit
        if (stop_w & bit) != wp.uint32(0):
            break
        w = walk32_next_sel(w, o, d, s, sf, nx, ny, nz)
    if pending != wp.uint32(0):
        my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


def make_tiled(maxreg=None, tile_c=4, select=False, eager=False):
    """One thread per ray, ray order permuted by ``tiled_ray`` with a ``tile_c`` known at compile time
    (divisions by it fold to shifts); ``select``: the branch-free step (``walk32_next_sel``); ``eager``:
    that and per-step mask loads (``walk_ray_brick_eager``). Launch dim: all rays; inputs: the shipped
    kernel's, then ``n_az``."""
    body = walk_ray_brick_eager if eager else (walk_ray_brick_sel if select else walk_ray_brick)

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def tiled_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                     pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                     nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                     masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                     words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                     sums: wp.array(dtype=wp.int64), n_az: wp.int32):
        rig, sd = tiled_ray(wp.tid(), sensor_dirs.shape[0], n_az, wp.static(tile_c))
        body(rig, sd, sensor_dirs, rot, pos, n_lidars, t_max, s, nx, ny, nz, bny, bnz, masks64,
                       weights, words_per_candidate, bits, sums)
    return tiled_kernel


@wp.func
def advance_keep(w: Walk32, o: wp.vec3d, d: wp.vec3d, rig: wp.int32, sd: wp.int32,
                 sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                 pos: wp.array(dtype=wp.vec3d), s: wp.float64, sf: wp.float32, nx: wp.int32, ny: wp.int32,
                 nz: wp.int32) -> Walk32:
    # the shipped step: the ray's float64 origin and direction stay in registers for the fallback
    return walk32_next(w, o, d, s, sf, nx, ny, nz)


@wp.func
def advance_sel(w: Walk32, o: wp.vec3d, d: wp.vec3d, rig: wp.int32, sd: wp.int32,
                sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                pos: wp.array(dtype=wp.vec3d), s: wp.float64, sf: wp.float32, nx: wp.int32, ny: wp.int32,
                nz: wp.int32) -> Walk32:
    # the branch-free step
    return walk32_next_sel(w, o, d, s, sf, nx, ny, nz)


@wp.func
def advance_reload(w: Walk32, o: wp.vec3d, d: wp.vec3d, rig: wp.int32, sd: wp.int32,
                   sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                   pos: wp.array(dtype=wp.vec3d), s: wp.float64, sf: wp.float32, nx: wp.int32, ny: wp.int32,
                   nz: wp.int32) -> Walk32:
    # walk32_next whose rare float64 fallback re-derives o and d from (rig, sd) (the same products, no FMA:
    # the same bits), so the persistent loop need not keep 12 registers of float64 ray alive
    fast = wp.int32(0)
    if w.exact == 0:
        if w.tx < w.ty and w.tx < w.tz:
            lim = w.tx + w.tol
            if not (w.ty <= lim or w.tz <= lim or w.t1 <= lim):
                fast = 1
        elif w.ty < w.tz:
            lim = w.ty + w.tol
            if not (w.tx <= lim or w.tz <= lim or w.t1 <= lim):
                fast = 2
        else:
            lim = w.tz + w.tol
            if not (w.tx <= lim or w.ty <= lim or w.t1 <= lim):
                fast = 3
    if fast == 1:
        w.i = w.i + w.si
        w.ki = w.ki + w.si
        w.tx = (wp.float32(w.ki) * sf - w.qx) * w.vx
        if w.i < 0 or w.i >= nx:
            w.alive = 0
        return w
    if fast == 2:
        w.j = w.j + w.sj
        w.kj = w.kj + w.sj
        w.ty = (wp.float32(w.kj) * sf - w.qy) * w.vy
        if w.j < 0 or w.j >= ny:
            w.alive = 0
        return w
    if fast == 3:
        w.k = w.k + w.sk
        w.kk = w.kk + w.sk
        w.tz = (wp.float32(w.kk) * sf - w.qz) * w.vz
        if w.k < 0 or w.k >= nz:
            w.alive = 0
        return w
    return walk32_exact(w, pos[rig], rot[rig] * sensor_dirs[sd], s, sf, nx, ny, nz)


def make_persistent(maxreg=None, mode=1, tile_c=4, chunk=1, reload=False, batch=1, select=False):
    """Persistent threads with ray refill, specialised at compile time. Launch dim: ``n_threads``;
    inputs: the shipped kernel's, then ``n_az``, ``n_rays``, ``n_threads`` and ``counter`` (one int32,
    zeroed before each launch).

    Args:
        maxreg: CUDA register cap (None: uncapped).
        mode: 0: thread t walks rays t, t + T, t + 2T, ... (T = ``n_threads``; no atomics); 1: a lane
            whose ray has ended takes the next ``chunk`` ray numbers from ``counter[0]`` once its previous
            chunk is used up.
        tile_c: ray order (``tiled_ray``); 1 is the shipped order.
        chunk: ray numbers per atomic fetch (mode 1).
        reload: the float64 fallback re-derives the ray (``advance_reload``) instead of keeping it in
            registers.
        batch: 1: a lane takes a new ray as soon as its own has ended; K > 1: only once K lanes of its
            warp (or all still looping) are done, so the float64 set-up of new rays (``walk32_begin``)
            runs for several lanes at once instead of stalling the warp once per lane (the dynamic fetch
            of Aila & Laine; a warp vote, ``warp_vote``).
        select: the branch-free step (``walk32_next_sel``).

    A walk takes at most nx + ny + nz steps, so the shipped loop's bound never binds and the refill loop
    needs none. The loop has one call site of flush_brick and one mask load (a ray's end is handled as a
    change of brick to "none"). Branches that replace the walk end in ``continue``: Warp merges a
    variable assigned in an ``if`` with ``wp::where`` after it, which for the 25-register walk struct
    would keep the old and the new walk alive together; a branch that jumps back to the loop's head
    needs no merge.
    """
    advance = advance_sel if select else (advance_reload if reload else advance_keep)

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def persistent_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                          pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                          nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                          masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                          words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                          sums: wp.array(dtype=wp.int64), n_az: wp.int32, n_rays: wp.int32, n_threads: wp.int32,
                          counter: wp.array(dtype=wp.int32)):
        tid = wp.tid()
        n = sensor_dirs.shape[0]
        sf = wp.float32(s)
        none = wp.int64(-2)            # the brick word of "no ray in hand"
        # the ray in hand: its walk and score_ray_brick's per-ray state
        o = wp.vec3d()
        d = wp.vec3d()
        w = walk32_begin(o, d, wp.float64(-1.0), s, sf, nx, ny, nz)     # t_end < 0: an empty walk (alive 0)
        ray_rig = wp.int32(0)
        ray_sd = wp.int32(0)
        cand = wp.int32(0)
        base = wp.int64(0)
        my_sum = wp.int64(0)
        cur = wp.int64(-1)             # brick in hand; -1 (not none): the first pass takes a ray
        seen = wp.uint32(0)
        pending = wp.uint32(0)
        stop_w = wp.uint32(0)
        nz_w = wp.uint32(0)
        nxt = tid                      # next ray number to take (mode 1: within the chunk in hand, up to end)
        end = tid
        while True:
            word = none
            if w.alive != 0:
                word = brick_word(w, bny, bnz)
            if wp.static(batch > 1):
                vote = warp_vote(wp.where(word == none, 1, 0))    # every lane still looping votes
            if word != cur:
                # leaving a brick (or the ray ended): its newly marked bits go out in one atomic_or
                if pending != wp.uint32(0):
                    my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
                    pending = wp.uint32(0)
                if word == none:
                    # the ray in hand is done (or none was taken yet): settle it
                    if my_sum > wp.int64(0):
                        wp.atomic_add(sums, cand, my_sum)
                        my_sum = wp.int64(0)
                    cur = none
                else:
                    cur = word
                    m = masks64[word]
                    stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
                    nz_w = wp.uint32(m >> wp.uint64(32))
                    seen = bits[base + word]
            if word == none:
                if wp.static(batch > 1):
                    # wait (idle this pass) until enough lanes of the warp are done to set up together
                    if (vote & 255) < wp.min(wp.static(batch), vote >> 8):
                        continue
                r = nxt
                if wp.static(mode == 0):
                    nxt = nxt + n_threads
                else:
                    if nxt >= end:
                        r = wp.atomic_add(counter, 0, wp.static(chunk))
                        end = r + wp.static(chunk)
                    nxt = r + 1
                if r >= n_rays:
                    break
                rig, sd = tiled_ray(r, n, n_az, wp.static(tile_c))
                ray_rig = rig
                ray_sd = sd
                cand = rig / n_lidars
                base = wp.int64(cand) * words_per_candidate
                o = pos[rig]
                d = rot[rig] * sensor_dirs[sd]
                w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
                cur = wp.int64(-1)           # the next pass enters the new ray's first brick (or takes another)
                continue
            # one step of score_ray_brick's loop
            bit = brick_bit(w)
            if (seen & bit) == wp.uint32(0):
                seen = seen | bit
                pending = pending | bit
            if (stop_w & bit) != wp.uint32(0):
                w.alive = 0                  # occlusion: the ray ends after this voxel
                continue
            w = advance(w, o, d, ray_rig, ray_sd, sensor_dirs, rot, pos, s, sf, nx, ny, nz)
    return persistent_kernel
