"""Warp kernels of the dense-rig study's ninth round (``gpu_dense_variants.py``, issue 17, goal 3): bricks of
64 voxels in one 64-bit word.

The thirteenth session's near-field study found the score kernel's time in the far field, where each lane's
step touches a brick no other lane has loaded: every brick a ray enters costs an L2 trip for the brick's masks,
one for the candidate's bitset word, and (with new bits) an atomic on leaving. The shipped brick is 4 x 4 x 2
voxels (32 bits). Along a ray of direction d the number of bricks entered per unit length is about
``|dx| / BX + |dy| / BY + |dz| / BZ`` (voxel units); the dense LiDAR's rays are mostly near horizontal
(elevations -25..15 degrees), and Nsight saw 27 % of lanes enter a new brick per step, as that formula gives
for 4 x 4 x 2 (0.37 bricks per voxel length over 1.37 steps). A 64-bit brick enters fewer: 4 x 4 x 4 about
0.34, 8 x 4 x 2 about 0.29 (for azimuths spread evenly), 8 x 8 x 1 about 0.26. The price is registers: the
snapshot, the pending bits and the brick's nonzero-weight bits are 64-bit, three more registers live across
steps at the 64-register cap.

Variants (``b64-<BX>x<BY>x<BZ>[-late]-rN``):

* the brick's stop and nonzero-weight words side by side (16 bytes per brick, one vector load per step, kept on
  entering the brick, as the shipped kernel's one 8-byte load);
* ``-late``: only the stop word is loaded per step; the nonzero-weight word is read at the flush, which frees
  its two registers (the flush waits for that load, an L1 hit in the common case: the stop word beside it
  was just read);
* the candidate's bitset is the same bytes (32 MB per candidate on the 0.05 m grid) in 64-bit words, counted
  by the shipped count kernel through a 32-bit view.

The walk is the shipped one (``certain_step``, ``exact_step``, the same loop head), so each variant visits the
same voxels with the same decisions and sums the same weights: the study checks sums and counts against the
shipped kernel's on every launch, and tests/test_dense_variants.py on Warp's CPU.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from gpu_dense_variants_kernels import OPTS
from place3d_kernels.backends.warp.kernels import walk32_begin
from place3d_kernels.backends.warp.score_gpu import (WalkGPU, atomic_or_word, load_mask, load_word, next_step,
                                                     walk_from, word_address)

LAYOUTS = ((2, 2, 2), (3, 2, 1), (2, 3, 1), (3, 3, 0))   # log2 of (BX, BY, BZ), 64 voxels each
#: 32-voxel bricks and brick orders (slowest axis first): (2, 2, 1) "xyz" is the shipped kernel's
LAYOUTS32 = (((2, 2, 1), "xyz"), ((2, 2, 1), "zxy"), ((2, 2, 1), "zyx"), ((3, 2, 0), "zxy"), ((2, 3, 0), "zxy"),
             ((3, 2, 0), "xyz"), ((2, 3, 0), "zyx"), ((1, 3, 1), "zxy"), ((3, 1, 1), "zyx"),
             ((3, 2, 0), "zyx"), ((3, 2, 0), "xzy"), ((3, 2, 0), "yzx"), ((3, 2, 0), "yxz"),
             ((4, 1, 0), "zxy"), ((1, 4, 0), "zyx"), ((4, 1, 0), "zyx"), ((5, 0, 0), "zxy"))
#: super-blocks of 2^swz bricks (x, y, z) for the shipped 4 x 4 x 2 bricks, with the super-blocks' order
SWIZZLES = (((1, 1, 0), "xyz"), ((1, 1, 1), "xyz"), ((1, 1, 0), "zxy"), ((1, 1, 1), "zxy"), ((2, 1, 0), "xyz"),
            ((2, 2, 0), "xyz"), ((2, 2, 1), "xyz"))


def layout_name(lx: int, ly: int, lz: int) -> str:
    return f"{1 << lx}x{1 << ly}x{1 << lz}"


def brick_shape64(shape, layout) -> tuple[int, int, int]:
    """Bricks along x, y, z of a grid of ``shape`` voxels for bricks of 2^layout voxels."""
    return tuple(-(-int(n) // (1 << b)) for n, b in zip(shape, layout))


def pack_bricks(mask: np.ndarray, shape, layout) -> np.ndarray:
    """A flat per-voxel boolean mask (C order over ``shape``) packed into one word per brick of 2^``layout``
    voxels (uint32 for 32 voxels, uint64 for 64), bricks in x-major order ``(bi * by + bj) * bz + bk``
    (``brick_words`` renumbers them), bit ``(i & (BX-1)) | (j & (BY-1)) << LX | (k & (BZ-1)) << (LX+LY)``."""
    nx, ny, nz = (int(v) for v in shape)
    ex, ey, ez = (1 << b for b in layout)
    bx, by, bz = brick_shape64(shape, layout)
    m = np.zeros((bx * ex, by * ey, bz * ez), dtype=bool)
    m[:nx, :ny, :nz] = np.asarray(mask).reshape(nx, ny, nz)
    # (bx, ii, by, jj, bz, kk) -> (bx, by, bz, kk, jj, ii): a brick's voxels in the order of their bit numbers
    b = m.reshape(bx, ex, by, ey, bz, ez).transpose(0, 2, 4, 5, 3, 1)
    width = ex * ey * ez
    b = np.packbits(b.reshape(-1, width), axis=1, bitorder="little")
    return b.view("<u4" if width == 32 else "<u8").reshape(-1).astype(np.uint32 if width == 32 else np.uint64)


def order_counts(shape, layout, order: str, swz=(0, 0, 0)) -> tuple[int, int]:
    """(n1, n2): super-blocks of 2^``swz`` bricks (bricks where swz is 0) along the second and third axes of
    ``order``."""
    nb = dict(zip("xyz", (-(-b // (1 << a)) for b, a in zip(brick_shape64(shape, layout), swz))))
    return nb[order[1]], nb[order[2]]


def brick_words(shape, layout, order: str, swz=(0, 0, 0)) -> tuple[np.ndarray, int]:
    """(word of each brick in x-major order (bx, by, bz), words in all) for bricks numbered in ``order`` with
    super-blocks of 2^``swz`` bricks: ``word = (((S0 * n1 + S1) * n2 + S2) << (a + b + c)) | kl << (a + b) |
    il << b | jl``, where (S0, S1, S2) is the super-block in ``order`` and (il, jl, kl) the brick within it
    (so the 4 words of a 32-byte sector of masks are 2 x 2 bricks in x and y where a = b = 1)."""
    bx, by, bz = brick_shape64(shape, layout)
    a, b, c = swz
    sup = dict(zip("xyz", (-(-n // (1 << e)) for n, e in zip((bx, by, bz), swz))))
    bi, bj, bk = np.meshgrid(np.arange(bx), np.arange(by), np.arange(bz), indexing="ij")
    S = {"x": bi >> a, "y": bj >> b, "z": bk >> c}
    n1, n2 = sup[order[1]], sup[order[2]]
    word = ((S[order[0]] * n1 + S[order[1]]) * n2 + S[order[2]]) << (a + b + c)
    word |= ((bk & ((1 << c) - 1)) << (a + b)) | ((bi & ((1 << a) - 1)) << b) | (bj & ((1 << b) - 1))
    return word.reshape(-1), sup["x"] * sup["y"] * sup["z"] << (a + b + c)


def brick_masks64(shape, layout, nonzero: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Per brick the pair (occlusion word, nonzero-weight word), interleaved: 16 bytes a brick."""
    nzb = pack_bricks(nonzero, shape, layout)
    out = np.zeros(2 * len(nzb), dtype=np.uint64)
    out[0::2] = pack_bricks(stop, shape, layout)
    out[1::2] = nzb
    return out


