"""Frozen Warp device functions of the GPU score study (``gpu_score_variants.py``).

A copy, taken on 2026-11-24, of the voxel walks and score bodies of
``place3d_kernels/backends/warp/kernels.py`` as they were then: the float64 walk (``Walk``, ``walk_begin``,
``walk_next``, ``flat_index`` and the ``brick_word`` / ``brick_bit`` overloads for it; no longer shipped),
the float32 walk with its float64 fallback (``Walk32``, ``walk32_*``, ``flat32``) and the score bodies
(``score_ray``, ``score_ray_brick``, ``flush_brick``). The study's variants are built on these, so its
baselines stay fixed when the shipped kernels change; the study times the shipped kernels themselves
(``score_kernel``, ``score_kernel_gpu``) through the backend and checks every exact variant's sums against
them. Comments are the shipped module's of that date; "the kernels" there means the shipped ones.
"""

from __future__ import annotations

import warp as wp

# as the shipped module: forward only, no fused multiply-add (FMA contraction flips voxel-boundary ties)
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

INF64 = wp.constant(wp.float64(1.0e300))


# ----------------------------------------------------------------------------- voxel walk
@wp.struct
class Walk:
    i: wp.int32
    j: wp.int32
    k: wp.int32
    si: wp.int32
    sj: wp.int32
    sk: wp.int32
    tx: wp.float64
    ty: wp.float64
    tz: wp.float64
    t1: wp.float64
    alive: wp.int32


@wp.func
def _axis_clip(o: wp.float64, d: wp.float64, size: wp.float64, t0: wp.float64, t1: wp.float64):
    # returns the clipped (t0, t1); an empty interval marks "no overlap"
    zero = wp.float64(0.0)
    if d == zero:
        if o < zero or o > size:
            return wp.float64(1.0), zero
        return t0, t1
    ta = (zero - o) / d
    tb = (size - o) / d
    return wp.max(t0, wp.min(ta, tb)), wp.min(t1, wp.max(ta, tb))


@wp.func
def _sign(x: wp.float64) -> wp.int32:
    zero = wp.float64(0.0)
    return wp.where(x > zero, 1, wp.where(x < zero, -1, 0))


@wp.func
def _clip_grid(o: wp.vec3d, d: wp.vec3d, t_end: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32,
               nz: wp.int32):
    # the segment [0, t_end] clipped to the grid box [0, n s]^3; empty when t1 <= t0
    t0 = wp.float64(0.0)
    t1 = t_end
    t0, t1 = _axis_clip(o[0], d[0], wp.float64(nx) * s, t0, t1)
    t0, t1 = _axis_clip(o[1], d[1], wp.float64(ny) * s, t0, t1)
    t0, t1 = _axis_clip(o[2], d[2], wp.float64(nz) * s, t0, t1)
    return t0, t1


@wp.func
def _start_index(p: wp.float64, d: wp.float64, s: wp.float64, n: wp.int32):
    i = wp.int32(wp.floor(p / s))
    # a start exactly on a plane belongs to the voxel the ray moves into
    zero = wp.float64(0.0)
    if d < zero and p <= wp.float64(i) * s:
        i = i - 1
    if d > zero and p >= wp.float64(i + 1) * s:
        i = i + 1
    return wp.clamp(i, 0, n - 1)


@wp.func
def _next_t(i: wp.int32, step: wp.int32, o: wp.float64, d: wp.float64, s: wp.float64):
    if step == 0:
        return INF64
    b = i
    if step > 0:
        b = i + 1
    return (wp.float64(b) * s - o) / d


@wp.func
def walk_begin(o: wp.vec3d, d: wp.vec3d, t_end: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32,
               nz: wp.int32) -> Walk:
    w = Walk()
    t0, t1 = _clip_grid(o, d, t_end, s, nx, ny, nz)
    w.alive = 0
    w.t1 = t1
    if t1 > t0:
        w.alive = 1
        p = o + t0 * d
        w.i = _start_index(p[0], d[0], s, nx)
        w.j = _start_index(p[1], d[1], s, ny)
        w.k = _start_index(p[2], d[2], s, nz)
        w.si = _sign(d[0])
        w.sj = _sign(d[1])
        w.sk = _sign(d[2])
        w.tx = _next_t(w.i, w.si, o[0], d[0], s)
        w.ty = _next_t(w.j, w.sj, o[1], d[1], s)
        w.tz = _next_t(w.k, w.sk, o[2], d[2], s)
    return w


