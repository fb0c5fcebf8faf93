// Chaining on the device: slots of (edge, layer) crossings, the successor of every segment, per-layer segment
// lists, and a walk of each layer's chains (one work-item per layer).
//
// Canonical result (the same as gpuslice.chain.order_chains, the numpy reference): every open chain starts at its
// head (the segment without predecessor), every closed loop at its smallest segment index, chains by (layer, open
// before closed, first segment). Walking a host successor array, the walk emits a layer's chains in whatever order
// its list holds them and the driver sorts them (one key per chain); walking the device's own segments (`gather`:
// closed loops only) it sorts each layer's loops itself, so the output is deterministic either way.

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

// Per segment: its start and end slot; record the segment starting at each slot (a second start at one slot sets
// `conflict`: the driver then pairs on the host; a second end at one slot gives some segment two predecessors,
// which walk_layers finds: it meets a segment twice). Each layer's segment list is filled in STRIPES parts
// (_stripes.cl), segment s in part stripe_of(s): count s in its layer's part (part_count[stripe * n_layers + layer])
// and keep its rank there in `rank` (the driver passes the buffer that link_segments then fills with the
// successors: each reads its own entry before overwriting it).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void place_segments(__global const int *seg_layer, __global const int2 *seg_edges, const int n_segments,
                    __global const int *k0, __global const int *edge_off,
                    __global int *starter, __global int *end_slot,
                    __global int *part_count, const int n_layers, __global int *rank, __global int *conflict) {
    const int s = get_global_id(0);
    if (s >= n_segments) return;
    const int k = seg_layer[s];
    const int2 e = seg_edges[s];
    const int a = edge_off[e.x] + k - k0[e.x];
    const int b = edge_off[e.y] + k - k0[e.y];
    end_slot[s] = b;
    if (atomic_xchg(&starter[a], s) != -1) atomic_or(conflict, 1);
    rank[s] = atomic_inc(&part_count[stripe_of(s) * n_layers + k]);
}

// Per layer: its parts' counts turned into their first positions within the layer's list (in place), and the
// layer's total checked against layer_off (its counts came from the driver: wrong ones set `conflict`). With
// `write_totals`, the layer's total is written to `totals` instead (the driver did not know the counts).
__kernel
void part_starts(__global int *part_count, const int n_layers, __global const long *layer_off,
                 __global int *totals, const int write_totals, __global int *conflict) {
    const int k = get_global_id(0);
    if (k >= n_layers) return;
    int acc = 0;
    for (int p = 0; p < STRIPES; ++p) {
        const int c = part_count[p * n_layers + k];
        part_count[p * n_layers + k] = acc;
        acc += c;
    }
    if (write_totals) totals[k] = acc;
    else if (acc != layer_off[k + 1] - layer_off[k]) atomic_or(conflict, 2);
}

// Per segment: its successor and its place in its layer's list (its part's start plus its rank there: no atomics).
// A segment without successor (an open chain: the driver repairs those on the host) sets `conflict`; without that
// (or wrong layer counts), every segment has one successor, in its own layer (a slot is an edge's crossing of one
// layer). `next` holds the segments' ranks from place_segments on entry.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void link_segments(__global const int *seg_layer, __global const int *end_slot, const int n_segments,
                   __global const int *starter, __global const long *layer_off, __global const int *part_start,
                   const int n_layers, __global int *next, __global int *perm, __global int *conflict) {
    const int s = get_global_id(0);
    if (s >= n_segments) return;
    const int t = starter[end_slot[s]];
    const int r = next[s];
    next[s] = t;
    if (t < 0) atomic_or(conflict, 4);
    const int k = seg_layer[s];
    const long at = layer_off[k] + part_start[stripe_of(s) * n_layers + k] + r;
    if (at < layer_off[k + 1]) perm[at] = s;
    else atomic_or(conflict, 2);
}

