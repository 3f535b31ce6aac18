"""Real-scan folders rendered by our renderer at another sampling than the twins': each
camera pixel integrated over 4 x 4 subpixels (as a camera's pixel averages its area), binned,
saved as 16-bit PNGs; the twins sample pixel centres."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.optics.lens import AberratedLens
from sim.optics.rig import DeviceCalibration, Rig, small_rig
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import RenderSettings
from sim.scanner import Scanner
from station.validation.folder import (
    BallBarArtefact,
    Pose,
    PositionFile,
    SphereArtefact,
    write_position,
    write_scan_file,
)
from station.validation.twin import scene_at, supersampled

SPHERE_MM = 50.8007
FOCUS_MM = 760.0


def small_test_rig(size: tuple[int, int] = (128, 96), scale: float = 0.1) -> Rig:
    """``small_rig(scale)`` without distortion, cameras cropped to ``size`` about the centre."""
    full = small_rig(scale, distortion=False)
    w, h = size
    cams = []
    for c in full.cameras:
        K = c.K_array.copy()
        K[0, 2], K[1, 2] = (w - 1) / 2, (h - 1) / 2
        cams.append(DeviceCalibration(name=c.name, K=K, dist=c.dist, R=c.R, T=c.T, size=(w, h)))
    return Rig(cameras=cams, projector=full.projector)


def thin_lens(pupil_mm: float = 4.0, samples: int = 32) -> AberratedLens:
    return AberratedLens(pupil_diameter_mm=pupil_mm, focus_distance_mm=FOCUS_MM, samples=samples)


PATTERNS = PhaseShiftSet(periods_px=[192.0, 24.0, 8.0], steps=4, direction="u")
COUNTS = {"projector": {"input_bits": 8},
          "camera": {"exposure_e": 40000.0, "full_well_e": 65535.0, "bit_depth": 16,
                     "quantize": False, "shot_noise": False, "read_noise_e": 0.0}}


def world_point(z_mm: float, y_mm: float = 0.0) -> tuple[float, float, float]:
    """A world point on the rig's mid axis: world z 0 is ``FOCUS_MM`` from the cameras."""
    return (0.0, float(y_mm), float(z_mm))


def write_real_folder(folder: Path, positions: dict[str, tuple[str, object, Pose]],
                      rig: Rig | None = None, lens=None, factor: int = 4,
                      gamma: float = 1.0) -> Rig:
    """A real-scan folder: per position (name -> (defocus, artefact, true pose)) the
    artefact rendered with ``lens`` at ``factor`` x ``factor`` subpixels per pixel, binned."""
    rig = rig or small_test_rig()
    lens = lens or thin_lens()
    fine = supersampled(rig, factor)
    write_scan_file(folder, rig, PATTERNS)
    settings = RenderSettings.model_validate(COUNTS)
    for name, (defocus, art, pose) in positions.items():
        s = Scanner(fine, (lens, lens), PATTERNS, scene_at(art, pose, name), settings)
        res = s.render()
        stacks = []
        for c in res.cameras:
            im = c.images.astype(np.float64)
            n, hh, ww = im.shape
            stacks.append(im.reshape(n, hh // factor, factor, ww // factor, factor)
                          .mean(axis=(2, 4)))
        write_position(folder, name, PositionFile(artefact=art, defocus=defocus,
                                                  true_pose=pose), stacks)
    return rig


def sphere() -> SphereArtefact:
    return SphereArtefact(diameter_mm=SPHERE_MM)


def ballbar() -> BallBarArtefact:
    return BallBarArtefact(ball_diameter_mm=38.1, centre_distance_mm=209.8219)
