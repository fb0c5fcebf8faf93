// Chaining on the device: slots of (edge, layer) crossings, the successor of every segment, per-layer segment
// lists, and a walk of each layer's chains (one work-item per layer).
//
// Canonical result (the same as gpuslice.chain.order_chains, the numpy reference): every open chain starts at its
// head (the segment without predecessor), every closed loop at its smallest segment index. The walk emits chains in
// whatever order the per-layer lists hold them (filled with atomics); the driver then sorts the chains by (layer,
// open before closed, first segment), which is cheap (one key per chain) and makes the output deterministic.

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

// Per mesh edge: the first layer it crosses and how many (from the per-vertex upper bounds ``vub``).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void edge_ranges(__global const int *vub, __global const int *edge_vertices, const int n_edges,
                 __global int *k0, __global int *count) {
    const int e = get_global_id(0);
    if (e >= n_edges) return;
    const int a = vub[edge_vertices[2 * e]], b = vub[edge_vertices[2 * e + 1]];
    k0[e] = min(a, b);
    count[e] = max(a, b) - min(a, b);
}

// Per segment: its start and end slot; record the segment starting at each slot and count the segments ending
// there (a second start or end at one slot sets `conflict`: the driver then pairs on the host); count per layer.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void place_segments(__global const int *seg_layer, __global const int2 *seg_edges, const int n_segments,
                    __global const int *k0, __global const int *edge_off,
                    __global int *starter, __global int *n_enders, __global int *end_slot,
                    __global int *layer_count, __global int *conflict) {
    const int s = get_global_id(0);
    if (s >= n_segments) return;
    const int k = seg_layer[s];
    const int2 e = seg_edges[s];
    const int a = edge_off[e.x] + k - k0[e.x];
    const int b = edge_off[e.y] + k - k0[e.y];
    end_slot[s] = b;
    if (atomic_xchg(&starter[a], s) != -1) atomic_or(conflict, 1);
    if (atomic_inc(&n_enders[b]) != 0) atomic_or(conflict, 1);
    atomic_inc(&layer_count[k]);
}

// Per segment: its successor, the predecessor flag of that successor, and its place in its layer's list.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void link_segments(__global const int *seg_layer, __global const int *end_slot, const int n_segments,
                   __global const int *starter, __global const long *layer_off, __global int *layer_fill,
                   __global int *next, __global uchar *has_prev, __global int *perm) {
    const int s = get_global_id(0);
    if (s >= n_segments) return;
    const int t = starter[end_slot[s]];
    next[s] = t;
    if (t >= 0) has_prev[t] = 1;
    const int k = seg_layer[s];
    perm[layer_off[k] + atomic_inc(&layer_fill[k])] = s;
}

// One work-item per layer: walk the chains of the segments listed in perm[layer_off[k] .. layer_off[k + 1]),
// writing them to the same range of `order`; start_flag marks each chain's first position (1: open chain,
// 2: closed loop; zeroed by the driver). Open chains are walked from their heads first; each closed loop is
// walked twice, once to find its smallest segment and once from there.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void walk_layers(__global const int *next, __global const uchar *has_prev, __global const int *perm,
                 __global const long *layer_off, const int n_layers,
                 __global uchar *visited, __global int *order, __global uchar *start_flag) {
    const int k = get_global_id(0);
    if (k >= n_layers) return;
    const long a = layer_off[k], b = layer_off[k + 1];
    long out = a;
    for (long i = a; i < b; ++i) {            // open chains, from their heads
        int s = perm[i];
        if (has_prev[s]) continue;
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
        int m = s0;
        for (int s = next[s0]; s != s0; s = next[s]) m = min(m, s);
        start_flag[out] = 2;
        int s = m;
        do {
            visited[s] = 1;
            order[out++] = s;
            s = next[s];
        } while (s != m);
    }
}
