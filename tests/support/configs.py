"""Small fake-bench station configs for tests that need a quick acquisition."""

from __future__ import annotations

from station.acquisition.config import example_text


def small_fake_config_text(depths_mm: tuple[float, ...] = (40.0,)) -> str:
    """The fake example config at ``depths_mm``, period 4, a short timeout and few pupil
    samples and subpixels: a run store in about a second."""
    depths = ", ".join(f"{d:.1f}" for d in depths_mm)
    text = example_text("fake")
    for old, new in {"depths_mm = [40.0, 70.0, 130.0, 160.0]": f"depths_mm = [{depths}]",
                     "period = 12": "period = 4", "timeout_s = 2.0": "timeout_s = 0.05",
                     "pupil_samples = 200 ": "pupil_samples = 48 ",
                     "subpixels = 2": "subpixels = 1"}.items():
        assert old in text, old
        text = text.replace(old, new, 1)
    return text
