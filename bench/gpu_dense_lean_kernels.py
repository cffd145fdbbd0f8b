"""Warp kernels of the dense-rig study's third round (``gpu_dense_variants.py``, issue 17, goal 3): fewer
instructions per step, and full bricks skipped.

All start from ``walk_ray_brick_eager`` (``gpu_dense_variants_kernels.py``; the shipped
``score_ray_brick``): one thread per ray in the shipped order, the brick's masks and bitset word loaded
on every step and kept on entry, one ``atomic_or`` per brick left.

* **lean** (``make_lean``): the same walk decisions (every float32 and float64 comparison unchanged),
  cheaper address arithmetic. The brick's word within the candidate is an int32 kept as the walk steps
  (a coordinate crossing a brick boundary flips bit 2 of i or j, bit 1 of k, so one XOR per axis finds
  it, also when walk32_exact steps two or three axes at once), instead of three int64 multiplies per
  step; the loads use the raw address (one 32-bit multiply-add) instead of Warp's indexing (negative
  index wrap, int32 stride multiply, 64-bit add); the walk's grid test is three unsigned compares; the
  flush works on the raw address and finds the brick's coordinates with 32-bit divisions.
* **lean32** (``make_lean(inc=False)``): lean with the word recomputed from (i, j, k) in int32 on every
  step: three shifts and two multiply-adds by kernel constants, fewer instructions than the XOR form
  and no registers for the word strides (nvcc's SASS for sm_90, counted by the study).
* **skip** (``make_eager_skip``, and ``make_lean(skip=True)``): a brick whose bits are all set in this
  candidate's bitset (the word read on entry plus the ray's own bits) and that holds no stop bit cannot
  give the ray a new voxel or stop it, so the walk jumps to the voxel where it leaves the brick
  (``walk32_skip_brick``). Bits only ever get set, so a brick seen full stays full.
* **skipu** (``make_lean(skip="unified")``): the jump and the step in one body (``walk32_step_or_jump``),
  so that lanes of a warp that jump and lanes that step do not run both; longer common step.
* **keep** (``make_lean(keep=True)``): lean32 with the brick's masks kept from its entry, loaded in a
  native branch (``load_mask_if``), so nvcc predicates both loads on entering a brick and a step inside
  it touches no memory and waits for none (the shipped kernel waits for an L1 hit on every step).
* **ahead** (``make_lean(ahead=True)``): lean, with the loads for the next voxel issued right after the
  step, before the current voxel's masks are used (software pipelining by one step), so a load's latency
  overlaps the next iteration's work instead of stalling the stop test that follows it. The bitset word
  is then read before the previous brick's flush, an earlier snapshot of another word: a snapshot only
  filters which bits a ray sends to its atomic_or, and the atomic decides who set a bit first, so the
  sums do not change.
* **walk-only** (``make_walk_only``): a floor diagnostic with today's step (``walk32_next_sel``) and
  today's stop read (``masks64[brick_word]``), no bitset, no weights; it adds each ray's step count to
  the sums (wrong on purpose; it keeps the walk from being optimised away).

Every kernel has the shipped kernel's inputs followed by ``stats`` (int64, 4 slots). Built with
``count=True``, a kernel adds there: [0] loop iterations (voxels visited, the last one included),
[1] full-brick jumps that moved the ray past at least one voxel (two or more plane crossings at once),
[2] the plane crossings those jumps took, [3] steps from a full brick with one crossing (a jump that
was not certain and stepped instead, or a ray already on the brick's exit face). Without ``count`` the
slots are untouched (no atomics).

Why a jump is exact: the reference walk visits voxels in the order of its float64 plane-crossing times
(ties step several axes at once), and the float32 walk takes the same steps (``walk32_next_sel`` steps
in float32 only where the other crossings and the segment end are more than ``tol`` later). After the
walk leaves a brick, each axis has taken exactly the crossings that come no later than the exit
crossing (the earliest of the three axes' exit-plane crossings). ``walk32_skip_brick`` evaluates those
crossings with the walk's own float32 expression, ``(K sf - q) v`` (monotone in K), and jumps only if
every comparison it makes is certain by ``tol`` as the walk's step test is: the exit crossing against the
other axes' exit crossings and the segment end, and each interior crossing of the other axes against
the exit crossing. Otherwise it takes one ordinary step. The crossing times after the jump are
recomputed from the new plane indices with the same expression, so the walk's state is the one that
stepping would have reached, bit for bit. Where the grid ends inside the brick (bricks cut by the grid's
edge, or a ray leaving through a side), stepping ends the ray at the first voxel outside; the jump lands
outside too (coordinates only move one way), so the ray ends with nothing marked either way.
"""

