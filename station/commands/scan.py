"""Reconstruct a point cloud from fringe images (ltc render output or a zarr stack).

Phase, unwrapping, stereo matching (or camera against projector), triangulation. IMAGES is an
ltc render folder, a zarr stack, or a folder with camera_0/ and camera_1/ image folders (PNG,
TIFF, float TIFF or .npy; docs/formats.md, "Bring your own scanner"). Stereo between the rig's
two cameras by default; --camera i triangulates camera i against the projector instead.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.commands import positive_float
from station.errors import UsageError
from station.outputs import check_output

OPTIONS = {"out": "point cloud to write (PLY)", "force": None, "json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", type=Path, help="ltc render folder, zarr stack, or camera_<i>/ folder")
    p.add_argument("--rig", type=Path, required=True, help="rig calibration (JSON or OpenCV YAML)")
    p.add_argument("--patterns", type=Path, help="pattern set JSON (overrides the one in IMAGES)")
    p.add_argument("--camera", type=int, help="triangulate this camera against the projector")
    p.add_argument("--min-modulation", type=positive_float,
                   help="also drop pixels whose fringe amplitude is below this, image units "
                        "(default: only the relative threshold)")
    p.add_argument("--min-modulation-fraction", type=_fraction, default=0.05,
                   help="drop pixels whose fringe amplitude is below this fraction of the "
                        "image's 99th percentile (default 0.05)")
    p.add_argument("--pixel-variance", type=float, metavar="PX2",
                   help="second moment per axis of a pixel's spatial response, px^2, whose "
                        "averaging across the pixel is undone (default: 1/12, a full square "
                        "pixel, for camera images; 0 for ltc render output, which samples "
                        "pixel centres)")
    p.add_argument("--unwrap", choices=("auto", "hierarchical", "heterodyne"), default="auto",
                   help="temporal unwrapping of phase-shift sets (default auto)")


def _fraction(text: str) -> float:
    """An argparse type: a number in [0, 1) (argparse reports a bad value, exit 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 <= value < 1:
        raise argparse.ArgumentTypeError(f"must be a fraction in [0, 1), got {text}")
    return value


def run(args: argparse.Namespace) -> dict:
    """Read, decode, match, triangulate, write."""
    from sim.fpp.scan_input import scan_files
    from station.outputs import PLY_FILE, staged

    inputs = [args.images, args.rig] + ([args.patterns] if args.patterns else [])
    out = check_output(args.out, args.force, kind=PLY_FILE, inputs=inputs)
    v = args.pixel_variance
    if v is not None and not 0 <= v < float("inf"):
        raise UsageError(f"--pixel-variance must be a finite number >= 0, got {v}")
    with staged(out, PLY_FILE, always=True) as target:
        summary = scan_files(args.images, args.rig, target, patterns=args.patterns,
                             camera=args.camera, pixel_variance_px2=v,
                             min_modulation=args.min_modulation or 0.0,
                             min_modulation_fraction=args.min_modulation_fraction,
                             unwrap=args.unwrap)
    return {**summary, "out": str(out)}


def text(s: dict) -> str:
    head = f"{s['points']} points ({s['mode']}) in {s['timings']['total_s']:.2f} s; wrote {s['out']}"
    return "\n".join([head, *s.get("report_lines", [])])
