"""Reading a scan's input: the cameras' fringe-image stacks and the pattern set projected.

A scan input is one of:

- a folder written by ``ltc render``: ``camera_<i>/pattern_<nnn>.png`` and ``summary.json`` (its
  ``pattern_set`` says what was projected); without PNGs (unquantised renders) the images come
  from its ``render.zarr``;
- a zarr stack (``render.zarr``): groups ``camera_<i>`` with ``images`` (n, H, W), the pattern set
  in the root attributes (``summary.pattern_set``);
- any folder with ``camera_0/`` and ``camera_1/`` holding one image per pattern, sorted by name:
  8- or 16-bit PNG or TIFF, float32 TIFF, or ``.npy`` (one 2-D array each; or a single ``.npy``
  holding the whole (n, H, W) stack), with the pattern set given separately: a JSON file of a
  ``sim.render.fringe_patterns`` set, in which a phase-shift set may give ``fringes`` (fringe
  counts across the projector) instead of ``periods_px``, and a Gray-code set ``fringes`` (one
  count) instead of ``period_px``.

docs/formats.md describes every layout.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import zarr
from pydantic import ValidationError

from sim.errors import SimInputError
from sim.render.fringe_patterns import GrayCodeSet, PhaseShiftSet, pattern_set_from
from sim.validation import format_validation_error

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")


class ScanInputError(SimInputError):
    """IMAGES cannot be read as a scan; the message names the path and what was expected."""


def _read_image(f: Path) -> np.ndarray | None:
    """One image file: PNG / TIFF (8, 16 bit or float32) or a 2-D ``.npy`` array; None when
    OpenCV cannot read the file."""
    if f.suffix.lower() == ".npy":
        try:
            im = np.load(f, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise ScanInputError(f"{f}: not a readable .npy array: {exc}") from exc
        if im.dtype.kind not in "uif":
            raise ScanInputError(f"{f}: .npy images must hold numbers, got dtype {im.dtype}")
        return im
    return cv2.imread(str(f), cv2.IMREAD_UNCHANGED)


def _depth(im: np.ndarray) -> str:
    return f"{8 * im.dtype.itemsize}-bit {'floats' if im.dtype.kind == 'f' else 'integers'}"


def _read_stack(folder: Path) -> np.ndarray:
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ScanInputError(f"{folder}: no PNG, TIFF or .npy images")
    if len(files) == 1 and files[0].suffix.lower() == ".npy":
        stack = _read_image(files[0])
        assert stack is not None, "a .npy file is read or refused with an error"
        if stack.ndim == 3:
            return stack
    images: list[np.ndarray] = []
    for f in files:
        im = _read_image(f)
        if im is None or im.ndim != 2:
            raise ScanInputError(f"{f}: not a single-channel image")
        if images and im.shape != images[0].shape:
            raise ScanInputError(
                f"{f}: image is {im.shape[1]} x {im.shape[0]} pixels, {files[0].name} is "
                f"{images[0].shape[1]} x {images[0].shape[0]}: all images of a camera must match"
            )
        if images and im.dtype != images[0].dtype:
            raise ScanInputError(
                f"{f}: image holds {_depth(im)}, {files[0].name} {_depth(images[0])}: all images "
                "of a camera must have one bit depth"
            )
        images.append(im)
    return np.stack(images)


def _pattern_set(raw: object, where: str, projector_size: tuple[int, int] | None = None
                 ) -> PhaseShiftSet | GrayCodeSet:
    try:
        return pattern_set_from(raw, projector_size)
    except ValidationError as exc:
        raise ScanInputError(format_validation_error(where, exc)) from exc


def _from_zarr(path: Path) -> tuple[list[np.ndarray], dict | None]:
    try:
        root = zarr.open_group(str(path), mode="r")
    except (FileNotFoundError, ValueError) as exc:
        raise ScanInputError(f"{path}: not a readable zarr group: {exc}") from exc
    stacks = []
    for i in range(2):
        key = f"camera_{i}"
        if key not in root or "images" not in root[key]:
            raise ScanInputError(f"{path}: zarr stack has no '{key}/images' array")
        stacks.append(np.asarray(root[key]["images"][:]))
    return stacks, dict(root.attrs).get("summary", {}).get("pattern_set")


def load_pattern_set(path: Path, projector_size: tuple[int, int] | None = None
                     ) -> PhaseShiftSet | GrayCodeSet:
    """A pattern set from a JSON file (``sim.render.fringe_patterns``); errors name the file.
    ``projector_size`` (width, height) turns fringe counts into periods."""
    path = Path(path)
    if not path.is_file():
        raise ScanInputError(f"{path}: not found")
    try:
        raw = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ScanInputError(f"{path}: not valid JSON: {exc}") from exc
    return _pattern_set(raw, str(path), projector_size)


def point_sampled(images: Path) -> bool:
    """Whether a scan input is our renderer's output (``ltc render`` folder or zarr stack),
    whose pixels sample their centres; a real camera's pixels average their area."""
    return ((images / "zarr.json").is_file() or (images / "summary.json").is_file()
            or (images / "render.zarr").is_dir())


