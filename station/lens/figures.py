"""Figures of a lens derivation (matplotlib, Agg, no pyplot state), one PNG each:

* ``ltc_depths.png``: the LTC window of chosen pixels (centre, edge, corner) at every depth,
  with the centroid and the fitted principal ray marked.
* ``principal_rays.png``: principal rays (every n-th pixel) in x-z and y-z with their
  centroids, the optical centre and the principal-ray intersection.
* ``aperture.png``: the LTC at the optical centre of the same pixels (fused aperture
  distribution, mm) with the K samples on top (area ~ weight).
* ``ray_residuals.png``: per-pixel RMS principal-ray residual (mm), flagged pixels marked.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from sim.storage.durable import durable_figure
from station.lens.centroids import centroid_rows
from station.lens.derive import LensResult, aperture_set
from station.lens.rays import UNUSABLE
from station.ltc.store import LtcVolume

DPI = 110
RAYS_SHOWN = 60  # principal rays drawn at most


def chosen_pixels(camera_size: tuple[int, int]) -> dict[str, tuple[int, int]]:
    """Pixels (u, v) a metrologist looks at first: centre, middle of the right edge, corner."""
    w, h = camera_size
    return {"centre": (w // 2, h // 2), "edge": (w - 1, h // 2), "corner": (w - 1, h - 1)}


def _flat(uv: tuple[int, int], w: int) -> int:
    return uv[1] * w + uv[0]


def _centroids_lcd_px(volume: LtcVolume, pixels: np.ndarray) -> np.ndarray:
    """LTC centroids (D, n, 2) LCD px of flat pixels (n,), computed again from the store (a
    ``LensGeometry`` keeps none: a full-size sensor's would cost 48 B per pixel)."""
    w = volume.camera_size[0]
    out = np.empty((len(volume.depths_mm), len(pixels), 2))
    for k, p in enumerate(np.asarray(pixels, dtype=np.int64).tolist()):
        v, u = divmod(p, w)
        for i in range(len(volume.depths_mm)):
            out[i, k] = centroid_rows(volume, i, v, v + 1, u, u + 1)["xy"][0, 0]
    return out


def ltc_depths_figure(volume: LtcVolume, result: LensResult, path: Path) -> Path:
    """LTC windows of the chosen pixels at every depth."""
    g = result.geometry
    w = volume.camera_size[0]
    pix = chosen_pixels(volume.camera_size)
    depths = g.centroids.depths_mm
    fig = Figure(figsize=(2.0 * len(depths) + 0.5, 2.2 * len(pix)), dpi=DPI)
    axes = fig.subplots(len(pix), len(depths), squeeze=False)
    pitch = volume.pitch_mm
    cen = _centroids_lcd_px(volume, np.array([_flat(uv, w) for uv in pix.values()]))
    for r, (name, (u, v)) in enumerate(pix.items()):
        ltc, origin, _, _ = volume.rows(v, v + 1)
        ray = g.rays
        for i, z in enumerate(depths):
            ax = axes[r, i]
            win = ltc[i, 0, u]
            o = origin[i, 0, u]
            p = win.shape[-1]
            ext = (o[0] - 0.5, o[0] + p - 0.5, o[1] + p - 0.5, o[1] - 0.5)
            ax.imshow(np.nan_to_num(win), extent=ext, cmap="magma", interpolation="nearest")
            c = cen[i, r]
            if np.all(np.isfinite(c)):
                ax.plot(c[0], c[1], "c+", ms=8)
            f = ray.xy_at(z)[_flat((u, v), w)] / pitch
            ax.plot(f[0], f[1], "gx", ms=6)
            ax.set_title(f"{name} ({u},{v})  z={z:g} mm", fontsize=7)
            ax.tick_params(labelsize=6)
    fig.suptitle("LTC at each depth (LCD pixels); + centroid, x principal ray", fontsize=9)
    fig.tight_layout()
    durable_figure(fig, path)
    return path


def rays_figure(volume: LtcVolume, result: LensResult, path: Path) -> Path:
    """Principal rays in x-z and y-z with the optical centre."""
    g = result.geometry
    rays = g.rays
    ok = np.flatnonzero(rays.usable)
    show = ok[np.linspace(0, len(ok) - 1, min(RAYS_SHOWN, len(ok))).astype(np.int64)]
    cen = _centroids_lcd_px(volume, show) * g.centroids.pitch_mm  # (D, n, 2) mm
    zs = np.broadcast_to(g.centroids.depths_mm[:, None], cen.shape[:2])
    z0 = min(g.centre.position[2], g.centre_rays.position[2])
    z = np.array([z0, float(np.max(g.centroids.depths_mm))])
    fig = Figure(figsize=(10, 4.5), dpi=DPI)
    axes = fig.subplots(1, 2)
    for k, (ax, name) in enumerate(zip(axes, ("x", "y"), strict=True)):
        xy = np.stack([rays.xy_at(zz)[show, k] for zz in z])
        ax.plot(z, xy, "-", color="0.6", lw=0.5)
        ax.plot(zs.ravel(), cen[..., k].ravel(), ".", color="C0", ms=2, label="LTC centroids")
        ax.plot(g.centre.position[2], g.centre.position[k], "r*", ms=12,
                label=f"optical centre ({g.centre.method})")
        ax.plot(g.centre_rays.position[2], g.centre_rays.position[k], "kx", ms=9,
                label="principal-ray intersection")
        ax.axvline(g.focus_plane_z_mm, color="C2", ls="--", lw=0.8, label="focus plane")
        ax.set_xlabel("z (station frame), mm")
        ax.set_ylabel(f"{name}, mm")
        ax.legend(fontsize=7, loc="best")
    fig.suptitle("Principal rays", fontsize=10)
    fig.tight_layout()
    durable_figure(fig, path)
    return path


def aperture_figure(volume: LtcVolume, result: LensResult, path: Path) -> Path:
    """Fused aperture distributions and K samples of the chosen pixels."""
    g = result.geometry
    w = volume.camera_size[0]
    pix = chosen_pixels(volume.camera_size)
    flat = np.array([_flat(uv, w) for uv in pix.values()])
    aps = aperture_set(volume, g, result.grid, flat, result.config)
    fused = aps.fused
    if fused is None:
        raise ValueError("aperture_set kept no fused distributions")
    x, y, wk = result.samples_at(np.array(list(pix.values()), dtype=np.float64))
    hw = result.grid.half_width_mm
    fig = Figure(figsize=(3.6 * len(pix), 3.6), dpi=DPI)
    axes = fig.subplots(1, len(pix), squeeze=False)[0]
    for k, (name, uv) in enumerate(pix.items()):
        ax = axes[k]
        ax.imshow(fused[k], extent=(-hw, hw, hw, -hw), cmap="viridis",
                  interpolation="nearest")
        s = wk[k] / max(float(wk[k].max()), 1e-12)
        ax.scatter(x[k], y[k], s=40 * s + 2, facecolors="none", edgecolors="r", lw=0.8)
        ax.set_title(f"{name} {uv}", fontsize=8)
        ax.set_xlabel("x_k, mm")
        ax.set_ylabel("y_k, mm")
    fig.suptitle(f"LTC at the optical centre (z_f = {g.focus_distance_mm:.2f} mm); "
                 f"circles: {result.config.samples} samples", fontsize=9)
    fig.tight_layout()
    durable_figure(fig, path)
    return path


def residuals_figure(result: LensResult, path: Path) -> Path:
    """Map of each pixel's RMS principal-ray residual; flagged pixels outlined."""
    g = result.geometry
    w, h = g.camera_size
    res = g.rays.residual_norm()
    n = np.isfinite(res).sum(axis=0)
    rms = np.sqrt(np.nansum(res**2, axis=0) / np.maximum(n, 1))
    rms = np.where(n > 0, rms, np.nan)
    img = np.where((g.rays.flags & UNUSABLE) == 0, rms, np.nan).reshape(h, w)
    fig = Figure(figsize=(6, 4.5), dpi=DPI)
    ax = fig.subplots()
    im = ax.imshow(img, cmap="inferno", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="RMS residual, mm")
    bad = np.flatnonzero(g.rays.flags != 0)
    if bad.size:
        ax.plot(bad % w, bad // w, "cs", ms=4, mfc="none", label="flagged")
        ax.legend(fontsize=7)
    ax.set_title("Principal-ray residuals per pixel", fontsize=9)
    ax.set_xlabel("u, px")
    ax.set_ylabel("v, px")
    fig.tight_layout()
    durable_figure(fig, path)
    return path


def write_figures(volume: LtcVolume, result: LensResult, folder: str | Path) -> list[Path]:
    """Write all four figures into ``folder`` (created); returns their paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    return [
        ltc_depths_figure(volume, result, folder / "ltc_depths.png"),
        rays_figure(volume, result, folder / "principal_rays.png"),
        aperture_figure(volume, result, folder / "aperture.png"),
        residuals_figure(result, folder / "ray_residuals.png"),
    ]