from __future__ import annotations

import warp as wp

from gpu_dense_variants_kernels import OPTS, walk32_next_sel
from gpu_score_variants_kernels import FLT_BIG, Walk32, brick_bit, brick_word, flush_brick, walk32_begin, walk32_exact

FULL = wp.constant(wp.uint32(0xFFFFFFFF))


# ----------------------------------------------------------------------------- raw loads
@wp.func_native("""
return reinterpret_cast<const unsigned long long*>(arr.data)[i];
""")
def load_mask(arr: wp.array(dtype=wp.uint64), i: wp.int32) -> wp.uint64:
    """``arr[i]`` for 0 <= i < 2^31 without Warp's negative-index wrap: one 32-bit multiply-add."""
    ...


@wp.func_native("""
if (pred)
    return reinterpret_cast<const unsigned long long*>(arr.data)[i];
return old;
""")
def load_mask_if(arr: wp.array(dtype=wp.uint64), i: wp.int32, pred: wp.bool, old: wp.uint64) -> wp.uint64:
    """``arr[i]`` where ``pred``, else ``old``: a load in a branch of native code, which nvcc cannot hoist
    out of it (it may not speculate a load it cannot prove safe), so it becomes a predicated load; the
    same where() in Warp code let nvcc load on every step and select."""
    ...


@wp.func_native("""
wp::uint64 p = (wp::uint64)(arr.data + base);
#if defined(__CUDA_ARCH__)
asm("mov.b64 %0, %0;" : "+l"(p));
#endif
return p;
""")
def word_address(arr: wp.array(dtype=wp.uint32), base: wp.int64) -> wp.uint64:
    """Address of ``arr[base]`` (a candidate's first bitset word), computed once per ray. On CUDA an empty
    inline-asm move hides where it came from: otherwise nvcc, short of registers, recomputes
    ``(cand * words_per_candidate + word) * 4 + data`` on every step (seven instructions in the SASS of
    the study's kernels) instead of keeping the address."""
    ...


@wp.func_native("""
const unsigned int* q = reinterpret_cast<const unsigned int*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
#endif
return *q;
""")
def load_word(p: wp.uint64, i: wp.int32) -> wp.uint32:
    """The bitset word ``i`` after address ``p``, a plain load as Warp's indexing emits. On CUDA the
    address is declared global (it passed through ``word_address``'s asm, after which nvcc only knows a
    generic address and would emit LD instead of LDG)."""
    ...


@wp.func_native("""
wp::uint32 r = old;
if (pred) {
    const unsigned int* q = reinterpret_cast<const unsigned int*>(p) + i;
#if defined(__CUDA_ARCH__)
    __builtin_assume(__isGlobal(q));
#endif
    r = *q;
}
return r;
""")
def load_word_if(p: wp.uint64, i: wp.int32, pred: wp.bool, old: wp.uint32) -> wp.uint32:
    """Bitset word ``i`` after ``p`` where ``pred``, else ``old``: a load in native code that nvcc predicates
    instead of hoisting, so the register is written when the load lands and nothing waits for it until
    the value is used (``lazy``: at the flush, several steps later)."""
    ...


