// Resin layers as run-length runs (gpuslice/raster/runs.py, RunsKernel): the greys of raster.cl without a bitmap.
//
// Same float32 formulas and rint as raster_accumulate, so the integer contributions are identical. Passes:
//   runs_prep: one work-item per edge: an upper bound of the records it gives each of its rows, added to a
//       difference array over rows (integer atomics), and whether it is one work unit (<= 16 rows, <= 256 cells a
//       row: nearly all edges); host: two prefix sums -> each row's capacity and first slot (row_off);
//   runs_edges (whole edges) and runs_pieces (the host's units (edge, <= 16 rows, <= 256 columns) of the others):
//       every row piece written as (column, value) records, columns ascending and merged within the piece, into
//       its row's slice of recs (slot = row_off + an atomic cursor: the order inside a row is arbitrary, but all
//       downstream depends only on the multiset of records: integer sums, sorted by column); the cursors end as the
//       rows' record counts;
//   runs_rows: one work-item per row with <= RUNS_CH records: insertion sort by column in place, duplicate columns
//       summed, prefix sum, grey = lut[min(lut_max, |S| >> 8)] (lut_max 255, or 256*K-1 for K z samples), and
//       only the grey changes kept (longer rows: the host);
//   host: prefix sum of the run counts -> run_off;
//   runs_emit: one work-item per row: a run from each non-blank grey change to the next; display coordinates.
// Tiles: tiles[t] = (first global row of the tile, cols, display row of tile row 0, display column of tile col 0);
// tiles[L].x = the batch's rows (a sentinel: tile t has tiles[t + 1].x - tiles[t].x rows).
#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define RUNS_ONE 65536.0f
#ifndef RUNS_CH
#define RUNS_CH 256
#endif

// min/max of non-NaN floats (fmin/fmax may cost NaN handling; values equal up to the sign of a zero, which no
// integer result depends on)
#define RUNS_LO(a_, b_) ((a_) < (b_) ? (a_) : (b_))
#define RUNS_HI(a_, b_) ((a_) > (b_) ? (a_) : (b_))

// One row piece: the part (ys..ye, u from xs to xe, signed height dy) of an edge in row g of a tile w columns wide,
// cells c0..c1 only (c0 == INT_MIN: also the cells that do not come from the per-cell loop). Its records, columns
// ascending and merged (cell c gets d * (1 - xm) of its own step and d * xm of step c - 1), counted in closed form,
// go to off[g] + atomic_add(cnt + g, n), if they fit in the row's capacity (else the host sees cnt > capacity).
inline void runs_piece(const float xs, const float xe, const float dy, const int w, const int c0, const int c1,
                       const int g, __global int *cnt, __global const int *off, __global int2 *recs) {
    const float umin = RUNS_LO(xs, xe), umax = RUNS_HI(xs, xe);
    const int first = c0 == INT_MIN;
    int p;
    if (umin >= (float)w) return;
    if (umax <= 0.0f || umin == umax) {
        if (!first) return;
        const int c = umax <= 0.0f ? 0 : (int)floor(umin);
        const float xm = umax <= 0.0f ? 0.0f : umin - (float)c;
        const int n = 1 + (umax > 0.0f && c + 1 < w);
        if ((p = atomic_add(cnt + g, n)) + n > off[g + 1] - off[g]) return;
        __global int2 *o = recs + off[g] + p;
        if (umax <= 0.0f) {
            o[0] = (int2)(0, (int)rint(dy * RUNS_ONE));
            return;
        }
        o[0] = (int2)(c, (int)rint(dy * (1.0f - xm) * RUNS_ONE));
        if (n == 2) o[1] = (int2)(c + 1, (int)rint(dy * xm * RUNS_ONE));
        return;
    }
    const int ca = max(max(0, (int)floor(umin)), c0);
    const int cb = min(min(w - 1, (int)ceil(umax) - 1), c1);
    if (ca > cb) return;  // (never for the first column range: then ca = 0 <= cb whenever umin < 0)
    const int n = cb - ca + 1 + (cb + 1 < w);
    if ((p = atomic_add(cnt + g, n)) + n > off[g + 1] - off[g]) return;
    __global int2 *o = recs + off[g] + p;
    const float slope = dy / (umax - umin);
    int carry = first && umin < 0.0f ? (int)rint((0.0f - umin) * slope * RUNS_ONE) : 0;  // goes to cell 0 = ca
    for (int c = ca; c <= cb; ++c) {
        const float a = RUNS_HI(umin, (float)c), b = RUNS_LO(umax, (float)(c + 1));
        const float d = (b - a) * slope;
        const float xm = (a + b) * 0.5f - (float)c;
        o[c - ca] = (int2)(c, carry + (int)rint(d * (1.0f - xm) * RUNS_ONE));
        carry = (int)rint(d * xm * RUNS_ONE);
    }
    if (cb + 1 < w) o[cb + 1 - ca] = (int2)(cb + 1, carry);
}

