"""The whole station sequence unattended: check, gamma, align, acquire, reconstruct, lens.

Run the station sequence into one folder: bench check, gamma calibration (if [sequence] gamma
= true), alignment report, acquisition at every depth, LTC reconstruction and lens derivation.
Re-running with the same config and --out continues where it stopped (also after a crash or
a kill: the lock a dead run leaves is free). DIR/run.log logs every
step, DIR/summary.json records every step's outcome.
"""

from __future__ import annotations

import argparse
from pathlib import Path

OPTIONS = {"config": None,
           "out": "sequence folder (created, or continued when it holds this config's earlier run)",
           "force": "accepted for scripts; a lock a killed run left is free anyway (never a live "
                    "writer's)",
           "json": None, "quiet": None}


def run(args: argparse.Namespace) -> dict:
    from station.sequence import run_sequence

    args.resume_hint = f"; continue with: ltc run {args.config} --out {args.out}"
    args.log_file = Path(args.out) / "run.log"  # where the CLI keeps a bug's traceback
    summary = run_sequence(args.config, args.out, progress=not args.quiet, force=args.force)
    return {**summary.to_json(), "out": str(args.out)}


def text(s: dict) -> str:
    out = Path(s["out"])
    lines = [f"{name:12s} {step['status']}"
             + (f" in {step['seconds']:.1f} s" if "seconds" in step else "")
             for name, step in s["steps"].items()]
    lens = s["steps"].get("lens", {}).get("result", {})
    if lens:
        o = lens["optical_centre_mm"]
        lines.append(f"optical centre ({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) mm; lens "
                     f"{out / 'lens.npz'}")
    lines.append(f"summary {out / 'summary.json'}; log {out / 'run.log'}")
    return "\n".join(lines)
