"""Reconstruction benchmark: fringe images of the sphere rendered by an independent
renderer (Mitsuba 3), decoded and triangulated by our scanner pipeline, and the sphere measured.

Same scene as ``render_vs_mitsuba.py`` (``_bench_scene.py``): the 50.8007 mm sphere at 760 mm, a
plane behind it, one 2048 x 1088 camera and one projector; 12 images (4-step phase shift at
periods 1920, 240, 30 px). The images go through ``sim.fpp.decode.scan`` (``sim.fpp.phase``:
wrapped phase, hierarchical unwrapping; ``sim.fpp.stereo.camera_projector_cloud``: camera against
projector), the sphere is found with ``sim.metrology.spheres.find_spheres`` (RANSAC on the nominal
radius, then the least-squares fit with outlier rejection) and compared with the truth.
Our own renderer's images of the same scene go through the same pipeline for reference.

Mitsuba's radiance needs no conversion here: its distance fall-off multiplies all shifts of a
pixel alike, and the phase ignores it.

Run::

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        .venv/bin/python benchmarks/reconstruct_mitsuba.py [--images DIR] [--thin] [--write-results]

``--images DIR`` reuses the images that ``render_vs_mitsuba.py --save DIR`` kept.
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

from _bench_scene import (  # noqa: E402
    SPHERE_DIAMETER_MM, BenchConfig, bench_lens, bench_patterns, bench_rig, bench_scene, machine,
)
from _mitsuba_scene import MitsubaFringeRenderer, irradiance_scale_at, unavailable_reason  # noqa: E402
from _results import command_line, write_results  # noqa: E402

from sim.metrology.spheres import find_spheres  # noqa: E402
from sim.fpp.decode import DecodeSettings, scan  # noqa: E402
from sim.render.images import (  # noqa: E402
    CameraResponse, ProjectorResponse, project_patterns, render_camera,
)

TITLE = "Reconstruction of Mitsuba's images (one camera against the projector)"
SPHERE_CENTRE_MM = np.zeros(3)
# radiance is in [0, 1]-ish units, not DN: keep pixels by relative modulation only
DECODE = DecodeSettings(min_modulation=0.0, min_modulation_fraction=0.05)


def measure_sphere(images: np.ndarray, cfg: BenchConfig) -> dict:
    """Decode, triangulate (camera 0 against the projector) and fit the sphere; errors in mm."""
    rig = bench_rig(cfg)
    ps, _ = bench_patterns(rig)
    cloud = scan([np.asarray(images, dtype=np.float64)], ps, rig, DECODE, camera=0)
    fit = find_spheres(cloud.points, 1, SPHERE_DIAMETER_MM / 2, inlier_mm=0.2)[0]
    return dict(points=int(len(cloud.points)), sphere_points=int(fit.inliers.size),
                inliers=int(fit.inliers.sum()), diameter_mm=fit.diameter,
                diameter_error_mm=fit.diameter - SPHERE_DIAMETER_MM,
                centre_error_mm=float(np.linalg.norm(fit.centre - SPHERE_CENTRE_MM)),
                fit_rms_mm=fit.rms, fit_pv_mm=fit.pv)


def render_images(cfg: BenchConfig, lens_kind: str, who: str) -> np.ndarray:
    """The 12 images (12, H, W) of the bench scene from ``who`` ('ours' or 'mitsuba')."""
    rig = bench_rig(cfg)
    _, pats = bench_patterns(rig)
    lens = bench_lens(lens_kind, cfg)
    if who == "ours":
        cols = project_patterns(pats, ProjectorResponse(input_bits=None))
        return render_camera(bench_scene().trace_geometry(), rig, 0, lens, cols,
                             CameraResponse(quantize=False), None).radiance
    spp = cfg.pinhole_spp if lens_kind == "pinhole" else cfg.thin_samples
    r = MitsubaFringeRenderer(bench_scene(), rig.cameras[0], rig.projector, lens, spp, cfg.variant,
                              cfg.sampler, irradiance_scale_at(rig.projector, SPHERE_CENTRE_MM))
    return r.render_all(pats)


def load_or_render(cfg: BenchConfig, images_dir: Path | None, case: str) -> np.ndarray:
    """Images of ``case`` (``ours-pinhole``, ``mitsuba-thin``, ...) from ``images_dir`` when it
    holds them, else rendered now."""
    if images_dir is not None:
        path = images_dir / f"{case}.npz"
        if not path.is_file():
            raise FileNotFoundError(f"--images {images_dir}: {path.name} not found; run "
                                    f"render_vs_mitsuba.py --save {images_dir} first")
        return np.load(path)["radiance"]
    who, lens_kind = case.split("-")[:2]
    return render_images(cfg, lens_kind, who)


def report_markdown(rows: dict, cfg: BenchConfig, date: str, host: str) -> str:
    L = ["`benchmarks/reconstruct_mitsuba.py`: the 12 images of the render benchmark's scene (`_bench_scene.py`), rendered "
         "by Mitsuba (and, for reference, by ours), go through our scanner pipeline "
         "(`sim.fpp.decode.scan`: `sim.fpp.phase` wrapped phase and hierarchical unwrapping, "
         "`sim.fpp.stereo.camera_projector_cloud` triangulation of the camera against the projector); "
         "`sim.metrology.spheres.find_spheres` finds the sphere (RANSAC on the nominal radius, least-squares "
         "fit with 3-sigma outlier rejection). `--images DIR` reuses `render_vs_mitsuba.py --save DIR`.",
         "",
         f"Run of {date} on {host}. Nominal diameter {SPHERE_DIAMETER_MM} mm, centre at the world "
         "origin; errors in micrometres.", "",
         "| images | points | sphere inliers | diameter error | centre error | fit RMS | fit PV |",
         "|---|---|---|---|---|---|---|"]
    labels = {"mitsuba-pinhole": f"Mitsuba, pinhole, {cfg.pinhole_spp} spp",
              "mitsuba-thin": f"Mitsuba, thin lens f/{cfg.f_number:g}, {cfg.thin_samples} spp",
              "ours-pinhole": "ours, pinhole", "ours-thin": f"ours, thin lens f/{cfg.f_number:g}, "
                                                           f"{cfg.thin_samples} rays"}
    for case, m in rows.items():
        L.append(f"| {labels[case]} | {m['points']} | {m['inliers']} of {m['sphere_points']} | "
                 f"{1e3 * m['diameter_error_mm']:+.2f} | {1e3 * m['centre_error_mm']:.2f} | "
                 f"{1e3 * m['fit_rms_mm']:.2f} | {1e3 * m['fit_pv_mm']:.1f} |")
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--images", type=Path, help="folder of render_vs_mitsuba.py --save (else render now)")
    ap.add_argument("--thin", action="store_true", help="also the 64-sample thin lens")
    ap.add_argument("--scale", type=float, default=1.0, help="image sizes times this (as render_vs_mitsuba.py)")
    ap.add_argument("--pinhole-spp", type=int, default=16, help="Mitsuba pinhole samples per pixel")
    ap.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant")
    ap.add_argument("--json", type=Path, help="write the results as JSON")
    ap.add_argument("--write-results", action="store_true",
                    help="rewrite benchmarks/results/reconstruct_mitsuba.md with this run")
    args = ap.parse_args(argv)
    cfg = BenchConfig(scale=args.scale, pinhole_spp=args.pinhole_spp, variant=args.variant)
    if args.images is None and (why := unavailable_reason(cfg.variant)):
        print(f"cannot render with Mitsuba: {why}", file=sys.stderr)
        return 2
    cases = ["mitsuba-pinhole", "ours-pinhole"] + (["mitsuba-thin", "ours-thin"] if args.thin else [])
    rows = {}
    for case in cases:
        t0 = time.perf_counter()
        images = load_or_render(cfg, args.images, case)
        rows[case] = measure_sphere(images, cfg)
        m = rows[case]
        print(f"{case}: diameter error {1e3 * m['diameter_error_mm']:+.2f} um, fit RMS "
              f"{1e3 * m['fit_rms_mm']:.2f} um ({time.perf_counter() - t0:.0f} s)", flush=True)
    text = report_markdown(rows, cfg, datetime.date.today().isoformat(), machine())
    print("\n" + text)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    if args.write_results:
        write_results(__file__, TITLE, text, command=command_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