@wp.func_native("""
wp::uint32* q = reinterpret_cast<wp::uint32*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
#endif
return wp::atomic_or(q, v);
""")
def atomic_or_word(p: wp.uint64, i: wp.int32, v: wp.uint32) -> wp.uint32:
    """``atomic_or`` on the bitset word ``i`` after address ``p`` (declared global on CUDA, as in
    ``load_word``); returns the old word (a result left unused compiles to a reduction the GPU does not
    wait for, as Warp's own atomic_or)."""
    ...


@wp.func
def flush_brick32(p: wp.uint64, word: wp.int32, pending: wp.uint32, nz_w: wp.uint32, bny: wp.int32,
                  bnz: wp.int32, ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)) -> wp.int64:
    # flush_brick on the raw address with an int32 word: the brick's coordinates by 32-bit unsigned
    # divisions (the int64 ones call a slow subroutine), the same bits, the same sums
    add = wp.int64(0)
    if pending != wp.uint32(0):
        if (pending & nz_w) != wp.uint32(0):
            old = atomic_or_word(p, word, pending)
            m = pending & ~old & nz_w
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


@wp.func_native("""
if (pred) {
    wp::uint32* q = reinterpret_cast<wp::uint32*>(p) + i;
#if defined(__CUDA_ARCH__)
    __builtin_assume(__isGlobal(q));
#endif
    wp::atomic_or(q, v);
}
""")
def red_or_if(p: wp.uint64, i: wp.int32, v: wp.uint32, pred: wp.bool):
    """``atomic_or`` of ``v`` on bitset word ``i`` after ``p`` where ``pred``, its result unused: one
    predicated reduction instead of a branch around it (``pred`` variant)."""
    ...


@wp.func
def flush_entropy32(p: wp.uint64, word: wp.int32, pending: wp.uint32, nz_w: wp.uint32, bny: wp.int32,
                    bnz: wp.int32, ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)) -> wp.int64:
    # flush_brick32's rare path alone (some of the pending bits have entropy): the atomic whose old word
    # tells which bits this ray set first, and their weights
    old = atomic_or_word(p, word, pending)
    m = pending & ~old & nz_w
    uw = wp.uint32(word)
    bk = wp.int32(uw % wp.uint32(bnz))
    r = uw / wp.uint32(bnz)
    bj = wp.int32(r % wp.uint32(bny))
    bi = wp.int32(r / wp.uint32(bny))
    add = wp.int64(0)
    while m != wp.uint32(0):
        b = wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1))
        i = bi * 4 + (b & 3)
        j = bj * 4 + ((b >> 2) & 3)
        k = bk * 2 + (b >> 4)
        add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
        m = m & (m - wp.uint32(1))
    return add


# ----------------------------------------------------------------------------- steps
@wp.func
def walk32_next_lean(w: Walk32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32, nx: wp.int32,
                     ny: wp.int32, nz: wp.int32) -> Walk32:
    """``walk32_next_sel`` with the grid test as three unsigned compares (a coordinate of -1 wraps to
    2^32 - 1). Same comparisons, same crossing expression, same fallback: the same voxels."""
    xa = w.tx < w.ty and w.tx < w.tz
    ya = (not xa) and w.ty < w.tz
    za = (not xa) and (not ya)
    tmin = wp.where(xa, w.tx, wp.where(ya, w.ty, w.tz))
    o1 = wp.where(xa, w.ty, w.tx)
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
def crossing(kp: wp.int32, sf: wp.float32, q: wp.float32, v: wp.float32) -> wp.float32:
    # the walk's float32 crossing time of boundary plane kp (relative to the first voxel), as walk32_*
    return (wp.float32(kp) * sf - q) * v


