"""``ltc measure CLOUD.ply (--sphere | --ballbar | --reference MESH | --against CLOUD2.ply) [--json]``.

- ``--sphere``: sphere fit with outlier rejection: centre, diameter, fit RMS and peak-to-valley
  (with ``--diameter D`` the sphere of about that size is first found among other points, and
  the diameter error is reported);
- ``--ballbar``: the two balls (nominal ``--diameter``, required) and their centre distance
  (with ``--length L`` also the length error);
- ``--reference MESH``: signed distances to a CAD mesh (positive outside), after ICP alignment
  unless ``--no-align``;
- ``--against CLOUD2.ply``: ICP-align the cloud to CLOUD2, then mean and RMSE of the signed
  distances of corresponding points.

``--png FILE`` writes a colour map of the signed distances (reference and against). Lengths mm.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import trimesh

from sim.metrology.compare import (
    compare_clouds,
    distance_colormap_png,
    icp,
    mesh_signed_distance,
)
from sim.fpp.cloud import read_ply
from sim.metrology.spheres import find_spheres, fit_sphere, measure_ball_bar


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``measure`` subcommand."""
    p = subparsers.add_parser(
        "measure",
        help="sphere, ball-bar, cloud-to-CAD and cloud-to-cloud metrology on a point cloud",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("cloud", type=Path, help="point cloud (PLY)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--sphere", action="store_true",
                      help="fit one sphere to the whole cloud (with --diameter: find the sphere "
                           "of about that size among other points first)")
    what.add_argument("--ballbar", action="store_true", help="find two balls, measure their distance")
    what.add_argument("--reference", type=Path, metavar="MESH", help="CAD mesh (PLY, STL, OBJ)")
    what.add_argument("--against", type=Path, metavar="CLOUD2", help="reference point cloud (PLY)")
    p.add_argument("--diameter", type=float, help="nominal sphere / ball diameter, mm")
    p.add_argument("--length", type=float, help="nominal ball-bar centre distance, mm")
    p.add_argument("--no-align", action="store_true", help="skip the ICP alignment")
    p.add_argument("--png", type=Path, help="write a colour map of the signed distances here")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.set_defaults(func=run)


def _stats(d: np.ndarray) -> dict:
    return {"points": int(d.size), "mean_mm": float(d.mean()), "rmse_mm": float(np.sqrt(np.mean(d * d))),
            "std_mm": float(d.std()), "min_mm": float(d.min()), "max_mm": float(d.max())}


def _to_mesh(points: np.ndarray, mesh: trimesh.Trimesh, align: bool) -> tuple[np.ndarray, dict]:
    info: dict = {}
    if align:
        ref, face = trimesh.sample.sample_surface_even(mesh, max(20000, len(points)), seed=0)
        tf, n_it = icp(points, ref, mesh.face_normals[face])
        points = tf.apply(points)
        info = {"icp_iterations": n_it, "R": tf.R.tolist(), "t_mm": tf.t.tolist()}
    return mesh_signed_distance(points, mesh), info


def measure(args: argparse.Namespace) -> dict:
    """The measurement asked for, as a JSON-able dict (raises ValueError / OSError on bad input)."""
    cloud = read_ply(args.cloud)
    pts = cloud.points
    out: dict = {"cloud": str(args.cloud)}
    if args.sphere:
        if args.diameter is not None:
            fit = find_spheres(pts, 1, args.diameter / 2)[0]
        else:
            fit = fit_sphere(pts)
        out.update(kind="sphere", **fit.as_dict())
        if args.diameter is not None:
            out["diameter_error_mm"] = fit.diameter - args.diameter
    elif args.ballbar:
        if args.diameter is None:
            raise ValueError("--ballbar needs --diameter (the nominal ball diameter, mm)")
        bar = measure_ball_bar(pts, args.diameter / 2)
        out.update(kind="ballbar", **bar.as_dict())
        if args.length is not None:
            out["length_error_mm"] = bar.length - args.length
    elif args.reference is not None:
        if not args.reference.is_file():
            raise FileNotFoundError(f"--reference {args.reference}: not found")
        mesh = trimesh.load(args.reference, force="mesh")
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise ValueError(f"--reference {args.reference}: no triangles in the file")
        d, info = _to_mesh(pts, mesh, not args.no_align)
        out.update(kind="reference", reference=str(args.reference), **_stats(d), **info)
    else:
        ref = read_ply(args.against)
        res = compare_clouds(pts, ref.points, ref.normals, align=not args.no_align)
        d = res.distances
        icp_info = {k: v for k, v in res.as_dict().items() if k in ("icp_iterations", "R", "t_mm")}
        out.update(kind="against", against=str(args.against), **_stats(d), **icp_info)
    if args.png is not None and out["kind"] in ("reference", "against"):
        lim = distance_colormap_png(pts, d, args.png, title=f"signed distance, {out['kind']}")
        out.update(png=str(args.png), png_limit_mm=lim)
    return out


def _text(r: dict) -> str:
    if r["kind"] == "sphere":
        s = (f"sphere: diameter {r['diameter_mm']:.4f} mm, fit RMS {1e3 * r['fit_rms_mm']:.2f} um, "
             f"PV {1e3 * r['fit_pv_mm']:.2f} um, {r['inliers']}/{r['points']} points")
        return s + (f", error {1e3 * r['diameter_error_mm']:+.2f} um" if "diameter_error_mm" in r else "")
    if r["kind"] == "ballbar":
        s = f"ball bar: length {r['length_mm']:.4f} mm"
        return s + (f", error {1e3 * r['length_error_mm']:+.2f} um" if "length_error_mm" in r else "")
    return (f"{r['kind']}: {r['points']} points, mean {1e3 * r['mean_mm']:+.2f} um, "
            f"RMSE {1e3 * r['rmse_mm']:.2f} um, range [{r['min_mm']:.4f}, {r['max_mm']:.4f}] mm")


def run(args: argparse.Namespace) -> int:
    """Measure and print; exit code 2 for bad input."""
    try:
        result = measure(args)
    except (ValueError, OSError) as exc:
        print(f"ltc measure: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(result) if args.json else _text(result))
    return 0
