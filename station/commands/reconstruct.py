"""Reconstruct per-pixel LTC from a complete acquisition run.

Demodulate the Fourier frames of a run store, unfold with the localisation map and write an
LTC store, tile by tile (bounded memory), on every core, on a local Dask cluster (--dask) or
on an existing one (--scheduler); all give the same store bit for bit. A killed
reconstruction is finished with --resume.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.commands import at_least
from station.errors import UsageError

OPTIONS = {"out": "LTC store to create (LTC.zarr)",
           "force": "replace the LTC store in --out (the old one stays until the new one is "
                    "complete; only an LTC store is replaced)",
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
    from station.outputs import LTC_STORE, check_output, staged

    args.resume_hint = f"; finish with: ltc reconstruct {args.run} --out {args.out} --resume"
    if args.resume and args.force:
        raise UsageError("--resume and --force exclude each other (--force starts afresh)")
    if args.resume:
        return reconstruct_ltc(args.run, args.out, tile_px=args.tile, progress=not args.quiet,
                               resume=True, workers=args.workers, dask=args.dask,
                               scheduler=args.scheduler)
    out = check_output(args.out, args.force, kind=LTC_STORE, inputs=[args.run])
    if out.exists():
        args.resume_hint = (f"; the old LTC store {out} is unchanged; start again with: "
                            f"ltc reconstruct {args.run} --out {out} --force")
    with staged(out, LTC_STORE) as target:
        summary = reconstruct_ltc(args.run, target, tile_px=args.tile, progress=not args.quiet,
                                  resume=False, workers=args.workers, dask=args.dask,
                                  scheduler=args.scheduler)
    return {**summary, "out": str(out)}


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
