"""Validate a twin against a real scanner's scans (a real-scan folder).

REAL_DIR holds scan.toml (rig, pattern set, optional camera and projector response) and
positions/NAME/ with position.toml (the artefact: sphere, ball bar or CAD part, and its nominal
size) and camera_0/, camera_1/ fringe images (docs/formats.md, "Real-scan folder"). Each
position is scanned as ltc scan does, the artefact located, its pose refined by analysis by
synthesis with the first twin, every twin rendered and scanned at that pose with the camera
response estimated from the real images, and compared with the real scan: points by pixel
(unaligned and after ICP), sizes, fringe images and phases. --lenses takes per camera a
measured lens (.npz) or a lens spec (TOML or JSON: kind thin, aberrated, gaussian or pinhole,
as in a scene file). Writes report.md, figures/ and results.json into --out; run again to
continue after an interruption.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.commands import at_least, positive_float

OPTIONS = {"out": "folder for report.md, figures and results.json",
           "force": "validate again into an --out that holds a validation (of other inputs, "
                    "or finished)",
           "json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("real_dir", type=Path, help="real-scan folder")
    p.add_argument("--lenses", nargs="+", required=True, metavar="LENS",
                   help="per camera a measured lens (.npz) or a lens spec (.toml / .json)")
    p.add_argument("--positions", nargs="+", metavar="NAME", help="only these positions")
    p.add_argument("--gaussian-sigma", type=positive_float, metavar="MM",
                   help="a Gaussian twin of this aperture sigma (default with measured lenses: "
                        "each measured lens's equivalent)")
    p.add_argument("--smoothing", type=float, default=0.0, metavar="NODES",
                   help="measured lenses smoothed over this many nodes (default 0: as measured)")
    p.add_argument("--pixel-samples", type=at_least(1), metavar="N",
                   help="render each twin pixel on N x N subpixels (default: 4 for camera "
                        "images, whose pixels average their area; 1 where the folder's "
                        "pixel_variance_px2 is 0)")
    p.add_argument("--noise", action="store_true",
                   help="add the estimated camera noise to the twins' images")


def run(args: argparse.Namespace) -> dict:
    """Validate; the results as a JSON-able dict."""
    import sys

    from station.validation.run import validate

    log = (lambda s: None) if args.json else (lambda s: print(s, file=sys.stderr))
    return validate(args.real_dir, args.lenses, args.out, positions=args.positions,
                    gaussian_sigma_mm=args.gaussian_sigma, smoothing_nodes=args.smoothing,
                    noise=args.noise, pixel_samples=args.pixel_samples, force=args.force,
                    log=log).to_json()


def text(r: dict) -> str:
    lines = [f"{t}: worst |mean| {s['worst_abs_mean_um']:.2f} um, RMSE "
             f"{s['worst_rmse_um']:.2f} um, size vs real {s['worst_size_vs_real_um']:.2f} um"
             for t, s in r["summary"].items()]
    return "\n".join(lines + [f"report: {r['report']}"])
