/* primitives.cl: portable data-parallel building blocks (scan, bucket sort, compaction,
 * segmented sums, gather) for per-sample arrays that stay on the device.
 *
 * Host wrappers and the contracts live in clscatter/primitives.py; the tests in
 * tests/test_primitives.py compare every kernel with NumPy.
 *
 * Portability: OpenCL C 1.2 only. Plain __global buffers, no local memory, no barriers,
 * no recursion, int32 indices (sizes < 2^31). Every kernel guards `gid >= n`, so the
 * host may round global sizes up to a friendly multiple. The only atomics are the
 * 32-bit atomic_inc of the bucket-sort histogram and scatter; their ordering never
 * reaches a result (each bucket is sorted afterwards by a unique key).
 *
 * Floating point: FP_CONTRACT is off, so v * w + acc is two roundings (no fused
 * multiply-add) and segment sums equal a float32 sequential sum on the host bit for bit.
 */
#pragma OPENCL FP_CONTRACT OFF

/* ---- fill ---- */

__kernel void fill_int(__global int *buf, int n, int value) {
    int i = get_global_id(0);
    if (i < n) buf[i] = value;
}

/* ---- exclusive scan, three passes ----
 * scan_blocks: one work-item per block of `block` entries scans it sequentially into
 *   out[] (offsets relative to the block start) and writes the block's sum.
 *   nonzero != 0 scans (src[i] != 0) instead of src[i] (used by compaction).
 * scan_single: one work-item scans a short array (the block sums): dst has n + 1 entries.
 * scan_add: adds each block's offset; the work-item i == n writes the total out[n].
 */

__kernel void scan_blocks(__global const int *src, int n, int block, int nonzero,
                          __global int *out, __global int *block_sums) {
    int b = get_global_id(0);
    int nblocks = (n + block - 1) / block;
    if (b >= nblocks) return;
    int lo = b * block;
    int hi = min(n, lo + block);
    int acc = 0;
    for (int i = lo; i < hi; ++i) {
        int v = src[i];
        out[i] = acc;
        acc += nonzero ? (v != 0) : v;
    }
    block_sums[b] = acc;
}

__kernel void scan_single(__global const int *src, int n, __global int *dst) {
    if (get_global_id(0) != 0) return;
    int acc = 0;
    for (int i = 0; i < n; ++i) {
        dst[i] = acc;
        acc += src[i];
    }
    dst[n] = acc;
}

__kernel void scan_add(__global int *out, int n, int block,
                       __global const int *block_offsets) {
    int i = get_global_id(0);
    if (i > n) return;
    if (i == n) {
        out[n] = block_offsets[(n + block - 1) / block];
    } else {
        out[i] += block_offsets[i / block];
    }
}

/* ---- compaction: write index i at offsets[i] when flags[i] != 0 ---- */

__kernel void compact_write(__global const int *flags, __global const int *offsets, int n,
                            __global int *out) {
    int i = get_global_id(0);
    if (i < n && flags[i] != 0) out[offsets[i]] = i;
}

/* ---- bucket sort ---- */

/* Keys outside [0, nkeys) are clamped to the nearest end (documented in primitives.py). */
inline int clamp_key(int k, int nkeys) {
    return k < 0 ? 0 : (k >= nkeys ? nkeys - 1 : k);
}

/* A float as a uint whose unsigned order is the float order, with -0 == +0 and every
 * NaN (either sign, any payload) equal to each other and above +inf: the order of
 * NumPy's sort. Pure bit operations, so no compiler flag can change it. */
