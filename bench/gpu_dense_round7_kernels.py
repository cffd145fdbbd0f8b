"""Warp kernels of the dense-rig study's seventh round (``gpu_dense_variants.py``, issue 17, goal 3): the shipped
``score_kernel_gpu`` without the grid test at the head of its loop.

The shipped loop starts every step with ``inside``: three unsigned compares of (i, j, k) against the grid's
shape, plus the loop counter's own compare. Only two things end a walk there: a walk that never started
(``walk_from`` gives it ``i = DEAD``) and the float64 step's end of the segment (``exact_step`` sets
``i = DEAD`` when the next crossing is at or after ``t1d``). A walk never steps out of the grid before that,
so the three compares never decide anything else:

* The float64 step crosses the grid's far plane along an axis (b = n for a positive step, b = 0 for a
  negative one) at ``(float64(b) * s - o) / d`` (``next_t``). ``_clip_grid`` computes the same axis's exit as
  ``(float64(n) * s - o) / d`` and ``(0.0 - o) / d`` (``_axis_clip``): the same operands in the same order
  (no FMA contraction), so the same bits, and ``t1d`` is at most that exit. So the crossing of a far plane is
  never below ``t1d``, and the step that would leave the grid is the one that ends the walk.
* The float32 step is taken only where its decision is certain, i.e. where the float64 step would take the
  same axis before the segment's end (``certain_step``; the bound is the one ``kernels.walk32_next`` and
  OpenCL's ``grid.cl`` use). So it never leaves the grid either.
* A start voxel is clamped into the grid (``_start_index``).

The variants, each at the shipped 64-register cap unless named otherwise:

* ``head1``: the loop runs while ``i >= 0`` (one compare; ``DEAD`` is -1), no counter.
* ``headless``: no test at the head at all: a dead walk is caught before the loop and after each float64
  step, the one place that ends a segment; the common (float32) step then ends in an unconditional jump
  back. No counter.
* ``early``: ``head1`` with the step to the next voxel taken right after the current voxel's two loads are
  issued, before their values are used (the stop test, the bitset bookkeeping): the step is register work
  that needs neither load, so it fills the loads' latency instead of following it. nvcc does not move it
  above the stop test's branch itself. A walk that stops discards the step.
* ``prefetch`` / ``prefetch-l2``: ``head1`` with, on entering a brick, a prefetch hint (PTX ``prefetch.global.L1``
  or ``.L2``: no register, no fault) for the masks and the bitset word of the brick one ahead along the ray's
  dominant axis, so that the loads on entering it, which the step then waits for, may hit in L1.
* ``nosum`` / ``nosum-head1``: ``headless`` / ``head1`` without the ray's running sum in the loop: a flush that
  finds bits with entropy adds their weights to the candidate's sum at once (an ``atomic_add``), which frees
  the two registers of the int64 sum (offline: 74 instructions and 1 spill load per common step).
* ``headless-guard``: ``headless`` with the shipped loop's iteration bound kept (``nx + ny + nz + 3``), a
  safety net that the argument above says never fires.

Each visits the shipped kernel's voxels in the same order with the same decisions (the step bodies are the
shipped ``certain_step`` and ``exact_step``), so sums and counts must equal the shipped kernel's: the study
checks that on every launch, and tests/test_dense_variants.py on Warp's CPU.
"""

from __future__ import annotations

import warp as wp

from gpu_dense_lean_kernels import flush_brick32
from gpu_dense_variants_kernels import OPTS
from place3d_kernels.backends.warp.kernels import walk32_begin
from place3d_kernels.backends.warp.score_gpu import (WalkGPU, certain_step, exact_step, load_mask, load_word,
                                                     next_step, walk_from, word_address)

@wp.func
def word32(w: WalkGPU, bny: wp.int32, bnz: wp.int32) -> wp.int32:
    # the 4 x 4 x 2 brick's word within the candidate's bitset (kernels.brick_word in int32): the shipped
    # kernel's until the ninth round's flat bricks
    return ((w.i >> 2) * bny + (w.j >> 2)) * bnz + (w.k >> 1)


MODES = ("head1", "headless", "headless-guard", "early", "prefetch", "prefetch-l2", "nosum", "nosum-head1")


