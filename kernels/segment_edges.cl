// The segment-buffer shortcut of --z-samples (gpuslice/raster/segment_edges.py, SegmentEdgesKernel): the oriented
// segments of the crossings kernel (seg_layer, seg_points in mm, facet order) become the runs kernel's input, the
// edges of each layer in pixels relative to its tile, without chaining or nesting.
//
// The pixel coordinates are those of the polygon path bit for bit (gpuslice/raster/edges.py, _to_pixels and
// merge_layer_groups): u and v in double (correctly rounded operations, no fused multiply-add), minus the tile's
// integer corner (exact in double), rounded once to float. A layer's tile is the pixel box of its
// segments' start points (its loops' points), zero-length segments left out (a plane through a vertex: the point
// of a loop of one point, which the polygon path drops); K consecutive sub-planes share their tiles' union.
//   segment_bounds: one work-item per segment: floor(u), floor(v) of its start into the sub-plane's box (integer
//       atomic min/max: order-free) and one count for its layer group (sub-plane / K), whose value before it is the
//       segment's rank; boxes and counts are kept per stripe (_stripes.cl: neighbouring work-groups, which cut the
//       same planes, count apart);
//   host: the stripes' boxes and counts joined, the tiles, each group's and stripe's first slot (prefix sum of the
//       counts);
//   segment_scatter: one work-item per segment: its edge relative to the group's tile, at its stripe's first slot
//       plus its rank (the order inside a group is arbitrary: the runs depend only on the set of edges).
// Built only where the device has doubles (cl_khr_fp64); elsewhere the driver reports the shortcut unavailable.
#ifdef cl_khr_fp64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

// u = (x * au.x + y * au.y) + au.z, v likewise with av: RasterSpec.to_pixels_xy's formula, which _to_pixels's shorter
// one equals bit for bit (one coefficient is 0, and the sign of a zero product never reaches the sum)
inline double2 seg_pixel(const float x, const float y, const double4 au, const double4 av) {
    const double dx = (double)x, dy = (double)y;
    return (double2)((dx * au.x + dy * au.y) + au.z, (dx * av.x + dy * av.y) + av.z);
}

// A segment shorter than 2^-20 of its largest coordinate (at least 1 mm; 8 float32 ulps there), in float32 as the
// numpy twin computes it: where rounding can make points coincide or loops touch (a plane a few ulps from a vertex),
// which chaining and nesting then repair; its layer is cut the polygon way (segment_edges.py).
#define SEG_SHORT 9.5367431640625e-7f

// box[4 * (stripe * n_planes + s)] = (min floor u, max floor u, min floor v, max floor v) of sub-plane s (filled with
// INT_MAX, INT_MIN, INT_MAX, INT_MIN by the host); count[stripe * n_groups + s / k] += 1 for every segment, zero-length
// ones included, its value before that in rank[i]; short[s / k] = 1 where a segment is short (above).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void segment_bounds(const int n, __global const int *seg_layer, __global const float4 *seg_points, const double4 au,
                    const double4 av, const int k, const int n_planes, __global int *box, __global int *count,
                    __global int *short_, __global int *rank) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int s = seg_layer[i];
    const float4 p = seg_points[i];
    const int stripe = stripe_of(i);
    rank[i] = atomic_inc(count + stripe * (n_planes / k) + s / k);
    const float dx = p.z - p.x, dy = p.w - p.y;
    // |x| and max by selects, floor by truncation: PoCL's CPU device calls fabs, fmax and floor out of line (this
    // pass took ~1.6x as long with them: BENCHMARKS, "Runs pieces", eighth session; runs.cl says the same). Equal
    // here: the max is at least 1 (the sign of a zero never counts), and the pixel coordinates of a model on the
    // display are far below 2^31
    const float ax = p.x < 0.0f ? -p.x : p.x, ay = p.y < 0.0f ? -p.y : p.y;
    const float az = p.z < 0.0f ? -p.z : p.z, aw = p.w < 0.0f ? -p.w : p.w;
    const float m0 = ax > ay ? ax : ay, m1 = az > aw ? az : aw, m2 = m0 > m1 ? m0 : m1;
    const float m = (m2 > 1.0f ? m2 : 1.0f) * SEG_SHORT;
    if (dx * dx + dy * dy <= m * m) atomic_max(short_ + s / k, 1);
    if (p.x == p.z && p.y == p.w) return;
    const double2 uv = seg_pixel(p.x, p.y, au, av);
    const int iu = (int)uv.x, iv = (int)uv.y;
    const int fu = (double)iu > uv.x ? iu - 1 : iu, fv = (double)iv > uv.y ? iv - 1 : iv;
    __global int *b = box + 4 * ((long)stripe * n_planes + s);
    atomic_min(b, fu);
    atomic_max(b + 1, fu);
    atomic_min(b + 2, fv);
    atomic_max(b + 3, fv);
}

// edges[4 * (first[stripe * n_groups + g] + rank[i]) ...] = (u0 - c0, v0 - r0, u1 - c0, v1 - r0) as floats,
// g = seg_layer / k, (r0, c0) = corner[g].
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void segment_scatter(const int n, __global const int *seg_layer, __global const float4 *seg_points, const double4 au,
                     const double4 av, const int k, const int n_groups, __global const int *first,
                     __global const int2 *corner, __global const int *rank, __global float *edges) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int g = seg_layer[i] / k;
    const float4 p = seg_points[i];
    const int2 rc = corner[g];
    const double r0 = (double)rc.x, c0 = (double)rc.y;
    const double2 s = seg_pixel(p.x, p.y, au, av), e = seg_pixel(p.z, p.w, au, av);
    const int slot = first[stripe_of(i) * n_groups + g] + rank[i];
    // vstore4, not `edges[slot] = (float4)(...)`: the same 16 bytes, without the store of `undef` clang 14 makes
    // of the latter, which Oclgrind's uninitialised-value check reports (as in crossings.cl)
    vstore4((float4)((float)(s.x - c0), (float)(s.y - r0), (float)(e.x - c0), (float)(e.y - r0)), (size_t)slot, edges);
}

#pragma OPENCL EXTENSION cl_khr_fp64 : disable
#endif
