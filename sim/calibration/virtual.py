"""Virtual calibration captures: the virtual scanner renders a board at many poses for a rig,
written in the capture layout (``sim.calibration.capture``) as 16-bit PNGs, so the whole loop
runs against a rig whose truth is known.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sim.calibration.capture import CalibrationPatterns
from sim.optics.lens import LensModel, PinholeLens
from sim.optics.rig import DeviceCalibration, Rig, look_at
from sim.render.board import CalibrationBoard
from sim.render.images import RenderSettings, render_views
from sim.render.scene import BoardObject, Pose, Scene

PNG_COMPRESSION = 1  # fast zlib level: the capture is written and read back, not archived


def calibration_rig(camera_dist: Sequence[float] = (0.0,) * 5,
                    projector_dist: Sequence[float] = (0.0,) * 5, scale: float = 1.0) -> Rig:
    """A lab-sized scanner: two 1280 x 1024 cameras (f = 2400 px) 760 mm from the world origin
    converging at +-15 degrees, a 1920 x 1080 projector (f = 3040 px) between them; principal
    points off centre. ``scale`` multiplies image sizes and focal lengths (0.25: 320 x 256
    cameras). World: origin at the centre of the volume, z away from the rig, y down."""
    a = np.radians(15.0)
    s = float(scale)
    devs = []
    for name, x, pp in (("left", -1.0, (652.3, 498.1)), ("right", 1.0, (628.7, 521.4))):
        R, T = look_at(np.array([x * 760 * np.sin(a), 0.0, -760 * np.cos(a)]), np.zeros(3))
        K = [[2400.0 * s, 0, (pp[0] + 0.5) * s - 0.5], [0, 2400.0 * s, (pp[1] + 0.5) * s - 0.5],
             [0, 0, 1]]
        devs.append(DeviceCalibration(name=name, K=K, dist=list(camera_dist), R=R, T=T,
                                      size=(round(1280 * s), round(1024 * s))))
    R, T = look_at(np.array([0.0, -40.0, -760.0]), np.zeros(3))
    K = [[3040.0 * s, 0, 961.7 * s - 0.5], [0, 3040.0 * s, 613.0 * s - 0.5], [0, 0, 1]]
    proj = DeviceCalibration(name="projector", K=K, dist=list(projector_dist), R=R, T=T,
                             size=(round(1920 * s), round(1080 * s)))
    return Rig(cameras=devs, projector=proj)


def _rot(ax_deg: float, ay_deg: float, az_deg: float = 0.0) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.radians([ax_deg, 0.0, 0.0]))
    Ry, _ = cv2.Rodrigues(np.radians([0.0, ay_deg, 0.0]))
    Rz, _ = cv2.Rodrigues(np.radians([0.0, 0.0, az_deg]))
    return Ry @ R @ Rz


# (tilt about x, tilt about y, roll, deg; centre x, y, z, mm): tilts up to 30 degrees, the
# centre spread over the working volume (+-60 mm in depth)
DEFAULT_POSES = (
    (0, 0, 0, 0, 0, 0), (25, 0, 0, 0, 0, 20), (-25, 0, 0, 0, 0, -20), (0, 28, 0, 0, 0, 40),
    (0, -28, 0, 0, 0, -40), (18, 18, 5, 20, 10, 60), (-18, 18, -5, -20, -10, -60),
    (18, -18, 5, -20, 10, 0), (-18, -18, -5, 20, -10, 30), (30, 8, 0, 0, 15, -30),
    (-30, -8, 0, 0, -15, 50), (8, 30, 10, 15, 0, -50), (-8, -30, -10, -15, 0, 10),
    (12, -24, 0, 25, 20, -10), (-12, 24, 0, -25, -20, 25),
)


def default_poses(board: CalibrationBoard, count: int = 15) -> list[Pose]:
    """``count`` board poses (board to world), up to 15: tilts up to 30 degrees, spread over
    the working volume of ``calibration_rig``, the board's centre on the table's point."""
    if not 1 <= count <= len(DEFAULT_POSES):
        raise ValueError(f"default_poses: count must be 1..{len(DEFAULT_POSES)}, got {count}")
    w, h = board.size_mm
    out = []
    for ax, ay, az, x, y, z in DEFAULT_POSES[:count]:
        R = _rot(ax, ay, az)
        t = np.array([x, y, z], float) - R @ np.array([w / 2, h / 2, 0.0])
        out.append(Pose(R=R, t=t))
    return out


@dataclass(frozen=True)
class RenderedCapture:
    """A rendered capture: its folder, the true rig and poses, and timings (s)."""

    directory: Path
    rig: Rig
    poses: list[Pose]
    render_s: float
    write_s: float


def _write_png16(path: Path, image: np.ndarray) -> None:
    im = np.asarray(image)
    if im.dtype != np.uint16:
        raise ValueError(f"{path}: expected uint16 image, got {im.dtype}")
    if not cv2.imwrite(str(path), im, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]):
        raise OSError(f"could not write {path}")


def render_capture(out: str | Path, board: CalibrationBoard, rig: Rig | None = None,
                   poses: Sequence[Pose] | None = None,
                   patterns: CalibrationPatterns | None = None,
                   lenses: Sequence[LensModel] | None = None,
                   settings: RenderSettings | None = None, seed: int = 0,
                   progress: bool = False) -> RenderedCapture:
    """Render the board at every pose for ``rig`` (default ``calibration_rig()``) and write the
    capture folder ``out`` (new): ``capture.json`` and ``pose_<nnn>/camera_<i>/<nnn>.png``,
    16-bit (12-bit cameras keep 0..4095). Default settings: 16-bit noise-free cameras."""
    out = Path(out)
    rig = rig or calibration_rig()
    poses = list(poses) if poses is not None else default_poses(board)
    patterns = patterns or CalibrationPatterns.default(rig.projector.size)
    if tuple(patterns.projector_size) != tuple(rig.projector.size):
        raise ValueError(f"patterns are for a {patterns.projector_size} projector, the rig's is "
                         f"{rig.projector.size}")
    lenses = list(lenses) if lenses is not None else [PinholeLens(), PinholeLens()]
    if settings is None:
        settings = RenderSettings.model_validate(
            {"camera": {"bit_depth": 16, "exposure_e": 9000.0, "full_well_e": 10000.0}})
    if settings.camera.bit_depth == 8:
        raise ValueError("render_capture writes 16-bit PNGs: use a 12- or 16-bit camera")
    out.mkdir(parents=True)
    patterns.save(out)
    images = patterns.images()
    rng = np.random.default_rng(seed)
    t_render = t_write = 0.0
    for j, pose in enumerate(poses):
        t0 = time.perf_counter()
        geom = Scene(objects=[BoardObject(name="board", board=board, pose=pose)]).trace_geometry(
            where=f"pose_{j:03d}")
        res = render_views(geom, rig, lenses, images, settings, rng, progress=progress,
                           where=f"pose_{j:03d}")
        t1 = time.perf_counter()
        for i, cam in enumerate(res.cameras):
            d = out / f"pose_{j:03d}" / f"camera_{i}"
            d.mkdir(parents=True)
            for k, im in enumerate(cam.images):
                _write_png16(d / f"{k:03d}.png", im)
        t_render += t1 - t0
        t_write += time.perf_counter() - t1
    return RenderedCapture(out, rig, poses, t_render, t_write)
