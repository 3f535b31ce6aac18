"""``ltc check``: open the three devices, home, visit three depths, show a crosshair and a
checkerboard at each, capture them, and report what worked, with a contact sheet."""

from __future__ import annotations

import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.storage.durable import durable_figure
from station.acquisition.backend import Hardware, open_hardware
from station.acquisition.config import StationConfig

MIN_CONTRAST = 0.05  # a pattern must span this fraction of full scale to count as seen
MAX_SATURATED = 0.01  # more saturated pixels than this fraction is a warning


def crosshair(size: tuple[int, int], width_px: int | None = None) -> np.ndarray:
    """White crosshair through the LCD centre on black, (h, w) uint8."""
    w, h = size
    lw = width_px or max(2, min(w, h) // 200)
    img = np.zeros((h, w), np.uint8)
    cx, cy = (w - lw) // 2, (h - lw) // 2
    img[cy : cy + lw, :] = 255
    img[:, cx : cx + lw] = 255
    return img


def checkerboard(size: tuple[int, int], squares_across_short_side: int = 16) -> np.ndarray:
    """Black and white checkerboard, (h, w) uint8, square edge ``min(w, h) // n`` (>= 2 px)."""
    w, h = size
    s = max(2, min(w, h) // squares_across_short_side)
    yy, xx = np.mgrid[:h, :w]
    return np.where(((xx // s) + (yy // s)) % 2 == 0, 255, 0).astype(np.uint8)


def three_depths(depths_mm: list[float]) -> list[float]:
    """Nearest, middle and farthest configured depths (fewer when fewer are configured)."""
    d = sorted(set(depths_mm))
    return sorted({d[0], d[len(d) // 2], d[-1]})


@dataclass
class Step:
    """One step of the check and how it went."""

    name: str
    ok: bool = False
    seconds: float = 0.0
    detail: dict = field(default_factory=dict)
    error: str | None = None


WHITE_PERCENTILE = 99.0  # the white level: this percentile of a capture, over full scale


def _capture_stats(image: np.ndarray, bit_depth: int) -> dict:
    full = float(2**bit_depth - 1)
    return {
        "min": int(image.min()),
        "max": int(image.max()),
        "mean": round(float(image.mean()), 2),
        "white_level": round(float(np.percentile(image, WHITE_PERCENTILE)) / full, 4),
        "contrast": round(float(np.ptp(image)) / full, 4),
        "saturated_fraction": round(float(np.mean(image >= full)), 5),
    }


class Checker:
    """Runs the check steps on opened hardware, recording each."""

    def __init__(self, hw: Hardware) -> None:
        self.hw = hw
        self.steps: list[Step] = []
        self.images: list[tuple[str, np.ndarray]] = []

    def step(self, name: str, fn) -> Step:
        s = Step(name)
        t0 = time.monotonic()
        try:
            s.detail = fn() or {}
            s.ok = s.detail.pop("_ok", True)
        except Exception as exc:  # noqa: BLE001 - every failure is reported, none hidden
            s.error = f"{type(exc).__name__}: {exc}"
            s.detail["traceback"] = traceback.format_exc(limit=3)
        s.seconds = round(time.monotonic() - t0, 3)
        self.steps.append(s)
        return s

    def show_and_capture(self, label: str, pattern: np.ndarray) -> dict:
        self.hw.display.show(pattern)
        frame = self.hw.camera.capture()
        self.images.append((label, frame.image))
        stats = _capture_stats(frame.image, self.hw.camera.bit_depth)
        stats["frame_id"] = frame.frame_id
        stats["_ok"] = stats["contrast"] >= MIN_CONTRAST
        if stats["saturated_fraction"] > MAX_SATURATED:
            stats["warning"] = "saturated: lower the exposure"
        if not stats["_ok"]:
            stats["warning"] = f"pattern not seen (contrast {stats['contrast']} < {MIN_CONTRAST})"
        return stats


def run_check(config: StationConfig, out_dir: Path | None = None,
              sheet_name: str = "check.png") -> dict:
    """Run the check; return a JSON-ready report whose ``ok`` is True only if every step was.
    The contact sheet goes to ``out_dir / sheet_name``. ``white_level`` (report and steps): the
    99th percentile of the checkerboard captures as a fraction of full scale (tune the
    exposure until it is 0.80-0.90 with no saturated pixels)."""
    started = time.time()
    steps: list[Step] = []
    images: list[tuple[str, np.ndarray]] = []
    opened = Step("open devices")
    t0 = time.monotonic()
    try:
        with open_hardware(config) as hw:
            opened.ok = True
            opened.detail = {
                "stage": hw.stage.describe(),
                "display_size": list(hw.display.size),
                "camera_size": list(hw.camera.size),
                "camera_bit_depth": hw.camera.bit_depth,
            }
            opened.seconds = round(time.monotonic() - t0, 3)
            ck = Checker(hw)
            if ck.step("home stage", lambda: {"position_mm": _home(hw)}).ok:
                size = hw.display.size
                for z in three_depths(config.depths_mm):
                    if not ck.step(f"move to {z:g} mm", lambda z=z: _move(hw, z)).ok:
                        continue
                    ck.step(f"crosshair at {z:g} mm",
                            lambda z=z: ck.show_and_capture(f"crosshair {z:g} mm", crosshair(size)))
                    ck.step(f"checkerboard at {z:g} mm",
                            lambda z=z: ck.show_and_capture(f"checker {z:g} mm", checkerboard(size)))
            steps, images = ck.steps, ck.images
    except Exception as exc:  # noqa: BLE001 - reported as a failed step
        if not opened.ok:
            opened.error = f"{type(exc).__name__}: {exc}"
            opened.seconds = round(time.monotonic() - t0, 3)
        else:
            steps.append(Step("close devices", error=f"{type(exc).__name__}: {exc}"))
    all_steps = [opened] + steps
    whites = [s.detail["white_level"] for s in steps
              if s.name.startswith("checkerboard") and "white_level" in s.detail]
    report = {
        "ok": all(s.ok for s in all_steps) and len(all_steps) > 2,
        "backend": config.backend,
        "started": time.strftime("%Y-%m-%dT%H:%M:%S%z", time.localtime(started)),
        "seconds": round(time.time() - started, 3),
        "white_level": [min(whites), max(whites)] if whites else None,
        "steps": [
            {"name": s.name, "ok": s.ok, "seconds": s.seconds, "error": s.error,
             **{k: v for k, v in s.detail.items() if k != "traceback"}}
            for s in all_steps
        ],
    }
    if out_dir is not None and images:
        report["contact_sheet"] = str(write_contact_sheet(images, Path(out_dir) / sheet_name))
    return report


def _home(hw: Hardware) -> float:
    hw.stage.home()
    if not hw.stage.is_homed:
        raise RuntimeError("stage reports not homed after home()")
    return round(hw.stage.position_mm, 6)


def _move(hw: Hardware, z_mm: float) -> dict:
    measured = hw.stage.move_to(z_mm)
    return {"target_mm": z_mm, "measured_mm": round(measured, 6)}


def write_contact_sheet(images: list[tuple[str, np.ndarray]], path: Path) -> Path:
    """A PNG grid of the captured images (two per depth), labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = 2
    rows = (len(images) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (label, img) in zip(axes.ravel(), images, strict=False):
        ax.imshow(img, cmap="gray", interpolation="nearest")
        ax.set_title(label, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    durable_figure(fig, path, dpi=100)
    plt.close(fig)
    return path


def format_report(report: dict) -> str:
    """Human summary of a check report."""
    lines = [f"ltc check ({report['backend']} bench): {'OK' if report['ok'] else 'FAILED'}"
             f" in {report['seconds']:.1f} s"]
    for s in report["steps"]:
        mark = "ok  " if s["ok"] else "FAIL"
        extra = s.get("error") or s.get("warning") or ""
        facts = ", ".join(f"{k}={s[k]}" for k in ("measured_mm", "position_mm", "contrast",
                                                   "white_level", "saturated_fraction")
                          if k in s)
        lines.append(f"  [{mark}] {s['name']:<28} {facts} {extra}".rstrip())
    if report.get("white_level"):
        lo, hi = report["white_level"]
        lines.append(f"  white level: {100 * lo:.0f}-{100 * hi:.0f} % of full scale (99th "
                     "percentile of the checkerboards; tune the exposure to 80-90 % with no "
                     "saturated pixels)")
    if "contact_sheet" in report:
        lines.append(f"  contact sheet: {report['contact_sheet']}")
    return "\n".join(lines)
