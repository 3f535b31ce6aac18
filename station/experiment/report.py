"""The experiment's report: ``report.md`` with PNG figures in ``figures/`` (the paper's
Tables 4, 5 and 6; real and virtual fringe images with intensity- and phase-difference maps;
distance maps per position; the CAD error map; the station's lens figures)."""

from __future__ import annotations

import os
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sim.storage.durable import durable_figure, durable_file
from station.experiment.acceptance import size_vs_real_um
from station.experiment.config import (
    BALLBAR_LENGTH_MM,
    MODELS,
    SPHERE_DIAMETER_MM,
    VIRTUAL,
    ExperimentConfig,
)
from station.experiment.rows import PositionRow
from station.experiment.scan import Maps

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.collections import PathCollection
    from matplotlib.figure import Figure

    from sim.optics.measured_lens import MeasuredLens
    from sim.optics.rig import Rig

LABELS = {"real": "real", "ltc": "measured LTC", "gaussian": "Gaussian", "pinhole": "pinhole"}


def _figure(size: tuple[float, float]) -> Figure:
    """A figure (inches) laid out by matplotlib's constrained layout."""
    from matplotlib.figure import Figure

    return Figure(figsize=size, dpi=100, layout="constrained")


def wrapped_phase(images: np.ndarray, steps: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Wrapped phase (H, W) rad and modulation of the last ``steps`` images (the finest
    period): ``atan2(sum I_i sin(2 pi i / N), sum I_i cos(2 pi i / N))``."""
    stack = np.asarray(images[-steps:], dtype=np.float64)
    a = 2 * np.pi * np.arange(steps) / steps
    s = np.tensordot(np.sin(a), stack, axes=1)
    c = np.tensordot(np.cos(a), stack, axes=1)
    return np.arctan2(s, c), 2 * np.hypot(s, c) / steps


def fringe_figure(images: dict[str, Any], path: Path) -> Path:
    """Camera 0's finest fringe image, real and virtual side by side, with the per-pixel
    intensity difference and the wrapped-phase difference of each virtual scanner."""
    fig = _figure((15, 9))
    axes = fig.subplots(3, 4)
    real = np.asarray(images["real"][-4], dtype=np.float64)
    phase_real, mod = wrapped_phase(images["real"])
    mask = mod > 0.05 * mod.max()
    for j, n in enumerate(MODELS):
        img = np.asarray(images[n][-4], dtype=np.float64)
        axes[0, j].imshow(img, cmap="gray")
        axes[0, j].set_title(f"{LABELS[n]}: finest fringe, camera 0", fontsize=10)
        if n == "real":
            axes[1, j].axis("off")
            axes[2, j].axis("off")
            continue
        d = img - real
        lim = max(1.0, np.percentile(np.abs(d[mask]), 99)) if mask.any() else 1.0
        im = axes[1, j].imshow(np.where(mask, d, np.nan), cmap="coolwarm", vmin=-lim, vmax=lim)
        fig.colorbar(im, ax=axes[1, j], shrink=0.8, label="DN")
        axes[1, j].set_title(f"intensity: {LABELS[n]} - real")
        ph, _ = wrapped_phase(images[n])
        dp = np.angle(np.exp(1j * (ph - phase_real)))
        plim = max(1e-3, np.percentile(np.abs(dp[mask]), 99)) if mask.any() else 0.1
        im = axes[2, j].imshow(np.where(mask, dp, np.nan), cmap="coolwarm", vmin=-plim,
                               vmax=plim)
        fig.colorbar(im, ax=axes[2, j], shrink=0.8, label="rad")
        axes[2, j].set_title(f"phase: {LABELS[n]} - real")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"position {images['name']} ({images['defocus']} defocus)")
    durable_figure(fig, path)
    return path


def distance_map_figure(name: str, maps: Maps, path: Path) -> Path:
    """Each virtual cloud's signed distance to the real cloud (unaligned), world x-y, each on
    its own colour scale covering its 1st to 99th percentile (diverging about 0 when the
    range holds 0, else sequential): a cloud offset by hundreds of um still shows its
    structure."""
    fig = _figure((15, 4.2))
    axes = fig.subplots(1, 3)
    for ax, n in zip(axes, VIRTUAL, strict=True):
        pts, d = maps[n]
        lo, hi = ((float(np.percentile(d, 1)) * 1e3, float(np.percentile(d, 99)) * 1e3)
                  if d.size else (-1.0, 1.0))
        title = (f"{name}: {LABELS[n]} - real\nmean {d.mean() * 1e3:+.1f} um, RMSE "
                 f"{np.sqrt(np.mean(d * d)) * 1e3:.1f} um")
        if lo < 0 < hi or hi - lo < 1.0:
            lim = max(abs(lo), abs(hi), 1.0)
            sc = _distance_map(ax, pts, d, lim, 2, title)
        else:
            sc = _distance_map(ax, pts, d, 0.0, 2, title, vmin_um=lo, vmax_um=hi)
        ax.set_xlabel("world x, mm")
        ax.set_ylabel("world y, mm")
        fig.colorbar(sc, ax=ax, shrink=0.8, label="um (its 1st-99th percentile)")
    durable_figure(fig, path)
    return path


def _distance_map(ax: Axes, pts: np.ndarray, d_mm: np.ndarray, lim_um: float, size: float,
                  title: str, vmin_um: float | None = None,
                  vmax_um: float | None = None) -> PathCollection:
    """Signed distances (mm) of points (n, 3) drawn in image orientation, um: +-lim_um on a
    diverging map, or vmin_um..vmax_um on a sequential one."""
    if vmin_um is None or vmax_um is None:
        cmap, lo, hi = "coolwarm", -lim_um, lim_um
    else:
        cmap, lo, hi = "viridis", vmin_um, vmax_um
    sc = ax.scatter(pts[:, 0], pts[:, 1], c=d_mm * 1e3, s=size, cmap=cmap, vmin=lo, vmax=hi)
    ax.set_aspect("equal")
    ax.invert_yaxis()
    ax.set_title(title, fontsize=9)
    return sc


def cad_figure(maps: Maps, path: Path) -> Path:
    """Every scanner's cloud of the CAD part against the CAD mesh (Fig. 17), on one colour
    scale (+- the real cloud's 95th percentile of |distance|), the colour bars below."""
    fig = _figure((16, 4.0))
    axes = fig.subplots(1, 4)
    d_real = maps["cad_real"][1]
    lim = max(float(np.percentile(np.abs(d_real), 95)) * 1e3, 1.0)
    for ax, n in zip(axes, MODELS, strict=True):
        pts, d = maps[f"cad_{n}"]
        sc = _distance_map(ax, pts, d, lim, 1, f"{LABELS[n]} - CAD\nmean {d.mean() * 1e3:+.0f} "
                           f"um, RMSE {np.sqrt(np.mean(d * d)) * 1e3:.0f} um")
        fig.colorbar(sc, ax=ax, location="bottom", shrink=0.8, label="um")
    durable_figure(fig, path)
    return path


def summary_figure(rows: list[PositionRow], path: Path) -> Path:
    """Mean and RMSE against the real cloud, and the size error against real's, versus
    defocus, per virtual scanner (colour) and object kind (marker: spheres and ball bars,
    unjoined: each point is its own position)."""
    fig = _figure((16, 4.8))
    axes = fig.subplots(1, 3)
    colours = {"ltc": "C0", "gaussian": "C1", "pinhole": "C2"}
    kinds = {"sphere": ("o", "sphere"), "ballbar": ("s", "ball bar")}
    for kind, (marker, label) in kinds.items():
        sel = [r for r in rows if r.kind == kind]
        if not sel:
            continue
        x = np.array([r.defocus_mm for r in sel])
        for n in VIRTUAL:
            m = [r.models[n] for r in sel]
            style = dict(marker=marker, linestyle="none", color=colours[n],
                         label=f"{LABELS[n]}, {label}",
                         markerfacecolor=colours[n] if kind == "sphere" else "none")
            axes[0].plot(x, [(v.mean_mm or 0.0) * 1e3 for v in m], **style)
            axes[1].plot(x, [(v.rmse_mm or 0.0) * 1e3 for v in m], **style)
            axes[2].plot(x, [abs(size_vs_real_um(v)) for v in m], **style)
    for ax, t in zip(axes, ("mean distance to real, um", "RMSE to real, um",
                            "|size - real's size|, shared pixels, um"), strict=True):
        ax.set_yscale("symlog", linthresh=10.0)
        ax.set_xlabel("defocus (depth - focus distance), mm")
        ax.set_title(t)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    durable_figure(fig, path)
    return path


def _size_table(rows: list[PositionRow], kind: str, title: str, unit: str,
                cell: Callable[[float], str]) -> list[str]:
    """Markdown table of every model's size on its own points (``cell(size_mm)``) at the
    positions of ``kind``, then each virtual model against real on the pixels both clouds
    share, and ltc and Gaussian against real on their own points (um)."""
    out = ["", title, "", "| position | defocus, mm | " + " | ".join(LABELS[n] for n in MODELS)
           + " | " + " | ".join(f"{LABELS[n]} - real, shared{unit}" for n in VIRTUAL)
           + f" | ltc - real, own{unit} | Gaussian - real, own{unit} |",
           "|" + "---|" * (4 + len(MODELS) + len(VIRTUAL))]
    for r in (r for r in rows if r.kind == kind):
        m = r.models
        size = {n: _given(m[n].size_mm) for n in MODELS}
        out.append(f"| {r.name} ({r.defocus}) | {r.defocus_mm:+.0f} | "
                   + " | ".join(cell(size[n]) for n in MODELS) + " | "
                   + " | ".join(f"{size_vs_real_um(m[n]):+.1f}" for n in VIRTUAL)
                   + f" | {_um(size['ltc'] - size['real'])}"
                   f" | {_um(size['gaussian'] - size['real'])} |")
    return out


def _given(value: float | None) -> float:
    """A number the position's kind always has (None: a bug)."""
    if value is None:
        raise TypeError("a number the position's kind always has is missing")
    return value


SIZE_RULE = (
    "Sizes: each ball is fitted to the points within 2 mm of the true ball (geometric least "
    "squares, outliers beyond 3 robust standard deviations trimmed), the same rule for every "
    "scanner; the columns per scanner are its size on its own points against nominal. "
    "Against the real scanner, sizes are compared on the pixels both clouds share: the pixels "
    "both scanners' own fits kept, both clouds refitted there without further trimming, so "
    "the difference comes from the points' offsets, not from which rim points each scanner "
    "kept (\"shared\"; \"own\": the difference of the own-point sizes).")


def _um(x: float, sign: bool = True) -> str:
    return f"{x * 1e3:+.1f}" if sign else f"{x * 1e3:.1f}"


def tables(rows: list[PositionRow]) -> list[str]:
    """Markdown: Table 4 (distances), Table 5 (sphere fits), Table 6 (ball-bar lengths)."""
    out = ["### Table 4: virtual against real, point distances (um)", "",
           "Mean / RMSE of the signed distances of each virtual cloud to the real one, "
           "unaligned, then after ICP; by pixel correspondence (the same camera pixel in "
           "both clouds, along the real surface's normal, pixels within 1 px of a silhouette "
           "left out: `sim.metrology.compare.compare_by_pixel`).", "",
           "| position | defocus, mm | " + " | ".join(
               f"{LABELS[n]} | {LABELS[n]} (ICP)" for n in VIRTUAL) + " |",
           "|" + "---|" * (2 + 2 * len(VIRTUAL))]
    for r in rows:
        m = r.models
        out.append(f"| {r.name} ({r.kind}, {r.defocus}) | {r.defocus_mm:+.0f} | "
                   + " | ".join(f"{_um(_given(m[n].mean_mm))} / "
                                f"{_um(_given(m[n].rmse_mm), False)} | "
                                f"{_um(_given(m[n].mean_icp_mm))} / "
                                f"{_um(_given(m[n].rmse_icp_mm), False)}"
                                for n in VIRTUAL) + " |")
    out += ["", textwrap.fill(SIZE_RULE, 100)]
    out += _size_table(rows, "sphere", f"### Table 5: sphere fits, diameter - "
                       f"{SPHERE_DIAMETER_MM} mm (um)", "", _um)
    out += _size_table(rows, "ballbar", f"### Table 6: ball-bar lengths (nominal "
                       f"{BALLBAR_LENGTH_MM} mm), mm", ", um",
                       lambda mm: f"{BALLBAR_LENGTH_MM + mm:.4f}")
    cad = [r for r in rows if r.kind == "cad"]
    if cad:
        out += ["", "### CAD part against the CAD model (um)", "",
                "| scanner | mean | RMSE | std | points | against real: mean / RMSE |",
                "|---|---|---|---|---|---|"]
        for n in MODELS:
            mc = cad[0].models[n]
            vs = (f"{_um(_given(mc.mean_mm))} / {_um(_given(mc.rmse_mm), False)}"
                  if n != "real" else "")
            c = mc.cad
            if c is None:
                raise TypeError(f"position {cad[0].name}: no CAD distances for {n}")
            out.append(f"| {LABELS[n]} | {_um(c.mean_mm)} | {_um(c.rmse_mm, False)} | "
                       f"{_um(c.std_mm, False)} | {mc.points} | {vs} |")
    return out


def pose_table(rows: list[PositionRow]) -> list[str]:
    """Markdown: the pose refinement of the validation path per position (um from the true
    pose): the real cloud's own fit, the pose refined with the measured-LTC scanner, and
    where one step with the Gaussian and the pinhole scanners puts it."""
    sel = [(r, r.validation, t) for r in rows if r.validation is not None
           and (t := r.validation.true_offsets_um)]
    if not sel:
        return []
    out = ["### The artefact's pose, refined by analysis by synthesis (um from the true pose)",
           "", "The real cloud's fit carries the real scanner's bias; the measured-LTC scanner "
           "is moved until its fit matches the real fit (steps below 1 um), every virtual "
           "scanner is rendered there; the Gaussian and pinhole columns are where one such "
           "step with them puts the artefact (their own bias).", "",
           "| position | real fit | refined (ltc) | Gaussian | pinhole | steps, um |",
           "|---|---|---|---|---|---|"]
    for r, v, t in sel:
        out.append(f"| {r.name} ({r.kind}, {r.defocus}) | {t['real_fit']:.1f} | "
                   f"{t['refined']:.2f} | {t.get('refined_gaussian', float('nan')):.1f} | "
                   f"{t.get('refined_pinhole', float('nan')):.1f} | "
                   + ", ".join(f"{x:.2f}" for x in v.refine_steps_um) + " |")
    return out


def write_report(results: dict[str, Any], cfg: ExperimentConfig, rig: Rig,
                 measured: list[MeasuredLens], models: dict[str, tuple[Any, ...]],
                 maps: dict[str, Maps], images: dict[str, Any], out: Path) -> list[str]:
    """Write ``figures/*.png`` and ``report.md``; returns the figure paths."""
    figs = out / "figures"
    figs.mkdir(exist_ok=True)
    rows: list[PositionRow] = results["rows"]
    paths = [summary_figure(rows, figs / "summary.png")]
    if images:
        paths.append(fringe_figure(images, figs / "fringes.png"))
    for r in rows:
        if r.kind != "cad":
            paths.append(distance_map_figure(r.name, maps[r.name],
                                             figs / f"distances_{r.name}.png"))
        else:
            paths.append(cad_figure(maps[r.name], figs / "cad_error_map.png"))
    acc = results["acceptance"]

    def rel(p: str | Path) -> str:
        return os.path.relpath(p, out)

    lines = ["# The reference paper's experiment: measured LTC against a Gaussian defocus model",
             "", f"Run of {results['date']} on {results['machine']}; "
             f"{results['seconds']['total']:.0f} s in all.", ""]
    setup = [
        f"Rig: `small_rig({cfg.scale:g})` without distortion, cameras cropped to "
        f"{cfg.camera_size[0]} x {cfg.camera_size[1]} px (f = {rig.cameras[0].K_array[0, 0]:.1f}"
        f" px), projector {rig.projector.size[0]} x {rig.projector.size[1]}; 4-step fringes at "
        f"periods {', '.join(f'{p:g}' for p in cfg.periods_px)} projector px, no noise, 12 bits.",
        "Ground-truth lenses (16 mm, focus " f"{cfg.focus_distance_mm:g} mm): " + "; ".join(
            f"camera {i}: f/{s.f_number:g}, vignetting shift {s.vignetting_shift_mm:g} mm, "
            f"clip radius x{s.vignetting_radius_ratio:g}, spherical {s.spherical_mm:g} mm"
            for i, s in enumerate(cfg.lenses)) + ".",
        f"Scanners: real = the ground-truth lenses with {cfg.real_samples} pupil samples; "
        f"ltc = the measured lenses (K = {measured[0].samples} per node every "
        f"{cfg.lens_grid_step} px, bilinear, smoothed over {cfg.lens_smoothing_nodes:g} nodes); "
        f"Gaussian = docs/optics.md section 4, sigma " + ", ".join(
            f"{g.sigma_mm:.3f}" for g in models["gaussian"]) + " mm, "
        f"{models['gaussian'][0].samples} samples; pinhole.",
    ]
    if results["station"]:
        setup.append(
            f"Station: fake bench per camera, LCD pitch {cfg.lcd_pitch_mm:g} mm, P = "
            f"{cfg.period} ({cfg.steps}-step), {len(cfg.depths_mm)} depths (LCD at "
            + ", ".join(f"{cfg.lcd_distance_at_zero_mm + z:g}" for z in cfg.depths_mm)
            + " mm). " + " ".join(
                f"Camera {i}: {s['total_s']:.0f} s, optical centre error "
                f"{s['optical_centre_error_mm'] * 1e3:.1f} um, focus distance "
                f"{s['focus_distance_mm']:.1f} mm." for i, s in enumerate(results["station"])))
    lines += [textwrap.fill(t, 100, initial_indent="- ", subsequent_indent="  ") for t in setup]
    w = acc["ltc_worst"]
    near = acc["near_focus_average"]
    verdict = [
        f"ltc against real at every sphere and ball-bar position (mean within +-"
        f"{acc['limits']['mean_um']:g} um, RMSE <= {acc['limits']['rmse_um']:g} um, size within "
        f"{acc['limits']['size_um']:g} um of real's on the pixels both clouds share): "
        + ("**met**" if acc["ltc_within_limits"] else
           f"**not met** at {', '.join(acc['ltc_failing'])}")
        + f"; worst |mean| {w['mean_um']:.1f} um, RMSE {w['rmse_um']:.1f} um, size "
        f"{w['size_um']:.1f} um (on each scanner's own points {w['size_own_um']:.1f} um).",
        "Gaussian worse than ltc at every large-defocus position in |mean| and size error: "
        + ("**yes**" if acc["gaussian_worse_at_large"] else
           f"**no** at {', '.join(acc['gaussian_not_worse'])}") + ".",
    ]
    if near:
        verdict.append(
            f"Near focus (average over slight-defocus positions): ltc |mean| "
            f"{near['ltc']['abs_mean_um']:.1f} um, RMSE {near['ltc']['rmse_um']:.1f} um; Gaussian "
            f"{near['gaussian']['abs_mean_um']:.1f} um and {near['gaussian']['rmse_um']:.1f} um.")
    rt = results["render_s"]
    verdict.append("Render time (all positions, both cameras): " + ", ".join(
        f"{LABELS[n]} {rt[n]:.1f} s ({results['render_vs_pinhole'][n]:.1f} x pinhole)"
        for n in MODELS) + ".")
    lines += ["", "## Result", ""] + [textwrap.fill(t, 100, initial_indent="- ",
                                                    subsequent_indent="  ") for t in verdict]
    lines += ["", *tables(rows), "", *pose_table(rows), "", "## Figures", "",
              f"![summary]({rel(paths[0])})", ""]
    if images:
        lines += ["Real and virtual fringe images (camera 0), intensity and phase differences:",
                  "", f"![fringes]({rel(figs / 'fringes.png')})", ""]
    lines += ["Distance maps per position (virtual cloud - real cloud, unaligned):", ""]
    lines += [f"![{r.name}]({rel(figs / ('distances_' + r.name + '.png'))})"
              for r in rows if r.kind != "cad"]
    if any(r.kind == "cad" for r in rows):
        lines += ["", "CAD error map (each scanner's cloud against the CAD mesh, Fig. 17):", "",
                  f"![cad]({rel(figs / 'cad_error_map.png')})"]
    if results["station"]:
        lines += ["", "Lens figures from the station step:", ""]
        for i, s in enumerate(results["station"]):
            lines += [f"- camera {i}: " + ", ".join(
                f"[{Path(p).stem}]({rel(p)})" for p in s["figures"])]
    lines += ["", "Every number: `results.json`.", ""]
    with durable_file(out / "report.md") as f:
        f.write("\n".join(lines))
    return [str(p) for p in paths]
