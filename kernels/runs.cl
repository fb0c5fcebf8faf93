// Resin layers as run-length runs (gpuslice/raster/runs.py, RunsKernel): the greys of raster.cl without a bitmap.
//
// Same float32 formulas and rint as raster_accumulate, so the integer contributions are identical. Passes:
//   runs_prep: one work-item per edge: an upper bound of the cell records (touched cells, one more at a piece's
//       end) it gives each of its rows, added to a difference array over rows (integer atomics), and whether it is
//       one work unit (<= rows_max rows, RunsKernel.ROWS_PER_UNIT: nearly all edges); host: two prefix sums ->
//       each row's capacity (rounded up to even) and first slot row_off (slots: a piece takes 2, a record 1);
//   runs_edges (whole edges) and runs_pieces (the host's units (edge, <= rows_max rows) of the others): every row piece
//       (the part of an edge in one row) written as one descriptor int4 (ca << 16 | ce, umin, umax, dy: its first
//       and last touched cells, the floats as int bits) into its row's slice of pcs (int4 slot row_off / 2 + an
//       atomic cursor: the order inside a row is arbitrary, all downstream depends only on the set of pieces); the
//       cursors end as the rows' piece counts;
//   runs_rows: one work-item per row: insertion sort of its pieces by first cell, then the cells they touch, left
//       to right, each cell's integer contributions computed there as raster.cl does (a piece alone in its cells:
//       straight into the row sum; overlapping pieces: summed per cell first), the prefix sum S, grey =
//       lut[min(lut_max, |S| >> 8)] (lut_max 255, or 256*K-1 for K z samples), and only the grey changes written,
//       column << 8 | grey, to recs (ints) at row_off; rows of more than ch cell records are left to the host
//       (row_runs = -1), a row whose pieces did not fit its capacity is flagged (row_runs = -2: the host redoes the
//       batch);
//   host: prefix sum of the run counts -> run_off;
//   runs_emit: one work-item per row: a run from each non-blank grey change to the next; display coordinates.
// Tiles: tiles[t] = (first global row of the tile, cols, display row of tile row 0, display column of tile col 0);
// tiles[L].x = the batch's rows (a sentinel: tile t has tiles[t + 1].x - tiles[t].x rows).
#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define RUNS_ONE 65536.0f

// min/max of non-NaN floats or of ints (fmin/fmax may cost NaN handling; values equal up to the sign of a zero,
// which no integer result depends on)
#define RUNS_LO(a_, b_) ((a_) < (b_) ? (a_) : (b_))
#define RUNS_HI(a_, b_) ((a_) > (b_) ? (a_) : (b_))

// (int)floor, (int)ceil and (int)rint without builtins, exact for the values here: PoCL's CPU device calls its
// builtins out of line (measured: rint, floor, ceil, min, max, abs were ~15% of the runs' CPU time); a GPU's
// compiler makes the same few instructions of either. Floor and ceil: |x| < 2^31 (tile coordinates are < 2^15).
// Rint: |x| < 2^22 (every contribution is |d| <= 1 pixel times 65536 = 2^16, float32 rounding aside): x + 1.5 * 2^23
// lies in [2^23, 2^24), where floats are the integers, so the sum is x rounded to nearest, ties to even (1.5 * 2^23
// is even), as rint; the subtraction is exact. (Correctly rounded float add: required by OpenCL.)
inline int runs_floor(const float x) {
    const int i = (int)x;
    return (float)i > x ? i - 1 : i;
}
inline int runs_ceil(const float x) {
    const int i = (int)x;
    return (float)i < x ? i + 1 : i;
}
inline int runs_rint(const float x) {
    return (int)((x + 12582912.0f) - 12582912.0f);
}

