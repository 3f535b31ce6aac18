"""station.experiment.rows: a position's numbers as typed rows, their JSON, the demo's
closing table (size column: against real on the pixels both clouds share), and the
validation path's figures (``PoseValidation``) in the pose summary and the report's table."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import pytest

from station.experiment.acceptance import public_row, size_vs_real_um
from station.experiment.rows import DistanceStats, ModelNumbers, PoseValidation, PositionRow


def _row() -> PositionRow:
    real = ModelNumbers(points=900, render_s=1.0, size_mm=-0.0168, fit_rms_mm=0.002)
    ltc = ModelNumbers(points=880, render_s=2.0, size_mm=-0.00158, fit_rms_mm=0.002,
                       size_shared_mm=-0.0050, size_shared_real_mm=-0.0161,
                       size_shared_points=700, mean_mm=-0.00047, rmse_mm=0.00179,
                       mean_icp_mm=-0.00006, rmse_icp_mm=0.00165, mean_nn_mm=0.0,
                       rmse_nn_mm=0.002, pixels_compared=650)
    return PositionRow(name="S1", kind="sphere", defocus="slight", defocus_mm=-28.978,
                       centre_mm=[0.0, -10.0, -30.0], models={"real": real, "ltc": ltc,
                                                              "gaussian": ltc, "pinhole": ltc})


def test_a_row_round_trips_through_json_and_leaves_unmeasured_fields_out():
    row = _row()
    data = row.to_json()
    assert PositionRow.from_json(data) == row
    assert set(data["models"]["real"]) == {"points", "render_s", "size_mm", "fit_rms_mm"}
    cad = ModelNumbers(points=5, render_s=0.1, cad=DistanceStats(5, 0.01, 0.02, 0.015, -0.1,
                                                                 0.1))
    assert ModelNumbers.from_json(cad.to_json()) == cad
    assert cad.to_json()["cad"]["rmse_mm"] == 0.02


def test_the_shared_size_difference_and_the_public_row():
    row = _row()
    # (-5.0) - (-16.1) um on the shared pixels, not the own-point difference (+15.2 um)
    assert abs(size_vs_real_um(row.models["ltc"]) - 11.1) < 1e-9
    assert row.models["real"].size_vs_real_um is None
    pub = public_row(row)
    assert pub["models"]["ltc"] == {"size_um": -1.58, "mean_um": -0.47, "rmse_um": 1.79,
                                    "mean_icp_um": -0.06, "rmse_icp_um": 1.65}


def test_the_demo_table_prints_the_shared_size_difference():
    from station.commands.experiment import report, text

    row = _row()
    results = {"report": "r.md", "positions": [public_row(row)], "rows": [row],
               "acceptance": {"ltc_within_limits": True, "gaussian_worse_at_large": True},
               "seconds": {"total": 1.0}}
    shown = report(results, argparse.Namespace(json=False))
    assert "rows" not in report(results, argparse.Namespace(json=True))
    table = text(shown)
    assert "+11.1" in table and "+15.2" not in table


def _validated(name: str, defocus: str, real_fit_um: float, refined_um: float) -> PositionRow:
    v = PoseValidation(
        true_offsets_um={"real_fit": real_fit_um, "refined": refined_um,
                         "refined_gaussian": 0.9 * real_fit_um, "refined_pinhole": real_fit_um},
        refine_steps_um=[real_fit_um, 1.9, 0.01], refine_converged=True,
        twin_pose_offset_um={"ltc": 0.0, "gaussian": 20.0, "pinhole": 22.0},
        response={"gain": [40000.0, 39990.0], "offset": [0.0, 1.5], "read_noise_dn": [2.0, 2.0],
                  "shot_dn": [0.1, 0.1], "bits": 16, "source": "phase-shift residuals"},
        images={"ltc": [{"camera": 0, "pixels": 500, "intensity_mean_dn": 0.1,
                         "intensity_rms_dn": 2.0, "intensity_rms_of_modulation": 0.001,
                         "phase_mean_rad": 0.0, "phase_rms_rad": 0.001}]})
    return replace(_row(), name=name, defocus=defocus, validation=v)


def test_the_validation_figures_round_trip_and_feed_the_pose_summary_and_table():
    from station.experiment.report import pose_table
    from station.experiment.validated import pose_summary

    plain = _row()
    assert "validation" not in plain.to_json()
    s2 = _validated("S2", "large", 20.8, 0.28)
    data = json.loads(json.dumps(s2.to_json()))  # as results.json and positions/NAME.json
    assert PositionRow.from_json(data) == s2
    assert data["validation"]["true_offsets_um"]["refined"] == 0.28
    bad = {**data, "validation": {**data["validation"], "seconds": 1.0}}
    with pytest.raises(ValueError, match="validation: fields"):
        PositionRow.from_json(bad)
    rows = [plain, _validated("S1", "slight", 2.5, 0.17), s2, _validated("S3", "large", 23.8,
                                                                           0.34)]
    pose = pose_summary(rows)  # the large-defocus positions only
    assert pose["positions"] == ["S2", "S3"]
    assert pose["ltc_refined_worst_um"] == 0.34 and pose["ltc_within_limit"]
    assert pose["real_fit_um"] == {"S2": 20.8, "S3": 23.8}
    assert pose["gaussian_one_step_um"]["S3"] == pytest.approx(0.9 * 23.8)
    assert pose["converged"]
    table = pose_table(rows)
    assert [line.split(" |")[0] for line in table if line.startswith("| S")] == [
        "| S1 (sphere, slight)", "| S2 (sphere, large)", "| S3 (sphere, large)"]
    assert "| S2 (sphere, large) | 20.8 | 0.28 | 18.7 | 20.8 | 20.80, 1.90, 0.01 |" in table
    assert pose_table([plain]) == []
