"""Render, scan and measure with the virtual scanner.

    .venv/bin/python examples/virtual_scan.py [SCENE.toml] [OUT.ply]

Renders the scene's fringe images on both cameras, reconstructs the stereo point cloud,
writes it as PLY, and measures the sphere against its nominal diameter (50.8007 mm in
examples/sphere_scene.toml).
"""

from __future__ import annotations

import sys
from pathlib import Path

import sim

HERE = Path(__file__).resolve().parent
NOMINAL_DIAMETER_MM = 50.8007


def main(scene_file: str = str(HERE / "sphere_scene.toml"), out_ply: str | None = None) -> dict:
    scanner = sim.Scanner.from_scene_file(scene_file)
    images = scanner.render()
    print(f"rendered: {len(images.cameras)} cameras x {images.cameras[0].images.shape[0]} images")
    cloud = scanner.scan(images)
    print(f"scanned: {len(cloud.points)} points (stereo)")
    if out_ply:
        sim.write_ply(out_ply, cloud)
        print(f"wrote: {out_ply}")
    report = scanner.measure(cloud, sphere_mm=NOMINAL_DIAMETER_MM)
    assert isinstance(report, sim.SphereMeasurement)
    print(f"sphere: diameter {report.diameter_mm:.4f} mm, error "
          f"{1e3 * (report.diameter_error_mm or 0.0):+.1f} um, fit RMS "
          f"{1e3 * report.fit_rms_mm:.1f} um")
    return report.to_json()


if __name__ == "__main__":
    main(*sys.argv[1:3])
