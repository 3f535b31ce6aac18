"""The main job on the fake benches: station per camera, experiment, report.

Run the whole chain on the built-in fake benches: for each rig camera a bench check,
acquisition, LTC reconstruction and lens derivation; then the experiment (real, measured-LTC,
Gaussian and pinhole scanners on spheres, ball bars and a CAD part) and its report. Ends with
the report's path and a short table; with --json, one JSON object: the report's path and every
position's numbers (micrometres).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from station.commands.experiment import log, report, text  # noqa: F401 - the same table

OPTIONS = {"json": None, "quiet": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, help="new output folder (default: out/demo-<time>)")
    p.add_argument("--config", type=Path, help="an experiment config (TOML or JSON) whose "
                   "fields replace the demo's")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from station.experiment.config import load_experiment_config
    from station.experiment.demo import demo_config, run_demo

    config = demo_config() if args.config is None else load_experiment_config(args.config)
    return report(run_demo(args.out, config=config, progress=not args.quiet, log=log(args)),
                  args)
