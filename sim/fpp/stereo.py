"""Stereo correspondence by equal projector coordinate along epipolar lines, and triangulation.

Method (``stereo_cloud``), for the maps of projector coordinate ``u_p`` (NaN = invalid) of two
cameras, each camera in turn the reference and the other the search camera:

1. ``cv2.stereoRectify`` gives the rectified frame (rows are epipolar lines).
2. Every valid reference pixel is used **at its own centre, with its own measured phase**: no
   interpolation on the reference side. Its rectified coordinates follow from the calibration
   (undistortion, rotation), exactly.
3. A coarse match: the search map resampled on the rectified grid (``interpolation_order``
   1 or 3, float64 maps as ``cv2.initUndistortRectifyMap``'s) is searched along the rectified
   row nearest the pixel's for every monotone run holding its phase (binary search).
4. The sub-pixel match is where a **local model of the search camera's phase** equals the
   reference phase, on the reference pixel's own epipolar line (its exact rectified row, mapped
   into the search image through the distortion): the model is the least-squares quadratic
   over the 3 x 3 original pixels around the nearest search pixel (``local_phase_model``),
   solved by Newton steps that re-centre on the nearest pixel; where the phase falls in the
   step between two neighbouring pixels' models at their common cell edge, the match is that
   edge. The coarse step only picks the run; the result does not depend on the interpolation
   order.
5. Triangulation in the rectified frame (``triangulate``, linear least squares as
   ``cv2.triangulatePoints``), then to the world frame.

Why it is unbiased. The reference phase is measured, not interpolated. The search model's
error is the part of the phase its quadratic cannot follow: third-order terms, which on the
symmetric 3 x 3 stencil are odd in the offset from the model's centre pixel, so their effect on
the matched position averages to zero over the offsets the pixels of a surface fall at (a
linear interpolation's error, in contrast, has one sign between nodes: ``-t (1 - t) phi'' / 2``,
and biased the diameter of a sphere by micrometres to tens of micrometres as the sphere spans
hundreds to tens of pixels). Running both directions puts both cameras' pixels in the cloud.

Consistency checks: a pixel is used only where its whole 3 x 3 stencil is valid and the
model's RMS residual is within ``max_model_residual`` times the camera's median (mixed pixels
at silhouettes, steep flanks, phase errors); the search runs must be monotone and the model's
slope along the row non-zero at the converged match, inside the centre pixel's cell; where a
row holds the phase more than once, the candidate whose point projects into the projector
closest to ``u_p`` wins (without a projector calibration such pixels are dropped), and points
further than ``max_projector_error_px`` are dropped; left-right: a match must be confirmed
by the other direction's matches (interpolated at the matched position: bilinear, or an
affine fit to the 4 x 4 around it at the edge of those matches) within ``max_lr_error_px``;
continuity: a point whose 8 neighbours are not all reconstructed, or whose range differs from
one of theirs by more than ``max_range_step`` pixel footprints, is dropped (silhouettes and
the points a blurred silhouette leaves between two surfaces). A point that cannot be made
right is dropped, not kept wrong.

``camera_projector_cloud`` triangulates one camera against the projector (ray and the
projector's plane of constant coordinate, refined through the projector's distortion).

The steps live in :mod:`sim.fpp.rectify` (1), :mod:`sim.fpp.match` (2-4 and the checks) and
:mod:`sim.fpp.triangulation` (5); their public names are importable from here too, and
``PointCloud`` from :mod:`sim.fpp.cloud`.
"""

from __future__ import annotations

import numpy as np

from sim.errors import SimInputError
from sim.fpp.cloud import PointCloud
from sim.fpp.match import (
    MEDIAN_CHI_RATIO,
    MODEL_DEGREE,
    MODEL_RADIUS,
    _lr_consistent,
    _masked,
    _match_direction,
    _Side,
    local_phase_model,
    match_row,
    phase_noise_px,
    pixel_footprint_correction,
    usable_pixels,
)
from sim.fpp.rectify import (
    Rectification,
    rectify_map,
    relative_pose,
    sample_image,
    stereo_rectification,
)
from sim.fpp.triangulation import (
    STEREO_SENSITIVITY_PX,
    camera_projector_cloud,
    grid_normals,
    triangulate,
)
from sim.optics.projection import camera_to_world
from sim.optics.rig import DeviceCalibration

__all__ = [
    "MEDIAN_CHI_RATIO", "MODEL_DEGREE", "MODEL_RADIUS", "STEREO_SENSITIVITY_PX", "PointCloud",
    "Rectification", "camera_projector_cloud", "grid_normals", "local_phase_model", "match_row",
    "phase_noise_px", "pixel_footprint_correction", "rectify_map", "relative_pose",
    "sample_image", "stereo_cloud", "stereo_rectification", "triangulate", "usable_pixels",
]


