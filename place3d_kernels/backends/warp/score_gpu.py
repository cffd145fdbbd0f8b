"""The CUDA score kernel (``score_kernel_gpu``): M-SOG sums of a population of rigs on a bricked bitset.

The CPU runs ``kernels.score_kernel`` (one ray per thread, an atomic per voxel, which the CPU pays
little for). On CUDA this kernel walks the same voxels with the same float32/float64 decisions
(``kernels.walk32_*``) and does the bookkeeping per brick of 4 x 4 x 2 voxels (one 32-bit bitset word):

* the brick's masks (occlusion bits low, nonzero-weight bits high; one 64-bit load) and the
  candidate's bitset word are loaded on every step (cache hits while the ray stays in the brick) and
  kept only when the ray enters a new brick, so no branch decides whether to load;
* the bits a ray marks in a brick are sent with one ``atomic_or`` when it leaves (``flush_brick32``);
  only bricks holding entropy wait for the old word, to add the weights of the bits this ray set first.

What makes it cheap is the address arithmetic of a step, which a dense rig takes hundreds of millions
of times: the brick word is an int32 from (i, j, k) (three shifts, two multiply-adds by kernel
constants), loads and atomics use raw addresses (no index wrap, no 64-bit stride multiplies), and the
grid test is three unsigned compares. That took about a third of the instructions out of a step's common
path against the previous form with int64 indices, which this replaced (figures: bench/README.md, "The
dense rig's score kernel, third round"). The walk's decisions are untouched, so the voxels, sums and
counts are the same bits (tests/test_dense_variants.py runs the previous form against this one; the
cross-backend suites compare scores with the reference).

Limits: a candidate's bitset must have fewer than 2^31 words (32 x that many voxels) and each grid axis
fewer than 2^31 voxels; ``WarpBackend.score_placements`` checks the first.
"""

from __future__ import annotations

import warp as wp

from place3d_kernels.backends.warp.kernels import Walk32, walk32_begin, walk32_exact

# Warp builds a module once per (device, launch block_dim) and hashes block_dim into it (Warp 1.19,
# Module.load): a 128-thread launch of a kernel in kernels.py, whose other launches use CUDA's default
# 256, compiled that whole file a second time on a cold CUDA host (3.4 s). So this kernel lives in a module
# of its own, with kernels.py's options restated (forward only; no FMA contraction, which would move
# voxel-boundary ties). 128-thread blocks and a register cap: uncapped, the kernel takes so many registers
# that few warps fit on an SM (figures: bench/README.md, "Figures behind backend code comments").
SCORE_BLOCK_DIM = 128
SCORE_MAX_REGISTERS = 64
_MODULE_OPTIONS = {"enable_backward": False, "fuse_fp": False, "block_dim": SCORE_BLOCK_DIM}
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


# ----------------------------------------------------------------------------- walk and bookkeeping
@wp.func
def word32(w: Walk32, bny: wp.int32, bnz: wp.int32) -> wp.int32:
    # the brick's word within the candidate's bitset (kernels.brick_word in int32)
    return ((w.i >> 2) * bny + (w.j >> 2)) * bnz + (w.k >> 1)


@wp.func
def walk32_next_lean(w: Walk32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32, nx: wp.int32,
                     ny: wp.int32, nz: wp.int32) -> Walk32:
    # kernels.walk32_next_sel with the grid test as three unsigned compares (a coordinate of -1 wraps to
    # 2^32 - 1): the same comparisons, crossing expression and float64 fallback, so the same voxels
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
    out = wp.uint32(w.i) >= wp.uint32(nx) or wp.uint32(w.j) >= wp.uint32(ny) or wp.uint32(w.k) >= wp.uint32(nz)
    w.alive = wp.where(out, 0, w.alive)
    return w


@wp.func
def flush_brick32(p: wp.uint64, word: wp.int32, pending: wp.uint32, nz_w: wp.uint32, bny: wp.int32,
                  bnz: wp.int32, ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)) -> wp.int64:
    # one atomic_or for the bits a ray marked in one brick; only where some have entropy is the old word
    # waited for: the bits this ray set first are its own, and it adds their weights
    add = wp.int64(0)
    if pending != wp.uint32(0):
        if (pending & nz_w) != wp.uint32(0):
            old = atomic_or_word(p, word, pending)
            m = pending & ~old & nz_w
            # the brick's coordinates from its word, by 32-bit divisions (int64 ones call a subroutine)
            uw = wp.uint32(word)
            bk = wp.int32(uw % wp.uint32(bnz))
            r = uw / wp.uint32(bnz)
            bj = wp.int32(r % wp.uint32(bny))
            bi = wp.int32(r / wp.uint32(bny))
            while m != wp.uint32(0):
                b = wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1))     # index of the lowest set bit
                i = bi * 4 + (b & 3)
                j = bj * 4 + ((b >> 2) & 3)
                k = bk * 2 + (b >> 4)
                add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
                m = m & (m - wp.uint32(1))
        else:
            atomic_or_word(p, word, pending)
    return add


@wp.kernel(cuda_max_registers=SCORE_MAX_REGISTERS, module="unique", module_options=_MODULE_OPTIONS)
def score_kernel_gpu(
    sensor_dirs: wp.array(dtype=wp.vec3d),      # (C*A,)
    rot: wp.array(dtype=wp.mat33d),             # (P*L,)
    pos: wp.array(dtype=wp.vec3d),              # (P*L,) grid-local
    n_lidars: wp.int32, t_max: wp.float64,
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32,               # bricks along y and z
    masks64: wp.array(dtype=wp.uint64),         # per brick: occlusion bits | nonzero-weight bits << 32
    weights: wp.array(dtype=wp.int64),          # flat voxel order
    words_per_candidate: wp.int64,
    bits: wp.array(dtype=wp.uint32),            # (P * words_per_candidate,) zeroed, bricked
    sums: wp.array(dtype=wp.int64),             # (P,) zeroed
):
    tid = wp.tid()
    n = sensor_dirs.shape[0]
    rig = tid / n                               # candidate * n_lidars + lidar
    cand = rig / n_lidars
    o = pos[rig]
    d = rot[rig] * sensor_dirs[tid - rig * n]   # as lidar_rays_kernel: the reference's rays bit for bit
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
    cbits = word_address(bits, wp.int64(cand) * words_per_candidate)
    my_sum = wp.int64(0)
    cur = wp.int32(-1)
    seen = wp.uint32(0)
    pending = wp.uint32(0)
    nz_w = wp.uint32(0)
    for _ in range(nx + ny + nz + 3):
        if w.alive == 0:
            break
        word = word32(w, bny, bnz)
        change = word != cur
        if change and pending != wp.uint32(0):
            my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        m = load_mask(masks64, word)
        fresh = load_word(cbits, word)
        stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
        nz_w = wp.uint32(m >> wp.uint64(32))
        # the snapshot of the bitset word is the one read on entering the brick (bits only ever get set,
        # so a stale copy is safe: it only filters what this ray sends to its atomic_or)
        seen = wp.where(change, fresh, seen)
        pending = wp.where(change, wp.uint32(0), pending)
        cur = word
        bit = wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))
        pending = pending | (bit & ~seen)
        seen = seen | bit
        if (stop_w & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
            break
        w = walk32_next_lean(w, o, d, s, sf, nx, ny, nz)
    if pending != wp.uint32(0):
        my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)
