"""Exact light transport from a pixelated plane (an LCD) to camera pixels, by dense sampling.

For every camera pixel, rays from a grid of points over the pixel's area and from every
aperture sample of the lens are intersected with the plane; each ray deposits its weight on
the plane pixel it lands in. The result is the per-pixel LTC as a sparse matrix.

Plane frame: origin at the centre of plane pixel (0, 0), x along columns, y along rows,
z along the normal away from the camera; plane pixel (i, j) covers
``[(i - 0.5) pitch, (i + 0.5) pitch] x [(j - 0.5) pitch, (j + 0.5) pitch]``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from sim.optics.lens import LensModel
from sim.optics.projection import pixel_to_normalized

RAYS_PER_CHUNK = 1 << 21


def subpixel_offsets(n: int) -> np.ndarray:
    """Centres of an n x n grid over a pixel's area, offsets in pixels, (n*n, 2)."""
    if n < 1:
        raise ValueError(f"subpixel grid needs n >= 1, got {n}")
    g = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(g, g)
    return np.stack([du.ravel(), dv.ravel()], axis=1)


def plane_ltc(
    K: np.ndarray,
    dist: np.ndarray | None,
    camera_size: tuple[int, int],
    lens: LensModel,
    R_cam_to_plane: np.ndarray,
    t_cam_to_plane_mm: np.ndarray,
    plane_size: tuple[int, int],
    pitch_mm: float,
    subpixels: int = 4,
    pixels: np.ndarray | None = None,
) -> sp.csr_array:
    """Per-pixel LTC of a camera looking at a pixelated plane.

    K, dist : camera intrinsics (3x3) and OpenCV distortion.
    camera_size : (width, height) in pixels.
    lens : any ``LensModel``; its rays are in the camera frame.
    R_cam_to_plane, t_cam_to_plane_mm : ``X_plane = R X_cam + t``.
    plane_size : (width, height) of the plane in its pixels; pitch_mm : plane pixel pitch.
    subpixels : the pixel area is sampled on a subpixels x subpixels grid.
    pixels : optional (m,) flat camera pixel indices ``v * width + u`` to compute; others
        get empty rows.

    Returns a (height*width, plane_h*plane_w) CSR array; row ``v * width + u``, column
    ``j * plane_w + i``; each row sums to the fraction of the pixel's light that comes
    from the plane (its relative transmittance when the plane fills the view).
    """
    w, h = camera_size
    pw, ph = plane_size
    R = np.asarray(R_cam_to_plane, dtype=np.float64)
    t = np.asarray(t_cam_to_plane_mm, dtype=np.float64).ravel()
    flat = np.arange(w * h) if pixels is None else np.asarray(pixels, dtype=np.int64).ravel()
    offsets = subpixel_offsets(subpixels)
    s = len(offsets)
    k = lens.bundle(np.zeros((1, 2))).weights.shape[1]
    per_chunk = max(1, RAYS_PER_CHUNK // (s * k))
    rows, cols, vals = [], [], []
    for start in range(0, len(flat), per_chunk):
        pix = flat[start : start + per_chunk]
        uv = np.stack([pix % w, pix // w], axis=1).astype(np.float64)
        uv_sub = (uv[:, None, :] + offsets[None, :, :]).reshape(-1, 2)
        xy_n = pixel_to_normalized(uv_sub, K, dist)
        b = lens.bundle(xy_n, uv_sub)
        o = b.origins @ R.T + t
        d = b.directions @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            tt = -o[..., 2] / d[..., 2]
        xy = o[..., :2] + tt[..., None] * d[..., :2]
        ij = np.rint(xy / pitch_mm)
        ok = (tt > 0) & (b.weights > 0)
        ok &= (ij[..., 0] >= 0) & (ij[..., 0] < pw) & (ij[..., 1] >= 0) & (ij[..., 1] < ph)
        ij = np.where(ok[..., None], ij, 0).astype(np.int64).reshape(len(pix), s * k, 2)
        okp = ok.reshape(len(pix), s * k)
        lo = np.where(okp[..., None], ij, np.iinfo(np.int64).max).min(axis=1)  # (n, 2)
        hi = np.where(okp[..., None], ij, -1).max(axis=1)
        lo = np.where(okp.any(axis=1)[:, None], lo, 0)
        span = np.maximum(hi - lo + 1, 1)
        wx, wy = int(span[:, 0].max()), int(span[:, 1].max())
        rel = ij - lo[:, None, :]
        local = np.arange(len(pix))[:, None]
        key = ((local * wy + rel[..., 1]) * wx + rel[..., 0])[okp]
        wts = (b.weights.reshape(len(pix), s * k) / s)[okp]
        acc = np.bincount(key, weights=wts, minlength=len(pix) * wx * wy)
        nz = np.flatnonzero(acc)
        p_loc, rem = np.divmod(nz, wx * wy)
        jj, ii = np.divmod(rem, wx)
        rows.append(pix[p_loc])
        cols.append((lo[p_loc, 1] + jj) * pw + lo[p_loc, 0] + ii)
        vals.append(acc[nz])
    rows_a = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    cols_a = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    vals_a = np.concatenate(vals) if vals else np.zeros(0)
    return sp.csr_array((vals_a, (rows_a, cols_a)), shape=(w * h, pw * ph))
