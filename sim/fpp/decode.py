"""From fringe images to projector-coordinate maps and point clouds (the scanner's pipeline).

``decode_view`` turns one camera's image stack, taken with a ``sim.render.fringe_patterns`` set, into
per-axis projector-coordinate maps (NaN where invalid) and a modulation map; ``scan``
matches the two cameras of a rig (``sim.fpp.stereo.stereo_cloud``) or triangulates one camera
against the projector (``sim.fpp.triangulation.camera_projector_cloud``).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sim.errors import SimInputError
from sim.fpp.cloud import PointCloud
from sim.fpp.match import (
    local_phase_model,
    phase_noise_px,
    pixel_footprint_correction,
    usable_pixels,
)
from sim.fpp.phase import (
    absolute_phase_to_projector,
    gray_bits,
    gray_to_index,
    quality_mask,
    unwrap_gray_code,
    unwrap_heterodyne,
    unwrap_hierarchical,
    wrapped_phase,
)
from sim.fpp.stereo import stereo_cloud
from sim.fpp.triangulation import camera_projector_cloud, grid_normals
from sim.optics.rig import DeviceCalibration, Rig
from sim.render.fringe_patterns import GrayCodeSet, PatternDescriptor, PhaseShiftSet
from sim.tolerances import EDGE_MARGIN_PX

SENSITIVITY_PX = 1e-3
"""Projector px: step of the finite difference giving a point's sensitivity to phase error."""
MAX_FOOTPRINT_SHIFT = 0.01
"""The largest pixel-footprint correction applied, as a fraction of the finest fringe period
(the correction is a second-order shift: 99.9 % of a sphere's are below 3e-4 of it)."""



