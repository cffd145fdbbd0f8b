"""The dense rig's near field (issue 17, goal 3, eighth round): voxels near a LiDAR marked one thread per voxel
instead of by every ray, exactly. Measured and not shipped: the walks it saves are the cheap ones (figures:
bench/README.md, "The dense rig's near field"). ``gpu_dense_variants.py`` times it as ``near-hN``,
``dense_near_parts.py`` launch by launch; ``tests/test_dense_variants.py`` checks its bits.

Within a few metres of a LiDAR its rays are denser than the voxels: a dense rig's 64 x 2048 rays cross a
0.05 m voxel 2 m away some 18 times, and every ray walks its first metres voxel by voxel. For each LiDAR of
each candidate, kernels here replace that part of the walk:

1. ``near_levels_kernel`` and ``near_choose_kernel`` carve a box around the LiDAR's voxel c that holds no
   occlusion bit: per level of voxels, the nearest stop voxel in x and y; then the floor and half-width
   of the largest box above that floor (``near_box`` turns the two numbers into the box).
2. ``near_cover_kernel`` marks each voxel of the box that some ray of the LiDAR visits. A warp is one
   bitset word (a brick of 4 x 4 x 2 voxels), a lane one voxel; the lanes' bits go out in one ``atomic_or``
   per brick, and where some have entropy the old word says which bits are new, whose weights the
   candidate's sum gets (as ``score_gpu.flush_brick32``).
3. ``score_kernel_near``, the shipped ``score_gpu.score_kernel_gpu`` with a prologue (``leave_box``), walks
   each ray from its first voxel after the box.

Why the voxels are the same bits. The walk (``kernels.walk32_*``, the reference's float64 decisions) starts
in voxel i0 per axis (``_start_index``) at t0 = 0 (the origin is inside the grid) and, at each step, takes
every crossing equal to the smallest next one, ``next_t(i, step, ...)``, which depends only on the plane's
index. So after the crossings up to time t it is in the voxel whose index on each axis counts that axis's
crossings <= t. A voxel V = (i, j, k) is therefore visited exactly when, with E the largest of its entry
crossings (t0 on an axis where V is the first voxel) and X the smallest of its exit crossings, E < X (and E
comes before the segment's end and any occlusion: inside the box there is no stop bit, and ``near_box``
keeps the box well within the segment). ``visits`` evaluates this with the walk's own float64
expressions, so ties between axes resolve as the walk resolves them. Rays leave a convex box once, at the
first crossing tb of one of its faces, and ``leave_box`` puts the walk on the voxel after every crossing
<= tb; the float32 crossings are a function of the voxel, so the walk goes on as it would have.

Which rays can visit V: those whose direction lies within the cone around V's centre that holds V's
bounding sphere (angle asin(r / distance), widened by 2e-4 rad for float32 rounding); on the LiDAR's
lattice (channels sorted by elevation, azimuths a * 2 pi / A) that is a range of channels and of
azimuths (the azimuth half-width of a cone of angle delta at elevation e is asin(sin delta / cos e)),
widened by one azimuth step. They are tried from the one nearest V's centre outwards, and the first that
visits ends the search.

Applies to a LiDAR whose azimuths step a full turn evenly from 0 (``lattice``), whose origin lies inside
the grid and whose box holds its first voxels; any other walks from its origin.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from gpu_dense_round7_kernels import flush_brick32, word32
from place3d_kernels.backends.warp.kernels import INF64, _sign, _start_index, next_t, walk32_begin
from place3d_kernels.backends.warp.score_gpu import (DEAD, WalkGPU, atomic_or_word, inside, load_mask, load_word,
                                                     next_step, walk_from, word_address)

# the score kernel's module options (no FMA contraction: the ray directions must round as the walk's)
wp.set_module_options({"enable_backward": False, "fuse_fp": False, "block_dim": 128})

#: largest half-width of a near box in voxels, x and y / z (a 0.05 m grid: 3.2 m)
NEAR_H = 64
NEAR_HZ = 64


def launch_shape(near_h: int, near_hz: int, bricks_z: int) -> tuple[int, int, int]:
    """Bricks per LiDAR along x, y, z that cover any near box (the carve and cover kernels' launch)."""
    return near_h // 2 + 2, near_h // 2 + 2, min(bricks_z, near_hz + 2)


@wp.struct
class NearBox:
    x0: wp.int32     # voxels x0..x1, y0..y1, z0..z1 (x0 > x1: no box)
    x1: wp.int32
    y0: wp.int32
    y1: wp.int32
    z0: wp.int32
    z1: wp.int32


@wp.func
def near_origin(o: wp.vec3d, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32) -> wp.vec3i:
    # the voxel holding the origin, or (-1, -1, -1) unless the origin lies strictly inside the grid
    zero = wp.float64(0.0)
    if o[0] > zero and o[1] > zero and o[2] > zero and o[0] < wp.float64(nx) * s and o[1] < wp.float64(ny) * s \
            and o[2] < wp.float64(nz) * s:
        return wp.vec3i(wp.int32(wp.floor(o[0] / s)), wp.int32(wp.floor(o[1] / s)), wp.int32(wp.floor(o[2] / s)))
    return wp.vec3i(-1, -1, -1)


@wp.func
def near_box(o: wp.vec3d, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32, t_max: wp.float64,
             near: wp.array(dtype=wp.int32), rig: wp.int32, n_rigs: wp.int32, near_h: wp.int32,
             near_hz: wp.int32) -> NearBox:
    """The near box of LiDAR ``rig``: voxels within near_h (x, y) and near_hz (z) of its origin's voxel c,
    from near[rig] (floor) and near[n_rigs + rig] (how far the half-width was cut), one voxel inside the
    grid. None (x0 > x1) unless it holds every voxel a ray can start in (c - 1 .. c + 1: a start on a
    plane belongs to the voxel the ray moves into) and lies well within the segment."""
    b = NearBox()
    b.x0 = 1
    b.x1 = 0
    c = near_origin(o, s, nx, ny, nz)
    if near_h <= 0 or c[0] < 0:
        return b
    h = near_h - near[n_rigs + rig]
    z0 = wp.max(wp.max(1, c[2] - near_hz), near[rig])
    z1 = wp.min(nz - 2, c[2] + near_hz)
    x0 = wp.max(1, c[0] - h)
    x1 = wp.min(nx - 2, c[0] + h)
    y0 = wp.max(1, c[1] - h)
    y1 = wp.min(ny - 2, c[1] + h)
    reach = wp.float64(4 * (wp.max(near_h, near_hz) + 2)) * s
    if x0 <= c[0] - 1 and x1 >= c[0] + 1 and y0 <= c[1] - 1 and y1 >= c[1] + 1 and z0 <= c[2] - 1 \
            and z1 >= c[2] + 1 and t_max > reach:
        b.x0 = x0
        b.x1 = x1
        b.y0 = y0
        b.y1 = y1
        b.z0 = z0
        b.z1 = z1
    return b


@wp.func
def cell_at(t: wp.float64, i0: wp.int32, si: wp.int32, o: wp.float64, d: wp.float64, s: wp.float64) -> wp.int32:
    # the walk's voxel along one axis once every crossing at or before t is taken (it started in i0)
    if si == 0:
        return i0
    e = wp.int32(wp.floor((o + t * d) / s))
    if (e - i0) * si < 0:
        e = i0
    n = wp.int32(0)
    while n < 8 and next_t(e, si, o, d, s) <= t:
        e = e + si
        n = n + 1
    while n < 16 and e != i0 and next_t(e - si, si, o, d, s) > t:
        e = e - si
        n = n + 1
    return e


@wp.func
def leave_box(w: WalkGPU, b: NearBox, o: wp.vec3d, d: wp.vec3d, t1d: wp.float64, s: wp.float64,
              sf: wp.float32) -> WalkGPU:
    # the walk's state on its first voxel after box b (module doc)
    tb = INF64
    if w.si != 0:
        tb = wp.min(tb, next_t(wp.where(w.si > 0, b.x1, b.x0), w.si, o[0], d[0], s))
    if w.sj != 0:
        tb = wp.min(tb, next_t(wp.where(w.sj > 0, b.y1, b.y0), w.sj, o[1], d[1], s))
    if w.sk != 0:
        tb = wp.min(tb, next_t(wp.where(w.sk > 0, b.z1, b.z0), w.sk, o[2], d[2], s))
    if tb >= t1d:
        w.i = DEAD
        return w
    ni = cell_at(tb, w.i, w.si, o[0], d[0], s)
    nj = cell_at(tb, w.j, w.sj, o[1], d[1], s)
    nk = cell_at(tb, w.k, w.sk, o[2], d[2], s)
    w.ki = w.ki + (ni - w.i)
    w.kj = w.kj + (nj - w.j)
    w.kk = w.kk + (nk - w.k)
    w.i = ni
    w.j = nj
    w.k = nk
    if w.t1 >= wp.float32(0.0):
        if w.si != 0:
            w.tx = (wp.float32(w.ki) * sf - w.qx) * w.vx
        if w.sj != 0:
            w.ty = (wp.float32(w.kj) * sf - w.qy) * w.vy
        if w.sk != 0:
            w.tz = (wp.float32(w.kk) * sf - w.qz) * w.vz
    return w


@wp.func
def region_brick(b: wp.int32, c: wp.vec3i, near_h: wp.int32, near_hz: wp.int32, nby: wp.int32,
                 nbz: wp.int32) -> wp.vec3i:
    # brick b (of nbx * nby * nbz) of the region around voxel c that the launch covers
    bi = ((c[0] - near_h) >> 2) + b / (nby * nbz)
    bj = ((c[1] - near_h) >> 2) + (b / nbz) % nby
    bk = (wp.max(c[2] - near_hz, 0) >> 1) + b % nbz
    return wp.vec3i(bi, bj, bk)


@wp.kernel
def near_levels_kernel(pos: wp.array(dtype=wp.vec3d), s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
                       bnx: wp.int32, bny: wp.int32, bnz: wp.int32, masks64: wp.array(dtype=wp.uint64),
                       near_h: wp.int32, near_hz: wp.int32, nbx: wp.int32, nby: wp.int32, nbz: wp.int32,
                       levels: wp.array(dtype=wp.int32)):
    # levels[rig, z] = near_h + 1 - r for the nearest stop voxel of level c[2] - near_hz + z (r = its larger
    # distance in x or y from the LiDAR's voxel c, at most near_h); 0 where that level has none
    tid = wp.tid()
    per = nbx * nby * nbz
    rig = tid / per
    c = near_origin(pos[rig], s, nx, ny, nz)
    if c[0] < 0:
        return
    br = region_brick(tid - rig * per, c, near_h, near_hz, nby, nbz)
    if br[0] < 0 or br[1] < 0 or br[0] >= bnx or br[1] >= bny or br[2] >= bnz:
        return
    m = wp.uint32(load_mask(masks64, (br[0] * bny + br[1]) * bnz + br[2]) & wp.uint64(0xFFFFFFFF))
    while m != wp.uint32(0):
        bit = wp.int32(wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1)))
        m = m & (m - wp.uint32(1))
        i = br[0] * 4 + (bit & 3)
        j = br[1] * 4 + ((bit >> 2) & 3)
        z = br[2] * 2 + (bit >> 4) - (c[2] - near_hz)
        r = wp.max(wp.abs(i - c[0]), wp.abs(j - c[1]))
        if r <= near_h and z >= 0 and z <= 2 * near_hz:
            wp.atomic_max(levels, rig * (2 * near_hz + 1) + z, near_h + 1 - r)


