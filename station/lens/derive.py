"""The lens model file from the lens's geometry and its LTCs (OPTICS.md section 6).

This module's line: given the ``LensGeometry`` (``station.lens.geometry``: principal rays ->
optical centre -> focus plane), it takes every node pixel's LTC at each depth, scales it onto
the aperture plane at the optical centre and fuses the depths (``station.lens.aperture``),
draws K samples per node and writes the lens model (``sim.optics.measured_lens``).

Each depth's LTC is placed on the aperture plane by its own centroid, and the samples'
centroid is the pixel's principal ray on the optical centre's plane, fitted as a local plane
over the pixels within ``ray_window_px`` (``local_ray_centres``). One pixel's ray is only
as good as its centroids extrapolated ~4x from the LCD depths to the centre (~150 um RMS on
the experiment's benches), and the fused distribution's own mean adds each depth's residual
times ``|s_i|`` (~5 at the extreme depths): the samples' centroids were ~300-400 um RMS off
the true lens's, ~30 um with both changes (``benchmarks/README.md``).
``derive_lens`` runs the whole chain from an LTC volume. With a camera matrix and
``LensFitConfig.focus_zones`` it first fits the focus per pupil zone (spherical aberration)
from the LTCs at the optical centre (``station.lens.zones``), maps every LTC onto the
aperture plane through it (``aperture.zone_map``; depths between the zones' foci are not
used) and stores it as the lens file's ``focus_zones_mm``, where each sample aims.

Nodes: every ``grid_step``-th pixel in u and v, plus the last column and row. A node without
a usable principal ray (flagged) or without a fused distribution takes the samples of the
nearest node that has one; the file's metadata lists how many were filled.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from tqdm import tqdm

from sim.optics.measured_lens import (LensFileWriter, MeasuredLens, aim_depths, match_moments,
                                     read_lens_nodes)
from sim.optics.projection import pixel_to_normalized
from station.lens import aperture as ap
from station.lens.centroids import STATUS_OK, region_stats
from station.compute import Engine, run_ordered
from station.ltc.store import LtcVolume
from station.lens.geometry import (
    LensFitConfig,
    LensFitError,
    LensGeometry,
    fit_geometry,
    footprint_mm,
)
from station.lens.rays import FLAG_BAD_FIT, FLAG_FEW_DEPTHS, FLAG_OUTLIER, UNUSABLE
from station.lens.zones import fit_focus_zones

GRID_MARGIN = 1.2  # aperture grid half-width over the largest pupil extent seen
EXTENT_PERCENTILE = 99.5
GRID_PIXELS = 1 << 16  # pixels per block of the grid extent's temporaries (~1 kB each)
# pixels per block of the summary's residual lengths: their order (depth-major per block)
# fixes the mean and std reported in the lens file to the last bit
RESIDUAL_PIXELS = 1 << 18
MIN_COVERAGE = 0.5  # a depth whose resampled LTC falls mostly off the grid is not fused


@dataclass(frozen=True)
class ApertureSet:
    """Aperture-plane distributions of n pixels (flat indices ``pixels``).

    per_depth : (n, D, G, G) each depth's normalised masses (0 where not used);
    weight : (n, D) fusion weights (0: not used); coverage : (n, D) mass that fell on the grid;
    fused : (n, G, G) normalised (0 where no depth was usable); ok : (n,);
    mean : (n, 2) mm and cov : (n, 2, 2) mm^2 target moments of the samples.
    """

    pixels: np.ndarray
    per_depth: np.ndarray | None
    weight: np.ndarray
    coverage: np.ndarray
    fused: np.ndarray
    ok: np.ndarray
    mean: np.ndarray
    cov: np.ndarray


def aperture_grid(geom: LensGeometry, cfg: LensFitConfig) -> ap.ApertureGrid:
    """A grid covering every usable pixel's scaled LTC (robust maximum extent, with margin);
    computed in pixel blocks, so its temporaries do not grow with the sensor."""
    c, rays = geom.centroids, geom.rays
    d = len(c.depths_mm)
    zc = float(geom.centre.position[2])
    s = ap.scale_ratio(c.depths_mm, geom.focus_plane_z_mm, zc)
    moments = c.moments_px2.reshape(d, -1, 3)
    n = moments.shape[1]
    usable = rays.usable
    blocks = [slice(a0, min(n, a0 + GRID_PIXELS)) for a0 in range(0, n, GRID_PIXELS)]
    # one array of every used (depth, pixel) reach, partitioned in place by the percentile
    reach_all = np.empty(sum(int((rays.used[:, b] & usable[None, b]).sum()) for b in blocks))
    at = 0
    for sl in blocks:
        use = rays.used[:, sl] & usable[None, sl]  # not empty: the centre needed rays
        mom = moments[:, sl] * c.pitch_mm**2 * (s**2)[:, None, None]
        lam = 0.5 * (mom[..., 0] + mom[..., 1]) + np.hypot(0.5 * (mom[..., 0] - mom[..., 1]),
                                                           mom[..., 2])
        a = (rays.xy_ref[sl] + rays.slope[sl] * (zc - rays.z_ref[sl])[:, None]
             - geom.centre.position[:2])
        reach = np.abs(a).max(axis=1)[None] + 2.0 * np.sqrt(np.maximum(lam, 0.0))
        reach = reach + 0.5 * c.pitch_mm * np.abs(s)[:, None]
        got = reach[use]
        reach_all[at:at + len(got)] = got
        at += len(got)
    half = GRID_MARGIN * float(np.percentile(reach_all, EXTENT_PERCENTILE,
                                             overwrite_input=True))
    return ap.ApertureGrid(half, cfg.aperture_cells)


def tile_shape(volume: LtcVolume) -> tuple[int, int]:
    """Camera rows and columns of one stored chunk of ``ltc`` (64 x 64 for in-memory arrays):
    the blocks the lens passes read, so each chunk is decoded once per pass."""
    chunks = getattr(volume.ltc, "chunks", None)
    return (int(chunks[1]), int(chunks[2])) if chunks else (64, 64)


def tile_groups(volume: LtcVolume, pixels: np.ndarray) -> list[tuple[np.ndarray, tuple]]:
    """Flat pixels grouped by the stored ``ltc`` chunk they lie in: (indices into ``pixels``,
    the chunk's (r0, r1, c0, c1)) per chunk, so each chunk is read once."""
    w, h = volume.camera_size
    tr, tc = tile_shape(volume)
    if not len(pixels):
        return []
    key = (pixels // w // tr) * ((w + tc - 1) // tc) + (pixels % w) // tc
    order = np.argsort(key, kind="stable")
    out = []
    for sel in np.split(order, np.flatnonzero(np.diff(key[order])) + 1):
        r0, c0 = pixels[sel[0]] // w // tr * tr, pixels[sel[0]] % w // tc * tc
        out.append((sel, (int(r0), int(min(h, r0 + tr)), int(c0), int(min(w, c0 + tc)))))
    return out


@dataclass(frozen=True)
class ApertureJob:
    """What every aperture block needs besides its own pixels (small; sent to each task).

    ratio : (D,) scale to the aperture plane; footprint_mm : (D,); rot2 : (2, 2) in-plane
    station-to-camera rotation; samples : draw the K samples of the good nodes;
    keep_fused, keep_depths : also return the fused (m, G, G) / per-depth (m, D, G, G)
    distributions. zones : the focus per pupil zone's radial maps (``aperture.zone_map``),
    which then place each depth's LTC on the aperture plane; ``ratio`` sizes the blur and
    noise predictions (with zones, their ``blur_ratio``).
    """

    grid: ap.ApertureGrid
    cfg: LensFitConfig
    depths_mm: np.ndarray
    pitch_mm: float
    ratio: np.ndarray
    footprint_mm: np.ndarray
    rot2: np.ndarray
    samples: bool = False
    keep_fused: bool = False
    keep_depths: bool = False
    zones: ap.ZoneMap | None = None


def aperture_job(geom: LensGeometry, grid: ap.ApertureGrid, cfg: LensFitConfig,
                 zone_fit: dict | None = None, **flags: bool) -> ApertureJob:
    """The aperture pass's shared inputs; ``zone_fit`` (``fit_focus_zones``'s dict) maps
    the LTCs through the focus per pupil zone."""
    c = geom.centroids
    zc = float(geom.centre.position[2])
    u, _, vt = np.linalg.svd(geom.rotation[:2, :2])
    zones = None
    ratio = ap.scale_ratio(c.depths_mm, geom.focus_plane_z_mm, zc)
    if zone_fit is not None:
        zones = ap.zone_map(c.depths_mm, zc, zone_fit["c0_per_mm"], zone_fit["c1_per_mm3"],
                            zone_fit["radius_mm"])
        ratio = np.where(zones.fold, ratio, zones.blur_ratio)
    return ApertureJob(grid, cfg, c.depths_mm.copy(), float(c.pitch_mm), ratio,
                       footprint_mm(c.depths_mm, zc, geom.camera_matrix, cfg.pixel_samples), u @ vt,
                       zones=zones, **flags)


def pixel_inputs(geom: LensGeometry, pix: np.ndarray,
                 cfg: LensFitConfig) -> dict[str, np.ndarray]:
    """The per-pixel inputs of an aperture block for flat pixels ``pix`` (m,): principal ray
    (``xy_ref``, ``slope``, ``z_ref``; ``at_centre`` on z_O relative to the centre, fitted
    over the pixel's neighbours: ``local_ray_centres``), ``used`` (D, m), ``usable`` (m,) and
    the centroid moments ``mom`` (D, m, 3) LCD px^2."""
    c, rays = geom.centroids, geom.rays
    d = len(c.depths_mm)
    xy_ref, slope, z_ref = rays.xy_ref[pix], rays.slope[pix], rays.z_ref[pix]
    return {"xy_ref": xy_ref, "slope": slope, "z_ref": z_ref,
            "at_centre": local_ray_centres(geom, pix, cfg.ray_window_px),
            "used": rays.used[:, pix], "usable": (rays.flags[pix] & UNUSABLE) == 0,
            "mom": c.moments_px2.reshape(d, -1, 3)[:, pix].astype(np.float64)}


def aperture_block(volume: LtcVolume, job: ApertureJob, r0: int, r1: int, c0: int, c1: int,
                   pix: np.ndarray, inp: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Scale, resample and fuse the LTC of flat pixels ``pix`` (m,), all inside camera rows
    ``r0:r1`` and columns ``c0:c1``, onto the aperture plane; with ``job.samples`` also the
    K samples of each good node (usable, fused). A pure function of its inputs: every
    engine computes blocks with it. Returns ``weight`` (m, D), ``coverage`` (m, D), ``ok``
    (m,), ``mean`` (m, 2), ``cov`` (m, 2, 2); ``x`` (m, K, 2), ``w`` (m, K) (0 where not
    good) with samples; ``fused`` / ``per_depth`` when kept."""
    cfg, grid = job.cfg, job.grid
    c_pitch, s, fp = job.pitch_mm, job.ratio, job.footprint_mm
    d, n, g = len(job.depths_mm), len(pix), grid.cells
    w_cam = volume.camera_size[0]
    ltc = np.asarray(volume.ltc[:, r0:r1, c0:c1])  # store dtype: converted per node chunk
    origin = np.asarray(volume.origin[:, r0:r1, c0:c1], dtype=np.int64)
    noise = np.asarray(volume.noise[:, r0:r1, c0:c1], dtype=np.float64)
    ltc = ltc.reshape(d, -1, *ltc.shape[-2:])
    origin = origin.reshape(d, -1, 2)
    noise = noise.reshape(d, -1)
    local = (pix // w_cam - r0) * (c1 - c0) + (pix % w_cam - c0)
    out = {"weight": np.zeros((n, d)), "coverage": np.zeros((n, d)), "mean": np.zeros((n, 2)),
           "cov": np.zeros((n, 2, 2))}
    if job.samples:
        out["x"], out["w"] = np.zeros((n, cfg.samples, 2)), np.zeros((n, cfg.samples))
    if job.keep_fused:
        out["fused"] = np.zeros((n, g, g))
    if job.keep_depths:
        out["per_depth"] = np.zeros((n, d, g, g))
    for k0 in range(0, n, cfg.nodes_per_chunk):
        idx = np.arange(k0, min(n, k0 + cfg.nodes_per_chunk))
        loc = local[idx]
        usable = inp["usable"][idx]
        m_all = np.zeros((len(idx), d, g, g))
        coverage = np.zeros((len(idx), d))
        for i in range(d):
            used = inp["used"][i, idx] & usable
            if not used.any() or (job.zones is not None and job.zones.fold[i]):
                continue
            h = ltc[i, loc].astype(np.float64)  # a copy: zeroed in place
            h[~used] = 0.0  # (NaN where no signal)
            st = region_stats(h, used, noise[i, loc])  # h: 0 outside each region
            # each depth's LTC is placed by its own centroid onto the principal ray at the
            # centre's plane: the depths' noisy residuals (x |s_i| ~ 5 at the extreme
            # depths) neither shift nor blur the fused distribution
            at_depth = inp["xy_ref"][idx] + inp["slope"][idx] * (job.depths_mm[i]
                                                                 - inp["z_ref"][idx])[:, None]
            own = (st.centroid + origin[i, loc]) * c_pitch
            at_depth = np.where(np.isfinite(own), own, at_depth)
            z = job.zones  # with zones: the pupil centre's scale and the radial term
            m = ap.resample(h, origin[i, loc], at_depth, inp["at_centre"][idx],
                            s[i] if z is None else z.centre_ratio[i], c_pitch, grid, job.rot2,
                            cfg.supersample, g2_per_mm2=0.0 if z is None else z.g2_per_mm2[i],
                            rim_mm=np.inf if z is None else z.rim_mm)
            cov_i = m.sum(axis=(1, 2))
            coverage[:, i] = np.where(used, cov_i, 0.0)
            m_all[:, i] = m / np.where(cov_i > 0, cov_i, 1.0)[:, None, None]
        mm = inp["mom"][:, idx] * (c_pitch * s)[:, None, None] ** 2
        none = ~np.isfinite(mm[..., 0]).any(axis=0)  # no depth with signal: any cov
        mm[:, none] = [1.0, 1.0, 0.0]
        cov2 = np.nanmedian(np.stack([mm[..., 0], mm[..., 2], mm[..., 2], mm[..., 1]],
                                     axis=-1), axis=0).reshape(-1, 2, 2)
        blur, nse = ap.depth_errors(noise[:, loc].T, s, c_pitch, fp, cov2, grid.cell_mm)
        wd = ap.fusion_weights(blur, nse, coverage > MIN_COVERAGE)
        acc = np.einsum("nd,ndij->nij", wd, m_all)
        tot = wd.sum(axis=1)
        fz = acc / np.where(tot > 0, tot, 1.0)[:, None, None]
        ok_c = tot > 0
        _, cov_c = _moments(fz, wd, ok_c, grid, c_pitch * s, fp * s, cfg.deblur)
        # the samples' centroid is the principal ray on the centre's plane (camera axes):
        # the fit over all depths and the pixel's neighbours, not the fused grid's mean
        mean_c = inp["at_centre"][idx] @ job.rot2.T
        out["weight"][idx], out["coverage"][idx] = wd, coverage
        out["mean"][idx], out["cov"][idx] = mean_c, cov_c
        if job.keep_fused:
            out["fused"][idx] = fz
        if job.keep_depths:
            out["per_depth"][idx] = m_all
        good = ok_c & usable
        if job.samples and good.any():
            xs, ws = ap.ring_samples(ap.deblur(fz[good], wd[good], grid, s, c_pitch, fp,
                                               cfg.pixel_samples, cfg.deconvolve_iterations,
                                               cfg.support_floor),
                                     grid, cfg.samples)
            out["x"][idx[good]] = match_moments(xs, ws, mean_c[good], cov_c[good])
            out["w"][idx[good]] = ws
    out["ok"] = out["weight"].sum(axis=1) > 0
    return out


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

    def focus(x_mm, y_mm):
        return aim_depths(zones, z_plane, x_mm, y_mm)

    def tasks():
        for sel, tile in tile_groups(volume, pix):
            p = pix[sel]
            yield sel, aperture_block, (volume, job, *tile, p, pixel_inputs(geom, p, cfg))

    def on_result(sel, res) -> None:
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
        xn[a0:a0 + len(blk)] = pixel_to_normalized(uv, geom.camera_matrix, geom.dist_coeffs)
        bias[a0:a0 + len(blk)] = (_cubic_terms(blk, w, h) @ coef) @ job.rot2  # to station
    plane_var = (geom.focus.plane_std_mm**2 if geom.focus is not None
                 and geom.focus_distance_config_mm is None else 0.0)  # as fit_geometry's
    pin, rot = pinhole_centre(geom.rays, usable, xn, geom.focus_plane_z_mm, plane_var,
                              geom.centre_rays, bias_mm=bias)
    pin = replace(pin, method="pinhole: in-focus points vs K, zones' misses removed")
    shift = float(pin.position[2] - geom.centre.position[2])
    return replace(geom, centre_pinhole=pin, centre=pin, rotation=rot), shift


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
    def at_centre(rays, band):
        dz = float(geom.centre.position[2]) - rays.z_ref[band]
        own = rays.xy_ref[band] + rays.slope[band] * dz[:, None] - geom.centre.position[:2]
        return own, rays.var_ref[band] + dz**2 * rays.var_slope[band]

    return _local_ray_fit(geom, pixels, radius_px, at_centre)


def local_ray_slopes(geom: LensGeometry, pixels: np.ndarray, radius_px: int) -> np.ndarray:
    """Principal-ray slopes (n, 2) of the given flat pixels in the camera frame (dx/dz,
    dy/dz), by ``local_plane_fit`` of the station-frame slopes over the same windows as
    ``local_ray_centres``, then rotated (``geom.rotation``)."""
    def slope(rays, band):
        return rays.slope[band], rays.var_slope[band]

    s = _local_ray_fit(geom, pixels, radius_px, slope)
    d = np.concatenate([s, np.ones((len(s), 1))], axis=1) @ np.asarray(geom.rotation).T
    return d[:, :2] / d[:, 2:]


def _local_ray_fit(geom: LensGeometry, pixels: np.ndarray, radius_px: int,
                   values) -> np.ndarray:
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


def sample_moment(x: np.ndarray, y: np.ndarray, w: np.ndarray, lens_focus) -> np.ndarray:
    """``sum_k w_k p_k / z_k`` (..., 2) of samples x, y mm and weights (..., K) (normalised
    here), ``z_k = lens_focus(x, y)`` mm (a scalar focus distance or the zones' focus)."""
    w = w / w.sum(axis=-1, keepdims=True)
    z = np.broadcast_to(lens_focus(x, y), x.shape)
    return np.stack([(w * x / z).sum(axis=-1), (w * y / z).sum(axis=-1)], axis=-1)


def aperture_set(volume: LtcVolume, geom: LensGeometry, grid: ap.ApertureGrid,
                 pixels: np.ndarray, cfg: LensFitConfig | None = None,
                 keep_depths: bool = False, progress: bool = False,
                 keep_fused: bool = True, zone_fit: dict | None = None) -> ApertureSet:
    """Scale, resample and fuse the LTC of the given flat pixels onto the aperture plane, in
    this process, block by block (``aperture_block``); ``progress``: a bar over the blocks.
    ``keep_fused=False`` keeps no (n, G, G) array (``fused`` is then None); ``zone_fit``: map
    through the focus per pupil zone (``aperture_job``)."""
    cfg = cfg or LensFitConfig()
    pixels = np.asarray(pixels, dtype=np.int64).ravel()
    n, d, g = len(pixels), len(geom.centroids.depths_mm), grid.cells
    job = aperture_job(geom, grid, cfg, zone_fit, keep_fused=keep_fused,
                       keep_depths=keep_depths)
    out = {"weight": np.zeros((n, d)), "coverage": np.zeros((n, d)), "mean": np.zeros((n, 2)),
           "cov": np.zeros((n, 2, 2))}
    fused = np.zeros((n, g, g)) if keep_fused else None
    per_depth = np.zeros((n, d, g, g)) if keep_depths else None
    for sel, tile in tqdm(tile_groups(volume, pixels), desc="lens: aperture", unit="block",
                          disable=None if progress else True):
        pix = pixels[sel]
        res = aperture_block(volume, job, *tile, pix, pixel_inputs(geom, pix, cfg))
        for name in out:
            out[name][sel] = res[name]
        if fused is not None:
            fused[sel] = res["fused"]
        if per_depth is not None:
            per_depth[sel] = res["per_depth"]
    ok = out["weight"].sum(axis=1) > 0
    return ApertureSet(pixels, per_depth, out["weight"], out["coverage"], fused, ok,
                       out["mean"], out["cov"])


def _moments(fused: np.ndarray, weight: np.ndarray, ok: np.ndarray, grid: ap.ApertureGrid,
             pitch_scaled: np.ndarray, footprint_scaled: np.ndarray,
             deblur: bool) -> tuple[np.ndarray, np.ndarray]:
    """Target mean (m, 2) and covariance (m, 2, 2) mm of fused distributions (m, G, G).

    Masses binned in cells have the second moment of what was binned plus a cell's
    variance (Sheppard's correction), so a cell's variance is subtracted. With ``deblur``
    also, per depth by the fusion weights (m, D): the LCD pixel's variance twice (an LTC
    coefficient is the light binned in that LCD pixel, and the resampling spreads it
    uniformly over the pixel's area again) and the camera pixel's once (a box blur).
    Without this the aperture came out 6-9 % wide against the true lens
    (benchmarks/README.md, "The fake bench's lens converged")."""
    mean, cov = ap.grid_moments(fused, grid)
    cov = cov - np.eye(2) * grid.cell_mm**2 / 12.0
    if deblur:
        wn = weight / np.where(ok, weight.sum(axis=1), 1.0)[:, None]
        blur = (2.0 * pitch_scaled ** 2 + footprint_scaled ** 2) / 12.0
        cov = cov - np.eye(2) * (wn @ blur)[:, None, None]
    val, vec = np.linalg.eigh(cov)
    val = np.maximum(val, 1e-6 * np.maximum(val.max(axis=1, keepdims=True), 1e-12))
    return mean, np.einsum("nij,nj,nkj->nik", vec, val, vec)


def node_positions(size: int, step: int) -> np.ndarray:
    """Node coordinates along one axis: every ``step``-th pixel and the last one."""
    a = np.arange(0, size, step)
    return a if a[-1] == size - 1 else np.append(a, size - 1)


@dataclass
class LensResult:
    """The derivation's result: geometry, grid, nodes, fused distributions, the lens.

    Derived to a file (``derive_lens(..., out=path)``): ``lens`` and ``apertures`` are None
    (nothing per node is held in memory) and ``lens_path`` is the file written.
    """

    config: LensFitConfig
    geometry: LensGeometry
    grid: ap.ApertureGrid
    node_u: np.ndarray
    node_v: np.ndarray
    apertures: ApertureSet | None
    lens: MeasuredLens | None
    filled_nodes: int
    figures: list[Path] = field(default_factory=list)
    lens_path: Path | None = None

    def samples_at(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Aperture samples x, y mm and weights (n, K) of pixels uv (n, 2): the lens's own
        interpolation in memory; from the written file, the nearest node's."""
        if self.lens is not None:
            return self.lens.samples_at(uv)
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        i = np.abs(uv[:, 0, None] - self.node_u[None]).argmin(axis=1)
        j = np.abs(uv[:, 1, None] - self.node_v[None]).argmin(axis=1)
        return read_lens_nodes(self.lens_path, j * len(self.node_u) + i)

    def summary(self) -> dict:
        """A JSON-able report of what was measured."""
        g = self.geometry
        r = g.rays
        res_mean, res_std, res_count = _residual_stats(r)
        fl = r.flags
        out = {
            "optical_centre_mm": g.centre.position.tolist(),
            "optical_centre_std_mm": g.centre.std.tolist(),
            "optical_centre_method": g.centre.method,
            "principal_ray_intersection_mm": g.centre_rays.position.tolist(),
            "principal_ray_intersection_std_mm": g.centre_rays.std.tolist(),
            "focus_plane_z_mm": g.focus_plane_z_mm,
            "focus_distance_mm": g.focus_distance_mm,
            "focus_distance_fitted_mm": g.focus_distance_fit_mm,
            "focus_distance_config_mm": g.focus_distance_config_mm,
            "focus_fit_spread_mm": None if g.focus is None else g.focus.spread_mm,
            "ray_residual_mean_mm": res_mean,
            "ray_residual_std_mm": res_std,
            "ray_residual_count": res_count,
            "pixels": len(fl),
            "pixels_usable": int(r.usable.sum()),
            "pixels_few_depths": int(((fl & FLAG_FEW_DEPTHS) > 0).sum()),
            "pixels_outlier_removed": int(((fl & FLAG_OUTLIER) > 0).sum()),
            "pixels_bad_fit": int(((fl & FLAG_BAD_FIT) > 0).sum()),
            "depths_mm": g.centroids.depths_mm.tolist(),
            "samples": self.config.samples,
            "nodes": [len(self.node_v), len(self.node_u)],
            "nodes_filled": self.filled_nodes,
            "aperture_half_width_mm": self.grid.half_width_mm,
            "aperture_cells": self.grid.cells,
            "camera_matrix_known": g.camera_matrix is not None,
            "notes": list(g.notes),
        }
        if g.centre_pinhole is not None:
            out["camera_rotation_deg"] = float(np.degrees(np.arccos(
                np.clip((np.trace(g.rotation) - 1) / 2, -1, 1))))
        return out


def _residual_stats(rays) -> tuple[float | None, float | None, int]:
    """Mean, std (None without any) and count of the usable rays' residual lengths (float32)
    of the points in their fits, in pixel blocks: the values numpy's float64 ``mean`` and
    ``std`` give of them in this order, with one float64 array of the lengths (no (D, N)
    temporaries, no float32 copy beside the deviations): the float32 lengths are packed into
    its first half, then turned into the float64 squared deviations in place, from the end."""
    n = len(rays.flags)
    usable = rays.usable
    blocks = [slice(a0, min(n, a0 + RESIDUAL_PIXELS)) for a0 in range(0, n, RESIDUAL_PIXELS)]

    def keep(sl: slice) -> np.ndarray:
        res = rays.residual_mm[:, sl]
        return rays.used[:, sl] & usable[None, sl] & np.isfinite(res)

    count = sum(int(keep(sl).sum()) for sl in blocks)
    if not count:
        return None, None, 0
    buf = np.empty(count)
    res = buf.view(np.float32)[:count]
    at = 0
    for sl in blocks:
        got = rays.residual_mm[:, sl][keep(sl)]
        res[at:at + len(got)] = got
        at += len(got)
    mean = float(res.mean(dtype=np.float64))
    # numpy's std: the float64 mean kept as a (1,) array, deviations squared, summed, / n
    m = np.true_divide(np.add.reduce(res, dtype=np.float64, keepdims=True), count)
    step = 1 << 16
    for b in range(count, 0, -step):  # buf[a:b] overwrites res[2a:2b]: read already
        a = max(0, b - step)
        buf[a:b] = res[a:b].copy() - m
    del res
    np.multiply(buf, buf, out=buf)
    var = np.add.reduce(buf, dtype=np.float64)
    return mean, float(np.sqrt(np.float64(var / count))), count


def derive_lens(volume: LtcVolume, config: LensFitConfig | None = None,
                K: np.ndarray | None = None, dist: np.ndarray | None = None,
                progress: bool = False, engine: Engine | None = None,
                out: str | Path | None = None) -> LensResult:
    """The measured lens of an LTC volume (see the module docstrings for every step);
    ``progress`` shows bars over the centroid and aperture passes.

    engine : where the centroid and aperture blocks are computed (``station.compute``;
    default: in this process); every engine gives the same lens bit for bit.
    out : write the lens file there as nodes are produced (``LensFileWriter``) instead of
    building it in memory: memory then does not grow with the number of nodes, and the
    result has ``lens_path`` instead of ``lens`` and ``apertures``.
    """
    cfg = config or LensFitConfig()
    own = engine is None
    engine = engine or Engine(1)
    try:
        return _derive(volume, cfg, K, dist, progress, engine, out)
    finally:
        if own:
            engine.close()


def _derive(volume: LtcVolume, cfg: LensFitConfig, K, dist, progress: bool, engine: Engine,
            out: str | Path | None) -> LensResult:
    geom = fit_geometry(volume, cfg, K, dist, progress=progress, engine=engine)
    grid = aperture_grid(geom, cfg)
    w, h = volume.camera_size
    nu, nv = node_positions(w, cfg.grid_step), node_positions(h, cfg.grid_step)
    shape = (len(nv), len(nu))
    k = cfg.samples
    writer = LensFileWriter(out, nu, nv, k) if out is not None else None
    try:
        good = np.zeros(shape, dtype=bool)
        zones, zone_fit = None, None
        if cfg.focus_zones and geom.camera_matrix is not None:
            # fitted first: the zones' radial maps place every LTC on the aperture plane
            found = fit_focus_zones(volume, float(geom.centre.position[2]), geom.camera_matrix,
                                    geom.focus_distance_mm, _centre_radius_mm(geom),
                                    pixel_samples=cfg.pixel_samples)
            if found is not None:
                geom, shift = zoned_centre(volume, geom, grid, cfg, *found, engine=engine)
                zones, zone_fit = shift_zones(*found, shift)
                grid = aperture_grid(geom, cfg)
        if writer is None:
            x = np.zeros(shape + (k, 2))
            wk = np.zeros(shape + (k,))
            parts = {"weight": np.zeros(shape + (len(volume.depths_mm),)),
                     "coverage": np.zeros(shape + (len(volume.depths_mm),)),
                     "mean": np.zeros(shape + (2,)), "cov": np.zeros(shape + (2, 2))}
        job = aperture_job(geom, grid, cfg, zone_fit=zone_fit, samples=True)
        aim = cfg.aim_offset_sigma_px > 0 and geom.camera_matrix is not None
        slope_term = np.zeros(shape + (2,)) if aim else None  # s - xy_n per node
        tr, tc = tile_shape(volume)
        blocks = []
        for r0 in range(0, h, tr):
            jv = np.flatnonzero((nv >= r0) & (nv < r0 + tr))
            for c0 in range(0, w, tc):
                iu = np.flatnonzero((nu >= c0) & (nu < c0 + tc))
                if len(jv) and len(iu):
                    blocks.append((r0, min(h, r0 + tr), c0, min(w, c0 + tc), jv, iu))
        bar = tqdm(total=len(blocks), desc="lens: aperture", unit="block",
                   disable=None if progress else True)

        def tasks():
            for r0, r1, c0, c1, jv, iu in blocks:
                pix = (nv[jv][:, None] * w + nu[iu][None, :]).ravel()
                if slope_term is not None:
                    uv = np.stack([pix % w, pix // w], axis=1).astype(np.float64)
                    xn = pixel_to_normalized(uv, geom.camera_matrix, geom.dist_coeffs)
                    slope_term[jv[0]:jv[-1] + 1, iu[0]:iu[-1] + 1] = (
                        local_ray_slopes(geom, pix, cfg.ray_window_px) - xn
                    ).reshape(len(jv), len(iu), 2)
                yield ((jv, iu), aperture_block,
                       (volume, job, r0, r1, c0, c1, pix, pixel_inputs(geom, pix, cfg)))

        def on_result(key, res) -> None:
            jv, iu = key
            sub = (len(jv), len(iu))
            g = (res["ok"] & res["w"].any(axis=1)).reshape(sub)
            good[jv[0]:jv[-1] + 1, iu[0]:iu[-1] + 1] = g
            xs, ws = res["x"].reshape(sub + (k, 2)), res["w"].reshape(sub + (k,))
            if writer is None:
                x[jv[0]:jv[-1] + 1, iu[0]:iu[-1] + 1] = xs
                wk[jv[0]:jv[-1] + 1, iu[0]:iu[-1] + 1] = ws
                for name, a in parts.items():
                    a[jv[0]:jv[-1] + 1, iu[0]:iu[-1] + 1] = res[name].reshape(
                        sub + a.shape[2:])
            else:  # nodes not good get a placeholder, replaced by a neighbour's below
                ws = np.where(g[..., None], ws, 1.0 / k)
                writer.write_nodes(jv[0], iu[0], xs[..., 0], xs[..., 1], ws)
            bar.update()

        run_ordered(engine, tasks(), on_result)
        bar.close()
        if not good.any():
            raise LensFitError(f"{volume.name}: no node pixel has a usable LTC at any depth")
        bad = ~good
        if bad.any():
            near = ndimage.distance_transform_edt(bad, return_distances=False,
                                                  return_indices=True)
            flat = (near[0] * len(nu) + near[1]).ravel()
            del near
            fill = np.flatnonzero(bad.ravel())  # the sources are good nodes
            if writer is None:
                x.reshape(-1, k, 2)[fill] = x.reshape(-1, k, 2)[flat[fill]]
                wk.reshape(-1, k)[fill] = wk.reshape(-1, k)[flat[fill]]
            else:
                writer.copy_nodes(fill, flat[fill])
            del flat
        trans = _transmittance(volume, geom.centroids.status, nu, nv)
        offset = None
        if slope_term is not None:
            def focus(x_mm, y_mm):  # where the lens file's samples will aim
                return aim_depths(zones, geom.focus_distance_mm, x_mm, y_mm)

            moment = np.empty(shape + (2,))
            step = max(1, GRID_PIXELS // len(nu))  # node rows per block
            for j0 in range(0, len(nv), step):
                j1 = min(len(nv), j0 + step)
                xs, ys, ws = (writer.read_rows(j0, j1) if writer is not None
                              else (x[j0:j1, ..., 0], x[j0:j1, ..., 1], wk[j0:j1]))
                moment[j0:j1] = sample_moment(xs, ys, ws, focus)
            offset = aim_offsets(slope_term, moment, good,
                                 cfg.aim_offset_sigma_px / cfg.grid_step)
            del moment, slope_term
        meta = {"source": volume.name, "config": cfg.model_dump(mode="json"),
                "summary_at_fit": None, "focus_zone_fit": zone_fit}
        fields_ = dict(focus_distance_mm=geom.focus_distance_mm,
                       optical_centre_mm=geom.centre.position, camera_size=volume.camera_size,
                       transmittance=trans, interpolation=cfg.interpolation,
                       camera_matrix=geom.camera_matrix, dist_coeffs=geom.dist_coeffs,
                       metadata=meta, focus_zones_mm=zones, aim_offset=offset)
        if writer is None:
            lens = MeasuredLens(node_u=nu.astype(np.float64), node_v=nv.astype(np.float64),
                                aperture_x_mm=x[..., 0], aperture_y_mm=x[..., 1], weights=wk,
                                **fields_)
            pix = (nv[:, None] * w + nu[None, :]).ravel()
            aps = ApertureSet(pix, None, parts["weight"].reshape(len(pix), -1),
                              parts["coverage"].reshape(len(pix), -1), None,
                              parts["weight"].reshape(len(pix), -1).sum(axis=1) > 0,
                              parts["mean"].reshape(-1, 2), parts["cov"].reshape(-1, 2, 2))
            result = LensResult(cfg, geom, grid, nu, nv, aps, lens, int(bad.sum()))
            meta["summary_at_fit"] = result.summary()
            return result
        result = LensResult(cfg, geom, grid, nu, nv, None, None, int(bad.sum()),
                            lens_path=Path(out))
        meta["summary_at_fit"] = result.summary()
        writer.close(**fields_)
        writer = None
        return result
    finally:
        if writer is not None:
            writer.abort()


def _centre_radius_mm(geom: LensGeometry) -> float:
    """A start for the pupil radius, mm: the uniform disk's ``sqrt(2 trace(cov))`` of the
    LTC's second moments at the principal point's pixel, scaled to the aperture plane (the
    median over its depths; the blur of the LCD and camera pixels is left in)."""
    c = geom.centroids
    d = len(c.depths_mm)
    w, h = geom.camera_size
    u, v = np.clip(np.rint(geom.camera_matrix[:2, 2]).astype(np.int64), 0, [w - 1, h - 1])
    mom = c.moments_px2.reshape(d, -1, 3)[:, v * w + u].astype(np.float64)
    s = ap.scale_ratio(c.depths_mm, geom.focus_plane_z_mm, float(geom.centre.position[2]))
    var = (mom[:, 0] + mom[:, 1]) * (c.pitch_mm * s) ** 2
    return float(np.sqrt(2.0 * np.nanmedian(var))) if np.isfinite(var).any() else 1.0


def _transmittance(volume: LtcVolume, status: np.ndarray, nu: np.ndarray,
                   nv: np.ndarray) -> np.ndarray:
    """Relative transmittance of the nodes (Gv, Gu): each pixel's median gain over its
    valid depths (``status`` (D, H, W) STATUS_OK), over the sensor's maximum after a 3 x 3
    median; read and filtered in row blocks (one float64 map of the sensor, no other
    sensor-wide temporaries)."""
    w, h = volume.camera_size
    # column-major: the layout the lens file has always stored (numpy's result of
    # ``tg[nv][:, nu]``), so that the array can be the nodes' own when every pixel is one
    tg = np.zeros((h, w), order="F")
    rows = tile_shape(volume)[0]
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        gain = np.where(status[:, r0:r1] == STATUS_OK,
                        np.asarray(volume.gain[:, r0:r1], dtype=np.float64), np.nan)
        tg[r0:r1] = np.nan_to_num(np.nanmedian(
            np.where(np.isfinite(gain).any(axis=0), gain, 0.0), axis=0))
    norm = -np.inf
    for r0 in range(0, h, rows):  # the 3 x 3 median of each block with its neighbour rows
        r1 = min(h, r0 + rows)
        a0, a1 = max(0, r0 - 1), min(h, r1 + 1)
        med = ndimage.median_filter(tg[a0:a1], size=3)[r0 - a0:r1 - a0]
        norm = max(norm, float(med.max()))
    if norm <= 0:
        return np.ones((len(nv), len(nu)), order="F")
    out = tg if (len(nv), len(nu)) == (h, w) else tg[nv][:, nu]  # every pixel a node: tg
    out /= norm
    return out
