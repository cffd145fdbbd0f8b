/* Voxel grid kernels: traversal (count + fill CSR), coverage, batched placement scores, voxel keys,
 * LiDAR rays. Needs common.cl in front.
 *
 * Traversal semantics (backends/base.py; docs/architecture.md, Kernel contract): the segment [0, t_end] is clipped to the
 * grid box [0, n*s]^3; a voxel is visited when the open segment passes through its interior.
 *
 * The walk. Setup (clip, first voxel) runs once per ray in `real`. The loop runs in float32 in a frame
 * rebased at the entry point p0 = o + t0 d and the first voxel b: the time (after t0) at which the ray
 * crosses boundary plane k of an axis is computed from the integer index,
 *     t' = ((k - b) * s - (p0 - b s)) / d,
 * never by accumulating t. The error of that float32 value is bounded (DDA_ERR below), so each step knows
 * whether its decision "which plane comes first / does the segment end first" is certain. When it is not
 * (a near-tie: the ray passes within ~1e-6 relative of an edge or corner, or ends near a plane), the step
 * recomputes the candidate times in double from the float64 inputs with the reference's formula
 * t = (k s - o) / d, so on fp64 devices the visit list equals the exact float64 one. Exact ties step every
 * tied axis at once (the ray passes through the edge/corner and never enters the voxels beside it).
 */

/* Error bound of a float32 crossing time t_f = (fl(n s_f) - q_f) * fl(1/d_f), with u = 2^-24 and q the
 * rebased origin (|q| <= about one voxel):
 *     |t_f - t| <= 6u|t| + 5u|q||1/d|   (rounding of s, n*s, q, the subtraction, 1/d and the product).
 * With C = 2^-20 = 16u (2.6x the 6u above, and 2C >= 5u), each event's error is below C|t| + 2C|q||1/d|.
 * Two events a, b (crossings or the segment end, compared only while they are <= t1 + tol) are in a
 * certain order when they differ by more than the sum of their errors, which
 *     tol = 2.5 (C t1 + 2C max|q||1/d|)
 * exceeds (2C t1 + 4C max|q||1/d| plus second-order terms). */
#define DDA_ERR 9.5367431640625e-07f
/* direction components smaller than this are treated as 0 (over any segment a ray moves < 1e-17 m on
 * that axis, so it can only matter for rays lying on a plane, where either side is allowed) */
#define DIR_EPS 1e-20

typedef struct {
    int ix, iy, iz;           /* current voxel */
    int sx, sy, sz;           /* step direction per axis: -1, 0, +1 */
    int nx, ny, nz;
    long flat;                /* (ix * ny + iy) * nz + iz */
    long fx, fy, fz;          /* change of flat per step on each axis (sign included) */
    float tx, ty, tz;         /* next crossing time after t0 per axis (FLT_MAX: never) */
    int kx, ky, kz;           /* next boundary index minus the first voxel's index */
    float qx, qy, qz;         /* rebased origin p0 - b s */
    float vx, vy, vz;         /* 1 / d */
    float sf;
    float t1, tol;            /* segment end after t0, and the certainty threshold */
#ifdef HAVE_FP64
    double dox, doy, doz, ddx, ddy, ddz, ds, dt1;
#endif
} dda_t;

ALWAYS_INLINE real cross_r(int k, real o, real d, real s) { return ((real)k * s - o) / d; }

/* clip one axis; false when the ray misses the slab */
ALWAYS_INLINE bool clip_axis(real o, real d, real S, real* t0, real* t1, int* entry, int axis)
{
    if (d == (real)0) return o >= (real)0 && o <= S;
    real ta = ((real)0 - o) / d;
    real tb = (S - o) / d;
    real tn = MINF(ta, tb), tf = MAXF(ta, tb);
    if (tn > *t0) { *t0 = tn; *entry = axis; }
    if (tf < *t1) *t1 = tf;
    return true;
}

