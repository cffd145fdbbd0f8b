/* Majority vote per voxel with open-addressing hash tables (32-bit atomics only). Needs common.cl.
 *
 * 1. vote_insert: every voting point (key >= 0, label > 0) puts its voxel key into table T (linear
 *    probing with atomic_cmpxchg) and remembers its slot.
 * 2. (host) the occupied slots, sorted by key, give each voxel its rank 0..M-1 (output order).
 * 3. vote_pairs: every voting point counts (rank * n_classes + label) in table T2.
 * 4. vote_best_count / vote_best_label: per rank, the largest count, then the lowest label with it.
 * Integer atomics only: the result does not depend on scheduling.
 */

inline uint hash32(uint x)
{
    x ^= x >> 16; x *= 0x7feb352dU;
    x ^= x >> 15; x *= 0x846ca68bU;
    x ^= x >> 16;
    return x;
}

inline int table_insert(__global volatile int* table, uint mask, int key)
{
    uint h = hash32((uint)key) & mask;
    for (;;) {  /* the table has at least twice as many slots as keys: always terminates */
        int old = atomic_cmpxchg(&table[h], -1, key);
        if (old == -1 || old == key) return (int)h;
        h = (h + 1) & mask;
    }
}

__kernel void vote_insert(__global const long* keys, __global const int* labels, __global volatile int* table,
                          const uint mask, __global int* slot, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    long k = keys[i];
    if (k < 0 || labels[i] <= 0) { slot[i] = -1; return; }
    slot[i] = table_insert(table, mask, (int)k);
}

__kernel void vote_pairs(__global const int* slot, __global const int* labels, __global const int* rank,
                         const int n_classes, __global volatile int* table, __global volatile int* count,
                         const uint mask, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    int sl = slot[i];
    if (sl < 0) return;
    int h = table_insert(table, mask, rank[sl] * n_classes + labels[i]);
    atomic_inc(&count[h]);
}

__kernel void vote_best_count(__global const int* table, __global const int* count, const int n_classes,
                              __global volatile int* best_count, const int n_slots)
{
    int j = get_global_id(0);
    if (j >= n_slots) return;
    int key = table[j];
    if (key < 0) return;
    atomic_max(&best_count[key / n_classes], count[j]);
}

__kernel void vote_best_label(__global const int* table, __global const int* count, const int n_classes,
                              __global const int* best_count, __global volatile int* best_label, const int n_slots)
{
    int j = get_global_id(0);
    if (j >= n_slots) return;
    int key = table[j];
    if (key < 0) return;
    int r = key / n_classes;
    if (count[j] == best_count[r]) atomic_min(&best_label[r], key - r * n_classes);
}

/* Dense variant, used when the largest key and the rank x class table are small enough (the usual case:
 * keys are voxels of one grid). vote_mark flags the voting voxels; the host's prefix sum of the flags
 * gives every voxel its rank in ascending order; vote_count_dense counts (rank, label) pairs in a dense
 * table and vote_argmax picks, per rank, the label with the largest count (the lowest label on ties). */
__kernel void vote_mark(__global const long* keys, __global const int* labels, __global uchar* mark, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    long k = keys[i];
    if (k >= 0 && labels[i] > 0) mark[k] = 1;
}

__kernel void vote_count_dense(__global const long* keys, __global const int* labels, __global const int* rank,
                               const int n_classes, __global volatile int* count, const int n)
{
    int i = get_global_id(0);
    if (i >= n) return;
    long k = keys[i];
    int lab = labels[i];
    if (k < 0 || lab <= 0) return;
    atomic_inc(&count[(long)rank[k] * n_classes + lab]);
}

__kernel void vote_argmax(__global const int* count, const int n_classes, __global int* best_label, const int m)
{
    int r = get_global_id(0);
    if (r >= m) return;
    __global const int* c = count + (long)r * n_classes;
    int best = 1, bc = c[1];
    for (int l = 2; l < n_classes; ++l) {
        if (c[l] > bc) { bc = c[l]; best = l; }
    }
    best_label[r] = best;
}
