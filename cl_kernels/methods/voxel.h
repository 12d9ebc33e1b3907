/* voxel.h: what the voxel pipeline's kernels (voxel.cl) share with the host.
 *
 * VoxRay is a view ray handed between the straight tracer (outside the grid) and the
 * viewing pass (inside it); mirrored by VOX_RAY in clscatter/methods/voxel/grid.py and
 * checked by tests/test_voxel_grid.py (layout test). */
#ifndef CLSCATTER_VOXEL_H
#define CLSCATTER_VOXEL_H
#include "common.h"
#include "bvh.h"
#include "lights.h"
#include "specular.h"

/* flags (low 4 bits of VoxRay.flags; the specular depth is stored above them) */
#define VOX_SKIP_FIRST 1   /* first straight piece already integrated by the viewing pass */

typedef struct {
    float4 o;          /* origin (on or in the grid box for the viewing pass) */
    float4 d;          /* unit direction */
    float4 thr;        /* rgb throughput, 1/spp and all attenuation so far included */
    int pixel;
    int sample;        /* camera sample index */
    int branch;        /* branch id within the sample's path tree */
    int flags;         /* (depth << 4) | VOX_* flags */
} VoxRay;

#endif