/* index of the voxel the ray is in just after t0 on one axis; consistent with cross_r */
ALWAYS_INLINE int start_index(real o, real d, real s, int n, real t0, bool is_entry)
{
    if (is_entry) return d > (real)0 ? 0 : n - 1;
    real fi = floor((d == (real)0 ? o : o + t0 * d) / s);
    int i = fi < (real)0 ? 0 : (fi > (real)(n - 1) ? n - 1 : (int)fi);
    if (d == (real)0) return i;
    if (d > (real)0) {
        while (i + 1 <= n - 1 && cross_r(i + 1, o, d, s) <= t0) i++;
        while (i >= 1 && cross_r(i, o, d, s) > t0) i--;
    } else {
        while (i >= 1 && cross_r(i, o, d, s) <= t0) i--;
        while (i + 1 <= n - 1 && cross_r(i + 1, o, d, s) > t0) i++;
    }
    return i;
}

#define AXIS_T(K, Q, V) (((float)(K) * sf - (Q)) * (V))

/* false when the clipped segment is empty */
ALWAYS_INLINE bool dda_init(dda_t* st, real ox, real oy, real oz, real dx, real dy, real dz, real t_end, real s,
                            int nx, int ny, int nz)
{
    if (absr(dx) < (real)DIR_EPS) dx = (real)0;
    if (absr(dy) < (real)DIR_EPS) dy = (real)0;
    if (absr(dz) < (real)DIR_EPS) dz = (real)0;
    real t0 = (real)0, t1 = t_end;
    int entry = -1;
    if (!clip_axis(ox, dx, (real)nx * s, &t0, &t1, &entry, 0)) return false;
    if (!clip_axis(oy, dy, (real)ny * s, &t0, &t1, &entry, 1)) return false;
    if (!clip_axis(oz, dz, (real)nz * s, &t0, &t1, &entry, 2)) return false;
    if (!(t1 > t0)) return false;
    st->nx = nx; st->ny = ny; st->nz = nz;
    int bx = start_index(ox, dx, s, nx, t0, entry == 0);
    int by = start_index(oy, dy, s, ny, t0, entry == 1);
    int bz = start_index(oz, dz, s, nz, t0, entry == 2);
    st->ix = bx; st->iy = by; st->iz = bz;
    st->sx = dx > (real)0 ? 1 : (dx < (real)0 ? -1 : 0);
    st->sy = dy > (real)0 ? 1 : (dy < (real)0 ? -1 : 0);
    st->sz = dz > (real)0 ? 1 : (dz < (real)0 ? -1 : 0);
    st->flat = ((long)bx * ny + by) * nz + bz;
    st->fx = (long)st->sx * ny * nz;
    st->fy = (long)st->sy * nz;
    st->fz = (long)st->sz;
    float sf = (float)s;
    st->sf = sf;
    st->qx = (float)(ox + t0 * dx - (real)bx * s);
    st->qy = (float)(oy + t0 * dy - (real)by * s);
    st->qz = (float)(oz + t0 * dz - (real)bz * s);
    st->kx = st->sx > 0; st->ky = st->sy > 0; st->kz = st->sz > 0;
    float emax = 0.0f;
    if (st->sx) { st->vx = 1.0f / (float)dx; st->tx = AXIS_T(st->kx, st->qx, st->vx);
                  emax = MAXF(emax, absf(st->qx * st->vx)); }
    else { st->vx = 0.0f; st->tx = FLT_MAX; }
    if (st->sy) { st->vy = 1.0f / (float)dy; st->ty = AXIS_T(st->ky, st->qy, st->vy);
                  emax = MAXF(emax, absf(st->qy * st->vy)); }
    else { st->vy = 0.0f; st->ty = FLT_MAX; }
    if (st->sz) { st->vz = 1.0f / (float)dz; st->tz = AXIS_T(st->kz, st->qz, st->vz);
                  emax = MAXF(emax, absf(st->qz * st->vz)); }
    else { st->vz = 0.0f; st->tz = FLT_MAX; }
    st->t1 = (float)(t1 - t0);
    st->tol = 2.5f * DDA_ERR * (st->t1 + 2.0f * emax);
#ifdef HAVE_FP64
    st->dox = ox; st->doy = oy; st->doz = oz;
    st->ddx = dx; st->ddy = dy; st->ddz = dz;
    st->ds = s; st->dt1 = t1;
#endif
    return true;
}

