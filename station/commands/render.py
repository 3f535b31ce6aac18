"""Render fringe images of a scene file with the virtual scanner.

Render the fringe images of a scene file (rig, lenses, objects, pattern set) with the virtual
scanner; write into the new folder --out: camera_<i>/pattern_<nnn>.png per camera (8-bit, or
16-bit PNG holding 12/16-bit values unscaled; none when the scene asks for unquantised
images), render.zarr with the images and the truth maps, and summary.json (docs/formats.md).
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


def run(args: argparse.Namespace) -> dict:
    from station.outputs import RENDER_FOLDER, check_output, staged

    out: Path = check_output(args.out, args.force, kind=RENDER_FOLDER, inputs=[args.scene])
    from sim.render.scene import load_scene_file

    loaded = load_scene_file(args.scene)
    check_output(out, args.force, kind=RENDER_FOLDER, inputs=loaded.input_files())
    result = loaded.render(progress=not args.quiet)
    with staged(out, RENDER_FOLDER, always=True) as target:
        return loaded.save(result, target, radiance=args.radiance, final=out)


def text(s: dict) -> str:
    lines = [f"{c['name']}: {s['images']} images {c['size'][0]}x{c['size'][1]}, "
             f"{c['lit_fraction']:.1%} lit, {c['rays']} rays, trace "
             f"{c['timings']['trace_s']:.2f} s, gather {c['timings']['gather_s']:.2f} s"
             for c in s["cameras"]]
    return "\n".join(lines + [f"wrote {s['out']}"])
