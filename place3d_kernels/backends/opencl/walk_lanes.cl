/* score_walk_lanes: score_walk (grid.cl) with SW rays in flight per work-item, one per vector lane. Needs
 * common.cl and grid.cl in front. The CPU strategy of score_placements uses it.
 *
 * Why: one ray per CPU thread leaves the core waiting. Each step's axis choice depends on the previous
 * step's crossing time, and the branch that takes it is mispredicted about every other step, so a core
 * walked about 0.25 G steps/s. Here the common step (dda_step's certain case) runs for SW rays at once in
 * vector registers, without branches; a lane whose step is a near-tie (or the segment's end) takes
 * dda_step_slow on its own, and a lane whose ray ended takes the work-item's next ray. Each lane makes
 * exactly dda_step's decisions (the certain case is the same test: one axis's crossing leads the other
 * two and the segment end by more than tol, so it is the unique minimum), and the voxels are marked in
 * score_walk's bitset, so score_reduce sums the same integers.
 *
 * Measured faster than score_walk on PoCL, the stop mask as bits (below) included (figures:
 * bench/README.md, "What the studies found", M-SOG walk on the CPU).
 * Slower and not kept: 8 lanes, one ray per work-item written branch-free (each step then waits for the
 * last), spilling the lanes to private arrays for the marking, 64-bit voxel indices. The host builds this
 * file with FLAT32 (32-bit indices) and uses it for grids of fewer than 2^31 voxels, score_walk beyond.
 *
 * Only the marking loop is unrolled. The lanes' first rays and their slow path are plain loops over j:
 * unrolled, sixteen inlined copies of dda_init and dda_step_slow made PoCL take 10-20 s to compile this
 * kernel at its first launch (a first `place3d evaluate` on a CPU waited for it) against 3-4 s, and the walk
 * was no faster (bench/results/opencl-walk-compile-2026-12-02-s45/README.md).
 */
#ifndef SW
#define SW 16
#endif
#define VCAT(a, b) a##b
#define VTYPE(t, n) VCAT(t, n)
#define VF VTYPE(float, SW)
#define VI VTYPE(int, SW)
#define CONVF VTYPE(convert_float, SW)
#define CONVU VTYPE(convert_uint, SW)
#ifdef FLAT32
#define VL VI
#define CONVL(x) (x)
typedef int flat_t;
#else
#define VL VTYPE(long, SW)
#define CONVL VTYPE(convert_long, SW)
typedef long flat_t;
#endif

/* the work-item's next ray with a non-empty segment in st; false when none is left */
ALWAYS_INLINE bool lane_next_ray(dda_t* st, long* next, long r1, __global const real* rig,
                                 __global const real* sdir, long p, int L, int CA, real t_max, real s,
                                 int nx, int ny, int nz)
{
    while (*next < r1) {
        real o[3], d[3];
        rig_ray(rig, sdir, p, *next, L, CA, o, d);
        *next += 1;
        if (dda_init(st, o[0], o[1], o[2], d[0], d[1], d[2], t_max, s, nx, ny, nz)) return true;
    }
    return false;
}

/* lane J's walking fields, from the vectors to its dda_t and back */
#define LANE_OUT(J) { lane[J].ix = ix[J]; lane[J].iy = iy[J]; lane[J].iz = iz[J]; lane[J].flat = flat[J];   \
                      lane[J].kx = kx[J]; lane[J].ky = ky[J]; lane[J].kz = kz[J];                              \
                      lane[J].tx = tx[J]; lane[J].ty = ty[J]; lane[J].tz = tz[J]; }
#define LANE_IN(J)  { ix[J] = lane[J].ix; iy[J] = lane[J].iy; iz[J] = lane[J].iz; flat[J] = (flat_t)lane[J].flat; \
                      kx[J] = lane[J].kx; ky[J] = lane[J].ky; kz[J] = lane[J].kz;                              \
                      tx[J] = lane[J].tx; ty[J] = lane[J].ty; tz[J] = lane[J].tz; }
/* every field of lane J, which holds a new ray */
#define LANE_NEW(J) { LANE_IN(J);                                                                          \
                      sx[J] = lane[J].sx; sy[J] = lane[J].sy; sz[J] = lane[J].sz;                              \
                      fx[J] = (flat_t)lane[J].fx; fy[J] = (flat_t)lane[J].fy; fz[J] = (flat_t)lane[J].fz;      \
                      qx[J] = lane[J].qx; qy[J] = lane[J].qy; qz[J] = lane[J].qz;                              \
                      vx[J] = lane[J].vx; vy[J] = lane[J].vy; vz[J] = lane[J].vz;                              \
                      t1[J] = lane[J].t1; tol[J] = lane[J].tol; guard[J] = nx + ny + nz; live[J] = -1; }