@wp.kernel
def near_choose_kernel(pos: wp.array(dtype=wp.vec3d), s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
                       near_h: wp.int32, near_hz: wp.int32, levels: wp.array(dtype=wp.int32),
                       near: wp.array(dtype=wp.int32)):
    # per LiDAR: the floor f and half-width h of the largest box (2 h + 1)^2 (top - f + 1) holding no stop
    # voxel: from the top level down, h shrinks below each level's nearest stop voxel. near[rig] = f,
    # near[n_rigs + rig] = near_h - h (score_gpu.near_box); a LiDAR without one gets f above its voxel
    rig = wp.tid()
    n_rigs = pos.shape[0]
    c = near_origin(pos[rig], s, nx, ny, nz)
    near[rig] = nz
    near[n_rigs + rig] = 0
    if c[0] < 0:
        return
    top = wp.min(nz - 2, c[2] + near_hz)
    bottom = wp.max(1, c[2] - near_hz)
    cut = wp.int32(0)
    best = wp.int64(0)
    for q in range(top - bottom + 1):
        z = top - q
        cut = wp.max(cut, levels[rig * (2 * near_hz + 1) + z - (c[2] - near_hz)])
        h = near_h - cut
        if h < 1:
            break
        vol = wp.int64(2 * h + 1) * wp.int64(2 * h + 1) * wp.int64(top - z + 1)
        if z <= c[2] - 1 and vol > best:
            best = vol
            near[rig] = z
            near[n_rigs + rig] = cut


