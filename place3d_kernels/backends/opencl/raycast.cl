/* Closest-hit ray casting through the host-built BVH (bvh.py). Needs common.cl in front and
 * -DSTACK_SIZE=<n> (the builder's proven inner-depth cap).
 *
 * - Front-to-back: both child boxes of a node are tested; the nearer child is descended, the farther
 *   pushed with its entry distance; a popped entry is skipped only if the box test would now reject it,
 *   i.e. with the box test's slack (entry > best * 1.0000004). Without the slack, a leaf whose (flat)
 *   box is entered a few ulps after a hit of equal or nearly equal float distance was dropped on pop
 *   but not on the way down, so at shared edges and vertices the face found depended on traversal order.
 * - Box test: slab test with the far distance scaled by 1 + 2*gamma(3) (Ize 2013, "Robust BVH Ray
 *   Traversal") so that rounding never culls a box the ray touches.
 * - Triangle test: Woop, Benthin & Wald 2013, "Watertight Ray/Triangle Intersection" (JCGT 2(1)):
 *   translate to the ray origin, permute so the dominant direction axis is z, shear, and take the signs
 *   of the three 2D edge functions; in float32 without doubles (tri_hit), in float64 with them (tri_t64).
 * - Equal distances go to the lower original face id, so results do not depend on traversal order.
 * - With doubles (HAVE_FP64) the float32 tree only proposes triangles and float64 decides: every box test
 *   grows the box by a radius (``rad``, 4e-6 of the ray origin's and the mesh's coordinate reach) that
 *   covers the float32 rounding of the origin, the direction and the boxes, so no box culls a triangle
 *   the float64 ray meets; each proposed triangle gets the reference's float64 watertight test
 *   (backends/geometry.py, watertight_intersect, operation for operation); the smallest float64 t wins,
 *   ties to the lower face id. The hit and its face are then the reference's, bit for bit, whatever the
 *   tree and the order it is walked in. Without doubles the float32 test decides (and a face at a
 *   grazing angle or a near tie can differ from the reference's).
 * - A ray that would overflow the stack (impossible for trees of the builder; checked anyway) reports
 *   face -2 (and sets flag slot 3) and the host traces it again.
 * - With a face map (map_faces, ``raycast_checked``) faces are written as 64-bit integers, the API's dtype,
 *   so the host neither converts nor copies them again; without one, as 32-bit.
 */

#ifndef STACK_SIZE
#error "STACK_SIZE must be defined by the host"
#endif

typedef struct {
    float ox, oy, oz;         /* origin */
    float ix, iy, iz;         /* 1 / direction (components below 1e-20 clamped, box test only) */
    int kx, ky, kz;           /* axis permutation: kz = dominant direction axis */
    float sx, sy, sz;         /* shear constants */
    float lx, ly, lz;         /* origin + rad: subtracted from a box's low planes (the box grown by rad) */
    float hx, hy, hz;         /* origin - rad: subtracted from its high planes */
    float rad;                /* box growth (0 without doubles) */
#ifdef HAVE_FP64
    double dox, doy, doz;     /* the float64 ray: origin */
    int dkx, dky, dkz;        /* its axis permutation */
    double dsx, dsy, dsz;     /* its shear constants */
#endif
} ray_t;

ALWAYS_INLINE float comp3(float x, float y, float z, int k) { return k == 0 ? x : (k == 1 ? y : z); }

/* slab test of box lo/hi (6 floats at b) against [0, best]; tnear out */
ALWAYS_INLINE bool slab(__global const float* b, const ray_t* r, float best, float* tnear)
{
    float tx0 = (b[0] - r->lx) * r->ix, tx1 = (b[3] - r->hx) * r->ix;
    float ty0 = (b[1] - r->ly) * r->iy, ty1 = (b[4] - r->hy) * r->iy;
    float tz0 = (b[2] - r->lz) * r->iz, tz1 = (b[5] - r->hz) * r->iz;
    float tn = MAXF(MAXF(MINF(tx0, tx1), MINF(ty0, ty1)), MAXF(MINF(tz0, tz1), 0.0f));
    float tf = MINF(MINF(MAXF(tx0, tx1), MAXF(ty0, ty1)), MINF(MAXF(tz0, tz1), best)) * 1.0000004f;
    *tnear = tn;
    return tn <= tf;
}

