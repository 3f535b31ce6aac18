"""The calibration report: ``report.md`` and figures (residual vectors over each sensor, the
coverage of each sensor and of the projector image, the error per pose)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.calibration.calibrator import CalibrationResult

DEVICES = ("camera_0", "camera_1", "projector")


def _figures(result: CalibrationResult, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sizes = {d.name: d.size for d in [*result.rig.cameras, result.rig.projector]}
    names = []
    # residual vectors over the sensor, exaggerated to be seen
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    for ax, dev in zip(axes, DEVICES, strict=True):
        rs = [r for r in result.residuals if r.device == dev and len(r.uv)]
        uv = np.concatenate([r.uv for r in rs])
        e = np.concatenate([r.error for r in rs])
        mag = np.linalg.norm(e, axis=1)
        scale = 0.05 * max(sizes[dev]) / max(float(np.percentile(mag, 95)), 1e-12)
        ax.quiver(uv[:, 0], uv[:, 1], e[:, 0] * scale, e[:, 1] * scale, mag, angles="xy",
                  scale_units="xy", scale=1, cmap="viridis", width=0.003)
        w, h = sizes[dev]
        ax.set_xlim(0, w)
        ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_title(f"{dev}: RMS {result.rms_px[dev]:.4f} px (arrows x{scale:.0f})")
        ax.set_xlabel("u, px")
        ax.set_ylabel("v, px")
    fig.tight_layout()
    fig.savefig(out / "residuals.png", dpi=90)
    plt.close(fig)
    names.append("residuals.png")
    # coverage: the features of every pose, one colour per pose
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    for ax, dev in zip(axes, DEVICES, strict=True):
        for r in result.residuals:
            if r.device == dev and len(r.uv):
                ax.plot(r.uv[:, 0], r.uv[:, 1], ".", ms=3, label=r.pose)
        w, h = sizes[dev]
        ax.add_patch(plt.Rectangle((0, 0), w, h, fill=False, ec="k"))
        ax.set_xlim(-0.02 * w, 1.02 * w)
        ax.set_ylim(1.02 * h, -0.02 * h)
        ax.set_aspect("equal")
        ax.set_title(f"{dev}: coverage of the image")
    fig.tight_layout()
    fig.savefig(out / "coverage.png", dpi=90)
    plt.close(fig)
    names.append("coverage.png")
    # error per pose
    fig, ax = plt.subplots(figsize=(max(6, 0.6 * len(result.poses) + 2), 4))
    x = np.arange(len(result.poses))
    for k, dev in enumerate(DEVICES):
        ax.bar(x + (k - 1) * 0.27, [result.pose_rms_px[dev][p] for p in result.poses], 0.27,
               label=dev)
    ax.set_xticks(x, result.poses, rotation=60)
    ax.set_ylabel("RMS reprojection error, px")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "error_per_pose.png", dpi=90)
    plt.close(fig)
    names.append("error_per_pose.png")
    return names


def write_report(result: CalibrationResult, directory: str | Path) -> Path:
    """Write ``report.md`` and its figures into ``directory`` (created); returns the report."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    figs = _figures(result, out)
    rig = result.rig
    lines = ["# Calibration report", "",
             f"Board: {result.board.kind}, {result.board.rows} x {result.board.columns}; "
             f"{len(result.poses)} poses; projector features by `{result.projector_method}`.", "",
             "| device | RMS px | worst pose | fx px | fy px | cx px | cy px | distortion "
             "| model | fx rel. std |", "|---|---|---|---|---|---|---|---|---|---|"]
    for d in [*rig.cameras, rig.projector]:
        per = result.pose_rms_px[d.name]
        worst = max(per, key=lambda pose: per[pose])
        K = d.K_array
        lines.append(f"| {d.name} | {result.rms_px[d.name]:.4f} | {worst} ({per[worst]:.4f}) | "
                     f"{K[0, 0]:.3f} | {K[1, 1]:.3f} | {K[0, 2]:.3f} | {K[1, 2]:.3f} | "
                     f"{' '.join(f'{v:.5g}' for v in d.dist)} | {result.distortion[d.name]} | "
                     f"{result.focal_rel_std[d.name]:.2g} |")
    lines += ["", "Extrinsics from camera 0 (R as a rotation vector, degrees; T mm):", ""]
    import cv2

    for d in [rig.cameras[1], rig.projector]:
        r = np.degrees(cv2.Rodrigues(d.R_array)[0].ravel())
        lines.append(f"- {d.name}: R = {np.round(r, 5).tolist()}, T = "
                     f"{np.round(d.T_array, 4).tolist()}")
    lines += ["", "## Error per pose", "", "| pose | camera_0 | camera_1 | projector |",
              "|---|---|---|---|"]
    for p in result.poses:
        lines.append(f"| {p} | " + " | ".join(f"{result.pose_rms_px[d][p]:.4f}"
                                             for d in DEVICES) + " |")
    lines += [""] + [f"![{f}]({f})" for f in figs] + [""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    (out / "calibration.json").write_text(result.to_json())
    return path
