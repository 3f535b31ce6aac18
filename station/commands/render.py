"""Render fringe images of a scene file with the virtual scanner.

Render the fringe images of a scene file (rig, lenses, objects, pattern set) with the virtual
scanner; write into the new folder --out: camera_<i>/pattern_<nnn>.png per camera (8-bit, or
16-bit PNG holding 12/16-bit values unscaled; none when the scene asks for unquantised
images), render.zarr with the images and the truth maps, and summary.json (docs/formats.md).
With --calibration BOARD the scene file gives the rig, lenses and camera and projector response
only: the board file's board is rendered at --poses default poses (tilts up to 30 degrees over
the working volume) into a calibration capture folder (capture.json, pose_<nnn>/camera_<i>/ as
16-bit PNGs; docs/formats.md, "Calibration capture") for ltc calibrate.
"""

from __future__ import annotations

import argparse
from pathlib import Path

OPTIONS = {"out": "output folder (created)",
           "force": "replace the render folder in --out (the old one stays until the new one is "
                    "complete; only a render folder is replaced)",
           "json": None, "quiet": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scene", type=Path, help="scene file (TOML, docs/formats.md)")
    p.add_argument("--radiance", action="store_true",
                   help="also store the noise-free radiance (float32) in render.zarr")
    p.add_argument("--calibration", type=Path, metavar="BOARD",
                   help="render a calibration capture of this board file (TOML) instead")
    p.add_argument("--poses", type=int, default=15, help="calibration poses, 1-15 (default 15)")


def run(args: argparse.Namespace) -> dict:
    from station.outputs import RENDER_FOLDER, check_output, staged

    if args.calibration is not None:
        return _calibration(args)
    out: Path = check_output(args.out, args.force, kind=RENDER_FOLDER, inputs=[args.scene])
    from sim.render.scene import load_scene_file

    loaded = load_scene_file(args.scene)
    check_output(out, args.force, kind=RENDER_FOLDER, inputs=loaded.input_files())
    result = loaded.render(progress=not args.quiet)
    with staged(out, RENDER_FOLDER, always=True) as target:
        return loaded.save(result, target, radiance=args.radiance, final=out)


def _calibration(args: argparse.Namespace) -> dict:
    from sim.calibration.board import load_board
    from sim.calibration.virtual import default_poses, render_capture
    from sim.render.scene import load_scene_file
    from station.errors import UsageError
    from station.outputs import CALIBRATION_CAPTURE, check_output, staged

    out: Path = check_output(args.out, args.force, kind=CALIBRATION_CAPTURE,
                             inputs=[args.scene, args.calibration])
    if not 1 <= args.poses <= 15:
        raise UsageError(f"--poses must be 1..15, got {args.poses}")
    board = load_board(args.calibration)
    loaded = load_scene_file(args.scene)
    with staged(out, CALIBRATION_CAPTURE, always=True) as target:
        rc = render_capture(target, board, loaded.rig, default_poses(board, args.poses),
                            lenses=loaded.lenses, settings=loaded.config.render,
                            seed=loaded.config.seed, progress=not args.quiet)
    return {"out": str(out), "poses": len(rc.poses), "render_s": rc.render_s,
            "write_s": rc.write_s, "calibration": True}


def text(s: dict) -> str:
    if s.get("calibration"):
        return (f"{s['poses']} board poses rendered in {s['render_s']:.1f} s, written in "
                f"{s['write_s']:.1f} s; wrote {s['out']}")
    lines = [f"{c['name']}: {s['images']} images {c['size'][0]}x{c['size'][1]}, "
             f"{c['lit_fraction']:.1%} lit, {c['rays']} rays, trace "
             f"{c['timings']['trace_s']:.2f} s, gather {c['timings']['gather_s']:.2f} s"
             for c in s["cameras"]]
    return "\n".join(lines + [f"wrote {s['out']}"])
