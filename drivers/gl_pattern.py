"""One moderngl program that draws an 8-bit pattern 1:1 through an exact inverse-response LUT.

The pattern is uploaded as an unsigned-integer texture and read with ``texelFetch`` (no
filtering, no scaling); each value indexes a 256-entry LUT texture, again with ``texelFetch``,
so the output byte is exactly ``lut[value]``. An optional frame code (see
:mod:`drivers.frame_code`) replaces the pattern in its rectangle, bypassing the LUT.
Drawing goes into an RGBA8 framebuffer of the display's size, which the caller may blit to a
window; :meth:`PatternRenderer.read` returns what was drawn.
"""

from __future__ import annotations

import moderngl
import numpy as np

from drivers.errors import DeviceSettingError

_GL_DITHER = 0x0BD0

_VERTEX_SHADER = """
#version 330 core
void main() {
    // one triangle covering the viewport
    vec2 corner = vec2(float((gl_VertexID & 1) << 2), float((gl_VertexID & 2) << 1)) - 1.0;
    gl_Position = vec4(corner, 0.0, 1.0);
}
"""

_FRAGMENT_SHADER = """
#version 330 core
uniform usampler2D u_image;   // pattern, texel row 0 = image row 0 (top)
uniform sampler2D u_lut;      // 256 x 1, unorm8
uniform usampler2D u_code;    // frame code pixels, 0 or 255
uniform ivec4 u_code_rect;    // x, y (from the top), width, height; width 0 = no code
uniform int u_height;         // display height, pixels
out vec4 color;

void main() {
    ivec2 p = ivec2(int(gl_FragCoord.x), u_height - 1 - int(gl_FragCoord.y));
    ivec2 c = p - u_code_rect.xy;
    if (all(greaterThanEqual(c, ivec2(0))) && all(lessThan(c, u_code_rect.zw))) {
        color = vec4(vec3(float(texelFetch(u_code, c, 0).r) / 255.0), 1.0);
        return;
    }
    uvec3 v = texelFetch(u_image, p, 0).rgb;
    color = vec4(
        texelFetch(u_lut, ivec2(int(v.r), 0), 0).r,
        texelFetch(u_lut, ivec2(int(v.g), 0), 0).r,
        texelFetch(u_lut, ivec2(int(v.b), 0), 0).r,
        1.0);
}
"""


def as_lut(lut: np.ndarray | None) -> np.ndarray:
    """Validate an inverse response LUT: 256 integers in 0..255 -> (256,) uint8; None -> identity."""
    if lut is None:
        return np.arange(256, dtype=np.uint8)
    arr = np.asarray(lut)
    if arr.shape != (256,) or not np.issubdtype(arr.dtype, np.integer):
        raise DeviceSettingError(f"LUT must be 256 integers, "
                                 f"got shape {arr.shape} dtype {arr.dtype}")
    if arr.min() < 0 or arr.max() > 255:
        raise DeviceSettingError(f"LUT values must be in 0..255, got {arr.min()}..{arr.max()}")
    return arr.astype(np.uint8)


def check_image(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Check a pattern against the display size ``(width, height)``; return it C-contiguous."""
    width, height = size
    shape = getattr(image, "shape", None)
    dtype = getattr(image, "dtype", type(image).__name__)
    if dtype != np.uint8 or shape not in ((height, width), (height, width, 3)):
        raise DeviceSettingError(
            f"pattern must be uint8 of shape ({height}, {width}) or ({height}, {width}, 3) "
            f"to match the {width}x{height} display, got {shape} {dtype}"
        )
    return np.ascontiguousarray(image)


def _nearest(texture: moderngl.Texture) -> moderngl.Texture:
    texture.filter = (moderngl.NEAREST, moderngl.NEAREST)
    texture.repeat_x = texture.repeat_y = False
    return texture


class PatternRenderer:
    """Draws patterns of one size on a moderngl context into its own RGBA8 framebuffer."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]) -> None:
        self.ctx = ctx
        self.size = (int(size[0]), int(size[1]))
        self._program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        self._vao = ctx.vertex_array(self._program, [])
        self._target = ctx.texture(self.size, 4)
        self.framebuffer = ctx.framebuffer(color_attachments=[self._target])
        gray = _nearest(ctx.texture(self.size, 1, dtype="u1"))
        gray.swizzle = "RRR1"
        self._images = {1: gray, 3: _nearest(ctx.texture(self.size, 3, dtype="u1"))}
        self._lut = _nearest(ctx.texture((256, 1), 1))
        self._code = _nearest(ctx.texture((1, 1), 1, dtype="u1"))
        self._program["u_image"] = 0
        self._program["u_lut"] = 1
        self._program["u_code"] = 2
        self._program["u_height"] = self.size[1]
        self.set_lut(None)

    def set_lut(self, lut: np.ndarray | None) -> None:
        """Set the inverse response LUT (256 values in 0..255); None for identity."""
        self._lut.write(as_lut(lut).tobytes())

    def draw(self, image: np.ndarray, code: np.ndarray | None = None,
             code_xy: tuple[int, int] = (0, 0)) -> None:
        """Draw ``image`` (checked by :func:`check_image`) into :attr:`framebuffer`, with ``code``
        ((rows, cols) uint8) drawn as is at ``code_xy`` (x, y from the top-left) when given."""
        image = check_image(image, self.size)
        texture = self._images[1 if image.ndim == 2 else 3]
        texture.write(image.tobytes())
        if code is None:
            self._program["u_code_rect"] = (0, 0, 0, 0)
        else:
            rows, cols = code.shape
            if self._code.size != (cols, rows):
                self._code.release()
                self._code = _nearest(self.ctx.texture((cols, rows), 1, dtype="u1"))
            self._code.write(np.ascontiguousarray(code, dtype=np.uint8).tobytes())
            self._program["u_code_rect"] = (code_xy[0], code_xy[1], cols, rows)
        self.framebuffer.use()
        self.ctx.disable_direct(_GL_DITHER)
        self.ctx.disable(moderngl.BLEND)
        texture.use(location=0)
        self._lut.use(location=1)
        self._code.use(location=2)
        self._vao.render(moderngl.TRIANGLES, vertices=3)

    def read(self) -> np.ndarray:
        """What was last drawn: (height, width, 3) uint8, row 0 at the top."""
        width, height = self.size
        data = self.framebuffer.read(components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(height, width, 3)[::-1].copy()

    def release(self) -> None:
        """Free the GL objects."""
        for obj in (self._vao, self._program, self.framebuffer, self._target, self._lut, self._code,
                    *self._images.values()):
            obj.release()
