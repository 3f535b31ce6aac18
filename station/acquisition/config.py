"""Station configuration: pydantic models read from TOML, with errors naming file and field."""

from __future__ import annotations

import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from drivers.frame_code import FrameCodeLayout, frame_code_rect
from sim.render.fringe_patterns import Modulation
from sim.validation import field_path
from station.errors import StationError


class ConfigError(StationError, ValueError):
    """A config file is missing, unreadable or invalid; the message names file and field."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class StageConfig(_Strict):
    """Zaber stage on a serial port."""

    port: str = Field("/dev/ttyUSB0", description="serial device path or pyserial URL")
    baudrate: int = Field(115200, description="serial speed, baud")
    address: int = Field(1, ge=1, le=99, description="Zaber device address")
    axis: int = Field(1, ge=1, le=9, description="Zaber axis number")
    microstep_um: float = Field(0.047625, gt=0, description="microstep size, um")
    travel_mm: tuple[float, float] = Field(
        (0.0, 300.0), description="allowed travel (low, high), mm; low keeps the camera off the LCD"
    )
    tolerance_um: float = Field(2.0, gt=0, description="position tolerance of a finished move, um")
    timeout_s: float = Field(1.0, gt=0, description="deadline for one command's reply, s")
    settle_s: float = Field(0.2, ge=0, description="wait after every finished move, s")

    @model_validator(mode="after")
    def _travel_ordered(self) -> StageConfig:
        lo, hi = self.travel_mm
        if not lo < hi:
            raise ValueError(f"travel_mm must be (low, high) with low < high, got {self.travel_mm}")
        return self


class DisplayConfig(_Strict):
    """The pattern LCD."""

    monitor: int = Field(1, ge=0, description="GLFW monitor index of the LCD")
    lut_path: str | None = Field(None, description="inverse response LUT file (from `ltc gamma`)")
    refresh_hz: float = Field(60.0, gt=0, description="display refresh rate, Hz")
    latency_frames: int = Field(2, ge=0, description="refreshes to wait after show before capture")
    settle_ms: float = Field(0.0, ge=0, description="the LCD's liquid-crystal settle time after "
                             "the latency, ms (a few ms for fast panels; see its datasheet)")
    frame_code: bool = Field(
        False, description="the display driver draws its own strip frame code in the LCD's top-left "
        "corner (for a camera that sees that corner sharply); the acquisition's own check code "
        "is [frame_check]"
    )
    frame_code_block_px: int = Field(16, ge=1, description="strip frame code block edge, LCD pixels")
    pitch_mm: float = Field(0.2715, gt=0, description="LCD pixel pitch, mm")

    @property
    def settled_s(self) -> float:
        """Seconds from a frame's swap until the LCD shows it steadily: the latency, then the
        settle time; the camera is triggered no earlier."""
        return self.latency_frames / self.refresh_hz + self.settle_ms / 1000.0


CameraMatrix = tuple[tuple[float, float, float], tuple[float, float, float],
                     tuple[float, float, float]]

CAMERA_KINDS = ("fake", "opencv", "genicam")
GENICAM_PIXEL_FORMATS = ("Mono8", "Mono10", "Mono12", "Mono16")


class _CameraCommon(_Strict):
    """Fields every camera kind has."""

    exposure_ms: float = Field(33.333, gt=0, description="exposure, ms (a multiple of the refresh period)")
    timeout_s: float = Field(2.0, gt=0, description="capture deadline, s")
    average_frames: int = Field(
        1, ge=1, le=256, description="frames captured of each pattern and averaged: the run "
        "store keeps their mean rounded to whole ADU; frame noise / sqrt(N), capture time x N"
    )
    saturation_fraction: float = Field(
        0.98, gt=0, le=1, description="pixels at or above this fraction of full scale count as saturated"
    )
    matrix: CameraMatrix | None = Field(
        None, description="camera matrix K (3x3, pixels) from a calibration, e.g. the FPP rig's; "
        "`ltc lens` places the optical centre with it and `ltc align` takes the principal point "
        "from it. None: unknown (principal point at the image centre)"
    )

    @field_validator("matrix")
    @classmethod
    def _matrix_is_a_camera_matrix(cls, k: CameraMatrix | None) -> CameraMatrix | None:
        if k is None:
            return k
        if not all(math.isfinite(v) for row in k for v in row):
            raise ValueError(f"camera matrix K must be finite, got {k}")
        if not (k[0][0] > 0 and k[1][1] > 0):
            raise ValueError(f"camera matrix K must have fx = K[0][0] > 0 and fy = K[1][1] > 0 "
                             f"(pixels), got fx = {k[0][0]}, fy = {k[1][1]}")
        if tuple(k[2]) != (0.0, 0.0, 1.0) or k[1][0] != 0:
            raise ValueError(f"camera matrix K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], "
                             f"got {k}")
        return k


class FakeCameraConfig(_CameraCommon):
    """The fake bench's camera (``backend = "fake"`` only; its sensor is set in ``[fake]``)."""

    kind: Literal["fake"] = "fake"