@wp.func
def axis_span(i: wp.int32, o: wp.float64, d: wp.float64, s: wp.float64, n: wp.int32):
    # along one axis: (reachable, entry, exit) of voxel index i for the walk of ray (o, d) from t0 = 0 (entry
    # 0 where i is the first voxel; exit INF64 on an axis the ray never steps along)
    si = _sign(d)
    i0 = _start_index(o, d, s, n)
    if si == 0:
        return i == i0, wp.float64(0.0), INF64
    a = (i - i0) * si
    if a < 0:                       # behind the ray's first voxel: no division
        return False, wp.float64(0.0), wp.float64(0.0)
    e = wp.float64(0.0)
    if a > 0:
        e = next_t(i - si, si, o, d, s)
    return True, e, next_t(i, si, o, d, s)


@wp.func
def visits(i: wp.int32, j: wp.int32, k: wp.int32, o: wp.vec3d, d: wp.vec3d, s: wp.float64, nx: wp.int32,
           ny: wp.int32, nz: wp.int32) -> wp.bool:
    # the walk of ray (o, d) from t0 = 0 (its origin inside the grid) takes voxel (i, j, k): E < X (module doc)
    # an axis that rules the voxel out ends the test before the next axis's divisions
    ok, ex, xx = axis_span(i, o[0], d[0], s, nx)
    if not ok:
        return False
    ok, ey, xy = axis_span(j, o[1], d[1], s, ny)
    if not ok:
        return False
    ok, ez, xz = axis_span(k, o[2], d[2], s, nz)
    return ok and wp.max(ex, wp.max(ey, ez)) < wp.min(xx, wp.min(xy, xz))


