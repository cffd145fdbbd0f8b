"""The CUDA score kernel (``score_kernel_gpu``): M-SOG sums of a population of rigs on a bricked bitset.

The CPU runs ``kernels.score_kernel`` (one ray per thread, an atomic per voxel, which the CPU pays
little for). On CUDA this kernel walks the same voxels with the same float32/float64 decisions
(``kernels.walk32_*``) and does the bookkeeping per flat brick of 8 x 4 x 1 voxels (one 32-bit bitset
word; layout in ``bricks.py``; the masks come from the grid's 4 x 4 x 2 pairs by ``flat_masks_kernel``):

* the brick's masks (occlusion bits low, nonzero-weight bits high; one 64-bit load) and the
  candidate's bitset word are loaded on every step (cache hits while the ray stays in the brick) and
  kept only when the ray enters a new brick, so no branch decides whether to load;
* the bits a ray marks in a brick are sent with one ``atomic_or`` when it leaves (``flush_flat``);
  only bricks holding entropy wait for the old word, to add the weights of the bits this ray set first.

What makes it cheap is the address arithmetic of a step, which a dense rig takes hundreds of millions
of times: the brick word is an int32 from (i, j, k) (two shifts, two multiply-adds by kernel
constants), the voxel's bit needs no z term (a flat brick is one voxel high), loads and atomics use raw
addresses (no index wrap, no 64-bit stride multiplies), and the loop has no grid test (below). The
third round took about a third of the instructions out of a step's common path against a form with int64
indices; the ninth (flat bricks, numbered so that a 32-byte sector of words lies along the rays, and no
grid test) a further part of the time on the dense rig (figures: bench/README.md, "What the studies
found", dense-rig score kernel). The walk's decisions are untouched, so the voxels, sums and counts are
the same bits (the cross-backend suites compare scores with the reference; the earlier forms and their
tests are at tag lab-2026-11-27).

The walk's state is a ``WalkGPU``, ``kernels.Walk32`` without the fields a step seldom needs (a walk that
has ended has i = DEAD = -1; a float64-only walk has t1 = -1; the float64 segment end is a local of the
kernel), and the float32 step's certainty test is written with the minimum and the median of the three
crossings: the same decision and axis as ``walk32_next``'s chain of compares (proof at ``certain_step``),
fewer instructions and registers (bench/README.md, "What the studies found", dense-rig score kernel).

Why the loop needs no grid test (``inside``, which the walk's tests still use): a walk starts in the grid
(``walk32_begin`` clamps its first voxel, or starts none: i = DEAD) and ends only where ``exact_step`` finds the
next crossing at or after the segment end ``t1d`` and sets i = DEAD. The float32 step is taken only where the
float64 step would take the same axis before ``t1d`` (``certain_step``), so neither leaves the grid first: the
float64 crossing of a far plane, ``(b * s - o) / d`` in ``next_t``, has the operands and order of the clip's
exit in ``_clip_grid``, so the same bits, and ``t1d`` is at most that exit (the argument in full:
bench/gpu_dense_round7_kernels.py at tag lab-2026-11-27). Nor is a bound on the steps needed: each step moves
one voxel along a ray of finite length.

Limits: a candidate's bitset must have fewer than 2^31 words (32 x that many voxels) and each grid axis
fewer than 2^31 voxels; ``WarpBackend.score_placements`` checks the first.
"""

from __future__ import annotations

import warp as wp

from place3d_kernels.backends.warp.kernels import Walk32, next_t, walk32_begin

# Warp builds a module once per (device, launch block_dim) and hashes block_dim into it (Warp 1.19,
# Module.load): a 128-thread launch of a kernel in kernels.py, whose other launches use CUDA's default
# 256, compiled that whole file a second time on a cold CUDA host. So this kernel lives in a module
# of its own, with kernels.py's options restated (forward only; no FMA contraction, which would move
# voxel-boundary ties). 128-thread blocks and a register cap: uncapped, the kernel takes so many registers
# that few warps fit on an SM; 56 since the flat bricks, where 64, 52 and 48 were each slower on the dense
# rig (bench/README.md, "What the studies found", dense-rig score kernel, brick shape and loop).
SCORE_BLOCK_DIM = 128
SCORE_MAX_REGISTERS = 56
_MODULE_OPTIONS = {"enable_backward": False, "fuse_fp": False, "block_dim": SCORE_BLOCK_DIM}
wp.set_module_options(_MODULE_OPTIONS)
#: a candidate's bitset words must be int32 indices
MAX_WORDS = 2**31 - 1


