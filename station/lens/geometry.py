"""The lens's geometry from an LTC volume (docs/optics.md section 6): principal rays -> optical
centre -> focus plane, as a ``LensGeometry``.

This module's line: it measures where the lens is and where it focuses, nothing of its
aperture. Steps: centroids (``station.lens.centroids``) -> principal rays
(``station.lens.rays``) -> optical centre (``station.lens.centre``: the principal-ray
intersection, or with K the pinhole centre) -> focus plane from the LTC sizes. What the
lens does with the light (each pixel's LTC seen from the optical centre, the aperture
samples) and the lens model file are ``station.lens.derive``.

**Focus.** The LTC's second moment, less the known blurs (LCD pixel ``pitch^2/12`` and the
camera pixel's footprint ``(d/f)^2/12`` per axis), is quadratic in depth for a thin lens
(spherical aberration included: each ray's offset is linear in depth); its vertex is the
pixel's focus plane ``Z_F`` (the plane of least blur). The lens's ``Z_F`` is the median over
pixels. A configured focus distance ``z_f`` (from the optical centre) is reported beside the
fitted ``Z_F - z_O`` and, when given, used. The centre and the focus plane depend on each
other with K (the footprint blur and ``z_f``), so ``fit_geometry`` iterates them to a fixed
point.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sim.optics.projection import pixel_to_normalized
from station.errors import StationError
from station.lens.centre import OpticalCentre, intersect_rays, pinhole_centre
from station.lens.centroids import STATUS_OK, Centroids
from station.lens.rays import PrincipalRays, RayFitError, fit_principal_rays
from station.ltc.store import LtcVolume

if TYPE_CHECKING:
    from station.compute import Engine

LCD_BIN_VAR = 1.0 / 12.0  # variance of an LCD pixel box, pitch^2
TRACE_REL_FLOOR = 0.01  # relative error floor of an LTC second moment in the focus fit
RAY_FIT_PIXELS = 1 << 16  # pixels per block of the focus fit and K directions (~1 kB each)


class LensFitError(StationError, ValueError):
    """The lens cannot be derived; the message says which input and why."""


class LensFitConfig(BaseModel):
    """Options of the lens derivation. The defaults are the recommended settings (K = 256
    samples on nodes every 4 px, a 64-cell aperture grid, the samples drawn from the deblurred
    and support-cut aperture distribution, a focus per pupil zone and each node's aim offset:
    docs/decisions/0025-recommended-lens-settings.md); ``LensFitConfig.basic()`` is the plain
    derivation without the refinements."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    samples: int = Field(256, ge=1, le=4096, description="aperture samples K per node")
    grid_step: int = Field(4, ge=1, description="node spacing, camera pixels (1: every pixel)")
    interpolation: Literal["nearest", "bilinear"] = Field(
        "bilinear", description="how the simulator reads samples between nodes")
    aperture_cells: int = Field(64, ge=8, le=256, description="aperture grid cells per side")
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
    ray_window_px: int = Field(4, ge=0, description="the aperture samples' centroid is the "
                               "principal ray on the optical centre's plane, fitted as a local "
                               "plane over the pixels within this many pixels (0: the pixel's "
                               "own ray)")
    deblur: bool = Field(True, description="remove the known LCD-pixel and camera-pixel box "
                         "variances from the samples' second moments")
    deconvolve_iterations: int = Field(20, ge=0, le=1000, description="Richardson-Lucy "
                                       "steps removing the known LCD-pixel and camera-pixel "
                                       "blur from the fused aperture distribution before the "
                                       "samples are drawn (aperture.deblur; about 0.5 ms per "
                                       "node); 0: off")
    support_floor: float = Field(0.1, ge=0, lt=1, description="before the samples are "
                                 "drawn, the fused aperture distribution is cut to its main "
                                 "body: the connected cells above this fraction of its largest "
                                 "cell (aperture.support_floor); 0: only negative noise cut")
    focus_zones: bool = Field(True, description="fit a focus distance per pupil zone "
                              "(spherical aberration) from the LTCs at the optical centre, "
                              "map every LTC onto the aperture plane through it, refit the "
                              "optical centre with the zones' misses of the pinhole points "
                              "removed (not with centre_method 'rays'), and store it as the lens "
                              "file's focus_zones_mm "
                              "(needs K; without K: one focus)")
    aim_offset_sigma_px: float = Field(8.0, ge=0, description="give each node the aim "
                                       "offset (the lens file's aim_offset) that makes its "
                                       "principal ray's slope the station's measured one "
                                       "(local-plane fits over ray_window_px), smoothed over "
                                       "this many pixels (Gaussian sigma) and without its "
                                       "mean over the sensor (a uniform offset is the camera "
                                       "matrix's, not the lens's); needs K; 0: off (every "
                                       "principal ray passes its pixel's pinhole point at the "
                                       "focus plane)")
    pixel_samples: int = Field(0, ge=0, le=16, description="how a camera pixel integrates "
                               "its footprint on the LCD in the focus-zone fit: 0 a box (a "
                               "real camera), n an n x n grid of points (a simulated camera "
                               "rendered with n x n subpixels)")
    nodes_per_chunk: int = Field(256, ge=1, description="node pixels processed together")

    @classmethod
    def basic(cls, **fields: Any) -> LensFitConfig:
        """The plain derivation (K = 32 samples at every pixel, a 32-cell aperture grid, no
        deconvolution or support cut, one focus, no aim offsets) with ``fields`` on top."""
        plain: dict[str, Any] = {"samples": 32, "grid_step": 1, "aperture_cells": 32,
                                 "deconvolve_iterations": 0, "support_floor": 0.0,
                                 "focus_zones": False, "aim_offset_sigma_px": 0.0}
        return cls(**{**plain, **fields})