def brick_masks32(shape, layout, order, nonzero: np.ndarray, stop: np.ndarray, swz=(0, 0, 0)) -> np.ndarray:
    """Per brick one uint64: occlusion bits low, nonzero-weight bits high (as the shipped ``brick_masks``
    read by ``score_kernel_gpu``), at the brick's word of ``brick_words`` (padding words zero)."""
    pair = (pack_bricks(stop, shape, layout).astype(np.uint64)
            | (pack_bricks(nonzero, shape, layout).astype(np.uint64) << np.uint64(32)))
    word, total = brick_words(shape, layout, order, swz)
    out = np.zeros(total, dtype=np.uint64)
    out[word] = pair
    return out


vec2u64 = wp.types.vector(length=2, dtype=wp.uint64)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
const ulonglong2 v = reinterpret_cast<const ulonglong2*>(arr.data)[i];
return wp::vec_t<2, wp::uint64>(v.x, v.y);
#else
const wp::uint64* p = reinterpret_cast<const wp::uint64*>(arr.data) + 2 * (long long)i;
return wp::vec_t<2, wp::uint64>(p[0], p[1]);
#endif
""")
def load_pair(arr: wp.array(dtype=wp.uint64), i: wp.int32) -> vec2u64:
    """Brick ``i``'s (occlusion, nonzero-weight) words in one 16-byte load."""
    ...


