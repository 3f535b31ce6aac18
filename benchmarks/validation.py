"""Validation experiment (the mission's claim): does the virtual scanner with the lens measured by
the LTC station reproduce the "real" scanner better than a Gaussian defocus model, most of all at
large defocus? (OPTICS.md section 1, "paper's result"; section 7, the Gaussian baseline.)

* **Real scanner**: the FPP rig (``sim.optics.rig.small_rig`` geometry without distortion, both
  cameras cropped about the image centre to the measurement volume) rendered with the
  ground-truth aberrated lens (``sim.optics.lens.AberratedLens``: field-dependent vignetting,
  spherical aberration) on both cameras, with many pupil samples.
* **Measured lens**: the station run end to end on a fake bench whose camera *is* the rig's
  camera (same K, sensor and ground-truth lens): ``station.acquisition.acquire.acquire`` (Fourier SPI and
  localisation frames at several depths through the fake stage, LCD and noisy camera),
  ``station.ltc.spi.reconstruct`` (per-pixel LTC) and ``station.lens.derive.derive_lens``
  (centroids, principal rays, optical centre placed with K, focus fitted from the LTC sizes,
  K aperture samples per node), saved and read back through the lens file
  (``sim.optics.measured_lens``).
* **Virtual scanners**: the same rig rendered with (a) the measured lens, (b) the Gaussian
  baseline (OPTICS.md section 7): same ray geometry (the measured focus distance, as many
  samples), Gaussian aperture weights with the second moment of the measured LTC at the
  optical centre, the same for every pixel, (c) a pinhole; and, as the floor of the
  comparison, (d) the true lens itself with only as many samples as the measured one.
* **Scenes**: the 50.8007 mm sphere near the focus distance (slight defocus) and far from it
  (large defocus). Same fringe patterns, no noise, same quantisation for every lens.
* **Comparison**: each virtual cloud (``sim.fpp.decode.scan``, stereo) against the
  real one, ``sim.metrology.compare.compare_clouds`` *without* ICP: all clouds share the rig's
  world frame, so a shift is a difference to report, not an alignment to remove. Mean and
  RMSE of the signed distances; the sphere fit (``sim.metrology.spheres.fit_sphere``) of each cloud.

Run (about 5-6 minutes on 2 cores; ``--quick``: a reduced smoke run, under a minute)::

    .venv/bin/python benchmarks/validation.py --out out/validation --write-readme

``--out`` (a new or empty folder) receives the station config, run store, LTC store, lens
file, ``results.json`` and ``validation.png``; ``--write-readme`` replaces the section
"Validation: measured LTC vs Gaussian" of ``benchmarks/README.md`` (nothing else).
``--lens LENS.npz`` skips the station and reuses a measured lens made with the same config.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from sim.metrology.compare import compare_clouds
from sim.render.fringe_patterns import PhaseShiftSet
from sim.optics.lens import AberratedLens, GaussianLens, LensModel, PinholeLens, sunflower_disk
from station.experiment.run import machine  # noqa: E402 - one description of the machine
from sim.optics.measured_lens import (MeasuredLens, centre_moments, gaussian_equivalent, load_lens,
                                      save_lens)
from sim.metrology.spheres import fit_sphere
from sim.fpp.decode import scan as fpp_scan
from sim.render.images import CameraResponse, ProjectorResponse, RenderSettings, render_views
from sim.optics.rig import DeviceCalibration, Rig, small_rig
from sim.render.scene import Scene, SphereObject
from sim.render.trace import TraceGeometry
from station.acquisition.acquire import acquire
from station.ltc.store import open_ltc_volume
from station.acquisition.config import StationConfig
from station.lens.derive import derive_lens
from station.lens.geometry import LensFitConfig
from station.ltc.spi import reconstruct as reconstruct_ltc

README = Path(__file__).resolve().with_name("README.md")
SECTION = "## Validation: measured LTC vs Gaussian"
SPHERE_DIAMETER_MM = 50.8007
FOCAL_MM = 16.0  # the reference system's lens (OPTICS.md section 1)
PAPER_RMSE_MM = 0.022  # OPTICS.md section 1: real vs virtual RMSE with LTC
SPHERE_SHELL_MM = 2.0  # points this close to the true sphere go to the sphere fit
STATION_OUTPUTS = ("station.json", "run.zarr", "ltc.zarr", "lens.npz")
LENSES = ("measured", "gaussian", "pinhole", "truth_k")
LENS_LABELS = {"measured": "measured LTC", "gaussian": "Gaussian", "pinhole": "pinhole",
               "truth_k": "true lens, K samples"}
RENDER = RenderSettings(
    projector=ProjectorResponse(input_bits=8),
    camera=CameraResponse(exposure_e=8000.0, full_well_e=10000.0, bit_depth=12,
                          shot_noise=False, read_noise_e=0.0),
)


class ValidationConfig(BaseModel):
    """Everything the experiment depends on; the defaults are the benchmark's."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    scale: float = Field(0.2, gt=0, le=1, description="rig scale (sim.optics.rig.small_rig): focal "
                         "lengths in pixels and the projector size times this")
    camera_size: tuple[int, int] = Field((224, 128), description="cropped camera sensor "
                                         "(width, height), px; principal point at its centre")
    focus_distance_mm: float = Field(760.0, gt=0, description="paraxial focus distance of the "
                                     "true lens, mm (the rig's working distance)")
    f_number: float = Field(1.0, gt=0, description="f-number of the 16 mm true lens (pupil "
                            "16 / N mm); at scale 0.2, f/1 blurs as many pixels as f/5 does "
                            "on the full-size rig")
    vignetting_shift_mm: float = Field(30.0, description="true lens: clipping-circle shift per "
                                       "unit tan(field angle), mm")
    spherical_mm: float = Field(15.0, description="true lens: focus shift at the pupil rim, mm")
    truth_samples: int = Field(512, ge=1, description="pupil samples of the real scanner's lens")
    # the station
    lcd_pitch_mm: float = Field(0.2715, gt=0, description="fake LCD pixel pitch, mm")
    lcd_size: tuple[int, int] = Field((880, 520), description="fake LCD (width, height), px; "
                                      "covers the camera's view at the farthest depth")
    lcd_distance_at_zero_mm: float = Field(550.0, gt=0, description="pupil to LCD at stage 0, mm")
    depths_mm: tuple[float, ...] = Field((50.0, 130.0, 290.0, 370.0), description="stage "
                                         "readings of the LTC depths, mm (LCD at 550 mm + reading)")
    period: int = Field(24, ge=4, description="Fourier pattern period P, LCD px")
    steps: int = Field(4, ge=3, le=4, description="Fourier phase steps (3 or 4)")
    lens_samples: int = Field(128, ge=1, description="aperture samples K of the measured lens "
                              "(and of the Gaussian lens and the K-sample true lens)")
    aperture_cells: int = Field(48, ge=8, description="lens derivation: aperture grid cells")
    grid_step: int = Field(4, ge=1, description="measured-lens node spacing, px")
    seed: int = Field(0, description="fake camera noise seed")
    # the scanner
    periods_px: tuple[float, ...] = Field((384.0, 48.0, 12.0), description="fringe periods, "
                                          "projector px (the first covers the projector)")
    slight_mm: tuple[tuple[float, float], ...] = Field(
        ((-30.0, -10.0), (30.0, 10.0), (-15.0, 12.0), (15.0, -12.0)),
        description="slight-defocus sphere centres (world z, world y), mm; x = 0")
    large_mm: tuple[tuple[float, float], ...] = Field(
        ((-150.0, 0.0), (160.0, 0.0), (-140.0, 8.0), (150.0, -10.0)),
        description="large-defocus sphere centres (world z, world y), mm; x = 0")


