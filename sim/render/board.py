"""Calibration boards: exact feature geometry and a two-level diffuse albedo evaluated where
each ray hits (not a texture, not a tessellation).

Board frame (mm): ``x`` along the columns, ``y`` along the rows, ``z = 0`` the printed face,
seen from ``-z`` (a board with ``R = I`` faces cameras looking along world ``+z``). The board
covers ``[0, width_mm] x [0, height_mm]``. Features, in OpenCV's order (row by row):

- ``chessboard``: ``rows x columns`` squares of ``square_mm``, square ``(r, c)`` dark where
  ``r + c`` is even; features are the ``(rows - 1) x (columns - 1)`` inner corners
  ``((j + 1) s, (i + 1) s)``;
- ``circles``: ``rows x columns`` dark circles of ``circle_diameter_mm`` at
  ``((j + 1) p, (i + 1) p)``, ``p = pitch_mm``;
- ``asymmetric_circles``: ``rows`` staggered rows of ``columns`` circles, ``pitch_mm`` apart in
  a row, rows ``pitch_mm / 2`` apart and every odd row shifted by ``pitch_mm / 2``: centres
  ``((2 j + i % 2 + 2) p / 2, (i + 2) p / 2)``;
- ``charuco``: OpenCV's ``cv2.aruco.CharucoBoard`` of ``rows x columns`` squares, markers of
  ``marker_mm`` from ``dictionary``; features are its chessboard corners (ids row by row).

``apply_boards`` is the renderer's hook: for every ray of a traced transport whose pixel sees a
board, it integrates the albedo over the pixel's footprint on the board (around the ray's own
hit point, so a thin lens's rays blur it), scales the ray's weight by the mean albedo and moves
its projector coordinate to the albedo-weighted centroid of the footprint: to first order in the
pattern's variation across a pixel this is the pixel's integral of albedo x pattern.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from sim.optics.rig import DeviceCalibration
from sim.render.trace import Transport, normalized_grid

BoardKind = Literal["chessboard", "circles", "asymmetric_circles", "charuco"]
FOOTPRINT_SAMPLES = (144, 89)  # Fibonacci lattice (points, generator), mirrored in both axes,
# over a footprint where the albedo changes inside it: straight edges at any angle are
# integrated to ~1/500 of a pixel
CHARUCO_PX_PER_SQUARE = 120  # raster of the ChArUco markers (squares stay exact)


class CalibrationBoard(BaseModel):
    """A printed calibration target (see the module docstring for the frame and features)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: BoardKind = Field(description="chessboard, circles, asymmetric_circles or charuco")
    rows: int = Field(ge=2, description="squares (chessboard, charuco) or circle rows")
    columns: int = Field(ge=2, description="squares (chessboard, charuco) or circles per row")
    square_mm: float | None = Field(None, gt=0, description="square side, mm (chessboard, charuco)")
    pitch_mm: float | None = Field(None, gt=0, description="circle spacing in a row, mm (circles)")
    circle_diameter_mm: float | None = Field(None, gt=0, description="circle diameter, mm "
                                             "(default 0.4 x the nearest-neighbour distance)")
    marker_mm: float | None = Field(None, gt=0, description="ChArUco marker side, mm")
    dictionary: str = Field("DICT_5X5_100", description="ChArUco marker dictionary (cv2.aruco)")
    light_albedo: float = Field(0.9, gt=0, le=1, description="albedo of the white print")
    dark_albedo: float = Field(0.1, ge=0, le=1, description="albedo of the dark print")

    @model_validator(mode="after")
    def _check(self) -> CalibrationBoard:
        square = self.kind in ("chessboard", "charuco")
        if square and self.square_mm is None:
            raise ValueError(f"a {self.kind} board needs square_mm")
        if not square and self.pitch_mm is None:
            raise ValueError(f"a {self.kind} board needs pitch_mm")
        if self.kind == "chessboard" and (self.rows + self.columns) % 2 == 0:
            raise ValueError(f"a chessboard needs one odd and one even count of squares (rows "
                             f"{self.rows}, columns {self.columns}) so that its orientation is "
                             "unambiguous")
        if self.kind == "charuco":
            if self.marker_mm is None or self.marker_mm >= self._square:
                raise ValueError("a charuco board needs marker_mm smaller than square_mm")
            if not hasattr(cv2.aruco, self.dictionary):
                raise ValueError(f"unknown ArUco dictionary {self.dictionary!r} "
                                 "(e.g. DICT_5X5_100)")
        if self.dark_albedo >= self.light_albedo:
            raise ValueError("dark_albedo must be below light_albedo")
        return self

    @property
    def _square(self) -> float:
        """Square side, mm, of a chessboard or charuco board (the validator requires it)."""
        assert self.square_mm is not None, f"a {self.kind} board has no square_mm"
        return self.square_mm

    @property
    def _pitch(self) -> float:
        """Circle spacing in a row, mm, of a circle grid (the validator requires it)."""
        assert self.pitch_mm is not None, f"a {self.kind} board has no pitch_mm"
        return self.pitch_mm

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV pattern size (features per row, feature rows)."""
        if self.kind in ("chessboard", "charuco"):
            return self.columns - 1, self.rows - 1
        return self.columns, self.rows

    @property
    def diameter_mm(self) -> float:
        """Circle diameter, mm (circle grids)."""
        if self.circle_diameter_mm is not None:
            return self.circle_diameter_mm
        nn = self._pitch if self.kind == "circles" else self._pitch / np.sqrt(2.0)
        return 0.4 * nn

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the printed board, mm."""
        if self.kind in ("chessboard", "charuco"):
            return self.columns * self._square, self.rows * self._square
        p = self._pitch
        if self.kind == "circles":
            return (self.columns + 1) * p, (self.rows + 1) * p
        return (2 * self.columns + 3) * p / 2, (self.rows + 3) * p / 2

    def object_points(self) -> np.ndarray:
        """Every feature (n, 3) in the board frame, mm, in OpenCV's order (row by row)."""
        nx, ny = self.pattern_size
        i, j = np.mgrid[0:ny, 0:nx]
        i, j = i.ravel().astype(float), j.ravel().astype(float)
        if self.kind in ("chessboard", "charuco"):
            xy = np.stack([(j + 1) * self._square, (i + 1) * self._square], axis=1)
        elif self.kind == "circles":
            xy = np.stack([(j + 1) * self._pitch, (i + 1) * self._pitch], axis=1)
        else:
            p = self._pitch
            xy = np.stack([(2 * j + i % 2 + 2) * p / 2, (i + 2) * p / 2], axis=1)
        return np.concatenate([xy, np.zeros((len(xy), 1))], axis=1)

    @cached_property
    def charuco(self):
        """The ``cv2.aruco.CharucoBoard`` (charuco boards only)."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.columns, self.rows), self._square, self.marker_mm, d)

    @cached_property
    def _charuco_raster(self) -> np.ndarray:
        n = CHARUCO_PX_PER_SQUARE
        img = self.charuco.generateImage((self.columns * n, self.rows * n), marginSize=0,
                                         borderBits=1)
        return img > 127

    def is_light(self, xy_mm: np.ndarray) -> np.ndarray:
        """Whether board points (..., 2) mm lie on the white print (outside the board: white)."""
        x, y = np.asarray(xy_mm)[..., 0], np.asarray(xy_mm)[..., 1]
        if self.kind == "chessboard":
            r, c = np.floor(y / self._square), np.floor(x / self._square)
            inside = (r >= 0) & (r < self.rows) & (c >= 0) & (c < self.columns)
            return ~inside | ((r + c) % 2 == 1)
        if self.kind == "charuco":
            ras = self._charuco_raster
            s = CHARUCO_PX_PER_SQUARE / self._square
            r, c = np.floor(y * s).astype(np.int64), np.floor(x * s).astype(np.int64)
            inside = (r >= 0) & (r < ras.shape[0]) & (c >= 0) & (c < ras.shape[1])
            return ~inside | ras[np.clip(r, 0, ras.shape[0] - 1), np.clip(c, 0, ras.shape[1] - 1)]
        centres = self.object_points()[:, :2]
        rad2 = (self.diameter_mm / 2) ** 2
        if self.kind == "circles":
            p = self._pitch
            j, i = np.rint(x / p) - 1, np.rint(y / p) - 1
            ok = (i >= 0) & (i < self.rows) & (j >= 0) & (j < self.columns)
            return ~ok | ((x - (j + 1) * p) ** 2 + (y - (i + 1) * p) ** 2 > rad2)
        dark = np.zeros(np.shape(x), bool)
        h = self._pitch / 2
        # asymmetric: the nearest centre is one of the lattice points (2j + i%2 + 2, i + 2) h
        i0 = np.rint(y / h) - 2
        for di in (-1.0, 0.0, 1.0):
            i = i0 + di
            par = np.mod(i, 2)
            j = np.rint((x / h - par - 2) / 2)
            ok = (i >= 0) & (i < self.rows) & (j >= 0) & (j < self.columns)
            cx, cy = (2 * j + par + 2) * h, (i + 2) * h
            dark |= ok & ((x - cx) ** 2 + (y - cy) ** 2 <= rad2)
        del centres
        return ~dark

    def albedo(self, xy_mm: np.ndarray) -> np.ndarray:
        """Diffuse albedo at board points (..., 2) mm."""
        return np.where(self.is_light(xy_mm), self.light_albedo, self.dark_albedo)


@dataclass(frozen=True)
class PlacedBoard:
    """A board in a scene: scene object index, the board and its pose (board to world
    ``X = R x + t``, mm)."""

    object_index: int
    board: CalibrationBoard
    R: np.ndarray
    t: np.ndarray


def _plane_hits(board: PlacedBoard, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Board-frame points (n, 2) mm where world rays from ``origin`` (3,) or (n, 3) along
    ``dirs`` (n, 3) meet the board plane."""
    o_b = (np.asarray(origin) - board.t) @ board.R  # board frame
    d_b = dirs @ board.R
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o_b[..., 2] / d_b[:, 2]
    return o_b[..., :2] + s[:, None] * d_b[:, :2]


