/* Backend.score_rays: explicit rays, each tagged with its candidate. Needs common.cl and grid.cl in front
 * (mark_walk_bricked over dda_init / dda_step, the walk every grid kernel shares, so covered sets equal
 * traverse's).
 *
 * One work-item per ray, as score_rays_flat: the ray marks its voxels in its candidate's bricked bitset
 * with atomic_or; the first marker of a voxel with entropy adds its weight to the ray's partial sum, so each
 * weight is added exactly once per candidate (the host adds the partial sums per candidate in int64, and
 * count_bits counts the covered voxels). Rays may have different segment ends (t_end per ray). */
__kernel void score_rays_csr(__global const real* orig, __global const real* dir, __global const real* t_end,
                             __global const int* cand, const real s, const int nx, const int ny, const int nz,
                             const int bny, const int bnz, __global const uint* masks,
                             __global const long* weights, __global uint* bits, const long words,
                             __global long* part_sum, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    real o[3] = {orig[3 * (long)i], orig[3 * (long)i + 1], orig[3 * (long)i + 2]};
    real d[3] = {dir[3 * (long)i], dir[3 * (long)i + 1], dir[3 * (long)i + 2]};
    long sum = mark_walk_bricked(o, d, t_end[i], s, nx, ny, nz, bny, bnz, masks, weights,
                                 bits + (long)cand[i] * words);
    part_sum[i] = sum;
}
