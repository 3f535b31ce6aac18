"""One position scanned by every scanner (``scan_position``) and its numbers
(``compare_position``): sizes, distances to the CAD mesh, virtual clouds against the real one."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sim.errors import SimError
from station.errors import StationError
from station.experiment.bench import RENDER
from station.experiment.config import MODELS, ExperimentConfig
from station.experiment.objects import Position, scene_of
from station.experiment.rows import DistanceStats, ModelNumbers, PositionRow
from station.experiment.sizes import check_coverage, shared_size_mm, size_error_mm, size_fit

if TYPE_CHECKING:
    from trimesh import Trimesh

    from sim.fpp.cloud import PointCloud
    from sim.optics.lens import LensModel
    from sim.optics.rig import Rig

Maps = dict[str, tuple[np.ndarray, np.ndarray]]  # per map: points (n, 3) mm, distances (n,) mm


def world_cad_mesh(mesh: Trimesh, pos: Position) -> Trimesh:
    """The CAD mesh at the position's pose (world frame)."""
    m = mesh.copy()
    m.apply_translation(pos.centre_mm)
    return m


@dataclass
class Scan:
    """One scanner's result at one position: cloud (``PointCloud``, mm), camera 0's images,
    seconds."""

    cloud: PointCloud
    images: np.ndarray
    render_s: float


def scan_position(pos: Position, cfg: ExperimentConfig, rig: Rig,
                  lenses: dict[str, tuple[LensModel, ...]],
                  cad_path: Path | None) -> dict[str, Scan]:
    """Render and reconstruct the position with every scanner (one traced geometry)."""
    from sim.render.fringe_patterns import PhaseShiftSet
    from sim.render.images import RenderSettings
    from sim.scanner import Scanner

    patterns = PhaseShiftSet(periods_px=list(cfg.periods_px), steps=4, direction="u")
    base = Scanner(rig, lenses["real"], patterns, scene_of(pos, cfg, cad_path),
                   RenderSettings.model_validate(RENDER), where=f"position {pos.name}")
    out: dict[str, Scan] = {}
    for name in MODELS:
        s = base.with_lenses(lenses[name])
        t0 = time.perf_counter()
        images = s.render()
        dt = time.perf_counter() - t0
        try:
            cloud = s.scan(images)
        except SimError as exc:  # name where: a long run's one line must say which scan
            raise StationError(f"position {pos.name} ({pos.kind}, {pos.defocus} defocus), "
                               f"scanner {name}: {exc}") from exc
        out[name] = Scan(cloud, images.cameras[0].images, dt)
    return out


def compare_position(pos: Position, cfg: ExperimentConfig, rig: Rig, scans: dict[str, Scan],
                     cad_path: Path | None, cad_mesh: Trimesh | None) -> tuple[PositionRow, Maps]:
    """The numbers of one position: per model the size error (sphere, ball bar) or the
    distances to the CAD mesh, and each virtual cloud against the real one, unaligned and
    after ICP (mm). Cloud against cloud is by pixel correspondence
    (``sim.metrology.compare.compare_by_pixel``: the same rig pixel in both clouds, away from
    the silhouettes; ICP aligns the whole clouds); ``*_nn_mm`` are the nearest-surface
    distances of every point (``compare_clouds``), which sparse clouds' differing rims bias."""
    from sim.metrology.compare import compare_by_pixel, compare_clouds, mesh_signed_distance
    from sim.metrology.measure import distance_stats

    scene = scene_of(pos, cfg, cad_path)
    real = scans["real"].cloud
    models: dict[str, ModelNumbers] = {}
    maps: Maps = {}
    world_mesh = None
    if pos.kind == "cad":
        if cad_mesh is None:
            raise StationError(f"position {pos.name}: a CAD position needs the CAD mesh")
        world_mesh = world_cad_mesh(cad_mesh, pos)
    real_size = None
    if pos.kind != "cad":
        check_coverage(scans, pos, scene, rig)
        real_size = size_fit(real, pos, scene)
    for name in MODELS:
        cloud = scans[name].cloud
        pts = cloud.points
        m: dict[str, Any] = {"points": int(len(pts)), "render_s": scans[name].render_s}
        if world_mesh is not None:
            d = mesh_signed_distance(pts, world_mesh)
            m["cad"] = DistanceStats(**distance_stats(d))
            maps[f"cad_{name}"] = (pts, d)
        elif real_size is not None:
            own = real_size if name == "real" else size_fit(cloud, pos, scene)
            m.update(size_error_mm(own))
            if name != "real":
                m.update(shared_size_mm(cloud, own, real, real_size, pos))
        if name != "real":
            nn = compare_clouds(pts, real.points, align=False)
            tf = compare_clouds(pts, real.points, align=True).transform
            c = compare_by_pixel(cloud, real)
            a = compare_by_pixel(cloud, real, transform=tf)
            m.update(mean_mm=c.mean, rmse_mm=c.rmse, mean_icp_mm=a.mean, rmse_icp_mm=a.rmse,
                     mean_nn_mm=nn.mean, rmse_nn_mm=nn.rmse, pixels_compared=int(c.index.size))
            maps[name] = (pts[c.index], c.distances)
        models[name] = ModelNumbers(**m)
    row = PositionRow(name=pos.name, kind=pos.kind, defocus=pos.defocus,
                      defocus_mm=round(pos.depth_mm - cfg.focus_distance_mm, 3),
                      centre_mm=list(pos.centre_mm), models=models)
    return row, maps
