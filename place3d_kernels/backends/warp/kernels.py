"""Warp kernels of the core contract: LiDAR rays, ray-mesh, voxel traversal, scores, voting.

Grid kernels take grid-local coordinates (the host subtracted the grid's lower corner in float64) and
walk voxels with the float64 reference's decisions (walk32_*: float32 where an error bound makes a step
certain, float64 otherwise), so covered voxel sets, and therefore M-SOG, agree with the reference bit
for bit (the contract asks for identical coverage across backends). Voxel boundary crossings are
computed from integer plane indices, never accumulated. Ray-mesh intersection: a float32 BVH proposes
triangles, and the reference's float64 test decides which is hit and where (closest_hit).
"""

from __future__ import annotations

import math
from typing import Any

import warp as wp

# forward kernels only: no adjoints to generate, which roughly halves compile time. No fused multiply-add
# (fuse_fp): CUDA's default --fmad=true contracts b*s - o and the rotation products into FMAs, which round
# differently from the reference's separate multiply and add and flip voxel-boundary ties on fine grids.
wp.set_module_options({"enable_backward": False, "fuse_fp": False})

INF64 = wp.constant(wp.float64(1.0e300))
#: hit distance of a miss (only ever stored, never computed with, so no device's inf arithmetic matters)
MISS_T = wp.constant(wp.float64(math.inf))


# ----------------------------------------------------------------------------- rays
@wp.kernel
def lidar_rays_kernel(
    sensor_dirs: wp.array(dtype=wp.vec3d),     # (C*A,) sensor-frame directions
    rot: wp.array(dtype=wp.mat33d),            # (L,) rotations
    pos: wp.array(dtype=wp.vec3d),             # (L,) origins
    out_o: wp.array(dtype=wp.vec3d),
    out_d: wp.array(dtype=wp.vec3d),
):
    tid = wp.tid()
    n = sensor_dirs.shape[0]
    lid = tid / n
    # R @ local, not renormalised: the reference's rays bit for bit (sensor_directions are unit vectors)
    d = rot[lid] * sensor_dirs[tid - lid * n]
    out_o[tid] = pos[lid]
    out_d[tid] = d


# ----------------------------------------------------------------------------- ray-mesh
@wp.func
def _comp(v: wp.vec3d, k: wp.int32):
    r = v[0]
    if k == 1:
        r = v[1]
    if k == 2:
        r = v[2]
    return r


