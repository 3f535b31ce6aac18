"""Drive the built-in fake bench by hand: home, move, show a pattern, capture, save.

    .venv/bin/python examples/drive_fake_bench.py OUT_DIR

The same script drives a real bench: give it a real config instead of the fake example
(``ltc config --example real``). Prints one line per step; writes OUT_DIR/frame.png and
OUT_DIR/frame.json (the frame's metadata).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

import station
from station.acquisition.config import example_config


def main(out_dir: str) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    config = example_config("fake")                   # or station.load_config("bench.toml")
    with station.open_bench(config) as bench:
        bench.stage.home()
        print(f"homed: stage at {bench.stage.position_mm:.3f} mm")
        z_mm = config.depths_mm[0]
        bench.stage.move_to(z_mm)
        print(f"moved: stage at {bench.stage.position_mm:.3f} mm (asked {z_mm} mm)")
        w, h = bench.display.size
        pattern = np.zeros((h, w), np.uint8)
        pattern[:, : w // 2] = 255                    # left half of the LCD white
        shown = bench.display.show(pattern)
        print(f"showed: a {w} x {h} half-white pattern, swap {shown.index}")
        frame = bench.camera.capture()
        print(f"captured: frame {frame.frame_id}, {frame.image.shape[1]} x {frame.image.shape[0]} "
              f"{frame.image.dtype}, {bench.camera.bit_depth} bits, exposure {frame.exposure_ms} ms")
    cv2.imwrite(str(out / "frame.png"), frame.image)
    meta = {"stage_mm": z_mm, "frame_id": frame.frame_id, "exposure_ms": frame.exposure_ms,
            "mean_left": float(frame.image[:, : frame.image.shape[1] // 2].mean()),
            "mean_right": float(frame.image[:, frame.image.shape[1] // 2 :].mean())}
    (out / "frame.json").write_text(json.dumps(meta, indent=2))
    print(f"saved: {out / 'frame.png'} (mean left {meta['mean_left']:.1f}, "
          f"right {meta['mean_right']:.1f} DN)")
    return meta


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "out/drive")