/* Watertight test; `simd`: permute the vertices with one float4 shuffle each (x86 CPUs: a single
 * permute instruction) instead of nine scalar three-way selects (kept for GPUs, where a shuffle with a
 * run-time mask is not one instruction). Both give the same floats: a permutation of the same
 * differences. Lane w of a vertex row holds the face id bits or 0 and is never used. */
ALWAYS_INLINE bool tri_hit(__global const float* tri, const ray_t* r, float best, float* t_out, const bool simd)
{
    float Ax, Ay, Az, Bx, By, Bz, Cx, Cy, Cz;
    if (simd) {
        __global const float4* t4 = (__global const float4*)tri;   /* rows of 12 floats: 16-byte aligned */
        float4 o4 = (float4)(r->ox, r->oy, r->oz, 0.0f);
        uint4 pm = (uint4)(r->kx, r->ky, r->kz, 3);
        float4 a = shuffle(t4[0] - o4, pm), b = shuffle(t4[1] - o4, pm), c = shuffle(t4[2] - o4, pm);
        Az = a.z; Bz = b.z; Cz = c.z;
        Ax = a.x - r->sx * Az; Ay = a.y - r->sy * Az;
        Bx = b.x - r->sx * Bz; By = b.y - r->sy * Bz;
        Cx = c.x - r->sx * Cz; Cy = c.y - r->sy * Cz;
    } else {
        float ax = tri[0] - r->ox, ay = tri[1] - r->oy, az = tri[2] - r->oz;
        float bx = tri[4] - r->ox, by = tri[5] - r->oy, bz = tri[6] - r->oz;
        float cx = tri[8] - r->ox, cy = tri[9] - r->oy, cz = tri[10] - r->oz;
        Az = comp3(ax, ay, az, r->kz); Bz = comp3(bx, by, bz, r->kz); Cz = comp3(cx, cy, cz, r->kz);
        Ax = comp3(ax, ay, az, r->kx) - r->sx * Az; Ay = comp3(ax, ay, az, r->ky) - r->sy * Az;
        Bx = comp3(bx, by, bz, r->kx) - r->sx * Bz; By = comp3(bx, by, bz, r->ky) - r->sy * Bz;
        Cx = comp3(cx, cy, cz, r->kx) - r->sx * Cz; Cy = comp3(cx, cy, cz, r->ky) - r->sy * Cz;
    }
    float U = Cx * By - Cy * Bx;
    float V = Ax * Cy - Ay * Cx;
    float W = Bx * Ay - By * Ax;
    if ((U < 0.0f || V < 0.0f || W < 0.0f) && (U > 0.0f || V > 0.0f || W > 0.0f)) return false;
    float det = U + V + W;
    if (det == 0.0f) return false;
    float T = U * (r->sz * Az) + V * (r->sz * Bz) + W * (r->sz * Cz);
    float t = T / det;
    if (!(t >= 0.0f && t <= best)) return false;
    *t_out = t;
    return true;
}

#ifdef HAVE_FP64
ALWAYS_INLINE double comp3d(double x, double y, double z, int k) { return k == 0 ? x : (k == 1 ? y : z); }

/* Face f against the float64 ray with the reference's test and formula (Woop et al. in float64,
 * backends/geometry.py watertight_intersect): its t in [0, tm], or INFINITY for a miss. Components are
 * picked with selects, not private arrays indexed at run time (which CPUs keep in memory and GPUs in
 * local memory). */
