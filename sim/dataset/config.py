"""The data-set config: one TOML file describing what every sample may be (docs/formats.md,
"Fringe data set").

Every range is ``[low, high]`` and a sample draws uniformly inside it; a choice list is drawn
with the weights given. Unknown fields are refused; errors name the file and the field
(``sim.validation.format_validation_error``). Lengths in mm, angles in degrees, image sizes in
pixels (width, height); the unit is in each field's name.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from sim.errors import SimInputError
from sim.validation import format_validation_error, read_toml

Range = tuple[float, float]


def _check_range(name: str, r: Range, low: float | None = None) -> None:
    if not r[0] <= r[1]:
        raise ValueError(f"{name} must be [low, high] with low <= high, got {list(r)}")
    if low is not None and r[0] < low:
        raise ValueError(f"{name} must be >= {low:g}, got {list(r)}")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class BuiltinRig(_Model):
    """The built-in rig (``sim.optics.rig``'s reference system: cameras 760 mm from the
    centre of the volume at +-15 degrees, projector between them) at chosen image sizes:
    each device's focal length is the reference's times its ``*_scale``."""

    camera_size_px: tuple[int, int] = Field((960, 960), description="camera (width, height)")
    camera_scale: float = Field(0.25, gt=0, le=1, description="camera focal length / 4638 px")
    projector_size_px: tuple[int, int] = Field((1920, 1080), description="(width, height)")
    projector_scale: float = Field(1.0, gt=0, le=1, description="projector focal / 3040 px")
    distortion: bool = Field(True, description="the reference's lens distortion")


class RigSource(_Model):
    """Where the rig comes from: a rig file (``path``, e.g. from a calibration; relative to the
    config file) or the built-in rig."""

    path: Path | None = Field(None, description="rig file (OpenCV YAML or JSON); None: built-in")
    builtin: BuiltinRig = Field(default_factory=BuiltinRig)


Family = Literal["primitive", "union", "displaced", "steps", "holes", "sphere", "ball_bar",
                 "plane"]
FAMILIES: tuple[Family, ...] = get_args(Family)


class ObjectSource(_Model):
    """What each sample shows: one object, from the user's mesh folder (with probability
    ``mesh_fraction``) or from the built-in procedural families (weights ``families``)."""

    mesh_folder: Path | None = Field(None, description="folder of PLY/STL/OBJ meshes")
    mesh_fraction: float = Field(0.0, ge=0, le=1, description="share of samples from the folder")
    families: dict[Family, float] = Field(
        default_factory=lambda: {f: 1.0 for f in FAMILIES},
        description="procedural families and their weights")
    size_mm: Range = Field((60.0, 140.0), description="bounding-sphere diameter, mm")
    albedo: Range = Field((0.3, 1.0), description="diffuse reflectance")

    @model_validator(mode="after")
    def _check(self):
        _check_range("size_mm", self.size_mm, 1e-3)
        _check_range("albedo", self.albedo, 0.0)
        if self.albedo[1] > 1:
            raise ValueError(f"albedo must lie in [0, 1], got {list(self.albedo)}")
        if self.mesh_fraction > 0 and self.mesh_folder is None:
            raise ValueError("mesh_fraction > 0 needs mesh_folder")
        if self.mesh_fraction < 1 and not any(w > 0 for w in self.families.values()):
            raise ValueError("families: at least one weight must be > 0")
        if any(w < 0 for w in self.families.values()):
            raise ValueError("families: weights must be >= 0")
        return self


class Placement(_Model):
    """Pose inside the rig's common working volume (every camera and the projector see the
    whole object): the object's centre at a distance from the projector within
    ``distance_mm`` (default: +-15 % around where the optical axes meet), a uniformly random
    rotation; a backdrop plane behind it with probability ``backdrop_probability``."""

    distance_mm: Range | None = Field(None, description="from the projector centre, mm")
    backdrop_probability: float = Field(0.5, ge=0, le=1)
    backdrop_gap_mm: Range = Field((10.0, 80.0), description="object's back to backdrop, mm")
    backdrop_tilt_deg: Range = Field((0.0, 20.0), description="backdrop tilt from facing, deg")
    backdrop_albedo: Range = Field((0.2, 0.9))
    tries: int = Field(5000, ge=1, description="draws before a pose is declared impossible")

    @model_validator(mode="after")
    def _check(self):
        if self.distance_mm is not None:
            _check_range("distance_mm", self.distance_mm, 1e-3)
        _check_range("backdrop_gap_mm", self.backdrop_gap_mm, 0.0)
        _check_range("backdrop_tilt_deg", self.backdrop_tilt_deg, 0.0)
        _check_range("backdrop_albedo", self.backdrop_albedo, 0.0)
        return self


class PinholeChoice(_Model):
    kind: Literal["pinhole"] = "pinhole"
    weight: float = Field(1.0, ge=0, description="relative probability")


class GaussianChoice(_Model):
    """``sim.optics.lens.GaussianLens`` with sigma and focus drawn in their ranges."""

    kind: Literal["gaussian"] = "gaussian"
    weight: float = Field(1.0, ge=0)
    sigma_mm: Range = Field((0.2, 1.0), description="aperture weight std, mm")
    focus_distance_mm: Range = Field((700.0, 820.0))
    samples: int = Field(32, ge=1, description="aperture samples per pixel")


class ThinChoice(_Model):
    """An ideal thin lens (``AberratedLens`` without aberrations)."""

    kind: Literal["thin"] = "thin"
    weight: float = Field(1.0, ge=0)
    pupil_diameter_mm: Range = Field((1.0, 4.0))
    focus_distance_mm: Range = Field((700.0, 820.0))
    samples: int = Field(32, ge=1)


class AberratedChoice(_Model):
    """``sim.optics.lens.AberratedLens`` with spherical aberration and coma drawn too."""

    kind: Literal["aberrated"] = "aberrated"
    weight: float = Field(1.0, ge=0)
    pupil_diameter_mm: Range = Field((1.0, 4.0))
    focus_distance_mm: Range = Field((700.0, 820.0))
    spherical_mm: Range = Field((0.0, 0.02), description="spherical aberration, mm")
    coma_mm: Range = Field((0.0, 0.01), description="coma, mm")
    samples: int = Field(32, ge=1)


class MeasuredChoice(_Model):
    """A measured lens file (``ltc lens``; relative to the config file), its pupil scaled by a
    factor drawn in ``pupil_scale`` (1: as measured; the defocus grows with it)."""

    kind: Literal["measured"] = "measured"
    weight: float = Field(1.0, ge=0)
    path: Path = Field(description="lens file (.npz) for this camera size")
    pupil_scale: Range = Field((1.0, 1.0))


LensChoice = Annotated[PinholeChoice | GaussianChoice | ThinChoice | AberratedChoice
                       | MeasuredChoice, Field(discriminator="kind")]


class ProjectorChoice(_Model):
    gamma: Range = Field((1.0, 1.0), description="light = value ** gamma")
    defocus_sigma_px: Range = Field((0.0, 0.0), description="Gaussian blur, projector px")
    black_level: Range = Field((0.0, 0.0), description="black pixel light, fraction of white")
    input_bits: int | None = Field(8, ge=1, le=16, description="pattern bits (None: exact)")


class CameraChoice(_Model):
    exposure_e: Range = Field((4000.0, 9000.0), description="electrons at radiance 1")
    full_well_e: float = Field(10000.0, gt=0)
    read_noise_e: Range = Field((0.0, 0.0), description="read noise, electrons rms")
    shot_noise: bool = Field(False, description="Poisson photon noise")
    bit_depth: Literal[8, 12, 16] = 8
    quantize: bool = Field(True, description="round to integers (False: float32 DN)")


class PhaseShiftChoice(_Model):
    """N-step phase shift at 2 or 3 frequencies: ``steps`` and ``periods_px`` drawn from their
    lists (each entry of ``periods_px`` one set of periods, projector px)."""

    kind: Literal["phase_shift"] = "phase_shift"
    weight: float = Field(1.0, ge=0)
    steps: list[int] = Field([4], min_length=1)
    periods_px: list[list[float]] = Field([[2048.0, 128.0, 16.0]], min_length=1)

    @model_validator(mode="after")
    def _check(self):
        if any(n < 3 for n in self.steps):
            raise ValueError(f"steps must all be >= 3, got {self.steps}")
        if any(len(p) not in (1, 2, 3) or min(p) <= 0 for p in self.periods_px):
            raise ValueError("periods_px: each set has 1 to 3 periods > 0")
        return self


class GrayCodeChoice(_Model):
    """Gray code plus N-step phase shift at one period (``sim.render.GrayCodeSet``)."""

    kind: Literal["gray_code"] = "gray_code"
    weight: float = Field(1.0, ge=0)
    steps: list[int] = Field([4], min_length=1)
    period_px: list[float] = Field([32.0], min_length=1)


PatternChoice = Annotated[PhaseShiftChoice | GrayCodeChoice, Field(discriminator="kind")]


def _pinhole_per_camera() -> list[list[LensChoice]]:
    """The default lenses: a pinhole for each of the two cameras."""
    return [[PinholeChoice()], [PinholeChoice()]]


def _phase_shift_only() -> list[PatternChoice]:
    """The default patterns: phase shifting only."""
    return [PhaseShiftChoice()]


class Split(_Model):
    train: float = Field(0.8, ge=0)
    val: float = Field(0.1, ge=0)
    test: float = Field(0.1, ge=0)

    @model_validator(mode="after")
    def _check(self):
        if abs(self.train + self.val + self.test - 1) > 1e-9:
            raise ValueError("train + val + test must be 1")
        return self


class Storage(_Model):
    """Lossless compression of every array (zarr v3 codecs; blosc with bit shuffle). The
    default, zstd level 3, was chosen by measurement (docs/decisions/0048)."""

    codec: Literal["zstd", "blosc_zstd", "blosc_lz4", "gzip", "none"] = "zstd"
    level: int = Field(3, ge=0, le=22)


class DatasetConfig(_Model):
    """Contents of a data-set config file (see the module docstring)."""

    seed: int = Field(0, ge=0, description="the data set's seed; samples are (seed, index)")
    rig: RigSource = Field(default_factory=RigSource)
    objects: ObjectSource = Field(default_factory=ObjectSource)
    placement: Placement = Field(default_factory=Placement)
    lenses: list[list[LensChoice]] = Field(
        default_factory=_pinhole_per_camera,
        description="per camera, the lens models to draw from")
    projector: ProjectorChoice = Field(default_factory=ProjectorChoice)
    camera: CameraChoice = Field(default_factory=CameraChoice)
    patterns: list[PatternChoice] = Field(default_factory=_phase_shift_only,
                                          min_length=1)
    split: Split = Field(default_factory=Split)
    storage: Storage = Field(default_factory=Storage)

    @model_validator(mode="after")
    def _check(self):
        for i, choices in enumerate(self.lenses):
            if not choices or not any(c.weight > 0 for c in choices):
                raise ValueError(f"lenses[{i}]: give at least one lens with weight > 0")
        if not any(p.weight > 0 for p in self.patterns):
            raise ValueError("patterns: at least one weight must be > 0")
        return self


def _absolute(cfg: DatasetConfig, base: Path) -> DatasetConfig:
    """``cfg`` with every relative path (rig, mesh folder, lens files) made absolute from
    ``base``."""
    def a(p: Path | None) -> Path | None:
        return None if p is None or p.is_absolute() else base / p

    rig = cfg.rig.model_copy(update={"path": a(cfg.rig.path) or cfg.rig.path})
    objects = cfg.objects.model_copy(
        update={"mesh_folder": a(cfg.objects.mesh_folder) or cfg.objects.mesh_folder})
    lenses = [[c.model_copy(update={"path": a(c.path) or c.path}) if isinstance(c, MeasuredChoice)
               else c for c in cam] for cam in cfg.lenses]
    return cfg.model_copy(update={"rig": rig, "objects": objects, "lenses": lenses})


def parse_config(raw: dict, source: str = "config", base_dir: Path | None = None
                 ) -> DatasetConfig:
    """A config from parsed TOML (or a manifest's JSON); relative paths start at ``base_dir``
    (default: the working directory); errors (ValueError) name ``source`` and the field."""
    try:
        cfg = DatasetConfig.model_validate(raw)
    except ValidationError as exc:
        raise SimInputError(format_validation_error(source, exc)) from exc
    return _absolute(cfg, (base_dir or Path.cwd()).resolve())


def load_config(path: str | Path) -> DatasetConfig:
    """Read a data-set config TOML file; errors name the file and the field."""
    path = Path(path)
    raw = read_toml(path, "data-set config")
    return parse_config(raw, str(path), path.parent)
