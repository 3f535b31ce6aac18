"""``ltc acquire CONFIG --out RUN.zarr [--resume] [--json] [--quiet]``."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from drivers.interfaces import DeviceError
from station.acquisition.acquire import AcquisitionError, acquire
from station.acquisition.config import ConfigError, load_config
from station.acquisition.run_store import RunStoreError


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
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not logging.getLogger().handlers:
        logging.basicConfig(level=logging.INFO, format="ltc acquire: %(levelname)s: %(message)s")
    try:
        config = load_config(args.config)
    except ConfigError as exc:
        print(f"ltc acquire: {exc}", file=sys.stderr)
        return 2
    try:
        summary = acquire(config, args.out, resume=args.resume, progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"ltc acquire: interrupted; finish with: ltc acquire {args.config} --out "
              f"{args.out} --resume", file=sys.stderr)
        return 130
    except (AcquisitionError, RunStoreError, ConfigError, DeviceError) as exc:
        notes = "".join(f"\n  {n}" for n in getattr(exc, "__notes__", []))
        print(f"ltc acquire: {type(exc).__name__}: {exc}{notes}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"ltc acquire: {summary['status']}: {summary['frames_written']} frames in "
              f"{summary['seconds']:.1f} s ({summary['frames_per_second']:.1f}/s) -> {args.out}; "
              f"retries {summary['retries'] or 'none'}; saturated frames "
              f"{summary['saturated_frames']}")
    return 0
