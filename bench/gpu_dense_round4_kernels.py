"""Warp kernels of the dense-rig study's fourth round (``gpu_dense_variants.py``, issue 17, goal 3): the
shipped ``score_kernel_gpu`` (round three's lean32) with a smaller walk state, so that a 48- or 56-register
cap spills less, and a shorter common step.

``make_lean32x`` builds ``lean32x`` variants: the shipped kernel's loop, loads and flush, walking a
``Walk32x`` instead of a ``Walk32``. ``Walk32x`` drops the fields the common step never needs:

* ``alive``: a walk that has ended has ``i = -1`` (``DEAD``), and the loop's head tests the voxel against the
  grid with three unsigned compares (as the shipped step did at its end), so the step writes no flag: the
  shipped step's ``alive = where(out, 0, alive)`` and the head's ``alive == 0`` go, and so does the spill
  store nvcc issued for ``alive`` on every step at the 64-register cap. A walk ends in the same places:
  where the shipped step's coordinate left the grid, this one's leaves it too (the same coordinates); where
  the float64 step ended the segment (``tn >= t1d``), this one sets ``DEAD``.
* ``exact`` (every step in float64, for rays with a direction component below ``DIR_SMALL``): such a walk has
  ``t1 = -1`` and ``tx = ty = tz = tol = 0``; the common step's test then always sends it to the float64
  step (``lim = 0`` and ``t1 <= lim``), which keeps those float32 fields as they are. Any other walk has
  ``t1 = float32(t1d - t0) >= 0`` (``t1d > t0``), so ``t1 < 0`` tells the two apart, and its comparisons
  are the shipped ones, on the same operands.
* ``t1d`` (the float64 segment end) leaves the struct but stays a local of the kernel, passed to the float64
  step. Recomputing it there instead (a copy of kernels._clip_grid, same bits) was tried and is worse:
  the clip's three float64 divisions on the rare path raised register pressure so that nvcc spilled hot
  values (sm_90, 64-register cap: 13 spill loads on the common step against 2, 94 instructions against 81).

With ``med=True`` (``lean32xm``) the common step decides by the minimum and the median of (tx, ty, tz),
fewer instructions than the shipped chain of strict compares and selects, and the same decision. Proof: the
shipped test picks tmin by ``tx < ty and tx < tz``, then ``ty < tz``, else z; each branch's pick is the
smallest value (e.g. not xa and ty < tz: tx >= ty, or else tx >= tz > ty, a contradiction), and o1, o2 are
the two other values, ties kept; so "o1 > lim and o2 > lim" is "median > lim". min and max return one of
their operands unchanged (no NaN arises: a float32 walk's crossings are finite, a float64-only walk's are
0), so lim = tmin + tol has the same operands and bits. Where the test passes the minimum is unique
(median > tmin + tol >= tmin), so ``tx == tmin`` picks the shipped axis. tests/test_dense_variants.py
fails if the tolerance or the segment-end test is dropped from it.

With ``reload=True`` the float64 step also reloads the ray (``o = pos[rig]``, ``d = rot[rig] * dir``, the
kernel's own expressions, so the same bits) instead of keeping o and d (12 registers) live across the
loop; rig and the direction's index come from the thread index.

Every float32 and float64 expression that decides a step is the shipped one, with the same operands in the
same order (fuse_fp off), so the walk visits the same voxels; tests/test_dense_variants.py steps
``walk32x_next`` against ``walk32_next`` field by field and runs the kernels against the shipped one.
"""

from __future__ import annotations

import warp as wp

from gpu_dense_lean_kernels import flush_brick32, load_mask, load_word, word_address
from gpu_dense_variants_kernels import OPTS
from place3d_kernels.backends.warp.kernels import INF64, Walk32, walk32_begin

DEAD = wp.constant(wp.int32(-1))       # i of a walk that has ended


@wp.struct
class Walk32x:
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
    t1: wp.float32         # segment end after t0; -1: every step in float64 (Walk32.exact)
    tol: wp.float32        # certainty threshold (0 for a float64-only walk)