/* The general step: several axes may cross at once, the segment may end, and near-ties are settled in
 * double (or, without fp64, by the float values). */
ALWAYS_INLINE bool dda_step_slow(dda_t* st)
{
    float tx = st->tx, ty = st->ty, tz = st->tz;
    float m = MINF(tx, MINF(ty, tz));
    bool mx, my, mz;
#ifdef HAVE_FP64
    double dx = st->sx ? cross_r(st->ix + (st->sx > 0), st->dox, st->ddx, st->ds) : DBL_MAX;
    double dy = st->sy ? cross_r(st->iy + (st->sy > 0), st->doy, st->ddy, st->ds) : DBL_MAX;
    double dz = st->sz ? cross_r(st->iz + (st->sz > 0), st->doz, st->ddz, st->ds) : DBL_MAX;
    double md = MINF(dx, MINF(dy, dz));
    if (md >= st->dt1) return false;
    mx = dx == md; my = dy == md; mz = dz == md;
#else
    if (m >= st->t1) return false;
    mx = tx == m; my = ty == m; mz = tz == m;
#endif
    float sf = st->sf;
    if (mx) {
        st->ix += st->sx;
        if ((uint)st->ix >= (uint)st->nx) return false;
        st->flat += st->fx;
        st->kx += st->sx;
        st->tx = AXIS_T(st->kx, st->qx, st->vx);
    }
    if (my) {
        st->iy += st->sy;
        if ((uint)st->iy >= (uint)st->ny) return false;
        st->flat += st->fy;
        st->ky += st->sy;
        st->ty = AXIS_T(st->ky, st->qy, st->vy);
    }
    if (mz) {
        st->iz += st->sz;
        if ((uint)st->iz >= (uint)st->nz) return false;
        st->flat += st->fz;
        st->kz += st->sz;
        st->tz = AXIS_T(st->kz, st->qz, st->vz);
    }
    return true;
}

/* The common step: axis T crosses first, by more than tol before the other two and the segment end, so
 * the decision is certain in float32; step it and compute its next crossing from the integer index. */
#define STEP_AXIS(I, S, N, F, K, T, Q, V, O1, O2)                                                \
    {                                                                                          \
        float lim = T + st->tol;                                                               \
        if (O1 <= lim || O2 <= lim || st->t1 <= lim) return dda_step_slow(st);                 \
        st->I += st->S;                                                                        \
        st->flat += st->F;                                                                     \
        st->K += st->S;                                                                        \
        st->T = ((float)st->K * st->sf - st->Q) * st->V;                                       \
        return (uint)st->I < (uint)st->N;                                                      \
    }

/* Advance to the next voxel; false when the segment ends (or leaves the grid) in the current one. */
ALWAYS_INLINE bool dda_step(dda_t* st)
{
    float tx = st->tx, ty = st->ty, tz = st->tz;
    if (tx < ty) {
        if (tx < tz) STEP_AXIS(ix, sx, nx, fx, kx, tx, qx, vx, ty, tz)
        else STEP_AXIS(iz, sz, nz, fz, kz, tz, qz, vz, tx, ty)
    } else {
        if (ty < tz) STEP_AXIS(iy, sy, ny, fy, ky, ty, qy, vy, tx, tz)
        else STEP_AXIS(iz, sz, nz, fz, kz, tz, qz, vz, tx, ty)
    }
}

/* Walk ray i, running VISIT (which may use st.flat) for each voxel in order. A visited voxel with a
 * non-zero stop byte ends the walk. `guard` bounds the loop: a ray visits at most nx + ny + nz - 2. */
