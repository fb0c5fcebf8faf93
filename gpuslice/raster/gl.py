"""The GL rasteriser (moderngl, headless EGL): each layer's polygons filled into an 8-bit mask on the GPU.

Pass 1 fills the layer's tile at ``s × s`` samples per pixel into an R8 texture: every edge (a, b) becomes the
triangle (pivot, a, b) of a fan, drawn with blending ``ONE_MINUS_DST_COLOR, ZERO`` so that each covering triangle
toggles a sample between 0 and 1 — an even-odd fill in one pass (moderngl has no stencil API). The polygons of a
:class:`~gpuslice.result.SliceResult` are already resolved under its fill rule (winding 0 or 1), so even-odd
gives the same region as the rule the contours used. Pass 2 averages each pixel's ``s²`` samples into a coverage,
``k = min(255, floor(256·c))``, and maps it through the same gamma table as the other backends. Coverage is thus
quantised to ``1/s²`` (s = 8 by default: 64 levels); the OpenCL/numpy backends compute it exactly.

Pixel coordinates are tile-local (see :mod:`gpuslice.raster`): GL window y = v, so reading the texture back row by
row gives the tile's rows top-down without a flip. ``moderngl.create_standalone_context(backend="egl")`` works
without a display; on a machine with no GPU Mesa's llvmpipe renders (``gl_info()["software"]`` is True).
"""

from __future__ import annotations

from functools import cache

import numpy as np

from ..errors import DeviceError

__all__ = ["GLRasteriser", "gl_info"]

_VS_FILL = """
#version 330
uniform vec2 size;
in vec2 p;
void main() { gl_Position = vec4(p / size * 2.0 - 1.0, 0.0, 1.0); }
"""
_FS_FILL = """
#version 330
out vec4 colour;
void main() { colour = vec4(1.0); }
"""
_VS_QUAD = """
#version 330
in vec2 p;
void main() { gl_Position = vec4(p, 0.0, 1.0); }
"""
_FS_RESOLVE = """
#version 330
uniform sampler2D samples;
uniform sampler2D lut;
uniform int s;
out vec4 colour;
void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float n = 0.0;
    for (int j = 0; j < s; ++j)
        for (int i = 0; i < s; ++i)
            n += texelFetch(samples, px * s + ivec2(i, j), 0).r;
    int k = min(255, int(floor(256.0 * n / float(s * s))));
    colour = vec4(texelFetch(lut, ivec2(k, 0), 0).r, 0.0, 0.0, 1.0);
}
"""


@cache
def _context():
    try:
        import moderngl
    except ImportError as exc:
        raise DeviceError(f"the GL raster backend needs moderngl (pip install 'gpuslice[raster]'): {exc}") from None
    try:
        return moderngl.create_standalone_context(backend="egl")
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DeviceError(f"no EGL context for the GL raster backend ({first})") from None


def gl_info() -> dict | None:
    """Renderer name and whether it is Mesa's software renderer; None when no EGL context can be made."""
    try:
        ctx = _context()
    except DeviceError:
        return None
    renderer = ctx.info.get("GL_RENDERER", "")
    software = any(k in renderer.lower() for k in ("llvmpipe", "softpipe", "swrast"))
    return {"renderer": renderer, "version": ctx.info.get("GL_VERSION", ""), "software": software}


