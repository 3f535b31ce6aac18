"""``ltc reconstruct RUN.zarr --out LTC.zarr [--json] [--tile N]``: LTC store from a run store."""

from __future__ import annotations

import argparse
import json
import sys

from station.ltc.store import LtcStoreError
from station.acquisition.run_store import RunStoreError
from station.ltc.spi import reconstruct


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``reconstruct`` subcommand."""
    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct per-pixel LTC from a complete acquisition run",
        description="Demodulate the Fourier frames of a run store, unfold with the "
        "localisation map and write an LTC store, tile by tile (bounded memory).",
    )
    p.add_argument("run", metavar="RUN.zarr", help="run store written by 'ltc acquire'")
    p.add_argument("--out", required=True, metavar="LTC.zarr",
                   help="LTC store to create (must not exist)")
    p.add_argument("--tile", type=int, default=None, metavar="N",
                   help="camera tile edge in pixels (default: the run store's chunk)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the command; returns the exit code (1 on a store error, message on stderr)."""
    try:
        summary = reconstruct(args.run, args.out, tile_px=args.tile, progress=not args.json)
    except (RunStoreError, LtcStoreError) as exc:
        print(f"ltc reconstruct: error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"LTC store {summary['out']}: {summary['camera_size'][0]}x{summary['camera_size'][1]} "
          f"pixels, P = {summary['period']}, {summary['patterns_per_depth']} patterns per depth, "
          f"{summary['seconds']:.1f} s ({summary['pixels_per_second']:.0f} pixels/s)")
    for d in summary["depths"]:
        print(f"  z = {d['depth_mm']:g} mm: valid {100 * d['valid_fraction']:.1f} %, "
              f"gain {_fmt(d['gain_median_adu'])} ADU, noise {_fmt(d['noise_median'])}, "
              f"edge mass p95 {_fmt(d['edge_mass_p95'])}")
    return 0


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"
