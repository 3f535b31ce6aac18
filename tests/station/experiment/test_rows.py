"""station.experiment.rows: a position's numbers as typed rows, their JSON, and the demo's
closing table (size column: against real on the pixels both clouds share)."""

from __future__ import annotations

import argparse

from station.experiment.acceptance import public_row, size_vs_real_um
from station.experiment.rows import DistanceStats, ModelNumbers, PositionRow


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