def stereo_cloud(
    coord1: np.ndarray,
    coord2: np.ndarray,
    cam1: DeviceCalibration,
    cam2: DeviceCalibration,
    projector: DeviceCalibration | None = None,
    axis: str = "u",
    max_projector_error_px: float = 0.5,
    quality1: np.ndarray | None = None,
    order: int = 3,
    quality2: np.ndarray | None = None,
    max_lr_error_px: float = 0.25,
    max_model_residual: float = 5.0,
    max_range_step: float = 8.0,
    residual1: np.ndarray | None = None,
    residual2: np.ndarray | None = None,
    rejected: list[dict[str, int]] | None = None,
) -> PointCloud:
    """Point cloud from the projector-coordinate maps (H, W) of two cameras (NaN = invalid).

    projector : its calibration resolves ambiguous matches and rejects points that reproject
        further than ``max_projector_error_px`` from the measured coordinate along ``axis``.
    quality1, quality2 : optional per-pixel quality (e.g. modulation) of each camera, returned
        per point (of the point's reference pixel).
    order : interpolation of the search map for the coarse match, 1 linear or 3 cubic
        (``sample_image``); the sub-pixel position does not depend on it.
    max_lr_error_px : left-right consistency tolerance, pixels.
    max_model_residual : pixels whose local phase model fits worse than this many times the
        median over the camera (silhouettes, mixed pixels, phase errors) are not used.
    max_range_step : points whose range differs from a neighbour's by more than this many
        pixel footprints, or that lack a neighbour, are dropped (depth steps, edges; 8 passes
        surfaces up to 83 degrees oblique; ``inf`` skips the check).
    residual1, residual2 : each map's local phase model residual (H, W) projector px as
        measured, when the maps were corrected afterwards (``pixel_footprint_correction``,
        whose per-pixel shift estimate roughens the map): which pixels are usable, the
        phase noise and the ``phase_error`` field then come from the measurement.
    rejected : if given, filled with one dict per camera: the pixels each check dropped with
        that camera as the reference (``stereo_model_residual``, ``stereo_no_match``,
        ``stereo_projector_error``, ``stereo_left_right``, ``stereo_range_step``).
    Returns points in the world frame, from both directions, with normals (facing each point's
    reference camera), quality and per-point fields (see ``PointCloud``).
    """
    for cam, c in ((cam1, coord1), (cam2, coord2)):
        if np.shape(c) != (cam.height, cam.width):
            raise SimInputError(
                f"camera '{cam.name}': projector-coordinate map has shape {np.shape(c)}, "
                f"its calibration expects (height, width) = ({cam.height}, {cam.width})"
            )
    rect = stereo_rectification(cam1, cam2, np.isfinite(coord1), np.isfinite(coord2))
    sides = []
    for coord, cam, r, p, cols, measured_res in (
            (coord1, cam1, rect.R1, rect.P1, rect.cols1, residual1),
            (coord2, cam2, rect.R2, rect.P2, rect.cols2, residual2)):
        coef, res = local_phase_model(coord)
        if measured_res is not None:
            res = np.where(np.isfinite(res), measured_res, np.nan)
        sides.append(_Side(np.asarray(coord, dtype=np.float64), cam, r, p, cols, coef, res))
    usable = []
    for s in sides:
        if not np.isfinite(s.residual).any():
            raise SimInputError(f"camera '{s.cam.name}': no valid pixel with 8 valid neighbours to "
                                "match")
        usable.append(usable_pixels(s.residual, max_model_residual))
    noise = [phase_noise_px(s.residual, q) for s, q in zip(sides, (quality1, quality2), strict=True)]
    # the search model is used at the matched pixel too: mask its coefficients
    sides = [_masked(s, u) for s, u in zip(sides, usable, strict=True)]
    tally = [dict.fromkeys(("stereo_model_residual", "stereo_no_match", "stereo_projector_error",
                             "stereo_left_right", "stereo_range_step"), 0) for _ in sides]
    for t, s, u in zip(tally, sides, usable, strict=True):
        t["stereo_model_residual"] = int(np.isfinite(s.coord).sum() - u.sum())
    results = []
    for a, b in ((0, 1), (1, 0)):
        flat, xy_ref, x_s, uv_s, slope = _match_direction(sides[a], sides[b], rect.rows, order,
                                                         usable[a])
        xy_s = np.stack([x_s, xy_ref[:, 1]], axis=1)
        pa, pb = (rect.P1, rect.P2) if a == 0 else (rect.P2, rect.P1)
        pts_rect = triangulate(pa, pb, xy_ref, xy_s)
        world = camera_to_world(pts_rect @ rect.R1, cam1.R_array, cam1.T_array)
        # mm per projector px of phase error: the search position moves by 1 / slope
        moved = triangulate(pa, pb, xy_ref, xy_s + [STEREO_SENSITIVITY_PX, 0.0])
        sens = np.linalg.norm(moved - pts_rect, axis=1) / STEREO_SENSITIVITY_PX / np.abs(slope)
        w = sides[a].coord.shape[1]
        measured = sides[a].coord.ravel()[flat]
        if projector is not None:
            k = 0 if axis == "u" else 1
            err = np.abs(projector.project(world)[:, k] - measured)
            good = err <= max_projector_error_px
        else:
            err = np.zeros(len(world))
            good = np.ones(len(world), dtype=bool)
        ranked = np.lexsort((np.where(good, err, np.inf), flat))
        first = np.r_[True, np.diff(flat[ranked]) != 0] if len(ranked) else np.zeros(0, bool)
        counts = np.diff(np.r_[np.flatnonzero(first), len(ranked)])
        chosen = ranked[first]
        if projector is None:
            chosen = chosen[counts == 1]
        tally[a]["stereo_no_match"] = int(usable[a].sum()) - len(chosen)
        tally[a]["stereo_projector_error"] = int((~good[chosen]).sum())
        chosen = chosen[good[chosen]]
        ref_pix = np.stack([flat[chosen] % w, flat[chosen] // w], axis=1).astype(np.float64)
        results.append((world[chosen], ref_pix, uv_s[chosen], sens[chosen]))
    kept = []
    for a in (0, 1):
        world, ref_pix, uv_s, sens = results[a]
        other = results[1 - a]
        hs, ws = sides[1 - a].coord.shape
        back = np.full((hs, ws, 2), np.nan)
        back[other[1][:, 1].astype(int), other[1][:, 0].astype(int)] = other[2]
        ok = _lr_consistent(uv_s, ref_pix, back, max_lr_error_px)
        tally[a]["stereo_left_right"] = int((~ok).sum())
        if np.isfinite(max_range_step):
            before = int(ok.sum())
            ok[ok] = _continuous(world[ok], ref_pix[ok], sides[a].cam, max_range_step)
            tally[a]["stereo_range_step"] = before - int(ok.sum())
        node = np.round(uv_s[ok]).astype(np.int64)
        sigma = np.hypot(noise[a][ref_pix[ok][:, 1].astype(int), ref_pix[ok][:, 0].astype(int)],
                         noise[1 - a][node[:, 1], node[:, 0]])
        kept.append((world[ok], ref_pix[ok], sens[ok] * sigma))
    if rejected is not None:
        rejected[:] = tally
    if not any(len(k[0]) for k in kept):
        raise SimInputError("stereo matching found no pixel with the same projector coordinate in "
                            "both cameras")
    points, normals, quality, camera, pixels, perr, unc = [], [], [], [], [], [], []
    for a, (world, ref_pix, u_mm) in enumerate(kept):
        cam = sides[a].cam
        iu, iv = ref_pix[:, 0].astype(int), ref_pix[:, 1].astype(int)
        grid = np.full((cam.height, cam.width, 3), np.nan)
        grid[iv, iu] = world
        points.append(world)
        normals.append(grid_normals(grid, cam.centre_world)[iv, iu])
        qa = (quality1, quality2)[a]
        quality.append(np.asarray(qa, dtype=np.float64)[iv, iu] if qa is not None
                       else np.full(len(world), np.nan))
        camera.append(np.full(len(world), a))
        pixels.append(ref_pix)
        perr.append(sides[a].residual[iv, iu])
        unc.append(u_mm)
    has_q = quality1 is not None or quality2 is not None
    pix = np.concatenate(pixels)
    return PointCloud(np.concatenate(points), np.concatenate(normals),
                      np.concatenate(quality) if has_q else None,
                      {"camera": np.concatenate(camera).astype(np.float64), "u": pix[:, 0],
                       "v": pix[:, 1], "phase_error": np.concatenate(perr),
                       "uncertainty_mm": np.concatenate(unc)})


def _continuous(world: np.ndarray, ref_pix: np.ndarray, cam: DeviceCalibration, max_step: float
                ) -> np.ndarray:
    """Points (n,) whose 8 neighbours are all reconstructed, with ranges from the camera within
    ``max_step`` pixel footprints (range / f) of theirs: the edges of what was reconstructed
    and depth steps (silhouettes, and the mixed pixels a blurred silhouette leaves between
    the surfaces) are dropped, on both sides."""
    h, w = cam.height, cam.width
    rng = np.full((h + 2, w + 2), np.nan)
    iu, iv = ref_pix[:, 0].astype(np.int64) + 1, ref_pix[:, 1].astype(np.int64) + 1
    rng[iv, iu] = np.linalg.norm(world - cam.centre_world, axis=1)
    limit = max_step * rng[iv, iu] / min(cam.K_array[0, 0], cam.K_array[1, 1])
    ok = np.ones(len(world), dtype=bool)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx or dy:
                step = np.abs(rng[iv + dy, iu + dx] - rng[iv, iu])
                ok &= step <= limit  # NaN (no neighbour) fails
    return ok
