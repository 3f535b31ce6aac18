"""Measure: show the Fourier and localisation patterns at every depth, capture them.

Run an acquisition into a run store (zarr). Every frame is written durably; an interrupted run
continues with --resume at the first frame not done. One writer at a time: the store's lock
file names its holder.
"""

from __future__ import annotations

import argparse
import logging
import shutil

from station.errors import UsageError

OPTIONS = {"config": None, "out": "run store to create (RUN.zarr)",
           "force": "delete an existing run store in --out and start again (never one a live "
                    "writer holds)",
           "json": None, "quiet": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--resume", action="store_true",
                   help="finish the run in --out (its config must be the same)")


def run(args: argparse.Namespace) -> dict:
    from sim.storage.lock import StoreLock
    from station.api import acquire, load_config

    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="ltc acquire: %(levelname)s: %(message)s")
    args.resume_hint = (f"; finish with: ltc acquire {args.config} --out {args.out} --resume")
    config = load_config(args.config)
    if args.out.exists() and not args.resume:
        if not args.force:
            raise UsageError(f"--out {args.out} exists; pass --resume to finish that run, "
                             "--force to delete it and start again, or choose another path")
        if args.out.is_dir():
            with StoreLock(args.out, force=True):  # refuses a store a live writer holds
                pass
            shutil.rmtree(args.out)
        else:
            args.out.unlink()
    summary = acquire(config, args.out, resume=args.resume, progress=not args.quiet,
                      force=args.force)
    return {**summary, "out": str(args.out)}


def text(s: dict) -> str:
    return (f"ltc acquire: {s['status']}: {s['frames_written']} frames in {s['seconds']:.1f} s "
            f"({s['frames_per_second']:.1f}/s) -> {s['out']}; retries {s['retries'] or 'none'}; "
            f"saturated frames {s['saturated_frames']}"
            + (f"; recaptured {len(s['frames_recaptured'])} damaged frame(s) "
               f"{[tuple(f) for f in s['frames_recaptured']]}"
               if s.get("frames_recaptured") else ""))