@wp.func_native("""
return reinterpret_cast<const unsigned long long*>(arr.data)[2 * (long long)i + j];
""")
def load_half(arr: wp.array(dtype=wp.uint64), i: wp.int32, j: wp.int32) -> wp.uint64:
    """Word ``j`` (0: occlusion, 1: nonzero weight) of brick ``i``."""
    ...


@wp.func_native("""
wp::uint64 p = (wp::uint64)(arr.data + base);
#if defined(__CUDA_ARCH__)
asm("mov.b64 %0, %0;" : "+l"(p));
#endif
return p;
""")
def word_address64(arr: wp.array(dtype=wp.uint64), base: wp.int64) -> wp.uint64:
    """Address of ``arr[base]`` (as score_gpu.word_address, for 64-bit words)."""
    ...


@wp.func_native("""
const unsigned long long* q = reinterpret_cast<const unsigned long long*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
#endif
return *q;
""")
def load_word64(p: wp.uint64, i: wp.int32) -> wp.uint64:
    """Bitset word ``i`` after address ``p``."""
    ...


@wp.func_native("""
unsigned long long* q = reinterpret_cast<unsigned long long*>(p) + i;
#if defined(__CUDA_ARCH__)
__builtin_assume(__isGlobal(q));
return atomicOr(q, (unsigned long long)v);
#else
const unsigned long long old = *q;
*q = old | v;
return old;
#endif
""")
def atomic_or_word64(p: wp.uint64, i: wp.int32, v: wp.uint64) -> wp.uint64:
    """``atomic_or`` on 64-bit bitset word ``i`` after address ``p``; returns the old word."""
    ...


