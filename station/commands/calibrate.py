"""Calibrate the scanner (both cameras and the projector) from a calibration capture.

CAPTURE_DIR holds capture.json and pose_<nnn>/camera_<i>/ image folders (white, then the
fringes along projector columns and rows; docs/formats.md, "Calibration capture"); --board is
the board file (TOML). Writes the rig in OpenCV stereoCalibrate naming (M1 D1 M2 D2 R T,
projector M3 D3 R3 T3), which ltc scan and scene files read, and with --report a report folder
(report.md, figures). Bad input is refused with one line naming the pose and camera.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from station.errors import StationError, UsageError, check_output

OPTIONS = {"out": "rig file to write (.yaml, .yml or .xml)", "force": None, "json": None}
MODELS = ("none", "k1k2", "k1k2p1p2k3")


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture", type=Path, help="calibration capture folder")
    p.add_argument("--board", type=Path, required=True, help="board file (TOML)")
    p.add_argument("--report", type=Path, help="report folder to create (report.md, figures)")
    p.add_argument("--camera-distortion", choices=MODELS, default="k1k2p1p2k3",
                   help="distortion model of both cameras (default k1k2p1p2k3)")
    p.add_argument("--projector-distortion", choices=MODELS, default="k1k2",
                   help="distortion model of the projector (default k1k2)")
    p.add_argument("--projector-features", choices=("homography", "sample"),
                   default="homography", help="projector coordinates of a feature: a local "
                   "homography over the phase around it (default) or the phase at its pixel")


def run(args: argparse.Namespace) -> dict:
    from sim.calibration.calibrator import calibrate
    from sim.optics.rig import save_stereo_calibrate

    out = check_output(args.out, args.force)
    if out.suffix.lower() not in (".yaml", ".yml", ".xml"):
        raise UsageError(f"--out {out}: the rig is written as OpenCV FileStorage; use .yaml, "
                         ".yml or .xml")
    if args.report is not None:
        check_output(args.report, args.force, "--report")
    if not args.capture.is_dir():
        raise StationError(f"capture folder {args.capture} not found")
    if not args.board.is_file():
        raise StationError(f"board file {args.board} not found")
    cam = args.camera_distortion
    result = calibrate(args.capture, args.board,
                       distortion=(cam, cam, args.projector_distortion),
                       projector_method=args.projector_features)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_stereo_calibrate(result.rig, out)
    summary = {"out": str(out), "rms_px": result.rms_px, "poses": len(result.poses),
               "timings": result.timings}
    if args.report is not None:
        from sim.calibration.report import write_report

        if args.report.exists():
            shutil.rmtree(args.report)
        summary["report"] = str(write_report(result, args.report))
    return summary


def text(s: dict) -> str:
    rms = ", ".join(f"{k} {v:.4f} px" for k, v in s["rms_px"].items())
    extra = f"; report {s['report']}" if "report" in s else ""
    return f"{s['poses']} poses, RMS {rms}; wrote {s['out']}{extra}"
