"""The render benchmark's scene (shared by ``render_vs_mitsuba.py`` and ``reconstruct_mitsuba.py``),
our side of it, and the image comparison.

Scene (world frame: origin at the sphere centre, z away from the camera, y down, mm): the
50.8007 mm sphere; a plane 100 mm behind it facing the camera; one 2048 x 1088 camera (16 mm
lens on 6.9 um pixels) 760 mm in front of the sphere looking along +z; one 1920 x 1080 projector
200 mm to the camera's right aimed at the sphere centre. Both devices are ideal centred pinholes
(principal point at the image centre, no distortion) because Mitsuba's projector is one.
Patterns: 4-step phase shift at periods of 1, 1/8 and 1/64 of the projector width (1920, 240
and 30 px), 12 images, fringes along u.
"""

from __future__ import annotations


import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from sim.render.fringe_patterns import PhaseShiftSet
from sim.optics.lens import AberratedLens, PinholeLens
from sim.fpp.phase import wrapped_phase
from sim.optics.projection import camera_to_world
from sim.optics.rig import DeviceCalibration, Rig, look_at
from sim.render.scene import PlaneObject, Pose, Scene, SphereObject

CAMERA_SIZE = (2048, 1088)
CAMERA_FOCAL_MM = 16.0
CAMERA_PITCH_MM = 0.0069  # 2 x 2 binned 3.45 um pixels
PROJECTOR_SIZE = (1920, 1080)
PROJECTOR_FOCAL_PX = 3040.0
WORKING_DISTANCE_MM = 760.0
PROJECTOR_OFFSET_MM = 200.0
PLANE_BEHIND_MM = 100.0
PLANE_SIZE_MM = (1000.0, 600.0)
SPHERE_DIAMETER_MM = 50.8007
PERIOD_DIVISORS = (1, 8, 64)  # fringe periods: projector width / these
STEPS = 4


class BenchConfig(BaseModel):
    """Settings of one benchmark run."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    scale: float = Field(1.0, gt=0, le=1, description="image sizes and focal lengths times this "
                         "(1: the 2048 x 1088 camera and 1920 x 1080 projector); < 1 for smoke runs")
    repeats: int = Field(5, ge=1, description="timed repeats of every case; medians are reported")
    pinhole_spp: int = Field(64, ge=1, description="Mitsuba samples per pixel for the pinhole agreement")
    thin_samples: int = Field(64, ge=1, description="thin-lens rays per pixel, both renderers")
    f_number: float = Field(2.8, gt=0, description="thin lens: focal length / entrance pupil diameter")
    variant: str = Field("llvm_ad_rgb", description="Mitsuba variant")
    sampler: str = Field("stratified", description="Mitsuba sampler (independent, stratified, ...)")
    band_fraction: float = Field(0.125, gt=0, le=1, description="fraction of the camera rows (a band "
                                 "through the sphere) for the thin-lens throughput and pattern-count cases")
    mitsuba: bool = Field(True, description="run the Mitsuba cases")


def _device(name: str, size: tuple[int, int], f_px: float, centre, target) -> DeviceCalibration:
    R, T = look_at(np.asarray(centre, dtype=float), np.asarray(target, dtype=float))
    w, h = size
    K = [[f_px, 0.0, (w - 1) / 2], [0.0, f_px, (h - 1) / 2], [0.0, 0.0, 1.0]]
    return DeviceCalibration(name=name, K=K, dist=[0.0] * 5, R=R, T=T, size=size)


def _scaled(size: tuple[int, int], scale: float) -> tuple[int, int]:
    return max(8, round(size[0] * scale)), max(8, round(size[1] * scale))


def bench_rig(cfg: BenchConfig) -> Rig:
    """Camera 0 is the benchmark camera; ``Rig`` wants two, so camera 1 is a copy of it."""
    s = cfg.scale
    cam = _device("camera", _scaled(CAMERA_SIZE, s), CAMERA_FOCAL_MM / CAMERA_PITCH_MM * s,
                  [0.0, 0.0, -WORKING_DISTANCE_MM], [0.0, 0.0, 0.0])
    proj = _device("projector", _scaled(PROJECTOR_SIZE, s), PROJECTOR_FOCAL_PX * s,
                   [PROJECTOR_OFFSET_MM, 0.0, -WORKING_DISTANCE_MM], [0.0, 0.0, 0.0])
    return Rig(cameras=[cam, cam.model_copy(update={"name": "camera_copy"})], projector=proj)


def bench_scene() -> Scene:
    return Scene(objects=[
        SphereObject(name="sphere", diameter_mm=SPHERE_DIAMETER_MM, pose=Pose(t=[0.0, 0.0, 0.0])),
        PlaneObject(name="plane", size_mm=PLANE_SIZE_MM, pose=Pose(t=[0.0, 0.0, PLANE_BEHIND_MM])),
    ])


def bench_lens(kind: str, cfg: BenchConfig) -> PinholeLens | AberratedLens:
    """``pinhole`` or ``thin`` (ideal thin lens focused on the sphere centre)."""
    if kind == "pinhole":
        return PinholeLens()
    if kind == "thin":
        return AberratedLens(pupil_diameter_mm=CAMERA_FOCAL_MM / cfg.f_number,
                             focus_distance_mm=WORKING_DISTANCE_MM, samples=cfg.thin_samples)
    raise ValueError(f"lens kind must be 'pinhole' or 'thin', got '{kind}'")


def bench_patterns(rig: Rig, direction: str = "u") -> tuple[PhaseShiftSet, np.ndarray]:
    """The pattern set and its images (12 along u; 24 with ``direction='both'``)."""
    wp = rig.projector.width
    ps = PhaseShiftSet(periods_px=[wp / d for d in PERIOD_DIVISORS], steps=STEPS, direction=direction)
    return ps, ps.images(rig.projector.size)


def band_pixels(cam: DeviceCalibration, fraction: float) -> np.ndarray:
    """Flat indices of a band of rows centred on the image (through the sphere)."""
    w, h = cam.size
    rows = max(1, round(h * fraction))
    r0 = (h - rows) // 2
    return np.arange(r0 * w, (r0 + rows) * w, dtype=np.int64)


def surface_points(cam: DeviceCalibration, depth: np.ndarray) -> np.ndarray:
    """World points (H, W, 3) mm of the chief rays' hits from a depth map (H, W) (NaN: none)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    xy = cam.normalized(np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64))
    pc = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) * depth.reshape(-1, 1)
    return camera_to_world(pc, cam.R_array, cam.T_array).reshape(h, w, 3)


