"""``report.md`` of a validation, with PNG figures in ``figures/``: the pose refinement, the
reference's Tables 4, 5 and 6 for every twin against the real scanner, per-position image and
phase statistics, and Fig. 14 (real and twin fringe images, intensity and phase differences)."""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from station.validation.folder import write_durable

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from station.validation.run import ValidationResult


def _um(x: float | None, sign: bool = True) -> str:
    if x is None:
        return "-"
    return f"{x * 1e3:+.1f}" if sign else f"{x * 1e3:.1f}"


def _save(fig: Figure, path: Path) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    write_durable(path, buf.getvalue())
    return str(path)


def fringe_figure(name: str, twins: list[str], maps: dict[str, np.ndarray], path: Path) -> str:
    """Fig. 14 for one position, camera 0: the real finest fringe image and each twin's, each
    twin's intensity difference (DN) and wrapped phase difference (rad)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(4 * (len(twins) + 1), 9), dpi=90)
    ax = fig.subplots(3, len(twins) + 1, squeeze=False)
    ax[0, 0].imshow(maps["real.image"], cmap="gray")
    ax[0, 0].set_title(f"{name}: real, camera 0")
    ax[1, 0].axis("off")
    ax[2, 0].axis("off")
    for j, t in enumerate(twins, start=1):
        ax[0, j].imshow(maps[f"{t}.image"], cmap="gray")
        ax[0, j].set_title(f"twin {t}")
        for row, key, unit in ((1, "image_diff_dn", "DN"), (2, "phase_diff_rad", "rad")):
            m = maps[f"{t}.{key}"]
            fin = np.isfinite(m)
            lim = float(np.percentile(np.abs(m[fin]), 99)) if fin.any() else 1.0
            im = ax[row, j].imshow(m, cmap="coolwarm", vmin=-max(lim, 1e-6), vmax=max(lim, 1e-6))
            fig.colorbar(im, ax=ax[row, j], shrink=0.8, label=unit)
            ax[row, j].set_title(f"{t} - real: {'intensity' if row == 1 else 'phase'}")
    fig.tight_layout()
    return _save(fig, path)


def summary_figure(rows: list[dict[str, Any]], twins: list[str], path: Path) -> str:
    """Per position each twin's mean and RMSE against real (by pixel, unaligned), um."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=90)
    a, b = fig.subplots(1, 2)
    x = np.arange(len(rows))
    w = 0.8 / max(len(twins), 1)
    for k, t in enumerate(twins):
        a.bar(x + k * w, [r["twins"][t]["mean_mm"] * 1e3 for r in rows], w, label=t)
        b.bar(x + k * w, [r["twins"][t]["rmse_mm"] * 1e3 for r in rows], w, label=t)
    for ax, title in ((a, "mean, um"), (b, "RMSE, um")):
        ax.set_xticks(x + 0.4 - w / 2, [r["name"] for r in rows])
        ax.set_title(f"twin - real by pixel: {title}")
        ax.legend()
    fig.tight_layout()
    return _save(fig, path)


