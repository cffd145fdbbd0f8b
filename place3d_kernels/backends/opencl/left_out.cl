/* The jackknife's left-out fields on the device (OpenCLBackend.left_out_fields), as Warp's left_out_kernels.py
 * computes them: for row r, the pool's count row rows[r] less the record's entries estart[r]..estart[r + 1]
 * of (ecls, ecnt), each count clipped into [0, T], the empty count T - (occupied), then the voxel's fixed-point
 * entropy weight and stop flag from the host's tables (left_out_tables.device_tables). Bit for bit the host's
 * FieldTables: every term comes from the table, the terms of a row are added in the order NumPy adds a row of an
 * (R, K) float64 array (for K >= 8 eight running sums over blocks of eight, combined pairwise, then the rest one
 * by one; below 8 one by one), and no multiply-add is contracted. Needs cl_khr_fp64. */
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

/* the pool's count of class k in this row, less the record's entry for k (a row has a few entries) */
inline int count_at(__global const int* counts, const int K, const long row, const int k, const int e0,
                    const int e1, __global const int* ecls, __global const int* ecnt)
{
    int c = counts[row * K + k];
    for (int e = e0; e < e1; ++e)
        if (ecls[e] == k) c -= ecnt[e];
    return c;
}

/* a base row some record touched can hold more than T subsets; a left-out row always lies in [0, T] */
inline int clip_t(const int c, const int t) { return max(min(c, t), 0); }

#define TERM(k) (term[tbase + ((k) == 0 ? c0 : clip_t(count_at(counts, K, row, (k), e0, e1, ecls, ecnt), t))])

__kernel void left_out_fields(__global const int* counts, const int K, __global const long* rows,
                              __global const int* estart, __global const int* ecls, __global const int* ecnt,
                              __global const int* row_t, __global const int* Ts, __global const double* term,
                              __global const uchar* stop_t, __global const double* other, const int tn,
                              const int det, const int veh, const double scale, const long R,
                              __global long* w_out, __global uchar* s_out)
{
    const long r = get_global_id(0);
    if (r >= R) return;
    const long row = rows[r];
    const int e0 = estart[r], e1 = estart[r + 1];
    const int ti = row_t[r];
    const long tbase = (long)ti * tn;
    int occ = 0;
    for (int k = 1; k < K; ++k) occ += count_at(counts, K, row, k, e0, e1, ecls, ecnt);
    const int t = Ts[ti];
    const int c0 = clip_t(t - occ, t);
    double h;
    if (det) {
        const int cv = veh < K ? clip_t(count_at(counts, K, row, veh, e0, e1, ecls, ecnt), t) : 0;
        h = ((-0.0 + term[tbase + c0]) + term[tbase + cv]) + other[(tbase + c0) * tn + cv];
    } else if (K < 8) {
        h = -0.0;
        for (int k = 0; k < K; ++k) h = h + TERM(k);
    } else {
        double r0 = TERM(0), r1 = TERM(1), r2 = TERM(2), r3 = TERM(3);
        double r4 = TERM(4), r5 = TERM(5), r6 = TERM(6), r7 = TERM(7);
        int i = 8;
        for (; i < K - K % 8; i += 8) {
            r0 = r0 + TERM(i); r1 = r1 + TERM(i + 1); r2 = r2 + TERM(i + 2); r3 = r3 + TERM(i + 3);
            r4 = r4 + TERM(i + 4); r5 = r5 + TERM(i + 5); r6 = r6 + TERM(i + 6); r7 = r7 + TERM(i + 7);
        }
        h = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7));
        for (; i < K; ++i) h = h + TERM(i);
    }
    w_out[r] = convert_long(rint(h * scale));
    s_out[r] = stop_t[tbase + c0];
}