@wp.func
def lower_bound(a: wp.array(dtype=wp.float32), v: wp.float32) -> wp.int32:
    # first index with a[index] >= v (a sorted ascending)
    lo = wp.int32(0)
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) / 2
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def covered(i: wp.int32, j: wp.int32, k: wp.int32, o: wp.vec3d, rot: wp.mat33d, sensor_dirs: wp.array(dtype=wp.vec3d),
            s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32, el_sorted: wp.array(dtype=wp.float32),
            el_order: wp.array(dtype=wp.int32), n_az: wp.int32) -> wp.bool:
    # some ray of the LiDAR visits voxel (i, j, k): the candidates of its cone, nearest first (module doc)
    half_s = wp.float64(0.5) * s
    cx = wp.float32(wp.float64(i) * s + half_s - o[0])
    cy = wp.float32(wp.float64(j) * s + half_s - o[1])
    cz = wp.float32(wp.float64(k) * s + half_s - o[2])
    ux = wp.float32(rot[0, 0]) * cx + wp.float32(rot[1, 0]) * cy + wp.float32(rot[2, 0]) * cz
    uy = wp.float32(rot[0, 1]) * cx + wp.float32(rot[1, 1]) * cy + wp.float32(rot[2, 1]) * cz
    uz = wp.float32(rot[0, 2]) * cx + wp.float32(rot[1, 2]) * cy + wp.float32(rot[2, 2]) * cz
    rho = wp.sqrt(ux * ux + uy * uy)
    dist = wp.sqrt(rho * rho + uz * uz)
    r = wp.float32(s) * wp.float32(0.8661) + wp.float32(1.0e-5)     # the bounding sphere, a little wider
    el = wp.atan2(uz, rho)
    full = dist <= r * wp.float32(1.01)
    delta = wp.float32(4.0)
    half = wp.float32(4.0)
    if not full:
        delta = wp.asin(r / dist) + wp.float32(2.0e-4)
        if wp.abs(el) + delta < wp.float32(1.5697963):     # pi / 2 - 1e-3: the cone holds no pole
            half = wp.asin(wp.min(wp.float32(1.0), wp.sin(delta) / wp.cos(el))) + wp.float32(2.0e-4)
    lo = lower_bound(el_sorted, el - delta)
    hi = lower_bound(el_sorted, el + delta)
    while hi < el_sorted.shape[0] and el_sorted[hi] <= el + delta:
        hi = hi + 1
    if lo >= hi:
        return False
    cc = wp.clamp(lower_bound(el_sorted, el), lo, hi - 1)
    step = wp.float32(2.0 * math.pi) / wp.float32(n_az)
    ac = wp.int32(0)
    na = n_az
    if half < wp.float32(3.0):
        ac = wp.int32(wp.floor(wp.atan2(uy, ux) / step + wp.float32(0.5)))
        span = wp.int32(wp.ceil(half / step)) + 1
        na = wp.min(n_az, 2 * span + 1)
    nc = hi - lo
    for q in range(2 * nc):
        off = (q + 1) / 2
        ch = cc + wp.where((q & 1) != 0, off, -off)
        if ch >= lo and ch < hi:
            row = el_order[ch] * n_az
            for p in range(na):
                off2 = (p + 1) / 2
                a = (ac + wp.where((p & 1) != 0, off2, -off2)) % n_az
                if a < 0:
                    a = a + n_az
                d = rot * sensor_dirs[row + a]        # as score_kernel_gpu: the same ray bit for bit
                if visits(i, j, k, o, d, s, nx, ny, nz):
                    return True
    return False


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __reduce_or_sync(0xffffffffu, v);
#else
return v;
#endif
""")
def warp_or(v: wp.uint32) -> wp.uint32:
    """OR of ``v`` over the 32 lanes of a warp (every lane must call it); on the CPU, ``v``."""
    ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return (threadIdx.x & 31) == 0 ? 1 : 0;
#else
return 1;
#endif
""")
def warp_leader() -> wp.int32:
    """1 on a warp's first lane (on the CPU, on every thread)."""
    ...


