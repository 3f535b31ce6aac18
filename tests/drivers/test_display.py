"""Pattern displays under a real X server (Xvfb) and on EGL; the frame code's encode and decode."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from PIL import ImageGrab

from drivers.display import DisplayError, GlfwDisplay, OffscreenDisplay
from drivers.frame_code import (
    FrameCodeError,
    FrameCodeLayout,
    code_blocks,
    decode_frame_code,
    frame_code_rect,
    render_frame_code,
    stamp_frame_code,
)
from drivers.gl_pattern import as_lut
from tests.support.xvfb import XVFB_SCREEN, start_xvfb

SIZE = XVFB_SCREEN[:2]  # (width, height): the offscreen display matches the Xvfb screen
GAMMA_LUT = np.round(255.0 * (np.arange(256) / 255.0) ** (1 / 2.2)).astype(np.uint8)


def as_rgb(image: np.ndarray) -> np.ndarray:
    return image if image.ndim == 3 else np.repeat(image[:, :, None], 3, axis=2)


def open_display(kind: str, **kwargs) -> GlfwDisplay | OffscreenDisplay:
    return GlfwDisplay(0, **kwargs) if kind == "glfw" else OffscreenDisplay(SIZE, **kwargs)


def screen_of(display: GlfwDisplay | OffscreenDisplay, server) -> np.ndarray:
    """What is really on screen: the X server's pixels for a window, the read-back offscreen."""
    if isinstance(display, GlfwDisplay):
        return np.asarray(ImageGrab.grab(xdisplay=server.display))
    return display.read_back()


@pytest.fixture(params=["glfw", "offscreen"])
def kind(request, xvfb_display) -> str:
    return request.param


# --- displays -------------------------------------------------------------------------------


def test_window_covers_the_screen(xvfb_display):
    with GlfwDisplay(0) as display:
        info = display.describe()
    width, height = xvfb_display.width, xvfb_display.height
    assert info["video_mode"][:2] == (width, height)
    assert info["window_size"] == info["framebuffer_size"] == (width, height)
    assert display.size == (width, height)
    assert info["monitor_pos"] == (0, 0)
    assert "llvmpipe" in info["gl_renderer"]


def test_random_patterns_are_drawn_pixel_for_pixel(kind, xvfb_display):
    rng = np.random.default_rng(7)
    width, height = SIZE
    with open_display(kind) as display:
        for shape in [(height, width)] * 3 + [(height, width, 3)] * 2:
            pattern = rng.integers(0, 256, shape, dtype=np.uint8)
            display.show(pattern)
            np.testing.assert_array_equal(display.read_back(), as_rgb(pattern))
            np.testing.assert_array_equal(screen_of(display, xvfb_display), as_rgb(pattern))


def test_structured_pattern_keeps_orientation(kind, xvfb_display):
    width, height = SIZE
    ramp = (np.add.outer(np.arange(height), 2 * np.arange(width)) % 256).astype(np.uint8)
    with open_display(kind) as display:
        display.show(ramp)
        np.testing.assert_array_equal(screen_of(display, xvfb_display), as_rgb(ramp))


def test_lut_is_applied_exactly(kind, xvfb_display):
    rng = np.random.default_rng(3)
    width, height = SIZE
    pattern = rng.integers(0, 256, (height, width), dtype=np.uint8)
    pattern[0, :256] = np.arange(256)  # every value at least once
    with open_display(kind, lut=GAMMA_LUT) as display:
        display.show(pattern)
        np.testing.assert_array_equal(screen_of(display, xvfb_display), as_rgb(GAMMA_LUT[pattern]))
        inverted = (255 - np.arange(256)).astype(np.uint8)
        display.set_lut(inverted)
        display.show(pattern)
        np.testing.assert_array_equal(display.read_back(), as_rgb(inverted[pattern]))
        display.set_lut(None)
        display.show(pattern)
        np.testing.assert_array_equal(display.read_back(), as_rgb(pattern))


