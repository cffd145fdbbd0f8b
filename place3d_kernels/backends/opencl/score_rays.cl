/* Backend.score_rays: explicit rays, each tagged with its candidate. Needs common.cl and grid.cl in front
 * (dda_init / dda_step, the walk every grid kernel shares, so covered sets equal traverse's).
 *
 * One work-item per ray, as score_rays_bricked: the ray marks its voxels in its candidate's bricked bitset
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
    __global const real* o = orig + 3 * (long)i;
    __global const real* d = dir + 3 * (long)i;
    __global volatile uint* mine = bits + (long)cand[i] * words;
    long sum = 0;
    dda_t st;
    if (dda_init(&st, o[0], o[1], o[2], d[0], d[1], d[2], t_end[i], s, nx, ny, nz)) {
        int guard = nx + ny + nz;
        for (;;) {
            long w = ((long)(st.ix >> 2) * bny + (st.iy >> 2)) * bnz + (st.iz >> 1);
            uint bit = 1u << (uint)((st.ix & 3) | ((st.iy & 3) << 2) | ((st.iz & 1) << 4));
            if (!(mine[w] & bit)) {
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
    }
    part_sum[i] = sum;
}
