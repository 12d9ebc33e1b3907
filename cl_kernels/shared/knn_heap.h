/* knn_heap.h: the bounded max-heap of (distance, index) behind every K-nearest query
 * (the ray map's, raymap.h; the volumetric photon map's, vpm.h).
 *
 * The heap keeps the k smallest distances seen so far with the largest at the root, so
 * the root is the current search bound once the heap is full. It lives in the address
 * space KNN_HEAP: private memory by default; an includer that needs larger heaps than a
 * work-item's private memory holds defines KNN_HEAP as __global before including this
 * file and hands each work-item its own slice of a scratch buffer.
 */
#ifndef CLSCATTER_KNN_HEAP_H
#define CLSCATTER_KNN_HEAP_H

#ifndef KNN_HEAP
#define KNN_HEAP
#endif

/* Restore the heap order below the root of a heap of `count` entries. */
void knn_heap_sift_down(KNN_HEAP float *hd, KNN_HEAP int *hx, int count) {
    int i = 0;
    for (;;) {
        int l = 2 * i + 1, r = l + 1, m = i;
        if (l < count && hd[l] > hd[m]) m = l;
        if (r < count && hd[r] > hd[m]) m = r;
        if (m == i) return;
        float td = hd[i]; hd[i] = hd[m]; hd[m] = td;
        int tx = hx[i]; hx[i] = hx[m]; hx[m] = tx;
        i = m;
    }
}

/* Offer (v, idx) to a heap of *count entries and capacity k: inserted while the heap
 * has room (sifted up), else it replaces the root when nearer than the root. */
void knn_heap_insert(KNN_HEAP float *hd, KNN_HEAP int *hx, int *count, int k, float v,
                     int idx) {
    if (*count < k) {
        int i = (*count)++;
        while (i > 0) {
            int p = (i - 1) / 2;
            if (hd[p] >= v) break;
            hd[i] = hd[p];
            hx[i] = hx[p];
            i = p;
        }
        hd[i] = v;
        hx[i] = idx;
    } else if (v < hd[0]) {
        hd[0] = v;
        hx[0] = idx;
        knn_heap_sift_down(hd, hx, *count);
    }
}

#endif