# The ray-mesh query. float32 only proposes, float64 decides. The walk visits the mesh's own BVH (Warp's tree,
# built over the triangles, WarpCore.upload_mesh) nearest child first, as Warp's mesh_query_ray does, but tests
# every node's box grown by rad and gives every triangle of a leaf the reference's float64 test; the smallest t
# wins, ties to the lower face, and each hit shrinks the float32 bound that prunes the rest. The float32 ray
# strays from the float64 one by a few float32 ulps of |origin| + t, t is at most about 2 (|origin| + reach) for
# any point of the mesh (reach: its largest |coordinate|), and the boxes round by an ulp of reach; growing every
# box by 4e-6 of those reaches (60 ulps) covers them, so no box culls a triangle the float64 ray meets before the
# bound. The hit and its face are then the reference's, bit for bit, whatever the tree and its walk order (the
# OpenCL backend decides the same way, raycast.cl). The node test is the one of Warp's capsule query (its robust
# slab test on the grown box, a direction component tested as zero when 1 / (1 / d) is).
#
# Warp has no ordered walk that takes a test of the caller's, so the walk is native code over Warp's node layout
# (native/bvh.h: a node is two BVHPackedNodeHalf, lower and upper, whose i is the left and right child, or for a
# leaf, flagged b, the range of primitive_indices). Its stack: every Warp builder (SAH, LBVH, cuBQL) makes a node
# at depth BVH_QUERY_STACK_SIZE - 1 a leaf (LBVH: a node within one group, the subtrees group roots start), so
# Warp's own queries, which push both children, fit in BVH_QUERY_STACK_SIZE (32) entries; this walk pushes at
# most the two children of the node it pops and keeps at most one deferred sibling per level above, so it fits
# too, and the array has twice that. A plain loop with a vector as stack in Warp's kernel language took 4x the
# native walk on an H200, and Warp's capsule query, which visits children in a fixed order, 5-11x (2026-11-29).
_ORDERED_WALK = r"""
using namespace wp;
const Mesh m = mesh_get(mesh);
const BVHPackedNodeHalf* lows = m.bvh.node_lowers;
const BVHPackedNodeHalf* ups = m.bvh.node_uppers;
const int* prims = m.bvh.primitive_indices;
const vec3 o(float(o64[0]), float(o64[1]), float(o64[2]));
const vec3 d(float(d64[0]), float(d64[1]), float(d64[2]));
const vec3 rcp(1.0f / d[0], 1.0f / d[1], 1.0f / d[2]);
const vec3 dz(1.0f / rcp[0], 1.0f / rcp[1], 1.0f / rcp[2]);
const double om = wp::max(wp::max(wp::abs(o64[0]), wp::abs(o64[1])), wp::abs(o64[2]));
const float rad = float((om + reach + 1.0) * 4.0e-6);
const vec3 grow(rad, rad, rad);
float bound = float(tm) * 1.00000024f + rad;
// the float64 ray's shear frame (backends/geometry.py, watertight_intersect), the same for every triangle
const double adx = wp::abs(d64[0]), ady = wp::abs(d64[1]), adz = wp::abs(d64[2]);
int kz = 0;
if (ady > adx) kz = 1;
if (adz > (kz == 0 ? adx : ady)) kz = 2;
int kx = (kz + 1) % 3;
int ky = (kx + 1) % 3;
if (d64[kz] < 0.0) { const int swap = kx; kx = ky; ky = swap; }
const double sx = d64[kx] / d64[kz];
const double sy = d64[ky] / d64[kz];
const double sz = 1.0 / d64[kz];
double best = miss;
int face = -1;
int stack[2 * BVH_QUERY_STACK_SIZE];
float entry[2 * BVH_QUERY_STACK_SIZE];
int n = 0;
const int top = root == -1 ? *m.bvh.root : root;
float t0 = FLT_MAX;
if (intersect_ray_aabb_robust(o, dz, rcp, vec3(lows[top].x, lows[top].y, lows[top].z) - grow,
                              vec3(ups[top].x, ups[top].y, ups[top].z) + grow, t0) && !(t0 > bound)) {
    stack[0] = top;
    entry[0] = t0;
    n = 1;
}
while (n > 0) {
    --n;
    if (entry[n] > bound) continue;
    const BVHPackedNodeHalf lo = lows[stack[n]];
    const BVHPackedNodeHalf hi = ups[stack[n]];
    if (lo.b) {
        for (int pc = int(lo.i); pc < int(hi.i); ++pc) {
            // the reference's watertight test in float64, operation for operation (no FMA: fuse_fp is off)
            const int i = prims[pc];
            const vec3d ra = index(corners64, 3 * i) - o64;
            const vec3d rb = index(corners64, 3 * i + 1) - o64;
            const vec3d rc = index(corners64, 3 * i + 2) - o64;
            const double ax = ra[kx] - sx * ra[kz];
            const double ay = ra[ky] - sy * ra[kz];
            const double az = sz * ra[kz];
            const double bx = rb[kx] - sx * rb[kz];
            const double by = rb[ky] - sy * rb[kz];
            const double bz = sz * rb[kz];
            const double cx = rc[kx] - sx * rc[kz];
            const double cy = rc[ky] - sy * rc[kz];
            const double cz = sz * rc[kz];
            const double u = cx * by - cy * bx;
            const double v = ax * cy - ay * cx;
            const double w = bx * ay - by * ax;
            if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) continue;
            const double det = u + v + w;
            if (det == 0.0) continue;
            const double t = (u * az + v * bz + w * cz) / det;
            if (!(t >= 0.0 && t <= tm)) continue;
            if (t < best || (t == best && i < face)) {
                best = t;
                face = i;
                bound = float(t) + rad;
            }
        }
        continue;
    }
    const int a = int(lo.i);
    const int b = int(hi.i);
    const BVHPackedNodeHalf al = lows[a], ah = ups[a], bl = lows[b], bh = ups[b];
    float ta = FLT_MAX, tb = FLT_MAX;
    const bool ha = intersect_ray_aabb_robust(o, dz, rcp, vec3(al.x, al.y, al.z) - grow, vec3(ah.x, ah.y, ah.z) + grow, ta)
                    && !(ta > bound);
    const bool hb = intersect_ray_aabb_robust(o, dz, rcp, vec3(bl.x, bl.y, bl.z) - grow, vec3(bh.x, bh.y, bh.z) + grow, tb)
                    && !(tb > bound);
    if (ha && hb) {
        const bool a_first = ta <= tb;
        stack[n] = a_first ? b : a;
        entry[n] = a_first ? tb : ta;
        stack[n + 1] = a_first ? a : b;
        entry[n + 1] = a_first ? ta : tb;
        n += 2;
    } else if (ha || hb) {
        stack[n] = ha ? a : b;
        entry[n] = ha ? ta : tb;
        ++n;
    }
}
return vec2d(best, double(face));
"""


