"""Calibration of a fringe projection scanner from a capture folder: both cameras and the
projector, intrinsics and extrinsics, in one bundle adjustment.

Steps: features in each camera's white image (``sim.calibration.board.detect``); their projector
pixels from the unwrapped phase (``sim.calibration.projector``, averaged over the cameras that
see them); Zhang's method per device (``cv2.calibrateCamera``) as the start; one joint bundle
adjustment (``sim.calibration.bundle``). Bad input is refused with one line naming the pose
and camera (``CalibrationError``): a board not found, fewer than ``MIN_POSES`` poses, poses
that leave the focal length unconstrained, a projector error far above the cameras'.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sim.calibration.board import detect, load_board
from sim.calibration.bundle import (
    CV_FLAGS,
    DistortionModel,
    Layout,
    Observations,
    adjust,
    distort_project,
    initial_vector,
)
from sim.calibration.capture import Capture
from sim.calibration.errors import CalibrationError
from sim.calibration.projector import Method, apply_maps, projector_features
from sim.fpp.decode import DecodeSettings
from sim.optics.rig import DeviceCalibration, Rig
from sim.render.board import CalibrationBoard

MIN_POSES = 3
MIN_NORMAL_SPREAD_DEG = 5.0  # board normals must spread at least this much (Zhang)
MAX_FOCAL_REL_STD = 0.01  # refuse a focal length known worse than 1 % (from the Jacobian)
PROJECTOR_RATIO = 8.0  # refuse a projector RMS above this many times the cameras' ...
PROJECTOR_FLOOR_PX = 0.3  # ... and above this many pixels
MIN_PROJECTOR_FEATURES = 6
DEVICE_NAMES = ("camera 0", "camera 1", "projector")


@dataclass(frozen=True)
class PoseResiduals:
    """One pose's residuals on one device: features ``ids`` (n,), observed pixels ``uv`` (n, 2),
    residuals ``error`` (n, 2) px (predicted - observed)."""

    pose: str
    device: str
    ids: np.ndarray
    uv: np.ndarray
    error: np.ndarray

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.error**2, axis=1)))) if len(self.error) else 0.0


@dataclass(frozen=True)
class CalibrationResult:
    """The calibrated rig (world frame: camera 0), RMS reprojection error (px) per device and
    per pose and device, the per-pose residuals, and what was used."""

    rig: Rig
    rms_px: dict[str, float]
    pose_rms_px: dict[str, dict[str, float]]
    residuals: list[PoseResiduals]
    focal_rel_std: dict[str, float]
    distortion: dict[str, str]
    projector_method: str
    poses: list[str]
    board: CalibrationBoard
    timings: dict[str, float] = field(default_factory=dict)

    def summary(self) -> dict:
        """JSON-able summary (no per-feature arrays)."""
        return {"rms_px": self.rms_px, "pose_rms_px": self.pose_rms_px,
                "focal_rel_std": self.focal_rel_std, "distortion": self.distortion,
                "projector_method": self.projector_method, "poses": self.poses,
                "board": self.board.model_dump(mode="json"),
                "rig": self.rig.model_dump(mode="json"), "timings": self.timings}

    def to_json(self) -> str:
        return json.dumps(self.summary(), indent=2)


@dataclass
class _Views:
    """Features of every pose: per camera (ids, uv) and the projector's (ids, uv)."""

    poses: list[str]
    cams: list[list[tuple[np.ndarray, np.ndarray]]]
    proj: list[tuple[np.ndarray, np.ndarray]]
    camera_size: tuple[int, int]
    maps: list[list[np.ndarray]]  # per camera, per pose: the local maps to the projector

    def projector_view(self, j: int, cams_uv: list[np.ndarray], n: int
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Pose j's projector features from camera points (one (k, 2) per camera, in the
        order of their ids) through the local maps, averaged over the cameras."""
        acc, cnt = np.zeros((n, 2)), np.zeros(n)
        for c in range(2):
            ids = self.cams[c][j][0]
            p = apply_maps(self.maps[c][j], cams_uv[c])
            ok = np.all(np.isfinite(p), axis=1)
            np.add.at(acc, ids[ok], p[ok])
            np.add.at(cnt, ids[ok], 1)
        ids = np.flatnonzero(cnt > 0)
        return ids, acc[ids] / cnt[ids, None]


def _gather(capture: Capture, board: CalibrationBoard, method: Method,
            settings: DecodeSettings) -> _Views:
    cams: list[list] = [[], []]
    maps: list[list] = [[], []]
    proj: list = []
    size: tuple[int, int] | None = None  # (width, height) px
    for pose in capture.poses:
        per_cam = []
        for c in range(capture.cameras):
            found: list = []

            def features(white, found=found):
                f = detect(white, board)
                found.append(f)
                return None if f is None else f.uv

            view = capture.view(pose, c, settings, features)
            h, w = view.white.shape
            size = (w, h)
            feats = found[0]
            if feats is None:
                nx, ny = board.pattern_size
                raise CalibrationError(
                    f"{pose}, camera {c}: board not found ({board.kind}, {nx} x {ny} features) "
                    "in the white image; check focus, exposure and that the whole board is in "
                    "view, or remove the pose")
            cams[c].append((feats.ids, feats.uv))
            p, m = projector_features(view.u_p, view.v_p, feats.uv, method)
            maps[c].append(m)
            per_cam.append((feats, p))
        # the projector's view: the mean of the cameras' estimates of each feature
        n = len(board.object_points())
        acc, cnt = np.zeros((n, 2)), np.zeros(n)
        for feats, p in per_cam:
            ok = np.all(np.isfinite(p), axis=1)
            np.add.at(acc, feats.ids[ok], p[ok])
            np.add.at(cnt, feats.ids[ok], 1)
        ids = np.flatnonzero(cnt > 0)
        if len(ids) < MIN_PROJECTOR_FEATURES:
            raise CalibrationError(
                f"{pose}, camera 0 and camera 1: only {len(ids)} board features have a valid "
                "projector phase around them; is the board lit by the projector and the fringe "
                "modulation high enough?")
        proj.append((ids, acc[ids] / cnt[ids, None]))
    assert size is not None, "calibrate refuses a capture with fewer than MIN_POSES poses"
    return _Views(list(capture.poses), cams, proj, size, maps)


def _check_conditioning(views: _Views, object_points: np.ndarray) -> None:
    """Refuse poses whose board normals hardly differ (the focal length is then
    unconstrained): normals from solvePnP with a nominal camera 0."""
    w, h = views.camera_size
    K = np.array([[float(max(w, h)), 0, (w - 1) / 2], [0, float(max(w, h)), (h - 1) / 2],
                  [0, 0, 1]])
    normals = []
    for ids, uv in views.cams[0]:
        ok, rvec, _ = cv2.solvePnP(object_points[ids], uv, K, None)
        R, _ = cv2.Rodrigues(rvec)
        normals.append(R[:, 2])
    n = np.array(normals)
    cosang = np.clip(np.abs(n @ n.T), -1, 1)
    spread = float(np.degrees(np.arccos(cosang.min())))
    if spread < MIN_NORMAL_SPREAD_DEG:
        tilt = np.degrees(np.arccos(np.clip(np.abs(n[:, 2]), 0, 1)))
        raise CalibrationError(
            f"{views.poses[0]} .. {views.poses[-1]}, camera 0: the board's normals differ by at "
            f"most {spread:.2f} degrees across the {len(n)} poses (tilts "
            f"{tilt.min():.1f}-{tilt.max():.1f} degrees): the focal length is unconstrained; "
            "tilt the board by 20-40 degrees about different axes in several poses")


def _zhang(obj: np.ndarray, feats: list[tuple[np.ndarray, np.ndarray]], size, model: str,
           name: str, poses: list[str]) -> tuple[np.ndarray, np.ndarray, list, list, np.ndarray]:
    """Zhang's method on one device: K, dist, rvecs, tvecs and the RMS error of each pose."""
    op = [obj[ids].astype(np.float32) for ids, _ in feats]
    ip = [uv.astype(np.float32).reshape(-1, 1, 2) for _, uv in feats]
    try:
        _, K, dist, rv, tv = cv2.calibrateCamera(op, ip, tuple(int(s) for s in size), None, None,
                                                 flags=CV_FLAGS[model])
    except cv2.error as exc:
        raise CalibrationError(f"{poses[0]} .. {poses[-1]}, {name}: Zhang's initialisation "
                               f"failed ({' '.join(str(exc).split())[:120]}); vary the board's "
                               "tilt between poses") from exc
    per_pose = []
    for o, i, r, t in zip(op, ip, rv, tv, strict=True):
        p, _ = cv2.projectPoints(o, r, t, K, dist)
        per_pose.append(np.sqrt(np.mean(np.sum((p - i).reshape(-1, 2) ** 2, axis=1))))
    return K, dist.ravel()[:5], [r.ravel() for r in rv], [t.ravel() for t in tv], \
        np.array(per_pose)