ALWAYS_INLINE double tri_t64(__global const double* verts, __global const int* faces, int f, const ray_t* r,
                             double tm)
{
    const int kx = r->dkx, ky = r->dky, kz = r->dkz;
    __global const int* fv = faces + 3 * (long)f;
    __global const double* v0 = verts + 3 * (long)fv[0];
    __global const double* v1 = verts + 3 * (long)fv[1];
    __global const double* v2 = verts + 3 * (long)fv[2];
    double okx = comp3d(r->dox, r->doy, r->doz, kx), oky = comp3d(r->dox, r->doy, r->doz, ky);
    double okz = comp3d(r->dox, r->doy, r->doz, kz);
    double rz0 = comp3d(v0[0], v0[1], v0[2], kz) - okz;
    double rz1 = comp3d(v1[0], v1[1], v1[2], kz) - okz;
    double rz2 = comp3d(v2[0], v2[1], v2[2], kz) - okz;
    double px0 = (comp3d(v0[0], v0[1], v0[2], kx) - okx) - r->dsx * rz0;
    double py0 = (comp3d(v0[0], v0[1], v0[2], ky) - oky) - r->dsy * rz0;
    double px1 = (comp3d(v1[0], v1[1], v1[2], kx) - okx) - r->dsx * rz1;
    double py1 = (comp3d(v1[0], v1[1], v1[2], ky) - oky) - r->dsy * rz1;
    double px2 = (comp3d(v2[0], v2[1], v2[2], kx) - okx) - r->dsx * rz2;
    double py2 = (comp3d(v2[0], v2[1], v2[2], ky) - oky) - r->dsy * rz2;
    double u = px2 * py1 - py2 * px1;
    double v_ = px0 * py2 - py0 * px2;
    double w_ = px1 * py0 - py1 * px0;
    if ((u < 0.0 || v_ < 0.0 || w_ < 0.0) && (u > 0.0 || v_ > 0.0 || w_ > 0.0)) return INFINITY;
    double det = u + v_ + w_;
    if (det == 0.0) return INFINITY;
    double t = (u * (r->dsz * rz0) + v_ * (r->dsz * rz1) + w_ * (r->dsz * rz2)) / det;
    return (t >= 0.0 && t <= tm) ? t : INFINITY;
}
#endif

ALWAYS_INLINE void ray_init(ray_t* r, const real* od, const real* dd, const real reach)
{
    float dx = (float)dd[0], dy = (float)dd[1], dz = (float)dd[2];
    r->ox = (float)od[0]; r->oy = (float)od[1]; r->oz = (float)od[2];
    r->ix = 1.0f / (absf(dx) < 1e-20f ? (dx < 0.0f ? -1e-20f : 1e-20f) : dx);
    r->iy = 1.0f / (absf(dy) < 1e-20f ? (dy < 0.0f ? -1e-20f : 1e-20f) : dy);
    r->iz = 1.0f / (absf(dz) < 1e-20f ? (dz < 0.0f ? -1e-20f : 1e-20f) : dz);
    float adx = absf(dx), ady = absf(dy), adz = absf(dz);
    r->kz = 0;
    if (ady > adx) r->kz = 1;
    if (adz > comp3(adx, ady, adz, r->kz)) r->kz = 2;
    r->kx = r->kz == 2 ? 0 : r->kz + 1;
    r->ky = r->kx == 2 ? 0 : r->kx + 1;
    float dk = comp3(dx, dy, dz, r->kz);
    if (dk < 0.0f) { int tmp = r->kx; r->kx = r->ky; r->ky = tmp; }
    r->sx = comp3(dx, dy, dz, r->kx) / dk;
    r->sy = comp3(dx, dy, dz, r->ky) / dk;
    r->sz = 1.0f / dk;
    r->rad = 0.0f;
#ifdef HAVE_FP64
    /* the float64 ray, and its permutation and shear as the reference makes them */
    r->dox = od[0]; r->doy = od[1]; r->doz = od[2];
    double ax = absd(dd[0]), ay = absd(dd[1]), az = absd(dd[2]);
    int kz = 0;
    if (ay > ax) kz = 1;
    if (az > comp3d(ax, ay, az, kz)) kz = 2;
    int kx = kz == 2 ? 0 : kz + 1, ky = kx == 2 ? 0 : kx + 1;
    double ddz = comp3d(dd[0], dd[1], dd[2], kz);
    if (ddz < 0.0) { int tmp = kx; kx = ky; ky = tmp; }
    r->dkx = kx; r->dky = ky; r->dkz = kz;
    r->dsx = comp3d(dd[0], dd[1], dd[2], kx) / ddz;
    r->dsy = comp3d(dd[0], dd[1], dd[2], ky) / ddz;
    r->dsz = 1.0 / ddz;
    /* The float32 ray strays from the float64 one by a few float32 ulps of |origin| + t, and t <= about
     * 2 (|origin| + reach) for any point of the mesh; boxes round by an ulp of reach. 4e-6 of those
     * reaches (60 ulps) covers both with room for the slab test's own rounding. */
    double om = MAXF(MAXF(absd(od[0]), absd(od[1])), absd(od[2]));
    r->rad = (float)((om + reach + 1.0) * 4e-6);
#endif
    r->lx = r->ox + r->rad; r->ly = r->oy + r->rad; r->lz = r->oz + r->rad;
    r->hx = r->ox - r->rad; r->hy = r->oy - r->rad; r->hz = r->oz - r->rad;
}

