"""PNG layers straight from runs (gpuslice.raster.deflate_runs): decoded by Pillow and by zlib (which checks the
Adler-32), compared with ``Runs.to_mask`` and with a bitmap painted run by run in plain Python."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec
from gpuslice.raster.deflate_runs import HUFFMAN, _adler, _huffman_lengths, encode_png_from_runs
from gpuslice.raster.runs import Runs, layer_runs

Image = pytest.importorskip("PIL.Image")


def make_runs(layers: list[list[tuple[int, int, int, int]]], shape: tuple[int, int]) -> Runs:
    """A :class:`Runs` of layers given as lists of (row, x, length, grey), each sorted by (row, x)."""
    flat = [r for layer in layers for r in layer]
    off = np.cumsum([0] + [len(layer) for layer in layers]).astype(np.int64)
    col = lambda i, dt: np.array([r[i] for r in flat], dt)  # noqa: E731
    return Runs(np.arange(len(layers), dtype=np.int64), off, col(0, np.int32), col(1, np.int32), col(2, np.int32),
                col(3, np.uint8), shape)


def painted(layer: list[tuple[int, int, int, int]], shape: tuple[int, int]) -> np.ndarray:
    """The independent bitmap: every pixel of every run set in a Python loop."""
    out = np.zeros(shape, np.uint8)
    for row, x, n, g in layer:
        for j in range(x, x + n):
            out[row, j] = g
    return out


def idat(png: bytes) -> bytes:
    """The IDAT payload of a PNG (and the chunk layout checked: IHDR, one IDAT, IEND, CRCs)."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    pos, kinds, data = 8, [], b""
    while pos < len(png):
        (n,) = struct.unpack(">I", png[pos : pos + 4])
        kind, body = png[pos + 4 : pos + 8], png[pos + 8 : pos + 8 + n]
        assert struct.unpack(">I", png[pos + 8 + n : pos + 12 + n])[0] == zlib.crc32(kind + body)
        kinds.append(kind)
        if kind == b"IDAT":
            data = body
        pos += 12 + n
    assert kinds == [b"IHDR", b"IDAT", b"IEND"]
    return data


def check(runs: Runs, k: int, expected: np.ndarray | None = None) -> None:
    """Every encoding of entry ``k`` decodes (Pillow and zlib) to its mask (and to ``expected`` when given)."""
    rows, cols = runs.shape
    mask = runs.to_mask(k)
    if expected is not None:
        assert np.array_equal(mask, expected)
    for huffman in HUFFMAN:
        png = encode_png_from_runs(runs, k, cols, rows, huffman=huffman)
        with Image.open(io.BytesIO(png)) as im:
            assert im.mode == "L" and im.size == (cols, rows)
            assert np.array_equal(np.asarray(im), mask), huffman
        z = idat(png)
        assert z[:2] == b"\x78\x01"
        raw = zlib.decompress(z)  # checks the Adler-32
        assert len(raw) == rows * (cols + 1)
        assert struct.unpack(">I", z[-4:])[0] == zlib.adler32(raw)
        img = np.frombuffer(raw, np.uint8).reshape(rows, cols + 1)
        assert not img[:, 0].any()  # filter 0 on every row
        assert np.array_equal(img[:, 1:], mask), huffman


def random_layer(rng: np.random.Generator, shape: tuple[int, int], density: float = 0.5, max_len: int = 700):
    rows, cols = shape
    out = []
    for r in range(rows):
        if rng.random() > density:
            continue
        x, last = int(rng.integers(0, 3)), 0
        while x < cols:
            n = int(rng.integers(1, min(max_len, cols - x) + 1))
            g = int(rng.integers(1, 256))
            if out and out[-1][0] == r and out[-1][1] + out[-1][2] == x and g == last:
                g = g % 255 + 1  # touching runs of a row differ in grey, as Runs promises
            out.append((r, x, n, g))
            last = g
            x += n + int(rng.integers(0, 2)) * int(rng.integers(1, 40))
    return out


# ---- hand-made corner cases ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("width", [1, 2, 3, 4, 5, 11520])
def test_random_runs_small_and_wide(width):
    rng = np.random.default_rng(width)
    shape = (7 if width > 5 else 9, width)
    layers = [random_layer(rng, shape, d) for d in (0.3, 0.7, 1.0)] + [[]]
    runs = make_runs(layers, shape)
    for k, layer in enumerate(layers):
        check(runs, k, painted(layer, shape))


