"""The real-scan folder: what a lab brings to validate its twin (docs/formats.md, "Real-scan
folder").

::

    REAL_DIR/
      scan.toml                   rig, pattern set, optional camera and projector response
      rig.yaml                    the rig file (ltc calibrate, or any stereoCalibrate output)
      patterns.json               the pattern set (as ltc scan --patterns reads it)
      positions/NAME/position.toml   the artefact and its nominal size
      positions/NAME/camera_0/    camera 0's fringe images, one per pattern (as ltc scan reads)
      positions/NAME/camera_1/    camera 1's

``load_real_scan`` reads and checks it: every refusal is one line naming the position and the
camera (``RealScanError``).
"""

from __future__ import annotations

import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar, cast

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from station.errors import StationError

if TYPE_CHECKING:
    from sim.optics.rig import Rig
    from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet

_M = TypeVar("_M", bound=BaseModel)

SCAN_FILE = "scan.toml"
POSITION_FILE = "position.toml"
POSITIONS = "positions"
CAMERA_IMAGES = 1.0 / 12.0  # a real camera's square pixels average their area (px^2)


class RealScanError(StationError):
    """A real-scan folder that cannot be validated; one line naming the position and camera."""


class ResponseSpec(BaseModel):
    """What the lab knows of its cameras and projector (all optional)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    exposure_ms: float | None = Field(None, gt=0, description="the cameras' exposure, ms")
    gain_dn_per_e: float | None = Field(None, gt=0, description="camera gain, DN per electron "
                                        "(with read_noise_e: the noise model)")
    read_noise_e: float | None = Field(None, ge=0, description="camera read noise, electrons")
    dark: tuple[Path, Path] | None = Field(None, description="one dark frame per camera "
                                           "(image files, relative to the folder): offset "
                                           "and read noise")
    bit_depth: int | None = Field(None, ge=1, le=32, description="the cameras' ADC bits "
                                  "(default: from the images' type)")
    projector_gamma: float = Field(1.0, gt=0, description="projector light = value ** gamma")
    projector_input_bits: int = Field(8, ge=1, le=16, description="projector input bits")


class ScanFile(BaseModel):
    """``scan.toml``: the folder's rig, patterns, camera and projector response."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    rig: Path = Field(description="rig file, relative to the folder")
    patterns: Path = Field(description="pattern set JSON, relative to the folder")
    pixel_variance_px2: float = Field(CAMERA_IMAGES, ge=0, description="second moment of a "
                                      "pixel's spatial response per axis, px^2 (ltc scan "
                                      "--pixel-variance): 1/12 for camera images, 0 for "
                                      "renders that sample pixel centres")
    response: ResponseSpec = Field(default_factory=ResponseSpec)


class Pose(BaseModel):
    """A rigid pose, world from object: ``x_world = R x_object + t`` (mm)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    R: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                 (0.0, 0.0, 1.0))
    t: tuple[float, float, float] = (0.0, 0.0, 0.0)


class SphereArtefact(BaseModel):
    """A sphere of nominal ``diameter_mm``."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["sphere"] = "sphere"
    diameter_mm: float = Field(gt=0)


class BallBarArtefact(BaseModel):
    """A ball bar: two balls of ``ball_diameter_mm``, centres ``centre_distance_mm`` apart."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["ballbar"] = "ballbar"
    ball_diameter_mm: float = Field(gt=0)
    centre_distance_mm: float = Field(gt=0)


class CadArtefact(BaseModel):
    """A CAD part: its mesh (relative to the position file) and optionally a rough pose."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: Literal["cad"] = "cad"
    mesh: Path
    pose: Pose | None = None


Artefact = Annotated[SphereArtefact | BallBarArtefact | CadArtefact,
                     Field(discriminator="kind")]
AnyArtefact = SphereArtefact | BallBarArtefact | CadArtefact  # for annotations