// The pieces of edge e in its rows r0..r1 as raster.cl cuts them: ys = max(va, r), ye = min(vb, r + 1),
// x = u0 + (y - v0) * dudv (for r > floor(va), ys = r = the previous row's ye, so its x is carried over). A piece
// with umin >= w touches no cell; the others go to off[g] / 2 + atomic_add(cnt + g, 1) as a descriptor
// (ca << 16 | ce, umin, umax, dy) (its first and last touched cells; the floats as int bits), if they fit in the
// row's capacity (2 int2 slots each; else the row flags it). Touched cells: umax <= 0: cell 0 only (the whole dy);
// umin == umax: floor(umin) and the next; else max(0, floor(umin)) .. cb = min(w - 1, ceil(umax) - 1) and the next
// (the carry); "the next" only where < w. Tiles are < 32768 columns wide (the host checks).
// Up to RUNS_UNIT_ROWS pieces are made first, then their atomics run back to back, then their stores: each atomic
// is a locked read-modify-write of a row counter that is seldom in cache, and interleaved with the 16-byte stores
// each one waited for the stores before it (on PoCL the pieces pass takes ~0.8x the time: BENCHMARKS, "Runs
// pieces", eighth session). Any value gives the same pieces (1: the interleaved order); the private arrays take
// 24 bytes a row, which a GPU keeps in its per-thread memory: not yet measured on one.
#ifndef RUNS_UNIT_ROWS
#define RUNS_UNIT_ROWS 32
#endif
inline void runs_rows_of(const float4 e, const int4 t, const int r0, const int r1, __global int *cnt,
                         __global const int *off, __global int4 *pcs) {
    const float u0 = e.x, v0 = e.y, u1 = e.z, v1 = e.w;
    const float sgn = v1 > v0 ? 1.0f : -1.0f;
    const float va = RUNS_LO(v0, v1), vb = RUNS_HI(v0, v1);
    const float dudv = (u1 - u0) / (v1 - v0);
    const int w = t.y;
    int4 d[RUNS_UNIT_ROWS];
    int gs[RUNS_UNIT_ROWS], ps[RUNS_UNIT_ROWS];
    float ys = RUNS_HI(va, (float)r0), xs = u0 + (ys - v0) * dudv;
    for (int r = r0; r <= r1;) {
        const int r_end = RUNS_LO(r1, r + RUNS_UNIT_ROWS - 1);
        int m = 0;
        for (; r <= r_end; ++r) {
            const float ye = RUNS_LO(vb, (float)(r + 1));
            const float xe = u0 + (ye - v0) * dudv;
            const float umin = RUNS_LO(xs, xe), umax = RUNS_HI(xs, xe);
            if (ye > ys && umin < (float)w) {
                int ca = 0, ce = 0;
                if (umax > 0.0f) {
                    ca = RUNS_HI(0, runs_floor(umin));
                    const int cb = umin == umax ? ca : RUNS_LO(w - 1, runs_ceil(umax) - 1);
                    ce = cb + 1 < w ? cb + 1 : cb;
                }
                gs[m] = t.x + r;
                d[m++] = (int4)(ca << 16 | ce, as_int(umin), as_int(umax), as_int((ye - ys) * sgn));
            }
            ys = ye;
            xs = xe;
        }
        for (int i = 0; i < m; ++i) ps[i] = atomic_add(cnt + gs[i], 1);
        for (int i = 0; i < m; ++i) {
            const int g = gs[i], p = ps[i];
            if (2 * (p + 1) <= off[g + 1] - off[g]) pcs[off[g] / 2 + p] = d[i];
        }
    }
}

// units[u] = (edge, first row, last row, -); row_count: the rows' fill cursors.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_pieces(const int n_units, __global const int4 *units, __global const float4 *edges,
                 __global const int *edge_tile, __global const int4 *tiles, __global int *row_count,
                 __global const int *row_off, __global int4 *pcs) {
    const int gid = get_global_id(0);
    if (gid >= n_units) return;
    const int4 un = units[gid];
    runs_rows_of(edges[un.x], tiles[edge_tile[un.x]], un.y, un.z, row_count, row_off, pcs);
}

