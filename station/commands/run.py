"""``ltc run CONFIG --out DIR``: the whole station sequence, unattended and resumable."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="the whole station sequence unattended: check, gamma, align, acquire, "
        "reconstruct, lens",
        description="Run the station sequence into one folder: bench check, gamma calibration "
        "(if [sequence] gamma = true), alignment report, acquisition at every depth, LTC "
        "reconstruction and lens derivation. Re-running with the same config and --out "
        "continues where it stopped. DIR/run.log logs every step, DIR/summary.json records "
        "every step's outcome.",
    )
    p.add_argument("config", type=Path, help="station config (TOML)")
    p.add_argument("--out", type=Path, required=True, help="sequence folder (created, or "
                   "continued when it holds this config's earlier run)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.sequence import run_sequence

    args.resume_hint = f"; continue with: ltc run {args.config} --out {args.out}"
    summary = run_sequence(args.config, args.out, progress=not args.quiet)
    if args.json:
        print(json.dumps(summary))
        return 0
    for name, step in summary["steps"].items():
        took = f" in {step['seconds']:.1f} s" if "seconds" in step else ""
        print(f"{name:12s} {step['status']}{took}")
    lens = summary["steps"].get("lens", {}).get("result", {})
    if lens:
        o = lens["optical_centre_mm"]
        print(f"optical centre ({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) mm; lens {args.out / 'lens.npz'}")
    print(f"summary {args.out / 'summary.json'}; log {args.out / 'run.log'}")
    return 0
