/* Writing voxels of a prepared grid in place (OpenCLBackend.write_voxels): the jackknife's left-out grids
 * differ from each other in the rows of one record, so one grid on the device is rewritten there instead of
 * uploaded whole per grid. Each written voxel sets its weight (and stop byte), and sets or clears its bits in
 * the masks the score kernels read. Voxels are distinct, so no two work-items write one weight; bits of one
 * word are set by atomics, and setting or clearing distinct bits commutes. */

/* the private strategy's masks: bit b of word q for voxel 32 q + b (nonzero weights; stop when use_stop) */
__kernel void patch_private(__global const long* ids, __global const long* w, __global const uchar* s, const long n,
                            __global long* weights, __global uint* nonzero, const int use_stop,
                            __global uchar* stop, __global uint* stop_bits)
{
    long i = get_global_id(0);
    if (i >= n) return;
    long v = ids[i];
    long q = v >> 5;
    uint bit = 1u << (uint)(v & 31);
    weights[v] = w[i];
    if (w[i] != 0) atomic_or(&nonzero[q], bit); else atomic_and(&nonzero[q], ~bit);
    if (use_stop) {
        stop[v] = s[i];
        if (s[i]) atomic_or(&stop_bits[q], bit); else atomic_and(&stop_bits[q], ~bit);
    }
}

/* the atomic strategy's brick pairs (backends/bricks.py, brick_masks): word 2b the occlusion bits of 4 x 4 x 2
 * brick b, 2b + 1 its nonzero-weight bits (flat_masks makes the score kernel's bricks from them afterwards) */
__kernel void patch_bricked(__global const long* ids, __global const long* w, __global const uchar* s, const long n,
                            __global long* weights, __global uint* pairs, const int use_stop, const int ny,
                            const int nz, const int by, const int bz)
{
    long i = get_global_id(0);
    if (i >= n) return;
    long v = ids[i];
    long k = v % nz, r = v / nz;
    long j = r % ny, x = r / ny;
    long b = ((x >> 2) * by + (j >> 2)) * bz + (k >> 1);
    uint bit = 1u << (uint)((x & 3) | ((j & 3) << 2) | ((k & 1) << 4));
    weights[v] = w[i];
    if (w[i] != 0) atomic_or(&pairs[2 * b + 1], bit); else atomic_and(&pairs[2 * b + 1], ~bit);
    if (use_stop) {
        if (s[i]) atomic_or(&pairs[2 * b], bit); else atomic_and(&pairs[2 * b], ~bit);
    }
}