#ifdef HAVE_FP64
/* closest float64 hit among the triangles of a leaf (equal distances to the lower original face id);
 * `best` is then the float bound of the box tests: the best distance plus the box growth */
ALWAYS_INLINE void leaf_hits64(__global const float* tris, int first, int count, const ray_t* r, double tm,
                               double* best64, float* best, int* best_face, __global const double* verts,
                               __global const int* faces)
{
    for (int j = first; j < first + count; ++j) {
        int f = as_int(tris[12 * (long)j + 3]);
        double t = tri_t64(verts, faces, f, r, tm);
        if (t < *best64 || (t == *best64 && t != INFINITY && f < *best_face)) {
            *best64 = t;
            *best_face = f;
            *best = (float)t + r->rad;
        }
    }
}
#endif

/* closest hit among the triangles of a leaf; equal distances go to the lower original face id */
ALWAYS_INLINE void leaf_hits(__global const float* tris, int first, int count, const ray_t* r, float* best,
                             int* best_face, const bool simd)
{
    for (int j = first; j < first + count; ++j) {
        __global const float* tri = tris + 12 * (long)j;
        float t;
        if (tri_hit(tri, r, *best, &t, simd)) {
            int f = as_int(tri[3]);
            if (t < *best || *best_face < 0 || f < *best_face) { *best = t; *best_face = f; }
        }
    }
}

/* one face result: 64-bit with a face map (out_face then holds two ints per ray), else 32-bit */
#define PUT_FACE(i, v) do { if (map_faces) ((__global long*)out_face)[i] = (long)(v); else out_face[i] = (v); } \
    while (0)

/* write the result (t_hit: the float64 distance with doubles, else the float one, which the host refines);
 * with a face map (map_faces), the caller's face id and the face's label instead of the uploaded face id */
ALWAYS_INLINE void store_hit(int i, bool overflow, real t_hit, int best_face, __global real* out_t,
                             __global int* out_face, __global int* out_label, __global const int* face_ids,
                             __global const int* face_labels, int map_faces)
{
    if (overflow) {
        out_t[i] = (real)INFINITY;
        PUT_FACE(i, -2);
        return;
    }
    out_t[i] = best_face >= 0 ? t_hit : (real)INFINITY;
    if (map_faces) {
        PUT_FACE(i, best_face >= 0 ? face_ids[best_face] : -1);
        out_label[i] = best_face >= 0 ? face_labels[best_face] : -1;
    } else {
        PUT_FACE(i, best_face);
    }
}

/* Read ray i as the caller gave it (float, or `real` when in_f32 is 0; o_step / t_step 0: one origin /
 * one bound for all rays), check it as the host's ops._check_od / _check_t would, and hand back the
 * shifted origin, the direction normalised by the host's rule, and min(t_max, 1e30) (the float32 BVH
 * needs a finite bound). A failed check stores 1 in its flag slot (every writer stores the same value, so
 * no atomic is needed; 0 origin, 1 direction or its norm, 2 t_max; slot 3, a stack overflow, is set at
 * RAY_STORE) and returns false: the host then redoes the call on its own path, which raises the error.
 *
 * The normalisation matches NumPy's bits with doubles: norm = sqrt((x*x + y*y) + z*z) as ops._row_norm
 * sums it, untouched when |norm - 1| <= 1e-12, else each component divided by the norm. FP_CONTRACT is
 * off (common.cl), so every product and sum rounds on its own as in NumPy; double sqrt and division are
 * correctly rounded in OpenCL C (no -cl-fast-relaxed-math or -cl-unsafe-math-optimizations is passed).
 * For float inputs the squares are exact in double anyway. Without doubles the rays are used as given
 * (the host only calls those devices with rays it has checked and normalised itself). */
