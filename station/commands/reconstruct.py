"""Reconstruct per-pixel LTC from a complete acquisition run.

Demodulate the Fourier frames of a run store, unfold with the localisation map and write an
LTC store, tile by tile (bounded memory), on every core, on a local Dask cluster (--dask) or
on an existing one (--scheduler); all give the same store bit for bit. A killed
reconstruction is finished with --resume.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from station.commands import at_least
from station.errors import UsageError, check_output

OPTIONS = {"out": "LTC store to create (LTC.zarr)", "force": "replace --out if it exists",
           "json": None, "quiet": None, "workers": None, "dask": None,
           "scheduler": "compute on an existing Dask cluster (e.g. tcp://host:8786); the stores "
                        "must be on a path every worker can read and write"}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", type=Path, metavar="RUN.zarr", help="run store written by 'ltc acquire'")
    p.add_argument("--resume", action="store_true",
                   help="finish the --out store a killed reconstruction of this run left")
    p.add_argument("--tile", type=at_least(1), default=None, metavar="N",
                   help="camera tile edge in pixels (default: the run store's chunk)")


def run(args: argparse.Namespace) -> dict:
    from station.api import reconstruct_ltc

    args.resume_hint = f"; finish with: ltc reconstruct {args.run} --out {args.out} --resume"
    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other (--force starts afresh)")
    if not args.resume and check_output(args.out, args.force).exists():
        if args.out.is_dir():
            from sim.storage.lock import StoreLock

            with StoreLock(args.out):  # never under a live writer (refused, naming it)
                shutil.rmtree(args.out)
        else:
            args.out.unlink()
    return reconstruct_ltc(args.run, args.out, tile_px=args.tile, progress=not args.quiet,
                           resume=args.resume, workers=args.workers, dask=args.dask,
                           scheduler=args.scheduler)


def text(s: dict) -> str:
    lines = [f"LTC store {s['out']}: {s['camera_size'][0]}x{s['camera_size'][1]} pixels, "
             f"P = {s['period']}, {s['patterns_per_depth']} patterns per depth, "
             f"{s['seconds']:.1f} s ({s['pixels_per_second']:.0f} pixels/s, {s['engine']})"]
    lines += [f"  z = {d['depth_mm']:g} mm: valid {100 * d['valid_fraction']:.1f} %, gain "
              f"{_fmt(d['gain_median_adu'])} ADU, noise {_fmt(d['noise_median'])}, edge mass "
              f"p95 {_fmt(d['edge_mass_p95'])}" for d in s["depths"]]
    return "\n".join(lines)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3g}"
