// Helpers of the layer-image encoders that read run-length runs (goo.cl, ctb.cl, photon.cl, png.cl): every
// kernels/*.cl file is built into one program, in file-name order, so this file (first) serves them all.
//
// A group of n_img layer images: image i owns runs img_off[i] .. img_off[i + 1] - 1 (row, x, len, grey of
// gpuslice.raster.runs.Runs, display pixels; the pixel index row * cols + x). For the formats that quantise greys
// and merge equal neighbours (ctb.cl, photon.cl), an image of n runs a .. a + n - 1 is a sequence of 2n + 1
// *pieces*: piece 2j the blank gap before run a + j (2n: the blank tail), piece 2j + 1 run a + j with the value
// grey >> shift (0: blank too). A *segment* is a longest stretch of non-empty pieces of one value; a piece is a
// segment's head when the non-empty piece before it has another value (or there is none).

// the image of run k: the largest i with img_off[i] <= k (img_off[0] = 0 <= k < img_off[n_img])
inline int run_image(__global const int *img_off, const int n_img, const int k) {
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

#define RUN_ARGS                                                                                               \
    const int cols, const long n_pixels, __global const int *row, __global const int *x, __global const int *len, \
        __global const uchar *grey, const int shift
#define RUN_PASS cols, n_pixels, row, x, len, grey, shift

// piece p (0 .. 2n) of the image of runs a .. a + n - 1: its length (pixels; negative: runs out of order) and value
inline long run_piece(const int p, const int a, const int n, RUN_ARGS, int *v) {
    const int j = p >> 1;
    if (p & 1) {
        *v = grey[a + j] >> shift;
        return len[a + j];
    }
    *v = 0;
    const long s = j < n ? (long)row[a + j] * cols + x[a + j] : n_pixels;
    const long pe = j > 0 ? (long)row[a + j - 1] * cols + x[a + j - 1] + len[a + j - 1] : 0;
    return s - pe;
}

// if piece p heads a segment: its length (pixels) and value; 0 when p is empty or not a head; -1 when the segment
// runs over more than scan pieces (bounded work: the caller leaves the group to its numpy twin)
inline long run_segment(const int p, const int a, const int n, RUN_ARGS, const int scan, int *v) {
    const long lp = run_piece(p, a, n, RUN_PASS, v);
    if (lp <= 0) return 0;
    // the non-empty piece before p: p - 1, or the run before an empty gap (runs are never empty); none: vq = -1
    int vq = -1;
    if (p >= 1 && run_piece(p - 1, a, n, RUN_PASS, &vq) == 0) {
        vq = -1;
        if (p >= 2) run_piece(p - 2, a, n, RUN_PASS, &vq);
    }
    if (vq == *v) return 0;  // the segment started earlier
    long total = lp;
    for (int t = p + 1; t <= 2 * n; ++t) {
        if (t - p > scan) return -1;
        int vt;
        const long lt = run_piece(t, a, n, RUN_PASS, &vt);
        if (lt > 0 && vt != *v) break;
        total += lt;
    }
    return total;
}

// the segments run a + j heads, in its pieces' order (t = 0: the gap before it, 1: itself, 2: for the image's last
// run the tail): their lengths in seg[t] (0: no segment starts there, or not its piece) and values in val[t];
// returns 1 when one runs over scan pieces (its seg[t] is -1)
inline int run_heads(const int a, const int n, const int j, RUN_ARGS, const int scan, long *seg, int *val) {
    int over = 0;
    for (int t = 0; t < 3; ++t) {
        val[t] = 0;
        seg[t] = t < 2 || j == n - 1 ? run_segment(2 * j + t, a, n, RUN_PASS, scan, val + t) : 0;
        over |= seg[t] < 0;
    }
    return over;
}

// run k is invalid for the twins (out of order, overlapping, outside the image, empty)
inline int run_invalid(const int k, const int first, RUN_ARGS) {
    const long s = (long)row[k] * cols + x[k];
    const long pe = first ? 0 : (long)row[k - 1] * cols + x[k - 1] + len[k - 1];
    return s < pe || s < 0 || len[k] < 1 || s + len[k] > n_pixels;
}
