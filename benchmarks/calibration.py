"""Calibration against rendering: the virtual scanner renders a 15-pose chessboard capture
for two 1280 x 1024 cameras and a 1920 x 1080 projector (pinhole, noise-free 16-bit, 25
images per pose and camera: white, 12 fringe images along u, 12 along v), written as PNGs;
then ``sim.calibration.calibrate`` reads it back and calibrates. Both are timed in the same
run on the same machine; the ratio calibrate / render (render = tracing and gathering, not the
PNG writing) must stay below 1. The calibrated rig's errors against the true rig are reported
too.

    .venv/bin/python benchmarks/calibration.py --write-results   # about 5-10 minutes, 2 cores
    .venv/bin/python benchmarks/calibration.py --poses 4          # smoke run

``--write-results`` rewrites benchmarks/results/calibration.md whole.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _results import command_line, write_results  # noqa: E402

from sim.calibration.calibrator import calibrate  # noqa: E402
from sim.calibration.virtual import calibration_rig, default_poses, render_capture  # noqa: E402
from sim.optics.rig import relative_to_camera_0  # noqa: E402
from sim.render.board import CalibrationBoard  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=15)
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/calibration.md")
    args = ap.parse_args()
    board = CalibrationBoard(kind="chessboard", rows=7, columns=10, square_mm=20.0)
    rig = calibration_rig(camera_dist=(-0.1, 0.0, 0.001, 0.0, 0.0))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        rc = render_capture(Path(tmp) / "capture", board, rig, default_poses(board, args.poses))
        t_render_total = time.perf_counter() - t0
        t1 = time.perf_counter()
        result = calibrate(rc.directory, board)
        t_cal = time.perf_counter() - t1
    true = relative_to_camera_0(rig)
    rows = []
    for a, b in zip([*result.rig.cameras, result.rig.projector],
                    [*true.cameras, true.projector], strict=True):
        dR = a.R_array @ b.R_array.T
        ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
        rows.append(f"| {a.name} | {result.rms_px[a.name]:.4f} | "
                    f"{100 * abs(a.K_array[0, 0] / b.K_array[0, 0] - 1):.4f} | "
                    f"{np.abs(a.K_array[:2, 2] - b.K_array[:2, 2]).max():.3f} | {ang:.5f} | "
                    f"{np.abs(a.T_array - b.T_array).max():.4f} |")
    ratio = t_cal / rc.render_s
    when = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        f"`benchmarks/calibration.py`, {when}, {platform.machine()}, {os.cpu_count()} cores "
        f"(shared: compare the ratio, not absolute times).", "",
        f"{args.poses} chessboard poses (7 x 10 squares of 20 mm), two 1280 x 1024 cameras "
        "(k1 = -0.1, p1 = 0.001), a 1920 x 1080 projector, pinhole, noise-free 16-bit; 25 "
        "images per pose and camera.", "",
        "| step | seconds |", "|---|---|",
        f"| render (trace, albedo, gather, camera response) | {rc.render_s:.1f} |",
        f"| write the PNGs | {rc.write_s:.1f} |",
        f"| render capture in all | {t_render_total:.1f} |",
        f"| calibrate (read, decode, features, Zhang, bundle adjustment) | {t_cal:.1f} |",
        f"| of which reading and features | {result.timings['features_s']:.1f} |",
        f"| of which Zhang and the bundle adjustment | {result.timings['adjust_s']:.1f} |", "",
        f"**calibrate / render = {ratio:.2f}** (calibrate / render and write = "
        f"{t_cal / t_render_total:.2f}).", "",
        "Calibrated against the true rig:", "",
        "| device | RMS px | focal error % | principal point error px | rotation error deg "
        "| translation error mm |", "|---|---|---|---|---|---|", *rows, ""]
    print("\n".join(lines))
    if args.write_results:
        write_results(__file__, "Calibration against rendering", "\n".join(lines),
                      command=command_line())


if __name__ == "__main__":
    main()
