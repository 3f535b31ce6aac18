"""The aperture pass's jobs: the aperture grid, the blocks of node pixels by stored chunk,
and each block's LTCs scaled, resampled and fused onto the aperture plane with its K samples
(``aperture_block``, a pure function every engine runs)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from sim.optics.lens_moments import match_moments
from station.lens import aperture as ap
from station.lens.centroids import region_stats
from station.lens.geometry import LensFitConfig, LensGeometry, footprint_mm
from station.lens.rayfit import local_ray_centres
from station.lens.rays import UNUSABLE
from station.ltc.store import LtcVolume

GRID_MARGIN = 1.2  # aperture grid half-width over the largest pupil extent seen
EXTENT_PERCENTILE = 99.5
GRID_PIXELS = 1 << 16  # pixels per block of the grid extent's temporaries (~1 kB each)
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
    fused: np.ndarray | None
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


def tile_groups(volume: LtcVolume,
                pixels: np.ndarray) -> list[tuple[np.ndarray, tuple[int, int, int, int]]]:
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
        r0, r1, c0, c1 = tile
        res = aperture_block(volume, job, r0, r1, c0, c1, pix, pixel_inputs(geom, pix, cfg))
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
    (docs/decisions 0015)."""
    mean, cov = ap.grid_moments(fused, grid)
    cov = cov - np.eye(2) * grid.cell_mm**2 / 12.0
    if deblur:
        wn = weight / np.where(ok, weight.sum(axis=1), 1.0)[:, None]
        blur = (2.0 * pitch_scaled ** 2 + footprint_scaled ** 2) / 12.0
        cov = cov - np.eye(2) * (wn @ blur)[:, None, None]
    val, vec = np.linalg.eigh(cov)
    val = np.maximum(val, 1e-6 * np.maximum(val.max(axis=1, keepdims=True), 1e-12))
    return mean, np.einsum("nij,nj,nkj->nik", vec, val, vec)