class GLRasteriser:
    """One EGL context with its programs; textures grown as tiles need. Use :meth:`get`."""

    _instances: dict[int, GLRasteriser] = {}

    @classmethod
    def get(cls, supersample: int = 8) -> GLRasteriser:
        if supersample not in cls._instances:
            cls._instances[supersample] = cls(supersample)
        return cls._instances[supersample]

    def __init__(self, supersample: int = 8) -> None:
        import moderngl

        self.ctx = ctx = _context()
        self.s = int(supersample)
        self.max_size = int(ctx.info.get("GL_MAX_TEXTURE_SIZE", 8192))
        self.fill = ctx.program(vertex_shader=_VS_FILL, fragment_shader=_FS_FILL)
        self.resolve = ctx.program(vertex_shader=_VS_QUAD, fragment_shader=_FS_RESOLVE)
        quad = np.array([-1, -1, 1, -1, -1, 1, 1, 1], np.float32)
        self.quad = ctx.vertex_array(self.resolve, [(ctx.buffer(quad.tobytes()), "2f", "p")])
        self.lut_tex = ctx.texture((256, 1), 1, dtype="f1")
        self.lut_tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._lut_bytes = b""
        self._hi = self._lo = None  # (texture, framebuffer, size)
        self._vbo = None
        self._vbo_size = 0

    def _target(self, which: str, w: int, h: int):
        import moderngl

        cur = getattr(self, which)
        if cur is None or cur[2][0] < w or cur[2][1] < h:
            if cur is not None:
                cur[1].release()
                cur[0].release()
            size = (max(w, cur[2][0] if cur else 0), max(h, cur[2][1] if cur else 0))
            tex = self.ctx.texture(size, 1, dtype="f1")
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
            cur = (tex, self.ctx.framebuffer(color_attachments=[tex]), size)
            setattr(self, which, cur)
        return cur

    def coverage(self, edges: np.ndarray, rows: int, cols: int, lut: np.ndarray) -> np.ndarray:
        """(rows, cols) uint8 greys of one tile from its edges (E, 4) in tile-local pixel coordinates."""
        import moderngl

        if rows == 0 or cols == 0 or len(edges) == 0:
            return np.zeros((rows, cols), np.uint8)
        s = max(1, min(self.s, self.max_size // max(rows, cols)))
        ctx = self.ctx
        lut_bytes = np.ascontiguousarray(lut, np.uint8).tobytes()
        if lut_bytes != self._lut_bytes:
            self.lut_tex.write(lut_bytes)
            self._lut_bytes = lut_bytes
        hi_tex, hi_fbo, _ = self._target("_hi", cols * s, rows * s)
        lo_tex, lo_fbo, _ = self._target("_lo", cols, rows)
        e = np.asarray(edges, np.float32)
        tri = np.empty((e.shape[0], 3, 2), np.float32)
        tri[:, 0] = e[0, :2]
        tri[:, 1] = e[:, :2]
        tri[:, 2] = e[:, 2:]
        data = tri.tobytes()
        if self._vbo is None or self._vbo_size < len(data):
            if self._vbo is not None:
                self._vbo.release()
            self._vbo_size = max(len(data), int(self._vbo_size * 1.5))
            self._vbo = ctx.buffer(reserve=self._vbo_size)
            self._vao = ctx.vertex_array(self.fill, [(self._vbo, "2f", "p")])
        self._vbo.write(data)
        # pass 1: even-odd fill of the samples
        hi_fbo.use()
        ctx.viewport = (0, 0, cols * s, rows * s)
        ctx.scissor = (0, 0, cols * s, rows * s)
        hi_fbo.clear(0.0, 0.0, 0.0, 0.0)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = moderngl.ONE_MINUS_DST_COLOR, moderngl.ZERO
        self.fill["size"].value = (float(cols), float(rows))
        self._vao.render(moderngl.TRIANGLES, vertices=3 * e.shape[0])
        ctx.disable(moderngl.BLEND)
        # pass 2: samples -> coverage -> gamma
        lo_fbo.use()
        ctx.viewport = (0, 0, cols, rows)
        ctx.scissor = (0, 0, cols, rows)
        hi_tex.use(0)
        self.lut_tex.use(1)
        self.resolve["samples"].value = 0
        self.resolve["lut"].value = 1
        self.resolve["s"].value = s
        self.quad.render(moderngl.TRIANGLE_STRIP)
        out = np.frombuffer(lo_fbo.read(viewport=(0, 0, cols, rows), components=1, alignment=1), np.uint8)
        ctx.scissor = None
        return out.reshape(rows, cols).copy()
