"""Write the projector images of a calibration capture (PNG, the projector's resolution).

With --calibration: the images a real projector shows at each board pose, in the order the
calibration capture expects (docs/formats.md, "Calibration capture"): pattern_000.png white,
then the phase shifts along projector columns (u), then along projector rows (v), 8-bit; and
capture.json, which goes into the capture folder. Fringe counts across the projector per
direction default to 1, 8, 64 (u) and 1, 6, 36 (v).
"""

from __future__ import annotations

import argparse

from station.commands import at_least
from station.errors import UsageError, check_output

OPTIONS = {"out": "folder to create", "force": "replace --out if it exists", "json": None}


def _counts(text: str) -> list[float]:
    try:
        values = [float(t) for t in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected fringe counts like 1,8,64, got {text!r}") \
            from None
    if not values or any(not v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"fringe counts must be > 0, got {text!r}")
    return values


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(t) for t in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be >= 1 px, got {text!r}")
    return w, h


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--calibration", action="store_true", required=True,
                   help="the calibration capture's patterns (the one kind so far)")
    p.add_argument("--projector-size", type=_size, default=(1920, 1080), metavar="WxH",
                   help="projector resolution (default 1920x1080)")
    p.add_argument("--u-fringes", type=_counts, default=[1.0, 8.0, 64.0],
                   help="fringe counts across the width (default 1,8,64)")
    p.add_argument("--v-fringes", type=_counts, default=[1.0, 6.0, 36.0],
                   help="fringe counts across the height (default 1,6,36)")
    p.add_argument("--steps", type=at_least(3), default=4, help="phase shifts (default 4)")


def run(args: argparse.Namespace) -> dict:
    import shutil

    import cv2
    import numpy as np

    from sim.calibration.capture import CalibrationPatterns
    from sim.render.fringe_patterns import PhaseShiftSet

    out = check_output(args.out, args.force)
    w, h = args.projector_size
    if max(args.u_fringes) > w / 2 or max(args.v_fringes) > h / 2:
        raise UsageError("a fringe needs at least 2 projector pixels: fewer fringes, please")
    pats = CalibrationPatterns(
        projector_size=(w, h),
        u=PhaseShiftSet(direction="u", periods_px=[w / c for c in args.u_fringes],
                        steps=args.steps),
        v=PhaseShiftSet(direction="v", periods_px=[h / c for c in args.v_fringes],
                        steps=args.steps))
    if out.exists():
        shutil.rmtree(out) if out.is_dir() else out.unlink()
    out.mkdir(parents=True)
    images = pats.images()
    for i, im in enumerate(images):
        path = out / f"pattern_{i:03d}.png"
        if not cv2.imwrite(str(path), np.round(im * 255).astype(np.uint8)):
            raise OSError(f"could not write {path}")
    pats.save(out)
    return {"out": str(out), "images": len(images), "projector_size": [w, h]}


def text(s: dict) -> str:
    w, h = s["projector_size"]
    return f"wrote {s['images']} projector images ({w}x{h}) and capture.json to {s['out']}"