#define DDA_WALK(O, D, TEND, VISIT)                                                                    \
    {                                                                                                  \
        dda_t st;                                                                                      \
        if (dda_init(&st, (O)[0], (O)[1], (O)[2], (D)[0], (D)[1], (D)[2], (TEND), s, nx, ny, nz)) {    \
            int guard = nx + ny + nz;                                                                  \
            for (;;) {                                                                                 \
                VISIT;                                                                                 \
                if (use_stop && stop[st.flat]) break;                                                  \
                if (--guard <= 0 || !dda_step(&st)) break;                                             \
            }                                                                                          \
        }                                                                                              \
    }

#define GRID_ARGS const real s, const int nx, const int ny, const int nz, \
                  __global const uchar* stop, const int use_stop

__kernel void dda_count(__global const real* orig, __global const real* dir, __global const real* t_end,
                        GRID_ARGS, __global long* counts, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    long c = 0;
    DDA_WALK(orig + 3 * (long)i, dir + 3 * (long)i, t_end[i], c++);
    counts[i] = c;
}

__kernel void dda_fill(__global const real* orig, __global const real* dir, __global const real* t_end,
                       GRID_ARGS, __global const long* offsets, __global long* voxels, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    __global long* out = voxels + offsets[i];
    long end = offsets[i + 1] - offsets[i];
    long c = 0;
    /* the fill pass takes the same decisions as the count pass; the bound is belt and braces */
    DDA_WALK(orig + 3 * (long)i, dir + 3 * (long)i, t_end[i], if (c < end) out[c] = st.flat; c++);
}

__kernel void dda_coverage(__global const real* orig, __global const real* dir, __global const real* t_end,
                           GRID_ARGS, __global uchar* mask, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    DDA_WALK(orig + 3 * (long)i, dir + 3 * (long)i, t_end[i], mask[st.flat] = 1);
}

/* Rays of candidate rigs, generated on the device. rig: (P*L, 12) = origin xyz, R row-major (3x3).
 * local: (C*A, 3) sensor-frame unit directions. Direction = R @ local (summed left to right, like the
 * reference's einsum). */
ALWAYS_INLINE void rig_ray(__global const real* rig, __global const real* sdir, long p, long r, int L, int CA,
                    real* o, real* d)
{
    int l = (int)(r / CA);
    long q = r - (long)l * CA;
    __global const real* g = rig + (p * L + l) * 12;
    real x = sdir[3 * q], y = sdir[3 * q + 1], z = sdir[3 * q + 2];
    o[0] = g[0]; o[1] = g[1]; o[2] = g[2];
    d[0] = g[3] * x + g[4] * y + g[5] * z;
    d[1] = g[6] * x + g[7] * y + g[8] * z;
    d[2] = g[9] * x + g[10] * y + g[11] * z;
}

__kernel void lidar_rays(__global const real* rig, __global const real* sdir, const int L, const int CA,
                         __global real* orig, __global real* dir)
{
    long r = get_global_id(0);
    if (r >= (long)L * CA) return;
    real o[3], d[3];
    rig_ray(rig, sdir, 0, r, L, CA, o, d);
    for (int k = 0; k < 3; ++k) { orig[3 * r + k] = o[k]; dir[3 * r + k] = d[k]; }
}

/* Batched placement score, two strategies with the same exact result (the union is a set; its sums are
 * int64 and added on the host in int64):
 *
 * score_rays_flat + count_bits (GPUs: many work-items): global size (items, P); each work-item walks
 * `per_item` consecutive rays of candidate p and marks their voxels in p's shared bitset of flat bricks.
 * The first marker of a voxel with entropy (atomic_or returns the old word) adds its weight, so each is
 * added exactly once; count_bits then counts the covered voxels of each candidate.
 *
 * score_walk + score_reduce (CPUs: few threads): global size (G, P); work-item (g, p) walks the g-th share
 * of p's rays into a bitset of its own (plain stores, no atomics), then score_reduce ORs the G bitsets of
 * a candidate word by word and adds the weights of the set bits. */