@wp.func
def crossings_before(kp: wp.int32, step: wp.int32, n: wp.int32, q: wp.float32, v: wp.float32,
                     sf: wp.float32, e: wp.float32, tol: wp.float32):
    """Of an axis's next ``n`` (at most 3) crossings, planes kp, kp + step, ...: how many come before
    ``e``, and 1 if each is certainly before or after it (more than ``tol`` apart, as the walk's step
    test), else 0."""
    c = wp.int32(0)
    ok = wp.int32(1)
    for m in range(3):
        if m < n:
            t = crossing(kp + step * m, sf, q, v)
            if e > t + tol:
                c += 1
            elif not (t > e + tol):
                ok = 0
    return c, ok


@wp.func
def walk32_skip_brick(w: Walk32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32, nx: wp.int32,
                      ny: wp.int32, nz: wp.int32) -> Walk32:
    """The walk's state once it has left the current brick (4 x 4 x 2 voxels), where every comparison
    that decides it is certain (module docstring); otherwise one ordinary step (``walk32_next_sel``)."""
    if w.exact != 0:
        return walk32_next_sel(w, o, d, s, sf, nx, ny, nz)
    # crossings left before each axis's exit plane from the brick (none along an axis the ray is parallel to)
    ni = wp.where(w.si > 0, 3 - (w.i & 3), wp.where(w.si < 0, w.i & 3, 0))
    nj = wp.where(w.sj > 0, 3 - (w.j & 3), wp.where(w.sj < 0, w.j & 3, 0))
    nk = wp.where(w.sk > 0, 1 - (w.k & 1), wp.where(w.sk < 0, w.k & 1, 0))
    ex = wp.where(w.si != 0, crossing(w.ki + w.si * ni, sf, w.qx, w.vx), FLT_BIG)
    ey = wp.where(w.sj != 0, crossing(w.kj + w.sj * nj, sf, w.qy, w.vy), FLT_BIG)
    ez = wp.where(w.sk != 0, crossing(w.kk + w.sk * nk, sf, w.qz, w.vz), FLT_BIG)
    xa = ex < ey and ex < ez
    ya = (not xa) and ey < ez
    za = (not xa) and (not ya)
    e = wp.where(xa, ex, wp.where(ya, ey, ez))
    o1 = wp.where(xa, ey, ex)
    o2 = wp.where(za, ey, ez)
    lim = e + w.tol
    if o1 <= lim or o2 <= lim or w.t1 <= lim:
        return walk32_next_sel(w, o, d, s, sf, nx, ny, nz)
    ci, oki = crossings_before(w.ki, w.si, ni, w.qx, w.vx, sf, e, w.tol)
    cj, okj = crossings_before(w.kj, w.sj, nj, w.qy, w.vy, sf, e, w.tol)
    ck, okk = crossings_before(w.kk, w.sk, nk, w.qz, w.vz, sf, e, w.tol)
    # the exit axis takes its interior crossings and the exit plane (its own are ordered: no test needed)
    ci = wp.where(xa, ni + 1, ci)
    cj = wp.where(ya, nj + 1, cj)
    ck = wp.where(za, nk + 1, ck)
    if (xa or oki != 0) and (ya or okj != 0) and (za or okk != 0):
        w.i = w.i + w.si * ci
        w.j = w.j + w.sj * cj
        w.k = w.k + w.sk * ck
        w.ki = w.ki + w.si * ci
        w.kj = w.kj + w.sj * cj
        w.kk = w.kk + w.sk * ck
        w.tx = wp.where(ci > 0, crossing(w.ki, sf, w.qx, w.vx), w.tx)
        w.ty = wp.where(cj > 0, crossing(w.kj, sf, w.qy, w.vy), w.ty)
        w.tz = wp.where(ck > 0, crossing(w.kk, sf, w.qz, w.vz), w.tz)
        if w.i < 0 or w.i >= nx or w.j < 0 or w.j >= ny or w.k < 0 or w.k >= nz:
            w.alive = 0
        return w
    return walk32_next_sel(w, o, d, s, sf, nx, ny, nz)


