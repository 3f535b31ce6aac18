"""Pattern displays: a borderless fullscreen GLFW window, and an offscreen EGL twin.

Both draw with :class:`drivers.gl_pattern.PatternRenderer` (patterns 1:1, exact LUT, optional
frame code) and number the patterns they show. GLFW calls must come from the main thread.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import os
import time
from collections.abc import Iterator

import glfw
import moderngl
import numpy as np

from drivers.errors import DeviceSettingError, DisplayError
from drivers.frame_code import (
    FrameCodeLayout,
    decode_frame_code,
    frame_code_rect,
    render_frame_code,
    stamp_frame_code,
)
from drivers.gl_pattern import PatternRenderer
from drivers.interfaces import PatternDisplay, ShownFrame

__all__ = [
    "DisplayError",
    "FrameCodeLayout",
    "GlfwDisplay",
    "OffscreenDisplay",
    "PatternDisplay",
    "ShownFrame",
    "decode_frame_code",
    "stamp_frame_code",
]

log = logging.getLogger(__name__)

_glfw_users = 0  # open GlfwDisplays; GLFW is terminated when the last one closes


def _layout(frame_code: bool | FrameCodeLayout) -> FrameCodeLayout | None:
    if isinstance(frame_code, FrameCodeLayout):
        return frame_code
    return FrameCodeLayout() if frame_code else None


class _RendererDisplay(PatternDisplay):
    """Show/number/LUT logic shared by the displays. Subclasses make their GL context current
    only inside :meth:`_current` (a thread may hold one GLX or EGL context at a time, so a window
    and an offscreen display can live side by side) and put the drawn frame on screen."""

    _closed = False

    def _start(self, renderer: PatternRenderer, lut: np.ndarray | None,
               frame_code: bool | FrameCodeLayout) -> None:
        self._renderer = renderer
        self._index = 0
        self._layout = _layout(frame_code)
        self._code_rect = None if self._layout is None else frame_code_rect(self._layout, renderer.size)
        renderer.set_lut(lut)

    @abc.abstractmethod
    def _current(self) -> contextlib.AbstractContextManager[None]:
        """Make this display's GL context current for the duration."""

    def _bound(self) -> contextlib.AbstractContextManager[None]:
        """:meth:`_current`, refused once the display is closed."""
        if self._closed:
            raise DisplayError(f"{type(self).__name__} is closed")
        return self._current()

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in display pixels."""
        return self._renderer.size

    @property
    def frame_code_layout(self) -> FrameCodeLayout | None:
        """The frame code's layout, None when no code is drawn."""
        return self._layout

    @property
    def frame_code_rect(self) -> tuple[int, int, int, int] | None:
        """(x, y, width, height) of the frame code in display pixels, None when no code is drawn."""
        return self._code_rect

    def set_lut(self, lut: np.ndarray | None) -> None:
        """Set the inverse response LUT (256 values in 0..255); None for identity."""
        with self._bound():
            self._renderer.set_lut(lut)

    def show(self, image: np.ndarray, frame_code: int | None = None) -> ShownFrame:
        """Show ``image`` ((height, width) or (height, width, 3) uint8) through the LUT and return
        after it is on screen. With a frame code layout the code drawn is ``frame_code``, or the
        show index modulo ``2**bits`` when None."""
        code = None
        if self._layout is None:
            if frame_code is not None:
                raise DeviceSettingError(
                    f"frame_code={frame_code} given but {type(self).__name__} draws no frame code; "
                    "open it with frame_code=True or a FrameCodeLayout"
                )
        else:
            if frame_code is None:
                frame_code = self._index % 2**self._layout.bits
            code = render_frame_code(frame_code, self._layout)
        xy = (0, 0) if self._code_rect is None else self._code_rect[:2]
        with self._bound():
            self._renderer.draw(image, code, xy)
            self._present()
            shown = ShownFrame(index=self._index, swap_time=time.monotonic(), frame_code=frame_code)
        log.debug("%s: frame %d shown (swap at %.6f s, frame code %s)", type(self).__name__,
                  shown.index, shown.swap_time, frame_code)
        self._after_present()
        self._index += 1
        return shown

    def read_back(self) -> np.ndarray:
        """The last drawn frame: (height, width, 3) uint8, row 0 at the top."""
        with self._bound():
            return self._renderer.read()

    def _present(self) -> None:
        """Put the drawn framebuffer on screen and return when it is there: offscreen, when
        the GPU has finished drawing it (``glFinish``)."""
        self._renderer.ctx.finish()

    def _after_present(self) -> None:
        """Housekeeping after the frame is shown and timed (window events)."""


class OffscreenDisplay(_RendererDisplay):
    """The pattern program on a headless EGL context, drawing into a framebuffer of ``size``."""

    def __init__(self, size: tuple[int, int], *, lut: np.ndarray | None = None,
                 frame_code: bool | FrameCodeLayout = False) -> None:
        width, height = int(size[0]), int(size[1])
        if width < 1 or height < 1:
            raise DeviceSettingError(f"display size must be positive (width, height), got {size}")
        self._ctx = moderngl.create_standalone_context(backend="egl")
        self._closed = False
        self._renderer = None
        opened = False
        try:
            with self._current():
                self._start(PatternRenderer(self._ctx, (width, height)), lut, frame_code)
            opened = True
        finally:
            if not opened:
                self.close()

    @contextlib.contextmanager
    def _current(self) -> Iterator[None]:
        with self._ctx:
            yield

    def close(self) -> None:
        """Release the context; idempotent."""
        if not self._closed:
            self._closed = True
            if self._renderer is not None:
                with self._current():
                    self._renderer.release()
            self._ctx.release()


