"""Joint bundle adjustment of every device (two cameras and the projector) and board pose.

Parameters: per device ``fx fy cx cy`` and its distortion coefficients (model per device:
``none``, ``k1k2`` or ``k1k2p1p2k3``, OpenCV's polynomial model); per pose the board's
rotation vector and translation into device 0 (camera 0, the world frame); per device after
the first its rotation vector and translation from device 0. Residuals are reprojection errors
in pixels; ``scipy.optimize.least_squares`` (trust region) with a sparse Jacobian pattern: a
residual depends on its device's intrinsics, its pose and its device's extrinsics only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

DistortionModel = Literal["none", "k1k2", "k1k2p1p2k3"]
DIST_INDEX = {"none": [], "k1k2": [0, 1], "k1k2p1p2k3": [0, 1, 2, 3, 4]}
CV_FLAGS = {
    "none": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3,
    "k1k2": cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3,
    "k1k2p1p2k3": 0,
}


@dataclass(frozen=True)
class Observations:
    """m observations: device index ``dev`` (m,), pose index ``pose`` (m,), board feature
    ``point`` (m,) into ``object_points`` (P, 3) mm, pixel ``uv`` (m, 2)."""

    dev: np.ndarray
    pose: np.ndarray
    point: np.ndarray
    uv: np.ndarray
    object_points: np.ndarray

    def of(self, d: int) -> np.ndarray:
        return np.flatnonzero(self.dev == d)


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors (n, 3)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3)
    th = np.linalg.norm(r, axis=1)
    small = th < 1e-12
    k = r / np.where(small, 1.0, th)[:, None]
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    R = np.eye(3) + s * K + (1 - c) * (K @ K)
    return np.where(small[:, None, None], np.eye(3) + _skew(r), R)


def _skew(r: np.ndarray) -> np.ndarray:
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -r[:, 2], r[:, 1], -r[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = r[:, 2], -r[:, 1], r[:, 0]
    return K


def distort_project(xc: np.ndarray, intr: np.ndarray) -> np.ndarray:
    """Pixels (m, 2) of device-frame points (m, 3) with per-point intrinsics (m, 9):
    fx fy cx cy k1 k2 p1 p2 k3 (OpenCV's model, no skew)."""
    x, y = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = intr.T
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([fx * xd + cx, fy * yd + cy], axis=1)


class Layout:
    """Where each parameter lives in the parameter vector."""

    def __init__(self, models: list[DistortionModel], n_poses: int) -> None:
        self.models = models
        self.intr_start, n = [], 0
        for m in models:
            self.intr_start.append(n)
            n += 4 + len(DIST_INDEX[m])
        self.pose_start = n
        n += 6 * n_poses
        self.ext_start = n
        n += 6 * (len(models) - 1)
        self.size = n
        self.n_poses = n_poses

    def intrinsics(self, x: np.ndarray) -> np.ndarray:
        """(devices, 9) fx fy cx cy k1 k2 p1 p2 k3."""
        out = np.zeros((len(self.models), 9))
        for d, m in enumerate(self.models):
            s = self.intr_start[d]
            out[d, :4] = x[s : s + 4]
            idx = DIST_INDEX[m]
            out[d, [4 + i for i in idx]] = x[s + 4 : s + 4 + len(idx)]
        return out

    def poses(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = x[self.pose_start : self.ext_start].reshape(-1, 6)
        return rodrigues(p[:, :3]), p[:, 3:]

    def extrinsics(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = x[self.ext_start :].reshape(-1, 6)
        R = np.concatenate([np.eye(3)[None], rodrigues(e[:, :3])])
        t = np.concatenate([np.zeros((1, 3)), e[:, 3:]])
        return R, t

    def columns(self, dev: int, pose: int) -> list[int]:
        s = self.intr_start[dev]
        cols = list(range(s, s + 4 + len(DIST_INDEX[self.models[dev]])))
        cols += list(range(self.pose_start + 6 * pose, self.pose_start + 6 * pose + 6))
        if dev > 0:
            e = self.ext_start + 6 * (dev - 1)
            cols += list(range(e, e + 6))
        return cols


def project_all(layout: Layout, x: np.ndarray, obs: Observations) -> np.ndarray:
    """Predicted pixels (m, 2) of every observation."""
    intr = layout.intrinsics(x)
    Rp, tp = layout.poses(x)
    Re, te = layout.extrinsics(x)
    X = obs.object_points[obs.point]
    xb = np.einsum("mij,mj->mi", Rp[obs.pose], X) + tp[obs.pose]
    xc = np.einsum("mij,mj->mi", Re[obs.dev], xb) + te[obs.dev]
    return distort_project(xc, intr[obs.dev])


def sparsity(layout: Layout, obs: Observations) -> lil_matrix:
    """The Jacobian's pattern (2 m, parameters)."""
    S = lil_matrix((2 * len(obs.dev), layout.size), dtype=np.int8)
    for k, (d, j) in enumerate(zip(obs.dev, obs.pose, strict=True)):
        cols = layout.columns(int(d), int(j))
        S[2 * k, cols] = 1
        S[2 * k + 1, cols] = 1
    return S


@dataclass(frozen=True)
class BundleSolution:
    """The adjusted parameters: per device K (3, 3), dist (5,), R (3, 3), T (3,) from device 0;
    per pose the board's R (3, 3), t (3,) into device 0; residuals (m, 2) px; the relative
    standard deviation of each device's fx from the Jacobian; the solver's status."""

    K: list[np.ndarray]
    dist: list[np.ndarray]
    R: list[np.ndarray]
    T: list[np.ndarray]
    pose_R: np.ndarray
    pose_t: np.ndarray
    residuals: np.ndarray
    fx_rel_std: np.ndarray
    nfev: int
    x: np.ndarray


def initial_vector(layout: Layout, K: list[np.ndarray], dist: list[np.ndarray],
                   pose_rvec: np.ndarray, pose_t: np.ndarray, ext_rvec: list[np.ndarray],
                   ext_t: list[np.ndarray]) -> np.ndarray:
    x = np.zeros(layout.size)
    for d, m in enumerate(layout.models):
        s = layout.intr_start[d]
        x[s : s + 4] = [K[d][0, 0], K[d][1, 1], K[d][0, 2], K[d][1, 2]]
        idx = DIST_INDEX[m]
        x[s + 4 : s + 4 + len(idx)] = np.asarray(dist[d]).ravel()[idx]
    x[layout.pose_start : layout.ext_start] = np.concatenate(
        [pose_rvec.reshape(-1, 3), pose_t.reshape(-1, 3)], axis=1).ravel()
    x[layout.ext_start :] = np.concatenate(
        [np.concatenate([np.ravel(r), np.ravel(t)]) for r, t in zip(ext_rvec, ext_t, strict=True)])
    return x


def _groups(S: np.ndarray) -> list[np.ndarray]:
    """Columns of the boolean pattern S (rows, cols) in groups that share no row (greedy)."""
    groups: list[list[int]] = []
    used: list[np.ndarray] = []
    for c in range(S.shape[1]):
        rows = S[:, c]
        for g, u in zip(groups, used, strict=True):
            if not np.any(u & rows):
                g.append(c)
                u |= rows
                break
        else:
            groups.append([c])
            used.append(rows.copy())
    return [np.array(g) for g in groups]


def adjust(layout: Layout, x0: np.ndarray, obs: Observations) -> BundleSolution:
    """Minimise the reprojection errors from ``x0``. The Jacobian is a forward difference
    taken group by group over the sparse pattern (columns that share no residual are stepped
    together), returned dense to the exact trust-region solver (a few hundred parameters)."""

    def fun(x):
        return (project_all(layout, x, obs) - obs.uv).ravel()

    S = sparsity(layout, obs).tocsc().astype(bool).toarray()
    groups = _groups(S)

    def jac(x):
        f0 = fun(x)
        J = np.zeros((len(f0), len(x)))
        for g in groups:
            h = 1e-7 * np.maximum(np.abs(x[g]), 1.0)
            xp = x.copy()
            xp[g] += h
            df = fun(xp) - f0
            for c, hc in zip(g, h, strict=True):
                rows = S[:, c]
                J[rows, c] = df[rows] / hc
        return J

    res = least_squares(fun, x0, jac=jac, method="trf", x_scale="jac", ftol=1e-15,
                        xtol=1e-15, gtol=1e-15, max_nfev=100, tr_solver="exact")
    x = res.x
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    r = res.fun
    dof = max(len(r) - len(x), 1)
    sigma2 = float(r @ r) / dof
    try:
        cov = np.linalg.pinv(J.T @ J) * sigma2
        std = np.sqrt(np.abs(np.diag(cov)))
    except np.linalg.LinAlgError:
        std = np.full(len(x), np.inf)
    intr = layout.intrinsics(x)
    fx_rel = np.array([std[s] / max(abs(x[s]), 1e-12) for s in layout.intr_start])
    Re, te = layout.extrinsics(x)
    Rp, tp = layout.poses(x)
    Ks = [np.array([[i[0], 0, i[2]], [0, i[1], i[3]], [0, 0, 1.0]]) for i in intr]
    return BundleSolution(Ks, [i[4:].copy() for i in intr], list(Re), list(te), Rp, tp,
                          r.reshape(-1, 2), fx_rel, int(res.nfev), x)