def load_scan_input(images: Path, patterns: Path | None = None,
                    projector_size: tuple[int, int] | None = None
                    ) -> tuple[list[np.ndarray], PhaseShiftSet | GrayCodeSet]:
    """The two cameras' image stacks (n, H, W) and the pattern set of a scan input;
    ``projector_size`` (width, height) turns fringe counts into periods."""
    if not images.exists():
        raise ScanInputError(f"{images}: not found")
    raw = None
    if (images / "zarr.json").is_file():
        stacks, raw = _from_zarr(images)
    elif (images / "camera_0").is_dir() and any((images / "camera_0").iterdir()):
        stacks = [_read_stack(images / f"camera_{i}") for i in range(2)]
        if (images / "summary.json").is_file():
            summary = images / "summary.json"
            try:
                raw = json.loads(summary.read_bytes())
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise ScanInputError(f"{summary}: not valid JSON: {exc}") from exc
            if not isinstance(raw, dict):
                raise ScanInputError(f"{summary}: expected a JSON object (the render summary)")
            raw = raw.get("pattern_set")
    elif (images / "render.zarr").is_dir():
        stacks, raw = _from_zarr(images / "render.zarr")
    else:
        raise ScanInputError(
            f"{images}: expected an ltc render folder, a zarr stack or camera_0/ and camera_1/ "
            "image folders"
        )
    if patterns is not None:
        return stacks, load_pattern_set(patterns, projector_size)
    if raw is None:
        raise ScanInputError(f"{images}: no pattern set recorded; give it with --patterns FILE.json")
    return stacks, _pattern_set(raw, f"{images}: pattern_set", projector_size)


def scan_files(images: str | Path, rig_path: str | Path, out: str | Path, *,
               patterns: str | Path | None = None, camera: int | None = None,
               pixel_variance_px2: float | None = None, min_modulation: float = 0.0,
               min_modulation_fraction: float = 0.05, unwrap: str = "auto") -> dict:
    """``ltc scan``: read a scan input and a rig file, decode, triangulate, write the PLY
    ``out``; returns the summary (with ``report``: the ``ScanReport`` of what each check
    rejected, and its ``report_lines``). ``pixel_variance_px2`` None: 0 for our renderer's output
    (pixel centres), 1/12 for camera images (square pixels average their area)."""

    from sim.fpp.cloud import write_ply
    from sim.fpp.decode import DecodeSettings, scan_with_report
    from sim.optics.rig import Rig

    images, out = Path(images), Path(out)
    t0 = time.perf_counter()
    rig = Rig.load(rig_path)
    stacks, pset = load_scan_input(images, None if patterns is None else Path(patterns),
                                   rig.projector.size)
    if pixel_variance_px2 is None:
        pixel_variance_px2 = 0.0 if point_sampled(images) else 1.0 / 12.0
    settings = DecodeSettings(min_modulation=min_modulation, unwrap=unwrap,
                              pixel_variance_px2=pixel_variance_px2,
                              min_modulation_fraction=min_modulation_fraction)
    t_read = time.perf_counter() - t0
    cloud, report = scan_with_report(stacks, pset, rig, settings, camera=camera)
    t1 = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, cloud)
    return {
        "images": str(images), "rig": str(rig_path), "out": str(out),
        "mode": "stereo" if camera is None else f"camera {camera} + projector",
        "points": len(cloud.points), "pattern_set": pset.model_dump(mode="json"),
        "pixel_variance_px2": pixel_variance_px2, "report": report.to_json(),
        "report_lines": report.lines(),
        "timings": {"read_s": t_read, "scan_s": t1 - t0 - t_read,
                    "total_s": time.perf_counter() - t0},
    }
