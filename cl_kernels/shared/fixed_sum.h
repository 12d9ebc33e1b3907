/* fixed_sum.h: exact sums of non-negative floats that many work-items add to at once.
 *
 * A sum is a 64-bit unsigned integer stored as two 32-bit words (acc[2 w]: low, acc[2 w +
 * 1]: high), in units of 1 / scale of the value summed. fixed_add rounds a term to units
 * once and adds it with one 64-bit atomic, or with OpenCL 1.2's 32-bit atomics: the low
 * word first, its carry (the low word wrapped) into the high word. Integer addition is associative, so the result
 * does not depend on the order the work-items add in, as a float sum (compare-and-swap)
 * would. The caller picks scale so that no sum reaches 2^64 (the host side's
 * FIXED_BITS = 62 leaves room for the rounding of every term). Used by the ray map's
 * splat (raymap.cl) and by line space gathering from the lighting side (lsg.cl). */
#ifndef CLSCATTER_FIXED_SUM_H
#define CLSCATTER_FIXED_SUM_H

/* add the non-negative value x (already times scale) to sum w: one 64-bit atomic where
 * the device has them (cl_khr_int64_base_atomics; the words of a little-endian ulong are
 * low, high), else two 32-bit ones. A build may define FIXED_SUM_WORDS to take the second
 * way on any device (tests compare the two). */
#if defined(cl_khr_int64_base_atomics) && defined(__ENDIAN_LITTLE__) && !defined(FIXED_SUM_WORDS)
#pragma OPENCL EXTENSION cl_khr_int64_base_atomics : enable
void fixed_add(volatile __global uint *acc, int w, float x) {
    ulong v = (ulong)(fmax(x, 0.0f) + 0.5f);
    if (v) atom_add((volatile __global ulong *)(acc + 2 * w), v);
}
#else
void fixed_add(volatile __global uint *acc, int w, float x) {
    ulong v = (ulong)(fmax(x, 0.0f) + 0.5f);
    uint lo = (uint)v, hi = (uint)(v >> 32);
    if (lo) {
        uint old = atomic_add(&acc[2 * w], lo);
        if (old + lo < old) hi += 1u;                    /* the low word's carry */
    }
    if (hi) atomic_add(&acc[2 * w + 1], hi);
}
#endif

/* sum w as a float, in units (divide by scale for the value) */
float fixed_read(__global const uint *acc, int w) {
    return convert_float(((ulong)acc[2 * w + 1] << 32) | (ulong)acc[2 * w]);
}

#endif
