"""One contract for every PatternDisplay implementation (drivers.interfaces.PatternDisplay), from
docs/hardware.md: patterns drawn 1:1 and on screen as soon as show() returns, the inverse response
LUT applied exactly, shows numbered and timed, bad input refused with ValueError, typed errors
after close, and an idempotent close.

Implementations: GlfwDisplay on Xvfb (what is on screen is read from the X server), the
offscreen EGL display (its framebuffer), and the fake LCD over an offscreen display (the
luminance it emits, with a linear panel: grey g emits g / 255).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from PIL import ImageGrab

from drivers.display import DisplayError, GlfwDisplay, OffscreenDisplay
from drivers.interfaces import DeviceError, PatternDisplay, ShownFrame
from fakes.lcd import FakeLCD, PanelResponse
from tests.support.xvfb import XVFB_SCREEN

SIZE = XVFB_SCREEN[:2]  # (width, height)
GAMMA_LUT = np.round(255.0 * (np.arange(256) / 255.0) ** (1 / 2.2)).astype(np.uint8)


@dataclass
class Case:
    """A display under test and how to see what it really shows."""

    display: PatternDisplay
    screen: Callable[[], np.ndarray]  # what is on screen now: (height, width) grey, uint8
    colour: bool  # shows (height, width, 3) patterns in colour (the fake LCD is monochrome)
    screen_rgb: Callable[[], np.ndarray] | None = None


@pytest.fixture
def glfw(xvfb_display) -> Iterator[Case]:
    with GlfwDisplay(0) as display:
        def rgb() -> np.ndarray:
            return np.asarray(ImageGrab.grab(xdisplay=xvfb_display.display))

        yield Case(display, lambda: rgb()[..., 0], True, rgb)


@pytest.fixture
def offscreen() -> Iterator[Case]:
    with OffscreenDisplay(SIZE) as display:
        yield Case(display, lambda: display.read_back()[..., 0], True, display.read_back)


@pytest.fixture
def fake_lcd() -> Iterator[Case]:
    with FakeLCD(OffscreenDisplay(SIZE), PanelResponse(gamma=1.0, black_level=0.0)) as lcd:
        yield Case(lcd, lambda: np.round(lcd.luminance() * 255.0).astype(np.uint8), False)


ALL = ["glfw", "offscreen", "fake_lcd"]
COLOUR = ["glfw", "offscreen"]


@pytest.fixture
def case(request) -> Case:
    return request.getfixturevalue(request.param)


def random_grey(rng: np.random.Generator) -> np.ndarray:
    return rng.integers(0, 256, SIZE[::-1], dtype=np.uint8)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_size_is_width_height(case):
    assert case.display.size == SIZE


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_each_pattern_is_on_screen_pixel_for_pixel_as_soon_as_show_returns(case):
    rng = np.random.default_rng(1)
    ramp = (np.add.outer(np.arange(SIZE[1]), 2 * np.arange(SIZE[0])) % 256).astype(np.uint8)
    # back to back, each checked at once: a display one frame behind fails here
    for pattern in [ramp, random_grey(rng), random_grey(rng), 255 - ramp]:
        case.display.show(pattern)
        np.testing.assert_array_equal(case.screen(), pattern)


@pytest.mark.parametrize("case", COLOUR, indirect=True)
def test_colour_patterns_keep_their_channels(case):
    pattern = np.random.default_rng(2).integers(0, 256, (*SIZE[::-1], 3), dtype=np.uint8)
    case.display.show(pattern)
    np.testing.assert_array_equal(case.screen_rgb(), pattern)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_lut_is_applied_exactly_and_none_restores_identity(case):
    pattern = random_grey(np.random.default_rng(3))
    pattern[0, :256] = np.arange(256)  # every value at least once
    case.display.set_lut(GAMMA_LUT)
    case.display.show(pattern)
    np.testing.assert_array_equal(case.screen(), GAMMA_LUT[pattern])
    case.display.set_lut(None)
    case.display.show(pattern)
    np.testing.assert_array_equal(case.screen(), pattern)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_shows_are_numbered_from_zero_and_timed_after_the_swap(case):
    before = time.monotonic()
    shown = []
    for v in (0, 128, 255):
        shown.append(case.display.show(np.full(SIZE[::-1], v, np.uint8)))
    after = time.monotonic()
    assert all(isinstance(s, ShownFrame) for s in shown)
    assert [s.index for s in shown] == [0, 1, 2] and [s.frame_code for s in shown] == [None] * 3
    times = [s.swap_time for s in shown]
    assert before < times[0] < times[1] < times[2] < after


@pytest.mark.parametrize("case", ALL, indirect=True)
@pytest.mark.parametrize("image", [
    np.zeros((10, 10), np.uint8), np.zeros(SIZE[::-1], np.uint16),
    np.zeros((*SIZE[::-1], 4), np.uint8), np.zeros(SIZE, np.uint8),  # (width, height): transposed
])
def test_wrong_patterns_are_value_errors_and_leave_the_screen_alone(case, image):
    pattern = random_grey(np.random.default_rng(4))
    case.display.show(pattern)
    with pytest.raises(ValueError, match=r"pattern must be uint8 of shape \(240, 320\)"):
        case.display.show(image)
    np.testing.assert_array_equal(case.screen(), pattern)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_bad_luts_and_unrequested_frame_codes_are_value_errors(case):
    with pytest.raises(ValueError, match="LUT must be 256 integers"):
        case.display.set_lut(np.arange(255))
    with pytest.raises(ValueError, match="LUT values must be in 0..255"):
        case.display.set_lut(np.arange(256) + 1)
    with pytest.raises(ValueError, match="draws no frame code"):
        case.display.show(np.zeros(SIZE[::-1], np.uint8), frame_code=3)


@pytest.mark.parametrize("case", ALL, indirect=True)
def test_close_is_idempotent_and_later_calls_are_typed_errors(case):
    case.display.show(np.zeros(SIZE[::-1], np.uint8))
    case.display.close()
    case.display.close()
    with pytest.raises(DisplayError, match="is closed"):
        case.display.show(np.zeros(SIZE[::-1], np.uint8))
    with pytest.raises(DisplayError, match="is closed"):
        case.display.set_lut(None)
    assert issubclass(DisplayError, DeviceError)
