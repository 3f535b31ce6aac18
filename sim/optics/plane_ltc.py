"""Exact light transport from a pixelated plane (an LCD) to camera pixels, by dense sampling.

For every camera pixel, rays from a grid of points over the pixel's area (its subpixels) and
from every aperture sample of the lens are intersected with the plane. Each ray stands for
its subpixel's footprint on the plane: a square of the subpixel's size at the hit's depth
(``1 / (n fx)`` by ``1 / (n fy)`` in normalised coordinates times the hit's camera-frame
depth), and deposits its weight on the plane pixels in proportion to the footprint's overlap
with each. So the pixel's area is integrated exactly for every aperture sample; only the
aperture is sampled. (Depositing each ray on the one plane pixel its hit lies in quantises
every ray by up to half a plane pixel: on the experiment's fake bench, 2 x 2 subpixels and 512
pupil samples, the principal rays through such LTCs miss the lens's own by 31 um RMS at the
pupil, pixel to pixel; with the footprints, 3.8 um: docs/decisions 0015.) The result is the
per-pixel LTC as a sparse matrix. The footprint ignores the plane's tilt and the distortion's
change of scale (both first order in small quantities here).

Plane frame: origin at the centre of plane pixel (0, 0), x along columns, y along rows,
z along the normal away from the camera; plane pixel (i, j) covers
``[(i - 0.5) pitch, (i + 0.5) pitch] x [(j - 0.5) pitch, (j + 0.5) pitch]``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from sim.errors import SimInputError
from sim.optics.lens import LensModel
from sim.optics.projection import pixel_to_normalized

RAYS_PER_CHUNK = 1 << 21


def subpixel_offsets(n: int) -> np.ndarray:
    """Centres of an n x n grid over a pixel's area, offsets in pixels, (n*n, 2)."""
    if n < 1:
        raise SimInputError(f"subpixel grid needs n >= 1, got {n}")
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
    pixels : optional (m,) flat camera pixel indices ``v * width + u`` to compute (each
        once); others get empty rows.

    Returns a (height*width, plane_h*plane_w) CSR array; row ``v * width + u``, column
    ``j * plane_w + i``; each row sums to the fraction of the pixel's light that comes
    from the plane (its relative transmittance when the plane fills the view).
    """
    # numba: loaded on first use
    from sim.optics.plane_kernels import MAX_HALF_PX, deposit_footprints, plane_hits

    w, h = camera_size
    pw, ph = plane_size
    R = np.asarray(R_cam_to_plane, dtype=np.float64)
    t = np.asarray(t_cam_to_plane_mm, dtype=np.float64).ravel()
    flat = np.arange(w * h) if pixels is None else np.unique(np.asarray(pixels, np.int64))
    offsets = subpixel_offsets(subpixels)
    s = len(offsets)
    k = lens.bundle(np.zeros((1, 2))).weights.shape[1]
    half_scale = 0.5 / (subpixels * pitch_mm) / np.asarray(K, dtype=np.float64)[[0, 1], [0, 1]]
    per_chunk = max(1, RAYS_PER_CHUNK // (s * k))
    counts = np.zeros(w * h, dtype=np.int64)
    col_type = np.int32 if pw * ph < 2**31 else np.int64
    cols, vals = [], []
    for start in range(0, len(flat), per_chunk):
        pix = flat[start : start + per_chunk]
        uv = np.stack([pix % w, pix // w], axis=1).astype(np.float64)
        uv_sub = (uv[:, None, :] + offsets[None, :, :]).reshape(-1, 2)
        xy_n = pixel_to_normalized(uv_sub, K, dist)
        b = lens.bundle(xy_n, uv_sub)
        n = len(pix)
        r = b.weights.size // n
        xy = np.empty((n, r, 2))
        half = np.empty((n, r, 2))
        weight = np.empty((n, r))
        box = np.empty((n, 4), dtype=np.int64)
        plane_hits(b.origins.reshape(n, r, 3), b.directions.reshape(n, r, 3),
                  np.ascontiguousarray(b.weights.reshape(n, r)), R, t, float(pitch_mm),
                  half_scale, xy, half, weight, box)
        if n and half.max() >= MAX_HALF_PX:
            raise SimInputError("plane_ltc: a subpixel's footprint spans more than 16 plane "
                             "pixels; use more subpixels")
        weight /= s
        lo = box[:, :2]
        span = np.maximum(box[:, 2:] - lo + 1, 1)
        wx, wy = int(span[:, 0].max()), int(span[:, 1].max())
        acc3 = np.zeros((n, wy, wx))
        deposit_footprints(xy, half, weight, lo, np.array([pw, ph], dtype=np.int64), acc3)
        acc = acc3.ravel()
        nz = np.flatnonzero(acc)
        p_loc, rem = np.divmod(nz, wx * wy)
        jj, ii = np.divmod(rem, wx)
        counts[pix] = np.bincount(p_loc, minlength=n)
        cols.append(((lo[p_loc, 1] + jj) * pw + lo[p_loc, 0] + ii).astype(col_type))
        vals.append(acc[nz])
    # the pixels increase within each chunk and from chunk to chunk, and each pixel's window
    # is row-major: the CSR rows and their sorted columns are assembled directly
    indptr = np.zeros(w * h + 1, dtype=np.int32 if counts.sum() < 2**31 else np.int64)
    np.cumsum(counts, out=indptr[1:])
    data = np.concatenate(vals) if vals else np.zeros(0)
    indices = np.concatenate(cols) if cols else np.zeros(0, col_type)
    return sp.csr_array((data, indices, indptr), shape=(w * h, pw * ph))