@pytest.mark.parametrize("width", [1, 2, 3, 4, 5, 257, 258, 259, 260, 517, 11520])
def test_full_rows_ends_and_single_pixels(width):
    shape = (6, width)
    layers = [
        [(r, 0, width, 255) for r in range(6)],  # every row full
        [(0, 0, 1, 7), (2, width - 1, 1, 9), (5, 0, width, 1)],  # the first pixel, the last pixel, a full last row
        [(r, x, 1, 1 + (x * 37 + r) % 255) for r in (1, 4) for x in range(width)],  # length-1 runs all along
        [(3, 0, width, 128)],
    ]
    runs = make_runs(layers, shape)
    for k, layer in enumerate(layers):
        check(runs, k, painted(layer, shape))


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 257, 258, 259, 260, 261, 262, 515, 516, 517, 518, 519, 520, 1000, 11520])
def test_run_lengths_around_copy_limits(n):
    """Body copies of 258 and tails of 0, 1, 2 (literals) and 3+ (one copy) for runs and zero gaps alike."""
    shape = (4, 11520)
    layer = [(0, 0, n, 200), (1, 11520 - n, n, 3), (2, (11520 - n) // 2, n, 77)]
    runs = make_runs([layer], shape)
    check(runs, 0, painted(layer, shape))


def test_blank_layer_and_blank_image():
    runs = make_runs([[], [(1, 1, 1, 1)], []], (5, 5))
    for k in range(3):
        check(runs, k)
    big = make_runs([[]], (5120, 11520))  # all black: one long zero segment
    check(big, 0, np.zeros((5120, 11520), np.uint8))
    assert len(encode_png_from_runs(big, 0, 11520, 5120)) < 80_000  # ~2 bits per 258 zeros


def test_image_larger_than_runs_shape():
    """The runs only need to fit: width and height may exceed runs.shape (pixels outside are 0)."""
    layer = [(0, 0, 3, 9), (2, 1, 2, 8)]
    runs = make_runs([layer], (3, 3))
    png = encode_png_from_runs(runs, 0, 5, 4)
    with Image.open(io.BytesIO(png)) as im:
        got = np.asarray(im)
    want = np.zeros((4, 5), np.uint8)
    want[:3, :3] = painted(layer, (3, 3))
    assert np.array_equal(got, want)


def test_errors():
    runs = make_runs([[(0, 2, 3, 9)]], (2, 5))
    with pytest.raises(ParameterError):
        encode_png_from_runs(runs, 0, 5, 2, huffman="adaptive")
    with pytest.raises(ParameterError):
        encode_png_from_runs(runs, 0, 4, 2)  # run past the right edge
    with pytest.raises(ParameterError):
        encode_png_from_runs(make_runs([[(0, 0, 3, 9), (0, 2, 2, 5)]], (2, 5)), 0, 5, 2)  # overlapping runs
    with pytest.raises(ParameterError):
        encode_png_from_runs(runs, 0, 0, 2)


# ---- the arithmetic Adler-32 and the Huffman code lengths ---------------------------------------------------------
def test_adler_from_runs_matches_zlib():
    rng = np.random.default_rng(5)
    for total in (1, 2, 100, 5000, 300_000):
        n_runs = int(rng.integers(0, 30))
        cuts = np.sort(rng.choice(total + 1, size=2 * n_runs, replace=True))
        p, n = cuts[0::2], cuts[1::2] - cuts[0::2]
        keep = n > 0
        p, n = p[keep].astype(np.int64), n[keep].astype(np.int64)
        v = rng.integers(1, 256, p.size).astype(np.int64)
        buf = np.zeros(total, np.uint8)
        for a, m, g in zip(p, n, v, strict=True):
            buf[a : a + m] = g
        assert _adler(p, n, v, total) == zlib.adler32(buf.tobytes())


def test_adler_run_update_formula():
    """The O(1) update of the brief: n bytes v from (A, B): A += n·v, B += n·A + v·n(n + 1)/2 (mod 65521)."""
    rng = np.random.default_rng(9)
    value = 1
    data = b""
    for _ in range(50):
        n, v = int(rng.integers(1, 20000)), int(rng.integers(0, 256))
        a, b = value & 0xFFFF, value >> 16
        a2 = (a + n * v) % 65521
        b2 = (b + n * a + v * n * (n + 1) // 2) % 65521
        data += bytes([v]) * n
        value = (b2 << 16) | a2
        assert value == zlib.adler32(data)


def test_huffman_lengths_limited_and_complete():
    fib = [1, 1]
    while len(fib) < 40:
        fib.append(fib[-1] + fib[-2])  # the deepest Huffman trees: 39 levels unlimited
    for freq in (np.array(fib), np.array([5, 0, 0, 1]), np.array([0, 3, 0]), np.arange(286) % 7):
        ln = _huffman_lengths(freq)
        assert np.all((ln > 0) == (freq > 0)) and ln.max() <= 15
        if np.count_nonzero(freq) > 1:
            assert sum(2.0 ** -int(x) for x in ln[ln > 0]) == 1.0  # complete, as inflate requires


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 40), st.lists(st.tuples(st.integers(0, 600), st.integers(1, 600), st.integers(1, 255)),
                                    max_size=12))
def test_hypothesis_row_of_segments(width_extra, pieces):
    """One row of gaps and runs of any lengths (a zero gap keeps touching runs apart or merges them)."""
    layer, x = [], 0
    for gap, n, g in pieces:
        x += gap
        if layer and layer[-1][1] + layer[-1][2] == x and layer[-1][3] == g:
            g = g % 255 + 1
        layer.append((1, x, n, g))
        x += n
    shape = (3, x + width_extra)
    check(make_runs([layer], shape), 0, painted(layer, shape))


# ---- a sliced model ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(40.0, 15.0, 96, 48)), thickness=2.0, backend="numpy")


@pytest.mark.parametrize("gamma", [1.0, 0.0])
@pytest.mark.parametrize("resolution, pixel", [((3840, 2400), 0.05), ((1000, 700), 0.13)])
def test_sliced_model(torus, gamma, resolution, pixel):
    spec = RasterSpec(resolution=resolution, pixel=pixel, gamma=gamma)
    layers = sorted({int(i) for i in np.linspace(0, torus.n_layers - 1, 5)})
    runs = layer_runs(torus, spec, backend="numpy", layers=layers, clip=True)  # (the 0.13 mm display crops it)
    assert runs.n_runs > 0
    for k in range(len(layers)):
        check(runs, k)


# ---- the PNG kernels (kernels/png.cl) against their twin, huffman="static" -----------------------------------------
def test_kernels_write_the_static_twins_bytes(device):
    """Groups of layers (any first entry; blank layers first, inside and last; whole rows; lone pixels in the
    corners; every grey): the kernels' PNGs equal the twin's, byte for byte, and decode to the layers."""
    import sys
    from pathlib import Path

    from gpuslice.raster.png_runs import PngRunsEncoder

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run_images import runs_of

    enc = PngRunsEncoder.of(device)
    rng = np.random.default_rng(23)
    h, w = 19, 61
    imgs = []
    for k in range(24):
        img = rng.choice(np.array([0, 0, 0, 255, 255, 1, 2, 77, 200, 230, 254], np.uint8), size=(h, w))
        img[rng.random((h, w)) < 0.2 * (k % 5)] = 0
        imgs.append(img)
    for k in (0, 9, 23):
        imgs[k][:] = 0
    imgs[4][:] = 0
    imgs[4][0, 0] = imgs[4][-1, -1] = 255
    imgs[5][:] = 255
    runs = runs_of(imgs)
    before = enc.fallbacks
    for a, b in ((0, 24), (0, 1), (3, 17), (4, 6), (9, 11), (23, 24), (5, 23)):
        got = enc.encode(runs, a, b, w, h)
        assert got == [encode_png_from_runs(runs, k, w, h, "static") for k in range(a, b)], (a, b)
        for k, png in zip(range(a, b), got, strict=True):
            assert np.array_equal(np.asarray(Image.open(io.BytesIO(png))), imgs[k])
    assert enc.fallbacks == before


def test_kernels_every_tail_and_long_blanks(device):
    """Runs and blank stretches of every tail (r = 0 … 257 bytes after the bodies of 258: literals for r < 3, one
    copy from 3), a 16K display's blank layer around one pixel (bodies of ~360,000 copies), and runs the twin
    refuses (overlapping): left to it, which raises."""
    from gpuslice.raster.png_runs import PngRunsEncoder

    enc = PngRunsEncoder.of(device)
    lengths = np.concatenate((np.arange(1, 261), np.arange(517, 778, 13)))
    cols = int(lengths.sum() + 2 * lengths.size) + 5
    x = np.cumsum(np.concatenate(([0], lengths[:-1] + 2))).astype(np.int32)
    grey = np.where(np.arange(lengths.size) % 3 == 0, 255, 1 + np.arange(lengths.size) % 250).astype(np.uint8)
    runs = Runs(np.arange(1), np.array([0, lengths.size]), np.zeros(lengths.size, np.int32), x,
                lengths.astype(np.int32), grey, (2, cols))
    got = enc.encode(runs, 0, 1, cols, 2)
    assert got == [encode_png_from_runs(runs, 0, cols, 2, "static")]
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(got[0]))), runs.to_mask(0))
    big = Runs(np.arange(2), np.array([0, 1, 1]), np.array([3000], np.int32), np.array([7000], np.int32),
               np.array([1], np.int32), np.array([200], np.uint8), (6230, 15120))
    got = enc.encode(big, 0, 2, 15120, 6230)
    assert got == [encode_png_from_runs(big, k, 15120, 6230, "static") for k in range(2)]
    n = struct.unpack(">I", got[0][33:37])[0]  # the IDAT after the signature and IHDR (zlib: no pixel-count limit)
    img = np.frombuffer(zlib.decompress(got[0][41 : 41 + n]), np.uint8).reshape(6230, 15121)[:, 1:]
    assert img[3000, 7000] == 200 and int(img.sum()) == 200
    bad = make_runs([[(0, 0, 3, 9), (0, 2, 2, 5)]], (2, 5))
    before = enc.fallbacks
    assert enc.encode(bad, 0, 1, 5, 2) is None and enc.fallbacks == before + 1