def quick_config() -> ValidationConfig:
    """A reduced experiment (under a minute): half the rig scale, a coarser LCD and P = 12
    3-step patterns, three depths, one position per group."""
    return ValidationConfig(
        scale=0.1, camera_size=(112, 64), truth_samples=256, lcd_pitch_mm=1.0, lcd_size=(240, 140),
        depths_mm=(50.0, 130.0, 370.0), period=12, steps=3, lens_samples=64, aperture_cells=32,
        grid_step=4, periods_px=(192.0, 24.0, 8.0), slight_mm=((-30.0, -10.0),),
        large_mm=((-150.0, 0.0),))


def build_rig(cfg: ValidationConfig) -> Rig:
    """``small_rig(scale)`` without distortion, both cameras cropped to ``camera_size`` about
    the image centre (same focal length and pose): the scanner whose camera the bench holds."""
    full = small_rig(cfg.scale, distortion=False)
    w, h = cfg.camera_size
    cams = []
    for c in full.cameras:
        K = c.K_array.copy()
        K[0, 2], K[1, 2] = (w - 1) / 2, (h - 1) / 2
        cams.append(DeviceCalibration(name=c.name, K=K, dist=c.dist, R=c.R, T=c.T, size=(w, h)))
    return Rig(cameras=cams, projector=full.projector)