// walk_layers, one work-item per layer: walk the chains of the segments listed in
// perm[layer_off[k] .. layer_off[k + 1]), writing them to the same range of `order`; start_flag marks each chain's
// first position (1: open chain, 2: closed loop; zeroed by the driver). Open chains are walked from their heads
// first; each closed loop is walked once from the first of its segments met in the list, then rotated in place to
// start at its smallest segment. Nothing is walked when `conflict` is set (the successors or the lists may be
// inconsistent: the driver then chains on the host). With `gather` (segments left on the device by the crossings
// kernel and linked by link_segments, so every chain is closed and has_prev is not read; seg_points: x0, y0, x1, y1
// each) the walk writes, in the canonical order itself (loops by smallest segment, each from it), every position's
// segment start point to `out` (x, y) and whether that segment has zero length (starts where it ends: the host
// drops its point, as the numpy path does) to `zero_length`, and not `order`: a first pass finds the loops and
// their smallest segments (written over the list entries it has read), which are sorted, and a second walks each
// from it. (Its helpers first.)

// the gather walk's output at position at: segment s's start point and whether s has zero length
inline void gather_put(__global const float *seg_points, __global float *out, __global uchar *zero_length,
                       const long at, const int s) {
    __global const float *q = seg_points + 4 * (long)s;
    const float x = q[0], y = q[1];
    out[2 * at] = x;
    out[2 * at + 1] = y;
    zero_length[at] = x == q[2] && y == q[3];
}

// reverse order[i .. j)
inline void walk_reverse(__global int *order, long i, long j) {
    for (--j; i < j; ++i, --j) {
        const int t = order[i];
        order[i] = order[j];
        order[j] = t;
    }
}

// v[root] moved down the max-heap v[0 .. n)
inline void walk_sift(__global int *v, long root, const long n) {
    const int x = v[root];
    for (;;) {
        long c = 2 * root + 1;
        if (c >= n) break;
        if (c + 1 < n && v[c + 1] > v[c]) ++c;
        if (v[c] <= x) break;
        v[root] = v[c];
        root = c;
    }
    v[root] = x;
}

// v[0 .. n) sorted ascending in place (heap sort: O(n log n) whatever the order)
inline void walk_sort(__global int *v, const long n) {
    for (long i = n / 2 - 1; i >= 0; --i) walk_sift(v, i, n);
    for (long e = n - 1; e > 0; --e) {
        const int t = v[0];
        v[0] = v[e];
        v[e] = t;
        walk_sift(v, 0, e);
    }
}

// the gather walk of one layer's loops (see walk_layers), in the canonical order; perm[a .. b) is overwritten
inline void walk_gather(__global const int *next, __global int *perm, const long a, const long b,
                        __global uchar *visited, __global uchar *start_flag, __global const float *seg_points,
                        __global float *out, __global uchar *zero_length, __global int *conflict) {
    long n_loops = 0, placed = 0;
    for (long i = a; i < b && placed < b - a; ++i) {  // each loop once, until every segment is placed
        const int s0 = perm[i];
        if (visited[s0]) continue;
        int m = s0, s = s0;
        do {
            // a segment met twice: the successors are no permutation (two segments ending at one slot); `conflict`
            // set, the driver chains on the host (without this test the walk would not come back to s0)
            if (visited[s]) {
                atomic_or(conflict, 8);
                return;
            }
            visited[s] = 1;
            ++placed;
            m = s < m ? s : m;
            s = next[s];
        } while (s != s0);
        perm[a + n_loops++] = m;  // (a + n_loops <= i: an entry already read)
    }
    walk_sort(perm + a, n_loops);
    long at = a;
    for (long j = 0; j < n_loops; ++j) {
        const int h = perm[a + j];
        start_flag[at] = 2;
        int s = h;
        do {
            gather_put(seg_points, out, zero_length, at++, s);
            s = next[s];
        } while (s != h);
    }
}

