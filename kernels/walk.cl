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

// Per position i of the chain order: the start point of segment order[i], and whether that segment has zero
// length (starts where it ends: the host drops its point, as the numpy path does).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void gather_starts(__global const int *order, __global const float *seg_points, const int n,
                   __global float *out, __global uchar *zero_length) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const float *s = seg_points + 4 * (long)order[i];  // x0, y0, x1, y1
    const float x = s[0], y = s[1];
    out[2 * (long)i] = x;
    out[2 * (long)i + 1] = y;
    zero_length[i] = x == s[2] && y == s[3];
}

// ---- A screen for simple loops (nesting's self-crossing test runs GEOS only on the loops this cannot clear) ----
// One work-item per loop of points[offsets[r] .. offsets[r + 1]) (x, y float pairs, cyclic). simple[r] = 1 proves the loop
// simple: no two of its edges meet except consecutive ones at their shared vertex. 0 means "not proven" (it may
// cross or touch itself, or the screen gave up: more than SIMPLE_MAX_CHAINS monotone chains, a repeated point,
// an orientation too close to call), never "crossing". Method: a sweep in lexicographic order (y, then x; or x,
// then y when that gives fewer chains) cuts the loop at its local extremes into chains whose vertices strictly
// increase; a chain cannot cross itself, and two chains whose ranges overlap are disjoint (but for the vertex that
// adjacent chains share) exactly when every vertex of either within the other's range lies strictly on one and the
// same side of it (their x difference is linear between consecutive vertices). Orientations are float64 with an
// error bound (1e-12 relative, far above the rounding of the products), so a cleared loop is simple in exact
// arithmetic. Needs cl_khr_fp64; without it the kernel is absent and nesting tests every loop with GEOS.
// Points are read as scalars, here and in gather_starts: vector swizzles crash Oclgrind 21.10's
// uninitialised-value plugin (tests/kernels/test_oclgrind.py).
#if defined(cl_khr_fp64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#ifndef SIMPLE_MAX_CHAINS
#define SIMPLE_MAX_CHAINS 64
#endif

inline float2 sweep_point(__global const float *p, long i, int swap) {
    return (float2)(p[2 * i + swap], p[2 * i + 1 - swap]);
}

inline int lex_less(float2 a, float2 b) { return a.y < b.y || (a.y == b.y && a.x < b.x); }

// sign of the turn a -> b -> c (1 left, -1 right), 0 when the float64 value is within its error bound of zero
inline int orient_sign(float2 a, float2 b, float2 c) {
    const double abx = (double)b.x - (double)a.x, aby = (double)b.y - (double)a.y;
    const double acx = (double)c.x - (double)a.x, acy = (double)c.y - (double)a.y;
    const double l = abx * acy, r = aby * acx;
    const double det = l - r, bound = 1e-12 * (fabs(l) + fabs(r));
    return det > bound ? 1 : (det < -bound ? -1 : 0);
}

// the k-th vertex (0 .. len) of a chain in increasing sweep order; chains start at loop-local index s
inline long chain_vertex(long s, int len, int up, int k, long n) {
    const long i = up ? s + k : s + len - k;
    return i >= n ? i - n : i;
}

// the first k in 0 .. len whose chain vertex is not below t in sweep order (len + 1 if none)
inline int chain_lower_bound(__global const float *p, long n, int swap, long s, int len, int up, float2 t) {
    int lo = 0, hi = len + 1;
    while (lo < hi) {
        const int mid = (lo + hi) / 2;
        if (lex_less(sweep_point(p, chain_vertex(s, len, up, mid, n), swap), t)) lo = mid + 1;
        else hi = mid;
    }
    return lo;
}