def truth_lens(cfg: ValidationConfig, samples: int) -> AberratedLens:
    """The ground-truth lens of the real scanner's cameras and of the fake bench camera."""
    return AberratedLens(pupil_diameter_mm=FOCAL_MM / cfg.f_number,
                         focus_distance_mm=cfg.focus_distance_mm,
                         vignetting_shift_mm=cfg.vignetting_shift_mm,
                         spherical_mm=cfg.spherical_mm, samples=samples)


def station_config(cfg: ValidationConfig, camera: DeviceCalibration) -> StationConfig:
    """A fake-backend station config whose bench camera is ``camera``: the same K (16 mm focal
    length over the pixel pitch gives K's focal length; principal point at the centre), sensor
    size and ground-truth lens; ``camera.matrix`` = K places the optical centre."""
    K = camera.K_array
    centre = [(camera.width - 1) / 2, (camera.height - 1) / 2]
    if K[0, 0] != K[1, 1] or K[0, 1] != 0 or not np.allclose(K[:2, 2], centre):
        raise ValueError(f"camera '{camera.name}': the fake bench needs square pixels, no skew "
                         f"and the principal point at the sensor centre {centre}, got K = "
                         f"{K.tolist()}")
    if np.any(camera.dist_array != 0):
        raise ValueError(f"camera '{camera.name}': the fake bench camera has no distortion, got "
                         f"dist = {camera.dist}")
    lens = truth_lens(cfg, 1)
    return StationConfig.model_validate({
        "backend": "fake",
        "depths_mm": list(cfg.depths_mm),
        "stage": {"port": "pty", "microstep_um": 0.1, "travel_mm": [0.0, max(cfg.depths_mm) + 20],
                  "tolerance_um": 1.0, "timeout_s": 0.5, "settle_s": 0.0},
        "display": {"monitor": 0, "latency_frames": 0, "frame_code": False,
                    "pitch_mm": cfg.lcd_pitch_mm},
        "camera": {"exposure_ms": 20.0, "timeout_s": 2.0, "matrix": K.tolist()},
        "patterns": {"period": cfg.period, "steps": cfg.steps, "offset": 0.5, "amplitude": 0.5},
        # the check code proves the frame order on real hardware; here it would only mask pixels
        "frame_check": {"enabled": False},
        "fake": {
            "seed": cfg.seed, "stage_maxspeed_mm_s": 1000.0, "stage_accel_mm_s2": 10000.0,
            "bench": {
                "lcd_size": list(cfg.lcd_size), "lcd_pitch_mm": cfg.lcd_pitch_mm,
                "camera_size": list(camera.size), "pixel_pitch_um": FOCAL_MM / K[0, 0] * 1e3,
                "focal_length_mm": FOCAL_MM, "f_number": cfg.f_number,
                "focus_distance_mm": lens.focus_distance_mm,
                "vignetting_shift_mm": lens.vignetting_shift_mm,
                "vignetting_radius_ratio": lens.vignetting_radius_ratio,
                "spherical_mm": lens.spherical_mm, "coma_mm": lens.coma_mm,
                "lcd_distance_at_zero_mm": cfg.lcd_distance_at_zero_mm,
                "tilt_deg": [0.0, 0.0], "pupil_samples": 200, "subpixels": 2,
            },
            "noise": {"enabled": True, "bit_depth": 12, "full_well_e": 10000.0,
                      "read_noise_e": 5.0},
            "panel": {"gamma": 1.0},
        },
    })


def check_out_dir(out: Path) -> None:
    """Refuse an output folder that already holds a station run (nothing is overwritten)."""
    found = [name for name in STATION_OUTPUTS if (out / name).exists()]
    if found:
        raise FileExistsError(f"--out {out} already holds {', '.join(found)}: choose a new "
                              "folder, or pass --lens to reuse a measured lens")


def measure_lens(cfg: ValidationConfig, rig: Rig, out: Path,
                 progress: bool = False) -> tuple[Path, dict]:
    """Run the station on the fake bench into ``out``: acquire, reconstruct the LTC, derive and
    save the lens. Returns the lens file and a JSON-able summary (times, the lens report)."""
    check_out_dir(out)
    config = station_config(cfg, rig.cameras[0])
    (out / "station.json").write_text(config.model_dump_json(indent=2))
    t0 = time.perf_counter()
    acq = acquire(config, out / "run.zarr", progress=progress)
    t1 = time.perf_counter()
    rec = reconstruct_ltc(out / "run.zarr", out / "ltc.zarr", progress=progress)
    t2 = time.perf_counter()
    fit = LensFitConfig(samples=cfg.lens_samples, grid_step=cfg.grid_step,
                        aperture_cells=cfg.aperture_cells)
    result = derive_lens(open_ltc_volume(out / "ltc.zarr"), fit)
    path = save_lens(out / "lens.npz", result.lens)
    t3 = time.perf_counter()
    return path, {"acquire_s": t1 - t0, "reconstruct_s": t2 - t1, "lens_s": t3 - t2,
                  "frames": acq["frames_total"],
                  "valid_fraction": [d["valid_fraction"] for d in rec["depths"]],
                  "lens": result.summary()}


