/* Writing voxels of a prepared grid in place (OpenCLBackend.write_voxels): the jackknife's left-out grids
 * differ from each other in the rows of one record, so one grid on the device is rewritten there instead of
 * uploaded whole per grid. Each written voxel sets its weight (and stop byte), and sets or clears its bits in
 * the masks the score kernels read. Voxels are distinct, so no two work-items write one weight; bits of one
 * word are set by atomics, and setting or clearing distinct bits commutes.
 *
 * Row i's weight and stop byte are w[w_off + j] and s[s_off + j] with j = i, or j = gather[i] with GATHER set
 * (rows of a longer device array: the base's rows put back, OpenCLBackend.left_out_fields' rows); with
 * POSITIVE set the weight written is 1 where that weight is above 0, else 0 (the "uncertain" indicator). */

#define GATHER 1
#define POSITIVE 2

inline long row_of(const long i, __global const long* gather, const int flags)
{
    return (flags & GATHER) ? gather[i] : i;
}

inline long weight_of(__global const long* w, const long at, const int flags)
{
    const long x = w[at];
    return (flags & POSITIVE) ? (long)(x > 0) : x;
}

/* the private strategy's masks: bit b of word q for voxel 32 q + b (nonzero weights; stop when use_stop) */
__kernel void patch_private(__global const long* ids, __global const long* w, __global const uchar* s, const long n,
                            const long w_off, const long s_off, __global const long* gather, const int flags,
                            __global long* weights, __global uint* nonzero, const int use_stop,
                            __global uchar* stop, __global uint* stop_bits)
{
    long i = get_global_id(0);
    if (i >= n) return;
    long v = ids[i];
    long j = row_of(i, gather, flags);
    long wv = weight_of(w, w_off + j, flags);
    long q = v >> 5;
    uint bit = 1u << (uint)(v & 31);
    weights[v] = wv;
    if (wv != 0) atomic_or(&nonzero[q], bit); else atomic_and(&nonzero[q], ~bit);
    if (use_stop) {
        uchar sv = s[s_off + j];
        stop[v] = sv;
        if (sv) atomic_or(&stop_bits[q], bit); else atomic_and(&stop_bits[q], ~bit);
    }
}

/* the atomic strategy's brick pairs (backends/bricks.py, brick_masks): word 2b the occlusion bits of 4 x 4 x 2
 * brick b, 2b + 1 its nonzero-weight bits (flat_masks makes the score kernel's bricks from them afterwards) */
__kernel void patch_bricked(__global const long* ids, __global const long* w, __global const uchar* s, const long n,
                            const long w_off, const long s_off, __global const long* gather, const int flags,
                            __global long* weights, __global uint* pairs, const int use_stop, const int ny,
                            const int nz, const int by, const int bz)
{
    long i = get_global_id(0);
    if (i >= n) return;
    long v = ids[i];
    long at = row_of(i, gather, flags);
    long wv = weight_of(w, w_off + at, flags);
    long k = v % nz, r = v / nz;
    long j = r % ny, x = r / ny;
    long b = ((x >> 2) * by + (j >> 2)) * bz + (k >> 1);
    uint bit = 1u << (uint)((x & 3) | ((j & 3) << 2) | ((k & 1) << 4));
    weights[v] = wv;
    if (wv != 0) atomic_or(&pairs[2 * b + 1], bit); else atomic_and(&pairs[2 * b + 1], ~bit);
    if (use_stop) {
        if (s[s_off + at]) atomic_or(&pairs[2 * b], bit); else atomic_and(&pairs[2 * b], ~bit);
    }
}