ALWAYS_INLINE bool load_ray(int i, __global const void* orig, int o_step, __global const void* dir, int in_f32,
                            __global const real* t_max, int t_step, real sx, real sy, real sz,
                            __global int* flags, real* o, real* d, real* tm)
{
    long io = 3 * (long)i * o_step, id = 3 * (long)i;
    real ow[3], dw[3];
    for (int k = 0; k < 3; ++k) {
        ow[k] = in_f32 ? (real)((__global const float*)orig)[io + k] : ((__global const real*)orig)[io + k];
        dw[k] = in_f32 ? (real)((__global const float*)dir)[id + k] : ((__global const real*)dir)[id + k];
    }
    bool ok = true;
    if (!(isfinite(ow[0]) && isfinite(ow[1]) && isfinite(ow[2]))) { flags[0] = 1; ok = false; }
    real norm = sqrt(dw[0] * dw[0] + dw[1] * dw[1] + dw[2] * dw[2]);
    if (!(isfinite(dw[0]) && isfinite(dw[1]) && isfinite(dw[2]) && isfinite(norm)) || norm == (real)0) {
        flags[1] = 1;
        ok = false;
    }
    bool scale = false;
#ifdef HAVE_FP64
    scale = absd(norm - 1.0) > 1e-12;
#endif
    for (int k = 0; k < 3; ++k) d[k] = scale ? dw[k] / norm : dw[k];
    real t = t_max[(long)i * t_step];
    if (!(t >= (real)0)) { flags[2] = 1; ok = false; }   /* NaN fails this too */
    *tm = MINF(t, (real)1e30);
    o[0] = ow[0] - sx; o[1] = ow[1] - sy; o[2] = ow[2] - sz;
    return ok;
}

/* the entry points' shared arguments: rays as given (see load_ray), outputs, face map, flags; a grouped
 * tree (bvh.py, build_bvh's groups) when per_group > 0: ray i meets group g = first + i / per_group alone,
 * from its root (node g), with that group's shift (shifts[3g..3g+2]) instead of shx, shy, shz */
#define RAY_ARGS __global const void* orig, const int o_step, __global const void* dir, const int in_f32, \
    __global const real* t_max, const int t_step, const real shx, const real shy, const real shz, \
    __global const real* shifts, const int per_group, const int first, \
    __global real* out_t, __global int* out_face, __global int* out_label, __global const int* face_ids, \
    __global const int* face_labels, const int map_faces, __global int* flags, const int n
#define RAY_LOAD \
    int i = get_global_id(0); \
    if (i >= n) return; \
    int root = per_group > 0 ? first + i / per_group : 0; \
    real sx_ = per_group > 0 ? shifts[3 * (long)root] : shx; \
    real sy_ = per_group > 0 ? shifts[3 * (long)root + 1] : shy; \
    real sz_ = per_group > 0 ? shifts[3 * (long)root + 2] : shz; \
    real ray_o[3], ray_d[3], tmr; \
    if (!load_ray(i, orig, o_step, dir, in_f32, t_max, t_step, sx_, sy_, sz_, flags, ray_o, ray_d, &tmr)) { \
        out_t[i] = (real)INFINITY; PUT_FACE(i, -1); if (map_faces) out_label[i] = -1; return; \
    } \
    ray_t r; \
    ray_init(&r, ray_o, ray_d, REACH);
#define RAY_STORE if (overflow) flags[3] = 1; \
    store_hit(i, overflow, (real)T_HIT, best_face, out_t, out_face, out_label, face_ids, face_labels, map_faces)