@wp.func_native("""
#if defined(__CUDA_ARCH__)
asm volatile("prefetch.global.L1 [%0];" :: "l"(p + (unsigned long long)i * b));
#endif
""")
def prefetch_l1(p: wp.uint64, i: wp.int32, b: wp.int32):
    """A hint that bytes [p + i b, ...) will be read soon (PTX ``prefetch.global.L1``; no register, no fault)."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
asm volatile("prefetch.global.L2 [%0];" :: "l"(p + (unsigned long long)i * b));
#endif
""")
def prefetch_l2(p: wp.uint64, i: wp.int32, b: wp.int32):
    """``prefetch_l1`` into L2 only."""
    ...


@wp.func_native("""
return (wp::uint64)(arr.data);
""")
def mask_address(arr: wp.array(dtype=wp.uint64)) -> wp.uint64:
    """The masks' first byte."""
    ...


def make_headless(maxreg=64, mode="headless"):
    """The shipped ``score_kernel_gpu`` with the loop head of ``mode`` (module docstring). Inputs: the shipped
    kernel's, then ``stats`` (unused, as the study's other kernels take it)."""
    if mode not in MODES:
        raise ValueError(f"mode {mode!r}: one of {MODES}")
    guard = mode == "headless-guard"
    early = mode == "early"
    nosum = mode.startswith("nosum")
    pf = mode.startswith("prefetch")
    pf2 = mode == "prefetch-l2"
    head1 = mode in ("head1", "early", "nosum-head1") or pf

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def headless_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
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
        w0 = walk32_begin(o, d, t_max, s, sf, nx, ny, nz)
        t1d = w0.t1d
        w = walk_from(w0)
        cbits = word_address(bits, wp.int64(cand) * words_per_candidate)
        my_sum = wp.int64(0)
        cur = wp.int32(-1)
        seen = wp.uint32(0)
        pending = wp.uint32(0)
        nz_w = wp.uint32(0)
        # steps left: the guard's bound (headless-guard), else 1 for the whole walk (a loop-invariant test)
        # prefetch: the brick one ahead along the ray's dominant axis, hinted on entering each brick
        adx = wp.abs(d[0])
        ady = wp.abs(d[1])
        adz = wp.abs(d[2])
        ahead = wp.where(adx >= ady and adx >= adz, w.si * bny * bnz, wp.where(ady >= adz, w.sj * bnz, w.sk))
        last = wp.int32(words_per_candidate) - 1
        mbase = mask_address(masks64)
        left = wp.int32(0)
        if w.i >= 0:
            left = wp.where(wp.static(guard), nx + ny + nz + 3, 1)
        while left > 0:
            if wp.static(guard):
                left = left - 1
            if wp.static(head1):
                if w.i < 0:
                    break
            word = word32(w, bny, bnz)
            change = word != cur
            if change and pending != wp.uint32(0):
                if wp.static(nosum):
                    add = flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
                    if add > wp.int64(0):
                        wp.atomic_add(sums, (wp.tid() / n) / n_lidars, add)
                else:
                    my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            m = load_mask(masks64, word)
            fresh = load_word(cbits, word)
            if wp.static(pf):
                if change:
                    nxt = wp.clamp(word + ahead, 0, last)
                    if wp.static(pf2):
                        prefetch_l2(mbase, nxt, 8)
                        prefetch_l2(cbits, nxt, 4)
                    else:
                        prefetch_l1(mbase, nxt, 8)
                        prefetch_l1(cbits, nxt, 4)
            cur = word
            bit = wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))
            if wp.static(early):
                # the next voxel first: the step needs none of the loads just issued, so it runs while they
                # are in flight (a walk that stops here discards it; the float64 step's DEAD ends the loop
                # at its head, after this voxel's bookkeeping)
                w = next_step(w, o, d, t1d, s, sf)
            stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
            nz_w = wp.uint32(m >> wp.uint64(32))
            seen = wp.where(change, fresh, seen)
            pending = wp.where(change, wp.uint32(0), pending)
            pending = pending | (bit & ~seen)
            seen = seen | bit
            if (stop_w & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
                break
            if not wp.static(early):
                xa, ya, za, go = certain_step(w)
                if go:
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
                else:
                    w = exact_step(w, o, d, t1d, s, sf)
                    if not wp.static(head1):
                        if w.i < 0:
                            break
        if pending != wp.uint32(0):
            my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        if my_sum > wp.int64(0):
            wp.atomic_add(sums, cand, my_sum)
    return headless_kernel
