"""Derive the measured lens (principal rays, optical centre, aperture samples) from an LTC store.

Centroids, principal rays, optical centre, focus, the LTC at the optical centre and K aperture
samples per node, with the recommended settings (LensFitConfig's defaults; --basic: the plain
derivation); writes the lens model file (.npz, docs/formats.md) as the nodes are derived,
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
    p.add_argument("--samples", type=at_least(1),
                   help="aperture samples K (default: LensFitConfig's, 256)")
    p.add_argument("--grid-step", type=at_least(1),
                   help="node spacing in pixels (default: LensFitConfig's, 4; 1: every pixel)")
    p.add_argument("--interpolation", choices=("bilinear", "nearest"),
                   help="how samples are read between nodes (default bilinear)")
    p.add_argument("--centre", choices=("auto", "pinhole", "rays"),
                   help="optical centre: pinhole (needs K), principal-ray intersection, or "
                   "auto (the default: pinhole when K is known)")
    p.add_argument("--basic", action="store_true", help="the plain derivation "
                   "(LensFitConfig.basic(): K = 32 at every pixel, one focus, no deconvolution, "
                   "support cut or aim offsets) instead of the recommended settings; the "
                   "options above still apply")
    p.add_argument("--rig", type=Path, help="rig calibration (JSON/YAML) giving K")
    p.add_argument("--rig-camera", help="camera name in --rig (default: the first camera)")


def run(args: argparse.Namespace) -> dict:
    from station.api import derive_lens, lens_config
    from station.lens.geometry import LensFitConfig
    from station.outputs import FIGURES_FOLDER, LENS_FILE, naming
    from station.outputs import check_output as check_kind

    check_kind(args.out, args.force, kind=LENS_FILE, inputs=[args.store, args.rig or args.store],
               parent_must_exist=True)
    if args.figures is not None:
        check_kind(args.figures, args.force, "--figures", kind=FIGURES_FOLDER,
                   inputs=[args.store])
    given = {"samples": args.samples, "grid_step": args.grid_step,
             "interpolation": args.interpolation, "centre_method": args.centre,
             "focus_distance_mm": args.focus_mm}
    fields = {k: v for k, v in given.items() if v is not None}
    config = (lens_config(**{**LensFitConfig.basic().model_dump(), **fields}) if args.basic
              else lens_config(**fields))
    with naming(args.out):
        result = derive_lens(args.store, config, rig=args.rig, rig_camera=args.rig_camera,
                             figures=args.figures, progress=not args.quiet, out=args.out,
                             workers=args.workers, dask=args.dask,
                             scheduler=args.scheduler)
    return {**result.summary().to_json(), "out": str(args.out),
            "figures": [str(f) for f in result.figures]}


def _mm(value: float | None, digits: int = 3) -> str:
    """A length in mm with ``digits`` decimals, or "n/a"."""
    return "n/a" if value is None else f"{value:.{digits}f} mm"


def _point(p: list[float], digits: int = 4) -> str:
    return "(" + ", ".join(f"{v:.{digits}f}" for v in p) + ") mm"


def text(r: dict) -> str:
    """Human-readable summary of ``LensSummary.to_json()`` plus output paths."""
    lines = [
        (f"optical centre   {_point(r['optical_centre_mm'])} +- "
         f"{_point(r['optical_centre_std_mm'])}  [{r['optical_centre_method']}]"),
        f"ray intersection {_point(r['principal_ray_intersection_mm'])}",
        (f"focus distance   {_mm(r['focus_distance_mm'])} (focus plane at z = "
         f"{_mm(r['focus_plane_z_mm'])}); fitted {_mm(r['focus_distance_fitted_mm'])}, "
         f"configured {_mm(r['focus_distance_config_mm'])}"),
        (f"ray residuals    mean {_mm(r['ray_residual_mean_mm'], 5)}, std "
         f"{_mm(r['ray_residual_std_mm'], 5)} over {r['ray_residual_count']} points"),
        (f"pixels           {r['pixels_usable']}/{r['pixels']} usable; few depths "
         f"{r['pixels_few_depths']}, outlier removed {r['pixels_outlier_removed']}, bad fit "
         f"{r['pixels_bad_fit']}"),
        (f"lens model       {r['samples']} samples x {r['nodes'][0]} x {r['nodes'][1]} nodes "
         f"({r['nodes_filled']} filled from a neighbour), aperture grid "
         f"{r['aperture_cells']} cells over +-{r['aperture_half_width_mm']:.3f} mm -> "
         f"{r['out']}"),
    ]
    if r.get("camera_rotation_deg") is not None:
        lines.append(f"camera rotation  {r['camera_rotation_deg']:.3f} deg (station to camera)")
    lines += [f"note             {n}" for n in r["notes"]]
    lines += [f"figure           {f}" for f in r["figures"]]
    return "\n".join(lines)
