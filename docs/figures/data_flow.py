"""Draw docs/figures/data_flow.png: the data flow from a station config to a measured cloud.

    .venv/bin/python docs/figures/data_flow.py      # rewrites data_flow.png beside this file
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch  # noqa: E402

OUT = Path(__file__).with_suffix(".png")
STEP = "#dbe8f5"  # a processing stage
DATA = "#fdf1d6"  # a file or store on disk
EDGE = "#44546a"


def box(ax, x: float, y: float, w: float, h: float, title: str, body: str, fill: str) -> None:
    """A rounded box centred at (x, y), title in bold, body below it."""
    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle="round,pad=0.02,rounding_size=0.08",
                                fc=fill, ec=EDGE, lw=1.2))
    ax.text(x, y + h / 2 - 0.16, title, ha="center", va="top", fontsize=9.5, weight="bold")
    ax.text(x, y + h / 2 - 0.45, body, ha="center", va="top", fontsize=7.6, linespacing=1.25)


def arrow(ax, a: tuple[float, float], b: tuple[float, float], label: str = "",
          rad: float = 0.0) -> None:
    ax.add_patch(FancyArrowPatch(a, b, arrowstyle="-|>", mutation_scale=12, lw=1.2, color=EDGE,
                                 connectionstyle=f"arc3,rad={rad}"))
    if label:
        ax.text((a[0] + b[0]) / 2, (a[1] + b[1]) / 2 + 0.12, label, ha="center", va="bottom",
                fontsize=7.2, style="italic", color="#333333")


def main() -> Path:
    fig, ax = plt.subplots(figsize=(13.5, 6.6))
    ax.set_xlim(0, 16.2)
    ax.set_ylim(0, 8.0)
    ax.axis("off")
    w, h = 2.35, 1.55

    ax.text(0.15, 7.75, "LTC measurement station  (station/ on drivers/; fakes/ without hardware)",
            fontsize=11, weight="bold", va="top")
    ax.text(0.15, 3.65, "Virtual FPP scanner  (sim/)", fontsize=11, weight="bold", va="top")

    top = 6.15
    xs = [1.45, 4.2, 6.95, 9.7, 12.45, 15.0]
    box(ax, xs[0], top, w, h, "station config", "TOML, pydantic\nltc config\nstage, display,\ncamera, depths", DATA)
    box(ax, xs[1], top, w, h, "acquisition", "per depth: move, settle\nper pattern: show,\ncapture, check code\nltc acquire", STEP)
    box(ax, xs[2], top, w, h, "run store", "zarr v3, one shard\nper frame, done mask,\nper-frame records\n(resumable)", DATA)
    box(ax, xs[3], top, w, h, "LTC reconstruction", "Fourier SPI, unfold,\ntile by tile, workers\nltc reconstruct", STEP)
    box(ax, xs[4], top, w, h, "LTC store", "zarr v3: per depth,\nper pixel, P x P\nwindow + origin,\ngain, noise", DATA)
    box(ax, xs[5], top - 2.0, 2.1, h + 0.2, "lens derivation",
        "centroids -> principal\nrays -> optical centre\n-> LTC at the centre\n-> aperture samples\nltc lens", STEP)
    for a, b in zip(xs[:5], xs[1:5]):
        arrow(ax, (a + w / 2, top), (b - w / 2, top))
    arrow(ax, (xs[4] + w / 2, top - 0.3), (xs[5], top - 2.0 + (h + 0.2) / 2), rad=-0.25)

    bot = 1.75
    bx = [1.45, 4.2, 6.95, 9.7, 12.45]
    box(ax, 15.0, 1.75, 2.1, h, "lens model file", ".npz, versioned:\n(x_k, y_k, w_k) per\nnode, focus, zones", DATA)
    arrow(ax, (15.0, top - 2.0 - (h + 0.2) / 2), (15.0, 1.75 + h / 2))
    box(ax, bx[0], bot, w, h, "scene + rig", "scene TOML: objects,\nposes, patterns;\nrig: K, dist, R, T\nltc render", DATA)
    box(ax, bx[1], bot, w, h, "trace once", "Embree: per pixel,\nper lens ray: projector\ncoordinate, weight,\nshadow; truth maps", STEP)
    box(ax, bx[2], bot, w, h, "render patterns", "gather every pattern\nfrom the transport;\ncamera response,\nnoise, digitise", STEP)
    box(ax, bx[3], bot, w, h, "scan", "phase, unwrap, stereo\nmatch, triangulate\n-> point cloud (PLY)\nltc scan", STEP)
    box(ax, bx[4], bot, w, h, "metrology", "sphere, ball bar,\ncloud to CAD, ICP,\ncloud to cloud\nltc measure", STEP)
    for a, b in zip(bx[:4], bx[1:]):
        arrow(ax, (a + w / 2, bot), (b - w / 2, bot))
    arrow(ax, (14.5, bot + h / 2 + 0.03), (bx[1] + 0.3, bot + h / 2 + 0.05), rad=0.12)
    ax.text(9.5, 3.2, "each camera's lens model (or a pinhole, thin, Gaussian or aberrated lens)",
            ha="center", va="bottom", fontsize=7.4, style="italic", color="#333333")
    arrow(ax, (bx[3], 0.3), (bx[3], bot - h / 2 - 0.05))
    ax.text(bx[3] + 0.1, 0.3, "a real scanner's images and calibration enter here", fontsize=7.2,
            style="italic", va="center", ha="left", color="#333333")
    ax.text(0.15, 0.2, "blue: a stage (Python API and an ltc command);  yellow: a file or store on disk",
            fontsize=7.6, color="#333333")
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    plt.close(fig)
    return OUT


if __name__ == "__main__":
    print(main())