/* With doubles: the mesh in float64 (shifted vertices, faces) and its reach (largest |coordinate|); the
 * best float64 distance, with `best` its float bound for the box tests (a hair above t_max at first). */
#ifdef HAVE_FP64
#define MESH_ARGS , __global const double* verts, __global const int* faces, const double reach
#define REACH reach
#define BEST_INIT double best64 = INFINITY; float best = (float)tmr * 1.00000024f + r.rad; int best_face = -1;
#define LEAF(simd) leaf_hits64(tris, ref, cnt, &r, tmr, &best64, &best, &best_face, verts, faces)
#define T_HIT best64
#else
#define MESH_ARGS
#define REACH 0.0f
#define BEST_INIT float best = (float)tmr * 1.00000024f; int best_face = -1;
#define LEAF(simd) leaf_hits(tris, ref, cnt, &r, &best, &best_face, simd)
#define T_HIT best
#endif

/* Binary BVH (bvh_width=2: the smaller stack). */
__kernel void raycast(__global const float* nodes, __global const float* tris, RAY_ARGS MESH_ARGS)
{
    RAY_LOAD
    BEST_INIT

    int st_ref[STACK_SIZE], st_cnt[STACK_SIZE];
    float st_t[STACK_SIZE];
    int sp = 0;
    int ref = root, cnt = 0;   /* the root, an inner node */
    bool overflow = false;
    for (;;) {
        if (cnt == 0) {
            __global const float* nd = nodes + 16 * (long)ref;
            float tn0, tn1;
            bool h0 = slab(nd, &r, best, &tn0);
            bool h1 = slab(nd + 6, &r, best, &tn1);
            int r0 = as_int(nd[12]), c0 = as_int(nd[13]), r1 = as_int(nd[14]), c1 = as_int(nd[15]);
            if (h0 && h1) {
                if (tn1 < tn0) {
                    int x = r0; r0 = r1; r1 = x;
                    x = c0; c0 = c1; c1 = x;
                    float y = tn0; tn0 = tn1; tn1 = y;
                }
                if (sp == STACK_SIZE) { overflow = true; break; }
                st_ref[sp] = r1; st_cnt[sp] = c1; st_t[sp] = tn1; sp++;
                ref = r0; cnt = c0;
                continue;
            }
            if (h0) { ref = r0; cnt = c0; continue; }
            if (h1) { ref = r1; cnt = c1; continue; }
        } else {
            LEAF(false);
        }
        bool found = false;
        while (sp > 0) {
            sp--;
            if (st_t[sp] <= best * 1.0000004f) { ref = st_ref[sp]; cnt = st_cnt[sp]; found = true; break; }
        }
        if (!found) break;
    }
    RAY_STORE;
}

#define VMIN(a, b) ((a) < (b) ? (a) : (b))
#define VMAX(a, b) ((a) > (b) ? (a) : (b))
/* order two (distance, ref, count) entries by distance */
#define CSWAP(ta, ra, ca, tb, rb, cb) do { if (tb < ta) { float t_ = ta; ta = tb; tb = t_; \
    int r_ = ra; ra = rb; rb = r_; r_ = ca; ca = cb; cb = r_; } } while (0)

/* 4-wide BVH (the default on every device): one node = four child boxes tested as float4 (SIMD), hit children visited nearest
 * first; the others are pushed farthest first. Stack bound: 3 entries per level, STACK4 = 3 * depth cap. */