__kernel
void walk_layers(__global const int *next, __global const uchar *has_prev, __global int *perm,
                 __global const long *layer_off, const int n_layers,
                 __global uchar *visited, __global int *order, __global uchar *start_flag,
                 const int gather, __global const float *seg_points, __global float *out,
                 __global uchar *zero_length, __global int *conflict) {
    const int k = get_global_id(0);
    if (k >= n_layers || atomic_or(conflict, 0)) return;  // (an atomic read: other layers may set it meanwhile)
    const long a = layer_off[k], b = layer_off[k + 1];
    if (gather) {
        walk_gather(next, perm, a, b, visited, start_flag, seg_points, out, zero_length, conflict);
        return;
    }
    long at = a;
    for (long i = a; i < b; ++i) {  // open chains, from their heads
        int s = perm[i];
        if (has_prev[s]) continue;
        start_flag[at] = 1;
        while (s >= 0 && !visited[s]) {
            visited[s] = 1;
            order[at++] = s;
            s = next[s];
        }
    }
    for (long i = a; i < b && at < b; ++i) {  // closed loops, from their smallest segment (until all are placed)
        const int s0 = perm[i];
        if (visited[s0]) continue;
        const long first = at;
        long smallest = at;
        int m = s0, s = s0;
        do {
            // a segment met twice: some segment has two predecessors (never in the host's pairing)
            if (visited[s]) {
                atomic_or(conflict, 8);
                return;
            }
            visited[s] = 1;
            if (s < m) {
                m = s;
                smallest = at;
            }
            order[at++] = s;
            s = next[s];
        } while (s != s0);
        start_flag[first] = 2;
        if (smallest != first) {  // rotate [first, at) left to start at the smallest: three reversals
            walk_reverse(order, first, smallest);
            walk_reverse(order, smallest, at);
            walk_reverse(order, first, at);
        }
    }
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
// Points are read as scalars, here and in walk_layers: vector swizzles crash Oclgrind 21.10's
// uninitialised-value plugin (tests/kernels/test_oclgrind.py), and it mis-ran the chain-building loop below while
// that carried a float2 from one vertex to the next (wrong chains, every touching loop cleared; found by a helper's
// run on such loops): that loop keeps scalars, and the Oclgrind test checks the screen's answers.
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

// the next vertex index along a chain (up: increasing loop index), wrapping around the loop
inline long chain_step(long i, int up, long n) {
    i += up ? 1 : -1;
    return i == n ? 0 : (i < 0 ? n - 1 : i);
}

// chains A and B (ranges overlapping) apart: one merge of their vertices in sweep order over the common range,
// each vertex tested against the other chain's edge across it. Every tested vertex of A must lie strictly on one
// side of B (+1 left, -1 right) and every tested one of B strictly on the other side of A; a vertex both chains
// share (their common extreme) is skipped. Returns that side, 0 when no vertex was tested, SIDE_FAIL when a
// vertex lies on the other chain (or too close to call), when two vertices coincide, or the sides disagree.
#define SIDE_FAIL 2
inline int chain_pair(__global const float *p, long n, int swap, long sa, int la, int ua, long sb, int lb, int ub) {
    const float2 a_lo = sweep_point(p, chain_vertex(sa, la, ua, 0, n), swap);
    const float2 a_hi = sweep_point(p, chain_vertex(sa, la, ua, la, n), swap);
    const float2 b_lo = sweep_point(p, chain_vertex(sb, lb, ub, 0, n), swap);
    const float2 b_hi = sweep_point(p, chain_vertex(sb, lb, ub, lb, n), swap);
    const float2 hi = lex_less(a_hi, b_hi) ? a_hi : b_hi;
    // the first vertex of each in the common range: the chain starting later starts it
    const int b_later = lex_less(a_lo, b_lo);
    int ka = b_later ? chain_lower_bound(p, n, swap, sa, la, ua, b_lo) : 0;
    int kb = b_later ? 0 : chain_lower_bound(p, n, swap, sb, lb, ub, a_lo);
    long ia = chain_vertex(sa, la, ua, ka <= la ? ka : la, n), ib = chain_vertex(sb, lb, ub, kb <= lb ? kb : lb, n);
    float2 va = sweep_point(p, ia, swap), vb = sweep_point(p, ib, swap);
    // the vertex before each: the start of its edge across the other's next vertex (not used before it is set)
    float2 pa = ka > 0 ? sweep_point(p, chain_vertex(sa, la, ua, ka - 1, n), swap) : va;
    float2 pb = kb > 0 ? sweep_point(p, chain_vertex(sb, lb, ub, kb - 1, n), swap) : vb;
    int side = 0;
    for (;;) {
        const int a_in = ka <= la && !lex_less(hi, va), b_in = kb <= lb && !lex_less(hi, vb);
        int take_a = a_in, take_b = b_in;
        if (a_in && b_in) {
            if (va.x == vb.x && va.y == vb.y) {
                if (ia != ib) return SIDE_FAIL;  // two vertices in one place
            } else {
                take_a = lex_less(va, vb);
                take_b = !take_a;
            }
        }
        if (!take_a && !take_b) break;
        if (take_a && !take_b) {  // A's vertex against B's edge pb -> vb
            const int o = orient_sign(pb, vb, va);
            if (o == 0 || (side != 0 && o != side)) return SIDE_FAIL;
            side = o;
        } else if (take_b && !take_a) {  // B's vertex against A's edge pa -> va, on the other side
            const int o = -orient_sign(pa, va, vb);
            if (o == 0 || (side != 0 && o != side)) return SIDE_FAIL;
            side = o;
        }
        if (take_a && ++ka <= la) {
            pa = va;
            ia = chain_step(ia, ua, n);
            va = sweep_point(p, ia, swap);
        }
        if (take_b && ++kb <= lb) {
            pb = vb;
            ib = chain_step(ib, ub, n);
            vb = sweep_point(p, ib, swap);
        }
    }
    return side;
}

__kernel
void simple_loops(__global const float *points, __global const long *offsets, const int n_loops,
                  __global uchar *simple) {
    const int r = get_global_id(0);
    if (r >= n_loops) return;
    const long base = offsets[r], n = offsets[r + 1] - offsets[r];
    __global const float *p = points + 2 * base;  // x, y interleaved
    simple[r] = 0;
    if (n < 3) return;
    // count the extremes for both sweep orders (in one pass); a repeated consecutive point, or one not finite,
    // gives up
    int turns0 = 0, turns1 = 0;
    {
        float ax = p[2 * (n - 1)], ay = p[2 * (n - 1) + 1];
        float bx = p[0], by = p[1];
        int prev0 = ay < by || (ay == by && ax < bx);
        int prev1 = ax < bx || (ax == bx && ay < by);
        for (long i = 0; i < n; ++i) {
            ax = bx;
            ay = by;
            const long j = i + 1 == n ? 0 : i + 1;
            bx = p[2 * j];
            by = p[2 * j + 1];
            if ((ax == bx && ay == by) || !isfinite(ax) || !isfinite(ay)) return;
            const int up0 = ay < by || (ay == by && ax < bx);
            const int up1 = ax < bx || (ax == bx && ay < by);
            turns0 += up0 != prev0;
            turns1 += up1 != prev1;
            prev0 = up0;
            prev1 = up1;
        }
    }
    const int swap = turns1 < turns0;
    const int n_chains = swap ? turns1 : turns0;
    if (n_chains < 2 || n_chains > SIMPLE_MAX_CHAINS) return;
    long start[SIMPLE_MAX_CHAINS];
    int len[SIMPLE_MAX_CHAINS], dir[SIMPLE_MAX_CHAINS];
    int c = 0;
    float xmin[SIMPLE_MAX_CHAINS], xmax[SIMPLE_MAX_CHAINS];  // each chain's range across the sweep
    {
        // chain c starts at an extreme vertex i (the first found at i >= 0); each chain's range is gathered on
        // the way (the vertices before the first extreme belong to the last chain)
        float ax = p[swap], ay = p[1 - swap];
        const float lx = p[2 * (n - 1) + swap], ly = p[2 * (n - 1) + 1 - swap];
        int prev = ly < ay || (ly == ay && lx < ax);
        float x0 = ax, x1 = ax, pre0 = ax, pre1 = ax;
        for (long i = 0; i < n; ++i) {
            const long j = i + 1 == n ? 0 : i + 1;
            const float bx = p[2 * j + swap], by = p[2 * j + 1 - swap];
            x0 = fmin(x0, ax);
            x1 = fmax(x1, ax);
            const int up = ay < by || (ay == by && ax < bx);
            if (up != prev) {
                if (c == 0) {
                    pre0 = x0;
                    pre1 = x1;
                } else {
                    xmin[c - 1] = x0;
                    xmax[c - 1] = x1;
                }
                start[c] = i;
                dir[c] = up;
                ++c;
                x0 = ax;
                x1 = ax;
            }
            prev = up;
            ax = bx;
            ay = by;
        }
        xmin[c - 1] = fmin(x0, pre0);
        xmax[c - 1] = fmax(x1, pre1);
    }
    for (int k = 0; k < n_chains; ++k) {
        const long e = start[k + 1 == n_chains ? 0 : k + 1];
        len[k] = (int)(e > start[k] ? e - start[k] : e + n - start[k]);
    }
    for (int a = 0; a < n_chains; ++a) {
        const float2 a_lo = sweep_point(p, chain_vertex(start[a], len[a], dir[a], 0, n), swap);
        const float2 a_hi = sweep_point(p, chain_vertex(start[a], len[a], dir[a], len[a], n), swap);
        for (int b = a + 1; b < n_chains; ++b) {
            const float2 b_lo = sweep_point(p, chain_vertex(start[b], len[b], dir[b], 0, n), swap);
            const float2 b_hi = sweep_point(p, chain_vertex(start[b], len[b], dir[b], len[b], n), swap);
            if (lex_less(a_hi, b_lo) || lex_less(b_hi, a_lo)) continue;  // ranges apart along the sweep
            if (xmax[a] < xmin[b] || xmax[b] < xmin[a]) continue;        // or across it
            if (chain_pair(p, n, swap, start[a], len[a], dir[a], start[b], len[b], dir[b]) == SIDE_FAIL) return;
        }
    }
    simple[r] = 1;
}
#endif

// ---- the boxes of nesting's chunks (gpuslice.slicing.contain.Chunks, whose host twin computes the same): chunk c
// holds the edges start[c] .. end[c] - 1 of a loop, so its box spans the points start[c] .. end[c] - 1 and the last
// edge's end point nxt[c]; box[4c .. 4c + 3] = (x min, y min, x max, y max). One work-item per chunk (at most CHUNK
// points). A NaN met makes the bound NaN, as numpy's minimum and maximum do; of +0.0 and -0.0 the first met is kept
// (numpy may keep the other: the boxes are only compared). Scalars, as in simple_loops.
inline float chunk_min(const float a, const float p) {
    return (p < a || isnan(p)) ? p : a;
}

inline float chunk_max(const float a, const float p) {
    return (p > a || isnan(p)) ? p : a;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void chunk_boxes(__global const float *points, __global const long *start, __global const long *end,
                 __global const long *nxt, const int n_chunks, __global float *box) {
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const long k = nxt[c];
    float x0 = points[2 * k], y0 = points[2 * k + 1];
    float x1 = x0, y1 = y0;
    for (long i = start[c]; i < end[c]; ++i) {
        const float x = points[2 * i], y = points[2 * i + 1];
        x0 = chunk_min(x0, x);
        y0 = chunk_min(y0, y);
        x1 = chunk_max(x1, x);
        y1 = chunk_max(y1, y);
    }
    box[4 * c] = x0;
    box[4 * c + 1] = y0;
    box[4 * c + 2] = x1;
    box[4 * c + 3] = y1;
}
