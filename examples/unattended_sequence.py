"""An unattended station sequence from config to lens model, resumable after an interruption.

    .venv/bin/python examples/unattended_sequence.py OUT_DIR [CONFIG.toml] [--force]

Start it in the evening; if the machine is stopped (Ctrl-C, a crash, a power cut), run the
same command again: finished steps are skipped, the acquisition continues at the first frame
not written, and the rest runs as before (a dead run's writer lock dies with it; a live run's
refuses the second one, naming it). OUT_DIR/summary.json says how every step went.
Without CONFIG the built-in fake bench is used.
"""

from __future__ import annotations

import sys
from pathlib import Path

import station
from station.acquisition.config import example_config


def main(out_dir: str, config_path: str | None = None,
         force: bool = False) -> station.SequenceSummary:
    config = station.load_config(config_path) if config_path else example_config("fake")
    try:
        summary = station.run_sequence(config, out_dir, force=force)
    except station.StationError as exc:
        sys.exit(f"unattended_sequence: {exc}")
    for name, step in summary.steps.items():
        print(f"{name}: {step.status}")
    o = (summary.steps["lens"].result or {})["optical_centre_mm"]
    print(f"optical centre: ({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) mm")
    print(f"lens model: {Path(out_dir) / 'lens.npz'}")
    return summary


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if a != "--force"]
    main(args[0] if args else "out/sequence", args[1] if len(args) > 1 else None,
         force="--force" in sys.argv[1:])