@wp.func
def walk32_step_or_jump(w: Walk32, full: wp.bool, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32,
                        nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32:
    """``walk32_skip_brick`` where ``full``, else the ordinary step, in one body: a lane that is not in a
    full brick jumps over a "brick" of one voxel (no interior crossings; the exit crossings are the next
    crossings, the test is walk32_next_sel's), which is exactly the float32 step. So the lanes of a warp
    that jump and those that step run the same instructions instead of both branches one after the
    other; the price is three crossing times per step instead of one."""
    if w.exact != 0:
        return walk32_exact(w, o, d, s, sf, nx, ny, nz)
    ni = wp.where(full, wp.where(w.si > 0, 3 - (w.i & 3), wp.where(w.si < 0, w.i & 3, 0)), 0)
    nj = wp.where(full, wp.where(w.sj > 0, 3 - (w.j & 3), wp.where(w.sj < 0, w.j & 3, 0)), 0)
    nk = wp.where(full, wp.where(w.sk > 0, 1 - (w.k & 1), wp.where(w.sk < 0, w.k & 1, 0)), 0)
    ex = wp.where(w.si != 0, crossing(w.ki + w.si * ni, sf, w.qx, w.vx), FLT_BIG)
    ey = wp.where(w.sj != 0, crossing(w.kj + w.sj * nj, sf, w.qy, w.vy), FLT_BIG)
    ez = wp.where(w.sk != 0, crossing(w.kk + w.sk * nk, sf, w.qz, w.vz), FLT_BIG)
    xa = ex < ey and ex < ez
    ya = (not xa) and ey < ez
    za = (not xa) and (not ya)
    e = wp.where(xa, ex, wp.where(ya, ey, ez))
    o1 = wp.where(xa, ey, ex)
    o2 = wp.where(za, ey, ez)
    lim = e + w.tol
    if o1 <= lim or o2 <= lim or w.t1 <= lim:
        return walk32_next_lean(w, o, d, s, sf, nx, ny, nz)
    ci, oki = crossings_before(w.ki, w.si, ni, w.qx, w.vx, sf, e, w.tol)
    cj, okj = crossings_before(w.kj, w.sj, nj, w.qy, w.vy, sf, e, w.tol)
    ck, okk = crossings_before(w.kk, w.sk, nk, w.qz, w.vz, sf, e, w.tol)
    ci = wp.where(xa, ni + 1, ci)
    cj = wp.where(ya, nj + 1, cj)
    ck = wp.where(za, nk + 1, ck)
    if (xa or oki != 0) and (ya or okj != 0) and (za or okk != 0):
        w.i = w.i + w.si * ci
        w.j = w.j + w.sj * cj
        w.k = w.k + w.sk * ck
        w.ki = w.ki + w.si * ci
        w.kj = w.kj + w.sj * cj
        w.kk = w.kk + w.sk * ck
        w.tx = wp.where(ci > 0, crossing(w.ki, sf, w.qx, w.vx), w.tx)
        w.ty = wp.where(cj > 0, crossing(w.kj, sf, w.qy, w.vy), w.ty)
        w.tz = wp.where(ck > 0, crossing(w.kk, sf, w.qz, w.vz), w.tz)
        out = (wp.uint32(w.i) >= wp.uint32(nx) or wp.uint32(w.j) >= wp.uint32(ny)
               or wp.uint32(w.k) >= wp.uint32(nz))
        w.alive = wp.where(out, 0, w.alive)
        return w
    return walk32_next_lean(w, o, d, s, sf, nx, ny, nz)


@wp.func
def step_or_skip(w: Walk32, full: wp.bool, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32,
                 nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32:
    # one function with two returns: no merge of two walk structs after an if in the caller
    if full:
        return walk32_skip_brick(w, o, d, s, sf, nx, ny, nz)
    return walk32_next_sel(w, o, d, s, sf, nx, ny, nz)


@wp.func
def step_or_skip_lean(w: Walk32, full: wp.bool, o: wp.vec3d, d: wp.vec3d, s: wp.float64, sf: wp.float32,
                      nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32:
    if full:
        return walk32_skip_brick(w, o, d, s, sf, nx, ny, nz)
    return walk32_next_lean(w, o, d, s, sf, nx, ny, nz)


@wp.func
def word32(w: Walk32, bny: wp.int32, bnz: wp.int32) -> wp.int32:
    # brick_word in int32 (the runner checks that a candidate's words fit)
    return ((w.i >> 2) * bny + (w.j >> 2)) * bnz + (w.k >> 1)


@wp.func
def word_delta(i0: wp.int32, j0: wp.int32, k0: wp.int32, w: Walk32, wsx: wp.int32, wsy: wp.int32,
               wsz: wp.int32) -> wp.int32:
    # change of the brick word over a step that moves each coordinate by at most one: a move of +-1 crosses
    # a multiple of 4 exactly when bit 2 flips (floor(i / 4) changes by one, so its lowest bit flips),
    # a multiple of 2 when bit 1 flips; wsx, wsy, wsz are the word strides signed by the step direction
    return (wp.where(((i0 ^ w.i) & 4) != 0, wsx, 0) + wp.where(((j0 ^ w.j) & 4) != 0, wsy, 0)
            + wp.where(((k0 ^ w.k) & 2) != 0, wsz, 0))


# ----------------------------------------------------------------------------- kernels
def make_eager_skip(maxreg=None, count=False):
    """``walk_ray_brick_eager`` (shipped order, shipped address arithmetic) with full bricks jumped."""

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def eager_skip_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                          pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                          nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                          masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                          words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                          sums: wp.array(dtype=wp.int64), stats: wp.array(dtype=wp.int64)):
        tid = wp.tid()
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
        nz_w = wp.uint32(0)
        steps = wp.int64(0)
        jumps = wp.int64(0)
        jumped = wp.int64(0)
        refused = wp.int64(0)
        for _ in range(nx + ny + nz + 3):
            if w.alive == 0:
                break
            if wp.static(count):
                steps += wp.int64(1)
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
            full = seen == FULL and stop_w == wp.uint32(0)
            i0 = w.i
            j0 = w.j
            k0 = w.k
            w = step_or_skip(w, full, o, d, s, sf, nx, ny, nz)
            if wp.static(count):
                if full:
                    c = wp.abs(w.i - i0) + wp.abs(w.j - j0) + wp.abs(w.k - k0)
                    if c > 1:
                        jumps += wp.int64(1)
                        jumped += wp.int64(c)
                    else:
                        refused += wp.int64(1)
        if pending != wp.uint32(0):
            my_sum += flush_brick(bits, base, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        if my_sum > wp.int64(0):
            wp.atomic_add(sums, cand, my_sum)
        if wp.static(count):
            wp.atomic_add(stats, 0, steps)
            wp.atomic_add(stats, 1, jumps)
            wp.atomic_add(stats, 2, jumped)
            wp.atomic_add(stats, 3, refused)
    return eager_skip_kernel


def make_lean(maxreg=None, skip=False, ahead=False, count=False, inc=True, keep=False, lazy=False, pred=False):
    """``walk_ray_brick_eager`` with the lean address arithmetic (module docstring); ``skip``: full bricks
    jumped (``True``: a branch between the jump and the step; ``"unified"``: ``walk32_step_or_jump``,
    only with ``inc=False``); ``keep``: the brick's masks kept from its entry (so that nvcc predicates
    their load on entering a brick, as it does the bitset word's); ``ahead``: the next voxel's loads issued one step early (not combined with ``skip``); ``inc``:
    the brick word kept incrementally (``word_delta``), else recomputed from (i, j, k) in int32 each step
    (``word32``: three shifts and two multiply-adds by kernel constants, no registers of its own)."""
    if skip == "unified" and inc:
        raise ValueError("make_lean: the unified skip recomputes the word each step; pass inc=False with it")
    unified = skip == "unified"     # booleans only: Warp hashes a kernel's closure constants, and refuses str
    skip = bool(skip)
    if keep and ahead:
        raise ValueError("make_lean: keep and ahead are not combined (ahead loads before the entry is known)")
    if pred and (inc or ahead or skip or lazy):
        raise ValueError("make_lean: pred is lean32's plain body (inc=False, no ahead, skip or lazy)")
    if lazy and (inc or ahead or skip):
        raise ValueError("make_lean: lazy is lean32's plain body (inc=False, no ahead, no skip)")
    if skip and ahead:
        raise ValueError("make_lean: skip and ahead are not combined (the jump needs the entry word before "
                         "the step, which ahead loads after it); pick one")

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def lean_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                    pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                    nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                    masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                    words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                    sums: wp.array(dtype=wp.int64), stats: wp.array(dtype=wp.int64)):
        tid = wp.tid()
        n = sensor_dirs.shape[0]
        rig = tid / n
        cand = rig / n_lidars
        o = pos[rig]
        d = rot[rig] * sensor_dirs[tid - rig * n]
        sf = wp.float32(s)
        w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
        base = wp.int64(cand) * words_per_candidate
        cbits = word_address(bits, base)
        wsx = wp.int32(0)
        wsy = wp.int32(0)
        wsz = wp.int32(0)
        if wp.static(inc):
            wsx = bny * bnz * w.si
            wsy = bnz * w.sj
            wsz = w.sk
        word = wp.where(w.alive != 0, word32(w, bny, bnz), 0)
        my_sum = wp.int64(0)
        cur = wp.int32(-1)
        seen = wp.uint32(0)
        pending = wp.uint32(0)
        nz_w = wp.uint32(0)
        steps = wp.int64(0)
        jumps = wp.int64(0)
        jumped = wp.int64(0)
        refused = wp.int64(0)
        m = wp.uint64(0)
        fresh = wp.uint32(0)
        if wp.static(ahead):
            m = load_mask(masks64, word)
            fresh = load_word(cbits, word)
        for _ in range(nx + ny + nz + 3):
            if w.alive == 0:
                break
            if wp.static(count):
                steps += wp.int64(1)
            if wp.static(not inc and not ahead):
                word = word32(w, bny, bnz)
            change = word != cur
            if wp.static(lazy):
                # the brick left: the bits this ray visited there, less those already set when it entered
                if change and (pending & ~seen) != wp.uint32(0):
                    my_sum += flush_brick32(cbits, cur, pending & ~seen, nz_w, bny, bnz, ny, nz, weights)
            elif wp.static(pred):
                # the common flush (no entropy among the bits) as one predicated reduction; only the rare
                # one branches
                send = change and pending != wp.uint32(0)
                rare = send and (pending & nz_w) != wp.uint32(0)
                red_or_if(cbits, cur, pending, send and not rare)
                if rare:
                    my_sum += flush_entropy32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            elif change and pending != wp.uint32(0):
                my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            bit = wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))
            wcur = word
            i0 = w.i
            j0 = w.j
            k0 = w.k
            if wp.static(ahead):
                # step first and issue the next voxel's loads; this voxel's masks came one step earlier
                w = walk32_next_lean(w, o, d, s, sf, nx, ny, nz)
                if wp.static(inc):
                    word = word + word_delta(i0, j0, k0, w, wsx, wsy, wsz)
                else:
                    word = word32(w, bny, bnz)
                nxt = wp.where(w.alive != 0, word, wcur)
                m_next = load_mask(masks64, nxt)
                fresh_next = load_word(cbits, nxt)
            elif wp.static(lazy):
                # the snapshot is loaded on entering a brick and used only when the ray leaves it
                if wp.static(keep):
                    m = load_mask_if(masks64, wcur, change, m)
                else:
                    m = load_mask(masks64, wcur)
                seen = load_word_if(cbits, wcur, change, seen)
            elif wp.static(keep):
                m = load_mask_if(masks64, wcur, change, m)
                fresh = load_word(cbits, wcur)
            else:
                m = load_mask(masks64, wcur)
                fresh = load_word(cbits, wcur)
            # keep: m is the masks word loaded on the brick's entry (load_mask_if), so a step within the
            # brick need not wait for L1
            stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
            nz_w = wp.uint32(m >> wp.uint64(32))
            if wp.static(lazy):
                pending = wp.where(change, wp.uint32(0), pending) | bit
            else:
                seen = wp.where(change, fresh, seen)
                pending = wp.where(change, wp.uint32(0), pending)
                pending = pending | (bit & ~seen)
                seen = seen | bit
            cur = wcur
            if (stop_w & bit) != wp.uint32(0):
                break
            if wp.static(ahead):
                m = m_next
                fresh = fresh_next
            elif wp.static(skip):
                full = seen == FULL and stop_w == wp.uint32(0)
                if wp.static(unified):
                    w = walk32_step_or_jump(w, full, o, d, s, sf, nx, ny, nz)
                else:
                    w = step_or_skip_lean(w, full, o, d, s, sf, nx, ny, nz)
                if wp.static(inc):
                    if full:
                        # a jump moves coordinates by more than one: the word from the new voxel
                        word = word32(w, bny, bnz)
                    else:
                        word = word + word_delta(i0, j0, k0, w, wsx, wsy, wsz)
                if wp.static(count):
                    if full:
                        c = wp.abs(w.i - i0) + wp.abs(w.j - j0) + wp.abs(w.k - k0)
                        if c > 1:
                            jumps += wp.int64(1)
                            jumped += wp.int64(c)
                        else:
                            refused += wp.int64(1)
            else:
                w = walk32_next_lean(w, o, d, s, sf, nx, ny, nz)
                if wp.static(inc):
                    word = word + word_delta(i0, j0, k0, w, wsx, wsy, wsz)
        if wp.static(lazy):
            pending = pending & ~seen
        if pending != wp.uint32(0):
            my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        if my_sum > wp.int64(0):
            wp.atomic_add(sums, cand, my_sum)
        if wp.static(count):
            wp.atomic_add(stats, 0, steps)
            wp.atomic_add(stats, 1, jumps)
            wp.atomic_add(stats, 2, jumped)
            wp.atomic_add(stats, 3, refused)
    return lean_kernel