/* global size (G, P), as score_walk: work-item (g, p) walks the g-th share of candidate p's rays into
 * its own bitset. The stop mask comes as bits in the bitset's layout (bit b of word w: voxel 32 w + b):
 * the byte mask is 4 MB on the default grid and a step along x lands on another cache line of it, where
 * the bits are an eighth of that and share the marked word's index. Vector comparisons give -1 (all bits)
 * for true, so masks combine with & and |. */
__kernel void score_walk_lanes(__global const real* rig, __global const real* sdir, const int L, const int CA,
                               const real t_max, const real s, const int nx, const int ny, const int nz,
                               __global const uint* stop_bits, const int use_stop, __global uint* bits,
                               const long words, const int G)
{
    int g = get_global_id(0);
    long p = get_global_id(1);
    if (g >= G) return;
    long n_rays = (long)L * CA;
    long next = n_rays * g / G, r1 = n_rays * (g + 1) / G;
    __global uint* mine = bits + (p * G + g) * words;
    dda_t lane[SW];
    VI ix = 0, iy = 0, iz = 0, sx = 0, sy = 0, sz = 0, kx = 0, ky = 0, kz = 0, guard = 0, live = 0;
    VL flat = 0, fx = 0, fy = 0, fz = 0;
    VF tx = 0, ty = 0, tz = 0, qx = 0, qy = 0, qz = 0, vx = 0, vy = 0, vz = 0, t1 = 0, tol = 0;
    const float sf = (float)s;
    const VI vnx = (VI)nx, vny = (VI)ny, vnz = (VI)nz;
    for (int j = 0; j < SW; ++j)
        if (lane_next_ray(&lane[j], &next, r1, rig, sdir, p, L, CA, t_max, s, nx, ny, nz)) LANE_NEW(j);
    while (any(live)) {
        /* visit (DDA_WALK's order): mark each live lane's voxel; a stop voxel or the guard ends its ray */
        VI done = 0;
        #pragma unroll
        for (int j = 0; j < SW; ++j) {
            if (live[j]) {
                flat_t f = flat[j];
                uint bit = 1u << (uint)(f & 31);
                mine[f >> 5] |= bit;
                if (use_stop && (stop_bits[f >> 5] & bit)) done[j] = -1;
            }
        }
        guard -= (live != 0) ? 1 : 0;
        done |= live & (guard <= 0);
        VI go = live & ~done;
        /* dda_step's certain case, for every lane at once */
        VF m = MINF(tx, MINF(ty, tz));
        VF lim = m + tol;
        VI n_at = -((tx <= lim) + (ty <= lim) + (tz <= lim));
        VI sure = go & (n_at == 1) & (t1 > lim);
        VI bx = sure & (tx == m);
        VI by = sure & ~bx & (ty == m);
        VI bz = sure & ~bx & ~by;
        VI dx = sx & bx, dy = sy & by, dz = sz & bz;
        ix += dx; iy += dy; iz += dz;
        kx += dx; ky += dy; kz += dz;
        flat += (fx & CONVL(bx)) + (fy & CONVL(by)) + (fz & CONVL(bz));
        tx = select(tx, (CONVF(kx) * sf - qx) * vx, bx);     /* AXIS_T, as dda_step */
        ty = select(ty, (CONVF(ky) * sf - qy) * vy, by);
        tz = select(tz, (CONVF(kz) * sf - qz) * vz, bz);
        VI out = (CONVU(ix) >= CONVU(vnx)) | (CONVU(iy) >= CONVU(vny)) | (CONVU(iz) >= CONVU(vnz));
        done |= sure & out;
        VI slow = go & ~sure;
        if (any(slow | done)) {
            for (int j = 0; j < SW; ++j) {
                if (slow[j]) {            /* a near-tie or the segment's end: settled as dda_step does */
                    LANE_OUT(j);
                    if (dda_step_slow(&lane[j])) { LANE_IN(j); } else done[j] = -1;
                }
                if (done[j]) {            /* the lane's ray ended: the next one, or the lane goes idle */
                    live[j] = 0;
                    if (lane_next_ray(&lane[j], &next, r1, rig, sdir, p, L, CA, t_max, s, nx, ny, nz)) LANE_NEW(j);
                }
            }
        }
    }
}