// The pieces of edge e in its rows r0..r1 (columns c0..c1) as raster.cl cuts them: ys = max(va, r), ye = min(vb,
// r + 1), x = u0 + (y - v0) * dudv. For r > floor(va), ys = r = the previous row's ye, so its x is carried over.
inline void runs_rows_of(const float4 e, const int4 t, const int r0, const int r1, const int c0, const int c1,
                         __global int *cnt, __global const int *off, __global int2 *recs) {
    const float u0 = e.x, v0 = e.y, u1 = e.z, v1 = e.w;
    const float sgn = v1 > v0 ? 1.0f : -1.0f;
    const float va = fmin(v0, v1), vb = fmax(v0, v1);
    const float dudv = (u1 - u0) / (v1 - v0);
    float ys = fmax(va, (float)r0), xs = u0 + (ys - v0) * dudv;
    for (int r = r0; r <= r1; ++r) {
        const float ye = fmin(vb, (float)(r + 1));
        const float xe = u0 + (ye - v0) * dudv;
        if (ye > ys) runs_piece(xs, xe, (ye - ys) * sgn, t.y, c0, c1, t.x + r, cnt, off, recs);
        ys = ye;
        xs = xe;
    }
}

// units[u] = (edge, first row, last row, -), ucols[u] = (c0, c1); row_count: the rows' fill cursors.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_pieces(const int n_units, __global const int4 *units, __global const int2 *ucols,
                 __global const float4 *edges, __global const int *edge_tile, __global const int4 *tiles,
                 __global int *row_count, __global const int *row_off, __global int2 *recs) {
    const int gid = get_global_id(0);
    if (gid >= n_units) return;
    const int4 un = units[gid];
    const int2 cr = ucols[gid];
    runs_rows_of(edges[un.x], tiles[edge_tile[un.x]], un.y, un.z, cr.x, cr.y, row_count, row_off, recs);
}

// One work-item per edge: its rows ra..rb, whether it is one work unit (<= rows_max rows, <= cells_max cells a row:
// whole[e] = 1; the host cuts the others into units), and an upper bound of the records it gives each row,
// added as a difference over its rows: cap_diff[g0] += b, cap_diff[g1 + 1] -= b (integer atomics: order-free).
// A row piece spans |xe - xs| <= |dudv| * 1.002 + 0.05 columns (ye - ys <= 1; float32 errors: y - v0 rounded by
// <= 2^-11 (tile-local v < 2^14), times |dudv|, twice; u < 2^14: < 0.002 more each), so <= floor(that) + 2 cells and one
// record more; each further column range of a cut edge adds a record; a row has at most w + ranges - 1 records.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_prep(const int n_edges, const int rows_max, const int cells_max, const int extra,
               __global const float4 *edges, __global const int *edge_tile, __global const int4 *tiles,
               __global uchar *whole, __global int *cap_diff) {
    const int gid = get_global_id(0);
    if (gid >= n_edges) return;
    const float4 e = edges[gid];
    const int k = edge_tile[gid];
    const int4 t = tiles[k];
    const float va = fmin(e.y, e.w), vb = fmax(e.y, e.w);
    const int ra = max(0, (int)floor(va)), rb = min(tiles[k + 1].x - t.x - 1, (int)ceil(vb) - 1);
    if (e.y == e.w || rb < ra) {
        whole[gid] = 1;  // no pieces
        return;
    }
    const float ad = fabs((e.z - e.x) / (e.w - e.y));
    const float span = fabs(e.z - e.x);
    whole[gid] = rb - ra < rows_max && fmin(span, ad) + 2.0f <= (float)cells_max;
    const int ncc = (int)fmin(span + 3.0f, (float)t.y) / cells_max + 1;  // >= the host's column ranges of this edge
    const int b = max(min((int)floor(fmin(ad * 1.002f + 0.05f, (float)t.y)) + 3, t.y + 1) + ncc - 1 + extra, 0);
    atomic_add(cap_diff + t.x + ra, b);
    atomic_sub(cap_diff + t.x + rb + 1, b);
}

