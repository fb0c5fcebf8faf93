// PNG layers' deflate streams from run-length runs (gpuslice/raster/png_runs.py, PngRunsEncoder): the bits of the
// numpy twin gpuslice.raster.deflate_runs with huffman="static", several layers at once.
//
// A layer's filtered image (each row: filter byte 0, then cols greys) read as one string of rows * (cols + 1) bytes
// is a sequence of segments of one byte value: the blank stretch before run k (when not empty), run k, and after
// the layer's last run the blank tail (runs never touch across a row: the filter byte parts them; inside a row the
// runs kernel's neighbours differ). A segment of n bytes of value v is sent as its head, one literal v; its body,
// (n - 1) / 258 copies <258, 1>; its tail, r = (n - 1) % 258 more bytes: a copy <r, 1> when r >= 3, else r literals.
// With the static code a <258, 1> copy is two 0 bits, so bodies are skipped: the output buffer starts zeroed.
// Tokens go into 32-bit words, stream bit b at bit b % 32 of word b / 32 (little-endian: the host checks), with
// atomic_or (order-free: neighbours' tokens may share a word). Passes:
//   png_sizes: one work-item per run: its bits (blank stretch before it, itself, and for its layer's last run the
//       tail and the end-of-block code); flags |= 2 for runs the twin refuses (out of order, overlapping, outside the
//       image, empty or blank);
//   host: inclusive prefix sum of the bits, each layer's first bit (its stream starts on a byte);
//   png_write: one work-item per run: the layer's block header (its first run), its tokens at base[i] + cum[k] -
//       bits[k] + the header's bits, and its Adler-32 terms: a run of n bytes v at p of N adds n * v to A and
//       v * (n * (N - p) - n (n - 1) / 2) to B (mod 65521; the host adds them up per layer).
// Tables (host): lit_code/lit_len[286] (bit-reversed codes), len_val/len_nb[259] (for r >= 3: the length code, its
// extra bits and the 1-bit distance code 0, as one token), hdr[] (the block header, hdr_bits bits).

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define PNG_MOD 65521

// a token of nb <= 32 bits at stream bit pos
inline void png_put(__global uint *out, const long pos, const uint val, const int nb) {
    if (val == 0) return;
    const long w = pos >> 5;
    const int s = (int)(pos & 31);
    atomic_or(out + w, val << s);
    if (s + nb > 32) atomic_or(out + w + 1, val >> (32 - s));
}

#define PNG_TABLES                                                                                       \
    __global const uint *lit_code, __global const uchar *lit_len, __global const uint *len_val,        \
        __global const uchar *len_nb
#define PNG_TABLE_ARGS lit_code, lit_len, len_val, len_nb

// bits of a segment of n >= 1 bytes of value v
// body copies and tail bytes of a segment of n >= 1 bytes (n < 2^32: the host checks; no division when short)
#define PNG_SPLIT(n_)                                                         \
    const uint q = (n_) <= 258 ? 0 : (uint)((n_) - 1) / 258;                  \
    const int r = (int)((n_) - 1 - (long)q * 258)

inline long png_seg_bits(const long n, const int v, PNG_TABLES) {
    PNG_SPLIT(n);
    return lit_len[v] + (long)q * len_nb[258] + (r >= 3 ? len_nb[r] : r * lit_len[v]);
}

// writes the segment's tokens from pos; returns the bit after them
inline long png_seg_write(__global uint *out, long pos, const long n, const int v, PNG_TABLES) {
    PNG_SPLIT(n);
    png_put(out, pos, lit_code[v], lit_len[v]);
    pos += lit_len[v] + (long)q * len_nb[258];  // the body: zero bits (the host checks len_val[258] == 0)
    if (r >= 3) {
        png_put(out, pos, len_val[r], len_nb[r]);
        pos += len_nb[r];
    } else {
        for (int t = 0; t < r; ++t) {
            png_put(out, pos, lit_code[v], lit_len[v]);
            pos += lit_len[v];
        }
    }
    return pos;
}

// run k's byte position p in the flat filtered image, its end, the end of the run before it (0: none), whether it
// is its layer's last run, the image's byte count N
#define PNG_RUN(k_)                                                                             \
    const int i = run_image(img_off, n_img, k_);                                              \
    const int first = (k_) == img_off[i], last = (k_) == img_off[i + 1] - 1;                  \
    const long N = (long)rows * (cols + 1);                                                     \
    const long p = (long)row[k_] * (cols + 1) + 1 + x[k_];                                      \
    const long e = p + len[k_];                                                                 \
    const long pe = first ? 0 : (long)row[(k_) - 1] * (cols + 1) + 1 + x[(k_) - 1] + len[(k_) - 1]; \
    const int v = grey[k_]

// bits of run k (PNG_RUN in scope)
#define PNG_BITS                                                                                       \
    ((p > pe ? png_seg_bits(p - pe, 0, PNG_TABLE_ARGS) : 0) + png_seg_bits(len[k], v, PNG_TABLE_ARGS) + \
     (last ? (N > e ? png_seg_bits(N - e, 0, PNG_TABLE_ARGS) : 0) + lit_len[256] : 0))

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void png_sizes(const int m, const int n_img, const int cols, const int rows, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               PNG_TABLES, __global int *bits, __global int *flags) {
    const int k = get_global_id(0);
    if (k >= m) return;
    PNG_RUN(k);
    if (p < pe || row[k] < 0 || row[k] >= rows || x[k] < 0 || len[k] < 1 || x[k] + len[k] > cols || v == 0) {
        atomic_or(flags, 2);
        bits[k] = 0;
        return;
    }
    bits[k] = (int)PNG_BITS;
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void png_write(const int m, const int n_img, const int cols, const int rows, __global const int *img_off,
               __global const int *row, __global const int *x, __global const int *len, __global const uchar *grey,
               PNG_TABLES, __global const int *cum, __global const long *base, __global const uint *hdr,
               const int hdr_bits, __global uint *out, __global uint *ad_a, __global uint *ad_b) {
    const int k = get_global_id(0);
    if (k >= m) return;
    PNG_RUN(k);
    long pos = base[i] + cum[k] - PNG_BITS;
    if (first)  // the block header, just before the layer's first token
        for (int b = 0; b < hdr_bits; b += 32) png_put(out, pos - hdr_bits + b, hdr[b >> 5], min(32, hdr_bits - b));
    if (p > pe) pos = png_seg_write(out, pos, p - pe, 0, PNG_TABLE_ARGS);
    pos = png_seg_write(out, pos, len[k], v, PNG_TABLE_ARGS);
    if (last) {
        if (N > e) pos = png_seg_write(out, pos, N - e, 0, PNG_TABLE_ARGS);
        png_put(out, pos, lit_code[256], lit_len[256]);
    }
    const long n = len[k];
    ad_a[k] = (uint)((n * v) % PNG_MOD);
    ad_b[k] = (uint)((((n * (N - p) - n * (n - 1) / 2) % PNG_MOD) * v) % PNG_MOD);
}