// One work-item per edge: its rows ra..rb, whether it is one work unit (<= rows_max rows: whole[e] = 1; the host
// cuts the others into units), and an upper bound of the cell records it gives each row, added as a difference
// over its rows: cap_diff[g0] += b, cap_diff[g1 + 1] -= b (integer atomics: order-free). A row piece spans
// |xe - xs| <= |dudv| * 1.002 + 0.05 columns (ye - ys <= 1; float32 errors: y - v0 rounded by <= 2^-11 (tile-local
// v < 2^14), times |dudv|, twice; u < 2^14: < 0.002 more each), and <= |u1 - u0| * 1.002 + 0.05 (a piece lies on
// the edge: y - v0 is exact where y and v0 are within 2x of each other (Sterbenz), else both are under 2 |dv| and
// it is rounded by <= 2^-23 |dv|, so x = u0 + (y - v0) * dudv is off by <= ~2^-21 |du| + 2^-11: without that bound
// a short, nearly horizontal edge reserved a whole tile row, 60x a batch's budget on a CAD part), so <= floor(the
// smaller) + 2 cells and one record more; b >= 2 (a piece's descriptor takes 2 int2 slots) unless extra < 0 (tests:
// forces the fallback, which also catches a bound that was too small).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_prep(const int n_edges, const int rows_max, const int extra, __global const float4 *edges,
               __global const int *edge_tile, __global const int4 *tiles, __global uchar *whole,
               __global int *cap_diff) {
    const int gid = get_global_id(0);
    if (gid >= n_edges) return;
    const float4 e = edges[gid];
    const int k = edge_tile[gid];
    const int4 t = tiles[k];
    const float va = RUNS_LO(e.y, e.w), vb = RUNS_HI(e.y, e.w);
    const int ra = RUNS_HI(0, runs_floor(va)), rb = RUNS_LO(tiles[k + 1].x - t.x - 1, runs_ceil(vb) - 1);
    if (e.y == e.w || rb < ra) {
        whole[gid] = 1;  // no pieces
        return;
    }
    const float q = (e.z - e.x) / (e.w - e.y), ad = RUNS_HI(q, -q);
    whole[gid] = rb - ra < rows_max;
    const float du = e.z - e.x, span = RUNS_LO(ad, RUNS_HI(du, -du)) * 1.002f + 0.05f;
    const int b = RUNS_HI(RUNS_LO(runs_floor(RUNS_LO(span, (float)t.y)) + 3, t.y + 1) + extra, 0);
    atomic_add(cap_diff + t.x + ra, b);
    atomic_sub(cap_diff + t.x + rb + 1, b);
}

// One work-item per edge with whole[e] = 1: its pieces written (the others: runs_pieces over the host's units).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_edges(const int n_edges, __global const uchar *whole, __global const float4 *edges,
                __global const int *edge_tile, __global const int4 *tiles, __global int *row_count,
                __global const int *row_off, __global int4 *pcs) {
    const int gid = get_global_id(0);
    if (gid >= n_edges || !whole[gid]) return;
    const float4 e = edges[gid];
    if (e.y == e.w) return;
    const int k = edge_tile[gid];
    const int4 t = tiles[k];
    const int ra = RUNS_HI(0, runs_floor(RUNS_LO(e.y, e.w)));
    const int rb = RUNS_LO(tiles[k + 1].x - t.x - 1, runs_ceil(RUNS_HI(e.y, e.w)) - 1);
    runs_rows_of(e, t, ra, rb, row_count, row_off, pcs);
}

// lut has lut_max + 1 entries: 256, or 256*K for a layer averaged over K sub-planes (z samples): its records are the
// K sub-layers' records together, and lut[i] = gamma_lut[i / K], so lut[min(lut_max, |S| >> 8)] is the grey of the
// mean coverage floor(256 * |S| / (65536 * K)), exactly.
inline uchar runs_grey(__global const uchar *lut, const uint lut_max, const int s) {
    // |s| as uint, exact for every int: s for s >= 0, ~s + 1 = -s else (n = 1). Not the abs builtin (PoCL calls it
    // out of line: ~10% of runs_rows' time) nor a compare-and-negate or s * (s >> 31 | 1) (clang makes llvm.abs of
    // those, unknown to Oclgrind).
    const uint n = (uint)s >> 31, i = (((uint)s ^ (0u - n)) + n) >> 8;
    return lut[i < lut_max ? i : lut_max];
}