class DecodeSettings(BaseModel):
    """How fringe images are decoded and matched."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    min_modulation: float = Field(
        0.0, ge=0, description="smallest fringe amplitude B kept, image units (0: only the "
        "relative threshold applies)"
    )
    min_modulation_fraction: float = Field(
        0.05, ge=0, lt=1,
        description="smallest B kept as a fraction of the 99th percentile of B over the image",
    )
    min_contrast: float = Field(0.0, ge=0, description="smallest B / A kept")
    saturation: float | None = Field(
        None, gt=0, description="pixels reaching this value in any image are dropped, image units"
    )
    unwrap: Literal["auto", "hierarchical", "heterodyne"] = Field(
        "auto",
        description="temporal unwrapping of phase-shift sets: auto picks hierarchical when the "
        "longest period covers the projector, else heterodyne",
    )
    max_order_error: float = Field(
        0.4, gt=0, le=0.5,
        description="pixels whose temporal unwrapping missed the chosen fringe order by more "
        "than this fraction of a fringe are dropped (Gray code: right ones reach 0.25)",
    )
    max_projector_error_px: float = Field(
        0.5, gt=0, description="stereo points must reproject into the projector this close, px"
    )
    interpolation_order: Literal[1, 3] = Field(
        3, description="phase-map interpolation of the coarse stereo search: 1 linear, 3 cubic "
        "(the sub-pixel match comes from the local phase model and does not depend on it)"
    )
    max_lr_error_px: float = Field(
        0.25, gt=0, description="stereo left-right consistency tolerance, camera px"
    )
    max_model_residual: float = Field(
        5.0, gt=0, description="stereo: pixels whose local phase model fits worse than this many "
        "times the camera's median residual are not matched (silhouettes, mixed pixels)"
    )
    pixel_variance_px2: float = Field(
        0.0, ge=0, description="second moment per axis (px^2) of a camera pixel's spatial "
        "response, whose averaging of intensity and phase across the pixel is undone to second "
        "order (sim.fpp.stereo.pixel_footprint_correction): 1/12 for real cameras (a square "
        "pixel of full fill factor; Mitsuba's box filter), 0 for point-sampled renders (ours)"
    )
    max_range_step: float = Field(
        8.0, gt=0, description="stereo: points whose range differs from a neighbour's by more "
        "than this many pixel footprints, or that lack one of their 8 neighbours, are dropped "
        "(depth steps, silhouettes); inf skips the check"
    )


@dataclass(frozen=True)
class DecodedView:
    """One camera's decoded images: ``coord[axis]`` (H, W) projector coordinate in pixels along
    'u' (columns) and/or 'v' (rows), NaN where invalid; ``modulation`` (H, W) the smallest
    fringe amplitude over the phase sets, image units; ``residual[axis]`` (H, W) the local
    phase model's RMS residual of the map as decoded, projector px, where the map was then
    corrected for the pixel footprint (else empty); ``rejected`` the pixels each check
    dropped (``REJECTION_REASONS``)."""

    coord: dict[str, np.ndarray]
    modulation: np.ndarray
    residual: dict[str, np.ndarray] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)


REJECTION_REASONS = {
    "modulation": "fringe amplitude below the threshold (or contrast, saturation): dark, "
                  "shadowed or unlit",
    "fringe_order": "temporal unwrapping missed the fringe order by more than max_order_error",
    "projector_edge": "outside the projector's outer pixel centres",
    "camera_projector_model_residual": "camera against projector: local phase model missing "
                                       "or rough",
    "stereo_model_residual": "stereo: local phase model missing or rough (edges, mixed pixels)",
    "stereo_no_match": "stereo: no same phase found along the epipolar line",
    "stereo_projector_error": "stereo: the point reprojects too far from the measured phase "
                              "in the projector",
    "stereo_left_right": "stereo: the match back from the other camera lands elsewhere",
    "stereo_range_step": "stereo: a range step to a neighbour, or a neighbour missing "
                         "(silhouettes, edges)",
}
"""Why a pixel was dropped: the keys of ``ScanReport.rejected`` and their meaning."""


@dataclass(frozen=True)
class ScanReport:
    """What a scan kept and dropped: ``pixels`` per camera, ``decoded`` per camera (pixels with
    a projector coordinate after every decoding check), ``rejected`` per camera the pixels
    each check dropped (``REJECTION_REASONS``; each pixel is counted at the first check that
    drops it; the stereo checks count reference pixels of both matching directions), and
    ``points`` the cloud's size."""

    pixels: tuple[int, ...]
    decoded: tuple[int, ...]
    rejected: tuple[dict[str, int], ...]
    points: int
    pixel_variance_px2: float

    def to_json(self) -> dict:
        """The report as a JSON-able dict."""
        return {"pixels": list(self.pixels), "decoded": list(self.decoded),
                "rejected": [dict(r) for r in self.rejected], "points": self.points,
                "pixel_variance_px2": self.pixel_variance_px2}

    def lines(self) -> list[str]:
        """One line per camera: decoded pixels and the non-zero rejections, most first."""
        out = []
        for i, (n, d, r) in enumerate(zip(self.pixels, self.decoded, self.rejected, strict=True)):
            parts = ", ".join(f"{k} {v}" for k, v in sorted(r.items(), key=lambda kv: -kv[1])
                              if v)
            out.append(f"camera {i}: {d} of {n} pixels decoded; rejected: {parts or 'none'}")
        return out


def _check_stack(images: np.ndarray, descs: list[PatternDescriptor], where: str) -> np.ndarray:
    images = np.asarray(images)
    if images.ndim != 3:
        raise SimInputError(f"{where}: images must be a stack (n, H, W), got shape {images.shape}")
    if len(images) != len(descs):
        raise SimInputError(
            f"{where}: {len(images)} images, but the pattern set has {len(descs)} patterns"
        )
    return images


def _threshold(mod: np.ndarray, settings: DecodeSettings, where: str) -> float:
    top = float(np.percentile(mod, 99))
    thr = max(settings.min_modulation, settings.min_modulation_fraction * top)
    if not np.any(mod >= thr) or top <= 0:
        raise SimInputError(
            f"{where}: no pixel has a fringe modulation of {thr:g} or more (largest "
            f"{float(mod.max()):g}): the images are dark or show no fringes"
        )
    return thr


def _valid(wps, images, settings: DecodeSettings, where: str) -> tuple[np.ndarray, np.ndarray]:
    mod = np.min([w.modulation for w in wps], axis=0)
    thr = _threshold(mod, settings, where)
    peak = images.max(axis=0) if settings.saturation is not None else None
    ok = np.ones(mod.shape, dtype=bool)
    for w in wps:
        ok &= quality_mask(w, thr, settings.min_contrast, settings.saturation, peak)
    return ok, mod


def _typed(periods: list[float], extent: int) -> str:
    """Periods as typed and as fringe counts across the projector."""
    return ", ".join(f"{p:g} px = {extent / p:.4g} fringes" for p in periods)