class OpenCVCameraConfig(_CameraCommon):
    """A camera behind OpenCV's ``VideoCapture`` (UVC webcams, video files, streams)."""

    kind: Literal["opencv"] = "opencv"
    source: int | str = Field(0, description="OpenCV device index, path or URL")
    api: str | None = Field(
        None, description="OpenCV backend ('V4L2', 'FFMPEG', 'DSHOW', ...); None: any"
    )
    gain: float | None = Field(None, description="camera gain in backend units; None leaves it")


class GenICamCameraConfig(_CameraCommon):
    """A GigE Vision or USB3 Vision camera through Aravis (``drivers.genicam``)."""

    kind: Literal["genicam"] = "genicam"
    device_id: str | None = Field(
        None, description="Aravis device id ('Vendor-Model-Serial', as `ltc cameras` lists it) "
        "or the camera's IP address; give this or serial"
    )
    serial: str | None = Field(None, description="the camera's serial number; give this or device_id")
    gain: float | None = Field(
        None, description="gain in the device's units (GenICam Gain, usually dB); None leaves it"
    )
    pixel_format: Literal[GENICAM_PIXEL_FORMATS] = Field(  # type: ignore[valid-type]
        "Mono8", description="Mono8, Mono10, Mono12 or Mono16 (unpacked); sets the bit depth"
    )
    roi: tuple[int, int, int, int] | None = Field(
        None, description="region of interest (x, y, width, height), sensor pixels; None: whole sensor"
    )
    trigger: str = Field(
        "software", min_length=1, description="'software' (one frame per shown pattern), a "
        "hardware line the camera offers ('Line0', ...), or 'free-run'"
    )
    frame_rate_hz: float | None = Field(
        None, gt=0, description="frame rate with trigger = 'free-run', Hz; None leaves the camera's"
    )
    control_timeout_s: float = Field(3.0, gt=0, description="deadline for one setting or trigger command, s")
    buffers: int = Field(8, ge=1, description="stream buffers in the pool")

    @model_validator(mode="after")
    def _one_identity(self) -> GenICamCameraConfig:
        if (self.device_id is None) == (self.serial is None):
            raise ValueError("give exactly one of camera.device_id and camera.serial "
                             "(`ltc cameras` lists both)")
        if self.roi is not None and (min(self.roi[:2]) < 0 or min(self.roi[2:]) < 1):
            raise ValueError(f"camera.roi must be (x >= 0, y >= 0, width >= 1, height >= 1), "
                             f"got {self.roi}")
        if self.frame_rate_hz is not None and self.trigger != "free-run":
            raise ValueError("camera.frame_rate_hz applies only with trigger = 'free-run'")
        return self


CameraConfig = Annotated[
    FakeCameraConfig | OpenCVCameraConfig | GenICamCameraConfig, Field(discriminator="kind")
]


class PatternConfig(Modulation):
    """Fourier single-pixel-imaging patterns (docs/optics.md section 5): ``offset`` A and
    ``amplitude`` B of ``A + B cos(...)`` (fractions of white, A +- B within [0, 1])."""

    period: int = Field(24, ge=4, le=256, description="pattern period P, LCD pixels (at most "
                        "the LCD's shorter side)")
    steps: Literal[3, 4] = Field(4, description="phase steps per frequency")


