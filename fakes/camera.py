"""The fake camera: what the bench camera sees of the fake LCD from the stage's current
position, through the exact per-pixel LTC, with a physical noise model.

Signal chain per pixel: electrons ``e = white_e_per_ms * exposure_ms * (h . L)`` with
``h`` the true (unnormalised) LTC and ``L`` the LCD luminance in [0, 1], then the sensor model
shared with the renderer (``sim.optics.sensor``): Poisson shot noise; clipping at the full
well; Gaussian read noise (electrons); ``ADU = black_level + gain * e`` rounded to integers
and clipped to the bit depth.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from drivers.camera import CameraTimeout
from drivers.interfaces import Camera, Frame
from fakes.bench import FakeBench
from fakes.lcd import FakeLCD
from sim.optics.sensor import Sensor


class NoiseModel(BaseModel):
    """Sensor response and noise of the fake camera."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    enabled: bool = Field(True, description="False: noise-free, unquantised-in-electrons camera")
    full_well_e: float = Field(10000.0, gt=0, description="full-well capacity, electrons")
    read_noise_e: float = Field(5.0, ge=0, description="read noise std, electrons")
    bit_depth: int = Field(12, ge=1, le=16, description="ADC bits, 1..16 (8, 10, 12 or 16)")
    black_level_adu: float = Field(16.0, ge=0, description="offset added to every pixel, ADU")
    white_fraction: float = Field(
        0.85, gt=0, description="full white at the reference exposure fills this fraction of "
        "the full well for a pixel with transmittance 1"
    )
    reference_exposure_ms: float = Field(20.0, gt=0, description="reference exposure, ms")

    @property
    def gain_adu_per_e(self) -> float:
        """Conversion gain: the full well maps to full scale above the black level."""
        return (2**self.bit_depth - 1 - self.black_level_adu) / self.full_well_e

    @property
    def sensor(self) -> Sensor:
        """The sensor model (``sim.optics.sensor``) of this camera."""
        return Sensor(full_well_e=self.full_well_e, dn_per_e=self.gain_adu_per_e,
                      black_level_dn=self.black_level_adu, bit_depth=self.bit_depth,
                      shot_noise=self.enabled, read_noise_e=self.read_noise_e * self.enabled)

    def electrons_per_ms_white(self) -> float:
        """Signal rate for full white and transmittance 1, electrons per ms."""
        return self.white_fraction * self.full_well_e / self.reference_exposure_ms

    def mean_adu(self, electrons: np.ndarray) -> np.ndarray:
        """Expected ADU for expected electrons (no saturation)."""
        return self.sensor.mean_dn(electrons)

    def variance_adu(self, electrons: np.ndarray) -> np.ndarray:
        """Expected ADU variance: shot + read noise, plus uniform quantisation (1/12)."""
        return self.sensor.variance_dn(electrons)


@dataclass
class CameraFaults:
    """Switches a test sets at any time; each counts down per capture."""

    timeout: int = 0  # the next n captures raise CameraTimeout after the timeout
    drop: int = 0  # the next n frames are lost: the frame counter skips them
    stale: int = 0  # the next n captures return the previous frame again
    garbage: int = 0  # the next n frames are one flat grey (a broken transfer): no check code


class SettableExposure:
    """``exposure_ms`` of a fake camera: any value > 0, ms (kept in ``_exposure_ms``)."""

    _exposure_ms: float

    @property
    def exposure_ms(self) -> float:
        return self._exposure_ms

    @exposure_ms.setter
    def exposure_ms(self, value: float) -> None:
        if not value > 0:
            raise ValueError(f"{type(self).__name__}: exposure_ms must be > 0, got {value}")
        self._exposure_ms = float(value)