def _check_projector(pose_rms: list[np.ndarray], poses: list[str], stage: str) -> None:
    """Refuse a projector error far above the cameras' (per-pose RMS px per device)."""
    rms = [float(np.sqrt(np.mean(r**2))) for r in pose_rms]
    cam = max(rms[:2])
    if rms[2] > max(PROJECTOR_FLOOR_PX, PROJECTOR_RATIO * cam):
        j = int(np.argmax(pose_rms[2]))
        raise CalibrationError(
            f"{poses[j]}, camera 0 and camera 1: the projector's reprojection error "
            f"({rms[2]:.3g} px RMS {stage}, {pose_rms[2][j]:.3g} px at {poses[j]}) is far above "
            f"the cameras' ({cam:.3g} px): the phase is wrong; likely causes: an uncorrected "
            "projector gamma (linearise the projector or use more phase steps) or a capture "
            "out of sync with the projector (each image must show its own pattern)")


def ellipse_offsets(layout: Layout, x: np.ndarray, obs: Observations, radius_mm: float,
                    sel: np.ndarray) -> np.ndarray:
    """Pixel offsets (k, 2) from the image of each circle's centre to the centre of its image
    (the projected ellipse), for the observations ``sel``: through the dual conic
    ``H diag(r^2, r^2, -1) H^T`` of the board-to-device plane homography (distortion applied to
    both points)."""
    intr = layout.intrinsics(x)
    Rp, tp = layout.poses(x)
    Re, te = layout.extrinsics(x)
    d, j = obs.dev[sel], obs.pose[sel]
    R = np.einsum("mij,mjk->mik", Re[d], Rp[j])
    t = np.einsum("mij,mj->mi", Re[d], tp[j]) + te[d]
    c = obs.object_points[obs.point[sel]]
    Hn = np.stack([R[:, :, 0], R[:, :, 1], t + np.einsum("mij,mj->mi", R[:, :, :2], c[:, :2])],
                  axis=2)  # board plane centred on the circle -> device (normalised)
    Q = np.diag([radius_mm**2, radius_mm**2, -1.0])
    M = np.einsum("mij,jk,mlk->mil", Hn, Q, Hn)
    ell = np.stack([M[:, 0, 2] / M[:, 2, 2], M[:, 1, 2] / M[:, 2, 2], np.ones(len(M))], axis=1)
    ctr = Hn[:, :, 2]
    return distort_project(ell, intr[d]) - distort_project(ctr, intr[d])