// every vertex of chain A strictly inside B's range, or on its ends but not shared with B, against B's edges:
// accumulates the side (+1 / -1 times `flip`; 0: none yet) and returns it, or SIDE_FAIL when a vertex is on B or
// the sides disagree
#define SIDE_FAIL 2
inline int chain_side(__global const float *p, long n, int swap, long sa, int la, int ua, long sb, int lb, int ub,
                      int flip, int side) {
    const long b_lo = chain_vertex(sb, lb, ub, 0, n), b_hi = chain_vertex(sb, lb, ub, lb, n);
    const float2 lo = sweep_point(p, b_lo, swap), hi = sweep_point(p, b_hi, swap);
    const int k0 = chain_lower_bound(p, n, swap, sa, la, ua, lo);  // A's first vertex in B's range
    if (k0 > la) return side;
    // B's edge j runs from its vertex j to j + 1 (increasing): start at the last edge starting at or below A's k0
    int j = chain_lower_bound(p, n, swap, sb, lb, ub, sweep_point(p, chain_vertex(sa, la, ua, k0, n), swap));
    j = j > 0 ? j - 1 : 0;
    j = j < lb - 1 ? j : lb - 1;
    float2 b0 = sweep_point(p, chain_vertex(sb, lb, ub, j, n), swap);
    float2 b1 = sweep_point(p, chain_vertex(sb, lb, ub, j + 1, n), swap);
    for (int k = k0; k <= la; ++k) {
        const long iv = chain_vertex(sa, la, ua, k, n);
        if (iv == b_lo || iv == b_hi) continue;  // the vertex adjacent chains share
        const float2 v = sweep_point(p, iv, swap);
        if (lex_less(v, lo)) continue;
        if (lex_less(hi, v)) break;
        while (lex_less(b1, v) && j < lb - 1) {
            ++j;
            b0 = b1;
            b1 = sweep_point(p, chain_vertex(sb, lb, ub, j + 1, n), swap);
        }
        const int o = orient_sign(b0, b1, v) * flip;
        if (o == 0 || (side != 0 && o != side)) return SIDE_FAIL;
        side = o;
    }
    return side;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void simple_loops(__global const float *points, __global const long *offsets, const int n_loops,
                  __global uchar *simple) {
    const int r = get_global_id(0);
    if (r >= n_loops) return;
    const long base = offsets[r], n = offsets[r + 1] - offsets[r];
    __global const float *p = points + 2 * base;  // x, y interleaved
    simple[r] = 0;
    if (n < 3) return;
    // count the extremes for both sweep orders; a repeated consecutive point, or one not finite, gives up
    int turns0 = 0, turns1 = 0;
    for (int swap = 0; swap < 2; ++swap) {
        int prev = lex_less(sweep_point(p, n - 1, swap), sweep_point(p, 0, swap));
        for (long i = 0; i < n; ++i) {
            const float2 a = sweep_point(p, i, swap), b = sweep_point(p, i + 1 == n ? 0 : i + 1, swap);
            if ((a.x == b.x && a.y == b.y) || !isfinite(a.x) || !isfinite(a.y)) return;
            const int up = lex_less(a, b);
            if (swap) turns1 += up != prev; else turns0 += up != prev;
            prev = up;
        }
    }
    const int swap = turns1 < turns0;
    const int n_chains = swap ? turns1 : turns0;
    if (n_chains < 2 || n_chains > SIMPLE_MAX_CHAINS) return;
    long start[SIMPLE_MAX_CHAINS];
    int len[SIMPLE_MAX_CHAINS], dir[SIMPLE_MAX_CHAINS];
    int c = 0;
    int prev = lex_less(sweep_point(p, n - 1, swap), sweep_point(p, 0, swap));
    for (long i = 0; i < n; ++i) {  // chain c starts at an extreme vertex i (the first found at i >= 0)
        const int up = lex_less(sweep_point(p, i, swap), sweep_point(p, i + 1 == n ? 0 : i + 1, swap));
        if (up != prev) {
            start[c] = i;
            dir[c] = up;
            ++c;
        }
        prev = up;
    }
    float xmin[SIMPLE_MAX_CHAINS], xmax[SIMPLE_MAX_CHAINS];  // each chain's range across the sweep
    for (int k = 0; k < n_chains; ++k) {
        const long e = start[k + 1 == n_chains ? 0 : k + 1];
        len[k] = (int)(e > start[k] ? e - start[k] : e + n - start[k]);
        float x0 = INFINITY, x1 = -INFINITY;
        for (int i = 0; i <= len[k]; ++i) {
            const float x = sweep_point(p, chain_vertex(start[k], len[k], 1, i, n), swap).x;
            x0 = fmin(x0, x);
            x1 = fmax(x1, x);
        }
        xmin[k] = x0;
        xmax[k] = x1;
    }
    for (int a = 0; a < n_chains; ++a) {
        const float2 a_lo = sweep_point(p, chain_vertex(start[a], len[a], dir[a], 0, n), swap);
        const float2 a_hi = sweep_point(p, chain_vertex(start[a], len[a], dir[a], len[a], n), swap);
        for (int b = a + 1; b < n_chains; ++b) {
            const float2 b_lo = sweep_point(p, chain_vertex(start[b], len[b], dir[b], 0, n), swap);
            const float2 b_hi = sweep_point(p, chain_vertex(start[b], len[b], dir[b], len[b], n), swap);
            if (lex_less(a_hi, b_lo) || lex_less(b_hi, a_lo)) continue;  // ranges apart along the sweep
            if (xmax[a] < xmin[b] || xmax[b] < xmin[a]) continue;        // or across it
            int side = chain_side(p, n, swap, start[a], len[a], dir[a], start[b], len[b], dir[b], 1, 0);
            if (side == SIDE_FAIL) return;
            side = chain_side(p, n, swap, start[b], len[b], dir[b], start[a], len[a], dir[a], -1, side);
            if (side == SIDE_FAIL) return;
        }
    }
    simple[r] = 1;
}
#endif
