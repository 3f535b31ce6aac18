"""Each sample's scene, drawn from (config, seed, index): objects, pose, albedo, backdrop,
lenses, projector, camera and pattern set; and the description that regenerates it alone.

Every random choice of a sample comes from its own stream
``np.random.default_rng([seed, index, STREAM])``, one stream per aspect, so a sample never
depends on another sample, on the order samples are made in, or on how many workers make
them; and changing, say, the lens ranges leaves the poses of every sample as they were.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sim.dataset.config import (
    AberratedChoice,
    DatasetConfig,
    GaussianChoice,
    GrayCodeChoice,
    MeasuredChoice,
    PhaseShiftChoice,
    Placement,
    ThinChoice,
)
from sim.dataset.objects import mesh_files
from sim.errors import SimError, SimInputError
from sim.optics.lens import AberratedLens, GaussianLens, PinholeLens
from sim.optics.rig import DeviceCalibration, Rig
from sim.render.fringe_patterns import GrayCodeSet, PatternSet, PhaseShiftSet
from sim.render.images import CameraResponse, ProjectorResponse
from sim.render.scene import Pose

FORMAT_VERSION = 1
# the streams of a sample: np.random.default_rng([seed, index, stream])
OBJECT, POSE, LENS, PROJECTOR, CAMERA, PATTERN, SPLIT, NOISE = range(8)


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SampleObject(_Model):
    """One object of a sample: procedural (``family`` drawn from ``seed``), a mesh file
    (``path``), or the backdrop (a plane of ``extent_mm``); normalised to a bounding sphere of
    ``size_mm`` (not the backdrop), then placed by ``pose`` (object frame to world, mm)."""

    kind: Literal["procedural", "mesh", "backdrop"]
    family: str | None = None
    seed: list[int] | None = None
    path: str | None = None
    size_mm: float = Field(0.0, ge=0)
    extent_mm: tuple[float, float] | None = None
    albedo: float = Field(ge=0, le=1)
    pose: Pose


class MeasuredLensDraw(_Model):
    """A measured lens file with its aperture samples scaled by ``pupil_scale``."""

    kind: Literal["measured"] = "measured"
    path: str
    pupil_scale: float = Field(1.0, gt=0)


LensDraw = PinholeLens | GaussianLens | AberratedLens | MeasuredLensDraw  # told apart by kind


class SampleScene(_Model):
    """Everything a sample is made of: with this and the software version it is regenerated
    alone (``sim.dataset.generate.render_sample``)."""

    format_version: int = FORMAT_VERSION
    seed: int
    index: int
    split: Literal["train", "val", "test"]
    rig: Rig
    objects: list[SampleObject]
    lenses: list[LensDraw]
    projector: ProjectorResponse
    camera: CameraResponse
    patterns: PatternSet
    noise_seed: list[int]


def stream(seed: int, index: int, which: int) -> np.random.Generator:
    """The sample's independent random stream ``which``."""
    return np.random.default_rng([seed, index, which])


def _u(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])


def _pick(rng: np.random.Generator, choices: list):
    w = np.array([c.weight for c in choices], dtype=np.float64)
    return choices[int(rng.choice(len(choices), p=w / w.sum()))]


def split_of(cfg: DatasetConfig, index: int) -> str:
    """The split of sample ``index``: drawn from its own stream with the config's fractions."""
    x = stream(cfg.seed, index, SPLIT).random()
    s = cfg.split
    return "train" if x < s.train else "val" if x < s.train + s.val else "test"


# ---------------------------------------------------------------- the working volume


def _frustum(dev: DeviceCalibration) -> np.ndarray:
    """Inward unit normals (4, 3), device frame, of the planes through the device's centre and
    its image's edges (pixel borders, with distortion)."""
    w, h = dev.size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5], [-0.5, h - 0.5]])
    c = np.concatenate([dev.normalized(corners), np.ones((4, 1))], axis=1)
    n = np.cross(c, np.roll(c, -1, axis=0))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return n * np.sign(n @ np.array([0.0, 0.0, 1.0]))[:, None]


def _fits(devices: list[DeviceCalibration], normals: list[np.ndarray], centres: np.ndarray,
          radius: float) -> np.ndarray:
    """(m,) bool: each ball (centres (m, 3) world, radius mm) lies inside every device's
    view."""
    ok = np.ones(len(centres), bool)
    for dev, n in zip(devices, normals, strict=True):
        x = dev.to_device(centres)
        ok &= (x[:, 2] >= radius + 1.0) & np.all(x @ n.T >= radius, axis=1)
    return ok