@wp.func
def walk32x_from(a: Walk32) -> Walk32x:
    # the shipped walk's state in the smaller struct (the same values; the flags become markers)
    w = Walk32x()
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
        w.t1 = wp.float32(-1.0)
        w.tx = wp.float32(0.0)
        w.ty = wp.float32(0.0)
        w.tz = wp.float32(0.0)
        w.tol = wp.float32(0.0)
    return w


@wp.func
def walk32x_begin(o: wp.vec3d, d: wp.vec3d, t_end: wp.float64, s: wp.float64, sf: wp.float32, nx: wp.int32,
                  ny: wp.int32, nz: wp.int32) -> Walk32x:
    return walk32x_from(walk32_begin(o, d, t_end, s, sf, nx, ny, nz))


@wp.func
def inside(w: Walk32x, nx: wp.int32, ny: wp.int32, nz: wp.int32) -> wp.bool:
    # the walk is on: its voxel is in the grid (a coordinate of -1, DEAD included, wraps to 2^32 - 1)
    return wp.uint32(w.i) < wp.uint32(nx) and wp.uint32(w.j) < wp.uint32(ny) and wp.uint32(w.k) < wp.uint32(nz)


# ----------------------------------------------------------------------------- float64 step
@wp.func
def next_t(i: wp.int32, step: wp.int32, o: wp.float64, d: wp.float64, s: wp.float64) -> wp.float64:
    # a copy of kernels._next_t (private there)
    if step == 0:
        return INF64
    b = i
    if step > 0:
        b = i + 1
    return (wp.float64(b) * s - o) / d


