"""The lens derivation's result (``LensResult``: geometry, grid, nodes, the lens or its file)
and its summary."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.optics.lens_file import read_lens_nodes
from sim.optics.measured_lens import MeasuredLens
from station.lens import aperture as ap
from station.lens.geometry import LensFitConfig, LensGeometry
from station.lens.jobs import ApertureSet
from station.lens.rays import FLAG_BAD_FIT, FLAG_FEW_DEPTHS, FLAG_OUTLIER, PrincipalRays

# pixels per block of the summary's residual lengths: their order (depth-major per block)
# fixes the mean and std reported in the lens file to the last bit
RESIDUAL_PIXELS = 1 << 18


def node_positions(size: int, step: int) -> np.ndarray:
    """Node coordinates along one axis: every ``step``-th pixel and the last one."""
    a = np.arange(0, size, step)
    return a if a[-1] == size - 1 else np.append(a, size - 1)


@dataclass
class LensResult:
    """The derivation's result: geometry, grid, nodes, fused distributions, the lens.

    Derived to a file (``derive_lens(..., out=path)``): ``lens`` and ``apertures`` are None
    (nothing per node is held in memory) and ``lens_path`` is the file written.
    """

    config: LensFitConfig
    geometry: LensGeometry
    grid: ap.ApertureGrid
    node_u: np.ndarray
    node_v: np.ndarray
    apertures: ApertureSet | None
    lens: MeasuredLens | None
    filled_nodes: int
    figures: list[Path] = field(default_factory=list)
    lens_path: Path | None = None

    def samples_at(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Aperture samples x, y mm and weights (n, K) of pixels uv (n, 2): the lens's own
        interpolation in memory; from the written file, the nearest node's."""
        if self.lens is not None:
            return self.lens.samples_at(uv)
        if self.lens_path is None:
            raise ValueError("LensResult: neither a lens nor a lens file")
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        i = np.abs(uv[:, 0, None] - self.node_u[None]).argmin(axis=1)
        j = np.abs(uv[:, 1, None] - self.node_v[None]).argmin(axis=1)
        return read_lens_nodes(self.lens_path, j * len(self.node_u) + i)

    def summary(self) -> LensSummary:
        """What was measured (``LensSummary``; ``.to_json()`` for the JSON fields)."""
        g = self.geometry
        r = g.rays
        res_mean, res_std, res_count = _residual_stats(r)
        fl = r.flags
        rotation = None
        if g.centre_pinhole is not None:
            rotation = float(np.degrees(np.arccos(
                np.clip((np.trace(g.rotation) - 1) / 2, -1, 1))))
        return LensSummary(
            optical_centre_mm=g.centre.position.tolist(),
            optical_centre_std_mm=g.centre.std.tolist(),
            optical_centre_method=g.centre.method,
            principal_ray_intersection_mm=g.centre_rays.position.tolist(),
            principal_ray_intersection_std_mm=g.centre_rays.std.tolist(),
            focus_plane_z_mm=g.focus_plane_z_mm,
            focus_distance_mm=g.focus_distance_mm,
            focus_distance_fitted_mm=g.focus_distance_fit_mm,
            focus_distance_config_mm=g.focus_distance_config_mm,
            focus_fit_spread_mm=None if g.focus is None else g.focus.spread_mm,
            ray_residual_mean_mm=res_mean,
            ray_residual_std_mm=res_std,
            ray_residual_count=res_count,
            pixels=len(fl),
            pixels_usable=int(r.usable.sum()),
            pixels_few_depths=int(((fl & FLAG_FEW_DEPTHS) > 0).sum()),
            pixels_outlier_removed=int(((fl & FLAG_OUTLIER) > 0).sum()),
            pixels_bad_fit=int(((fl & FLAG_BAD_FIT) > 0).sum()),
            depths_mm=g.centroids.depths_mm.tolist(),
            samples=self.config.samples,
            nodes=[len(self.node_v), len(self.node_u)],
            nodes_filled=self.filled_nodes,
            aperture_half_width_mm=self.grid.half_width_mm,
            aperture_cells=self.grid.cells,
            camera_matrix_known=g.camera_matrix is not None,
            notes=list(g.notes),
            camera_rotation_deg=rotation,
        )


@dataclass(frozen=True)
class LensSummary:
    """What the lens derivation measured (``ltc lens --json``, the lens file's
    ``summary_at_fit``, docs/formats.md). Positions in the station frame, mm; ``*_std_mm``
    standard errors, mm; None where not measured."""

    optical_centre_mm: list[float]
    optical_centre_std_mm: list[float]
    optical_centre_method: str
    principal_ray_intersection_mm: list[float]
    principal_ray_intersection_std_mm: list[float]
    focus_plane_z_mm: float
    focus_distance_mm: float
    focus_distance_fitted_mm: float | None
    focus_distance_config_mm: float | None
    focus_fit_spread_mm: float | None
    ray_residual_mean_mm: float | None
    ray_residual_std_mm: float | None
    ray_residual_count: int
    pixels: int
    pixels_usable: int
    pixels_few_depths: int
    pixels_outlier_removed: int
    pixels_bad_fit: int
    depths_mm: list[float]
    samples: int
    nodes: list[int]  # (rows, columns)
    nodes_filled: int
    aperture_half_width_mm: float
    aperture_cells: int
    camera_matrix_known: bool
    notes: list[str]
    camera_rotation_deg: float | None = None  # with the pinhole centre only

    def to_json(self) -> dict[str, Any]:
        """The JSON fields (``camera_rotation_deg`` only where measured)."""
        out = asdict(self)
        if out["camera_rotation_deg"] is None:
            del out["camera_rotation_deg"]
        return out


def _residual_stats(rays: PrincipalRays) -> tuple[float | None, float | None, int]:
    """Mean, std (None without any) and count of the usable rays' residual lengths (float32)
    of the points in their fits, in pixel blocks: the values numpy's float64 ``mean`` and
    ``std`` give of them in this order, with one float64 array of the lengths (no (D, N)
    temporaries, no float32 copy beside the deviations): the float32 lengths are packed into
    its first half, then turned into the float64 squared deviations in place, from the end."""
    n = len(rays.flags)
    usable = rays.usable
    blocks = [slice(a0, min(n, a0 + RESIDUAL_PIXELS)) for a0 in range(0, n, RESIDUAL_PIXELS)]

    def keep(sl: slice) -> np.ndarray:
        res = rays.residual_mm[:, sl]
        return rays.used[:, sl] & usable[None, sl] & np.isfinite(res)

    count = sum(int(keep(sl).sum()) for sl in blocks)
    if not count:
        return None, None, 0
    buf = np.empty(count)
    res = buf.view(np.float32)[:count]
    at = 0
    for sl in blocks:
        got = rays.residual_mm[:, sl][keep(sl)]
        res[at:at + len(got)] = got
        at += len(got)
    mean = float(res.mean(dtype=np.float64))
    # numpy's std: the float64 mean kept as a (1,) array, deviations squared, summed, / n
    m = np.true_divide(np.add.reduce(res, dtype=np.float64, keepdims=True), count)
    step = 1 << 16
    for b in range(count, 0, -step):  # buf[a:b] overwrites res[2a:2b]: read already
        a = max(0, b - step)
        buf[a:b] = res[a:b].copy() - m
    del res
    np.multiply(buf, buf, out=buf)
    var = np.add.reduce(buf, dtype=np.float64)
    return mean, float(np.sqrt(np.float64(var / count))), count