def _circle_corrected(views: _Views, obs: Observations, layout: Layout, x: np.ndarray,
                      board: CalibrationBoard) -> Observations:
    uv = obs.uv.copy()
    cams = obs.dev < 2
    uv[cams] -= ellipse_offsets(layout, x, obs, board.diameter_mm / 2, cams)
    proj = np.flatnonzero(obs.dev == 2)
    n = len(obs.object_points)
    dev, pose, point, pts = [obs.dev[~(obs.dev == 2)]], [obs.pose[obs.dev != 2]], \
        [obs.point[obs.dev != 2]], [uv[obs.dev != 2]]
    del proj
    for j in range(len(views.poses)):
        cams_uv = [uv[(obs.dev == c) & (obs.pose == j)] for c in range(2)]
        ids, p = views.projector_view(j, cams_uv, n)
        dev.append(np.full(len(ids), 2))
        pose.append(np.full(len(ids), j))
        point.append(ids)
        pts.append(p)
    return Observations(np.concatenate(dev), np.concatenate(pose), np.concatenate(point),
                        np.concatenate(pts), obs.object_points)


def _mean_rotation(Rs: list[np.ndarray]) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.sum(Rs, axis=0))
    R = U @ Vt
    return R if np.linalg.det(R) > 0 else U @ np.diag([1, 1, -1]) @ Vt


