"""Alignment (``ltc align``): where the LCD centre appears at each depth, and the tilt of the
camera's optical axis against the stage axis that this implies.

At each depth the LCD shows the arms of a crosshair through its centre, one at a time (so
neither hides the other), then the same arms shifted by ``s`` LCD pixels. Each arm's image
is located row by row (column by column) by intensity centroids and fitted with a straight
line; two arms cross at a point. The unshifted arms give the LCD centre's image ``p``; the
shifted ones give the local image scale ``J`` (camera px per LCD px, a 2x2 Jacobian) and the
magnification ``m = sqrt|det J|``, which is ``f * pitch / distance``.

As the stage moves the camera along its axis, ``p = A + B m``: ``A`` is where the stage axis
points (its vanishing point in the image) and ``B`` the lateral offset of the LCD centre from
the optical axis, in LCD pixels; fitting that line over the depths needs no distances. The
image scale of the angles about the axis is the effective focal length
``f = 1 / (pitch * d(1/m)/dz)``, measured from how the magnification changes with the stage
reading z (for a pinhole ``1/m = Z / (f pitch)``). Measuring it, rather than taking the lens's
nominal focal length, matters with a defocused, vignetted lens: the centroid of a blurred
image follows the centroid of the vignetted pupil, which moves with the field angle, so the
defocused image is scaled about the principal point by ``k(Z) = kappa + e / Z``. Then
``p - c = f (t Z + b) / (kappa Z + e)`` and ``m = f pitch / (kappa Z + e)``: still a line in m,
with ``A - c = f t / kappa``, and ``d(1/m)/dz = kappa / (f pitch)`` gives exactly the
``f / kappa`` needed (the fake bench's lens makes kappa ~ 0.88, a 14 % error otherwise).
The offset ``B`` is then ``(b - e t / kappa) / pitch``: exact only once the tilt is zero.

With the principal point ``c`` the stage axis's direction in the camera frame is
``((A_u - c_u) / f, (A_v - c_v) / f, 1)``; in the convention of the fake bench (camera
rotated about its x axis by ``t_x``, then its y axis by ``t_y``) that direction is
``(-tan t_y / cos t_x, tan t_x, 1)``, which gives the reported tilt.
"""

from __future__ import annotations

import numpy as np

from drivers.frame_code import frame_code_rect
from station.acquisition.backend import Hardware, open_hardware
from station.acquisition.config import StationConfig
from station.acquisition.gamma import capture_after
from station.errors import StationError

ROW_SIGNAL_FRACTION = 0.2  # rows used: signal >= this fraction of the best row's
PROFILE_FRACTION = 0.03  # a row's profile counts while above this fraction of its peak


class AlignError(StationError):
    """The alignment could not be measured; the message says at which depth and why."""


def arm_image(size: tuple[int, int], axis: str, shift_px: int = 0) -> tuple[np.ndarray, float]:
    """One crosshair arm through the LCD centre (+ ``shift_px``) on black: (h, w) uint8 image
    and the arm's centre line in LCD pixels. ``axis`` "x": a vertical line (it marks an x);
    "y": a horizontal one. Two pixels wide on an even dimension, three on an odd one, so it is
    centred exactly on ``(n - 1) / 2 + shift_px``."""
    w, h = size
    n = w if axis == "x" else h
    width = 2 if n % 2 == 0 else 3
    lo = (n - width) // 2 + shift_px
    if lo < 0 or lo + width > n:
        raise AlignError(f"crosshair shift {shift_px} px puts the arm off the {w}x{h} LCD")
    img = np.zeros((h, w), np.uint8)
    if axis == "x":
        img[:, lo : lo + width] = 255
    else:
        img[lo : lo + width, :] = 255
    return img, lo + (width - 1) / 2


