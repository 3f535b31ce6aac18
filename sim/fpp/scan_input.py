"""Reading a scan's input: the cameras' fringe-image stacks and the pattern set projected.

A scan input is one of:

- a folder written by ``ltc render``: ``camera_<i>/pattern_<nnn>.png`` and ``summary.json`` (its
  ``pattern_set`` says what was projected); without PNGs (unquantised renders) the images come
  from its ``render.zarr``;
- a zarr stack (``render.zarr``): groups ``camera_<i>`` with ``images`` (n, H, W), the pattern set
  in the root attributes (``summary.pattern_set``);
- any folder with ``camera_0/`` and ``camera_1/`` of PNG or TIFF images (sorted by name), with the
  pattern set given separately (a JSON file of a ``sim.render.fringe_patterns`` set).

docs/formats.md describes every layout.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import zarr
from pydantic import TypeAdapter, ValidationError

from sim.render.fringe_patterns import PatternSet
from sim.validation import format_validation_error

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


class ScanInputError(ValueError):
    """IMAGES cannot be read as a scan; the message names the path and what was expected."""


def _read_stack(folder: Path) -> np.ndarray:
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ScanInputError(f"{folder}: no PNG or TIFF images")
    images = []
    for f in files:
        im = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if im is None or im.ndim != 2:
            raise ScanInputError(f"{f}: not a single-channel image")
        if images and im.shape != images[0].shape:
            raise ScanInputError(
                f"{f}: image is {im.shape[1]} x {im.shape[0]} pixels, {files[0].name} is "
                f"{images[0].shape[1]} x {images[0].shape[0]}: all images of a camera must match"
            )
        images.append(im)
    return np.stack(images)


def _pattern_set(raw, where: str):
    try:
        return TypeAdapter(PatternSet).validate_python(raw)
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


def load_pattern_set(path: Path) -> object:
    """A pattern set from a JSON file (``sim.render.fringe_patterns``); errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise ScanInputError(f"{path}: not found")
    try:
        raw = json.loads(path.read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ScanInputError(f"{path}: not valid JSON: {exc}") from exc
    return _pattern_set(raw, str(path))


def load_scan_input(images: Path, patterns: Path | None = None) -> tuple[list[np.ndarray], object]:
    """The two cameras' image stacks (n, H, W) and the pattern set of a scan input."""
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
        return stacks, load_pattern_set(patterns)
    if raw is None:
        raise ScanInputError(f"{images}: no pattern set recorded; give it with --patterns FILE.json")
    return stacks, _pattern_set(raw, f"{images}: pattern_set")