@dataclass(frozen=True)
class FocusFit:
    """plane_z_mm : station z of the focus plane; plane_std_mm : its standard error;
    spread_mm : robust std of the pixels' vertices."""

    plane_z_mm: float
    plane_std_mm: float
    spread_mm: float


def footprint_mm(depths_mm: np.ndarray, centre_z_mm: float, K: np.ndarray | None,
                 pixel_samples: int = 0) -> np.ndarray:
    """Camera-pixel footprint on the LCD (D,) mm: distance / focal length in pixels (0 if no
    K), as the width of the box with the pixel's blur variance: the footprint itself for a
    box pixel (``pixel_samples = 0``), ``sqrt(1 - 1/n^2)`` of it for a pixel sampled as an
    n x n point grid (``LensFitConfig.pixel_samples``)."""
    if K is None:
        return np.zeros(len(depths_mm))
    f = np.sqrt(K[0, 0] * K[1, 1])
    shrink = 1.0 if pixel_samples == 0 else np.sqrt(1.0 - 1.0 / pixel_samples**2)
    return shrink * np.abs(np.asarray(depths_mm) - centre_z_mm) / f


def fit_focus_plane(c: Centroids, usable: np.ndarray, centre_z_mm: float,
                    K: np.ndarray | None, pixel_samples: int = 0) -> FocusFit | None:
    """Per-pixel quadratic fit of the de-blurred LTC second moment over depth (in pixel
    blocks of ``RAY_FIT_PIXELS``: temporaries do not grow with the sensor); None if fewer
    than 3 depths or no pixel gives a minimum."""
    d = len(c.depths_mm)
    if d < 3:
        return None
    p2 = c.pitch_mm**2
    fp = footprint_mm(c.depths_mm, centre_z_mm, K, pixel_samples)
    z0 = float(np.mean(c.depths_mm))
    dz = (c.depths_mm - z0)[:, None]
    span = np.ptp(c.depths_mm)
    if c.trace_std_px2 is None:
        raise ValueError("fit_focus_plane: centroids without trace_std_px2")
    mom = c.moments_px2.reshape(d, -1, 3)
    tstd = c.trace_std_px2.reshape(d, -1)
    status = c.status.reshape(d, -1)
    n = mom.shape[1]
    zg = np.empty(n)  # the vertices found, in float64 for the median, packed at the front
    at = 0
    for a0 in range(0, n, RAY_FIT_PIXELS):
        sl = slice(a0, min(n, a0 + RAY_FIT_PIXELS))
        tr = (mom[:, sl, 0] + mom[:, sl, 1]) * p2
        tr = tr - 2 * LCD_BIN_VAR * p2 - 2 * (fp**2 / 12.0)[:, None]
        var = (tstd[:, sl] * p2) ** 2 + (TRACE_REL_FLOOR * tr) ** 2 + 1e-12
        ok = (status[:, sl] == STATUS_OK) & usable[None, sl] & np.isfinite(tr)
        w = np.where(ok, 1.0 / var, 0.0)
        a = np.broadcast_to(np.concatenate([np.ones_like(dz), dz, dz**2], axis=1)[:, None, :],
                            (d, w.shape[1], 3))  # design (D, n, 3): 1, dz, dz^2
        ata = np.einsum("dn,dni,dnj->nij", w, a, a)
        atb = np.einsum("dn,dni,dn->ni", w, a, np.where(ok, tr, 0.0))
        good = ok.sum(axis=0) >= 3
        ata[~good] = np.eye(3)
        coef = np.linalg.solve(ata, atb[..., None])[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            vertex = z0 - coef[:, 1] / (2 * coef[:, 2])
        good &= (coef[:, 2] > 0) & (np.abs(vertex - z0) < 2 * span)
        got = vertex[good]
        zg[at:at + len(got)] = got
        at += len(got)
    if not at:
        return None
    zg = zg[:at]
    # medians of the values and of their deviations, each partitioning zg in place (a
    # median does not depend on the order)
    med = float(np.median(zg, overwrite_input=True))
    np.subtract(zg, med, out=zg)
    np.abs(zg, out=zg)
    spread = float(1.4826 * np.median(zg, overwrite_input=True))
    return FocusFit(med, 1.2533 * spread / np.sqrt(at), spread)


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

    def known_camera_matrix(self) -> np.ndarray:
        """The camera matrix K (3, 3) px; a step that needs it refuses a geometry without."""
        if self.camera_matrix is None:
            raise LensFitError("this step needs the camera matrix K (store attribute "
                               "camera_matrix, or --rig)")
        return self.camera_matrix


def _focus_plane(fit: FocusFit | None, z_f_config: float | None, centre_z: float,
                 name: str) -> tuple[float, float]:
    if z_f_config is not None:
        return centre_z + z_f_config, 0.0
    if fit is None:
        raise LensFitError(f"{name}: the focus distance cannot be fitted (needs >= 3 depths "
                           "and LTC sizes that shrink towards a focus); give focus_distance_mm "
                           "(--focus-mm)")
    return fit.plane_z_mm, fit.plane_std_mm**2


def centroids_and_rays(volume: LtcVolume, cfg: LensFitConfig, progress: bool = False,
                       engine: Engine | None = None) -> tuple[Centroids, PrincipalRays]:
    """The centroid pass (``centroid_rows`` per depth of each stored chunk, on ``engine``)
    with each chunk's principal rays fitted as soon as all its depths have arrived (from
    the float64 centroids and their stds, which are then dropped): the geometry holds
    float32 moments and no centroids (``Centroids.xy_lcd_px`` and ``std_lcd_px`` are None:
    the rays and their residual lengths are what later steps read), so memory per pixel
    stays what the later fits need. Same values as ``compute_centroids`` then
    ``fit_principal_rays`` (rays are per pixel)."""
    from tqdm import tqdm

    from station.lens.centroids import STATUS_NO_SIGNAL, run_centroid_blocks

    d = len(volume.depths_mm)
    w, h = volume.camera_size
    chunks = getattr(volume.ltc, "chunks", None)
    rows = volume.chunk_rows
    cols = int(chunks[2]) if chunks else w
    f4 = np.float32
    out: dict[str, np.ndarray] = {"mom": np.full((d, h, w, 3), np.nan, f4),
                                  "tstd": np.full((d, h, w), np.nan, f4),
                                  "status": np.full((d, h, w), STATUS_NO_SIGNAL, dtype=np.int8)}
    rays = PrincipalRays.empty(d, w * h)
    z = volume.depths_mm.reshape(d, 1, 1)
    tasks = [(i, r0, min(h, r0 + rows), c0, min(w, c0 + cols))
             for r0 in range(0, h, rows) for c0 in range(0, w, cols) for i in range(d)]
    bar = tqdm(total=len(tasks), desc="lens: centroids", unit="block",
               disable=None if progress else True)
    waiting: dict[tuple[int, int], dict[int, dict]] = {}

    def on_result(key: tuple[int, int, int, int, int], part: dict[str, np.ndarray]) -> None:
        i, r0, r1, c0, c1 = key
        for name in out:
            out[name][i, r0:r1, c0:c1] = part[name]
        got = waiting.setdefault((r0, c0), {})
        got[i] = part
        bar.update()
        if len(got) < d:
            return
        del waiting[(r0, c0)]
        pix = (np.arange(r0, r1)[:, None] * w + np.arange(c0, c1)[None, :]).ravel()
        xy = np.stack([got[j]["xy"].reshape(-1, 2) for j in range(d)]) * volume.pitch_mm
        rays.put(pix, fit_principal_rays(
            np.concatenate([xy, np.broadcast_to(z, xy.shape[:2] + (1,))], axis=-1),
            # float32 stds, as compute_centroids holds them
            np.stack([got[j]["std"].reshape(-1, 2) for j in range(d)]).astype(np.float32)
            * volume.pitch_mm,
            np.stack([got[j]["status"].ravel() == STATUS_OK for j in range(d)]),
            min_depths=min(cfg.min_depths, d), outlier_sigma=cfg.outlier_sigma,
            max_outliers=cfg.max_outliers, floor_mm=cfg.ray_floor_mm))

    run_centroid_blocks(volume, tasks, on_result, engine, bar)
    c = Centroids(None, None, out["mom"], out["tstd"], out["status"],
                  volume.depths_mm.copy(), float(volume.pitch_mm))
    return c, rays


def fit_geometry(volume: LtcVolume, config: LensFitConfig | None = None,
                 K: np.ndarray | None = None, dist: np.ndarray | None = None,
                 progress: bool = False, engine: Engine | None = None) -> LensGeometry:
    """Centroids, principal rays, focus plane and optical centre of an LTC volume.

    K, dist : camera matrix and distortion; default: the volume's (``camera_matrix``).
    progress : a progress bar over the centroid pass; engine : where the centroid pass
    runs (``station.compute.Engine``; default: in this process).
    """
    cfg = config or LensFitConfig()
    K = volume.camera_matrix if K is None else np.asarray(K, dtype=np.float64)
    dist = volume.dist_coeffs if dist is None else dist
    if cfg.centre_method == "pinhole" and K is None:
        raise LensFitError(f"{volume.name}: centre_method 'pinhole' needs the camera matrix K "
                           "(store attribute camera_matrix, or --rig)")
    c, rays = centroids_and_rays(volume, cfg, progress=progress, engine=engine)
    usable = rays.usable
    notes: list[str] = []
    try:
        centre_rays = intersect_rays(rays)
    except RayFitError as exc:
        raise LensFitError(f"{volume.name}: {exc}") from exc
    z_c = float(centre_rays.position[2])
    fit = fit_focus_plane(c, usable, z_c, K, cfg.pixel_samples)
    zf_cfg = cfg.focus_distance_mm
    plane, plane_var = _focus_plane(fit, zf_cfg, z_c, volume.name)
    centre, rot, pin = centre_rays, np.eye(3), None
    if K is not None and cfg.centre_method != "rays":  # the pinhole centre
        w = volume.camera_size[0]
        idx = np.flatnonzero(usable)  # the usable rays' pixels, normalised in blocks
        xn = np.empty((len(idx), 2))
        for a in range(0, len(idx), RAY_FIT_PIXELS):
            v, u = np.divmod(idx[a:a + RAY_FIT_PIXELS], w)
            xn[a:a + len(u)] = pixel_to_normalized(np.stack([u, v], axis=1).astype(np.float64),
                                                   K, dist)
        del idx
        try:
            for _ in range(30):  # fixed point: footprint and z_f depend on the centre
                pin, rot = pinhole_centre(rays, usable, xn, plane, plane_var, centre_rays)
                fit = fit_focus_plane(c, usable, float(pin.position[2]), K,
                                      cfg.pixel_samples)
                new_plane, plane_var = _focus_plane(fit, zf_cfg, float(pin.position[2]),
                                                    volume.name)
                moved = abs(new_plane - plane)
                plane = new_plane
                if moved < 1e-9:
                    break
            pin, rot = pinhole_centre(rays, usable, xn, plane, plane_var, centre_rays)
        except RayFitError as exc:
            raise LensFitError(f"{volume.name}: {exc}") from exc
        del xn
        centre = pin
    else:
        if K is None:
            notes.append("no camera matrix: optical centre is the principal-ray intersection, "
                         "which vignetting pulls behind the pupil; give K for a centre "
                         "consistent with the simulator's pixel directions")
    # the focus fits were the trace stds' last reader: the geometry does not keep them
    c = replace(c, trace_std_px2=None)
    zf_fit = None if fit is None else float(fit.plane_z_mm - centre.position[2])
    if zf_cfg is not None and zf_fit is not None:
        notes.append(f"focus distance: configured {zf_cfg:.3f} mm (used), fitted "
                     f"{zf_fit:.3f} mm")
    return LensGeometry(c, rays, centre_rays, pin, centre, rot, fit, zf_fit, zf_cfg, plane,
                        K, None if dist is None else np.asarray(dist, dtype=np.float64),
                        volume.camera_size, notes)
