"""From an LTC volume to a measured lens (OPTICS.md section 6), and the choices it makes.

Steps: centroids (``station.lens.centroids``) -> principal rays and their intersection
(``station.lens.rays``) -> focus plane from LTC size -> optical centre -> every node
pixel's LTC at each depth scaled onto the aperture plane and fused (``station.lens.aperture``) ->
K samples -> ``sim.optics.measured_lens.MeasuredLens``.

**Focus.** The LTC's second moment, less the known blurs (LCD pixel ``pitch^2/12`` and the
camera pixel's footprint ``(d/f)^2/12`` per axis), is quadratic in depth for a thin lens
(spherical aberration included: each ray's offset is linear in depth); its vertex is the
pixel's focus plane ``Z_F`` (the plane of least blur). The lens's ``Z_F`` is the median over
pixels. A configured focus distance ``z_f`` (from the optical centre) is reported beside the
fitted ``Z_F - z_O`` and, when given, used.

**Which optical centre.** A pixel's LTC centroid follows the centroid of its *clipped*
pupil. With vignetting that shifts with the field (cat's eyes), the centroid rays cross the
pupil plane at ``p_n ~ field``, so all of them converge on the axis behind the pupil (34 mm
on the small fake bench), near as well as far from the axis: no weighting fixes it, and rays
alone cannot fix it either (a field-shifted clipping circle is a second stop in another
plane, and two stops give the same rays whichever is called the pupil). The simulator casts
pixel n's rays through ``O + z_f (x_n, y_n, 1)`` with ``x_n`` from the camera matrix K, so
the centre it needs is the one from which the in-focus points are seen in K's directions.
With K known, that is what is estimated (``pinhole_centre``): the principal rays at the focus
plane give each pixel's in-focus point (every ray of the pixel passes there, clipped or
not), whose spread over the sensor is ``z_f`` times that of K's directions; the centre lies
``z_f`` before the focus plane, on the axis through the principal-ray intersection. Without
K the principal-ray intersection (the paper's definition) is used, and the report says so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sim.optics.projection import pixel_to_normalized
from station.lens.centroids import Centroids, compute_centroids
from station.ltc.store import LtcVolume
from station.lens.rays import (
    HUBER_K,
    OpticalCentre,
    PrincipalRays,
    RayFitError,
    fit_principal_rays,
    intersect_rays,
)

LCD_BIN_VAR = 1.0 / 12.0  # variance of an LCD pixel box, pitch^2
TRACE_REL_FLOOR = 0.01  # relative error floor of an LTC second moment in the focus fit


class LensFitError(ValueError):
    """The lens cannot be derived; the message says which input and why."""


class LensFitConfig(BaseModel):
    """Options of the lens derivation."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    samples: int = Field(32, ge=1, le=4096, description="aperture samples K per node")
    grid_step: int = Field(1, ge=1, description="node spacing, camera pixels (1: every pixel)")
    interpolation: Literal["nearest", "bilinear"] = Field(
        "bilinear", description="how the simulator reads samples between nodes")
    aperture_cells: int = Field(32, ge=8, le=256, description="aperture grid cells per side")
    supersample: int = Field(2, ge=1, le=8, description="sub-samples per cell and axis")
    focus_distance_mm: float | None = Field(
        None, gt=0, description="configured focus distance from the optical centre, mm; "
        "used instead of the fitted one when given (both are reported)")
    centre_method: Literal["auto", "pinhole", "rays"] = Field(
        "auto", description="optical centre: 'pinhole' (needs K), 'rays' (principal-ray "
        "intersection), 'auto' (pinhole when K is known)")
    min_depths: int = Field(3, ge=2, description="depths with signal a ray needs")
    outlier_sigma: float = Field(6.0, gt=0, description="outlier threshold, normalised residual")
    max_outliers: int = Field(1, ge=0, description="outlier depths dropped per pixel at most")
    ray_floor_mm: float = Field(0.005, gt=0, description="centroid error floor, mm")
    deblur: bool = Field(True, description="remove the known LCD-pixel and camera-pixel box "
                         "variances from the samples' second moments")
    kmeans_iterations: int = Field(30, ge=1, description="Lloyd iterations")
    nodes_per_chunk: int = Field(64, ge=1, description="node pixels processed together")