class FrameCheckConfig(_Strict):
    """A small code the acquisition draws into every pattern and reads back through the lens to
    prove which pattern each frame shows. It is calibrated at every depth (a capture of every
    code value), so it reads through any blur; camera pixels that see it are masked out of
    the LTC (``code_mask`` in the run store)."""

    enabled: bool = Field(True, description="draw and verify the check code")
    bits: int = Field(3, ge=1, le=6, description="code bits: the pattern index modulo 2**bits")
    block_px: int = Field(
        16, ge=1, description="block edge, LCD pixels; larger than the LTC at the most defocused depth"
    )
    columns: int = Field(0, ge=0, description="blocks per row; 0 puts all bits in one row")
    origin_px: tuple[int, int] | None = Field(
        None, description="LCD (x, y) of the code's top-left pixel; None: one block right of and "
        "below the LCD centre. It must be in the camera's view at every depth (`ltc align` shows)"
    )
    leak_max: float = Field(
        0.2, gt=0, lt=1, description="pixels read the code only where the pattern adds at most "
        "this fraction of the code's response"
    )
    pollution: float = Field(
        0.005, gt=0, lt=1, description="pixels whose response to the code exceeds this fraction "
        "of their response to white are masked out of the LTC"
    )
    min_margin: float = Field(
        0.25, ge=0, lt=0.5, description="a frame must lie within 0.5 - min_margin of the way to "
        "the nearest other code value, else it is re-captured"
    )

    def check_on(self, lcd_size: tuple[int, int]) -> None:
        """Raise ``ValueError`` naming the field unless the code fits an LCD of (width,
        height) pixels."""
        if not self.enabled:
            return
        try:
            frame_code_rect(self.layout(lcd_size), lcd_size)
        except ValueError as exc:
            field = "origin_px" if self.origin_px is not None else "block_px"
            raise ValueError(f"field 'frame_check.{field}': {exc}") from None

    def layout(self, lcd_size: tuple[int, int]) -> FrameCodeLayout:
        """The code's layout on an LCD of (width, height) pixels."""
        w, h = lcd_size
        origin = self.origin_px or (w // 2 + self.block_px, h // 2 + self.block_px)
        return FrameCodeLayout(bits=self.bits, block_px=self.block_px, style="blocks",
                               columns=self.columns, origin=(int(origin[0]), int(origin[1])))


class AcquireConfig(_Strict):
    """How an acquisition run handles trouble."""

    max_retries: int = Field(
        3, ge=0, description="re-captures of one frame (camera timeout, stale frame, wrong or "
        "unreadable check code) before the run stops"
    )
    saturation_warn_fraction: float = Field(
        0.001, ge=0, le=1, description="log a warning when more than this fraction of a frame's "
        "pixels is saturated (camera.saturation_fraction)"
    )


class SequenceConfig(_Strict):
    """What ``ltc run`` (``station.run_sequence``) does besides check, acquire, reconstruct
    and derive the lens."""

    gamma: bool = Field(False, description="measure the display response first and use its "
                        "inverse LUT for the run (written as lut.npy in the run folder)")
    align: bool = Field(True, description="image a crosshair at every depth and write the "
                        "alignment report (align.json) before acquiring")
    lens_samples: int | None = Field(None, ge=1, description="aperture samples K per node "
                                     "pixel (None: the lens step's default, 256)")
    lens_grid_step: int | None = Field(None, ge=1, description="lens node spacing, camera "
                                       "pixels (None: the lens step's default, 4)")
    lens_pixel_samples: int | None = Field(None, ge=0, le=16, description="how a camera "
                                           "pixel integrates its LCD footprint in the lens "
                                           "fit: 0 a box (a real camera), n an n x n point "
                                           "grid (a simulated camera rendered with n x n "
                                           "subpixels); None: the lens step's default, 0")
    lens_settings: dict[str, float | int | bool] = Field(
        default_factory=dict, description="further settings of the lens step by name "
        "(station.lens.geometry.LensFitConfig, whose defaults are the recommended settings: "
        "e.g. deconvolve_iterations, support_floor, aim_offset_sigma_px); checked when the "
        "lens step starts")


class StationConfig(_Strict):
    """The whole station: hardware, depths, patterns. ``fake`` holds the fake bench's settings
    (validated by the fake backend) and is used only with ``backend = "fake"``."""

    backend: Literal["fake", "real"] = Field(description="'fake' (software bench) or 'real'")
    depths_mm: list[float] = Field(min_length=1, description="stage readings to measure at, mm")
    stage: StageConfig = StageConfig()
    display: DisplayConfig = DisplayConfig()
    camera: CameraConfig = Field(
        default_factory=FakeCameraConfig, description="[camera]: kind 'fake' (the default with "
        "backend 'fake'), 'opencv' (the default with backend 'real') or 'genicam'"
    )
    patterns: PatternConfig = PatternConfig()
    frame_check: FrameCheckConfig = FrameCheckConfig()
    acquire: AcquireConfig = AcquireConfig()
    sequence: SequenceConfig = SequenceConfig()
    fake: dict[str, Any] = Field(default_factory=dict, description="fake bench settings")

    @field_validator("depths_mm")
    @classmethod
    def _depths_once(cls, depths: list[float]) -> list[float]:
        first: dict[float, int] = {}
        for i, z in enumerate(depths):
            if z in first:
                raise ValueError(f"depths_mm[{i}] = {z} repeats depths_mm[{first[z]}]; give "
                                 "each depth once")
            first[z] = i
        return depths

    @model_validator(mode="before")
    @classmethod
    def _default_camera_kind(cls, data: Any) -> Any:
        """``[camera]`` without ``kind``: the fake camera on the fake bench, else OpenCV."""
        if isinstance(data, dict):
            camera = data.get("camera", {})
            if isinstance(camera, dict) and "kind" not in camera:
                kind = "fake" if data.get("backend") == "fake" else "opencv"
                data = {**data, "camera": {**camera, "kind": kind}}
        return data

    @model_validator(mode="after")
    def _fake_camera_on_fake_bench(self) -> StationConfig:
        if self.camera.kind == "fake" and self.backend != "fake":
            raise ValueError("camera.kind = 'fake' needs backend = 'fake' (the fake camera looks "
                             "at the fake LCD); use 'genicam' or 'opencv' for a real camera")
        return self

    @model_validator(mode="after")
    def _depths_in_travel(self) -> StationConfig:
        lo, hi = self.stage.travel_mm
        for i, z in enumerate(self.depths_mm):
            if z < 0:
                raise ValueError(f"depths_mm[{i}] = {z} is negative; depths are stage readings >= 0")
            if not lo <= z <= hi:
                raise ValueError(
                    f"depths_mm[{i}] = {z} is outside stage.travel_mm {self.stage.travel_mm}"
                )
        return self


def check_on_lcd(config: StationConfig, lcd_size: tuple[int, int], source: str) -> None:
    """Refuse (:class:`ConfigError` naming ``source`` and the field) a pattern period or a
    check code that does not fit an LCD of (width, height) pixels."""
    w, h = lcd_size
    if config.patterns.period > min(w, h):
        raise ConfigError(f"{source}: field 'patterns.period': {config.patterns.period} LCD "
                          f"pixels does not fit the {w}x{h} LCD; at most {min(w, h)}")
    try:
        config.frame_check.check_on(lcd_size)
    except ValueError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def placeholder_warnings(text: str, source: str) -> list[str]:
    """Warnings for the values of ``text`` (a config's TOML) still as ``ltc config --example
    real`` gives them where it marks them CHECK, and for any value "CHANGE-ME"."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return []
    example = example_text("real")
    ref = tomllib.loads(example)
    warnings = []
    section: tuple[str, ...] = ()
    for line in example.splitlines():
        stripped = line.strip()
        if stripped.startswith("[") and not stripped.startswith("[["):
            section = tuple(stripped.strip("[]").split("."))
            continue
        if stripped.startswith("#") or "# CHECK" not in line or "=" not in line:
            continue
        key = stripped.split("=", 1)[0].strip()
        mine, theirs = _dig(data, section + (key,)), _dig(ref, section + (key,))
        if mine is not None and mine == theirs and mine != "CHANGE-ME":
            warnings.append(f"{source}: field '{'.'.join(section + (key,))}' still has the "
                            f"example's value {mine!r}, marked CHECK: set it for this bench")
    warnings += [f"{source}: field '{path}' is still \"CHANGE-ME\": set it for this bench"
                 for path in _placeholders(data)]
    return warnings


def _dig(data: Any, path: tuple[str, ...]) -> Any:
    for key in path:
        if not isinstance(data, dict) or key not in data:
            return None
        data = data[key]
    return data


def _placeholders(data: Any, prefix: str = "") -> list[str]:
    if isinstance(data, dict):
        return [p for k, v in data.items() for p in _placeholders(v, f"{prefix}{k}.")]
    return [prefix.rstrip(".")] if data == "CHANGE-ME" else []


def parse_config(text: str, source: str = "<config>") -> StationConfig:
    """Parse TOML text into a validated config; errors name ``source`` and the field."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from exc
    try:
        return StationConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_format_errors(source, exc)) from exc