def calibrate(capture_dir: str | Path, board: CalibrationBoard | str | Path,
              distortion: tuple[DistortionModel, DistortionModel, DistortionModel] | None = None,
              projector_method: Method = "homography",
              settings: DecodeSettings | None = None) -> CalibrationResult:
    """Calibrate both cameras and the projector from a capture folder and a board (or a board
    file). ``distortion``: the model per device (camera 0, camera 1, projector), default
    ``k1k2p1p2k3`` for the cameras and ``k1k2`` for the projector."""
    import time

    t0 = time.perf_counter()
    if not isinstance(board, CalibrationBoard):
        board = load_board(board)
    models = list(distortion or ("k1k2p1p2k3", "k1k2p1p2k3", "k1k2"))
    capture = Capture(capture_dir)
    if len(capture.poses) < MIN_POSES:
        have = ", ".join(capture.poses) or "none"
        raise CalibrationError(
            f"{capture.directory}: {len(capture.poses)} usable pose(s) ({have}) seen by camera 0 "
            f"and camera 1; calibration needs at least {MIN_POSES} (10-20 recommended)")
    views = _gather(capture, board, projector_method, settings or DecodeSettings())
    t_feat = time.perf_counter()
    obj = board.object_points()
    _check_conditioning(views, obj)
    psize = capture.patterns.projector_size
    sizes = [views.camera_size, views.camera_size, psize]
    feats_per_dev = [views.cams[0], views.cams[1], views.proj]
    K, D, rv, tv, zrms = [], [], [], [], []
    for d in range(3):
        k, dist, r, t, e = _zhang(obj, feats_per_dev[d], sizes[d], models[d], DEVICE_NAMES[d],
                                  views.poses)
        K.append(k)
        D.append(dist)
        rv.append(r)
        tv.append(t)
        zrms.append(e)
    _check_projector(zrms, views.poses, "after Zhang's method")
    ext_r, ext_t = [], []
    R0 = [cv2.Rodrigues(r)[0] for r in rv[0]]
    for d in (1, 2):
        Rd = [cv2.Rodrigues(r)[0] for r in rv[d]]
        Rrel = _mean_rotation([a @ b.T for a, b in zip(Rd, R0, strict=True)])
        trel = np.median([td - Rrel @ t0_ for td, t0_ in zip(tv[d], tv[0], strict=True)], axis=0)
        ext_r.append(cv2.Rodrigues(Rrel)[0].ravel())
        ext_t.append(trel)
    layout = Layout(models, len(views.poses))
    x0 = initial_vector(layout, K, D, np.array(rv[0]), np.array(tv[0]), ext_r, ext_t)
    dev, pose, point, uv = [], [], [], []
    for d in range(3):
        for j, (ids, p) in enumerate(feats_per_dev[d]):
            dev.append(np.full(len(ids), d))
            pose.append(np.full(len(ids), j))
            point.append(ids)
            uv.append(p)
    obs = Observations(np.concatenate(dev), np.concatenate(pose), np.concatenate(point),
                       np.concatenate(uv), obj)
    sol = adjust(layout, x0, obs)
    if board.kind in ("circles", "asymmetric_circles"):
        # a circle's image is an ellipse whose centre is not the centre's image: take the
        # perspective offset off the cameras' points, carry them into the projector, adjust again
        obs = _circle_corrected(views, obs, layout, sol.x, board)
        sol = adjust(layout, sol.x, obs)
    t_ba = time.perf_counter()
    names = ["camera_0", "camera_1", "projector"]
    residuals, rms = [], {}
    pose_rms: dict[str, dict[str, float]] = {}  # device, pose: RMS px
    for d in range(3):
        sel = obs.dev == d
        e = sol.residuals[sel]
        rms[names[d]] = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
        pose_rms[names[d]] = {}
        for j, pname in enumerate(views.poses):
            s = sel & (obs.pose == j)
            pr = PoseResiduals(pname, names[d], obs.point[s], obs.uv[s], sol.residuals[s])
            residuals.append(pr)
            pose_rms[names[d]][pname] = pr.rms_px
    _check_projector([np.array(list(pose_rms[n].values())) for n in names], views.poses,
                     "after the bundle adjustment")
    for d in range(3):
        if not sol.fx_rel_std[d] <= MAX_FOCAL_REL_STD:
            raise CalibrationError(
                f"{views.poses[0]} .. {views.poses[-1]}, {DEVICE_NAMES[d]}: the focal length is "
                f"unconstrained by these poses (relative std {sol.fx_rel_std[d]:.2g}); tilt the "
                "board by 20-40 degrees about different axes in several poses")
    devices = []
    for d in range(3):
        devices.append(DeviceCalibration(name=names[d], K=sol.K[d], dist=sol.dist[d], R=sol.R[d],
                                         T=sol.T[d], size=tuple(int(s) for s in sizes[d])))
    rig = Rig(cameras=devices[:2], projector=devices[2])
    timings = {"features_s": t_feat - t0, "adjust_s": t_ba - t_feat,
               "total_s": time.perf_counter() - t0}
    return CalibrationResult(rig, rms, pose_rms, residuals,
                             {names[d]: float(sol.fx_rel_std[d]) for d in range(3)},
                             dict(zip(names, models, strict=True)), projector_method, views.poses, board,
                             timings)