class FakeCamera(SettableExposure, Camera):
    """Renders the fake LCD through the bench's true LTC at the stage's current position.

    seed : noise seed (None: a fresh one). seed_per_scene : draw each capture's noise from
    ``(seed, scene_key)``, the scene being what the LCD shows and where the stage is, so a
    frame does not depend on what was captured before it (a run interrupted and resumed, or
    a retried frame, gives the same frames); the k-th further frame of an unchanged scene
    (frames averaged per pattern) from ``(seed, scene_key, k)``, so each has noise of its
    own; a garbage-fault frame is not counted. Otherwise one stream from ``seed``. The
    noise-free electrons of the last scene are kept, so further frames of it cost only
    their noise.
    """

    def __init__(
        self,
        bench: FakeBench,
        lcd: FakeLCD,
        stage_position_mm: Callable[[], float],
        noise: NoiseModel | None = None,
        *,
        exposure_ms: float | None = None,
        seed: int | None = 0,
        timeout_s: float = 2.0,
        seed_per_scene: bool = False,
    ) -> None:
        if lcd.size != bench.config.lcd_size:
            raise ValueError(
                f"FakeCamera: display size {lcd.size} differs from bench lcd_size "
                f"{bench.config.lcd_size}"
            )
        self.bench = bench
        self.lcd = lcd
        self.noise = noise or NoiseModel()
        self._position = stage_position_mm
        self._exposure_ms = exposure_ms or self.noise.reference_exposure_ms
        self.seed = seed
        self.seed_per_scene = seed_per_scene
        self.rng = np.random.default_rng(seed)
        self.timeout_s = timeout_s
        self.faults = CameraFaults()
        self._frame_id = -1
        self._last: Frame | None = None
        # the last scene: its key (with the exposure), noise-free electrons and frames so far
        self._scene: tuple | None = None
        self._scene_electrons: np.ndarray | None = None
        self._scene_frames = 0

    def scene_key(self, z_mm: float) -> tuple[int, ...]:
        """Identity of the scene of a capture: a hash of the LCD's luminance (H, W) and of the
        stage position ``z_mm``, as four 32-bit ints."""
        h = hashlib.blake2b(digest_size=16)
        h.update(np.ascontiguousarray(self.lcd.luminance()).tobytes())
        h.update(np.float64(z_mm).tobytes())
        return tuple(int(v) for v in np.frombuffer(h.digest(), dtype="<u4"))

    @property
    def size(self) -> tuple[int, int]:
        return self.bench.config.camera_size

    @property
    def bit_depth(self) -> int:
        return self.noise.bit_depth

    def expected_electrons(self, z_mm: float | None = None) -> np.ndarray:
        """Noise-free electrons (H, W) for what is on the LCD now, at ``z_mm`` (default: now)."""
        z = self._position() if z_mm is None else z_mm
        m = self.bench.true_ltc(z)
        rate = self.noise.electrons_per_ms_white() * self._exposure_ms
        w, h = self.size
        return (rate * (m @ self.lcd.luminance().ravel().astype(np.float64))).reshape(h, w)

    def _digitise(self, electrons: np.ndarray) -> np.ndarray:
        sensor = self.noise.sensor
        return sensor.digitise(sensor.expose(electrons, self.rng))

    def capture(self, timeout: float | None = None) -> Frame:
        """One frame of what the camera sees now."""
        timeout = self.timeout_s if timeout is None else timeout
        f = self.faults
        if f.timeout > 0:
            f.timeout -= 1
            time.sleep(timeout)
            raise CameraTimeout(f"FakeCamera: no frame within {timeout:.3f} s (fault switch)")
        if f.stale > 0 and self._last is not None:
            f.stale -= 1
            return self._last
        if f.drop > 0:
            self._frame_id += f.drop
            f.drop = 0
        z = self._position()
        self._frame_id += 1
        key = self.scene_key(z)
        scene = (key, self._exposure_ms)
        if scene != self._scene:
            self._scene, self._scene_frames = scene, 0
            self._scene_electrons = self.expected_electrons(z)
        if self.seed_per_scene and self.seed is not None:
            k = self._scene_frames
            self.rng = np.random.default_rng([self.seed, *key] + ([k] if k else []))
        image = self._digitise(self._scene_electrons)
        if f.garbage > 0:
            f.garbage -= 1
            image = np.full_like(image, 2 ** (self.noise.bit_depth - 1))
        else:
            self._scene_frames += 1
        frame = Frame(
            image=image,
            timestamp=time.monotonic(),
            exposure_ms=self._exposure_ms,
            frame_id=self._frame_id,
            meta={"stage_mm": z},
        )
        self._last = frame
        return frame

    def close(self) -> None:
        self._last = None