// The cells of piece v (a descriptor, see runs_rows_of) in a tile w columns wide, left to right, each as
// EMIT(column, int contribution), as raster.cl computes them: in exact arithmetic cell c gets d * (1 - xm) of its
// own step and d * xm of step c - 1 (cell 0 also the part left of the tile), so the piece's share of the row's
// running sum after cell c is S(c) = (a - umin) * slope + d * (1 - xm) (its steps before c, then its own part). Each
// cell gets rint(S(c)) - rint(S(c - 1)) in 16.16 fixed point, the next cell after the last the rest of rint(dy):
// the running sum is the piece's exact share rounded once, never the sum of one rounding per cell (along a long
// edge nearly parallel to the rows every cell rounded the same way: greys drifted by up to 27 levels over 10,500
// columns; BENCHMARKS, tenth session). A macro: EMIT either resolves the cell or adds into a buffer.
#define RUNS_PIECE(v_, w_, EMIT)                                                                 \
    do {                                                                                         \
        const int ca_ = (v_).x >> 16, ce_ = (v_).x & 0xffff;                                     \
        const float umin_ = as_float((v_).y), umax_ = as_float((v_).z), dy_ = as_float((v_).w);  \
        if (umax_ <= 0.0f) {                                                                     \
            EMIT(0, runs_rint(dy_ * RUNS_ONE));                                                  \
        } else if (umin_ == umax_) {                                                             \
            const float xm_ = umin_ - (float)ca_;                                                \
            const int own_ = runs_rint(dy_ * (1.0f - xm_) * RUNS_ONE);                           \
            EMIT(ca_, own_);                                                                     \
            if (ce_ > ca_) EMIT(ce_, runs_rint(dy_ * RUNS_ONE) - own_);                          \
        } else {                                                                                 \
            const float slope_ = dy_ / (umax_ - umin_);                                          \
            const int cb_ = RUNS_LO((w_) - 1, runs_ceil(umax_) - 1);                            \
            int done_ = 0;                                                                       \
            for (int c_ = ca_; c_ <= cb_; ++c_) {                                                \
                const float a_ = RUNS_HI(umin_, (float)c_), b_ = RUNS_LO(umax_, (float)(c_ + 1)); \
                const float d_ = (b_ - a_) * slope_;                                             \
                const float xm_ = (a_ + b_) * 0.5f - (float)c_;                                  \
                const int s_ = runs_rint(((a_ - umin_) * slope_ + d_ * (1.0f - xm_)) * RUNS_ONE); \
                EMIT(c_, s_ - done_);                                                            \
                done_ = s_;                                                                      \
            }                                                                                    \
            if (ce_ > cb_) EMIT(ce_, runs_rint(dy_ * RUNS_ONE) - done_);                         \
        }                                                                                        \
    } while (0)

// The prefix sum of the row after cell c, its grey, and a grey change written: (column, grey from there on).
// Branch-free (grey changes are data-dependent): out[k] is always written, k advances only on a change.
#define RUNS_CELL(c_, v_)                                   \
    do {                                                    \
        s += (v_);                                          \
        const uchar gr_ = runs_grey(lut, (uint)lut_max, s); \
        const int ch_ = gr_ != prev;                        \
        out[k] = (c_) << 8 | gr_;                           \
        k += ch_;                                           \
        runs += ch_ & (gr_ != zero);                        \
        prev = gr_;                                         \
    } while (0)

// a cell's contribution added into the group's sums (acc[c - ca] = out[k0 + c - ca], see runs_rows)
#define RUNS_ACC(c_, v_) (acc[(c_) - ca] += (v_))