# ----------------------------------------------------------------------------- raw addresses
@wp.func_native("""
return reinterpret_cast<const unsigned long long*>(arr.data)[i];
""")
def load_mask(arr: wp.array(dtype=wp.uint64), i: wp.int32) -> wp.uint64:
    """``arr[i]`` for 0 <= i < 2^31 without Warp's negative-index wrap: one 32-bit multiply-add."""
    ...


@wp.func_native("""
wp::uint64 p = (wp::uint64)(arr.data + base);
#if defined(__CUDA_ARCH__)
asm("mov.b64 %0, %0;" : "+l"(p));
#endif
return p;
""")
def word_address(arr: wp.array(dtype=wp.uint32), base: wp.int64) -> wp.uint64:
    """Address of ``arr[base]`` (the candidate's first bitset word), computed once per ray. The empty
    inline-asm move hides where it came from: without it nvcc, short of registers at the cap, recomputed
    ``(cand * words_per_candidate + word) * 4 + data`` on every step instead of keeping the address."""
    ...


@wp.func_native("""
const unsigned int* q = reinterpret_cast<const unsigned int*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
#endif
return *q;
""")
def load_word(p: wp.uint64, i: wp.int32) -> wp.uint32:
    """Bitset word ``i`` after address ``p``. The address is declared global (after ``word_address``'s asm
    nvcc only knows a generic address, and would emit a generic load instead of a global one)."""
    ...


@wp.func_native("""
wp::uint32* q = reinterpret_cast<wp::uint32*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
#endif
return wp::atomic_or(q, v);
""")
def atomic_or_word(p: wp.uint64, i: wp.int32, v: wp.uint32) -> wp.uint32:
    """``atomic_or`` on bitset word ``i`` after address ``p``; returns the old word (left unused, it compiles
    to a reduction the GPU does not wait for, as Warp's own ``atomic_or``)."""
    ...


@wp.func_native("""
wp::uint32* q = reinterpret_cast<wp::uint32*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
#endif
*q = v;
""")
def store_word(p: wp.uint64, i: wp.int32, v: wp.uint32):
    """Bitset word ``i`` after address ``p`` set to ``v``."""
    ...


# ----------------------------------------------------------------------------- walk and bookkeeping
DEAD = wp.constant(wp.int32(-1))       # i of a walk that has ended


@wp.struct
class WalkGPU:
    i: wp.int32            # current voxel (i = DEAD: the walk has ended)
    j: wp.int32
    k: wp.int32
    si: wp.int32           # step per axis: -1, 0, +1
    sj: wp.int32
    sk: wp.int32
    ki: wp.int32           # next boundary plane minus the first voxel, per axis
    kj: wp.int32
    kk: wp.int32
    tx: wp.float32         # next crossing after t0 per axis (0 for a float64-only walk)
    ty: wp.float32
    tz: wp.float32
    qx: wp.float32         # rebased entry point p0 - b s
    qy: wp.float32
    qz: wp.float32
    vx: wp.float32         # 1 / d
    vy: wp.float32
    vz: wp.float32
    t1: wp.float32         # segment end after t0 (-1: every step in float64)
    tol: wp.float32        # certainty threshold (0 for a float64-only walk)


@wp.func
def walk_from(a: Walk32) -> WalkGPU:
    # kernels.walk32_begin's state with its flags turned into markers (the same values otherwise)
    w = WalkGPU()
    w.i = wp.where(a.alive != 0, a.i, DEAD)
    w.j = a.j
    w.k = a.k
    w.si = a.si
    w.sj = a.sj
    w.sk = a.sk
    w.ki = a.ki
    w.kj = a.kj
    w.kk = a.kk
    w.tx = a.tx
    w.ty = a.ty
    w.tz = a.tz
    w.qx = a.qx
    w.qy = a.qy
    w.qz = a.qz
    w.vx = a.vx
    w.vy = a.vy
    w.vz = a.vz
    w.t1 = a.t1
    w.tol = a.tol
    if a.exact != 0:
        # t1 = -1 fails the certainty test below on every step, so each goes to the float64 step, which
        # leaves these float32 fields alone; any other walk has t1 = float32(t1d - t0) >= 0
        w.t1 = wp.float32(-1.0)
        w.tx = wp.float32(0.0)
        w.ty = wp.float32(0.0)
        w.tz = wp.float32(0.0)
        w.tol = wp.float32(0.0)
    return w