def pattern_set(cfg: ValidationConfig) -> PhaseShiftSet:
    """4-step phase shifting along u at the configured periods (hierarchical unwrapping)."""
    return PhaseShiftSet(periods_px=list(cfg.periods_px), steps=4, direction="u")


@dataclass(frozen=True)
class Position:
    """A sphere position: name, group ('slight' or 'large'), world centre (3,) mm, and its depth
    along camera 0's axis, mm."""

    name: str
    group: str
    centre_mm: np.ndarray
    depth_mm: float


def positions(cfg: ValidationConfig, rig: Rig) -> list[Position]:
    """The configured sphere positions, slight defocus first."""
    out = []
    for group, items in (("slight", cfg.slight_mm), ("large", cfg.large_mm)):
        for i, (z, y) in enumerate(items):
            c = np.array([0.0, y, z])
            depth = float(rig.cameras[0].to_device(c[None])[0, 2])
            out.append(Position(f"{group[0].upper()}{i + 1}", group, c, depth))
    return out


def scan(rig: Rig, geom: TraceGeometry, lens: LensModel, patterns: PhaseShiftSet) -> np.ndarray:
    """Render the fringes on both cameras through ``lens`` and reconstruct by stereo: (n, 3) mm."""
    images = patterns.images(rig.projector.size)
    result = render_views(geom, rig, [lens, lens], images, RENDER)
    return fpp_scan([c.images for c in result.cameras], patterns, rig).points


def sphere_metrics(points: np.ndarray, centre_mm: np.ndarray) -> dict:
    """Sphere fit of the points within ``SPHERE_SHELL_MM`` of the true sphere (the fit trims
    3-sigma outliers): diameter error (mm), fitted centre, its error (mm), fit RMS (mm)."""
    near = np.abs(np.linalg.norm(points - centre_mm, axis=1) - SPHERE_DIAMETER_MM / 2)
    fit = fit_sphere(points[near < SPHERE_SHELL_MM])
    return {"diameter_error_mm": fit.diameter - SPHERE_DIAMETER_MM,
            "fit_centre_mm": fit.centre.tolist(),
            "centre_error_mm": float(np.linalg.norm(fit.centre - centre_mm)),
            "fit_rms_mm": fit.rms}


def compare_position(cfg: ValidationConfig, rig: Rig, pos: Position,
                     lenses: dict[str, LensModel]) -> dict:
    """Scan one position with the real lens (``lenses['real']``) and every lens of ``LENSES``;
    each virtual cloud against the real one and each sphere fit."""
    geom = Scene(objects=[SphereObject(pose={"t": pos.centre_mm.tolist()})]).trace_geometry()
    patterns = pattern_set(cfg)
    real = scan(rig, geom, lenses["real"], patterns)
    row = {"position": pos.name, "group": pos.group, "centre_mm": pos.centre_mm.tolist(),
           "depth_mm": pos.depth_mm, "defocus_mm": pos.depth_mm - cfg.focus_distance_mm,
           "real": {"points": len(real), **sphere_metrics(real, pos.centre_mm)}}
    real_centre = np.asarray(row["real"]["fit_centre_mm"])
    for name in LENSES:
        pts = scan(rig, geom, lenses[name], patterns)
        cmp = compare_clouds(pts, real, align=False)
        sm = sphere_metrics(pts, pos.centre_mm)
        row[name] = {"mean_mm": cmp.mean, "rmse_mm": cmp.rmse, "points": len(pts), **sm,
                     "centre_vs_real_mm": float(np.linalg.norm(np.asarray(sm["fit_centre_mm"])
                                                               - real_centre))}
    return row


def scanner_lenses(cfg: ValidationConfig, measured: MeasuredLens) -> dict[str, LensModel]:
    """The real scanner's lens and the virtual scanners' lenses (keys 'real' and ``LENSES``)."""
    return {"real": truth_lens(cfg, cfg.truth_samples), "measured": measured,
            "gaussian": gaussian_equivalent(measured), "pinhole": PinholeLens(),
            "truth_k": truth_lens(cfg, measured.samples)}


