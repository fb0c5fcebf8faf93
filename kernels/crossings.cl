// Facet-plane crossings for all layers at once.
//
// On-plane rule (half-open): a vertex is BELOW plane p when v.z < p and ABOVE when v.z >= p. A vertex lying exactly
// on the plane therefore counts as above, and the section at p is the limit of the sections at p - eps as eps -> 0+.
// Every case of the paper's Fig. 3 follows from this one rule:
//   (a) vertex on the plane, others on one side: above-side -> no segment; below-side -> a zero-length segment
//       whose ends are both at that vertex (dropped when loops are built);
//   (b) edge on the plane: the facet counts as entirely above (no segment) or crosses through the two edges
//       meeting at its third, lower vertex; the edge is never a segment end, so each edge is shared consistently;
//   (c) plane through a vertex and the opposite edge: a segment from the opposite edge to the vertex;
//   (d) facet in the plane: all three vertices above, no segment (the face is not part of this section);
//   (e) plane through two edges: the ordinary case.
// So a facet crosses layer k iff zmin < z[k] <= zmax, its layers are [upper_bound(zmin), upper_bound(zmax)), and in
// each it has exactly one side going down (above -> below, in winding order) and one going up. The segment runs
// from the crossing of the downward side to the crossing of the upward side: for an outward-wound mesh that is
// counter-clockwise around material seen from +z.
//
// A crossing of edge (u, w) is computed from the endpoint with the smaller vertex id, so the two facets sharing an
// edge compute bit-identical points; an endpoint lying on the plane is returned exactly.

// No fused multiply-add and correctly rounded division (build option), so every device and the numpy
// reference compute bit-identical points.
#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

// first index i in [0, n) with zs[i] > value (n if none)
inline int upper_bound(__global const float *zs, const int n, const float value) {
    int lo = 0, hi = n;
    while (lo < hi) {
        const int mid = (lo + hi) >> 1;
        if (zs[mid] > value) hi = mid; else lo = mid + 1;
    }
    return lo;
}

inline float2 edge_point(__global const float *verts, int a, int b, const float p) {
    const int u = min(a, b), w = max(a, b);
    const float zu = verts[3 * u + 2], zw = verts[3 * w + 2];
    const float2 pu = (float2)(verts[3 * u], verts[3 * u + 1]);
    const float2 pw = (float2)(verts[3 * w], verts[3 * w + 1]);
    if (zw == p) return pw;
    if (zu == p) return pu;
    const float t = (p - zu) / (zw - zu);
    return (float2)(pu.x + t * (pw.x - pu.x), pu.y + t * (pw.y - pu.y));
}

// Per vertex: the first layer whose plane is above it (upper_bound of its z). upper_bound is monotone, so the
// layers a facet or an edge crosses follow from its vertices' values by min and max, with no further search.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void vertex_layers(__global const float *verts, const int n_verts, __global const float *zs, const int n_layers,
                   __global int *vub) {
    const int v = get_global_id(0);
    if (v >= n_verts) return;
    vub[v] = upper_bound(zs, n_layers, verts[3 * v + 2]);
}

// Per facet: the first layer it crosses and how many (layers k with zmin < zs[k] <= zmax).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void count_crossings(__global const int *vub, __global const int *faces, const int n_faces,
                     __global int *first_layer, __global int *count) {
    const int f = get_global_id(0);
    if (f >= n_faces) return;
    const int a = vub[faces[3 * f]], b = vub[faces[3 * f + 1]], c = vub[faces[3 * f + 2]];
    const int lo = min(a, min(b, c));
    first_layer[f] = lo;
    count[f] = max(a, max(b, c)) - lo;
}

// One segment per crossed layer of facet f: layers lo .. lo + n - 1, written at out .. out + n - 1.
inline void emit_facet(__global const float *verts, __global const int *faces, __global const int *face_edges,
                       __global const float *zs, const int f, const int lo, const int n, long out,
                       __global int *seg_layer, __global int *seg_edges, __global float4 *seg_points) {
    int v[3], e[3];
    float z[3];
    for (int k = 0; k < 3; ++k) {
        v[k] = faces[3 * f + k];
        e[k] = face_edges[3 * f + k];
        z[k] = verts[3 * v[k] + 2];
    }
    for (int j = 0; j < n; ++j, ++out) {
        const int layer = lo + j;
        const float p = zs[layer];
        int down = 0, up = 0;
        for (int k = 0; k < 3; ++k) {
            const int k1 = (k + 1) % 3;
            const bool below0 = z[k] < p, below1 = z[k1] < p;
            if (!below0 && below1) down = k;
            if (below0 && !below1) up = k;
        }
        const float2 a = edge_point(verts, v[down], v[(down + 1) % 3], p);
        const float2 b = edge_point(verts, v[up], v[(up + 1) % 3], p);
        seg_layer[out] = layer;
        // seg_edges holds int2 pairs. vstore2, not `seg_edges[out] = (int2)(...)`: the same 8 bytes, but clang 14
        // (Oclgrind's) lowers that store to a store of `undef` then two lane stores, which Oclgrind's
        // uninitialised-value check reports (jrprice/Oclgrind#126; tests/kernels/test_oclgrind.py)
        vstore2((int2)(e[down], e[up]), (size_t)out, seg_edges);
        seg_points[out] = (float4)(a.x, a.y, b.x, b.y);
    }
}

// Per facet: one segment per crossed layer, written at offsets[f] + j (offsets: exclusive scan of count).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void emit_segments(__global const float *verts, __global const int *faces, __global const int *face_edges,
                   const int n_faces, __global const float *zs,
                   __global const int *first_layer, __global const int *count, __global const long *offsets,
                   __global int *seg_layer, __global int *seg_edges, __global float4 *seg_points) {
    const int f = get_global_id(0);
    if (f >= n_faces) return;
    const int n = count[f];
    if (n == 0) return;
    emit_facet(verts, faces, face_edges, zs, f, first_layer[f], n, offsets[f], seg_layer, seg_edges, seg_points);
}

// The same for the facets ids[0 .. n_ids - 1] alone (a layer batch's: the others cross none of its planes); entry i
// has its first layer, count and offset at index i.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void emit_segments_of(__global const float *verts, __global const int *faces, __global const int *face_edges,
                      __global const int *ids, const int n_ids, __global const float *zs,
                      __global const int *first_layer, __global const int *count, __global const long *offsets,
                      __global int *seg_layer, __global int *seg_edges, __global float4 *seg_points) {
    const int i = get_global_id(0);
    if (i >= n_ids) return;
    const int n = count[i];
    if (n == 0) return;
    emit_facet(verts, faces, face_edges, zs, ids[i], first_layer[i], n, offsets[i], seg_layer, seg_edges, seg_points);
}