def _camera_xy(cam: DeviceCalibration, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates (n, 2) of flat pixels and their Jacobian (n, 2, 2) per pixel."""
    w, h = cam.size
    v, u = np.divmod(pixels, w)
    grid = normalized_grid(cam)
    if grid is None:
        Kinv = np.linalg.inv(cam.K_array)
        xy = np.stack([u, v, np.ones_like(u)], axis=1).astype(float) @ Kinv.T
        J = np.broadcast_to(Kinv[:2, :2], (len(pixels), 2, 2))
        return xy[:, :2], J
    xy = grid[pixels]
    ul, ur = np.maximum(u - 1, 0), np.minimum(u + 1, w - 1)
    vu, vd = np.maximum(v - 1, 0), np.minimum(v + 1, h - 1)
    du = (grid[v * w + ur] - grid[v * w + ul]) / (ur - ul)[:, None]
    dv = (grid[vd * w + u] - grid[vu * w + u]) / (vd - vu)[:, None]
    return xy, np.stack([du, dv], axis=2)


def _device_dirs(dev: DeviceCalibration, xy: np.ndarray) -> np.ndarray:
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    return d @ dev.R_array  # world directions (R^T d per row)


def _projector_xy(proj: DeviceCalibration, uv: np.ndarray) -> np.ndarray:
    """Undistorted normalised coordinates of projector pixels (n, 2), iterated to 1e-12."""
    if not np.any(proj.dist_array):
        Kinv = np.linalg.inv(proj.K_array)
        return (np.concatenate([uv, np.ones((len(uv), 1))], axis=1) @ Kinv.T)[:, :2]
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14)
    # the stubs shipped with opencv-python lack undistortPointsIter (it exists at runtime)
    out = cv2.undistortPointsIter(  # type: ignore[attr-defined]
        uv.reshape(-1, 1, 2).astype(np.float64), proj.K_array, proj.dist_array, None, None, crit)
    return out.reshape(-1, 2)


def _footprint_integral(board: CalibrationBoard, centre: np.ndarray, J: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Mean albedo (n,) over footprints ``centre + J s``, ``s`` in the unit pixel square, and
    the albedo-weighted centroid offset (n, 2) mm (0 where the albedo is uniform)."""
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]])
    c_pts = centre[:, None, :] + np.einsum("nij,kj->nki", J, corners)
    light = board.is_light(c_pts)
    mixed = np.any(light != light[:, :1], axis=1)
    mean = np.where(light[:, 0], board.light_albedo, board.dark_albedo).astype(np.float64)
    shift = np.zeros_like(centre)
    if np.any(mixed):
        n, gen = FOOTPRINT_SAMPLES
        k = np.arange(n)
        s = np.stack([(k + 0.5) / n - 0.5, np.mod(k * gen + 0.5, n) / n - 0.5], axis=1)
        # mirrored in both axes: no centroid bias along an axis-aligned edge
        s = np.concatenate([s, s * [-1, 1], s * [1, -1], -s])
        off = np.einsum("nij,kj->nki", J[mixed], s)
        a = board.albedo(centre[mixed][:, None, :] + off)
        am = a.mean(axis=1)
        mean[mixed] = am
        shift[mixed] = np.einsum("nk,nki->ni", a, off) / (a.sum(axis=1)[:, None])
    return mean, shift