def _format_errors(source: str, exc: ValidationError) -> str:
    """One line per error, ``source: field 'camera.gain': ...``: the camera kind pydantic puts
    in the path of a tagged union is taken out, and a bad kind is named as ``camera.kind``."""
    lines = []
    for e in exc.errors():
        loc = tuple(e["loc"])
        msg = e["msg"].removeprefix("Value error, ")
        if loc[:1] == ("camera",) and len(loc) > 1 and loc[1] in CAMERA_KINDS:
            if e["type"] == "extra_forbidden":
                msg += f" (not a field of camera kind {loc[1]!r})"
            loc = loc[:1] + loc[2:]
        if e["type"] == "union_tag_invalid":
            loc = loc + ("kind",)
            msg = f"unknown camera kind {e['input'].get('kind')!r}; expected one of " \
                  f"{', '.join(repr(k) for k in CAMERA_KINDS)}"
        lines.append(f"{source}: field '{field_path(loc)}': {msg}")
    return "; ".join(lines)


def load_config(path: str | Path) -> StationConfig:
    """Read and validate a station config file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config: {exc.strerror}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") \
            from exc
    return parse_config(text, str(path))


def example_text(kind: Literal["fake", "real"]) -> str:
    """The commented example config shipped with the package."""
    return resources.files("station").joinpath("examples", f"{kind}.toml").read_text("utf-8")


def example_config(kind: Literal["fake", "real"] = "fake") -> StationConfig:
    """The example config, validated."""
    return parse_config(example_text(kind), f"station/examples/{kind}.toml")
