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
``derive_lens`` runs the whole chain from an LTC volume.

Nodes: every ``grid_step``-th pixel in u and v, plus the last column and row. A node without
a usable principal ray (flagged) or without a fused distribution takes the samples of the
nearest node that has one; the file's metadata lists how many were filled.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage
from tqdm import tqdm

from sim.optics.measured_lens import MeasuredLens
from station.lens import aperture as ap
from station.lens.centroids import rows_per_read, window_stats
from station.ltc.store import LtcVolume
from station.lens.geometry import (
    LensFitConfig,
    LensFitError,
    LensGeometry,
    fit_geometry,
    footprint_mm,
)
from station.lens.rays import FLAG_BAD_FIT, FLAG_FEW_DEPTHS, FLAG_OUTLIER

GRID_MARGIN = 1.2  # aperture grid half-width over the largest pupil extent seen
EXTENT_PERCENTILE = 99.5
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
    """A grid covering every usable pixel's scaled LTC (robust maximum extent, with margin)."""
    c, rays = geom.centroids, geom.rays
    d = len(c.depths_mm)
    zc = float(geom.centre.position[2])
    s = ap.scale_ratio(c.depths_mm, geom.focus_plane_z_mm, zc)
    use = rays.used & rays.usable[None]  # not empty: the centre needed usable rays
    mom = c.moments_px2.reshape(d, -1, 3) * c.pitch_mm**2 * (s**2)[:, None, None]
    lam = 0.5 * (mom[..., 0] + mom[..., 1]) + np.hypot(0.5 * (mom[..., 0] - mom[..., 1]),
                                                       mom[..., 2])
    a = rays.xy_at(zc) - geom.centre.position[:2]
    reach = np.abs(a).max(axis=1)[None] + 2.0 * np.sqrt(np.maximum(lam, 0.0))
    reach = reach + 0.5 * c.pitch_mm * np.abs(s)[:, None]
    half = GRID_MARGIN * float(np.percentile(reach[use], EXTENT_PERCENTILE))
    return ap.ApertureGrid(half, cfg.aperture_cells)


