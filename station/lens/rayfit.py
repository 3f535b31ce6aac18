"""Per-pixel principal rays smoothed over their neighbours (``local_plane_fit``: on the
optical centre's plane, and their slopes) and the nodes' aim offsets (``aim_offsets``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage

from station.lens.geometry import LensGeometry
from station.lens.rays import UNUSABLE, PrincipalRays


def local_plane_fit(values: np.ndarray, var: np.ndarray, ok: np.ndarray,
                    camera_size: tuple[int, int], pixels: np.ndarray,
                    radius_px: int) -> np.ndarray:
    """Per-pixel ``values`` (N, k) (flat pixel order, variance ``var`` (N,), ``ok`` (N,)
    usable) at the given flat pixels (n,), as a weighted local-plane fit (``a + b du + c dv``,
    weights ``1 / var``) over the usable pixels within ``radius_px`` (a square window): the
    pixels' noise averages out while linear field trends pass unbiased, also at the
    sensor's border. ``radius_px = 0`` or no usable pixel in the window: the pixel's own
    value. Returns (n, k)."""
    pixels = np.asarray(pixels, dtype=np.int64)
    if radius_px <= 0:
        return values[pixels]
    w, h = camera_size
    r = np.arange(-radius_px, radius_px + 1)
    du, dv = (a.ravel() for a in np.meshgrid(r, r))
    u = pixels[:, None] % w + du[None]
    v = pixels[:, None] // w + dv[None]
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    q = np.where(inside, v * w + u, 0)
    good = inside & ok[q] & np.isfinite(values[q]).all(-1) & (var[q] > 0)
    wt = np.where(good, 1.0 / np.where(good, var[q], 1.0), 0.0)
    a = np.stack([np.ones(q.shape), np.broadcast_to(du, q.shape),
                  np.broadcast_to(dv, q.shape)], axis=-1).astype(np.float64)
    ata = np.einsum("nm,nmi,nmj->nij", wt, a, a)
    atb = np.einsum("nm,nmi,nmk->nik", wt, a, np.where(good[..., None], values[q], 0.0))
    solvable = np.linalg.det(ata) > 1e-12 * np.maximum(ata[:, 0, 0], 1e-300) ** 3
    ata[~solvable] = np.eye(3)
    coef = np.linalg.solve(ata, atb)
    return np.where(solvable[:, None], coef[:, 0], values[pixels])


def local_ray_centres(geom: LensGeometry, pixels: np.ndarray, radius_px: int) -> np.ndarray:
    """Principal rays of the given flat pixels on the optical centre's plane, minus the
    centre (n, 2) mm, station frame, by ``local_plane_fit`` over ``radius_px``: the ray's
    per-pixel noise (centroid noise magnified ~4x by the extrapolation from the LCD depths
    to the centre) averages out. Only the rows the pixels' windows reach are evaluated, so
    a block's cost does not grow with the sensor."""
    def at_centre(rays: PrincipalRays, band: slice) -> tuple[np.ndarray, np.ndarray]:
        dz = float(geom.centre.position[2]) - rays.z_ref[band]
        own = rays.xy_ref[band] + rays.slope[band] * dz[:, None] - geom.centre.position[:2]
        return own, rays.var_ref[band] + dz**2 * rays.var_slope[band]

    return _local_ray_fit(geom, pixels, radius_px, at_centre)


def local_ray_slopes(geom: LensGeometry, pixels: np.ndarray, radius_px: int) -> np.ndarray:
    """Principal-ray slopes (n, 2) of the given flat pixels in the camera frame (dx/dz,
    dy/dz), by ``local_plane_fit`` of the station-frame slopes over the same windows as
    ``local_ray_centres``, then rotated (``geom.rotation``)."""
    def slope(rays: PrincipalRays, band: slice) -> tuple[np.ndarray, np.ndarray]:
        return rays.slope[band], rays.var_slope[band]

    s = _local_ray_fit(geom, pixels, radius_px, slope)
    d = np.concatenate([s, np.ones((len(s), 1))], axis=1) @ np.asarray(geom.rotation).T
    return d[:, :2] / d[:, 2:]


def _local_ray_fit(geom: LensGeometry, pixels: np.ndarray, radius_px: int,
                   values: Callable[[PrincipalRays, slice], tuple[np.ndarray, np.ndarray]]
                   ) -> np.ndarray:
    """``local_plane_fit`` of ``values(rays, band)`` -> (per-pixel values (m, 2), variances
    (m,)) over the camera rows the pixels' windows reach (a block's cost does not grow with
    the sensor)."""
    rays = geom.rays
    w, h = geom.camera_size
    pixels = np.asarray(pixels, dtype=np.int64)
    if not len(pixels):
        return np.zeros((0, 2))
    v0 = max(0, int(pixels.min()) // w - radius_px)
    v1 = min(h, int(pixels.max()) // w + radius_px + 1)
    band = slice(v0 * w, v1 * w)
    own, var = values(rays, band)
    return local_plane_fit(own, var, (rays.flags[band] & UNUSABLE) == 0, (w, v1 - v0),
                           pixels - v0 * w, radius_px)


def aim_offsets(slope_term: np.ndarray, moment: np.ndarray, good: np.ndarray,
                sigma_nodes: float) -> np.ndarray:
    """The nodes' aim offsets (Gv, Gu, 2) (the lens file's ``aim_offset``): with a node's
    samples aiming at ``(xy_n + e) z_k``, its principal ray (the samples' weighted centroid
    line) has the slope ``xy_n + e - sum_k w_k p_k / z_k``; ``e`` makes that the station's
    measured slope ``s``. slope_term : (Gv, Gu, 2) ``s - xy_n``; moment : (Gv, Gu, 2)
    ``sum_k w_k p_k / z_k`` of the node's samples (weights summing to 1, p mm, z mm);
    good : (Gv, Gu) nodes with their own samples (the others take the nearest good node's
    offset). The mean over the good nodes is removed (a uniform offset is a camera-matrix
    error, and the optical centre's error puts one there) and the field is smoothed by a
    Gaussian of ``sigma_nodes`` (the measured slopes' noise, ~20 urad per node over 9 x 9
    pixels, against offsets of a few urad; 0: not smoothed)."""
    from scipy.ndimage import gaussian_filter

    e = slope_term + moment
    if not good.all():
        near = ndimage.distance_transform_edt(~good, return_distances=False,
                                              return_indices=True)
        e = e[near[0], near[1]]
    e = e - e[good].mean(axis=0)
    if sigma_nodes > 0:
        e = np.stack([gaussian_filter(e[..., c], sigma_nodes, mode="nearest")
                      for c in range(2)], axis=-1)
    return e


def sample_moment(x: np.ndarray, y: np.ndarray, w: np.ndarray,
                  lens_focus: Callable[[np.ndarray, np.ndarray], np.ndarray | float]
                  ) -> np.ndarray:
    """``sum_k w_k p_k / z_k`` (..., 2) of samples x, y mm and weights (..., K) (normalised
    here), ``z_k = lens_focus(x, y)`` mm (a scalar focus distance or the zones' focus)."""
    w = w / w.sum(axis=-1, keepdims=True)
    z = np.broadcast_to(lens_focus(x, y), x.shape)
    return np.stack([(w * x / z).sum(axis=-1), (w * y / z).sum(axis=-1)], axis=-1)
