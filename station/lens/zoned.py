"""The optical centre refitted for a lens whose pupil zones focus at different depths
(``zoned_centre``) and the zones' focus table seen from the moved centre (``shift_zones``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from sim.optics.measured_lens import aim_depths
from sim.optics.projection import pixel_to_normalized
from station.compute import Engine, run_ordered
from station.lens import aperture as ap
from station.lens.geometry import LensFitConfig, LensGeometry
from station.lens.jobs import GRID_PIXELS, aperture_block, aperture_job, pixel_inputs, tile_groups
from station.lens.rayfit import sample_moment
from station.lens.result import node_positions
from station.ltc.store import LtcVolume


def shift_zones(zones: np.ndarray, fit: dict, shift_mm: float) -> tuple[np.ndarray, dict]:
    """The focus per pupil zone seen from an optical centre ``shift_mm`` farther along z:
    the table's focus distances less the shift, and the model ``1 / z = c0 + c1 rho^2``
    through its new ends (exact there; between them off by the shift squared over z, well
    under a nanometre for micrometre shifts)."""
    table = zones.copy()
    table[:, 1] -= shift_mm
    out = dict(fit)
    rim = float(fit["radius_mm"])
    out["c0_per_mm"] = 1.0 / float(table[0, 1])
    out["c1_per_mm3"] = (1.0 / float(table[-1, 1]) - out["c0_per_mm"]) / rim**2
    out["centre_shift_mm"] = shift_mm
    return table, out


CENTRE_PIXELS = 2000  # about this many node pixels refit the zoned lens's centre
MISS_TERMS = 10  # a cubic in the pixel coordinates


def _cubic_terms(pix: np.ndarray, w: int, h: int) -> np.ndarray:
    """The 10 monomials up to degree 3 (n, 10) of flat pixels' coordinates, scaled to +-1."""
    x = (pix % w) / max(w - 1, 1) * 2.0 - 1.0
    y = (pix // w) / max(h - 1, 1) * 2.0 - 1.0
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y, x**3, x * x * y, x * y * y,
                     y**3], axis=1)


def zoned_centre(volume: LtcVolume, geom: LensGeometry, grid: ap.ApertureGrid,
                 cfg: LensFitConfig, zones: np.ndarray, zone_fit: dict,
                 engine: Engine) -> tuple[LensGeometry, float]:
    """The optical centre again, for a lens whose zones focus at different depths: the
    geometry with the new centre (and roll) and how far the centre moved along z, mm.

    ``pinhole_centre`` takes each principal ray's point on the focus plane as its pixel's
    in-focus point, seen from the centre in K's direction. With one focus every ray of the
    pixel passes there; with zones the principal ray (the samples' centroid line, ``a`` on
    the centre's plane, slope ``x_n - sum_k w_k p_k / z_k`` = ``x_n - m``) misses it by
    ``a - Z m`` at the focus plane's distance Z. A vignetted pupil has ``a`` growing with the
    field, so the miss is a scale that the fit took for z_f: on the paper-size benches the
    centre came out 23-31 um behind the pupil, which moves a scan's points by 2-3 um at
    large defocus. Here about ``CENTRE_PIXELS`` node pixels are sampled through the zones
    (the aperture pass's own ``aperture_block``, on ``engine``), their misses computed from
    the samples and fitted by a cubic over the sensor, and the centre refitted from every
    usable ray with its miss removed (``pinhole_centre(bias_mm=...)``)."""
    from dataclasses import replace

    from station.lens.centre import pinhole_centre

    w, h = volume.camera_size
    step = max(cfg.grid_step, int(np.ceil(np.sqrt(w * h / CENTRE_PIXELS))))
    nu, nv = node_positions(w, step), node_positions(h, step)
    pix = (nv[:, None] * w + nu[None, :]).ravel()
    pix = pix[geom.rays.usable[pix]]
    job = aperture_job(geom, grid, cfg, zone_fit, samples=True)
    miss = np.zeros((len(pix), 2))
    good = np.zeros(len(pix), dtype=bool)
    z_plane = geom.focus_distance_mm

    def focus(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray | float:
        return aim_depths(zones, z_plane, x_mm, y_mm)

    def tasks() -> Iterator[tuple[np.ndarray, Callable[..., dict[str, np.ndarray]],
                                  tuple[Any, ...]]]:
        for sel, tile in tile_groups(volume, pix):
            p = pix[sel]
            yield sel, aperture_block, (volume, job, *tile, p, pixel_inputs(geom, p, cfg))

    def on_result(sel: np.ndarray, res: dict[str, np.ndarray]) -> None:
        ok = res["ok"] & res["w"].any(axis=1)
        x, wk = res["x"], np.where(ok[:, None], res["w"], 1.0)
        # the samples' mean is the node's target mean (match_moments keeps it exactly)
        miss[sel] = res["mean"] - z_plane * sample_moment(x[..., 0], x[..., 1], wk, focus)
        good[sel] = ok

    run_ordered(engine, tasks(), on_result)
    if good.sum() < 2 * MISS_TERMS:
        return geom, 0.0
    # the misses are smooth over the field (the vignetting): a cubic in (u, v) fitted to the
    # sampled nodes gives every usable ray's, so the refit keeps all of the rays' averaging
    coef = np.linalg.lstsq(_cubic_terms(pix[good], w, h), miss[good], rcond=None)[0]
    usable = geom.rays.usable
    idx = np.flatnonzero(usable)
    xn = np.empty((len(idx), 2))
    bias = np.empty((len(idx), 2))
    for a0 in range(0, len(idx), GRID_PIXELS):
        blk = idx[a0:a0 + GRID_PIXELS]
        uv = np.stack([blk % w, blk // w], axis=1).astype(np.float64)
        xn[a0:a0 + len(blk)] = pixel_to_normalized(uv, geom.known_camera_matrix(),
                                                   geom.dist_coeffs)
        bias[a0:a0 + len(blk)] = (_cubic_terms(blk, w, h) @ coef) @ job.rot2  # to station
    plane_var = (geom.focus.plane_std_mm**2 if geom.focus is not None
                 and geom.focus_distance_config_mm is None else 0.0)  # as fit_geometry's
    pin, rot = pinhole_centre(geom.rays, usable, xn, geom.focus_plane_z_mm, plane_var,
                              geom.centre_rays, bias_mm=bias)
    pin = replace(pin, method="pinhole: in-focus points vs K, zones' misses removed")
    shift = float(pin.position[2] - geom.centre.position[2])
    return replace(geom, centre_pinhole=pin, centre=pin, rotation=rot), shift
