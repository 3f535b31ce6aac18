"""One twin against the real scanner at one position: points by pixel correspondence
(unaligned at the refined pose, and after ICP: the reference's Table 4), sizes on each
scanner's own points and on the pixels both share (Tables 5 and 6), and the fringe images and
their phases pixel by pixel (Fig. 14). Lengths mm, phases rad."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from station.validation.folder import AnyArtefact, CadArtefact, RealScanError, SphereArtefact
from station.validation.locate import ArtefactFit, pixel_keys

if TYPE_CHECKING:
    from trimesh import Trimesh

    from sim.fpp.cloud import PointCloud
    from sim.metrology.spheres import SphereFit
    from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet


@dataclass(frozen=True)
class ImageStats:
    """Per camera the real-minus-twin fringe image and phase differences over the pixels lit
    in both: intensity mean and RMS (DN) and as a fraction of the real modulation, wrapped
    phase mean and RMS of the finest fringes (rad), pixels compared."""

    camera: int
    pixels: int
    intensity_mean_dn: float
    intensity_rms_dn: float
    intensity_rms_of_modulation: float
    phase_mean_rad: float
    phase_rms_rad: float

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class TwinComparison:
    """One twin against the real scan at one position (mm; ``size_*`` against nominal)."""

    twin: str
    points: int
    pixels_compared: int
    mean_mm: float
    rmse_mm: float
    mean_icp_mm: float
    rmse_icp_mm: float
    size_mm: float | None
    size_shared_mm: float | None
    size_shared_real_mm: float | None
    size_shared_points: int | None
    cad_mean_mm: float | None
    cad_rmse_mm: float | None
    images: tuple[ImageStats, ...]

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["images"] = [i.to_json() for i in self.images]
        return d

    @property
    def size_vs_real_um(self) -> float | None:
        """Size minus the real scanner's on the pixels both share, um."""
        if self.size_shared_mm is None or self.size_shared_real_mm is None:
            return None
        return (self.size_shared_mm - self.size_shared_real_mm) * 1e3