/* Walk one ray and mark its voxels in a candidate's bricked bitset (mine); return the weights of the
 * voxels with entropy whose bit this ray set first. Used by score_rays_csr (score_rays.cl); score_rays_flat
 * walks with the same dda_step, so both cover the same voxels as traverse. */
long mark_walk_bricked(const real* o, const real* d, const real t_end, const real s, const int nx, const int ny,
                       const int nz, const int bny, const int bnz, __global const uint* masks,
                       __global const long* weights, __global volatile uint* mine)
{
    long sum = 0;
    dda_t st;
    if (!dda_init(&st, o[0], o[1], o[2], d[0], d[1], d[2], t_end, s, nx, ny, nz)) return 0;
    int guard = nx + ny + nz;
    for (;;) {
        long w = ((long)(st.ix >> 2) * bny + (st.iy >> 2)) * bnz + (st.iz >> 1);
        uint bit = 1u << (uint)((st.ix & 3) | ((st.iy & 3) << 2) | ((st.iz & 1) << 4));
        if (!(mine[w] & bit)) {
            /* only voxels with entropy need the old word (to add the weight once); free space takes
             * an atomic whose result is unused, and count_bits counts the covered voxels afterwards */
            if (masks[2 * w + 1] & bit) {
                uint old = atomic_or(&mine[w], bit);
                if (!(old & bit)) sum += weights[st.flat];
            } else {
                atomic_or(&mine[w], bit);
            }
        }
        if (masks[2 * w] & bit) break;
        if (--guard <= 0 || !dda_step(&st)) break;
    }
    return sum;
}

/* flat[f] = the masks of flat brick f (backends/bricks.py, flat_brick_masks) from the grid's 4 x 4 x 2 brick
 * pairs (brick_masks: word 2b occlusion, 2b + 1 nonzero weight): x bricks 2 bi and 2 bi + 1 of row bj, layer
 * k & 1 of brick k >> 1; each row of 4 voxels along x is a nibble there and half a byte here. */
__kernel void flat_masks(__global const uint* pairs, const int bx, const int by, const int bz, const int nbx,
                         const int nby, const long n, __global ulong* flat)
{
    long f = get_global_id(0);
    if (f >= n) return;
    int bj = (int)(f % nby);
    long r = f / nby;
    int bi = (int)(r % nbx), k = (int)(r / nbx);
    uint lo = 0u, hi = 0u;
    for (int h = 0; h < 2; ++h) {
        int x = 2 * bi + h;
        if (x >= bx) break;
        long b = ((long)x * by + bj) * bz + (k >> 1);
        uint so = pairs[2 * b], nz = pairs[2 * b + 1];
        for (int row = 0; row < 4; ++row) {
            int src = (k & 1) * 16 + 4 * row, at = h * 4 + 8 * row;
            lo |= ((so >> src) & 0xFu) << at;
            hi |= ((nz >> src) & 0xFu) << at;
        }
    }
    flat[f] = (ulong)lo | ((ulong)hi << 32);
}

/* One ray's bits in one flat brick sent with one atomic_or when the ray leaves the brick (score_rays_flat);
 * only where some have entropy is the old word waited for, and the weights of the bits this ray set first
 * added. Word w = (k * nbx + bi) * nby + bj, bit (i & 7) | (j & 3) << 3 (backends/bricks.py, flat bricks). */
ALWAYS_INLINE long flush_flat(__global volatile uint* mine, const int w, const uint pending, const uint nz_w,
                              const int nbx, const int nby, const int ny, const int nz, __global const long* weights)
{
    if ((pending & nz_w) == 0u) {
        atomic_or(&mine[w], pending);
        return 0;
    }
    uint m = pending & ~atomic_or(&mine[w], pending) & nz_w;
    int bj = w % nby, r = w / nby;
    int bi = r % nbx, k = r / nbx;
    long sum = 0;
    while (m) {
        int b = (int)popcount((m & (~m + 1u)) - 1u);       /* index of the lowest set bit */
        long i = (long)(bi * 8 + (b & 7)), j = (long)(bj * 4 + (b >> 3));
        sum += weights[(i * ny + j) * nz + k];
        m &= m - 1u;
    }
    return sum;
}