@wp.func
def inside(w: WalkGPU, nx: wp.int32, ny: wp.int32, nz: wp.int32) -> wp.bool:
    # the walk goes on: its voxel is in the grid (a coordinate of -1, DEAD included, wraps to 2^32 - 1)
    return wp.uint32(w.i) < wp.uint32(nx) and wp.uint32(w.j) < wp.uint32(ny) and wp.uint32(w.k) < wp.uint32(nz)


@wp.func
def exact_step(w: WalkGPU, o: wp.vec3d, d: wp.vec3d, t1d: wp.float64, s: wp.float64, sf: wp.float32) -> WalkGPU:
    # kernels.walk32_exact on a WalkGPU: the reference's float64 step (every axis whose boundary comes
    # first steps), the walk ending at the segment end t1d
    tx = next_t(w.i, w.si, o[0], d[0], s)
    ty = next_t(w.j, w.sj, o[1], d[1], s)
    tz = next_t(w.k, w.sk, o[2], d[2], s)
    tn = wp.min(tx, wp.min(ty, tz))
    if tn >= t1d:
        w.i = DEAD
        return w
    f32 = w.t1 >= wp.float32(0.0)         # not a float64-only walk: keep the float32 crossings current
    if tx == tn:
        w.i = w.i + w.si
        w.ki = w.ki + w.si
        if f32:
            w.tx = (wp.float32(w.ki) * sf - w.qx) * w.vx
    if ty == tn:
        w.j = w.j + w.sj
        w.kj = w.kj + w.sj
        if f32:
            w.ty = (wp.float32(w.kj) * sf - w.qy) * w.vy
    if tz == tn:
        w.k = w.k + w.sk
        w.kk = w.kk + w.sk
        if f32:
            w.tz = (wp.float32(w.kk) * sf - w.qz) * w.vz
    return w


@wp.func
def certain_step(w: WalkGPU):
    """(xa, ya, za, go): the axis of the first crossing, and whether the float32 step along it is certain.

    kernels.walk32_next picks tmin by ``tx < ty and tx < tz``, then ``ty < tz``, else z, and goes when
    both other crossings and the segment end exceed tmin + tol. Each branch's pick is the smallest value
    (ties kept), so "both others > lim" is "median > lim"; min and max return one of their operands
    unchanged (the crossings are finite: no NaN), so lim has the same operands and bits. Where go holds
    the minimum is unique (median > tmin + tol >= tmin), so ``tx == tmin`` picks the same axis.
    tests/test_dense_variants.py steps this walk against walk32_next field by field."""
    a = wp.min(w.tx, w.ty)
    b = wp.max(w.tx, w.ty)
    tmin = wp.min(a, w.tz)
    med = wp.max(a, wp.min(b, w.tz))
    lim = tmin + w.tol
    go = med > lim and w.t1 > lim
    xa = w.tx == tmin
    ya = (not xa) and w.ty == tmin
    za = (not xa) and (not ya)
    return xa, ya, za, go


@wp.func
def next_step(w: WalkGPU, o: wp.vec3d, d: wp.vec3d, t1d: wp.float64, s: wp.float64, sf: wp.float32) -> WalkGPU:
    # the certain float32 step along the first axis (no grid test: the loop's head makes it), else the
    # float64 one; no FMA (fuse_fp off), so the new crossing rounds as the reference's expression
    xa, ya, za, go = certain_step(w)
    if not go:
        return exact_step(w, o, d, t1d, s, sf)
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
    return w


# ----------------------------------------------------------------------------- flat bricks
#: log2 of the CUDA bitset's brick sides along x and y (8 x 4 x 1 voxels, bricks.flat_shape)
FLAT_LX = 3
FLAT_LY = 2


@wp.func
def word_flat(w: WalkGPU, nbx: wp.int32, nby: wp.int32) -> wp.int32:
    # the brick's word within the candidate's bitset (bricks.flat_brick_masks' numbering: z slowest, y fastest)
    return (w.k * nbx + (w.i >> FLAT_LX)) * nby + (w.j >> FLAT_LY)