@wp.func_native(_ORDERED_WALK)
def ordered_walk(mesh: wp.uint64, corners64: wp.array(dtype=wp.vec3d), reach: wp.float64, o64: wp.vec3d,
                 d64: wp.vec3d, tm: wp.float64, root: wp.int32, miss: wp.float64) -> wp.vec2d:
    # (t, face) of the closest float64 hit, (miss, -1) for none
    ...


@wp.func
def closest_hit(mesh: wp.uint64, corners64: wp.array(dtype=wp.vec3d), reach: wp.float64, o64: wp.vec3d,
                d64: wp.vec3d, tm: wp.float64, root: wp.int32):
    # the closest float64 hit of the ray (o64, d64) in [0, tm] among the triangles of the subtree at ``root``
    # (a group's, mesh_get_group_root), or the whole tree for -1: (t, uploaded face), or (MISS_T, -1)
    r = ordered_walk(mesh, corners64, reach, o64, d64, tm, root, MISS_T)
    return r[0], wp.int32(r[1])


@wp.kernel
def raycast_query_kernel(
    mesh: wp.uint64,
    corners64: wp.array(dtype=wp.vec3d),    # (3F,) true triangle corners, float64
    reach: wp.float64,
    origins: wp.array(dtype=wp.vec3d),
    shift: wp.vec3d,                        # subtracted from origins in float64 (zero: already shifted)
    dirs: wp.array(dtype=wp.vec3d),
    t_max: wp.array(dtype=wp.float64),
    out_t: wp.array(dtype=wp.float64),
    out_face: wp.array(dtype=wp.int32),
):
    tid = wp.tid()
    # componentwise float64 subtraction: bit-identical to np.subtract(origins, shift) on the host
    t, f = closest_hit(mesh, corners64, reach, origins[tid] - shift, dirs[tid], t_max[tid], wp.int32(-1))
    out_t[tid] = t
    out_face[tid] = f


# flag slots of raycast_checked_kernel (one int32 each; a ray that fails a check writes 1 into its slot)
FLAG_ORIGIN = wp.constant(0)       # non-finite origin
FLAG_DIRECTION = wp.constant(1)    # non-finite or zero direction, or a norm that is not finite
FLAG_T_MAX = wp.constant(2)        # t_max negative or NaN
N_FLAGS = 3


@wp.func
def unit_like_host(d: wp.vec3d):
    # The host's normalisation (ops._check_od) operation for operation, so the bits agree:
    # norm = sqrt((x*x + y*y) + z*z) as ops._row_norm sums it, untouched when |norm - 1| <= 1e-12, else
    # each component divided by the norm. Exact on every Warp device: the module is built with
    # fuse_fp=False (no FMA contraction, so each product and sum rounds as NumPy's does) and without
    # fast_math (Warp's default), and float64 sqrt and division are correctly rounded IEEE operations on
    # CUDA (nvcc's fast-math and -prec-* switches only touch float32) and on the CPU. For float32 inputs
    # the squares are exact in float64 (24-bit significands), so even a contracted sum would be the same.
    n = wp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    out = d
    if wp.abs(n - wp.float64(1.0)) > wp.float64(1.0e-12):
        out = wp.vec3d(d[0] / n, d[1] / n, d[2] / n)
    return out, n


@wp.func
def checked_ray(origins: wp.array(dtype=Any), o_step: wp.int32, dirs: wp.array(dtype=Any),
                t_max: wp.array(dtype=wp.float64), t_step: wp.int32, tid: wp.int32):
    # ray tid as ops.raycast's host path takes it: (world origin, unit direction, its norm, t_max); float32
    # inputs widen to float64 exactly
    ow = wp.vec3d(origins[tid * o_step])
    dw = wp.vec3d(dirs[tid])
    d64, n = unit_like_host(dw)
    return ow, dw, d64, n, t_max[tid * t_step]