def _row_blocks(pixels: np.ndarray, width: int,
                max_rows: int) -> Iterator[tuple[int, int, np.ndarray]]:
    """Blocks of at most ``max_rows`` camera rows holding the pixels: (r0, r1, indices)."""
    rows = pixels // width
    start = 0
    order = np.argsort(rows, kind="stable")
    while start < len(order):
        r0 = rows[order[start]]
        stop = start
        while stop < len(order) and rows[order[stop]] < r0 + max_rows:
            stop += 1
        yield int(r0), int(rows[order[stop - 1]]) + 1, order[start:stop]
        start = stop


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
    to the centre) averages out."""
    rays = geom.rays
    zc = float(geom.centre.position[2])
    own = rays.xy_at(zc) - geom.centre.position[:2]
    return local_plane_fit(own, rays.var_at(zc), rays.usable, geom.camera_size, pixels,
                           radius_px)


def aperture_set(volume: LtcVolume, geom: LensGeometry, grid: ap.ApertureGrid,
                 pixels: np.ndarray, cfg: LensFitConfig | None = None,
                 keep_depths: bool = False, progress: bool = False,
                 keep_fused: bool = True,
                 on_chunk: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                     np.ndarray], None] | None = None) -> ApertureSet:
    """Scale, resample and fuse the LTC of the given flat pixels onto the aperture plane
    (``progress``: a bar over the row blocks read).

    Streams: camera rows are read in chunk-aligned blocks and nodes fused
    ``cfg.nodes_per_chunk`` at a time; ``on_chunk(idx, fused, ok, mean, cov)`` is called per
    chunk with the positions ``idx`` in ``pixels``, their fused distributions (m, G, G) and
    their ``ok``, ``mean``, ``cov``. ``keep_fused=False`` keeps no (n, G, G) array (``fused``
    is then None), so memory grows only by (n, 2, 2)-sized arrays with the nodes."""
    cfg = cfg or LensFitConfig()
    pixels = np.asarray(pixels, dtype=np.int64).ravel()
    c, rays = geom.centroids, geom.rays
    d, n, g = len(c.depths_mm), len(pixels), grid.cells
    w_cam = volume.camera_size[0]
    zc = float(geom.centre.position[2])
    s = ap.scale_ratio(c.depths_mm, geom.focus_plane_z_mm, zc)
    fp = footprint_mm(c.depths_mm, zc, geom.camera_matrix)
    rot2 = geom.rotation[:2, :2]
    u, _, vt = np.linalg.svd(rot2)
    rot2 = u @ vt  # in-plane part of the station-to-camera rotation
    per_depth = np.zeros((n, d, g, g)) if keep_depths else None
    weight = np.zeros((n, d))
    coverage = np.zeros((n, d))
    fused = np.zeros((n, g, g)) if keep_fused else None
    mean, cov = np.zeros((n, 2)), np.zeros((n, 2, 2))
    mom = c.moments_px2.reshape(d, -1, 3)
    blocks = list(_row_blocks(pixels, w_cam, rows_per_read(volume)))
    for r0, r1, sel in tqdm(blocks, desc="lens: aperture", unit="block",
                            disable=None if progress else True):
        ltc = np.asarray(volume.ltc[:, r0:r1])  # store dtype: converted per node chunk
        origin = np.asarray(volume.origin[:, r0:r1], dtype=np.int64)
        noise = np.asarray(volume.noise[:, r0:r1], dtype=np.float64)
        ltc = ltc.reshape(d, -1, *ltc.shape[-2:])
        origin = origin.reshape(d, -1, 2)
        noise = noise.reshape(d, -1)
        for k0 in range(0, len(sel), cfg.nodes_per_chunk):
            idx = sel[k0 : k0 + cfg.nodes_per_chunk]
            pix = pixels[idx]
            loc = pix - r0 * w_cam
            m_all = np.zeros((len(idx), d, g, g))
            a_c = local_ray_centres(geom, pix, cfg.ray_window_px)
            for i in range(d):
                used = rays.used[i, pix] & rays.usable[pix]
                if not used.any():
                    continue
                h = ltc[i, loc].astype(np.float64)
                st = window_stats(np.where(used[:, None, None], h, np.nan), noise[i, loc])
                hh = np.where(st.region, h, 0.0)
                # each depth's LTC is placed by its own centroid onto the principal ray at
                # the centre's plane: the depths' noisy residuals (x |s_i| ~ 5 at the
                # extreme depths) neither shift nor blur the fused distribution
                at_depth = rays.xy_ref[pix] + rays.slope[pix] * (c.depths_mm[i]
                                                                 - rays.z_ref[pix])[:, None]
                own = (st.centroid + origin[i, loc]) * c.pitch_mm
                at_depth = np.where(np.isfinite(own), own, at_depth)
                m = ap.resample(hh, origin[i, loc], at_depth, a_c, s[i], c.pitch_mm,
                                grid, rot2, cfg.supersample)
                cov_i = m.sum(axis=(1, 2))
                coverage[idx, i] = np.where(used, cov_i, 0.0)
                m_all[:, i] = m / np.where(cov_i > 0, cov_i, 1.0)[:, None, None]
            mm = mom[:, pix] * (c.pitch_mm * s)[:, None, None] ** 2
            none = ~np.isfinite(mm[..., 0]).any(axis=0)  # no depth with signal: any cov
            mm[:, none] = [1.0, 1.0, 0.0]
            cov2 = np.nanmedian(np.stack([mm[..., 0], mm[..., 2], mm[..., 2], mm[..., 1]],
                                         axis=-1), axis=0).reshape(-1, 2, 2)
            blur, nse = ap.depth_errors(noise[:, loc].T, s, c.pitch_mm, fp, cov2, grid.cell_mm)
            wd = ap.fusion_weights(blur, nse, coverage[idx] > MIN_COVERAGE)
            weight[idx] = wd
            acc = np.einsum("nd,ndij->nij", wd, m_all)
            tot = wd.sum(axis=1)
            fz = acc / np.where(tot > 0, tot, 1.0)[:, None, None]
            if fused is not None:
                fused[idx] = fz
            if per_depth is not None:
                per_depth[idx] = m_all
            ok_c = wd.sum(axis=1) > 0
            _, cov_c = _moments(fz, wd, ok_c, grid, c.pitch_mm * s, fp * s, cfg.deblur)
            # the samples' centroid is the principal ray on the centre's plane (camera axes):
            # the fit over all depths and the pixel's neighbours, not the fused grid's mean
            mean_c = a_c @ rot2.T
            mean[idx], cov[idx] = mean_c, cov_c
            if on_chunk is not None:
                on_chunk(idx, fz, ok_c, mean_c, cov_c)
    ok = weight.sum(axis=1) > 0
    return ApertureSet(pixels, per_depth, weight, coverage, fused, ok, mean, cov)


def _moments(fused: np.ndarray, weight: np.ndarray, ok: np.ndarray, grid: ap.ApertureGrid,
             pitch_scaled: np.ndarray, footprint_scaled: np.ndarray,
             deblur: bool) -> tuple[np.ndarray, np.ndarray]:
    """Target mean (m, 2) and covariance (m, 2, 2) mm of fused distributions (m, G, G):
    the grid moments plus the cell's own variance, less (``deblur``) the LCD-pixel and
    camera-pixel blurs of the depths by their fusion weights (m, D)."""
    mean, cov = ap.grid_moments(fused, grid)
    cov = cov + np.eye(2) * grid.cell_mm**2 / 12.0
    if deblur:
        wn = weight / np.where(ok, weight.sum(axis=1), 1.0)[:, None]
        blur = (pitch_scaled ** 2 + footprint_scaled ** 2) / 12.0
        cov = cov - np.eye(2) * (wn @ blur)[:, None, None]
        val, vec = np.linalg.eigh(cov)
        val = np.maximum(val, 1e-6 * np.maximum(val.max(axis=1, keepdims=True), 1e-12))
        cov = np.einsum("nij,nj,nkj->nik", vec, val, vec)
    return mean, cov


def node_positions(size: int, step: int) -> np.ndarray:
    """Node coordinates along one axis: every ``step``-th pixel and the last one."""
    a = np.arange(0, size, step)
    return a if a[-1] == size - 1 else np.append(a, size - 1)


@dataclass
class LensResult:
    """The derivation's result: geometry, grid, nodes, fused distributions, the lens."""

    config: LensFitConfig
    geometry: LensGeometry
    grid: ap.ApertureGrid
    node_u: np.ndarray
    node_v: np.ndarray
    apertures: ApertureSet
    lens: MeasuredLens
    filled_nodes: int
    figures: list[Path] = field(default_factory=list)

    def summary(self) -> dict:
        """A JSON-able report of what was measured."""
        g = self.geometry
        r = g.rays
        res = r.residual_norm()
        res = res[np.isfinite(res) & r.usable[None]]
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
            "ray_residual_mean_mm": float(res.mean()) if res.size else None,
            "ray_residual_std_mm": float(res.std()) if res.size else None,
            "ray_residual_count": int(res.size),
            "pixels": len(fl),
            "pixels_usable": int(r.usable.sum()),
            "pixels_few_depths": int(((fl & FLAG_FEW_DEPTHS) > 0).sum()),
            "pixels_outlier_removed": int(((fl & FLAG_OUTLIER) > 0).sum()),
            "pixels_bad_fit": int(((fl & FLAG_BAD_FIT) > 0).sum()),
            "depths_mm": g.centroids.depths_mm.tolist(),
            "samples": self.lens.samples,
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


