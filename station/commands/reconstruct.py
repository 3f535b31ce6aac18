"""``ltc reconstruct RUN.zarr --out LTC.zarr [--json] [--tile N] [--resume] [--workers N]
[--dask | --scheduler ADDRESS]``: LTC store from a run store."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from station.commands import at_least
from station.errors import check_output


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``reconstruct`` subcommand."""
    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct per-pixel LTC from a complete acquisition run",
        description="Demodulate the Fourier frames of a run store, unfold with the "
        "localisation map and write an LTC store, tile by tile (bounded memory).",
    )
    p.add_argument("run", type=Path, metavar="RUN.zarr", help="run store written by 'ltc acquire'")
    p.add_argument("--out", type=Path, required=True, metavar="LTC.zarr",
                   help="LTC store to create")
    p.add_argument("--force", action="store_true", help="replace --out if it exists")
    p.add_argument("--resume", action="store_true",
                   help="finish the --out store a killed reconstruction of this run left")
    p.add_argument("--workers", type=at_least(1), default=None, metavar="N",
                   help="worker processes (default: every core; 1: in this process)")
    p.add_argument("--dask", action="store_true",
                   help="compute on a local Dask cluster of --workers processes")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="compute on an existing Dask cluster (e.g. tcp://host:8786); the stores "
                   "must be on a path every worker can read and write")
    p.add_argument("--tile", type=at_least(1), default=None, metavar="N",
                   help="camera tile edge in pixels (default: the run store's chunk)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command; returns the exit code."""
    from station.api import reconstruct_ltc
    from station.errors import UsageError

    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other (--force starts afresh)")
    if not args.resume and check_output(args.out, args.force).exists():
        shutil.rmtree(args.out) if args.out.is_dir() else args.out.unlink()
    summary = reconstruct_ltc(args.run, args.out, tile_px=args.tile, progress=not args.quiet,
                              resume=args.resume, workers=args.workers, dask=args.dask,
                              scheduler=args.scheduler)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"LTC store {summary['out']}: {summary['camera_size'][0]}x{summary['camera_size'][1]} "
          f"pixels, P = {summary['period']}, {summary['patterns_per_depth']} patterns per depth, "
          f"{summary['seconds']:.1f} s ({summary['pixels_per_second']:.0f} pixels/s, "
          f"{summary['engine']})")
    for d in summary["depths"]:
        print(f"  z = {d['depth_mm']:g} mm: valid {100 * d['valid_fraction']:.1f} %, "
              f"gain {_fmt(d['gain_median_adu'])} ADU, noise {_fmt(d['noise_median'])}, "
              f"edge mass p95 {_fmt(d['edge_mass_p95'])}")
    return 0


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"
