"""The layer viewer (``gpuslice view``): the page's embedded data, the command line, and the page in headless Chromium.

The browser tests drive Debian's ``/usr/bin/chromium`` through playwright (never a downloaded browser) and skip with
a reason where either is absent. Each opens a page over ``file://``, moves the slider (keys, the input, the chart)
and compares the shown text with the :class:`SliceResult`, reads the drawing back from screenshots, and checks that
the page asks for nothing but its own ``file:``/``data:`` URLs.
"""

from __future__ import annotations

import io
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import gpuslice
from gpuslice.cli import main
from gpuslice.errors import MeshFileError, ParameterError
from gpuslice.mesh import shapes
from gpuslice.view.page import build_view_html, read_view_data, write_view

CHROMIUM = os.environ.get("GPUSLICE_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]
WHITE = np.array([255, 255, 255])


def _slice(tri: np.ndarray, **kw) -> gpuslice.SliceResult:
    mesh = gpuslice.mesh_from_triangles(tri, name="test.stl")
    return gpuslice.slice_mesh(mesh, backend="numpy", **kw)


@pytest.fixture(scope="module")
def torus() -> gpuslice.SliceResult:
    """A torus lying on the bed: every layer is a ring, an outer loop and a hole, centred on (0, 0)."""
    return _slice(shapes.torus(), thickness=0.5)


@pytest.fixture(scope="module")
def open_box() -> gpuslice.SliceResult:
    """A box with a side facet missing, gap closing and hole filling off: every layer is one open chain."""
    return _slice(np.delete(shapes.box(), 5, axis=0), thickness=1.0, max_gap=0.0, fill_holes=False)


# ---- the page and its data (no browser) ------------------------------------------------------------------------
def test_page_embeds_the_result_columns(torus, open_box, tmp_path):
    for res in (torus, open_box):
        path = tmp_path / "v.html"
        size = write_view(res, path)
        assert size == path.stat().st_size
        data = read_view_data(path)
        a = data["arrays"]
        np.testing.assert_array_equal(a["points"].reshape(-1, 2), res.points)
        np.testing.assert_array_equal(a["loop_offsets"], res.loop_offsets)
        np.testing.assert_array_equal(a["layer_offsets"], res.layer_offsets)
        np.testing.assert_array_equal(a["loop_flags"] & 1, res.loop_is_hole)
        np.testing.assert_array_equal(a["loop_flags"] >> 1, ~res.loop_closed)
        for name in ("z", "thickness", "area"):
            np.testing.assert_array_equal(a[name], getattr(res, name))
        np.testing.assert_array_equal(a["layer_points"], res.points_per_layer)
        assert set(data["repairs"]) == {k for k, v in res.repairs.items() if v.any()}
        for kind, counts in data["repairs"].items():
            np.testing.assert_array_equal(counts, res.repairs[kind])
        assert data["fill_rule"] == "nonzero"
        assert f"{res.n_layers:,} layers" in data["summary"]
    assert "open_chains" in read_view_data(build_view_html(open_box))["repairs"]
    with pytest.raises(MeshFileError, match="not a gpuslice viewer page"):
        read_view_data("<html></html>")


def test_browser_pages_without_polygons(browser, tmp_path):
    """Layers above the part (no loops) and a result with no layers at all: the page loads and says so."""
    above = _slice(shapes.box(), z=np.array([30.0, 40.0]))
    assert above.n_layers == 2 and above.n_loops == 0
    v = Page(browser, above, tmp_path)
    v.page.keyboard.press("End")
    v.check_layer_text(1)
    # nothing drawn (read from the canvas itself: the screenshot also shows the legend laid over it)
    js = "(() => { const c = document.getElementById('view'); const d = c.getContext('2d')" \
         ".getImageData(0, 0, c.width, c.height).data; let n = 0; for (const b of d) n += b !== 255; return n; })()"
    assert v.page.evaluate(js) == 0
    v.close()
    empty = above.__class__(**{**above.__dict__, "z": above.z[:0], "thickness": above.thickness[:0],
                               "area": above.area[:0], "layer_offsets": above.layer_offsets[:1], "repairs": {}})
    v = Page(browser, empty, tmp_path)
    assert v.text("layer-last") == "no layers" and v.page.evaluate("gpusliceViewer.nLayers") == 0
    v.close()


def test_the_written_page_is_the_built_page(torus, tmp_path):
    """write_view streams the page as its JSON is encoded (memory: a helper's audit); it is build_view_html's page,
    byte for byte, with masks, a title to escape and a name that is not UTF-8 (as Python keeps it)."""
    from gpuslice.io.atomic import utf8

    masks = {0: b"\x89PNG fake <b>", 3: b"x" * 100}
    for title in ('</script><b>"x"', "part-\udcfe"):
        path = tmp_path / "p.html"
        size = write_view(torus, path, title=title, masks=masks)
        assert path.read_bytes() == utf8(build_view_html(torus, title=title, masks=masks))
        assert size == path.stat().st_size


def test_page_is_self_contained_and_escapes_the_title(torus):
    page = build_view_html(torus)
    assert not re.search(r"(?i)https?:|//[a-z0-9.-]+\.[a-z]{2,}/|<link|<script[^>]*\ssrc=|@import|url\(", page)
    page = build_view_html(torus, title='</script><img src="x.png">')
    assert "</script><img" not in page and "&lt;/script&gt;&lt;img" in page
    assert "default-src 'none'" in page  # the page's CSP forbids every fetch but data: images
    assert page.count("</script>") == 2  # the data block and the code; nothing in the data ended the element

    # a title holding the data mark's text: the page's data are still where they belong (it broke the whole page)
    page = build_view_html(torus, title="x /*__GPUSLICE_DATA__*/ y")
    assert read_view_data(page)["summary"] == read_view_data(build_view_html(torus))["summary"]
    assert "<title>x /*__GPUSLICE_DATA__*/ y" in page


def test_a_first_layer_of_its_own_is_not_called_adaptive(tmp_path):
    """``--first-layer`` gives a first layer of its own, the others uniform: the page said "adaptive layers"."""
    res = gpuslice.slice_mesh(gpuslice.mesh_from_triangles(shapes.box((0, 0, 0), (10, 10, 10))), thickness=0.05,
                              first_layer=0.2)
    summary = read_view_data(build_view_html(res))["summary"]
    assert "0.05 mm layers (the first 0.2 mm)" in summary and "adaptive" not in summary
    one = gpuslice.slice_mesh(gpuslice.mesh_from_triangles(shapes.box((0, 0, 0), (10, 10, 0.05))), thickness=0.05)
    assert read_view_data(build_view_html(one))["summary"].startswith("1 layer ·")


def test_masks_and_limits(torus, tmp_path, monkeypatch):
    png = b"\x89PNG fake"
    data = read_view_data(build_view_html(torus, masks={3: png}, mask_label="8x8 px"))
    assert data["masks"]["png"] == {3: png} and data["masks"]["size"] == "8x8 px"
    with pytest.raises(ParameterError, match="layer 99"):
        build_view_html(torus, masks={99: png})
    monkeypatch.setattr("gpuslice.view.page.MAX_VIEW_POINTS", 100)
    out = tmp_path / "big.html"
    with pytest.raises(ParameterError, match=r"big\.html: .*too many"):
        write_view(torus, out)
    assert not out.exists() and not list(tmp_path.iterdir())


# ---- the command line --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def torus_stl(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("view") / "torus.stl"
    shapes.write_stl(shapes.torus(), path)
    return path


def test_cli_from_mesh_and_from_npz(torus_stl, tmp_path, capsys):
    out = tmp_path / "t.html"
    assert main(["view", str(torus_stl), "-t", "0.25", "--backend", "numpy", "-o", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"({out.stat().st_size:,} bytes)" in said and "40 layers" in said
    data = read_view_data(out)
    assert data["arrays"]["z"].size == 40 and "torus.stl" in out.read_text()
    npz = tmp_path / "t.npz"
    assert main(["slice", str(torus_stl), "-t", "0.5", "--backend", "numpy", "-o", str(npz), "-q"]) == 0
    out2 = tmp_path / "n.html"
    assert main(["view", str(npz), "-o", str(out2), "-q"]) == 0
    res = gpuslice.SliceResult.load(npz)
    np.testing.assert_array_equal(read_view_data(out2)["arrays"]["area"], res.area)
    assert capsys.readouterr().out == ""


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.stl", "-o", "v.html"], "missing.stl: "),
        (["bad.npz", "-o", "v.html"], "bad.npz: not a gpuslice result"),
        (["good.npz", "-t", "0.2", "-o", "v.html"], "good.npz: a saved result is already sliced; -t"),
        (["torus.stl", "-o", "v.png"], "v.png: the viewer is an HTML page"),
        (["torus.stl", "-t", "-1", "-o", "v.html"], "thickness"),
    ],
)
def test_cli_errors_are_one_line_and_leave_no_file(args, message, torus_stl, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shutil.copy(torus_stl, "torus.stl")
    Path("bad.npz").write_bytes(b"not an npz")
    assert main(["slice", "torus.stl", "-t", "1", "--backend", "numpy", "-o", "good.npz", "-q"]) == 0
    before = sorted(os.listdir(tmp_path))
    assert main(["view", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gpuslice: error: ") and err.count("\n") == 1 and message in err
    assert sorted(os.listdir(tmp_path)) == before


# ---- in a real browser -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright (the python package) is not installed")
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not found: install Debian's chromium (scripts/setup-system.sh)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _until(ok, timeout: float = 5.0) -> None:
    """Wait until ``ok()`` is true (the page's CSP forbids the string evaluation of ``wait_for_function``)."""
    import time

    end = time.monotonic() + timeout
    while not ok():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.02)


class Page:
    """One viewer page open in Chromium, with the URLs it requested and the errors it raised."""

    def __init__(self, browser, result, tmp_path: Path, **kw):
        self.result = result
        self.path = tmp_path / "view.html"
        write_view(result, self.path, **kw)
        self.page = browser.new_page(viewport={"width": 1000, "height": 700}, device_scale_factor=1)
        self.requests: list[str] = []
        self.errors: list[str] = []
        self.page.on("request", lambda r: self.requests.append(r.url))
        self.page.on("pageerror", lambda e: self.errors.append(str(e)))
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.goto(self.path.as_uri())
        self.page.wait_for_function("window.gpusliceViewer && window.gpusliceViewer.ready", timeout=20_000)

    def text(self, element_id: str) -> str:
        return self.page.inner_text(f"#{element_id}")

    def layer(self) -> int:
        shown = int(self.text("layer-index"))
        assert shown == self.page.evaluate("gpusliceViewer.layer") == int(self.page.input_value("#layer"))
        return shown

    def check_layer_text(self, i: int) -> None:
        res = self.result
        assert self.layer() == i
        assert float(self.text("area")) == pytest.approx(res.area[i], rel=1e-6, abs=1e-3)
        assert float(self.text("z")) == pytest.approx(res.z[i], abs=1e-4)
        assert float(self.text("thickness")) == pytest.approx(res.thickness[i], abs=1e-4)
        assert int(self.text("points").replace(",", "")) == res.points_per_layer[i]
        assert int(self.text("loops")) == res.loops_per_layer[i]

    def canvas_pixels(self, element_id: str = "view") -> np.ndarray:
        from PIL import Image

        png = self.page.locator(f"#{element_id}").screenshot()
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)

    def close(self) -> None:
        assert self.errors == []
        assert self.requests and all(u.startswith(("file:", "data:")) for u in self.requests), self.requests
        self.page.close()


def test_browser_slider_keys_and_shown_values(browser, torus, tmp_path):
    v = Page(browser, torus, tmp_path)
    n = torus.n_layers
    assert int(v.text("layer-last")) == n - 1
    v.check_layer_text(0)
    v.page.keyboard.press("End")
    v.check_layer_text(n - 1)
    v.page.keyboard.press("Home")
    for _ in range(3):
        v.page.keyboard.press("ArrowUp")
    v.check_layer_text(3)
    v.page.keyboard.press("PageUp")
    v.check_layer_text(13)
    v.page.keyboard.press("ArrowDown")
    v.check_layer_text(12)
    # the slider itself, focused: its own keys step once (not twice)
    v.page.focus("#layer")
    v.page.keyboard.press("ArrowRight")
    v.check_layer_text(13)
    # setting the input as a user's drag does
    k = n // 2 + 1
    v.page.eval_on_selector("#layer", f"s => {{ s.value = '{k}'; s.dispatchEvent(new Event('input')); }}")
    v.check_layer_text(k)
    assert int(v.text("outer-holes").split("/")[1]) == torus.loop_is_hole[torus.layer(k).loops].sum() == 1
    assert v.text("repairs") == "none" and v.text("open") == "0"
    # PageUp on the focused slider: ten layers, as elsewhere (the slider's own step was a tenth of all the layers)
    v.page.evaluate("gpusliceViewer.setLayer(2)")
    v.page.focus("#layer")
    v.page.keyboard.press("PageUp")
    v.check_layer_text(12)
    # keys with Ctrl, Alt or Meta are the browser's: no layer step, not prevented (Ctrl+P printed nothing before)
    prevented = v.page.evaluate("""() => ["p", "n", "ArrowLeft"].map((key) => {
        const e = new KeyboardEvent("keydown", {key, ctrlKey: key !== "ArrowLeft", altKey: key === "ArrowLeft",
                                                 bubbles: true, cancelable: true});
        document.body.dispatchEvent(e);
        return e.defaultPrevented;
    })""")
    assert prevented == [False, False, False]
    v.check_layer_text(12)
    # the layer is in the address (a link to it), and a #layer=N followed later goes there
    _until(lambda: v.page.evaluate("location.hash") == "#layer=12")  # (written once the layer has settled)
    v.page.evaluate("location.hash = '#layer=3'")
    _until(lambda: v.page.evaluate("gpusliceViewer.layer") == 3)
    v.check_layer_text(3)
    v.close()


def test_cli_empty_title_and_one_flag_messages(torus_stl, tmp_path, capsys):
    """An empty --title takes the default (the model's name), not a blank header; one flag given for a saved result
    "applies" (an audit's cosmetic findings)."""
    page = tmp_path / "t.html"
    assert main(["view", str(torus_stl), "-t", "1", "--title", "", "-o", str(page), "-q"]) == 0
    assert f"<title>{torus_stl.name}" in page.read_text()
    npz = tmp_path / "t.npz"
    assert main(["slice", str(torus_stl), "-t", "1", "-o", str(npz), "-q"]) == 0
    assert main(["view", str(npz), "-t", "0.2", "-o", str(tmp_path / "u.html")]) == 2
    assert "-t only applies to meshes" in capsys.readouterr().err


def test_browser_shows_explicit_planes_in_their_own_slabs(browser, tmp_path):
    """Planes at 3, 5 and 7 mm with 0.1 mm layers sit in slabs 2.95-3.05 ...: the page said 0-0.1, 0.1-0.2 and a
    0.3 mm tall model (an audit), summing thicknesses from the bed where the exports use SliceResult.bottom."""
    res = _slice(shapes.box((0, 0, 0), (10, 10, 10)), z=np.array([3.0, 5.0, 7.0]), layer_thickness=0.1)
    v = Page(browser, res, tmp_path)
    for i, (lo, hi) in enumerate([(2.95, 3.05), (4.95, 5.05), (6.95, 7.05)]):
        v.page.evaluate(f"gpusliceViewer.setLayer({i})")
        got = [float(x) for x in v.text("span").split("–")]
        assert got == pytest.approx([lo, hi], abs=1e-4)
    v.close()


def test_browser_draws_holes_as_holes_and_chart_jumps(browser, torus, tmp_path):
    v = Page(browser, torus, tmp_path)
    mid = torus.n_layers // 2  # the torus's widest ring: material for 10 < r < 20 mm around (0, 0)
    v.page.evaluate(f"gpusliceViewer.setLayer({mid})")
    px = v.canvas_pixels()
    background = np.all(px == WHITE, axis=2)
    assert (~background).mean() > 0.05  # not blank: the ring covers a good part of the canvas
    (cx, cy), (rx, ry) = (v.page.evaluate(f"gpusliceViewer.toPixel({x}, 0)") for x in (0.0, 15.0))
    assert background[round(cy), round(cx)]  # the hole's middle is not filled
    r, g, b = px[round(ry), round(rx)]
    assert b > r + 30 and not background[round(ry), round(rx)]  # the ring is (blue) material
    # the chart: clicks jump to layers in order along the curve, and the marker follows
    box = v.page.locator("#chart").bounding_box()
    jumped = []
    for f in (0.25, 0.5, 0.75):
        v.page.mouse.click(box["x"] + f * box["width"], box["y"] + box["height"] / 2)
        jumped.append(v.layer())
        v.check_layer_text(jumped[-1])
    assert 0 < jumped[0] < jumped[1] < jumped[2] < torus.n_layers - 1
    assert abs(jumped[1] - (torus.n_layers - 1) / 2) <= 0.05 * torus.n_layers
    v.close()


def test_browser_highlights_open_chains(browser, open_box, tmp_path):
    v = Page(browser, open_box, tmp_path)
    v.page.evaluate("gpusliceViewer.setLayer(4)")
    v.check_layer_text(4)
    assert v.text("open") == str(open_box.open_chains_per_layer[4]) == "1"
    assert "open chains 1" in v.text("repairs")
    px = v.canvas_pixels()
    red = (px[..., 0] > 200) & (px[..., 1] < 80) & (px[..., 2] > 60) & (px[..., 2] < 130)  # #e0245e
    assert red.sum() > 500
    v.page.keyboard.press("Home")
    v.page.keyboard.press("n")  # the next layer with repairs
    assert v.layer() == 1
    v.close()


def test_browser_adaptive_thickness_and_masks(browser, tmp_path):
    from PIL import Image

    z = np.cumsum(np.linspace(0.2, 0.6, 25)) - 0.1  # growing layers: an adaptive-looking schedule
    res = _slice(shapes.torus(), z=z[z < 10])
    assert np.ptp(res.thickness) > 0.1
    buf = io.BytesIO()
    Image.new("L", (32, 24), 255).save(buf, format="PNG")
    v = Page(browser, res, tmp_path, masks={2: buf.getvalue()}, mask_label="32×24 px")
    assert "adaptive" in v.page.inner_text("#model")
    for i in (1, 2, res.n_layers - 1):
        v.page.evaluate(f"gpusliceViewer.setLayer({i})")
        v.check_layer_text(i)
        if i == 2:
            v.page.wait_for_function("document.getElementById('mask').complete")
            assert v.page.evaluate("document.getElementById('mask').naturalWidth") == 32
            assert v.page.is_visible("#mask") and not v.page.is_visible("#mask-none")
        else:
            assert v.page.is_visible("#mask-none") and not v.page.is_visible("#mask")
    v.close()


def test_browser_says_blank_mask_for_a_layer_with_no_pixel(browser, tmp_path):
    """Two boxes one above the other with empty layers between: every layer was rasterised (``every=1``), and the
    empty ones have no PNG; the page said "no mask stored for this layer" as if they had not been."""
    from gpuslice.raster import RasterSpec
    from gpuslice.view.page import raster_masks

    tri = np.concatenate([shapes.box((0, 0, 0), (5, 5, 1)), shapes.box((0, 0, 2), (5, 5, 3))])
    res = _slice(tri, z=np.arange(0.25, 3.0, 0.5))
    empty = [i for i in range(res.n_layers) if res.area[i] == 0]
    assert empty == [2, 3]
    masks = raster_masks(res, RasterSpec(resolution=(200, 200), pixel=0.05), every=1)
    assert sorted(masks.blank) == empty and not set(masks.png) & set(empty)
    v = Page(browser, res, tmp_path, masks=masks)
    v.page.evaluate("gpusliceViewer.setLayer(2)")
    assert v.page.is_visible("#mask-none") and "blank mask" in v.text("mask-none")
    v.page.evaluate("gpusliceViewer.setLayer(0)")
    assert v.page.is_visible("#mask") and not v.page.is_visible("#mask-none")
    v.close()


def test_browser_resin_mask_drawn_in_place(browser, torus, tmp_path):
    """--raster: each layer's mask tile is drawn under its contours, where the display's pixels lie in mm."""
    raster = pytest.importorskip("gpuslice.raster.coverage", reason="gpuslice.raster is not available")
    pytest.importorskip("PIL", reason="pillow is not installed")
    from gpuslice.view.page import raster_masks

    spec = raster.RasterSpec(resolution=(640, 480), pixel=0.1)
    masks = raster_masks(torus, spec, every=2, backend="numpy")
    assert sorted(masks.png) == list(range(0, torus.n_layers, 2))
    v = Page(browser, torus, tmp_path, masks=masks)
    mid = torus.n_layers // 2 // 2 * 2
    for i, has_mask in ((mid, True), (mid + 1, False)):
        v.page.evaluate(f"gpusliceViewer.setLayer({i})")
        v.page.wait_for_function("document.getElementById('mask').complete")
        v.page.wait_for_timeout(100)  # the tile is decoded, then the view redrawn
        px = v.canvas_pixels()
        (cx, cy), (rx, ry), (ox, oy) = (
            v.page.evaluate(f"gpusliceViewer.toPixel({x}, {y})") for x, y in ((0, 0), (15, 0), (19, 19))
        )
        hole, ring, outside = px[round(cy), round(cx)], px[round(ry), round(rx)], px[round(oy), round(ox)]
        if has_mask:  # the mask is black off the part (the hole, the tile's corners) and white on it
            assert hole.max() < 40 and outside.max() < 40 and ring.min() > 150
            assert v.page.is_visible("#mask") and "640×480 px" in v.text("mask-size")
        else:
            assert (hole == WHITE).all() and (outside == WHITE).all() and v.page.is_visible("#mask-none")
    v.close()


def test_cli_raster_option(torus_stl, tmp_path, capsys):
    pytest.importorskip("gpuslice.raster.coverage", reason="gpuslice.raster is not available")
    pytest.importorskip("PIL", reason="pillow is not installed")
    out = tmp_path / "r.html"
    args = ["view", str(torus_stl), "-t", "1", "--raster", "--mask-every", "5", "--printer", "elegoo-mars"]
    assert main([*args, "-o", str(out)]) == 0
    assert "2 masks (1440×2560 px, 0.04725 mm)" in capsys.readouterr().out
    data = read_view_data(out)
    pngs = data["masks"]["png"]
    assert sorted(pngs) == [0, 5] and all(p.startswith(b"\x89PNG") for p in pngs.values())
    assert main([*args, "--fit", "500", "-o", str(tmp_path / "x.html")]) == 2
    assert "torus.stl: the model" in capsys.readouterr().err and not (tmp_path / "x.html").exists()


def test_browser_two_thousand_layers_a_million_points(browser, tmp_path):
    """Scale: 2,000 layers of 500 points (a 500-gon prism): the page loads, reaches its last layer and draws it."""
    angle = np.linspace(0.0, 2.0 * np.pi, 500, endpoint=False)
    polygon = np.stack([20.0 * np.cos(angle), 20.0 * np.sin(angle)], axis=1)
    res = _slice(shapes.prism(polygon, 0.0, 20.0), thickness=0.01)
    assert res.n_layers >= 2000 and res.points.shape[0] >= 1_000_000
    v = Page(browser, res, tmp_path)
    assert v.path.stat().st_size < 12 * res.points.shape[0]  # compact: ~10.7 bytes a point
    v.page.keyboard.press("End")
    v.check_layer_text(res.n_layers - 1)
    assert (~np.all(v.canvas_pixels() == WHITE, axis=2)).mean() > 0.05
    times = v.page.evaluate("gpusliceViewer.stepTimes(1000, 1100)")
    assert len(times) == 100  # the numbers are for the benchmark (scripts/bench_view.py), not asserted here
    v.close()


def test_cli_resin_views_slice_as_the_resin_commands(tmp_path, capsys):
    """`view --check` and `view --raster` slice at `check`'s and `raster`'s 0.05 mm unless -t is given (their
    reports and masks are those commands'); a plain view keeps `slice`'s 0.1 mm."""
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    run = ["view", str(stl), "--fit", "4", "--backend", "numpy", "-o", str(tmp_path / "v.html"), "-q"]
    layers = {}
    raster = ("--raster", "--mask-every", "100")
    for extra in ((), ("--check",), ("--check", "-t", "0.1"), raster):
        assert main([*run, *extra]) == 0
        layers[extra] = read_view_data(tmp_path / "v.html")["arrays"]["z"].size
    assert layers == {(): 40, ("--check",): 80, ("--check", "-t", "0.1"): 40, raster: 80}
