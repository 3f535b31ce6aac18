"""The whole fake bench as hardware: a fake Zaber controller on a real pty driven by the real
``ZaberStage`` driver, a real offscreen GL display seen as the fake LCD, and the fake camera
that looks at it from wherever the fake controller's carriage is."""

from __future__ import annotations

import contextlib
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from drivers.display import OffscreenDisplay
from drivers.frame_code import FrameCodeLayout
from drivers.stage import ZaberStage
from drivers.zaber_protocol import ACCEL_UNIT, SPEED_UNIT
from fakes.bench import BenchConfig, FakeBench
from fakes.camera import FakeCamera, NoiseModel
from fakes.lcd import FakeLCD, PanelResponse
from fakes.zaber import FakeZaberDevice, FakeZaberPty
from sim.validation import format_validation_error



class FakeSettings(BaseModel):
    """The ``[fake]`` section of a station config."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    seed: int | None = Field(0, ge=0, description="camera noise seed (>= 0); None for a fresh "
                             "one each run")
    stage_maxspeed_mm_s: float = Field(200.0, gt=0, description="fake stage top speed, mm/s")
    stage_accel_mm_s2: float = Field(2000.0, gt=0, description="fake stage acceleration, mm/s^2")
    start_mm: float = Field(0.0, description="where the carriage is at power-up, mm")
    bench: dict[str, Any] = Field(default_factory=dict, description="BenchConfig.small() overrides")
    noise: NoiseModel = NoiseModel()
    panel: PanelResponse = PanelResponse()

    def bench_config(self) -> BenchConfig:
        return BenchConfig.small(**self.bench)


def parse_fake_settings(data: dict[str, Any], source: str = "config") -> FakeSettings:
    """Validate the ``[fake]`` section; errors name ``source`` and the field as
    ``fake.<field>`` (``fake.bench.<field>`` for the bench overrides)."""
    try:
        settings = FakeSettings.model_validate(data)
    except ValidationError as exc:
        raise ValueError(format_validation_error(source, exc, ("fake",))) from exc
    try:
        settings.bench_config()
    except ValidationError as exc:
        raise ValueError(format_validation_error(source, exc, ("fake", "bench"))) from exc
    return settings


class FakeHardware(contextlib.ExitStack):
    """Stage, display and camera of the fake bench, opened together and closed together.

    ``stage_kwargs`` are the ``ZaberStage`` settings (microstep_um, travel_mm, tolerance_um,
    timeout_s, settle_s); the fake controller's device limits are set to cover that travel.
    """

    def __init__(
        self,
        settings: FakeSettings,
        *,
        microstep_um: float,
        travel_mm: tuple[float, float],
        tolerance_um: float,
        timeout_s: float,
        settle_s: float,
        frame_code: FrameCodeLayout | None = None,
        lut=None,
    ) -> None:
        super().__init__()
        self.settings = settings
        self.bench = FakeBench(settings.bench_config())
        um = self.microstep_um = microstep_um
        try:
            self.device = FakeZaberDevice(
                limit_min=0,
                limit_max=round(travel_mm[1] * 1000 / um) + 1000,
                maxspeed=round(settings.stage_maxspeed_mm_s * 1000 / um * SPEED_UNIT),
                accel=max(1, round(settings.stage_accel_mm_s2 * 1000 / um * ACCEL_UNIT)),
                position=round(settings.start_mm * 1000 / um),
            )
            self.pty = self.enter_context(FakeZaberPty(self.device))
            self.stage = self.enter_context(
                ZaberStage(
                    self.pty.port, microstep_um=um, travel_mm=travel_mm,
                    tolerance_um=tolerance_um, timeout_s=timeout_s, settle_s=settle_s,
                )
            )
            display = OffscreenDisplay(
                self.bench.config.lcd_size, lut=lut,
                frame_code=frame_code if frame_code is not None else False,
            )
            self.lcd = self.enter_context(FakeLCD(display, settings.panel))
            self.camera = self.enter_context(
                FakeCamera(
                    self.bench, self.lcd, self.carriage_mm, settings.noise, seed=settings.seed,
                    seed_per_scene=True,
                )
            )
        except BaseException:
            self.close()
            raise

    def carriage_mm(self) -> float:
        """Where the fake controller's carriage physically is, mm."""
        return self.device.position * self.microstep_um / 1000.0
