"""``ltc render SCENE.toml --out DIR [--json]``: fringe images of a scene from the virtual scanner.

Writes into DIR:

- ``camera_<i>/pattern_<nnn>.png``: the images of camera i (8-bit PNG for 8 bits; 12 and 16 bits
  as 16-bit PNG holding the DN values unscaled, so 12-bit images keep 0..4095); none when the
  scene asks for unquantised images (``render.camera.quantize = false``);
- ``render.zarr``: the same images plus the truth maps of every camera (``sim.render.images.write_zarr``:
  depth, projector coordinates, lit mask, object ids), the scene, rig and pattern descriptors in
  its attributes;
- ``summary.json``: what was rendered, where it went, and how long it took.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from station.errors import check_output


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``render`` subcommand."""
    p = subparsers.add_parser(
        "render",
        help="render fringe images of a scene file with the virtual scanner",
        description="Render the fringe images of a scene file (rig, lenses, objects, pattern set) "
        "with the virtual scanner; write PNGs per camera, render.zarr with the truth maps, and "
        "summary.json.",
    )
    p.add_argument("scene", type=Path, help="scene file (TOML, see sim.render.scene)")
    p.add_argument("--out", type=Path, required=True, help="output directory (created)")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--radiance", action="store_true",
                   help="also store the noise-free radiance (float32) in render.zarr")
    p.set_defaults(func=run)


def summarize(loaded, result, out: Path, png_dirs: list[str | None]) -> dict:
    """The JSON-able summary of a rendering (a ``LoadedScene`` and its ``RenderResult``)."""
    import numpy as np

    cfg = loaded.config
    cams = []
    for i, (c, dev) in enumerate(zip(result.cameras, loaded.rig.cameras)):
        depth = c.depth[np.isfinite(c.depth)]
        cams.append({
            "name": c.name, "group": f"camera_{i}", "size": list(dev.size),
            "lens": cfg.lenses[i].kind,
            "rays": c.n_rays, "seen_fraction": float(np.mean(c.object_id >= 0)),
            "lit_fraction": float(np.mean(c.lit)),
            "depth_mm": [float(depth.min()), float(depth.max())] if depth.size else None,
            "png_dir": png_dirs[i], "timings": c.timings,
        })
    return {
        "scene": str(loaded.source), "rig": str(loaded.source.parent / cfg.rig), "out": str(out),
        "zarr": str(out / "render.zarr"),
        "images": int(result.cameras[0].images.shape[0]), "bit_depth": cfg.render.camera.bit_depth,
        "quantized": cfg.render.camera.quantize, "pattern_set": cfg.patterns.model_dump(mode="json"),
        "cameras": cams, "timings": result.timings,
    }


def run(args: argparse.Namespace) -> int:
    """Load, render, write."""
    from sim.render.images import write_pngs, write_zarr
    from sim.render.scene import load_scene_file

    out: Path = check_output(args.out, args.force)
    loaded = load_scene_file(args.scene)
    result = loaded.render(progress=not args.quiet)
    if out.exists():
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    out.mkdir(parents=True)
    cam_cfg = loaded.config.render.camera
    png_dirs: list[str | None] = []
    for i, c in enumerate(result.cameras):
        if cam_cfg.quantize:
            write_pngs(out / f"camera_{i}", c.images, cam_cfg.bit_depth)
            png_dirs.append(str(out / f"camera_{i}"))
        else:
            png_dirs.append(None)
    summary = summarize(loaded, result, out, png_dirs)
    descriptors = loaded.config.patterns.descriptors(loaded.rig.projector.size)
    attrs = {"summary": summary, "scene": loaded.config.model_dump(mode="json"),
                 "rig": loaded.rig.model_dump(mode="json"),
                 "patterns": [d.model_dump(mode="json") for d in descriptors],
                 "png_note": "12-bit images are stored unscaled (0..4095) in 16-bit PNG"}
    write_zarr(out / "render.zarr", result, attrs, radiance=args.radiance)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    if args.json:
        print(json.dumps(summary))
    else:
        for c in summary["cameras"]:
            print(f"{c['name']}: {summary['images']} images {c['size'][0]}x{c['size'][1]}, "
                  f"{c['lit_fraction']:.1%} lit, {c['rays']} rays, "
                  f"trace {c['timings']['trace_s']:.2f} s, gather {c['timings']['gather_s']:.2f} s")
        print(f"wrote {out}")
    return 0