def _corner_xy(cam: DeviceCalibration, pixels: np.ndarray) -> np.ndarray:
    """Normalised coordinates (n, 4, 2) of the four corners of flat pixels (u -+ 0.5, v -+ 0.5;
    order (-,-), (+,-), (-,+), (+,+)); through the pixel-centre grid and its differences where
    the camera is distorted (second order in the pixel)."""
    xy, J = _camera_xy(cam, pixels)
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.5, 0.5]])
    return xy[:, None, :] + np.einsum("nij,kj->nki", J, corners)


def _apply_pinhole(tr: Transport, b: PlacedBoard, rows: np.ndarray, cam: DeviceCalibration,
                   projector: DeviceCalibration) -> None:
    """``apply_boards`` for one ray per pixel: the footprint is the pixel's four corners."""
    cxy = _corner_xy(cam, tr.pixels[rows]).reshape(-1, 2)
    corners = _plane_hits(b, cam.centre_world, _device_dirs(cam, cxy)).reshape(-1, 4, 2)
    light = b.board.is_light(corners)
    mixed = np.any(light != light[:, :1], axis=1)
    w = tr.weight[rows, 0]
    w *= np.where(light[:, 0], b.board.light_albedo, b.board.dark_albedo).astype(np.float32)
    m = np.flatnonzero(mixed & (w > 0))
    if len(m):
        c = corners[m]
        centre = c.mean(axis=1)
        J = np.stack([0.5 * (c[:, 1] - c[:, 0] + c[:, 3] - c[:, 2]),
                      0.5 * (c[:, 2] - c[:, 0] + c[:, 3] - c[:, 1])], axis=2)
        mean, shift = _footprint_integral(b.board, centre, J)
        base = np.where(light[m, 0], b.board.light_albedo, b.board.dark_albedo)
        w[m] *= (mean / base).astype(np.float32)
        p = centre + shift
        world = np.concatenate([p, np.zeros((len(p), 1))], axis=1) @ b.R.T + b.t
        tr.proj_uv[rows[m], 0] = projector.project(world).astype(np.float32)
    tr.weight[rows, 0] = w


