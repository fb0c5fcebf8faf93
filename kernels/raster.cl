// Resin raster: exact area coverage of each layer's polygons over its tile of display pixels.
//
// Pixel coordinates are tile-local: column c covers u in [c, c+1), row r covers v in [r, r+1). Each edge
// (u0, v0) -> (u1, v1) is cut into pieces, one per row and then one per pixel cell; a piece of signed height dy
// whose mid-point lies at fraction xm across its cell adds dy * (1 - xm) to that cell and dy * xm to the next
// (the signed area to the right of the edge). Summed along a row, the accumulator gives the winding-weighted
// coverage of each pixel: exact area coverage for resolved polygons (winding 0 or 1). Pieces left of the tile give
// all of dy to column 0; pieces right of it are dropped. Sums are 16.16 fixed-point integers (order-independent
// atomics, so results are deterministic); a piece adds to the running sum its exact share rounded once at every
// cell, rint(S(c)) - rint(S(c - 1)) with S(c) = (a - umin) * slope + d * (1 - xm), not one rounding per cell
// (which drifted along long edges nearly parallel to the rows). The float64 twin is gpuslice.raster.coverage_numpy.
#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define RASTER_ONE 65536.0f

inline void raster_add(__global int *acc, const int base, const int w, const int r, const int c, const int a) {
    if (c < w) atomic_add(acc + base + r * w + c, a);
}

// tiles[t] = (pixel offset of the tile, cols, rows, first global row)
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void raster_accumulate(const int n_edges, __global const float4 *edges, __global const int *edge_tile,
                       __global const int4 *tiles, __global int *acc) {
    const int gid = get_global_id(0);
    if (gid >= n_edges) return;
    const float4 e = edges[gid];
    const int4 t = tiles[edge_tile[gid]];
    const int base = t.x, w = t.y, h = t.z;
    const float u0 = e.x, v0 = e.y, u1 = e.z, v1 = e.w;
    if (v0 == v1) return;
    const float sgn = v1 > v0 ? 1.0f : -1.0f;
    const float va = fmin(v0, v1), vb = fmax(v0, v1);
    const float dudv = (u1 - u0) / (v1 - v0);
    const int ra = max(0, (int)floor(va));
    const int rb = min(h - 1, (int)ceil(vb) - 1);
    for (int r = ra; r <= rb; ++r) {
        const float ys = fmax(va, (float)r), ye = fmin(vb, (float)(r + 1));
        if (!(ye > ys)) continue;
        const float xs = u0 + (ys - v0) * dudv, xe = u0 + (ye - v0) * dudv;
        const float dy = (ye - ys) * sgn;
        const float umin = fmin(xs, xe), umax = fmax(xs, xe);
        if (umax <= 0.0f) { raster_add(acc, base, w, r, 0, (int)rint(dy * RASTER_ONE)); continue; }
        if (umin >= (float)w) continue;
        if (umin == umax) {
            const int c = (int)floor(umin);
            const float xm = umin - (float)c;
            const int own = (int)rint(dy * (1.0f - xm) * RASTER_ONE);
            raster_add(acc, base, w, r, c, own);
            raster_add(acc, base, w, r, c + 1, (int)rint(dy * RASTER_ONE) - own);
            continue;
        }
        // the piece's share of the row's running sum after cell c, rounded once (see the file's head)
        const float slope = dy / (umax - umin);
        const int ca = max(0, (int)floor(umin));
        const int cb = min(w - 1, (int)ceil(umax) - 1);
        int done = 0;
        for (int c = ca; c <= cb; ++c) {
            const float a = fmax(umin, (float)c), b = fmin(umax, (float)(c + 1));
            const float d = (b - a) * slope;
            const float xm = (a + b) * 0.5f - (float)c;
            const int s = (int)rint(((a - umin) * slope + d * (1.0f - xm)) * RASTER_ONE);
            raster_add(acc, base, w, r, c, s - done);
            done = s;
        }
        raster_add(acc, base, w, r, cb + 1, (int)rint(dy * RASTER_ONE) - done);
    }
}

// One work-item per tile row: prefix sum along the row, grey = lut[min(255, floor(256 * |coverage|))], and the
// accumulator cleared for the next launch. Four pixels per step (vload4/vstore4 need only int alignment).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void raster_resolve(const int n_rows, __global const int *row_tile, __global const int4 *tiles,
                    __global int *acc, __global const uchar *lut, __global uchar *out) {
    const int gid = get_global_id(0);
    if (gid >= n_rows) return;
    const int4 t = tiles[row_tile[gid]];
    const int w = t.y;
    __global int *a = acc + t.x + (gid - t.w) * w;
    __global uchar *o = out + t.x + (gid - t.w) * w;
    int s = 0;
    int c = 0;
    for (; c + 4 <= w; c += 4) {
        const int4 v = vload4(0, a + c);
        vstore4((int4)(0), 0, a + c);
        const int s0 = s + v.x, s1 = s0 + v.y, s2 = s1 + v.z, s3 = s2 + v.w;
        s = s3;
        const uint4 k = min((uint4)(255u), convert_uint4(abs((int4)(s0, s1, s2, s3))) >> 8);
        vstore4((uchar4)(lut[k.x], lut[k.y], lut[k.z], lut[k.w]), 0, o + c);
    }
    for (; c < w; ++c) {
        s += a[c];
        a[c] = 0;
        o[c] = lut[min(255u, (uint)abs(s) >> 8)];
    }
}
