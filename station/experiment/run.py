"""The reference paper's experiment (``ltc experiment``, ``ltc demo``): from a measured lens to
a faithful virtual scanner.

1. **Station**: for each of the rig's two cameras, a fake bench whose camera *is* that rig
   camera (same K and sensor) carrying that camera's own ground-truth lens (the two lenses
   differ); the station sequence (``station.sequence.run_sequence``: check, alignment report,
   acquisition at six depths, LTC reconstruction, lens derivation with figures) measures it,
   with the recommended lens settings (``LensFitConfig``'s defaults; ``lens_settings``
   changes them: docs/decisions/0025-recommended-lens-settings.md).
2. **Scanners** on the same rig and calibration: ``real`` (the ground-truth lenses, sampled
   densely enough that their own sampling noise is negligible), ``ltc`` (the measured lenses,
   smoothed over ``lens_smoothing_nodes`` neighbouring nodes against the station's
   node-to-node noise),
   ``gaussian`` (docs/optics.md section 4: the measured lens's focus distance, Gaussian aperture
   weights with the second moment of the measured LTC at the optical centre, the same for
   every pixel) and ``pinhole``.
3. **Objects**: the 50.8007 mm sphere at 4 slight and 4 large defocus positions, the
   209.8219 mm ball bar at 2 + 2, and one CAD part (steps, holes, a freeform face).
4. **Comparison**: each virtual cloud against the real one (mean and RMSE of the signed
   distances by pixel correspondence, unaligned and after ICP), the sphere diameter or
   ball-bar length against nominal for every scanner (each on its own points:
   ``size_fit``), each virtual size against the real one on the pixels both clouds share
   (``shared_size_mm``), and every scanner's cloud of the CAD part against the CAD mesh.
5. **Report**: ``report.md`` with PNG figures and ``results.json`` with every number.

Everything is written under one folder ``out``: ``experiment.json`` (the config),
``station/cam0``, ``station/cam1`` (sequence folders), ``lenses.json`` (the measured lenses'
SHA-256), ``cad_part.ply``, ``real/`` (the real scanner's images as a real-scan folder, or
``real_out``), ``positions/`` (each finished position's numbers and arrays),
``figures/``, ``results.json``, ``report.md``. An interrupted experiment resumes where it
stopped when run again with the same config and folder.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from sim.storage.durable import durable_file, write_json
from sim.storage.lock import StoreLock
from station.errors import StationError, UsageError
from station.experiment.acceptance import acceptance, position_line, public_row, size_vs_real_um
from station.experiment.bench import (
    RENDER,
    build_rig,
    lcd_size,
    measure_cameras,
    scanner_lenses,
    station_config,
    truth_lens,
)
from station.experiment.config import (
    BALLBAR_BALL_MM,
    BALLBAR_LENGTH_MM,
    BENCH_SUBPIXELS,
    FOCAL_MM,
    MIN_BALL_COVERAGE,
    MODELS,
    REFERENCE_PITCH_UM,
    SHELL_MM,
    SPHERE_DIAMETER_MM,
    VIRTUAL,
    ExperimentConfig,
    LensSpec,
    Log,
    load_experiment_config,
    paper_size_config,
)
from station.experiment.objects import (
    Position,
    cad_part_mesh,
    check_views,
    positions,
    scene_of,
    view_extents_px,
)
from station.experiment.resume import (
    POSITIONS,
    check_lenses,
    image_position,
    load_position,
    save_position,
    start_or_resume,
)
from station.experiment.rows import ModelNumbers, PoseValidation, PositionRow
from station.experiment.scan import Maps, Scan, compare_position, scan_position, world_cad_mesh
from station.experiment.sizes import (
    SizeFit,
    check_coverage,
    on_ball,
    shared_size_mm,
    size_error_mm,
    size_fit,
)
from station.experiment.validated import (
    pose_summary,
    scan_position_validated,
    start_real_folder,
)
from station.validation.folder import SCAN_FILE

__all__ = [
    "BALLBAR_BALL_MM", "BALLBAR_LENGTH_MM", "BENCH_SUBPIXELS", "FOCAL_MM", "MIN_BALL_COVERAGE",
    "MODELS", "POSITIONS", "REFERENCE_PITCH_UM", "RENDER", "SHELL_MM", "SPHERE_DIAMETER_MM",
    "VIRTUAL", "ExperimentConfig", "LensSpec", "Log", "Maps", "ModelNumbers", "PoseValidation",
    "Position", "PositionRow", "Scan", "SizeFit",
    "acceptance", "build_rig", "cad_part_mesh", "check_coverage", "check_lenses", "check_views",
    "compare_position", "image_position", "lcd_size", "load_experiment_config", "load_position",
    "machine", "measure_cameras", "on_ball", "paper_size_config", "position_line", "positions",
    "public_row", "run_experiment", "save_position", "scan_position", "scanner_lenses",
    "scene_of", "shared_size_mm", "size_error_mm", "size_fit", "size_vs_real_um",
    "start_or_resume", "station_config", "truth_lens", "view_extents_px", "world_cad_mesh",
]


def run_experiment(cfg: ExperimentConfig, out: str | Path, *, progress: bool = True,
                   log: Log = print, lenses: list[str | Path] | None = None,
                   force: bool = False, real_out: str | Path | None = None
                   ) -> dict[str, Any]:
    """The whole experiment into the folder ``out`` (see the module docstring); returns the
    results (``rows``: one ``PositionRow`` per position; ``out/results.json`` holds the same
    with the rows as JSON objects). ``lenses``: two measured-lens files made with this
    config, used instead of running the station.

    Resumable: run again with the same config and ``out`` after an interruption, and the
    station's steps and the positions already finished (``out/positions``) are taken up, not
    redone; a different config or different lenses are refused. One run writes the folder
    at a time (``writer.lock``, as the stores'). ``force`` takes over the writer locks a
    killed run left (the folder's, the stations', their run stores'; never a live
    writer's).

    The real scanner's images go into a real-scan folder (``real_out``, default
    ``out/real``), and the virtual scanners are validated against it by ``ltc validate``'s
    code (``station.experiment.validated``), the path a lab's real scanner takes; each row's
    ``validation`` holds that path's figures (``PoseValidation``)."""
    from sim.optics.lens import GaussianLens
    from sim.optics.lens_file import load_lens

    out = Path(out)
    t_start = time.perf_counter()
    rig = build_rig(cfg)
    cad_mesh = cad_part_mesh() if cfg.cad else None
    check_views(cfg, rig, cad_mesh)
    resumed = start_or_resume(cfg, out)
    with StoreLock(out, force=force):  # one experiment writes a folder at a time
        if resumed:
            log(f"resuming the experiment in {out}")
        if lenses is None:
            station = measure_cameras(cfg, rig, out, progress, log, force)
            lens_paths = [s["lens"] for s in station]
        else:
            station, lens_paths = [], [str(p) for p in lenses]
        measured = [load_lens(p) for p in lens_paths]
        for i, m in enumerate(measured):
            if tuple(m.camera_size) != tuple(cfg.camera_size):
                raise StationError(f"{lens_paths[i]}: the lens is for a {m.camera_size} camera, "
                                   f"this experiment's cameras are {cfg.camera_size}")
        check_lenses(out, lens_paths)
        models = scanner_lenses(cfg, measured)
        cad_path = None
        if cad_mesh is not None:  # cfg.cad
            cad_path = out / "cad_part.ply"
            if not cad_path.exists():
                with durable_file(cad_path, "wb") as f:
                    cad_mesh.export(f, file_type="ply")
        real_dir = Path(real_out) if real_out is not None else out / "real"
        if real_dir.exists() and any(real_dir.iterdir()) and not (real_dir / SCAN_FILE).exists():
            raise UsageError(f"--real-out {real_dir} exists and is not a real-scan folder; "
                             "choose a new folder")
        start_real_folder(real_dir, cfg, rig, cad_path)
        rows: list[PositionRow] = []
        maps: dict[str, Maps] = {}
        images: dict[str, Any] = {}
        poss = positions(cfg, rig)
        shown = image_position(poss)
        folder = out / POSITIONS
        t_scan, earlier = time.perf_counter(), 0
        for k, pos in enumerate(poss):
            t0 = time.perf_counter()
            done = load_position(folder, pos.name)
            if done is None:
                scans, checks = scan_position_validated(pos, cfg, rig, models, cad_path,
                                                        real_dir)
                row, mp = compare_position(pos, cfg, rig, scans, cad_path, cad_mesh)
                row = replace(row, validation=checks)
                pics = {n: scans[n].images for n in MODELS} if pos.name == shown else None
                save_position(folder, pos.name, row, mp, pics)
                took = f"{time.perf_counter() - t0:.0f} s"
            else:
                row, mp, pics = done
                earlier += 1
                took = "scanned in an earlier run"
            rows.append(row)
            maps[pos.name] = mp
            if pos.name == shown:
                if pics is None:
                    raise StationError(f"{folder / (pos.name + '.npz')}: has no fringe images; "
                                       f"delete {folder / (pos.name + '.json')} and it to scan "
                                       f"position {pos.name} again")
                images = {"name": pos.name, "defocus": pos.defocus, **pics}
            log(f"[{k + 1}/{len(poss)}] {position_line(row)} [{took}]")
        scan_s = time.perf_counter() - t_scan
        render_s = {n: float(sum(r.models[n].render_s for r in rows)) for n in MODELS}
        gaussian_sigma_mm = [g.sigma_mm for g in models["gaussian"] if isinstance(g, GaussianLens)]
        results = {
            "report": str(out / "report.md"),
            "real_scan_folder": str(real_dir),
            "positions": [public_row(r) for r in rows],
            "rows": rows,
            "station": station,
            "lenses": [{"file": p, "samples": m.samples, "focus_distance_mm": m.focus_distance_mm,
                        "gaussian_sigma_mm": gaussian_sigma_mm[i]}
                       for i, (p, m) in enumerate(zip(lens_paths, measured, strict=True))],
            "render_s": render_s,
            "render_vs_pinhole": {n: render_s[n] / render_s["pinhole"] for n in MODELS},
            "acceptance": acceptance(rows),
            "pose_refinement": pose_summary(rows),
            "seconds": {"total": time.perf_counter() - t_start, "scan": scan_s},
            "resumed": {"resumed": resumed, "positions_from_earlier_runs": earlier},
            "config": cfg.model_dump(mode="json"),
            "date": _dt.date.today().isoformat(),
            "machine": machine(),
        }
        from station.experiment.report import write_report

        results["figures"] = write_report(results, cfg, rig, measured, models, maps, images, out)
        write_json(out / "results.json", {**results, "rows": [r.to_json() for r in rows]})
        return results


def machine() -> str:
    """CPU, cores, memory, OS and Python in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f if ln.startswith("model name")),
                       cpu)
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return (f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB, {platform.system()} "
            f"{platform.release()}, Python {platform.python_version()}")
