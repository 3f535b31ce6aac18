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


STATION = [  # (title, body, fill), left to right along the top row
    ("station config", "TOML, pydantic\nltc config\nstage, display,\ncamera, depths", DATA),
    ("acquisition", "per depth: move, settle\nper pattern: show,\ncapture, check code\n"
     "ltc acquire", STEP),
    ("run store", "zarr v3, one shard\nper frame, done mask,\nper-frame records\n(resumable)",
     DATA),
    ("LTC reconstruction", "Fourier SPI, unfold,\ntile by tile, workers\nltc reconstruct", STEP),
    ("LTC store", "zarr v3: per depth,\nper pixel, P x P\nwindow + origin,\ngain, noise", DATA),
]
SCANNER = [  # along the bottom row
    ("scene + rig", "scene TOML: objects,\nposes, patterns;\nrig: K, dist, R, T\nltc render",
     DATA),
    ("trace once", "Embree: per pixel,\nper lens ray: projector\ncoordinate, weight,\n"
     "shadow; truth maps", STEP),
    ("render patterns", "gather every pattern\nfrom the transport;\ncamera response,\n"
     "noise, digitise", STEP),
    ("scan", "phase, unwrap, stereo\nmatch, triangulate\n-> point cloud (PLY)\nltc scan", STEP),
    ("metrology", "sphere, ball bar,\ncloud to CAD, ICP,\ncloud to cloud\nltc measure", STEP),
]
LENS = ("lens derivation", "centroids -> principal\nrays -> optical centre\n-> LTC at the centre\n"
        "-> aperture samples\nltc lens", STEP)
LENS_FILE = ("lens model file", ".npz, versioned:\n(x_k, y_k, w_k) per\nnode, focus, zones", DATA)
NOTE = "#333333"


def box(ax, x: float, y: float, w: float, h: float, spec: tuple[str, str, str]) -> None:
    """A rounded box centred at (x, y): title in bold, body below it."""
    title, body, fill = spec
    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h,
                                boxstyle="round,pad=0.02,rounding_size=0.08",
                                fc=fill, ec=EDGE, lw=1.2))
    ax.text(x, y + h / 2 - 0.16, title, ha="center", va="top", fontsize=9.5, weight="bold")
    ax.text(x, y + h / 2 - 0.45, body, ha="center", va="top", fontsize=7.6, linespacing=1.25)


def arrow(ax, a: tuple[float, float], b: tuple[float, float], rad: float = 0.0) -> None:
    ax.add_patch(FancyArrowPatch(a, b, arrowstyle="-|>", mutation_scale=12, lw=1.2, color=EDGE,
                                 connectionstyle=f"arc3,rad={rad}"))


def row(ax, specs: list, xs: list[float], y: float, w: float, h: float) -> None:
    """Boxes at ``xs`` on the line ``y``, each joined to the next by an arrow."""
    for x, spec in zip(xs, specs, strict=True):
        box(ax, x, y, w, h, spec)
    for a, b in zip(xs[:-1], xs[1:], strict=True):
        arrow(ax, (a + w / 2, y), (b - w / 2, y))


def main() -> Path:
    fig, ax = plt.subplots(figsize=(13.5, 6.6))
    ax.set_xlim(0, 16.2)
    ax.set_ylim(0, 8.0)
    ax.axis("off")
    w, h = 2.35, 1.55
    xs = [1.45, 4.2, 6.95, 9.7, 12.45]
    top, bot, right = 6.15, 1.75, 15.0
    ax.text(0.15, 7.75, "LTC measurement station  (station/ on drivers/; fakes/ without hardware)",
            fontsize=11, weight="bold", va="top")
    ax.text(0.15, 3.65, "Virtual FPP scanner  (sim/)", fontsize=11, weight="bold", va="top")
    row(ax, STATION, xs, top, w, h)
    row(ax, SCANNER, xs, bot, w, h)
    lens_y, lens_h = top - 2.0, h + 0.2
    box(ax, right, lens_y, 2.1, lens_h, LENS)
    box(ax, right, bot, 2.1, h, LENS_FILE)
    arrow(ax, (xs[-1] + w / 2, top - 0.3), (right, lens_y + lens_h / 2), rad=-0.25)
    arrow(ax, (right, lens_y - lens_h / 2), (right, bot + h / 2))
    arrow(ax, (right - 0.5, bot + h / 2 + 0.03), (xs[1] + 0.3, bot + h / 2 + 0.05), rad=0.12)
    ax.text(9.5, 3.2, "each camera's lens model (or a pinhole, thin, Gaussian or aberrated lens)",
            ha="center", va="bottom", fontsize=7.4, style="italic", color=NOTE)
    arrow(ax, (xs[3], 0.3), (xs[3], bot - h / 2 - 0.05))
    ax.text(xs[3] + 0.1, 0.3, "a real scanner's images and calibration enter here", fontsize=7.2,
            style="italic", va="center", ha="left", color=NOTE)
    ax.text(0.15, 0.2, "blue: a stage (Python API and an ltc command);  yellow: a file or store "
            "on disk", fontsize=7.6, color=NOTE)
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    plt.close(fig)
    return OUT


if __name__ == "__main__":
    print(main())