def run_positions(cfg: ValidationConfig, rig: Rig, lenses: dict[str, LensModel],
                  log: Callable[[str], None] = print) -> list[dict]:
    """``compare_position`` at every configured position, logging one line each."""
    rows = []
    for pos in positions(cfg, rig):
        t0 = time.perf_counter()
        row = compare_position(cfg, rig, pos, lenses)
        rows.append(row)
        log(f"{pos.name} ({pos.group}, depth {pos.depth_mm:.0f} mm): " + ", ".join(
            f"{LENS_LABELS[n]} {row[n]['mean_mm'] * 1e3:+.1f} / {row[n]['rmse_mm'] * 1e3:.1f} um"
            for n in LENSES) + f" (mean / RMSE vs real) [{time.perf_counter() - t0:.0f} s]")
    return rows


def summary(rows: list[dict]) -> dict:
    """Per group and lens, averages over the positions: |mean| and RMSE (mm); and whether the
    claim holds: at every large-defocus position the measured-LTC cloud is closer to the real
    one than the Gaussian cloud, in |mean| and in RMSE."""
    out: dict = {}
    for group in ("slight", "large"):
        sel = [r for r in rows if r["group"] == group]
        out[group] = {n: {"abs_mean_mm": float(np.mean([abs(r[n]["mean_mm"]) for r in sel])),
                          "rmse_mm": float(np.mean([r[n]["rmse_mm"] for r in sel]))}
                      for n in LENSES} if sel else {}
    large = [r for r in rows if r["group"] == "large"]
    out["claim_holds"] = bool(large) and all(
        abs(r["measured"]["mean_mm"]) < abs(r["gaussian"]["mean_mm"])
        and r["measured"]["rmse_mm"] < r["gaussian"]["rmse_mm"] for r in large)
    return out


def _um(x: float) -> str:
    return f"{x * 1e3:+.1f}"


def tables(rows: list[dict]) -> str:
    """Markdown: each virtual cloud against the real one; then the sphere fits (micrometres)."""
    lines = ["| position | depth, mm | defocus, mm | " + " | ".join(
        f"{LENS_LABELS[n]}: mean / RMSE" for n in LENSES) + " |",
        "|" + "---|" * (3 + len(LENSES))]
    for r in rows:
        lines.append(f"| {r['position']} ({r['group']}) | {r['depth_mm']:.0f} | "
                     f"{r['defocus_mm']:+.0f} | " + " | ".join(
                         f"{_um(r[n]['mean_mm'])} / {r[n]['rmse_mm'] * 1e3:.1f}" for n in LENSES)
                     + " |")
    s = summary(rows)
    for group in ("slight", "large"):
        if s[group]:
            lines.append(f"| **{group}: average** | | | " + " | ".join(
                f"**{s[group][n]['abs_mean_mm'] * 1e3:.1f} (abs) / "
                f"{s[group][n]['rmse_mm'] * 1e3:.1f}**" for n in LENSES) + " |")
    lines += ["", "| position | real: diameter error / centre error | " + " | ".join(
        f"{LENS_LABELS[n]}: diameter error / centre vs real" for n in LENSES) + " |",
        "|" + "---|" * (2 + len(LENSES))]
    for r in rows:
        lines.append(f"| {r['position']} | {_um(r['real']['diameter_error_mm'])} / "
                     f"{r['real']['centre_error_mm'] * 1e3:.1f} | " + " | ".join(
                         f"{_um(r[n]['diameter_error_mm'])} / "
                         f"{r[n]['centre_vs_real_mm'] * 1e3:.1f}" for n in LENSES) + " |")
    return "\n".join(lines)