class PositionFile(BaseModel):
    """``positions/NAME/position.toml``: the artefact; ``true_pose`` only where known (a
    simulation), reported beside the refined pose, never used to find it."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    artefact: Artefact
    defocus: Literal["slight", "large"] | None = Field(None, description="optional label")
    true_pose: Pose | None = None


@dataclass(frozen=True)
class RealPosition:
    """One position of a real-scan folder: its name, folder, artefact and pattern images."""

    name: str
    folder: Path
    spec: PositionFile

    def images(self, rig: Rig, patterns: PhaseShiftSet | GrayCodeSet) -> list[np.ndarray]:
        """Both cameras' image stacks (n, H, W), checked against the rig and pattern set."""
        return read_position_images(self, rig, patterns)


@dataclass(frozen=True)
class RealScan:
    """A loaded real-scan folder: its rig, pattern set, settings and positions."""

    folder: Path
    spec: ScanFile
    rig: Rig
    patterns: PhaseShiftSet | GrayCodeSet
    positions: tuple[RealPosition, ...]

    def position(self, name: str) -> RealPosition:
        for p in self.positions:
            if p.name == name:
                return p
        raise RealScanError(f"position {name}: not in {self.folder / POSITIONS} "
                            f"(positions: {', '.join(p.name for p in self.positions)})")


def _read_toml_or_json(path: Path, what: str) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
        return json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise RealScanError(f"{path}: {what} not readable: {exc}") from exc


def _model(cls: type[_M], data: dict[str, Any], where: str) -> _M:
    from sim.validation import format_validation_error

    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        raise RealScanError(format_validation_error(where, exc)) from exc


def load_real_scan(folder: str | Path, names: list[str] | None = None) -> RealScan:
    """Read a real-scan folder's ``scan.toml``, rig, pattern set and position files (the
    images are read per position, ``RealPosition.images``). ``names``: only these positions
    (each must exist). Raises ``RealScanError`` naming the file, position and field."""
    from sim.fpp.scan_input import ScanInputError, load_pattern_set
    from sim.optics.rig import Rig

    folder = Path(folder)
    path = folder / SCAN_FILE
    if not path.is_file():
        raise RealScanError(f"{folder}: no {SCAN_FILE}; a real-scan folder names its rig and "
                            "pattern set there (docs/formats.md, 'Real-scan folder')")
    spec = _model(ScanFile, _read_toml_or_json(path, "scan file"), str(path))
    try:
        rig = Rig.load(folder / spec.rig)
    except (OSError, ValueError) as exc:
        raise RealScanError(f"{path}: field 'rig': {exc}") from exc
    if len(rig.cameras) != 2:
        raise RealScanError(f"{folder / spec.rig}: {len(rig.cameras)} cameras; a real scan is "
                            "stereo (2 cameras)")
    try:
        size = (int(rig.projector.size[0]), int(rig.projector.size[1]))
        patterns = cast("PhaseShiftSet | GrayCodeSet",
                        load_pattern_set(folder / spec.patterns, size))
    except ScanInputError as exc:
        raise RealScanError(f"{path}: field 'patterns': {exc}") from exc
    root = folder / POSITIONS
    found = sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    if names:
        missing = [n for n in names if n not in found]
        if missing:
            raise RealScanError(f"position {missing[0]}: no folder {root / missing[0]}")
        found = list(names)
    if not found:
        raise RealScanError(f"{root}: no position folders")
    positions = []
    for name in found:
        pf = root / name / POSITION_FILE
        if not pf.is_file():
            raise RealScanError(f"position {name}: no {POSITION_FILE} in {root / name} (the "
                                "artefact and its nominal size)")
        pspec = _model(PositionFile, _read_toml_or_json(pf, "position file"),
                       f"position {name}: {pf}")
        if isinstance(pspec.artefact, CadArtefact):
            mesh = pf.parent / pspec.artefact.mesh
            if not mesh.is_file():
                raise RealScanError(f"position {name}: {pf}: field 'artefact.mesh': {mesh} not "
                                    "found")
        positions.append(RealPosition(name, root / name, pspec))
    return RealScan(folder, spec, rig, patterns, tuple(positions))


