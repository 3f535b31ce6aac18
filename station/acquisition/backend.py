"""Open the station's three devices, real or fake, as the config says: ``backend`` picks the
stage and display (the fake bench's, or a Zaber stage and a GLFW window), ``[camera] kind``
the camera (the fake bench's, OpenCV or GenICam).

The only station module allowed to import ``fakes`` (import-linter enforces it).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.frame_code import FrameCodeLayout
from drivers.interfaces import Camera, PatternDisplay, ShownFrame, Stage
from station.acquisition.config import (
    ConfigError,
    GenICamCameraConfig,
    OpenCVCameraConfig,
    StationConfig,
)


@dataclass
class Hardware:
    """The opened devices, real or fake: the station sees only their interfaces."""

    stage: Stage
    display: PatternDisplay
    camera: Camera

    def show_settled(self, image: np.ndarray, settled_s: float) -> ShownFrame:
        """Show ``image`` and return once the LCD shows it steadily: ``settled_s`` after the
        swap (``DisplayConfig.settled_s``); the camera may be triggered then."""
        shown = self.display.show(image)
        time.sleep(max(0.0, shown.swap_time + settled_s - time.monotonic()))
        return shown


def load_lut(path: str | Path) -> np.ndarray:
    """Read an inverse response LUT (256 uint8 values, .npy or one value per line text)."""
    path = Path(path)
    try:
        lut = np.load(path, allow_pickle=False) if path.suffix == ".npy" else np.loadtxt(path)
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read display LUT: {exc}") from exc
    lut = np.asarray(lut).ravel()
    if lut.shape != (256,) or np.any(lut < 0) or np.any(lut > 255) or np.any(lut % 1):
        raise ConfigError(f"{path}: display LUT must be 256 integers in 0..255, got shape "
                          f"{lut.shape}, range [{lut.min()}, {lut.max()}]")
    return lut.astype(np.uint8)


def frame_code_layout(config: StationConfig) -> FrameCodeLayout | None:
    """The frame code the display draws, or None when it is off."""
    d = config.display
    return FrameCodeLayout(block_px=d.frame_code_block_px) if d.frame_code else None


def open_fake_hardware(config: StationConfig, *, lut: np.ndarray | None = None):
    """The fake bench's devices (a ``fakes.hardware.FakeHardware``, a context manager) as
    the config's ``[fake]``, ``stage``, ``display`` and ``camera`` sections set them up.
    Tests reach the fakes' fault switches and wire log through it; the station does not."""
    from fakes.hardware import FakeHardware, parse_fake_settings

    try:
        settings = parse_fake_settings(config.fake)
    except ValueError as exc:  # the [fake] section, refused by its validation
        raise ConfigError(str(exc)) from exc
    s = config.stage
    fake = FakeHardware(
        settings, microstep_um=s.microstep_um, travel_mm=s.travel_mm,
        tolerance_um=s.tolerance_um, timeout_s=s.timeout_s, settle_s=s.settle_s,
        frame_code=frame_code_layout(config), lut=lut,
    )
    fake.camera.exposure_ms = config.camera.exposure_ms
    return fake


def open_camera(camera: OpenCVCameraConfig | GenICamCameraConfig) -> Camera:
    """The real camera ``[camera]`` describes (kind 'opencv' or 'genicam'), opened and set up."""
    if camera.kind == "genicam":
        from drivers.genicam import GenICamCamera

        return GenICamCamera(
            camera.device_id, serial=camera.serial, exposure_ms=camera.exposure_ms,
            gain=camera.gain, pixel_format=camera.pixel_format, roi=camera.roi,
            trigger=None if camera.trigger == "free-run" else camera.trigger,
            frame_rate_hz=camera.frame_rate_hz, timeout_s=camera.timeout_s,
            control_timeout_s=camera.control_timeout_s, n_buffers=camera.buffers,
        )
    if camera.kind == "opencv":
        from drivers.camera import OpenCVCamera

        return OpenCVCamera(camera.source, exposure_ms=camera.exposure_ms, gain=camera.gain,
                            timeout_s=camera.timeout_s, backend=camera.api)
    raise ConfigError(f"camera.kind = {camera.kind!r} is not a real camera")


