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
from typing import TYPE_CHECKING, Any

import numpy as np

from station.experiment.bench import RENDER
from station.experiment.config import (
    BALLBAR_BALL_MM,
    BALLBAR_LENGTH_MM,
    SPHERE_DIAMETER_MM,
    ExperimentConfig,
)
from station.experiment.objects import Position, scene_of
from station.experiment.rows import PoseValidation, PositionRow
from station.experiment.scan import Scan
from station.validation.folder import (
    POSITION_FILE,
    POSITIONS,
    SCAN_FILE,
    AnyArtefact,
    BallBarArtefact,
    CadArtefact,
    Pose,
    PositionFile,
    SphereArtefact,
    load_real_scan,
    write_position,
    write_scan_file,
)

if TYPE_CHECKING:
    from sim.optics.lens import LensModel
    from sim.optics.rig import Rig
    from sim.render.fringe_patterns import PhaseShiftSet

TWINS = ("ltc", "gaussian", "pinhole")  # the first refines the pose


def patterns_of(cfg: ExperimentConfig) -> PhaseShiftSet:
    """The experiment's pattern set: four-step phase shifts of ``cfg.periods_px`` along u."""
    from sim.render.fringe_patterns import PhaseShiftSet

    return PhaseShiftSet(periods_px=list(cfg.periods_px), steps=4, direction="u")


def start_real_folder(folder: Path, cfg: ExperimentConfig, rig: Rig,
                      cad_path: Path | None) -> None:
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
        art: AnyArtefact = SphereArtefact(diameter_mm=SPHERE_DIAMETER_MM)
    elif pos.kind == "ballbar":
        art = BallBarArtefact(ball_diameter_mm=BALLBAR_BALL_MM,
                              centre_distance_mm=BALLBAR_LENGTH_MM)
    else:
        art = CadArtefact(mesh=Path("../../cad_part.ply"), pose=true)
    return PositionFile(artefact=art, defocus=pos.defocus, true_pose=true)


def scan_position_validated(pos: Position, cfg: ExperimentConfig, rig: Rig,
                            lenses: dict[str, tuple[LensModel, ...]], cad_path: Path | None,
                            real_dir: Path) -> tuple[dict[str, Scan], PoseValidation]:
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
    keep: dict[str, Any] = {}
    result, _ = validate_position(scan, scan.positions[0], {n: lenses[n] for n in TWINS},
                                  pixel_samples=1, keep=keep)
    scans = {"real": Scan(keep["real"], keep["real_images"][0], real_s)}
    for n in TWINS:  # one render's time (the primary's refinement rendered it more often)
        scans[n] = Scan(keep[n].cloud, keep[f"images.{n}"], keep[n].render_s)
    figures = PoseValidation(
        true_offsets_um=result.true_offsets_um, refine_steps_um=result.refine_steps_um,
        refine_converged=result.refine_converged,
        twin_pose_offset_um=result.twin_pose_offset_um, response=result.response,
        images={n: result.twins[n]["images"] for n in TWINS})
    return scans, figures


def true_offsets(row: PositionRow) -> dict[str, float] | None:
    """The row's pose offsets from the true pose (``PoseValidation.true_offsets_um``, um), or
    None where the position was not validated or no true pose was known."""
    v = row.validation
    return v.true_offsets_um if v is not None and v.true_offsets_um else None


def pose_summary(rows: list[PositionRow], limit_um: float = 3.0) -> dict[str, Any]:
    """``results.json``'s ``pose_refinement``: at the large-defocus sphere and ball-bar
    positions the worst offset of the ltc-refined pose from the true pose and whether it is
    within ``limit_um``; the real fit's, the ltc-refined and the Gaussian's one-step offsets
    there (um), and whether every refinement converged."""
    sel = [(r, t) for r in rows if r.kind != "cad" and r.defocus == "large"
           and (t := true_offsets(r)) is not None]
    worst = max((t["refined"] for _, t in sel), default=0.0)
    return {"positions": [r.name for r, _ in sel], "limit_um": limit_um,
            "ltc_refined_worst_um": worst, "ltc_within_limit": bool(sel) and worst <= limit_um,
            "real_fit_um": {r.name: t["real_fit"] for r, t in sel},
            "ltc_refined_um": {r.name: t["refined"] for r, t in sel},
            "gaussian_one_step_um": {r.name: t.get("refined_gaussian") for r, t in sel},
            "converged": all(r.validation is not None and r.validation.refine_converged
                             for r, _ in sel)}
