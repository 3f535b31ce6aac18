"""What ``ltc measure`` and ``Scanner.measure`` report of a point cloud: a sphere, a ball
bar, distances to a CAD mesh, or distances to another cloud. Lengths in mm.

Each function returns a JSON-able dict (``kind`` plus the figures) and raises ``ValueError``
or ``OSError`` with a message naming the file or the value that is wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.errors import SimInputError
from sim.metrology.compare import compare_clouds, distance_colormap_png, icp, mesh_signed_distance
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


def measure_against_mesh(points: np.ndarray, mesh_path: str | Path, align: bool = True) -> tuple[dict, np.ndarray]:
    """Signed distances (mm, positive outside) of the points to a CAD mesh, after ICP
    alignment unless ``align`` is False. Returns the report and the distances (n,)."""
    import trimesh

    mesh = load_mesh(mesh_path)
    info: dict = {}
    if align:
        ref, face = trimesh.sample.sample_surface_even(mesh, max(20000, len(points)), seed=0)
        tf, n_it = icp(points, ref, mesh.face_normals[face])
        points = tf.apply(points)
        info = {"icp_iterations": n_it, "R": tf.R.tolist(), "t_mm": tf.t.tolist()}
    d = mesh_signed_distance(points, mesh)
    return {"kind": "reference", "reference": str(mesh_path), **distance_stats(d), **info}, d


def measure_against_cloud(points: np.ndarray, reference, align: bool = True) -> tuple[dict, np.ndarray]:
    """Signed distances (mm) of the points to a reference ``PointCloud``, after ICP unless
    ``align`` is False. Returns the report and the distances (n,)."""
    res = compare_clouds(points, reference.points, reference.normals, align=align)
    d = res.distances
    icp_info = {k: v for k, v in res.as_dict().items() if k in ("icp_iterations", "R", "t_mm")}
    return {"kind": "against", **distance_stats(d), **icp_info}, d


def distance_png(points: np.ndarray, distances: np.ndarray, path: str | Path, title: str) -> dict:
    """Write a colour map of signed distances; returns ``png`` and its limit (mm)."""
    lim = distance_colormap_png(points, distances, path, title=title)
    return {"png": str(path), "png_limit_mm": lim}