def open_synthetic_hardware(config: StationConfig, *, lut: np.ndarray | None = None):
    """The synthetic full-size bench (``fakes.synthetic``, selected by ``[fake] model =
    "synthetic"``): analytic per-pixel LTCs, zero-latency stage, display and camera."""
    from fakes.synthetic import SyntheticHardware, parse_synthetic_settings

    if lut is not None:
        raise ConfigError("the synthetic bench has a linear panel: no display LUT")
    if config.frame_check.enabled:
        raise ConfigError("the synthetic bench renders the station's patterns only: set "
                          "[frame_check] enabled = false")
    try:
        settings = parse_synthetic_settings(config.fake)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc
    return SyntheticHardware(settings, period=config.patterns.period,
                             travel_mm=config.stage.travel_mm,
                             exposure_ms=config.camera.exposure_ms)


def preflight(config: StationConfig, source: str, text: str | None = None) -> list[str]:
    """Everything about ``config`` that can be checked before any device opens: the
    ``[fake]`` section (on the fake bench) and the pattern period and check code against the
    LCD when its size is known here (the fake benches'; a real LCD's when it opens). Raises
    :class:`ConfigError` naming ``source`` and the field; returns warnings (values still as
    the example gives them, when ``text``, the file's TOML, is given)."""
    from station.acquisition.config import check_on_lcd, placeholder_warnings

    lcd_size = None
    if config.backend == "fake" and config.fake.get("model") == "synthetic":
        from fakes.synthetic import parse_synthetic_settings

        try:
            lcd_size = parse_synthetic_settings(config.fake, source).synthetic.lcd_size
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
    elif config.backend == "fake":
        from fakes.hardware import parse_fake_settings

        try:
            lcd_size = parse_fake_settings(config.fake, source).bench_config().lcd_size
        except ValueError as exc:
            raise ConfigError(str(exc)) from exc
    if lcd_size is not None:
        check_on_lcd(config, tuple(lcd_size), source)
    warnings = (placeholder_warnings(text, source)
                if text is not None and config.backend == "real" else [])
    if config.backend != "fake" and config.fake:
        warnings.append(f"{source}: field 'fake': the [fake] section is used only with "
                        "backend = 'fake'; it is ignored")
    return warnings


@contextlib.contextmanager
def open_hardware(config: StationConfig, *, lut: np.ndarray | None = None) -> Iterator[Hardware]:
    """Open stage, display and camera; close all of them on exit, whatever happened."""
    if lut is None and config.display.lut_path:
        lut = load_lut(config.display.lut_path)
    s = config.stage
    if config.backend == "fake" and config.fake.get("model") == "synthetic":
        with open_synthetic_hardware(config, lut=lut) as fake:
            yield Hardware(fake.stage, fake.lcd, fake.camera)
        return
    if config.backend == "fake":
        with open_fake_hardware(config, lut=lut) as fake:
            if config.camera.kind == "fake":
                yield Hardware(fake.stage, fake.lcd, fake.camera)
            else:  # the fake stage and display with a real camera
                with open_camera(config.camera) as camera:
                    yield Hardware(fake.stage, fake.lcd, camera)
        return

    from drivers.display import GlfwDisplay
    from drivers.stage import ZaberStage

    with contextlib.ExitStack() as stack:
        stage = stack.enter_context(ZaberStage(
            s.port, baudrate=s.baudrate, address=s.address, axis=s.axis,
            microstep_um=s.microstep_um, travel_mm=s.travel_mm, tolerance_um=s.tolerance_um,
            timeout_s=s.timeout_s, settle_s=s.settle_s,
        ))
        display = stack.enter_context(GlfwDisplay(
            config.display.monitor, lut=lut, frame_code=frame_code_layout(config) or False,
        ))
        camera = stack.enter_context(open_camera(config.camera))
        yield Hardware(stage, display, camera)