def _decode_phase_shift(images, descs, ps: PhaseShiftSet, size, settings, where):
    groups: dict[tuple[str, float], list[int]] = defaultdict(list)
    for d in sorted(descs, key=lambda d: d.shift or 0):
        groups[(d.direction, d.period_px)].append(d.index)
    coord, wps_all, fine = {}, [], {}
    for axis in sorted({a for a, _ in groups}):
        extent = size[0] if axis == "u" else size[1]
        periods = [p for a, p in groups if a == axis]
        wps = [wrapped_phase(images[groups[(axis, p)]]) for p in periods]
        wps_all += wps
        fine[axis] = wps[int(np.argmin(periods))].modulation
        method = settings.unwrap
        if method == "auto":
            method = "hierarchical" if max(periods) >= extent else "heterodyne"
        if method == "hierarchical":
            if max(periods) < extent:
                raise SimInputError(
                    f"{where}: hierarchical unwrapping needs a period of at least {extent} px "
                    f"(1 fringe across the projector along '{axis}'); the longest is "
                    f"{max(periods):g} px ({extent / max(periods):.4g} fringes); periods are in "
                    "projector pixels, or give fringe counts as 'fringes'"
                )
            absph, oerr = unwrap_hierarchical([w.phase for w in wps], periods, extent, True)
        else:
            if len(periods) not in (2, 3):
                raise SimInputError(
                    f"{where}: {len(periods)} period(s) along '{axis}' cannot be unwrapped "
                    f"({_typed(periods, extent)}): use one period >= {extent} px (1 fringe) or "
                    "2-3 periods for heterodyne"
                )
            try:
                absph, oerr = unwrap_heterodyne([w.phase for w in wps], periods, extent, True)
            except SimInputError as exc:
                raise SimInputError(
                    f"{where}: the periods along '{axis}' ({_typed(periods, extent)}) cannot be "
                    f"unwrapped: the longest is {max(periods):g} px ({extent / max(periods):.4g} "
                    f"fringes), shorter than the {extent} px projector, and heterodyne failed "
                    f"({exc}); periods are in projector pixels, or give fringe counts as 'fringes'"
                ) from exc
        c = absolute_phase_to_projector(absph, min(periods))
        coord[axis] = np.where(oerr <= settings.max_order_error, c, np.nan)
    return coord, wps_all, fine


def _indices(descs: list[PatternDescriptor], kind: str) -> list[int]:
    """Image indices of the patterns of one kind, by bit plane then shift."""
    sel = [d for d in descs if d.kind == kind]
    sel.sort(key=lambda d: (d.bit or 0, d.shift or 0))
    return [d.index for d in sel]


def _decode_gray(images, descs, gs: GrayCodeSet, settings, where):
    coord, wps_all, fine = {}, [], {}
    for axis in sorted({d.direction for d in descs}):
        mine = [d for d in descs if d.direction == axis]
        wp = wrapped_phase(images[_indices(mine, "phase")])
        wps_all.append(wp)
        fine[axis] = wp.modulation
        gray = images[_indices(mine, "gray")]
        if gs.inverse:
            bits = gray_bits(gray, inverse=images[_indices(mine, "gray_inverse")])
        elif gs.references:
            white = images[_indices(mine, "white")[0]].astype(np.float64)
            bits = gray_bits(gray, threshold=0.5 * (white + images[_indices(mine, "black")[0]]))
        else:
            bits = gray_bits(gray, threshold=wp.offset)
        absph, oerr = unwrap_gray_code(
            wp.phase, gs.period_px, gray_to_index(bits), gs.stripe_width, return_order_error=True
        )
        c = absolute_phase_to_projector(absph, gs.period_px)
        coord[axis] = np.where(oerr <= settings.max_order_error, c, np.nan)
    return coord, wps_all, fine


