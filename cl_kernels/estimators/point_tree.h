/* point_tree.h: k nearest points over a balanced point kd-tree (the compact layout of
 * clscatter/estimators/segment_tree.py, SegmentTree.balanced and point_nodes): vpm's
 * photons (vpm.h) and the ray map's ray end points (raymap.cl, rm_kth_end).
 *
 * PointNode: the bounds of one node of a perfect binary tree stored breadth-first (node i
 * has children 2i+1, 2i+2; leaf j = node 2^levels - 1 + j holds the points
 * [floor(j n / 2^levels), floor((j + 1) n / 2^levels)) of the point array, which is
 * sorted by leaf). An empty tree is one root with the empty box (+1e30, -1e30).
 * Points are read as floats x, y, z at the start of records of `stride` floats (a float4
 * array: 4; vpm's 20-byte Photon: 5).
 *
 * The query keeps the k nearest points within the search radius in a bounded max-heap
 * (knn_heap.h, root = farthest kept point), visits the nearer child first and prunes every
 * box farther than the current search radius (r2_search until the heap is full, then the
 * heap's root). The traversal stack is explicit: one entry per level at most.
 */
#ifndef CLSCATTER_POINT_TREE_H
#define CLSCATTER_POINT_TREE_H
#include "common.h"
#include "knn_heap.h"

#define PT_STACK 48

typedef struct {
    float bmin[3];
    float bmax[3];
} PointNode;

float pt_point_dist2(__global const float *pts, int stride, int i, float4 p) {
    __global const float *q = pts + (size_t)i * (size_t)stride;
    float dx = q[0] - p.x, dy = q[1] - p.y, dz = q[2] - p.z;
    return dx * dx + dy * dy + dz * dz;
}

float pt_node_dist2(__global const PointNode *nd, float4 p) {
    float dx = fmax(fmax(nd->bmin[0] - p.x, p.x - nd->bmax[0]), 0.0f);
    float dy = fmax(fmax(nd->bmin[1] - p.y, p.y - nd->bmax[1]), 0.0f);
    float dz = fmax(fmax(nd->bmin[2] - p.z, p.z - nd->bmax[2]), 0.0f);
    return dx * dx + dy * dy + dz * dz;
}

/* The (at most) k points nearest to p with squared distance < r2_search, as a max-heap
 * (hd: squared distances, hi: indices into the sorted points); returns how many were
 * found. work[0] += boxes tested, work[1] += points tested (statistics). */
int pt_knn(__global const float *pts, int stride, int n, __global const PointNode *nodes,
           int levels, float4 p, float r2_search, int k, KNN_HEAP float *hd, KNN_HEAP int *hi,
           int *work) {
    int count = 0;
    float r2 = r2_search;
    if (n <= 0 || pt_node_dist2(&nodes[0], p) >= r2) return 0;
    int stack[PT_STACK];
    float sdist[PT_STACK];
    int sp = 0;
    int first_leaf = (1 << levels) - 1;
    int node = 0;
    while (1) {
        if (node >= first_leaf) {
            long j = node - first_leaf;
            int start = (int)((j * n) >> levels);
            int end = (int)(((j + 1) * n) >> levels);
            work[1] += end - start;
            for (int i = start; i < end; ++i) {
                float d2 = pt_point_dist2(pts, stride, i, p);
                if (d2 >= r2) continue;
                knn_heap_insert(hd, hi, &count, k, d2, i);
                if (count == k) r2 = hd[0];
            }
        } else {
            int c = 2 * node + 1;
            work[0] += 2;
            float da = pt_node_dist2(&nodes[c], p);
            float db = pt_node_dist2(&nodes[c + 1], p);
            int near = da <= db ? c : c + 1;
            float dn = fmin(da, db), df = fmax(da, db);
            if (df < r2 && sp < PT_STACK) {
                stack[sp] = near == c ? c + 1 : c;
                sdist[sp] = df;
                ++sp;
            }
            if (dn < r2) { node = near; continue; }
        }
        node = -1;
        while (sp > 0) {
            --sp;
            if (sdist[sp] < r2) { node = stack[sp]; break; }
        }
        if (node < 0) break;
    }
    return count;
}

#endif
