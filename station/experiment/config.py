"""The experiment's config (``ExperimentConfig``, TOML or JSON), its ground-truth lenses
(``LensSpec``), the paper-size preset and the experiment's constants (nominal sizes, mm)."""

from __future__ import annotations

import json
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from station.errors import StationError
from station.lens.geometry import LensFitConfig

SPHERE_DIAMETER_MM = 50.8007
BALLBAR_LENGTH_MM = 209.8219
BALLBAR_BALL_MM = 38.1
FOCAL_MM = 16.0  # the reference system's lens (docs/optics.md section 1)
BENCH_SUBPIXELS = 1  # the fake benches trace each pixel's rays from its centre, each spread over
# the pixel's whole footprint on the LCD: the pixel's area, with all the rays for the pupil
REFERENCE_PITCH_UM = 3.45  # the reference cameras' pixel pitch (sim.optics.rig)
SHELL_MM = 2.0  # points this close to a true sphere go to its fit
MIN_BALL_COVERAGE = 0.25  # a blurring scanner's points on a ball / the pinhole scanner's
MODELS = ("real", "ltc", "gaussian", "pinhole")
VIRTUAL = ("ltc", "gaussian", "pinhole")
Log = Callable[[str], None]
_LENS_DEFAULTS = LensFitConfig()


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
    lens_samples: int = Field(_LENS_DEFAULTS.samples, ge=1, description="aperture samples K "
                              "of the measured lens (default: LensFitConfig's)")
    lens_grid_step: int = Field(_LENS_DEFAULTS.grid_step, ge=1, description="measured-lens "
                                "node spacing, px (default: LensFitConfig's)")
    lens_settings: dict[str, float | int | bool] = Field(
        {}, description="further settings of the station's lens step by name "
        "(station.lens.geometry.LensFitConfig); empty: LensFitConfig's defaults, the "
        "recommended settings (docs/decisions 0025)")
    average_frames: int = Field(4, ge=1, description="camera frames averaged per station "
                                "pattern ([camera] average_frames): the noise of the principal "
                                "rays' intercepts / sqrt(N) (docs/decisions 0015)")
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
                              "size at the farthest sphere: docs/decisions 0015)")
    bench_samples: int = Field(2048, ge=1, description="pupil samples of each fake bench's "
                               "ground-truth lens (soft clipping edge), traced from each camera "
                               "pixel's centre, each ray spread over the pixel's footprint on "
                               "the LCD (sim.optics.plane_ltc): its principal rays then sit "
                               "~4 um RMS from the converged lens's at the pupil (512: 13 um, "
                               "which the measured lens inherited: docs/decisions 0015)")
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


def paper_size_config(**overrides: Any) -> ExperimentConfig:
    """The reference camera's pixel pitch and focal length (scale 1: f = 4638 px), the
    camera cropped to the region the objects occupy (LCD pitch and period of the paper)."""
    base = dict(scale=1.0, camera_size=(1536, 768), lcd_pitch_mm=0.2715, period=24, steps=4,
                lens_grid_step=8, periods_px=(1920.0, 240.0, 30.0),
                # the crop's common view of both cameras is ~160 mm wide at 640 mm: no pose of
                # the 248 mm bar fits it there (check_views), so the large-defocus bars are on
                # the far side, turned 25 degrees: each camera sees one ball at 808 / 817 mm
                # and the other at 857 / 867 mm. Farther, the 38.1 mm balls leave the
                # scanner's working range: at 899 mm 11 % of a ball's pixels pass the
                # projector-consistency check, against 66-77 % here (docs/decisions 0015)
                ballbar_large=((75.0, 0.0), (85.0, 0.0)), ballbar_large_roll_deg=25.0,
                # the paper-size station's node noise is small (4 frames averaged, nodes every
                # 8 px); smoothing over 2 nodes there moved which limb pixels the near-side
                # spheres kept and their own-point sizes by -16 / -35 um against real's, the
                # lens as measured by -4 / -3 um (docs/decisions 0015)
                lens_smoothing_nodes=0.0)
    base.update(overrides)
    return ExperimentConfig(**base)


def load_experiment_config(path: str | Path | None, **overrides: Any) -> ExperimentConfig:
    """The config of a TOML or JSON file (None: the defaults), with ``overrides``; errors
    name the file and the field."""
    from sim.validation import format_validation_error

    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise StationError(f"{path}: no such experiment config")
        text = path.read_text(encoding="utf-8")
        try:
            data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
        except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
            raise StationError(
                f"{path}: not valid {path.suffix[1:].upper() or 'TOML'}: {exc}") from exc
    data.update(overrides)
    try:
        return ExperimentConfig(**data)
    except ValidationError as exc:
        raise StationError(format_validation_error(str(path or "experiment config"), exc)) from exc
