"""The synthetic full-size bench: a fast fake camera whose every pixel has an analytic LTC.

Select it in a station config with ``backend = "fake"`` and ``[fake] model = "synthetic"``
(settings in ``[fake.synthetic]``, :class:`SyntheticConfig`). The exact fake bench
(``fakes/bench.py``, ray-traced LTCs) stays the reference for small-size accuracy; this one
makes full-size frames (4096 x 2168 by default) in a fraction of a second.

The world (LCD pixels, pixel centres at integers; the LCD pixel j covers [j - 1/2, j + 1/2]):
camera pixel (u, v) at stage reading z sees an elliptical Gaussian LTC of LCD luminance,
centre ``mu`` (LCD px), covariance ``S`` (LCD px^2), transmittance ``T``:

* ``mu``: a pinhole at the LCD centre seen from ``D = lcd_distance_at_zero_mm + z``, plus a
  vignetting-like outward shift of ``shift_sigmas * sigma * r`` (r: field radius, 1 at the
  corners);
* ``S``: ``sigma = hypot(sigma_focus_px, defocus blur)`` (blur radius
  ``pupil/2 |D - D_f| / D_f`` mm, sigma half of it), stretched by ``1 + radial_stretch r^2``
  radially and ``1 + tangential_stretch r^2`` tangentially, oriented along the field;
* ``T = 1 - vignetting r^2``.

Each LCD pixel shows its luminance uniformly, so the true LTC over LCD pixels is the Gaussian
integrated over each pixel: centroid ``mu``, central second moments ``S + I/12``
(:meth:`SyntheticBench.true_moments`). A pixel's response to a P-periodic pattern with tile
DFT ``C[l, k]`` is ``T sum C[l, k] exp(2 pi i f.mu - 2 pi^2 f S f) sinc(f_x) sinc(f_y)``,
``f = (k, l) / P`` reduced to (-1/2, 1/2]; coefficients below ``1e-3`` of full white (the
8-bit rounding harmonics, up to 7e-4: a dozen per pattern, different for every phase step) are
left out, which moves a response by at most 3.3e-4 of white against the exact 8-bit pattern
(measured; 30 times below the shot noise at half well), as is aliasing (``exp(-pi^2 sigma^2 / 2)``,
< 1e-3 for sigma >= 1.2 px). Stripe patterns (Gray code, phase shifts: every row or every
column equal) go through the Gaussian marginal along their axis, from tables of the profile
blurred at ``SIGMA_LEVELS`` widths, interpolated
bilinearly in width and position. Noise: Gaussian with the shot-noise variance plus read
noise, seeded per scene (the image shown and the stage reading), so a resumed run captures
the same frames; the k-th further frame of an unchanged scene (frames averaged per pattern)
is seeded with k too, so it has noise of its own.
"""

from __future__ import annotations

import contextlib
import hashlib
import time
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from scipy import ndimage

from drivers.interfaces import Camera, Frame, PatternDisplay, ShownFrame, Stage
from fakes.bench import BenchGeometry
from fakes.camera import NoiseModel, SettableExposure
from sim.validation import format_validation_error

SIGMA_LEVELS = 24  # blur widths tabulated for stripe patterns
PROFILE_SUB = 4  # stripe-table samples per LCD pixel
MIN_COEFFICIENT = 1e-3  # tile DFT coefficients kept, fraction of full white


class SyntheticConfig(BenchGeometry):
    """Geometry, LTC field and camera of the synthetic bench (defaults: the paper's scale)."""

    pupil_mm: float = Field(4.0, gt=0, description="entrance pupil diameter, mm")
    focus_distance_mm: float = Field(760.0, gt=0, description="in-focus distance D_f, mm")
    lcd_distance_at_zero_mm: float = Field(600.0, gt=0, description="pupil-LCD distance at z=0")
    sigma_focus_px: float = Field(1.3, ge=1.2, description="LTC sigma in focus, LCD px")
    radial_stretch: float = Field(0.4, ge=0, description="radial sigma growth at r = 1")
    tangential_stretch: float = Field(0.15, ge=0, description="tangential sigma growth at r = 1")
    shift_sigmas: float = Field(0.3, description="outward centroid shift at r = 1, in sigma")
    vignetting: float = Field(0.35, ge=0, lt=1, description="transmittance loss at r = 1")
    camera: NoiseModel = Field(default_factory=NoiseModel, description="sensor response and "
                               "noise, as the exact fake camera's (enabled = false: noise-free)")


