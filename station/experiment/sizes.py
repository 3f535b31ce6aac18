"""The size rule of the experiment (sphere diameter, ball-bar length, mm): each scanner on
its own points (``size_fit``), virtual against real on shared pixels (``shared_size_mm``) and
the coverage check."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from station.errors import StationError
from station.experiment.config import (
    BALLBAR_LENGTH_MM,
    MIN_BALL_COVERAGE,
    MODELS,
    SHELL_MM,
    SPHERE_DIAMETER_MM,
)
from station.experiment.objects import Position
from station.validation.compare import shared_pixel_fits
from station.validation.locate import pixel_keys

if TYPE_CHECKING:
    from sim.fpp.cloud import PointCloud
    from sim.metrology.spheres import SphereFit
    from sim.optics.rig import Rig
    from sim.render.scene import Scene
    from station.experiment.scan import Scan

def _size_of(fits: list[SphereFit], pos: Position) -> float:
    """Sphere: diameter minus nominal; ball bar: centre distance minus nominal, mm."""
    if pos.kind == "sphere":
        return float(fits[0].diameter - SPHERE_DIAMETER_MM)
    return float(np.linalg.norm(fits[0].centre - fits[1].centre) - BALLBAR_LENGTH_MM)


@dataclass(frozen=True)
class SizeFit:
    """One scanner's size at one position on its own points: per ball the sphere fit and the
    pixel keys of the points it kept (its inliers); ``size_mm`` against nominal."""

    fits: tuple[SphereFit, ...]
    kept: tuple[np.ndarray, ...]
    size_mm: float


def on_ball(points: np.ndarray, ball: np.ndarray) -> np.ndarray:
    """Which points (n, 3) mm lie within ``SHELL_MM`` of the true ball (cx, cy, cz, r) mm:
    the points every size rule and coverage check counts."""
    cx, cy, cz, r = ball
    return np.abs(np.linalg.norm(points - [cx, cy, cz], axis=1) - r) < SHELL_MM


def size_fit(cloud: PointCloud, pos: Position, scene: Scene) -> SizeFit:
    """The size rule, the same for every scanner: each ball fitted (geometric least squares,
    ``fit_sphere``: 3-sigma robust trimming) to the cloud's points within ``SHELL_MM`` of the
    true ball; sphere: fitted diameter minus nominal; ball bar: fitted centre distance minus
    nominal (mm)."""
    from sim.metrology.spheres import fit_sphere

    points = np.asarray(cloud.points, dtype=np.float64)
    keys = pixel_keys(cloud)
    fits, kept = [], []
    for ball in scene.objects[0].spheres():
        near = on_ball(points, ball)
        if near.sum() < 20:
            raise StationError(f"position {pos.name}: only {int(near.sum())} points on a "
                               f"{2 * ball[3]:g} mm ball; move it into both cameras' view")
        fit = fit_sphere(points[near])
        fits.append(fit)
        kept.append(keys[near][fit.inliers])
    return SizeFit(tuple(fits), tuple(kept), _size_of(fits, pos))


def check_coverage(scans: dict[str, Scan], pos: Position, scene: Scene, rig: Rig) -> None:
    """Refuse a size from balls a scanner barely saw: per ball, each blurring scanner's points
    within ``SHELL_MM`` must reach ``MIN_BALL_COVERAGE`` of the pinhole scanner's (the same
    decoder, no blur: whatever the pixel scale, it keeps what the silhouettes and shadows
    leave). Below it the ball lies outside the scanner's working range: its fringes are too
    blurred to pass the decoder's checks but in patches, and a sphere fitted to the patches is
    not a size (a 38.1 mm ball kept 11 % of its disc's pixels at +139 mm of defocus; with the
    far balls at +176 / +196 mm the real and virtual scanners' lengths differed by 0.7 mm:
    docs/decisions 0018)."""
    balls = scene.objects[0].spheres()

    def counts(cloud: PointCloud) -> list[int]:
        p = np.asarray(cloud.points, dtype=np.float64)
        return [int(on_ball(p, ball).sum()) for ball in balls]

    ref = counts(scans["pinhole"].cloud)
    for name in MODELS:
        if name == "pinhole":
            continue
        for k, (found, full) in enumerate(zip(counts(scans[name].cloud), ref, strict=True)):
            if found < MIN_BALL_COVERAGE * full:
                cx, cy, cz, r = balls[k]
                depth = float(rig.cameras[0].to_device(np.array([[cx, cy, cz]]))[0, 2])
                raise StationError(
                    f"position {pos.name}, scanner {name}: ball {k + 1} ({2 * r:g} mm, "
                    f"{depth:.0f} mm from camera 0) gave {found} points against the pinhole "
                    f"scanner's {full} ({100 * found / max(full, 1):.0f} %, at least "
                    f"{100 * MIN_BALL_COVERAGE:.0f} % needed): it lies outside the scanner's "
                    f"working range; move it nearer focus (sphere_*, ballbar_*)")


def size_error_mm(own: SizeFit) -> dict[str, float]:
    """``size_mm`` (own points against nominal) and the fits' largest RMS, mm."""
    return {"size_mm": own.size_mm, "fit_rms_mm": float(max(f.rms for f in own.fits))}


def shared_size_mm(cloud: PointCloud, own: SizeFit, real: PointCloud, real_own: SizeFit,
                   pos: Position) -> dict[str, float | int]:
    """Sizes of a virtual cloud and the real one compared on the pixels both share: per ball
    the pixels both scanners' own fits kept (``size_fit``), each cloud refitted there with no
    further trimming (``fit_sphere(reject_sigma=None)``), so the two sizes differ only by the
    per-point offsets, not by which points each scanner kept. Returns ``size_shared_mm`` and
    ``size_shared_real_mm`` (against nominal) and ``size_shared_points``."""
    fits, real_fits, count = shared_pixel_fits(cloud, own.kept, real, real_own.kept, pos.name)
    return {"size_shared_mm": _size_of(fits, pos), "size_shared_real_mm": _size_of(real_fits, pos),
            "size_shared_points": int(count)}
