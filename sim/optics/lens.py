"""Lens models: each turns camera pixels into a bundle of weighted rays in the camera frame.

Every model answers ``bundle(xy_n, uv) -> RayBundle`` where ``xy_n`` are the pixels'
undistorted normalised coordinates (see ``sim.optics.projection.pixel_to_normalized``; distortion
lives there, not here) and ``uv`` their pixel coordinates (used by models that vary per
pixel). Rays start on the aperture plane ``z = 0`` of the camera frame (docs/optics.md section 3):
ray k leaves ``(x_k, y_k, 0)`` and passes through the pixel's in-focus point
``(x_n z_f, y_n z_f, z_f)``. Lengths in mm.

The ground-truth lens of the fakes (docs/optics.md section 9) is ``AberratedLens``; the virtual
scanner renders with the same class, so there is one implementation.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sim.errors import SimInputError

GOLDEN_ANGLE_RAD = np.pi * (3.0 - np.sqrt(5.0))


@dataclass(frozen=True)
class RayBundle:
    """Rays of n pixels, K samples each, in the camera frame.

    origins : (n, K, 3) float64, mm, on the aperture plane z = 0 (may be a read-only
        broadcast view where every pixel shares its aperture samples).
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
        raise SimInputError(f"sunflower_disk needs n >= 1 samples, got {n}")
    return _sunflower(n).copy()


@lru_cache(maxsize=16)
def _sunflower(n: int) -> np.ndarray:
    """``sunflower_disk(n)``, computed once: a read-only array."""
    k = np.arange(n, dtype=np.float64)
    r = np.sqrt((k + 0.5) / n)
    t = k * GOLDEN_ANGLE_RAD
    disk = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    disk.flags.writeable = False
    return disk


def hit_plane(bundle_origins: np.ndarray, directions: np.ndarray, z_mm: float) -> np.ndarray:
    """Points (..., 2) where rays meet the plane ``z = z_mm`` of their own frame."""
    t = (z_mm - bundle_origins[..., 2]) / directions[..., 2]
    return bundle_origins[..., :2] + t[..., None] * directions[..., :2]


def _aimed_directions(xy_n: np.ndarray, pupil: np.ndarray, z_aim: np.ndarray,
                      coma: np.ndarray, out: np.ndarray) -> None:
    """Unit directions (n, K, 3) into ``out`` of rays from the aperture points ``pupil`` (K, 2)
    mm (z = 0) through the aim points ``(x z_k + c_k x, y z_k + c_k y, z_k)`` of pixels with
    normalised coordinates ``xy_n`` (n, 2), for per-sample aim depths ``z_aim`` and lateral
    factors ``coma`` (K,): ``sim.optics.lens_kernels.aimed_directions``, a compiled loop (imported
    here on first use, so importing this module does not load numba)."""
    from sim.optics.lens_kernels import aimed_directions

    aimed_directions(xy_n, pupil, z_aim, coma, out)


def _shared_origins(pupil_xy_mm: np.ndarray, n: int) -> np.ndarray:
    """Origins (n, K, 3) of aperture points (K, 2) shared by n pixels: a read-only view."""
    o = np.zeros((len(pupil_xy_mm), 3))
    o[:, :2] = pupil_xy_mm
    return _repeated(o, n)


def _repeated(a: np.ndarray, n: int) -> np.ndarray:
    """``a`` (contiguous) n times along a new first axis: a read-only view (stride 0)."""
    view = np.ndarray((n,) + a.shape, a.dtype, a, strides=(0,) + a.strides)
    view.flags.writeable = False
    return view