def finest_phase(images: np.ndarray, patterns: PhaseShiftSet | GrayCodeSet,
                 projector_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Wrapped phase (H, W) rad and modulation of the finest phase-shift group."""
    descs = [d for d in patterns.descriptors(projector_size) if d.kind == "phase"]
    p = min(d.period_px for d in descs if d.period_px is not None)
    idx = [d.index for d in sorted(descs, key=lambda d: d.shift or 0) if d.period_px == p]
    x = np.asarray(images, np.float64)[idx]
    a = 2 * np.pi * np.arange(len(idx)) / len(idx)
    s, c = np.tensordot(np.sin(a), x, axes=1), np.tensordot(np.cos(a), x, axes=1)
    return np.arctan2(s, c), 2 * np.hypot(s, c) / len(idx)


def image_differences(real: np.ndarray, twin: np.ndarray, lit: np.ndarray,
                      patterns: PhaseShiftSet | GrayCodeSet, projector_size: tuple[int, int],
                      camera: int) -> tuple[ImageStats, np.ndarray, np.ndarray]:
    """Fig. 14's numbers of one camera: stats, the finest fringe image's difference map
    (twin - real, DN, NaN where not compared) and the wrapped phase difference map (rad)."""
    pr, br = finest_phase(real, patterns, projector_size)
    pv, bv = finest_phase(twin, patterns, projector_size)
    mask = np.asarray(lit, bool) & (br > 0.2 * np.percentile(br, 99)) & \
        (bv > 0.2 * np.percentile(bv, 99))
    if not mask.any():
        raise RealScanError(f"camera {camera}: no pixel lit in both the real and the twin's "
                            "images")
    descs = [d for d in patterns.descriptors(projector_size) if d.kind == "phase"]
    p = min(d.period_px for d in descs if d.period_px is not None)
    k = [d.index for d in descs if d.period_px == p and (d.shift or 0) == 0][0]
    diff = np.asarray(twin[k], np.float64) - np.asarray(real[k], np.float64)
    dp = np.angle(np.exp(1j * (pv - pr)))
    d, ph = diff[mask], dp[mask]
    stats = ImageStats(camera, int(mask.sum()), float(d.mean()), float(np.sqrt(np.mean(d * d))),
                       float(np.sqrt(np.mean(d * d)) / np.median(br[mask])),
                       float(ph.mean()), float(np.sqrt(np.mean(ph * ph))))
    return stats, np.where(mask, diff, np.nan), np.where(mask, dp, np.nan)


def shared_pixel_fits(cloud: PointCloud, kept: Sequence[np.ndarray], real: PointCloud,
                      real_kept: Sequence[np.ndarray], name: str
                      ) -> tuple[list[SphereFit], list[SphereFit], int]:
    """Per ball, both clouds refitted on the pixels both scanners' own fits kept (``kept``,
    ``real_kept``: pixel keys per ball), with no further trimming, so the two fits differ only
    by the points' offsets, not by which points each scanner kept: the twin's fits, the real
    fits and the points used. Fewer than 20 shared pixels on a ball is refused."""
    from sim.metrology.spheres import fit_sphere

    fits_v, fits_r, count = [], [], 0
    pv, kv = np.asarray(cloud.points, np.float64), pixel_keys(cloud)
    pr, kr = np.asarray(real.points, np.float64), pixel_keys(real)
    for a, b in zip(kept, real_kept, strict=True):
        both = np.intersect1d(a, b)
        if both.size < 20:
            raise RealScanError(f"position {name}: the twin and real clouds share only "
                                f"{both.size} pixels on a ball; move it into both cameras' view")
        iv = np.flatnonzero(np.isin(kv, both))
        ir = np.flatnonzero(np.isin(kr, both))
        iv, ir = iv[np.argsort(kv[iv])], ir[np.argsort(kr[ir])]
        fits_v.append(fit_sphere(pv[iv], reject_sigma=None))
        fits_r.append(fit_sphere(pr[ir], reject_sigma=None))
        count += both.size
    return fits_v, fits_r, count


def shared_sizes(cloud: PointCloud, own: ArtefactFit, real: PointCloud, real_own: ArtefactFit,
                 artefact: AnyArtefact, name: str) -> tuple[float, float, int]:
    """Both clouds' sizes on the pixels both scanners' own fits kept
    (:func:`shared_pixel_fits`): twin size, real size (mm) and the points used."""
    fits_v, fits_r, count = shared_pixel_fits(cloud, own.kept, real, real_own.kept, name)

    def size(fits: list[SphereFit]) -> float:
        if len(fits) == 1:
            return float(fits[0].diameter)
        return float(np.linalg.norm(fits[0].centre - fits[1].centre))

    return size(fits_v), size(fits_r), count


def nominal_size(artefact: AnyArtefact) -> float | None:
    """The artefact's nominal size: a sphere's diameter, a ball bar's centre distance, mm."""
    if isinstance(artefact, CadArtefact):
        return None
    if isinstance(artefact, SphereArtefact):
        return artefact.diameter_mm
    return artefact.centre_distance_mm


def compare_twin(twin: str, cloud: PointCloud, real: PointCloud, real_fit: ArtefactFit,
                 own_fit: ArtefactFit | None, artefact: AnyArtefact, name: str,
                 images: list[tuple[ImageStats, np.ndarray, np.ndarray]],
                 world_mesh: Trimesh | None = None) -> TwinComparison:
    """Every number of one twin at one position (see ``TwinComparison``)."""
    from sim.metrology.compare import compare_by_pixel, compare_clouds, mesh_signed_distance

    try:
        c = compare_by_pixel(cloud, real)
        tf = compare_clouds(cloud.points, real.points, real.normals, align=True).transform
        a = compare_by_pixel(cloud, real, transform=tf)
    except ValueError as exc:
        raise RealScanError(f"position {name}, twin {twin}: {exc}") from exc
    size = shared = shared_real = shared_n = cad_mean = cad_rmse = None
    nominal = nominal_size(artefact)
    if nominal is not None and own_fit is not None:
        size = own_fit.size_mm - nominal
        sv, sr, shared_n = shared_sizes(cloud, own_fit, real, real_fit, artefact, name)
        shared, shared_real = sv - nominal, sr - nominal
    if world_mesh is not None:
        d = mesh_signed_distance(np.asarray(cloud.points, np.float64), world_mesh)
        cad_mean, cad_rmse = float(d.mean()), float(np.sqrt(np.mean(d * d)))
    return TwinComparison(twin, int(len(cloud.points)), int(c.index.size), c.mean, c.rmse,
                          a.mean, a.rmse, size, shared, shared_real, shared_n, cad_mean,
                          cad_rmse, tuple(s for s, _, _ in images))
