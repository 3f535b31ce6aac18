"""The experiment's rig, the fake bench of each rig camera and its station run, and the
four scanners' lenses (real, measured LTC, Gaussian, pinhole)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from station.experiment.config import BENCH_SUBPIXELS, FOCAL_MM, ExperimentConfig, Log
from station.sequence import run_sequence

if TYPE_CHECKING:
    from sim.optics.lens import AberratedLens, LensModel
    from sim.optics.measured_lens import MeasuredLens
    from sim.optics.rig import DeviceCalibration, Rig
    from station.acquisition.config import StationConfig

def build_rig(cfg: ExperimentConfig) -> Rig:
    """``small_rig(scale)`` without distortion, both cameras cropped to ``camera_size``
    about the image centre (same focal length and pose)."""
    from sim.optics.rig import DeviceCalibration, Rig, small_rig

    full = small_rig(cfg.scale, distortion=False)
    w, h = cfg.camera_size
    cams = []
    for c in full.cameras:
        K = c.K_array.copy()
        K[0, 2], K[1, 2] = (w - 1) / 2, (h - 1) / 2
        cams.append(DeviceCalibration(name=c.name, K=K, dist=c.dist, R=c.R, T=c.T, size=(w, h)))
    return Rig(cameras=cams, projector=full.projector)


def truth_lens(cfg: ExperimentConfig, index: int, samples: int) -> AberratedLens:
    """Camera ``index``'s ground-truth lens with ``samples`` pupil samples."""
    from sim.optics.lens import AberratedLens

    s = cfg.lenses[index]
    return AberratedLens(pupil_diameter_mm=FOCAL_MM / s.f_number,
                         focus_distance_mm=cfg.focus_distance_mm,
                         vignetting_shift_mm=s.vignetting_shift_mm,
                         vignetting_radius_ratio=s.vignetting_radius_ratio,
                         spherical_mm=s.spherical_mm, samples=samples, edge="soft")


def lcd_size(cfg: ExperimentConfig, camera: DeviceCalibration) -> tuple[int, int]:
    """LCD pixels covering the camera's view at the farthest depth, with a blur margin."""
    far = cfg.lcd_distance_at_zero_mm + max(cfg.depths_mm)
    f = camera.K_array[0, 0]
    margin = 2 * cfg.period
    return (int(np.ceil(camera.width / f * far / cfg.lcd_pitch_mm)) + margin,
            int(np.ceil(camera.height / f * far / cfg.lcd_pitch_mm)) + margin)


def station_config(cfg: ExperimentConfig, rig: Rig, index: int) -> StationConfig:
    """The fake-bench station config of camera ``index``: the rig camera's K and sensor, its
    own ground-truth lens; ``camera.matrix`` = K places the optical centre."""
    from station.acquisition.config import StationConfig

    camera = rig.cameras[index]
    K = camera.K_array
    lens = truth_lens(cfg, index, 1)
    size = lcd_size(cfg, camera)
    return StationConfig.model_validate({
        "backend": "fake",
        "depths_mm": list(cfg.depths_mm),
        "stage": {"port": "pty", "microstep_um": 0.1, "travel_mm": [0.0, max(cfg.depths_mm) + 20],
                  "tolerance_um": 1.0, "timeout_s": 0.5, "settle_s": 0.0},
        "display": {"monitor": 0, "latency_frames": 0, "frame_code": False,
                    "pitch_mm": cfg.lcd_pitch_mm},
        "camera": {"exposure_ms": 20.0, "timeout_s": 2.0, "matrix": K.tolist(),
                   "average_frames": cfg.average_frames},
        "patterns": {"period": cfg.period, "steps": cfg.steps, "offset": 0.5, "amplitude": 0.5},
        # the check code proves the frame order on real hardware; here it would only mask pixels
        "frame_check": {"enabled": False},
        "sequence": {"align": False, "lens_samples": cfg.lens_samples,
                     "lens_grid_step": cfg.lens_grid_step,
                     # the bench integrates each camera pixel's area (sim.optics.plane_ltc):
                     # a box, as a real camera's pixel
                     "lens_pixel_samples": 0,
                     "lens_settings": dict(cfg.lens_settings)},
        "fake": {
            "seed": cfg.seed + index, "stage_maxspeed_mm_s": 1000.0,
            "stage_accel_mm_s2": 10000.0,
            "bench": {
                "lcd_size": list(size), "lcd_pitch_mm": cfg.lcd_pitch_mm,
                "camera_size": list(camera.size), "pixel_pitch_um": FOCAL_MM / K[0, 0] * 1e3,
                "focal_length_mm": FOCAL_MM, "f_number": cfg.lenses[index].f_number,
                "focus_distance_mm": lens.focus_distance_mm,
                "vignetting_shift_mm": lens.vignetting_shift_mm,
                "vignetting_radius_ratio": lens.vignetting_radius_ratio,
                "spherical_mm": lens.spherical_mm, "coma_mm": 0.0,
                "lcd_distance_at_zero_mm": cfg.lcd_distance_at_zero_mm,
                "tilt_deg": [0.0, 0.0], "subpixels": BENCH_SUBPIXELS,
                # the true lens with a soft-edged pupil: the LTC the station measures is then
                # the lens's own, not a 200-sample hard-edged rendering of it (whose principal
                # rays sit ~70 um RMS off the converged lens's at the optical centre); the
                # same rays per pixel as 2 x 2 subpixels of 512, a better pupil quadrature
                "pupil_samples": cfg.bench_samples, "pupil_edge": "soft",
            },
            "noise": {"enabled": True, "bit_depth": 12, "full_well_e": 10000.0,
                      "read_noise_e": 5.0},
            "panel": {"gamma": 1.0},
        },
    })


