/* density_test.cl: test hooks for density.h (tests/test_density_kernels.py): the
 * sampling and the optical depths of a density buffer, one work-item per point or ray. */
#include "density.h"

__kernel void density_points(__global const Medium *medium, __global const float4 *p, int n,
                             __global float *dens, __global float4 *sigma_s) {
    int i = get_global_id(0);
    if (i >= n) return;
    dens[i] = density_at(density_grids(medium), density_values(medium), p[i]);
    sigma_s[i] = density_sigma_s(medium, p[i]);
}

__kernel void density_rays(__global const Medium *medium, __global const float4 *o,
                           __global const float4 *d, __global const float2 *span, int n,
                           __global float *integral, __global float *hom_len,
                           __global float4 *tau) {
    int i = get_global_id(0);
    if (i >= n) return;
    float t0 = span[i].x, t1 = span[i].y;
    integral[i] = density_integral(density_grids(medium), density_values(medium), o[i], d[i],
                                   t0, t1);
    hom_len[i] = homogeneous_length(medium, o[i], d[i], t0, t1);
    tau[i] = density_optical_depth(medium, o[i], d[i], t0, t1);
}
