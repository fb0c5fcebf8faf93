"""Archive previews show the part as seen from above, whatever the display does to the layers.

The layers are mirrored or turned for the printer's optics (``RasterSpec`` mirrors, portrait); a preview copied from
them showed a mirror image on the printer's screen (an audit found every mirror-x preset's previews mirrored and the
portrait SL1's transposed). A chiral part (a bar along x and a block above its left end) must come out with the
block at the top left and the bar twice as wide as the whole is tall, on every display."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec, iter_tiles
from gpuslice.raster.layers import top_view
from gpuslice.raster.photon import BACKGROUND, PREVIEW, _TopView
from gpuslice.raster.sl1 import _Thumb

pytest.importorskip("PIL.Image")

DISPLAYS = [dict(), dict(mirror_x=True), dict(mirror_y=True), dict(mirror_x=True, mirror_y=True),
            dict(portrait=True), dict(portrait=True, mirror_x=True), dict(portrait=True, mirror_y=True),
            dict(pixel_y=0.15, mirror_x=True), dict(pixel_y=0.15, portrait=True, mirror_x=True)]


@pytest.fixture(scope="module")
def chiral():
    """A 20 x 4 mm bar along x and a 4 x 4 mm block 2 mm above its left end (y up): 20 mm wide, 10 mm tall."""
    tris = np.concatenate([shapes.box((0, 0, 0), (20, 4, 2)), shapes.box((0, 6, 0), (4, 10, 2))])
    return slice_mesh(mesh_from_triangles(tris), thickness=0.5, backend="numpy")


def _seen_from_above(lit: np.ndarray, what: str) -> None:
    ys, xs = np.nonzero(lit)
    assert ys.size, what
    part = lit[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
    h, w = part.shape
    assert 1.7 < w / h < 2.3, f"{what}: {w}x{h}, not 20 x 10 mm (turned?)"
    top, bottom = part[: int(0.3 * h)], part[int(0.7 * h) :]
    assert top[:, : int(0.15 * w)].mean() > 0.8 and top[:, int(0.3 * w) :].mean() < 0.05, f"{what}: mirrored?"
    assert bottom.mean() > 0.8, f"{what}: the bar is not at the bottom"


@pytest.mark.parametrize("kw", DISPLAYS, ids=lambda kw: "-".join(kw) or "plain")
def test_thumbnails_show_the_part_as_seen_from_above(chiral, kw):
    spec = RasterSpec(resolution=(600, 400), pixel=0.1, **kw)
    thumb = _Thumb(spec, chiral.n_layers, step=1)
    view = _TopView(spec, chiral.n_layers)
    for tile in iter_tiles(chiral, spec, backend="numpy"):
        thumb.add(tile)
        view.add(tile)
    rgb = np.asarray(thumb.image((400, 400)))
    _seen_from_above(rgb[..., 0] > 60, f"SL1-style thumbnail, {kw}")
    v = np.frombuffer(view.rgb565(PREVIEW), "<u2").reshape(PREVIEW[1], PREVIEW[0])
    _seen_from_above((v >> 11) * 8 > BACKGROUND[0] + 40, f"Photon preview, {kw}")


def test_top_view_undoes_the_display_and_copies_nothing():
    img = np.arange(12).reshape(3, 4)
    plain = RasterSpec(resolution=(4, 3), pixel=0.1)
    assert np.shares_memory(top_view(img, plain), img) and np.array_equal(top_view(img, plain), img)
    assert np.array_equal(top_view(img, RasterSpec(resolution=(4, 3), pixel=0.1, mirror_x=True)), img[:, ::-1])
    # portrait without mirrors: the PNG's columns run down along -y, its rows up along x
    assert np.array_equal(top_view(img, RasterSpec(resolution=(3, 4), pixel=0.1, portrait=True)), img.T[:, ::-1])
