"""``ltc scan IMAGES --rig RIG --out CLOUD.ply [--json]``: fringe images to a point cloud.

IMAGES is an ``ltc render`` folder, a zarr stack, or a folder with ``camera_0/`` and
``camera_1/`` image folders (PNG, TIFF, float TIFF or ``.npy``; ``sim.fpp.scan_input``;
docs/formats.md, "Bring your own scanner"). Stereo between the rig's
two cameras by default; ``--camera i`` triangulates camera i against the projector instead.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from station.commands import positive_float
from station.errors import UsageError, check_output


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``scan`` subcommand."""
    p = subparsers.add_parser(
        "scan",
        help="reconstruct a point cloud from fringe images (ltc render output or a zarr stack)",
        description="Fringe images to a point cloud: phase, unwrapping, stereo matching (or "
        "camera against projector), triangulation.",
    )
    p.add_argument("images", type=Path, help="ltc render folder, zarr stack, or camera_<i>/ folder")
    p.add_argument("--rig", type=Path, required=True, help="rig calibration (JSON or OpenCV YAML)")
    p.add_argument("--out", type=Path, required=True, help="point cloud to write (PLY)")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--patterns", type=Path, help="pattern set JSON (overrides the one in IMAGES)")
    p.add_argument("--camera", type=int, help="triangulate this camera against the projector")
    p.add_argument("--min-modulation", type=positive_float,
                   help="also drop pixels whose fringe amplitude is below this, image units "
                        "(default: only the relative threshold)")
    p.add_argument("--min-modulation-fraction", type=positive_float, default=0.05,
                   help="drop pixels whose fringe amplitude is below this fraction of the "
                        "image's 99th percentile (default 0.05)")
    p.add_argument("--pixel-variance", type=float, metavar="PX2",
                   help="second moment per axis of a pixel's spatial response, px^2, whose "
                        "averaging across the pixel is undone (default: 1/12, a full square "
                        "pixel, for camera images; 0 for ltc render output, which samples "
                        "pixel centres)")
    p.add_argument("--unwrap", choices=("auto", "hierarchical", "heterodyne"), default="auto",
                   help="temporal unwrapping of phase-shift sets (default auto)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Read, decode, match, triangulate, write."""
    from sim.fpp.cloud import write_ply
    from sim.fpp.decode import DecodeSettings, scan
    from sim.fpp.scan_input import load_scan_input, point_sampled
    from sim.optics.rig import Rig

    check_output(args.out, args.force)
    t0 = time.perf_counter()
    rig = Rig.load(args.rig)
    stacks, pset = load_scan_input(args.images, args.patterns, tuple(rig.projector.size))
    variance = args.pixel_variance
    if variance is None:
        variance = 0.0 if point_sampled(args.images) else 1.0 / 12.0
    if not (variance >= 0 and variance < float("inf")):
        raise UsageError(f"--pixel-variance must be a finite number >= 0, got {args.pixel_variance}")
    settings = DecodeSettings(min_modulation=args.min_modulation or 0.0, pixel_variance_px2=variance,
                              min_modulation_fraction=args.min_modulation_fraction,
                              unwrap=args.unwrap)
    t_read = time.perf_counter() - t0
    cloud = scan(stacks, pset, rig, settings, camera=args.camera)
    t1 = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(args.out, cloud)
    summary = {
        "images": str(args.images), "rig": str(args.rig), "out": str(args.out),
        "mode": "stereo" if args.camera is None else f"camera {args.camera} + projector",
        "points": len(cloud.points), "pattern_set": pset.model_dump(mode="json"),
        "pixel_variance_px2": variance,
        "timings": {"read_s": t_read, "scan_s": t1 - t0 - t_read,
                    "total_s": time.perf_counter() - t0},
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"{summary['points']} points ({summary['mode']}) in {summary['timings']['total_s']:.2f} s; "
              f"wrote {args.out}")
    return 0