@dataclass(frozen=True)
class FocusFit:
    """plane_z_mm : station z of the focus plane; plane_std_mm : its standard error;
    per_pixel_z_mm : (N,) vertices (NaN where not fitted); spread_mm : robust std of those."""

    plane_z_mm: float
    plane_std_mm: float
    per_pixel_z_mm: np.ndarray
    spread_mm: float


def footprint_mm(depths_mm: np.ndarray, centre_z_mm: float, K: np.ndarray | None) -> np.ndarray:
    """Camera-pixel footprint on the LCD (D,) mm: distance / focal length in pixels (0 if no K)."""
    if K is None:
        return np.zeros(len(depths_mm))
    f = np.sqrt(K[0, 0] * K[1, 1])
    return np.abs(np.asarray(depths_mm) - centre_z_mm) / f


def fit_focus_plane(c: Centroids, usable: np.ndarray, centre_z_mm: float,
                    K: np.ndarray | None) -> FocusFit | None:
    """Per-pixel quadratic fit of the de-blurred LTC second moment over depth; None if fewer
    than 3 depths or no pixel gives a minimum."""
    d = len(c.depths_mm)
    if d < 3:
        return None
    p2 = c.pitch_mm**2
    fp = footprint_mm(c.depths_mm, centre_z_mm, K)
    tr = (c.moments_px2[..., 0] + c.moments_px2[..., 1]).reshape(d, -1) * p2
    tr = tr - 2 * LCD_BIN_VAR * p2 - 2 * (fp**2 / 12.0)[:, None]
    var = (c.trace_std_px2.reshape(d, -1) * p2) ** 2 + (TRACE_REL_FLOOR * tr) ** 2 + 1e-12
    ok = c.valid.reshape(d, -1) & usable[None] & np.isfinite(tr)
    w = np.where(ok, 1.0 / var, 0.0)
    z0 = float(np.mean(c.depths_mm))
    dz = (c.depths_mm - z0)[:, None]
    a = np.broadcast_to(np.concatenate([np.ones_like(dz), dz, dz**2], axis=1)[:, None, :],
                        (d, w.shape[1], 3))  # design (D, N, 3): 1, dz, dz^2
    ata = np.einsum("dn,dni,dnj->nij", w, a, a)
    atb = np.einsum("dn,dni,dn->ni", w, a, np.where(ok, tr, 0.0))
    good = ok.sum(axis=0) >= 3
    ata[~good] = np.eye(3)
    coef = np.linalg.solve(ata, atb[..., None])[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = z0 - coef[:, 1] / (2 * coef[:, 2])
    span = np.ptp(c.depths_mm)
    good &= (coef[:, 2] > 0) & (np.abs(vertex - z0) < 2 * span)
    z = np.where(good, vertex, np.nan)
    if not good.any():
        return None
    zg = z[good]
    med = float(np.median(zg))
    spread = float(1.4826 * np.median(np.abs(zg - med)))
    return FocusFit(med, 1.2533 * spread / np.sqrt(len(zg)), z, spread)


def pinhole_centre(rays: PrincipalRays, usable: np.ndarray, uv: np.ndarray, K: np.ndarray,
                   dist: np.ndarray | None, focus_plane_z_mm: float,
                   focus_plane_var_mm2: float, axis: OpticalCentre,
                   iterations: int = 20) -> tuple[OpticalCentre, np.ndarray]:
    """Optical centre consistent with K (see the module docstring).

    The in-focus points ``A_n`` (principal rays at the focus plane ``Z_F``) must be the
    pixels' directions ``x_n`` (from K) scaled by z_f about the axis, up to a roll phi:
    ``A_n = o + z_f Rot(phi) x_n``, linear in ``(o_x, o_y, z_f cos phi, z_f sin phi)``
    (robust: Huber-reweighted). The centre is at ``z = Z_F - z_f`` on the axis through the
    principal-ray intersection ``axis`` (its x, y; a camera tilt would enter ``o`` with a
    lever of z_f, and only 34 mm x tilt into the intersection). Covariance: x, y from the
    intersection, z from the fit's residuals plus the focus-plane variance propagated.
    Returns the centre and the rotation (3, 3) from station to camera axes (the roll).
    """
    idx = np.flatnonzero(usable)
    if len(idx) < 3:
        raise RayFitError(f"pinhole optical centre: {len(idx)} usable principal rays; need >= 3")
    xn = pixel_to_normalized(uv[idx], K, dist)
    n = len(idx)
    a = np.zeros((2 * n, 4))
    a[0::2, 0] = 1.0
    a[1::2, 1] = 1.0
    a[0::2, 2], a[0::2, 3] = xn[:, 0], -xn[:, 1]
    a[1::2, 2], a[1::2, 3] = xn[:, 1], xn[:, 0]
    data = rays.xy_at(focus_plane_z_mm)[idx].ravel()
    slope = rays.slope[idx].ravel()  # d data / d Z_F
    prior = np.repeat(1.0 / rays.var_at(focus_plane_z_mm)[idx], 2)
    robust = np.ones(2 * n)
    for _ in range(iterations):
        w = prior * robust
        ata = a.T @ (w[:, None] * a)
        theta = np.linalg.solve(ata, a.T @ (w * data))
        r = data - a @ theta
        dist_n = np.hypot(r[0::2], r[1::2])
        scaled = dist_n * np.sqrt(prior[0::2])
        scale = max(float(np.median(scaled)) / np.sqrt(np.log(4.0)), 1e-300)
        new = np.repeat(np.where(scaled <= HUBER_K * scale, 1.0,
                                 HUBER_K * scale / np.maximum(scaled, 1e-300)), 2)
        done = np.allclose(new, robust, atol=1e-10)
        robust = new
        if done:
            break
    w = prior * robust
    ata_inv = np.linalg.inv(a.T @ (w[:, None] * a))
    s2 = float((w * r * r).sum()) / max(2 * n - 4, 1)
    ca, cb = theta[2], theta[3]
    z_f = float(np.hypot(ca, cb))
    jac = np.array([ca, cb]) / z_f
    var_zf = float(jac @ (s2 * ata_inv[2:, 2:]) @ jac)
    dtheta = ata_inv @ (a.T @ (w * slope))
    dz_o = 1.0 - float(jac @ dtheta[2:])
    cov = np.array(axis.covariance, dtype=np.float64, copy=True)
    cov[2, :] = cov[:, 2] = 0.0
    cov[2, 2] = var_zf + dz_o**2 * focus_plane_var_mm2
    o = np.array([axis.position[0], axis.position[1], focus_plane_z_mm - z_f])
    phi = float(np.arctan2(cb, ca))
    rot = np.array([[np.cos(phi), np.sin(phi), 0.0], [-np.sin(phi), np.cos(phi), 0.0],
                    [0.0, 0.0, 1.0]])
    weights = np.zeros(len(usable))
    weights[idx] = w[0::2]
    distance = np.full(len(usable), np.nan)
    distance[idx] = dist_n
    return OpticalCentre(o, cov, weights, distance, "pinhole: in-focus points vs K"), rot


@dataclass
class LensGeometry:
    """The lens's geometry as measured: rays, centre, focus (see ``fit_geometry``).

    centre : the chosen optical centre (station frame); rotation : (3, 3) station-to-camera
    axes (identity without K); focus_plane_z_mm : station z of the focus plane used;
    focus_distance_mm : ``focus_plane_z_mm - centre z`` (the lens model's z_f).
    """

    centroids: Centroids
    rays: PrincipalRays
    centre_rays: OpticalCentre
    centre_pinhole: OpticalCentre | None
    centre: OpticalCentre
    rotation: np.ndarray
    focus: FocusFit | None
    focus_distance_fit_mm: float | None
    focus_distance_config_mm: float | None
    focus_plane_z_mm: float
    camera_matrix: np.ndarray | None
    dist_coeffs: np.ndarray | None
    camera_size: tuple[int, int]
    notes: list[str] = field(default_factory=list)

    @property
    def focus_distance_mm(self) -> float:
        return float(self.focus_plane_z_mm - self.centre.position[2])


def _focus_plane(fit: FocusFit | None, z_f_config: float | None, centre_z: float,
                 name: str) -> tuple[float, float]:
    if z_f_config is not None:
        return centre_z + z_f_config, 0.0
    if fit is None:
        raise LensFitError(f"{name}: the focus distance cannot be fitted (needs >= 3 depths "
                           "and LTC sizes that shrink towards a focus); give focus_distance_mm "
                           "(--focus-mm)")
    return fit.plane_z_mm, fit.plane_std_mm**2


def fit_geometry(volume: LtcVolume, config: LensFitConfig | None = None,
                 K: np.ndarray | None = None, dist: np.ndarray | None = None) -> LensGeometry:
    """Centroids, principal rays, focus plane and optical centre of an LTC volume.

    K, dist : camera matrix and distortion; default: the volume's (``camera_matrix``).
    """
    cfg = config or LensFitConfig()
    K = volume.camera_matrix if K is None else np.asarray(K, dtype=np.float64)
    dist = volume.dist_coeffs if dist is None else dist
    if cfg.centre_method == "pinhole" and K is None:
        raise LensFitError(f"{volume.name}: centre_method 'pinhole' needs the camera matrix K "
                           "(store attribute camera_matrix, or --rig)")
    c = compute_centroids(volume)
    d = len(c.depths_mm)
    pts = c.points_mm().reshape(d, -1, 3)
    rays = fit_principal_rays(pts, c.std_mm().reshape(d, -1, 2), c.valid.reshape(d, -1),
                              min_depths=min(cfg.min_depths, d), outlier_sigma=cfg.outlier_sigma,
                              max_outliers=cfg.max_outliers, floor_mm=cfg.ray_floor_mm)
    usable = rays.usable
    notes: list[str] = []
    try:
        centre_rays = intersect_rays(rays)
    except RayFitError as exc:
        raise LensFitError(f"{volume.name}: {exc}") from exc
    z_c = float(centre_rays.position[2])
    fit = fit_focus_plane(c, usable, z_c, K)
    zf_cfg = cfg.focus_distance_mm
    plane, plane_var = _focus_plane(fit, zf_cfg, z_c, volume.name)
    centre, rot, pin = centre_rays, np.eye(3), None
    use_pinhole = K is not None and cfg.centre_method != "rays"
    if use_pinhole:
        w, h = volume.camera_size
        v, u = np.divmod(np.arange(w * h), w)
        uv = np.stack([u, v], axis=1).astype(np.float64)  # flat pixel order of the rays
        try:
            for _ in range(30):  # fixed point: footprint and z_f depend on the centre
                pin, rot = pinhole_centre(rays, usable, uv, K, dist, plane, plane_var,
                                          centre_rays)
                fit = fit_focus_plane(c, usable, float(pin.position[2]), K)
                new_plane, plane_var = _focus_plane(fit, zf_cfg, float(pin.position[2]),
                                                    volume.name)
                moved = abs(new_plane - plane)
                plane = new_plane
                if moved < 1e-9:
                    break
            pin, rot = pinhole_centre(rays, usable, uv, K, dist, plane, plane_var, centre_rays)
        except RayFitError as exc:
            raise LensFitError(f"{volume.name}: {exc}") from exc
        centre = pin
    else:
        if K is None:
            notes.append("no camera matrix: optical centre is the principal-ray intersection, "
                         "which vignetting pulls behind the pupil; give K for a centre "
                         "consistent with the simulator's pixel directions")
    zf_fit = None if fit is None else float(fit.plane_z_mm - centre.position[2])
    if zf_cfg is not None and zf_fit is not None:
        notes.append(f"focus distance: configured {zf_cfg:.3f} mm (used), fitted "
                     f"{zf_fit:.3f} mm")
    return LensGeometry(c, rays, centre_rays, pin, centre, rot, fit, zf_fit, zf_cfg, plane,
                        K, None if dist is None else np.asarray(dist, dtype=np.float64),
                        volume.camera_size, notes)