def make_b64(layout=(2, 2, 2), maxreg=64, late=False):
    """The shipped ``score_kernel_gpu`` on 64-voxel bricks of 2^``layout`` voxels (module docstring). Inputs:
    the shipped kernel's, with the masks as ``brick_masks64``'s pairs and the bitset in uint64 words (bny,
    bnz and words_per_candidate counted in those bricks), then ``stats`` (unused)."""
    if sum(layout) != 6 or min(layout) < 0:
        raise ValueError(f"layout {layout}: log2 brick sides must sum to 6 (64 voxels a brick)")
    lx, ly, lz = layout
    mx, my, mz = (1 << lx) - 1, (1 << ly) - 1, (1 << lz) - 1

    @wp.func
    def word64(w: WalkGPU, bny: wp.int32, bnz: wp.int32) -> wp.int32:
        return ((w.i >> wp.static(lx)) * bny + (w.j >> wp.static(ly))) * bnz + (w.k >> wp.static(lz))

    @wp.func
    def flush64(p: wp.uint64, word: wp.int32, pending: wp.uint64, nz_w: wp.uint64, bny: wp.int32, bnz: wp.int32,
                ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)) -> wp.int64:
        # score_gpu.flush_brick32 on a 64-bit word: one atomic_or; only where some bits have entropy is the old
        # word waited for, and the weights of the bits this ray set first added
        add = wp.int64(0)
        if (pending & nz_w) != wp.uint64(0):
            old = atomic_or_word64(p, word, pending)
            m = pending & ~old & nz_w
            uw = wp.uint32(word)
            bk = wp.int32(uw % wp.uint32(bnz))
            r = uw / wp.uint32(bnz)
            bj = wp.int32(r % wp.uint32(bny))
            bi = wp.int32(r / wp.uint32(bny))
            while m != wp.uint64(0):
                b = wp.bit_count((m & (~m + wp.uint64(1))) - wp.uint64(1))     # index of the lowest set bit
                i = (bi << wp.static(lx)) + (b & wp.static(mx))
                j = (bj << wp.static(ly)) + ((b >> wp.static(lx)) & wp.static(my))
                k = (bk << wp.static(lz)) + (b >> wp.static(lx + ly))
                add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
                m = m & (m - wp.uint64(1))
        else:
            atomic_or_word64(p, word, pending)
        return add

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def b64_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                   pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                   nx: wp.int32, ny: wp.int32, nz: wp.int32, bny: wp.int32, bnz: wp.int32,
                   masks: wp.array(dtype=wp.uint64), weights: wp.array(dtype=wp.int64),
                   words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint64),
                   sums: wp.array(dtype=wp.int64), stats: wp.array(dtype=wp.int64)):
        tid = wp.tid()
        n = sensor_dirs.shape[0]
        rig = tid / n
        cand = rig / n_lidars
        o = pos[rig]
        d = rot[rig] * sensor_dirs[tid - rig * n]
        sf = wp.float32(s)
        w0 = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
        t1d = w0.t1d
        w = walk_from(w0)
        cbits = word_address64(bits, wp.int64(cand) * words_per_candidate)
        my_sum = wp.int64(0)
        cur = wp.int32(-1)
        seen = wp.uint64(0)
        pending = wp.uint64(0)
        nz_w = wp.uint64(0)
        for _ in range(nx + ny + nz + 3):
            if not (wp.uint32(w.i) < wp.uint32(nx) and wp.uint32(w.j) < wp.uint32(ny)
                    and wp.uint32(w.k) < wp.uint32(nz)):
                break
            word = word64(w, bny, bnz)
            change = word != cur
            if change and pending != wp.uint64(0):
                if wp.static(late):
                    nz_w = load_half(masks, cur, 1)
                my_sum += flush64(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            stop_w = wp.uint64(0)
            if wp.static(late):
                stop_w = load_half(masks, word, 0)
            else:
                mp = load_pair(masks, word)    # the flush of the brick before has used its nz_w
                stop_w = mp[0]
                nz_w = mp[1]
            fresh = load_word64(cbits, word)
            seen = wp.where(change, fresh, seen)
            pending = wp.where(change, wp.uint64(0), pending)
            cur = word
            bit = wp.uint64(1) << wp.uint64((w.i & wp.static(mx)) | ((w.j & wp.static(my)) << wp.static(lx))
                                            | ((w.k & wp.static(mz)) << wp.static(lx + ly)))
            pending = pending | (bit & ~seen)
            seen = seen | bit
            if (stop_w & bit) != wp.uint64(0):      # occlusion: the ray ends after this voxel
                break
            w = next_step(w, o, d, t1d, s, sf)
        if pending != wp.uint64(0):
            if wp.static(late):
                nz_w = load_half(masks, cur, 1)
            my_sum += flush64(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        if my_sum > wp.int64(0):
            wp.atomic_add(sums, cand, my_sum)
    return b64_kernel


def make_b32(layout=(2, 2, 1), order="xyz", maxreg=64, swz=(0, 0, 0), head1=False, block_dim=128, nosum=False):
    """The shipped ``score_kernel_gpu`` on 32-voxel bricks of 2^``layout`` voxels numbered in ``order``
    (slowest axis first), in super-blocks of 2^``swz`` bricks (``brick_words``). Inputs: the shipped kernel's
    with ``bny``, ``bnz`` replaced by ``order_counts``'s (n1, n2) and the masks from ``brick_masks32``, then
    ``stats`` (unused). (2, 2, 1) "xyz" without super-blocks is the shipped kernel, rebuilt: the control.
    ``head1``: the loop runs while ``i >= 0`` (round seven's head: the walk never leaves the grid before its
    segment ends, gpu_dense_round7_kernels.py) and the step bound; "free": without the bound; ``block_dim``:
    the launch's threads per block; ``nosum``: no running sum, a flush's weights added to the candidate's sum at
    once (round seven's ``nosum``)."""
    if sum(layout) != 5 or min(layout) < 0:
        raise ValueError(f"layout {layout}: log2 brick sides must sum to 5 (32 voxels a brick)")
    if sorted(order) != ["x", "y", "z"]:
        raise ValueError(f"order {order!r}: a permutation of 'xyz'")
    lx, ly, lz = layout
    mx, my, mz = (1 << lx) - 1, (1 << ly) - 1, (1 << lz) - 1
    o0, o1, o2 = ("xyz".index(a) for a in order)
    sa, sb, sc = swz
    ss = sa + sb + sc

    @wp.func
    def word_o(w: WalkGPU, n1: wp.int32, n2: wp.int32) -> wp.int32:
        c = wp.vec3i(w.i >> wp.static(lx + sa), w.j >> wp.static(ly + sb), w.k >> wp.static(lz + sc))
        sup = ((c[wp.static(o0)] * n1 + c[wp.static(o1)]) * n2 + c[wp.static(o2)]) << wp.static(ss)
        if wp.static(ss == 0):
            return sup
        low = ((((w.k >> wp.static(lz)) & wp.static((1 << sc) - 1)) << wp.static(sa + sb))
               | (((w.i >> wp.static(lx)) & wp.static((1 << sa) - 1)) << wp.static(sb))
               | ((w.j >> wp.static(ly)) & wp.static((1 << sb) - 1)))
        return sup | low

    @wp.func
    def flush_o(p: wp.uint64, word: wp.int32, pending: wp.uint32, nz_w: wp.uint32, n1: wp.int32, n2: wp.int32,
                ny: wp.int32, nz: wp.int32, weights: wp.array(dtype=wp.int64)) -> wp.int64:
        # score_gpu.flush_brick32 with this numbering's decode
        add = wp.int64(0)
        if (pending & nz_w) != wp.uint32(0):
            old = atomic_or_word(p, word, pending)
            m = pending & ~old & nz_w
            uw = wp.uint32(word) >> wp.uint32(ss)
            low = word & wp.static((1 << ss) - 1)
            r2 = wp.int32(uw % wp.uint32(n2))
            r = uw / wp.uint32(n2)
            r1 = wp.int32(r % wp.uint32(n1))
            r0 = wp.int32(r / wp.uint32(n1))
            c = wp.vec3i(0, 0, 0)
            c[wp.static(o0)] = r0
            c[wp.static(o1)] = r1
            c[wp.static(o2)] = r2
            c[0] = (c[0] << wp.static(sa)) | ((low >> wp.static(sb)) & wp.static((1 << sa) - 1))
            c[1] = (c[1] << wp.static(sb)) | (low & wp.static((1 << sb) - 1))
            c[2] = (c[2] << wp.static(sc)) | (low >> wp.static(sa + sb))
            while m != wp.uint32(0):
                b = wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1))     # index of the lowest set bit
                i = (c[0] << wp.static(lx)) + (b & wp.static(mx))
                j = (c[1] << wp.static(ly)) + ((b >> wp.static(lx)) & wp.static(my))
                k = (c[2] << wp.static(lz)) + (b >> wp.static(lx + ly))
                add += weights[(wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)]
                m = m & (m - wp.uint32(1))
        else:
            atomic_or_word(p, word, pending)
        return add

    @wp.kernel(module="unique", module_options=dict(OPTS, block_dim=block_dim), cuda_max_registers=maxreg)
    def b32_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                   pos: wp.array(dtype=wp.vec3d), n_lidars: wp.int32, t_max: wp.float64, s: wp.float64,
                   nx: wp.int32, ny: wp.int32, nz: wp.int32, n1: wp.int32, n2: wp.int32,
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
        w0 = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
        t1d = w0.t1d
        w = walk_from(w0)
        cbits = word_address(bits, wp.int64(cand) * words_per_candidate)
        my_sum = wp.int64(0)
        cur = wp.int32(-1)
        seen = wp.uint32(0)
        pending = wp.uint32(0)
        nz_w = wp.uint32(0)
        # the loop's bound: nx + ny + nz + 3 steps (the shipped loop's), or none ("free": left stays 1)
        left = wp.int32(1)
        if wp.static(head1 != "free"):
            left = nx + ny + nz + 3
        while left > 0:
            if wp.static(head1 != "free"):
                left = left - 1
            if wp.static(bool(head1)):
                if w.i < 0:
                    break
            else:
                if not (wp.uint32(w.i) < wp.uint32(nx) and wp.uint32(w.j) < wp.uint32(ny)
                        and wp.uint32(w.k) < wp.uint32(nz)):
                    break
            word = word_o(w, n1, n2)
            change = word != cur
            if change and pending != wp.uint32(0):
                add = flush_o(cbits, cur, pending, nz_w, n1, n2, ny, nz, weights)
                if wp.static(nosum):
                    if add > wp.int64(0):
                        wp.atomic_add(sums, (wp.tid() / n) / n_lidars, add)
                else:
                    my_sum += add
            m = load_mask(masks64, word)
            fresh = load_word(cbits, word)
            stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
            nz_w = wp.uint32(m >> wp.uint64(32))
            seen = wp.where(change, fresh, seen)
            pending = wp.where(change, wp.uint32(0), pending)
            cur = word
            bit = wp.uint32(1) << wp.uint32((w.i & wp.static(mx)) | ((w.j & wp.static(my)) << wp.static(lx))
                                            | ((w.k & wp.static(mz)) << wp.static(lx + ly)))
            pending = pending | (bit & ~seen)
            seen = seen | bit
            if (stop_w & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
                break
            w = next_step(w, o, d, t1d, s, sf)
        if pending != wp.uint32(0):
            my_sum += flush_o(cbits, cur, pending, nz_w, n1, n2, ny, nz, weights)
        if my_sum > wp.int64(0):
            wp.atomic_add(sums, cand, my_sum)
    return b32_kernel
