"""The paper's experiment: station per camera, four virtual scanners, spheres, ball bars, a CAD part, report.

Measure each rig camera's lens on its own fake bench (station sequence), build the real,
measured-LTC, Gaussian and pinhole scanners, scan the 50.8007 mm sphere at 8 positions, the
209.8219 mm ball bar at 4 and a CAD part, compare every virtual cloud with the real one
(unaligned and after ICP) and write DIR/report.md, DIR/figures/*.png and DIR/results.json.
With --json the one JSON object holds the report's path and every position's numbers
(micrometres). Run it again with the same config and --out after an interruption to resume.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from station.experiment.rows import PositionRow

OPTIONS = {"out": "new (or empty) output folder, or an interrupted experiment's folder to "
           "resume it (same config)",
           "force": "accepted for scripts; a lock a killed run left is free anyway (never a live "
                    "writer's)",
           "json": None, "quiet": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", type=Path, nargs="?", help="experiment config (TOML or JSON; "
                   "every field optional, see docs/formats.md); default: the built-in one")
    p.add_argument("--paper-size", action="store_true", help="render at the reference "
                   "camera's pixel pitch and focal length, cropped to the objects (slow)")
    p.add_argument("--lenses", type=Path, nargs=2, metavar="LENS.npz", help="reuse two "
                   "measured lenses made with this config (skip the station)")
    p.add_argument("--real-out", type=Path, metavar="DIR", help="write the real scanner's "
                   "images as a real-scan folder here (default: OUT/real), which ltc validate "
                   "reads as a lab's")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from station.experiment.run import load_experiment_config, paper_size_config, run_experiment

    cfg = load_experiment_config(args.config)
    if args.paper_size:
        cfg = paper_size_config(**cfg.model_dump(exclude_unset=True))
    return report(run_experiment(cfg, args.out, progress=not args.quiet, log=log(args),
                                 lenses=args.lenses, force=args.force,
                                 real_out=args.real_out), args)


def log(args: argparse.Namespace) -> Callable[[str], None]:
    """Where progress lines go: stdout, or stderr when stdout carries the one JSON object."""
    if args.json:
        return lambda line: print(line, file=sys.stderr)
    return print


def report(results: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """What the command prints: the report's path, every position, the verdicts, timings;
    for the text table also the positions' rows (``PositionRow``, not in the JSON)."""
    keys = ("report", "positions", "acceptance", "seconds")
    out: dict[str, Any] = {k: results[k] for k in keys if k in results}
    if not args.json:
        out["rows"] = results["rows"]
    return out


def text(results: dict[str, Any]) -> str:
    """A short table: per position ltc and Gaussian against real (``d size``: size minus
    real's on the pixels both clouds share, um), and the verdict."""
    rows: dict[str, PositionRow] = {r.name: r for r in results.get("rows", [])}
    lines = [f"{'pos':4s} {'kind':8s} {'defocus':>8s} | {'ltc mean/RMSE um':>17s} "
             f"{'d size':>7s} | {'gauss mean/RMSE um':>19s} {'d size':>7s}"]
    for r in results["positions"]:
        m = r["models"]
        cells = []
        for n in ("ltc", "gaussian"):
            row = rows.get(r["name"])
            shared = row.models[n].size_vs_real_um if row is not None else None
            ds = f"{shared:+7.1f}" if shared is not None else f"{'':7s}"
            cells.append(f"{m[n]['mean_um']:+8.1f}/{m[n]['rmse_um']:8.1f} {ds}")
        lines.append(f"{r['name']:4s} {r['kind']:8s} {r['defocus_mm']:+8.0f} | {cells[0]} | "
                     f"{cells[1]}")
    a = results["acceptance"]
    lines.append(f"ltc within limits at every position: {a['ltc_within_limits']}; Gaussian "
                 f"worse at every large defocus: {a['gaussian_worse_at_large']} (d size: "
                 "against real on the pixels both clouds share, um)")
    if "demo" in results.get("seconds", {}):
        lines.append(f"demo took {results['seconds']['demo']:.0f} s")
    lines.append(f"report {results['report']}")
    return "\n".join(lines)