@wp.kernel
def near_cover_kernel(
    sensor_dirs: wp.array(dtype=wp.vec3d), rot: wp.array(dtype=wp.mat33d), pos: wp.array(dtype=wp.vec3d),
    n_lidars: wp.int32, t_max: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bnx: wp.int32, bny: wp.int32, bnz: wp.int32, masks64: wp.array(dtype=wp.uint64),
    weights: wp.array(dtype=wp.int64), words_per_candidate: wp.int64, bits: wp.array(dtype=wp.uint32),
    sums: wp.array(dtype=wp.int64), near: wp.array(dtype=wp.int32), near_h: wp.int32, near_hz: wp.int32,
    nbx: wp.int32, nby: wp.int32, nbz: wp.int32, el_sorted: wp.array(dtype=wp.float32),
    el_order: wp.array(dtype=wp.int32), n_az: wp.int32,
):
    # thread = (LiDAR, brick of its launch region, voxel of the brick); no thread leaves before warp_or
    tid = wp.tid()
    lane = tid & 31
    per = nbx * nby * nbz
    brick = tid >> 5
    rig = brick / per
    b = brick - rig * per
    o = pos[rig]
    box = near_box(o, s, nx, ny, nz, t_max, near, rig, pos.shape[0], near_h, near_hz)
    i = ((box.x0 >> 2) + b / (nby * nbz)) * 4 + (lane & 3)
    j = ((box.y0 >> 2) + (b / nbz) % nby) * 4 + ((lane >> 2) & 3)
    k = ((box.z0 >> 1) + b % nbz) * 2 + (lane >> 4)
    mine = wp.uint32(0)
    if i >= box.x0 and i <= box.x1 and j >= box.y0 and j <= box.y1 and k >= box.z0 and k <= box.z1:
        if covered(i, j, k, o, rot[rig], sensor_dirs, s, nx, ny, nz, el_sorted, el_order, n_az):
            mine = wp.uint32(1) << wp.uint32(lane)
    word_bits = warp_or(mine)
    if warp_leader() != 0 and word_bits != wp.uint32(0):
        cand = rig / n_lidars
        word = ((i >> 2) * bny + (j >> 2)) * bnz + (k >> 1)
        p = word_address(bits, wp.int64(cand) * words_per_candidate)
        nz_w = wp.uint32(load_mask(masks64, word) >> wp.uint64(32))
        if (word_bits & nz_w) != wp.uint32(0):
            old = atomic_or_word(p, word, word_bits)
            m = word_bits & ~old & nz_w
            add = wp.int64(0)
            while m != wp.uint32(0):
                bit = wp.int32(wp.bit_count((m & (~m + wp.uint32(1))) - wp.uint32(1)))
                m = m & (m - wp.uint32(1))
                vi = (i >> 2) * 4 + (bit & 3)
                vj = (j >> 2) * 4 + ((bit >> 2) & 3)
                vk = (k >> 1) * 2 + (bit >> 4)
                add += weights[(wp.int64(vi) * wp.int64(ny) + wp.int64(vj)) * wp.int64(nz) + wp.int64(vk)]
            if add != wp.int64(0):
                wp.atomic_add(sums, cand, add)
        else:
            atomic_or_word(p, word, word_bits)