def write_report(result: ValidationResult, maps: dict[str, dict[str, np.ndarray]], out: Path
                 ) -> list[str]:
    """Write ``out/report.md`` and its figures; returns the figures' paths."""
    rows, twins = result.positions, result.twins
    figs = [summary_figure(rows, twins, out / "figures" / "summary.png")]
    lines = [f"# Twin validation against {result.real_dir}", "",
             f"Twins: {', '.join(twins)} (the first, `{twins[0]}`, refines the pose; every twin "
             "is rendered at that pose). Distances are twin minus real along the real point's "
             "normal, by pixel correspondence (`sim.metrology.compare.compare_by_pixel`), "
             "unaligned and after ICP; sizes against nominal, on each scanner's own points and "
             "on the pixels both share.", "", f"![summary](figures/{Path(figs[0]).name})", "",
             "## Pose refinement", "",
             "| position | steps (um) | converged | other twins' own pose (um from refined) "
             "| true pose: real fit (um) | refined (um) | other twins' (um) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        tr = r["true_offsets_um"] or {}
        others = ", ".join(f"{t} {v:.1f}" for t, v in r["twin_pose_offset_um"].items()
                           if t != twins[0])
        tother = ", ".join(f"{k[len('refined_'):]} {v:.1f}" for k, v in tr.items()
                           if k.startswith("refined_"))
        lines.append(f"| {r['name']} | {', '.join(f'{s:.2f}' for s in r['refine_steps_um'])} "
                     f"| {r['refine_converged']} | {others or '-'} "
                     f"| {tr.get('real_fit', float('nan')):.1f} "
                     f"| {tr.get('refined', float('nan')):.2f} | {tother or '-'} |")
    lines += ["", "## Points by pixel (Table 4), um", "",
              "| position | kind | defocus | " + " | ".join(
                  f"{t} mean / RMSE | {t} ICP mean / RMSE" for t in twins) + " |",
              "|---|---|---|" + "---|---|" * len(twins)]
    for r in rows:
        cells = []
        for t in twins:
            m = r["twins"][t]
            cells += [f"{_um(m['mean_mm'])} / {_um(m['rmse_mm'], False)}",
                      f"{_um(m['mean_icp_mm'])} / {_um(m['rmse_icp_mm'], False)}"]
        lines.append(f"| {r['name']} | {r['kind']} | {r['defocus'] or '-'} | "
                     + " | ".join(cells) + " |")
    lines += ["", "## Sizes (Tables 5 and 6), um against nominal", "",
              "| position | real | " + " | ".join(
                  f"{t} own | {t} - real, shared pixels" for t in twins) + " |",
              "|---|---|" + "---|---|" * len(twins)]
    for r in rows:
        if r["kind"] == "cad":
            continue
        nominal_err = r["twins"][twins[0]]["size_shared_real_mm"]
        cells = []
        for t in twins:
            m = r["twins"][t]
            cells += [_um(m["size_mm"]), _um(m["size_shared_mm"] - m["size_shared_real_mm"])]
        lines.append(f"| {r['name']} | {_um(nominal_err)} | " + " | ".join(cells) + " |")
    lines += ["", "## Fringe images and phases (Fig. 14), per camera", "",
              "| position | twin | camera | pixels | intensity mean / RMS (DN) | RMS / B "
              "| phase mean / RMS (mrad) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        for t in twins:
            for s in r["twins"][t]["images"]:
                lines.append(f"| {r['name']} | {t} | {s['camera']} | {s['pixels']} | "
                             f"{s['intensity_mean_dn']:+.2f} / {s['intensity_rms_dn']:.2f} | "
                             f"{s['intensity_rms_of_modulation']:.4f} | "
                             f"{s['phase_mean_rad'] * 1e3:+.2f} / "
                             f"{s['phase_rms_rad'] * 1e3:.2f} |")
    lines += ["", "## Camera response and the real scans", "",
              "| position | gain | offset (DN) | read noise (DN) | shot (DN per DN) | source "
              "| real points | rejected (camera 0) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        rs = r["response"]
        rej = r["real_scan"]["rejected"][0]
        top = ", ".join(f"{k} {v}" for k, v in sorted(rej.items(), key=lambda kv: -kv[1]) if v)
        lines.append(f"| {r['name']} | {', '.join(f'{g:.4g}' for g in rs['gain'])} | "
                     f"{', '.join(f'{o:.2f}' for o in rs['offset'])} | "
                     f"{', '.join(f'{n:.2f}' for n in rs['read_noise_dn'])} | "
                     f"{', '.join(f'{n:.3g}' for n in rs['shot_dn'])} | {rs['source']} | "
                     f"{r['real_points']} | {top} |")
    shown = [r for r in rows if r.get("defocus") == "large"] or rows
    name = shown[0]["name"]
    figs.append(fringe_figure(name, twins, maps[name], out / "figures" / f"fringes_{name}.png"))
    lines += ["", f"## Fig. 14: position {name}", "",
              f"![fringes](figures/{Path(figs[-1]).name})", "", "## Summary per twin", ""]
    for t, s in result.summary.items():
        lines.append(f"- {t}: " + ", ".join(f"{k} {v:.2f}" if isinstance(v, float)
                                            else f"{k} {v}" for k, v in s.items()))
    write_durable(out / "report.md", ("\n".join(lines) + "\n").encode())
    return figs
