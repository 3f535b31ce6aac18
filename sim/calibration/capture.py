"""The calibration capture: what the projector shows and how the images are laid out on disk.

Per board pose and camera the capture holds one image with the projector fully on (white)
then the phase-shift fringe images along projector columns (``u``) then along projector rows
(``v``): ``CalibrationPatterns.images()`` in that order, which ``ltc patterns --calibration``
writes for a real projector. Layout (docs/formats.md, "Calibration capture")::

    CAPTURE_DIR/
      capture.json              # {"projector_size": [w, h], "u": {...}, "v": {...}}
      pose_000/camera_0/*.png   # sorted by name: white, u fringes, v fringes
      pose_000/camera_1/*.png
      pose_001/...

``u`` and ``v`` are phase-shift sets in ``ltc scan``'s vocabulary (``kind = "phase_shift"``,
``periods_px`` or ``fringes`` across the projector along that axis, ``steps``); each direction
has its own. Images may be 8-bit, 16-bit or float (PNG, TIFF, ``.npy``), as for ``ltc scan``.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from sim.calibration.errors import CalibrationError
from sim.fpp.decode import DecodeSettings, decode_view
from sim.fpp.scan_input import ScanInputError, _pattern_set, _read_stack
from sim.render.fringe_patterns import PhaseShiftSet
from sim.validation import format_validation_error

CAPTURE_FILE = "capture.json"


def default_direction(axis: str, projector_size: tuple[int, int]) -> PhaseShiftSet:
    """1, 8 and 64 fringes across the projector's width (u), 1, 6 and 36 across its height
    (v), 4 steps each."""
    w, h = projector_size
    if axis == "u":
        return PhaseShiftSet(direction="u", periods_px=[w / 1, w / 8, w / 64], steps=4)
    return PhaseShiftSet(direction="v", periods_px=[h / 1, h / 6, h / 36], steps=4)


class CalibrationPatterns(BaseModel):
    """What the projector shows at each board pose: white, then the ``u`` set, then the ``v``
    set (``images()``). Periods are in projector pixels."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    projector_size: tuple[int, int] = Field(description="projector (width, height), px")
    u: PhaseShiftSet = Field(description="phase shifts along projector columns")
    v: PhaseShiftSet = Field(description="phase shifts along projector rows")

    @model_validator(mode="after")
    def _axes(self) -> CalibrationPatterns:
        if self.u.direction != "u" or self.v.direction != "v":
            raise ValueError("field 'u' must have direction 'u' and field 'v' direction 'v'")
        if min(self.projector_size) < 1:
            raise ValueError(f"projector_size must be >= 1 px, got {self.projector_size}")
        return self

    @classmethod
    def default(cls, projector_size: tuple[int, int]) -> CalibrationPatterns:
        """``default_direction`` along both axes."""
        return cls(projector_size=projector_size, u=default_direction("u", projector_size),
                   v=default_direction("v", projector_size))

    @property
    def count(self) -> int:
        """Images per pose and camera."""
        size = self.projector_size
        return 1 + len(self.u.descriptors(size)) + len(self.v.descriptors(size))

    def images(self) -> np.ndarray:
        """Every projector image (n, H, W) float32 in [0, 1], in capture order."""
        w, h = self.projector_size
        white = np.ones((1, h, w), np.float32)
        return np.concatenate([white, self.u.images(self.projector_size),
                               self.v.images(self.projector_size)])

    def split(self, stack: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A camera's stack (n, H, W) as (white (H, W), u images, v images)."""
        nu = len(self.u.descriptors(self.projector_size))
        return stack[0], stack[1 : 1 + nu], stack[1 + nu :]

    def save(self, directory: Path) -> Path:
        """Write ``capture.json`` into ``directory``; returns its path."""
        path = Path(directory) / CAPTURE_FILE
        path.write_text(self.model_dump_json(indent=2))
        return path


def load_patterns(path: Path) -> CalibrationPatterns:
    """Read ``capture.json``; ``u`` and ``v`` may give ``fringes`` instead of ``periods_px``."""
    try:
        raw = json.loads(path.read_bytes())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: not a readable JSON file: {exc}") from exc
    if not isinstance(raw, dict) or "projector_size" not in raw:
        raise CalibrationError(f"{path}: expected an object with 'projector_size', 'u' and 'v'")
    size = raw["projector_size"]
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(s, int) for s in size)):
        raise CalibrationError(f"{path}: field 'projector_size' must be [width, height] in px")
    sets = {}
    for axis in ("u", "v"):
        item = raw.get(axis)
        if not isinstance(item, dict):
            raise CalibrationError(f"{path}: field '{axis}' must be a phase_shift pattern set")
        item = {"kind": "phase_shift", "direction": axis, **item}
        try:
            sets[axis] = _pattern_set(item, f"{path}: field '{axis}'", tuple(size))
        except ScanInputError as exc:
            raise CalibrationError(str(exc)) from exc
        if not isinstance(sets[axis], PhaseShiftSet):
            raise CalibrationError(f"{path}: field '{axis}' must be a phase_shift set")
    try:
        return CalibrationPatterns(projector_size=tuple(size), u=sets["u"], v=sets["v"])
    except ValidationError as exc:
        raise CalibrationError(format_validation_error(str(path), exc)) from exc