@wp.kernel(cuda_max_registers=64)     # the register cap of the kernel it was built on (4 x 4 x 2 bricks)
def score_kernel_near(
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
    near: wp.array(dtype=wp.int32),             # (2 P L,) the near boxes' carve
    near_h: wp.int32, near_hz: wp.int32,        # their largest half-widths in voxels (0: no near field)
):
    # score_gpu.score_kernel_gpu with the walk starting after the LiDAR's near box (leave_box)
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
    if near_h > 0 and w.i != DEAD:
        b = near_box(o, s, nx, ny, nz, t_max, near, rig, rot.shape[0], near_h, near_hz)
        if b.x0 <= b.x1:            # the box's voxels are near_cover_kernel's
            w = leave_box(w, b, o, d, t1d, s, sf)
    cbits = word_address(bits, wp.int64(cand) * words_per_candidate)
    my_sum = wp.int64(0)
    cur = wp.int32(-1)
    seen = wp.uint32(0)
    pending = wp.uint32(0)
    nz_w = wp.uint32(0)
    for _ in range(nx + ny + nz + 3):
        if not inside(w, nx, ny, nz):
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
        w = next_step(w, o, d, t1d, s, sf)
    if pending != wp.uint32(0):
        my_sum += flush_brick32(cbits, cur, pending, nz_w, bny, bnz, ny, nz, weights)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