@pytest.mark.parametrize("corner", ["top-left", "bottom-right"])
def test_frame_code_is_drawn_and_decodes(kind, corner, xvfb_display):
    layout = FrameCodeLayout(bits=10, block_px=16, corner=corner)
    rng = np.random.default_rng(11)
    width, height = SIZE
    pattern = rng.integers(0, 256, (height, width), dtype=np.uint8)
    with open_display(kind, lut=GAMMA_LUT, frame_code=layout) as display:
        x, y, w, h = display.frame_code_rect
        assert display.frame_code_layout == layout
        for expected_code, given in [(0, None), (1, None), (777, 777)]:
            shown = display.show(pattern, frame_code=given)
            assert shown.frame_code == expected_code
            screen = screen_of(display, xvfb_display)
            expected = stamp_frame_code(GAMMA_LUT[pattern], expected_code, layout)
            np.testing.assert_array_equal(screen, as_rgb(expected))
            assert decode_frame_code(screen[y : y + h, x : x + w], bits=10) == expected_code


def test_automatic_frame_code_wraps_around(xvfb_display):
    layout = FrameCodeLayout(bits=2, block_px=8)
    with OffscreenDisplay(SIZE, frame_code=layout) as display:
        codes = [display.show(np.zeros(SIZE[::-1], np.uint8)).frame_code for _ in range(6)]
    assert codes == [0, 1, 2, 3, 0, 1]


def test_show_numbers_frames_and_returns_after_the_swap(kind):
    width, height = SIZE
    with open_display(kind) as display:
        before = time.monotonic()
        frames = [display.show(np.full((height, width), v, np.uint8)) for v in (0, 128, 255)]
        after = time.monotonic()
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.frame_code for f in frames] == [None] * 3
    times = [f.swap_time for f in frames]
    assert before < times[0] < times[1] < times[2] < after


def test_show_finishes_the_frame_before_the_swap_and_waits_for_the_swap(xvfb_display, monkeypatch):
    """glFinish, swap, glFinish: show() is timed and returns only once the swap has happened."""
    import glfw

    calls: list[tuple[str, float]] = []
    with GlfwDisplay(0) as display:
        ctx = display._renderer.ctx
        real_finish, real_swap = ctx.finish, glfw.swap_buffers

        def finish() -> None:
            real_finish()
            calls.append(("finish", time.monotonic()))

        def swap(window) -> None:
            calls.append(("swap", time.monotonic()))
            real_swap(window)

        monkeypatch.setattr(ctx, "finish", finish)
        monkeypatch.setattr(glfw, "swap_buffers", swap)
        pattern = np.random.default_rng(9).integers(0, 256, SIZE[::-1], dtype=np.uint8)
        shown = display.show(pattern)
        np.testing.assert_array_equal(np.asarray(ImageGrab.grab(xdisplay=xvfb_display.display)),
                                      as_rgb(pattern))
    assert [name for name, _ in calls] == ["finish", "swap", "finish"]
    assert shown.swap_time >= calls[-1][1]


def test_offscreen_and_window_work_side_by_side(xvfb_display):
    pattern = np.random.default_rng(5).integers(0, 256, SIZE[::-1], dtype=np.uint8)
    with OffscreenDisplay(SIZE) as offscreen, GlfwDisplay(0) as window:
        offscreen.show(pattern)
        window.show(255 - pattern)
        np.testing.assert_array_equal(offscreen.read_back(), as_rgb(pattern))
        np.testing.assert_array_equal(window.read_back(), as_rgb(255 - pattern))


# --- display errors -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "image",
    [np.zeros((10, 10), np.uint8), np.zeros((SIZE[1], SIZE[0]), np.uint16),
     np.zeros((SIZE[1], SIZE[0], 4), np.uint8), [[0, 1], [2, 3]]],
)
def test_wrong_image_is_refused(kind, image):
    with open_display(kind) as display:
        with pytest.raises(ValueError, match=r"pattern must be uint8 of shape \(240, 320\) or "
                                             r"\(240, 320, 3\) to match the 320x240 display, got"):
            display.show(image)


