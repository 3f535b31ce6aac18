"""``ltc lens LTC.zarr --out LENS.npz [--figures DIR] [--json] [--focus-mm Z] [--samples K]``.

Derives the measured lens from an LTC store (``station.lens.derive``) and writes the lens
model file (``sim.optics.measured_lens``). The camera matrix comes from the store's
``camera_matrix`` attribute or from ``--rig RIG --rig-camera NAME`` (``sim.optics.rig`` file).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pydantic import ValidationError

from sim.optics.measured_lens import LensFileError, save_lens
from sim.optics.rig import Rig
from sim.validation import format_validation_error
from station.ltc.store import LtcVolumeError, open_ltc_volume
from station.lens.derive import derive_lens
from station.lens.figures import write_figures
from station.lens.geometry import LensFitConfig, LensFitError
from station.ltc.store import LtcStoreError
from station.lens.rays import RayFitError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "lens",
        help="derive the measured lens (principal rays, optical centre, aperture samples) "
        "from an LTC store",
        description="Centroids -> principal rays -> optical centre -> focus -> LTC at the "
        "optical centre -> K aperture samples per pixel; writes the lens model (.npz).",
    )
    p.add_argument("store", type=Path, help="LTC store (zarr) from 'ltc reconstruct'")
    p.add_argument("--out", type=Path, required=True, help="lens model file to write (.npz)")
    p.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    p.add_argument("--figures", type=Path, help="folder for the figures (PNG)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--focus-mm", type=float, help="focus distance from the optical centre, mm "
                   "(used instead of the fitted one; both are reported)")
    p.add_argument("--samples", type=int, default=32, help="aperture samples K (default 32)")
    p.add_argument("--grid-step", type=int, default=1,
                   help="node spacing in pixels (default 1: every pixel)")
    p.add_argument("--interpolation", choices=("bilinear", "nearest"), default="bilinear",
                   help="how samples are read between nodes (default bilinear)")
    p.add_argument("--centre", choices=("auto", "pinhole", "rays"), default="auto",
                   help="optical centre: pinhole (needs K), principal-ray intersection, or "
                   "auto (pinhole when K is known)")
    p.add_argument("--rig", type=Path, help="rig calibration (sim.optics.rig JSON/YAML) giving K")
    p.add_argument("--rig-camera", help="camera name in --rig (default: the first camera)")
    p.set_defaults(func=run)


def _camera(args: argparse.Namespace, size: tuple[int, int]):
    """K and distortion from --rig, checked against the store's camera size."""
    if args.rig is None:
        return None, None
    rig = Rig.load(args.rig)
    cams = {c.name: c for c in rig.cameras}
    name = args.rig_camera or rig.cameras[0].name
    if name not in cams:
        raise ValueError(f"{args.rig}: no camera named {name!r}; cameras are {list(cams)}")
    if tuple(cams[name].size) != tuple(size):
        raise ValueError(f"{args.rig}: camera {name!r} is {tuple(cams[name].size)} pixels but "
                         f"the LTC store's camera is {tuple(size)}")
    return cams[name].K_array, cams[name].dist_array


def run(args: argparse.Namespace) -> int:
    if args.out.exists() and not args.force:
        print(f"ltc lens: error: {args.out} exists; pass --force to overwrite it",
              file=sys.stderr)
        return 2
    try:
        config = LensFitConfig(samples=args.samples, grid_step=args.grid_step,
                               interpolation=args.interpolation, centre_method=args.centre,
                               focus_distance_mm=args.focus_mm)
        volume = open_ltc_volume(args.store)
        K, dist = _camera(args, volume.camera_size)
        result = derive_lens(volume, config, K, dist)
        save_lens(args.out, result.lens)
        figures = [] if args.figures is None else write_figures(volume, result, args.figures)
    except ValidationError as exc:
        print(f"ltc lens: error: {format_validation_error('options', exc)}", file=sys.stderr)
        return 2
    except (LtcStoreError, LtcVolumeError, LensFitError, RayFitError, LensFileError,
            FileNotFoundError, ValueError) as exc:
        print(f"ltc lens: error: {exc}", file=sys.stderr)
        return 2
    report = {**result.summary(), "out": str(args.out), "figures": [str(f) for f in figures]}
    if args.json:
        print(json.dumps(report))
    else:
        print(format_report(report))
    return 0


def format_report(r: dict) -> str:
    """Human-readable summary of ``LensResult.summary()`` plus output paths."""
    o, s = r["optical_centre_mm"], r["optical_centre_std_mm"]
    q = r["principal_ray_intersection_mm"]
    lines = [
        (f"optical centre  ({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) mm  +- ({s[0]:.4f}, "
         f"{s[1]:.4f}, {s[2]:.4f})  [{r['optical_centre_method']}]"),
        f"ray intersection ({q[0]:.4f}, {q[1]:.4f}, {q[2]:.4f}) mm",
        (f"focus distance  {r['focus_distance_mm']:.3f} mm (focus plane at z = "
         f"{r['focus_plane_z_mm']:.3f} mm); fitted {r['focus_distance_fitted_mm']}, "
         f"configured {r['focus_distance_config_mm']}"),
        (f"ray residuals   mean {r['ray_residual_mean_mm']:.5f} mm, std "
         f"{r['ray_residual_std_mm']:.5f} mm over {r['ray_residual_count']} points"),
        (f"pixels          {r['pixels_usable']}/{r['pixels']} usable; few depths "
         f"{r['pixels_few_depths']}, outlier removed {r['pixels_outlier_removed']}, bad fit "
         f"{r['pixels_bad_fit']}"),
        (f"lens model      {r['samples']} samples x {r['nodes'][0]}x{r['nodes'][1]} nodes "
         f"({r['nodes_filled']} filled from a neighbour) -> {r['out']}"),
    ]
    lines += [f"note            {n}" for n in r["notes"]]
    lines += [f"figure          {f}" for f in r["figures"]]
    return "\n".join(lines)
