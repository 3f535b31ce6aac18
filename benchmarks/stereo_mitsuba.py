"""Two-camera benchmark against Mitsuba 3: stereo and camera-projector
reconstruction of the sphere from an independent renderer's images.

Scene: the 50.8007 mm sphere at the world origin and a plane 100 mm behind it
(``_bench_scene.bench_scene``); two 1280 x 1024 cameras (16 mm lens, 4.8 um pixels) 220 mm
apart, 760 mm from the sphere, converging on it; a 1280 x 800 projector between them. All three
are ideal centred pinholes (Mitsuba's projector is one). Patterns: 4-step phase shift at 1, 8
and 64 fringes across the projector (12 images). Lenses: pinhole (Mitsuba 64 spp) and an ideal
thin lens at f/2.8 focused at 760 mm (64 spp).

Each camera is rendered by Mitsuba (``_mitsuba_scene.MitsubaFringeRenderer``, one renderer per
camera, same projector), and, for reference, by ours. The images go through
``sim.fpp.decode.scan`` in stereo and camera-projector mode (relative modulation threshold
only: the images are float radiance; Mitsuba's images with the pixel-footprint correction of a
full square pixel, ``pixel_variance_px2 = 1/12``, as its box pixel filter averages each pixel's
area like a real camera; ours sample the pixel centres). Judged with no outlier rejection on every point within
R + 3 mm of the true centre: the least-squares diameter error, the fit RMS, the share of
points more than 20 um off the true surface; and the scan time (decode, match, triangulate).

Run::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        .venv/bin/python benchmarks/stereo_mitsuba.py [--spp 64] [--scale 1] [--write-results]
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _bench_scene import SPHERE_DIAMETER_MM, bench_scene, machine  # noqa: E402
from _mitsuba_scene import MitsubaFringeRenderer, irradiance_scale_at, unavailable_reason  # noqa: E402
from _results import command_line, write_results  # noqa: E402

from sim.fpp.decode import DecodeSettings, scan  # noqa: E402
from sim.metrology.spheres import fit_sphere  # noqa: E402
from sim.optics.lens import AberratedLens, PinholeLens  # noqa: E402
from sim.optics.rig import DeviceCalibration, Rig, look_at  # noqa: E402
from sim.render.fringe_patterns import PhaseShiftSet  # noqa: E402
from sim.render.images import (  # noqa: E402
    CameraResponse, ProjectorResponse, RenderSettings, render_views,
)

TITLE = "Stereo reconstruction of Mitsuba's images (two cameras)"
CAMERA_SIZE = (1280, 1024)
CAMERA_F_PX = 16.0 / 0.0048
PROJECTOR_SIZE = (1280, 800)
PROJECTOR_F_PX = 3200.0
BASELINE_MM = 220.0
DISTANCE_MM = 760.0
FRINGES = (1, 8, 64)
F_NUMBER = 2.8
DECODE = {  # Mitsuba's box filter averages each pixel's area, as a real camera does; ours samples its centre
    "mitsuba": DecodeSettings(min_modulation=0.0, pixel_variance_px2=1.0 / 12.0),
    "ours": DecodeSettings(min_modulation=0.0),
}
R = SPHERE_DIAMETER_MM / 2


def _device(name, size, f_px, centre) -> DeviceCalibration:
    rot, t = look_at(np.asarray(centre, float), np.zeros(3))
    w, h = size
    k = [[f_px, 0.0, (w - 1) / 2], [0.0, f_px, (h - 1) / 2], [0.0, 0.0, 1.0]]
    return DeviceCalibration(name=name, K=k, dist=[0.0] * 5, R=rot, T=t, size=size)


def stereo_rig(scale: float = 1.0) -> Rig:
    cam = [max(16, round(s * scale)) for s in CAMERA_SIZE]
    proj = [max(16, round(s * scale)) for s in PROJECTOR_SIZE]
    cams = [_device(n, tuple(cam), CAMERA_F_PX * scale, [x, 0.0, -DISTANCE_MM])
            for n, x in (("left", -BASELINE_MM / 2), ("right", BASELINE_MM / 2))]
    return Rig(cameras=cams, projector=_device("projector", tuple(proj), PROJECTOR_F_PX * scale,
                                               [0.0, 0.0, -DISTANCE_MM]))


def lens_of(kind: str, samples: int):
    if kind == "pinhole":
        return PinholeLens()
    return AberratedLens(pupil_diameter_mm=16.0 / F_NUMBER, focus_distance_mm=DISTANCE_MM,
                         samples=samples)


def render(rig: Rig, ps: PhaseShiftSet, kind: str, who: str, spp: int, variant: str) -> list[np.ndarray]:
    pats = ps.images(rig.projector.size)
    lens = lens_of(kind, spp)
    if who == "ours":
        res = render_views(bench_scene().trace_geometry(), rig, [lens, lens], pats,
                           RenderSettings(projector=ProjectorResponse(input_bits=None),
                                          camera=CameraResponse(quantize=False)), None)
        return [c.images for c in res.cameras]
    scale = irradiance_scale_at(rig.projector, np.zeros(3))
    return [MitsubaFringeRenderer(bench_scene(), cam, rig.projector, lens, spp, variant,
                                  "stratified", scale).render_all(pats) for cam in rig.cameras]


def judge(points: np.ndarray) -> dict:
    """No rejection: every point within R + 3 mm of the true centre."""
    near = points[np.linalg.norm(points, axis=1) < R + 3.0]
    off = np.abs(np.linalg.norm(near, axis=1) - R)
    fit = fit_sphere(near, reject_sigma=None)
    return dict(points=int(len(near)), diameter_error_mm=fit.diameter - SPHERE_DIAMETER_MM,
                fit_rms_mm=fit.rms, over_20um=float(np.mean(off > 0.020)),
                centre_error_mm=float(np.linalg.norm(fit.centre)))


def run_case(rig, ps, images, who: str) -> dict:
    out = {}
    for mode, camera in (("stereo", None), ("camera 0 + projector", 0), ("camera 1 + projector", 1)):
        t0 = time.perf_counter()
        cloud = scan(images, ps, rig, DECODE[who], camera=camera)
        out[mode] = {**judge(cloud.points), "scan_s": time.perf_counter() - t0}
    return out


def report(rows: dict, spp: int, scale: float, date: str, host: str) -> str:
    rig = stereo_rig(scale)
    L = [f"`benchmarks/stereo_mitsuba.py`: two {rig.cameras[0].width} x "
         f"{rig.cameras[0].height} cameras {BASELINE_MM:g} mm apart at {DISTANCE_MM:g} mm, a "
         f"{rig.projector.width} x {rig.projector.height} projector between them, the sphere and "
         "a plane 100 mm behind it; 4-step phase shift at 1, 8 and 64 fringes. Each camera rendered "
         "by Mitsuba and by ours, scanned by `sim.fpp.decode.scan` (stereo: both directions, local "
         "phase model, consistency checks; and each camera against the projector; Mitsuba's "
         "box-filtered pixels with the pixel-footprint correction 1/12 px^2). No outlier "
         "rejection: every point within R + 3 mm of the true centre counts.", "",
         f"Run of {date} on {host}. Errors in micrometres; 'off' is the share of points more than "
         "20 um from the true surface.", "",
         "| images | mode | points | diameter error | fit RMS | off > 20 um | scan time |",
         "|---|---|---|---|---|---|---|"]
    for case, modes in rows.items():
        who, kind = case.split("-")
        label = (f"{'Mitsuba' if who == 'mitsuba' else 'ours'}, "
                 f"{'pinhole' if kind == 'pinhole' else f'thin lens f/{F_NUMBER:g}'}, {spp} spp")
        for mode, m in modes.items():
            L.append(f"| {label} | {mode} | {m['points']} | {1e3 * m['diameter_error_mm']:+.2f} | "
                     f"{1e3 * m['fit_rms_mm']:.2f} | {100 * m['over_20um']:.2f} % | {m['scan_s']:.1f} s |")
    L += ["", "Notes. Scan time is decoding (12 images per camera), matching and triangulation; the "
          "renders (both cameras, 12 images each) took, on the same machine in the first run: "
          "Mitsuba pinhole 77 s, thin lens 86 s; ours pinhole 1 s, thin lens 22 s (`--save DIR` "
          "keeps them, and a later run only scans). Without the pixel-footprint correction "
          "(`pixel_variance_px2 = 0`) Mitsuba's images measured +2.77 um (stereo) and +2.5 um "
          "(camera-projector, where the model-residual check was not yet applied): the box "
          "filter's averaging of each pixel's area, which ours, sampling pixel centres, does not "
          "have; rendering ours 2 x 2 supersampled and averaged moved its stereo diameter from "
          "+0.74 to +2.26 um. Ours with the thin lens against the projector: +4.8 and -3.9 um, "
          "of opposite sign for the two converging cameras (camera defocus against an in-focus "
          "projector; not investigated further: stereo, matching the two cameras, cancels it)."]
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel (Mitsuba) / thin-lens rays")
    ap.add_argument("--scale", type=float, default=1.0, help="image sizes and focal lengths times this")
    ap.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant")
    ap.add_argument("--cases", default="mitsuba-pinhole,mitsuba-thin,ours-pinhole,ours-thin")
    ap.add_argument("--save", type=Path, help="keep the rendered images here (.npz per case)")
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/stereo_mitsuba.md with this run")
    args = ap.parse_args(argv)
    cases = args.cases.split(",")
    if any(c.startswith("mitsuba") for c in cases) and (why := unavailable_reason(args.variant)):
        print(f"cannot render with Mitsuba: {why}", file=sys.stderr)
        return 2
    rig = stereo_rig(args.scale)
    ps = PhaseShiftSet(periods_px=[rig.projector.width / n for n in FRINGES], steps=4)
    rows = {}
    for case in cases:
        who, kind = case.split("-")
        t0 = time.perf_counter()
        path = args.save / f"{case}.npz" if args.save else None
        if path is not None and path.is_file():
            images = list(np.load(path)["images"])
        else:
            images = render(rig, ps, kind, who, args.spp, args.variant)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                np.savez(path, images=np.stack(images))
        t_render = time.perf_counter() - t0
        rows[case] = run_case(rig, ps, images, who)
        for mode, m in rows[case].items():
            print(f"{case} {mode}: diameter {1e3 * m['diameter_error_mm']:+.2f} um, RMS "
                  f"{1e3 * m['fit_rms_mm']:.2f} um, off {100 * m['over_20um']:.2f} %, "
                  f"{m['points']} points, scan {m['scan_s']:.1f} s (render {t_render:.0f} s)", flush=True)
    text = report(rows, args.spp, args.scale, datetime.date.today().isoformat(), machine())
    print("\n" + text)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    if args.write_results:
        write_results(__file__, TITLE, text, command=command_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