@wp.func
def ray_ok(ow: wp.vec3d, dw: wp.vec3d, n: wp.float64, tm: wp.float64, flags: wp.array(dtype=wp.int32)) -> wp.bool:
    # ops.raycast's checks of one ray: a ray that fails one sets its flag (a plain store of 1; every
    # writer stores the same value, so no atomic is needed) and is not traced
    ok = True
    if not (wp.isfinite(ow[0]) and wp.isfinite(ow[1]) and wp.isfinite(ow[2])):
        flags[FLAG_ORIGIN] = 1
        ok = False
    finite_d = wp.isfinite(dw[0]) and wp.isfinite(dw[1]) and wp.isfinite(dw[2]) and wp.isfinite(n)
    if not finite_d or n == wp.float64(0.0):
        flags[FLAG_DIRECTION] = 1
        ok = False
    if not (tm >= wp.float64(0.0)):      # NaN fails this too
        flags[FLAG_T_MAX] = 1
        ok = False
    return ok


@wp.func
def put_hit(t: wp.float64, f: wp.int32, face_ids: wp.array(dtype=wp.int64), face_labels: wp.array(dtype=wp.int32),
            tid: wp.int32, out_t: wp.array(dtype=wp.float64), out_face: wp.array(dtype=wp.int64),
            out_label: wp.array(dtype=wp.int32)):
    # ray tid's hit written as the caller's face id and label
    out_t[tid] = t
    if f >= 0:
        out_face[tid] = face_ids[f]
        out_label[tid] = face_labels[f]


@wp.kernel
def raycast_checked_kernel(
    mesh: wp.uint64,
    corners64: wp.array(dtype=wp.vec3d),    # (3F,) true triangle corners, float64
    reach: wp.float64,
    face_ids: wp.array(dtype=wp.int64),     # (F,) caller's face id of each uploaded face
    face_labels: wp.array(dtype=wp.int32),  # (F,) label of each uploaded face
    origins: wp.array(dtype=Any),           # world frame, vec3f or vec3d as the caller gave them
    o_step: wp.int32,                       # 1, or 0 for one origin shared by every ray
    shift: wp.vec3d,                        # mesh shift, subtracted in float64
    dirs: wp.array(dtype=Any),              # same dtype as origins; any length, not validated
    t_max: wp.array(dtype=wp.float64),
    t_step: wp.int32,                       # 1, or 0 for one bound shared by every ray
    out_t: wp.array(dtype=wp.float64),
    out_face: wp.array(dtype=wp.int64),
    out_label: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),        # (N_FLAGS,) zeroed by the host
):
    # ops.raycast's checks on the device (ray_ok); where a ray fails one, the host redoes the call on its
    # own path, which raises today's error. Then the query (closest_hit).
    tid = wp.tid()
    ow, dw, d64, n, tm = checked_ray(origins, o_step, dirs, t_max, t_step, tid)
    out_t[tid] = MISS_T
    out_face[tid] = wp.int64(-1)
    out_label[tid] = -1
    if ray_ok(ow, dw, n, tm, flags):
        # as ops.raycast's host path: float32 kernels need a finite bound
        t, f = closest_hit(mesh, corners64, reach, ow - shift, d64, wp.min(tm, wp.float64(1.0e30)), wp.int32(-1))
        put_hit(t, f, face_ids, face_labels, tid, out_t, out_face, out_label)