class PinholeLens(BaseModel):
    """One ray per pixel from the optical centre, weight 1."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = Field("pinhole", pattern="^pinhole$")

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        xy_n = np.ascontiguousarray(xy_n, dtype=np.float64).reshape(-1, 2)
        n = len(xy_n)
        d = np.empty((n, 1, 3))
        _aimed_directions(xy_n, np.zeros((1, 2)), np.ones(1), np.zeros(1), d)
        return RayBundle(_shared_origins(np.zeros((1, 2)), n), d, np.ones((n, 1)))


class AberratedLens(BaseModel):
    """Thin lens with a circular entrance pupil, field-dependent vignetting, spherical
    aberration and coma: the ground-truth lens of the fakes (docs/optics.md section 9).

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
    edge: Literal["hard", "soft"] = Field(
        "hard", description="how a sample meets the clipping circle: 'hard' (weight 1 inside, "
        "0 outside) or 'soft' (weight ramps from 1 to 0 over one sample spacing across the "
        "circle: the fraction of the sample's cell inside, to first order); 'soft' moves the "
        "weights continuously with the field and converges far faster, to the same limit")

    @property
    def pupil_radius_mm(self) -> float:
        return 0.5 * self.pupil_diameter_mm

    def transmission(self, xy_n: np.ndarray, pupil_xy_mm: np.ndarray) -> np.ndarray:
        """1 where a pupil point (n, K, 2) mm passes the field-shifted clipping circle, else 0
        (``edge = "soft"``: a linear ramp of width ``pupil radius sqrt(pi / K)``, one sample
        spacing, across the circle). ``pupil_xy_mm`` may also be (K, 2), the same points for
        every pixel."""
        xy_n = np.asarray(xy_n, dtype=np.float64).reshape(-1, 2)
        pupil = np.asarray(pupil_xy_mm, dtype=np.float64)
        r_clip = self.vignetting_radius_ratio * self.pupil_radius_mm
        shape = (len(xy_n),) + pupil.shape[-2:-1]
        if self.vignetting_shift_mm == 0 and pupil.ndim == 2:  # the same for every pixel
            inside = self._inside(np.sum(pupil**2, axis=-1), r_clip, pupil)
            return np.broadcast_to(inside, shape).copy()
        cx = self.vignetting_shift_mm * xy_n[:, 0, None]
        cy = self.vignetting_shift_mm * xy_n[:, 1, None]
        ex, ey = pupil[..., 0] - cx, pupil[..., 1] - cy
        return self._inside(ex * ex + ey * ey, r_clip, pupil)

    def _inside(self, r2: np.ndarray, r_clip: float, pupil: np.ndarray) -> np.ndarray:
        """Transmission (float64) of pupil points (..., K, 2) at squared distance ``r2`` from
        the clip centre. Soft: the fraction of a sample's cell (one spacing wide) inside the
        clip circle, over the fraction inside the pupil (the samples already tile the pupil,
        so a rim sample is cut only where the clip circle runs inside the pupil's rim)."""
        if self.edge == "hard":
            return (r2 <= r_clip**2).astype(np.float64)
        spacing = self.pupil_radius_mm * np.sqrt(np.pi / pupil.shape[-2])
        clip = np.clip(0.5 + (r_clip - np.sqrt(r2)) / spacing, 0.0, 1.0)
        rim = np.clip(0.5 + (self.pupil_radius_mm - np.hypot(pupil[..., 0], pupil[..., 1]))
                      / spacing, 0.5, 1.0)
        return np.minimum(clip / rim, 1.0)

    def bundle_from_pupil(
        self, xy_n: np.ndarray, unit_disk: np.ndarray
    ) -> RayBundle:
        """Bundle through the given unit-disk pupil samples (K, 2) with equal area weights."""
        xy_n = np.ascontiguousarray(xy_n, dtype=np.float64).reshape(-1, 2)
        pupil, origins, z_aim, coma, w = _pupil_rule(self, np.asarray(unit_disk, dtype=np.float64))
        n, k = len(xy_n), len(pupil)
        d = np.empty((n, k, 3))
        _aimed_directions(xy_n, pupil, z_aim, coma, d)
        if w is None:  # vignetting moves with the field
            w = self.transmission(xy_n, pupil) / k
        else:
            w = np.repeat(w[None], n, axis=0)
        return RayBundle(_repeated(origins, n), d, w)

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        return self.bundle_from_pupil(xy_n, _sunflower(self.samples))


def _pupil_rule(lens: AberratedLens, unit_disk: np.ndarray) -> tuple:
    """What does not depend on the pixel, for unit-disk samples (K, 2): aperture points (K, 2)
    mm and as ray origins (K, 3), aim depths ``z_f + spherical rho^2`` (K,), coma factors
    ``coma rho^2`` (K,), and the weights (K,) ``transmission / K`` when the clipping circle
    does not move with the field (else None). Cached for the lens's own samples
    (``_sunflower``)."""
    if unit_disk is _sunflower(lens.samples):
        return _own_pupil_rule(lens)
    return _compute_pupil_rule(lens, unit_disk)


@lru_cache(maxsize=16)
def _own_pupil_rule(lens: AberratedLens) -> tuple:
    """``_pupil_rule`` of the lens's own samples, computed once per lens."""
    return _compute_pupil_rule(lens, _sunflower(lens.samples))


def _compute_pupil_rule(lens: AberratedLens, unit_disk: np.ndarray) -> tuple:
    """``_pupil_rule``, computed (arrays made read-only: they may be cached)."""
    rho2 = np.sum(unit_disk**2, axis=1)  # (K,) in units of rho_max^2
    pupil = np.ascontiguousarray(unit_disk * lens.pupil_radius_mm)
    z_aim = lens.focus_distance_mm + lens.spherical_mm * rho2
    w = None
    if lens.vignetting_shift_mm == 0:
        w = lens.transmission(np.zeros((1, 2)), pupil)[0] / len(pupil)
    origins = np.zeros((len(pupil), 3))
    origins[:, :2] = pupil
    out = (pupil, origins, z_aim, lens.coma_mm * rho2, w)
    for a in out:
        if a is not None:
            a.flags.writeable = False
    return out


class GaussianLens(BaseModel):
    """Position-invariant Gaussian defocus (docs/optics.md section 4): the thin-lens ray geometry
    with Gaussian aperture weights of standard deviation ``sigma_mm`` on the pupil plane."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: str = Field("gaussian", pattern="^gaussian$")
    sigma_mm: float = Field(ge=0, description="std of the aperture weight distribution, mm")
    focus_distance_mm: float = Field(gt=0, description="distance of the plane in focus, mm")
    samples: int = Field(64, ge=1, description="aperture samples per pixel")
    extent_sigmas: float = Field(3.0, gt=0, description="samples cover this many sigmas")

    def bundle(self, xy_n: np.ndarray, uv: np.ndarray | None = None) -> RayBundle:
        xy_n = np.ascontiguousarray(xy_n, dtype=np.float64).reshape(-1, 2)
        n = len(xy_n)
        disk = _sunflower(self.samples) * self.extent_sigmas
        w = np.exp(-0.5 * np.sum(disk**2, axis=1))
        w /= w.sum()
        disk = disk / np.sqrt(0.5 * np.sum(w[:, None] * disk**2))  # per-axis variance 1 exactly
        pupil = np.ascontiguousarray(disk * self.sigma_mm)
        d = np.empty((n, self.samples, 3))
        _aimed_directions(xy_n, pupil, np.full(self.samples, self.focus_distance_mm),
                          np.zeros(self.samples), d)
        return RayBundle(_shared_origins(pupil, n), d,
                         np.broadcast_to(w, (n, self.samples)).copy())