def decode_view(
    images: np.ndarray,
    patterns: PhaseShiftSet | GrayCodeSet,
    projector_size: tuple[int, int],
    settings: DecodeSettings | None = None,
    where: str = "images",
) -> DecodedView:
    """Decode one camera's image stack (n, H, W) taken with ``patterns`` on a projector of
    ``projector_size`` (width, height). Errors name ``where``."""
    settings = settings or DecodeSettings()
    descs = patterns.descriptors(projector_size)
    images = _check_stack(images, descs, where)
    if isinstance(patterns, GrayCodeSet):
        coord, wps, fine = _decode_gray(images, descs, patterns, settings, where)
    else:
        coord, wps, fine = _decode_phase_shift(images, descs, patterns, projector_size, settings,
                                               where)
    ok, mod = _valid(wps, images, settings, where)
    rejected = dict.fromkeys(("modulation", "fringe_order", "projector_edge"), 0)
    residuals = {}
    for axis, c in coord.items():
        extent = projector_size[0] if axis == "u" else projector_size[1]
        # outside the edge pixels' centres the pattern stops varying and the phase is wrong
        inside = (c >= EDGE_MARGIN_PX) & (c <= extent - 1 - EDGE_MARGIN_PX)
        rejected["modulation"] += int((~ok).sum())
        rejected["fringe_order"] += int((ok & ~np.isfinite(c)).sum())
        rejected["projector_edge"] += int((ok & np.isfinite(c) & ~inside).sum())
        coord[axis] = np.where(ok & inside, c, np.nan)
        if settings.pixel_variance_px2 > 0:
            # the correction's models only where trustworthy (not at silhouettes, mixed pixels)
            _, residual = local_phase_model(coord[axis])
            usable = usable_pixels(residual, settings.max_model_residual)
            corrected = pixel_footprint_correction(np.where(usable, coord[axis], np.nan),
                                                   fine[axis], settings.pixel_variance_px2)
            # where the correction has no full 3 x 3 of usable pixels the pixel is kept as
            # measured, and the stereo checks judge it as they would with no correction:
            # dropping it here took a ring of pixels off every region, twice (here and in the
            # stereo's own local models), 64 % of a 31 px sphere's points
            # (docs/decisions/0052-pixel-footprint-keeps-points.md)
            # a shift beyond a small part of the finest period is not the second-order
            # footprint effect but a 3 x 3 model across a step that it fits exactly (a jump
            # between rows): there too the pixel keeps its measured value
            finest = min(d.period_px for d in descs if d.kind == "phase"
                         and d.direction == axis and d.period_px)
            small = np.abs(corrected - coord[axis]) <= MAX_FOOTPRINT_SHIFT * finest
            coord[axis] = np.where(np.isfinite(corrected) & small, corrected, coord[axis])
            residuals[axis] = residual
    return DecodedView(coord, mod, residuals, rejected)


def _check_camera(view_images: np.ndarray, cam: DeviceCalibration, where: str) -> None:
    h, w = np.shape(view_images)[1:]
    if (w, h) != tuple(cam.size):
        raise SimInputError(
            f"{where}: images are {w} x {h} pixels but the rig's camera '{cam.name}' is "
            f"{cam.size[0]} x {cam.size[1]}; is the rig file for these images?"
        )


def scan(
    images: list[np.ndarray],
    patterns: PhaseShiftSet | GrayCodeSet,
    rig: Rig,
    settings: DecodeSettings | None = None,
    camera: int | None = None,
) -> PointCloud:
    """Point cloud (world frame, mm) from the image stacks (n, H, W) of the rig's cameras.

    ``camera=None``: stereo between cameras 0 and 1 (both stacks needed); ``camera=i``:
    camera i against the projector (``images`` may hold just that camera's stack).
    ``scan_with_report`` also says what each check dropped.
    """
    return scan_with_report(images, patterns, rig, settings, camera)[0]


def _report(views: list[DecodedView], stereo: list[dict[str, int]], cloud: PointCloud,
            settings: DecodeSettings) -> ScanReport:
    pixels, decoded, rejected = [], [], []
    for v, r in zip(views, stereo, strict=True):
        c = next(iter(v.coord.values()))
        pixels.append(int(c.size))
        decoded.append(int(np.isfinite(c).sum()))
        rejected.append({**v.rejected, **r})
    return ScanReport(tuple(pixels), tuple(decoded), tuple(rejected), len(cloud.points),
                      settings.pixel_variance_px2)