@wp.func
def walk_next(w: Walk, o: wp.vec3d, d: wp.vec3d, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk:
    # step every axis whose boundary is crossed first (exact ties: an edge or corner, no side voxel)
    tn = wp.min(w.tx, wp.min(w.ty, w.tz))
    if tn >= w.t1:
        w.alive = 0
        return w
    if w.tx == tn:
        w.i = w.i + w.si
        w.tx = _next_t(w.i, w.si, o[0], d[0], s)
    if w.ty == tn:
        w.j = w.j + w.sj
        w.ty = _next_t(w.j, w.sj, o[1], d[1], s)
    if w.tz == tn:
        w.k = w.k + w.sk
        w.tz = _next_t(w.k, w.sk, o[2], d[2], s)
    if w.i < 0 or w.i >= nx or w.j < 0 or w.j >= ny or w.k < 0 or w.k >= nz:
        w.alive = 0
    return w


# ----------------------------------------------------------------------------- float32 walk, exact
# The walk the kernels run. It takes the same decisions as walk_begin / walk_next (the float64 reference
# walk) but makes them in float32 where that is certain, as the OpenCL backend does (place3d_kernels/backends/opencl/
# grid.cl, which derives the bound): in a frame rebased at the entry point p0 = o + t0 d and the first
# voxel b, the time after t0 at which the ray crosses boundary plane b + K of an axis is
#     t' = (K s - q) / d,   q = p0 - b s,
# computed in float32 as (K sf - q) * (1 / d) with an error below DDA_ERR (|t'| + 2 |q / d|). A step
# whose axis crosses first by more than ``tol`` (2.5 times that bound, for the segment end as well) is
# certain; any other step (near-ties: rays within about 1e-6 relative of a voxel edge or corner, or
# ending near a plane) is taken by walk_next's float64 arithmetic on the same indices, so every backend
# walks the reference's voxels, bit for bit. The float64 fallback is also used for a whole ray when a
# direction component is too small for a float32 reciprocal.
DDA_ERR = wp.constant(wp.float32(9.5367431640625e-07))     # 2^-20
FLT_BIG = wp.constant(wp.float32(3.0e38))
DIR_SMALL = wp.constant(wp.float64(1.0e-30))


@wp.struct
class Walk32:
    i: wp.int32            # current voxel
    j: wp.int32
    k: wp.int32
    si: wp.int32           # step per axis: -1, 0, +1
    sj: wp.int32
    sk: wp.int32
    ki: wp.int32           # next boundary plane minus the first voxel, per axis
    kj: wp.int32
    kk: wp.int32
    tx: wp.float32         # next crossing after t0 per axis (FLT_BIG: never)
    ty: wp.float32
    tz: wp.float32
    qx: wp.float32         # rebased entry point p0 - b s
    qy: wp.float32
    qz: wp.float32
    vx: wp.float32         # 1 / d
    vy: wp.float32
    vz: wp.float32
    t1: wp.float32         # segment end after t0
    tol: wp.float32        # certainty threshold
    t1d: wp.float64        # segment end, float64 (for the fallback)
    exact: wp.int32        # 1: every step in float64
    alive: wp.int32


@wp.func
def walk32_begin(o: wp.vec3d, d: wp.vec3d, t_end: wp.float64, s: wp.float64, sf: wp.float32, nx: wp.int32,
                 ny: wp.int32, nz: wp.int32) -> Walk32:
    w = Walk32()
    zero = wp.float64(0.0)
    t0, t1 = _clip_grid(o, d, t_end, s, nx, ny, nz)
    w.alive = 0
    w.t1d = t1
    if t1 > t0:
        w.alive = 1
        p = o + t0 * d
        w.i = _start_index(p[0], d[0], s, nx)
        w.j = _start_index(p[1], d[1], s, ny)
        w.k = _start_index(p[2], d[2], s, nz)
        w.si = _sign(d[0])
        w.sj = _sign(d[1])
        w.sk = _sign(d[2])
        w.ki = wp.where(w.si > 0, 1, 0)
        w.kj = wp.where(w.sj > 0, 1, 0)
        w.kk = wp.where(w.sk > 0, 1, 0)
        w.qx = wp.float32(p[0] - wp.float64(w.i) * s)
        w.qy = wp.float32(p[1] - wp.float64(w.j) * s)
        w.qz = wp.float32(p[2] - wp.float64(w.k) * s)
        w.exact = 0
        for a in range(3):
            if d[a] != zero and wp.abs(d[a]) < DIR_SMALL:
                w.exact = 1
        w.vx = wp.float32(0.0)
        w.vy = wp.float32(0.0)
        w.vz = wp.float32(0.0)
        w.tx = FLT_BIG
        w.ty = FLT_BIG
        w.tz = FLT_BIG
        emax = wp.float32(0.0)
        if w.si != 0:
            w.vx = wp.float32(1.0) / wp.float32(d[0])
            w.tx = (wp.float32(w.ki) * sf - w.qx) * w.vx
            emax = wp.max(emax, wp.abs(w.qx * w.vx))
        if w.sj != 0:
            w.vy = wp.float32(1.0) / wp.float32(d[1])
            w.ty = (wp.float32(w.kj) * sf - w.qy) * w.vy
            emax = wp.max(emax, wp.abs(w.qy * w.vy))
        if w.sk != 0:
            w.vz = wp.float32(1.0) / wp.float32(d[2])
            w.tz = (wp.float32(w.kk) * sf - w.qz) * w.vz
            emax = wp.max(emax, wp.abs(w.qz * w.vz))
        w.t1 = wp.float32(t1 - t0)
        w.tol = wp.float32(2.5) * DDA_ERR * (w.t1 + wp.float32(2.0) * emax)
    return w


@wp.func
def walk32_exact(w: Walk32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32, nx: wp.int32,
                 ny: wp.int32, nz: wp.int32) -> Walk32:
    # walk_next's float64 step (every axis whose boundary comes first steps; the segment may end)
    tx = _next_t(w.i, w.si, o[0], d[0], s)
    ty = _next_t(w.j, w.sj, o[1], d[1], s)
    tz = _next_t(w.k, w.sk, o[2], d[2], s)
    tn = wp.min(tx, wp.min(ty, tz))
    if tn >= w.t1d:
        w.alive = 0
        return w
    if tx == tn:
        w.i = w.i + w.si
        w.ki = w.ki + w.si
        w.tx = (wp.float32(w.ki) * sf - w.qx) * w.vx
    if ty == tn:
        w.j = w.j + w.sj
        w.kj = w.kj + w.sj
        w.ty = (wp.float32(w.kj) * sf - w.qy) * w.vy
    if tz == tn:
        w.k = w.k + w.sk
        w.kk = w.kk + w.sk
        w.tz = (wp.float32(w.kk) * sf - w.qz) * w.vz
    if w.i < 0 or w.i >= nx or w.j < 0 or w.j >= ny or w.k < 0 or w.k >= nz:
        w.alive = 0
    return w


@wp.func
def walk32_next(w: Walk32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32, nx: wp.int32,
                ny: wp.int32, nz: wp.int32) -> Walk32:
    # the common step: one axis crosses first by more than tol (before the other two and the segment
    # end), so the float32 decision is certain; anything else goes to walk32_exact
    if w.exact != 0:
        return walk32_exact(w, o, d, s, sf, nx, ny, nz)
    if w.tx < w.ty and w.tx < w.tz:
        lim = w.tx + w.tol
        if w.ty <= lim or w.tz <= lim or w.t1 <= lim:
            return walk32_exact(w, o, d, s, sf, nx, ny, nz)
        w.i = w.i + w.si
        w.ki = w.ki + w.si
        w.tx = (wp.float32(w.ki) * sf - w.qx) * w.vx
        if w.i < 0 or w.i >= nx:
            w.alive = 0
        return w
    if w.ty < w.tz:
        lim = w.ty + w.tol
        if w.tx <= lim or w.tz <= lim or w.t1 <= lim:
            return walk32_exact(w, o, d, s, sf, nx, ny, nz)
        w.j = w.j + w.sj
        w.kj = w.kj + w.sj
        w.ty = (wp.float32(w.kj) * sf - w.qy) * w.vy
        if w.j < 0 or w.j >= ny:
            w.alive = 0
        return w
    lim = w.tz + w.tol
    if w.tx <= lim or w.ty <= lim or w.t1 <= lim:
        return walk32_exact(w, o, d, s, sf, nx, ny, nz)
    w.k = w.k + w.sk
    w.kk = w.kk + w.sk
    w.tz = (wp.float32(w.kk) * sf - w.qz) * w.vz
    if w.k < 0 or w.k >= nz:
        w.alive = 0
    return w


@wp.func
def flat32(w: Walk32, ny: wp.int32, nz: wp.int32) -> wp.int64:
    return (wp.int64(w.i) * wp.int64(ny) + wp.int64(w.j)) * wp.int64(nz) + wp.int64(w.k)


@wp.func
def flat_index(w: Walk, ny: wp.int32, nz: wp.int32) -> wp.int64:
    return (wp.int64(w.i) * wp.int64(ny) + wp.int64(w.j)) * wp.int64(nz) + wp.int64(w.k)


@wp.kernel
def traverse_count_kernel(
    origins: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d), t_end: wp.array(dtype=wp.float64),
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    stop: wp.array(dtype=wp.uint8), use_stop: wp.int32,
    counts: wp.array(dtype=wp.int64),
):
    tid = wp.tid()
    o = origins[tid]
    d = dirs[tid]
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_end[tid], s, sf, nx, ny, nz)
    c = wp.int64(0)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        c += wp.int64(1)
        if use_stop != 0:
            if stop[flat32(w, ny, nz)] != wp.uint8(0):
                break
        w = walk32_next(w, o, d, s, sf, nx, ny, nz)
    counts[tid] = c


