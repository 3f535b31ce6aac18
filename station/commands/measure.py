"""Sphere, ball-bar, cloud-to-CAD and cloud-to-cloud metrology on a point cloud.

--sphere: sphere fit with outlier rejection: centre, diameter, fit RMS and peak-to-valley. With
--diameter D the sphere of about that size is found among other points and the diameter error
reported; a fit more than --tolerance (default 2 %) from D is refused (exit 1). Without it, the
best-supported sphere of any size (RANSAC with no radius prior). --ballbar: the two balls
(nominal --diameter, required, same refusal) and their centre distance (with --length L also
the length error). --reference MESH: signed distances to a CAD mesh (positive outside), after
ICP alignment unless --no-align. --against CLOUD2.ply: ICP-align the cloud to CLOUD2, then
mean and RMSE of the signed distances of corresponding points; with --by-pixel the points of
the same rig pixel (the reference's Table 4 metric), unaligned and after ICP. --reference keeps
only the points inside the mesh's bounding box at its given pose (--no-select: all), and
refuses an ICP that slid off the part. --png FILE writes a colour map
of the signed distances (to the fitted spheres, the mesh or the reference cloud). Lengths in
mm.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from station.commands import positive_float
from station.errors import UsageError
from station.outputs import PNG_FILE, check_output

OPTIONS = {"json": None}


def arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("cloud", type=Path, help="point cloud (PLY)")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--sphere", action="store_true",
                      help="fit one sphere to the whole cloud (with --diameter: find the sphere "
                           "of about that size among other points first)")
    what.add_argument("--ballbar", action="store_true", help="find two balls, measure their distance")
    what.add_argument("--reference", type=Path, metavar="MESH", help="CAD mesh (PLY, STL, OBJ)")
    what.add_argument("--against", type=Path, metavar="CLOUD2", help="reference point cloud (PLY)")
    p.add_argument("--diameter", type=positive_float, help="nominal sphere / ball diameter, mm")
    p.add_argument("--length", type=positive_float, help="nominal ball-bar centre distance, mm")
    p.add_argument("--tolerance", type=positive_float, default=2.0, metavar="PERCENT",
                   help="refuse sphere / ball fits further than this from --diameter (default 2)")
    p.add_argument("--no-align", action="store_true", help="skip the ICP alignment")
    p.add_argument("--no-select", action="store_true",
                   help="--reference: align every point, not only those inside the mesh's "
                        "bounding box at its given pose (the part's, not another object's)")
    p.add_argument("--by-pixel", action="store_true",
                   help="--against: compare the points of the same rig pixel (both clouds from "
                        "ltc scan with one rig; the reference's Table 4 metric), unaligned and, "
                        "unless --no-align, after ICP")
    p.add_argument("--png", type=Path,
                   help="write a colour map of the signed distances here (to the fitted "
                        "sphere(s), the mesh or the reference cloud)")
    p.add_argument("--force", action="store_true", help="overwrite --png if it exists")


def run(args: argparse.Namespace) -> dict:
    """The measurement asked for, as a JSON-able dict (raises ValueError / OSError on bad input)."""
    from sim.fpp.cloud import read_ply
    from sim.metrology import measure as m

    if args.by_pixel and args.against is None:
        raise UsageError("--by-pixel compares with --against CLOUD2")
    if args.ballbar and args.diameter is None:
        raise UsageError("--ballbar needs --diameter (the nominal ball diameter, mm)")
    if args.png is not None:
        check_output(args.png, args.force, "--png", kind=PNG_FILE,
                     inputs=[args.cloud] + [p for p in (args.reference, args.against) if p])
    import numpy as np

    pts = read_ply(args.cloud).points
    dropped = int((~np.isfinite(pts).all(axis=1)).sum())  # the fits skip them
    tol = args.tolerance / 100.0
    if args.sphere:
        out, pts, d = m.measure_sphere(pts, args.diameter, tol)
    elif args.ballbar:
        out, pts, d = m.measure_ballbar(pts, args.diameter, args.length, tol)
    elif args.reference is not None:
        out, d = m.measure_against_mesh(pts, args.reference, not args.no_align,
                                        select=not args.no_select)
        if out["warnings"]:
            import sys

            for w in out["warnings"]:
                print(f"ltc measure: warning: {w}", file=sys.stderr)
    elif args.by_pixel:
        out, pts, d = m.measure_by_pixel(read_ply(args.cloud), read_ply(args.against),
                                         not args.no_align)
        out["against"] = str(args.against)
    else:
        out, d = m.measure_against_cloud(pts, read_ply(args.against), not args.no_align)
        out["against"] = str(args.against)
    out = {"cloud": str(args.cloud), "non_finite_dropped": dropped, **out}
    if args.png is not None:
        from station.outputs import staged

        with staged(args.png, PNG_FILE, always=True) as target:
            out.update(m.distance_png(pts, d, target, f"signed distance, {out['kind']}"))
        out["png"] = str(args.png)
    return out


def text(r: dict) -> str:
    dropped = r.get("non_finite_dropped", 0)
    note = (f"\n(dropped {dropped} point{'s' if dropped != 1 else ''} of {r['cloud']} with "
            "non-finite coordinates)") if dropped else ""
    return _text(r) + note


def _text(r: dict) -> str:
    if r["kind"] == "sphere":
        c = r["centre_mm"]
        s = (f"sphere: diameter {r['diameter_mm']:.4f} mm, fit RMS {1e3 * r['fit_rms_mm']:.2f} um, "
             f"PV {1e3 * r['fit_pv_mm']:.2f} um, {r['inliers']}/{r['points']} points")
        s += f", centre ({c[0]:.4f}, {c[1]:.4f}, {c[2]:.4f}) mm"
        return s + (f", error {1e3 * r['diameter_error_mm']:+.2f} um" if "diameter_error_mm" in r else "")
    if r["kind"] == "ballbar":
        s = f"ball bar: length {r['length_mm']:.4f} mm, centres " + ", ".join(
            "({:.4f}, {:.4f}, {:.4f}) mm".format(*b["centre_mm"]) for b in r["spheres"])
        return s + (f", error {1e3 * r['length_error_mm']:+.2f} um" if "length_error_mm" in r else "")
    if r["kind"] == "by_pixel" and "mean_icp_mm" in r:
        return (f"by pixel: {r['points']} pixels, mean {1e3 * r['mean_mm']:+.2f} um, RMSE "
                f"{1e3 * r['rmse_mm']:.2f} um; after ICP mean {1e3 * r['mean_icp_mm']:+.2f} um, "
                f"RMSE {1e3 * r['rmse_icp_mm']:.2f} um")
    return (f"{r['kind']}: {r['points']} points, mean {1e3 * r['mean_mm']:+.2f} um, "
            f"RMSE {1e3 * r['rmse_mm']:.2f} um, range [{r['min_mm']:.4f}, {r['max_mm']:.4f}] mm")

