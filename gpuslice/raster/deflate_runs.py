"""PNG layers written straight from run-length runs (:class:`~gpuslice.raster.runs.Runs`): no bitmap, no deflater.

A layer's PNG is greyscale, 8 bits, filter 0 on every row, one IDAT, as :mod:`gpuslice.raster.png`'s. Its filtered
image (each row: filter byte 0, then ``width`` greys), read as one string of ``height·(width + 1)`` bytes, is a
sequence of *segments* of one byte value each: the layer's runs, and the stretches of zeros between them (blank
pixels, filter bytes and whole blank rows alike, so a blank row costs only its share of a long zero segment). A
segment of n bytes of value v is deflated (RFC 1951) with distance-1 copies, which repeat the byte before them:

* **head**: one literal ``v`` (the byte before differs, or there is none);
* **body**: ``(n − 1) // 258`` copies <length 258, distance 1>, all the same code;
* **tail**: r = (n − 1) % 258 more bytes: one copy <r, 1> if r ≥ 3, else r literals ``v``.

The zlib stream is ``78 01``, one final deflate block, the Adler-32. The block's codes are (``huffman``):

* ``"static"`` (default): one code for every layer (:data:`STATIC_LENGTHS`), sent in a dynamic block's header as
  ``"dynamic"`` sends its own; a <258, 1> copy is two 0 bits. The PNG kernel (``kernels/png.cl``,
  :mod:`gpuslice.raster.png_runs`) writes these bytes, this module is its twin; files ~2-3 % larger than
  ``"dynamic"``'s on the armadillo job;
* ``"dynamic"``: Huffman code lengths (≤ 15) from this layer's symbol counts; the header sends every code
  length with a flat 4-bit code-length code (about 150 bytes). The only distance is 1, one code of one bit, so a
  body copy costs about 2 bits per 258 bytes (zlib level 9 does no better on zeros);
* ``"fixed"``: RFC 1951 §3.2.6's fixed codes: no header, but 13 bits per 258 bytes, so blank areas come out ~6×
  larger than zlib's.

**Bit packing** (numpy, no loop per run): each head, tail and header field is a *token* (value, bit count ≤ 64) and
each body one token of ``q·b`` bits (b: bits of one copy); bit offsets are a cumulative sum. Tokens are OR-ed into
little-endian 64-bit words (the stream's bit k is bit k % 8 of byte k // 8) with ``bitwise_or.reduceat`` over the
tokens starting in each word, plus the one token that spills into the next word. A body is periodic with period b,
so its words come from a table of the b phases of the pattern: the cost is per output word, not per copy.

**Adler-32** from the runs alone: over N bytes from A = 1, B = 0, A = 1 + Σ d_i and B = N + Σ d_i·(N − i); a run of
n bytes v at p adds n·v to A and v·(n·(N − p) − n(n − 1)/2) to B; zeros add nothing beyond the N.

The decoded pixels equal ``runs.to_mask(k)``; the files are not byte-identical to :class:`~.png.PngEncoder`'s.
"""

from __future__ import annotations

import heapq
import struct

import numpy as np

from ..errors import ParameterError
from ..ragged import expand_ranges
from .png import png_chunk
from .runs import Runs

__all__ = ["encode_png_from_runs", "HUFFMAN"]

HUFFMAN = ("dynamic", "fixed", "static")
_SIG = b"\x89PNG\r\n\x1a\n"
_MOD = 65521
_MAXLEN = 258
_U64 = np.uint64
_ONES = _U64(0xFFFFFFFFFFFFFFFF)
# lengths 3..258 -> symbols 257..285 (RFC 1951 §3.2.5)
_LEN_BASE = np.array([3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115, 131,
                      163, 195, 227, 258])
_LEN_XBITS = np.array([0] * 8 + [1] * 4 + [2] * 4 + [3] * 4 + [4] * 4 + [5] * 4 + [0])
_L = np.arange(_MAXLEN + 1)
_LCODE = np.clip(np.searchsorted(_LEN_BASE, _L, side="right") - 1, 0, None)  # index 0..28 of length L (L >= 3)
_LSYM, _LXBITS, _LXVAL = 257 + _LCODE, _LEN_XBITS[_LCODE], _L - _LEN_BASE[_LCODE]
_FIXED_LENGTHS = np.array([8] * 144 + [9] * 112 + [7] * 24 + [8] * 8)
_CL_ORDER = [16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15]


_REV15 = sum(((np.arange(1 << 15) >> b) & 1) << (14 - b) for b in range(15))  # [c]: c's 15 bits reversed