def figure(rows: list[dict], cfg: ValidationConfig, lenses: dict[str, LensModel], rig: Rig,
           path: Path) -> Path:
    """PNG: mean and RMSE against the real cloud versus defocus, per lens; and the aperture
    samples of the measured lens against the true pupil and the Gaussian, at the optical
    centre's pixel and at a field pixel (where the large-defocus spheres are imaged)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 8.5), dpi=100)
    axes = fig.subplots(2, 2)
    defocus = np.array([r["defocus_mm"] for r in rows])
    order = np.argsort(defocus)
    marks = {"measured": "o-", "gaussian": "s-", "pinhole": "^--", "truth_k": "x:"}
    for ax, key, title in ((axes[0, 0], "mean_mm", "mean signed distance to the real cloud"),
                           (axes[0, 1], "rmse_mm", "RMSE of the distances to the real cloud")):
        for n in LENSES:
            y = np.array([r[n][key] for r in rows])[order] * 1e3
            ax.plot(defocus[order], y, marks[n], label=LENS_LABELS[n])
        ax.set_yscale("symlog" if key == "mean_mm" else "log",
                      **({"linthresh": 10.0} if key == "mean_mm" else {}))
        ax.set_xlabel("sphere depth in camera 0 - focus distance, mm")
        ax.set_ylabel("um")
        ax.set_title(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    measured, gauss = lenses["measured"], lenses["gaussian"]
    real = truth_lens(cfg, 2048)
    cam = rig.cameras[0]
    field = np.array([[cam.K_array[0, 2] + 0.3 * cam.width, cam.K_array[1, 2]]])
    disk = sunflower_disk(2048) * real.pupil_radius_mm
    for ax, uv, name in ((axes[1, 0], cam.K_array[:2, 2][None], "optical centre's pixel"),
                         (axes[1, 1], field, "field pixel")):
        t = real.transmission(cam.normalized(uv), disk)[0] > 0
        ax.scatter(disk[t, 0], disk[t, 1], s=2, c="0.8", label="true pupil (transmitted)")
        x, y, w = (a[0] for a in measured.samples_at(uv))
        ax.scatter(x, y, s=12 * w / w.mean(), c="C0", alpha=0.7,
                   label=f"measured samples (K = {len(w)}, area ~ weight)")
        a = np.linspace(0, 2 * np.pi, 200)
        for k in (1, 2):
            ax.plot(k * gauss.sigma_mm * np.cos(a), k * gauss.sigma_mm * np.sin(a), "C1",
                    lw=1, label="Gaussian 1 and 2 sigma" if k == 1 else None)
        ax.set_aspect("equal")
        ax.set_xlabel("aperture x, mm")
        ax.set_ylabel("aperture y, mm")
        ax.set_title(f"aperture samples, {name} (u, v) = ({uv[0, 0]:.0f}, {uv[0, 1]:.0f})")
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path)
    return path


def _bullet(text: str) -> str:
    return textwrap.fill(" ".join(text.split()), width=100, initial_indent="- ",
                         subsequent_indent="  ")


def findings(rows: list[dict]) -> list[str]:
    """Sentences on the numbers: the claim, the paper's RMSE figure, the sphere diameters, the
    Gaussian against the pinhole."""
    s = summary(rows)
    large = [r for r in rows if r["group"] == "large"]
    out = []
    if large:
        lg, ll, lt = (s["large"][n] for n in ("gaussian", "measured", "truth_k"))
        out.append(
            f"The claim {'holds' if s['claim_holds'] else 'does NOT hold'} at every large-defocus "
            f"position: on average the Gaussian model's clouds lie {lg['abs_mean_mm'] * 1e3:.0f} "
            f"um (|mean|) and {lg['rmse_mm'] * 1e3:.0f} um (RMSE) from the real ones, the "
            f"measured-LTC lens's {ll['abs_mean_mm'] * 1e3:.1f} um and {ll['rmse_mm'] * 1e3:.1f} "
            f"um; the true lens with as few samples {lt['abs_mean_mm'] * 1e3:.1f} um and "
            f"{lt['rmse_mm'] * 1e3:.1f} um.")
        worst = max(r["measured"]["rmse_mm"] for r in large)
        n_ok = sum(r["measured"]["rmse_mm"] < PAPER_RMSE_MM for r in rows)
        out.append(
            f"Paper's figure (RMSE < {PAPER_RMSE_MM * 1e3:.0f} um with LTC): met at {n_ok} of "
            f"{len(rows)} positions; the worst large-defocus RMSE is {worst * 1e3:.1f} um.")
    for group in ("slight", "large"):
        sel = [r for r in rows if r["group"] == group]
        if sel:
            dd = {n: max(abs(r[n]["diameter_error_mm"] - r["real"]["diameter_error_mm"])
                         for r in sel) for n in LENSES}
            out.append(
                f"Sphere diameter, {group} defocus: the real scanner's diameter error is "
                f"reproduced within {dd['measured'] * 1e3:.0f} um by the measured lens, "
                f"{dd['gaussian'] * 1e3:.0f} um by the Gaussian, {dd['pinhole'] * 1e3:.0f} um by "
                f"the pinhole, {dd['truth_k'] * 1e3:.0f} um by the true lens with K samples "
                "(worst position).")
    if rows:
        gp = max(abs(r["gaussian"]["mean_mm"] - r["pinhole"]["mean_mm"]) for r in rows)
        out.append(
            f"The Gaussian's mean differs from the pinhole's by at most {gp * 1e3:.1f} um: a "
            "centred blur that is the same for every pixel hardly moves the phase, while the "
            "real lens's vignetting shifts each pixel's effective ray with the defocus.")
    return out


def readme_section(cfg: ValidationConfig, rows: list[dict], station: dict | None,
                   measured: MeasuredLens, gauss: GaussianLens, seconds: float) -> str:
    """The whole "Validation: measured LTC vs Gaussian" section of benchmarks/README.md."""
    rig = build_rig(cfg)
    cam = rig.cameras[0]
    pupil = truth_lens(cfg, 1).pupil_radius_mm
    depths = ", ".join(f"{cfg.lcd_distance_at_zero_mm + z:g}" for z in cfg.depths_mm)
    n_slight, n_large = len(cfg.slight_mm), len(cfg.large_mm)
    setup = [
        f"""**Real scanner**: the reference rig geometry (`small_rig({cfg.scale:g})`: cameras 760 mm
        from the centre of the volume at +-15 degrees, projector {rig.projector.size[0]} x
        {rig.projector.size[1]}) without distortion, cameras cropped to {cam.width} x
        {cam.height} px (f = {cam.K_array[0, 0]:.1f} px), rendered with the ground-truth
        `AberratedLens` on both cameras: 16 mm at f/{cfg.f_number:g} (at this scale it blurs as
        many pixels as f/{cfg.f_number / cfg.scale:g} on the full-size rig), focus
        {cfg.focus_distance_mm:g} mm, vignetting shift {cfg.vignetting_shift_mm:g} mm per unit
        tan(field), spherical aberration {cfg.spherical_mm:g} mm, {cfg.truth_samples} pupil
        samples.""",
        f"""**Measured lens**: the station run end to end (`station.acquisition.acquire.acquire` ->
        `station.ltc.spi.reconstruct` -> `station.lens.derive.derive_lens`, the library functions
        behind `ltc acquire / reconstruct / lens`) on a fake bench whose camera is the rig's
        camera (same K, sensor and true lens): LCD {cfg.lcd_size[0]} x {cfg.lcd_size[1]} at
        {cfg.lcd_pitch_mm:g} mm pitch, P = {cfg.period} ({cfg.steps}-step), LCD at {depths} mm
        from the pupil, camera noise on (12 bits, shot and read noise); K =
        {measured.samples} samples per node every {cfg.grid_step} px (bilinear); focus distance
        fitted from the LTC sizes: {measured.focus_distance_mm:.1f} mm (true: paraxial
        {cfg.focus_distance_mm:g}, rim {cfg.focus_distance_mm + cfg.spherical_mm:g}). The frame
        check code is off: it proves the frame order on hardware and here would only mask
        pixels.""",
        f"""**Virtual scanners**: the same rig and calibration with (a) the measured lens; (b) the
        Gaussian baseline (OPTICS.md section 7): the measured lens's focus distance and K,
        Gaussian aperture weights with the measured LTC's second moment at the optical centre,
        sigma = {gauss.sigma_mm:.3f} mm for every pixel (the true unvignetted pupil's:
        {pupil / 2:.3f} mm); (c) pinhole; (d) the true lens with only K = {measured.samples}
        samples: the floor that the sample count alone sets.""",
        f"""**Scenes and comparison**: the 50.8007 mm sphere alone at {n_slight} positions near
        the focus distance and {n_large} far from it (x = 0; depth along camera 0's axis; defocus
        = depth - {cfg.focus_distance_mm:g} mm); 4-step fringes at periods
        {', '.join(f'{p:g}' for p in cfg.periods_px)} projector px, no noise, 12-bit
        quantisation, the same for every lens; stereo reconstruction (`sim.fpp.decode`). Each
        virtual cloud against the real one with `sim.metrology.compare.compare_clouds(align=False)`:
        the clouds share the rig's world frame, so a shift is a difference to report, not an
        alignment to remove (ICP would hide a sphere's shift). Positive distance: the virtual
        cloud lies outside the real one.""",
        """**What the comparison means**: both scanners reconstruct with the nominal pinhole
        calibration, exact at the focus plane. The true lens's vignetting moves each pixel's
        effective (centroid) ray off its chief ray in proportion to the defocus, so the real
        scanner itself errs most at large defocus (column "real: centre error": its fitted
        sphere centre against the true one). A virtual scanner is faithful when it makes the
        same errors; that is what is compared.""",
    ]
    st = ""
    if station is not None:
        ls = station["lens"]
        true_centre = [(cfg.lcd_size[0] - 1) / 2 * cfg.lcd_pitch_mm,
                       (cfg.lcd_size[1] - 1) / 2 * cfg.lcd_pitch_mm, -cfg.lcd_distance_at_zero_mm]
        st = textwrap.fill(
            f"Station: {station['frames']} frames; acquisition {station['acquire_s']:.0f} s, LTC "
            f"reconstruction {station['reconstruct_s']:.0f} s (valid pixels "
            f"{100 * min(station['valid_fraction']):.1f} % at the worst depth), lens derivation "
            f"{station['lens_s']:.0f} s. Optical centre ("
            + ", ".join(f"{v:.3f}" for v in ls["optical_centre_mm"]) + ") mm, true ("
            + ", ".join(f"{v:.3f}" for v in true_centre) + "); principal-ray residuals mean "
            f"{ls['ray_residual_mean_mm'] * 1e3:.1f} um, std {ls['ray_residual_std_mm'] * 1e3:.1f}"
            " um.", width=100)
    intro = textwrap.fill(
        "`benchmarks/validation.py`: the mission's claim, that the virtual scanner with the lens "
        "measured by the LTC station reproduces a real scanner more faithfully than a Gaussian "
        "defocus model, most of all at large defocus (OPTICS.md section 1, the paper's result).",
        width=100)
    run = textwrap.fill(f"Run of {datetime.date.today().isoformat()} on {machine()}; whole "
                        f"experiment {seconds:.0f} s.", width=100)
    return "\n".join([
        SECTION, "", intro, "",
        ("    .venv/bin/python benchmarks/validation.py --out out/validation --write-readme  "
         "# ~6 min, 2 cores"),
        ("    .venv/bin/python benchmarks/validation.py --out out/validation-quick --quick  "
         "# smoke run, < 1 min"),
        "", *[_bullet(t) for t in setup], "", "### Results", "", run, "", st, "",
        ("Each virtual cloud against the real one, micrometres (mean signed distance / RMSE); "
         "then the sphere fits, micrometres:"), "", tables(rows), "",
        *[_bullet(t) for t in findings(rows)], "",
        textwrap.fill("Figure (`validation.png` in `--out`): mean and RMSE against defocus for "
                      "each lens; the measured aperture samples against the true (vignetted) "
                      "pupil and the Gaussian, at the optical centre and at a field pixel.",
                      width=100), ""])


def write_readme(text: str, path: Path = README) -> None:
    """Replace the section starting at ``SECTION`` (up to the next ``## `` heading) with
    ``text``, or append it; nothing else in the file changes."""
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: it holds the benchmark sections, the "
                                f"'{SECTION}' section goes into it")
    lines = path.read_text().splitlines()
    new = text.strip().splitlines()
    if SECTION in lines:
        start = lines.index(SECTION)
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")),
                   len(lines))
        lines[start:end] = new + ([""] if end < len(lines) else [])
    else:
        while lines and not lines[-1].strip():
            lines.pop()
        lines += [""] + new
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for stores, lens, figure")
    ap.add_argument("--lens", type=Path, help="reuse this measured lens (skip the station)")
    ap.add_argument("--quick", action="store_true", help="reduced smoke run (quick_config)")
    ap.add_argument("--write-readme", action="store_true",
                    help="replace the validation section of benchmarks/README.md")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    cfg = quick_config() if args.quick else ValidationConfig()
    rig = build_rig(cfg)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    station = None
    lens_path = args.lens
    if lens_path is None:
        lens_path, station = measure_lens(cfg, rig, args.out, not args.quiet)
        print(f"station: {station['frames']} frames; acquire {station['acquire_s']:.0f} s, "
              f"reconstruct {station['reconstruct_s']:.0f} s, lens {station['lens_s']:.0f} s")
    measured = load_lens(lens_path)
    if tuple(measured.camera_size) != tuple(cfg.camera_size):
        raise ValueError(f"--lens {lens_path}: the lens is for a {measured.camera_size} camera, "
                         f"this experiment's cameras are {cfg.camera_size}")
    lenses = scanner_lenses(cfg, measured)
    rows = run_positions(cfg, rig, lenses)
    seconds = time.perf_counter() - t0
    s = summary(rows)
    print(tables(rows))
    print(f"claim holds: {s['claim_holds']}; total {seconds:.0f} s")
    (args.out / "results.json").write_text(json.dumps(
        {"config": cfg.model_dump(mode="json"), "station": station, "rows": rows, "summary": s,
         "seconds": seconds, "machine": machine()}, indent=1))
    print(f"figure: {figure(rows, cfg, lenses, rig, args.out / 'validation.png')}")
    if args.write_readme:
        write_readme(readme_section(cfg, rows, station, measured, lenses["gaussian"], seconds))
        print(f"README: {README} section '{SECTION}'")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