def measure_cameras(cfg: ExperimentConfig, rig: Rig, out: Path, progress: bool, log: Log,
                    force: bool = False) -> list[dict[str, Any]]:
    """The station sequence (``ltc run``) for each camera into ``out/station/camI``; returns
    per camera the lens file, its figures and a summary (steps' seconds, optical centre and
    its error against the fake bench's true one). ``force`` takes over a run store's writer
    lock that a killed run left (never a live writer's)."""

    results = []
    for i, cam in enumerate(rig.cameras):
        folder = out / "station" / f"cam{i}"
        config = station_config(cfg, rig, i)
        log(f"station, camera {i} ({cam.name}): check, acquire {len(cfg.depths_mm)} depths, "
            f"reconstruct, lens -> {folder}")
        t0 = time.perf_counter()
        summary = run_sequence(config, folder, progress=progress, force=force)
        lens = summary.steps["lens"].result or {}
        w, h = lcd_size(cfg, cam)
        true_centre = np.array([(w - 1) / 2 * cfg.lcd_pitch_mm, (h - 1) / 2 * cfg.lcd_pitch_mm,
                                -cfg.lcd_distance_at_zero_mm])
        err = np.asarray(lens["optical_centre_mm"]) - true_centre
        rec = {"camera": cam.name, "folder": str(folder), "lens": str(folder / "lens.npz"),
               "figures": sorted(str(p) for p in (folder / "figures").glob("*.png")),
               "seconds": {k: v.seconds for k, v in summary.steps.items()},
               "total_s": time.perf_counter() - t0,
               "optical_centre_mm": lens["optical_centre_mm"],
               "optical_centre_true_mm": true_centre.tolist(),
               "optical_centre_error_mm": float(np.linalg.norm(err)),
               "focus_distance_mm": lens["focus_distance_mm"],
               "pixels_usable": lens["pixels_usable"], "pixels": lens["pixels"]}
        log(f"  camera {i}: {rec['total_s']:.0f} s; optical centre error "
            f"{rec['optical_centre_error_mm'] * 1e3:.1f} um, focus distance "
            f"{rec['focus_distance_mm']:.1f} mm")
        results.append(rec)
    return results


# --- the scanners -----------------------------------------------------------------------------

def scanner_lenses(cfg: ExperimentConfig,
                   measured: list[MeasuredLens]) -> dict[str, tuple[LensModel, ...]]:
    """Per scanner the lens of each camera: "ltc" the measured lenses smoothed over
    ``lens_smoothing_nodes``; "gaussian" from the measured lenses as derived (docs/optics.md
    section 4: the second moment of the measured LTC at the optical centre, which the
    derivation gives each node's samples exactly; averaging sample k over nodes narrows
    the deblurred samples by a few per cent, an artefact of the smoothing, not of the
    measurement)."""
    from sim.optics.lens import PinholeLens
    from sim.optics.lens_moments import gaussian_equivalent, smoothed_lens

    return {"real": tuple(truth_lens(cfg, i, cfg.real_samples) for i in range(2)),
            "ltc": tuple(smoothed_lens(m, cfg.lens_smoothing_nodes) for m in measured),
            "gaussian": tuple(gaussian_equivalent(m, cfg.gaussian_samples) for m in measured),
            "pinhole": (PinholeLens(), PinholeLens())}


RENDER = dict(projector={"input_bits": 8},
              camera={"exposure_e": 8000.0, "full_well_e": 10000.0, "bit_depth": 12,
                      "shot_noise": False, "read_noise_e": 0.0})
