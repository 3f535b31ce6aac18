"""Board features in projector pixels, from a camera's unwrapped phase maps.

The projector is calibrated as an inverse camera (Zhang & Huang 2006): a camera pixel's
unwrapped phases give the projector pixel ``(u_p, v_p)`` it sees. Two ways to carry a board
feature at camera pixel ``(u, v)`` (sub-pixel) into the projector:

- ``"sample"``: the phase maps interpolated bilinearly at the feature's pixel;
- ``"homography"`` (Moreno & Taubin 2012): a homography from camera to projector pixels fitted
  over the valid pixels of a patch around the feature, with iterative rejection of pixels whose
  residual is far above the patch's median (wrong unwrapping, mixed pixels), the feature mapped
  through it. The board is a plane, so camera and projector are related by a homography
  (up to lens distortion, smooth over a patch).
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

PATCH_HALF_PX = 20  # the homography's patch: (2 h + 1)^2 camera pixels around the feature
MIN_PATCH_PIXELS = 50
REJECT_MADS = 4.0  # residuals beyond this many (scaled) MADs of the patch are rejected
REJECT_FLOOR_PX = 0.02  # ... but never below this, projector px

Method = Literal["homography", "sample"]


def _bilinear(m: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = m.shape
    u, v = uv[:, 0], uv[:, 1]
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    u0, v0 = np.clip(u0, 0, w - 2), np.clip(v0, 0, h - 2)
    fu, fv = u - u0, v - v0
    val = ((1 - fu) * (1 - fv) * m[v0, u0] + fu * (1 - fv) * m[v0, u0 + 1]
           + (1 - fu) * fv * m[v0 + 1, u0] + fu * fv * m[v0 + 1, u0 + 1])
    return np.where(ok, val, np.nan)


def sample(u_p: np.ndarray, v_p: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Projector pixels (n, 2) of camera points uv (n, 2): the phase maps (H, W) interpolated
    bilinearly; NaN where a neighbour is invalid."""
    return np.stack([_bilinear(u_p, uv), _bilinear(v_p, uv)], axis=1)


def _robust_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray | None:
    keep = np.ones(len(src), bool)
    H = None
    for _ in range(4):
        if keep.sum() < MIN_PATCH_PIXELS:
            return None
        H, _ = cv2.findHomography(src[keep], dst[keep], 0)
        if H is None:
            return None
        p = cv2.perspectiveTransform(src.reshape(-1, 1, 2), H).reshape(-1, 2)
        r = np.linalg.norm(p - dst, axis=1)
        mad = 1.4826 * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = r <= max(np.median(r[keep]) + REJECT_MADS * mad, REJECT_FLOOR_PX)
        if np.array_equal(new, keep):
            break
        keep = new
    return H


def local_homography(u_p: np.ndarray, v_p: np.ndarray, uv: np.ndarray,
                     half_px: int = PATCH_HALF_PX, return_maps: bool = False):
    """Projector pixels (n, 2) of camera points uv (n, 2) through a robust local homography
    fitted over a (2 half_px + 1)^2 patch of the phase maps (H, W); NaN where the patch has
    fewer than ``MIN_PATCH_PIXELS`` valid pixels. With ``return_maps`` also the homographies
    (n, 3, 3), camera to projector pixels (NaN where none), to map points near the features."""
    h, w = u_p.shape
    out = np.full((len(uv), 2), np.nan)
    maps = np.full((len(uv), 3, 3), np.nan)
    for i, (u, v) in enumerate(uv):
        cu, cv_ = int(round(u)), int(round(v))
        x0, x1 = max(cu - half_px, 0), min(cu + half_px + 1, w)
        y0, y1 = max(cv_ - half_px, 0), min(cv_ + half_px + 1, h)
        if x1 <= x0 or y1 <= y0:
            continue
        pu, pv = u_p[y0:y1, x0:x1], v_p[y0:y1, x0:x1]
        ok = np.isfinite(pu) & np.isfinite(pv)
        if ok.sum() < MIN_PATCH_PIXELS:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        # centred on the feature: better conditioned
        src = np.stack([xx[ok] - u, yy[ok] - v], axis=1).astype(np.float64)
        dst = np.stack([pu[ok], pv[ok]], axis=1)
        c = dst.mean(axis=0)
        H = _robust_homography(src, dst - c)
        if H is None:
            continue
        out[i] = H[:2, 2] / H[2, 2] + c
        maps[i] = np.array([[1, 0, c[0]], [0, 1, c[1]], [0, 0, 1.0]]) @ H @ \
            np.array([[1, 0, -u], [0, 1, -v], [0, 0, 1.0]])
    return (out, maps) if return_maps else out


def apply_maps(maps: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Points uv (n, 2) through their homographies (n, 3, 3)."""
    p = np.einsum("nij,nj->ni", maps, np.concatenate([uv, np.ones((len(uv), 1))], axis=1))
    return p[:, :2] / p[:, 2:]


def projector_features(u_p: np.ndarray, v_p: np.ndarray, uv: np.ndarray,
                       method: Method = "homography") -> tuple[np.ndarray, np.ndarray]:
    """Projector pixels (n, 2) of board features at camera pixels uv (n, 2), NaN where the
    phase around a feature is not usable, and the local maps camera to projector (n, 3, 3)
    (``"sample"``: the affine map of the phase maps' local gradient)."""
    if method == "sample":
        p = sample(u_p, v_p, uv)
        e = 0.5
        gu = (sample(u_p, v_p, uv + [e, 0]) - sample(u_p, v_p, uv - [e, 0])) / (2 * e)
        gv = (sample(u_p, v_p, uv + [0, e]) - sample(u_p, v_p, uv - [0, e])) / (2 * e)
        maps = np.zeros((len(uv), 3, 3))
        maps[:, :2, 0], maps[:, :2, 1] = gu, gv
        maps[:, :2, 2] = p - gu * uv[:, :1] - gv * uv[:, 1:]
        maps[:, 2, 2] = 1.0
        return p, maps
    if method == "homography":
        return local_homography(u_p, v_p, uv, return_maps=True)
    raise ValueError(f"projector feature method must be 'homography' or 'sample', got {method!r}")