@wp.func
def bit_flat(w: WalkGPU) -> wp.uint32:
    # the voxel's bit within its brick: (i & 7) | (j & 3) << 3
    return wp.uint32(1) << wp.uint32((w.i & 7) | ((w.j & 3) << FLAT_LX))


@wp.func
def flush_flat(p: wp.uint64, word: wp.int32, pending: wp.uint32, nz_w: wp.uint32, nbx: wp.int32,
               nby: wp.int32, ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)) -> wp.int64:
    # one atomic_or for the bits a ray marked in one brick; only where some have entropy is the old word
    # waited for: the bits this ray set first are its own, and it adds their weights
    add = wp.int64(0)
    if pending != wp.uint32(0):
        if (pending & nz_w) != wp.uint32(0):
            old = atomic_or_word(p, word, pending)
            m = pending & ~old & nz_w
            # the brick's coordinates from its word, by 32-bit divisions (int64 ones call a subroutine)
            uw = wp.uint32(word)
            bj = wp.int32(uw % wp.uint32(nby))
            r = uw / wp.uint32(nby)
            bi = wp.int32(r % wp.uint32(nbx))
            k = wp.int32(r / wp.uint32(nbx))
            while m != wp.uint32(0):
                b = wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1))     # index of the lowest set bit
                i = (bi << FLAT_LX) + (b & 7)
                j = (bj << FLAT_LY) + (b >> FLAT_LX)
                add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
                m = m & (m - wp.uint32(1))
        else:
            atomic_or_word(p, word, pending)
    return add


