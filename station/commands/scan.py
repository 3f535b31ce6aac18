"""Reconstruct a point cloud from fringe images (ltc render output or a zarr stack).

Phase, unwrapping, stereo matching (or camera against projector), triangulation. IMAGES is an
ltc render folder, a zarr stack, or a folder with camera_0/ and camera_1/ image folders
(docs/formats.md). Stereo between the rig's two cameras by default; --camera i triangulates
camera i against the projector instead.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from station.commands import positive_float
from station.errors import check_output


OPTIONS = {"out": "point cloud to write (PLY)", "force": None, "json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("images", type=Path, help="ltc render folder, zarr stack, or camera_<i>/ folder")
    p.add_argument("--rig", type=Path, required=True, help="rig calibration (JSON or OpenCV YAML)")
    p.add_argument("--patterns", type=Path, help="pattern set JSON (overrides the one in IMAGES)")
    p.add_argument("--camera", type=int, help="triangulate this camera against the projector")
    p.add_argument("--min-modulation", type=positive_float, default=2.0,
                   help="smallest fringe amplitude kept, image units (default 2)")
    p.add_argument("--unwrap", choices=("auto", "hierarchical", "heterodyne"), default="auto",
                   help="temporal unwrapping of phase-shift sets (default auto)")


def run(args: argparse.Namespace) -> dict:
    """Read, decode, match, triangulate, write."""
    from sim.fpp.cloud import write_ply
    from sim.fpp.decode import DecodeSettings, scan
    from sim.fpp.scan_input import load_scan_input
    from sim.optics.rig import Rig

    check_output(args.out, args.force)
    t0 = time.perf_counter()
    rig = Rig.load(args.rig)
    stacks, pset = load_scan_input(args.images, args.patterns)
    settings = DecodeSettings(min_modulation=args.min_modulation, unwrap=args.unwrap)
    t_read = time.perf_counter() - t0
    cloud = scan(stacks, pset, rig, settings, camera=args.camera)
    t1 = time.perf_counter()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(args.out, cloud)
    summary = {
        "images": str(args.images), "rig": str(args.rig), "out": str(args.out),
        "mode": "stereo" if args.camera is None else f"camera {args.camera} + projector",
        "points": len(cloud.points), "pattern_set": pset.model_dump(mode="json"),
        "timings": {"read_s": t_read, "scan_s": t1 - t0 - t_read,
                    "total_s": time.perf_counter() - t0},
    }
    return summary


def text(s: dict) -> str:
    return f"{s['points']} points ({s['mode']}) in {s['timings']['total_s']:.2f} s; wrote {s['out']}"
