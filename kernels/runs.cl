// Resin layers as run-length runs (gpuslice/runs.py, RunsKernel): the greys of raster.cl without a bitmap.
//
// Same float32 formulas and rint as raster_accumulate, so the integer contributions are identical. Three passes:
//   runs_pieces (write = 0): one work-item per unit = (edge, <= 16 rows, <= ~256 cells): how many records (cells,
//       merged within the piece) each row piece gives, in closed form, added to its global row's count (atomics);
//   host: prefix sum of the row counts -> row_off;
//   runs_pieces (write = 1): the same pieces, written as (column, value) records into their row's slice of recs
//       (slot = row_off + an atomic cursor: the order inside a row is arbitrary, but everything downstream depends
//       only on the multiset of records: integer sums, sorted by column);
//   runs_rows: one work-item per row with <= RUNS_CH records: insertion sort by column in private memory, duplicate
//       columns summed, the sorted cells written back, and its runs counted (longer rows: the host, row_m = -1);
//   host: prefix sum of the run counts -> run_off;
//   runs_emit: one work-item per row: prefix sum over its sorted cells, grey = lut[min(255, |S| >> 8)], runs of
//       equal grey between grey changes, blank runs left out; display coordinates.
// Tiles: tiles[t] = (first global row of the tile, cols, display row of tile row 0, display column of tile col 0).
#pragma OPENCL FP_CONTRACT OFF

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define RUNS_ONE 65536.0f
#ifndef RUNS_CH
#define RUNS_CH 256
#endif

#define RUNS_REC(cc_, a_)                                                      \
    do {                                                                       \
        const int cc = (cc_);                                                  \
        if (cc < w) {                                                          \
            const int vv = (int)rint((a_) * RUNS_ONE);                         \
            if (cc == pc) {                                                    \
                pv += vv;                                                      \
            } else {                                                           \
                if (pc >= 0) {                                                 \
                    if (write) out[n] = (int2)(pc, pv);                        \
                    ++n;                                                       \
                }                                                              \
                pc = cc;                                                       \
                pv = vv;                                                       \
            }                                                                  \
        }                                                                      \
    } while (0)

// The records of the piece of edge (u0, v0, dudv, sgn, va, vb) in row r of a tile w columns wide, cells c0..c1
// only (c0 == INT_MIN: also the cells that do not come from the per-cell loop). Returns how many; stores them at
// out when write != 0. Columns ascend, so equal columns are adjacent and merged.
inline int runs_piece(const float u0, const float v0, const float dudv, const float sgn, const float va,
                      const float vb, const int r, const int w, const int c0, const int c1, const int write,
                      __global int2 *out) {
    const float ys = fmax(va, (float)r), ye = fmin(vb, (float)(r + 1));
    if (!(ye > ys)) return 0;
    const float xs = u0 + (ys - v0) * dudv, xe = u0 + (ye - v0) * dudv;
    const float dy = (ye - ys) * sgn;
    const float umin = fmin(xs, xe), umax = fmax(xs, xe);
    const int first = c0 == INT_MIN;
    int n = 0, pc = -1, pv = 0;
    if (umax <= 0.0f) {
        if (first) RUNS_REC(0, dy);
    } else if (umin >= (float)w) {
        return 0;
    } else if (umin == umax) {
        if (first) {
            const int c = (int)floor(umin);
            const float xm = umin - (float)c;
            RUNS_REC(c, dy * (1.0f - xm));
            RUNS_REC(c + 1, dy * xm);
        }
    } else {
        const float slope = dy / (umax - umin);
        if (first && umin < 0.0f) RUNS_REC(0, (0.0f - umin) * slope);
        const int ca = max(max(0, (int)floor(umin)), c0);
        const int cb = min(min(w - 1, (int)ceil(umax) - 1), c1);
        for (int c = ca; c <= cb; ++c) {
            const float a = fmax(umin, (float)c), b = fmin(umax, (float)(c + 1));
            const float d = (b - a) * slope;
            const float xm = (a + b) * 0.5f - (float)c;
            RUNS_REC(c, d * (1.0f - xm));
            RUNS_REC(c + 1, d * xm);
        }
    }
    if (pc >= 0) {
        if (write) out[n] = (int2)(pc, pv);
        ++n;
    }
    return n;
}

