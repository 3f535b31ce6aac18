"""The experiment through the path a lab uses: the "real" scanner's images written as a
real-scan folder (``station.validation.folder``), then every virtual scanner validated against
them by ``ltc validate``'s code (``station.validation.run.validate_position``): the real scan
as ``ltc scan`` reads it, the artefact located and its pose refined by analysis by synthesis
with the measured-LTC scanner, the virtual scanners rendered at that pose. The experiment's
numbers (``compare_position``) are then computed from those clouds, with the truth only it
knows (the true balls, the CAD part's true pose); each row also carries the validation's own
figures (``validation``: the real fit's and the refined poses' offsets from the true pose,
the refinement's steps, the camera response, per-pixel image and phase statistics)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import numpy as np

from station.experiment.bench import RENDER
from station.experiment.config import (
    BALLBAR_BALL_MM,
    BALLBAR_LENGTH_MM,
    SPHERE_DIAMETER_MM,
    ExperimentConfig,
)
from station.experiment.objects import Position, scene_of
from station.experiment.scan import Scan
from station.validation.folder import (
    POSITION_FILE,
    POSITIONS,
    SCAN_FILE,
    BallBarArtefact,
    CadArtefact,
    Pose,
    PositionFile,
    SphereArtefact,
    load_real_scan,
    write_position,
    write_scan_file,
)

TWINS = ("ltc", "gaussian", "pinhole")  # the first refines the pose


def patterns_of(cfg: ExperimentConfig):
    from sim.render.fringe_patterns import PhaseShiftSet

    return PhaseShiftSet(periods_px=list(cfg.periods_px), steps=4, direction="u")


def start_real_folder(folder: Path, cfg: ExperimentConfig, rig, cad_path: Path | None) -> None:
    """The real-scan folder's ``scan.toml``, rig and patterns (the real scanner's renders
    sample pixel centres: ``pixel_variance_px2 = 0``) and the CAD mesh; kept as it is when
    an interrupted experiment resumes."""
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / SCAN_FILE).exists():
        write_scan_file(folder, rig, patterns_of(cfg), pixel_variance_px2=0.0)
    if cad_path is not None and not (folder / "cad_part.ply").exists():
        shutil.copyfile(cad_path, folder / "cad_part.ply")


def position_file(pos: Position, cfg: ExperimentConfig, cad_path: Path | None) -> PositionFile:
    """The position file of one experiment position: the artefact and its true pose (the
    CAD part's rough pose is its true pose: the experiment knows it)."""
    scene = scene_of(pos, cfg, cad_path)
    p = scene.objects[0].pose
    true = Pose(R=tuple(map(tuple, np.asarray(p.R).tolist())), t=tuple(np.asarray(p.t).tolist()))
    if pos.kind == "sphere":
        art = SphereArtefact(diameter_mm=SPHERE_DIAMETER_MM)
    elif pos.kind == "ballbar":
        art = BallBarArtefact(ball_diameter_mm=BALLBAR_BALL_MM,
                              centre_distance_mm=BALLBAR_LENGTH_MM)
    else:
        art = CadArtefact(mesh=Path("../../cad_part.ply"), pose=true)
    return PositionFile(artefact=art, defocus=pos.defocus, true_pose=true)


def scan_position_validated(pos: Position, cfg: ExperimentConfig, rig,
                            lenses: dict[str, tuple], cad_path: Path | None, real_dir: Path
                            ) -> tuple[dict[str, Scan], dict]:
    """Render the real scanner into the real-scan folder (unless an earlier run did), then
    validate the virtual scanners there; returns per model a ``Scan`` (cloud, camera 0's
    images in counts, seconds) and the validation's figures for the row."""
    from sim.render.images import RenderSettings
    from sim.scanner import Scanner
    from station.validation.run import validate_position

    real_s = 0.0
    if not (real_dir / POSITIONS / pos.name / POSITION_FILE).exists():
        s = Scanner(rig, lenses["real"], patterns_of(cfg), scene_of(pos, cfg, cad_path),
                    RenderSettings.model_validate(RENDER), where=f"position {pos.name}")
        t0 = time.perf_counter()
        res = s.render()
        real_s = time.perf_counter() - t0
        write_position(real_dir, pos.name, position_file(pos, cfg, cad_path),
                       [c.images for c in res.cameras])
    scan = load_real_scan(real_dir, [pos.name])
    keep: dict = {}
    result, _ = validate_position(scan, scan.positions[0], {n: lenses[n] for n in TWINS},
                                  pixel_samples=1, keep=keep)
    scans = {"real": Scan(keep["real"], keep["real_images"][0], real_s)}
    per = result.seconds
    for n in TWINS:
        scans[n] = Scan(keep[n].cloud, keep[f"images.{n}"], per.get(f"render_and_scan_{n}", 0.0))
    figures = {"true_offsets_um": result.true_offsets_um,
               "refine_steps_um": result.refine_steps_um,
               "refine_converged": result.refine_converged,
               "twin_pose_offset_um": result.twin_pose_offset_um,
               "response": result.response,
               "images": {n: result.twins[n]["images"] for n in TWINS}}
    return scans, figures


def pose_summary(rows: list[dict], limit_um: float = 3.0) -> dict:
    """The pose refinement at the large-defocus sphere and ball-bar positions: the worst
    offset of the ltc-refined pose from the true pose and whether it is within ``limit_um``;
    the real fit's and the Gaussian's one-step offsets there (um)."""
    sel = [r for r in rows if r["kind"] != "cad" and r["defocus"] == "large"
           and r.get("validation", {}).get("true_offsets_um")]
    t = [r["validation"]["true_offsets_um"] for r in sel]
    worst = max((x["refined"] for x in t), default=0.0)
    return {"positions": [r["name"] for r in sel], "limit_um": limit_um,
            "ltc_refined_worst_um": worst, "ltc_within_limit": bool(sel) and worst <= limit_um,
            "real_fit_um": {r["name"]: x["real_fit"] for r, x in zip(sel, t, strict=True)},
            "ltc_refined_um": {r["name"]: x["refined"] for r, x in zip(sel, t, strict=True)},
            "gaussian_one_step_um": {r["name"]: x.get("refined_gaussian") for r, x in
                                     zip(sel, t, strict=True)},
            "converged": all(r["validation"]["refine_converged"] for r in sel)}