def scan_with_report(
    images: list[np.ndarray],
    patterns: PhaseShiftSet | GrayCodeSet,
    rig: Rig,
    settings: DecodeSettings | None = None,
    camera: int | None = None,
) -> tuple[PointCloud, ScanReport]:
    """``scan``, and the ``ScanReport`` of what each check rejected."""
    settings = settings or DecodeSettings()
    psize = rig.projector.size
    if camera is None:
        if len(images) != 2:
            raise SimInputError(f"stereo needs the image stacks of 2 cameras, got {len(images)}")
        for i in range(2):
            _check_camera(images[i], rig.cameras[i], f"camera {i}")
        if np.shape(images[0])[0] != np.shape(images[1])[0]:
            raise SimInputError(
                f"camera 0 has {np.shape(images[0])[0]} images, camera 1 has "
                f"{np.shape(images[1])[0]}: the stacks must match"
            )
        views = [decode_view(images[i], patterns, psize, settings, f"camera {i}") for i in range(2)]
        if "u" not in views[0].coord:
            raise SimInputError("stereo matching needs fringes along 'u' (projector columns)")
        stereo: list[dict[str, int]] = []
        cloud = stereo_cloud(
            views[0].coord["u"], views[1].coord["u"], rig.cameras[0], rig.cameras[1],
            projector=rig.projector, max_projector_error_px=settings.max_projector_error_px,
            quality1=views[0].modulation, quality2=views[1].modulation,
            order=settings.interpolation_order, max_lr_error_px=settings.max_lr_error_px,
            max_model_residual=settings.max_model_residual, max_range_step=settings.max_range_step,
            residual1=views[0].residual.get("u"), residual2=views[1].residual.get("u"),
            rejected=stereo,
        )
        top = float(np.percentile(np.concatenate([v.modulation.ravel() for v in views]), 99))
        cloud = _relative_quality(cloud, top)
        return cloud, _report(views, stereo, cloud, settings)
    if not 0 <= camera < len(rig.cameras):
        raise SimInputError(f"camera must be 0 or 1, got {camera}")
    stack = images[camera] if len(images) == len(rig.cameras) else images[0]
    cam = rig.cameras[camera]
    _check_camera(stack, cam, f"camera {camera}")
    view = decode_view(stack, patterns, psize, settings, f"camera {camera}")
    axis = "u" if "u" in view.coord else "v"
    coord = view.coord[axis]
    _, residual = local_phase_model(coord)
    if axis in view.residual:  # judge the map as measured, not as corrected
        residual = np.where(np.isfinite(residual), view.residual[axis], np.nan)
    usable = usable_pixels(residual, settings.max_model_residual)
    dropped = int((np.isfinite(coord) & ~usable).sum())
    coord = np.where(usable, coord, np.nan)
    if not np.isfinite(coord).any():
        raise SimInputError(f"camera {camera}: no valid pixel with 8 valid neighbours to "
                            "triangulate")
    pts, uv = camera_projector_cloud(coord, cam, rig.projector, axis)
    grid = np.full((cam.height, cam.width, 3), np.nan)
    iu, iv = uv[:, 0].astype(int), uv[:, 1].astype(int)
    grid[iv, iu] = pts
    normals = grid_normals(grid, cam.centre_world)[iv, iu]
    # per-point phase error and the uncertainty it propagates to (mm per projector px)
    noise = phase_noise_px(residual, view.modulation)
    moved, _ = camera_projector_cloud(coord + SENSITIVITY_PX, cam, rig.projector, axis)
    sens = np.linalg.norm(moved - pts, axis=1) / SENSITIVITY_PX
    fields = {"camera": np.full(len(pts), float(camera)), "u": uv[:, 0], "v": uv[:, 1],
              "phase_error": residual[iv, iu], "uncertainty_mm": sens * noise[iv, iu]}
    cloud = _relative_quality(PointCloud(pts, normals, view.modulation[iv, iu], fields),
                              float(np.percentile(view.modulation, 99)))
    return cloud, _report([view], [{"camera_projector_model_residual": dropped}], cloud, settings)


def _relative_quality(cloud: PointCloud, top: float) -> PointCloud:
    """``cloud`` with its modulation (image units) as field ``modulation`` and as quality the
    modulation relative to ``top`` (the 99th percentile over the images: about 0 to 1)."""
    assert cloud.quality is not None, "scan clouds carry the modulation as their quality"
    fields = {"modulation": cloud.quality, **cloud.fields}
    quality = cloud.quality / top if top > 0 else cloud.quality
    return PointCloud(cloud.points, cloud.normals, quality, fields)