def _monitor_list(monitors: list) -> str:
    items = []
    for i, monitor in enumerate(monitors):
        mode = glfw.get_video_mode(monitor)
        name = glfw.get_monitor_name(monitor).decode(errors="replace")
        x, y = glfw.get_monitor_pos(monitor)
        items.append(f"{i}: {name!r} {mode.size.width}x{mode.size.height} at ({x}, {y})")
    return "; ".join(items) or "none"


def _glfw_error() -> str:
    code, description = glfw.get_error()
    return f"GLFW error {code:#x}: {description.decode(errors='replace')}" if code else "no GLFW error"


class GlfwDisplay(_RendererDisplay):
    """A borderless fullscreen window on monitor ``monitor`` (index into ``glfw.get_monitors()``),
    at the monitor's current video mode, swap interval 1, cursor hidden."""

    def __init__(self, monitor: int = 0, *, lut: np.ndarray | None = None,
                 frame_code: bool | FrameCodeLayout = False, gl_version: tuple[int, int] = (3, 3),
                 title: str = "pattern display") -> None:
        global _glfw_users
        self._window = None
        self._renderer = None
        self._closed = False
        if not glfw.init():
            display = os.environ.get("DISPLAY")
            raise DisplayError(f"GLFW could not start (DISPLAY={display!r}): {_glfw_error()}")
        _glfw_users += 1
        opened = False
        try:
            self._open(monitor, gl_version, title)
            with self._current():
                ctx = moderngl.create_context()
                self._start(PatternRenderer(ctx, self.window_size), lut, frame_code)
            opened = True
        finally:
            if not opened:
                self.close()

    def _open(self, index: int, gl_version: tuple[int, int], title: str) -> None:
        monitors = glfw.get_monitors()
        if not 0 <= index < len(monitors):
            raise DisplayError(f"no monitor {index}; monitors: {_monitor_list(monitors)}")
        self._monitor = monitors[index]
        mode = glfw.get_video_mode(self._monitor)
        glfw.default_window_hints()
        for hint, value in (
            (glfw.CONTEXT_VERSION_MAJOR, gl_version[0]), (glfw.CONTEXT_VERSION_MINOR, gl_version[1]),
            (glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE), (glfw.OPENGL_FORWARD_COMPAT, True),
            (glfw.RED_BITS, mode.bits.red), (glfw.GREEN_BITS, mode.bits.green),
            (glfw.BLUE_BITS, mode.bits.blue), (glfw.REFRESH_RATE, mode.refresh_rate),
            (glfw.DECORATED, False), (glfw.AUTO_ICONIFY, False), (glfw.SAMPLES, 0),
        ):
            glfw.window_hint(hint, value)
        self._window = glfw.create_window(mode.size.width, mode.size.height, title, self._monitor, None)
        if not self._window:
            raise DisplayError(
                f"GLFW could not open a {mode.size.width}x{mode.size.height} window with OpenGL "
                f"{gl_version[0]}.{gl_version[1]} core on monitor {index}: {_glfw_error()}"
            )
        with self._current():
            glfw.swap_interval(1)
        glfw.set_input_mode(self._window, glfw.CURSOR, glfw.CURSOR_HIDDEN)

    @contextlib.contextmanager
    def _current(self) -> Iterator[None]:
        glfw.make_context_current(self._window)
        try:
            yield
        finally:
            glfw.make_context_current(None)

    @property
    def window_size(self) -> tuple[int, int]:
        """Framebuffer (width, height) of the window, pixels."""
        return tuple(glfw.get_framebuffer_size(self._window))

    def describe(self) -> dict:
        """Monitor, video mode and GL renderer, for run metadata."""
        mode = glfw.get_video_mode(self._monitor)
        with self._bound():
            renderer = self._renderer.ctx.info["GL_RENDERER"]
        return {
            "type": type(self).__name__,
            "monitor": glfw.get_monitor_name(self._monitor).decode(errors="replace"),
            "monitor_pos": tuple(glfw.get_monitor_pos(self._monitor)),
            "video_mode": (mode.size.width, mode.size.height, mode.refresh_rate),
            "window_size": tuple(glfw.get_window_size(self._window)),
            "framebuffer_size": self.window_size,
            "gl_renderer": renderer,
        }

    def _present(self) -> None:
        """Copy the drawn pattern into the back buffer, ``glFinish`` (the frame is complete
        before it is queued), swap, and ``glFinish`` again: with swap interval 1 the second
        one blocks until the swap has happened at the refresh, so :meth:`show` returns only
        once the pattern is on screen, as careful SLM and display tools do."""
        ctx = self._renderer.ctx
        ctx.copy_framebuffer(ctx.screen, self._renderer.framebuffer)
        ctx.finish()
        glfw.swap_buffers(self._window)
        ctx.finish()

    def _after_present(self) -> None:
        glfw.poll_events()  # keep the window responsive; after the swap is timed

    def close(self) -> None:
        """Close the window; terminate GLFW when no other GlfwDisplay is open; idempotent."""
        global _glfw_users
        if self._closed:
            return
        self._closed = True
        if self._renderer is not None:
            with self._current():
                self._renderer.release()
        if self._window:
            glfw.destroy_window(self._window)
        _glfw_users -= 1
        if _glfw_users == 0:
            glfw.terminate()