# ----------------------------------------------------------------------------- host side
def lattice(elevations, azimuths):
    """``(el_sorted, el_order, n_az)`` for the cover kernel, or None where the near field does not apply:
    azimuths other than ``a * 2 pi / A`` (a full turn from 0, as ``LidarModel.uniform``), or no rays."""
    el = np.asarray(elevations, dtype=np.float64).reshape(-1)
    az = np.asarray(azimuths, dtype=np.float64).reshape(-1)
    if not len(el) or not len(az) or not np.all(np.isfinite(el)):
        return None
    if np.max(np.abs(az - np.arange(len(az)) * (2 * np.pi / len(az)))) > 1e-9:
        return None
    order = np.argsort(el, kind="stable").astype(np.int32)
    return el[order].astype(np.float32), order, len(az)


def carve(device, pos, s: float, shape, bricks, masks64, near_h: int = NEAR_H, near_hz: int = NEAR_HZ):
    """Every LiDAR's near box (``near_levels_kernel``, ``near_choose_kernel``): the ``near`` array that
    ``near_cover_kernel`` and ``score_kernel_near`` take with ``near_h`` and ``near_hz``. ``bricks``: the grid's
    bricks per axis."""
    nx, ny, nz = (int(v) for v in shape)
    bnx, bny, bnz = (int(v) for v in bricks)
    rigs = pos.shape[0]
    lx, ly, lz = launch_shape(near_h, near_hz, bnz)
    near = wp.empty(2 * rigs, dtype=wp.int32, device=device)
    levels = wp.zeros(rigs * (2 * near_hz + 1), dtype=wp.int32, device=device)
    wp.launch(near_levels_kernel, dim=rigs * lx * ly * lz, device=device,
              inputs=[pos, float(s), nx, ny, nz, bnx, bny, bnz, masks64, int(near_h), int(near_hz), lx, ly, lz, levels])
    wp.launch(near_choose_kernel, dim=rigs, device=device,
              inputs=[pos, float(s), nx, ny, nz, int(near_h), int(near_hz), levels, near])
    return near


def cover(device, near, table, sd_a, rot, pos, n_lidars: int, t_max: float, s: float, shape, bricks, masks64,
          weights, words: int, bits, sums, near_h: int = NEAR_H, near_hz: int = NEAR_HZ) -> None:
    """Mark the voxels of the boxes ``near`` (from ``carve``) that some ray visits; sums get their entropy.
    ``table``: uploaded ``lattice`` arrays ``(el_sorted, el_order, n_az)``."""
    nx, ny, nz = (int(v) for v in shape)
    bnx, bny, bnz = (int(v) for v in bricks)
    lx, ly, lz = launch_shape(near_h, near_hz, bnz)
    el_sorted, el_order, n_az = table
    wp.launch(near_cover_kernel, dim=rot.shape[0] * lx * ly * lz * 32, device=device,
              inputs=[sd_a, rot, pos, int(n_lidars), float(t_max), float(s), nx, ny, nz, bnx, bny, bnz, masks64,
                      weights, int(words), bits, sums, near, int(near_h), int(near_hz), lx, ly, lz, el_sorted,
                      el_order, int(n_az)])


def launch(device, table, sd_a, rot, pos, n_lidars: int, t_max: float, s: float, shape, bricks, masks64, weights,
           words: int, bits, sums, near_h: int = NEAR_H, near_hz: int = NEAR_HZ):
    """``carve`` then ``cover``; returns the ``near`` array that ``score_kernel_near`` takes."""
    near = carve(device, pos, s, shape, bricks, masks64, near_h, near_hz)
    cover(device, near, table, sd_a, rot, pos, n_lidars, t_max, s, shape, bricks, masks64, weights, words, bits,
          sums, near_h, near_hz)
    return near