def default_distance_mm(rig: Rig) -> tuple[float, float]:
    """+-15 % around the projector-distance of the point nearest to every optical axis."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for dev in (*rig.cameras, rig.projector):
        d = dev.R_array[2]
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ dev.centre_world
    x = np.linalg.lstsq(a, b, rcond=None)[0]
    z = float(rig.projector.to_device(x[None])[0, 2])
    return 0.85 * z, 1.15 * z


def place(rig: Rig, placement: Placement, radius_mm: float, rng: np.random.Generator
          ) -> np.ndarray | None:
    """A centre (3,) world mm for a ball of ``radius_mm`` inside the common working volume:
    the first of ``placement.tries`` draws (through a uniformly random projector pixel at a
    uniformly random distance) that fits; None when none does."""
    devices = [*rig.cameras, rig.projector]
    normals = [_frustum(d) for d in devices]
    lo, hi = placement.distance_mm or default_distance_mm(rig)
    p = rig.projector
    w, h = p.size
    m = placement.tries
    uv = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5], size=(m, 2))
    z = rng.uniform(lo, hi, size=m)
    xy = p.normalized(uv)
    ray = np.concatenate([xy, np.ones((m, 1))], axis=1) * z[:, None]
    centres = (ray - p.T_array) @ p.R_array
    ok = np.flatnonzero(_fits(devices, normals, centres, radius_mm))
    return centres[ok[0]] if len(ok) else None


def check_fits(rig: Rig, cfg: DatasetConfig, where: str = "config") -> None:
    """Refuse (ValueError) a rig whose common working volume cannot hold the largest object."""
    size = cfg.objects.size_mm[1]
    rng = np.random.default_rng([cfg.seed, 2**32 - 1])
    probe = cfg.placement.model_copy(update={"tries": max(50000, cfg.placement.tries)})
    if place(rig, probe, size / 2, rng) is None:
        lo, hi = cfg.placement.distance_mm or default_distance_mm(rig)
        raise SimInputError(
            f"{where}: the rig's common working volume (what both cameras and the projector "
            f"see, {lo:.0f}-{hi:.0f} mm from the projector) cannot hold an object of "
            f"{size:g} mm: lower objects.size_mm or change placement.distance_mm")


# ---------------------------------------------------------------- drawing a sample


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


SHEETS = ("plane", "displaced", "holes", "steps")  # families with a front: turned to the rig
SHEET_TILT_DEG = 50.0


def _facing(rig: Rig, centre: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A rotation whose z axis points at the projector, tilted by up to ``SHEET_TILT_DEG``
    about a random axis, spun about itself at random."""
    view = centre - rig.projector.centre_world
    z = -view / np.linalg.norm(view)
    spin = _axis_rotation(z, rng.uniform(0, 2 * math.pi))
    tilt = _axis_rotation(np.cross(z, rng.normal(size=3)),
                          math.radians(rng.uniform(0, SHEET_TILT_DEG)))
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    base = np.stack([x, np.cross(z, x), z], axis=1)
    return tilt @ spin @ base


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _backdrop(rig: Rig, pl: Placement, centre: np.ndarray, radius: float,
              rng: np.random.Generator) -> SampleObject:
    """A plane behind the object, facing the projector (tilted), covering its field."""
    p = rig.projector
    view = centre - p.centre_world
    dist = float(np.linalg.norm(view))
    view /= dist
    gap = _u(rng, pl.backdrop_gap_mm)
    t = centre + view * (radius + gap)
    tilt = math.radians(_u(rng, pl.backdrop_tilt_deg))
    axis = np.cross(view, rng.normal(size=3))
    normal = _axis_rotation(axis, tilt) @ (-view)
    z = normal / np.linalg.norm(normal)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
    R = np.stack([x, np.cross(z, x), z], axis=1)
    w, h = p.size
    far = dist + radius + gap
    extent = (1.5 * far * w / p.K_array[0, 0], 1.5 * far * h / p.K_array[1, 1])
    return SampleObject(kind="backdrop", extent_mm=extent, albedo=_u(rng, pl.backdrop_albedo),
                        pose=Pose(R=R.tolist(), t=t.tolist()))


def _lens(choice, rng: np.random.Generator):
    if isinstance(choice, GaussianChoice):
        return GaussianLens(sigma_mm=_u(rng, choice.sigma_mm),
                            focus_distance_mm=_u(rng, choice.focus_distance_mm),
                            samples=choice.samples)
    if isinstance(choice, ThinChoice):
        return AberratedLens(pupil_diameter_mm=_u(rng, choice.pupil_diameter_mm),
                             focus_distance_mm=_u(rng, choice.focus_distance_mm),
                             samples=choice.samples)
    if isinstance(choice, AberratedChoice):
        return AberratedLens(pupil_diameter_mm=_u(rng, choice.pupil_diameter_mm),
                             focus_distance_mm=_u(rng, choice.focus_distance_mm),
                             spherical_mm=_u(rng, choice.spherical_mm),
                             coma_mm=_u(rng, choice.coma_mm), samples=choice.samples)
    if isinstance(choice, MeasuredChoice):
        return MeasuredLensDraw(path=str(choice.path), pupil_scale=_u(rng, choice.pupil_scale))
    return PinholeLens()