def apply_boards(tr: Transport, boards: tuple[PlacedBoard, ...], cam: DeviceCalibration,
                 projector: DeviceCalibration) -> Transport:
    """The transport with every board's albedo applied (in place; see the module docstring).
    A pixel's lens rays are taken to hit the object its chief ray hits."""
    nk = tr.weight.shape[1]
    for b in boards:
        rows = np.flatnonzero(tr.object_id == b.object_index)
        if len(rows) == 0:
            continue
        if nk == 1:
            _apply_pinhole(tr, b, rows, cam, projector)
            continue
        xy, Jxy = _camera_xy(cam, tr.pixels[rows])
        dirs = _device_dirs(cam, xy)
        centre = _plane_hits(b, cam.centre_world, dirs)
        # footprint Jacobian d(board)/d(pixel) by central differences of the plane hits
        eps = 0.5
        Jb = np.empty((len(rows), 2, 2))
        for a in range(2):
            dxy = Jxy[:, :, a] * eps
            hp = _plane_hits(b, cam.centre_world, _device_dirs(cam, xy + dxy))
            hm = _plane_hits(b, cam.centre_world, _device_dirs(cam, xy - dxy))
            Jb[:, :, a] = (hp - hm) / (2 * eps)
        for k in range(nk):
            w = tr.weight[rows, k]
            live = np.flatnonzero(w > 0)
            if len(live) == 0:
                continue
            r = rows[live]
            if nk == 1:  # a pinhole: the ray is the chief ray
                hit = centre[live]
            else:
                pxy = _projector_xy(projector, tr.proj_uv[r, k].astype(np.float64))
                hit = _plane_hits(b, projector.centre_world, _device_dirs(projector, pxy))
            mean, shift = _footprint_integral(b.board, hit, Jb[live])
            tr.weight[r, k] = (w[live] * mean).astype(np.float32)
            moved = np.flatnonzero(np.any(shift != 0, axis=1))
            if len(moved):
                p = hit[moved] + shift[moved]
                world = np.concatenate([p, np.zeros((len(p), 1))], axis=1) @ b.R.T + b.t
                tr.proj_uv[r[moved], k] = projector.project(world).astype(np.float32)
    return tr
