"""``ltc scan IMAGES --rig RIG --out CLOUD.ply [--json]``: fringe images to a point cloud.

IMAGES is one of:

- a folder written by ``ltc render``: ``camera_<i>/pattern_<nnn>.png`` and ``summary.json`` (its
  ``pattern_set`` says what was projected); without PNGs (unquantised renders) the images come
  from its ``render.zarr``;
- a zarr stack (``render.zarr``): groups ``camera_<i>`` with ``images`` (n, H, W), the pattern set
  in the root attributes (``summary.pattern_set``);
- any folder with ``camera_0/`` and ``camera_1/`` of PNG or TIFF images (sorted by name), with the
  pattern set given by ``--patterns`` (a JSON file of a ``sim.render.fringe_patterns`` set).

Stereo between the rig's two cameras by default; ``--camera i`` triangulates camera i against
the projector instead.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import zarr
from pydantic import TypeAdapter, ValidationError

from sim.fpp.cloud import write_ply
from sim.render.fringe_patterns import PatternSet
from sim.fpp.scan import DecodeSettings, reconstruct
from sim.optics.rig import Rig
from sim.validation import format_validation_error

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


class ScanInputError(ValueError):
    """IMAGES cannot be read as a scan; the message names the path and what was expected."""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``scan`` subcommand."""
    p = subparsers.add_parser(
        "scan",
        help="reconstruct a point cloud from fringe images (ltc render output or a zarr stack)",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("images", type=Path, help="ltc render folder, zarr stack, or camera_<i>/ folder")
    p.add_argument("--rig", type=Path, required=True, help="rig calibration (JSON or OpenCV YAML)")
    p.add_argument("--out", type=Path, required=True, help="point cloud to write (PLY)")
    p.add_argument("--patterns", type=Path, help="pattern set JSON (overrides the one in IMAGES)")
    p.add_argument("--camera", type=int, help="triangulate this camera against the projector")
    p.add_argument("--min-modulation", type=float, default=2.0,
                   help="smallest fringe amplitude kept, image units (default 2)")
    p.add_argument("--unwrap", choices=("auto", "hierarchical", "heterodyne"), default="auto",
                   help="temporal unwrapping of phase-shift sets (default auto)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.set_defaults(func=run)


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
            raw = json.loads((images / "summary.json").read_text()).get("pattern_set")
    elif (images / "render.zarr").is_dir():
        stacks, raw = _from_zarr(images / "render.zarr")
    else:
        raise ScanInputError(
            f"{images}: expected an ltc render folder, a zarr stack or camera_0/ and camera_1/ "
            "image folders"
        )
    if patterns is not None:
        if not patterns.is_file():
            raise ScanInputError(f"--patterns {patterns}: not found")
        try:
            raw = json.loads(patterns.read_text())
        except json.JSONDecodeError as exc:
            raise ScanInputError(f"--patterns {patterns}: not valid JSON: {exc}") from exc
        return stacks, _pattern_set(raw, str(patterns))
    if raw is None:
        raise ScanInputError(f"{images}: no pattern set recorded; give it with --patterns FILE.json")
    return stacks, _pattern_set(raw, f"{images}: pattern_set")


def run(args: argparse.Namespace) -> int:
    """Read, decode, match, triangulate, write; exit code 2 for bad input."""
    t0 = time.perf_counter()
    try:
        rig = Rig.load(args.rig)
        stacks, pset = load_scan_input(args.images, args.patterns)
        settings = DecodeSettings(min_modulation=args.min_modulation, unwrap=args.unwrap)
        t_read = time.perf_counter() - t0
        cloud = reconstruct(stacks, pset, rig, settings, camera=args.camera)
    except (ValueError, OSError) as exc:
        print(f"ltc scan: error: {exc}", file=sys.stderr)
        return 2
    t1 = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(args.out, cloud)
    summary = {
        "images": str(args.images), "rig": str(args.rig), "out": str(args.out),
        "mode": "stereo" if args.camera is None else f"camera {args.camera} + projector",
        "points": len(cloud.points), "pattern_set": pset.model_dump(mode="json"),
        "timings": {"read_s": t_read, "reconstruct_s": t1 - t0 - t_read,
                    "total_s": time.perf_counter() - t0},
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{summary['points']} points ({summary['mode']}) in {summary['timings']['total_s']:.2f} s; "
              f"wrote {args.out}")
    return 0
