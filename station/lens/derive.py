"""The lens model file from the lens's geometry and its LTCs (docs/optics.md section 6).

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
the true lens's, ~30 um with both changes (docs/decisions 0002).
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

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from tqdm import tqdm

from sim.optics.lens_file import LensFileWriter
from sim.optics.measured_lens import MeasuredLens, aim_depths
from sim.optics.projection import pixel_to_normalized
from station.compute import Engine, run_ordered
from station.lens import aperture as ap
from station.lens.centroids import STATUS_OK
from station.lens.geometry import LensFitConfig, LensFitError, LensGeometry, fit_geometry
from station.lens.jobs import (
    EXTENT_PERCENTILE,
    GRID_MARGIN,
    GRID_PIXELS,
    MIN_COVERAGE,
    ApertureJob,
    ApertureSet,
    aperture_block,
    aperture_grid,
    aperture_job,
    aperture_set,
    pixel_inputs,
    tile_groups,
    tile_shape,
)
from station.lens.rayfit import (
    aim_offsets,
    local_plane_fit,
    local_ray_centres,
    local_ray_slopes,
    sample_moment,
)
from station.lens.result import (
    RESIDUAL_PIXELS,
    LensResult,
    LensSummary,
    _residual_stats,
    node_positions,
)
from station.lens.zoned import CENTRE_PIXELS, MISS_TERMS, shift_zones, zoned_centre
from station.lens.zones import fit_focus_zones
from station.ltc.store import LtcVolume

__all__ = [
    "CENTRE_PIXELS", "EXTENT_PERCENTILE", "GRID_MARGIN", "GRID_PIXELS", "MIN_COVERAGE",
    "MISS_TERMS", "RESIDUAL_PIXELS", "ApertureJob", "ApertureSet", "LensResult", "LensSummary",
    "aim_offsets",
    "aperture_block", "aperture_grid", "aperture_job", "aperture_set", "derive_lens",
    "local_plane_fit", "local_ray_centres", "local_ray_slopes", "node_positions",
    "pixel_inputs", "sample_moment", "shift_zones", "tile_groups", "tile_shape",
    "zoned_centre", "_residual_stats", "_transmittance",
]


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


def _derive(volume: LtcVolume, cfg: LensFitConfig, K: np.ndarray | None,
            dist: np.ndarray | None, progress: bool, engine: Engine,
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
            if found is not None and cfg.centre_method == "rays":
                # the principal-ray intersection asked for: the zones, not the pinhole refit
                zones, zone_fit = found[0], {**found[1], "centre_shift_mm": 0.0}
            elif found is not None:
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

        def tasks() -> Iterator[tuple[tuple[np.ndarray, np.ndarray],
                                      Callable[..., dict[str, np.ndarray]], tuple[Any, ...]]]:
            for r0, r1, c0, c1, jv, iu in blocks:
                pix = (nv[jv][:, None] * w + nu[iu][None, :]).ravel()
                if slope_term is not None:
                    uv = np.stack([pix % w, pix // w], axis=1).astype(np.float64)
                    xn = pixel_to_normalized(uv, geom.known_camera_matrix(),
                                             geom.dist_coeffs)
                    slope_term[jv[0]:jv[-1] + 1, iu[0]:iu[-1] + 1] = (
                        local_ray_slopes(geom, pix, cfg.ray_window_px) - xn
                    ).reshape(len(jv), len(iu), 2)
                yield ((jv, iu), aperture_block,
                       (volume, job, r0, r1, c0, c1, pix, pixel_inputs(geom, pix, cfg)))

        def on_result(key: tuple[np.ndarray, np.ndarray], res: dict[str, np.ndarray]) -> None:
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
            def focus(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray | float:
                # where the lens file's samples will aim
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
        fields_: dict[str, Any] = dict(focus_distance_mm=geom.focus_distance_mm,
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
            meta["summary_at_fit"] = result.summary().to_json()
            return result
        assert out is not None  # the writer's file
        result = LensResult(cfg, geom, grid, nu, nv, None, None, int(bad.sum()),
                            lens_path=Path(out))
        meta["summary_at_fit"] = result.summary().to_json()
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
    u, v = np.clip(np.rint(geom.known_camera_matrix()[:2, 2]).astype(np.int64), 0,
                   [w - 1, h - 1])
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
