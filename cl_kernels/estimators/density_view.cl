/* density_view.cl: the view paths of view_paths.cl in a scene with density grids
 * (density.h): the same kernels, rays, seeds and branching, with the medium's three
 * functions replaced by their density versions:
 *   medium_piece        -> density_piece: a branch's segment spans the scene medium and
 *                          every grid box it crosses
 *   branch_attenuation  -> density_branch_attenuation: exp(-optical depth), grids included
 *   light_transmission  -> density_light_transmission: shadow rays through the grids too,
 *                          so smoke shadows the surfaces behind it
 * The `medium` buffer is density.h's layout (the Medium record, the void record, the grids).
 */
#include "density.h"

#define medium_piece(m, br, t_hit, a, b) density_piece(m, br, t_hit, a, b)
#define branch_attenuation(m, materials, br, t_hit) \
    density_branch_attenuation(m, materials, br, t_hit)
#define light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin) \
    density_light_transmission(nodes, tris, light_grid, li, m, x, wi, dist, tmin)

#include "view_paths.cl"
