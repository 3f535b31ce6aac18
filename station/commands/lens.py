"""Derive the measured lens (principal rays, optical centre, aperture samples) from an LTC store.

Centroids, principal rays, optical centre, focus, the LTC at the optical centre and K aperture
samples per pixel; writes the lens model file (.npz, docs/formats.md) as the nodes are derived,
so memory does not grow with the sensor. Runs on every core (default), in this process
(--workers 1), on a local Dask cluster (--dask) or an existing one (--scheduler); all give the
same file bit for bit. The camera matrix comes
from the store's camera_matrix attribute or from --rig RIG --rig-camera NAME (a rig file).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.commands import at_least


OPTIONS = {"out": "lens model file to write (.npz)", "force": None, "json": None, "quiet": None,
           "workers": None, "dask": None,
           "scheduler": "compute on an existing Dask cluster (e.g. tcp://host:8786); the LTC "
                        "store must be on a path every worker can read"}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("store", type=Path, help="LTC store (zarr) from 'ltc reconstruct'")
    p.add_argument("--figures", type=Path, help="folder for the figures (PNG)")
    p.add_argument("--focus-mm", type=float, help="focus distance from the optical centre, mm "
                   "(used instead of the fitted one; both are reported)")
    p.add_argument("--samples", type=at_least(1), default=32,
                   help="aperture samples K (default 32)")
    p.add_argument("--grid-step", type=at_least(1), default=1,
                   help="node spacing in pixels (default 1: every pixel)")
    p.add_argument("--interpolation", choices=("bilinear", "nearest"), default="bilinear",
                   help="how samples are read between nodes (default bilinear)")
    p.add_argument("--centre", choices=("auto", "pinhole", "rays"), default="auto",
                   help="optical centre: pinhole (needs K), principal-ray intersection, or "
                   "auto (pinhole when K is known)")
    p.add_argument("--rig", type=Path, help="rig calibration (JSON/YAML) giving K")
    p.add_argument("--rig-camera", help="camera name in --rig (default: the first camera)")


def run(args: argparse.Namespace) -> dict:
    from station.api import derive_lens
    from station.outputs import FIGURES_FOLDER, LENS_FILE, naming
    from station.outputs import check_output as check_kind

    check_kind(args.out, args.force, kind=LENS_FILE, inputs=[args.store, args.rig or args.store],
               parent_must_exist=True)
    if args.figures is not None:
        check_kind(args.figures, args.force, "--figures", kind=FIGURES_FOLDER,
                   inputs=[args.store])
    with naming(args.out):
        result = derive_lens(args.store, samples=args.samples, grid_step=args.grid_step,
                             interpolation=args.interpolation, centre=args.centre,
                             focus_distance_mm=args.focus_mm, rig=args.rig,
                             rig_camera=args.rig_camera, figures=args.figures,
                             progress=not args.quiet, out=args.out, workers=args.workers,
                             dask=args.dask, scheduler=args.scheduler)
    report = {**result.summary(), "out": str(args.out),
              "figures": [str(f) for f in result.figures]}
    return report


def text(r: dict) -> str:
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
