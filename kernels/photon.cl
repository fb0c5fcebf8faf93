// Anycubic Photon Workshop layer images (PW0) from run-length runs (gpuslice/raster/photon.py, PhotonEncoder): the
// bytes of the numpy twin encode_pw0_batch(...), several layer images at once, and per run what the layer table
// needs (lit pixels, middle greys, the lit box), which the host adds up per layer.
//
// Images, pieces and segments as _run_images.cl has them (and ctb.cl uses them), with the 4-bit code grey >> 4 (0
// for greys below 16: blank); a segment is measured by the run owning its head, which looks ahead over at most
// PW_SCAN pieces (more: flagged, the twin encodes the group; faint edge pixels make long blank stretches of many
// pieces, hence the larger bound than CTB's). A segment of code c and n pixels is written as
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
    const int k = get_global_id(0), shift = 4;
    if (k >= m) return;
    const int i = run_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    if (run_invalid(k, j == 0, RUN_PASS)) {  // the twin raises its own error
        atomic_or(flags, 2);
        width[k] = 0;
        return;
    }
    long seg[3], w = 0;
    int val[3];
    if (run_heads(a, n, j, RUN_PASS, PW_SCAN, seg, val)) atomic_or(flags, 1);
    for (int t = 0; t < 3; ++t)
        if (seg[t] > 0) w += pw_width(seg[t], val[t]);
    width[k] = (int)w;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void pw_write(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
              __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
              __global const int *cum, __global const long *base, __global uchar *out, __global int *lit,
              __global uchar *mid, __global int *r0, __global int *c0, __global int *r1, __global int *c1) {
    const int k = get_global_id(0), shift = 4;
    if (k >= m) return;
    const int i = run_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    long seg[3], w = 0;
    int val[3];
    run_heads(a, n, j, RUN_PASS, PW_SCAN, seg, val);
    for (int t = 0; t < 3; ++t)
        if (seg[t] > 0) w += pw_width(seg[t], val[t]);
    long at = base[i] + cum[k] - w;
    for (int t = 0; t < 3; ++t) {
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