@wp.kernel
def raycast_groups_kernel(
    mesh: wp.uint64,                        # a grouped mesh: group g holds the triangles of mesh g
    corners64: wp.array(dtype=wp.vec3d), reach: wp.float64,
    face_ids: wp.array(dtype=wp.int64), face_labels: wp.array(dtype=wp.int32),   # face_ids: within its own mesh
    origins: wp.array(dtype=wp.vec3d),      # world frame; rays [(g - g0) R, (g - g0 + 1) R) are mesh g's
    shifts: wp.array(dtype=wp.vec3d),       # (G,) mesh g's shift, subtracted in float64
    dirs: wp.array(dtype=wp.vec3d),
    t_max: wp.array(dtype=wp.float64),      # (1,) one bound for every ray
    rays_per_group: wp.int32,               # R
    first_group: wp.int32,                  # g0: the group of these arrays' first ray
    out_t: wp.array(dtype=wp.float64),
    out_face: wp.array(dtype=wp.int64),
    out_label: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    # raycast_checked_kernel for one origin per ray and one t_max, each ray traced in its own mesh's
    # subtree and frame: that mesh's own checked cast, bit for bit (reach: the largest of the meshes')
    tid = wp.tid()
    g = first_group + tid / rays_per_group
    ow, dw, d64, n, tm = checked_ray(origins, 1, dirs, t_max, 0, tid)
    out_t[tid] = MISS_T
    out_face[tid] = wp.int64(-1)
    out_label[tid] = -1
    if ray_ok(ow, dw, n, tm, flags):
        root = wp.mesh_get_group_root(mesh, g)
        t, f = closest_hit(mesh, corners64, reach, ow - shifts[g], d64, wp.min(tm, wp.float64(1.0e30)), root)
        put_hit(t, f, face_ids, face_labels, tid, out_t, out_face, out_label)


#: the concrete kernels for float32 (vec3f) and float64 (vec3d) rays: launching these skips Warp's
#: per-launch overload lookup from the argument values (tens of microseconds per CPU chunk)
RAYCAST_CHECKED = {v: wp.overload(raycast_checked_kernel, {"origins": wp.array(dtype=v), "dirs": wp.array(dtype=v)})
                   for v in (wp.vec3f, wp.vec3d)}


# ----------------------------------------------------------------------------- voxel walk
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
def next_t(i: wp.int32, step: wp.int32, o: wp.float64, d: wp.float64, s: wp.float64):
    # the reference's float64 time of the next boundary plane along one axis (INF64: the axis never steps)
    if step == 0:
        return INF64
    b = i
    if step > 0:
        b = i + 1
    return (wp.float64(b) * s - o) / d


# ----------------------------------------------------------------------------- float32 walk, exact
# The walk the kernels run. It takes the same decisions as the float64 reference walk (``traverse_ray`` in
# place3d_kernels/backends/reference/host.py) but makes them in float32 where that is certain, as the OpenCL
# backend does (place3d_kernels/backends/opencl/grid.cl, which derives the bound): in a frame rebased at the
# entry point p0 = o + t0 d and the first voxel b, the time after t0 at which the ray crosses boundary plane
# b + K of an axis is
#     t' = (K s - q) / d,   q = p0 - b s,
# computed in float32 as (K sf - q) * (1 / d) with an error below DDA_ERR (|t'| + 2 |q / d|). A step
# whose axis crosses first by more than ``tol`` (2.5 times that bound, for the segment end as well) is
# certain; any other step (near-ties: rays within about 1e-6 relative of a voxel edge or corner, or
# ending near a plane) is taken by walk32_exact's float64 arithmetic on the same indices, so every backend
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
    # the reference's float64 step (every axis whose boundary comes first steps; the segment may end)
    tx = next_t(w.i, w.si, o[0], d[0], s)
    ty = next_t(w.j, w.sj, o[1], d[1], s)
    tz = next_t(w.k, w.sk, o[2], d[2], s)
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
def mark_walk(
    o: wp.vec3d, d: wp.vec3d, t_end: wp.float64, s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32, masks: wp.array(dtype=wp.uint32), weights: wp.array(dtype=wp.int64),
    base: wp.int64, bits: wp.array(dtype=wp.uint32),
) -> wp.int64:
    """Walk one ray, set its voxels' bits in the candidate's bricked bitset (words from ``base``) and
    return the weights of the voxels whose bit this ray set first (used by score_ray and score_rays.py)."""
    sf = wp.float32(s)
    w = walk32_begin(o, d, t_end, s, sf, nx, ny, nz)
    # the ray that sets a voxel's bit first owns it; integer partial sums make the total independent of
    # thread order, and one atomic per ray (not per voxel) keeps contention on the candidate's sum low
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
    return my_sum


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
    my_sum = mark_walk(o, d, t_max, s, nx, ny, nz, bny, bnz, masks, weights,
                       wp.int64(cand) * words_per_candidate, bits)
    if my_sum > wp.int64(0):
        wp.atomic_add(sums, cand, my_sum)


# a register cap of 72, kept from the GPU study of this kernel's form (at tag lab-2026-11-27); the CPU,
# which runs it, ignores it. CUDA runs score_gpu.score_kernel_gpu.
@wp.kernel(cuda_max_registers=72)
def score_kernel(
    sensor_dirs: wp.array(dtype=wp.vec3d),      # (C*A,)
    rot: wp.array(dtype=wp.mat33d),             # (P*L,)
    pos: wp.array(dtype=wp.vec3d),              # (P*L,) grid-local
    n_lidars: wp.int32,
    t_max: wp.float64,
    s: wp.float64, nx: wp.int32, ny: wp.int32, nz: wp.int32,
    bny: wp.int32, bnz: wp.int32,               # bricks along y and z (see brick_word)
    masks: wp.array(dtype=wp.uint32),           # per brick: (occlusion bits, nonzero-weight bits)
    weights: wp.array(dtype=wp.int64),          # flat voxel order
    words_per_candidate: wp.int64,
    bits: wp.array(dtype=wp.uint32),           # (P * words_per_candidate,) zeroed, bricked
    sums: wp.array(dtype=wp.int64),            # (P,) zeroed
):
    # the CPU's score kernel (CUDA runs score_gpu.score_kernel_gpu)
    score_ray(wp.tid(), sensor_dirs, rot, pos, n_lidars, t_max, s, nx, ny, nz, bny, bnz, masks, weights,
              words_per_candidate, bits, sums)


COUNT_WORDS = 64   # bitset words per thread of count_bits_kernel for small bitsets (count_words_per_thread)


def count_words_per_thread(total_words: int) -> int:
    """Words per thread of ``count_bits_kernel`` (the CPU's count; CUDA runs ``score_gpu.count_clear_kernel``
    since 2026-11-25) for ``total_words`` bitset words in all: each thread ends with one atomic add on its
    candidate's counter, and for the dense rig's bitsets (hundreds of MB) on a GPU those atomics made the
    count slow at 64 words per thread (bench/README.md, "What the studies found", dense-rig score kernel,
    API around the kernel); the rule was kept when the CPU became its only user. Small bitsets keep 64."""
    return 1024 if total_words >= 2**24 else COUNT_WORDS


@wp.kernel
def count_bits_kernel(bits: wp.array(dtype=wp.uint32), words_per_candidate: wp.int64,
                      chunks_per_candidate: wp.int64, per_thread: wp.int32, masks: wp.array(dtype=wp.uint64),
                      masked: wp.int32, counts: wp.array(dtype=wp.int64)):
    # covered voxels of each candidate = set bits of its bitset; one atomic add per per_thread words. With
    # ``masked``, only the bits whose voxel has a nonzero weight in another grid: masks[w] is that grid's word w
    # (occlusion bits low, nonzero-weight bits high) in the bitset's layout (4 x 4 x 2 bricks on the CPU, flat
    # bricks on CUDA); for a grid of 0/1 weights that is its sum over the covered voxels
    tid = wp.int64(wp.tid())
    cand = tid / chunks_per_candidate
    w0 = (tid - cand * chunks_per_candidate) * wp.int64(per_thread)
    base = cand * words_per_candidate
    c = wp.int64(0)
    for q in range(per_thread):
        at = w0 + wp.int64(q)
        if at < words_per_candidate:
            v = bits[base + at]
            if masked != 0:
                v = v & wp.uint32(masks[at] >> wp.uint64(32))
            c += wp.int64(wp.bit_count(v))
    if c > wp.int64(0):
        wp.atomic_add(counts, wp.int32(cand), c)


# ----------------------------------------------------------------------------- patched grids
# A grid prepared on the device from a dense base and a few changed voxels (WarpCore.patched_grid: the
# jackknife's left-out grids), with the per-brick masks bricks.brick_masks makes on the host.
@wp.kernel
def scatter_rows_kernel(voxels: wp.array(dtype=wp.int64), w_rows: wp.array(dtype=wp.int64),
                        s_rows: wp.array(dtype=wp.uint8), has_stop: wp.int32, weights: wp.array(dtype=wp.int64),
                        stop: wp.array(dtype=wp.uint8)):
    # each changed voxel once (the caller's voxels are distinct), so the writes never collide
    t = wp.tid()
    v = voxels[t]
    weights[v] = w_rows[t]
    if has_stop != 0:
        stop[v] = s_rows[t]


@wp.func
def brick_mask_bits(b: wp.int32, weights: wp.array(dtype=wp.int64), stop: wp.array(dtype=wp.uint8),
                    has_stop: wp.int32, nx: wp.int32, ny: wp.int32, nz: wp.int32, by: wp.int32, bz: wp.int32):
    # (occlusion bits, nonzero-weight bits) of brick b, in bricks.py's numbering; voxels past the grid's end
    # (a partial brick) are 0, as the host's padding leaves them
    bk = b % bz
    r = b / bz
    bj = r % by
    bi = r / by
    sb = wp.uint32(0)
    nb = wp.uint32(0)
    for q in range(32):
        i = bi * 4 + (q & 3)
        j = bj * 4 + ((q >> 2) & 3)
        k = bk * 2 + (q >> 4)
        if i < nx and j < ny and k < nz:
            v = (wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)
            bit = wp.uint32(1) << wp.uint32(q)
            if weights[v] != wp.int64(0):
                nb = nb | bit
            if has_stop != 0:
                if stop[v] != wp.uint8(0):
                    sb = sb | bit
    return sb, nb


@wp.kernel
def brick_masks_pairs_kernel(weights: wp.array(dtype=wp.int64), stop: wp.array(dtype=wp.uint8), has_stop: wp.int32,
                             nx: wp.int32, ny: wp.int32, nz: wp.int32, by: wp.int32, bz: wp.int32,
                             masks: wp.array(dtype=wp.uint32)):
    # bricks.brick_masks' layout: word 2b the occlusion bits, 2b + 1 the nonzero-weight bits (the CPU's grids)
    b = wp.tid()
    sb, nb = brick_mask_bits(b, weights, stop, has_stop, nx, ny, nz, by, bz)
    masks[2 * b] = sb
    masks[2 * b + 1] = nb


@wp.kernel
def brick_masks64_kernel(weights: wp.array(dtype=wp.int64), stop: wp.array(dtype=wp.uint8), has_stop: wp.int32,
                         nx: wp.int32, ny: wp.int32, nz: wp.int32, by: wp.int32, bz: wp.int32,
                         masks: wp.array(dtype=wp.uint64)):
    # the same pair as one little-endian uint64 per brick (CUDA's grids: score_kernel_gpu loads it at once)
    b = wp.tid()
    sb, nb = brick_mask_bits(b, weights, stop, has_stop, nx, ny, nz, by, bz)
    masks[b] = wp.uint64(sb) | (wp.uint64(nb) << wp.uint64(32))


# ----------------------------------------------------------------------------- occupancy
@wp.kernel
def voxel_keys_kernel(points: wp.array(dtype=wp.vec3d), s: wp.float64, nx: wp.int32, ny: wp.int32,
                      nz: wp.int32, out: wp.array(dtype=wp.int64)):
    # float64 on purpose: binning must agree bit for bit with the reference on every backend
    tid = wp.tid()
    p = points[tid]
    i = wp.int32(wp.floor(p[0] / s))
    j = wp.int32(wp.floor(p[1] / s))
    k = wp.int32(wp.floor(p[2] / s))
    if i < 0 or i >= nx or j < 0 or j >= ny or k < 0 or k >= nz:
        out[tid] = wp.int64(-1)
    else:
        out[tid] = (wp.int64(i) * wp.int64(ny) + wp.int64(j)) * wp.int64(nz) + wp.int64(k)


@wp.kernel
def vote_kernel(sorted_keys: wp.array(dtype=wp.int64), n: wp.int32, n_classes: wp.int64,
                out_label: wp.array(dtype=wp.int32)):
    # sorted_keys = voxel * n_classes + label, ascending; thread i leads its voxel's segment if the
    # previous key has another voxel. It scans the runs (labels ascending) and keeps the first maximum.
    i = wp.tid()
    vox = sorted_keys[i] / n_classes
    out_label[i] = -1
    if i > 0:
        if sorted_keys[i - 1] / n_classes == vox:
            return
    best_label = wp.int64(-1)
    best_count = wp.int32(0)
    run_label = wp.int64(-1)
    run_count = wp.int32(0)
    j = i
    while j < n:
        key = sorted_keys[j]
        if key / n_classes != vox:
            break
        lab = key - vox * n_classes
        if lab != run_label:
            run_label = lab
            run_count = 0
        run_count += 1
        if run_count > best_count:
            best_count = run_count
            best_label = run_label
        j += 1
    out_label[i] = wp.int32(best_label)