class SyntheticSettings(BaseModel):
    """The ``[fake]`` section of a config for the synthetic bench."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    model: str = Field("synthetic", pattern="^synthetic$", description="this bench")
    seed: int | None = Field(0, description="noise seed")
    rows: tuple[int, int] | None = Field(None, description="render camera rows [r0, r1) only")
    synthetic: SyntheticConfig = SyntheticConfig()


def is_synthetic(fake: dict[str, Any]) -> bool:
    """True when a config's ``[fake]`` section selects the synthetic bench."""
    return fake.get("model") == "synthetic"


def parse_synthetic_settings(data: dict[str, Any], source: str = "config") -> SyntheticSettings:
    """The ``[fake]`` section of a synthetic-bench config; errors name ``fake.<field>``."""
    try:
        s = SyntheticSettings.model_validate(data)
    except ValidationError as exc:
        raise ValueError(format_validation_error(source, exc, ("fake",))) from exc
    h = s.synthetic.camera_size[1]
    if s.rows is not None and not 0 <= s.rows[0] < s.rows[1] <= h:
        raise ValueError(f"{source}: fake.rows must be [r0, r1) inside 0..{h}, got {s.rows}")
    return s


class SyntheticBench:
    """The LTC field: per camera pixel, the Gaussian's parameters at a stage reading."""

    def __init__(self, config: SyntheticConfig, rows: tuple[int, int] | None = None) -> None:
        self.config = config
        w, h = config.camera_size
        self.rows = rows or (0, h)  # camera rows rendered (a crop of the full sensor)
        self._cache: dict[float, dict[str, np.ndarray]] = {}
        self._transfer: dict[tuple, tuple[dict, np.ndarray, np.ndarray]] = {}

    @property
    def focal_px(self) -> float:
        c = self.config
        return c.focal_length_mm / (c.pixel_pitch_um * 1e-3)

    @property
    def K(self) -> np.ndarray:
        """Camera matrix (3x3) of the pinhole: principal point at the full sensor's centre."""
        w, h = self.config.camera_size
        f = self.focal_px
        return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])

    def field(self, z_mm: float) -> dict[str, np.ndarray]:
        """Per-pixel ``mu_int`` (2, H, W) int32 and ``mu_frac`` (2, H, W) float32 (the
        centre, LCD px, split for exact phases), ``sxx, syy, sxy`` (H, W) float32 LCD px^2,
        ``t`` (H, W) float32 transmittance. Cached for the last two readings."""
        key = round(float(z_mm), 9)
        if key not in self._cache:
            if len(self._cache) >= 2:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = self._field(key)
        return self._cache[key]

    def _field(self, z_mm: float) -> dict[str, np.ndarray]:
        c = self.config
        w, h = c.camera_size
        r0, r1 = self.rows
        d_mm = c.lcd_distance_at_zero_mm + z_mm
        v, u = np.mgrid[r0:r1, 0:w].astype(np.float64)
        du, dv = u - (w - 1) / 2, v - (h - 1) / 2
        half = np.hypot((w - 1) / 2, (h - 1) / 2)
        r = np.hypot(du, dv) / half
        ang = np.arctan2(dv, du)
        scale = c.pixel_pitch_um * 1e-3 * d_mm / c.focal_length_mm / c.lcd_pitch_mm
        blur_mm = 0.5 * c.pupil_mm * abs(d_mm - c.focus_distance_mm) / c.focus_distance_mm
        sigma = np.hypot(c.sigma_focus_px, 0.5 * blur_mm / c.lcd_pitch_mm)
        shift = c.shift_sigmas * sigma * r
        lw, lh = c.lcd_size
        mx = (lw - 1) / 2 + du * scale + shift * np.cos(ang)
        my = (lh - 1) / 2 + dv * scale + shift * np.sin(ang)
        sr = sigma * (1 + c.radial_stretch * r**2)
        st = sigma * (1 + c.tangential_stretch * r**2)
        ca, sa = np.cos(ang), np.sin(ang)
        sxx = sr**2 * ca**2 + st**2 * sa**2
        syy = sr**2 * sa**2 + st**2 * ca**2
        sxy = (sr**2 - st**2) * ca * sa
        mi = np.floor(np.stack([mx, my]))
        return {"mu_int": mi.astype(np.int32), "mu_frac": (np.stack([mx, my]) - mi)
                .astype(np.float32), "sxx": sxx.astype(np.float32),
                "syy": syy.astype(np.float32), "sxy": sxy.astype(np.float32),
                "t": (1 - c.vignetting * r**2).astype(np.float32)}

    def true_moments(self, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """True LTC centroid (H, W, 2) LCD (x, y) px and central second moments (H, W, 3)
        ``m_xx, m_yy, m_xy`` LCD px^2 (the Gaussian integrated over LCD pixels)."""
        f = self.field(z_mm)
        mu = (f["mu_int"] + f["mu_frac"].astype(np.float64)).transpose(1, 2, 0)
        mom = np.stack([f["sxx"] + 1 / 12, f["syy"] + 1 / 12, f["sxy"]], axis=-1)
        return mu, mom.astype(np.float64)

    def response(self, kind: str, data: Any, z_mm: float) -> np.ndarray:
        """Expected relative response (H, W) float32 (T x luminance seen) to a shown image
        described by :func:`describe_image`."""
        f = self.field(z_mm)
        if kind == "tile":
            return self._tile_response(data, f)
        axis, profile = data
        return self._stripe_response(profile, f, 0 if axis == "x" else 1)

    def _tile_response(self, tile: np.ndarray, f: dict) -> np.ndarray:
        p = tile.shape[0]
        coef = np.fft.fft2(tile) / (p * p)  # [l, k]
        out = np.full(f["t"].shape, float(coef[0, 0].real), dtype=np.float32)
        seen = set()
        for l, k in zip(*np.nonzero(np.abs(coef) > MIN_COEFFICIENT), strict=True):
            kr, lr = (k + p // 2) % p - p // 2, (l + p // 2) % p - p // 2  # to (-P/2, P/2]
            if (kr, lr) == (0, 0) or (-kr, -lr) in seen:
                continue
            seen.add((kr, lr))
            conj = (-kr % p, -lr % p) != (k, l)  # its conjugate is a separate coefficient
            out += (2.0 if conj else 1.0) * self._harmonic(coef[l, k], kr, lr, p, f)
        return out * f["t"]

    def _harmonic(self, c: complex, k: int, l: int, p: int, f: dict) -> np.ndarray:
        """Re(c H(k/P, l/P)) / T per pixel, float32. H per pixel (its real and imaginary
        parts) is kept for the last few frequencies, so the phase steps of one pattern cost
        two multiply-adds per pixel instead of an exp and a cos."""
        key = (k, l, p)
        if key not in self._transfer or self._transfer[key][0] is not f:
            self._transfer.pop(key, None)
            if len(self._transfer) >= 4:
                self._transfer.pop(next(iter(self._transfer)))
            fx, fy = k / p, l / p
            var = fx * fx * f["sxx"] + 2 * fx * fy * f["sxy"] + fy * fy * f["syy"]
            amp = np.exp(np.float32(-2 * np.pi**2) * var)
            amp *= np.float32(np.sinc(fx) * np.sinc(fy))
            mi, mf = f["mu_int"], f["mu_frac"]
            ph = ((k * mi[0] + l * mi[1]) % p).astype(np.float32)
            ph += np.float32(k) * mf[0] + np.float32(l) * mf[1]
            ph *= np.float32(2 * np.pi / p)
            self._transfer[key] = (f, amp * np.cos(ph), amp * np.sin(ph))
        _, re, im = self._transfer[key]
        a = np.angle(c)
        return np.float32(abs(c) * np.cos(a)) * re - np.float32(abs(c) * np.sin(a)) * im

    def _stripe_response(self, profile: np.ndarray, f: dict, axis: int) -> np.ndarray:
        var = f["sxx"] if axis == 0 else f["syy"]  # the fine profile holds the pixel boxes
        sig = np.sqrt(var)
        lo, hi = float(sig.min()), float(sig.max())
        levels = np.linspace(lo, hi if hi > lo else lo + 1e-3, SIGMA_LEVELS)
        fine = np.repeat(np.asarray(profile, dtype=np.float64), PROFILE_SUB)
        table = np.stack([ndimage.gaussian_filter1d(fine, s * PROFILE_SUB, mode="nearest")
                          for s in levels]).astype(np.float32)
        mu = f["mu_int"][axis] + f["mu_frac"][axis]
        # bilinear in (sigma, position): sample j of the fine profile sits at LCD x
        # (j + 1/2) / PROFILE_SUB - 1/2
        x = np.clip((mu + 0.5) * PROFILE_SUB - 0.5, 0, len(fine) - 1)
        s = np.clip((sig - levels[0]) / (levels[1] - levels[0]), 0, SIGMA_LEVELS - 1)
        x0 = np.minimum(x.astype(np.int64), len(fine) - 2)
        s0 = np.minimum(s.astype(np.int64), SIGMA_LEVELS - 2)
        fx, fs = (x - x0).astype(np.float32), (s - s0).astype(np.float32)
        lo_s = table[s0, x0] * (1 - fx) + table[s0, x0 + 1] * fx
        hi_s = table[s0 + 1, x0] * (1 - fx) + table[s0 + 1, x0 + 1] * fx
        return (lo_s * (1 - fs) + hi_s * fs) * f["t"]


def describe_image(image: np.ndarray, period: int) -> tuple[str, Any]:
    """What a shown uint8 image (H, W) is, as relative luminance: ``("tile", (P, P))`` for
    a P-periodic (or uniform) image, ``("stripes", ("x" | "y", profile))`` for one whose
    rows (columns) are all equal. Anything else is refused (the synthetic bench renders the
    station's patterns only: turn ``[frame_check]`` off)."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., 0]
    h, w = img.shape
    p = period
    if h >= p and w >= p and np.array_equal(img[p:], img[:-p]) and np.array_equal(
            img[:, p:], img[:, :-p]):  # shifts by one period, no full-size float copy
        return "tile", img[:p, :p] / 255.0
    if np.array_equal(img[1:], img[:-1]):
        return "stripes", ("x", img[0] / 255.0)
    if np.array_equal(img[:, 1:], img[:, :-1]):
        return "stripes", ("y", img[:, 0] / 255.0)
    raise ValueError("synthetic bench: the shown image is neither P-periodic nor stripes; "
                     "it renders the station's patterns only (set [frame_check] enabled = "
                     "false)")


class SyntheticStage(Stage):
    """A stage that is where it is told at once (zero latency)."""

    def __init__(self, travel_mm: tuple[float, float], start_mm: float = 0.0) -> None:
        self._z = float(start_mm)
        self._limits = (float(travel_mm[0]), float(travel_mm[1]))
        self._homed = False

    def home(self) -> None:
        self._z, self._homed = 0.0, True

    def move_to(self, z_mm: float, timeout: float | None = None) -> float:
        lo, hi = self._limits
        if not lo <= z_mm <= hi:
            raise ValueError(f"SyntheticStage: {z_mm} mm is outside {self._limits}")
        self._z = float(z_mm)
        return self._z

    @property
    def position_mm(self) -> float:
        return self._z

    @property
    def limits_mm(self) -> tuple[float, float]:
        return self._limits

    @property
    def is_homed(self) -> bool:
        return self._homed

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass


class SyntheticDisplay(PatternDisplay):
    """Records what is shown, as :func:`describe_image` sees it (zero latency)."""

    def __init__(self, size: tuple[int, int], period: int) -> None:
        self._size = (int(size[0]), int(size[1]))
        self.period = int(period)
        self.shown: tuple[str, Any] = ("tile", np.zeros((period, period)))
        self.key = b""
        self._count = 0

    @property
    def size(self) -> tuple[int, int]:
        return self._size

    def show(self, image: np.ndarray, frame_code: int | None = None) -> ShownFrame:
        img = np.asarray(image)
        if img.shape[:2] != (self._size[1], self._size[0]):
            raise ValueError(f"SyntheticDisplay: image {img.shape} is not the LCD's "
                             f"{self._size[1]} x {self._size[0]}")
        self.shown = describe_image(img, self.period)
        kind, data = self.shown
        tag, raw = (b"tile", data) if kind == "tile" else (data[0].encode(), data[1])
        self.key = hashlib.blake2b(tag + np.ascontiguousarray(raw).tobytes(),
                                   digest_size=16).digest()
        index, self._count = self._count, self._count + 1
        return ShownFrame(index=index, swap_time=time.monotonic(), frame_code=frame_code)

    def set_lut(self, lut: np.ndarray | None) -> None:
        if lut is not None:
            raise ValueError("SyntheticDisplay: a linear panel; apply the LUT to the patterns")

    def close(self) -> None:
        pass


class SyntheticCamera(SettableExposure, Camera):
    """Renders the shown pattern through the bench's LTC field at the stage's reading."""

    def __init__(self, bench: SyntheticBench, display: SyntheticDisplay, stage: Stage,
                 seed: int | None = 0, exposure_ms: float = 20.0) -> None:
        self.bench, self.display, self.stage = bench, display, stage
        self.seed = seed
        self._exposure_ms = float(exposure_ms)
        self._frame_id = -1
        self._scene: tuple | None = None  # the last scene's key and its frames so far
        self._scene_frames = 0

    @property
    def size(self) -> tuple[int, int]:
        w, _ = self.bench.config.camera_size
        r0, r1 = self.bench.rows
        return w, r1 - r0

    @property
    def bit_depth(self) -> int:
        return self.bench.config.camera.bit_depth

    def capture(self, timeout: float | None = None) -> Frame:
        c = self.bench.config
        z = self.stage.position_mm
        kind, data = self.display.shown
        rel = self.bench.response(kind, data, z)
        n = c.camera
        electrons = rel * np.float32(n.electrons_per_ms_white() * self._exposure_ms)
        rng = None
        scene = (self.display.key, z, self._exposure_ms)
        if scene != self._scene:
            self._scene, self._scene_frames = scene, 0
        if n.enabled:  # noise drawn per scene: a resumed or retried frame is the same frame
            seed = np.frombuffer(self.display.key + np.float64(z).tobytes(), dtype="<u4")
            k = self._scene_frames
            rng = np.random.default_rng([self.seed or 0, *seed.tolist()] + ([k] if k else []))
        self._scene_frames += 1
        sensor = n.sensor
        image = sensor.digitise(sensor.expose_gaussian(electrons, rng))
        self._frame_id += 1
        return Frame(image=image,
                     timestamp=time.monotonic(), exposure_ms=self._exposure_ms,
                     frame_id=self._frame_id, meta={"stage_mm": z})

    def close(self) -> None:
        pass


class SyntheticHardware(contextlib.ExitStack):
    """Stage, display and camera of the synthetic bench. ``rows``: render only camera rows
    ``rows[0]:rows[1]`` (a crop, for quick full-width runs)."""

    def __init__(self, settings: SyntheticSettings, *, period: int,
                 travel_mm: tuple[float, float], exposure_ms: float = 20.0) -> None:
        super().__init__()
        self.settings = settings
        self.bench = SyntheticBench(settings.synthetic, settings.rows)
        self.stage = SyntheticStage(travel_mm)
        self.lcd = SyntheticDisplay(settings.synthetic.lcd_size, period)
        self.camera = SyntheticCamera(self.bench, self.lcd, self.stage, settings.seed,
                                      exposure_ms)