@wp.kernel
def traverse_fill_kernel(
    origins: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d), t_end: wp.array(dtype=wp.float64),
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    stop: wp.array(dtype=wp.uint8), use_stop: wp.int32,
    offsets: wp.array(dtype=wp.int64), voxels: wp.array(dtype=wp.int64),
):
    tid = wp.tid()
    o = origins[tid]
    d = dirs[tid]
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_end[tid], s, sf, nx, ny, nz)
    at = offsets[tid]
    end = offsets[tid + 1]
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0 or at >= end:
            break
        v = flat32(w, ny, nz)
        voxels[at] = v
        at += wp.int64(1)
        if use_stop != 0:
            if stop[v] != wp.uint8(0):
                break
        w = walk32_next(w, o, d, s, sf, nx, ny, nz)


@wp.kernel
def coverage_kernel(
    origins: wp.array(dtype=wp.vec3d), dirs: wp.array(dtype=wp.vec3d), t_end: wp.array(dtype=wp.float64),
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    stop: wp.array(dtype=wp.uint8), use_stop: wp.int32,
    mask: wp.array(dtype=wp.uint8),
):
    tid = wp.tid()
    o = origins[tid]
    d = dirs[tid]
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_end[tid], s, sf, nx, ny, nz)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        v = flat32(w, ny, nz)
        mask[v] = wp.uint8(1)
        if use_stop != 0:
            if stop[v] != wp.uint8(0):
                break
        w = walk32_next(w, o, d, s, sf, nx, ny, nz)


