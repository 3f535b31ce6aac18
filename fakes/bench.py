"""The fake bench's physical world: an LCD, and a camera carried by the stage along the
LCD's normal, looking through the ground-truth lens (``sim.optics.lens.AberratedLens``).

Frames (all mm):

* LCD frame: origin at the centre of LCD pixel (0, 0), x along columns, y along rows,
  z along the normal away from the camera (the camera sits at negative z).
* Station frame: the LCD frame shifted along z so that the LCD plane lies at
  ``z = stage reading``; it rides with the camera, so the camera's optical centre is fixed
  in it at ``(x_c, y_c, -lcd_distance_at_zero_mm)``. Principal rays and the optical centre
  measured by the station are expressed in this frame.

The stage moves the camera away from the LCD as its reading grows:
``distance(z_stage) = lcd_distance_at_zero_mm + z_stage``.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Literal

import numpy as np
import scipy.sparse as sp
from pydantic import BaseModel, ConfigDict, Field, model_validator

from sim.optics.lens import AberratedLens
from sim.optics.plane_ltc import plane_ltc

LTC_CACHE_BYTES = 4 << 30  # true LTCs kept in memory, bytes


class BenchGeometry(BaseModel):
    """LCD and camera of a fake bench (the exact one, ``fakes.synthetic``'s). Defaults are
    the reference system."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lcd_size: tuple[int, int] = Field((3840, 2160), description="LCD (width, height), pixels")
    lcd_pitch_mm: float = Field(0.2715, gt=0, description="LCD pixel pitch, mm")
    camera_size: tuple[int, int] = Field((4096, 2168), description="sensor (width, height), px")
    pixel_pitch_um: float = Field(3.45, gt=0, description="sensor pixel pitch, um")
    focal_length_mm: float = Field(16.0, gt=0, description="lens focal length, mm")


class BenchConfig(BenchGeometry):
    """Geometry and optics of the fake LTC bench. Defaults are the reference system."""

    f_number: float = Field(4.0, gt=0, description="f-number; pupil diameter = f / N")
    focus_distance_mm: float = Field(760.0, gt=0, description="in-focus distance z_f, mm")
    vignetting_shift_mm: float = Field(
        0.0, description="clipping-circle shift per unit tan(field angle), mm (0: none)"
    )
    vignetting_radius_ratio: float = Field(1.0, gt=0, description="clip radius / pupil radius")
    spherical_mm: float = Field(0.0, description="focus shift at the pupil rim, mm")
    coma_mm: float = Field(0.0, description="coma aim-point shift at the rim per unit tan, mm")
    lcd_distance_at_zero_mm: float = Field(
        600.0, gt=0, description="pupil-to-LCD distance when the stage reads 0, mm"
    )
    tilt_deg: tuple[float, float] = Field(
        (0.0, 0.0), description="camera tilt about its x and y axes relative to the stage axis, deg"
    )
    offset_mm: tuple[float, float] = Field(
        (0.0, 0.0), description="optical centre offset from the LCD centre along LCD x, y, mm"
    )
    pupil_samples: int = Field(400, ge=1, description="pupil samples for the exact LTC")
    pupil_edge: Literal["hard", "soft"] = Field(
        "hard", description="how the pupil samples meet the vignetting circle "
        "(sim.optics.lens.AberratedLens.edge): 'soft' converges with far fewer samples, so the "
        "LTC is the lens's own and not its sampling's (the experiment's benches use it)")
    subpixels: int = Field(3, ge=1, description="pixel area sampled on an n x n grid")

    @model_validator(mode="after")
    def _check_sizes(self) -> BenchConfig:
        for name in ("lcd_size", "camera_size"):
            w, h = getattr(self, name)
            if w < 1 or h < 1:
                raise ValueError(f"{name} must be positive (width, height), got {(w, h)}")
        return self

    @classmethod
    def small(cls, **overrides) -> BenchConfig:
        """A small, fast bench for tests and the demo: 40 x 30 camera, 96 x 72 LCD, f/2,
        strong vignetting and spherical aberration so the lens is visibly non-Gaussian."""
        base = dict(
            lcd_size=(96, 72),
            camera_size=(40, 30),
            pixel_pitch_um=25.0,
            focal_length_mm=16.0,
            f_number=2.0,
            focus_distance_mm=250.0,
            lcd_distance_at_zero_mm=150.0,
            vignetting_shift_mm=60.0,
            vignetting_radius_ratio=1.0,
            spherical_mm=6.0,
            pupil_samples=400,
            subpixels=3,
        )
        base.update(overrides)
        return cls(**base)


class FakeBench:
    """The world of the fake bench: where the camera is and what each pixel sees."""

    def __init__(self, config: BenchConfig) -> None:
        self.config = config
        self._cache: OrderedDict[float, sp.csr_array] = OrderedDict()

    def _ltc(self, z_key: float) -> sp.csr_array:
        """The true LTC at a stage reading, kept while the kept ones stay within
        ``LTC_CACHE_BYTES`` (the latest always: a paper-size depth is ~1.6 GB)."""
        m = self._cache.pop(z_key, None)
        if m is None:
            m = self._compute_ltc(z_key)
        self._cache[z_key] = m
        while len(self._cache) > 1 and sum(
                a.data.nbytes + a.indices.nbytes + a.indptr.nbytes
                for a in self._cache.values()) > LTC_CACHE_BYTES:
            self._cache.popitem(last=False)
        return m

    @property
    def lens(self) -> AberratedLens:
        """The ground-truth lens, sampled densely for the exact LTC."""
        c = self.config
        return AberratedLens(
            pupil_diameter_mm=c.focal_length_mm / c.f_number,
            focus_distance_mm=c.focus_distance_mm,
            vignetting_shift_mm=c.vignetting_shift_mm,
            vignetting_radius_ratio=c.vignetting_radius_ratio,
            spherical_mm=c.spherical_mm,
            coma_mm=c.coma_mm,
            samples=c.pupil_samples,
            edge=c.pupil_edge,
        )

    @property
    def K(self) -> np.ndarray:
        """Camera matrix (3x3): focal length in pixels, principal point at the sensor centre."""
        c = self.config
        f_px = c.focal_length_mm / (c.pixel_pitch_um * 1e-3)
        w, h = c.camera_size
        return np.array([[f_px, 0.0, (w - 1) / 2], [0.0, f_px, (h - 1) / 2], [0.0, 0.0, 1.0]])

    @property
    def R_cam_to_lcd(self) -> np.ndarray:
        """Rotation taking camera-frame vectors to the LCD frame (the tilt misalignment)."""
        ax, ay = np.deg2rad(self.config.tilt_deg)
        rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
        ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
        return ry @ rx

    def lcd_distance_mm(self, z_stage_mm: float) -> float:
        """Pupil-to-LCD distance along the stage axis at a stage reading, mm."""
        return self.config.lcd_distance_at_zero_mm + z_stage_mm

    def optical_centre_station_mm(self) -> np.ndarray:
        """True optical centre (entrance pupil centre) in the station frame, (3,) mm."""
        c = self.config
        w, h = c.lcd_size
        return np.array(
            [
                (w - 1) / 2 * c.lcd_pitch_mm + c.offset_mm[0],
                (h - 1) / 2 * c.lcd_pitch_mm + c.offset_mm[1],
                -c.lcd_distance_at_zero_mm,
            ]
        )

    def camera_pose_in_lcd(self, z_stage_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) with ``X_lcd = R X_cam + t`` at a stage reading."""
        t = self.optical_centre_station_mm()
        t[2] = -self.lcd_distance_mm(z_stage_mm)
        return self.R_cam_to_lcd, t

    def _compute_ltc(self, z_key: float) -> sp.csr_array:
        R, t = self.camera_pose_in_lcd(z_key)
        c = self.config
        return plane_ltc(
            self.K, None, c.camera_size, self.lens, R, t, c.lcd_size, c.lcd_pitch_mm,
            subpixels=c.subpixels,
        )

    def true_ltc(self, z_mm: float, normalise: bool = False) -> sp.csr_array:
        """Exact per-pixel LTC at stage reading ``z_mm``.

        Returns a (H*W, lcd_h*lcd_w) CSR array: row ``v * W + u`` holds the weights of
        LCD pixel ``j * lcd_w + i`` seen by camera pixel (u, v). Rows sum to the pixel's
        transmittance (vignetting and LCD coverage), or to 1 with ``normalise`` (rows with
        no light stay empty).
        """
        m = self._ltc(round(float(z_mm), 9))
        if not normalise:
            return m
        s = np.asarray(m.sum(axis=1)).ravel()
        inv = np.divide(1.0, s, out=np.zeros_like(s), where=s > 0)
        return sp.csr_array(sp.diags_array(inv) @ m)

    def true_centroids_lcd_px(self, z_mm: float) -> np.ndarray:
        """Grey-scale centroid of every pixel's true LTC in LCD pixels, (H, W, 2) as (x, y)."""
        c = self.config
        m = self.true_ltc(z_mm, normalise=True)
        lw, lh = c.lcd_size
        cols = np.arange(lw * lh)
        x = m @ (cols % lw).astype(np.float64)
        y = m @ (cols // lw).astype(np.float64)
        w, h = c.camera_size
        return np.stack([x, y], axis=1).reshape(h, w, 2)