// One work-item per edge with whole[e] = 1: its pieces written (the cut edges: runs_pieces over the host's units).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_edges(const int n_edges, __global const uchar *whole, __global const float4 *edges,
                __global const int *edge_tile, __global const int4 *tiles, __global int *row_count,
                __global const int *row_off, __global int2 *recs) {
    const int gid = get_global_id(0);
    if (gid >= n_edges || !whole[gid]) return;
    const float4 e = edges[gid];
    if (e.y == e.w) return;
    const int k = edge_tile[gid];
    const int4 t = tiles[k];
    const int ra = max(0, (int)floor(fmin(e.y, e.w))), rb = min(tiles[k + 1].x - t.x - 1, (int)ceil(fmax(e.y, e.w)) - 1);
    runs_rows_of(e, t, ra, rb, INT_MIN, INT_MAX, row_count, row_off, recs);
}

// lut has lut_max + 1 entries: 256, or 256*K for a layer averaged over K sub-planes (z samples): its records are the
// K sub-layers' records together, and lut[i] = gamma_lut[i / K], so lut[min(lut_max, |S| >> 8)] is the grey of the
// mean coverage floor(256 * |S| / (65536 * K)), exactly.
inline uchar runs_grey(__global const uchar *lut, const uint lut_max, const int s) {
    return lut[min(lut_max, (uint)abs(s) >> 8)];
}

// One work-item per global row: sort its records by column in place (<= RUNS_CH of them: insertion sort), sum equal
// columns, and keep only where the grey changes: recs[a + j] = (column, grey from there on), row_m = how many,
// row_runs = how many of them start a non-blank run (row_m = -1: more than ch records, the host finishes the row).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_rows(const int n_rows, const int ch, __global const int *row_off, __global const int *row_count,
               __global int2 *recs, __global const uchar *lut, const int lut_max, __global int *row_m,
               __global int *row_runs) {
    const int g = get_global_id(0);
    if (g >= n_rows) return;
    const int a = row_off[g], n = row_count[g];
    if (n > ch || n > RUNS_CH) {
        row_m[g] = -1;
        row_runs[g] = 0;
        return;
    }
    __global int2 *buf = recs + a;  // a row's records are few and contiguous
    for (int i = 1; i < n; ++i) {
        const int2 v = buf[i];
        int j = i;
        while (j > 0 && buf[j - 1].x > v.x) {
            buf[j] = buf[j - 1];
            --j;
        }
        buf[j] = v;
    }
    // cell (pc, pv) pending; a grey change is written at k <= the cells finished so far < i: records not yet read
    // are never overwritten
    const uchar zero = lut[0];
    uchar prev = zero;
    int s = 0, k = 0, runs = 0, pc = n > 0 ? buf[0].x : 0, pv = 0;
    for (int i = 0; i <= n; ++i) {
        const int2 v = i < n ? buf[i] : (int2)(INT_MAX, 0);
        if (v.x == pc) {
            pv += v.y;
            continue;
        }
        s += pv;
        const uchar gr = runs_grey(lut, (uint)lut_max, s);
        if (gr != prev) {
            buf[k++] = (int2)(pc, gr);
            runs += gr != zero;
            prev = gr;
        }
        pc = v.x;
        pv = v.y;
    }
    row_m[g] = k;
    row_runs[g] = runs;
}

// One work-item per global row with row_m > 0: its runs at run_off[g] in display coordinates, from its grey changes.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_emit(const int n_rows, __global const int *row_off, __global const int2 *recs, __global const int *row_m,
               __global const int *row_tile, __global const int4 *tiles, __global const uchar *lut,
               __global const int *run_off, __global int *out_row, __global int *out_x, __global int *out_len,
               __global uchar *out_grey) {
    const int g = get_global_id(0);
    if (g >= n_rows) return;
    const int m = row_m[g];
    if (m <= 0) return;
    const int4 t = tiles[row_tile[g]];
    __global const int2 *c = recs + row_off[g];
    const int drow = t.z + (g - t.x);
    const uchar zero = lut[0];
    int k = run_off[g];
    for (int i = 0; i < m; ++i) {
        const int2 v = c[i];
        if ((uchar)v.y == zero) continue;
        out_row[k] = drow;
        out_x[k] = t.w + v.x;
        out_len[k] = (i + 1 < m ? c[i + 1].x : t.y) - v.x;
        out_grey[k] = (uchar)v.y;
        ++k;
    }
}