def blur_radius_px(cam: DeviceCalibration, lens, depth: np.ndarray) -> float:
    """Largest thin-lens blur-disk radius (camera px) over the depths seen (0 for a pinhole)."""
    if isinstance(lens, PinholeLens):
        return 0.0
    z = depth[np.isfinite(depth)]
    d_px = cam.K_array[0, 0] * lens.pupil_diameter_mm * np.abs(1 / lens.focus_distance_mm - 1 / z)
    return float(0.5 * d_px.max(initial=0.0))


def comparison_mask(lit: np.ndarray, object_id: np.ndarray, margin_px: int) -> np.ndarray:
    """Lit pixels whose whole ``(2 margin + 1)^2`` neighbourhood is lit and shows one object:
    silhouettes, shadow edges and the projector's border are left out (H, W) bool."""
    k = 2 * margin_px + 1
    same = ndimage.minimum_filter(object_id, k) == ndimage.maximum_filter(object_id, k)
    return ndimage.binary_erosion(lit, np.ones((k, k), bool)) & same & (object_id >= 0)


def agreement(ours: np.ndarray, theirs: np.ndarray, white: np.ndarray, mask: np.ndarray) -> dict:
    """Differences of two image stacks (n, H, W) on ``mask`` as fractions of each pixel's white
    level ``white`` (H, W): median, 99th percentile and largest |difference|, the mean signed
    difference, and the fraction of pixel values more than 1 % of white apart."""
    e = (theirs[:, mask] - ours[:, mask]) / white[mask]
    a = np.abs(e)
    return dict(pixels=int(mask.sum()), median=float(np.median(a)), p99=float(np.percentile(a, 99)),
                max=float(a.max()), bias=float(e.mean()), over_1pct=float(np.mean(a > 0.01)))


def phase_rms_rad(ours: np.ndarray, theirs: np.ndarray, mask: np.ndarray) -> float:
    """RMS (rad) over ``mask`` of the wrapped-phase difference of two N-step stacks (N, H, W)."""
    d = wrapped_phase(theirs).phase[mask] - wrapped_phase(ours).phase[mask]
    d = np.angle(np.exp(1j * d))
    return float(np.sqrt(np.mean(d * d)))


def machine() -> str:
    """CPU, cores, memory, OS (``station.experiment.run.machine``) and the renderers' versions,
    in one line."""
    from station.experiment.run import machine as base

    vers = []
    for mod in ("embreex", "mitsuba", "drjit"):
        try:
            vers.append(f"{mod} {__import__(mod).__version__}")
        except ImportError:
            pass
    return base() + ("; " + ", ".join(vers) if vers else "")