__kernel void raycast4(__global const float4* nodes, __global const float* tris, RAY_ARGS MESH_ARGS)
{
    RAY_LOAD
    BEST_INIT
    float4 ix = (float4)(r.ix), iy = (float4)(r.iy), iz = (float4)(r.iz);
    /* offsets of the near planes in a node (lo_x = 0, hi_x = 1, lo_y = 2, ...); far = near ^ 1 */
    const int nx = r.ix < 0.0f ? 1 : 0, ny = r.iy < 0.0f ? 3 : 2, nz = r.iz < 0.0f ? 5 : 4;
    /* the origin subtracted from the near and the far planes: low planes take origin + rad, high ones
     * origin - rad (the box grown by rad; both equal the origin without doubles) */
    float4 nox = (float4)(nx ? r.hx : r.lx), noy = (float4)(ny & 1 ? r.hy : r.ly), noz = (float4)(nz & 1 ? r.hz : r.lz);
    float4 fox = (float4)(nx ? r.lx : r.hx), foy = (float4)(ny & 1 ? r.ly : r.hy), foz = (float4)(nz & 1 ? r.lz : r.hz);

    int st_ref[3 * STACK_SIZE], st_cnt[3 * STACK_SIZE];
    float st_t[3 * STACK_SIZE];
    int sp = 0;
    int ref = root, cnt = 0;   /* the root, an inner node */
    bool overflow = false;
    for (;;) {
        if (cnt == 0) {
            __global const float4* nd = nodes + 8 * (long)ref;
            /* near and far planes picked by the direction's signs: (lo - o) * i <= (hi - o) * i when
             * i > 0 (rounding is monotone), so this equals the min/max form bit for bit */
            float4 tn = VMAX(VMAX((nd[nx] - nox) * ix, (nd[ny] - noy) * iy), VMAX((nd[nz] - noz) * iz, (float4)(0.0f)));
            float4 tf = VMIN(VMIN((nd[nx ^ 1] - fox) * ix, (nd[ny ^ 1] - foy) * iy),
                             VMIN((nd[nz ^ 1] - foz) * iz, (float4)(best))) * (float4)(1.0000004f);
            int4 rf = as_int4(nd[6]), ct = as_int4(nd[7]);
            int4 hit = (tn <= tf) & (ct >= (int4)(0));
            /* misses get an infinite entry distance (a hit's is finite: tn <= tf <= best), so sorting
             * the four slots by distance puts the hit children first, nearest first; no hit: pop */
            int nh = -(hit.s0 + hit.s1 + hit.s2 + hit.s3);
            if (nh > 0) {
                float t0 = hit.s0 ? tn.s0 : INFINITY, t1 = hit.s1 ? tn.s1 : INFINITY;
                float t2 = hit.s2 ? tn.s2 : INFINITY, t3 = hit.s3 ? tn.s3 : INFINITY;
                int r0 = rf.s0, r1 = rf.s1, r2 = rf.s2, r3 = rf.s3;
                int c0 = ct.s0, c1 = ct.s1, c2 = ct.s2, c3 = ct.s3;
                if (nh == 1) {   /* the common case: no sort, nothing pushed */
                    ref = hit.s0 ? r0 : (hit.s1 ? r1 : (hit.s2 ? r2 : r3));
                    cnt = hit.s0 ? c0 : (hit.s1 ? c1 : (hit.s2 ? c2 : c3));
                    continue;
                }
                /* five compare-exchanges sort four keys (a sorting network: no private arrays, no loops) */
                CSWAP(t0, r0, c0, t1, r1, c1);
                CSWAP(t2, r2, c2, t3, r3, c3);
                CSWAP(t0, r0, c0, t2, r2, c2);
                CSWAP(t1, r1, c1, t3, r3, c3);
                CSWAP(t1, r1, c1, t2, r2, c2);
                if (sp + nh - 1 > 3 * STACK_SIZE) { overflow = true; break; }
                /* push farthest first, so that the nearer ones are popped first */
                if (nh == 4) { st_ref[sp] = r3; st_cnt[sp] = c3; st_t[sp] = t3; sp++; }
                if (nh >= 3) { st_ref[sp] = r2; st_cnt[sp] = c2; st_t[sp] = t2; sp++; }
                st_ref[sp] = r1; st_cnt[sp] = c1; st_t[sp] = t1; sp++;
                ref = r0; cnt = c0;
                continue;
            }
        } else {
            LEAF(true);
        }
        bool found = false;
        while (sp > 0) {
            sp--;
            if (st_t[sp] <= best * 1.0000004f) { ref = st_ref[sp]; cnt = st_cnt[sp]; found = true; break; }
        }
        if (!found) break;
    }
    RAY_STORE;
}