@wp.func
def walk32x_exact(w: Walk32x, o: wp.vec3d, d: wp.vec3d, t1d: wp.float64, s: wp.float64, sf: wp.float32,
                  nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32x:
    # kernels.walk32_exact on Walk32x: the reference's float64 step, to the segment end t1d
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
def ray_origin(pos: wp.array(dtype=wp.vec3d), tid: wp.int32, n: wp.int32) -> wp.vec3d:
    return pos[tid / n]


@wp.func
def ray_dir(rot: wp.array(dtype=wp.mat33d), sensor_dirs: wp.array(dtype=wp.vec3d), tid: wp.int32,
            n: wp.int32) -> wp.vec3d:
    # the kernel's d, the same expression (so the same bits)
    rig = tid / n
    return rot[rig] * sensor_dirs[tid - rig * n]


# ----------------------------------------------------------------------------- float32 step
@wp.func
def walk32x_certain(w: Walk32x):
    """The common step's decision: (xa, ya, za, go) with ``go`` where the float32 step is certain (the
    shipped walk32_next_lean's comparisons, on the same operands)."""
    xa = w.tx < w.ty and w.tx < w.tz
    ya = (not xa) and w.ty < w.tz
    za = (not xa) and (not ya)
    tmin = wp.where(xa, w.tx, wp.where(ya, w.ty, w.tz))
    o1 = wp.where(xa, w.ty, w.tx)                 # the two other axes' crossings
    o2 = wp.where(za, w.ty, w.tz)
    lim = tmin + w.tol
    go = not (o1 <= lim or o2 <= lim or w.t1 <= lim)
    return xa, ya, za, go


@wp.func
def walk32x_certain_med(w: Walk32x):
    """``walk32x_certain`` by minimum and median (``med`` in the module docstring): the same ``go``, and
    where ``go`` holds the same axis."""
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
def walk32x_step32(w: Walk32x, xa: wp.bool, ya: wp.bool, za: wp.bool, sf: wp.float32) -> Walk32x:
    # the certain float32 step along the first axis (walk32_next_lean's, without the grid test: the loop's
    # head makes it)
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


@wp.func
def walk32x_next(w: Walk32x, o: wp.vec3d, d: wp.vec3d, t1d: wp.float64, s: wp.float64, sf: wp.float32,
                 nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32x:
    """One step of a Walk32x: the certain float32 step, else the float64 one to the segment end ``t1d``
    (o, d and t1d at hand)."""
    xa, ya, za, go = walk32x_certain(w)
    if not go:
        return walk32x_exact(w, o, d, t1d, s, sf, nx, ny, nz)
    return walk32x_step32(w, xa, ya, za, sf)


@wp.func
def walk32x_next_med(w: Walk32x, o: wp.vec3d, d: wp.vec3d, t1d: wp.float64, s: wp.float64, sf: wp.float32,
                     nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32x:
    """``walk32x_next`` deciding by minimum and median (``walk32x_certain_med``)."""
    xa, ya, za, go = walk32x_certain_med(w)
    if not go:
        return walk32x_exact(w, o, d, t1d, s, sf, nx, ny, nz)
    return walk32x_step32(w, xa, ya, za, sf)


@wp.func
def walk32x_next_reload(w: Walk32x, pos: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
                        sensor_dirs: wp.array(dtype=wp.vec3d), tid: wp.int32, n: wp.int32, t1d: wp.float64,
                        s: wp.float64, sf: wp.float32, nx: wp.int32, ny: wp.int32, nz: wp.int32) -> Walk32x:
    """``walk32x_next`` whose float64 step reloads the ray (``reload`` in the module docstring)."""
    xa, ya, za, go = walk32x_certain(w)
    if not go:
        return walk32x_exact(w, ray_origin(pos, tid, n), ray_dir(rot, sensor_dirs, tid, n), t1d, s, sf, nx, ny, nz)
    return walk32x_step32(w, xa, ya, za, sf)


@wp.func
def word32x(w: Walk32x, bny: wp.int32, bnz: wp.int32) -> wp.int32:
    # the brick's word within the candidate's bitset (score_gpu.word32)
    return ((w.i >> 2) * bny + (w.j >> 2)) * bnz + (w.k >> 1)


# ----------------------------------------------------------------------------- kernel
def make_lean32x(maxreg=None, reload=False, med=False):
    """The shipped ``score_kernel_gpu`` on a ``Walk32x`` (module docstring); ``reload``: the float64 step
    reloads the ray instead of keeping o and d live. Inputs: the shipped kernel's, then ``stats`` (unused,
    as the study's other kernels take it)."""

    @wp.kernel(module="unique", module_options=OPTS, cuda_max_registers=maxreg)
    def lean32x_kernel(sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d),
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
        w = walk32x_from(w0)
        cbits = word_address(bits, wp.int64(cand) * words_per_candidate)
        my_sum = wp.int64(0)
        cur = wp.int32(-1)
        seen = wp.uint32(0)
        pending = wp.uint32(0)
        nz_w = wp.uint32(0)
        for _ in range(nx + ny + nz + 3):
            if not inside(w, nx, ny, nz):
                break
            word = word32x(w, bny, bnz)
            change = word != cur
            if change and pending != wp.uint32(0):
                my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
            m = load_mask(masks64, word)
            fresh = load_word(cbits, word)
            stop_w = wp.uint32(m & wp.uint64(0xFFFFFFFF))
            nz_w = wp.uint32(m >> wp.uint64(32))
            seen = wp.where(change, fresh, seen)
            pending = wp.where(change, wp.uint32(0), pending)
            cur = word
            bit = wp.uint32(1) << wp.uint32((w.i & 3) | ((w.j & 3) << 2) | ((w.k & 1) << 4))
            pending = pending | (bit & ~seen)
            seen = seen | bit
            if (stop_w & bit) != wp.uint32(0):      # occlusion: the ray ends after this voxel
                break
            if wp.static(reload):
                w = walk32x_next_reload(w, pos, rot, sensor_dirs, tid, n, t1d, s, sf, nx, ny, nz)
            elif wp.static(med):
                w = walk32x_next_med(w, o, d, t1d, s, sf, nx, ny, nz)
            else:
                w = walk32x_next(w, o, d, t1d, s, sf, nx, ny, nz)
        if pending != wp.uint32(0):
            my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
        if my_sum > wp.int64(0):
            wp.atomic_add(sums, cand, my_sum)
    return lean32x_kernel

