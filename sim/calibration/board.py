"""Board files and feature detection.

A board file (TOML) holds one ``sim.render.board.CalibrationBoard``::

    kind = "chessboard"        # chessboard | circles | asymmetric_circles | charuco
    rows = 7                   # squares (chessboard, charuco) or circle rows
    columns = 10               # squares or circles per row
    square_mm = 20.0           # chessboard, charuco; circle grids give pitch_mm
    # marker_mm = 15.0         # charuco: marker side, mm
    # dictionary = "DICT_5X5_100"

``detect`` finds the features in one image (8-bit, 16-bit or float) and returns them in the
board's feature order (``CalibrationBoard.object_points``) with their ids.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pydantic import ValidationError

from sim.calibration.errors import CalibrationError
from sim.render.board import CalibrationBoard
from sim.validation import format_validation_error, read_toml

SUBPIX_WINDOW_PX = 5  # cornerSubPix half window
MIN_CHARUCO_CORNERS = 6


def load_board(path: str | Path) -> CalibrationBoard:
    """Read a board file (TOML, see the module docstring); errors name the file and field."""
    path = Path(path)
    raw = read_toml(path, "board file")
    try:
        return CalibrationBoard.model_validate(raw)
    except ValidationError as exc:
        raise CalibrationError(format_validation_error(str(path), exc)) from exc


@dataclass(frozen=True)
class Features:
    """Board features found in one image: ``ids`` (n,) indices into the board's
    ``object_points()`` and their pixels ``uv`` (n, 2) (centres at integers)."""

    ids: np.ndarray
    uv: np.ndarray


def to_uint8(image: np.ndarray) -> np.ndarray:
    """An image of any depth scaled to 8 bits by its 99.9th percentile (for the detectors)."""
    im = np.asarray(image, dtype=np.float64)
    top = float(np.percentile(im, 99.9))
    if top <= 0:
        return np.zeros(im.shape, np.uint8)
    return np.clip(im * (255.0 / top), 0, 255).round().astype(np.uint8)


def _orient(board: CalibrationBoard, uv: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """Grid features reordered to the board's order: rows run left to right as seen on a board
    facing the camera (a positive 2-D cross product of the row and column directions), and the
    180-degree ambiguity resolved by the dark square at the first corner (chessboard) or by the
    first feature's being nearest the image's top-left (circle grids)."""
    nx, ny = board.pattern_size
    g = uv.reshape(ny, nx, 2)
    a, b = g[0, -1] - g[0, 0], g[-1, 0] - g[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:
        g = g[:, ::-1]
    if board.kind == "chessboard":
        a, b = (g[0, 1] - g[0, 0]), (g[1, 0] - g[0, 0])
        p0 = g[0, 0] - 0.5 * a - 0.5 * b  # centre of square (0, 0): dark
        p1 = g[0, 0] + 0.5 * a - 0.5 * b  # centre of square (0, 1): light
        h, w = gray.shape

        def val(p):
            x, y = int(np.clip(round(p[0]), 0, w - 1)), int(np.clip(round(p[1]), 0, h - 1))
            return float(gray[y, x])

        if val(p0) > val(p1):
            g = g[::-1, ::-1]
    elif np.sum(g[-1, -1]) < np.sum(g[0, 0]):
        g = g[::-1, ::-1]
    return g.reshape(-1, 2)


def detect(image: np.ndarray, board: CalibrationBoard) -> Features | None:
    """The board's features in one image, or None where the board is not found."""
    gray = to_uint8(image)
    nx, ny = board.pattern_size
    if board.kind == "chessboard":
        # found on a half-size image (fast), then the edge-line refinement at full size
        half = cv2.resize(gray, (gray.shape[1] // 2, gray.shape[0] // 2),
                          interpolation=cv2.INTER_AREA)
        ok, corners = cv2.findChessboardCornersSB(half, (nx, ny))
        if ok:
            corners = corners * 2.0 + 0.5
        else:
            ok, corners = cv2.findChessboardCornersSB(gray, (nx, ny),
                                                      flags=cv2.CALIB_CB_EXHAUSTIVE)
        if not ok:
            return None
        uv: np.ndarray = corners.reshape(-1, 2).astype(np.float32)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
        w = SUBPIX_WINDOW_PX
        uv = cv2.cornerSubPix(gray, uv.reshape(-1, 1, 2), (w, w), (-1, -1), crit).reshape(-1, 2)
        uv = _orient(board, uv.astype(np.float64), gray)
        uv = refine_corners(image, uv, board.pattern_size)
        return Features(np.arange(len(uv)), uv)
    if board.kind in ("circles", "asymmetric_circles"):
        flags = (cv2.CALIB_CB_SYMMETRIC_GRID if board.kind == "circles"
                 else cv2.CALIB_CB_ASYMMETRIC_GRID)
        params = cv2.SimpleBlobDetector.Params()
        params.maxArea = float(gray.size) / 20
        params.minArea = 10.0
        det = cv2.SimpleBlobDetector.create(params)
        ok, centres = cv2.findCirclesGrid(gray, (nx, ny), flags=flags, blobDetector=det)
        if not ok:
            return None
        uv = _orient(board, centres.reshape(-1, 2).astype(np.float64), gray)
        uv = refine_circles(image, uv)
        return Features(np.arange(len(uv)), uv)
    detector = cv2.aruco.CharucoDetector(board.charuco)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    ids = ids.ravel().astype(np.int64)
    square, marker = board.square_mm, board.marker_mm
    assert square is not None and marker is not None, "a charuco board has both (validated)"
    clear = (square - marker) / (2 * square)
    uv = refine_corners(image, corners.reshape(-1, 2).astype(np.float64), (nx, ny), ids, clear)
    return Features(ids, uv)


def refine_circles(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Circle centres (n, 2) refined to the grey-level centroid of each dark blob: the white
    around it is a plane fitted over an annulus (the shading varies across the board), a
    pixel's weight is how much darker than that plane it is, over a disc of 1.6 times the
    blob's radius. On area-integrated images this is the centroid of the circle's image, the
    projected ellipse's centre."""
    im = np.asarray(image, dtype=np.float64)
    h, w = im.shape
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    np.fill_diagonal(d, np.inf)
    out = uv.copy()
    for i, (u, v) in enumerate(uv):
        r = 0.5 * float(d[i].min())
        x0, x1 = max(int(u - r), 0), min(int(u + r) + 2, w)
        y0, y1 = max(int(v - r), 0), min(int(v + r) + 2, h)
        if x1 - x0 < 5 or y1 - y0 < 5:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1]
        rr = np.hypot(xx - u, yy - v)
        win = im[y0:y1, x0:x1]
        disc = rr <= r
        lo, hi = np.percentile(win[disc], [2, 98])
        rc = np.sqrt(np.sum(disc & (win < 0.5 * (lo + hi))) / np.pi)  # blob radius, px
        ring = (rr >= 1.6 * rc + 2) & disc
        if rc < 1 or ring.sum() < 10:
            continue
        A = np.stack([np.ones(ring.sum()), xx[ring] - u, yy[ring] - v], axis=1)
        coef = np.linalg.lstsq(A, win[ring], rcond=None)[0]
        bg = coef[0] + coef[1] * (xx - u) + coef[2] * (yy - v)
        wgt = np.where(rr <= 1.6 * rc + 1, np.clip(bg - win, 0, None), 0.0)
        total = wgt.sum()
        if total > 0:
            out[i] = (np.sum(wgt * xx) / total, np.sum(wgt * yy) / total)
    return out


EDGE_WINDOW_PX = 6  # half length of the scan across an edge
EDGE_GAP_PX = 4.0  # edge samples start this far from the corner


def _edge_points(im: np.ndarray, c: np.ndarray, d: np.ndarray, reach: float | np.floating,
                 half_window: int = EDGE_WINDOW_PX) -> np.ndarray:
    """Sub-pixel points (m, 2) of the straight edge through corner ``c`` along unit ``d``,
    from ``EDGE_GAP_PX`` to ``reach`` px on both sides. Each point comes from one pixel row
    or column across the edge: the edge sits where the normalised intensity's integral says
    (``first - 0.5 + sum(1 - n)`` from the dark side), exact for an area-sampled step under any
    symmetric blur narrower than the window."""
    h, w = im.shape
    L = half_window
    ends = max(1, min(3, L // 2))
    across_rows = abs(d[0]) >= abs(d[1])  # a near-horizontal edge: scan each column
    a = 0 if across_rows else 1  # the coordinate stepped along the edge
    pts = []
    for sign in (-1.0, 1.0):
        s0, s1 = c[a] + sign * EDGE_GAP_PX * abs(d[a]), c[a] + sign * reach * abs(d[a])
        lo, hi = sorted((s0, s1))
        for k in range(int(np.ceil(lo)), int(np.floor(hi)) + 1):
            o = c[1 - a] + (k - c[a]) * d[1 - a] / d[a]  # the edge's other coordinate
            first = int(round(o)) - L
            if first < 0 or first + 2 * L >= (h if across_rows else w) or not 0 <= k < (
                    w if across_rows else h):
                continue
            prof = im[first : first + 2 * L + 1, k] if across_rows else \
                im[k, first : first + 2 * L + 1]
            top, bottom = prof[:ends].mean(), prof[-ends:].mean()
            if abs(bottom - top) <= 0:
                continue
            n = np.clip((prof - top) / (bottom - top), -0.5, 1.5)  # 0 at the start, 1 at the end
            e = first - 0.5 + float(np.sum(1.0 - n))
            pts.append((k, e) if across_rows else (e, k))
    return np.asarray(pts, dtype=np.float64).reshape(-1, 2)


def _fit_line(p: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Line ``n . x = r`` (unit n) through points (m, 2), total least squares."""
    if len(p) < 4:
        return None
    m = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - m)
    n = vt[1]
    return n, float(n @ m)


def refine_corners(image: np.ndarray, uv: np.ndarray, pattern_size: tuple[int, int],
                   ids: np.ndarray | None = None, clear_fraction: float = 0.5) -> np.ndarray:
    """Chessboard corners (n, 2) refined to the intersection of the two edge lines through
    each: each line fitted to sub-pixel edge points (``_edge_points``) within 0.6 squares of
    the corner. ``ids``: the corners' indices in the grid (``pattern_size`` = per row, rows;
    default: the whole grid in order); the edge directions come from neighbouring corners.
    ``clear_fraction``: how far from an edge, as a fraction of the square, the print stays
    plain (ChArUco: the margin around the markers); the scan across an edge stays inside it.
    Corners whose edges cannot be fitted keep their position."""
    im = np.asarray(image, dtype=np.float64)
    nx, ny = pattern_size
    ids = np.arange(nx * ny) if ids is None else np.asarray(ids)
    where = {int(k): i for i, k in enumerate(ids)}
    out = np.asarray(uv, dtype=np.float64).copy()
    for n, k in enumerate(ids):
        i, j = divmod(int(k), nx)
        c = out[n].copy()
        lines = []
        for di, dj in ((0, 1), (1, 0)):
            ends = [(i + s * di, j + s * dj) for s in (-1, 1)]
            ends = [(a, b) for a, b in ends if 0 <= a < ny and 0 <= b < nx
                    and a * nx + b in where]
            pts = [uv[where[a * nx + b]] for a, b in ends]
            if len(pts) == 2:
                v, steps = pts[1] - pts[0], 2
            elif len(pts) == 1:
                a, b = ends[0]
                v, steps = (pts[0] - c) * (1 if (a - i) + (b - j) > 0 else -1), 1
            else:
                break
            side = np.linalg.norm(v) / steps
            d = v / np.linalg.norm(v)
            reach = 0.6 * side
            if reach <= EDGE_GAP_PX + 2:
                break
            half = int(min(EDGE_WINDOW_PX, np.floor(side * clear_fraction) - 1))
            line = _fit_line(_edge_points(im, c, d, reach, half)) if half >= 2 else None
            if line is None:
                break
            lines.append(line)
        if len(lines) == 2:
            A = np.array([lines[0][0], lines[1][0]])
            if abs(np.linalg.det(A)) > 0.1:
                p = np.linalg.solve(A, [lines[0][1], lines[1][1]])
                if np.linalg.norm(p - c) < 2.0:
                    out[n] = p
    return out
