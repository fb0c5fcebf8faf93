// Anycubic Photon Workshop layer images (PW0) from run-length runs (gpuslice/raster/photon.py, PhotonEncoder): the
// bytes of the numpy twin encode_pw0_batch(...), several layer images at once, and per run what the layer table
// needs (lit pixels, middle greys, the lit box), which the host adds up per layer.
//
// As ctb.cl: image i owns runs img_off[i] .. img_off[i + 1] - 1; its 2n + 1 pieces are the blank gaps (piece 2j
// before run a + j, 2n the tail) and the runs (2j + 1) with the 4-bit code grey >> 4 (0 for greys below 16: blank);
// a segment is a longest stretch of non-empty pieces of one code, measured by the run owning its head, which looks
// ahead over at most PW_SCAN pieces (more: flagged, the twin encodes the group; faint edge pixels make long blank
// stretches of many pieces, hence the larger bound than CTB's). A segment of code c and n pixels is written as
// records of at most cap = 0xFFF pixels (c = 0 or 15: two bytes, c << 4 | n >> 8, n & 0xFF) or 0xF pixels (other
// codes: one byte, c << 4 | n): full records first, then the rest. Passes:
//   pw_sizes: one work-item per run: the bytes of the records it writes; flags |= 1 (a segment over PW_SCAN pieces),
//       |= 2 (runs the twin refuses or would read otherwise: overlapping, out of the image, empty);
//   pw_write: one work-item per run: its records at base[i] + cum[k] - width[k]; and lit[k] (its pixels when its
//       code is not 0), mid[k] (0 < code < 15), its row and first/last columns when lit (r0 = r1 = row, c0, c1;
//       else r0 = c0 = INT_MAX, r1 = c1 = -1) for the host's per-layer sums, maxima and minima.
// Work: a head's look-ahead is bounded by PW_SCAN; a blank segment's records by the image (a 16K image's blank
// top is ~23,000 two-byte records written by one work-item).

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define PW_SCAN 4096

// the image of run k: the largest i with img_off[i] <= k (img_off[0] = 0 <= k < img_off[n_img])
inline int pw_image(__global const int *img_off, const int n_img, const int k) {
    int lo = 0, hi = n_img;
    while (hi - lo > 1) {
        const int mid = (lo + hi) >> 1;
        if (img_off[mid] <= k)
            lo = mid;
        else
            hi = mid;
    }
    return lo;
}

#define PW_ARGS                                                                                              \
    const int cols, const long n_pixels, __global const int *row, __global const int *x, __global const int *len, \
        __global const uchar *grey
#define PW_PASS cols, n_pixels, row, x, len, grey

// piece p (0 .. 2n) of the image of runs a .. a + n - 1: its length (pixels) and code
inline long pw_piece(const int p, const int a, const int n, PW_ARGS, int *v) {
    const int j = p >> 1;
    if (p & 1) {
        *v = grey[a + j] >> 4;
        return len[a + j];
    }
    *v = 0;
    const long s = j < n ? (long)row[a + j] * cols + x[a + j] : n_pixels;
    const long pe = j > 0 ? (long)row[a + j - 1] * cols + x[a + j - 1] + len[a + j - 1] : 0;
    return s - pe;
}

// if piece p heads a segment: its length (pixels) and code; 0 when p is empty or not a head; -1 when the segment
// runs over more than PW_SCAN pieces
inline long pw_segment(const int p, const int a, const int n, PW_ARGS, int *v) {
    const long lp = pw_piece(p, a, n, PW_PASS, v);
    if (lp <= 0) return 0;
    int q = p - 1, vq = -1;
    if (q >= 0 && pw_piece(q, a, n, PW_PASS, &vq) == 0) q -= 1;  // an empty gap: the run before it
    if (q >= 0) {
        pw_piece(q, a, n, PW_PASS, &vq);
        if (vq == *v) return 0;  // the segment started earlier
    }
    long total = lp;
    for (int t = p + 1; t <= 2 * n; ++t) {
        if (t - p > PW_SCAN) return -1;
        int vt;
        const long lt = pw_piece(t, a, n, PW_PASS, &vt);
        if (lt > 0 && vt != *v) break;
        total += lt;
    }
    return total;
}

// bytes of the records of a segment of n pixels of code c
inline long pw_width(const long n, const int c) {
    const int two = c == 0 || c == 15;
    const uint cap = two ? 0xFFF : 0xF;
    const uint records = n <= cap ? 1 : ((uint)n + cap - 1) / cap;  // (n < 2^31: the host checks; 32-bit division)
    return (long)records * (two ? 2 : 1);
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void pw_sizes(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
              __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
              __global int *width, __global int *flags) {
    const int k = get_global_id(0);
    if (k >= m) return;
    const int i = pw_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    const long s = (long)row[k] * cols + x[k];
    const long pe = j > 0 ? (long)row[k - 1] * cols + x[k - 1] + len[k - 1] : 0;
    if (s < pe || s < 0 || len[k] < 1 || s + len[k] > n_pixels) {
        atomic_or(flags, 2);
        width[k] = 0;
        return;
    }
    long w = 0;
    const int last = j == n - 1 ? 2 * n : 2 * j + 1;
    for (int p = 2 * j; p <= last; ++p) {
        int v;
        const long seg = pw_segment(p, a, n, PW_PASS, &v);
        if (seg < 0) atomic_or(flags, 1);
        if (seg > 0) w += pw_width(seg, v);
    }
    width[k] = (int)w;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void pw_write(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
              __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
              __global const int *cum, __global const long *base, __global uchar *out, __global int *lit,
              __global uchar *mid, __global int *r0, __global int *c0, __global int *r1, __global int *c1) {
    const int k = get_global_id(0);
    if (k >= m) return;
    const int i = pw_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    const int last = j == n - 1 ? 2 * n : 2 * j + 1;
    long seg[3];
    int val[3];
    long w = 0;
    for (int p = 2 * j; p <= last; ++p) {
        seg[p - 2 * j] = pw_segment(p, a, n, PW_PASS, val + p - 2 * j);
        if (seg[p - 2 * j] > 0) w += pw_width(seg[p - 2 * j], val[p - 2 * j]);
    }
    long at = base[i] + cum[k] - w;
    for (int t = 0; t <= last - 2 * j; ++t) {
        long left = seg[t];
        const int c = val[t], two = c == 0 || c == 15;
        const long cap = two ? 0xFFF : 0xF;
        while (left > 0) {
            const int rec = (int)(left < cap ? left : cap);
            if (two) {
                out[at] = (uchar)((c << 4) | (rec >> 8));
                out[at + 1] = (uchar)(rec & 0xFF);
                at += 2;
            } else {
                out[at++] = (uchar)((c << 4) | rec);
            }
            left -= rec;
        }
    }
    const int code = grey[k] >> 4;
    lit[k] = code ? len[k] : 0;
    mid[k] = code > 0 && code < 15;
    r0[k] = code ? row[k] : INT_MAX;
    r1[k] = code ? row[k] : -1;
    c0[k] = code ? x[k] : INT_MAX;
    c1[k] = code ? x[k] + len[k] - 1 : -1;
}