@wp.kernel(cuda_max_registers=SCORE_MAX_REGISTERS)
def score_kernel_gpu(
    sensor_dirs: wp.array(dtype=wp.vec3d),      # (C*A,)
    rot: wp.array(dtype=wp.mat33d),             # (P*L,)
    pos: wp.array(dtype=wp.vec3d),              # (P*L,) grid-local
    n_lidars: wp.int32, t_max: wp.float64,
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    nbx: wp.int32, nby: wp.int32,               # flat bricks along x and y (flat_shape)
    masks64: wp.array(dtype=wp.uint64),         # per flat brick: occlusion bits | nonzero-weight bits << 32
    weights: wp.array(dtype=wp.int64),          # flat voxel order
    words_per_candidate: wp.int64,
    bits: wp.array(dtype=wp.uint32),            # (P * words_per_candidate,) zeroed, in flat bricks
    sums: wp.array(dtype=wp.int64),             # (P,) zeroed
):
    tid = wp.tid()
    n = sensor_dirs.shape[0]
    rig = tid / n                               # candidate * n_lidars + lidar
    cand = rig / n_lidars
    o = pos[rig]
    d = rot[rig] * sensor_dirs[tid - rig * n]   # as lidar_rays_kernel: the reference's rays bit for bit
    sf = wp.float32(s)
    w0 = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
    t1d = w0.t1d
    w = walk_from(w0)
    cbits = word_address(bits, wp.int64(cand) * words_per_candidate)
    my_sum = wp.int64(0)
    cur = wp.int32(-1)
    seen = wp.uint32(0)
    pending = wp.uint32(0)
    nz_w = wp.uint32(0)
    # no grid test and no step bound: a walk ends only at its segment's end, where the float64 step sets
    # i = DEAD, before it could leave the grid (module docstring)
    while w.i >= 0:
        word = word_flat(w, nbx, nby)
        change = word != cur
        if change and pending != wp.uint32(0):
            my_sum += flush_flat(cbits, cur, pending, nz_w, nbx, nby, ny, nz, weights)
        m = load_mask(masks64, word)
        fresh = load_word(cbits, word)
        stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
        nz_w = wp.uint32(m >> wp.uint64(32))
        # the snapshot of the bitset word is the one read on entering the brick (bits only ever get set,
        # so a stale copy is safe: it only filters what this ray sends to its atomic_or)
        seen = wp.where(change, fresh, seen)
        pending = wp.where(change, wp.uint32(0), pending)
        cur = word
        bit = bit_flat(w)
        pending = pending | (bit & ~seen)
        seen = seen | bit
        if (stop_w & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
            break
        w = next_step(w, o, d, t1d, s, sf)
    if pending != wp.uint32(0):
        my_sum += flush_flat(cbits, cur, pending, nz_w, nbx, nby, ny, nz, weights)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


@wp.func
def spread_rows(pair: wp.uint64, layer: wp.int32, at: wp.int32) -> wp.uint64:
    # the four 4-bit rows (4 voxels along x) of one z layer of a 4 x 4 x 2 brick, in both words of its pair,
    # moved to bits at + 8 r of the same words
    out = wp.uint64(0)
    for r in range(4):
        src = layer + 4 * r
        out = out | (((pair >> wp.uint64(src)) & wp.uint64(0xF)) << wp.uint64(at + 8 * r))
        out = out | (((pair >> wp.uint64(32 + src)) & wp.uint64(0xF)) << wp.uint64(32 + at + 8 * r))
    return out


@wp.kernel
def flat_masks_kernel(pairs: wp.array(dtype=wp.uint64), bx: wp.int32, by: wp.int32, bz: wp.int32,
                      nbx: wp.int32, nby: wp.int32, flat: wp.array(dtype=wp.uint64)):
    # flat[f] = the masks of flat brick f (bricks.flat_brick_masks) from the grid's 4 x 4 x 2 brick pairs
    # (bricks.brick_masks as one uint64 each): the x bricks 2 bi and 2 bi + 1 of row bj, layer k & 1 of brick
    # k >> 1 (a brick past the grid's end holds no bits, as the host's padding)
    f = wp.tid()
    bj = f % nby
    r = f / nby
    bi = r % nbx
    k = r / nbx
    out = wp.uint64(0)
    for h in range(2):
        x = 2 * bi + h
        if x < bx:
            b = (wp.int64(x) * wp.int64(by) + wp.int64(bj)) * wp.int64(bz) + wp.int64(k >> 1)
            out = out | spread_rows(pairs[b], (k & 1) * 16, h * 4)
    flat[f] = out


# The bit count that follows every score launch, and the zeroing before the next, are passes over the whole
# bitset (512 MB for 16 dense rigs). Here they are one pass: each thread of a candidate counts every T-th word
# (so a warp's 32 loads are consecutive words) and zeroes the words it found set, which leaves the buffer as
# the next call needs it (WarpCore keeps it; bench/README.md, "What the studies found", dense-rig score
# kernel, API around the kernel).
def count_threads_per_candidate(words: int, candidates: int) -> int:
    """Threads per candidate of ``count_clear_kernel``: 64 words per thread for small bitsets, and for large
    ones about 2^18 threads in all (one atomic add each, so few enough that the counters do not queue)."""
    return max(1, min(-(-words // 64), -(-(1 << 18) // max(candidates, 1))))


@wp.kernel
def count_clear_kernel(bits: wp.array(dtype=wp.uint32), words_per_candidate: wp.int32,
                       threads_per_candidate: wp.int32, masks: wp.array(dtype=wp.uint64), has_masks: wp.int32,
                       counts: wp.array(dtype=wp.int64), masked: wp.array(dtype=wp.int64)):
    # counts[c] += set bits of candidate c's bitset; the words read are left zero. With has_masks, in the same
    # pass masked[c] += the set bits whose voxel the masks' high halves keep (a 0/1 grid's nonzero weights: the
    # "evidence" and "uncertain" denominators, counted by a pass of their own, uncoalesced, before 2026-12-01)
    tid = wp.tid()
    cand = tid / threads_per_candidate
    p = word_address(bits, wp.int64(cand) * wp.int64(words_per_candidate))
    n = wp.int32(0)
    m = wp.int32(0)
    c = tid - cand * threads_per_candidate
    if c < words_per_candidate:
        # words c, c + T, ... below words_per_candidate (a count, so the index never passes 2^31 - 1)
        for q in range((words_per_candidate - 1 - c) / threads_per_candidate + 1):
            at = c + q * threads_per_candidate
            v = load_word(p, at)
            if v != wp.uint32(0):
                n += wp.bit_count(v)
                if has_masks != 0:
                    m += wp.bit_count(v & wp.uint32(masks[at] >> wp.uint64(32)))
                store_word(p, at, wp.uint32(0))
    if n > 0:
        wp.atomic_add(counts, cand, wp.int64(n))
    if m > 0:
        wp.atomic_add(masked, cand, wp.int64(m))
