// Chitubox CTB layer images (RLE7) from run-length runs (gpuslice/raster/ctb.py, CtbEncoder): the bytes of the numpy
// twin rle7_batch(...), several layer images at once.
//
// Images, pieces and segments as _run_images.cl has them, with the value grey >> 1 (0 for grey 1: blank too). Each
// segment becomes one record: value | 0x80 when longer than one pixel, then 0-4 length bytes (module docstring of
// ctb.py). The run owning a segment's head (a gap belongs to the run after it, the tail to the image's last run)
// measures the segment by looking ahead over at most CTB_SCAN pieces, and writes its record. Passes:
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

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void ctb_sizes(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               __global int *width, __global int *flags) {
    const int k = get_global_id(0), shift = 1;
    if (k >= m) return;
    const int i = run_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    if (run_invalid(k, j == 0, RUN_PASS)) {  // the twin raises its own error
        atomic_or(flags, 2);
        width[k] = 0;
        return;
    }
    long seg[3];
    int val[3], w = 0;
    if (run_heads(a, n, j, RUN_PASS, CTB_SCAN, seg, val)) atomic_or(flags, 1);
    for (int t = 0; t < 3; ++t)
        if (seg[t] > 0) w += ctb_record_width(seg[t]);
    width[k] = w;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void ctb_write(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               __global const int *cum, __global const long *base, __global uchar *out) {
    const int k = get_global_id(0), shift = 1;
    if (k >= m) return;
    const int i = run_image(img_off, n_img, k);
    const int a = img_off[i], n = img_off[i + 1] - a, j = k - a;
    long seg[3];
    int val[3], w = 0;
    run_heads(a, n, j, RUN_PASS, CTB_SCAN, seg, val);
    for (int t = 0; t < 3; ++t)
        if (seg[t] > 0) w += ctb_record_width(seg[t]);
    long at = base[i] + cum[k] - w;
    for (int t = 0; t < 3; ++t) {
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
