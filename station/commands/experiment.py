"""``ltc experiment CONFIG --out DIR``: the reference paper's experiment, measured lens against
Gaussian defocus, with a report."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "experiment",
        help="the paper's experiment: station per camera, four virtual scanners, spheres, "
        "ball bars, a CAD part, report",
        description="Measure each rig camera's lens on its own fake bench (station sequence), "
        "build the real, measured-LTC, Gaussian and pinhole scanners, scan the 50.8007 mm "
        "sphere at 8 positions, the 209.8219 mm ball bar at 4 and a CAD part, compare every "
        "virtual cloud with the real one (unaligned and after ICP) and write DIR/report.md, "
        "DIR/figures/*.png and DIR/results.json.",
    )
    p.add_argument("config", type=Path, nargs="?", help="experiment config (TOML or JSON; "
                   "every field optional, see docs/formats.md); default: the built-in one")
    p.add_argument("--out", type=Path, required=True, help="new (or empty) output folder")
    p.add_argument("--paper-size", action="store_true", help="render at the reference "
                   "camera's pixel pitch and focal length, cropped to the objects (slow)")
    p.add_argument("--lenses", type=Path, nargs=2, metavar="LENS.npz", help="reuse two "
                   "measured lenses made with this config (skip the station)")
    p.add_argument("--json", action="store_true", help="end with one JSON line (report path "
                   "and every position's numbers, micrometres)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from station.experiment.run import load_experiment_config, paper_size_config, run_experiment

    cfg = load_experiment_config(args.config)
    if args.paper_size:
        cfg = paper_size_config(**cfg.model_dump(exclude_unset=True))
    results = run_experiment(cfg, args.out, progress=not args.quiet, log=print,
                             lenses=args.lenses)
    print_table(results)
    if args.json:
        print(json.dumps({"report": results["report"], "positions": results["positions"]}))
    return 0


def print_table(results: dict) -> None:
    """A short table: per position ltc and Gaussian against real, and the verdict."""
    print(f"{'pos':4s} {'kind':8s} {'defocus':>8s} | {'ltc mean/RMSE um':>17s} "
          f"{'d size':>7s} | {'gauss mean/RMSE um':>19s} {'d size':>7s}")
    for r in results["positions"]:
        m = r["models"]
        cells = []
        for n in ("ltc", "gaussian"):
            ds = (f"{m[n]['size_um'] - m['real']['size_um']:+7.1f}" if "size_um" in m[n]
                  else f"{'':7s}")
            cells.append(f"{m[n]['mean_um']:+8.1f}/{m[n]['rmse_um']:8.1f} {ds}")
        print(f"{r['name']:4s} {r['kind']:8s} {r['defocus_mm']:+8.0f} | {cells[0]} | {cells[1]}")
    a = results["acceptance"]
    print(f"ltc within limits at every position: {a['ltc_within_limits']}; Gaussian worse at "
          f"every large defocus: {a['gaussian_worse_at_large']}")
    print(f"report {results['report']}")