def read_position_images(pos: RealPosition, rig: Rig, patterns: PhaseShiftSet | GrayCodeSet
                         ) -> list[np.ndarray]:
    """Both cameras' stacks (n, H, W) of one position, as ``ltc scan`` reads them; refuses a
    missing camera folder, images of differing sizes, a stack whose count is not the pattern
    set's, and images whose size is not the rig camera's, each naming position and camera."""
    from sim.fpp.scan_input import ScanInputError, _read_stack

    stacks = []
    count = len(patterns.descriptors(rig.projector.size))
    for i, cam in enumerate(rig.cameras):
        where = f"position {pos.name}, camera {i}"
        sub = pos.folder / f"camera_{i}"
        if not sub.is_dir():
            raise RealScanError(f"{where}: no image folder {sub}")
        try:
            stack = _read_stack(sub)
        except ScanInputError as exc:
            raise RealScanError(f"{where}: {exc}") from exc
        if len(stack) != count:
            raise RealScanError(f"{where}: {len(stack)} images in {sub}, the pattern set has "
                                f"{count}")
        h, w = stack.shape[1:]
        if (w, h) != tuple(cam.size):
            raise RealScanError(f"{where}: images are {w} x {h} px, the rig's camera "
                                f"'{cam.name}' is {cam.size[0]} x {cam.size[1]}: the rig does "
                                "not fit the images (is it this scanner's calibration?)")
        stacks.append(stack)
    return stacks


def write_json_model(path: Path, model: BaseModel) -> None:
    """A pydantic model as JSON (``write_durable``)."""
    write_durable(path, model.model_dump_json(indent=2).encode())


def write_durable(path: Path, data: bytes) -> None:
    """The one place this package writes a file: durably, through ``sim.storage``'s durable
    write (temporary file, fsync, rename, fsync of the folder)."""
    from sim.storage.durable import durable_file

    path.parent.mkdir(parents=True, exist_ok=True)
    with durable_file(path, "wb") as f:
        f.write(data)


def write_position(folder: Path, name: str, spec: PositionFile, stacks: list[np.ndarray]
                   ) -> Path:
    """Write one position of a real-scan folder: ``positions/NAME/position.toml`` (written
    last) and per camera one 16-bit PNG per pattern (``pattern_NNN.png``; float images are
    rounded and clipped to 0..65535)."""
    import cv2
    import tomli_w

    out = Path(folder) / POSITIONS / name
    for i, stack in enumerate(stacks):
        for k, im in enumerate(np.asarray(stack)):
            a = np.clip(np.rint(im), 0, 65535).astype(np.uint16)
            ok, buf = cv2.imencode(".png", a)
            if not ok:
                raise RealScanError(f"position {name}, camera {i}: PNG encoding failed")
            write_durable(out / f"camera_{i}" / f"pattern_{k:03d}.png", buf.tobytes())
    data = spec.model_dump(mode="json", exclude_none=True)
    write_durable(out / POSITION_FILE, tomli_w.dumps(data).encode())
    return out


def write_scan_file(folder: Path, rig: Rig, patterns: PhaseShiftSet | GrayCodeSet, *,
                    pixel_variance_px2: float = CAMERA_IMAGES,
                    response: ResponseSpec | None = None) -> None:
    """Write a real-scan folder's ``rig.json``, ``patterns.json`` and ``scan.toml``."""
    import tomli_w

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_durable(folder / "rig.json", rig.model_dump_json(indent=2).encode())
    write_durable(folder / "patterns.json", patterns.model_dump_json(indent=2).encode())
    spec = ScanFile(rig=Path("rig.json"), patterns=Path("patterns.json"),
                    pixel_variance_px2=pixel_variance_px2, response=response or ResponseSpec())
    write_durable(folder / SCAN_FILE,
                  tomli_w.dumps(spec.model_dump(mode="json", exclude_none=True)).encode())
