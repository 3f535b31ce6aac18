"""The defocus-induced phase error a data set's labels carry: one sample, three lenses.

The same scene (a staircase before a tilted backdrop) rendered noise-free and unquantised
with a pinhole, a Gaussian defocus and a measured (space-variant) lens; each camera-0 image
stack decoded with the project's decoder (``sim.fpp.decode.decode_view``) and compared with
the sample's geometric truth, ``absolute_phase``. The pinhole's error is the decoder's own
(below 0.01 rad); the lenses' is what defocus does to the phase: largest at depth steps and
silhouettes, where the blur mixes surfaces at different phases.

    python examples/dataset_defocus_error.py [--out docs/figures/dataset_defocus_phase_error.png]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from sim.dataset.config import parse_config
from sim.dataset.generate import MASK_VALID, render_sample
from sim.dataset.randomise import MeasuredLensDraw, config_rig, draw_scene
from sim.fpp.decode import DecodeSettings, decode_view
from sim.optics.lens import GaussianLens, PinholeLens, sunflower_disk

SIZE = 320
K = 48  # aperture samples per node of the measured lens


def measured_lens(path: Path, size: tuple[int, int]) -> Path:
    """A synthetic measured lens: 5 x 5 nodes, K samples, pupil radius 0.8 mm at the centre
    growing to 1.6 mm at the corners, focused at 600 mm."""
    from sim.optics.measured_lens import MeasuredLens, save_lens

    w, h = size
    nu, nv = np.linspace(0, w - 1, 5), np.linspace(0, h - 1, 5)
    r = 0.8 + 0.8 * np.hypot(*np.meshgrid((nu - nu.mean()) / nu.max(),
                                          (nv - nv.mean()) / nv.max())) / np.sqrt(0.5)
    disk = sunflower_disk(K)
    return save_lens(path, MeasuredLens(
        focus_distance_mm=600.0, optical_centre_mm=np.zeros(3), camera_size=size, node_u=nu,
        node_v=nv, aperture_x_mm=r[..., None] * disk[:, 0], aperture_y_mm=r[..., None] * disk[:, 1],
        weights=np.full((5, 5, K), 1 / K), transmittance=np.ones((5, 5))))


def phase_error(sample, cam: int = 0) -> np.ndarray:
    """Decoded minus true absolute phase (H, W) rad of one camera, NaN where not valid."""
    scene, a = sample.scene, sample.cameras[cam]
    view = decode_view(a["images"], scene.patterns, tuple(scene.rig.projector.size),
                       DecodeSettings(min_modulation=1.0, min_modulation_fraction=0.0))
    fine = min(scene.patterns.periods_px)
    err = 2 * np.pi * view.coord["u"] / fine - a["absolute_phase"]
    return np.where(a["mask"] == MASK_VALID, err, np.nan)


def errors(seed: int = 4, index: int = 0) -> dict[str, np.ndarray]:
    cfg = parse_config({
        "seed": seed,
        "rig": {"builtin": {"camera_size_px": [SIZE, SIZE], "camera_scale": 0.25}},
        "objects": {"families": {"steps": 1.0}, "size_mm": [110.0, 110.0]},
        "placement": {"backdrop_probability": 1.0, "backdrop_gap_mm": [30.0, 30.0]},
        "camera": {"quantize": False}, "projector": {"input_bits": None},
        "patterns": [{"kind": "phase_shift", "steps": [4], "periods_px": [[2048, 128, 16]]}]})
    rig = config_rig(cfg)
    scene = draw_scene(cfg, rig, index)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        lens_path = measured_lens(Path(tmp) / "lens.npz", (SIZE, SIZE))
        for name, lens in (("pinhole", PinholeLens()),
                           ("Gaussian, sigma 1.5 mm, focus 600 mm",
                            GaussianLens(sigma_mm=1.5, focus_distance_mm=600.0, samples=64)),
                           ("measured (space-variant), focus 600 mm",
                            MeasuredLensDraw(path=str(lens_path)))):
            s = render_sample(scene.model_copy(update={"lenses": [lens, lens]}))
            out[name] = phase_error(s)
    return out


def figure(errs: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(17, 4.6))
    for ax, (name, e) in zip(axes, errs.items(), strict=False):
        im = ax.imshow(e, cmap="RdBu_r", vmin=-0.05, vmax=0.05)
        med = float(np.nanmedian(np.abs(e)))
        p99 = float(np.nanpercentile(np.abs(e), 99))
        ax.set_title(name.replace(", ", "\n", 1) + f"\nmedian |e| {med:.4f}, p99 {p99:.3f} rad",
                     fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes[:3], shrink=0.8, label="decoded - true phase, rad")
    ax = axes[3]
    for name, e in errs.items():
        v = np.abs(e[np.isfinite(e)])
        ax.hist(np.log10(np.maximum(v, 1e-6)), bins=60, histtype="step", label=name.split(",")[0])
    ax.set_xlabel("log10 |phase error| (rad)")
    ax.set_ylabel("valid pixels")
    ax.legend(fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path,
                    default=Path("docs/figures/dataset_defocus_phase_error.png"))
    args = ap.parse_args()
    errs = errors()
    for name, e in errs.items():
        v = e[np.isfinite(e)]
        print(f"{name}: {v.size} valid pixels, RMS {np.sqrt(np.mean(v**2)):.4f} rad, "
              f"p99 |e| {np.percentile(np.abs(v), 99):.4f} rad, max {np.abs(v).max():.3f} rad")
    figure(errs, args.out)
    print(f"wrote {args.out}")