@dataclass(frozen=True)
class PoseView:
    """One camera's images of one pose: white (H, W) and its projector coordinate maps
    ``u_p``, ``v_p`` (H, W) projector px (NaN where the phase is invalid)."""

    pose: str
    camera: int
    white: np.ndarray
    u_p: np.ndarray
    v_p: np.ndarray


class Capture:
    """A calibration capture folder (see the module docstring)."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise CalibrationError(f"capture folder {self.directory} not found")
        cfile = self.directory / CAPTURE_FILE
        if not cfile.is_file():
            raise CalibrationError(f"{self.directory}: no {CAPTURE_FILE} (the projector size and "
                                   "the u and v pattern sets); see docs/formats.md")
        self.patterns = load_patterns(cfile)
        self.poses = sorted(p.name for p in self.directory.iterdir()
                            if p.is_dir() and p.name.startswith("pose_"))
        self.cameras = 2

    def stack(self, pose: str, camera: int) -> np.ndarray:
        """The images (n, H, W) of one pose and camera, checked against the pattern count."""
        folder = self.directory / pose / f"camera_{camera}"
        if not folder.is_dir():
            raise CalibrationError(f"{pose}, camera {camera}: folder {folder} missing")
        try:
            st = _read_stack(folder)
        except ScanInputError as exc:
            raise CalibrationError(f"{pose}, camera {camera}: {exc}") from exc
        if len(st) != self.patterns.count:
            raise CalibrationError(
                f"{pose}, camera {camera}: {len(st)} images, the capture's patterns need "
                f"{self.patterns.count} (white + {self.patterns.count - 1} fringe images)")
        return st

    def view(self, pose: str, camera: int, settings: DecodeSettings | None = None,
             features=None, margin_px: int = 40) -> PoseView:
        """Read and decode one pose and camera. ``features(white) -> (n, 2) pixels | None``:
        when given, only the box around the pixels it returns (plus ``margin_px``) is decoded
        (the maps are NaN elsewhere); None from it leaves the maps all NaN."""
        st = self.stack(pose, camera)
        white, su, sv = self.patterns.split(st)
        white = np.asarray(white, dtype=np.float64)
        h, w = white.shape
        box = (0, h, 0, w)
        if features is not None:
            uv = features(white)
            if uv is None or len(uv) == 0:
                nan = np.full((h, w), np.nan)
                return PoseView(pose, camera, white, nan, nan.copy())
            x0, y0 = np.floor(uv.min(axis=0)).astype(int) - margin_px
            x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + margin_px + 1
            box = (max(y0, 0), min(y1, h), max(x0, 0), min(x1, w))
        y0, y1, x0, x1 = box
        size = self.patterns.projector_size
        where = f"{pose}, camera {camera}"
        settings = settings or DecodeSettings()
        cu, cv = np.full((h, w), np.nan), np.full((h, w), np.nan)
        try:
            cu[y0:y1, x0:x1] = decode_view(su[:, y0:y1, x0:x1], self.patterns.u, size, settings,
                                           where).coord["u"]
            cv[y0:y1, x0:x1] = decode_view(sv[:, y0:y1, x0:x1], self.patterns.v, size, settings,
                                           where).coord["v"]
        except ValueError as exc:
            raise CalibrationError(str(exc).splitlines()[0]) from exc
        return PoseView(pose, camera, white, cu, cv)

    def views(self, settings: DecodeSettings | None = None) -> Iterator[PoseView]:
        for pose in self.poses:
            for cam in range(self.cameras):
                yield self.view(pose, cam, settings)
