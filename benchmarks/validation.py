"""What validating one position costs against rendering and scanning its virtual scanners
once, in the same run: writes benchmarks/results/validation.md.

A lab-like real-scan folder: the 50.8 mm sphere at large defocus (+150 mm) through an f/1 thin
lens, each camera pixel integrating 5 x 5 subpixels (binned, 16-bit PNGs), cameras 128 x 96
of ``small_rig(0.1)``. The twins (thin lens, pinhole) integrate 4 x 4 subpixels, as
``ltc validate`` renders twins of area-integrating cameras.

    PYTHONPATH=. .venv/bin/python benchmarks/validation.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "station" / "validation"))

from realdata import (  # noqa: E402
    Pose,
    small_test_rig,
    sphere,
    thin_lens,
    world_point,
    write_real_folder,
)

from station.validation.folder import load_real_scan  # noqa: E402
from station.validation.run import DEFAULT_PIXEL_SAMPLES, _decode, validate_position  # noqa: E402
from station.validation.twin import build_twins, render_scan, scene_at  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "validation.md"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        real = Path(tmp) / "real"
        write_real_folder(real, {"S2": ("large", sphere(), Pose(t=world_point(150.0)))},
                          small_test_rig(), lens=thin_lens(16.0, 64), factor=5)
        spec = Path(tmp) / "thin.toml"
        spec.write_text('kind = "thin"\npupil_diameter_mm = 16.0\n'
                        'focus_distance_mm = 760.0\nsamples = 64\n')
        scan = load_real_scan(real)
        twins = build_twins(scan.rig, [spec, spec])
        pos = scan.positions[0]
        decode = _decode(scan.spec.pixel_variance_px2)
        validate_position(scan, pos, twins)  # warm up (numba, Embree)
        rows = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res, _ = validate_position(scan, pos, twins)
            t_val = time.perf_counter() - t0
            pose = Pose.model_validate(res.refined_pose)
            t1 = time.perf_counter()
            for lenses in twins.values():
                render_scan(scan.rig, lenses, scan.patterns,
                            scene_at(pos.spec.artefact, pose, pos.name), pos.name, None, decode,
                            pixel_samples=DEFAULT_PIXEL_SAMPLES)
            t_once = time.perf_counter() - t1
            rows.append((t_val, t_once, len(res.refine_steps_um), res.seconds))
    mid = sorted(rows, key=lambda r: r[0])[len(rows) // 2]  # the median validation's run
    t_val, t_once, steps, sec = mid
    lines = [
        "# Validating one position (benchmarks/validation.py)", "",
        f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, "
        f"{time.strftime('%Y-%m-%d')}; the median of {args.repeats} runs (each: validate the "
        "position, then render and scan its twins once at the refined pose).", "",
        "| what | seconds |", "|---|---|",
        f"| render and scan of the twins once at the refined pose ({', '.join(twins)}) "
        f"| {t_once:.2f} |",
        f"| validating the position (`validate_position`) | {sec['total']:.2f} |",
        f"| of which render and scan, refinement included ({steps} renders of "
        f"`{next(iter(twins))}`) | {sec['render_and_scan']:.2f} |",
        f"| of which the real scan, locating, response and comparisons "
        f"| {sec['total'] - sec['render_and_scan']:.2f} |", "",
        f"Validation / one render and scan of its twins: **{sec['total'] / t_once:.2f} x** "
        f"(target <= 1.20 x); the overhead beyond every render and scan it does: "
        f"{(sec['total'] - sec['render_and_scan']) / sec['render_and_scan'] * 100:.0f} %.", "",
        "The refinement renders the primary twin once per step (the last step's render is "
        "the one compared), so a position costs one render per twin plus one per extra "
        f"step of the primary twin: here {sec['render_and_scan'] / t_once:.2f} x in renders "
        "alone. A refinement to 1 um takes at least two steps (the real fit is 100-850 um "
        "from the pose at large defocus and the twin's bias changes by about 1 % of a step), "
        "so the 1.2 x asked for is out of reach while every step is a full render "
        "(docs/decisions/0051-pose-by-analysis-by-synthesis.md).", ""]
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
