"""``ltc acquire CONFIG --out RUN.zarr [--resume] [--force] [--json] [--quiet]``."""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

from station.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "acquire",
        help="measure: show the Fourier and localisation patterns at every depth, capture them",
        description="Run an acquisition into a run store (zarr). Every frame is written durably; "
        "an interrupted run continues with --resume at the first frame not done.",
    )
    p.add_argument("config", type=Path, help="station config (TOML)")
    p.add_argument("--out", type=Path, required=True, help="run store to create (RUN.zarr)")
    p.add_argument("--resume", action="store_true",
                   help="finish the run in --out (its config must be the same)")
    p.add_argument("--force", action="store_true",
                   help="delete an existing run store in --out and start again; with --resume, "
                   "take over the writer lock left by a killed run (never a live writer's)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.acquisition.lock import StoreLock
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
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"ltc acquire: {summary['status']}: {summary['frames_written']} frames in "
              f"{summary['seconds']:.1f} s ({summary['frames_per_second']:.1f}/s) -> {args.out}; "
              f"retries {summary['retries'] or 'none'}; saturated frames "
              f"{summary['saturated_frames']}")
    return 0
