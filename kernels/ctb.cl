// Chitubox CTB layer images (RLE7) from run-length runs (gpuslice/raster/ctb.py, CtbEncoder): the bytes of the numpy
// twin rle7_batch(...), several layer images at once.
//
// A group of n_img images: image i owns runs img_off[i] .. img_off[i + 1] - 1 (row, x, len, grey of
// gpuslice.raster.runs.Runs, display pixels; the pixel index row * cols + x). An image of n runs a .. a + n - 1 is
// a sequence of 2n + 1 *pieces*: piece 2j the blank gap before run a + j (2n: the blank tail), piece 2j + 1 run a + j
// with the value grey >> 1 (0 for grey 1: blank too). A *segment* is a longest stretch of non-empty pieces of one
// value; each becomes one record: value | 0x80 when longer than one pixel, then 0-4 length bytes (module docstring
// of ctb.py). A piece is a segment's head when the non-empty piece before it has another value (or there is none);
// the run owning the head (a gap belongs to the run after it, the tail to the image's last run) measures the segment
// by looking ahead over at most CTB_SCAN pieces, and writes its record. Passes:
//   ctb_sizes: one work-item per run: the bytes of the records it writes (width[k]); flags |= 1 where a segment
//       runs over more than CTB_SCAN pieces (the host then encodes the group with the twin: bounded work here),
//       |= 2 for runs the twin refuses (overlapping, out of the image, empty: it raises);
//   host: inclusive prefix sum of the widths, each image's first byte;
//   ctb_write: one work-item per run: its records at base[i] + cum[k] - width[k].
// Integer atomics only for the flags (order-free).

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define CTB_SCAN 64

// bytes of a record of n pixels (1 <= n < 2^28; the host checks the image size)
inline int ctb_record_width(const long n) {
    return n == 1 ? 1 : (n <= 0x7F ? 2 : (n <= 0x3FFF ? 3 : (n <= 0x1FFFFF ? 4 : 5)));
}

// the image of run k: the largest i with img_off[i] <= k (img_off[0] = 0 <= k < img_off[n_img])
inline int ctb_image(__global const int *img_off, const int n_img, const int k) {
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

#define CTB_ARGS                                                                                             \
    const int cols, const long n_pixels, __global const int *row, __global const int *x, __global const int *len, \
        __global const uchar *grey
#define CTB_PASS cols, n_pixels, row, x, len, grey

// piece p (0 .. 2n) of the image of runs a .. a + n - 1: its length (pixels; negative: runs out of order) and value
inline long ctb_piece(const int p, const int a, const int n, CTB_ARGS, int *v) {
    const int j = p >> 1;
    if (p & 1) {
        *v = grey[a + j] >> 1;
        return len[a + j];
    }
    *v = 0;
    const long s = j < n ? (long)row[a + j] * cols + x[a + j] : n_pixels;
    const long pe = j > 0 ? (long)row[a + j - 1] * cols + x[a + j - 1] + len[a + j - 1] : 0;
    return s - pe;
}

// if piece p heads a segment: its length (pixels) and value; 0 when p is empty or not a head; -1 when the segment
// runs over more than CTB_SCAN pieces
inline long ctb_segment(const int p, const int a, const int n, CTB_ARGS, int *v) {
    const long lp = ctb_piece(p, a, n, CTB_PASS, v);
    if (lp <= 0) return 0;
    int q = p - 1, vq = -1;
    if (q >= 0 && ctb_piece(q, a, n, CTB_PASS, &vq) == 0) q -= 1;  // an empty gap: the run before it
    if (q >= 0) {
        ctb_piece(q, a, n, CTB_PASS, &vq);
        if (vq == *v) return 0;  // the segment started earlier
    }
    long total = lp;
    for (int t = p + 1; t <= 2 * n; ++t) {
        if (t - p > CTB_SCAN) return -1;
        int vt;
        const long lt = ctb_piece(t, a, n, CTB_PASS, &vt);
        if (lt > 0 && vt != *v) break;
        total += lt;
    }
    return total;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void ctb_sizes(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               __global int *width, __global int *flags) {
    const int k = get_global_id(0);
    if (k >= m) return;
    const int i = ctb_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    // the twin's checks: sorted, not overlapping, inside the image, not empty
    const long s = (long)row[k] * cols + x[k];
    const long pe = j > 0 ? (long)row[k - 1] * cols + x[k - 1] + len[k - 1] : 0;
    if (s < pe || s < 0 || len[k] < 1 || s + len[k] > n_pixels) {
        atomic_or(flags, 2);
        width[k] = 0;
        return;
    }
    int w = 0;
    const int last = j == n - 1 ? 2 * n : 2 * j + 1;
    for (int p = 2 * j; p <= last; ++p) {
        int v;
        const long seg = ctb_segment(p, a, n, CTB_PASS, &v);
        if (seg < 0) atomic_or(flags, 1);
        if (seg > 0) w += ctb_record_width(seg);
    }
    width[k] = w;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void ctb_write(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               __global const int *cum, __global const long *base, __global uchar *out) {
    const int k = get_global_id(0);
    if (k >= m) return;
    const int i = ctb_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    const int last = j == n - 1 ? 2 * n : 2 * j + 1;
    long seg[3];
    int val[3], w = 0;
    for (int p = 2 * j; p <= last; ++p) {
        seg[p - 2 * j] = ctb_segment(p, a, n, CTB_PASS, val + p - 2 * j);
        if (seg[p - 2 * j] > 0) w += ctb_record_width(seg[p - 2 * j]);
    }
    long at = base[i] + cum[k] - w;
    for (int t = 0; t <= last - 2 * j; ++t) {
        const long L = seg[t];
        if (L <= 0) continue;
        const int size = ctb_record_width(L);
        out[at] = (uchar)(val[t] | (L > 1 ? 0x80 : 0));
        if (size >= 2) {
            const int lead = size == 2 ? 0x00 : (size == 3 ? 0x80 : (size == 4 ? 0xC0 : 0xE0));
            out[at + 1] = (uchar)(((L >> (8 * (size - 2))) & 0xFF) | lead);
            for (int b = 2; b < size; ++b) out[at + b] = (uchar)((L >> (8 * (size - 1 - b))) & 0xFF);
        }
        at += size;
    }
}
