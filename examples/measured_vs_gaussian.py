"""Load a measured lens and compare its virtual scan with the Gaussian defocus model's.

    .venv/bin/python examples/measured_vs_gaussian.py LENS.npz [OUT_DIR]

LENS.npz is a lens model from the station (``ltc lens``, ``ltc run``). The script builds a
stereo rig of two such cameras (their camera matrix and size from the lens file) converging
at +-12 degrees on a sphere, with a projector between them; scans the sphere in focus and
at large defocus with the measured lens on both cameras, then with its Gaussian equivalent
(docs/optics.md, section 4: the same focus distance, Gaussian aperture weights with the measured
LTC's second moment at the optical centre), and prints the sphere diameters and how far the
Gaussian scanner's cloud lies from the measured one's. OUT_DIR (default out/measured_vs_gaussian)
receives the clouds (PLY) and summary.json.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

import sim
from sim.optics.rig import look_at
from sim.render import SphereObject

ANGLE_DEG = 12.0  # each camera's angle to the rig's axis
PERIODS_PX = [64.0, 16.0, 8.0]  # the longest covers the projector


def stereo_rig(lens: sim.MeasuredLens) -> sim.Rig:
    """Two cameras with the lens's camera matrix and size at its focus distance from the world
    origin, converging at +-ANGLE_DEG; a 64 x 48 projector on the axis between them."""
    d = lens.focus_distance_mm
    K = lens.camera_matrix if lens.camera_matrix is not None else np.array(
        [[2.0 * lens.camera_size[0], 0, (lens.camera_size[0] - 1) / 2],
         [0, 2.0 * lens.camera_size[0], (lens.camera_size[1] - 1) / 2], [0, 0, 1]])
    devices = []
    for name, sign in (("left", -1), ("right", 1)):
        a = np.radians(sign * ANGLE_DEG)
        R, T = look_at(np.array([d * np.sin(a), 0.0, -d * np.cos(a)]), np.zeros(3))
        devices.append(sim.DeviceCalibration(name=name, K=K.tolist(), dist=[0.0] * 5,
                                             R=R.tolist(), T=T.tolist(),
                                             size=tuple(lens.camera_size)))
    f_p = K[0, 0] * 64 / lens.camera_size[0]
    R, T = look_at(np.array([0.0, 0.0, -d]), np.zeros(3))
    projector = sim.DeviceCalibration(name="projector", K=[[f_p, 0, 31.5], [0, f_p, 23.5],
                                                           [0, 0, 1]],
                                      dist=[0.0] * 5, R=R.tolist(), T=T.tolist(), size=(64, 48))
    return sim.Rig(cameras=devices, projector=projector)


def main(lens_path: str, out_dir: str = "out/measured_vs_gaussian") -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    measured = sim.MeasuredLens.load(lens_path)
    gaussian = sim.gaussian_equivalent(measured)
    rig = stereo_rig(measured)
    # the sphere fills about half the view at the focus distance
    diameter_mm = 0.5 * measured.focus_distance_mm * measured.camera_size[1] / rig.cameras[0].K[1][1]
    print(f"lens: {measured.camera_size[0]} x {measured.camera_size[1]} px, {measured.samples} "
          f"aperture samples, focus {measured.focus_distance_mm:.1f} mm; Gaussian sigma "
          f"{gaussian.sigma_mm:.3f} mm; sphere {diameter_mm:.2f} mm")
    summary = {"lens": str(lens_path), "gaussian_sigma_mm": gaussian.sigma_mm,
               "sphere_diameter_mm": diameter_mm, "positions": []}
    for name, shift in (("in focus", 0.0), ("defocused", -0.12)):
        z_mm = shift * measured.focus_distance_mm  # towards the cameras: nearer than focus
        scene = sim.Scene(objects=[SphereObject(name="sphere", diameter_mm=diameter_mm,
                                                pose={"t": [0.0, 0.0, z_mm]})])
        scanner = sim.Scanner(rig, (measured, measured), sim.PhaseShiftSet(periods_px=PERIODS_PX),
                              scene)
        row = {"position": name, "z_mm": z_mm}
        clouds = {}
        for label, lens in (("measured", measured), ("gaussian", gaussian)):
            s = scanner.with_lenses([lens, lens])
            cloud = s.scan(s.render())
            sim.write_ply(out / f"{name.replace(' ', '_')}_{label}.ply", cloud)
            fit = s.measure(cloud, sphere_mm=diameter_mm)
            assert isinstance(fit, sim.SphereMeasurement)
            clouds[label] = cloud
            row[label] = {"points": len(cloud.points),
                          "diameter_error_um": 1e3 * (fit.diameter_mm - diameter_mm)}
        cmp = sim.Scanner.measure(clouds["gaussian"], reference=clouds["measured"], align=False)
        assert isinstance(cmp, sim.DistanceMeasurement)
        row["gaussian_vs_measured"] = {"mean_um": 1e3 * cmp.mean_mm,
                                       "rmse_um": 1e3 * cmp.rmse_mm}
        summary["positions"].append(row)
        print(f"{name} (z = {z_mm:+.1f} mm): diameter error measured "
              f"{row['measured']['diameter_error_um']:+.1f} um, Gaussian "
              f"{row['gaussian']['diameter_error_um']:+.1f} um; Gaussian cloud vs measured: mean "
              f"{row['gaussian_vs_measured']['mean_um']:+.1f} um, RMSE "
              f"{row['gaussian_vs_measured']['rmse_um']:.1f} um")
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"wrote: {out / 'summary.json'}")
    return summary


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    main(*sys.argv[1:3])
