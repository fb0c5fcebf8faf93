// Adaptive layer heights: per-facet slope data and per-slab maximum |n_z| (gpuslice.adaptive).
//
// adaptive_facets: per facet its z range and |n_z| of its unit normal from the winding, (b - a) x (c - a),
// computed in float32 in a fixed order (no FMA contraction, correctly rounded sqrt and division) so the numpy
// twin gives bit-identical values; |n_z| is 0 for a degenerate facet.
// adaptive_slab_blocks + adaptive_push_down: for slabs [edges[l], edges[l + 1]] (l < n_slabs, edges increasing),
// the largest |n_z| of the non-horizontal facets (zmax > zmin) that touch or overlap the slab: edges[l] <= zmax and
// edges[l + 1] >= zmin.
// Touching counts, so the float32 test is a superset of the exact test zmin < top, zmax > bottom in float64.
// Horizontal facets make no staircase and are skipped. |n_z| >= 0, so its bits order as unsigned integers and
// atomic_max on them is a float max; the table must start at 0.

#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

// The slabs' binary searches, started from a guess: `guide` (n_guide + 1 ints) holds, for bucket b of the edges'
// range [e0, e0 + n_guide / inv_w], an index near the first edge at or above the bucket's start (the host's
// guess: any index in [0, n] gives the same answer, only the steps change). From the guess the search gallops
// (steps 1, 2, 4, ... towards the answer) and then bisects the last step: exact for any sorted `a` and any guess,
// O(log distance) steps, one or two compares where the guide is good (uniform and adaptive schedules alike).
// A plain binary search over the 6,000 edges of 1.6M facets took ~100 ms of PoCL's two threads, most of the
// adaptive schedule's time.

// the guess for `value`: guide[bucket of value], the bucket clamped to [0, n_guide] in float first (NaN: 0)
inline int adaptive_guess(__global const int *guide, const int n_guide, const float e0, const float inv_w,
                          const float value) {
    const float t = (value - e0) * inv_w;
    return guide[t >= 0.0f ? (int)min(t, (float)n_guide) : 0];
}

// the first index i in [0, n) with a[i] >= value (upper: a[i] > value), n if none, from the guess g in [0, n]
inline int adaptive_bound(__global const float *a, const int n, const float value, const int g, const bool upper) {
    int lo, hi;  // the answer lies in [lo, hi]
#define ADAPTIVE_AT_OR_ABOVE(i) (upper ? a[i] > value : a[i] >= value)
    if (g > 0 && ADAPTIVE_AT_OR_ABOVE(g - 1)) {  // below g: a[hi] qualifies, gallop down
        hi = g - 1;
        int step = 1;
        lo = hi - step;
        while (lo >= 0 && ADAPTIVE_AT_OR_ABOVE(lo)) {
            hi = lo;
            step <<= 1;
            lo = hi - step;
        }
        lo = max(lo + 1, 0);  // a[lo - 1] does not qualify (or lo == 0)
    } else if (g < n && !ADAPTIVE_AT_OR_ABOVE(g)) {  // above g: a[lo - 1] does not qualify, gallop up
        lo = g + 1;
        int step = 1;
        hi = lo;
        while (hi < n && !ADAPTIVE_AT_OR_ABOVE(hi)) {
            lo = hi + 1;
            hi = lo + step;
            step <<= 1;
        }
        hi = min(hi, n);  // a[hi] qualifies (or hi == n)
    } else {
        return g;
    }
    while (lo < hi) {
        const int mid = (lo + hi) >> 1;
        if (ADAPTIVE_AT_OR_ABOVE(mid)) hi = mid; else lo = mid + 1;
    }
#undef ADAPTIVE_AT_OR_ABOVE
    return lo;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void adaptive_facets(__global const float *verts, __global const int *faces, const int n_faces,
                     __global float *zmin, __global float *zmax, __global float *nz) {
    const int f = get_global_id(0);
    if (f >= n_faces) return;
    const int ia = faces[3 * f], ib = faces[3 * f + 1], ic = faces[3 * f + 2];
    const float ax = verts[3 * ia], ay = verts[3 * ia + 1], az = verts[3 * ia + 2];
    const float bx = verts[3 * ib], by = verts[3 * ib + 1], bz = verts[3 * ib + 2];
    const float cx = verts[3 * ic], cy = verts[3 * ic + 1], cz = verts[3 * ic + 2];
    const float ux = bx - ax, uy = by - ay, uz = bz - az;
    const float vx = cx - ax, vy = cy - ay, vz = cz - az;
    const float nx = uy * vz - uz * vy;
    const float ny = uz * vx - ux * vz;
    const float nzz = ux * vy - uy * vx;
    const float len = sqrt((nx * nx + ny * ny) + nzz * nzz);
    nz[f] = len > 0.0f ? fabs(nzz) / len : 0.0f;
    zmin[f] = fmin(fmin(az, bz), cz);
    zmax[f] = fmax(fmax(az, bz), cz);
}

// Each facet touches a run [first, last) of slabs; it is covered by two blocks of 2^k slabs (k = floor(log2 of the
// run's length)), starting at first and at last - 2^k, and the facet's key goes into level k of a sparse table
// (n_levels rows of n_slabs) with two atomic_max. adaptive_push_down then pushes level j into level j - 1 (a block
// of 2^j slabs is two blocks of 2^(j-1)), from the top level down; row 0 ends as the per-slab maximum. Two atomics
// per facet instead of one per (facet, slab) pair.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void adaptive_slab_blocks(__global const float *zmin, __global const float *zmax, __global const float *nz,
                          const int n_faces, __global const float *edges, const int n_slabs,
                          __global const int *guide, const int n_guide, const float e0, const float inv_w,
                          __global volatile uint *table) {
    const int f = get_global_id(0);
    if (f >= n_faces) return;
    const float lo = zmin[f], hi = zmax[f];
    if (!(hi > lo)) return;
    // slabs l with edges[l + 1] >= lo and edges[l] <= hi: the first edge at or above lo (its slab is first) and the
    // first edge above hi (the slab below it is the last)
    const int first = max(adaptive_bound(edges, n_slabs + 1, lo, adaptive_guess(guide, n_guide, e0, inv_w, lo),
                                         false) - 1, 0);
    const int last = min(adaptive_bound(edges, n_slabs + 1, hi, adaptive_guess(guide, n_guide, e0, inv_w, hi),
                                        true), n_slabs);
    const int len = last - first;
    if (len <= 0) return;
    const int k = 31 - (int)clz((uint)len);
    const uint key = as_uint(nz[f]);
    atomic_max(&table[k * n_slabs + first], key);
    atomic_max(&table[k * n_slabs + last - (1 << k)], key);
}

// level >= 1: row level - 1 takes the max of itself, table[level][i] and table[level][i - 2^(level-1)] (a gather,
// so no two work-items write the same slot)
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void adaptive_push_down(__global uint *table, const int n_slabs, const int level) {
    const int i = get_global_id(0);
    if (i >= n_slabs) return;
    const int step = 1 << (level - 1);
    __global uint *up = table + level * n_slabs;
    __global uint *down = table + (level - 1) * n_slabs;
    uint v = max(down[i], up[i]);
    if (i >= step) v = max(v, up[i - step]);
    down[i] = v;
}