def _reverse(code: np.ndarray, length: np.ndarray) -> np.ndarray:
    """``code`` with its ``length`` (≤ 15) low bits reversed (Huffman codes are sent most significant bit first)."""
    return _REV15[code] >> (15 - length)


def _canonical(lengths: np.ndarray) -> np.ndarray:
    """Canonical Huffman codes (RFC 1951 §3.2.2) of code ``lengths`` (0 = unused), bit-reversed, as int64."""
    sym = np.flatnonzero(lengths)
    sym = sym[np.argsort(lengths[sym], kind="stable")]
    ln = lengths[sym].astype(np.int64)
    kraft = np.int64(1) << (15 - ln)
    code = (np.cumsum(kraft) - kraft) >> (15 - ln)
    out = np.zeros(lengths.size, np.int64)
    out[sym] = _reverse(code, ln)
    return out


_FIXED_CODE = _canonical(_FIXED_LENGTHS)

#: ``"static"``: one dynamic-block code for every layer (RFC 1951 §3.2.7 header, sent as ``"dynamic"`` sends it):
#: the <258, 1> copy's length symbol 285 gets 1 bit, the literals 0 and 255 3 bits, literals 200-253 11 bits and the
#: other literals, lengths and the end of block 10 bits (a complete code: 1/2 + 2/8 + 229/1024 + 54/2048 = 1). With
#: the one distance code of 1 bit, a <258, 1> copy is two 0 bits: blank areas cost no writes (the PNG kernel's
#: bodies are its zeroed buffer). Files about as small as "dynamic"'s for binary layers, a few % larger with greys.
STATIC_LENGTHS = np.full(286, 10, np.int64)
STATIC_LENGTHS[[0, 255]] = 3
STATIC_LENGTHS[200:254] = 11
STATIC_LENGTHS[285] = 1
STATIC_CODE = _canonical(STATIC_LENGTHS)


def _huffman_lengths(freq: np.ndarray, limit: int = 15) -> np.ndarray:
    """Huffman code lengths of ``freq`` (0 for unused symbols), at most ``limit`` bits: the counts are halved
    (nonzero ones kept ≥ 1) until the tree is shallow enough. Heap items are ``count << 10 | node`` (ints)."""
    f = np.asarray(freq, np.int64)
    out = np.zeros(f.size, np.int64)
    while True:
        syms = np.flatnonzero(f)
        n = syms.size
        if n == 1:
            out[syms] = 1
            return out
        heap = ((f[syms] << 10) | np.arange(n)).tolist()
        heapq.heapify(heap)
        parent = [0] * (2 * n - 1)
        for node in range(n, 2 * n - 1):
            a = heapq.heappop(heap)
            b = heap[0]
            parent[a & 1023] = parent[b & 1023] = node
            heapq.heapreplace(heap, (((a >> 10) + (b >> 10)) << 10) | node)
        depth = [0] * (2 * n - 1)
        for i in range(2 * n - 3, -1, -1):
            depth[i] = depth[parent[i]] + 1
        if max(depth[:n]) <= limit:
            out[syms] = depth[:n]
            return out
        f = np.where(f > 0, np.maximum(f >> 1, 1), 0)


def _segments(runs: Runs, k: int, width: int, height: int):
    """(value, length, run starts, run lengths, run greys) of entry ``k``: segments of the flat filtered image."""
    a, b = int(runs.layer_offsets[k]), int(runs.layer_offsets[k + 1])
    row, x = runs.row[a:b].astype(np.int64), runs.x[a:b].astype(np.int64)
    n, v = runs.length[a:b].astype(np.int64), runs.grey[a:b].astype(np.int64)
    total = height * (width + 1)
    if n.size and (row.min() < 0 or row.max() >= height or x.min() < 0 or (x + n).max() > width or n.min() < 1):
        raise ParameterError(f"runs of entry {k} do not fit a {width}x{height} image")
    p = row * (width + 1) + 1 + x
    seg_n = np.empty(2 * n.size + 1, np.int64)
    seg_n[1::2] = n
    seg_n[0:-1:2] = p - np.concatenate(([0], p[:-1] + n[:-1]))
    seg_n[-1] = total - (p[-1] + n[-1] if n.size else 0)
    if np.any(seg_n < 0):
        raise ParameterError(f"runs of entry {k} overlap or are not sorted by (row, x)")
    seg_v = np.zeros(seg_n.size, np.int64)
    seg_v[1::2] = v
    keep = seg_n > 0
    return seg_v[keep], seg_n[keep], p, n, v