@wp.func
def brick_word(w: Walk32, bny: wp.int32, bnz: wp.int32) -> wp.int64:
    # bitsets of the score kernel are bricked: one 32-bit word holds a 4 x 4 x 2 block of voxels, so the
    # next voxel of a walk usually sits in the word just read (cache hit, no new atomic)
    return (wp.int64(w.i >> 2) * wp.int64(bny) + wp.int64(w.j >> 2)) * wp.int64(bnz) + wp.int64(w.k >> 1)


@wp.func
def brick_bit(w: Walk32) -> wp.uint32:
    return wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))


@wp.func
def brick_word(w: Walk, bny: wp.int32, bnz: wp.int32) -> wp.int64:
    # the same for the float64 walk (overload; the GPU study's frozen kernels use it)
    return (wp.int64(w.i >> 2) * wp.int64(bny) + wp.int64(w.j >> 2)) * wp.int64(bnz) + wp.int64(w.k >> 1)


@wp.func
def brick_bit(w: Walk) -> wp.uint32:
    return wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))


@wp.func
def score_ray(
    tid: wp.int32,
    sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d), pos: wp.array(dtype=wp.vec3d),
    n_lidars: wp.int32, t_max: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32, masks: wp.array(dtype=wp.uint32),
    weights: wp.array(dtype=wp.int64), words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
    sums: wp.array(dtype=wp.int64),
):
    n = sensor_dirs.shape[0]
    rig = tid / n                              # candidate * n_lidars + lidar
    cand = rig / n_lidars
    o = pos[rig]
    d = rot[rig] * sensor_dirs[tid - rig * n]   # as lidar_rays_kernel: the reference's rays bit for bit
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
    base = wp.int64(cand) * words_per_candidate
    # the ray that sets a voxel's bit first owns it; integer partial sums make the total independent of
    # thread order, and one atomic per ray (not per voxel) keeps contention on sums[cand] low
    my_sum = wp.int64(0)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        word = brick_word(w, bny, bnz)
        bit = brick_bit(w)
        # plain read first: a set bit stays set, so most revisits (near the sensor every ray passes the
        # same voxels) cost a cached load instead of an atomic
        if (bits[base + word] & bit) == wp.uint32(0):
            # Only voxels with entropy need to know whether this ray set their bit first (to add the
            # weight once); the mask sits next to the occlusion word, in the same cache sector. Free
            # space (most covered voxels) takes an atomic whose result is unused, which the GPU issues
            # without waiting for it; the number of covered voxels is counted afterwards from the bitset
            # (count_bits_kernel).
            if (masks[wp.int64(2) * word + wp.int64(1)] & bit) != wp.uint32(0):
                old = wp.atomic_or(bits, base + word, bit)
                if (old & bit) == wp.uint32(0):
                    my_sum += weights[flat32(w, ny, nz)]
            else:
                wp.atomic_or(bits, base + word, bit)
        if (masks[wp.int64(2) * word] & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
            break
        w = walk32_next(w, o, d, s, sf, nx, ny, nz)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


@wp.func
def flush_brick(bits: wp.array(dtype=wp.uint32), base: wp.int64, word: wp.int64, pending: wp.uint32,
                nz_w: wp.uint32, bny: wp.int32, bnz: wp.int32, ny: wp.int32, nz: wp.int32,
                weights: wp.array(dtype=wp.int64)) -> wp.int64:
    # one atomic_or for the bits a ray marked in one brick; only when some have entropy is its result
    # waited for (the bits the ray set first are its own: it adds their weights)
    add = wp.int64(0)
    if pending != wp.uint32(0):
        at = base + word
        if (pending & nz_w) != wp.uint32(0):
            old = wp.atomic_or(bits, at, pending)
            m = pending & ~old & nz_w
            # the brick's coordinates from its word (rare: only bricks with entropy the ray marked first)
            bk = wp.int32(word % wp.int64(bnz))
            bj = wp.int32((word / wp.int64(bnz)) % wp.int64(bny))
            bi = wp.int32(word / (wp.int64(bnz) * wp.int64(bny)))
            while m != wp.uint32(0):
                b = wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1))     # index of the lowest set bit
                i = bi * 4 + (b & 3)
                j = bj * 4 + ((b >> 2) & 3)
                k = bk * 2 + (b >> 4)
                add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
                m = m & (m - wp.uint32(1))
        else:
            wp.atomic_or(bits, at, pending)
    return add


@wp.func
def score_ray_brick(
    tid: wp.int32,
    sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d), pos: wp.array(dtype=wp.vec3d),
    n_lidars: wp.int32, t_max: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32, masks64: wp.array(dtype=wp.uint64),
    weights: wp.array(dtype=wp.int64), words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
    sums: wp.array(dtype=wp.int64),
):
    # The GPU form of score_ray (same sums). Memory is touched per brick a ray passes, not per voxel: on
    # entering a brick, one 64-bit load of its masks (occlusion bits low, nonzero-weight bits high) and a
    # plain read of its bitset word (bits only ever get set, so a stale copy is safe: it only filters);
    # on leaving, one atomic_or with the bits the ray newly marked there (flush_brick). The first ray to
    # set a voxel's bit owns it and adds its weight. On the H100 this ran the dense rig on the 0.05 m
    # grid in 3.10 against 3.38 ms (bench/results/gpu-H100-score-variants-0.05m-2026-11-22.json); on the CPU it was slower (no atomics
    # to save there), so the CPU keeps score_ray.
    n = sensor_dirs.shape[0]
    rig = tid / n
    cand = rig / n_lidars
    o = pos[rig]
    d = rot[rig] * sensor_dirs[tid - rig * n]
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