inline uint float_order_key(float f) {
    uint u = as_uint(f);
    if ((u & 0x7fffffffu) > 0x7f800000u) return 0xffffffffu;   /* NaN */
    if ((u & 0x7fffffffu) == 0u) u = 0u;                        /* -0 -> +0 */
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

__kernel void bucket_histogram(__global const int *keys, int n, int nkeys,
                               __global int *counts) {
    int i = get_global_id(0);
    if (i < n) atomic_inc(&counts[clamp_key(keys[i], nkeys)]);
}

/* cursor[k] starts at the first slot of bucket k. Each element goes to some slot of its
 * bucket (which one depends on atomic order) as the 64-bit sort key
 * (float_order_key(fkey[i]) << 32) | i, unique per element. */
__kernel void bucket_scatter(__global const int *keys, __global const float *fkey,
                             int use_fkey, int n, int nkeys, __global int *cursor,
                             __global ulong *slots) {
    int i = get_global_id(0);
    if (i >= n) return;
    int pos = atomic_inc(&cursor[clamp_key(keys[i], nkeys)]);
    ulong hi = use_fkey ? (ulong)float_order_key(fkey[i]) : 0ul;
    slots[pos] = (hi << 32) | (ulong)(uint)i;
}

#define INSERTION_MAX 24

inline void insertion_sort(__global ulong *a, int m) {
    for (int j = 1; j < m; ++j) {
        ulong v = a[j];
        int k = j - 1;
        while (k >= 0 && a[k] > v) {
            a[k + 1] = a[k];
            --k;
        }
        a[k + 1] = v;
    }
}

/* Restore the max-heap property below `root` of the heap a[0, end). */
inline void sift_down(__global ulong *a, int root, int end) {
    ulong v = a[root];
    int r = root;
    int last_parent = (end - 2) / 2;     /* nodes r <= last_parent have a child */
    while (end >= 2 && r <= last_parent) {
        int c = 2 * r + 1;
        if (c + 1 < end && a[c + 1] > a[c]) ++c;
        if (a[c] <= v) break;
        a[r] = a[c];
        r = c;
    }
    a[r] = v;
}

inline void heap_sort(__global ulong *a, int m) {
    for (int s = m / 2 - 1; s >= 0; --s) sift_down(a, s, m);
    for (int e = m - 1; e > 0; --e) {
        ulong t = a[0];
        a[0] = a[e];
        a[e] = t;
        sift_down(a, 0, e);
    }
}

/* One work-item per bucket: sort its slots ascending (insertion sort for short runs,
 * heapsort otherwise: O(m log m) worst case, no recursion, in place), then write the
 * original indices (the low 32 bits) to perm. */
__kernel void bucket_sort_runs(__global ulong *slots, __global const int *offsets,
                               int nkeys, __global int *perm) {
    int b = get_global_id(0);
    if (b >= nkeys) return;
    int lo = offsets[b];
    int m = offsets[b + 1] - lo;
    __global ulong *a = slots + lo;
    if (m <= INSERTION_MAX) insertion_sort(a, m);
    else heap_sort(a, m);
    for (int j = 0; j < m; ++j) perm[lo + j] = (int)(uint)(a[j] & 0xffffffffu);
}

/* ---- segmented sums: one work-item per output, sequential in index order ---- */

__kernel void segment_sums(__global const float4 *values, __global const float *weights,
                           int use_weights, __global const int *offsets, int nout,
                           __global float4 *out) {
    int s = get_global_id(0);
    if (s >= nout) return;
    int lo = offsets[s], hi = offsets[s + 1];
    float4 acc = (float4)(0.0f);
    if (use_weights) {
        for (int j = lo; j < hi; ++j) acc += values[j] * weights[j];
    } else {
        for (int j = lo; j < hi; ++j) acc += values[j];
    }
    out[s] = acc;
}

/* ---- gather of fixed-size records, one work-item per 32-bit word (or 16-byte quad) ----
 * dst record i = src record index[i]; an index outside [0, nsrc) gives a zero record. */

/* Records of a whole number of 16-byte quads (segments, hits): one work-item per
 * record, copying its quads in order. On the CPU device a 1.08 M x 64-byte permutation
 * takes ~50 ms this way against ~170 ms one word per work-item (whose 64-bit division
 * and four times as many items dominate); each item still reads whole cache lines. */
__kernel void gather_quads(__global const uint4 *src, int nsrc, __global const int *index,
                           int n, int quads, __global uint4 *dst) {
    int i = get_global_id(0);
    if (i >= n) return;
    int j = index[i];
    int ok = j >= 0 && j < nsrc;
    for (int w = 0; w < quads; ++w)
        dst[(size_t)i * quads + w] = ok ? src[(size_t)j * (size_t)quads + w] : (uint4)(0u);
}

__kernel void gather_words(__global const uint *src, int nsrc, __global const int *index,
                           int n, int words, __global uint *dst) {
    size_t gid = get_global_id(0);
    if (gid >= (size_t)n * (size_t)words) return;
    size_t i = gid / (size_t)words;
    size_t w = gid - i * (size_t)words;
    int j = index[i];
    dst[gid] = (j >= 0 && j < nsrc) ? src[(size_t)j * (size_t)words + w] : 0u;
}

/* ---- totals of int32 counters: lanes interleaved ints per record, n records; work-item
 * g sums records [g*per, (g+1)*per) of lane l into a 64-bit partial[g*lanes + l]
 * (64-bit integer arithmetic is core OpenCL C, atomics on it are not: no atomics). */

__kernel void int_totals(__global const int *values, int n, int lanes, int per,
                         int groups, __global long *partial) {
    int g = get_global_id(0);
    if (g >= groups) return;
    int lo = g * per, hi = min(n, lo + per);
    for (int l = 0; l < lanes; ++l) {
        long acc = 0;
        for (int i = lo; i < hi; ++i) acc += values[(size_t)i * lanes + l];
        partial[(size_t)g * lanes + l] = acc;
    }
}