def make_walk_only(maxreg=None, count=False, lean=False):
    """The floor diagnostic: today's step and stop read, nothing else; sums get step counts (wrong on
    purpose, never compared). ``lean``: lean32's step, word and mask load instead (its own floor)."""

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def walk_only_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                         pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                         nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                         masks64: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                         words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
                         sums: wp.array(dtype=wp.int64), stats: wp.array(dtype=wp.int64)):
        tid = wp.tid()
        n = sensor_dirs.shape[0]
        rig = tid / n
        cand = rig / n_lidars
        o = pos[rig]
        d = rot[rig] * sensor_dirs[tid - rig * n]
        sf = wp.float32(s)
        w = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
        steps = wp.int64(0)
        for _ in range(nx + ny + nz + 3):
            if w.alive == 0:
                break
            steps += wp.int64(1)
            if wp.static(lean):
                stop_w = wp.uint32(load_mask(masks64, word32(w, bny, bnz)) & wp.uint64(0xFFFFFFFF))
                bit = wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))
                if (stop_w & bit) != wp.uint32(0):
                    break
                w = walk32_next_lean(w, o, d, s, sf, nx, ny, nz)
            else:
                stop_w = wp.uint32(masks64[brick_word(w, bny, bnz)] & wp.uint64(0xFFFFFFFF))
                if (stop_w & brick_bit(w)) != wp.uint32(0):
                    break
                w = walk32_next_sel(w, o, d, s, sf, nx, ny, nz)
        if steps > wp.int64(0):
            wp.atomic_add(sums, cand, steps)      # keeps the walk live; wrong sums on purpose
        if wp.static(count):
            wp.atomic_add(stats, 0, steps)
    return walk_only_kernel