def _patterns(choice, rng: np.random.Generator) -> PhaseShiftSet | GrayCodeSet:
    steps = int(choice.steps[int(rng.integers(len(choice.steps)))])
    if isinstance(choice, PhaseShiftChoice):
        periods = choice.periods_px[int(rng.integers(len(choice.periods_px)))]
        return PhaseShiftSet(steps=steps, periods_px=list(periods), direction="u")
    assert isinstance(choice, GrayCodeChoice)
    period = float(choice.period_px[int(rng.integers(len(choice.period_px)))])
    return GrayCodeSet(steps=steps, period_px=period, direction="u")


def draw_scene(cfg: DatasetConfig, rig: Rig, index: int) -> SampleScene:
    """The scene of sample ``index`` (a pure function of the config, the rig and the index)."""
    seed, src = cfg.seed, cfg.objects
    r = stream(seed, index, OBJECT)
    size = _u(r, src.size_mm)
    albedo = _u(r, src.albedo)
    obj: dict[str, Any]
    if src.mesh_folder is not None and r.random() < src.mesh_fraction:
        files = mesh_files(src.mesh_folder)
        obj = dict(kind="mesh", path=str(files[int(r.integers(len(files)))]))
    else:
        fams = [f for f, w in src.families.items() if w > 0]
        w = np.array([src.families[f] for f in fams])
        obj = dict(kind="procedural", family=fams[int(r.choice(len(fams), p=w / w.sum()))],
                   seed=[seed, index, int(r.integers(2**31))])
    rp = stream(seed, index, POSE)
    centre = place(rig, cfg.placement, size / 2, rp)
    if centre is None:
        raise SimInputError(f"sample {index}: no pose in {cfg.placement.tries} draws puts an "
                         f"object of {size:.1f} mm inside the rig's common working volume; "
                         "lower objects.size_mm or raise placement.tries")
    if obj.get("family") in SHEETS:
        R = _facing(rig, centre, rp)
    else:
        R = _rotation(rp)
    objects = [SampleObject(**obj, size_mm=size, albedo=albedo,
                            pose=Pose(R=R.tolist(), t=centre.tolist()))]
    if rp.random() < cfg.placement.backdrop_probability:
        objects.append(_backdrop(rig, cfg.placement, centre, size / 2, rp))
    rl = stream(seed, index, LENS)
    if len(cfg.lenses) != len(rig.cameras):
        raise SimInputError(f"lenses: {len(cfg.lenses)} lens lists for {len(rig.cameras)} cameras")
    lenses = [_lens(_pick(rl, choices), rl) for choices in cfg.lenses]
    rj, pc = stream(seed, index, PROJECTOR), cfg.projector
    projector = ProjectorResponse(input_bits=pc.input_bits, gamma=_u(rj, pc.gamma),
                                  black_level=_u(rj, pc.black_level),
                                  defocus_sigma_px=_u(rj, pc.defocus_sigma_px))
    rc, cc = stream(seed, index, CAMERA), cfg.camera
    camera = CameraResponse(exposure_e=_u(rc, cc.exposure_e), full_well_e=cc.full_well_e,
                            shot_noise=cc.shot_noise, read_noise_e=_u(rc, cc.read_noise_e),
                            bit_depth=cc.bit_depth, quantize=cc.quantize)
    rq = stream(seed, index, PATTERN)
    patterns = _patterns(_pick(rq, cfg.patterns), rq)
    return SampleScene(seed=seed, index=index, split=split_of(cfg, index), rig=rig,
                       objects=objects, lenses=lenses, projector=projector, camera=camera,
                       patterns=patterns, noise_seed=[seed, index, NOISE])


def config_rig(cfg: DatasetConfig, where: str = "config") -> Rig:
    """The config's rig: its rig file, or the built-in rig at the config's sizes; errors name
    ``where`` and the field."""
    if cfg.rig.path is not None:
        try:
            return Rig.load(cfg.rig.path)
        except FileNotFoundError as exc:
            raise FileNotFoundError(f"{where}: field 'rig.path': {exc}") from exc
        except SimError as exc:
            raise SimInputError(f"{where}: field 'rig.path': {exc}") from exc
    from sim.optics.rig import CAMERA_FOCAL_MM, CAMERA_PITCH_MM, PROJECTOR_FOCAL_PX, _scaled_rig

    b = cfg.rig.builtin
    rig = _scaled_rig(b.camera_size_px, b.projector_size_px, 1.0, b.distortion)
    f_cam = CAMERA_FOCAL_MM / CAMERA_PITCH_MM * b.camera_scale
    f_proj = PROJECTOR_FOCAL_PX * b.projector_scale

    def focal(dev: DeviceCalibration, f: float) -> DeviceCalibration:
        K = dev.K_array.copy()
        K[0, 0] = K[1, 1] = f
        return DeviceCalibration(**{**dev.model_dump(), "K": K.tolist()})

    return Rig(cameras=[focal(c, f_cam) for c in rig.cameras],
               projector=focal(rig.projector, f_proj))
