"""``ltc demo``: the whole chain on the fake benches, from station to report."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="the main job on the fake benches: station per camera, experiment, report",
        description="Run the whole chain on the built-in fake benches: for each rig camera a "
        "bench check, acquisition, LTC reconstruction and lens derivation; then the "
        "experiment (real, measured-LTC, Gaussian and pinhole scanners on spheres, ball bars "
        "and a CAD part) and its report. Ends with the report's path and a short table.",
    )
    p.add_argument("--out", type=Path, help="new output folder (default: out/demo-<time>)")
    p.add_argument("--config", type=Path, help="an experiment config (TOML or JSON) whose "
                   "fields replace the demo's")
    p.add_argument("--json", action="store_true", help="end with one JSON line: the report "
                   "path and every position's numbers (micrometres)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.commands.experiment import print_table
    from station.experiment.demo import demo_config, run_demo
    from station.experiment.run import load_experiment_config

    config = demo_config()
    if args.config is not None:
        config = load_experiment_config(args.config)
    results = run_demo(args.out, config=config, progress=not args.quiet)
    print_table(results)
    print(f"demo took {results['seconds']['demo']:.0f} s")
    if args.json:
        print(json.dumps({"report": results["report"], "positions": results["positions"]}))
    return 0