/* One step's flat-brick bookkeeping (score_rays_flat, score_rays_gpu in score_gpu.cl; as the Warp CUDA score
 * kernel's): the brick's masks and the candidate's word are read on every step and kept on entering a brick,
 * the bits a ray sets in a brick are sent with one atomic_or when it leaves (flush_flat, whose sum goes to
 * *sum). Returns whether the walk's voxel stops the ray. The word is read through a plain pointer: bits only
 * get set, so a stale copy only filters what this ray sends (and NVIDIA's volatile loads skip L1). */
typedef struct {
    int cur;                  /* the brick's word, -1 before the first */
    uint seen, pending, nz_w; /* bits known set, bits this ray set and has not sent, the brick's nonzero bits */
} flat_marks_t;

ALWAYS_INLINE bool mark_flat(flat_marks_t* fm, const dda_t* st, __global uint* mine, __global const ulong* flat,
                             const int nbx, const int nby, const int ny, const int nz, __global const long* weights,
                             long* sum)
{
    int w = (st->iz * nbx + (st->ix >> 3)) * nby + (st->iy >> 2);
    bool change = w != fm->cur;
    if (change && fm->pending) *sum += flush_flat(mine, fm->cur, fm->pending, fm->nz_w, nbx, nby, ny, nz, weights);
    ulong m = flat[w];
    uint fresh = mine[w];
    fm->nz_w = (uint)(m >> 32);
    fm->seen = change ? fresh : fm->seen;
    fm->pending = change ? 0u : fm->pending;
    fm->cur = w;
    uint bit = 1u << (uint)((st->ix & 7) | ((st->iy & 3) << 3));
    fm->pending |= bit & ~fm->seen;
    fm->seen |= bit;
    return ((uint)m & bit) != 0u;
}

/* score_rays_flat (the GPU path, atomic strategy): the walk of mark_walk_bricked (dda_step, the same voxels)
 * with the Warp CUDA score kernel's bookkeeping (backends/warp/score_gpu.py): flat bricks of 8 x 4 x 1 voxels
 * (flat: the brick's occlusion bits low, nonzero-weight bits high), the brick's masks and the candidate's
 * word read on every step and kept on entering a brick, the bits a ray sets in a brick sent at once when it
 * leaves. The same sums and counts as mark_walk_bricked's per-voxel atomics, which it replaced on this path
 * because it was faster (bench/README.md, "What the studies found", dense rig, OpenCL on the GPU). */
__kernel void score_rays_flat(__global const real* rig, __global const real* sdir, const int L, const int CA,
                              const real t_max, const real s, const int nx, const int ny, const int nz,
                              const int nbx, const int nby, __global const ulong* flat,
                              __global const long* weights, __global uint* bits, const long words,
                              const int per_item, const int items, __global long* part_sum)
{
    int item = get_global_id(0);
    long p = get_global_id(1);
    if (item >= items) return;
    long n_rays = (long)L * CA;
    long r0 = (long)item * per_item;
    long r1 = r0 + per_item < n_rays ? r0 + per_item : n_rays;
    __global uint* mine = bits + p * words;
    long sum = 0;
    for (long r = r0; r < r1; ++r) {
        real o[3], d[3];
        rig_ray(rig, sdir, p, r, L, CA, o, d);
        dda_t st;
        if (!dda_init(&st, o[0], o[1], o[2], d[0], d[1], d[2], t_max, s, nx, ny, nz)) continue;
        int guard = nx + ny + nz;
        flat_marks_t fm = {-1, 0u, 0u, 0u};
        for (;;) {
            if (mark_flat(&fm, &st, mine, flat, nbx, nby, ny, nz, weights, &sum)) break;
            if (--guard <= 0 || !dda_step(&st)) break;
        }
        if (fm.pending) sum += flush_flat(mine, fm.cur, fm.pending, fm.nz_w, nbx, nby, ny, nz, weights);
    }
    part_sum[p * items + item] = sum;
}

