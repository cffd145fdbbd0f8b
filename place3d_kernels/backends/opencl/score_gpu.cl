/* score_rays_gpu: the batched placement score on GPUs (atomic strategy). Needs common.cl and grid.cl in
 * front (dda_init, dda_step_slow, mark_flat, flush_flat, rig_ray), and 64-bit atomics for the per-candidate sums.
 *
 * The same walk, voxels, bitsets and sums as score_rays_flat, laid out as the Warp CUDA score kernel
 * (backends/warp/score_gpu.py), which is several times faster on the same GPU:
 *   - one ray per work-item (no loop over rays), in work-groups of SCORE_GROUP;
 *   - the float32 step's certainty test by the minimum and median of the three crossings (the same
 *     decision and axis as dda_step's chain of compares: the argument is at certain_step in score_gpu.py);
 *   - no grid test and no step counter in the loop: a walk ends only where dda_step_slow finds the next
 *     crossing at or after the clipped segment end (or, without doubles, leaving the grid), and the
 *     float32 step is taken only where it is certain to come before that end, which is at most the grid's
 *     exit (the clip's exit and the far plane's crossing are the same expression of the same operands);
 *   - the brick word and bit in 32-bit integers.
 * dda_t's other fields (the flat index, the step counter's inputs) are left to the compiler to drop. */

#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable

#ifndef SCORE_GROUP
#define SCORE_GROUP 128
#endif

/* One step of the walk: false when the segment ends in the current voxel. */
ALWAYS_INLINE bool dda_step_gpu(dda_t* st)
{
    float tx = st->tx, ty = st->ty, tz = st->tz;
    float a = MINF(tx, ty), b = MAXF(tx, ty);
    float tmin = MINF(a, tz);
    float med = MAXF(a, MINF(b, tz));
    float lim = tmin + st->tol;
    if (!(med > lim && st->t1 > lim)) return dda_step_slow(st);
    bool xa = tx == tmin;
    bool ya = !xa && ty == tmin;
    bool za = !xa && !ya;
    int di = xa ? st->sx : 0, dj = ya ? st->sy : 0, dk = za ? st->sz : 0;
    st->ix += di; st->iy += dj; st->iz += dk;
    st->kx += di; st->ky += dj; st->kz += dk;
    int k = xa ? st->kx : (ya ? st->ky : st->kz);
    float q = xa ? st->qx : (ya ? st->qy : st->qz);
    float v = xa ? st->vx : (ya ? st->vy : st->vz);
    float t = ((float)k * st->sf - q) * v;
    st->tx = xa ? t : tx;
    st->ty = ya ? t : ty;
    st->tz = za ? t : tz;
    return true;
}

__kernel __attribute__((reqd_work_group_size(SCORE_GROUP, 1, 1)))
void score_rays_gpu(__global const real* rig, __global const real* sdir, const int L, const int CA,
                    const real t_max, const real s, const int nx, const int ny, const int nz,
                    const int nbx, const int nby, __global const ulong* flat, __global const long* weights,
                    __global uint* bits, const long words, const int n_rays, __global long* sums)
{
    int r = get_global_id(0);
    int p = get_global_id(1);
    if (r >= n_rays) return;
    real o[3], d[3];
    rig_ray(rig, sdir, p, r, L, CA, o, d);
    dda_t st;
    if (!dda_init(&st, o[0], o[1], o[2], d[0], d[1], d[2], t_max, s, nx, ny, nz)) return;
    __global uint* mine = bits + (long)p * words;
    long sum = 0;
    flat_marks_t fm = {-1, 0u, 0u, 0u};
    for (;;) {
        if (mark_flat(&fm, &st, mine, flat, nbx, nby, ny, nz, weights, &sum)) break;
        if (!dda_step_gpu(&st)) break;
    }
    if (fm.pending) sum += flush_flat(mine, fm.cur, fm.pending, fm.nz_w, nbx, nby, ny, nz, weights);
    if (sum) atom_add(&sums[p], sum);
}