// One work-item per global row: sort its pieces by first cell (insertion sort in place), then per group of pieces
// whose cells overlap (first cells ascending: their cells are contiguous; nearly always one piece, else mostly two
// sharing an end cell), the cells left to right, and keep where the grey changes: recs[row_off + j] = column << 8 |
// grey from there on (columns < 2^15), row_m = how many, row_runs = how many of them start a non-blank run. A group
// of several pieces first sums its cells in the row's own recs slice, at the first slot not yet written (k0): it
// holds the row's cells (<= its records <= its capacity), and a grey change is written at k <= the cell read.
// row_runs = -1: more than ch cell records (the host finishes the row); -2: its pieces did not fit its capacity (the
// host redoes the batch).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_rows(const int n_rows, const int ch, __global const int *row_off, __global const int *row_count,
               __global int4 *pcs, __global int *recs, __global const int *row_tile, __global const int4 *tiles,
               __global const uchar *lut, const int lut_max, __global int *row_m, __global int *row_runs) {
    const int g = get_global_id(0);
    if (g >= n_rows) return;
    const int a0 = row_off[g], cap = row_off[g + 1] - a0, n = row_count[g];
    row_m[g] = 0;
    if (2 * n > cap || n > ch) {
        row_runs[g] = 2 * n > cap ? -2 : -1;
        return;
    }
    const int w = tiles[row_tile[g]].y;
    __global int4 *p = pcs + a0 / 2;
    int nrec = 0;
    for (int i = 0; i < n; ++i) {
        const int4 v = p[i];
        nrec += (v.x & 0xffff) - (v.x >> 16) + 1;
        int j = i;
        while (j > 0 && p[j - 1].x > v.x) {
            p[j] = p[j - 1];
            --j;
        }
        p[j] = v;
    }
    if (nrec > ch || nrec > cap) {
        row_runs[g] = nrec > cap ? -2 : -1;
        return;
    }
    __global int *out = recs + a0;
    const uchar zero = lut[0];
    uchar prev = zero;
    int s = 0, k = 0, runs = 0;
    for (int i = 0; i < n;) {
        const int4 v = p[i];
        const int ca = v.x >> 16;
        int ce = v.x & 0xffff, j = i + 1;
        while (j < n && (p[j].x >> 16) <= ce) {
            const int e = p[j++].x & 0xffff;
            ce = RUNS_HI(ce, e);
        }
        if (j == i + 1) {  // alone in its cells
            RUNS_PIECE(v, w, RUNS_CELL);
        } else {
            __global int *acc = out + k;
            for (int c = 0; c <= ce - ca; ++c) acc[c] = 0;
            for (int m = i; m < j; ++m) {
                const int4 q = p[m];
                RUNS_PIECE(q, w, RUNS_ACC);
            }
            for (int c = ca; c <= ce; ++c) {
                const int sum = acc[c - ca];
                RUNS_CELL(c, sum);
            }
        }
        i = j;
    }
    row_m[g] = k;
    row_runs[g] = runs;
}

// One work-item per global row with row_m > 0: its runs at run_off[g] in display coordinates, from its grey changes.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_emit(const int n_rows, __global const int *row_off, __global const int *recs, __global const int *row_m,
               __global const int *row_tile, __global const int4 *tiles, __global const uchar *lut,
               __global const int *run_off, __global int *out_row, __global int *out_x, __global int *out_len,
               __global uchar *out_grey) {
    const int g = get_global_id(0);
    if (g >= n_rows) return;
    const int m = row_m[g];
    if (m <= 0) return;
    const int4 t = tiles[row_tile[g]];
    __global const int *c = recs + row_off[g];
    const int drow = t.z + (g - t.x);
    const uchar zero = lut[0];
    int k = run_off[g];
    for (int i = 0; i < m; ++i) {
        const int v = c[i], x = v >> 8;
        if ((uchar)v == zero) continue;
        out_row[k] = drow;
        out_x[k] = t.w + x;
        out_len[k] = (i + 1 < m ? c[i + 1] >> 8 : t.y) - x;
        out_grey[k] = (uchar)v;
        ++k;
    }
}