/* global size (chunks, P): set bits of words [c * per, (c + 1) * per) of candidate p's bitset */
/* Set bits of each candidate's bitset, or (masked) of those whose voxel has a nonzero weight in another grid:
 * masks[q] is that grid's word q in the bitset's layout (flat bricks: occlusion bits low, nonzero-weight bits
 * high); for a grid of 0/1 weights (an indicator) that is its sum over the covered voxels. */
__kernel void count_bits(__global const uint* bits, const long words, const int per, const int chunks,
                         __global const ulong* masks, const int masked, __global long* part_cnt)
{
    int c = get_global_id(0);
    long p = get_global_id(1);
    if (c >= chunks) return;
    long w0 = (long)c * per, w1 = w0 + per < words ? w0 + per : words;
    __global const uint* mine = bits + p * words;
    long cnt = 0;
    if (masked) {
        for (long q = w0; q < w1; ++q) cnt += popcount(mine[q] & (uint)(masks[q] >> 32));
    } else {
        for (long q = w0; q < w1; ++q) cnt += popcount(mine[q]);
    }
    part_cnt[p * chunks + c] = cnt;
}

__kernel void score_walk(__global const real* rig, __global const real* sdir, const int L, const int CA,
                         const real t_max, GRID_ARGS, __global uint* bits, const long words, const int G)
{
    int g = get_global_id(0);
    long p = get_global_id(1);
    if (g >= G) return;
    long n_rays = (long)L * CA;
    long r0 = n_rays * g / G, r1 = n_rays * (g + 1) / G;
    __global uint* mine = bits + (p * G + g) * words;
    for (long r = r0; r < r1; ++r) {
        real o[3], d[3];
        rig_ray(rig, sdir, p, r, L, CA, o, d);
        DDA_WALK(o, d, t_max, mine[st.flat >> 5] |= 1u << (uint)(st.flat & 31));
    }
}

/* global size (chunks, P): chunk c of candidate p covers words [c * per, (c + 1) * per) */
__kernel void score_reduce(__global const uint* bits, const long words, const int G, const int per,
                           const int chunks, __global const long* weights, __global const uint* nonzero,
                           const int binary, const long n_voxels, __global long* part_sum, __global long* part_cnt)
{
    /* nonzero: bit b of word w set when voxel 32 w + b has a nonzero weight. Covered voxels are counted
       with popcount, and weights are read only for covered voxels with entropy (about 8 % of them on the
       default town): the sum is the same integer, with a tenth of the gathers */
    int c = get_global_id(0);
    long p = get_global_id(1);
    if (c >= chunks) return;
    long w0 = (long)c * per, w1 = w0 + per < words ? w0 + per : words;
    __global const uint* base = bits + p * G * words;
    long sum = 0, cnt = 0;
    for (long w = w0; w < w1; ++w) {
        uint u = 0;
        for (int g = 0; g < G; ++g) u |= base[(long)g * words + w];
        cnt += popcount(u);
        u &= nonzero[w];
        if (binary) {               /* every weight 0 or 1 (an indicator grid): the sum is the bits left */
            sum += popcount(u);
            continue;
        }
        while (u) {
            int b = 31 - clz(u & (~u + 1u));   /* index of the lowest set bit */
            u &= u - 1u;
            sum += weights[w * 32 + b];
        }
    }
    part_sum[p * chunks + c] = sum;
    part_cnt[p * chunks + c] = cnt;
}

__kernel void voxel_keys(__global const real* pts, const real s, const int nx, const int ny, const int nz,
                         __global long* out, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    real fx = floor(pts[3 * (long)i] / s);
    real fy = floor(pts[3 * (long)i + 1] / s);
    real fz = floor(pts[3 * (long)i + 2] / s);
    bool in = fx >= (real)0 && fx < (real)nx && fy >= (real)0 && fy < (real)ny && fz >= (real)0 && fz < (real)nz;
    out[i] = in ? ((long)fx * ny + (long)fy) * nz + (long)fz : -1L;
}
