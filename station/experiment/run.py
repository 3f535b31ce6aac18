"""The reference paper's experiment (``ltc experiment``, ``ltc demo``): from a measured lens to
a faithful virtual scanner.

1. **Station**: for each of the rig's two cameras, a fake bench whose camera *is* that rig
   camera (same K and sensor) carrying that camera's own ground-truth lens (the two lenses
   differ); the station sequence (``station.sequence.run_sequence``: check, alignment report,
   acquisition at six depths, LTC reconstruction, lens derivation with figures) measures it,
   with the lens settings ``lens_settings`` (by default the samples drawn from the deblurred
   aperture distribution and each node's aim offset from the station's principal-ray
   slopes: benchmarks/README.md, "What limits the measured lens").
2. **Scanners** on the same rig and calibration: ``real`` (the ground-truth lenses, sampled
   densely enough that their own sampling noise is negligible), ``ltc`` (the measured lenses,
   smoothed over ``lens_smoothing_nodes`` neighbouring nodes against the station's
   node-to-node noise),
   ``gaussian`` (OPTICS.md section 7: the measured lens's focus distance, Gaussian aperture
   weights with the second moment of the measured LTC at the optical centre, the same for
   every pixel) and ``pinhole``.
3. **Objects**: the 50.8007 mm sphere at 4 slight and 4 large defocus positions, the
   209.8219 mm ball bar at 2 + 2, and one CAD part (steps, holes, a freeform face).
4. **Comparison**: each virtual cloud against the real one (mean and RMSE of the signed
   distances by pixel correspondence, unaligned and after ICP), the sphere diameter or ball-bar length against
   nominal for every scanner (each on its own points: ``size_fit``), each virtual size
   against the real one on the pixels both clouds share (``shared_size_mm``), and every
   scanner's cloud of the CAD part against the CAD mesh.
5. **Report**: ``report.md`` with PNG figures and ``results.json`` with every number.

Everything is written under one folder ``out``: ``experiment.json`` (the config),
``station/cam0``, ``station/cam1`` (sequence folders), ``lenses.json`` (the measured lenses'
SHA-256), ``cad_part.ply``, ``positions/`` (each finished position's numbers and arrays),
``figures/``, ``results.json``, ``report.md``. An interrupted experiment resumes where it
stopped when run again with the same config and folder.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from sim.storage.lock import LOCK_NAME, StoreLock
from station.errors import StationError, UsageError
from station.sequence import durable_file, run_sequence, write_json

SPHERE_DIAMETER_MM = 50.8007
BALLBAR_LENGTH_MM = 209.8219
BALLBAR_BALL_MM = 38.1
FOCAL_MM = 16.0  # the reference system's lens (OPTICS.md section 1)
BENCH_SUBPIXELS = 1  # the fake benches trace each pixel's rays from its centre, each spread over
# the pixel's whole footprint on the LCD: the pixel's area, with all the rays for the pupil
REFERENCE_PITCH_UM = 3.45  # the reference cameras' pixel pitch (sim.optics.rig)
SHELL_MM = 2.0  # points this close to a true sphere go to its fit
MIN_BALL_COVERAGE = 0.25  # a blurring scanner's points on a ball / the pinhole scanner's
MODELS = ("real", "ltc", "gaussian", "pinhole")
VIRTUAL = ("ltc", "gaussian", "pinhole")
Log = Callable[[str], None]


class LensSpec(BaseModel):
    """The ground-truth lens of one camera (``sim.optics.lens.AberratedLens``, 16 mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    f_number: float = Field(1.0, gt=0, description="f-number (pupil 16 / N mm)")
    vignetting_shift_mm: float = Field(30.0, description="clipping-circle shift per unit "
                                       "tan(field angle), mm")
    vignetting_radius_ratio: float = Field(1.0, gt=0, description="clip radius / pupil radius")
    spherical_mm: float = Field(15.0, description="focus shift at the pupil rim, mm")


class ExperimentConfig(BaseModel):
    """Everything the experiment depends on (TOML or JSON file; every field optional)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    # the rig
    scale: float = Field(0.1, gt=0, le=1, description="rig scale (sim.optics.rig.small_rig): "
                         "focal lengths in pixels and the projector size times this")
    camera_size: tuple[int, int] = Field((256, 128), description="cropped camera sensor "
                                         "(width, height), px; principal point at its centre")
    focus_distance_mm: float = Field(760.0, gt=0, description="paraxial focus distance of "
                                     "both true lenses, mm")
    lenses: tuple[LensSpec, LensSpec] = Field(
        (LensSpec(), LensSpec(vignetting_shift_mm=20.0, vignetting_radius_ratio=0.9,
                              spherical_mm=8.0)),
        description="the ground-truth lenses of camera 0 and camera 1")
    # the station
    lcd_pitch_mm: float = Field(0.75, gt=0, description="fake LCD pixel pitch, mm")
    lcd_distance_at_zero_mm: float = Field(550.0, gt=0, description="pupil to LCD at stage 0")
    depths_mm: tuple[float, ...] = Field((50.0, 90.0, 130.0, 290.0, 330.0, 370.0),
                                         min_length=3, description="stage readings of the LTC "
                                         "depths, mm (six in the paper)")
    period: int = Field(12, ge=4, description="Fourier pattern period P, LCD px")
    steps: int = Field(3, ge=3, le=4, description="Fourier phase steps")
    lens_samples: int = Field(256, ge=1, description="aperture samples K of the measured "
                              "lens: 256 measured better at large defocus than 128 on two "
                              "noise seeds (worst size 12 / 14 against 20 / 18 um), though "
                              "the samples with weight are only 61 against 53 per node "
                              "(benchmarks/README.md)")
    lens_grid_step: int = Field(4, ge=1, description="measured-lens node spacing, px")
    lens_settings: dict[str, float | int | bool] = Field(
        {"support_floor": 0.1, "deconvolve_iterations": 20, "aim_offset_sigma_px": 8.0,
         "aperture_cells": 64, "focus_zones": True},
        description="further settings of the station's lens step "
        "(station.lens.geometry.LensFitConfig): the samples drawn from the deblurred aperture "
        "distribution, each node's aim offset from the station's principal-ray slopes "
        "(benchmarks/README.md, 'What limits the measured lens'); the aperture on a 64-cell "
        "grid, on which the samples' quadrature has converged (K = 256 and 1024 agree within "
        "0.3 um; on 32 cells they differ by 4.6 um at the near large-defocus sphere, "
        "benchmarks/README.md); and the focus per pupil zone, through which the LTCs are "
        "mapped onto the aperture plane and the optical centre refitted (one focus skews a "
        "vignetted pupil and put the centre 23-31 um behind the pupil at paper size)")
    average_frames: int = Field(4, ge=1, description="camera frames averaged per station "
                                "pattern ([camera] average_frames): the noise of the principal "
                                "rays' intercepts / sqrt(N) (benchmarks/README.md)")
    seed: int = Field(0, description="fake camera noise seed")
    # the scanners
    lens_smoothing_nodes: float = Field(2.0, ge=0, description="the measured lenses' "
                                        "node-to-node measurement noise averaged over "
                                        "neighbouring nodes (Gaussian sigma, node spacings; "
                                        "sim.optics.measured_lens.smoothed_lens: the "
                                        "centroids by a local quadratic regression, the "
                                        "shape keeping its second moment and radial "
                                        "profile); 0: off")
    real_samples: int = Field(4096, ge=1, description="pupil samples of the real scanner's "
                              "lenses (soft clipping edge): converged, twice as many move its "
                              "clouds <= 0.4 um and its sizes <= 2.4 um (512 left a 26 um "
                              "size at the farthest sphere: benchmarks/README.md)")
    bench_samples: int = Field(2048, ge=1, description="pupil samples of each fake bench's "
                               "ground-truth lens (soft clipping edge), traced from each camera "
                               "pixel's centre, each ray spread over the pixel's footprint on "
                               "the LCD (sim.optics.plane_ltc): its principal rays then sit "
                               "~4 um RMS from the converged lens's at the pupil (512: 13 um, "
                               "which the measured lens inherited: benchmarks/README.md)")
    gaussian_samples: int | None = Field(None, ge=1, description="aperture samples of the "
                                         "Gaussian lens (default: the measured lens's K)")
    periods_px: tuple[float, ...] = Field((256.0, 32.0, 8.0), description="fringe periods, "
                                          "projector px (the first covers the projector)")
    # the objects: (world z, world y) mm, x = 0; world z = 0 is 760 mm from the cameras
    sphere_slight: tuple[tuple[float, float], ...] = Field(
        ((-30.0, -10.0), (30.0, 10.0), (-15.0, 12.0), (15.0, -12.0)),
        description="slight-defocus sphere centres (z, y), mm")
    sphere_large: tuple[tuple[float, float], ...] = Field(
        ((-150.0, 0.0), (160.0, 0.0), (-140.0, 8.0), (150.0, -10.0)),
        description="large-defocus sphere centres (z, y), mm")
    ballbar_slight: tuple[tuple[float, float], ...] = Field(
        ((-20.0, 0.0), (25.0, 0.0)), description="slight-defocus ball-bar centres (z, y), mm")
    ballbar_large: tuple[tuple[float, float], ...] = Field(
        ((-120.0, 0.0), (150.0, 0.0)), description="large-defocus ball-bar centres (z, y), mm")
    ballbar_roll_deg: float = Field(20.0, description="ball bar turned about the view axis, deg")
    ballbar_large_roll_deg: float | None = Field(
        None, description="the large-defocus ball bars' own turn about the view axis, deg "
        "(None: ballbar_roll_deg); farther away the crop is taller in mm, so a steeper bar "
        "fits where a flatter one overhangs sideways (--paper-size)")
    cad: bool = Field(True, description="scan the CAD part")
    cad_z_mm: float = Field(0.0, description="CAD part's world z, mm")


def paper_size_config(**overrides) -> ExperimentConfig:
    """The reference camera's pixel pitch and focal length (scale 1: f = 4638 px), the
    camera cropped to the region the objects occupy (LCD pitch and period of the paper)."""
    base = dict(scale=1.0, camera_size=(1536, 768), lcd_pitch_mm=0.2715, period=24, steps=4,
                lens_grid_step=8, periods_px=(1920.0, 240.0, 30.0),
                # the crop's common view of both cameras is ~160 mm wide at 640 mm: no pose of
                # the 248 mm bar fits it there (check_views), so the large-defocus bars are on
                # the far side, turned 25 degrees: each camera sees one ball at 808 / 817 mm
                # and the other at 857 / 867 mm. Farther, the 38.1 mm balls leave the
                # scanner's working range: at 899 mm 11 % of a ball's pixels pass the
                # projector-consistency check, against 66-77 % here (benchmarks/README.md)
                ballbar_large=((75.0, 0.0), (85.0, 0.0)), ballbar_large_roll_deg=25.0,
                # the paper-size station's node noise is small (4 frames averaged, nodes every
                # 8 px); smoothing over 2 nodes there moved which limb pixels the near-side
                # spheres kept and their own-point sizes by -16 / -35 um against real's, the
                # lens as measured by -4 / -3 um (benchmarks/README.md)
                lens_smoothing_nodes=0.0)
    base.update(overrides)
    return ExperimentConfig(**base)


def load_experiment_config(path: str | Path | None, **overrides) -> ExperimentConfig:
    """The config of a TOML or JSON file (None: the defaults), with ``overrides``; errors
    name the file and the field."""
    from sim.validation import format_validation_error

    data: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise StationError(f"{path}: no such experiment config")
        text = path.read_text(encoding="utf-8")
        try:
            data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
        except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
            raise StationError(f"{path}: not valid {path.suffix[1:].upper() or 'TOML'}: {exc}")
    data.update(overrides)
    try:
        return ExperimentConfig(**data)
    except ValidationError as exc:
        raise StationError(format_validation_error(str(path or "experiment config"), exc)) from exc


# --- the rig and the benches ------------------------------------------------------------------

def build_rig(cfg: ExperimentConfig):
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


def truth_lens(cfg: ExperimentConfig, index: int, samples: int):
    """Camera ``index``'s ground-truth lens with ``samples`` pupil samples."""
    from sim.optics.lens import AberratedLens

    s = cfg.lenses[index]
    return AberratedLens(pupil_diameter_mm=FOCAL_MM / s.f_number,
                         focus_distance_mm=cfg.focus_distance_mm,
                         vignetting_shift_mm=s.vignetting_shift_mm,
                         vignetting_radius_ratio=s.vignetting_radius_ratio,
                         spherical_mm=s.spherical_mm, samples=samples, edge="soft")


def lcd_size(cfg: ExperimentConfig, camera) -> tuple[int, int]:
    """LCD pixels covering the camera's view at the farthest depth, with a blur margin."""
    far = cfg.lcd_distance_at_zero_mm + max(cfg.depths_mm)
    f = camera.K_array[0, 0]
    margin = 2 * cfg.period
    return (int(np.ceil(camera.width / f * far / cfg.lcd_pitch_mm)) + margin,
            int(np.ceil(camera.height / f * far / cfg.lcd_pitch_mm)) + margin)


def station_config(cfg: ExperimentConfig, rig, index: int):
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


def measure_cameras(cfg: ExperimentConfig, rig, out: Path, progress: bool, log: Log,
                    force: bool = False) -> list[dict]:
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
        lens = summary["steps"]["lens"]["result"]
        w, h = lcd_size(cfg, cam)
        true_centre = np.array([(w - 1) / 2 * cfg.lcd_pitch_mm, (h - 1) / 2 * cfg.lcd_pitch_mm,
                                -cfg.lcd_distance_at_zero_mm])
        err = np.asarray(lens["optical_centre_mm"]) - true_centre
        rec = {"camera": cam.name, "folder": str(folder), "lens": str(folder / "lens.npz"),
               "figures": sorted(str(p) for p in (folder / "figures").glob("*.png")),
               "seconds": {k: v.get("seconds") for k, v in summary["steps"].items()},
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

def scanner_lenses(cfg: ExperimentConfig, measured: list) -> dict[str, tuple]:
    """Per scanner the lens of each camera: "ltc" the measured lenses smoothed over
    ``lens_smoothing_nodes``; "gaussian" from the measured lenses as derived (OPTICS.md
    section 7: the second moment of the measured LTC at the optical centre, which the
    derivation gives each node's samples exactly; averaging sample k over nodes narrows
    the deblurred samples by a few per cent, an artefact of the smoothing, not of the
    measurement)."""
    from sim.optics.lens import PinholeLens
    from sim.optics.measured_lens import gaussian_equivalent, smoothed_lens

    return {"real": tuple(truth_lens(cfg, i, cfg.real_samples) for i in range(2)),
            "ltc": tuple(smoothed_lens(m, cfg.lens_smoothing_nodes) for m in measured),
            "gaussian": tuple(gaussian_equivalent(m, cfg.gaussian_samples) for m in measured),
            "pinhole": (PinholeLens(), PinholeLens())}


RENDER = dict(projector={"input_bits": 8},
              camera={"exposure_e": 8000.0, "full_well_e": 10000.0, "bit_depth": 12,
                      "shot_noise": False, "read_noise_e": 0.0})


# --- the objects ------------------------------------------------------------------------------

@dataclass(frozen=True)
class Position:
    """One object pose: name (S1.., B1.., C1), kind ('sphere', 'ballbar', 'cad'), defocus
    group ('slight' or 'large'), world centre (3,) mm and its depth along camera 0's axis."""

    name: str
    kind: str
    defocus: str
    centre_mm: tuple[float, float, float]
    depth_mm: float


def positions(cfg: ExperimentConfig, rig) -> list[Position]:
    """Spheres (slight, then large), ball bars (slight, then large), the CAD part."""
    out = []
    groups = [("sphere", "S", "slight", cfg.sphere_slight), ("sphere", "S", "large", cfg.sphere_large),
              ("ballbar", "B", "slight", cfg.ballbar_slight),
              ("ballbar", "B", "large", cfg.ballbar_large)]
    if cfg.cad:
        groups.append(("cad", "C", "slight", ((cfg.cad_z_mm, 0.0),)))
    count: dict[str, int] = {}
    for kind, letter, group, items in groups:
        for z, y in items:
            count[letter] = count.get(letter, 0) + 1
            c = (0.0, float(y), float(z))
            depth = float(rig.cameras[0].to_device(np.array([c]))[0, 2])
            out.append(Position(f"{letter}{count[letter]}", kind, group, c, depth))
    return out


def cad_part_mesh(step_mm: float = 0.5):
    """The CAD part: a 120 x 80 mm plate (object frame, z towards the rig negative) with two
    steps (8 and 16 mm), two holes (12 and 8 mm diameter, 10 mm deep) and a freeform face
    (a smooth bump and saddle); a height field meshed every ``step_mm``, closed by no walls
    (the rig sees only its front)."""
    import trimesh

    xs = np.arange(-60.0, 60.0 + step_mm / 2, step_mm)
    ys = np.arange(-40.0, 40.0 + step_mm / 2, step_mm)
    X, Y = np.meshgrid(xs, ys)
    h = np.zeros_like(X)
    h[X > 20] = 8.0
    h[X > 42] = 16.0
    for cx, cy, r in ((5.0, -18.0, 6.0), (5.0, 18.0, 4.0)):
        h[(X - cx) ** 2 + (Y - cy) ** 2 < r * r] = -10.0
    free = X < -12
    u, v = (X + 36.0) / 24.0, Y / 40.0
    h[free] = (7.0 * np.exp(-(u**2 + (v / 0.6) ** 2)) + 3.0 * u * v)[free]
    verts = np.stack([X.ravel(), Y.ravel(), -h.ravel()], axis=1)
    ny, nx = X.shape
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    # x right, y down: (a, c, b) winds so that the normals point towards -z (the rig)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, d], -1).reshape(-1, 3)])
    return trimesh.Trimesh(verts, faces, process=False)


def scene_of(pos: Position, cfg: ExperimentConfig, cad_path: Path | None):
    """The ``sim`` scene of one position."""
    from sim.render.scene import BallBarObject, MeshObject, Scene, SphereObject

    if pos.kind == "sphere":
        obj = SphereObject(name=pos.name, pose={"t": list(pos.centre_mm)})
    elif pos.kind == "ballbar":
        roll = cfg.ballbar_roll_deg
        if pos.defocus == "large" and cfg.ballbar_large_roll_deg is not None:
            roll = cfg.ballbar_large_roll_deg
        a = np.radians(roll)
        R = [[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]]
        obj = BallBarObject(name=pos.name, diameter_mm=BALLBAR_BALL_MM,
                            centre_distance_mm=BALLBAR_LENGTH_MM,
                            pose={"t": list(pos.centre_mm), "R": R})
    else:
        obj = MeshObject(name=pos.name, path=cad_path, smooth_angle_deg=30.0,
                         pose={"t": list(pos.centre_mm)})
    return Scene(objects=[obj])


def view_extents_px(pos: Position, cfg: ExperimentConfig, rig, cad_mesh=None) -> np.ndarray:
    """Per camera the pixel box (u0, u1, v0, v1) the position's object covers (pinhole, the
    OpenCV pixel-centre convention): its balls' surfaces, or the CAD part's bounding box
    corners (``cad_mesh``, object frame)."""
    import trimesh

    if pos.kind != "cad":
        unit = trimesh.creation.icosphere(3).vertices
        balls = scene_of(pos, cfg, None).objects[0].spheres()
        pts = np.concatenate([c[:3] + c[3] * unit for c in balls])
    else:
        lo, hi = (cad_mesh if cad_mesh is not None else cad_part_mesh()).bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        pts = corners + np.asarray(pos.centre_mm)
    boxes = []
    for cam in rig.cameras:
        uv = cam.project(pts)
        boxes.append([uv[:, 0].min(), uv[:, 0].max(), uv[:, 1].min(), uv[:, 1].max()])
    return np.asarray(boxes)


def check_views(cfg: ExperimentConfig, rig, cad_mesh=None) -> None:
    """Refuse a config with an object that does not lie wholly inside both cameras' crops
    (which would leave a scan with too few, or no, pixels seen by both cameras), naming each
    such position, its overhang and what to change."""
    w, h = cfg.camera_size
    bad = []
    for pos in positions(cfg, rig):
        for i, (u0, u1, v0, v1) in enumerate(view_extents_px(pos, cfg, rig, cad_mesh)):
            over = max(-u0, u1 - (w - 1), -v0, v1 - (h - 1))
            if over > 0:
                bad.append(f"{pos.name} ({pos.kind} at z {pos.centre_mm[2]:g} mm) overhangs "
                           f"camera {i}'s {w} x {h} crop by {over:.0f} px (u {u0:.0f}..{u1:.0f},"
                           f" v {v0:.0f}..{v1:.0f})")
    if bad:
        raise StationError("experiment config: " + "; ".join(bad) + "; move or turn the "
                           "object (sphere_*, ballbar_*, cad_z_mm) or enlarge camera_size")


# --- measuring and comparing ------------------------------------------------------------------

def _pixel_keys(cloud) -> np.ndarray:
    """One integer per point naming its rig pixel (camera, v, u) (n,)."""
    f = cloud.fields
    return ((np.asarray(f["camera"], np.int64) * 1_000_000 + np.asarray(f["v"], np.int64))
            * 1_000_000 + np.asarray(f["u"], np.int64))


def _size_of(fits: list, pos: Position) -> float:
    """Sphere: diameter minus nominal; ball bar: centre distance minus nominal, mm."""
    if pos.kind == "sphere":
        return float(fits[0].diameter - SPHERE_DIAMETER_MM)
    return float(np.linalg.norm(fits[0].centre - fits[1].centre) - BALLBAR_LENGTH_MM)


@dataclass(frozen=True)
class SizeFit:
    """One scanner's size at one position on its own points: per ball the sphere fit and the
    pixel keys of the points it kept (its inliers); ``size_mm`` against nominal."""

    fits: tuple
    kept: tuple
    size_mm: float


def on_ball(points: np.ndarray, ball) -> np.ndarray:
    """Which points (n, 3) mm lie within ``SHELL_MM`` of the true ball (cx, cy, cz, r) mm:
    the points every size rule and coverage check counts."""
    cx, cy, cz, r = ball
    return np.abs(np.linalg.norm(points - [cx, cy, cz], axis=1) - r) < SHELL_MM


def size_fit(cloud, pos: Position, scene) -> SizeFit:
    """The size rule, the same for every scanner: each ball fitted (geometric least squares,
    ``fit_sphere``: 3-sigma robust trimming) to the cloud's points within ``SHELL_MM`` of the
    true ball; sphere: fitted diameter minus nominal; ball bar: fitted centre distance minus
    nominal (mm)."""
    from sim.metrology.spheres import fit_sphere

    points = np.asarray(cloud.points, dtype=np.float64)
    keys = _pixel_keys(cloud)
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


def check_coverage(scans: dict[str, Scan], pos: Position, scene, rig) -> None:
    """Refuse a size from balls a scanner barely saw: per ball, each blurring scanner's points
    within ``SHELL_MM`` must reach ``MIN_BALL_COVERAGE`` of the pinhole scanner's (the same
    decoder, no blur: whatever the pixel scale, it keeps what the silhouettes and shadows
    leave). Below it the ball lies outside the scanner's working range: its fringes are too
    blurred to pass the decoder's checks but in patches, and a sphere fitted to the patches is
    not a size (a 38.1 mm ball kept 11 % of its disc's pixels at +139 mm of defocus; with the
    far balls at +176 / +196 mm the real and virtual scanners' lengths differed by 0.7 mm:
    benchmarks/README.md)."""
    balls = scene.objects[0].spheres()

    def counts(cloud) -> list[int]:
        p = np.asarray(cloud.points, dtype=np.float64)
        return [int(on_ball(p, ball).sum()) for ball in balls]

    ref = counts(scans["pinhole"].cloud)
    for name in MODELS:
        if name == "pinhole":
            continue
        for k, (found, full) in enumerate(zip(counts(scans[name].cloud), ref)):
            if found < MIN_BALL_COVERAGE * full:
                cx, cy, cz, r = balls[k]
                depth = float(rig.cameras[0].to_device(np.array([[cx, cy, cz]]))[0, 2])
                raise StationError(
                    f"position {pos.name}, scanner {name}: ball {k + 1} ({2 * r:g} mm, "
                    f"{depth:.0f} mm from camera 0) gave {found} points against the pinhole "
                    f"scanner's {full} ({100 * found / max(full, 1):.0f} %, at least "
                    f"{100 * MIN_BALL_COVERAGE:.0f} % needed): it lies outside the scanner's "
                    f"working range; move it nearer focus (sphere_*, ballbar_*)")


def size_error_mm(own: SizeFit) -> dict:
    """``size_mm`` (own points against nominal) and the fits' largest RMS, mm."""
    return {"size_mm": own.size_mm, "fit_rms_mm": float(max(f.rms for f in own.fits))}


def shared_size_mm(cloud, own: SizeFit, real, real_own: SizeFit, pos: Position) -> dict:
    """Sizes of a virtual cloud and the real one compared on the pixels both share: per ball
    the pixels both scanners' own fits kept (``size_fit``), each cloud refitted there with no
    further trimming (``fit_sphere(reject_sigma=None)``), so the two sizes differ only by the
    per-point offsets, not by which points each scanner kept. Returns ``size_shared_mm`` and
    ``size_shared_real_mm`` (against nominal) and ``size_shared_points``."""
    from sim.metrology.spheres import fit_sphere

    fits, real_fits, count = [], [], 0
    pv, kv = np.asarray(cloud.points, np.float64), _pixel_keys(cloud)
    pr, kr = np.asarray(real.points, np.float64), _pixel_keys(real)
    for a, b in zip(own.kept, real_own.kept):
        both = np.intersect1d(a, b)
        if both.size < 20:
            raise StationError(f"position {pos.name}: the virtual and real clouds share only "
                               f"{both.size} pixels on a ball; move it into both cameras' view")
        iv = np.flatnonzero(np.isin(kv, both))
        ir = np.flatnonzero(np.isin(kr, both))
        iv, ir = iv[np.argsort(kv[iv])], ir[np.argsort(kr[ir])]
        fits.append(fit_sphere(pv[iv], reject_sigma=None))
        real_fits.append(fit_sphere(pr[ir], reject_sigma=None))
        count += both.size
    return {"size_shared_mm": _size_of(fits, pos), "size_shared_real_mm": _size_of(real_fits, pos),
            "size_shared_points": int(count)}


def world_cad_mesh(mesh, pos: Position):
    """The CAD mesh at the position's pose (world frame)."""
    m = mesh.copy()
    m.apply_translation(pos.centre_mm)
    return m


@dataclass
class Scan:
    """One scanner's result at one position: cloud (``PointCloud``, mm), camera 0's images,
    seconds."""

    cloud: object
    images: np.ndarray
    render_s: float


def scan_position(pos: Position, cfg: ExperimentConfig, rig, lenses: dict[str, tuple],
                  cad_path: Path | None) -> dict[str, Scan]:
    """Render and reconstruct the position with every scanner (one traced geometry)."""
    from sim.render.fringe_patterns import PhaseShiftSet
    from sim.render.images import RenderSettings
    from sim.scanner import Scanner

    patterns = PhaseShiftSet(periods_px=list(cfg.periods_px), steps=4, direction="u")
    base = Scanner(rig, lenses["real"], patterns, scene_of(pos, cfg, cad_path),
                   RenderSettings.model_validate(RENDER), where=f"position {pos.name}")
    out = {}
    for name in MODELS:
        s = base.with_lenses(lenses[name])
        t0 = time.perf_counter()
        images = s.render()
        dt = time.perf_counter() - t0
        try:
            cloud = s.scan(images)
        except ValueError as exc:  # name where: a long run's one line must say which scan
            raise StationError(f"position {pos.name} ({pos.kind}, {pos.defocus} defocus), "
                               f"scanner {name}: {exc}") from exc
        out[name] = Scan(cloud, images.cameras[0].images, dt)
    return out


def compare_position(pos: Position, cfg: ExperimentConfig, rig, scans: dict[str, Scan],
                     cad_path: Path | None, cad_mesh) -> dict:
    """The numbers of one position: per model the size error (sphere, ball bar) or the
    distances to the CAD mesh, and each virtual cloud against the real one, unaligned and
    after ICP (mm). Cloud against cloud is by pixel correspondence
    (``sim.metrology.compare.compare_by_pixel``: the same rig pixel in both clouds, away from
    the silhouettes; ICP aligns the whole clouds); ``*_nn_mm`` are the nearest-surface
    distances of every point (``compare_clouds``), which sparse clouds' differing rims bias."""
    from sim.metrology.compare import compare_by_pixel, compare_clouds, mesh_signed_distance
    from sim.metrology.measure import distance_stats

    scene = scene_of(pos, cfg, cad_path)
    real = scans["real"].cloud
    row = {"name": pos.name, "kind": pos.kind, "defocus": pos.defocus,
           "defocus_mm": round(pos.depth_mm - cfg.focus_distance_mm, 3),
           "centre_mm": list(pos.centre_mm), "models": {}}
    maps = {}
    world_mesh = world_cad_mesh(cad_mesh, pos) if pos.kind == "cad" else None
    real_size = None
    if pos.kind != "cad":
        check_coverage(scans, pos, scene, rig)
        real_size = size_fit(real, pos, scene)
    for name in MODELS:
        cloud = scans[name].cloud
        pts = cloud.points
        m: dict = {"points": int(len(pts)), "render_s": scans[name].render_s}
        if pos.kind == "cad":
            d = mesh_signed_distance(pts, world_mesh)
            m["cad"] = distance_stats(d)
            maps[f"cad_{name}"] = (pts, d)
        else:
            own = real_size if name == "real" else size_fit(cloud, pos, scene)
            m.update(size_error_mm(own))
            if name != "real":
                m.update(shared_size_mm(cloud, own, real, real_size, pos))
        if name != "real":
            nn = compare_clouds(pts, real.points, align=False)
            tf = compare_clouds(pts, real.points, align=True).transform
            c = compare_by_pixel(cloud, real)
            a = compare_by_pixel(cloud, real, transform=tf)
            m.update(mean_mm=c.mean, rmse_mm=c.rmse, mean_icp_mm=a.mean, rmse_icp_mm=a.rmse,
                     mean_nn_mm=nn.mean, rmse_nn_mm=nn.rmse, pixels_compared=int(c.index.size))
            maps[name] = (pts[c.index], c.distances)
        row["models"][name] = m
    return row, maps


POSITIONS = "positions"  # one finished position per file pair: NAME.npz, then NAME.json


def start_or_resume(cfg: ExperimentConfig, out: Path) -> bool:
    """Make ``out`` this experiment's folder, or take up the unfinished one there; returns
    whether it resumes. Refuses a finished experiment, one with another config, and a folder
    that is not an experiment's."""
    config_path = out / "experiment.json"
    data = cfg.model_dump(mode="json")
    if config_path.exists():
        if (out / "results.json").exists():
            raise UsageError(f"{out} holds a finished experiment ({out / 'results.json'}); "
                             "choose a new --out folder")
        try:
            same = json.loads(config_path.read_text(encoding="utf-8")) == data
        except (OSError, ValueError):
            same = False
        if not same:
            raise UsageError(f"{out} holds an experiment started with another config "
                             f"({config_path}); use a new --out, or the same config to "
                             "resume it")
        return True
    if out.exists() and any(p.name != LOCK_NAME for p in out.iterdir()):
        raise UsageError(f"--out {out} exists and is not an experiment's folder; choose a new "
                         "--out folder")
    out.mkdir(parents=True, exist_ok=True)
    write_json(config_path, data)
    return False


def _sha256(path: str | Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


def check_lenses(out: Path, lens_paths: list[str]) -> None:
    """Record the measured lenses' digests (``out/lenses.json``) before the first position is
    scanned; on resume, refuse lenses that differ from those the scanned positions used."""
    record = out / "lenses.json"
    now = [{"file": str(p), "sha256": _sha256(p)} for p in lens_paths]
    if not record.exists():
        write_json(record, {"lenses": now})
        return
    before = json.loads(record.read_text(encoding="utf-8"))["lenses"]
    for i, (a, b) in enumerate(zip(before, now)):
        if a["sha256"] != b["sha256"]:
            raise UsageError(f"{b['file']}: camera {i}'s measured lens differs from the one "
                             f"this experiment's positions were scanned with ({record}: "
                             f"{a['file']}); use a new --out")


def image_position(poss: list[Position]) -> str | None:
    """The position whose fringe images the report shows: the first large-defocus sphere or
    ball bar, else the first one."""
    objects = [p for p in poss if p.kind != "cad"]
    pick = [p for p in objects if p.defocus == "large"] or objects
    return pick[0].name if pick else None


def save_position(folder: Path, name: str, row: dict, maps: dict, images: dict | None) -> None:
    """One finished position, durably: its arrays (``NAME.npz``: per map
    ``KEY.points_mm`` (n, 3) and ``KEY.distances_mm`` (n,), per model ``images.MODEL``),
    then its numbers (``NAME.json``), which mark it done."""
    folder.mkdir(exist_ok=True)
    arrays = {}
    for key, (pts, d) in maps.items():
        arrays[f"{key}.points_mm"] = np.asarray(pts)
        arrays[f"{key}.distances_mm"] = np.asarray(d)
    for model, im in (images or {}).items():
        arrays[f"images.{model}"] = np.asarray(im)
    with durable_file(folder / f"{name}.npz", "wb") as f:
        np.savez(f, **arrays)
    write_json(folder / f"{name}.json", row)


def load_position(folder: Path, name: str) -> tuple[dict, dict, dict | None] | None:
    """A position finished in an earlier run (row, maps, images or None), or None."""
    import zipfile

    row_path, arr_path = folder / f"{name}.json", folder / f"{name}.npz"
    if not row_path.exists():
        return None
    again = f"delete {row_path} and {arr_path} to scan position {name} again"
    try:
        row = json.loads(row_path.read_text(encoding="utf-8"))
        with np.load(arr_path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}  # every member's CRC-32 is checked here
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise StationError(f"{arr_path}: unreadable ({exc}); {again}") from exc
    if row.get("name") != name:
        raise StationError(f"{row_path}: holds position {row.get('name')!r}, not {name}; {again}")
    maps = {k[: -len(".points_mm")]: (v, arrays[k[: -len(".points_mm")] + ".distances_mm"])
            for k, v in arrays.items() if k.endswith(".points_mm")}
    images = {k[len("images."):]: v for k, v in arrays.items() if k.startswith("images.")}
    return row, maps, images or None


def run_experiment(cfg: ExperimentConfig, out: str | Path, *, progress: bool = True,
                   log: Log = print, lenses: list[str | Path] | None = None,
                   force: bool = False) -> dict:
    """The whole experiment into the folder ``out`` (see the module docstring); returns the
    results (also ``out/results.json``). ``lenses``: two measured-lens files made with this
    config, used instead of running the station.

    Resumable: run again with the same config and ``out`` after an interruption, and the
    station's steps and the positions already finished (``out/positions``) are taken up, not
    redone; a different config or different lenses are refused. One run writes the folder
    at a time (``writer.lock``, as the stores'). ``force`` takes over the writer locks a
    killed run left (the folder's, the stations', their run stores'; never a live
    writer's)."""
    from sim.optics.measured_lens import load_lens

    out = Path(out)
    t_start = time.perf_counter()
    rig = build_rig(cfg)
    cad_mesh = cad_part_mesh() if cfg.cad else None
    check_views(cfg, rig, cad_mesh)
    resumed = start_or_resume(cfg, out)
    with StoreLock(out, force=force):  # one experiment writes a folder at a time
        if resumed:
            log(f"resuming the experiment in {out}")
        if lenses is None:
            station = measure_cameras(cfg, rig, out, progress, log, force)
            lens_paths = [s["lens"] for s in station]
        else:
            station, lens_paths = [], [str(p) for p in lenses]
        measured = [load_lens(p) for p in lens_paths]
        for i, m in enumerate(measured):
            if tuple(m.camera_size) != tuple(cfg.camera_size):
                raise StationError(f"{lens_paths[i]}: the lens is for a {m.camera_size} camera, "
                                   f"this experiment's cameras are {cfg.camera_size}")
        check_lenses(out, lens_paths)
        models = scanner_lenses(cfg, measured)
        cad_path = None
        if cfg.cad:
            cad_path = out / "cad_part.ply"
            if not cad_path.exists():
                with durable_file(cad_path, "wb") as f:
                    cad_mesh.export(f, file_type="ply")
        rows, maps, images = [], {}, {}
        poss = positions(cfg, rig)
        shown = image_position(poss)
        folder = out / POSITIONS
        t_scan, earlier = time.perf_counter(), 0
        for k, pos in enumerate(poss):
            t0 = time.perf_counter()
            done = load_position(folder, pos.name)
            if done is None:
                scans = scan_position(pos, cfg, rig, models, cad_path)
                row, mp = compare_position(pos, cfg, rig, scans, cad_path, cad_mesh)
                pics = {n: scans[n].images for n in MODELS} if pos.name == shown else None
                save_position(folder, pos.name, row, mp, pics)
                took = f"{time.perf_counter() - t0:.0f} s"
            else:
                row, mp, pics = done
                earlier += 1
                took = "scanned in an earlier run"
            rows.append(row)
            maps[pos.name] = mp
            if pos.name == shown:
                if pics is None:
                    raise StationError(f"{folder / (pos.name + '.npz')}: has no fringe images; "
                                       f"delete {folder / (pos.name + '.json')} and it to scan "
                                       f"position {pos.name} again")
                images = {"name": pos.name, "defocus": pos.defocus, **pics}
            log(f"[{k + 1}/{len(poss)}] {position_line(row)} [{took}]")
        scan_s = time.perf_counter() - t_scan
        render_s = {n: float(sum(r["models"][n]["render_s"] for r in rows)) for n in MODELS}
        results = {
            "report": str(out / "report.md"),
            "positions": [public_row(r) for r in rows],
            "rows": rows,
            "station": station,
            "lenses": [{"file": p, "samples": m.samples, "focus_distance_mm": m.focus_distance_mm,
                        "gaussian_sigma_mm": models["gaussian"][i].sigma_mm}
                       for i, (p, m) in enumerate(zip(lens_paths, measured))],
            "render_s": render_s,
            "render_vs_pinhole": {n: render_s[n] / render_s["pinhole"] for n in MODELS},
            "acceptance": acceptance(rows),
            "seconds": {"total": time.perf_counter() - t_start, "scan": scan_s},
            "resumed": {"resumed": resumed, "positions_from_earlier_runs": earlier},
            "config": cfg.model_dump(mode="json"),
            "date": _dt.date.today().isoformat(),
            "machine": machine(),
        }
        from station.experiment.report import write_report

        results["figures"] = write_report(results, cfg, rig, measured, models, maps, images, out)
        write_json(out / "results.json", results)
        return results


def public_row(row: dict) -> dict:
    """One position in the ``ltc demo --json`` shape (micrometres)."""
    models = {}
    for n, m in row["models"].items():
        d = {}
        if "size_mm" in m:
            d["size_um"] = round(m["size_mm"] * 1e3, 2)
        if "cad" in m:
            d["cad_mean_um"] = round(m["cad"]["mean_mm"] * 1e3, 2)
            d["cad_rmse_um"] = round(m["cad"]["rmse_mm"] * 1e3, 2)
        for k in ("mean", "rmse", "mean_icp", "rmse_icp"):
            if f"{k}_mm" in m:
                d[f"{k}_um"] = round(m[f"{k}_mm"] * 1e3, 2)
        models[n] = d
    return {"name": row["name"], "kind": row["kind"], "defocus": row["defocus"],
            "defocus_mm": row["defocus_mm"], "models": models}


def position_line(row: dict) -> str:
    """One line per position: ltc and Gaussian against real, sizes."""
    m = row["models"]
    head = f"{row['name']} ({row['kind']}, {row['defocus']}, {row['defocus_mm']:+.0f} mm):"
    parts = [f"{n} {m[n]['mean_mm'] * 1e3:+.1f}/{m[n]['rmse_mm'] * 1e3:.1f} um" for n in VIRTUAL]
    if "size_mm" in m["real"]:
        parts.append("size " + " ".join(f"{n} {m[n]['size_mm'] * 1e3:+.0f}" for n in MODELS)
                     + " um, on shared pixels ltc - real " + f"{size_vs_real_um(m['ltc']):+.0f}"
                     + " um")
    return head + " " + ", ".join(parts)


def size_vs_real_um(m: dict) -> float:
    """A virtual scanner's size minus the real scanner's, compared on the pixels both clouds
    share (``shared_size_mm``), um."""
    return (m["size_shared_mm"] - m["size_shared_real_mm"]) * 1e3


def acceptance(rows: list[dict], mean_um: float = 5.0, rmse_um: float = 10.0,
               size_um: float = 20.0) -> dict:
    """The issue's acceptance on the sphere and ball-bar positions: ltc against real (mean
    within +-mean_um, RMSE <= rmse_um, size within size_um of real's at every position,
    sizes compared on the pixels both clouds share: ``size_vs_real_um``); Gaussian worse
    than ltc at every large-defocus position in |mean| and size error; and how similar the
    two are near focus. ``ltc_worst.size_own_um``: the same on each scanner's own points."""
    sel = [r for r in rows if r["kind"] in ("sphere", "ballbar")]
    ltc_ok, gauss_worse = [], []
    worst = {"mean_um": 0.0, "rmse_um": 0.0, "size_um": 0.0, "size_own_um": 0.0}
    for r in sel:
        m = r["models"]
        l, g, real = m["ltc"], m["gaussian"], m["real"]
        dl = abs(size_vs_real_um(l))
        worst["mean_um"] = max(worst["mean_um"], abs(l["mean_mm"]) * 1e3)
        worst["rmse_um"] = max(worst["rmse_um"], l["rmse_mm"] * 1e3)
        worst["size_um"] = max(worst["size_um"], dl)
        worst["size_own_um"] = max(worst["size_own_um"],
                                   abs(l["size_mm"] - real["size_mm"]) * 1e3)
        ok = abs(l["mean_mm"]) * 1e3 <= mean_um and l["rmse_mm"] * 1e3 <= rmse_um \
            and dl <= size_um
        if not ok:
            ltc_ok.append(r["name"])
        if r["defocus"] == "large":
            dg = abs(size_vs_real_um(g))
            if not (abs(g["mean_mm"]) > abs(l["mean_mm"]) and dg > dl):
                gauss_worse.append(r["name"])
    slight = [r for r in sel if r["defocus"] == "slight"]
    near = {n: {"abs_mean_um": float(np.mean([abs(r["models"][n]["mean_mm"]) for r in slight]) * 1e3),
                "rmse_um": float(np.mean([r["models"][n]["rmse_mm"] for r in slight]) * 1e3)}
            for n in ("ltc", "gaussian")} if slight else {}
    return {"ltc_within_limits": not ltc_ok, "ltc_failing": ltc_ok,
            "gaussian_worse_at_large": not gauss_worse, "gaussian_not_worse": gauss_worse,
            "ltc_worst": worst, "near_focus_average": near,
            "limits": {"mean_um": mean_um, "rmse_um": rmse_um, "size_um": size_um}}


def machine() -> str:
    """CPU, cores, memory, OS and Python in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")),
                       cpu)
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return (f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB, {platform.system()} "
            f"{platform.release()}, Python {platform.python_version()}")