@pytest.mark.parametrize(
    ("lut", "message"),
    [(np.arange(255), r"LUT must be 256 integers, got shape \(255,\)"),
     (np.linspace(0, 1, 256), "LUT must be 256 integers, got shape .* dtype float64"),
     (np.arange(256) + 1, r"LUT values must be in 0..255, got 1..256")],
)
def test_bad_lut_is_refused(lut, message):
    with pytest.raises(ValueError, match=message):
        as_lut(lut)
    with OffscreenDisplay(SIZE) as display, pytest.raises(ValueError, match=message):
        display.set_lut(lut)


def test_frame_code_needs_a_layout():
    message = "frame_code=3 given but OffscreenDisplay draws no frame code"
    with OffscreenDisplay(SIZE) as display, pytest.raises(ValueError, match=message):
        display.show(np.zeros(SIZE[::-1], np.uint8), frame_code=3)


def test_frame_code_out_of_range_is_refused():
    message = r"frame code 1024 out of range 0..1023 for 10 bits"
    with OffscreenDisplay(SIZE, frame_code=True) as display, pytest.raises(ValueError, match=message):
        display.show(np.zeros(SIZE[::-1], np.uint8), frame_code=1024)


def test_frame_code_larger_than_the_display_is_refused():
    message = r"frame code of 352x96 px \(4 bits, 32 px blocks\) does not fit the 320x240 display"
    with pytest.raises(ValueError, match=message):
        OffscreenDisplay(SIZE, frame_code=FrameCodeLayout(bits=4, block_px=32))


def test_closed_display_refuses_to_show(kind):
    display = open_display(kind)
    display.close()
    display.close()  # idempotent
    with pytest.raises(DisplayError, match=f"{type(display).__name__} is closed"):
        display.show(np.zeros(SIZE[::-1], np.uint8))


def test_offscreen_size_must_be_positive():
    with pytest.raises(ValueError, match=r"display size must be positive \(width, height\), got \(0, 10"):
        OffscreenDisplay((0, 10))


def test_missing_monitor_is_named(xvfb_display):
    with pytest.raises(DisplayError, match=r"no monitor 1; monitors: 0: 'screen' 320x240 at \(0, 0\)"):
        GlfwDisplay(1)
    with pytest.raises(DisplayError, match="no monitor -1"):
        GlfwDisplay(-1)


@pytest.mark.filterwarnings("ignore::glfw.GLFWError")
def test_unavailable_gl_version_is_reported(xvfb_display):
    message = r"GLFW could not open a 320x240 window with OpenGL 9.9 core on monitor 0: GLFW error"
    with pytest.raises(DisplayError, match=message):
        GlfwDisplay(0, gl_version=(9, 9))
    with GlfwDisplay(0) as display:  # GLFW still usable afterwards
        display.show(np.zeros(SIZE[::-1], np.uint8))


@pytest.mark.filterwarnings("ignore::glfw.GLFWError")
def test_missing_x_server_is_reported(monkeypatch, xvfb_display):
    monkeypatch.setenv("DISPLAY", ":9999")
    with pytest.raises(DisplayError, match=r"GLFW could not start \(DISPLAY=':9999'\): GLFW error"):
        GlfwDisplay(0)


def test_missing_xvfb_fails_rather_than_skips(monkeypatch):
    monkeypatch.setenv("PATH", "/nonexistent")
    with pytest.raises(pytest.fail.Exception, match="Xvfb is not on PATH"):
        with start_xvfb(64, 48):
            pass


# --- frame code (pure numpy) ----------------------------------------------------------------


def test_code_blocks_layout():
    blocks = code_blocks(0b1011, 4)
    assert blocks.astype(int).tolist() == [1, 0, 1, 0, 1, 1, 1, 0, 1]  # guards, data, parity 1
    image = render_frame_code(0b1011, FrameCodeLayout(bits=4, block_px=3))
    assert image.shape == FrameCodeLayout(bits=4, block_px=3).shape == (9, 33)
    assert set(np.unique(image)) == {0, 255}
    assert image[:3].max() == 0 and image[6:].max() == 0 and image[:, :3].max() == 0
    assert image[4, 3::3].tolist() == [255 * b for b in blocks] + [0]


