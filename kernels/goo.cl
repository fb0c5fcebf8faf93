// Elegoo GOO layer images from run-length runs (gpuslice/raster/goo.py, GooEncoder): the bytes of the numpy twin
// encode_segments(*batch_image_segments(...)), several layer images at once, without a numpy pass per chunk field.
//
// A group of n_img images: image i owns runs img_off[i] .. img_off[i + 1] - 1 (row, x, len, grey of
// gpuslice.raster.runs.Runs, display pixels; the pixel index row * cols + x). Each run k writes the chunk of the
// blank gap before it (when not empty), its own chunk and, when it is its image's last run, the chunk of the blank
// tail (when not empty). A chunk: one byte TTSSLLLL (T: 0 blank, 3 all 0xFF, 1 a grey in the next byte; S: how many
// more bytes hold the length above its low 4 bits, most significant first), [the grey], [S length bytes].
// Passes:
//   goo_sizes: one work-item per run: its bytes (width[k]); flags |= 1 where a run touches the one before it with
//       the same grey (the twin merges them into one chunk: the host then encodes the group with the twin), |= 2 for
//       runs the twin would not take as sorted, non-overlapping, non-blank and inside the image (the twin again);
//   host: inclusive prefix sum of the widths (in place) and each image's first byte;
//   goo_write: one work-item per run: its chunks at base[i] + cum[k] - width[k], and the sum of its bytes mod 256
//       (the host adds them up per image for the image's checksum, and writes each image's 0x55 and checksum).
// Bounded work: at most 3 chunks of at most 6 bytes per work-item; integer atomics only for the flags (order-free).

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

// extra length bytes of a chunk of n pixels (n < 2^28, the host checks the image size)
inline int goo_extra(const long n) {
    return (n > 0xF) + (n > 0xFFF) + (n > 0xFFFFF);
}

// bytes of a chunk of n pixels of grey v
inline int goo_chunk_width(const long n, const int v) {
    return 1 + (v != 0 && v != 255) + goo_extra(n);
}

// run k's pixel index, its end, and the end of the run before it in its image (0 for the image's first run)
#define GOO_RUN(k_, i_)                                                     \
    const int r = (k_);                                                     \
    const long s = (long)row[r] * cols + x[r];                              \
    const long e = s + len[r];                                              \
    const int first = (k_) == img_off[i_];                                  \
    const long ps = first ? 0 : (long)row[r - 1] * cols + x[r - 1] + len[r - 1]; \
    const int last = (k_) == img_off[(i_) + 1] - 1;                         \
    const int g = grey[r]

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void goo_sizes(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               __global int *width, __global int *flags) {
    const int k = get_global_id(0);
    if (k >= m) return;
    const int i = run_image(img_off, n_img, k);
    GOO_RUN(k, i);
    if (!first && s == ps && g == grey[r - 1]) atomic_or(flags, 1);
    if (s < ps || len[r] < 1 || g == 0 || e > n_pixels) atomic_or(flags, 2);
    int w = goo_chunk_width(len[r], g);
    if (s > ps) w += goo_chunk_width(s - ps, 0);
    if (last && e < n_pixels) w += goo_chunk_width(n_pixels - e, 0);
    width[k] = w;
}

// one chunk of n pixels of grey v at out[at]: returns the next free position; the bytes' sum added to *sum
inline long goo_put(__global uchar *out, long at, const long n, const int v, uint *sum) {
    const int kind = v == 0 ? 0 : (v == 255 ? 3 : 1);
    const int size = goo_extra(n);
    const uint b0 = (uint)((kind << 6) | (size << 4) | (int)(n & 0xF));
    out[at++] = (uchar)b0;
    *sum += b0;
    if (kind == 1) {
        out[at++] = (uchar)v;
        *sum += (uint)v;
    }
    for (int j = size - 1; j >= 0; --j) {
        const uint b = (uint)((n >> (4 + 8 * j)) & 0xFF);
        out[at++] = (uchar)b;
        *sum += b;
    }
    return at;
}

// cum: the inclusive prefix sum of goo_sizes' widths; base[i]: image i's first chunk byte minus the widths of the
// runs before image i (so run k's first byte is base[i] + cum[k] - its width)
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void goo_write(const int m, const int n_img, const int cols, const long n_pixels, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               __global const int *cum, __global const long *base, __global uchar *out, __global uchar *sums) {
    const int k = get_global_id(0);
    if (k >= m) return;
    const int i = run_image(img_off, n_img, k);
    GOO_RUN(k, i);
    int w = goo_chunk_width(len[r], g);
    if (s > ps) w += goo_chunk_width(s - ps, 0);
    if (last && e < n_pixels) w += goo_chunk_width(n_pixels - e, 0);
    long at = base[i] + cum[k] - w;
    uint sum = 0;
    if (s > ps) at = goo_put(out, at, s - ps, 0, &sum);
    at = goo_put(out, at, len[r], g, &sum);
    if (last && e < n_pixels) goo_put(out, at, n_pixels - e, 0, &sum);
    sums[k] = (uchar)sum;
}
