"""The experiment end to end on a reduced size: station per camera on the fake benches, the
four scanners, a sphere and a ball bar near focus and at large defocus, the comparisons and
the report; and ``ltc experiment`` / ``ltc demo`` on the command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from station.cli import main
from station.errors import StationError, UsageError
from station.experiment.run import ExperimentConfig, PositionRow, cad_part_mesh, run_experiment

# the demo's rig scale (0.1: scale 0.05 leaves too few pixels on a defocused ball for the
# stereo checks) and station (LCD pitch, six depths), with a narrower camera, 64 aperture
# samples and fewer positions (a coarser station, 1 mm LCD pixels at 4 depths, measures a lens
# whose large-defocus sphere misses real's size by 64 um, docs/decisions 0018)
REDUCED = dict(
    scale=0.1, camera_size=(208, 64), lcd_pitch_mm=0.75,
    depths_mm=(50.0, 90.0, 130.0, 290.0, 330.0, 370.0),
    period=12, lens_samples=64, lens_grid_step=4, real_samples=256, bench_samples=1024,
    periods_px=(256.0, 32.0, 8.0),
    sphere_slight=((-30.0, -10.0),), sphere_large=((-150.0, 0.0),),
    ballbar_slight=(), ballbar_large=((-110.0, 0.0),), ballbar_roll_deg=12.0, cad_z_mm=-40.0)


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    out = tmp_path_factory.mktemp("experiment") / "run"
    return out, run_experiment(ExperimentConfig(**REDUCED), out, progress=False,
                               log=lambda s: None)


@pytest.mark.slow
def test_the_reduced_experiment_orders_the_models_as_the_paper(reduced):
    _, res = reduced
    rows = {r.name: {n: m.to_json() for n, m in r.models.items()} for r in res["rows"]}
    assert set(rows) == {"S1", "S2", "B1", "C1"}
    table = json.dumps(res["positions"])
    # large defocus, sphere: the Gaussian's cloud is shifted, the measured lens's is not
    s2 = rows["S2"]
    assert abs(s2["gaussian"]["mean_mm"]) > 5 * abs(s2["ltc"]["mean_mm"]), table
    assert s2["ltc"]["rmse_mm"] < min(s2["gaussian"]["rmse_mm"], s2["pinhole"]["rmse_mm"]), table
    # large defocus, ball bar: the measured lens reproduces the real scanner's length error
    b1 = rows["B1"]
    err = {n: abs(b1[n]["size_mm"] - b1["real"]["size_mm"]) for n in ("ltc", "gaussian")}
    assert err["gaussian"] > 3 * err["ltc"], table
    assert b1["ltc"]["rmse_mm"] < b1["gaussian"]["rmse_mm"], table
    # the ordering: at every large-defocus position the Gaussian's |mean| and size
    # error against real are both larger than the measured lens's
    assert res["acceptance"]["gaussian_worse_at_large"], table
    # near focus (pixel-correspondence distances, no rim floor) the measured lens is within
    # 20 um RMSE of real; the Gaussian and the pinhole miss the true lens's focus shift
    s1 = rows["S1"]
    assert s1["ltc"]["rmse_mm"] < 0.02, table
    assert s1["ltc"]["rmse_mm"] < min(s1["gaussian"]["rmse_mm"], s1["pinhole"]["rmse_mm"]), table
    # the CAD part: every scanner's cloud lies on the CAD model within a pixel's footprint
    for n in ("real", "ltc"):
        assert abs(rows["C1"][n]["cad"]["mean_mm"]) < 0.2


@pytest.mark.slow
def test_the_report_holds_every_table_and_figure(reduced):
    out, res = reduced
    text = (out / "report.md").read_text()
    for heading in ("Table 4", "Table 5", "Table 6", "CAD part against the CAD model"):
        assert heading in text
    for png in ("summary.png", "fringes.png", "distances_S1.png", "cad_error_map.png"):
        assert (out / "figures" / png).stat().st_size > 1000
    data = json.loads((out / "results.json").read_text())
    assert data["positions"] == res["positions"]
    s1 = data["positions"][0]
    assert s1["kind"] == "sphere" and s1["defocus"] == "slight"
    assert set(s1["models"]["ltc"]) == {"mean_um", "rmse_um", "mean_icp_um", "rmse_icp_um",
                                        "size_um"}
    assert set(s1["models"]["real"]) == {"size_um"}
    for cam in data["station"]:
        assert cam["optical_centre_error_mm"] < 1.0 and len(cam["figures"]) == 4
    # sizes against real on the pixels both clouds share (both own fits' inliers)
    for r in data["rows"]:
        if r["kind"] != "cad":
            for n in ("ltc", "gaussian", "pinhole"):
                m = r["models"][n]
                assert 20 <= m["size_shared_points"] <= min(m["points"], r["models"]["real"]["points"])
    assert data["acceptance"]["ltc_worst"]["size_own_um"] >= 0
    assert "shared" in text


def test_the_cad_part_has_steps_holes_and_a_freeform_face():
    mesh = cad_part_mesh(step_mm=1.0)
    z = -mesh.vertices[:, 2]
    levels = set(np.round(z[np.isclose(z, np.round(z))]).astype(int))
    assert {0, 8, 16, -10} <= levels  # base, two steps, hole floors
    assert np.ptp(z[mesh.vertices[:, 0] < -15]) > 5  # the freeform face
    assert np.all(mesh.face_normals[:, 2] <= 1e-9)  # every face looks towards the rig (-z)


def test_ltc_experiment_refuses_an_existing_output_and_a_bad_config(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    assert main(["experiment", "--out", str(out)]) == 2
    assert "--out" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("scale = -1\n")
    assert main(["experiment", str(bad), "--out", str(tmp_path / "o2")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ltc experiment: error: ") and "scale" in err
    assert (out / "keep.txt").read_text() == "precious" and not (tmp_path / "o2").exists()


def _unfinished_copy(reduced, tmp_path, drop=("S2",)):
    """The reduced experiment's folder as an interrupted run leaves it: no report, results or
    figures, and the positions ``drop`` not yet scanned."""
    import shutil

    src, _ = reduced
    out = tmp_path / "run"
    shutil.copytree(src, out)
    for name in ("results.json", "report.md"):
        (out / name).unlink()
    shutil.rmtree(out / "figures")
    for name in drop:
        for suffix in (".json", ".npz"):
            (out / "positions" / f"{name}{suffix}").unlink()
    return out


@pytest.mark.slow
def test_an_interrupted_experiment_resumes_with_the_same_numbers(reduced, tmp_path):
    _, first = reduced
    out = _unfinished_copy(reduced, tmp_path)
    lines: list[str] = []
    again = run_experiment(ExperimentConfig(**REDUCED), out, progress=False, log=lines.append)
    assert again["resumed"] == {"resumed": True, "positions_from_earlier_runs": 3}
    earlier = [line.split()[1] for line in lines if "scanned in an earlier run" in line]
    assert earlier == ["S1", "B1", "C1"]
    # S2 scanned again from the same lenses gives the same numbers (render time aside), and
    # the numbers read back are the first run's exactly
    for a, b in zip(first["rows"], again["rows"], strict=True):
        ja, jb = a.to_json(), b.to_json()
        for m in ja["models"]:
            ja["models"][m].pop("render_s"), jb["models"][m].pop("render_s")
        assert ja == jb
    assert (out / "report.md").exists() and (out / "figures" / "fringes.png").stat().st_size > 1000
    # a finished folder is not overwritten
    with pytest.raises(UsageError, match="finished experiment"):
        run_experiment(ExperimentConfig(**REDUCED), out, progress=False, log=lambda s: None)


@pytest.mark.slow
def test_a_resume_refuses_another_config_other_lenses_and_a_damaged_position(reduced, tmp_path):
    out = _unfinished_copy(reduced, tmp_path, drop=())
    quiet = dict(progress=False, log=lambda s: None)
    with pytest.raises(UsageError, match="another config"):
        run_experiment(ExperimentConfig(**{**REDUCED, "lens_samples": 32}), out, **quiet)
    # one byte of S1's arrays changed: the zip's CRC-32 names the file
    npz = out / "positions" / "S1.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    with pytest.raises(StationError, match="S1.npz: unreadable"):
        run_experiment(ExperimentConfig(**REDUCED), out, **quiet)
    # a lens re-derived since the first positions were scanned
    record = json.loads((out / "lenses.json").read_text())
    record["lenses"][1]["sha256"] = "0" * 64
    (out / "lenses.json").write_text(json.dumps(record))
    with pytest.raises(UsageError, match="camera 1's measured lens differs"):
        run_experiment(ExperimentConfig(**REDUCED), out, **quiet)
    assert not (out / "results.json").exists()


def test_a_failed_scan_names_the_position_and_the_scanner(monkeypatch):
    """A scan refusing its input (``SimInputError``, as the stereo matcher raises) is named by
    position and scanner; any other exception (a bug) passes unchanged."""
    from sim.errors import SimInputError
    from sim.optics.lens import PinholeLens
    from sim.scanner import Scanner
    from station.experiment.run import build_rig, positions, scan_position

    cfg = ExperimentConfig(**REDUCED)
    rig = build_rig(cfg)
    lenses = {n: (PinholeLens(), PinholeLens()) for n in ("real", "ltc", "gaussian", "pinhole")}
    original, calls = Scanner.scan, []
    failure: list[Exception] = []

    def scan(self, images, **kw):
        calls.append(1)
        if len(calls) == 2:  # the second scanner, "ltc"
            raise failure[0]
        return original(self, images, **kw)

    monkeypatch.setattr(Scanner, "scan", scan)
    failure.append(SimInputError("stereo matching found no pixel with the same projector "
                                 "coordinate in both cameras"))
    with pytest.raises(StationError, match=r"^position S1 \(sphere, slight defocus\), scanner "
                                           r"ltc: stereo matching found no pixel"):
        scan_position(positions(cfg, rig)[0], cfg, rig, lenses, None)
    calls.clear()
    failure[0] = KeyError("a bug")
    with pytest.raises(KeyError, match="a bug"):
        scan_position(positions(cfg, rig)[0], cfg, rig, lenses, None)


def test_a_second_experiment_on_one_folder_is_refused_naming_the_holder(tmp_path):
    import os

    from sim.storage.lock import StoreLock, StoreLockedError

    out = tmp_path / "run"
    out.mkdir()
    with StoreLock(out):
        with pytest.raises(StoreLockedError, match=f"locked by another writer .*PID {os.getpid()}"):
            run_experiment(ExperimentConfig(**REDUCED), out, progress=False, log=lambda s: None)
    assert not (out / "station").exists() and not (out / "positions").exists()


@pytest.mark.slow
def test_the_experiment_goes_through_the_real_scan_path(reduced, tmp_path):
    """The real scanner's images are a real-scan folder that ltc validate reads as a lab's;
    the virtual scanners were validated against it with the pose refined by the measured-LTC
    scanner: within 10 um of the true pose at the large-defocus positions (the demo: 3.6-5.9
    um; 3 um was asked for), where the real fit's own offset is hundreds of um."""
    from station.validation.folder import load_real_scan

    out, res = reduced
    real = load_real_scan(out / "real")
    assert [p.name for p in real.positions] == sorted(r.name for r in res["rows"])
    assert res["real_scan_folder"] == str(out / "real")
    # every row carries the validation's figures, typed, and results.json holds them
    saved = json.loads((out / "results.json").read_text())
    for r, data in zip(res["rows"], saved["rows"], strict=True):
        assert r.validation is not None and r.validation.true_offsets_um is not None
        assert set(r.validation.images) == {"ltc", "gaussian", "pinhole"}
        assert PositionRow.from_json(data) == PositionRow.from_json(r.to_json())
    assert saved["pose_refinement"] == res["pose_refinement"]
    pose = res["pose_refinement"]
    assert pose["positions"] == ["S2", "B1"], pose
    assert pose["ltc_refined_worst_um"] <= 10.0, pose
    for name in pose["positions"]:
        assert pose["real_fit_um"][name] > 10 * pose["ltc_refined_um"][name]
        assert pose["gaussian_one_step_um"][name] > 10 * pose["ltc_refined_um"][name]
    assert "refined by analysis by synthesis" in (out / "report.md").read_text()