def fit_arm(image: np.ndarray, background: np.ndarray, axis: str) -> tuple[float, float]:
    """Image line ``coord = a + b t`` of a crosshair arm: for axis "x" (a vertical arm) coord is
    the column u and t the row v; for "y" coord is v and t is u. Per row (column), the
    centroid of the profile around its peak; rows weighted by their signal."""
    d = np.asarray(image, dtype=np.float64) - np.asarray(background, dtype=np.float64)
    if axis == "y":
        d = d.T
    d = np.maximum(d, 0.0)
    peak_idx = d.argmax(axis=1)
    peak = d.max(axis=1)
    ts, cs, ws = [], [], []
    for t in np.flatnonzero((peak > 0) & (peak >= ROW_SIGNAL_FRACTION * peak.max())):
        row, k = d[t], peak_idx[t]
        above = row > PROFILE_FRACTION * peak[t]
        lo = k - np.argmin(above[k::-1]) + 1 if not above[: k + 1].all() else 0
        hi = k + np.argmin(above[k:]) if not above[k:].all() else len(row)
        if lo == 0 or hi == len(row):
            continue  # the profile runs off the image: its centroid would be biased
        seg = row[lo:hi]
        ts.append(t)
        cs.append(float((seg * np.arange(lo, hi)).sum() / seg.sum()))
        ws.append(float(seg.sum()))
    if len(ts) < 3:
        raise AlignError(f"the crosshair arm along {axis} is not seen (only {len(ts)} usable "
                         "lines of pixels): is the LCD centre in the camera's view?")
    b, a = np.polyfit(np.array(ts, float), np.array(cs), 1, w=np.sqrt(ws))
    return float(a), float(b)


def cross(vertical: tuple[float, float], horizontal: tuple[float, float]) -> np.ndarray:
    """Image point (u, v) where the arms ``u = a + b v`` and ``v = c + d u`` cross."""
    a, b = vertical
    c, d = horizontal
    u = (a + b * c) / (1.0 - b * d)
    return np.array([u, c + d * u])


