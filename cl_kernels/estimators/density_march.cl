/* density_march.cl: raymarch.cl's kernel for a scene with density grids (density.h),
 * built with DENSITY_GRIDS: sigma_s at every sample from the grids, the view's
 * transmittance along the segment and the light's along every shadow ray as exact optical
 * depths through them, and samples at the middle of their strata (no jitter: a grid's
 * density varies along the segment, and jittered samples of it would be noise). The
 * `medium` buffer is density.h's layout; segments come from density_view.cl.
 */
#define DENSITY_GRIDS 1
#include "density.h"

#define light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin) \
    density_light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin)

#include "raymarch.cl"