@pytest.mark.parametrize("corner", ["top-left", "top-right", "bottom-left", "bottom-right"])
def test_frame_code_rect_is_in_its_corner(corner):
    x, y, w, h = frame_code_rect(FrameCodeLayout(bits=8, block_px=10, corner=corner), (640, 480))
    assert (w, h) == (150, 30)
    assert x == (0 if "left" in corner else 490)
    assert y == (0 if "top" in corner else 450)


@pytest.mark.parametrize("value", [0, 1, 2, 341, 682, 1023])
def test_frame_code_round_trip(value):
    layout = FrameCodeLayout(bits=10, block_px=16)
    assert decode_frame_code(render_frame_code(value, layout), bits=10) == value


def camera_view(code: np.ndarray, scale: float, rng: np.random.Generator, blur_px: float = 1.0,
                black: float = 20.0, white: float = 200.0, pad: int = 12) -> np.ndarray:
    """The code as a camera might see it: scaled, blurred, with black level, gain and noise."""
    image = cv2.resize(code.astype(np.float32), None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    image = np.pad(image, pad)
    image = cv2.GaussianBlur(image, (0, 0), blur_px)
    image = black + image / 255.0 * (white - black) + rng.normal(0.0, 2.0, image.shape)
    return np.clip(np.round(image), 0, 4095).astype(np.uint16)


@pytest.mark.parametrize("scale", [0.4, 0.77, 1.0, 1.6, 2.3])
def test_frame_code_decodes_through_a_camera_like_view(scale):
    rng = np.random.default_rng(int(scale * 100))
    layout = FrameCodeLayout(bits=12, block_px=16)
    for value in rng.integers(0, 2**12, 5):
        view = camera_view(render_frame_code(int(value), layout), scale, rng)
        assert decode_frame_code(view, bits=12) == value


def test_two_frames_mixed_in_one_exposure_are_refused():
    layout = FrameCodeLayout(bits=10, block_px=16)
    blend = 0.5 * render_frame_code(0b1010101010, layout) + 0.5 * render_frame_code(0b1010101001, layout)
    message = r"frame code blocks \[10, 11\] are neither black nor white"
    with pytest.raises(FrameCodeError, match=message):
        decode_frame_code(blend, bits=10)


def test_frame_code_decode_errors():
    layout = FrameCodeLayout(bits=10, block_px=16)
    code = render_frame_code(300, layout)
    b = layout.block_px
    with pytest.raises(FrameCodeError, match="touches the region's edge"):
        decode_frame_code(code[b:-b, b:-b], bits=10)
    with pytest.raises(FrameCodeError, match=r"blocks are 1.00 px wide in the region; need >= 2 px"):
        decode_frame_code(code[::16, ::16], bits=10)
    bad_guard = code.copy()
    bad_guard[b : 2 * b, 2 * b : 3 * b] = 255  # the black start guard turned white
    with pytest.raises(FrameCodeError, match="guard blocks not found"):
        decode_frame_code(bad_guard, bits=10)
    bad_parity = code.copy()
    bad_parity[b : 2 * b, 5 * b : 6 * b] = 255 - bad_parity[b + 1, 5 * b + 1]  # flip one data bit
    with pytest.raises(FrameCodeError, match="parity check failed"):
        decode_frame_code(bad_parity, bits=10)
    with pytest.raises(FrameCodeError, match="no contrast in the region"):
        decode_frame_code(np.full((40, 200), 7, np.uint8), bits=10)
    with pytest.raises(FrameCodeError, match=r"region must be a 2-D image, got shape \(5,\)"):
        decode_frame_code(np.zeros(5), bits=10)
    with pytest.raises(FrameCodeError, match="no bright blocks along the strip"):
        decode_frame_code(np.pad(np.eye(40) * 255, 2), bits=10)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"bits": 0}, "frame code bits must be 1..32, got 0"),
     ({"block_px": 0}, "frame code block_px must be >= 1, got 0"),
     ({"corner": "middle"}, "frame code corner must be one of .*, got 'middle'")],
)
def test_frame_code_layout_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FrameCodeLayout(**kwargs)
