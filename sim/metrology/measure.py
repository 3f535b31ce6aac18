"""What ``ltc measure`` and ``Scanner.measure`` report of a point cloud: a sphere, a ball
bar, distances to a CAD mesh, or distances to another cloud. Lengths in mm.

Each function returns a JSON-able dict (``kind`` plus the figures) and raises ``ValueError``
or ``OSError`` with a message naming the file or the value that is wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.errors import SimInputError
from sim.metrology.compare import (
    compare_by_pixel,
    compare_clouds,
    distance_colormap_png,
    icp,
    mesh_signed_distance,
)
from sim.metrology.spheres import find_sphere_unknown, find_spheres, measure_ball_bar, sphere_shell


def distance_stats(d: np.ndarray) -> dict:
    """Mean, RMSE, std, min and max of signed distances (mm) and their count."""
    return {"points": int(d.size), "mean_mm": float(d.mean()), "rmse_mm": float(np.sqrt(np.mean(d * d))),
            "std_mm": float(d.std()), "min_mm": float(d.min()), "max_mm": float(d.max())}


class NotCredible(SimInputError):
    """A fit that does not match what the user said was measured (exit 1 in the CLI)."""


def _check_diameter(what: str, fitted: float, nominal: float, tolerance: float) -> None:
    dev = abs(fitted - nominal) / nominal
    if dev > tolerance:
        raise NotCredible(
            f"{what}: the fitted diameter {fitted:.4f} mm differs from the nominal {nominal:g} mm "
            f"by {100 * dev:.1f} % (tolerance {100 * tolerance:g} %); is the nominal diameter right "
            "(not the radius), and is the artefact in the cloud?"
        )


def measure_sphere(points: np.ndarray, diameter_mm: float | None = None,
                   tolerance: float = 0.02) -> tuple[dict, np.ndarray, np.ndarray]:
    """Sphere fit with outlier rejection. With ``diameter_mm`` the sphere of about that size is
    found among other points (RANSAC on the radius), the diameter error is reported, and a fit
    further than ``tolerance`` (relative) from the nominal raises ``NotCredible``; without it
    the best-supported sphere of any size (``find_sphere_unknown``). Returns the report, the
    points near the sphere (m, 3) and their signed radial distances (m,) mm."""
    if diameter_mm is not None:
        if not diameter_mm > 0:
            raise SimInputError(f"nominal diameter must be > 0 mm, got {diameter_mm:g}")
        try:
            fit = find_spheres(points, 1, diameter_mm / 2)[0]
        except SimInputError as exc:
            raise NotCredible(f"no sphere of nominal diameter {diameter_mm:g} mm in the points "
                              f"({exc}); is the nominal diameter right (not the radius)?") from exc
        _check_diameter("sphere", fit.diameter, diameter_mm, tolerance)
    else:
        fit = find_sphere_unknown(points)
    out = {"kind": "sphere", **fit.as_dict()}
    if diameter_mm is not None:
        out["diameter_error_mm"] = fit.diameter - diameter_mm
    near, d = sphere_shell(points, fit)
    return out, near, d


def measure_ballbar(points: np.ndarray, diameter_mm: float, length_mm: float | None = None,
                    tolerance: float = 0.02) -> tuple[dict, np.ndarray, np.ndarray]:
    """The two balls of nominal ``diameter_mm`` and their centre distance (with ``length_mm``
    also the length error); a ball further than ``tolerance`` from the nominal diameter raises
    ``NotCredible``. Returns the report, the points near the balls and their distances (mm)."""
    try:
        bar = measure_ball_bar(points, diameter_mm / 2)
    except SimInputError as exc:
        raise NotCredible(f"no two balls of nominal diameter {diameter_mm:g} mm: {exc}") from exc
    for i, s in enumerate(bar.spheres):
        _check_diameter(f"ball {i + 1}", s.diameter, diameter_mm, tolerance)
    out = {"kind": "ballbar", **bar.as_dict()}
    if length_mm is not None:
        out["length_error_mm"] = bar.length - length_mm
    shells = [sphere_shell(points, s) for s in bar.spheres]
    return out, np.concatenate([p for p, _ in shells]), np.concatenate([d for _, d in shells])


def load_mesh(path: str | Path):
    """A CAD mesh (PLY, STL, OBJ) as a ``trimesh.Trimesh`` with at least one triangle."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(2, "not found", str(path))
    mesh = trimesh.load(path, force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SimInputError(f"{path}: no triangles in the file")
    return mesh


ICP_MAX_ITERATIONS = 40
"""Iterations after which cloud-to-CAD ICP counts as not converged."""
ICP_DIVERGED_FRACTION = 0.02
"""Cloud-to-CAD ICP whose aligned RMSE exceeds this fraction of the CAD part's bounding-box
diagonal is refused: it slid off the part (a cloud of two objects went to a 76 mm mean)."""


def select_object(points: np.ndarray, mesh, margin_mm: float | None = None) -> np.ndarray:
    """Which points (n,) bool lie inside the CAD ``mesh``'s bounding box at its given pose,
    grown by ``margin_mm`` (default: 5 % of its diagonal, at least 2 mm): the object's points,
    not a neighbouring object's or the backdrop's. Raises ``NotCredible`` when fewer than 20
    points are inside (the part is not where its pose puts it)."""
    lo, hi = np.asarray(mesh.bounds, dtype=np.float64)
    if margin_mm is None:
        margin_mm = max(2.0, 0.05 * float(np.linalg.norm(hi - lo)))
    p = np.asarray(points, dtype=np.float64)
    inside = np.all((p >= lo - margin_mm) & (p <= hi + margin_mm), axis=1)
    if inside.sum() < 20:
        raise NotCredible(
            f"only {int(inside.sum())} of {len(p)} points lie inside the CAD part's bounding box "
            f"({lo.round(1).tolist()} .. {hi.round(1).tolist()} mm, +{margin_mm:g} mm); give the "
            "mesh at the part's pose in the cloud's frame (or a rough pose), or --no-select")
    return inside


def measure_against_mesh(points: np.ndarray, mesh_path: str | Path, align: bool = True,
                         select: bool = True) -> tuple[dict, np.ndarray]:
    """Signed distances (mm, positive outside) of the points to a CAD mesh, after ICP
    alignment unless ``align`` is False. ``select``: only the points inside the mesh's
    bounding box at its given pose (``select_object``) take part; the others are another
    object's. ICP that ends after ``ICP_MAX_ITERATIONS`` is reported (``warnings``), and one
    whose aligned RMSE exceeds ``ICP_DIVERGED_FRACTION`` of the part's diagonal is refused
    (``NotCredible``). Returns the report and the distances (n,) of the selected points."""
    import trimesh

    mesh = load_mesh(mesh_path)
    info: dict = {}
    warnings: list[str] = []
    if select:
        keep = select_object(points, mesh)
        info["points_selected"] = int(keep.sum())
        info["points_outside_part"] = int(len(keep) - keep.sum())
        points = np.asarray(points, dtype=np.float64)[keep]
    if align:
        ref, face = trimesh.sample.sample_surface_even(mesh, max(20000, len(points)), seed=0)
        tf, n_it = icp(points, ref, mesh.face_normals[face], max_iterations=ICP_MAX_ITERATIONS)
        points = tf.apply(points)
        converged = n_it < ICP_MAX_ITERATIONS
        info.update(icp_iterations=n_it, icp_converged=converged, R=tf.R.tolist(),
                    t_mm=tf.t.tolist())
        if not converged:
            warnings.append(f"ICP did not converge in {ICP_MAX_ITERATIONS} iterations")
    d = mesh_signed_distance(points, mesh)
    if align:
        diag = float(np.linalg.norm(np.ptp(mesh.bounds, axis=0)))
        rmse = float(np.sqrt(np.mean(d * d)))
        if rmse > ICP_DIVERGED_FRACTION * diag:
            raise NotCredible(
                f"{mesh_path}: ICP did not converge onto the part: RMSE {rmse:.3g} mm after "
                f"{info['icp_iterations']} iterations, over {100 * ICP_DIVERGED_FRACTION:g} % of "
                f"the part's {diag:.1f} mm diagonal; is another object in the cloud (keep the "
                "selection on), and is the mesh near the part's pose?")
    return {"kind": "reference", "reference": str(mesh_path), **distance_stats(d), **info,
            "warnings": warnings}, d


def measure_against_cloud(points: np.ndarray, reference, align: bool = True) -> tuple[dict, np.ndarray]:
    """Signed distances (mm) of the points to a reference ``PointCloud``, after ICP unless
    ``align`` is False. Returns the report and the distances (n,)."""
    res = compare_clouds(points, reference.points, reference.normals, align=align)
    d = res.distances
    icp_info = {k: v for k, v in res.as_dict().items() if k in ("icp_iterations", "R", "t_mm")}
    return {"kind": "against", **distance_stats(d), **icp_info}, d


def measure_by_pixel(cloud, reference, align: bool = True) -> tuple[dict, np.ndarray, np.ndarray]:
    """Two clouds of the same rig compared pixel by pixel (``compare_by_pixel``, the
    reference's Table 4 metric): the signed distance along the reference normal between the
    points of each rig pixel both measured, away from silhouettes; unaligned, and with
    ``align`` also after ICP of the whole clouds (``mean_icp_mm``, ``rmse_icp_mm``). Both
    clouds need the ``camera``, ``u``, ``v`` fields ``ltc scan`` writes. Returns the report,
    the compared points of ``cloud`` and their distances (mm)."""
    for name, c in (("cloud", cloud), ("reference", reference)):
        missing = [k for k in ("camera", "u", "v") if k not in c.fields]
        if missing:
            raise SimInputError(f"{name}: no per-point {', '.join(missing)} fields (scalar_camera, "
                             "scalar_u, scalar_v): compare by pixel needs clouds written by ltc "
                             "scan")
    c = compare_by_pixel(cloud, reference)
    out = {"kind": "by_pixel", **distance_stats(c.distances),
           "unmatched_points": list(c.unmatched)}
    if align:
        tf = compare_clouds(cloud.points, reference.points, reference.normals, align=True).transform
        a = compare_by_pixel(cloud, reference, transform=tf)
        out.update(mean_icp_mm=a.mean, rmse_icp_mm=a.rmse, R=tf.R.tolist(), t_mm=tf.t.tolist())
    return out, np.asarray(cloud.points)[c.index], c.distances


def distance_png(points: np.ndarray, distances: np.ndarray, path: str | Path, title: str) -> dict:
    """Write a colour map of signed distances; returns ``png`` and its limit (mm)."""
    lim = distance_colormap_png(points, distances, path, title=title)
    return {"png": str(path), "png_limit_mm": lim}
