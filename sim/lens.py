"""Lens models: each turns camera pixels into a bundle of weighted rays in the camera frame.

Every model answers ``bundle(xy_n, uv) -> RayBundle`` where ``xy_n`` are the pixels'
undistorted normalised coordinates (see ``sim.projection.pixel_to_normalized``; distortion
lives there, not here) and ``uv`` their pixel coordinates (used by models that vary per
pixel). Rays start on the aperture plane ``z = 0`` of the camera frame (OPTICS.md section 4):
ray k leaves ``(x_k, y_k, 0)`` and passes through the pixel's in-focus point
``(x_n z_f, y_n z_f, z_f)``. Lengths in mm.

The ground-truth lens of the fakes (OPTICS.md section 8) is ``AberratedLens``; the virtual
scanner renders with the same class, so there is one implementation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

GOLDEN_ANGLE_RAD = np.pi * (3.0 - np.sqrt(5.0))


@dataclass(frozen=True)
class RayBundle:
    """Rays of n pixels, K samples each, in the camera frame.

    origins : (n, K, 3) float64, mm, on the aperture plane z = 0.
    directions : (n, K, 3) float64, unit vectors, z > 0.
    weights : (n, K) float64; per pixel they sum to the relative transmittance
        (1 for an unvignetted pixel); blocked samples have weight 0.
    """

    origins: np.ndarray
    directions: np.ndarray
    weights: np.ndarray


class LensModel(Protocol):
    """Anything that turns pixels into ray bundles."""

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle: ...


def sunflower_disk(n: int) -> np.ndarray:
    """``n`` equal-area points covering the unit disk evenly (Vogel spiral), (n, 2) float64."""
    if n < 1:
        raise ValueError(f"sunflower_disk needs n >= 1 samples, got {n}")
    k = np.arange(n, dtype=np.float64)
    r = np.sqrt((k + 0.5) / n)
    t = k * GOLDEN_ANGLE_RAD
    return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)


def hit_plane(bundle_origins: np.ndarray, directions: np.ndarray, z_mm: float) -> np.ndarray:
    """Points (..., 2) where rays meet the plane ``z = z_mm`` of their own frame."""
    t = (z_mm - bundle_origins[..., 2]) / directions[..., 2]
    return bundle_origins[..., :2] + t[..., None] * directions[..., :2]


def _rays_through_focus(
    aperture_xy_mm: np.ndarray, aim_mm: np.ndarray, weights: np.ndarray
) -> RayBundle:
    """Bundle from aperture points (n, K, 2) aimed at points (n, K, 3)."""
    n, k = aperture_xy_mm.shape[:2]
    origins = np.zeros((n, k, 3))
    origins[..., :2] = aperture_xy_mm
    d = aim_mm - origins
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return RayBundle(origins, d, weights)


class PinholeLens(BaseModel):
    """One ray per pixel from the optical centre, weight 1."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = Field("pinhole", pattern="^pinhole$")

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        xy_n = np.asarray(xy_n, dtype=np.float64).reshape(-1, 2)
        n = len(xy_n)
        origins = np.zeros((n, 1, 3))
        d = np.concatenate([xy_n, np.ones((n, 1))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return RayBundle(origins, d[:, None, :], np.ones((n, 1)))


class AberratedLens(BaseModel):
    """Thin lens with a circular entrance pupil, field-dependent vignetting, spherical
    aberration and coma: the ground-truth lens of the fakes (OPTICS.md section 8).

    With ``vignetting_shift_mm = spherical_mm = coma_mm = 0`` it is the ideal thin lens,
    whose blur disk on a plane at distance z has diameter ``pupil_diameter_mm * |z - z_f| / z_f``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = Field("aberrated", pattern="^aberrated$")
    pupil_diameter_mm: float = Field(
        gt=0, description="entrance pupil diameter, mm (focal length / f-number)"
    )
    focus_distance_mm: float = Field(
        gt=0, description="distance z_f of the plane in focus from the pupil plane (paraxial), mm"
    )
    vignetting_shift_mm: float = Field(
        0.0,
        description="offset of the clipping circle on the pupil plane per unit tan(field angle), "
        "mm; it shifts towards the field direction, giving cat's-eye PSFs in the corners",
    )
    vignetting_radius_ratio: float = Field(
        1.0, gt=0, description="radius of the clipping circle relative to the pupil radius"
    )
    spherical_mm: float = Field(
        0.0,
        description="spherical aberration: a ray through pupil radius rho focuses at "
        "z_f + spherical_mm * (rho / rho_max)^2, mm",
    )
    coma_mm: float = Field(
        0.0,
        description="coma: the aim point of a ray through pupil radius rho is displaced "
        "laterally by coma_mm * (rho / rho_max)^2 per unit tan(field angle), mm",
    )
    samples: int = Field(64, ge=1, description="aperture samples per pixel (Vogel spiral)")

    @property
    def pupil_radius_mm(self) -> float:
        return 0.5 * self.pupil_diameter_mm

    def transmission(self, xy_n: np.ndarray, pupil_xy_mm: np.ndarray) -> np.ndarray:
        """1 where a pupil point (n, K, 2) mm passes the field-shifted clipping circle, else 0."""
        centre = self.vignetting_shift_mm * np.asarray(xy_n)[:, None, :]
        r_clip = self.vignetting_radius_ratio * self.pupil_radius_mm
        inside = np.sum((pupil_xy_mm - centre) ** 2, axis=-1) <= r_clip**2
        return inside.astype(np.float64)

    def bundle_from_pupil(
        self, xy_n: np.ndarray, unit_disk: np.ndarray
    ) -> RayBundle:
        """Bundle through the given unit-disk pupil samples (K, 2) with equal area weights."""
        xy_n = np.asarray(xy_n, dtype=np.float64).reshape(-1, 2)
        n, k = len(xy_n), len(unit_disk)
        rho2 = np.sum(unit_disk**2, axis=1)  # (K,) in units of rho_max^2
        pupil = np.broadcast_to(unit_disk * self.pupil_radius_mm, (n, k, 2))
        z_aim = self.focus_distance_mm + self.spherical_mm * rho2  # (K,)
        aim = np.empty((n, k, 3))
        aim[..., :2] = xy_n[:, None, :] * z_aim[None, :, None]
        aim[..., :2] += self.coma_mm * rho2[None, :, None] * xy_n[:, None, :]
        aim[..., 2] = z_aim[None, :]
        weights = self.transmission(xy_n, pupil) / k
        return _rays_through_focus(pupil, aim, weights)

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        return self.bundle_from_pupil(xy_n, sunflower_disk(self.samples))


class GaussianLens(BaseModel):
    """Position-invariant Gaussian defocus (OPTICS.md section 7): the thin-lens ray geometry
    with Gaussian aperture weights of standard deviation ``sigma_mm`` on the pupil plane."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = Field("gaussian", pattern="^gaussian$")
    sigma_mm: float = Field(ge=0, description="std of the aperture weight distribution, mm")
    focus_distance_mm: float = Field(gt=0, description="distance of the plane in focus, mm")
    samples: int = Field(64, ge=1, description="aperture samples per pixel")
    extent_sigmas: float = Field(3.0, gt=0, description="samples cover this many sigmas")

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        xy_n = np.asarray(xy_n, dtype=np.float64).reshape(-1, 2)
        n = len(xy_n)
        disk = sunflower_disk(self.samples) * self.extent_sigmas
        w = np.exp(-0.5 * np.sum(disk**2, axis=1))
        w /= w.sum()
        disk = disk / np.sqrt(0.5 * np.sum(w[:, None] * disk**2))  # per-axis variance 1 exactly
        pupil = np.broadcast_to(disk * self.sigma_mm, (n, self.samples, 2))
        aim = np.empty((n, self.samples, 3))
        aim[..., :2] = xy_n[:, None, :] * self.focus_distance_mm
        aim[..., 2] = self.focus_distance_mm
        return _rays_through_focus(pupil, aim, np.broadcast_to(w, (n, self.samples)).copy())