def fit_axis(points: np.ndarray, magnification: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                     float | None]:
    """Fit ``p = A + B m`` to image points (D, 2) at magnifications (D,): returns A (2,) px,
    B (2,) LCD px, and the RMS residual (px; None with two depths)."""
    m = np.asarray(magnification, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    if len(m) < 2 or np.ptp(m) <= 0:
        raise AlignError("need at least two depths with different magnifications")
    design = np.stack([np.ones_like(m), m], axis=1)
    coef, *_ = np.linalg.lstsq(design, pts, rcond=None)
    resid = pts - design @ coef
    rms = float(np.sqrt(np.mean(resid**2))) if len(m) > 2 else None
    return coef[0], coef[1], rms


def effective_focal_px(stage_mm: np.ndarray, magnification: np.ndarray, pitch_mm: float) -> float:
    """Focal length (px) that scales angles about the stage axis: ``1 / (pitch d(1/m)/dz)``
    from magnifications (D,) (camera px per LCD px) at stage readings (D,) mm."""
    slope = np.polyfit(np.asarray(stage_mm, float), 1.0 / np.asarray(magnification, float), 1)[0]
    if not slope > 0:
        raise AlignError(f"the image does not shrink as the stage moves away (d(1/m)/dz = "
                         f"{slope:.3g} per mm): are the depths distinct and the stage moving?")
    return float(1.0 / (pitch_mm * slope))


def tilt_from_axis(vanishing_px: np.ndarray, principal_px: np.ndarray,
                   focal_px: float) -> tuple[float, float]:
    """Tilt (about camera x, then y; degrees) whose stage axis points at ``vanishing_px``."""
    xn, yn = (np.asarray(vanishing_px) - np.asarray(principal_px)) / focal_px
    tx = np.arctan(yn)
    ty = np.arctan(-xn * np.cos(tx))
    return float(np.degrees(tx)), float(np.degrees(ty))


def measure_depth(hw: Hardware, config: StationConfig, shift_px: int) -> dict:
    """LCD centre image point, Jacobian and magnification at the current stage position."""
    size = hw.display.size

    def capture(img: np.ndarray) -> np.ndarray:
        shown = hw.show_settled(img, config.display.settled_s)
        return capture_after(hw, shown.swap_time, config).astype(np.float64)

    background = capture(np.zeros(size[::-1], np.uint8))
    arms = {}
    for axis in ("x", "y"):
        for s in (0, shift_px):
            img, _ = arm_image(size, axis, s)
            arms[axis, s] = fit_arm(capture(img), background, axis)
    p0 = cross(arms["x", 0], arms["y", 0])
    jac = np.stack([cross(arms["x", shift_px], arms["y", 0]) - p0,
                    cross(arms["x", 0], arms["y", shift_px]) - p0], axis=1) / shift_px
    return {"lcd_centre_px": p0, "jacobian": jac, "magnification": float(np.sqrt(abs(np.linalg.det(jac))))}


def run_align(config: StationConfig, *, hw: Hardware | None = None,
              shift_px: int | None = None) -> dict:
    """Measure at every configured depth and fit the stage axis; returns a JSON-able report."""
    if hw is None:
        with open_hardware(config) as opened:
            return run_align(config, hw=opened, shift_px=shift_px)
    w, h = hw.display.size
    s = shift_px or max(2, min(w, h) // 12)
    for axis in ("x", "y"):
        arm_image((w, h), axis, s)  # a shift off the LCD fails here, before anything moves
    hw.display.set_lut(None)
    if not hw.stage.is_homed:
        hw.stage.home()
    cam_w, cam_h = hw.camera.size
    k = config.camera.matrix
    pp = np.array((k[0][2], k[1][2]) if k else ((cam_w - 1) / 2, (cam_h - 1) / 2))
    lcd_c = np.array([(w - 1) / 2, (h - 1) / 2])
    code = None
    if config.frame_check.enabled:
        x, y, cw, ch = frame_code_rect(config.frame_check.layout((w, h)), (w, h))
        code = np.array([[x, y], [x + cw - 1, y], [x, y + ch - 1], [x + cw - 1, y + ch - 1]])
    depths = []
    for z in config.depths_mm:
        measured = hw.stage.move_to(z)
        d = measure_depth(hw, config, s)
        inv = np.linalg.inv(d["jacobian"])
        corners = np.array([[0, 0], [cam_w - 1, 0], [0, cam_h - 1], [cam_w - 1, cam_h - 1]])
        seen = (corners - d["lcd_centre_px"]) @ inv.T + lcd_c
        entry = {
            "depth_mm": z, "measured_mm": round(measured, 6),
            "lcd_centre_px": d["lcd_centre_px"].round(4).tolist(),
            "offset_px": (d["lcd_centre_px"] - pp).round(4).tolist(),
            "magnification": round(d["magnification"], 6),
            "lcd_seen_px": [round(float(seen[:, 0].min()), 1), round(float(seen[:, 1].min()), 1),
                            round(float(seen[:, 0].max()), 1), round(float(seen[:, 1].max()), 1)],
        }
        if code is not None:
            img = (code - lcd_c) @ d["jacobian"].T + d["lcd_centre_px"]
            entry["check_code_in_view"] = bool(
                (img >= 0).all() and (img[:, 0] <= cam_w - 1).all() and (img[:, 1] <= cam_h - 1).all())
        depths.append(entry)
    pts = np.array([q["lcd_centre_px"] for q in depths])
    mags = np.array([q["magnification"] for q in depths])
    axis_px, offset_lcd, rms = fit_axis(pts, mags)
    f = effective_focal_px(np.array([q["measured_mm"] for q in depths]), mags,
                           config.display.pitch_mm)
    tilt = [round(v, 5) for v in tilt_from_axis(axis_px, pp, f)]
    return {
        "depths": depths, "principal_point_px": pp.tolist(), "effective_focal_px": round(f, 3),
        "stage_axis_px": axis_px.round(4).tolist(),
        "lcd_centre_offset_mm": (offset_lcd * config.display.pitch_mm).round(4).tolist(),
        "fit_rms_px": None if rms is None else round(rms, 5),
        "tilt_deg": tilt, "shift_px": s,
    }


def format_align(report: dict) -> str:
    """Human summary of an alignment report."""
    lines = ["ltc align: LCD centre in the image at each depth"]
    for q in report["depths"]:
        du, dv = q["offset_px"]
        code = "" if "check_code_in_view" not in q else \
            ("; check code in view" if q["check_code_in_view"] else "; CHECK CODE NOT IN VIEW")
        lines.append(f"  z = {q['depth_mm']:g} mm: offset ({du:+.2f}, {dv:+.2f}) px from the "
                     f"principal point, {q['magnification']:.4f} px per LCD px; sees LCD "
                     f"{q['lcd_seen_px']}{code}")
    u, v = report["stage_axis_px"]
    lines.append(f"  stage axis points at image ({u:.2f}, {v:.2f}) px"
                 + ("" if report["fit_rms_px"] is None else f" (fit RMS {report['fit_rms_px']:.3f} px)"))
    tx, ty = report["tilt_deg"]
    lines.append(f"  tilt of the optical axis: {tx:+.4f} deg about camera x, {ty:+.4f} deg "
                 f"about camera y (0, 0 when square); effective focal length "
                 f"{report['effective_focal_px']:.1f} px")
    ox, oy = report["lcd_centre_offset_mm"]
    lines.append(f"  LCD centre lies ({ox:+.3f}, {oy:+.3f}) mm from the optical axis (camera x, y)")
    return "\n".join(lines)
