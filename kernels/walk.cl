// Walk the successor graph of the segments into chains, one work-item per layer.
//
// Canonical order (the same as gpuslice.chain.order_chains, the numpy reference): within each layer, first the
// open chains, each from its head (a segment without predecessor), in increasing head index; then the closed
// loops, each from its smallest segment index, in increasing order. Segment ids of layer k are listed, increasing,
// in perm[layer_off[k] .. layer_off[k + 1]); the walk writes the chained segment ids to the same range of `order`
// and marks where each chain starts in `start_flag` (1: open chain, 2: closed loop); the driver zeroes it first.

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void walk_layers(__global const int *next, __global const uchar *has_prev, __global const int *perm,
                 __global const long *layer_off, const int n_layers,
                 __global uchar *visited, __global int *order, __global uchar *start_flag) {
    const int k = get_global_id(0);
    if (k >= n_layers) return;
    const long a = layer_off[k], b = layer_off[k + 1];
    long out = a;
    for (long i = a; i < b; ++i) {            // open chains, from their heads
        const int s0 = perm[i];
        if (has_prev[s0]) continue;
        int s = s0;
        start_flag[out] = 1;
        while (s >= 0 && !visited[s]) {
            visited[s] = 1;
            order[out++] = s;
            s = next[s];
        }
    }
    for (long i = a; i < b; ++i) {            // closed loops, from their smallest segment
        const int s0 = perm[i];
        if (visited[s0]) continue;
        int s = s0;
        start_flag[out] = 2;
        while (!visited[s]) {
            visited[s] = 1;
            order[out++] = s;
            s = next[s];
        }
    }
}