def _adler(p: np.ndarray, n: np.ndarray, v: np.ndarray, total: int) -> int:
    """Adler-32 of ``total`` bytes, zero but for runs of ``n`` bytes ``v`` at ``p`` (module docstring)."""
    a = (1 + int(np.dot(v, n))) % _MOD
    w = (n * (total - p) - n * (n - 1) // 2) % _MOD
    b = (total + int(np.dot(v, w) % _MOD)) % _MOD
    return (b << 16) | a


def _pack(val: np.ndarray, nb: np.ndarray, body: np.ndarray, pattern: int, pbits: int) -> bytes:
    """The bit stream of tokens ``val`` (uint64) of ``nb`` bits, in order; entries flagged ``body`` are runs of the
    ``pbits``-bit ``pattern`` repeated ``nb / pbits`` times (their ``val`` is ignored). Padded to a byte."""
    off = np.cumsum(nb) - nb
    total = int(off[-1] + nb[-1])
    words = _pack_words(val, nb, off, body, pattern, pbits, total // 64 + 2)
    return words.astype("<u8", copy=False).view(np.uint8)[: (total + 7) // 8].tobytes()


def _pack_words(val: np.ndarray, nb: np.ndarray, off: np.ndarray, body: np.ndarray, pattern: int, pbits: int,
                n_words: int) -> np.ndarray:
    """``n_words`` uint64 words holding tokens ``val`` of ``nb`` bits at bit offsets ``off`` (increasing; tokens do
    not overlap), bodies as in :func:`_pack`. A body's words after its first and before its last hold nothing else;
    when ``pbits`` divides 64 (the usual case: a 1-bit <258> code and the 1-bit distance) they are all one word,
    so all bodies' middles are laid down with one ``np.repeat``, the cost of a memset."""
    bi = np.flatnonzero(body)
    o, ln = off[bi], nb[bi]
    w0, w1 = o >> 6, (o + ln - 1) >> 6
    i = np.arange(64)
    ph = np.arange(pbits)[:, None]
    tape = np.bitwise_or.reduce(((pattern >> (ph + i) % pbits) & 1).astype(_U64) << i.astype(_U64), axis=1)
    periodic = bi.size and 64 % pbits == 0
    if periodic:  # words = zeros, then each body's middle words [w0 + 1, w1): one constant per body
        mids = np.maximum(w1 - w0 - 1, 0)
        gaps = (w0 + 1) - np.concatenate(([0], w0[:-1] + 1 + mids[:-1]))
        lens = np.empty(2 * bi.size + 1, np.int64)
        lens[0:-1:2], lens[1::2], lens[-1] = gaps, mids, n_words - (w0[-1] + 1 + mids[-1])
        vals = np.zeros(lens.size, _U64)
        vals[1::2] = tape[(-o) % pbits]
        words = np.repeat(vals, lens)
    else:
        words = np.zeros(n_words, _U64)
    val = np.where(body, _U64(0), val)  # bodies add nothing here (zero value, and zero spill)
    w, s = off >> 6, (off & 63).astype(_U64)
    first = np.flatnonzero(np.concatenate(([True], w[1:] != w[:-1])))
    words[w[first]] = np.bitwise_or.reduceat(val << s, first)  # never a body's middle word: no token starts there
    sp = np.flatnonzero((s + nb.astype(_U64) > 64) & ~body)
    words[w[sp] + 1] |= val[sp] >> (_U64(64) - s[sp])
    if bi.size:
        single = w0 == w1
        head = tape[0] << (o & 63).astype(_U64)
        head[single] &= (_ONES >> (64 - ln[single]).astype(_U64)) << (o[single] & 63).astype(_U64)
        if periodic:  # only the last words are left
            multi = np.flatnonzero(~single)
            wi, ow = w1[multi], multi
        else:
            ow, wi = expand_ranges(w0 + 1, w1 - w0)
        part = tape[(64 * wi - o[ow]) % pbits]
        last = wi == w1[ow]
        end = (o + ln)[ow[last]] - 64 * wi[last]
        part[last] &= _ONES >> (64 - end).astype(_U64)
        if not periodic:
            words[wi[~last]] = part[~last]
        np.bitwise_or.at(words, np.concatenate((w0, wi[last])), np.concatenate((head, part[last])))
    return words


def _codes(seg_v: np.ndarray, q: np.ndarray, r: np.ndarray, huffman: str):
    """(code, lengths, header values, header bit counts, distance bits) of one deflate block for segments of values
    ``seg_v`` with ``q`` body copies and tails of ``r`` bytes (module docstring)."""
    if huffman == "fixed":
        return _FIXED_CODE, _FIXED_LENGTHS, np.array([3]), np.array([3]), 5  # BFINAL 1, BTYPE 01
    if huffman == "static":
        lengths, code = STATIC_LENGTHS, STATIC_CODE
    else:
        tail_match = r >= 3
        freq = np.zeros(286, np.int64)
        freq[:256] = np.bincount(seg_v, weights=1 + np.where(tail_match, 0, r), minlength=256)
        freq[256] = 1
        freq[_LSYM[_MAXLEN]] += int(q.sum())
        np.add.at(freq, _LSYM[r[tail_match]], 1)
        lengths = _huffman_lengths(freq)
        code = _canonical(lengths)
    nlit = int(np.flatnonzero(lengths)[-1]) + 1
    cl = [4 * (s < 16) for s in _CL_ORDER]  # the code-length code: symbols 0..15, 4 bits each
    code_lens = np.concatenate((lengths[:nlit], [1]))  # then one distance code of 1 bit
    hdr_val = np.concatenate(([5, nlit - 257, 0, 15], cl, _reverse(code_lens, np.full(code_lens.size, 4))))
    hdr_nb = np.concatenate(([3, 5, 5, 4], [3] * 19, np.full(code_lens.size, 4)))
    return code, lengths, hdr_val, hdr_nb, 1


def _split(seg_n: np.ndarray):
    """(q, r, per): body copies, tail bytes and tokens (head, body?, tail?) of segments of ``seg_n`` bytes."""
    m = seg_n - 1
    q, r = m // _MAXLEN, m % _MAXLEN
    return q, r, 1 + (q > 0) + (r > 0)


def _fill_tokens(seg_v, q, r, es, val, nb, body, code, lengths, dist_bits) -> tuple[int, int]:
    """Write each segment's tokens (head literal, body, tail) at token positions ``es`` of ``val``/``nb``/``body``;
    returns (the body pattern, its bits): one <258, 1> copy."""
    has_body, has_tail, tail_match = q > 0, r > 0, r >= 3
    lit_val, lit_nb = code[:256], lengths[:256]
    mval = code[_LSYM] | (_LXVAL << lengths[_LSYM])  # then the distance code: dist_bits zeros
    mnb = lengths[_LSYM] + _LXBITS + dist_bits
    val[es], nb[es] = lit_val[seg_v], lit_nb[seg_v]
    bi = es[has_body] + 1
    nb[bi], body[bi] = q[has_body] * mnb[_MAXLEN], True
    ti, rt, vt, tm = es[has_tail] + 1 + has_body[has_tail], r[has_tail], seg_v[has_tail], tail_match[has_tail]
    lv, lb = lit_val[vt], lit_nb[vt]
    val[ti] = np.where(tm, mval[rt], lv | np.where(rt == 2, lv << lb, 0))
    nb[ti] = np.where(tm, mnb[rt], rt * lb)
    return int(mval[_MAXLEN]), int(mnb[_MAXLEN])


def _deflate(seg_v: np.ndarray, seg_n: np.ndarray, huffman: str) -> bytes:
    """One final deflate block of the segments (module docstring)."""
    q, r, per = _split(seg_n)
    code, lengths, hdr_val, hdr_nb, dist_bits = _codes(seg_v, q, r, huffman)
    h = hdr_val.size
    es = h + np.cumsum(per) - per
    e = h + int(per.sum()) + 1
    val, nb, body = np.zeros(e, np.int64), np.zeros(e, np.int64), np.zeros(e, bool)
    val[:h], nb[:h] = hdr_val, hdr_nb
    pattern, pbits = _fill_tokens(seg_v, q, r, es, val, nb, body, code, lengths, dist_bits)
    val[-1], nb[-1] = code[256], lengths[256]  # end of block
    return _pack(val.astype(_U64), nb, body, pattern, pbits)


def encode_png_from_runs(runs: Runs, k: int, width: int, height: int, huffman: str = "static") -> bytes:
    """The PNG file (greyscale, 8 bits, ``width`` × ``height``) of entry ``k`` of ``runs`` (a position in
    ``runs.layers``): its decoded pixels are ``runs.to_mask(k)``. ``huffman``: ``"static"`` (one code for every
    layer: the PNG kernel's bytes), ``"dynamic"`` (each layer's own code) or ``"fixed"`` (RFC 1951's fixed codes);
    see the module docstring for the encoding."""
    if huffman not in HUFFMAN:
        raise ParameterError(f"unknown huffman '{huffman}' (use {', '.join(HUFFMAN)})")
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise ParameterError(f"image size must be positive, got {width}x{height}")
    seg_v, seg_n, p, n, v = _segments(runs, k, width, height)
    adler = _adler(p, n, v, height * (width + 1))
    return _png(b"\x78\x01" + _deflate(seg_v, seg_n, huffman) + struct.pack(">I", adler), width, height)


def _png(idat: bytes, width: int, height: int) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return _SIG + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")