// How many records runs_piece gives, in closed form (no cell loop): the cells ca..cb + 1 of the loop (below w),
// column 0 for a piece left of the tile or partly left of it, the two cells of a vertical piece.
inline int runs_count(const float u0, const float v0, const float dudv, const float va, const float vb, const int r,
                      const int w, const int c0, const int c1) {
    const float ys = fmax(va, (float)r), ye = fmin(vb, (float)(r + 1));
    if (!(ye > ys)) return 0;
    const float xs = u0 + (ys - v0) * dudv, xe = u0 + (ye - v0) * dudv;
    const float umin = fmin(xs, xe), umax = fmax(xs, xe);
    const int first = c0 == INT_MIN;
    if (umax <= 0.0f) return first;
    if (umin >= (float)w) return 0;
    if (umin == umax) return first ? 1 + ((int)floor(umin) + 1 < w) : 0;
    const int ca = max(max(0, (int)floor(umin)), c0);
    const int cb = min(min(w - 1, (int)ceil(umax) - 1), c1);
    const int n = ca <= cb ? min(cb + 1, w - 1) - ca + 1 : 0;
    return n + (first && umin < 0.0f && !(ca <= cb && ca == 0));
}

// units[u] = (edge, first row, last row, -), ucols[u] = (c0, c1); row_count: the counts (write = 0) or the fill
// cursors, zeroed (write = 1).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_pieces(const int n_units, const int write, __global const int4 *units, __global const int2 *ucols,
                 __global const float4 *edges, __global const int *edge_tile, __global const int4 *tiles,
                 __global int *row_count, __global const int *row_off, __global int2 *recs) {
    const int gid = get_global_id(0);
    if (gid >= n_units) return;
    const int4 un = units[gid];
    const int2 cr = ucols[gid];
    const float4 e = edges[un.x];
    const int4 t = tiles[edge_tile[un.x]];
    const float u0 = e.x, v0 = e.y, u1 = e.z, v1 = e.w;
    const float sgn = v1 > v0 ? 1.0f : -1.0f;
    const float va = fmin(v0, v1), vb = fmax(v0, v1);
    const float dudv = (u1 - u0) / (v1 - v0);
    for (int r = un.y; r <= un.z; ++r) {
        const int g = t.x + r;
        const int n = runs_count(u0, v0, dudv, va, vb, r, t.y, cr.x, cr.y);
        if (n == 0) continue;
        if (!write) {
            atomic_add(row_count + g, n);
        } else {
            const int pos = row_off[g] + atomic_add(row_count + g, n);
            runs_piece(u0, v0, dudv, sgn, va, vb, r, t.y, cr.x, cr.y, 1, recs + pos);
        }
    }
}

inline uchar runs_grey(__global const uchar *lut, const int s) { return lut[min(255u, (uint)abs(s) >> 8)]; }

// One work-item per global row: sort its records by column (private memory, <= RUNS_CH), sum equal columns,
// write the cells back (row_m = their count; -1: more than ch, the host finishes the row) and count its runs.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void runs_rows(const int n_rows, const int ch, __global const int *row_off, __global int2 *recs, __global const uchar *lut,
               __global int *row_m, __global int *row_runs) {
    const int g = get_global_id(0);
    if (g >= n_rows) return;
    const int a = row_off[g], n = row_off[g + 1] - a;
    if (n > ch || n > RUNS_CH) {
        row_m[g] = -1;
        row_runs[g] = 0;
        return;
    }
    int2 buf[RUNS_CH];
    for (int i = 0; i < n; ++i) {
        const int2 v = recs[a + i];
        int j = i;
        while (j > 0 && buf[j - 1].x > v.x) {
            buf[j] = buf[j - 1];
            --j;
        }
        buf[j] = v;
    }
    int m = 0;
    for (int i = 0; i < n; ++i) {
        if (m > 0 && buf[m - 1].x == buf[i].x) buf[m - 1].y += buf[i].y;
        else buf[m++] = buf[i];
    }
    const uchar zero = lut[0];
    uchar prev = zero;
    int s = 0, runs = 0;
    for (int i = 0; i < m; ++i) {
        recs[a + i] = buf[i];
        s += buf[i].y;
        const uchar gr = runs_grey(lut, s);
        if (gr != prev && gr != zero) ++runs;
        prev = gr;
    }
    row_m[g] = m;
    row_runs[g] = runs;
}

// One work-item per global row with row_m >= 0: its runs at run_off[g] in display coordinates.
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
    const int a = row_off[g], drow = t.z + (g - t.x);
    const uchar zero = lut[0];
    uchar prev = zero;
    int s = 0, k = run_off[g], open = 0, start = 0;
    for (int i = 0; i < m; ++i) {
        const int2 v = recs[a + i];
        s += v.y;
        const uchar gr = runs_grey(lut, s);
        if (gr == prev) continue;
        if (open) {
            out_len[k] = v.x - start;
            ++k;
        }
        open = gr != zero;
        if (open) {
            start = v.x;
            out_row[k] = drow;
            out_x[k] = t.w + v.x;
            out_grey[k] = gr;
        }
        prev = gr;
    }
    if (open) out_len[k] = t.y - start;
}