def derive_lens(volume: LtcVolume, config: LensFitConfig | None = None,
                K: np.ndarray | None = None, dist: np.ndarray | None = None,
                progress: bool = False) -> LensResult:
    """The measured lens of an LTC volume (see the module docstrings for every step);
    ``progress`` shows bars over the centroid and aperture passes."""
    cfg = config or LensFitConfig()
    geom = fit_geometry(volume, cfg, K, dist, progress=progress)
    grid = aperture_grid(geom, cfg)
    w, h = volume.camera_size
    nu, nv = node_positions(w, cfg.grid_step), node_positions(h, cfg.grid_step)
    pix = (nv[:, None] * w + nu[None, :]).ravel()
    x = np.zeros((len(pix), cfg.samples, 2))
    wk = np.zeros((len(pix), cfg.samples))
    usable = geom.rays.usable[pix]
    buf: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []

    def sample(flush: bool = False) -> None:
        """K samples of the buffered good nodes, ``nodes_per_chunk`` at a time in node order."""
        while buf and (flush or sum(len(b[0]) for b in buf) >= cfg.nodes_per_chunk):
            sl, fz, mu, cv = (np.concatenate(a) for a in zip(*buf))
            buf.clear()
            take = cfg.nodes_per_chunk
            if len(sl) > take:
                buf.append((sl[take:], fz[take:], mu[take:], cv[take:]))
            sl, fz, mu, cv = sl[:take], fz[:take], mu[:take], cv[:take]
            xs, ws = ap.kmeans_samples(fz, grid, cfg.samples, cfg.kmeans_iterations)
            x[sl], wk[sl] = ap.canonical_order(ap.match_moments(xs, ws, mu, cv), ws)

    def on_chunk(idx, fz, ok, mu, cv) -> None:
        keep = ok & usable[idx]
        if keep.any():
            buf.append((idx[keep], fz[keep], mu[keep], cv[keep]))
            sample()

    aps = aperture_set(volume, geom, grid, pix, cfg, progress=progress, keep_fused=False,
                       on_chunk=on_chunk)
    sample(flush=True)
    good = aps.ok & usable
    if not good.any():
        raise LensFitError(f"{volume.name}: no node pixel has a usable LTC at any depth")
    shape = (len(nv), len(nu))
    bad = ~good.reshape(shape)
    if bad.any():
        near = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
        flat = (near[0] * len(nu) + near[1]).ravel()
        fill = np.flatnonzero(bad.ravel())  # in place: the sources are good nodes
        x[fill], wk[fill] = x[flat[fill]], wk[flat[fill]]
    gain = np.where(geom.centroids.valid, _gain(volume), np.nan)
    tg = np.nanmedian(np.where(np.isfinite(gain).any(axis=0), gain, 0.0), axis=0)
    tg = np.nan_to_num(tg)
    norm = float(ndimage.median_filter(tg, size=3).max())
    trans = (tg / norm if norm > 0 else np.ones_like(tg))[nv][:, nu]
    meta = {"source": volume.name, "config": cfg.model_dump(mode="json"),
            "summary_at_fit": None}
    lens = MeasuredLens(
        focus_distance_mm=geom.focus_distance_mm, optical_centre_mm=geom.centre.position,
        camera_size=volume.camera_size, node_u=nu.astype(np.float64),
        node_v=nv.astype(np.float64), aperture_x_mm=x[..., 0].reshape(shape + (-1,)),
        aperture_y_mm=x[..., 1].reshape(shape + (-1,)), weights=wk.reshape(shape + (-1,)),
        transmittance=trans, interpolation=cfg.interpolation,
        camera_matrix=geom.camera_matrix, dist_coeffs=geom.dist_coeffs, metadata=meta,
    )
    result = LensResult(cfg, geom, grid, nu, nv, aps, lens, int(bad.sum()))
    meta["summary_at_fit"] = result.summary()
    return result


def _gain(volume: LtcVolume) -> np.ndarray:
    w, h = volume.camera_size
    out = np.empty((len(volume.depths_mm), h, w))
    for r0 in range(0, h, 64):
        out[:, r0 : r0 + 64] = np.asarray(volume.gain[:, r0 : r0 + 64], dtype=np.float64)
    return out
